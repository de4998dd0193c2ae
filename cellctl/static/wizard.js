// Jog-to-mark tab: the wizard that walks the operator from mark to mark, then shows the fit.
import { $, $$, api, fmt, grabBitmap, sleep, startRoutine, followJob, state, waitCameraAvailable } from "./core.js";
import { activate } from "./calib.js";

// ---------------------------------------------------------------- jog-to-mark wizard

const wiz = { run: 0, job: null, marks: [], recorded: new Map(), current: null, image: null, result: null };

// Built here rather than in index.html: the tool-centre option (engineer: it moves the robot) and
// the verdict block of the result.
const tcpLabel = document.createElement("label");
tcpLabel.dataset.minRole = "engineer";
tcpLabel.title = "after the marks, the robot turns the tool at one mark so a fixed camera can find the tool centre";
tcpLabel.innerHTML = '<input type="checkbox" id="wiz-tool-centre"> then turn the tool for the tool centre';
$("#wiz-start-button").before(tcpLabel, " ");
const verdictBox = document.createElement("div");
verdictBox.id = "wiz-verdict";
$("#wiz-summary").before(verdictBox);

function wizReset() {
  wiz.run += 1;
  wiz.job = null; wiz.marks = []; wiz.recorded = new Map(); wiz.current = null; wiz.result = null; wiz.image = null;
  $("#wiz-start").hidden = false;
  $("#wiz-run").hidden = true;
  $("#wiz-result").hidden = true;
  $("#wiz-error").textContent = "";
  $("#wiz-activated").textContent = "";
  showVerdict(null);
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
    const params = { marks: Number($("#wiz-marks").value) };
    if ($("#wiz-tool-centre").checked) params.tool_centre = true;
    const job = await startRoutine("jog-to-mark", params);
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
  const tc = res.tool_centre;
  if (tc) {
    const ax = tc.uncertainty.offset_axes_mm;
    rows.push(["tool centre offset", `dx ${fmt(tc.offset_mm[0], 3)} ± ${fmt(ax[0], 3)}, dy ${fmt(tc.offset_mm[1], 3)} `
      + `± ${fmt(ax[1], 3)} mm (base-aligned at the mark's orientation)`],
    ["tool centre fit", `${tc.rotations.length} angles over ${fmt(tc.positions[0].arc_deg, 0)}°, RMS ${fmt(tc.rms_mm, 4)} mm`]);
  }
  showVerdict(res.verdict);
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

// The N-point verdict (calibration/npoint/verdict.py): OK, or NOT OK with each problem's advice.
function showVerdict(v) {
  verdictBox.replaceChildren();
  if (!v) return;
  verdictBox.dataset.ok = String(v.ok);
  const head = document.createElement("p");
  head.className = v.ok ? "verdict-ok" : "verdict-bad";
  head.textContent = v.ok ? `Verdict: OK — leave-one-out RMS ${fmt(v.loo_rms_mm, 3)} mm (limit ${v.loo_limit_mm} mm), `
    + `${v.marks} marks over ${fmt(100 * v.hull_fraction, 1)} % of the image`
    : "Verdict: NOT OK — what to do:";
  verdictBox.append(head);
  const items = [...(v.problems || []).map((p) => [p, "problem"]), ...(v.advice || []).map((p) => [p, "advice"])];
  if (!items.length) return;
  const ul = document.createElement("ul");
  for (const [p, kind] of items) {
    const li = document.createElement("li");
    li.className = kind;
    const b = document.createElement("b"); b.textContent = kind === "advice" ? `${p.code} (advice)` : p.code;
    li.append(b, `: ${p.message}`);
    ul.append(li);
  }
  verdictBox.append(ul);
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

// Jog buttons (engineer): a checked linear move of the tool by one step along a base axis, keeping
// its orientation; one at a time (a second click while moving is refused by the service: 409).
const JOG_SPEED_M_S = 0.02;
for (const b of $$("#wiz-jog button")) {
  b.addEventListener("click", async () => {
    const axis = Number(b.dataset.axis), step = Number(b.dataset.sign) * Number($("#jog-step").value) * 1e-3;
    const buttons = $$("#wiz-jog button");
    for (const x of buttons) x.disabled = true;
    try {
      const s = await api("GET", `/robots/${encodeURIComponent(state.robotId)}/state`);
      const pose = { ...s.pose_ur };
      pose[["x_m", "y_m", "z_m"][axis]] += step;
      await api("POST", `/robots/${encodeURIComponent(state.robotId)}/move`, { pose_ur: pose, speed_m_s: JOG_SPEED_M_S });
      $("#jog-status").textContent = `tool at x ${fmt(pose.x_m * 1e3, 1)}, y ${fmt(pose.y_m * 1e3, 1)}, z ${fmt(pose.z_m * 1e3, 1)} mm`;
    } catch (e) {
      $("#jog-status").textContent = `jog refused: ${e.message}`;
    } finally {
      for (const x of buttons) x.disabled = false;
    }
  });
}
