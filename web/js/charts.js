// uPlot charts of an estimator's fields (a spec's ChartSpec: title, unit, fields, labels from
// the spec), with units on the axes and a colour-blind-safe palette (Okabe–Ito). Time runs on the
// x axis in the zone the reader chose (the browser's or UTC, js/clock.js), named in the axis
// label; x values are seconds since the epoch. Stretches of degraded rows (the spec's
// degraded_flags) and of rows without its ok_flag can be shaded (qualitySpans).

import { fmtClock, timeMode, zoneName } from "./clock.js";
import { degradedMask, fieldOf, flagMask } from "./specs.js";

// Series colours in chart order; the first series is drawn thicker.
const PALETTE = ["#0072B2", "#D55E00", "#111111", "#56B4E9", "#E69F00", "#009E73", "#CC79A7", "#F0E442"];

export function seriesStyle(i, label) {
  return { label, stroke: PALETTE[i % PALETTE.length], width: i === 0 ? 2.5 : 1.5, dash: i >= PALETTE.length ? [6, 4] : undefined };
}

// makeChart options of a spec's chart: title, unit on the y axis, its fields and their labels;
// slip charts (every field a slip channel's) draw with one decimal.
export function chartOptions(spec, chart) {
  const slipFields = new Set(spec.slips.map((s) => s.field));
  return {
    title: chart.title,
    yLabel: chart.unit ? `${chart.title.toLowerCase()} (${chart.unit})` : chart.title.toLowerCase(),
    fields: chart.fields,
    labels: chart.fields.map((f) => fieldOf(spec, f).label),
    decimals: chart.fields.every((f) => slipFields.has(f)) ? 1 : 2,
    isSlip: chart.fields.some((f) => slipFields.has(f)),
  };
}

// How each kind of shaded stretch is filled: rows with a degraded flag of the spec, and rows
// without its ok_flag (for MDSF: no GNSS velocity fused) that are not degraded.
export const SHADE_FILL = { degraded: "rgba(120, 120, 120, 0.22)", no_reference: "rgba(204, 121, 167, 0.20)" };

// The shade kind of a row's flags, or null.
function shadeKind(bits, degraded, ok) {
  if (bits & degraded) return "degraded";
  if (ok && !(bits & ok)) return "no_reference";
  return null;
}

// [[x0, x1, kind], ...] (seconds) of the runs of rows of one shade kind (shadeKind); a run
// ends at the next row's time. Over min/max rows, whose flags are the OR of a bucket's, a bucket
// with any degraded row is shaded degraded, and one with any ok row is not shaded no_reference.
export function qualitySpans(spec, cols) {
  const degraded = degradedMask(spec);
  const ok = spec.ok_flag ? flagMask(spec, spec.ok_flag) : 0;
  const out = [];
  const flags = cols.flags;
  if ((!degraded && !ok) || !flags) return out;
  let start = null;
  let kind = null;
  for (let i = 0; i <= flags.length; i++) {
    const k = i < flags.length ? shadeKind(flags[i] ?? 0, degraded, ok) : null;
    if (k === kind) continue;
    const t = cols.stamp_ns[Math.min(i, flags.length - 1)] / 1e9;
    if (kind !== null) out.push([start, t, kind]);
    kind = k;
    start = t;
  }
  return out;
}

// The legend of the shades a spec can give: [{kind, label, title}].
export function shadeLegend(spec) {
  const out = [];
  if (spec.degraded_flags.length) {
    const text = spec.degraded_flags.map((n) => spec.flags.find((f) => f.name === n)?.description || n);
    out.push({ kind: "degraded", label: `degraded (${spec.degraded_flags.join(", ")})`, title: text.join("; ") });
  }
  if (spec.ok_flag) {
    const f = spec.flags.find((x) => x.name === spec.ok_flag);
    out.push({ kind: "no_reference", label: `without ${spec.ok_flag}`, title: `not: ${f ? f.description : spec.ok_flag}` });
  }
  return out;
}

// uPlot's dates in the chosen zone (its own default is the browser's)
function zoned(ts) {
  return timeMode() === "utc" ? uPlot.tzDate(new Date(ts * 1e3), "Etc/UTC") : new Date(ts * 1e3);
}

// columns {stamp_ns: [...], field: [...]} -> uPlot aligned data
export function alignedData(cols, fields) {
  const xs = cols.stamp_ns.map((t) => t / 1e9);
  return [xs, ...fields.map((f) => cols[f] || xs.map(() => null))];
}

// Width of target's content box (inside its padding), CSS px; 0 when not laid out.
function contentWidth(target) {
  const cs = getComputedStyle(target);
  const w = target.clientWidth - (parseFloat(cs.paddingLeft) || 0) - (parseFloat(cs.paddingRight) || 0);
  return Math.max(0, Math.floor(w));
}

// Time axis ticks: steps in seconds. A step is taken when its labels fit between ticks: HH:MM:SS
// (steps under a minute), HH:MM, or MM-DD (steps of a day or more), measured in the axis font, plus
// a gap. So a short span on a phone still gets several labels.
const AXIS_FONT = '12px system-ui, -apple-system, "Segoe UI", Roboto, sans-serif';
const TIME_INCRS = [
  1, 2, 5, 10, 15, 20, 30, 60, 120, 300, 600, 900, 1200, 1800, 3600, 7200, 10800, 21600, 43200,
  86400, 2 * 86400, 7 * 86400, 14 * 86400, 28 * 86400,
];
const LABEL_GAP_PX = 10;
let labelWidths = null; // [HH:MM:SS, HH:MM] in CSS px
function labelRoom(incr) {
  if (!labelWidths) {
    const ctx = document.createElement("canvas").getContext("2d");
    ctx.font = AXIS_FONT;
    labelWidths = ["00:00:00", "00:00"].map((t) => Math.ceil(ctx.measureText(t).width));
  }
  return labelWidths[incr < 60 ? 0 : 1] + LABEL_GAP_PX;
}
function timeSpace(_u, _axisIdx, min, max, plotWidth) {
  const pxPerS = plotWidth / (max - min);
  if (!(pxPerS > 0) || !Number.isFinite(pxPerS)) return labelRoom(1);
  // uPlot takes the first step whose gap is at least the space returned: the gap of the first
  // step whose label fits, a hair less against rounding (a smaller step's gap is much smaller)
  for (const incr of TIME_INCRS) if (incr * pxPerS >= labelRoom(incr)) return incr * pxPerS * 0.999;
  return labelRoom(86400);
}
function timeLabel(v, incr) {
  const text = fmtClock(v * 1e3); // "YYYY-MM-DD HH:MM:SS" in the chosen zone
  if (incr >= 86400) return text.slice(5, 10); // MM-DD
  return text.slice(11, incr < 60 ? 19 : 16); // 24-hour clock, seconds when steps are shorter
}

// opts: title, yLabel, fields, labels (one per field; default the field names), height,
// threshold (draw ±threshold lines), decimals, syncKey (share the cursor with the page's other
// charts), onCursor(index, tS) (hover callback: the data index and its time in seconds, both
// null when the cursor leaves the chart)
//
// The chart is as wide as target's content box and follows it (ResizeObserver); target must get
// its width from the layout, not from the chart (e.g. a grid column minmax(0, 1fr)).
export function makeChart(target, opts) {
  const width = contentWidth(target) || 600;
  const digits = opts.decimals ?? 2;
  const chart = new uPlot(
    {
      title: opts.title,
      width,
      height: opts.height || 240,
      tzDate: zoned,
      scales: { x: { time: true }, y: { auto: true, range: opts.yRange } },
      axes: [
        {
          label: `time (${zoneName()})`,
          labelSize: 24,
          incrs: TIME_INCRS,
          space: timeSpace,
          font: AXIS_FONT,
          stroke: "#222",
          grid: { stroke: "#e3e3e3" },
          values: (u, splits, _axisIdx, _space, incr) => splits.map((v) => timeLabel(v, incr)),
        },
        {
          label: opts.yLabel,
          labelSize: 24,
          size: 56,
          font: AXIS_FONT,
          stroke: "#222",
          grid: { stroke: "#e3e3e3" },
        },
      ],
      series: [
        { label: `time (${zoneName()})`, value: (u, v) => (v == null ? "–" : fmtClock(v * 1e3, true).slice(11)) },
        ...opts.fields.map((f, i) => ({
          ...seriesStyle(i, (opts.labels || opts.fields)[i]),
          value: (u, v) => (v == null ? "–" : v.toFixed(digits)),
          points: { show: false },
          spanGaps: false,
        })),
      ],
      legend: { live: true },
      // charts of one page share the cursor (opts.syncKey)
      cursor: { drag: { x: true, y: false }, sync: opts.syncKey ? { key: opts.syncKey } : undefined },
      hooks: {
        setCursor: [
          (u) => {
            if (!opts.onCursor) return;
            const i = u.cursor.idx;
            opts.onCursor(i ?? null, i == null ? null : u.data[0][i]);
          },
        ],
        draw: [
          (u) => {
            const ctx = u.ctx;
            const { left, top, width: w, height: h } = u.bbox;
            if (chart && chart._shade.length) {
              ctx.save();
              for (const [x0, x1, kind] of chart._shade) {
                ctx.fillStyle = SHADE_FILL[kind] || SHADE_FILL.degraded;
                const p0 = Math.max(left, u.valToPos(x0, "x", true));
                const p1 = Math.min(left + w, u.valToPos(x1, "x", true));
                if (p1 > p0) ctx.fillRect(p0, top, Math.max(1, p1 - p0), h);
              }
              ctx.restore();
            }
            const thr = chart ? chart._threshold : opts.threshold;
            if (thr) {
              ctx.save();
              ctx.strokeStyle = "#8c141e";
              ctx.setLineDash([4, 4]);
              ctx.lineWidth = 1 * devicePixelRatio;
              ctx.fillStyle = "#8c141e";
              ctx.font = `${12 * devicePixelRatio}px system-ui, sans-serif`;
              ctx.textAlign = "right";
              ctx.textBaseline = "bottom";
              for (const y of [thr, -thr]) {
                const py = u.valToPos(y, "y", true);
                if (py >= top && py <= top + h) {
                  ctx.beginPath();
                  ctx.moveTo(left, py);
                  ctx.lineTo(left + w, py);
                  ctx.stroke();
                  ctx.fillText(`alert threshold ${y > 0 ? "" : "−"}${thr} %`, left + w - 4, py - 2);
                }
              }
              ctx.restore();
            }
            if (chart && chart._cursorT != null) {
              const px = u.valToPos(chart._cursorT, "x", true);
              if (px >= left && px <= left + w) {
                ctx.save();
                ctx.strokeStyle = "#6a3d9a";
                ctx.setLineDash([]);
                ctx.lineWidth = 2 * devicePixelRatio;
                ctx.beginPath();
                ctx.moveTo(px, top);
                ctx.lineTo(px, top + h);
                ctx.stroke();
                ctx.restore();
              }
            }
          },
        ],
      },
    },
    [[], ...opts.fields.map(() => [])],
    target,
  );
  chart._cursorT = null;
  chart._shade = [];
  chart._threshold = opts.threshold ?? null;
  target._uplot = chart; // lets tests and tools inspect the chart
  // follow the box's width (window resize, scroll bar, layout change); resized on the next frame,
  // not inside the observer's callback, so the chart's new size is not observed in the same pass
  let frame = 0;
  const observer = new ResizeObserver(() => {
    cancelAnimationFrame(frame);
    frame = requestAnimationFrame(() => fitWidth(chart, target));
  });
  observer.observe(target);
  const destroy = chart.destroy.bind(chart);
  chart.destroy = () => {
    observer.disconnect();
    cancelAnimationFrame(frame);
    destroy();
  };
  return chart;
}

// Move the replay cursor (seconds since the epoch, or null) and redraw without rescaling.
export function setCursorTime(chart, tS) {
  chart._cursorT = tS;
  chart.redraw(false, false);
}

// Shade these [[x0, x1, kind], ...] stretches (seconds; qualitySpans) on the next draw.
export function setShading(chart, spans) {
  chart._shade = spans;
}

// Change the dashed ±threshold lines (percent, or null for none).
export function setThreshold(chart, pct) {
  chart._threshold = pct;
  chart.redraw(false, false);
}

// Size the chart to target's content box (nothing to do while target is not laid out).
export function fitWidth(chart, target) {
  const w = contentWidth(target);
  if (w > 0 && w !== chart.width) chart.setSize({ width: w, height: chart.height });
}
