// Enumerated outputs (a spec's state channels, e.g. a crawler's motion state) drawn as a band of
// coloured stretches under an estimator's charts, on the charts' time axis. Colours follow the
// channel's state order (Okabe–Ito, colour-blind safe); a value the spec does not list is drawn
// as unknown. No view names a state: it reads the spec's channel.

import { flagMask } from "./specs.js";

export const STATE_PALETTE = ["#8a8a8a", "#0072B2", "#56B4E9", "#E69F00", "#D55E00", "#CC79A7", "#111111", "#009E73", "#F0E442"];
export const STATE_UNKNOWN = "#e2e2e2";
const BAND_PX = 22;

// Colour of a state value of a channel (unknown values and nulls: STATE_UNKNOWN).
export function stateColor(channel, value) {
  const i = channel.states.findIndex((s) => s.value === value);
  return i < 0 ? STATE_UNKNOWN : STATE_PALETTE[i % STATE_PALETTE.length];
}

// The state {value, name, label} of a value, or null.
export function stateOf(channel, value) {
  return channel.states.find((s) => s.value === value) || null;
}

// A step between rows longer than this (s) is a gap in the data: no state is drawn across it.
export const STATE_GAP_S = 1.0;

// [[t0, t1, value, uncertain], ...] (seconds) of the runs of equal state (and equal
// uncertainty, from the channel's uncertain_flag); a run ends at the next row's time, or at its
// last row's before a gap (STATE_GAP_S) and at the end. cols: {stamp_ns: [...], <field>: [...],
// flags: [...]}.
export function stateSpans(spec, channel, cols) {
  const vals = cols[channel.field] || [];
  const flags = cols.flags || [];
  const mask = channel.uncertain_flag ? flagMask(spec, channel.uncertain_flag) : 0;
  const n = Math.min(vals.length, cols.stamp_ns.length);
  const out = [];
  for (let i = 0; i < n; i++) {
    const v = vals[i] == null ? null : Math.round(vals[i]);
    const unsure = Boolean(mask && (flags[i] ?? 0) & mask);
    const t = cols.stamp_ns[i] / 1e9;
    const last = out[out.length - 1];
    const gap = !last || t - last[1] > STATE_GAP_S;
    if (!gap && last[2] === v && last[3] === unsure) last[1] = t;
    else {
      if (!gap) last[1] = t;
      out.push([t, t, v, unsure]);
    }
  }
  return out;
}

// A band under a chart: el is its box (a canvas inside, a legend below). draw(spans, chart)
// paints the spans on the chart's x axis (the uPlot chart whose plot area it lines up with).
export class StateBand {
  constructor(spec, channel, box) {
    this.spec = spec;
    this.channel = channel;
    this.canvas = document.createElement("canvas");
    this.canvas.className = "state-band-canvas";
    this.canvas.setAttribute("role", "img");
    this.canvas.setAttribute("aria-label", `${channel.label} over time`);
    this.canvas.style.height = `${BAND_PX}px`;
    box._band = this; // lets tests and tools inspect the band
    box.append(this.canvas, this.legend());
    this.spans = [];
  }

  legend() {
    const ul = document.createElement("ul");
    ul.className = "state-legend";
    for (const s of this.channel.states) {
      const li = document.createElement("li");
      li.dataset.state = s.name;
      const sw = document.createElement("span");
      sw.className = "swatch";
      sw.style.background = stateColor(this.channel, s.value);
      li.append(sw, ` ${s.label}`);
      ul.append(li);
    }
    if (this.channel.uncertain_flag) {
      const li = document.createElement("li");
      li.dataset.state = "uncertain";
      const sw = document.createElement("span");
      sw.className = "swatch swatch-uncertain";
      li.append(sw, " uncertain");
      ul.append(li);
    }
    return ul;
  }

  // Spans of cols, drawn on chart's x axis (its plot area's left and width).
  draw(cols, chart) {
    this.spans = stateSpans(this.spec, this.channel, cols);
    const c = this.canvas;
    const dpr = window.devicePixelRatio || 1;
    const w = c.clientWidth || 600;
    c.width = Math.round(w * dpr);
    c.height = Math.round(BAND_PX * dpr);
    const ctx = c.getContext("2d");
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.clearRect(0, 0, w, BAND_PX);
    if (!chart || !this.spans.length) return;
    const left = chart.bbox.left / dpr;
    const right = left + chart.bbox.width / dpr;
    const x = (t) => left + chart.valToPos(t, "x");
    for (const [t0, t1, v, unsure] of this.spans) {
      const p0 = Math.max(left, x(t0));
      const p1 = Math.min(right, x(t1));
      if (!(p1 >= p0)) continue;
      ctx.fillStyle = stateColor(this.channel, v);
      ctx.fillRect(p0, 2, Math.max(1, p1 - p0), BAND_PX - 4);
      if (unsure) {
        ctx.fillStyle = "rgba(255,255,255,0.55)";
        ctx.fillRect(p0, BAND_PX / 2, Math.max(1, p1 - p0), BAND_PX / 2 - 2);
      }
    }
  }
}
