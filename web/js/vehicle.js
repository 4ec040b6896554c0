// Vehicle page, live: slip and speed charts over a sliding window (30 s – 30 min) and the track on
// the slip map, from the /live/vehicles/{id} WebSocket (snapshot, then appends at 2–4 Hz).
//
// A vehicle that is not live (the feed's status "stale" or "offline", or the connection lost) keeps
// its last values on the page, dimmed, with the age of its data ("last data 52 s ago"); that age is
// not latency. A vehicle the server does not know (404, and no live data) gets a message and the
// page stops asking for it.

import { ApiError, fetchReport, fetchVehicle, liveSocket } from "./api.js";
import { SLIP_FIELDS, SPEED_FIELDS, alignedData, makeChart, setThreshold } from "./charts.js";
import { slipCss } from "./colors.js";
import { SlipMap, slipMetric } from "./slipmap.js";
import { el, fmt, fmtTimeNs, vehicleHref } from "./util.js";

const WINDOWS = [
  [30, "30 s"],
  [60, "1 min"],
  [300, "5 min"],
  [600, "10 min"],
  [1800, "30 min"],
];
const COLS = ["stamp_ns", ...SLIP_FIELDS, ...SPEED_FIELDS, "east_m", "north_m", "flags"];
const ALERT_THRESHOLD_PCT = 15; // SlipConfig default, until the vehicle's own config is loaded
// GNSS quality (the live feed's label) said in words where it is not "ok" or "gated"; the value
// takes the fleet table's class gnss-<label> (colour and weight)
const GNSS_NOTES = {
  degraded: "GNSS lost: speed from IMU + wheels",
  none: "no GNSS fix",
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

export function vehicleView(root, vehicleId) {
  let windowS = 60;
  let cols = null;
  let pending = false;
  let stopped = false;
  let connected = false;
  let latest = null; // newest "latest" of the feed, and its receive time (ms since the epoch)
  let latestRecvMs = 0;
  let latencyStamp = null; // stamp of the estimate last measured for latency
  let notStored = null; // the 404 of GET /vehicles/{id}
  let liveEmpty = false; // the live feed has nothing for the vehicle ("waiting", or no socket)
  const title = el("h1", {}, "Vehicle ", el("span", { class: "mono", text: vehicleId }));
  const statusPill = el("span", { class: "pill", id: "v-status", text: "connecting" });
  const ageNote = el("span", { class: "data-age", id: "v-age", hidden: true });
  const winButtons = el("div", { class: "seg", role: "group", "aria-label": "Chart window" });
  for (const [s, label] of WINDOWS) {
    const b = el("button", { type: "button", "data-window": s, "aria-pressed": String(s === windowS), text: label });
    b.addEventListener("click", () => {
      windowS = s;
      for (const x of winButtons.children) x.setAttribute("aria-pressed", String(x === b));
      sock.send({ window_s: s });
    });
    winButtons.append(b);
  }
  const stats = el(
    "div",
    { class: "stats" },
    stat("Slip left", "v-slip-left", "%"),
    stat("Slip right", "v-slip-right", "%"),
    stat("Ground speed Vg", "v-vg", "m/s"),
    stat("GNSS", "v-gnss"),
    stat("Sensor time", "v-stamp"),
    stat("Latency sensor → page", "v-latency", "ms"),
  );
  // Packet accounting of the vehicle (totals since registration): every packet the server got
  // is accepted, late, a duplicate or rejected with a reason; lost = sequence numbers never seen.
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
  const slipBox = el("div", { class: "chart", id: "chart-slip" });
  const speedBox = el("div", { class: "chart", id: "chart-speed" });
  const canvas = el("canvas", { class: "map", id: "live-map", role: "img", "aria-label": "Track of the window coloured by slip" });
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
    el("div", { class: "grid2" }, el("div", {}, slipBox, speedBox), el("div", {}, canvas, ingest)),
  );
  const slipChart = makeChart(slipBox, {
    title: "Wheel slip",
    yLabel: "slip (%)",
    fields: SLIP_FIELDS,
    threshold: ALERT_THRESHOLD_PCT,
    decimals: 1,
    syncKey: `live-${vehicleId}`,
  });
  const speedChart = makeChart(speedBox, {
    title: "Speeds",
    yLabel: "speed (m/s)",
    fields: SPEED_FIELDS,
    decimals: 2,
    syncKey: `live-${vehicleId}`,
  });
  const map = new SlipMap(canvas, { title: "Track (window) coloured by max |slip| of the two wheels" });
  fetchVehicle(vehicleId)
    .then((v) => {
      if (stopped) return;
      setThreshold(slipChart, v.config.slip.alert_threshold_pct);
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

  // The server does not know the vehicle: say so, stop the socket and the polling.
  function checkUnknown() {
    if (!notStored || !liveEmpty || cols || stopped) return;
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

  // Old or current: dim the values of a vehicle that is not live and show their age (the feed's
  // age at receipt plus the time since, so it goes on counting without messages).
  function showAge() {
    if (!latest) return;
    const old = !connected || latest.status !== "live";
    stats.classList.toggle("is-old", old);
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

  function showLatest(lt, recvMs) {
    if (!lt) return;
    latest = lt;
    latestRecvMs = recvMs;
    const sl = latest.slip_left_pct;
    const sr = latest.slip_right_pct;
    const a = document.getElementById("v-slip-left");
    const b = document.getElementById("v-slip-right");
    a.textContent = fmt(sl, 1);
    b.textContent = fmt(sr, 1);
    a.style.borderColor = slipCss(sl);
    b.style.borderColor = slipCss(sr);
    // why a wheel has no slip value (standing, starting or stopping), from the estimate's flags
    document.getElementById("v-slip-left-note").textContent = sl == null ? latest.slip_note || "" : "";
    document.getElementById("v-slip-right-note").textContent = sr == null ? latest.slip_note || "" : "";
    a.dataset.stampNs = String(latest.stamp_ns);
    document.getElementById("v-vg").textContent = fmt(latest.vg_mps, 2);
    const gnss = document.getElementById("v-gnss");
    gnss.textContent = latest.gnss;
    gnss.className = `gnss-${latest.gnss}`; // the fleet table's rule
    document.getElementById("v-gnss-note").textContent = GNSS_NOTES[latest.gnss] || "";
    document.getElementById("v-stamp").textContent = fmtTimeNs(latest.stamp_ns);
    // latency: only a new estimate of a live vehicle (a heartbeat repeats the newest estimate, and
    // a stale vehicle's is as old as its silence)
    if (latest.status === "live" && latest.stamp_ns !== latencyStamp) {
      latencyStamp = latest.stamp_ns;
      const lat = recvMs - latest.stamp_ns / 1e6;
      document.getElementById("v-latency").textContent = fmt(lat, 0);
      document.getElementById("v-latency-note").textContent = "";
      const L = window.slipfleetStats.latencyMs;
      L.push(lat);
      if (L.length > 10000) L.splice(0, L.length - 10000);
    }
    statusPill.textContent = latest.status;
    statusPill.className = `pill st-${latest.status}`;
    showAge();
  }

  function redraw() {
    pending = false;
    if (!cols || stopped) return;
    // the charts follow their boxes' widths themselves (charts.js)
    slipChart.setData(alignedData(cols, SLIP_FIELDS));
    speedChart.setData(alignedData(cols, SPEED_FIELDS));
    map.setTrack(cols.east_m, cols.north_m, slipMetric(cols.slip_left_pct, cols.slip_right_pct));
    map.draw();
  }

  function merge(fromNs, add) {
    // drop points at or after fromNs, append, trim to the window
    let keep = cols.stamp_ns.length;
    while (keep > 0 && cols.stamp_ns[keep - 1] >= fromNs) keep--;
    for (const k of COLS) {
      cols[k].length = keep;
      const extra = add[k] || [];
      for (const v of extra) cols[k].push(v);
    }
    const n = cols.stamp_ns.length;
    if (n) {
      const start = cols.stamp_ns[n - 1] - windowS * 1e9;
      let drop = 0;
      while (drop < n && cols.stamp_ns[drop] < start) drop++;
      if (drop) for (const k of COLS) cols[k].splice(0, drop);
    }
  }

  const sock = liveSocket(`/api/v1/live/vehicles/${encodeURIComponent(vehicleId)}`, { window_s: windowS }, {
    onMessage(msg, recvMs) {
      if (stopped) return;
      if (msg.type === "waiting") {
        statusPill.textContent = "no data yet";
        liveEmpty = true;
        checkUnknown();
        return;
      }
      if (msg.type === "snapshot") {
        cols = {};
        for (const k of COLS) cols[k] = (msg.columns[k] || []).slice();
        windowS = msg.window_s;
      } else if (msg.type === "append" && cols) {
        merge(msg.from_ns, msg.columns);
      } else {
        return;
      }
      showLatest(msg.latest, recvMs);
      if (!pending) {
        pending = true;
        requestAnimationFrame(redraw);
      }
    },
    onState(s) {
      if (stopped) return;
      connected = s === "open";
      if (s !== "open") {
        statusPill.textContent = `connection ${s}`;
        statusPill.className = "pill st-offline";
        showAge();
        if (!cols) {
          liveEmpty = true;
          checkUnknown();
        }
      }
    },
  });
  const onResize = () => redraw();
  window.addEventListener("resize", onResize);

  function stop() {
    if (stopped) return;
    stopped = true;
    clearInterval(ingestTimer);
    clearInterval(ageTimer);
    sock.close();
    window.removeEventListener("resize", onResize);
    slipChart.destroy();
    speedChart.destroy();
  }
  return stop;
}
