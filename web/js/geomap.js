// A WGS-84 map on a canvas: tracks coloured by |slip| (colors.js), a marker per vehicle at its
// last position, on latitude/longitude axes, over XYZ basemap tiles when a tile URL is
// configured (GET /api/v1/dashboard; none by default, and then nothing is fetched). Points are
// [lat_deg, lon_deg, slip_pct | null]; the view is Web Mercator (the tiles' projection), fitted
// to every point with equal scale on both axes.

import { drawSlipLegend, slipCss } from "./colors.js";
import { TILE_PX, degreeStep, fmtDegrees, mercator, unmercator } from "./geo.js";
import { LATLON_NAMES, TileCache, drawAttribution, drawGrid, paper } from "./slipmap.js";

const MIN_SPAN_M = 150; // the view shows at least this much, so one parked vehicle is not a dot
const MAX_TILE_ZOOM = 19;
const MARKER_PX = 8;
const PAD = { l: 88, r: 16, t: 12, b: 72 };

export class GeoMap {
  constructor(canvas, { onPick = null, label = "Fleet map" } = {}) {
    this.canvas = canvas;
    canvas._geomap = this; // lets tests and tools inspect the map
    this.label = label;
    this.vehicles = []; // [{id, points, live}]
    this.tiles = new TileCache(() => requestAnimationFrame(() => this.draw()));
    this.markers = []; // [{id, x, y}] in CSS px, after draw()
    this.tilesDrawn = 0;
    this.ticks = { lat: [], lon: [] }; // degrees of the labelled lines, after draw()
    this.onPick = onPick;
    canvas.addEventListener("click", (ev) => {
      const r = canvas.getBoundingClientRect();
      const id = this.pick(ev.clientX - r.left, ev.clientY - r.top);
      if (id !== null && this.onPick) this.onPick(id);
    });
    canvas.addEventListener("mousemove", (ev) => {
      const r = canvas.getBoundingClientRect();
      canvas.style.cursor = this.pick(ev.clientX - r.left, ev.clientY - r.top) === null ? "" : "pointer";
    });
  }

  setVehicles(vehicles) {
    this.vehicles = vehicles;
  }

  setTiles(template) {
    this.tiles.setTemplate(template);
  }

  // The vehicle whose marker is nearest to (x, y) CSS px, within 2 marker radii; else null.
  pick(x, y) {
    let best = null;
    let bestD = (2 * MARKER_PX) ** 2;
    for (const m of this.markers) {
      const d = (m.x - x) ** 2 + (m.y - y) ** 2;
      if (d <= bestD) [best, bestD] = [m.id, d];
    }
    return best;
  }

  // Mercator bounds of every point, widened to MIN_SPAN_M; null without points.
  bounds() {
    let x0 = Infinity, x1 = -Infinity, y0 = Infinity, y1 = -Infinity, lat = 0;
    for (const v of this.vehicles) {
      for (const p of v.points) {
        const [x, y] = mercator(p[0], p[1]);
        if (x < x0) x0 = x; if (x > x1) x1 = x; if (y < y0) y0 = y; if (y > y1) y1 = y;
        lat = p[0];
      }
    }
    if (!Number.isFinite(x0)) return null;
    // metres per zoom-0 pixel at this latitude
    const mPerPx = (40075016.686 * Math.cos((lat * Math.PI) / 180)) / TILE_PX;
    const minSpan = MIN_SPAN_M / mPerPx;
    const cx = (x0 + x1) / 2, cy = (y0 + y1) / 2;
    const hw = Math.max(x1 - x0, minSpan) / 2, hh = Math.max(y1 - y0, minSpan) / 2;
    return { x0: cx - hw, x1: cx + hw, y0: cy - hh, y1: cy + hh };
  }

  draw() {
    const { ctx, cssW, cssH } = paper(this.canvas);
    const W = cssW - PAD.l - PAD.r;
    const H = cssH - PAD.t - PAD.b;
    drawSlipLegend(ctx, PAD.l, cssH - 40, Math.min(300, W - 110), 14);
    this.markers = [];
    const b = this.bounds();
    if (!b || W <= 0 || H <= 0) {
      ctx.fillStyle = "#555";
      ctx.font = "14px system-ui, sans-serif";
      ctx.textBaseline = "top";
      ctx.fillText("No vehicle position yet", PAD.l + 10, PAD.t + 20);
      return;
    }
    const sc = Math.min(W / (b.x1 - b.x0), H / (b.y1 - b.y0)) / 1.1; // screen px per zoom-0 px
    const cx = (b.x0 + b.x1) / 2, cy = (b.y0 + b.y1) / 2;
    const view = {
      sc,
      px: (x) => PAD.l + W / 2 + (x - cx) * sc,
      py: (y) => PAD.t + H / 2 + (y - cy) * sc,
      mx: (px) => cx + (px - PAD.l - W / 2) / sc,
      my: (py) => cy + (py - PAD.t - H / 2) / sc,
    };
    ctx.save();
    ctx.beginPath();
    ctx.rect(PAD.l, PAD.t, W, H);
    ctx.clip();
    this.tilesDrawn = this.tiles.template ? this.drawTiles(ctx, view, W, H) : 0;
    ctx.restore();
    this.drawAxes(ctx, view, W, H);
    ctx.save();
    ctx.beginPath();
    ctx.rect(PAD.l, PAD.t, W, H);
    ctx.clip();
    this.drawTracks(ctx, view);
    this.drawMarkers(ctx, view);
    ctx.restore();
    drawAttribution(ctx, this.tiles.template, cssW - PAD.r, cssH - 4);
  }

  // The tiles covering the view at the zoom nearest the view's scale (each loads once and
  // redraws the map when it arrives). Returns how many were drawn.
  drawTiles(ctx, view, W, H) {
    const z = Math.max(0, Math.min(MAX_TILE_ZOOM, Math.round(Math.log2(view.sc))));
    const n = 2 ** z;
    const size = (TILE_PX / n) * view.sc; // one tile on screen, CSS px
    const tx0 = Math.floor((view.mx(PAD.l) / TILE_PX) * n), tx1 = Math.floor((view.mx(PAD.l + W) / TILE_PX) * n);
    const ty0 = Math.max(0, Math.floor((view.my(PAD.t) / TILE_PX) * n));
    const ty1 = Math.min(n - 1, Math.floor((view.my(PAD.t + H) / TILE_PX) * n));
    let drawn = 0;
    for (let tx = tx0; tx <= tx1; tx++) {
      for (let ty = ty0; ty <= ty1; ty++) {
        const img = this.tiles.get(z, tx, ty);
        if (!img) continue;
        ctx.drawImage(img, view.px((tx * TILE_PX) / n), view.py((ty * TILE_PX) / n), size + 0.5, size + 0.5);
        drawn++;
      }
    }
    return drawn;
  }

  // Latitude and longitude lines at round degrees, labelled on the left and bottom.
  drawAxes(ctx, view, W, H) {
    const [latTop, lonLeft] = unmercator(view.mx(PAD.l), view.my(PAD.t));
    const [latBottom, lonRight] = unmercator(view.mx(PAD.l + W), view.my(PAD.t + H));
    const lon = degreeStep(lonRight - lonLeft, Math.max(2, Math.floor(W / 250)));
    const lat = degreeStep(latTop - latBottom, Math.max(2, Math.floor(H / 150)));
    this.ticks = { lat: [], lon: [] };
    const xs = [], ys = [];
    for (let v = Math.ceil(lonLeft / lon.step) * lon.step; v <= lonRight; v += lon.step) {
      this.ticks.lon.push(v);
      xs.push([view.px(mercator(latTop, v)[0]), fmtDegrees(v, lon.decimals, "lon")]);
    }
    for (let v = Math.ceil(latBottom / lat.step) * lat.step; v <= latTop; v += lat.step) {
      this.ticks.lat.push(v);
      ys.push([view.py(mercator(v, lonLeft)[1]), fmtDegrees(v, lat.decimals, "lat")]);
    }
    drawGrid(ctx, { l: PAD.l, t: PAD.t, W, H }, xs, ys, LATLON_NAMES, Boolean(this.tiles.template));
  }

  drawTracks(ctx, view) {
    ctx.lineCap = "round";
    ctx.lineWidth = 3;
    for (const v of this.vehicles) {
      const pts = v.points.map((p) => mercator(p[0], p[1]));
      ctx.globalAlpha = v.live ? 1 : 0.45;
      for (let i = 1; i < pts.length; i++) {
        ctx.strokeStyle = slipCss(v.points[i][2]);
        ctx.beginPath();
        ctx.moveTo(view.px(pts[i - 1][0]), view.py(pts[i - 1][1]));
        ctx.lineTo(view.px(pts[i][0]), view.py(pts[i][1]));
        ctx.stroke();
      }
    }
    ctx.globalAlpha = 1;
  }

  // A marker at each vehicle's last point (filled with its slip colour when live, hollow grey
  // when not), its id beside it.
  drawMarkers(ctx, view) {
    ctx.font = "bold 12px system-ui, sans-serif";
    ctx.textAlign = "left";
    ctx.textBaseline = "middle";
    for (const v of this.vehicles) {
      const last = v.points[v.points.length - 1];
      if (!last) continue;
      const [mx, my] = mercator(last[0], last[1]);
      const x = view.px(mx), y = view.py(my);
      ctx.beginPath();
      ctx.arc(x, y, MARKER_PX, 0, 2 * Math.PI);
      ctx.fillStyle = v.live ? slipCss(last[2]) : "#ffffff";
      ctx.fill();
      ctx.lineWidth = 2;
      ctx.strokeStyle = v.live ? "#000" : "#777";
      ctx.stroke();
      ctx.lineWidth = 3;
      ctx.strokeStyle = "rgba(255,255,255,0.85)";
      ctx.strokeText(v.id, x + MARKER_PX + 3, y);
      ctx.fillStyle = "#111";
      ctx.fillText(v.id, x + MARKER_PX + 3, y);
      this.markers.push({ id: v.id, x, y });
    }
  }
}
