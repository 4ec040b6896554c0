// History of one vehicle: pick an estimator (default its primary) and a time range (in the zone the reader chose), load
// it from the REST series endpoint, then scrub or replay it at 1×–60× with the charts' cursor and
// the slip map's position in sync. The map can also show a heat grid of mean |slip| per cell over
// the range. Charts, cursor values and the track come from the estimator's spec (its charts, slip
// channels, motion speed and position), so any estimator is drawn without code of its own.
//
// Three requests, each right for what it draws:
// * charts: the series decimated to min/max per time bucket (`decimation=minmax`): the envelope
//   of every field is exact, spikes survive, but one row mixes values of several estimates;
// * track, replay position and the values at the cursor: whole stored rows (`decimation=first`,
//   the first row of each bucket), so a position, its slip and its speed belong together;
// * heat grid: the REST slip map of the range (`GET /vehicles/{id}/slipmap`), the same cells and
//   numbers as a GIS export (time-weighted mean |slip| over every slip channel's valid slips,
//   moving rows only, at full rate).
// The server sizes its buckets on the span of the stored rows in the range, not on the range, so
// a short drive in a long range keeps its detail; the page says how many points it shows of how
// many stored rows, and how wide the buckets are.

import { fetchVehicle, getJSON, loadDashboardConfig } from "./api.js";
import { clockToMs, fmtClock, timeMode, zoneName } from "./clock.js";
import {
  alignedData,
  chartOptions,
  qualitySpans,
  fitWidth,
  makeChart,
  setCursorTime,
  setShading,
  SHADE_FILL,
  shadeLegend,
} from "./charts.js";
import { SlipMap, showLayerHeat } from "./slipmap.js";
import { carriedRows, fieldOf, loadSpecs, motionChannel, positionSigma, slipMetric } from "./specs.js";
import { StateBand } from "./states.js";
import { el, fmt, fmtDuration, fmtSpeed, fmtTimeNs, lastAtOrBefore, timeTitle, vehicleHref } from "./util.js";

// Fields of a spec the charts need: every chart's, and flags (degraded stretches).
function chartFields(spec) {
  const f = spec.charts.flatMap((c) => c.fields);
  if (spec.flags.length) f.push("flags");
  return [...new Set(f)];
}

// Fields of a spec the track and the cursor values need: position (and its σ), slips, state
// channels, motion speed, flags.
function trackFields(spec) {
  const p = spec.position;
  const f = p ? [p.east_field, p.north_field, p.east_std_field, p.north_std_field].filter(Boolean) : [];
  f.push(...spec.slips.map((c) => c.field));
  f.push(...spec.states.map((c) => c.field));
  const motion = motionChannel(spec);
  if (motion) f.push(motion.field);
  if (spec.flags.length) f.push("flags");
  return [...new Set(f)];
}
const CHART_POINTS = 4000; // min/max: 2,000 buckets
const TRACK_POINTS = 10000; // whole rows: a 12 h drive gives one every 4.3 s
const PRESETS = [
  [300, "last 5 min"],
  [1800, "last 30 min"],
  [7200, "last 2 h"],
  [43200, "last 12 h"],
];
const CUSTOM = "custom";
const SPEEDS = [1, 2, 5, 10, 30, 60];
const CELLS_M = [1, 2, 5, 10, 20, 50, 100, 200, 500, 1000]; // the auto cell size picks from these
const CELL_CHOICES = [1, 2, 5, 10, 20, 50];
const AUTO_CELLS_ACROSS = 60; // auto: the smallest cell giving at most this many across the track
const SLIPMAP_MAX_RANGE_S = 24 * 3600; // the slip map endpoint's limit
const NS = 1000000000n;

// Times in the inputs: 24-hour ISO in the zone the reader chose (js/clock.js: the browser's or
// UTC), "2026-11-26 22:48:43" (a "T" instead of the space and a fraction of a second are
// accepted; a trailing "Z" or "UTC" reads the time as UTC whatever the choice). Values are BigInt
// nanoseconds: a Number holds an epoch nanosecond only to 256 ns.
const TIME_RE =
  /^\s*(\d{4})-(\d{2})-(\d{2})(?:T|\s+)(\d{2}):(\d{2})(?::(\d{2})(?:\.(\d{1,9}))?)?\s*(Z|UTC)?\s*$/i;

export function formatClockNs(ns) {
  return fmtClock(Number(BigInt(ns) / 1000000n));
}

export function parseClock(text) {
  const m = TIME_RE.exec(text || "");
  if (!m) return null;
  const [y, mo, d, h, mi, s] = m.slice(1, 7).map((v) => Number(v || 0));
  const ms = clockToMs(y, mo, d, h, mi, s, m[8] ? "utc" : timeMode());
  if (ms === null) return null; // 2026-02-30, 24:00, …
  return BigInt(ms / 1000) * NS + BigInt((m[7] || "").padEnd(9, "0"));
}

// "2026-11-26 22:36:10–22:50:12 CET" (the date again when the day changes)
function fmtSpanNs(first, last) {
  const a = formatClockNs(BigInt(Math.round(first / 1e6)) * 1000000n);
  const b = formatClockNs(BigInt(Math.round(last / 1e6)) * 1000000n);
  return `${a}–${a.slice(0, 10) === b.slice(0, 10) ? b.slice(11) : b} ${zoneName(last / 1e6)}`;
}

function setInvalid(input, bad) {
  if (bad) input.setAttribute("aria-invalid", "true");
  else input.removeAttribute("aria-invalid");
}

function seriesRequest(vehicleId, estimator, startNs, endNs, fields, maxPoints, decimation) {
  return getJSON(`/api/v1/vehicles/${encodeURIComponent(vehicleId)}/series`, {
    estimator,
    start: startNs.toString(),
    end: endNs.toString(),
    fields: fields.join(","),
    max_points: maxPoints,
    decimation,
    format: "json",
  });
}

export function historyView(root, vehicleId) {
  const preset = el("select", { id: "h-preset", "aria-label": "Range" });
  for (const [s, label] of PRESETS) preset.append(el("option", { value: String(s), text: label }));
  preset.append(el("option", { value: CUSTOM, text: "custom" }));
  preset.value = "1800";
  const timeInput = (id, label) =>
    el("input", {
      type: "text",
      id,
      class: "mono",
      size: "19",
      inputmode: "numeric",
      spellcheck: "false",
      autocomplete: "off",
      placeholder: "YYYY-MM-DD HH:MM:SS",
      title: `${zoneName()}, 24-hour clock: YYYY-MM-DD HH:MM:SS`,
      "aria-label": label,
    });
  const start = timeInput("h-start", `Start (${zoneName()})`);
  const end = timeInput("h-end", `End (${zoneName()})`);
  const load = el("button", { type: "button", id: "h-load", class: "primary", text: "Load" });
  const msg = el("span", { id: "h-msg" });
  const detail = el("span", { id: "h-detail" });
  const play = el("button", { type: "button", id: "h-play", text: "▶ Play", disabled: true });
  const speed = el("select", { id: "h-speed", "aria-label": "Replay speed" });
  for (const s of SPEEDS) speed.append(el("option", { value: String(s), text: `${s}×` }));
  speed.value = "10";
  const scrub = el("input", { type: "range", id: "h-scrub", min: "0", max: "0", value: "0", "aria-label": "Replay position", disabled: true });
  const at = el("span", { id: "h-at", class: "mono", text: "–" });
  const heatOn = el("input", { type: "checkbox", id: "h-heat" });
  const cell = el("select", { id: "h-cell", "aria-label": "Heat grid cell size" });
  const autoOption = el("option", { value: "auto", text: "auto" });
  cell.append(autoOption);
  for (const m of CELL_CHOICES) cell.append(el("option", { value: String(m), text: `${m} m` }));
  cell.value = "auto";
  const heatMsg = el("span", { id: "h-heat-msg", class: "summary" });
  // what the heat grid's cells show: mean |slip|, or a layer (a mapped value channel of the spec)
  const layerSel = el("select", { id: "h-layer", "aria-label": "Heat grid layer" });
  const estimatorSel = el("select", { id: "h-estimator", "aria-label": "Estimator" });
  const chartsBox = el("div", { id: "h-charts" });
  const shadeKey = el("p", { id: "h-shade-legend", class: "shade-legend" });
  const canvas = el("canvas", { class: "map", id: "h-map", role: "img", "aria-label": "Slip map of the range" });
  const mapTitle = el("h2", { class: "map-title", id: "h-map-title" });
  const cursorStats = el("div", { class: "stats", id: "h-cursor" });
  root.append(
    el(
      "div",
      { class: "toolbar" },
      el("h1", {}, "History ", el("span", { class: "mono", text: vehicleId })),
      el("a", { href: vehicleHref(vehicleId), class: "button", text: "Live" }),
      el("label", {}, "Estimator ", estimatorSel),
    ),
    el(
      "div",
      { class: "toolbar" },
      el("label", {}, "Range ", preset),
      el("label", {}, `Start (${zoneName()}) `, start),
      el("label", {}, `End (${zoneName()}) `, end),
      load,
    ),
    el("div", { class: "toolbar" }, el("p", { class: "summary", id: "h-summary", "aria-live": "polite" }, msg, " ", detail)),
    el(
      "div",
      { class: "toolbar" },
      play,
      el("label", {}, "Speed ", speed),
      el("label", { class: "grow" }, "Position ", scrub),
      at,
      el(
        "label",
        { title: "Per cell: the time-weighted mean |slip| over every slip channel's valid slips while moving, at full rate (GET /api/v1/vehicles/{id}/slipmap)" },
        heatOn,
        " Heat grid of ",
      ),
      layerSel,
      el("span", { text: " cell " }),
      cell,
      heatMsg,
    ),
    cursorStats,
    el("div", { class: "grid2" }, el("div", {}, shadeKey, chartsBox), el("div", {}, mapTitle, canvas)),
  );
  let spec = null; // the chosen estimator's spec
  let specs = null;
  let threshold = 15; // SlipConfig default until the vehicle's config is loaded
  let standstillMps = null; // the vehicle's SlipConfig.min_ground_speed_mps, once loaded
  let charts = []; // [{box, chart, fields}] of the spec's charts
  let bands = []; // a StateBand per state channel of the spec, under the charts
  let env = null; // chart columns: min/max envelope
  let track = null; // whole stored rows
  let range = null; // {s, e} BigInt ns of the loaded range
  let xs = []; // track stamps, seconds
  let metric = [];
  let idx = 0;
  let playing = false;
  let lastFrame = 0;
  let tPlay = 0;
  let loadGen = 0;
  let heatGen = 0;
  const heatCache = new Map();
  // hovering a chart moves the map's marker to that moment; leaving it, back to the replay
  // position
  const onCursor = (i, tS) => {
    if (!env || !track || playing || !xs.length) return;
    map.cursor = tS == null ? idx : bisect(tS);
    map.draw();
  };
  const sync = `history-${vehicleId}`;
  const TRACK_TITLE = "Track coloured by max |slip| of the wheels";
  const map = new SlipMap(canvas, { title: TRACK_TITLE, titleEl: mapTitle });
  loadDashboardConfig().then((cfg) => map.setTiles(cfg.map_tile_url));

  // Charts and cursor tiles of the chosen spec (its chart keys name the boxes: h-chart-<key>).
  function useSpec(name) {
    spec = specs.get(name);
    for (const c of charts) c.chart.destroy();
    chartsBox.replaceChildren();
    charts = spec.charts.map((c) => {
      const box = el("div", { class: "chart", id: `h-chart-${c.key}` });
      chartsBox.append(box);
      const o = chartOptions(spec, c);
      const chart = makeChart(box, { ...o, threshold: o.isSlip ? threshold : null, syncKey: sync, onCursor });
      return { box, chart, fields: c.fields };
    });
    bands = spec.states.map((ch) => {
      const box = el("div", { class: "state-band", id: `h-band-${ch.key}`, "data-channel": ch.key }, el("div", { class: "state-band-title", text: ch.label }));
      chartsBox.append(box);
      return new StateBand(spec, ch, box);
    });
    const tile = (label, id, unit) =>
      el("div", { class: "stat" }, el("div", { class: "stat-label", text: label }), el("div", { class: "stat-value" }, el("span", { id, text: "–" }), el("span", { class: "unit", text: ` ${unit}` })));
    const motion = motionChannel(spec);
    cursorStats.replaceChildren(
      ...spec.slips.map((ch) => tile(`Slip ${ch.label}`, `h-slip-${ch.key}`, "%")),
      ...(motion ? [tile(motion.label, "h-motion", fieldOf(spec, motion.field).unit)] : []),
    );
    shadeKey.replaceChildren(
      ...shadeLegend(spec).map((s) =>
        el("span", { class: "shade-key", "data-kind": s.kind, title: s.title }, el("span", { class: "swatch", style: `background: ${SHADE_FILL[s.kind]}` }), ` ${s.label}`),
      ),
    );
    if (shadeKey.childElementCount) shadeKey.prepend("Shaded: ");
    canvas.hidden = !spec.position;
    mapTitle.hidden = !spec.position;
    const layers = spec.values.filter((v) => v.mapped);
    layerSel.replaceChildren(
      ...(spec.slips.length ? [el("option", { value: "", text: "mean |slip|" })] : []),
      ...layers.map((v) => el("option", { value: v.key, text: `mean ${v.label}${v.valid_flag ? ` (${v.valid_flag.toLowerCase()})` : ""}` })),
    );
    layerSel.disabled = layerSel.options.length < 2;
    heatOn.disabled = !spec.position || !layerSel.options.length;
  }

  // The estimators the vehicle runs (primary first; every spec with a position when the server
  // does not say), then the default range and the first load.
  Promise.all([loadSpecs(), fetchVehicle(vehicleId).catch(() => null)])
    .then(([all, v]) => {
      specs = all;
      if (v) threshold = v.config.slip.alert_threshold_pct;
      if (v) standstillMps = v.config.slip.min_ground_speed_mps;
      if (v) map.setAnchor(v.anchor); // latitude/longitude axes through the vehicle's anchor
      const names = v && v.estimators && v.estimators.length ? v.estimators : [...all.values()].filter((s) => s.position).map((s) => s.name);
      for (const n of names) estimatorSel.append(el("option", { value: n, text: all.get(n)?.title || n }));
      useSpec(names[0]);
      return loadDefaultRange();
    })
    .catch((err) => {
      msg.textContent = `Could not load: ${err.message}`;
    });
  estimatorSel.addEventListener("change", () => {
    useSpec(estimatorSel.value);
    doLoad();
  });

  function setPresetRange(endNs) {
    // whole seconds, the end rounded up so the newest row stays inside
    const e = ((BigInt(endNs) + NS - 1n) / NS) * NS;
    end.value = formatClockNs(e);
    start.value = formatClockNs(e - BigInt(preset.value) * NS);
    setInvalid(start, false);
    setInvalid(end, false);
  }

  function autoCellM() {
    let e0 = Infinity, e1 = -Infinity, n0 = Infinity, n1 = -Infinity;
    if (track && spec.position) {
      const east = track[spec.position.east_field];
      const north = track[spec.position.north_field];
      for (let i = 0; i < east.length; i++) {
        const e = east[i], n = north[i];
        if (e == null || n == null) continue;
        if (e < e0) e0 = e; if (e > e1) e1 = e; if (n < n0) n0 = n; if (n > n1) n1 = n;
      }
    }
    const extent = Number.isFinite(e0) ? Math.max(e1 - e0, n1 - n0) : 0;
    for (const c of CELLS_M) if (extent / c <= AUTO_CELLS_ACROSS) return c;
    return CELLS_M[CELLS_M.length - 1];
  }

  async function fetchHeat(s, e, cellM) {
    const layer = layerSel.value;
    const key = `${spec.name}/${s}/${e}/${cellM}/${layer}`;
    if (!heatCache.has(key)) {
      const p = getJSON(`/api/v1/vehicles/${encodeURIComponent(vehicleId)}/slipmap`, {
        estimator: spec.name,
        start: s.toString(),
        end: e.toString(),
        cell_m: cellM,
        format: "json",
        ...(layer ? { layer } : {}),
      });
      heatCache.set(key, p);
      p.catch(() => heatCache.delete(key));
    }
    return heatCache.get(key);
  }

  async function applyHeat() {
    const my = ++heatGen;
    if (!heatOn.checked || !range || heatOn.disabled) {
      map.setHeat(null, 0);
      map.title = TRACK_TITLE;
      heatMsg.textContent = "";
      if (range) map.draw();
      return;
    }
    const { s, e } = range;
    if (Number(e - s) / 1e9 > SLIPMAP_MAX_RANGE_S) {
      map.setHeat(null, 0);
      map.draw();
      heatMsg.textContent = "no heat grid: the slip map covers at most 24 h";
      return;
    }
    const auto = cell.value === "auto";
    let cellM = auto ? autoCellM() : Number(cell.value);
    autoOption.textContent = auto ? `auto (${cellM} m)` : "auto";
    heatMsg.textContent = "loading…";
    let body = null;
    for (;;) {
      try {
        body = await fetchHeat(s, e, cellM);
        break;
      } catch (err) {
        if (my !== heatGen) return;
        const next = CELLS_M.find((c) => c > cellM);
        if (auto && err.code === "range_too_large" && next) {
          cellM = next; // too many cells: a coarser grid
          autoOption.textContent = `auto (${cellM} m)`;
          continue;
        }
        map.setHeat(null, 0);
        map.draw();
        heatMsg.textContent = `no heat grid: ${err.reason || err.message}`;
        return;
      }
    }
    if (my !== heatGen) return;
    if (body.layer) showLayer(body);
    else {
      const cells = body.cells.map((c) => ({ e0: c.east_m, n0: c.north_m, mean: c.mean_abs_slip_pct }));
      map.setHeat(cells, body.cell_m);
      map.title = "Track by max |slip|; cells by time-weighted mean |slip|";
      heatMsg.textContent = `${cells.length} cells`;
    }
    map.draw();
  }

  // A layer's cells: its mean over the samples that inform it (showLayerHeat).
  function showLayer(body) {
    heatMsg.textContent = showLayerHeat(map, body);
    map.title = `Track by max |slip|; cells by time-weighted mean ${body.layer.label}`;
  }

  function showAt(i) {
    if (!track || !xs.length) return;
    idx = Math.max(0, Math.min(xs.length - 1, i));
    scrub.value = String(idx);
    at.textContent = fmtTimeNs(track.stamp_ns[idx]);
    at.title = timeTitle(track.stamp_ns[idx]);
    for (const ch of spec.slips) document.getElementById(`h-slip-${ch.key}`).textContent = fmt(track[ch.field][idx], 1);
    const motion = motionChannel(spec);
    if (motion) document.getElementById("h-motion").textContent = fmtSpeed(track[motion.field][idx], standstillMps);
    for (const c of charts) setCursorTime(c.chart, xs[idx]);
    map.cursor = idx;
    map.upTo = idx;
    map.draw();
  }

  function describe(envBody, trackBody, s, e) {
    const stored = envBody.stored_rows;
    if (!stored) return "– no rows stored in this range";
    const parts = [];
    if (envBody.downsampled) {
      parts.push(`of ${stored} stored rows (charts: min/max per ${fmtDuration(envBody.bucket_ns / 1e9)})`);
    } else parts.push(`= all ${stored} stored rows`);
    if (trackBody.downsampled) {
      parts.push(`map: ${trackBody.rows} whole rows, one per ${fmtDuration(trackBody.bucket_ns / 1e9)}`);
    } else parts.push(`map: all ${trackBody.rows} rows`);
    const first = envBody.first_ns, last = envBody.last_ns;
    parts.push(
      `data ${fmtSpanNs(first, last)}: ${fmtDuration((last - first) / 1e9)} of the ` +
        `${fmtDuration(Number(e - s) / 1e9)} range`,
    );
    return parts.join(" · ");
  }

  async function doLoad() {
    if (!spec) return; // the estimators are not loaded yet
    const s = parseClock(start.value);
    const e = parseClock(end.value);
    setInvalid(start, s == null);
    setInvalid(end, e == null);
    if (s == null || e == null) {
      msg.textContent = `Enter the times as YYYY-MM-DD HH:MM:SS (${zoneName()}).`;
      detail.textContent = "";
      return;
    }
    if (e <= s) {
      msg.textContent = "Pick a start before the end.";
      detail.textContent = "";
      return;
    }
    if (preset.value !== CUSTOM && e - s !== BigInt(preset.value) * NS) preset.value = CUSTOM;
    const my = ++loadGen;
    stop();
    msg.textContent = "Loading…";
    detail.textContent = "";
    let envBody, trackBody;
    try {
      [envBody, trackBody] = await Promise.all([
        seriesRequest(vehicleId, spec.name, s, e, chartFields(spec), CHART_POINTS, "minmax"),
        seriesRequest(vehicleId, spec.name, s, e, trackFields(spec), TRACK_POINTS, "first"),
      ]);
    } catch (err) {
      if (my === loadGen) msg.textContent = `Could not load: ${err.message}`;
      return;
    }
    if (my !== loadGen) return;
    env = envBody.columns;
    track = trackBody.columns;
    range = { s, e };
    heatCache.clear();
    xs = track.stamp_ns.map((t) => t / 1e9);
    metric = slipMetric(spec, track);
    msg.textContent = `${envBody.rows} points`;
    detail.textContent = describe(envBody, trackBody, s, e);
    const shade = qualitySpans(spec, env);
    for (const c of charts) {
      fitWidth(c.chart, c.box);
      setShading(c.chart, shade);
      c.chart.setData(alignedData(env, c.fields));
    }
    // state bands from whole rows (a min/max bucket mixes states), on the first chart's axis
    const rows = track;
    requestAnimationFrame(() => bands.forEach((b) => b.draw(rows, charts[0]?.chart))); // after uPlot's rescale
    const pos = spec.position;
    if (pos) map.setTrack(track[pos.east_field], track[pos.north_field], metric, xs);
    else map.setTrack([], [], []);
    map.setCarried(pos ? carriedRows(spec, track) : null, pos ? positionSigma(pos, track) : null);
    scrub.max = String(Math.max(0, xs.length - 1));
    scrub.disabled = xs.length === 0;
    play.disabled = xs.length === 0;
    applyHeat();
    showAt(xs.length - 1);
  }

  const bisect = (t) => lastAtOrBefore(xs, t);

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
  layerSel.addEventListener("change", applyHeat);
  cell.addEventListener("change", applyHeat);
  preset.addEventListener("change", () => {
    if (preset.value === CUSTOM) return;
    const e = parseClock(end.value);
    setPresetRange(e != null ? e : BigInt(Date.now()) * 1000000n);
  });
  // a time typed by hand is a custom range
  for (const input of [start, end]) {
    input.addEventListener("input", () => {
      preset.value = CUSTOM;
      setInvalid(input, false);
    });
    input.addEventListener("keydown", (ev) => {
      if (ev.key === "Enter") doLoad();
    });
  }
  load.addEventListener("click", doLoad);

  // default range: the last 30 min up to the newest estimate (or now)
  function loadDefaultRange() {
    return getJSON(`/api/v1/vehicles/${encodeURIComponent(vehicleId)}/latest`, { estimator: spec.name })
      .then((row) => BigInt(Math.floor(row.stamp_ns / 1e6)) * 1000000n + 1000000n)
      .catch(() => BigInt(Date.now()) * 1000000n)
      .then((endNs) => {
        setPresetRange(endNs);
        doLoad();
      });
  }
  const onResize = () => {
    if (!env) return;
    for (const c of charts) fitWidth(c.chart, c.box);
    map.draw();
  };
  window.addEventListener("resize", onResize);
  return () => {
    stop();
    loadGen++;
    heatGen++;
    window.removeEventListener("resize", onResize);
    for (const c of charts) c.chart.destroy();
  };
}
