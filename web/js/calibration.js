// Vehicle page, online calibration: for every estimator of the vehicle whose spec declares
// calibrations (GET /api/v1/vehicles/{id}/calibration, every 5 s), a table of each calibration's
// value ± 1σ in its unit, converged / uncalibrated / configured (not learnt, not waited for) /
// learning (a spec without an uncalibrated flag) / off, and since when; whether the newest row
// is flagged uncalibrated. Operators get the estimator's commands (MDSF: the calibration drive,
// PUT …/commands/{estimator}/{key}) and a reset (DELETE …/calibration/{estimator}); a token
// below operator is refused by the server (403), which the panel says. Nothing here names an
// estimator's fields: labels, units and commands come from the answer and the specs.

import { ApiError, getJSON, sendJSON } from "./api.js";
import { el, fmtTimeNs, timeTitle } from "./util.js";

const REFRESH_MS = 5000;
// stored rows read for "since when" (the REST default, an hour, costs ~0.2 s a call; a stretch
// older than this is said "≤ <window start>")
const LOOKBACK_S = 900;

// A value with its σ in a readable unit: seconds as ms, radians as degrees, metres as mm for σ.
const SHOWN = {
  s: [1e3, "ms", 1],
  rad: [180 / Math.PI, "°", 2],
  m: [1, "m", 4],
};

function fmtValue(v, unit) {
  if (v == null) return "–";
  const [k, u, d] = SHOWN[unit] || [1, unit, 3];
  return `${(v * k).toFixed(d)} ${u}`.trim();
}

// A calibration's state; one not converged while the newest row is not flagged uncalibrated is
// one the estimator does not wait for (it cannot learn it now): the configured value, in use.
// An estimator whose spec has no uncalibrated flag (part.uncalibrated null) flags no row while
// a calibration converges: it is learning.
function stateOf(c, part) {
  if (!c.enabled) return ["off", "turned off in the vehicle's config"];
  if (c.value == null) return ["none", "no value yet"];
  if (c.converged) return ["converged", ""];
  const below = c.limit == null ? "" : `converges below σ ${fmtValue(c.limit, c.unit)}`;
  if (part.uncalibrated == null && part.stamp_ns != null) return ["learning", `${below}; its rows are not flagged meanwhile`];
  if (part.uncalibrated === false) return ["configured", "not learnt: the configured value is used"];
  return ["uncalibrated", below];
}

// What the newest row says of the estimator's calibration: flagged by the spec's uncalibrated
// flag (its description says what rests on it), not flagged, or a spec without such a flag.
function stateText(part, spec) {
  if (part.stamp_ns == null) return "No stored estimate yet.";
  const at = fmtTimeNs(part.stamp_ns, false);
  if (part.uncalibrated == null) return `As of ${at}; its rows are not flagged while these converge.`;
  if (!part.uncalibrated) return `Calibrated as of ${at}.`;
  const flag = (spec?.flags || []).find((f) => f.name === spec.uncalibrated_flag);
  const why = flag ? `: ${flag.description}` : "";
  return `Uncalibrated since ${fmtTimeNs(part.uncalibrated_since_ns, false)}, rows flagged ${spec?.uncalibrated_flag || "uncalibrated"}${why}.`;
}

function sinceCell(c) {
  if (c.since_ns == null) return el("td", { text: "–" });
  const when = fmtTimeNs(c.since_ns, false);
  return el("td", { class: "cal-since", title: timeTitle(c.since_ns), "data-since-ns": String(c.since_ns), text: c.since_window_start ? `≤ ${when}` : when });
}

function row(c, part) {
  const [state, note] = stateOf(c, part);
  return el(
    "tr",
    { "data-calibration": c.key, "data-state": state },
    el("th", { text: c.label }),
    el("td", { class: "num cal-value", text: fmtValue(c.value, c.unit) }),
    el("td", { class: "num cal-std", text: c.std == null ? "" : `± ${fmtValue(c.std, c.unit)}` }),
    el("td", {}, el("span", { class: `pill cal-${state}`, title: note, text: state })),
    sinceCell(c),
  );
}

// One estimator's part: its state, its table and the operator's controls.
function estimatorPart(vehicleId, part, spec, say) {
  const base = `/api/v1/vehicles/${encodeURIComponent(vehicleId)}`;
  const state = el("p", { class: "cal-state", "data-uncalibrated": String(part.uncalibrated), text: stateText(part, spec) });
  const controls = el("div", { class: "toolbar cal-controls" });
  for (const cmd of spec?.commands || []) {
    for (const on of [true, false]) {
      const b = el("button", { type: "button", "data-command": cmd.key, "data-on": String(on), title: cmd.description, text: `${on ? "Start" : "Stop"} ${cmd.label}` });
      b.addEventListener("click", () =>
        sendJSON("PUT", `${base}/commands/${encodeURIComponent(part.estimator)}/${encodeURIComponent(cmd.key)}`, { on })
          .then(() => say(`${cmd.label} ${on ? "started" : "stopped"}`))
          .catch((err) => say(refusal(err))),
      );
      controls.append(b);
    }
  }
  const reset = el("button", { type: "button", class: "cal-reset", text: "Reset calibration" });
  reset.addEventListener("click", () => {
    if (!window.confirm(`Forget ${vehicleId}'s ${spec?.title || part.estimator} calibration and learn it anew?`)) return;
    sendJSON("DELETE", `${base}/calibration/${encodeURIComponent(part.estimator)}`)
      .then(() => say("calibration reset: learning anew"))
      .catch((err) => say(refusal(err)));
  });
  controls.append(reset);
  return el(
    "div",
    { class: "cal-part", "data-estimator": part.estimator },
    el("h3", { text: spec?.title || part.estimator }),
    state,
    el("table", { class: "ingest-table cal-table" }, el("tbody", {}, ...part.calibrations.map((c) => row(c, part)))),
    controls,
  );
}

function refusal(err) {
  if (err instanceof ApiError && err.status === 403) return "refused: an operator token is needed";
  return `refused: ${err.reason || err.message}`;
}

// The panel: {root, stop()}; hidden while the vehicle runs nothing that calibrates.
export function calibrationPanel(vehicleId, specs) {
  const body = el("div", { id: "v-calibration-parts" });
  const msg = el("span", { class: "summary", id: "v-calibration-msg", role: "status" });
  const root = el("details", { class: "ingest", id: "v-calibration", open: true, hidden: true }, el("summary", { text: "Online calibration" }), body, msg);
  let stopped = false;
  const say = (text) => {
    msg.textContent = text;
    refresh();
  };
  async function refresh() {
    try {
      const cal = await getJSON(`/api/v1/vehicles/${encodeURIComponent(vehicleId)}/calibration`, { lookback_s: LOOKBACK_S });
      if (stopped) return;
      root.hidden = !cal.estimators.length;
      body.replaceChildren(...cal.estimators.map((p) => estimatorPart(vehicleId, p, specs.get(p.estimator), say)));
    } catch (_) {
      /* not stored yet, or refused: the next refresh tries again */
    }
  }
  refresh();
  const timer = setInterval(refresh, REFRESH_MS);
  return {
    root,
    stop() {
      stopped = true;
      clearInterval(timer);
    },
  };
}
