// Vehicle page, live: slip and speed charts over a sliding window (30 s – 30 min) and the track on
// the slip map, from the /live/vehicles/{id} WebSocket (snapshot, then appends at 2–4 Hz).

import { fetchReport, fetchVehicle, liveSocket } from "./api.js";
import { SLIP_FIELDS, SPEED_FIELDS, alignedData, fitWidth, makeChart, setThreshold } from "./charts.js";
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

// Shared with tests and the latency benchmark: receive time minus sensor stamp, ms.
window.slipfleetStats = window.slipfleetStats || {};
window.slipfleetStats.latencyMs = window.slipfleetStats.latencyMs || [];

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
  const title = el("h1", {}, "Vehicle ", el("span", { class: "mono", text: vehicleId }));
  const statusPill = el("span", { class: "pill", id: "v-status", text: "connecting" });
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
  refreshIngest();
  const ingestTimer = setInterval(refreshIngest, 5000);
  const slipBox = el("div", { class: "chart", id: "chart-slip" });
  const speedBox = el("div", { class: "chart", id: "chart-speed" });
  const canvas = el("canvas", { class: "map", id: "live-map", role: "img", "aria-label": "Track of the window coloured by slip" });
  root.append(
    el(
      "div",
      { class: "toolbar" },
      title,
      statusPill,
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
    .then((v) => setThreshold(slipChart, v.config.slip.alert_threshold_pct))
    .catch(() => {}); // unknown to the store yet: keep the default

  function showLatest(latest, recvMs) {
    if (!latest) return;
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
    document.getElementById("v-gnss").textContent = latest.gnss;
    document.getElementById("v-stamp").textContent = fmtTimeNs(latest.stamp_ns);
    const lat = recvMs - latest.stamp_ns / 1e6;
    document.getElementById("v-latency").textContent = fmt(lat, 0);
    const L = window.slipfleetStats.latencyMs;
    L.push(lat);
    if (L.length > 10000) L.splice(0, L.length - 10000);
    statusPill.textContent = latest.status;
    statusPill.className = `pill st-${latest.status}`;
  }

  function redraw() {
    pending = false;
    if (!cols) return;
    fitWidth(slipChart, slipBox);
    fitWidth(speedChart, speedBox);
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
      if (msg.type === "waiting") {
        statusPill.textContent = "no data yet";
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
      if (s !== "open") {
        statusPill.textContent = `connection ${s}`;
        statusPill.className = "pill st-offline";
      }
    },
  });
  const onResize = () => redraw();
  window.addEventListener("resize", onResize);
  return () => {
    clearInterval(ingestTimer);
    sock.close();
    window.removeEventListener("resize", onResize);
    slipChart.destroy();
    speedChart.destroy();
  };
}
