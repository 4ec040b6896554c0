// Fleet overview: one row per vehicle, fed by the /live/fleet WebSocket at 2 Hz.
// Rows are virtualised (only the visible ones exist in the DOM) so 1,000+ vehicles stay cheap;
// an update only rewrites the text and classes of those rows. The header sits inside the same
// scroll box as the rows (sticky at its top), so header and rows always share one width and
// scroll sideways together. Rows of stale and offline vehicles carry row-stale / row-offline:
// their last values are shown greyed and without slip-band shading, never as if live.
//
// Each vehicle is shown by its primary estimator (the feed's `estimator`): its motion speed, a
// column per slip channel key of any primary (labelled from the specs, GET /api/v1/estimators;
// band edges from the vehicle's config, else the channel's) and its quality.
//
// Stored vehicles the live feed does not hold (GET /api/v1/vehicles; parked since the server
// started) are listed too, with status "stored" (shown "not live") and their newest stored
// estimate (GET /vehicles/{id}/latest) greyed like an offline vehicle's, so they can be opened.

import { ApiError, fetchVehicles, getJSON, liveSocket } from "./api.js";
import { slipBand, slipCss } from "./colors.js";
import { fleetMapPanel } from "./fleetmap.js";
import { loadSpecs, motionChannel } from "./specs.js";
import { el, fmt, fmtSpeed, fmtTimeNs, timeTitle, vehicleHref } from "./util.js";

const ROW_H = 32; // px, keep in sync with .vrow in app.css
const STATUS_ORDER = { live: 0, stale: 1, offline: 2, stored: 3 };
const STATUS_TEXT = { stored: "not live" };
const LATEST_PER_REFRESH = 50; // newest stored estimates fetched per refresh of the stored list
const STORED_REFRESH_MS = 15000; // the stored list (band edges, anchors of new vehicles)

// Cost of applying one fleet message (sort + render), ms; read by the live benchmark.
window.slipfleetStats = window.slipfleetStats || {};
window.slipfleetStats.fleetUpdateMs = window.slipfleetStats.fleetUpdateMs || [];
const QUALITY_ORDER = { ok: 0, degraded: 1, none: 2 };

// "L" for channel key "left", "RL" for "rear_left": the short label of a slip column
function initials(key) {
  return key
    .split(/[_-]/)
    .map((w) => w.charAt(0).toUpperCase())
    .join("");
}

// The table's columns for these slip channel keys; short: the label shown on narrow screens
// (app.css switches .lab-long / .lab-short). A slip column's key is "slip:<channel key>".
function columnsFor(slipKeys, specs) {
  const label = (key) => {
    for (const spec of specs.values()) {
      const ch = spec.slips.find((c) => c.key === key);
      if (ch) return ch.label;
    }
    return key;
  };
  return [
    { key: "id", label: "Vehicle", numeric: false },
    { key: "status", label: "Status", numeric: false },
    { key: "speed_mps", label: "Speed (m/s)", short: "m/s", numeric: true },
    ...slipKeys.map((k) => ({ key: `slip:${k}`, label: `Slip ${label(k)} (%)`, short: `Slip ${initials(k)}`, numeric: true, slip: k })),
    { key: "quality", label: "Quality", numeric: false },
    { key: "age_s", label: "Last update (s ago)", short: "Age (s)", numeric: true },
  ];
}

// A column's value of vehicle i in a fleet message.
function cellValue(d, i, c) {
  return c.slip ? d.slip_pct[c.slip][i] : d[c.key][i];
}

// The fleet message `msg` (null before the first) with a row appended for every stored vehicle
// it does not hold: status "stored", its newest stored estimate's speed and slips (null until
// fetched or when it has none), age from that estimate's stamp.
function withStored(msg, stored, specs) {
  const d = msg || { ids: [], estimator: [], status: [], stamp_ns: [], age_s: [], speed_mps: [], quality: [], flags: [], slip_pct: {} };
  const live = new Set(d.ids);
  const extra = [...stored.keys()].filter((id) => !live.has(id)).sort();
  if (!extra.length) return d;
  const out = { ...d, slip_pct: {} };
  for (const k of ["ids", "estimator", "status", "stamp_ns", "age_s", "speed_mps", "quality", "flags"]) out[k] = [...(d[k] || [])];
  for (const [k, col] of Object.entries(d.slip_pct)) out.slip_pct[k] = [...col];
  const nowNs = msg ? msg.t_ns : Date.now() * 1e6;
  for (const id of extra) {
    const s = stored.get(id);
    const spec = specs.get(s.estimator);
    const row = s.latest;
    const motion = spec && motionChannel(spec);
    const i = out.ids.length;
    out.ids.push(id);
    out.estimator.push(s.estimator);
    out.status.push("stored");
    out.stamp_ns.push(row ? row.stamp_ns : null);
    out.age_s.push(row ? Math.max(0, (nowNs - row.stamp_ns) / 1e9) : null);
    out.speed_mps.push(row && motion ? row[motion.field] : null);
    out.quality.push("–");
    out.flags.push(row ? row.flags : 0);
    for (const col of Object.values(out.slip_pct)) col.push(null);
    for (const ch of spec ? spec.slips : []) {
      const col = out.slip_pct[ch.key] || (out.slip_pct[ch.key] = new Array(i + 1).fill(null));
      col[i] = row ? row[ch.field] : null;
    }
  }
  return out;
}

export function fleetView(root) {
  // bandEdges: vehicle id -> its SlipConfig.band_edges_pct (the channel's edges until loaded)
  // msg: the newest fleet message; stored: vehicle id -> {estimator, latest} of every stored
  // vehicle (latest: its newest stored estimate, null if none, undefined until fetched)
  const state = { msg: null, data: null, order: [], sortKey: "id", sortDir: 1, filter: "", bandEdges: new Map(), specs: new Map(), stored: new Map(), anchors: new Map(), standstill: new Map() };
  let stopped = false;
  loadSpecs()
    .then((specs) => {
      state.specs = specs;
      columns = [];
      update();
    })
    .catch(() => {});
  let columns = [];
  // Newest stored estimates of stored vehicles the feed does not hold, a few per refresh (only
  // once the feed has said which vehicles it holds).
  async function fetchLatest() {
    if (!state.msg) return;
    const live = new Set(state.msg ? state.msg.ids : []);
    const wanted = [...state.stored.entries()].filter(([id, s]) => s.latest === undefined && !live.has(id));
    for (const [id, s] of wanted.slice(0, LATEST_PER_REFRESH)) {
      if (stopped) return;
      try {
        s.latest = await getJSON(`/api/v1/vehicles/${encodeURIComponent(id)}/latest`);
      } catch (err) {
        if (err instanceof ApiError && err.status === 404) s.latest = null; // none stored
      }
    }
    if (wanted.length) update();
  }
  let storedAtMs = -Infinity;
  const loadStored = () => {
    storedAtMs = performance.now();
    return fetchVehicles()
      .then((body) => {
        const ids = new Set();
        for (const v of body.data) {
          ids.add(v.vehicle_id);
          state.bandEdges.set(v.vehicle_id, v.config.slip.band_edges_pct);
          state.anchors.set(v.vehicle_id, v.anchor);
          state.standstill.set(v.vehicle_id, v.config.slip.min_ground_speed_mps);
          const prev = state.stored.get(v.vehicle_id);
          state.stored.set(v.vehicle_id, { estimator: v.estimators[0] || "", latest: prev ? prev.latest : undefined });
        }
        for (const id of [...state.stored.keys()]) if (!ids.has(id)) state.stored.delete(id);
        update();
        return fetchLatest();
      })
      .catch(() => {});
  };
  loadStored();
  const bandTimer = setInterval(loadStored, STORED_REFRESH_MS);
  // The table's data: the newest fleet message plus the stored vehicles it does not hold.
  function update() {
    state.data = withStored(state.msg, state.stored, state.specs);
    resort();
  }
  const summary = el("p", { class: "summary", "aria-live": "polite", id: "fleet-summary" }, "Connecting…");
  const filter = el("input", {
    type: "search",
    placeholder: "Filter vehicles…",
    "aria-label": "Filter vehicles by id",
    id: "fleet-filter",
  });
  const header = el("div", { class: "vrow vhead", role: "row" });
  let headButtons = {};
  // (Re)build the header and drop the row pool when the slip channel keys change.
  function setColumns(slipKeys) {
    const next = columnsFor(slipKeys, state.specs);
    if (columns.length && next.map((c) => c.label).join() === columns.map((c) => c.label).join()) return;
    columns = next;
    headButtons = {};
    header.replaceChildren();
    table.style.setProperty("--slip-cols", String(slipKeys.length));
    for (const c of columns) {
      const b = el(
        "button",
        { type: "button", class: c.numeric ? "num" : "", title: c.short ? c.label : null },
        ...(c.short
          ? [el("span", { class: "lab-long", text: c.label }), el("span", { class: "lab-short", text: c.short })]
          : [c.label]),
      );
      b.addEventListener("click", () => {
        if (state.sortKey === c.key) state.sortDir = -state.sortDir;
        else {
          state.sortKey = c.key;
          state.sortDir = c.numeric && c.key !== "age_s" ? -1 : 1;
        }
        resort();
      });
      const cell = el("div", { role: "columnheader", class: cssClass(c) }, b);
      headButtons[c.key] = cell;
      header.append(cell);
    }
    for (const row of pool) row.remove();
    pool.length = 0;
  }
  // Rows are absolutely placed inside .vrows (its height is that of every matching row); the
  // header row group is sticky at the top of the same scroll box.
  const rowsBox = el("div", { class: "vrows", role: "rowgroup" });
  const empty = el("p", { class: "vempty", hidden: true });
  const scroller = el(
    "div",
    { class: "vscroll", id: "fleet-rows" },
    el("div", { role: "rowgroup", class: "vheadgroup" }, header),
    rowsBox,
    empty,
  );
  const table = el(
    "div",
    { class: "vtable", role: "table", "aria-label": "Fleet overview", "aria-rowcount": "0" },
    scroller,
  );
  // every vehicle of the table (stored ones too) for the map, by its primary estimator
  const fleetMap = fleetMapPanel({
    vehicles: () => {
      const d = state.data;
      if (!d) return [];
      return d.ids.map((id, i) => ({ id, estimator: d.estimator[i], live: d.status[i] === "live", stampNs: d.stamp_ns[i] }));
    },
    anchor: (id) => state.anchors.get(id) || null,
    specs: () => state.specs,
  });
  root.append(
    el("div", { class: "toolbar" }, el("h1", { text: "Fleet" }), filter, summary),
    table,
    fleetMap.root,
  );

  const pool = [];
  // c-<key> class of a column's cells ("c-slip-left" for slip channel "left")
  function cssClass(c) {
    return `c-${c.slip ? `slip-${c.slip}` : c.key}${c.numeric ? " num" : ""}`;
  }
  function makeRow() {
    const link = el("a", {});
    const cells = {};
    for (const c of columns) {
      if (c.key === "id") cells.id = el("div", { role: "cell", class: "c-id" }, link);
      else if (c.key === "status") cells.status = el("div", { role: "cell", class: "c-status" }, el("span", { class: "pill" }));
      else if (c.slip) cells[c.key] = el("div", { role: "cell", class: `${cssClass(c)} slip` }, el("span", { class: "dot", "aria-hidden": "true" }), el("span"));
      else cells[c.key] = el("div", { role: "cell", class: cssClass(c) });
    }
    const row = el("div", { class: "vrow", role: "row" }, ...Object.values(cells));
    row._cells = cells;
    row._link = link;
    rowsBox.append(row);
    return row;
  }

  function sortValue(d, i, c) {
    if (c.key === "id") return d.ids[i];
    if (c.key === "status") return STATUS_ORDER[d.status[i]] ?? 9;
    if (c.key === "quality") return QUALITY_ORDER[d.quality[i]] ?? 9;
    const v = cellValue(d, i, c);
    if (v === null || v === undefined) return null;
    return c.slip ? Math.abs(v) : v;
  }

  function resort() {
    const d = state.data;
    if (!d) return;
    const f = state.filter.toLowerCase();
    let idx = d.ids.map((_, i) => i);
    if (f) idx = idx.filter((i) => d.ids[i].toLowerCase().includes(f));
    setColumns(Object.keys(d.slip_pct));
    const key = state.sortKey;
    const dir = state.sortDir;
    const col = columns.find((c) => c.key === key) || columns[0];
    const vals = idx.map((i) => sortValue(d, i, col));
    const pos = idx.map((_, k) => k);
    pos.sort((a, b) => {
      const va = vals[a];
      const vb = vals[b];
      if (va === vb) return d.ids[idx[a]] < d.ids[idx[b]] ? -1 : 1;
      if (va === null) return 1; // missing values last either way
      if (vb === null) return -1;
      return va < vb ? -dir : dir;
    });
    state.order = pos.map((k) => idx[k]);
    for (const c of columns) {
      headButtons[c.key].setAttribute(
        "aria-sort",
        c.key === key ? (dir > 0 ? "ascending" : "descending") : "none",
      );
    }
    table.setAttribute("aria-rowcount", String(state.order.length + 1));
    rowsBox.style.height = `${state.order.length * ROW_H}px`;
    showSummary();
    render();
  }

  // "12 vehicles — 11 live, 1 stale, 0 offline" (", 3 stored, not live" when there are such);
  // with a filter, the counts are of the matching vehicles: "3 of 12 vehicles shown — …", or
  // that none matches.
  function showSummary() {
    const d = state.data;
    const total = d.ids.length;
    const counts = { live: 0, stale: 0, offline: 0, stored: 0 };
    for (const i of state.order) counts[d.status[i]] = (counts[d.status[i]] || 0) + 1;
    const parked = counts.stored ? `, ${counts.stored} stored, not live` : "";
    const states = `${counts.live} live, ${counts.stale} stale, ${counts.offline} offline${parked}`;
    const noun = total === 1 ? "vehicle" : "vehicles";
    if (!state.filter) {
      summary.textContent = `${total} ${noun} — ${states}`;
      empty.hidden = total > 0;
      empty.textContent = "No vehicle has sent data yet.";
    } else if (state.order.length) {
      summary.textContent = `${state.order.length} of ${total} ${noun} shown — ${states}`;
      empty.hidden = true;
    } else {
      summary.textContent = `No vehicle matches “${state.filter}” (${total} ${noun} in all)`;
      empty.hidden = false;
      empty.textContent = `No vehicle id contains “${state.filter}”.`;
    }
  }

  function render() {
    const d = state.data;
    if (!d) return;
    const top = Math.max(0, scroller.scrollTop - rowsBox.offsetTop);
    const first = Math.max(0, Math.floor(top / ROW_H) - 5);
    const count = Math.max(0, Math.min(state.order.length - first, Math.ceil(scroller.clientHeight / ROW_H) + 10));
    while (pool.length < count) pool.push(makeRow());
    for (let k = 0; k < pool.length; k++) {
      const row = pool[k];
      if (k >= count) {
        row.hidden = true; // app.css: [hidden] wins over .vrow's display: grid
        continue;
      }
      row.hidden = false;
      const n = first + k;
      const i = state.order[n];
      row.style.transform = `translateY(${n * ROW_H}px)`;
      row.setAttribute("aria-rowindex", String(n + 2));
      const c = row._cells;
      const id = d.ids[i];
      if (row._link.textContent !== id) {
        row._link.textContent = id;
        row._link.href = vehicleHref(id);
      }
      const st = d.status[i];
      const live = st === "live";
      const age = fmt(d.age_s[i], 1);
      row.className = live ? "vrow" : `vrow row-old row-${st}`;
      row.title = live ? "" : oldTitle(st, age, d.stamp_ns[i]);
      const pill = c.status.firstChild;
      pill.textContent = STATUS_TEXT[st] || st;
      pill.className = `pill st-${st}`;
      c.speed_mps.textContent = fmtSpeed(d.speed_mps[i], state.standstill.get(id));
      const spec = state.specs.get(d.estimator[i]);
      for (const col of columns) {
        if (!col.slip) continue;
        const v = cellValue(d, i, col);
        const cell = c[col.key];
        let cls = "old";
        if (live) {
          const ch = spec && spec.slips.find((s) => s.key === col.slip);
          const edges = state.bandEdges.get(id) || (ch ? ch.band_edges_pct : [5, 15]);
          const b = slipBand(v, edges); // lowest band 0, top band edges.length, none -1
          cls = b <= 0 ? b : b === edges.length ? 2 : 1; // styled low / moderate / high
        }
        cell.className = `${cssClass(col)} slip band-${cls}`;
        cell.firstChild.style.background = live ? slipCss(v) : "";
        cell.lastChild.textContent = fmt(v, 1);
      }
      const q = d.quality[i];
      c.quality.textContent = q;
      c.quality.className = live ? `c-quality quality-${q}` : "c-quality";
      c.quality.title = spec ? `${spec.title}` : "";
      c.age_s.textContent = age;
    }
  }

  // The tooltip of a row that is not live.
  function oldTitle(st, age, stampNs) {
    if (st !== "stored") return `${st}: last data ${age} s ago; the values shown are not live`;
    const last =
      stampNs == null ? "no estimate stored" : `last stored estimate ${fmtTimeNs(stampNs, false)} (${timeTitle(stampNs)})`;
    return `not live: nothing received since the server started; ${last}`;
  }

  scroller.addEventListener("scroll", () => requestAnimationFrame(render), { passive: true });
  filter.addEventListener("input", () => {
    state.filter = filter.value;
    resort();
  });
  const onResize = () => render();
  window.addEventListener("resize", onResize);

  const sock = liveSocket("/api/v1/live/fleet", { interval_ms: 500 }, {
    onMessage(msg) {
      if (msg.type !== "fleet") return;
      const t0 = performance.now();
      const news = msg.ids.some((id) => !state.stored.has(id));
      const first = state.msg === null;
      state.msg = msg;
      if (first) fetchLatest();
      update();
      if (news && performance.now() - storedAtMs > 5000) loadStored(); // registered since
      const ms = window.slipfleetStats.fleetUpdateMs;
      ms.push(performance.now() - t0);
      if (ms.length > 1000) ms.splice(0, ms.length - 1000);
    },
    onState(s) {
      if (s !== "open") summary.textContent = `Connection ${s}; retrying…`;
    },
  });
  return () => {
    stopped = true;
    fleetMap.stop();
    sock.close();
    clearInterval(bandTimer);
    window.removeEventListener("resize", onResize);
  };
}
