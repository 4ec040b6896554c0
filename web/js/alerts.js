// Alerts panel: open and recent alerts from GET /api/v1/alerts, refreshed every 2 s.

import { fetchAlerts } from "./api.js";
import { fmtClock, zoneName } from "./clock.js";
import { loadSpecs } from "./specs.js";
import { el, fmt, fmtDuration, timeTitle, vehicleHref } from "./util.js";

// Alert kinds of no estimator; slip, flag and rule alerts ("slip:<estimator>:<channel key>",
// "flag:<estimator>:<FLAG>", "rule:<estimator>:<rule key>") are said from the estimator's spec
// (kindLabel).
const KIND_LABEL = {
  stale: "No data (stale)",
  storage_down: "Server: database unavailable or full",
  zenoh_down: "Server: no Zenoh router",
};

// "Slip rear left wheel above threshold (MDSF wheel slip)", "GNSS lost: … (MDSF wheel slip)"
function kindLabel(a, specs) {
  const spec = a.estimator && specs ? specs.get(a.estimator) : null;
  if (!spec) return KIND_LABEL[a.kind] || a.kind;
  if (a.kind.startsWith("slip:")) {
    const ch = spec.slips.find((c) => c.key === a.channel);
    return `Slip ${ch ? ch.label : a.channel} above threshold (${spec.title})`;
  }
  if (a.kind.startsWith("rule:")) {
    const rule = (spec.alerts || []).find((r) => r.key === a.channel);
    return `${rule ? rule.label : a.channel} (${spec.title})`;
  }
  const flag = spec.flags.find((f) => f.name === a.channel);
  return `${flag ? flag.description : a.channel} (${spec.title})`;
}

// "2026-05-01 12:00:03" in the chosen zone (the column header names it; the other reading on
// hover); date and time each kept on one line, so a narrow column breaks between them only
function timeCell(ns) {
  if (ns === null || ns === undefined) return el("td", { class: "when" }, "–");
  const [day, time] = fmtClock(ns / 1e6).split(" ");
  return el("td", { class: "when", title: timeTitle(ns) }, el("span", { text: day }), " ", el("span", { text: time }));
}

export function alertsView(root) {
  const stateSel = el("select", { id: "a-state", "aria-label": "Which alerts" });
  for (const [v, t] of [["open", "open"], ["all", "open and closed"], ["closed", "closed"]]) {
    stateSel.append(el("option", { value: v, text: t }));
  }
  stateSel.value = "all";
  const msg = el("p", { class: "summary", "aria-live": "polite" });
  const tbody = el("tbody", { id: "alerts-body" });
  root.append(
    el("div", { class: "toolbar" }, el("h1", { text: "Alerts" }), el("label", {}, "Show ", stateSel), msg),
    // on a narrow screen the table scrolls sideways in its own box, its header with it
    el(
      "div",
      { class: "table-scroll", id: "alerts-scroll" },
      el(
        "table",
        { class: "plain" },
        el(
          "thead",
          {},
          el(
            "tr",
            {},
            ...["State", "Vehicle", "Kind", `Start (${zoneName()})`, `End (${zoneName()})`, "Duration", "Peak |slip| (%)", "Threshold (%)"].map((h) =>
              el("th", { scope: "col", text: h }),
            ),
          ),
        ),
        tbody,
      ),
    ),
  );
  let timer = null;
  let specs = null; // estimator specs, for the kinds' labels (raw kinds until loaded)
  loadSpecs()
    .then((all) => {
      specs = all;
      refresh();
    })
    .catch(() => {});
  async function refresh() {
    try {
      const body = await fetchAlerts({ state: stateSel.value, limit: 500 });
      msg.textContent = `${body.open_count} open`;
      const rows = body.alerts.map((a) => {
        const endNs = a.end_ns ?? null;
        const dur = endNs ? (endNs - a.start_ns) / 1e9 : Date.now() / 1e3 - a.start_ns / 1e9;
        return el(
          "tr",
          { class: a.open ? "alert-open" : "" },
          el("td", {}, el("span", { class: `pill ${a.open ? "st-offline" : "st-closed"}`, text: a.open ? "open" : "closed" })),
          el(
            "td",
            {},
            a.vehicle_id
              ? el("a", { href: vehicleHref(a.vehicle_id), text: a.vehicle_id })
              : el("strong", { text: "server" }),
          ),
          el("td", { text: kindLabel(a, specs) }),
          timeCell(a.start_ns),
          endNs ? timeCell(endNs) : el("td", { text: "ongoing" }),
          el("td", { text: fmtDuration(Math.max(0, dur)) }),
          el("td", { class: "num", text: fmt(a.peak, 1) }),
          el("td", { class: "num", text: fmt(a.threshold, 1) }),
        );
      });
      tbody.replaceChildren(...rows);
      if (!rows.length) tbody.append(el("tr", {}, el("td", { colspan: "8", text: "No alerts." })));
    } catch (err) {
      msg.textContent = `Could not load alerts: ${err.message}`;
    }
  }
  stateSel.addEventListener("change", refresh);
  refresh();
  timer = setInterval(refresh, 2000);
  return () => clearInterval(timer);
}

// Badge in the header: number of open alerts, refreshed every 5 s.
export function startAlertBadge(badge) {
  const tick = async () => {
    try {
      const body = await fetchAlerts({ state: "open", limit: 1 });
      badge.textContent = String(body.open_count);
      badge.hidden = body.open_count === 0;
    } catch (_) {
      badge.hidden = true;
    }
  };
  tick();
  setInterval(tick, 5000);
}
