// Slip map: the track in local metres (east right, north up, equal scale) on a canvas, coloured by
// |slip| with the fixed scale of colors.js, an optional heat grid of cells, a scale bar, axis
// labels and the colour legend. Stretches whose position was dead-reckoned carry white dashes,
// and the position's 1-σ (radial, sqrt(σe² + σn²)) is drawn as circles along the track
// (setCarried).
//
// The track's points are drawn as given: give it whole rows (full rate, or the series endpoint's
// `decimation=first`), never min/max-decimated rows, whose east and north may come from
// different estimates. The heat grid is drawn from cells computed elsewhere: the history page
// takes them from the REST slip map (`GET /api/v1/vehicles/{id}/slipmap`), so the page and a
// GIS export show the same cells and numbers.

import { drawSlipLegend, layerCss, slipCss } from "./colors.js";
import { TILE_PX, degreeStep, enuToLatLon, fmtDegrees, latLonToEnu, mercator, tileUrl, unmercator } from "./geo.js";
import { lastAtOrBefore } from "./util.js";

export const LATLON_NAMES = ["longitude (WGS 84)", "latitude (WGS 84)"];
const SIGMA_CIRCLES = 40; // circles of the position's 1-σ along a track, at most

// Grid lines and their labels in a plot box {l, t, W, H} (CSS px): xs / ys [[pixel, label]...],
// names [x axis, y axis]; on a basemap the lines are darker.
export function drawGrid(ctx, box, xs, ys, names, onBasemap) {
  ctx.strokeStyle = onBasemap ? "rgba(40,40,40,0.35)" : "#e6e6e6";
  ctx.lineWidth = 1;
  ctx.font = "11px system-ui, sans-serif";
  ctx.fillStyle = "#444";
  ctx.textAlign = "center";
  ctx.textBaseline = "top";
  for (const [x, label] of xs) {
    ctx.beginPath(); ctx.moveTo(x, box.t); ctx.lineTo(x, box.t + box.H); ctx.stroke();
    ctx.fillText(label, x, box.t + box.H + 3);
  }
  ctx.textAlign = "right";
  ctx.textBaseline = "middle";
  for (const [y, label] of ys) {
    ctx.beginPath(); ctx.moveTo(box.l, y); ctx.lineTo(box.l + box.W, y); ctx.stroke();
    ctx.fillText(label, box.l - 4, y);
  }
  ctx.strokeStyle = "#999";
  ctx.strokeRect(box.l + 0.5, box.t + 0.5, box.W, box.H);
  ctx.fillStyle = "#222";
  ctx.font = "12px system-ui, sans-serif";
  ctx.textAlign = "center";
  ctx.textBaseline = "top";
  ctx.fillText(names[0], box.l + box.W / 2, box.t + box.H + 17);
  ctx.save();
  ctx.translate(14, box.t + box.H / 2);
  ctx.rotate(-Math.PI / 2);
  ctx.fillText(names[1], 0, 0);
  ctx.restore();
}

// "basemap: <host>" at (right, bottom) when a tile template is in use.
export function drawAttribution(ctx, template, right, bottom) {
  if (!template) return;
  let host = "";
  try {
    host = new URL(template.replace(/[{}]/g, "")).host;
  } catch (_) {
    /* shown without a host */
  }
  ctx.fillStyle = "#333";
  ctx.font = "11px system-ui, sans-serif";
  ctx.textAlign = "right";
  ctx.textBaseline = "bottom";
  ctx.fillText(`basemap: ${host}`, right, bottom);
}

// Round-degree lines over the ENU box [e0, e1] × [n0, n1] of a vehicle's frame: x [[east_m,
// label]...], y [[north_m, label]...], and the degrees (lat, lon).
function degreeGrid(anchor, e0, e1, n0, n1, W, H) {
  const toLL = enuToLatLon(anchor);
  const toEnu = latLonToEnu(anchor);
  const [latS, lonW] = toLL(e0, n0);
  const [latN, lonE] = toLL(e1, n1);
  const lon = degreeStep(lonE - lonW, Math.max(2, Math.floor(W / 250)));
  const lat = degreeStep(latN - latS, Math.max(2, Math.floor(H / 150)));
  const out = { x: [], y: [], lat: [], lon: [] };
  for (let v = Math.ceil(lonW / lon.step) * lon.step; v <= lonE; v += lon.step) {
    out.lon.push(v);
    out.x.push([toEnu(anchor.lat_deg, v)[0], fmtDegrees(v, lon.decimals, "lon")]);
  }
  for (let v = Math.ceil(latS / lat.step) * lat.step; v <= latN; v += lat.step) {
    out.lat.push(v);
    out.y.push([toEnu(v, anchor.lon_deg)[1], fmtDegrees(v, lat.decimals, "lat")]);
  }
  return out;
}

// Basemap tiles, each loaded once; onLoad() is called when one arrives.
export class TileCache {
  constructor(onLoad) {
    this.template = null;
    this.images = new Map();
    this.onLoad = onLoad;
  }

  setTemplate(template) {
    this.template = template || null;
    this.images.clear();
  }

  // The loaded image of tile (z, x, y), or null while it loads (or failed).
  get(z, x, y) {
    const url = tileUrl(this.template, z, x, y);
    let img = this.images.get(url);
    if (!img) {
      img = new Image();
      img.onload = () => this.onLoad();
      img.src = url;
      this.images.set(url, img);
    }
    return img.complete && img.naturalWidth ? img : null;
  }
}

// The Web Mercator zoom whose tiles show at about their own size at `pxPerM` screen px per metre
// at latitude latDeg (0..19).
export function tileZoom(pxPerM, latDeg) {
  const mPerWorldPx = (40075016.686 * Math.cos((latDeg * Math.PI) / 180)) / TILE_PX;
  return Math.max(0, Math.min(19, Math.round(Math.log2(pxPerM * mPerWorldPx))));
}

// `text` cut to fit `maxW` pixels in the context's font, ending in "…" when cut.
export function fitText(ctx, text, maxW) {
  if (ctx.measureText(text).width <= maxW) return text;
  let lo = 0;
  let hi = text.length;
  while (lo < hi) {
    const mid = (lo + hi + 1) >> 1;
    if (ctx.measureText(text.slice(0, mid).trimEnd() + "…").width <= maxW) lo = mid;
    else hi = mid - 1;
  }
  return text.slice(0, lo).trimEnd() + "…";
}

// The canvas sized to its box at the screen's pixel ratio, cleared to white paper; its context
// draws in CSS px. Returns {ctx, cssW, cssH}.
export function paper(canvas) {
  const dpr = window.devicePixelRatio || 1;
  const cssW = canvas.clientWidth || 600;
  const cssH = canvas.clientHeight || 420;
  if (canvas.width !== Math.round(cssW * dpr) || canvas.height !== Math.round(cssH * dpr)) {
    canvas.width = Math.round(cssW * dpr);
    canvas.height = Math.round(cssH * dpr);
  }
  const ctx = canvas.getContext("2d");
  ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
  ctx.fillStyle = "#ffffff";
  ctx.fillRect(0, 0, cssW, cssH);
  return { ctx, cssW, cssH };
}

function niceStep(span) {
  const raw = span / 5;
  const p = 10 ** Math.floor(Math.log10(raw));
  for (const m of [1, 2, 5, 10]) if (raw <= m * p) return m * p;
  return 10 * p;
}

// A REST slip map with a layer (GET …/slipmap?layer=) as heat cells on `map`: each cell's layer
// mean coloured over the range of the cells shown (dark red low, green high; grey where no sample
// informs it). Returns the words that say so: "<n> cells, <k> informed samples; <label> lo … hi".
export function showLayerHeat(map, body) {
  const cells = body.cells.map((c) => ({ e0: c.east_m, n0: c.north_m, mean: c.layer.mean, samples: c.layer.samples }));
  const means = cells.map((c) => c.mean).filter((v) => v != null);
  const lo = Math.min(...means);
  const hi = Math.max(...means);
  map.setHeat(cells, body.cell_m, (v) => layerCss(v, lo, hi));
  const samples = cells.reduce((n, c) => n + c.samples, 0);
  const scale = means.length ? `${lo.toFixed(3)} (red) … ${hi.toFixed(3)} (green)` : "none informed";
  return `${cells.length} cells, ${samples} informed samples; ${body.layer.label} ${scale}`;
}

export class SlipMap {
  // titleEl: an element above the canvas that shows the title (it wraps on a narrow screen);
  // without one the title is drawn on the canvas, cut to its width
  constructor(canvas, { title = "Track coloured by |slip|", titleEl = null } = {}) {
    this.canvas = canvas;
    canvas._slipmap = this; // lets tests and tools inspect the map
    this.titleEl = titleEl;
    this.title = title;
    this.east = [];
    this.north = [];
    this.slip = [];
    this.heat = null;
    this.heatCell = 0;
    this.heatColor = slipCss;
    this.anchor = null; // {lat_deg, lon_deg, height_m} of the vehicle's frame: degree axes
    this.tiles = new TileCache(() => requestAnimationFrame(() => this.draw()));
    this.tilesDrawn = 0;
    this.ticks = { lat: [], lon: [] }; // degrees of the labelled lines (with an anchor)
    this.cursor = null; // index of the replay position
    this.upTo = null; // draw the track only up to this index (replay), null = all
    this.carried = null; // per point: dead-reckoned (dashed), or null
    this.sigma = null; // per point: radial 1-σ of the position in metres, or null
    this.carriedDrawn = 0; // dashed segments, after draw()
    this.sigmaDrawn = []; // [[east, north, radius_m], ...] circles, after draw()
  }

  // Per point: whether its position was dead-reckoned, and its radial 1-σ (m); null: none.
  setCarried(carried, sigmaM) {
    this.carried = carried;
    this.sigma = sigmaM;
  }

  // stampsS: each point's time (seconds), for cursorAt
  get title() {
    return this._title;
  }

  set title(text) {
    this._title = text;
    if (this.titleEl) this.titleEl.textContent = text;
  }

  setTrack(east, north, slip, stampsS = null) {
    this.east = east;
    this.north = north;
    this.slip = slip;
    this.stampsS = stampsS;
  }

  // The index of the last point at or before tS (the first point before them all), or null
  // without times or points.
  indexAt(tS) {
    const xs = this.stampsS;
    return !xs || !xs.length || tS == null ? null : lastAtOrBefore(xs, tS);
  }

  // The vehicle's anchor (latitude/longitude axes, and the basemap when configured), or null.
  setAnchor(anchor) {
    this.anchor = anchor || null;
  }

  setTiles(template) {
    this.tiles.setTemplate(template);
  }

  // The basemap tiles under the ENU box [e0, e1] × [n0, n1] (a tile's corners placed through
  // the anchor: at field scale Mercator and the local frame differ by far less than a pixel).
  drawTiles(ctx, px, py, sc, e0, e1, n0, n1) {
    const toLL = enuToLatLon(this.anchor);
    const toEnu = latLonToEnu(this.anchor);
    const z = tileZoom(sc, this.anchor.lat_deg);
    const n = 2 ** z;
    const tile = (ll) => mercator(ll[0], ll[1]).map((v) => Math.floor((v / TILE_PX) * n));
    const [tx0, ty0] = tile(toLL(e0, n1));
    const [tx1, ty1] = tile(toLL(e1, n0));
    let drawn = 0;
    for (let tx = tx0; tx <= tx1; tx++) {
      for (let ty = ty0; ty <= ty1; ty++) {
        const img = this.tiles.get(z, tx, ty);
        if (!img) continue;
        const [ea, na] = toEnu(...unmercator((tx * TILE_PX) / n, (ty * TILE_PX) / n));
        const [eb, nb] = toEnu(...unmercator(((tx + 1) * TILE_PX) / n, ((ty + 1) * TILE_PX) / n));
        ctx.drawImage(img, px(ea), py(na), px(eb) - px(ea) + 0.5, py(nb) - py(na) + 0.5);
        drawn++;
      }
    }
    return drawn;
  }

  // cells: [{e0, n0, mean}] (south-west corner in metres, the value coloured; null is grey);
  // colorOf(mean) gives a cell's colour (default: the slip scale)
  setHeat(cells, cellM, colorOf = slipCss) {
    this.heat = cells;
    this.heatCell = cellM;
    this.heatColor = colorOf;
  }

  draw() {
    const { ctx, cssW, cssH } = paper(this.canvas);
    const pad = { l: this.anchor ? 88 : 64, r: 16, t: this.titleEl ? 12 : 30, b: 90 }; // degrees are wider
    const W = cssW - pad.l - pad.r;
    const H = cssH - pad.t - pad.b;
    ctx.fillStyle = "#222";
    ctx.font = "bold 14px system-ui, sans-serif";
    ctx.textAlign = "left";
    ctx.textBaseline = "top";
    if (!this.titleEl) ctx.fillText(fitText(ctx, this.title, cssW - 24), 12, 8); // a phone's canvas is narrow

    // bounds over the track and the heat cells
    let e0 = Infinity, e1 = -Infinity, n0 = Infinity, n1 = -Infinity;
    for (let i = 0; i < this.east.length; i++) {
      const e = this.east[i], n = this.north[i];
      if (e == null || n == null) continue;
      if (e < e0) e0 = e; if (e > e1) e1 = e; if (n < n0) n0 = n; if (n > n1) n1 = n;
    }
    if (this.heat) {
      for (const h of this.heat) {
        e0 = Math.min(e0, h.e0); e1 = Math.max(e1, h.e0 + this.heatCell);
        n0 = Math.min(n0, h.n0); n1 = Math.max(n1, h.n0 + this.heatCell);
      }
    }
    drawSlipLegend(ctx, pad.l, cssH - 48, Math.min(300, W - 110), 14);
    if (!Number.isFinite(e0)) {
      ctx.fillStyle = "#555";
      ctx.font = "14px system-ui, sans-serif";
      ctx.fillText("No position data yet", pad.l + 10, pad.t + 20);
      this.drawn = 0;
      return;
    }
    const span = Math.max(e1 - e0, n1 - n0, 5) * 1.08;
    const sc = Math.min(W, H) / span; // px per metre, equal on both axes
    const ce = (e0 + e1) / 2, cn = (n0 + n1) / 2;
    const ox = pad.l + W / 2, oy = pad.t + H / 2;
    const px = (e) => ox + (e - ce) * sc;
    const py = (n) => oy - (n - cn) * sc;
    this.toPx = { px, py };

    // grid and axis labels: degrees through the vehicle's anchor, else metres of its frame
    const spanE = W / sc, spanN = H / sc;
    const e0v = ce - spanE / 2, e1v = ce + spanE / 2, n0v = cn - spanN / 2, n1v = cn + spanN / 2;
    const box = { l: pad.l, t: pad.t, W, H };
    if (this.anchor) {
      const g = degreeGrid(this.anchor, e0v, e1v, n0v, n1v, W, H);
      this.ticks = { lat: g.lat, lon: g.lon };
      ctx.save();
      ctx.beginPath();
      ctx.rect(pad.l, pad.t, W, H);
      ctx.clip();
      this.tilesDrawn = this.tiles.template ? this.drawTiles(ctx, px, py, sc, e0v, e1v, n0v, n1v) : 0;
      ctx.restore();
      drawGrid(ctx, box, g.x.map(([e, t]) => [px(e), t]), g.y.map(([n, t]) => [py(n), t]), LATLON_NAMES, Boolean(this.tiles.template));
    } else {
      const step = niceStep(Math.max(spanE, spanN));
      const lines = (a, b, at) => {
        const out = [];
        for (let v = Math.ceil(a / step) * step; v <= b; v += step) out.push([at(v), String(Math.round(v * 10) / 10)]);
        return out;
      };
      drawGrid(ctx, box, lines(e0v, e1v, px), lines(n0v, n1v, py), ["east (m)", "north (m)"], false);
    }

    ctx.save();
    ctx.beginPath();
    ctx.rect(pad.l, pad.t, W, H);
    ctx.clip();
    if (this.heat) {
      const s = this.heatCell * sc;
      for (const h of this.heat) {
        ctx.fillStyle = this.heatColor(h.mean);
        ctx.globalAlpha = 0.85;
        ctx.fillRect(px(h.e0), py(h.n0 + this.heatCell), s + 0.5, s + 0.5);
      }
      ctx.globalAlpha = 1;
    }
    // track: faint full path, then coloured segments (up to the replay position)
    const last = this.upTo == null ? this.east.length - 1 : Math.min(this.upTo, this.east.length - 1);
    ctx.lineCap = "round";
    ctx.lineJoin = "round";
    if (this.upTo != null || this.heat) {
      ctx.strokeStyle = "rgba(60,60,60,0.35)";
      ctx.lineWidth = 1.5;
      ctx.beginPath();
      let started = false;
      for (let i = 0; i < this.east.length; i++) {
        if (this.east[i] == null) { started = false; continue; }
        if (!started) { ctx.moveTo(px(this.east[i]), py(this.north[i])); started = true; }
        else ctx.lineTo(px(this.east[i]), py(this.north[i]));
      }
      ctx.stroke();
    }
    this.drawSigma(ctx, px, py, sc, last);
    ctx.lineWidth = this.heat ? 2 : 4;
    let drawn = 0;
    this.carriedDrawn = 0;
    for (let i = 1; i <= last; i++) {
      const ea = this.east[i - 1], na = this.north[i - 1], eb = this.east[i], nb = this.north[i];
      if (ea == null || na == null || eb == null || nb == null) continue;
      ctx.strokeStyle = slipCss(this.slip[i]);
      ctx.beginPath();
      ctx.moveTo(px(ea), py(na));
      ctx.lineTo(px(eb), py(nb));
      ctx.stroke();
      drawn++;
    }
    this.drawCarried(ctx, px, py, last);
    const mi = this.cursor != null ? this.cursor : last;
    if (mi >= 0 && this.east[mi] != null) {
      ctx.fillStyle = slipCss(this.slip[mi]);
      ctx.strokeStyle = "#000";
      ctx.lineWidth = 2;
      ctx.beginPath();
      ctx.arc(px(this.east[mi]), py(this.north[mi]), 7, 0, 2 * Math.PI);
      ctx.fill();
      ctx.stroke();
    }
    ctx.restore();
    // scale bar
    const barM = niceStep(spanE / 2);
    const bx = pad.l + W - barM * sc - 10, by = pad.t + H - 14;
    ctx.fillStyle = "rgba(255,255,255,0.85)";
    ctx.fillRect(bx - 6, by - 16, barM * sc + 12, 24);
    ctx.strokeStyle = "#222";
    ctx.lineWidth = 2;
    ctx.beginPath(); ctx.moveTo(bx, by); ctx.lineTo(bx + barM * sc, by); ctx.stroke();
    ctx.fillStyle = "#222";
    ctx.textAlign = "center";
    ctx.textBaseline = "bottom";
    ctx.font = "11px system-ui, sans-serif";
    ctx.fillText(`${barM} m`, bx + (barM * sc) / 2, by - 2);
    if (this.anchor) drawAttribution(ctx, this.tiles.template, cssW - pad.r, cssH - 4);
    if (this.carried || this.sigma) this.drawCarriedLegend(ctx, pad.l, cssH - 8);
    this.drawn = drawn;
  }

  // White dashes over the dead-reckoned runs of the track (one path per run, so the dashes run
  // on across its short segments).
  drawCarried(ctx, px, py, last) {
    this.carriedDrawn = 0;
    if (!this.carried) return;
    ctx.save();
    ctx.strokeStyle = "rgba(255,255,255,0.95)";
    ctx.lineWidth = 2;
    ctx.lineCap = "butt";
    ctx.setLineDash([6, 6]);
    let open = false;
    for (let i = 1; i <= last; i++) {
      const ea = this.east[i - 1], na = this.north[i - 1], eb = this.east[i], nb = this.north[i];
      const on = Boolean(this.carried[i]) && ea != null && na != null && eb != null && nb != null;
      if (on && !open) {
        ctx.beginPath();
        ctx.moveTo(px(ea), py(na));
        open = true;
      }
      if (on) {
        ctx.lineTo(px(eb), py(nb));
        this.carriedDrawn++;
      } else if (open) {
        ctx.stroke();
        open = false;
      }
    }
    if (open) ctx.stroke();
    ctx.restore();
  }

  // Circles of the position's 1-σ at up to SIGMA_CIRCLES points up to index `last` (evenly
  // spaced, always the last), faint blue.
  drawSigma(ctx, px, py, sc, last) {
    this.sigmaDrawn = [];
    if (!this.sigma || last < 0) return;
    const step = Math.max(1, Math.ceil((last + 1) / SIGMA_CIRCLES));
    ctx.fillStyle = "rgba(0,114,178,0.10)";
    ctx.strokeStyle = "rgba(0,114,178,0.55)";
    ctx.lineWidth = 1;
    for (let i = last; i >= 0; i -= step) {
      const e = this.east[i], n = this.north[i], r = this.sigma[i];
      if (e == null || n == null || r == null || !(r > 0)) continue;
      ctx.beginPath();
      ctx.arc(px(e), py(n), Math.max(1, r * sc), 0, 2 * Math.PI);
      ctx.fill();
      ctx.stroke();
      this.sigmaDrawn.push([e, n, r]);
    }
  }

  // "dashed: dead-reckoned · circles: position 1σ" at (x, y).
  drawCarriedLegend(ctx, x, y) {
    ctx.strokeStyle = "#555";
    ctx.lineWidth = 4;
    ctx.beginPath(); ctx.moveTo(x, y); ctx.lineTo(x + 30, y); ctx.stroke();
    ctx.strokeStyle = "#fff";
    ctx.lineWidth = 2;
    ctx.setLineDash([6, 6]);
    ctx.beginPath(); ctx.moveTo(x, y); ctx.lineTo(x + 30, y); ctx.stroke();
    ctx.setLineDash([]);
    ctx.fillStyle = "#222";
    ctx.font = "11px system-ui, sans-serif";
    ctx.textAlign = "left";
    ctx.textBaseline = "middle";
    ctx.fillText("dead-reckoned", x + 36, y);
    ctx.fillStyle = "rgba(0,114,178,0.10)";
    ctx.strokeStyle = "rgba(0,114,178,0.55)";
    ctx.lineWidth = 1;
    ctx.beginPath(); ctx.arc(x + 130, y, 6, 0, 2 * Math.PI); ctx.fill(); ctx.stroke();
    ctx.fillStyle = "#222";
    ctx.fillText("position 1σ", x + 140, y);
  }
}
