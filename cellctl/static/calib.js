// Calibrations tab: the stored calibrations, their verdicts and reports, guarded activation.
import { $, ApiError, api, fmt, has, showTab, state } from "./core.js";

// ---------------------------------------------------------------- calibrations

export function verdictText(kind, result) {
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

export async function refreshCalibrations() {
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
export async function activate(id) {
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

let reportUrl = null;  // the shown report as a page of its own (Full page): no token needed to open it

async function showReport(id) {
  try {
    const html = await api("GET", `/calibrations/${id}/report`);
    $("#report-title").textContent = `calibration ${id}`;
    $("#report-frame").srcdoc = html;
    $("#report-card").hidden = false;
    if (reportUrl) URL.revokeObjectURL(reportUrl);
    reportUrl = URL.createObjectURL(new Blob([html], { type: "text/html" }));
  } catch (e) { $("#calib-status").textContent = `report: ${e.message}`; }
}
$("#report-close").addEventListener("click", () => { $("#report-card").hidden = true; });
$("#report-full").addEventListener("click", () => { if (reportUrl) window.open(reportUrl, "_blank", "noopener"); });
$("#calib-refresh").addEventListener("click", refreshCalibrations);

document.addEventListener("cellctl:tab", (e) => { if (e.detail === "calib") refreshCalibrations(); });
