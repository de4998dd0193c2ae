// The Production tab: start (engineer), pause, resume and stop (operator) a run; its counters, cycle
// times, the last cycle's annotated picture and its failures, refreshed every second while shown.
// The header's Stop robot button (every tab) is the emergency stop: POST /robots/{id}/stop.
import { $, api, fmt, state } from "./core.js";

const PERIOD_MS = 1000;
let shownFrame = null;

function message(text, bad = false) {
  const el = $("#prod-message");
  el.textContent = text;
  el.className = bad ? "error" : "muted";
}

async function act(path, body) {
  try {
    const r = await api("POST", path, body);
    message(r.run_id !== undefined && path.endsWith("/start") ? `run ${r.run_id} started` : "");
    await refresh();
  } catch (e) {
    message(`${e.code}: ${e.message}`, true);
  }
}

function show(run) {
  $("#prod-state").textContent = run.state;
  $("#pc-run").textContent = run.run_id;
  for (const [k, v] of Object.entries(run.counters)) {
    const cell = $(`#pc-${k}`);
    if (cell) cell.textContent = v;
  }
  $("#pc-slot").textContent = run.next_slot;
  const ms = run.cycle_ms || {};
  $("#pc-cycle").textContent = `${fmt(ms.median, 0)} / ${fmt(ms.p95, 0)} ms`;
  $("#pc-split").textContent = `${fmt(ms.vision_median, 0)} / ${fmt(ms.motion_median, 0)} / ${fmt(ms.gripper_median, 0)} ms`;
  $("#pc-ended").textContent = run.ended_because || "–";
  if (run.error) message(run.error, true);
}

async function showCycles(runId) {
  const cycles = await api("GET", `/production/runs/${runId}/cycles`);
  const failed = cycles.filter((c) => c.result !== "placed");
  $("#prod-failures").replaceChildren(...(failed.length ? failed.slice(-10).map((c) => {
    const li = document.createElement("li");
    li.textContent = `#${c.n} ${c.result}${c.detail ? `: ${c.detail}` : ""}`;
    return li;
  }) : [Object.assign(document.createElement("li"), { textContent: "none" })]));
  const last = cycles.length ? cycles[cycles.length - 1] : null;
  if (last && last.frame_id !== null && last.frame_id !== shownFrame) {
    shownFrame = last.frame_id;
    try {
      const r = await api("GET", `/frames/${last.frame_id}.png`, undefined, { raw: true });
      const img = $("#prod-frame");
      if (img.src) URL.revokeObjectURL(img.src);
      img.src = URL.createObjectURL(await r.blob());
      img.hidden = false;
    } catch (_) { /* the frame has left the service's cache */ }
  }
}

async function refresh() {
  try {
    const run = await api("GET", "/production");
    show(run);
    await showCycles(run.run_id);
  } catch (e) {
    if (e.code === "no_run") $("#prod-state").textContent = "no run";
    else message(`${e.code}: ${e.message}`, true);
  }
}

async function loop(session) {
  while (state.session === session && state.tab === "production") {
    await refresh();
    await new Promise((resolve) => setTimeout(resolve, PERIOD_MS));
  }
}

document.addEventListener("cellctl:tab", (ev) => {
  if (ev.detail === "production") loop(state.session);
});

$("#prod-form").addEventListener("submit", (ev) => {
  ev.preventDefault();
  act("/production/start", { recipe_id: Number($("#prod-recipe").value), count: Number($("#prod-count").value) });
});
$("#prod-pause").addEventListener("click", () => act("/production/pause"));
$("#prod-resume").addEventListener("click", () => act("/production/resume"));
$("#prod-stop").addEventListener("click", () => act("/production/stop"));
