// WGS-84 for the maps: a vehicle's ENU metres to latitude/longitude through its anchor, the Web
// Mercator projection of XYZ tiles, and latitude/longitude ticks.
//
// ENU → geodetic uses the ellipsoid's radii of curvature at the anchor (meridian M, prime
// vertical N): lat = lat0 + north / (M + h), lon = lon0 + east / ((N + h)·cos lat0). Its error
// grows as d²/R: ≈ 0.2 m at 1 km from the anchor, well under a pixel of a field-scale map.

const A_M = 6378137.0; // WGS-84 semi-major axis
const E2 = 6.69437999014e-3; // first eccentricity squared
const DEG = Math.PI / 180;
export const TILE_PX = 256;

// anchor {lat_deg, lon_deg, height_m} -> (east_m, north_m) => [lat_deg, lon_deg] (null for null)
export function enuToLatLon(anchor) {
  const phi = anchor.lat_deg * DEG;
  const w = Math.sqrt(1 - E2 * Math.sin(phi) ** 2);
  const h = anchor.height_m || 0;
  const mPerRadLat = (A_M * (1 - E2)) / w ** 3 + h;
  const mPerRadLon = (A_M / w + h) * Math.cos(phi);
  return (east, north) =>
    east == null || north == null ? null : [anchor.lat_deg + north / mPerRadLat / DEG, anchor.lon_deg + east / mPerRadLon / DEG];
}

// The inverse: anchor -> (lat_deg, lon_deg) => [east_m, north_m].
export function latLonToEnu(anchor) {
  const toLL = enuToLatLon(anchor);
  const [lat1, lon1] = toLL(1, 1); // degrees per metre, both axes
  const dLat = lat1 - anchor.lat_deg, dLon = lon1 - anchor.lon_deg;
  return (latDeg, lonDeg) => [(lonDeg - anchor.lon_deg) / dLon, (latDeg - anchor.lat_deg) / dLat];
}

// Web Mercator at zoom 0, in tile pixels (the world is TILE_PX wide): [x, y], y down.
export function mercator(latDeg, lonDeg) {
  const lat = Math.max(-85.05112878, Math.min(85.05112878, latDeg)) * DEG;
  return [((lonDeg + 180) / 360) * TILE_PX, ((1 - Math.log(Math.tan(Math.PI / 4 + lat / 2)) / Math.PI) / 2) * TILE_PX];
}

// The inverse of mercator: [lat_deg, lon_deg].
export function unmercator(x, y) {
  const lon = (x / TILE_PX) * 360 - 180;
  const lat = Math.atan(Math.sinh(Math.PI * (1 - (2 * y) / TILE_PX))) / DEG;
  return [lat, lon];
}

// The largest round step of degrees (1, 2 or 5 × 10^k) that cuts `spanDeg` into at least
// `count` parts (so at least `count` ticks, at most 2.5 × count + 1), and the decimals its labels
// need.
export function degreeStep(spanDeg, count = 2) {
  const raw = spanDeg / count;
  const p = 10 ** Math.floor(Math.log10(raw));
  const step = [5, 2, 1].map((m) => m * p).find((s) => s <= raw) || p;
  return { step, decimals: Math.max(0, -Math.floor(Math.log10(step) + 1e-9)) };
}

// "52.1234° N", "13.40° E"; axis "lat" or "lon"
export function fmtDegrees(v, decimals, axis) {
  const hemi = axis === "lat" ? (v < 0 ? "S" : "N") : v < 0 ? "W" : "E";
  return `${Math.abs(v).toFixed(decimals)}° ${hemi}`;
}

// The tile URL of a template ("https://host/{z}/{x}/{y}.png"); x wraps around the world.
export function tileUrl(template, z, x, y) {
  const n = 2 ** z;
  return template.replace("{z}", String(z)).replace("{x}", String(((x % n) + n) % n)).replace("{y}", String(y));
}
