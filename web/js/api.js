// Every request of the dashboard goes through this module (base URL, credentials, errors).
//
// Access token: a server started with `slipfleet serve` answers 401 without a bearer token
// (create one with `slipfleet token create --name NAME --role viewer`). The token is kept in
// sessionStorage (gone when the tab closes), sent as `Authorization: Bearer …` on REST calls
// and as the WebSocket subprotocol pair ["slipfleet.bearer", token] (browsers cannot set
// headers on a WebSocket; a query parameter would end up in access logs). A 401 fires the
// window event "slipfleet:auth-required", on which main.js asks for a token.

const TOKEN_KEY = "slipfleet.token";

const config = {
  base: "", // same origin
  token: sessionStorage.getItem(TOKEN_KEY), // bearer token, when the server requires one
};

export function setToken(token) {
  config.token = token || null;
  if (config.token) sessionStorage.setItem(TOKEN_KEY, config.token);
  else sessionStorage.removeItem(TOKEN_KEY);
}

export function hasToken() {
  return Boolean(config.token);
}

function headers() {
  const h = { Accept: "application/json" };
  if (config.token) h.Authorization = `Bearer ${config.token}`;
  return h;
}

function query(params) {
  const q = new URLSearchParams();
  for (const [k, v] of Object.entries(params || {})) {
    if (v !== undefined && v !== null) q.set(k, String(v));
  }
  const s = q.toString();
  return s ? `?${s}` : "";
}

export class ApiError extends Error {
  constructor(status, code, reason) {
    super(`${status} ${code}: ${reason}`);
    this.status = status;
    this.code = code;
    this.reason = reason;
  }
}

export async function getJSON(path, params) {
  const resp = await fetch(`${config.base}${path}${query(params)}`, { headers: headers() });
  return answerOf(resp);
}

// REST write (PUT, POST, DELETE) with an optional JSON body; the answer's JSON, or ApiError.
export async function sendJSON(method, path, body) {
  const h = headers();
  if (body !== undefined) h["Content-Type"] = "application/json";
  const resp = await fetch(`${config.base}${path}`, { method, headers: h, body: body === undefined ? undefined : JSON.stringify(body) });
  return answerOf(resp);
}

async function answerOf(resp) {
  if (!resp.ok) {
    let code = "error";
    let reason = resp.statusText;
    try {
      const body = await resp.json();
      code = body.error || code;
      reason = body.reason || reason;
    } catch (_) {
      /* not JSON */
    }
    if (resp.status === 401) {
      window.dispatchEvent(new CustomEvent("slipfleet:auth-required", { detail: { reason } }));
    }
    throw new ApiError(resp.status, code, reason);
  }
  return resp.json();
}

// REST: one vehicle's series as {stamp_ns: [...], field: [...]} (column arrays, null for NaN).
export async function fetchSeries(vehicleId, startNs, endNs, fields, maxPoints) {
  const body = await getJSON(`/api/v1/vehicles/${encodeURIComponent(vehicleId)}/series`, {
    start: String(startNs),
    end: String(endNs),
    fields: fields.join(","),
    max_points: maxPoints,
    format: "json",
  });
  return body.columns;
}

// Registered vehicles with their configs: {data: [{vehicle_id, config: {slip: {...}}}], count}.
export function fetchVehicles() {
  return getJSON("/api/v1/vehicles");
}

export function fetchVehicle(vehicleId) {
  return getJSON(`/api/v1/vehicles/${encodeURIComponent(vehicleId)}`);
}

// Field report of one vehicle over [startNs, endNs): speeds, slip statistics, ingest counters.
export function fetchReport(vehicleId, startNs, endNs) {
  return getJSON(`/api/v1/vehicles/${encodeURIComponent(vehicleId)}/report`, {
    start: String(startNs),
    end: String(endNs),
  });
}

export function fetchAlerts(params) {
  return getJSON("/api/v1/alerts", params);
}

// A WebSocket that reconnects with back-off. onMessage(obj) gets each parsed JSON message;
// onState("open" | "closed" | "error") reports the connection. Returns {send, close}.
export function liveSocket(path, params, { onMessage, onState }) {
  const proto = location.protocol === "https:" ? "wss:" : "ws:";
  const url = `${proto}//${location.host}${config.base}${path}${query(params)}`;
  let ws = null;
  let closed = false;
  let delay = 500;
  let timer = null;
  const connect = () => {
    ws = config.token ? new WebSocket(url, ["slipfleet.bearer", config.token]) : new WebSocket(url);
    ws.onopen = () => {
      delay = 500;
      onState && onState("open");
    };
    ws.onmessage = (ev) => {
      let msg;
      try {
        msg = JSON.parse(ev.data);
      } catch (_) {
        return;
      }
      onMessage(msg, performance.timeOrigin + performance.now());
    };
    ws.onclose = () => {
      onState && onState("closed");
      if (!closed) {
        timer = setTimeout(connect, delay);
        delay = Math.min(delay * 2, 10000);
      }
    };
    ws.onerror = () => onState && onState("error");
  };
  connect();
  return {
    send(obj) {
      if (ws && ws.readyState === WebSocket.OPEN) ws.send(JSON.stringify(obj));
    },
    close() {
      closed = true;
      clearTimeout(timer);
      if (ws) ws.close();
    },
  };
}

// The dashboard's settings (GET /api/v1/dashboard: the basemap's tile URL or null), fetched once;
// {map_tile_url: null} when the server does not say (no basemap: nothing fetched elsewhere).
let dashboardConfig = null;
export function loadDashboardConfig() {
  if (!dashboardConfig) {
    dashboardConfig = getJSON("/api/v1/dashboard").catch(() => {
      dashboardConfig = null;
      return { map_tile_url: null };
    });
  }
  return dashboardConfig;
}
