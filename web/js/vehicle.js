// Vehicle page, live: one panel per estimator the vehicle runs (its primary first), each drawn
// from the estimator's spec (GET /api/v1/estimators): a tile per slip channel (band colour from
// the band edges), its motion speed, quality and flags, and a chart per ChartSpec with its
// degraded stretches shaded; the primary's track on the slip map, its marker at the charts'
// cursor while one is hovered (else at the newest point). Each panel has its own
// /live/vehicles/{id}?estimator= WebSocket (snapshot, then appends at 2–10 Hz); the primary's
// messages list the vehicle's other estimators, whose panels are added as they appear.
//
// A vehicle that is not live (the feed's status "stale" or "offline", or the connection lost) keeps
// its last values on the page, dimmed, with the age of its data ("last data 52 s ago"); that age is
// not latency. A vehicle the server does not know (404, and no live data) gets a message and the
// page stops asking for it. A stored vehicle with no live data (parked since the server started)
// is marked "not live", with the time of its newest stored estimate and a way to its history.

import { calibrationPanel } from "./calibration.js";
import { ApiError, fetchReport, fetchVehicle, getJSON, liveSocket, loadDashboardConfig } from "./api.js";
import { alignedData, chartOptions, qualitySpans, makeChart, setShading, setThreshold } from "./charts.js";
import { gripCss, slipBand, slipCss } from "./colors.js";
import { SlipMap, showLayerHeat } from "./slipmap.js";
import { carriedRows, fieldOf, loadSpecs, motionChannel, positionSigma, slipMetric } from "./specs.js";
import { StateBand, stateColor, stateOf } from "./states.js";
import { el, fmt, fmtSpeed, fmtTimeNs, timeTitle, vehicleHref } from "./util.js";

const WINDOWS = [
  [30, "30 s"],
  [60, "1 min"],
  [300, "5 min"],
  [600, "10 min"],
  [1800, "30 min"],
];
const ALERT_THRESHOLD_PCT = 15; // SlipConfig default, until the vehicle's own config is loaded
// Quality of a row (the live feed's label) said in words where it is not "ok"
const QUALITY_NOTES = {
  degraded: "computed without its main reference",
  none: "no reference yet",
};

// Shared with tests and the latency benchmark: receive time minus sensor stamp, ms, of each new
// estimate of a live vehicle (a repeated estimate or a stale vehicle's is data age, not latency).
window.slipfleetStats = window.slipfleetStats || {};
window.slipfleetStats.latencyMs = window.slipfleetStats.latencyMs || [];

// "52 s", "3 min 5 s", "2 h 4 min"
function fmtAge(s) {
  const t = Math.max(0, Math.round(s));
  if (t < 60) return `${t} s`;
  if (t < 3600) return `${Math.floor(t / 60)} min ${t % 60} s`;
  return `${Math.floor(t / 3600)} h ${Math.floor((t % 3600) / 60)} min`;
}

function stat(label, id, unit) {
  return el(
    "div",
    { class: "stat" },
    el("div", { class: "stat-label", text: label }),
    el("div", { class: "stat-value" }, el("span", { id, text: "–" }), unit ? el("span", { class: "unit", text: ` ${unit}` }) : null),
    el("div", { class: "stat-note", id: `${id}-note` }),
  );
}

// Window columns of a live message: drop points at or after fromNs, append, trim to the window.
function mergeColumns(cols, fromNs, add, windowS) {
  let keep = cols.stamp_ns.length;
  while (keep > 0 && cols.stamp_ns[keep - 1] >= fromNs) keep--;
  for (const k of Object.keys(cols)) {
    cols[k].length = keep;
    for (const v of add[k] || []) cols[k].push(v);
  }
  const n = cols.stamp_ns.length;
  if (!n) return;
  const start = cols.stamp_ns[n - 1] - windowS * 1e9;
  let drop = 0;
  while (drop < n && cols.stamp_ns[drop] < start) drop++;
  if (drop) for (const k of Object.keys(cols)) cols[k].splice(0, drop);
}

// One estimator's panel: tiles and charts from its spec; the page hands it its socket's messages.
// page: {vehicleId, windowS(), bandEdges(channel), threshold(), standstill(), onLatest(name, latest, recvMs),
// onColumns(name, cols)}
function estimatorPanel(spec, page, primary) {
  const id = (part) => `v-${spec.name}-${part}`;
  const motion = motionChannel(spec);
  const tiles = el(
    "div",
    { class: "stats" },
    ...spec.slips.map((ch) => stat(/^slip\b/i.test(ch.label) ? ch.label : `Slip ${ch.label}`, id(`slip-${ch.key}`), "%")),
    ...spec.states.map((ch) => stat(ch.label, id(`state-${ch.key}`))),
    ...spec.values.map((ch) => stat(ch.label, id(`value-${ch.key}`), ch.unit)),
    ...spec.wheel_values.map((ch) => stat(ch.label, id(`wheel-${ch.key}`), "%")),
    motion ? stat(motion.label, id("speed"), fieldOf(spec, motion.field).unit) : null,
    stat("Quality", id("quality")),
    spec.flags.length ? stat("Flags", id("flags")) : null,
  );
  const boxes = spec.charts.map((c) => el("div", { class: "chart", id: `chart-${spec.name}-${c.key}` }));
  const bandBoxes = spec.states.map((ch) => el("div", { class: "state-band", id: `band-${spec.name}-${ch.key}`, "data-channel": ch.key }, el("div", { class: "state-band-title", text: ch.label })));
  const root = el(
    "section",
    { class: "est-panel", "data-estimator": spec.name, "aria-label": spec.title },
    el("h2", {}, spec.title, primary ? el("span", { class: "pill", text: "primary" }) : null),
    tiles,
    el("div", { class: "est-charts" }, ...boxes, ...bandBoxes),
  );
  const bands = spec.states.map((ch, i) => new StateBand(spec, ch, bandBoxes[i]));
  const charts = spec.charts.map((c, i) => {
    const o = chartOptions(spec, c);
    return makeChart(boxes[i], { ...o, threshold: o.isSlip ? page.threshold() : null, syncKey: `live-${page.vehicleId}`, onCursor: (_i, tS) => page.onCursor(tS) });
  });
  let cols = null;
  let pending = false;

  function showLatest(lt) {
    for (const ch of spec.slips) {
      const v = lt[ch.field];
      const e = document.getElementById(id(`slip-${ch.key}`));
      e.textContent = fmt(v, 1);
      e.style.borderColor = slipCss(v);
      e.dataset.band = String(slipBand(v, page.bandEdges(ch)));
      e.dataset.stampNs = String(lt.stamp_ns);
      // why a channel has no value: the row's flags other than its quality (standstill, …)
      const why = lt.flag_names.filter((f) => f !== spec.ok_flag && !spec.slips.some((c) => c.valid_flag === f));
      document.getElementById(`${id(`slip-${ch.key}`)}-note`).textContent = v == null ? `no value: ${why.join(", ").toLowerCase().replace(/_/g, " ") || "unknown"}` : "";
    }
    showChannels(lt);
    if (motion) document.getElementById(id("speed")).textContent = fmtSpeed(lt[motion.field], page.standstill());
    const q = document.getElementById(id("quality"));
    q.textContent = lt.quality;
    q.className = `quality-${lt.quality}`;
    const degraded = lt.flag_names.filter((f) => spec.degraded_flags.includes(f));
    const notes = degraded.map((f) => spec.flags.find((x) => x.name === f).description);
    document.getElementById(`${id("quality")}-note`).textContent = notes.join("; ") || (QUALITY_NOTES[lt.quality] ?? "");
    if (spec.flags.length) document.getElementById(id("flags")).textContent = lt.flag_names.join(" ") || "none";
  }

  // State, value and wheel value tiles of the newest row: a state in its band colour (marked
  // when uncertain), a value said "held" where its row does not inform it, a wheel's share in
  // its grip colour.
  function showChannels(lt) {
    for (const ch of spec.states) {
      const e = document.getElementById(id(`state-${ch.key}`));
      const st = stateOf(ch, lt[ch.field]);
      e.textContent = st ? st.label : "–";
      e.dataset.state = st ? st.name : "";
      e.style.borderColor = stateColor(ch, lt[ch.field]);
      const unsure = ch.uncertain_flag && lt.flag_names.includes(ch.uncertain_flag);
      const conf = ch.confidence_field ? lt[ch.confidence_field] : null;
      document.getElementById(`${id(`state-${ch.key}`)}-note`).textContent = [unsure ? "uncertain" : "", conf == null ? "" : `confidence ${fmt(conf * 100, 0)} %`].filter(Boolean).join(", ");
    }
    for (const ch of spec.values) {
      const e = document.getElementById(id(`value-${ch.key}`));
      const informed = !ch.valid_flag || lt.flag_names.includes(ch.valid_flag);
      const std = ch.std_field ? lt[ch.std_field] : null;
      e.textContent = fmt(lt[ch.field], 3);
      e.dataset.informed = String(informed);
      e.classList.toggle("value-held", !informed);
      const sigma = std == null ? "" : `± ${fmt(std, 3)} (1σ)`;
      const note = informed ? sigma : lt[ch.field] == null ? "not informed yet" : ["held: not informed now", sigma].filter(Boolean).join(", ");
      document.getElementById(`${id(`value-${ch.key}`)}-note`).textContent = note;
    }
    for (const ch of spec.wheel_values) {
      const e = document.getElementById(id(`wheel-${ch.key}`));
      e.textContent = fmt(lt[ch.field], 0);
      e.style.borderColor = gripCss(lt[ch.field]);
    }
  }

  function redraw() {
    pending = false;
    if (!cols) return;
    const shade = qualitySpans(spec, cols);
    spec.charts.forEach((c, i) => {
      setShading(charts[i], shade);
      charts[i].setData(alignedData(cols, c.fields));
    });
    const rows = cols;
    requestAnimationFrame(() => bands.forEach((b) => b.draw(rows, charts[0]))); // after uPlot's rescale
    page.onColumns(spec.name, cols);
  }

  function onMessage(msg, recvMs) {
    if (msg.type === "snapshot") {
      cols = {};
      for (const [k, v] of Object.entries(msg.columns)) cols[k] = v.slice();
    } else if (msg.type === "append" && cols) {
      mergeColumns(cols, msg.from_ns, msg.columns, page.windowS());
    } else return false;
    if (msg.latest) {
      showLatest(msg.latest);
      page.onLatest(spec.name, msg.latest, recvMs);
    }
    if (!pending) {
      pending = true;
      requestAnimationFrame(redraw);
    }
    return true;
  }
  return {
    root,
    tiles,
    onMessage,
    setThreshold: (pct) => spec.charts.forEach((c, i) => chartOptions(spec, c).isSlip && setThreshold(charts[i], pct)),
    redraw,
    stop() {
      for (const c of charts) c.destroy();
    },
  };
}

export function vehicleView(root, vehicleId) {
  let windowS = 60;
  let stopped = false;
  let connected = false;
  let threshold = ALERT_THRESHOLD_PCT;
  let bandEdges = null; // the vehicle's SlipConfig.band_edges_pct, once loaded
  let standstillMps = null; // its SlipConfig.min_ground_speed_mps, once loaded
  let specs = null; // name -> spec
  let primary = null; // name of the primary estimator, from its socket's first message
  let latest = null; // newest "latest" of the primary, and its receive time (ms since the epoch)
  let latestRecvMs = 0;
  let latencyStamp = null; // stamp of the estimate last measured for latency
  let notStored = null; // the 404 of GET /vehicles/{id}
  let stored = false; // GET /vehicles/{id} found it
  let parked = null; // the "not live" note, once shown
  let liveEmpty = false; // the live feed has nothing for the vehicle ("waiting", or no socket)
  let cursorS = null; // time under the charts' cursor (seconds), null when none is hovered
  const panels = new Map(); // estimator -> panel
  let calibration = null; // the online calibration's panel, once the specs are loaded
  const sockets = new Map(); // estimator ("" for the primary's until it is known) -> socket
  const title = el("h1", {}, "Vehicle ", el("span", { class: "mono", text: vehicleId }));
  const statusPill = el("span", { class: "pill", id: "v-status", text: "connecting" });
  const ageNote = el("span", { class: "data-age", id: "v-age", hidden: true });
  const winButtons = el("div", { class: "seg", role: "group", "aria-label": "Chart window" });
  for (const [s, label] of WINDOWS) {
    const b = el("button", { type: "button", "data-window": s, "aria-pressed": String(s === windowS), text: label });
    b.addEventListener("click", () => {
      windowS = s;
      for (const x of winButtons.children) x.setAttribute("aria-pressed", String(x === b));
      for (const sock of new Set(sockets.values())) sock.send({ window_s: s });
    });
    winButtons.append(b);
  }
  const stats = el("div", { class: "stats" }, stat("Sensor time", "v-stamp"), stat("Latency sensor → page", "v-latency", "ms"));
  const panelBox = el("div", { class: "est-panels", id: "v-panels" });
  // Packet accounting of the vehicle (totals since registration): every packet the server got
  // is accepted, late, a duplicate or rejected with a reason; lost = sequence numbers never seen;
  // estimator errors = rows an estimator failed to compute for this vehicle.
  const ingestBody = el("tbody", { id: "v-ingest" });
  const ingest = el(
    "details",
    { class: "ingest", open: true },
    el("summary", { text: "Packets received from this vehicle" }),
    el("table", { class: "ingest-table" }, ingestBody),
  );
  async function refreshIngest() {
    const end = BigInt(Date.now()) * 1000000n;
    try {
      const rep = await fetchReport(vehicleId, end - 3600n * 1000000000n, end);
      const c = rep.ingest;
      const rows = [
        ["received", c.received],
        ["accepted", c.accepted],
        ["late (after the reorder window)", c.late],
        ["duplicate", c.duplicate],
        ["lost (sequence gaps)", c.lost],
        ["rejected", c.rejected],
        ...Object.entries(c.rejected_by_reason).map(([reason, n]) => [`  rejected: ${reason}`, n]),
        ...(c.estimator_errors === undefined ? [] : [["estimator errors", c.estimator_errors]]),
      ];
      ingestBody.replaceChildren(
        ...rows.map(([label, n]) =>
          el("tr", { "data-counter": label.trim() }, el("th", { text: label }), el("td", { class: "num", text: String(n) })),
        ),
      );
    } catch (_) {
      /* not registered yet, or refused: the next refresh tries again */
    }
  }
  let ingestTimer = null;
  function startIngest() {
    if (stopped || ingestTimer !== null) return;
    refreshIngest();
    ingestTimer = setInterval(refreshIngest, 5000);
  }
  const canvas = el("canvas", { class: "map", id: "live-map", role: "img", "aria-label": "Track of the window coloured by slip" });
  const mapTitle = el("h2", { class: "map-title", id: "live-map-title" });
  // heat cells of a map layer of the primary (a mapped value channel) over the window, if any
  const layerSel = el("select", { id: "live-layer", "aria-label": "Map layer" });
  const layerMsg = el("span", { id: "live-layer-msg", class: "summary" });
  const layerBox = el("div", { class: "toolbar", hidden: true }, el("label", {}, "Cells ", layerSel), layerMsg);
  root.append(
    el(
      "div",
      { class: "toolbar" },
      title,
      statusPill,
      ageNote,
      el("a", { href: vehicleHref(vehicleId, "history"), class: "button", text: "History & slip map" }),
      winButtons,
    ),
    stats,
    el("div", { class: "grid2" }, panelBox, el("div", {}, mapTitle, layerBox, canvas, ingest)),
  );
  const map = new SlipMap(canvas, { title: "Track (window) coloured by max |slip| of the wheels", titleEl: mapTitle });
  loadDashboardConfig().then((cfg) => map.setTiles(cfg.map_tile_url));
  fetchVehicle(vehicleId)
    .then((v) => {
      if (stopped) return;
      threshold = v.config.slip.alert_threshold_pct;
      bandEdges = v.config.slip.band_edges_pct;
      standstillMps = v.config.slip.min_ground_speed_mps;
      map.setAnchor(v.anchor); // latitude/longitude axes once the vehicle has a stored anchor
      map.draw();
      for (const p of panels.values()) p.setThreshold(threshold);
      stored = true;
      showParked();
      startIngest();
    })
    .catch((err) => {
      if (stopped) return;
      if (err instanceof ApiError && err.status === 404) {
        // not stored: unknown, unless the live feed has data of it (stored a moment later)
        notStored = err;
        ingest.hidden = true;
        checkUnknown();
      } else startIngest(); // keep the default threshold
    });

  // The server does not know the vehicle: say so, stop the sockets and the polling.
  function checkUnknown() {
    if (!notStored || !liveEmpty || panels.size || stopped) return;
    stop();
    root.replaceChildren(
      el("div", { class: "toolbar" }, title),
      el(
        "div",
        { class: "panel-msg", id: "v-unknown", role: "alert" },
        el("p", {}, "Unknown vehicle ", el("strong", { class: "mono", text: vehicleId }), ": the server has no vehicle with this id."),
        el("p", {}, el("a", { href: "#/fleet", text: "Back to the fleet" })),
      ),
    );
  }

  // A stored vehicle without live data: say so, with its newest stored estimate's time.
  function showParked() {
    if (!stored || !liveEmpty || panels.size || parked || stopped) return;
    const when = el("span", { id: "v-parked-last", text: "…" });
    parked = el(
      "div",
      { class: "panel-msg", id: "v-parked", role: "status" },
      el("p", {}, "Not live: the server has received nothing from this vehicle since it started."),
      el("p", {}, "Newest stored estimate: ", when, ". ", el("a", { href: vehicleHref(vehicleId, "history"), text: "Its history and slip map" }), "."),
    );
    stats.after(parked);
    statusPill.textContent = "not live";
    statusPill.className = "pill st-stored";
    getJSON(`/api/v1/vehicles/${encodeURIComponent(vehicleId)}/latest`)
      .then((row) => {
        when.textContent = fmtTimeNs(row.stamp_ns, false);
        when.title = timeTitle(row.stamp_ns);
        when.dataset.stampNs = String(row.stamp_ns);
      })
      .catch(() => {
        when.textContent = "none";
      });
  }

  // Old or current: dim the values of a vehicle that is not live and show their age (the feed's
  // age at receipt plus the time since, so it goes on counting without messages).
  function showAge() {
    if (!latest) return;
    const old = !connected || latest.status !== "live";
    for (const box of [stats, ...[...panels.values()].map((p) => p.tiles)]) box.classList.toggle("is-old", old);
    ageNote.hidden = !old;
    if (old) {
      const age = (latest.age_s ?? 0) + (performance.timeOrigin + performance.now() - latestRecvMs) / 1000;
      ageNote.textContent = `last data ${fmtAge(age)} ago`;
      document.getElementById("v-latency").textContent = "–";
      document.getElementById("v-latency-note").textContent = "not measured: no new data";
      latencyStamp = null;
    }
  }
  const ageTimer = setInterval(showAge, 1000);

  // The primary's newest row: sensor time, latency, status.
  function showLatest(lt, recvMs) {
    latest = lt;
    latestRecvMs = recvMs;
    document.getElementById("v-stamp").textContent = fmtTimeNs(lt.stamp_ns);
    document.getElementById("v-stamp").title = timeTitle(lt.stamp_ns);
    document.getElementById("v-stamp").dataset.stampNs = String(lt.stamp_ns);
    // latency: only a new estimate of a live vehicle (a heartbeat repeats the newest estimate, and
    // a stale vehicle's is as old as its silence)
    if (lt.status === "live" && lt.stamp_ns !== latencyStamp) {
      latencyStamp = lt.stamp_ns;
      const lat = recvMs - lt.stamp_ns / 1e6;
      document.getElementById("v-latency").textContent = fmt(lat, 0);
      document.getElementById("v-latency-note").textContent = "";
      const L = window.slipfleetStats.latencyMs;
      L.push(lat);
      if (L.length > 10000) L.splice(0, L.length - 10000);
    }
    statusPill.textContent = lt.status;
    statusPill.className = `pill st-${lt.status}`;
    showAge();
  }

  const page = {
    vehicleId,
    windowS: () => windowS,
    threshold: () => threshold,
    standstill: () => standstillMps,
    bandEdges: (ch) => bandEdges || ch.band_edges_pct,
    onLatest(name, lt, recvMs) {
      if (name === primary) showLatest(lt, recvMs);
    },
    onColumns(name, cols) {
      const spec = specs.get(name);
      if (name === primary && !spec.position && !canvas.hidden) {
        // nothing to map: say so once instead of waiting for a position forever
        canvas.hidden = true;
        mapTitle.textContent = `No map: ${spec.title} gives no position`;
      }
      if (name !== primary || !spec.position) return;
      const stampsS = cols.stamp_ns.map((t) => t / 1e9);
      const p = spec.position;
      map.setTrack(cols[p.east_field], cols[p.north_field], slipMetric(spec, cols), stampsS);
      map.setCarried(carriedRows(spec, cols), positionSigma(p, cols));
      map.cursor = map.indexAt(cursorS);
      map.draw();
    },
    // a chart's cursor at tS (seconds; null: it left the chart) puts the map's marker there
    onCursor(tS) {
      cursorS = tS;
      map.cursor = map.indexAt(tS);
      map.draw();
    },
  };

  // The primary's map layers in the "Cells" menu (hidden without any).
  function offerLayers(spec) {
    const layers = spec.position ? spec.values.filter((v) => v.mapped) : [];
    layerSel.replaceChildren(el("option", { value: "", text: "none" }), ...layers.map((v) => el("option", { value: v.key, text: `mean ${v.label}` })));
    layerBox.hidden = !layers.length;
  }

  // The layer's cells over the chart window, from the stored rows (every 5 s while chosen).
  let layerTimer = null;
  async function refreshLayer() {
    const key = layerSel.value;
    if (!key || stopped) {
      map.setHeat(null, 0);
      layerMsg.textContent = "";
      map.draw();
      return;
    }
    const end = BigInt(Date.now()) * 1000000n;
    try {
      const body = await getJSON(`/api/v1/vehicles/${encodeURIComponent(vehicleId)}/slipmap`, {
        estimator: primary,
        start: (end - BigInt(windowS) * 1000000000n).toString(),
        end: end.toString(),
        cell_m: 10,
        layer: key,
      });
      if (stopped || layerSel.value !== key) return;
      layerMsg.textContent = showLayerHeat(map, body);
    } catch (err) {
      map.setHeat(null, 0);
      layerMsg.textContent = `no cells: ${err.reason || err.message}`;
    }
    map.draw();
  }
  layerSel.addEventListener("change", () => {
    clearInterval(layerTimer);
    refreshLayer();
    if (layerSel.value) layerTimer = setInterval(refreshLayer, 5000);
  });

  function addPanel(name) {
    const spec = specs.get(name);
    if (!spec || panels.has(name)) return;
    if (name === primary) offerLayers(spec);
    if (parked) parked.remove(); // live again
    const panel = estimatorPanel(spec, page, name === primary);
    panels.set(name, panel);
    panelBox.append(panel.root);
  }

  // A socket of one estimator (null: the vehicle's primary, named by its first message).
  function openSocket(name) {
    const sock = liveSocket(
      `/api/v1/live/vehicles/${encodeURIComponent(vehicleId)}`,
      name ? { estimator: name, window_s: windowS } : { window_s: windowS },
      {
        onMessage(msg, recvMs) {
          if (stopped) return;
          if (name === null && msg.estimator && primary === null) {
            primary = msg.estimator;
            sockets.set(primary, sock);
          }
          for (const other of msg.estimators || []) if (!sockets.has(other)) openSocket(other);
          const key = name ?? primary;
          if (msg.type === "waiting") {
            if (key === primary && !panels.size) {
              if (!parked) statusPill.textContent = "no data yet";
              liveEmpty = true;
              checkUnknown();
              showParked();
            }
            return;
          }
          if (key) addPanel(key);
          if (key && panels.get(key)) panels.get(key).onMessage(msg, recvMs);
        },
        onState(s) {
          if (stopped || (name ?? primary) !== primary) return;
          connected = s === "open";
          if (s !== "open") {
            statusPill.textContent = `connection ${s}`;
            statusPill.className = "pill st-offline";
            showAge();
            if (!panels.size) {
              liveEmpty = true;
              checkUnknown();
            }
          }
        },
      },
    );
    sockets.set(name ?? "", sock);
  }
  loadSpecs()
    .then((all) => {
      if (stopped) return;
      specs = all;
      calibration = calibrationPanel(vehicleId, all);
      ingest.before(calibration.root);
      openSocket(null);
    })
    .catch(() => {
      if (!stopped) statusPill.textContent = "estimators unavailable";
    });

  const onResize = () => panels.forEach((p) => p.redraw());
  window.addEventListener("resize", onResize);

  function stop() {
    if (stopped) return;
    stopped = true;
    clearInterval(ingestTimer);
    clearInterval(ageTimer);
    clearInterval(layerTimer);
    calibration?.stop();
    for (const sock of new Set(sockets.values())) sock.close();
    window.removeEventListener("resize", onResize);
    for (const p of panels.values()) p.stop();
  }
  return stop;
}
