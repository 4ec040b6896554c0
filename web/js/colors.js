// Slip colour scale shared by every view (map, fleet table, 3D viewer).
//
// Colour is a function of |slip| in percent, linear in RGB between these stops and clamped
// beyond the last one; a missing slip value (standstill, invalid) is grey. The 3D viewer uses the
// same stops (server/live/viewer/colors.py; a test checks that the two agree).
//
//   |slip| %   colour
//   0          green      #1a9850
//   5          yellow     #f0c828
//   15         orange     #e6551e
//   30 and up  dark red   #8c141e
//   none       grey       #a0a0a0

export const SLIP_COLOR_STOPS = [
  [0, [26, 152, 80]],
  [5, [240, 200, 40]],
  [15, [230, 85, 30]],
  [30, [140, 20, 30]],
];
export const SLIP_COLOR_NONE = [160, 160, 160];

// Default slip band edges (SlipConfig.band_edges_pct): < 5 %, 5-15 %, >= 15 %.
export const SLIP_BAND_EDGES = [5, 15];
export const SLIP_BAND_NAMES = ["low", "moderate", "high"];

// RGB of |value| on a ramp of [value, [r, g, b]] stops: linear between stops, clamped beyond
// them; a missing value is SLIP_COLOR_NONE.
function rampRgb(stops, value) {
  if (value === null || value === undefined || Number.isNaN(value)) return SLIP_COLOR_NONE;
  const s = Math.abs(value);
  if (s <= stops[0][0]) return stops[0][1];
  for (let i = 1; i < stops.length; i++) {
    const [x1, c1] = stops[i];
    if (s <= x1) {
      const [x0, c0] = stops[i - 1];
      const f = (s - x0) / (x1 - x0);
      return [0, 1, 2].map((k) => Math.round(c0[k] + f * (c1[k] - c0[k])));
    }
  }
  return stops[stops.length - 1][1];
}

export function slipRgb(slipPct) {
  return rampRgb(SLIP_COLOR_STOPS, slipPct);
}

export function slipCss(slipPct) {
  const [r, g, b] = slipRgb(slipPct);
  return `rgb(${r},${g},${b})`;
}

// Band index 0..edges.length of a slip value, or -1 when there is none.
export function slipBand(slipPct, edges = SLIP_BAND_EDGES) {
  if (slipPct === null || slipPct === undefined || Number.isNaN(slipPct)) return -1;
  const s = Math.abs(slipPct);
  let i = 0;
  while (i < edges.length && s >= edges[i]) i++;
  return i;
}

// Draw a horizontal legend of the scale into a 2-D context at (x, y), width w, bar height h.
export function drawSlipLegend(ctx, x, y, w, h, { font = "12px system-ui, sans-serif", ink = "#222" } = {}) {
  const maxPct = SLIP_COLOR_STOPS[SLIP_COLOR_STOPS.length - 1][0];
  for (let i = 0; i < w; i++) {
    ctx.fillStyle = slipCss((i / (w - 1)) * maxPct);
    ctx.fillRect(x + i, y, 1, h);
  }
  ctx.strokeStyle = ink;
  ctx.lineWidth = 1;
  ctx.strokeRect(x + 0.5, y + 0.5, w - 1, h - 1);
  ctx.fillStyle = ink;
  ctx.font = font;
  ctx.textBaseline = "top";
  ctx.textAlign = "center";
  for (const [pct] of SLIP_COLOR_STOPS) {
    const px = x + (pct / maxPct) * (w - 1);
    ctx.fillRect(px, y + h, 1, 4);
    ctx.fillText(pct === maxPct ? `≥${pct}` : `${pct}`, px, y + h + 5);
  }
  ctx.textAlign = "left";
  ctx.textBaseline = "bottom";
  ctx.fillText("|slip| (%)", x, y - 3);
  // "no value" swatch, clear of the last tick label
  const gx = x + w + 34;
  ctx.fillStyle = slipCss(null);
  ctx.fillRect(gx, y, h, h);
  ctx.strokeRect(gx + 0.5, y + 0.5, h - 1, h - 1);
  ctx.fillStyle = ink;
  ctx.textBaseline = "middle";
  ctx.fillText("no value", gx + h + 5, y + h / 2);
}

// Share of the available grip in use (a spec's wheel value channels), the same in the 3D viewer
// (server/live/viewer/scene.py GRIP_COLOR_STOPS): green while the tyre uses little of it, dark red
// at the limit.
//
//   grip used %   colour
//   0             green      #1a9850
//   50            yellow     #f0c828
//   80            orange     #e6551e
//   100 and up    dark red   #8c141e
export const GRIP_COLOR_STOPS = [
  [0, [26, 152, 80]],
  [50, [240, 200, 40]],
  [80, [230, 85, 30]],
  [100, [140, 20, 30]],
];

// rgb(...) of a grip share in percent (grey when there is none).
export function gripCss(pct) {
  const [r, g, b] = rampRgb(GRIP_COLOR_STOPS, pct);
  return `rgb(${r},${g},${b})`;
}

// A map layer's value (a spec's mapped value channel, e.g. μ) on the range [lo, hi] of the cells
// shown: dark red at the low end (little grip), green at the high end; grey where none.
const LAYER_COLOR_STOPS = [
  [0, [140, 20, 30]],
  [33, [230, 85, 30]],
  [67, [240, 200, 40]],
  [100, [26, 152, 80]],
];

export function layerCss(value, lo, hi) {
  const t = value == null || Number.isNaN(value) ? null : hi > lo ? ((value - lo) / (hi - lo)) * 100 : 100;
  const [r, g, b] = rampRgb(LAYER_COLOR_STOPS, t);
  return `rgb(${r},${g},${b})`;
}
