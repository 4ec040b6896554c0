// Estimator specs (GET /api/v1/estimators, fetched once): what every view reads to draw an
// estimator's rows — field labels and units, slip channels with their band edges, speed
// channels, position, charts, flags. No view names an estimator's fields; it asks its spec.

import { getJSON } from "./api.js";

let loading = null; // Promise<Map<name, spec>>

// Every spec by name; fetched on the first call, shared afterwards (a failed fetch is retried on
// the next call).
export function loadSpecs() {
  if (!loading) {
    loading = getJSON("/api/v1/estimators")
      .then((body) => new Map(body.data.map((s) => [s.name, s])))
      .catch((err) => {
        loading = null;
        throw err;
      });
  }
  return loading;
}

// The field {name, unit, label, ...} of a spec, or a bare one for a name it does not list.
export function fieldOf(spec, name) {
  return spec.fields.find((f) => f.name === name) || { name, unit: "", label: name };
}

// Bit mask of a named flag (0 when the spec has no such flag).
export function flagMask(spec, name) {
  const f = spec.flags.find((x) => x.name === name);
  return f ? 2 ** f.bit : 0;
}

// Mask of every degraded flag of the spec (rows computed without their main reference).
export function degradedMask(spec) {
  return spec.degraded_flags.reduce((m, name) => m | flagMask(spec, name), 0);
}

// The motion speed channel {key, label, field} or null.
export function motionChannel(spec) {
  return spec.speeds.find((v) => v.key === spec.motion) || null;
}

// Names of the flags set in `bits`, lowest bit first.
export function flagNames(spec, bits) {
  return [...spec.flags].sort((a, b) => a.bit - b.bit).filter((f) => bits & (2 ** f.bit)).map((f) => f.name);
}

// Per row: the largest |slip| over the spec's slip channels that hold a value (a channel with a
// valid flag counts only where `flags` has it), or null where none does. cols: {field: [...]}.
export function slipMetric(spec, cols) {
  const n = cols.stamp_ns.length;
  const out = new Array(n).fill(null);
  for (const ch of spec.slips) {
    const vals = cols[ch.field] || [];
    const mask = ch.valid_flag && cols.flags ? flagMask(spec, ch.valid_flag) : 0;
    for (let i = 0; i < n; i++) {
      const v = vals[i];
      if (v == null || (mask && !((cols.flags[i] ?? 0) & mask))) continue;
      out[i] = Math.max(out[i] ?? 0, Math.abs(v));
    }
  }
  return out;
}

// Per row: whether its position was dead-reckoned (the position channel's carried_flag).
export function carriedRows(spec, cols) {
  const mask = spec.position.carried_flag ? flagMask(spec, spec.position.carried_flag) : 0;
  return cols.stamp_ns.map((_, i) => Boolean(mask && cols.flags && (cols.flags[i] ?? 0) & mask));
}

// Per row: the position's radial 1-σ, sqrt(σe² + σn²) in metres (null where unknown).
export function positionSigma(p, cols) {
  if (!p.east_std_field || !p.north_std_field) return null;
  const se = cols[p.east_std_field] || [];
  const sn = cols[p.north_std_field] || [];
  return cols.stamp_ns.map((_, i) => (se[i] == null || sn[i] == null ? null : Math.hypot(se[i], sn[i])));
}
