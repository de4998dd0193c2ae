// The operator page's entry: log in, roles, devices, tabs; each tab is its own module.
import { $, $$, TOKEN_KEY, api, applyRoles, hooks, showTab, state } from "./core.js";
import { liveLoop, robotLoop } from "./live.js";
import { refreshCalibrations } from "./calib.js";
import { refreshRecipes } from "./pick.js";
import "./wizard.js";
import "./routines.js";
import "./production.js";
import "./drift.js";
import "./recipes.js";
import "./plc.js";
import "./audit.js";
import { loadControls } from "./camera.js";

async function login(token) {
  const who = await api("GET", "/auth/whoami", undefined, { token });
  state.token = token;
  state.who = who;
  state.session += 1;
  sessionStorage.setItem(TOKEN_KEY, token);
  $("#who-name").textContent = who.name;
  $("#who-role").textContent = who.role;
  $("#who").hidden = false;
  $("#login-view").hidden = true;
  $("#main-view").hidden = false;
  document.body.dataset.role = who.role;
  applyRoles();
  document.dispatchEvent(new CustomEvent("cellctl:login"));
  await loadDevices();
  loadControls();
  const session = state.session;
  liveLoop(session);
  robotLoop(session);
  refreshCalibrations();
  refreshRecipes();
}

function logout(message) {
  state.token = null;
  state.who = null;
  state.session += 1;
  sessionStorage.removeItem(TOKEN_KEY);
  $("#who").hidden = true;
  $("#main-view").hidden = true;
  $("#login-view").hidden = false;
  $("#login-error").textContent = message || "";
  delete document.body.dataset.role;
}

$("#login-form").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  $("#login-error").textContent = "";
  const token = $("#token").value.trim();
  try {
    await login(token);
    $("#token").value = "";
  } catch (e) {
    $("#login-error").textContent = e.status === 401 ? "This token is not accepted by the cell." : `Cannot log in: ${e.message}`;
  }
});
$("#logout").addEventListener("click", () => logout(""));

for (const b of $$("#tabs button")) b.addEventListener("click", () => showTab(b.dataset.tab));

async function loadDevices() {
  const [cams, robots] = await Promise.all([api("GET", "/cameras"), api("GET", "/robots")]);
  const fill = (sel, items) => {
    sel.replaceChildren(...items.map((d) => new Option(`${d.id} (${d.kind})`, d.id)));
  };
  fill($("#camera-select"), cams);
  fill($("#robot-select"), robots);
  state.cameraId = cams.length ? cams[0].id : null;
  state.robotId = robots.length ? robots[0].id : null;
}
$("#camera-select").addEventListener("change", (e) => { state.cameraId = e.target.value; });
$("#robot-select").addEventListener("change", (e) => { state.robotId = e.target.value; });

hooks.unauthorized = logout;

// ---------------------------------------------------------------- start

(async () => {
  try {
    const h = await (await fetch("/health", { cache: "no-store" })).json();
    $("#cell-id").textContent = `· ${h.cell_id} · v${h.version}`;
  } catch (_) { /* the page still works without it */ }
  const saved = sessionStorage.getItem(TOKEN_KEY);
  if (saved) {
    try { await login(saved); } catch (_) { logout(""); }
  }
})();
