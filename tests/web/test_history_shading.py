"""The history charts shade what was computed without the main reference, in two kinds named
from the spec: degraded rows (its degraded_flags: MDSF's DEGRADED, GNSS lost) and rows without
its ok_flag (MDSF's GNSS_OK: no GNSS velocity fused, e.g. every GNSS packet refused), with a key
above the charts. Rows stored through the stack's real writer; real Chromium."""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import pytest

from estimator.config import WheeledRearDriveConfig
from estimator.mdsf_spec import MDSF_SPEC
from estimator.types import EstimateBatch, EstimateFlag, empty_estimates
from tests.support import poll_until
from tests.web.conftest import LiveStack, history_loaded

pytestmark = pytest.mark.browser

VEHICLE = "veh-gnss-free"
RATE_HZ = 10
# seconds from the first row: [0, 20) GNSS fused, [20, 30) degraded, [30, 40) no GNSS and not
# flagged degraded, [40, 60) GNSS fused again
DEGRADED_S = (20.0, 30.0)
NO_GNSS_S = (30.0, 40.0)
END_S = 60.0
_VALID = EstimateFlag.SLIP_LEFT_VALID | EstimateFlag.SLIP_RIGHT_VALID


def _rows(t0_ns: int) -> np.ndarray:
    t = np.arange(int(END_S * RATE_HZ)) / RATE_HZ
    r = empty_estimates(t.size)
    r["stamp_ns"] = t0_ns + (t * 1e9).astype(np.int64)
    r["vg_mps"] = r["vl_mps"] = r["vr_mps"] = 2.0
    r["slip_left_pct"] = 4.0 + np.sin(t)
    r["slip_right_pct"] = 3.0
    r["east_m"], r["north_m"] = 2.0 * t, 0.0
    flags = np.full(t.size, int(EstimateFlag.GNSS_OK | _VALID))
    flags[(t >= DEGRADED_S[0]) & (t < DEGRADED_S[1])] = int(EstimateFlag.DEGRADED | _VALID)
    flags[(t >= NO_GNSS_S[0]) & (t < NO_GNSS_S[1])] = int(_VALID)
    r["flags"] = flags
    return r


@pytest.fixture(scope="module")
def stored(live_stack: LiveStack) -> int:
    """The drive stored; its first stamp, ns."""
    writer = live_stack.runtime.writer
    assert writer is not None
    t0 = time.time_ns() - int((END_S + 5) * 1e9)
    writer.submit_vehicle(VEHICLE, WheeledRearDriveConfig().to_dict(), time.time_ns())
    writer.on_estimates(EstimateBatch.of([(VEHICLE, _rows(t0))], MDSF_SPEC))
    assert writer.flush(timeout=30.0)
    return t0


# per shaded span: start and end (s after t0), kind, and the chart's pixel colour at its middle
# near the top of the plot; and pixels outside every span (s after t0: 2, 5.5, 9, 12.5, 16 — no two
# a whole number of 5 s or 10 s apart, so a vertical grid line can cross at most one of them)
_SHADE_JS = """
(t0s) => {
  const u = document.getElementById('h-chart-slip')._uplot;
  const ctx = u.ctx;
  const y = Math.round(u.bbox.top + 4);
  const px = (x) => [...ctx.getImageData(Math.round(u.valToPos(x, 'x', true)), y, 1, 1).data];
  return {
    spans: u._shade.map(([a, b, kind]) => ({a: a - t0s, b: b - t0s, kind, rgb: px((a + b) / 2)})),
    outside: [2, 5.5, 9, 12.5, 16].map((s) => px(t0s + s)),
    key: document.getElementById('h-shade-legend').textContent,
  };
}
"""


def test_degraded_and_gnss_free_stretches_are_shaded(
    live_stack: LiveStack, stored: int, page: Any
) -> None:
    page.goto(f"{live_stack.base_url}/#/vehicle/{VEHICLE}/history")
    assert history_loaded(page) == int(END_S * RATE_HZ)

    def drawn() -> dict[str, Any] | None:  # a loaded host draws the chart later
        got = page.evaluate(_SHADE_JS, stored / 1e9)
        return got if len(got["spans"]) >= 2 and got["spans"][0]["rgb"][3] > 0 else None

    got = poll_until(drawn, "shaded chart", timeout_s=60.0, poll_s=0.2)
    spans = got["spans"]
    assert [s["kind"] for s in spans] == ["degraded", "no_reference"], spans
    for s, (a, b) in zip(spans, (DEGRADED_S, NO_GNSS_S), strict=True):
        assert abs(s["a"] - a) < 0.05 and abs(s["b"] - b) < 0.05, s
    degraded, no_gnss = (s["rgb"] for s in spans)
    # nothing drawn there but, at one point at most, a grid line (#e3e3e3): the paper shows
    assert sum(p[3] == 0 for p in got["outside"]) >= 4, got["outside"]
    # degraded: a grey veil; without GNSS: a pink one (red above green)
    assert degraded[3] > 20 and max(degraded[:3]) - min(degraded[:3]) < 12, degraded
    assert no_gnss[3] > 20 and no_gnss[0] - no_gnss[1] > 40, no_gnss
    assert "degraded (DEGRADED)" in got["key"] and "without GNSS_OK" in got["key"], got["key"]
