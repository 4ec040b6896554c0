// Dashboard entry: hash routes #/fleet, #/vehicle/<id>, #/vehicle/<id>/history, #/alerts.

import { alertsView, startAlertBadge } from "./alerts.js";
import { setToken } from "./api.js";
import { localZoneName, setTimeMode, timeMode } from "./clock.js";
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

// Access token dialog: opened on any 401 (see api.js) or from the header button.
const dialog = document.getElementById("token-dialog");
function askToken(reason) {
  document.getElementById("token-reason").textContent =
    reason || "This server needs an access token to show its data.";
  if (!dialog.open) dialog.showModal();
}
dialog.addEventListener("close", () => {
  const input = document.getElementById("token-input");
  if (dialog.returnValue === "save" && input.value.trim()) setToken(input.value.trim());
  else if (dialog.returnValue === "forget") setToken(null);
  input.value = "";
  route(); // reload the view with the new credentials
});
window.addEventListener("slipfleet:auth-required", (ev) =>
  askToken(`The server refused the request: ${ev.detail.reason}`),
);
document.getElementById("token-button").addEventListener("click", () => askToken());

// Times in the browser's zone (default) or UTC: every view is drawn again in the chosen one.
const tzSelect = document.getElementById("tz-select");
document.getElementById("tz-local").textContent = `Local (${localZoneName()})`;
tzSelect.value = timeMode();
tzSelect.addEventListener("change", () => {
  setTimeMode(tzSelect.value);
  route();
});

window.addEventListener("hashchange", route);
startAlertBadge(document.getElementById("alert-badge"));
route();
