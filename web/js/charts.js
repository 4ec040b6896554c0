// uPlot charts of slip and speeds, with units on the axes and a colour-blind-safe palette
// (Okabe–Ito). Time runs on the x axis in UTC; x values are seconds since the epoch.

export const SERIES_STYLE = {
  slip_left_pct: { label: "SL slip left", stroke: "#0072B2", width: 2 },
  slip_right_pct: { label: "SR slip right", stroke: "#D55E00", width: 2 },
  vg_mps: { label: "Vg ground", stroke: "#111111", width: 2.5 },
  vl_mps: { label: "VL left wheel ground", stroke: "#0072B2", width: 1.5 },
  vr_mps: { label: "VR right wheel ground", stroke: "#D55E00", width: 1.5 },
  rim_left_mps: { label: "rim left r·ω", stroke: "#56B4E9", width: 1.5, dash: [6, 4] },
  rim_right_mps: { label: "rim right r·ω", stroke: "#E69F00", width: 1.5, dash: [6, 4] },
};
export const SLIP_FIELDS = ["slip_left_pct", "slip_right_pct"];
export const SPEED_FIELDS = ["vg_mps", "vl_mps", "vr_mps", "rim_left_mps", "rim_right_mps"];

function utc(ts) {
  return uPlot.tzDate(new Date(ts * 1e3), "Etc/UTC");
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
  const iso = new Date(v * 1e3).toISOString();
  if (incr >= 86400) return iso.slice(5, 10); // MM-DD
  return iso.slice(11, incr < 60 ? 19 : 16); // 24-hour UTC clock, seconds when steps are shorter
}

// opts: title, yLabel, fields, height, threshold (draw ±threshold lines), decimals,
// syncKey (share the cursor with the page's other charts), onCursor(index) (hover callback)
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
      tzDate: utc,
      scales: { x: { time: true }, y: { auto: true, range: opts.yRange } },
      axes: [
        {
          label: "time (UTC)",
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
        { label: "time (UTC)", value: (u, v) => (v == null ? "–" : utc(v).toISOString().slice(11, 23)) },
        ...opts.fields.map((f) => ({
          ...SERIES_STYLE[f],
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
            if (opts.onCursor && u.cursor.idx != null) opts.onCursor(u.cursor.idx);
          },
        ],
        draw: [
          (u) => {
            const ctx = u.ctx;
            const { left, top, width: w, height: h } = u.bbox;
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
