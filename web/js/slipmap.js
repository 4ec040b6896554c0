// Slip map: the track in local metres (east right, north up, equal scale) on a canvas, coloured by
// |slip| with the fixed scale of colors.js, an optional heat grid of cells, a scale bar, axis
// labels and the colour legend.
//
// The track's points are drawn as given: give it whole rows (full rate, or the series endpoint's
// `decimation=first`), never min/max-decimated rows, whose east and north may come from
// different estimates. The heat grid is drawn from cells computed elsewhere: the history page
// takes them from the REST slip map (`GET /api/v1/vehicles/{id}/slipmap`), so the page and a
// GIS export show the same cells and numbers.

import { drawSlipLegend, slipCss } from "./colors.js";
import { lastAtOrBefore } from "./util.js";

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
    this.cursor = null; // index of the replay position
    this.upTo = null; // draw the track only up to this index (replay), null = all
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

  // cells: [{e0, n0, mean}] (south-west corner in metres, the value coloured; null is grey)
  setHeat(cells, cellM) {
    this.heat = cells;
    this.heatCell = cellM;
  }

  draw() {
    const { ctx, cssW, cssH } = paper(this.canvas);
    const pad = { l: 64, r: 16, t: this.titleEl ? 12 : 30, b: 90 };
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

    // grid and axis labels
    const spanE = W / sc, spanN = H / sc;
    const step = niceStep(Math.max(spanE, spanN));
    ctx.strokeStyle = "#e6e6e6";
    ctx.lineWidth = 1;
    ctx.font = "11px system-ui, sans-serif";
    ctx.fillStyle = "#444";
    ctx.textAlign = "center";
    ctx.textBaseline = "top";
    for (let e = Math.ceil((ce - spanE / 2) / step) * step; e <= ce + spanE / 2; e += step) {
      const x = px(e);
      ctx.beginPath(); ctx.moveTo(x, pad.t); ctx.lineTo(x, pad.t + H); ctx.stroke();
      ctx.fillText(String(Math.round(e * 10) / 10), x, pad.t + H + 3);
    }
    ctx.textAlign = "right";
    ctx.textBaseline = "middle";
    for (let n = Math.ceil((cn - spanN / 2) / step) * step; n <= cn + spanN / 2; n += step) {
      const y = py(n);
      ctx.beginPath(); ctx.moveTo(pad.l, y); ctx.lineTo(pad.l + W, y); ctx.stroke();
      ctx.fillText(String(Math.round(n * 10) / 10), pad.l - 4, y);
    }
    ctx.strokeStyle = "#999";
    ctx.strokeRect(pad.l + 0.5, pad.t + 0.5, W, H);
    ctx.fillStyle = "#222";
    ctx.font = "12px system-ui, sans-serif";
    ctx.textAlign = "center";
    ctx.textBaseline = "top";
    ctx.fillText("east (m)", pad.l + W / 2, pad.t + H + 17);
    ctx.save();
    ctx.translate(16, pad.t + H / 2);
    ctx.rotate(-Math.PI / 2);
    ctx.fillText("north (m)", 0, 0);
    ctx.restore();

    ctx.save();
    ctx.beginPath();
    ctx.rect(pad.l, pad.t, W, H);
    ctx.clip();
    if (this.heat) {
      const s = this.heatCell * sc;
      for (const h of this.heat) {
        ctx.fillStyle = slipCss(h.mean);
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
    ctx.lineWidth = this.heat ? 2 : 4;
    let drawn = 0;
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
    this.drawn = drawn;
  }
}
