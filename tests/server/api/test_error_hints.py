"""The two REST mistakes a curl user makes first get a message that says how to mend them: an
unencoded ``+`` in a time offset, and a body sent without ``Content-Type: application/json``."""

from __future__ import annotations

import pytest

from .conftest import ApiClient, error_of


@pytest.mark.parametrize(
    "start",
    ["2026-11-28T10:00:00+01:00", "2026-11-28T10:00:00.5+0100", "2026-11-28T10:00+01"],
)
def test_an_unencoded_plus_in_a_time_gets_a_hint(client: ApiClient, start: str) -> None:
    # written into the URL as is, the way a shell user types it: "+" arrives as a space
    error, reason = error_of(client.get(f"/api/v1/fleet/report?start={start}&end=now"), 422)
    assert error == "invalid_time"
    assert reason.startswith("start: ") and "%2B" in reason


def test_an_encoded_plus_is_read_and_other_bad_times_get_no_plus_hint(client: ApiClient) -> None:
    ok = client.get(
        "/api/v1/fleet/report",
        params={"start": "2024-05-01T10:00:00+01:00", "end": "2024-05-01T12:00:00Z"},
    )
    assert ok.status_code == 200, ok.text
    _, reason = error_of(client.get("/api/v1/fleet/report?start=yesterday&end=now"), 422)
    assert "%2B" not in reason


@pytest.mark.parametrize(
    ("headers", "said"),
    [
        ({}, "no Content-Type"),
        ({"content-type": "application/x-www-form-urlencoded"}, "x-www-form-urlencoded"),
        ({"content-type": "text/plain"}, "text/plain"),
    ],
)
def test_a_body_not_sent_as_json_says_so(
    client: ApiClient, headers: dict[str, str], said: str
) -> None:
    r = client.put("/api/v1/vehicles/t1", content=b"{}", headers=headers)
    error, reason = error_of(r, 422)  # the status every route documents for a refused body
    assert error == "invalid_request"
    assert "Content-Type: application/json" in reason and said in reason
    assert client.get("/api/v1/vehicles/t1").status_code == 404  # nothing registered


def test_a_json_body_is_still_validated_as_before(client: ApiClient) -> None:
    assert client.put("/api/v1/vehicles/t1", json={}).status_code == 201
    r = client.put(
        "/api/v1/vehicles/t2", content=b"[1]", headers={"content-type": "application/json"}
    )
    error, _ = error_of(r, 422)
    assert error == "invalid_request"


def test_a_body_that_is_not_valid_json_says_what_and_where(client: ApiClient) -> None:
    r = client.put(
        "/api/v1/vehicles/t1",
        content=b'{"kind": "tracked",, }',
        headers={"content-type": "application/json"},
    )
    error, reason = error_of(r, 422)
    assert error == "invalid_request"
    assert reason.startswith("the body is not valid JSON: ") and "at character 19" in reason
    assert "body.0" not in reason and "JSON decode error" not in reason
    assert client.get("/api/v1/vehicles/t1").status_code == 404  # nothing registered
