// The fleet page's map: every vehicle's last position and its recent track (the last
// TRACK_S seconds up to its newest estimate) coloured by |slip|, on WGS-84 axes or a basemap.
// A click on a vehicle opens its page.
//
// Positions come from each vehicle's primary estimator's spec: its position channel's
// east/north fields (metres in the vehicle's ENU frame) through the vehicle's anchor
// (GET /api/v1/vehicles); the slip is the largest |slip| of the spec's slip channels
// (specs.slipMetric). Tracks are whole stored rows (GET /vehicles/{id}/series,
// decimation=first), re-read vehicle after vehicle, live ones first, at most MAX_TRACKS.

import { getJSON, loadDashboardConfig } from "./api.js";
import { enuToLatLon } from "./geo.js";
import { GeoMap } from "./geomap.js";
import { slipMetric } from "./specs.js";
import { el, vehicleHref } from "./util.js";

const TRACK_S = 600;
const TRACK_POINTS = 200;
const MAX_TRACKS = 200;
const REFRESH_MS = 3000; // pause between two passes over the fleet

// One vehicle's recent track: [[lat, lon, slip]...] (rows without a position left out).
async function fetchTrack(v, spec, anchor) {
  const pos = spec.position;
  const endNs = BigInt(Math.round(v.stampNs / 1e6)) * 1000000n + 1000000000n;
  const body = await getJSON(`/api/v1/vehicles/${encodeURIComponent(v.id)}/series`, {
    estimator: spec.name,
    start: (endNs - BigInt(TRACK_S) * 1000000000n).toString(),
    end: endNs.toString(),
    fields: [pos.east_field, pos.north_field, ...spec.slips.map((s) => s.field), ...(spec.flags.length ? ["flags"] : [])].join(","),
    max_points: TRACK_POINTS,
    decimation: "first",
    format: "json",
  });
  const cols = body.columns;
  const toLatLon = enuToLatLon(anchor);
  const slip = slipMetric(spec, cols);
  const out = [];
  for (let i = 0; i < cols.stamp_ns.length; i++) {
    const ll = toLatLon(cols[pos.east_field][i], cols[pos.north_field][i]);
    if (ll) out.push([ll[0], ll[1], slip[i]]);
  }
  return out;
}

// source: {vehicles() -> [{id, estimator, live, stampNs}], anchor(id) -> anchor | null,
// specs() -> Map}. Returns {root, stop}.
export function fleetMapPanel(source) {
  const canvas = el("canvas", {
    class: "map fleet-map",
    id: "fleet-map",
    role: "img",
    "aria-label": "Fleet map: each vehicle's last position and recent track coloured by slip",
  });
  const note = el("p", { class: "summary", id: "fleet-map-note" });
  const root = el("section", { class: "fleet-map-box", "aria-labelledby": "fleet-map-title" },
    el("h2", { id: "fleet-map-title", text: "Fleet map: last positions, tracks of the last 10 min by |slip|" }),
    note,
    canvas,
  );
  const map = new GeoMap(canvas, { onPick: (id) => (location.hash = vehicleHref(id)) });
  const tracks = new Map(); // id -> {points, live}
  let stopped = false;
  let timer = null;

  function show() {
    const vs = source.vehicles();
    const ids = new Set(vs.map((v) => v.id));
    for (const id of [...tracks.keys()]) if (!ids.has(id)) tracks.delete(id);
    const shown = [...tracks.entries()].filter(([, t]) => t.points.length).map(([id, t]) => ({ id, ...t }));
    map.setVehicles(shown);
    map.draw();
    const unplaced = vs.length - shown.length;
    note.textContent = `${shown.length} of ${vs.length} vehicles placed` + (unplaced ? ` (${unplaced} without a position yet)` : "");
  }

  async function pass() {
    const specs = source.specs();
    const vs = source.vehicles().filter((v) => v.stampNs != null && source.anchor(v.id));
    vs.sort((a, b) => Number(b.live) - Number(a.live) || (a.id < b.id ? -1 : 1));
    for (const v of vs.slice(0, MAX_TRACKS)) {
      const spec = specs.get(v.estimator);
      if (stopped) return;
      if (!spec || !spec.position) continue;
      try {
        tracks.set(v.id, { points: await fetchTrack(v, spec, source.anchor(v.id)), live: v.live });
      } catch (_) {
        /* gone or refused: tried again on the next pass */
      }
    }
    if (!stopped) show();
  }
  async function loop() {
    await pass();
    if (!stopped) timer = setTimeout(loop, REFRESH_MS);
  }
  loadDashboardConfig().then((cfg) => {
    if (stopped) return;
    map.setTiles(cfg.map_tile_url);
    loop();
  });
  const onResize = () => map.draw();
  window.addEventListener("resize", onResize);
  return {
    root,
    stop() {
      stopped = true;
      clearTimeout(timer);
      window.removeEventListener("resize", onResize);
    },
  };
}
