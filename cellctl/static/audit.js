// The Audit tab (engineer): the audit log (GET /audit), newest first, filtered on the page by robot (the
// entry's target or a robot named in its detail), who (the token's name) and what (the action, e.g.
// robot.move, recipe.): the last 2000 entries are fetched and filtered here.
import { $, api, state } from "./core.js";

const LIMIT = 2000;

function matches(e, robot, who, what) {
  if (who && !e.who.toLowerCase().includes(who)) return false;
  if (what && !e.action.toLowerCase().startsWith(what)) return false;
  if (robot) {
    const detail = e.detail || {};
    const named = [e.target, detail.robot_id, detail.robot].map((x) => String(x ?? "").toLowerCase());
    if (!named.includes(robot) && !JSON.stringify(detail).toLowerCase().includes(`"${robot}"`)) return false;
  }
  return true;
}

let asked = 0;  // only the newest request's answer is shown (an older one may arrive after it)

export async function refreshAudit() {
  if (!state.token) return;
  const mine = ++asked;
  const robot = $("#audit-robot").value.trim().toLowerCase();
  const who = $("#audit-who").value.trim().toLowerCase();
  const what = $("#audit-what").value.trim().toLowerCase();
  try {
    const entries = await api("GET", `/audit?limit=${LIMIT}`);
    if (mine !== asked) return;
    const shown = entries.filter((e) => matches(e, robot, who, what));
    $("#audit-table tbody").replaceChildren(...shown.slice(0, 500).map((e) => {
      const tr = document.createElement("tr");
      for (const x of [new Date(e.at_s * 1000).toLocaleString(), e.who, e.action, e.target, e.result,
        JSON.stringify(e.detail, (_, v) => (typeof v === "number" && !Number.isInteger(v) ? Number(v.toFixed(4)) : v))]) {
        const td = document.createElement("td"); td.textContent = String(x ?? ""); tr.append(td);
      }
      tr.lastChild.className = "detail";
      return tr;
    }));
    $("#audit-count").textContent = `${shown.length} of the last ${entries.length} entries`
      + (robot || who || what ? ` (robot "${robot}", who "${who}", what "${what}")` : "")
      + (shown.length > 500 ? " (the newest 500 shown)" : "");
  } catch (e) { $("#audit-count").textContent = `audit: ${e.message}`; }
}

$("#audit-refresh").addEventListener("click", refreshAudit);
for (const id of ["#audit-robot", "#audit-who", "#audit-what"]) {
  $(id).addEventListener("keydown", (ev) => { if (ev.key === "Enter") refreshAudit(); });
}
document.addEventListener("cellctl:tab", (ev) => { if (ev.detail === "audit") refreshAudit(); });
