"""The fleet page in the system's light and dark schemes: the page, the table's header, rows,
links, status pills and slip-band cells all readable (WCAG AA contrast, 4.5:1), and the dark
scheme really dark. Real Chromium against the live stack."""

from __future__ import annotations

from typing import Any

import pytest

from tests.web.conftest import LiveStack, checked_page

pytestmark = pytest.mark.browser

# For each sample: the element's text colour and the first opaque background behind it, as
# [r, g, b]; the WCAG contrast ratio is computed in Python.
_SAMPLES_JS = """
() => {
  const rgb = (s) => (s.match(/[\\d.]+/g) || []).map(Number);
  const bgOf = (e) => {
    for (; e; e = e.parentElement) {
      const c = rgb(getComputedStyle(e).backgroundColor);
      if (c.length === 3 || (c.length === 4 && c[3] > 0.5)) return c.slice(0, 3);
    }
    return [255, 255, 255];
  };
  const pick = {
    page: document.getElementById('fleet-summary'),
    head: document.querySelector('.vhead button'),
    link: document.querySelector('.vrows .vrow .c-id a'),
    speed: document.querySelector('.vrows .vrow .c-speed_mps'),
    pill: document.querySelector('.vrows .vrow .pill'),
    band1: document.querySelector('.vrows .band-1 span:last-child'),
    band2: document.querySelector('.vrows .band-2 span:last-child'),
    nav: document.querySelector('header nav a'),
  };
  const out = {};
  for (const [k, e] of Object.entries(pick)) {
    if (e) out[k] = { ink: rgb(getComputedStyle(e).color).slice(0, 3), bg: bgOf(e) };
  }
  out.body = { bg: bgOf(document.body) };
  return out;
}
"""


def _luminance(rgb: list[float]) -> float:
    def lin(c: float) -> float:
        c /= 255.0
        return c / 12.92 if c <= 0.03928 else ((c + 0.055) / 1.055) ** 2.4

    r, g, b = (lin(c) for c in rgb)
    return 0.2126 * r + 0.7152 * g + 0.0722 * b


def _contrast(a: list[float], b: list[float]) -> float:
    hi, lo = sorted((_luminance(a), _luminance(b)), reverse=True)
    return (hi + 0.05) / (lo + 0.05)


@pytest.mark.parametrize("scheme", ["light", "dark"])
def test_fleet_page_is_readable_in_both_schemes(
    live_stack: LiveStack, browser: Any, scheme: str, screenshots: Any
) -> None:
    with checked_page(
        browser, viewport={"width": 1400, "height": 900}, color_scheme=scheme
    ) as page:
        page.goto(f"{live_stack.base_url}/#/fleet")
        page.wait_for_selector(".vrows .vrow .pill")
        # a band-shaded cell of each kind is there within a few seconds (the synthetic bursts)
        page.wait_for_function(
            "() => ['.band-1', '.band-2'].every((b) => document.querySelector('.vrows ' + b))",
            timeout=60000,
        )
        samples = page.evaluate(_SAMPLES_JS)
        page.screenshot(path=str(screenshots / f"fleet-{scheme}.png"))
    body = _luminance(samples.pop("body")["bg"])
    assert body < 0.05 if scheme == "dark" else body > 0.8
    assert set(samples) == {"page", "head", "link", "speed", "pill", "band1", "band2", "nav"}
    low = {k: round(_contrast(s["ink"], s["bg"]), 2) for k, s in samples.items()}
    assert all(c >= 4.5 for c in low.values()), f"{scheme}: {low}"
