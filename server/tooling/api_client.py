"""What tools read of a running server's REST API: its ingest counters, with a token if needed.

``slipfleet loadtest --connect`` and ``slipfleet replay`` read ``/api/v1/metrics`` (Prometheus
text, viewer role when the server requires tokens). :func:`check_metrics_access` turns the ways
that can fail (nothing listening, no token, a token refused) into one line on stderr before the
tool publishes anything; :func:`vehicle_packet_counts` gives each vehicle's packets by outcome
(received, accepted, late, duplicate, rejected), so a tool can say what the server made of them.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Collection
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # imported where used, so ``slipfleet --help`` stays instant
    import httpx

__all__ = [
    "OUTCOMES",
    "check_metrics_access",
    "open_client",
    "parse_metric_line",
    "vehicle_packet_counts",
]

#: Packet outcomes :func:`vehicle_packet_counts` reports (``rejected`` sums every reason).
OUTCOMES = ("received", "accepted", "late", "duplicate", "rejected")
_TOKEN_HINT = (
    "pass --token-file FILE (or set SLIPFLEET_TOKEN) with a viewer token: "
    "slipfleet token create --name tools --role viewer"
)


def parse_metric_line(line: str) -> tuple[str, dict[str, str], float] | None:
    """``(name, labels, value)`` of one Prometheus text line; None for comments and blanks."""
    if not line or line[0] == "#":
        return None
    head, _, value = line.rpartition(" ")
    labels: dict[str, str] = {}
    name = head
    if head.endswith("}") and "{" in head:
        name, _, inner = head[:-1].partition("{")
        for part in inner.split('",'):
            k, _, v = part.partition("=")
            labels[k] = v.strip('"')
    try:
        return name, labels, float(value)
    except ValueError:
        return None


def open_client(token: str | None, timeout_s: float = 30.0) -> httpx.Client:
    """An HTTP client that sends ``token`` as a bearer token (none when ``token`` is None)."""
    import httpx

    headers = {} if token is None else {"Authorization": f"Bearer {token}"}
    return httpx.Client(timeout=timeout_s, headers=headers)


def check_metrics_access(client: httpx.Client, api: str) -> None:
    """Read ``api``'s fleet-total metrics once; raise SystemExit with one line if that fails."""
    import httpx

    url = f"{api}/api/v1/metrics"
    try:
        status = client.get(url, params={"by_vehicle": "false"}).status_code
    except httpx.HTTPError as exc:
        raise SystemExit(f"no Slipfleet REST API answers at {api} ({exc})") from exc
    if status == 401:
        has = "Authorization" in client.headers
        what = "refused the access token given" if has else "requires an access token"
        raise SystemExit(f"the server at {api} {what}: {_TOKEN_HINT}")
    if status == 403:
        raise SystemExit(f"the token given may not read {url}: it needs the viewer role or higher")
    if status != 200:
        raise SystemExit(f"{url} answered HTTP {status}: is {api} a Slipfleet server?")


def vehicle_packet_counts(
    client: httpx.Client, api: str, vehicle_ids: Collection[str]
) -> dict[str, Counter[str]]:
    """Each of ``vehicle_ids``' packet counters by outcome (:data:`OUTCOMES`), as the server
    counts them now (a vehicle it does not know has none)."""
    text = client.get(f"{api}/api/v1/metrics").raise_for_status().text
    counts: dict[str, Counter[str]] = {vid: Counter() for vid in vehicle_ids}
    for line in text.splitlines():
        parsed = parse_metric_line(line)
        if parsed is None:
            continue
        name, labels, value = parsed
        vehicle = counts.get(labels.get("vehicle", ""))
        outcome = name.removeprefix("slipfleet_packets_").removesuffix("_total")
        if vehicle is not None and name.startswith("slipfleet_packets_") and outcome in OUTCOMES:
            vehicle[outcome] += int(value)
    return counts
