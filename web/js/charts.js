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

// opts: title, yLabel, fields, height, threshold (draw ±threshold lines), decimals,
// syncKey (share the cursor with the page's other charts), onCursor(index) (hover callback)
export function makeChart(target, opts) {
  const width = Math.max(320, target.clientWidth || 600);
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
          space: 80, // px between ticks: room for HH:MM:SS
          stroke: "#222",
          grid: { stroke: "#e3e3e3" },
          // 24-hour UTC clock; seconds only when the ticks are closer than a minute
          values: (u, splits, _axisIdx, _space, incr) =>
            splits.map((v) => new Date(v * 1e3).toISOString().slice(11, incr < 60 ? 19 : 16)),
        },
        {
          label: opts.yLabel,
          labelSize: 24,
          size: 56,
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

export function fitWidth(chart, target) {
  const w = Math.max(320, target.clientWidth);
  if (Math.abs(w - chart.width) > 2) chart.setSize({ width: w, height: chart.height });
}
