// The PLC tab: the plant's front ends as GET /plc/status shows them (Modbus, OPC UA, EtherNet/IP, the robot
// socket): enabled, address, connected clients, requests, the last request and its answer, refreshed every
// two seconds while shown. A service without the route (404) says so instead of failing.
import { $, api, sleep, state } from "./core.js";

const PERIOD_MS = 2000;

const compact = (v) => (v === null || v === undefined ? "–" : typeof v === "object" ? JSON.stringify(v) : String(v));

function answerText(a) {
  if (!a) return "–";
  if (a.ok === false) return `error ${a.error_class ?? ""}: ${a.message || ""}`.trim();
  const parts = ["ok"];
  if (a.picks !== undefined) parts.push(`${a.picks} pick(s)`);
  if (a.latency_ms !== undefined) parts.push(`${Number(a.latency_ms).toFixed(1)} ms`);
  return parts.join(" · ");
}

export function showPlc(status) {
  const fronts = status.front_ends || {};
  const names = Object.keys(fronts);
  const enabled = names.filter((n) => fronts[n].enabled);
  const badge = $("#plc-badge");
  badge.textContent = enabled.length ? (status.busy ? "busy" : "ready") : "no front end enabled";
  badge.className = `badge ${enabled.length ? "ok" : ""}`;
  $("#plc-summary").textContent = `motion from the PLC ${status.allow_motion ? "allowed" : "not allowed"}`
    + (status.running ? ` · running: ${compact(status.running)}` : "")
    + ` · ${enabled.length} of ${names.length} front ends enabled`;
  $("#plc-table tbody").replaceChildren(...names.map((n) => {
    const f = fronts[n];
    const tr = document.createElement("tr");
    tr.dataset.frontEnd = n;
    for (const x of [n, f.enabled ? "yes" : "no", f.address || "–", f.clients ?? 0, f.requests ?? 0, f.refused_busy ?? 0,
      compact(f.last_request), answerText(f.last_answer)]) {
      const td = document.createElement("td"); td.textContent = String(x); tr.append(td);
    }
    return tr;
  }));
  $("#plc-error").textContent = "";
}

async function refresh() {
  try {
    showPlc(await api("GET", "/plc/status"));
  } catch (e) {
    $("#plc-badge").textContent = "unknown";
    $("#plc-badge").className = "badge";
    $("#plc-error").textContent = e.status === 404
      ? "This service does not report its PLC front ends (GET /plc/status: 404); see docs/plc-modbus.md."
      : `PLC status: ${e.message}`;
  }
}

async function loop(session) {
  while (state.session === session && state.tab === "plc") {
    await refresh();
    await sleep(PERIOD_MS);
  }
}

document.addEventListener("cellctl:tab", (ev) => { if (ev.detail === "plc") loop(state.session); });
