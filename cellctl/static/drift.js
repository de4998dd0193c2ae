// The drift card of the Production tab: the cell's drift state and a small chart of the last checks'
// drift_mm with the chart's centre and 3-sigma limits (an inline SVG), refreshed every 2 s while the tab is
// shown. A cell without drift checks answers state "off" (GET /drift?none_ok=true) and the card says so.
import { $, api, fmt, state } from "./core.js";

const PERIOD_MS = 2000;
const SHOWN = 60;
const W = 320, H = 120, PAD = 6;
const SVG = "http://www.w3.org/2000/svg";

function el(name, attrs) {
  const e = document.createElementNS(SVG, name);
  for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, String(v));
  return e;
}

export function chart(records, limits) {
  const pts = records.filter((r) => r.drift_mm !== null && r.drift_mm !== undefined).slice(-SHOWN);
  const svg = el("svg", { viewBox: `0 0 ${W} ${H}`, width: W, height: H, role: "img",
    "aria-label": "drift_mm of the last checks with the chart's limits" });
  svg.append(el("rect", { x: 0, y: 0, width: W, height: H, fill: "#111827" }));
  if (!pts.length) return svg;
  const values = pts.map((r) => r.drift_mm);
  const lines = limits ? [limits.center_mm, limits.ucl_mm, Math.max(0, limits.lcl_mm)] : [];
  const lo = Math.min(0, ...values, ...lines), hi = Math.max(...values, ...lines) * 1.1 || 1;
  const x = (i) => PAD + (W - 2 * PAD) * (pts.length > 1 ? i / (pts.length - 1) : 0.5);
  const y = (v) => H - PAD - (H - 2 * PAD) * (v - lo) / (hi - lo);
  if (limits) {
    for (const [v, cls] of [[limits.ucl_mm, "ucl"], [limits.center_mm, "center"], [limits.lcl_mm, "lcl"]]) {
      if (v < lo) continue;
      svg.append(el("line", { x1: PAD, x2: W - PAD, y1: y(v), y2: y(v), class: `drift-${cls}`,
        stroke: cls === "center" ? "#9ca3af" : "#f59e0b", "stroke-dasharray": cls === "center" ? "" : "4 3" }));
    }
  }
  svg.append(el("polyline", { points: pts.map((r, i) => `${x(i)},${y(r.drift_mm)}`).join(" "), fill: "none",
    stroke: "#60a5fa", "stroke-width": 1.5 }));
  pts.forEach((r, i) => {
    const c = el("circle", { cx: x(i), cy: y(r.drift_mm), r: 2.5, class: `drift-point drift-${r.state}`,
      fill: r.state === "alarm" ? "#ef4444" : (r.state === "baseline" ? "#9ca3af" : "#60a5fa") });
    const t = el("title", {});
    t.textContent = `${r.drift_mm.toFixed(3)} mm, ${r.drift_deg === null ? "–" : r.drift_deg.toFixed(4)} deg`
      + ` (${r.state}${r.rule ? `: ${r.rule}` : ""})`;
    c.append(t);
    svg.append(c);
  });
  return svg;
}

async function refresh() {
  try {
    const d = await api("GET", `/drift?none_ok=true&limit=${SHOWN}`);
    const badge = $("#drift-state");
    badge.textContent = d.state;
    badge.className = `badge${d.state === "alarm" ? " bad" : (d.state === "ok" ? " ok" : "")}`;
    const last = d.records.length ? d.records[d.records.length - 1] : null;
    $("#drift-last").textContent = last && last.drift_mm !== null
      ? `last: ${fmt(last.drift_mm, 3)} mm, ${fmt(last.drift_deg, 4)} deg${last.rule ? ` (${last.rule})` : ""}`
      : (d.state === "off" ? "no drift checks configured (docs/drift.md)" : "no check yet");
    const lim = d.limits && d.limits.ucl_mm !== null ? d.limits : null;
    $("#drift-limits").textContent = lim ? `centre ${fmt(lim.center_mm, 3)} mm, UCL ${fmt(lim.ucl_mm, 3)} mm` : "";
    $("#drift-chart").replaceChildren(chart(d.records, lim));
  } catch (e) {
    $("#drift-last").textContent = `${e.code}: ${e.message}`;
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
