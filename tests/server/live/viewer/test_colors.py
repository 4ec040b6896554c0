"""The 3D viewer and the dashboard use the same slip colour scale."""

from __future__ import annotations

import json
import re
from pathlib import Path

from server.live.viewer.colors import GRIP_COLOR_STOPS, SLIP_COLOR_NONE, SLIP_COLOR_STOPS

COLORS_JS = Path(__file__).resolve().parents[4] / "web" / "js" / "colors.js"


def _js_constant(name: str) -> object:
    text = COLORS_JS.read_text()
    m = re.search(rf"export const {name} = (\[.*?\]);\n", text, re.S)
    assert m, f"{name} not found in {COLORS_JS}"
    return json.loads(re.sub(r",\s*\]", "]", m.group(1)))


def test_stops_match_the_dashboard() -> None:
    js = _js_constant("SLIP_COLOR_STOPS")
    assert js == [[s, list(c)] for s, c in SLIP_COLOR_STOPS]


def test_no_value_colour_matches_the_dashboard() -> None:
    assert _js_constant("SLIP_COLOR_NONE") == list(SLIP_COLOR_NONE)


def test_grip_stops_match_the_dashboard() -> None:
    js = _js_constant("GRIP_COLOR_STOPS")
    assert js == [[s, list(c)] for s, c in GRIP_COLOR_STOPS]
