// Times as the reader chose: in the browser's own time zone (the default) or in UTC, picked in
// the header and kept in localStorage ("slipfleet.time_zone"). Every time shown says its zone
// ("2026-11-28 04:09:03 CET"); where one is shown, the other reading is on hover (title).
// Times in inputs (history) are read in the chosen zone too.

const KEY = "slipfleet.time_zone";

// "local" or "utc"
export function timeMode() {
  try {
    return localStorage.getItem(KEY) === "utc" ? "utc" : "local";
  } catch (_) {
    return "local"; // storage refused (private mode): the default
  }
}

export function setTimeMode(mode) {
  try {
    localStorage.setItem(KEY, mode === "utc" ? "utc" : "local");
  } catch (_) {
    /* not kept across reloads */
  }
}

// Short name of the browser's zone at ms since the epoch: "CET", "CEST", "GMT+5:30", "UTC".
export function localZoneName(ms = Date.now()) {
  const parts = new Intl.DateTimeFormat("en-GB", { timeZoneName: "short" }).formatToParts(new Date(ms));
  const zone = parts.find((p) => p.type === "timeZoneName");
  return zone ? zone.value : "local time";
}

// The chosen zone's short name at ms ("UTC" in UTC mode).
export function zoneName(ms = Date.now()) {
  return timeMode() === "utc" ? "UTC" : localZoneName(ms);
}

const pad = (n, w = 2) => String(n).padStart(w, "0");

// [year, month (1-12), day, hour, minute, second, millisecond] of ms in the zone ("local"/"utc")
export function clockFields(ms, mode = timeMode()) {
  const d = new Date(ms);
  if (mode === "utc") {
    return [d.getUTCFullYear(), d.getUTCMonth() + 1, d.getUTCDate(), d.getUTCHours(), d.getUTCMinutes(), d.getUTCSeconds(), d.getUTCMilliseconds()];
  }
  return [d.getFullYear(), d.getMonth() + 1, d.getDate(), d.getHours(), d.getMinutes(), d.getSeconds(), d.getMilliseconds()];
}

// "2026-11-28 04:09:03" (".250" with withMs) in the zone, without its name.
export function fmtClock(ms, withMs = false, mode = timeMode()) {
  const [y, mo, d, h, mi, s, milli] = clockFields(ms, mode);
  const text = `${y}-${pad(mo)}-${pad(d)} ${pad(h)}:${pad(mi)}:${pad(s)}`;
  return withMs ? `${text}.${pad(milli, 3)}` : text;
}

// The other reading of ms, for a title: UTC when local times are shown, local when UTC is.
export function otherReading(ms, withMs = true) {
  const other = timeMode() === "utc" ? "local" : "utc";
  const name = other === "utc" ? "UTC" : localZoneName(ms);
  return `${fmtClock(ms, withMs, other)} ${name}`;
}

// ms since the epoch of y-mo-d h:mi:s in the chosen zone, or null for no such time (2026-02-30,
// 24:00, a local time skipped by a daylight-saving change).
export function clockToMs(y, mo, d, h, mi, s, mode = timeMode()) {
  const ms = mode === "utc" ? Date.UTC(y, mo - 1, d, h, mi, s) : new Date(y, mo - 1, d, h, mi, s).getTime();
  const back = clockFields(ms, mode);
  const same = back[0] === y && back[1] === mo && back[2] === d && back[3] === h && back[4] === mi && back[5] === s;
  return same ? ms : null;
}
