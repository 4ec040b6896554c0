// History of one vehicle: pick a time range, load it from the REST series endpoint, then scrub or
// replay it at 1×–60× with the charts' cursor and the slip map's position in sync. The map can also
// show a heat grid of mean |slip| per cell over the range.

import { fetchSeries, fetchVehicle, getJSON } from "./api.js";
import {
  SLIP_FIELDS,
  SPEED_FIELDS,
  alignedData,
  fitWidth,
  makeChart,
  setCursorTime,
  setThreshold,
} from "./charts.js";
import { SlipMap, heatGrid, slipMetric } from "./slipmap.js";
import { el, fmt, fmtTimeNs, vehicleHref } from "./util.js";

const FIELDS = [...SLIP_FIELDS, ...SPEED_FIELDS, "east_m", "north_m", "flags"];
const PRESETS = [
  [300, "last 5 min"],
  [1800, "last 30 min"],
  [7200, "last 2 h"],
  [43200, "last 12 h"],
];
const SPEEDS = [1, 2, 5, 10, 30, 60];
const MAX_POINTS = 4000;

function toInputValue(ns) {
  return new Date(ns / 1e6).toISOString().slice(0, 19);
}
function fromInputValue(v) {
  const ms = Date.parse(v.endsWith("Z") ? v : `${v}Z`);
  return Number.isNaN(ms) ? null : ms * 1e6;
}

export function historyView(root, vehicleId) {
  const preset = el("select", { id: "h-preset", "aria-label": "Range" });
  for (const [s, label] of PRESETS) preset.append(el("option", { value: String(s), text: label }));
  preset.value = "1800";
  const start = el("input", { type: "datetime-local", step: "1", id: "h-start", "aria-label": "Start (UTC)" });
  const end = el("input", { type: "datetime-local", step: "1", id: "h-end", "aria-label": "End (UTC)" });
  const load = el("button", { type: "button", id: "h-load", class: "primary", text: "Load" });
  const msg = el("p", { class: "summary", id: "h-msg", "aria-live": "polite" });
  const play = el("button", { type: "button", id: "h-play", text: "▶ Play", disabled: true });
  const speed = el("select", { id: "h-speed", "aria-label": "Replay speed" });
  for (const s of SPEEDS) speed.append(el("option", { value: String(s), text: `${s}×` }));
  speed.value = "10";
  const scrub = el("input", { type: "range", id: "h-scrub", min: "0", max: "0", value: "0", "aria-label": "Replay position", disabled: true });
  const at = el("span", { id: "h-at", class: "mono", text: "–" });
  const heatOn = el("input", { type: "checkbox", id: "h-heat" });
  const cell = el("select", { id: "h-cell", "aria-label": "Heat grid cell size" });
  for (const m of [1, 2, 5, 10, 20]) cell.append(el("option", { value: String(m), text: `${m} m` }));
  cell.value = "5";
  const slipBox = el("div", { class: "chart", id: "h-chart-slip" });
  const speedBox = el("div", { class: "chart", id: "h-chart-speed" });
  const canvas = el("canvas", { class: "map", id: "h-map", role: "img", "aria-label": "Slip map of the range" });
  const cursorStats = el(
    "div",
    { class: "stats" },
    el("div", { class: "stat" }, el("div", { class: "stat-label", text: "Slip left" }), el("div", { class: "stat-value" }, el("span", { id: "h-sl", text: "–" }), el("span", { class: "unit", text: " %" }))),
    el("div", { class: "stat" }, el("div", { class: "stat-label", text: "Slip right" }), el("div", { class: "stat-value" }, el("span", { id: "h-sr", text: "–" }), el("span", { class: "unit", text: " %" }))),
    el("div", { class: "stat" }, el("div", { class: "stat-label", text: "Ground speed Vg" }), el("div", { class: "stat-value" }, el("span", { id: "h-vg", text: "–" }), el("span", { class: "unit", text: " m/s" }))),
  );
  root.append(
    el("div", { class: "toolbar" }, el("h1", {}, "History ", el("span", { class: "mono", text: vehicleId })), el("a", { href: vehicleHref(vehicleId), class: "button", text: "Live" })),
    el(
      "div",
      { class: "toolbar" },
      el("label", {}, "Range ", preset),
      el("label", {}, "Start (UTC) ", start),
      el("label", {}, "End (UTC) ", end),
      load,
      msg,
    ),
    el(
      "div",
      { class: "toolbar" },
      play,
      el("label", {}, "Speed ", speed),
      el("label", { class: "grow" }, "Position ", scrub),
      at,
      el("label", {}, heatOn, " Heat grid of mean |slip|, cell "),
      cell,
    ),
    cursorStats,
    el("div", { class: "grid2" }, el("div", {}, slipBox, speedBox), el("div", {}, canvas)),
  );
  let cols = null;
  let xs = [];
  let metric = [];
  let idx = 0;
  let playing = false;
  let lastFrame = 0;
  let tPlay = 0;
  // hovering a chart moves the map's marker to that moment (the replay position stays)
  const onCursor = (i) => {
    if (!cols || playing) return;
    map.cursor = i;
    map.draw();
  };
  const sync = `history-${vehicleId}`;
  const slipChart = makeChart(slipBox, { title: "Wheel slip", yLabel: "slip (%)", fields: SLIP_FIELDS, threshold: 15, decimals: 1, syncKey: sync, onCursor });
  const speedChart = makeChart(speedBox, { title: "Speeds", yLabel: "speed (m/s)", fields: SPEED_FIELDS, decimals: 2, syncKey: sync, onCursor });
  const map = new SlipMap(canvas, { title: "Slip map of the range" });
  fetchVehicle(vehicleId)
    .then((v) => setThreshold(slipChart, v.config.slip.alert_threshold_pct))
    .catch(() => {});


  function setPresetRange(endNs) {
    const span = Number(preset.value) * 1e9;
    end.value = toInputValue(endNs);
    start.value = toInputValue(endNs - span);
  }

  function applyHeat() {
    if (!cols) return;
    if (heatOn.checked) {
      const m = Number(cell.value);
      map.setHeat(heatGrid(cols.east_m, cols.north_m, metric, m), m);
    } else map.setHeat(null, 0);
    map.draw();
  }

  function showAt(i) {
    if (!cols || !xs.length) return;
    idx = Math.max(0, Math.min(xs.length - 1, i));
    scrub.value = String(idx);
    at.textContent = fmtTimeNs(cols.stamp_ns[idx]);
    document.getElementById("h-sl").textContent = fmt(cols.slip_left_pct[idx], 1);
    document.getElementById("h-sr").textContent = fmt(cols.slip_right_pct[idx], 1);
    document.getElementById("h-vg").textContent = fmt(cols.vg_mps[idx], 2);
    setCursorTime(slipChart, xs[idx]);
    setCursorTime(speedChart, xs[idx]);
    map.cursor = idx;
    map.upTo = idx;
    map.draw();
  }

  async function doLoad() {
    const s = fromInputValue(start.value);
    const e = fromInputValue(end.value);
    if (s == null || e == null || e <= s) {
      msg.textContent = "Pick a start before the end.";
      return;
    }
    msg.textContent = "Loading…";
    try {
      cols = await fetchSeries(vehicleId, s, e, FIELDS, MAX_POINTS);
    } catch (err) {
      msg.textContent = `Could not load: ${err.message}`;
      return;
    }
    xs = cols.stamp_ns.map((t) => t / 1e9);
    metric = slipMetric(cols.slip_left_pct, cols.slip_right_pct);
    msg.textContent = `${xs.length} points`;
    fitWidth(slipChart, slipBox);
    fitWidth(speedChart, speedBox);
    slipChart.setData(alignedData(cols, SLIP_FIELDS));
    speedChart.setData(alignedData(cols, SPEED_FIELDS));
    map.setTrack(cols.east_m, cols.north_m, metric);
    scrub.max = String(Math.max(0, xs.length - 1));
    scrub.disabled = xs.length === 0;
    play.disabled = xs.length === 0;
    applyHeat();
    showAt(xs.length - 1);
  }

  function bisect(t) {
    let lo = 0;
    let hi = xs.length - 1;
    while (lo < hi) {
      const mid = (lo + hi + 1) >> 1;
      if (xs[mid] <= t) lo = mid;
      else hi = mid - 1;
    }
    return lo;
  }

  function frame(now) {
    if (!playing) return;
    const dt = (now - lastFrame) / 1000;
    lastFrame = now;
    tPlay += dt * Number(speed.value);
    const i = bisect(tPlay);
    if (i !== idx) showAt(i);
    if (i >= xs.length - 1) {
      stop();
      return;
    }
    requestAnimationFrame(frame);
  }
  function stop() {
    playing = false;
    play.textContent = "▶ Play";
  }
  play.addEventListener("click", () => {
    if (playing) return stop();
    if (idx >= xs.length - 1) showAt(0);
    playing = true;
    play.textContent = "❚❚ Pause";
    tPlay = xs[idx];
    lastFrame = performance.now();
    requestAnimationFrame(frame);
  });
  scrub.addEventListener("input", () => {
    showAt(Number(scrub.value));
    tPlay = xs[idx];
  });
  heatOn.addEventListener("change", applyHeat);
  cell.addEventListener("change", applyHeat);
  preset.addEventListener("change", () => setPresetRange(fromInputValue(end.value) || Date.now() * 1e6));
  load.addEventListener("click", doLoad);

  // default range: the last 30 min up to the vehicle's newest estimate (or now)
  getJSON(`/api/v1/vehicles/${encodeURIComponent(vehicleId)}/latest`)
    .then((row) => row.stamp_ns + 1)
    .catch(() => Date.now() * 1e6)
    .then((endNs) => {
      setPresetRange(endNs);
      doLoad();
    });
  const onResize = () => {
    if (!cols) return;
    fitWidth(slipChart, slipBox);
    fitWidth(speedChart, speedBox);
    map.draw();
  };
  window.addEventListener("resize", onResize);
  return () => {
    stop();
    window.removeEventListener("resize", onResize);
    slipChart.destroy();
    speedChart.destroy();
  };
}
