// Camera controls on the Live tab: exposure, gain and trigger mode where the camera's driver has them
// (GET /cameras/{id}/controls); an engineer applies a change (PUT, checked against the camera's bounds,
// audited); a control the driver lacks is shown as such, never as an input that does nothing.
import { $, api, has, state } from "./core.js";

const FIELDS = { exposure_us: "#cc-exposure", gain_db: "#cc-gain", trigger: "#cc-trigger" };

function show(controls) {
  for (const [name, sel] of Object.entries(FIELDS)) {
    const c = controls[name];
    const el = $(sel);
    el.closest("label").title = c.supported ? "" : c.why;
    el.disabled = !c.supported || !has("engineer");
    if (name === "trigger") {
      el.replaceChildren(...(c.supported ? c.options : ["–"]).map((o) => new Option(o, o)));
      if (c.supported) el.value = c.value;
    } else {
      el.value = c.supported && c.value !== null ? String(Number(c.value.toFixed(3))) : "";
      el.placeholder = c.supported ? `${c.min}..${c.max} ${c.unit}` : "not on this camera";
      if (c.supported) { el.min = String(c.min); el.max = String(c.max); }
    }
  }
  const missing = Object.entries(controls).filter(([, c]) => !c.supported).map(([k]) => k.replace("_", " "));
  $("#cc-note").textContent = missing.length ? `this camera's driver has no ${missing.join(", ")} control` : "";
  $("#cc-apply").disabled = !has("engineer") || Object.values(controls).every((c) => !c.supported);
}

export async function loadControls() {
  if (!state.token || !state.cameraId) return;
  $("#cc-error").textContent = "";
  try {
    const r = await api("GET", `/cameras/${encodeURIComponent(state.cameraId)}/controls`);
    state.controls = r.controls;
    $("#cc-camera").textContent = `${r.camera_id} (${r.kind})`;
    show(r.controls);
  } catch (e) { $("#cc-error").textContent = e.message; }
}

$("#cc-form").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  const body = {};
  for (const [name, sel] of Object.entries(FIELDS)) {
    const c = state.controls && state.controls[name];
    if (!c || !c.supported) continue;
    const v = $(sel).value;
    if (name === "trigger") { if (v !== c.value) body.trigger = v; } else if (v !== "" && Number(v) !== c.value) body[name] = Number(v);
  }
  $("#cc-error").textContent = "";
  if (!Object.keys(body).length) { $("#cc-status").textContent = "nothing changed"; return; }
  try {
    const r = await api("PUT", `/cameras/${encodeURIComponent(state.cameraId)}/controls`, body);
    state.controls = r.controls;
    show(r.controls);
    $("#cc-status").textContent = `set ${Object.entries(body).map(([k, v]) => `${k} ${v}`).join(", ")}`;
  } catch (e) { $("#cc-error").textContent = e.message; $("#cc-status").textContent = ""; }
});

$("#camera-select").addEventListener("change", (e) => { state.cameraId = e.target.value; loadControls(); });
