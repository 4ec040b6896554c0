// Small helpers shared by the views.

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

// "2024-05-01 12:00:03.250 UTC" from integer nanoseconds (number precision is enough for display)
export function fmtTimeNs(ns, withMs = true) {
  if (ns === null || ns === undefined) return "–";
  const d = new Date(ns / 1e6);
  const iso = d.toISOString().replace("T", " ");
  return (withMs ? iso.slice(0, 23) : iso.slice(0, 19)) + " UTC";
}

export function fmtDuration(s) {
  if (s === null || s === undefined) return "–";
  if (s < 60) return `${s.toFixed(1)} s`;
  if (s < 3600) return `${Math.floor(s / 60)} min ${Math.round(s % 60)} s`;
  return `${Math.floor(s / 3600)} h ${Math.round((s % 3600) / 60)} min`;
}

export function vehicleHref(id, sub) {
  return `#/vehicle/${encodeURIComponent(id)}${sub ? "/" + sub : ""}`;
}
