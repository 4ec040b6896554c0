// Small helpers shared by the views.

import { fmtClock, otherReading, zoneName } from "./clock.js";

export function el(tag, attrs = {}, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (v === undefined || v === null || v === false) continue;
    if (k === "class") e.className = v;
    else if (k === "text") e.textContent = v;
    else if (k.startsWith("on")) e.addEventListener(k.slice(2), v);
    else e.setAttribute(k, v === true ? "" : v);
  }
  for (const c of children) if (c !== null && c !== undefined) e.append(c);
  return e;
}

// v with `digits` decimals; "–" for no value. A value that rounds to zero prints without a minus
// sign ("0.00", not "-0.00" for -0.001).
export function fmt(v, digits) {
  if (v === null || v === undefined || Number.isNaN(v)) return "–";
  const s = v.toFixed(digits);
  return s.startsWith("-") && Number(s) === 0 ? s.slice(1) : s;
}

// A speed (m/s) with 2 decimals; below the vehicle's standstill speed (its
// SlipConfig.min_ground_speed_mps, where the product counts it as standing) "0.00", so a standing
// vehicle's estimate noise never reads as driving backwards ("-0.01").
export function fmtSpeed(v, standstillMps) {
  if (v !== null && v !== undefined && standstillMps != null && Math.abs(v) < standstillMps) return "0.00";
  return fmt(v, 2);
}

// "2024-05-01 14:00:03.250 CEST" from integer nanoseconds, in the zone the reader chose (the
// browser's, or UTC: js/clock.js); number precision is enough for display
export function fmtTimeNs(ns, withMs = true) {
  if (ns === null || ns === undefined) return "–";
  const ms = ns / 1e6;
  return `${fmtClock(ms, withMs)} ${zoneName(ms)}`;
}

// The same time in the other zone, for a title (hover): UTC when local times are shown.
export function timeTitle(ns) {
  return ns === null || ns === undefined ? "" : otherReading(ns / 1e6);
}

// A duration in seconds: "0.300 s", "4.25 s", "21.6 s", "14 min 2 s", "30 min", "1 h 30 min",
// "12 h" (whole seconds and minutes rounded once, so never "9 min 60 s"); "–" for no value.
export function fmtDuration(s) {
  if (s === null || s === undefined || Number.isNaN(s)) return "–";
  if (s < 60) return `${s >= 10 ? s.toFixed(1) : s >= 1 ? s.toFixed(2) : s.toFixed(3)} s`;
  if (s < 3600) {
    const t = Math.round(s);
    if (t >= 3600) return "1 h";
    return t % 60 ? `${Math.floor(t / 60)} min ${t % 60} s` : `${t / 60} min`;
  }
  const m = Math.round(s / 60);
  return m % 60 ? `${Math.floor(m / 60)} h ${m % 60} min` : `${m / 60} h`;
}

export function vehicleHref(id, sub) {
  return `#/vehicle/${encodeURIComponent(id)}${sub ? "/" + sub : ""}`;
}

// Index of the last of the ascending `xs` at or before x (0 when x precedes them all).
export function lastAtOrBefore(xs, x) {
  let lo = 0;
  let hi = xs.length - 1;
  while (lo < hi) {
    const mid = (lo + hi + 1) >> 1;
    if (xs[mid] <= x) lo = mid;
    else hi = mid - 1;
  }
  return lo;
}
