// cellctl operator page. Plain JavaScript, no build step, nothing loaded from elsewhere.
// Every call goes to the cell's REST API with the operator's bearer token (kept in sessionStorage).
// Job events (SSE) are read with fetch + a stream reader, since EventSource cannot send the token.
"use strict";

const RANK = { viewer: 0, operator: 1, engineer: 2 };
const TOKEN_KEY = "cellctl.token";
const LIVE_PAUSE_MS = 400;     // pause between live frames (the next request starts when one is drawn)
const ROBOT_PERIOD_MS = 1000;

const $ = (sel, root = document) => root.querySelector(sel);
const $$ = (sel, root = document) => Array.from(root.querySelectorAll(sel));
const sleep = (ms) => new Promise((resolve) => setTimeout(resolve, ms));
const fmt = (v, digits = 2) => (v === null || v === undefined || Number.isNaN(Number(v))) ? "–" : Number(v).toFixed(digits);
const deg = (rad) => rad * 180 / Math.PI;

const state = {
  token: null, who: null, session: 0, tab: "live",
  cameraId: null, robotId: null, lastPick: null, pickUrl: null,
};

// ---------------------------------------------------------------- API

class ApiError extends Error {
  constructor(status, code, message) { super(message); this.status = status; this.code = code; }
}

async function api(method, path, body, opts = {}) {
  const headers = { Authorization: `Bearer ${opts.token || state.token}` };
  const init = { method, headers, cache: "no-store" };
  if (body !== undefined) { headers["Content-Type"] = "application/json"; init.body = JSON.stringify(body); }
  if (opts.signal) init.signal = opts.signal;
  const r = await fetch(path, init);
  if (!r.ok) {
    let code = `http_${r.status}`, message = `${r.status} ${r.statusText}`;
    try {
      const j = await r.json();
      if (j.error) { code = j.error.code; message = j.error.message; } else if (j.reason) { message = j.reason; }
    } catch (_) { /* not JSON */ }
    if (r.status === 401 && !opts.token) { logout("Your token is no longer accepted: log in again."); }
    throw new ApiError(r.status, code, message);
  }
  if (opts.raw) return r;
  return (r.headers.get("content-type") || "").includes("json") ? r.json() : r.text();
}

// Server-sent events over fetch: calls onEvent(kind, data, id) per event until the stream ends.
async function readEvents(jobId, onEvent, signal) {
  const r = await api("GET", `/jobs/${encodeURIComponent(jobId)}/events`, undefined, { raw: true, signal });
  const reader = r.body.pipeThrough(new TextDecoderStream()).getReader();
  let buf = "";
  for (;;) {
    const { value, done } = await reader.read();
    if (done) return;
    buf += value.replace(/\r\n/g, "\n");
    let cut;
    while ((cut = buf.indexOf("\n\n")) >= 0) {
      const block = buf.slice(0, cut);
      buf = buf.slice(cut + 2);
      let kind = "message", id = null;
      const data = [];
      for (const line of block.split("\n")) {
        if (!line || line.startsWith(":")) continue;
        const c = line.indexOf(":");
        const field = c < 0 ? line : line.slice(0, c);
        let v = c < 0 ? "" : line.slice(c + 1);
        if (v.startsWith(" ")) v = v.slice(1);
        if (field === "event") kind = v; else if (field === "data") data.push(v); else if (field === "id") id = Number(v);
      }
      if (data.length) onEvent(kind, JSON.parse(data.join("\n")), id);
    }
  }
}

// Start a routine and follow it to its end; handlers.onEvent(kind, data) sees each event once.
// Resolves with the finished job (GET /jobs/{id}). Reconnects if the stream breaks early.
async function followJob(job, onEvent, isCurrent) {
  let seen = -1;
  for (;;) {
    try {
      await readEvents(job.id, (kind, data, id) => {
        if (id !== null && id <= seen) return;
        if (id !== null) seen = id;
        if (isCurrent()) onEvent(kind, data);
      });
    } catch (e) {
      if (e instanceof ApiError && e.status === 404) throw e;
    }
    const now = await api("GET", `/jobs/${encodeURIComponent(job.id)}`);
    if (now.state !== "running") return now;
    if (!isCurrent()) return now;
    await sleep(1000);
  }
}

async function startRoutine(name, params) {
  return api("POST", `/routines/${encodeURIComponent(name)}`, params);
}

// ---------------------------------------------------------------- login and roles

function has(role) { return state.who && RANK[state.who.role] >= RANK[role]; }

function applyRoles() {
  for (const el of $$("[data-min-role]")) el.hidden = !has(el.dataset.minRole);
  if ($("nav button.active").hidden) showTab("live");
}

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
  await loadDevices();
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

function showTab(name) {
  state.tab = name;
  for (const b of $$("#tabs button")) b.classList.toggle("active", b.dataset.tab === name);
  for (const s of $$(".tab")) s.hidden = s.id !== `tab-${name}`;
  if (name === "calib") refreshCalibrations();
  if (name === "pick") refreshRecipes();
}
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

// ---------------------------------------------------------------- live camera view

// One camera request at a time from this page: a slow camera is not made slower by piling up grabs.
let cameraQueue = Promise.resolve();

function grabBitmap(format) {
  const grab = async () => {
    const r = await api("GET", `/cameras/${encodeURIComponent(state.cameraId)}/image?format=${format}`, undefined,
      { raw: true });
    const bitmap = await createImageBitmap(await r.blob());
    return { bitmap, frameId: r.headers.get("X-Frame-Id") };
  };
  const result = cameraQueue.then(grab, grab);
  cameraQueue = result.catch(() => undefined);
  return result;
}

// After an outage the service retries the camera after a back-off; wait for it before a routine.
async function waitCameraAvailable(timeoutMs) {
  const deadline = performance.now() + timeoutMs;
  for (;;) {
    const cams = await api("GET", "/cameras");
    const cam = cams.find((c) => c.id === state.cameraId);
    if (!cam || cam.available || performance.now() > deadline) return;
    await sleep(500);
  }
}

function drawPicks(ctx, pick) {
  ctx.lineWidth = 3;
  ctx.font = "bold 22px sans-serif";
  pick.picks.forEach((p, k) => {
    const color = p.reachable ? "#22c55e" : "#ef4444";
    ctx.strokeStyle = color;
    ctx.fillStyle = color;
    ctx.beginPath();
    ctx.arc(p.u_px, p.v_px, 24, 0, 2 * Math.PI);
    ctx.stroke();
    const a = (p.angle_deg || 0) * Math.PI / 180;
    ctx.beginPath();
    ctx.moveTo(p.u_px, p.v_px);
    ctx.lineTo(p.u_px + 60 * Math.cos(a), p.v_px - 60 * Math.sin(a));
    ctx.stroke();
    ctx.fillText(`${k + 1} ${p.part} ${fmt(p.score, 2)}`, p.u_px + 28, p.v_px - 28);
  });
}

async function liveLoop(session) {
  const canvas = $("#live-canvas");
  while (session === state.session) {
    if (state.tab !== "live" || !$("#live-on").checked || document.hidden || !state.cameraId) {
      await sleep(300);
      continue;
    }
    const t0 = performance.now();
    try {
      const { bitmap, frameId } = await grabBitmap("jpeg");
      if (session !== state.session) return;
      canvas.width = bitmap.width;
      canvas.height = bitmap.height;
      const ctx = canvas.getContext("2d");
      ctx.drawImage(bitmap, 0, 0);
      const pick = state.lastPick;
      if (pick && $("#overlay-on").checked && pick.camera_id === state.cameraId) drawPicks(ctx, pick);
      canvas.dataset.frameId = frameId || "";
      $("#live-status").textContent = `${state.cameraId} frame ${frameId} · ${bitmap.width}×${bitmap.height} · `
        + `${fmt(performance.now() - t0, 0)} ms` + (pick ? ` · last pick: ${pick.picks.length} match(es), recipe ${pick.recipe_id}` : "");
      $("#live-status").className = "muted";
    } catch (e) {
      $("#live-status").textContent = `camera ${state.cameraId} unavailable: ${e.message}`;
      $("#live-status").className = "error";
      await sleep(1500);
    }
    await sleep(LIVE_PAUSE_MS);
  }
}

// ---------------------------------------------------------------- robot state

async function robotLoop(session) {
  while (session === state.session) {
    if (state.robotId && !document.hidden) {
      try {
        const s = await api("GET", `/robots/${encodeURIComponent(state.robotId)}/state`);
        if (session !== state.session) return;
        const p = s.pose_ur;
        $("#rs-x").textContent = fmt(p.x_m * 1e3, 2);
        $("#rs-y").textContent = fmt(p.y_m * 1e3, 2);
        $("#rs-z").textContent = fmt(p.z_m * 1e3, 2);
        $("#rs-rx").textContent = fmt(deg(p.rx_rad), 2);
        $("#rs-ry").textContent = fmt(deg(p.ry_rad), 2);
        $("#rs-rz").textContent = fmt(deg(p.rz_rad), 2);
        $("#rs-mode").textContent = s.mode;
        $("#rs-moving").textContent = s.moving ? "yes" : "no";
        $("#rs-age").textContent = `${fmt(s.age_s * 1e3, 0)} ms`;
        $("#robot-state").dataset.xMm = String(p.x_m * 1e3);
        $("#robot-status").textContent = "";
        setBadge(`${state.robotId} ${s.moving ? "moving" : s.mode}`, true);
      } catch (e) {
        $("#robot-status").textContent = `robot ${state.robotId} unavailable: ${e.message}`;
        setBadge(`${state.robotId} unavailable`, false);
      }
    }
    await sleep(ROBOT_PERIOD_MS);
  }
}

function setBadge(text, ok) {
  const b = $("#robot-badge");
  b.textContent = text;
  b.className = `badge ${ok ? "ok" : "bad"}`;
}

$("#robot-stop").addEventListener("click", async () => {
  try {
    await api("POST", `/robots/${encodeURIComponent(state.robotId)}/stop`);
    $("#robot-status").textContent = "stop sent";
  } catch (e) { $("#robot-status").textContent = `stop failed: ${e.message}`; }
});

// ---------------------------------------------------------------- calibrations

function verdictText(kind, result) {
  if (result.verdict) {
    const v = result.verdict;
    if (v.ok) return { text: "OK", ok: true };
    return { text: `NOT OK: ${(v.problems || []).map((p) => p.code).join(", ")}`, ok: false };
  }
  if (kind === "npoint") return { text: "n/a (n-point)", ok: true };
  return { text: "no verdict", ok: true };
}

function headline(kind, r) {
  if (kind === "camera") return `${r.model}, rms ${fmt(r.rms_px, 3)} px`;
  if (kind === "handeye") return `${r.setup}, rms ${fmt(r.rms_px, 3)} px`
    + (r.uncertainty ? `, ±${fmt(r.uncertainty.trans_mm, 3)} mm / ±${fmt(r.uncertainty.rot_deg, 3)}°` : "");
  if (kind === "npoint") {
    return `${r.model}, rms ${fmt(r.rms_mm, 3)} mm` + (r.loo_rms_mm && r.model in r.loo_rms_mm
      ? `, leave-one-out ${fmt(r.loo_rms_mm[r.model], 3)} mm` : "");
  }
  return "";
}

async function refreshCalibrations() {
  if (!state.token) return;
  let list;
  try { list = await api("GET", "/calibrations"); } catch (e) { $("#calib-status").textContent = e.message; return; }
  list.sort((a, b) => b.id - a.id);
  const shown = list.slice(0, 30);
  const details = await Promise.all(shown.map((c) => api("GET", `/calibrations/${c.id}`).catch(() => null)));
  const body = $("#calib-table tbody");
  body.replaceChildren();
  shown.forEach((c, k) => {
    const d = details[k];
    const tr = document.createElement("tr");
    tr.dataset.id = c.id;
    tr.dataset.active = String(c.active);
    const v = d ? verdictText(c.kind, d.result) : { text: "?", ok: false };
    const cells = [c.id, c.kind, c.camera_id, c.robot_id || "", c.version,
      new Date(c.created_s * 1000).toLocaleString(), c.creator, c.note];
    for (const x of cells) { const td = document.createElement("td"); td.textContent = x; tr.append(td); }
    const vt = document.createElement("td");
    vt.textContent = v.text;
    vt.className = v.ok ? "verdict-ok" : "verdict-bad";
    tr.append(vt);
    const st = document.createElement("td");
    st.textContent = c.active ? "active" : "";
    st.className = "state";
    tr.append(st);
    const actions = document.createElement("td");
    const rep = document.createElement("button");
    rep.type = "button"; rep.textContent = "Report"; rep.className = "report";
    rep.addEventListener("click", () => showReport(c.id));
    actions.append(rep);
    if (!c.active && has("engineer")) {
      const act = document.createElement("button");
      act.type = "button"; act.textContent = "Activate"; act.className = "activate";
      act.addEventListener("click", async () => {
        try { await activate(c.id); } catch (e) { $("#calib-status").textContent = e.message; }
      });
      actions.append(act);
    }
    tr.append(actions);
    body.append(tr);
  });
  $("#calib-status").textContent = list.length ? `${list.length} calibration(s)` : "no calibrations yet";
  // Active ones, with their verdicts, on the live view.
  const summary = $("#active-summary");
  summary.replaceChildren();
  const active = shown.map((c, k) => [c, details[k]]).filter(([c]) => c.active);
  for (const [c, d] of active) {
    const div = document.createElement("div");
    div.dataset.id = c.id;
    const v = d ? verdictText(c.kind, d.result) : { text: "?", ok: false };
    div.innerHTML = "<b></b> <span></span><br><small class='muted'></small> <span></span> ";
    div.children[0].textContent = `${c.kind} #${c.id} v${c.version}`;
    div.children[1].textContent = `${c.camera_id}${c.robot_id ? " / " + c.robot_id : ""}`;
    div.children[3].textContent = d ? headline(c.kind, d.result) : "";
    div.children[4].textContent = v.text;
    div.children[4].className = v.ok ? "verdict-ok" : "verdict-bad";
    const link = document.createElement("a");
    link.href = "#"; link.textContent = "report";
    link.addEventListener("click", (e) => { e.preventDefault(); showTab("calib"); showReport(c.id); });
    div.append(" ", link);
    summary.append(div);
  }
  if (!active.length) summary.textContent = "none active";
}

// Activation of a calibration whose verdict is not ok is refused (409 verdict_not_ok) unless the
// engineer confirms, naming the problems; the forced activation is audited by the service.
async function activate(id) {
  try {
    await api("POST", `/calibrations/${id}/activate`, {});
  } catch (e) {
    if (!(e instanceof ApiError) || e.code !== "verdict_not_ok") throw e;
    if (!window.confirm(`${e.message}\n\nActivate calibration #${id} anyway?`)) {
      throw new Error(`calibration #${id} not activated: its verdict is not ok`);
    }
    await api("POST", `/calibrations/${id}/activate`, { force: true });
  }
  await refreshCalibrations();
}

async function showReport(id) {
  try {
    const html = await api("GET", `/calibrations/${id}/report`);
    $("#report-title").textContent = `calibration ${id}`;
    $("#report-frame").srcdoc = html;
    $("#report-card").hidden = false;
  } catch (e) { $("#calib-status").textContent = `report: ${e.message}`; }
}
$("#report-close").addEventListener("click", () => { $("#report-card").hidden = true; });
$("#calib-refresh").addEventListener("click", refreshCalibrations);

// ---------------------------------------------------------------- jog-to-mark wizard

const wiz = { run: 0, job: null, marks: [], recorded: new Map(), current: null, image: null, result: null };

function wizReset() {
  wiz.run += 1;
  wiz.job = null; wiz.marks = []; wiz.recorded = new Map(); wiz.current = null; wiz.result = null; wiz.image = null;
  $("#wiz-start").hidden = false;
  $("#wiz-run").hidden = true;
  $("#wiz-result").hidden = true;
  $("#wiz-error").textContent = "";
  $("#wiz-activated").textContent = "";
  $("#wiz-start-button").disabled = false;
  delete $("#wiz-run").dataset.step;
  delete $("#wiz-run").dataset.markId;
}

function wizDraw() {
  const canvas = $("#wiz-canvas");
  const ctx = canvas.getContext("2d");
  if (wiz.image) {
    canvas.width = wiz.image.width; canvas.height = wiz.image.height;
    ctx.drawImage(wiz.image, 0, 0);
  } else {
    canvas.width = 1280; canvas.height = 960;
    ctx.fillStyle = "#111"; ctx.fillRect(0, 0, canvas.width, canvas.height);
  }
  ctx.font = "bold 26px sans-serif";
  ctx.textBaseline = "middle";
  for (const m of wiz.marks) {
    const isCurrent = wiz.current && wiz.current.mark_id === m.mark_id;
    const done = wiz.recorded.has(m.step);
    const color = isCurrent ? "#f59e0b" : done ? "#22c55e" : "#38bdf8";
    ctx.strokeStyle = color; ctx.fillStyle = color;
    ctx.lineWidth = isCurrent ? 6 : 3;
    ctx.beginPath(); ctx.arc(m.u_px, m.v_px, isCurrent ? 34 : 22, 0, 2 * Math.PI); ctx.stroke();
    if (isCurrent) {
      ctx.beginPath();
      ctx.moveTo(m.u_px - 52, m.v_px); ctx.lineTo(m.u_px - 38, m.v_px);
      ctx.moveTo(m.u_px + 38, m.v_px); ctx.lineTo(m.u_px + 52, m.v_px);
      ctx.moveTo(m.u_px, m.v_px - 52); ctx.lineTo(m.u_px, m.v_px - 38);
      ctx.moveTo(m.u_px, m.v_px + 38); ctx.lineTo(m.u_px, m.v_px + 52);
      ctx.stroke();
    }
    ctx.fillText(String(m.step), m.u_px + (isCurrent ? 42 : 28), m.v_px - (isCurrent ? 30 : 22));
  }
}

function wizTable() {
  const body = $("#wiz-marks-table tbody");
  body.replaceChildren();
  for (const m of wiz.marks) {
    const tr = document.createElement("tr");
    const rec = wiz.recorded.get(m.step);
    if (wiz.current && wiz.current.step === m.step) tr.className = "current"; else if (rec) tr.className = "done";
    for (const x of [m.step, m.mark_id, `${m.row},${m.col}`, rec ? fmt(rec.x_mm, 2) : "", rec ? fmt(rec.y_mm, 2) : ""]) {
      const td = document.createElement("td"); td.textContent = x; tr.append(td);
    }
    body.append(tr);
  }
}

function wizEvent(kind, data) {
  if (kind === "progress") {
    $("#wiz-bar").style.width = `${Math.round(data.progress * 100)}%`;
    if (data.marks) wiz.marks = data.marks;
    if (data.recorded) {
      const m = wiz.marks[data.recorded - 1];
      if (m) wiz.recorded.set(m.step, { x_mm: data.x_mm, y_mm: data.y_mm });
      if (data.recorded === wiz.marks.length) {
        wiz.current = null;
        $("#wiz-step").textContent = `All ${wiz.marks.length} marks recorded`;
        $("#wiz-instruction").textContent = "Calibrating…";
      }
    }
    if (!data.recorded && !wiz.current) $("#wiz-instruction").textContent = data.message;
  } else if (kind === "input_needed") {
    wiz.current = data;
    if (data.marks) wiz.marks = data.marks;
    $("#wiz-step").textContent = `Mark ${data.step} of ${data.of}`;
    $("#wiz-instruction").textContent = `Jog the tool to mark ${data.step} (plate mark ${data.mark_id}: row ${data.row}, col ${data.col}) `
      + "and press Record.";
    $("#wiz-run").dataset.step = String(data.step);
    $("#wiz-run").dataset.markId = String(data.mark_id);
    $("#wiz-record").disabled = false;
  } else if (kind === "state") {
    $("#wiz-record").disabled = true;
  }
  wizDraw();
  wizTable();
}

async function wizStart() {
  wizReset();
  const run = wiz.run;
  $("#wiz-start-button").disabled = true;
  $("#wiz-error").textContent = "";
  try {
    // The routine takes its own shot from this pose; this one is for showing the marks on.
    $("#wiz-start-button").textContent = "Taking a picture…";
    for (let attempt = 0; attempt < 2 && !wiz.image; attempt += 1) {
      try { wiz.image = (await grabBitmap("png")).bitmap; } catch (_) { await sleep(1000); }
    }
    await waitCameraAvailable(15000);
    if (run !== wiz.run) return;
    $("#wiz-start-button").textContent = "Start";
    const job = await startRoutine("jog-to-mark", { marks: Number($("#wiz-marks").value) });
    wiz.job = job;
    $("#wiz-run").dataset.jobId = job.id;
    $("#wiz-start").hidden = true;
    $("#wiz-run").hidden = false;
    $("#wiz-step").textContent = "Looking for the marks…";
    $("#wiz-instruction").textContent = "";
    $("#wiz-record").disabled = true;
    wizDraw();
    const done = await followJob(job, wizEvent, () => run === wiz.run);
    if (run !== wiz.run) return;
    if (done.state === "succeeded") wizResult(done.result);
    else {
      $("#wiz-error").textContent = done.state === "failed" ? `The routine failed: ${done.error}` : done.message;
      $("#wiz-run").hidden = true;
      $("#wiz-start").hidden = false;
      $("#wiz-start-button").disabled = false;
    }
  } catch (e) {
    if (run !== wiz.run) return;
    $("#wiz-error").textContent = e.message;
    $("#wiz-start-button").disabled = false;
    $("#wiz-start-button").textContent = "Start";
  }
}

function wizResult(res) {
  wiz.result = res;
  $("#wiz-run").hidden = true;
  $("#wiz-result").hidden = false;
  $("#wiz-result").dataset.calibrationId = String(res.calibration_id);
  const rows = [["calibration", `#${res.calibration_id} v${res.version} (${res.kind})`], ["model", res.model],
    ["marks", res.pairs.length], ["RMS residual", `${fmt(res.rms_mm, 4)} mm`],
    ["leave-one-out RMS", Object.entries(res.loo_rms_mm || {}).map(([m, v]) => `${m} ${fmt(v, 4)}`).join(" · ") + " mm"],
    ["map σ over the marks", res.field_sigma_mm ? `rms ${fmt(res.field_sigma_mm.rms, 4)} mm, max `
      + `${fmt(res.field_sigma_mm.max, 4)} mm` : "–"]];
  const kv = $("#wiz-summary");
  kv.replaceChildren();
  for (const [k, v] of rows) {
    const tr = document.createElement("tr");
    const th = document.createElement("th"); th.textContent = k;
    const td = document.createElement("td"); td.textContent = v;
    tr.append(th, td);
    kv.append(tr);
  }
  $("#wiz-summary").dataset.rmsMm = String(res.rms_mm);
  const body = $("#wiz-residuals tbody");
  body.replaceChildren();
  res.pairs.forEach((p, k) => {
    const tr = document.createElement("tr");
    for (const x of [p.step, p.mark_id, fmt(p.u_px, 1), fmt(p.v_px, 1), fmt(p.x_mm, 2), fmt(p.y_mm, 2),
      fmt(res.residuals_mm[k], 4)]) {
      const td = document.createElement("td"); td.textContent = x; tr.append(td);
    }
    body.append(tr);
  });
  plotResiduals(res);
  $("#wiz-activate").disabled = false;
}

// Residual size at each mark's robot position: a circle whose radius grows with the residual.
function plotResiduals(res) {
  const c = $("#wiz-residual-plot");
  const ctx = c.getContext("2d");
  ctx.fillStyle = "#fff"; ctx.fillRect(0, 0, c.width, c.height);
  const xs = res.pairs.map((p) => p.x_mm), ys = res.pairs.map((p) => p.y_mm);
  const minX = Math.min(...xs), maxX = Math.max(...xs), minY = Math.min(...ys), maxY = Math.max(...ys);
  const pad = 50, span = Math.max(maxX - minX, maxY - minY, 1);
  const s = Math.min((c.width - 2 * pad) / span, (c.height - 2 * pad - 20) / span);
  const X = (x) => pad + (x - minX) * s, Y = (y) => c.height - pad - (y - minY) * s;
  const rmax = Math.max(...res.residuals_mm, 1e-9);
  const radius = (r) => 4 + 26 * r / rmax;
  ctx.fillStyle = "#1f2933"; ctx.font = "13px sans-serif";
  ctx.fillText(`residual per mark over robot x/y (largest ${fmt(rmax, 4)} mm)`, 8, 16);
  ctx.strokeStyle = "#9ca3af"; ctx.lineWidth = 1;
  ctx.strokeRect(pad - 30, 30, c.width - 2 * pad + 60, c.height - pad - 10);
  res.pairs.forEach((p, k) => {
    const r = res.residuals_mm[k];
    ctx.fillStyle = "rgba(185, 28, 28, 0.25)"; ctx.strokeStyle = "#b91c1c"; ctx.lineWidth = 2;
    ctx.beginPath(); ctx.arc(X(p.x_mm), Y(p.y_mm), radius(r), 0, 2 * Math.PI); ctx.fill(); ctx.stroke();
    ctx.fillStyle = "#1f2933";
    ctx.fillText(`${p.step}: ${fmt(r, 3)}`, X(p.x_mm) + 6, Y(p.y_mm) + 4);
  });
}

$("#wiz-start-button").addEventListener("click", wizStart);
$("#wiz-record").addEventListener("click", async () => {
  if (!wiz.job) return;
  $("#wiz-record").disabled = true;
  const step = wiz.current ? wiz.current.step : null;
  try {
    await api("POST", `/jobs/${encodeURIComponent(wiz.job.id)}/record`);
    if (wiz.current && wiz.current.step === step) {
      wiz.current = null;
      $("#wiz-instruction").textContent = `Mark ${step} recorded.`;
    }
  } catch (e) {
    $("#wiz-error").textContent = `Record: ${e.message}`;
    $("#wiz-record").disabled = false;
  }
});
$("#wiz-cancel").addEventListener("click", async () => {
  if (!wiz.job) return;
  try { await api("DELETE", `/jobs/${encodeURIComponent(wiz.job.id)}`); } catch (e) { $("#wiz-error").textContent = e.message; }
});
$("#wiz-activate").addEventListener("click", async () => {
  if (!wiz.result) return;
  $("#wiz-activate").disabled = true;
  try {
    await activate(wiz.result.calibration_id);
    $("#wiz-activated").textContent = `Calibration #${wiz.result.calibration_id} is now active.`;
  } catch (e) {
    $("#wiz-error").textContent = `Activate: ${e.message}`;
    $("#wiz-activate").disabled = false;
  }
});
$("#wiz-again").addEventListener("click", wizReset);

// ---------------------------------------------------------------- capture routines and verify

const RESULT_KEYS = [
  ["calibration_id", "calibration", (v) => `#${v}`], ["views_used", "views used"], ["stations_used", "stations used"],
  ["rms_px", "RMS", (v) => `${fmt(v, 4)} px`], ["passed", "passed", (v) => (v ? "yes" : "NO")],
  ["drift_px", "drift", (v) => `${fmt(v, 3)} px`], ["drift_mm", "drift", (v) => `${fmt(v, 3)} mm`],
  ["verdict", "verdict", (v) => (v && v.ok ? "OK" : `NOT OK: ${((v && v.problems) || []).map((p) => p.code).join(", ")}`)],
];

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
    for (const input of $$("input[name]", card)) params[input.name] = Number(input.value);
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

// ---------------------------------------------------------------- pick test

async function refreshRecipes() {
  if (!state.token) return;
  try {
    const recipes = await api("GET", "/recipes");
    $("#pick-recipes").textContent = recipes.length
      ? `recipes: ${recipes.map((r) => `${r.recipe_id} ${r.name} (v${r.version})`).join(", ")}` : "no recipes stored yet";
  } catch (e) { $("#pick-recipes").textContent = e.message; }
}

$("#pick-form").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  const button = $("#pick-button");
  button.disabled = true;
  $("#pick-error").textContent = "";
  $("#pick-status").textContent = "picking…";
  try {
    const body = { recipe_id: Number($("#pick-recipe").value), move: has("engineer") && $("#pick-move").checked };
    const answer = await api("POST", "/pick", body);
    state.lastPick = answer;
    $("#pick-status").textContent = `${answer.picks.length} pick(s) · frame ${answer.frame_id} · calibration `
      + `${answer.calibration.kind} #${answer.calibration.id} · ${fmt(answer.latency_ms.total, 0)} ms`
      + (answer.moved ? " · robot moved to the best pick" : "");
    const tbody = $("#pick-table tbody");
    tbody.replaceChildren();
    answer.picks.forEach((p, k) => {
      const tr = document.createElement("tr");
      const pp = p.pick_pose || {};
      const sig = (p.uncertainty && p.uncertainty.sigma_mm) || [];
      const cells = [k + 1, p.part, fmt(p.u_px, 1), fmt(p.v_px, 1), fmt(p.score, 3), fmt(pp.x_mm, 2), fmt(pp.y_mm, 2),
        fmt(pp.z_mm, 2), fmt(p.part_yaw_deg, 2), sig.length ? fmt(Math.max(sig[0], sig[1]), 3) : "–",
        p.reachable ? "yes" : `no: ${p.not_reachable_reason}`];
      for (const x of cells) { const td = document.createElement("td"); td.textContent = x; tr.append(td); }
      tr.lastChild.className = p.reachable ? "reach-yes" : "reach-no";
      tbody.append(tr);
    });
    $("#pick-table").hidden = false;
    const r = await api("GET", answer.image_url, undefined, { raw: true });
    if (state.pickUrl) URL.revokeObjectURL(state.pickUrl);
    state.pickUrl = URL.createObjectURL(await r.blob());
    $("#pick-image").src = state.pickUrl;
    $("#pick-image").hidden = false;
  } catch (e) {
    $("#pick-error").textContent = e.message;
    $("#pick-status").textContent = "";
  } finally {
    button.disabled = false;
  }
});

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
