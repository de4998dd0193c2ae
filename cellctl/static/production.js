// The Production tab: start (engineer), pause, resume and stop (operator) a run; its counters, cycle
// times, parts per minute, the last cycle's annotated picture, its failures and the cycle table (filter by
// result, each cycle's frame, the CSV), refreshed every second while shown. With no run yet it asks
// GET /production?none_ok=true (200, no console error). The header's Stop robot is the emergency stop.
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

function cycleRow(c) {
  const tr = document.createElement("tr");
  tr.dataset.result = c.result;
  const zero = (v, digits) => (Math.abs(v) < 0.5 * 10 ** -digits ? 0 : v);  // no "-0.000"
  const pose = (p, keys, f, digits) => (p ? keys.map((k) => fmt(zero(p[k] * f, digits), digits)).join(", ") : "–");
  const mm = ["x_mm", "y_mm", "z_mm"], rv = ["rx_rad", "ry_rad", "rz_rad"];
  const cells = [c.n, new Date(c.t * 1000).toLocaleTimeString(), c.result, c.slot ?? "–", fmt(c.score, 3),
    pose(c.pick_pose, mm, 1, 1), pose(c.pick_pose, rv, 1, 3), pose(c.place_pose, mm, 1, 1),
    pose(c.place_pose, rv, 1, 3), fmt((c.durations_ms || {}).cycle, 0)];
  for (const x of cells) { const td = document.createElement("td"); td.textContent = String(x); tr.append(td); }
  const frame = document.createElement("td");
  if (c.frame_url) {
    const a = document.createElement("a");
    a.textContent = c.frame_kept ? "kept frame" : "frame";
    a.href = "#";
    a.className = "frame-link";
    a.addEventListener("click", (ev) => { ev.preventDefault(); openFrame(c.frame_url); });
    frame.append(a);
  } else frame.textContent = "–";
  tr.append(frame);
  const detail = document.createElement("td");
  detail.textContent = c.detail || "";
  detail.className = "detail";
  tr.append(detail);
  if (c.result !== "placed") tr.className = "failed";
  return tr;
}

// A frame link opens the picture in the tab's image (fetched with the token; a plain link cannot send it).
async function openFrame(url) {
  try {
    const r = await api("GET", url, undefined, { raw: true });
    const img = $("#prod-frame");
    if (img.src) URL.revokeObjectURL(img.src);
    img.src = URL.createObjectURL(await r.blob());
    img.hidden = false;
    img.dataset.url = url;
    shownFrame = null;
    pinned = true;
  } catch (e) { message(`frame: ${e.message}`, true); }
}

let pinned = false;  // a frame opened from the table stays until the next run
let cyclesShown = "";

function partsPerMinute(cycles) {
  const placed = cycles.filter((c) => c.result === "placed");
  if (cycles.length < 2 || !placed.length) return null;
  const minutes = (cycles[cycles.length - 1].t - cycles[0].t) / 60;
  return minutes > 0 ? placed.length / minutes : null;
}

async function showCycles(runId) {
  const cycles = await api("GET", `/production/runs/${runId}/cycles`);
  const failed = cycles.filter((c) => c.result !== "placed");
  $("#prod-failures").replaceChildren(...(failed.length ? failed.slice(-10).map((c) => {
    const li = document.createElement("li");
    li.textContent = `#${c.n} ${c.result}${c.detail ? `: ${c.detail}` : ""}`;
    return li;
  }) : [Object.assign(document.createElement("li"), { textContent: "none" })]));
  const rate = partsPerMinute(cycles);
  $("#pc-rate").textContent = rate === null ? "–" : fmt(rate, 1);
  const filter = $("#cycles-filter").value;
  const shown = cycles.filter((c) => !filter || (filter === "failed" ? c.result !== "placed" : c.result === filter));
  const key = `${runId}:${filter}:${cycles.length}`;
  if (key !== cyclesShown) {  // redraw only when it changed (a link being clicked is not replaced under the mouse)
    cyclesShown = key;
    $("#cycles-table tbody").replaceChildren(...shown.map(cycleRow));
    $("#cycles-count").textContent = `${shown.length} of ${cycles.length} cycles`;
  }
  const csv = $("#cycles-csv");
  csv.hidden = false;
  csv.dataset.run = String(runId);
  const last = cycles.length ? cycles[cycles.length - 1] : null;
  if (!pinned && last && last.frame_id !== null && last.frame_id !== shownFrame) {
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

// The CSV download: fetched with the token, handed to the browser as a file.
$("#cycles-csv").addEventListener("click", async (ev) => {
  ev.preventDefault();
  const runId = $("#cycles-csv").dataset.run;
  try {
    const r = await api("GET", `/production/runs/${runId}/cycles?format=csv`, undefined, { raw: true });
    const a = document.createElement("a");
    a.href = URL.createObjectURL(await r.blob());
    a.download = `run-${runId}-cycles.csv`;
    document.body.append(a);
    a.click();
    a.remove();
  } catch (e) { message(`CSV: ${e.message}`, true); }
});
$("#cycles-filter").addEventListener("change", () => { cyclesShown = ""; refresh(); });

async function refresh() {
  try {
    const run = await api("GET", "/production?none_ok=true");
    if (run.run_id === null) {
      $("#prod-state").textContent = "no run";
      $("#cycles-csv").hidden = true;
      return;
    }
    show(run);
    await showCycles(run.run_id);
  } catch (e) {
    message(`${e.code}: ${e.message}`, true);
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
  pinned = false;
  act("/production/start", { recipe_id: Number($("#prod-recipe").value), count: Number($("#prod-count").value) });
});
$("#prod-pause").addEventListener("click", () => act("/production/pause"));
$("#prod-resume").addEventListener("click", () => act("/production/resume"));
$("#prod-stop").addEventListener("click", () => act("/production/stop"));
