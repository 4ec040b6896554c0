// Dashboard entry: hash routes #/fleet, #/vehicle/<id>, #/vehicle/<id>/history, #/alerts.

import { alertsView, startAlertBadge } from "./alerts.js";
import { fleetView } from "./fleet.js";
import { historyView } from "./history.js";
import { vehicleView } from "./vehicle.js";

const main = document.getElementById("main");
let teardown = null;

function route() {
  if (teardown) teardown();
  teardown = null;
  main.replaceChildren();
  const parts = location.hash.replace(/^#\/?/, "").split("/").map(decodeURIComponent);
  let view = "fleet";
  if (parts[0] === "vehicle" && parts[1]) {
    view = parts[2] === "history" ? "history" : "vehicle";
    teardown = view === "history" ? historyView(main, parts[1]) : vehicleView(main, parts[1]);
  } else if (parts[0] === "alerts") {
    view = "alerts";
    teardown = alertsView(main);
  } else {
    teardown = fleetView(main);
  }
  for (const a of document.querySelectorAll("nav a[data-view]")) {
    if (a.dataset.view === view) a.setAttribute("aria-current", "page");
    else a.removeAttribute("aria-current");
  }
  document.title = `Slipfleet — ${view}`;
  main.focus({ preventScroll: true });
}

window.addEventListener("hashchange", route);
startAlertBadge(document.getElementById("alert-badge"));
route();
