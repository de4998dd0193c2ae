// The Recipes tab: list the stored recipes, edit one (name, models, search thresholds, the place section of
// each kind, the gripper and its device and grip check), save the edit as a new version (never over one),
// list its versions and roll back to one, duplicate it under a new number, delete it (engineer).
// Every save is a new version; rolling back stores the old version's data as the newest (REST: docs/rest.md).
import { $, api, has, state } from "./core.js";

const ed = { id: null, data: null };

const text = (el, s) => { el.textContent = s; return el; };
const cell = (tr, s) => tr.append(text(document.createElement("td"), s));
const setVal = (sel, v) => { $(sel).value = v === null || v === undefined ? "" : String(v); };
const num = (sel) => ($(sel).value === "" ? null : Number($(sel).value));
const when = (s) => new Date(s * 1000).toLocaleString();

function poseText(p) { return p ? p.map((x) => Number(x.toFixed(6))).join(",") : ""; }

function poseOf(sel) {
  const raw = $(sel).value.trim();
  const p = raw.split(",").map((x) => Number(x.trim()));
  if (p.length !== 6 || p.some((x) => !Number.isFinite(x))) {
    throw new Error(`${$(sel).closest("label").textContent.trim()}: six numbers x,y,z (m), rx,ry,rz (rad)`);
  }
  return p;
}

function message(ok, bad) {
  $("#re-status").textContent = ok || "";
  $("#re-error").textContent = bad || "";
}

export async function refreshRecipeList(select) {
  if (!state.token) return;
  try {
    const recipes = await api("GET", "/recipes");
    const tbody = $("#recipes-table tbody");
    tbody.replaceChildren(...recipes.map((r) => {
      const tr = document.createElement("tr");
      tr.dataset.recipe = String(r.recipe_id);
      for (const s of [r.recipe_id, r.name, r.version, r.place || "–", r.gripper_device || "–"]) cell(tr, String(s));
      tr.addEventListener("click", () => openRecipe(r.recipe_id));
      tr.style.cursor = "pointer";
      if (r.recipe_id === ed.id) tr.className = "current";
      return tr;
    }));
    $("#recipes-empty").hidden = recipes.length > 0;
    const keep = select ?? ed.id;
    if (keep !== null && recipes.some((r) => r.recipe_id === keep)) await openRecipe(keep);
    else { ed.id = null; $("#recipe-editor").hidden = true; }
  } catch (e) { message("", e.message); }
}

async function openRecipe(id) {
  const [r, versions] = await Promise.all([api("GET", `/recipes/${id}`), api("GET", `/recipes/${id}/versions`)]);
  ed.id = id;
  ed.data = r.data;
  for (const tr of document.querySelectorAll("#recipes-table tbody tr")) {
    tr.className = tr.dataset.recipe === String(id) ? "current" : "";
  }
  $("#recipe-editor").hidden = false;
  $("#re-title").textContent = `${id} · version ${r.version} in force`;
  fill(r.data);
  showVersions(id, versions);
}

function fill(d) {
  setVal("#re-name", d.name);
  setVal("#re-plane-z", d.plane_z_mm); setVal("#re-grasp-z", d.grasp_z_mm);
  setVal("#re-grasp-xy", (d.grasp_offset_mm || [0, 0]).join(",")); setVal("#re-grasp-yaw", d.grasp_yaw_deg ?? 0);
  setVal("#re-approach", d.approach_height_mm); setVal("#re-speed", d.speed_m_s);
  const ul = $("#re-models");
  ul.replaceChildren(...d.models.map((m, k) => {
    const li = text(document.createElement("li"), `${m.name || "part"} (${m.mode || "shape"}) `);
    const b = text(document.createElement("button"), "remove");
    b.type = "button"; b.dataset.minRole = "engineer"; b.hidden = !has("engineer") || d.models.length < 2;
    b.addEventListener("click", () => { ed.data = { ...ed.data, models: ed.data.models.filter((_, j) => j !== k) }; fill(ed.data); });
    li.append(b);
    return li;
  }));
  const s = d.search || {};
  setVal("#re-min-score", s.min_score); setVal("#re-max-count", s.max_count); setVal("#re-timeout", s.timeout_s);
  setVal("#re-angle-start", s.angle_start_deg); setVal("#re-angle-extent", s.angle_extent_deg);
  const p = d.place || {};
  setVal("#re-place-kind", p.kind || "");
  setVal("#re-place-approach", p.approach_height_mm);
  setVal("#re-fixed-pose", poseText(p.kind === "fixed" ? p.pose_ur : null));
  setVal("#re-grid-origin", poseText(p.kind === "grid" ? p.origin_ur : null));
  setVal("#re-grid-rows", p.kind === "grid" ? p.rows : 1); setVal("#re-grid-cols", p.kind === "grid" ? p.cols : 1);
  setVal("#re-grid-px", p.kind === "grid" ? p.pitch_mm[0] : 0); setVal("#re-grid-py", p.kind === "grid" ? p.pitch_mm[1] : 0);
  setVal("#re-grid-layers", p.layers ?? 1); setVal("#re-grid-layer-mm", p.layer_mm ?? 0);
  setVal("#re-loc-plane-z", p.kind === "located" ? p.plane_z_mm : null);
  setVal("#re-loc-min-score", p.kind === "located" ? p.min_score : 0.6);
  setVal("#re-loc-origin", poseText(p.kind === "located" ? p.origin_ur : null));
  setVal("#re-loc-rows", p.kind === "located" ? p.rows : 1); setVal("#re-loc-cols", p.kind === "located" ? p.cols : 1);
  $("#re-loc-model").textContent = p.kind === "located" ? `fixture model: ${p.model.name || "taught"}`
    : "a located place needs its fixture taught (POST /pick/teach) and stored through REST";
  showPlaceKind();
  const g = d.gripper || {};
  setVal("#re-grip-open", g.open_width_mm); setVal("#re-grip-close", g.grip_width_mm); setVal("#re-grip-force", g.force_n);
  const dev = g.device || {};
  setVal("#re-dev-io", dev.io_id); setVal("#re-dev-kind", dev.kind || "robotiq_2f");
  setVal("#re-dev-stroke", dev.stroke_mm); setVal("#re-dev-tol", dev.width_tolerance_mm);
  setVal("#re-dev-input", dev.input); setVal("#re-dev-output", dev.output);
  setVal("#re-dev-retries", dev.retries); setVal("#re-dev-clearance", dev.clearance_mm);
  for (const el of document.querySelectorAll("#re-form input, #re-form select")) el.disabled = !has("engineer");
  message("", "");
}

function showPlaceKind() {
  const kind = $("#re-place-kind").value;
  for (const k of ["fixed", "grid", "located"]) $(`#re-place-${k}`).hidden = kind !== k;
}
$("#re-place-kind").addEventListener("change", showPlaceKind);

function dropNulls(o) { return Object.fromEntries(Object.entries(o).filter(([, v]) => v !== null && v !== undefined)); }

// The edited recipe: the stored data with the form's fields over it (what the form does not show is kept).
function edited() {
  const d = structuredClone(ed.data);
  d.name = $("#re-name").value;
  d.plane_z_mm = num("#re-plane-z");
  d.grasp_z_mm = num("#re-grasp-z") ?? 0;
  const xy = $("#re-grasp-xy").value.split(",").map((x) => Number(x.trim()));
  if (xy.length !== 2 || xy.some((x) => !Number.isFinite(x))) throw new Error("grasp x, y: two numbers in mm, e.g. 0,-9");
  d.grasp_offset_mm = xy;
  d.grasp_yaw_deg = num("#re-grasp-yaw") ?? 0;
  d.approach_height_mm = num("#re-approach") ?? 50;
  if (num("#re-speed") !== null) d.speed_m_s = num("#re-speed");
  d.search = { ...(d.search || {}), ...dropNulls({ min_score: num("#re-min-score"), max_count: num("#re-max-count"),
    timeout_s: num("#re-timeout"), angle_start_deg: num("#re-angle-start"), angle_extent_deg: num("#re-angle-extent") }) };
  const kind = $("#re-place-kind").value;
  const approach = num("#re-place-approach");
  if (!kind) d.place = null;
  else if (kind === "fixed") d.place = { kind, pose_ur: poseOf("#re-fixed-pose"), approach_height_mm: approach };
  else if (kind === "grid") {
    d.place = { kind, origin_ur: poseOf("#re-grid-origin"), rows: num("#re-grid-rows") ?? 1, cols: num("#re-grid-cols") ?? 1,
      pitch_mm: [num("#re-grid-px") ?? 0, num("#re-grid-py") ?? 0], layers: num("#re-grid-layers") ?? 1,
      layer_mm: num("#re-grid-layer-mm") ?? 0, approach_height_mm: approach };
  } else {
    const old = ed.data.place && ed.data.place.kind === "located" ? ed.data.place : null;
    if (!old) throw new Error("a located place needs its fixture's model: teach it and store the recipe through REST");
    d.place = { ...old, plane_z_mm: num("#re-loc-plane-z"), min_score: num("#re-loc-min-score") ?? 0.6,
      origin_ur: poseOf("#re-loc-origin"), rows: num("#re-loc-rows") ?? 1, cols: num("#re-loc-cols") ?? 1,
      approach_height_mm: approach };
  }
  d.gripper = { ...(d.gripper || {}), open_width_mm: num("#re-grip-open"), grip_width_mm: num("#re-grip-close"),
    force_n: num("#re-grip-force") };
  const io = $("#re-dev-io").value.trim();
  d.gripper.device = io ? dropNulls({ ...(d.gripper.device || {}), io_id: io, kind: $("#re-dev-kind").value,
    stroke_mm: num("#re-dev-stroke"), width_tolerance_mm: num("#re-dev-tol"), input: num("#re-dev-input"),
    output: num("#re-dev-output"), retries: num("#re-dev-retries"), clearance_mm: num("#re-dev-clearance") }) : null;
  return d;
}

$("#re-form").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  try {
    const r = await api("POST", "/recipes", { recipe_id: ed.id, recipe: edited() });
    message(`recipe ${r.recipe_id} saved as version ${r.version}`);
    await refreshRecipeList(r.recipe_id);
    message(`recipe ${r.recipe_id} saved as version ${r.version}`);
  } catch (e) { message("", `save: ${e.message}`); }
});

$("#re-dup").addEventListener("click", async () => {
  const to = num("#re-dup-id");
  if (to === null) { message("", "duplicate: give the new recipe's number"); return; }
  try {
    const r = await api("POST", `/recipes/${ed.id}/duplicate`, { new_recipe_id: to });
    await refreshRecipeList(r.recipe_id);
    message(`recipe ${ed.id === r.recipe_id ? r.from_recipe : ed.id} duplicated as recipe ${r.recipe_id}`);
  } catch (e) { message("", `duplicate: ${e.message}`); }
});

$("#re-delete").addEventListener("click", async () => {
  const id = ed.id;
  if (!window.confirm(`Delete recipe ${id} and all its versions? (audited; a running production refuses it)`)) return;
  try {
    const r = await api("DELETE", `/recipes/${id}`);
    ed.id = null;
    await refreshRecipeList();
    message("", "");
    $("#recipes-empty").hidden = false;
    $("#recipes-empty").textContent = `recipe ${id} deleted (${r.deleted_versions} versions)`;
  } catch (e) { message("", `delete: ${e.message}`); }
});

function showVersions(id, versions) {
  const tbody = $("#re-versions tbody");
  tbody.replaceChildren(...versions.map((v) => {
    const tr = document.createElement("tr");
    tr.dataset.version = String(v.version);
    for (const s of [v.version, when(v.created_s), v.creator, v.place || "–", v.models]) cell(tr, String(s));
    const td = document.createElement("td");
    if (v.active) td.textContent = "in force";
    else if (has("engineer")) {
      const b = text(document.createElement("button"), "Roll back to this");
      b.type = "button";
      b.addEventListener("click", async () => {
        try {
          const r = await api("POST", `/recipes/${id}/versions/${v.version}/activate`);
          await refreshRecipeList(id);
          message(`recipe ${id}: version ${r.from_version} is in force again, as version ${r.version}`);
        } catch (e) { message("", `roll back: ${e.message}`); }
      });
      td.append(b);
    }
    tr.append(td);
    if (v.active) tr.className = "current";
    return tr;
  }));
}

$("#recipes-refresh").addEventListener("click", () => refreshRecipeList());
document.addEventListener("cellctl:tab", (e) => { if (e.detail === "recipes") refreshRecipeList(); });

