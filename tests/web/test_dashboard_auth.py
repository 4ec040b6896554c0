"""The dashboard against a server that requires access tokens (real Chromium)."""

from __future__ import annotations

import re
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from server.tokens import Role, issue_token
from tests.web.conftest import N_VEHICLES, LiveStack, checked_page

pytestmark = pytest.mark.browser


def _fleet_listed(page: Any) -> None:
    page.wait_for_function(
        "(p) => document.getElementById('fleet-summary')?.textContent.startsWith(p)",
        arg=f"{N_VEHICLES} vehicles",
        timeout=15000,
    )


REFUSED = re.compile(r"status of 401|Unexpected response code: 403")


@pytest.fixture
def page(browser: Any) -> Iterator[Any]:
    """A page that may log refused requests (401, refused socket handshakes) and nothing else."""
    with checked_page(
        browser,
        allowed=lambda msg: REFUSED.search(msg.text) is not None,
        viewport={"width": 1400, "height": 900},
    ) as pg:
        yield pg


def test_dashboard_asks_for_a_token_and_uses_it(
    secured_stack: LiveStack, page: Any, screenshots: Path
) -> None:
    token, _ = issue_token(secured_stack.runtime.store, "browser", Role.VIEWER, time.time_ns())
    page.goto(secured_stack.base_url + "/#/fleet")
    dialog = page.locator("#token-dialog")
    dialog.wait_for(state="visible", timeout=10000)
    page.screenshot(path=str(screenshots / "token-dialog.png"))
    assert "refused" in page.inner_text("#token-reason")

    page.fill("#token-input", "sft_" + "0" * 43)  # well-formed, unknown
    page.click("#token-dialog button[value=save]")
    dialog.wait_for(state="visible", timeout=10000)  # asked again

    page.fill("#token-input", token)
    page.click("#token-dialog button[value=save]")
    _fleet_listed(page)  # REST and the fleet WebSocket both accepted the token
    assert not dialog.is_visible()

    page.reload()  # the token survives a reload of the tab
    _fleet_listed(page)
    assert not dialog.is_visible()

    page.click("#token-button")
    page.click("#token-dialog button[value=forget]")
    dialog.wait_for(state="visible", timeout=10000)  # without it the server refuses again
