// Routines tab: capture routines and verify, followed over their event streams.
import { $, $$, api, fmt, followJob, has, startRoutine, state } from "./core.js";
import { activate } from "./calib.js";

// ---------------------------------------------------------------- capture routines and verify

const RESULT_KEYS = [
  ["calibration_id", "calibration", (v) => `#${v}`], ["views_used", "views used"], ["stations_used", "stations used"],
  ["rms_px", "RMS", (v) => `${fmt(v, 4)} px`], ["passed", "passed", (v) => (v ? "yes" : "NO")],
  ["drift_px", "drift", (v) => `${fmt(v, 3)} px`], ["drift_mm", "drift", (v) => `${fmt(v, 3)} mm`],
  ["verdict", "verdict", (v) => (v && v.ok ? "OK" : `NOT OK: ${((v && v.problems) || []).map((p) => p.code).join(", ")}`)],
];

// The form of each routine is generated from its parameter schema (GET /routines): numbers and
// choices with their defaults, ranges and descriptions (units are in the names and descriptions).
const SKIP = new Set(["camera_id", "robot_id", "target", "note", "mode"]);

function kindOf(prop) {
  const options = prop.anyOf || [prop];
  const enumOpt = options.find((o) => o.enum);
  if (enumOpt) return { type: "enum", values: enumOpt.enum };
  const n = options.find((o) => o.type === "integer" || o.type === "number");
  return n ? { type: n.type, min: n.minimum ?? n.exclusiveMinimum, max: n.maximum ?? n.exclusiveMaximum } : null;
}

function buildForm(card, schema) {
  const form = document.createElement("div");
  form.className = "params";
  for (const [key, prop] of Object.entries(schema.properties || {})) {
    if (SKIP.has(key)) continue;
    const k = kindOf(prop);
    if (!k) continue;
    const label = document.createElement("label");
    label.title = prop.description || "";
    label.append(`${key.replace(/_/g, " ")} `);
    let input;
    if (k.type === "enum") {
      input = document.createElement("select");
      input.append(new Option("(config default)", ""), ...k.values.map((v) => new Option(v, v)));
      if (prop.default) input.value = prop.default;
    } else {
      input = document.createElement("input");
      input.type = "number";
      input.step = k.type === "integer" ? "1" : "any";
      if (k.min !== undefined) input.min = String(k.min);
      if (k.max !== undefined) input.max = String(k.max);
      if (prop.default !== undefined && prop.default !== null) input.value = String(prop.default);
      else input.placeholder = "config default";
    }
    input.name = key;
    input.dataset.kind = k.type;
    label.append(input);
    form.append(label);
  }
  card.querySelector("p.muted").after(form);
}

let schemas = null;
async function loadForms() {
  if (schemas || !state.token) return;
  try {
    schemas = Object.fromEntries((await api("GET", "/routines")).map((r) => [r.name, r.params_schema]));
  } catch (_) { schemas = null; return; }
  for (const card of $$(".routine")) if (schemas[card.dataset.routine]) buildForm(card, schemas[card.dataset.routine]);
}
document.addEventListener("cellctl:tab", (e) => { if (e.detail === "routines") loadForms(); });
document.addEventListener("cellctl:login", () => { schemas = null; for (const f of $$(".routine .params")) f.remove(); });

function setupRoutineCard(card) {
  card.append($("#routine-controls").content.cloneNode(true));
  const name = card.dataset.routine;
  const start = $(".start", card), cancel = $(".cancel", card), bar = $(".bar", card);
  const msg = $(".message", card), err = $(".error", card), result = $(".result", card), act = $(".activate", card);
  const log = $(".log", card);
  const note = (text) => {
    msg.textContent = text;
    const li = document.createElement("li");
    li.textContent = text;
    log.append(li);
    while (log.children.length > 12) log.firstChild.remove();
  };
  let job = null;
  start.addEventListener("click", async () => {
    const params = {};
    for (const input of $$("[name]", card)) {
      if (input.value === "") continue;
      params[input.name] = input.dataset.kind === "enum" ? input.value : Number(input.value);
    }
    start.disabled = true; cancel.disabled = false; act.hidden = true;
    err.textContent = ""; result.replaceChildren(); log.replaceChildren(); bar.style.width = "0";
    card.dataset.state = "running";
    const session = state.session;
    try {
      job = await startRoutine(name, params);
      card.dataset.jobId = job.id;
      note(`started (job ${job.id})`);
      const done = await followJob(job, (kind, data) => {
        if (kind === "progress") { bar.style.width = `${Math.round(data.progress * 100)}%`; note(data.message); }
        if (kind === "state") note(`${data.state}: ${data.message}`);
      }, () => session === state.session);
      card.dataset.state = done.state;
      if (done.state === "succeeded") {
        bar.style.width = "100%";
        for (const [key, label, f] of RESULT_KEYS) {
          if (!(key in done.result)) continue;
          const tr = document.createElement("tr");
          const th = document.createElement("th"); th.textContent = label;
          const td = document.createElement("td"); td.textContent = f ? f(done.result[key]) : String(done.result[key]);
          tr.append(th, td); result.append(tr);
        }
        if (done.result.calibration_id && has("engineer")) {
          act.hidden = false; act.disabled = false;
          act.onclick = async () => {
            act.disabled = true;
            try { await activate(done.result.calibration_id); msg.textContent = `calibration #${done.result.calibration_id} is active`; }
            catch (e) { err.textContent = e.message; act.disabled = false; }
          };
        }
      } else {
        err.textContent = done.error || done.message;
      }
    } catch (e) {
      err.textContent = e.message;
      card.dataset.state = "error";
    } finally {
      start.disabled = false; cancel.disabled = true;
    }
  });
  cancel.addEventListener("click", async () => {
    if (job) { try { await api("DELETE", `/jobs/${encodeURIComponent(job.id)}`); } catch (e) { err.textContent = e.message; } }
  });
}
for (const card of $$(".routine")) setupRoutineCard(card);
