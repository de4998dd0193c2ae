// Pick tab: teach a part on a live picture (draw its region, preview the model's edges), store it
// as a named recipe with its capture pose (read from the robot) and gripper settings, test a pick.
import { $, api, fmt, grabBitmap, has, state } from "./core.js";

const teach = { image: null, roi: null, drag: null, model: null, preview: null, pose: null, grasp: null };

// ---------------------------------------------------------------- teach: picture and region

function teachDraw() {
  const c = $("#teach-canvas");
  const ctx = c.getContext("2d");
  if (teach.image) {
    c.width = teach.image.width; c.height = teach.image.height;
    ctx.drawImage(teach.image, 0, 0);
  } else {
    ctx.fillStyle = "#111"; ctx.fillRect(0, 0, c.width, c.height);
  }
  const r = teach.drag || teach.roi;
  if (r) {
    // The ROI spans pixel coordinates (U, V) to (U + W, V + H); pixel (0, 0)'s centre is at canvas (0.5, 0.5).
    ctx.strokeStyle = "#f59e0b"; ctx.lineWidth = 3; ctx.setLineDash([10, 6]);
    ctx.strokeRect(r[0] + 0.5, r[1] + 0.5, r[2], r[3]);
    ctx.setLineDash([]);
    const cx = r[0] + r[2] / 2 + 0.5, cy = r[1] + r[3] / 2 + 0.5;
    ctx.beginPath(); ctx.moveTo(cx - 12, cy); ctx.lineTo(cx + 12, cy); ctx.moveTo(cx, cy - 12); ctx.lineTo(cx, cy + 12);
    ctx.stroke();
  }
  if (teach.preview && !teach.drag) {
    ctx.strokeStyle = "#22c55e"; ctx.lineWidth = 2;
    ctx.beginPath();
    for (const [[u0, v0], [u1, v1]] of teach.preview.edges_px) { ctx.moveTo(u0 + 0.5, v0 + 0.5); ctx.lineTo(u1 + 0.5, v1 + 0.5); }
    ctx.stroke();
  }
  if (teach.grasp && !teach.drag) drawGrasp(ctx, teach.grasp);
}

// The recipe's grasp (POST /pick/grasp, image pixels): the closing line between the open fingers, each finger a
// bar across it, the gripper centre, and where the fingers meet the part (red when the grasp is refused).
function drawGrasp(ctx, g) {
  const [[u0, v0], [u1, v1]] = g.fingers_px;
  const n = Math.hypot(u1 - u0, v1 - v0) || 1, pu = -(v1 - v0) / n * 10, pv = (u1 - u0) / n * 10;
  ctx.strokeStyle = g.problem ? "#ef4444" : "#3b82f6"; ctx.lineWidth = 2; ctx.setLineDash([6, 4]);
  ctx.beginPath(); ctx.moveTo(u0 + 0.5, v0 + 0.5); ctx.lineTo(u1 + 0.5, v1 + 0.5); ctx.stroke();
  ctx.setLineDash([]); ctx.lineWidth = 6;
  ctx.beginPath();
  for (const [u, v] of g.fingers_px) { ctx.moveTo(u - pu + 0.5, v - pv + 0.5); ctx.lineTo(u + pu + 0.5, v + pv + 0.5); }
  ctx.stroke();
  ctx.lineWidth = 2;
  ctx.beginPath(); ctx.arc(g.centre_px[0] + 0.5, g.centre_px[1] + 0.5, 6, 0, 2 * Math.PI); ctx.stroke();
  ctx.fillStyle = g.problem ? "#ef4444" : "#3b82f6";
  for (const [u, v] of g.contacts_px || []) { ctx.beginPath(); ctx.arc(u + 0.5, v + 0.5, 4, 0, 2 * Math.PI); ctx.fill(); }
}

const numOr = (sel, d) => ($(sel).value === "" ? d : Number($(sel).value));

// The recipe the teach card would save (without the kept place section and device of an existing number).
function draftRecipe() {
  return {
    name: $("#recipe-name").value || "part", models: [teach.model], camera_id: state.cameraId, robot_id: state.robotId,
    plane_z_mm: numOr("#recipe-plane-z", null), grasp_z_mm: numOr("#recipe-grasp-z", 0),
    approach_height_mm: numOr("#recipe-approach", 50), capture_pose_ur: teach.pose,
    grasp_offset_mm: [numOr("#grasp-x", 0), numOr("#grasp-y", 0)], grasp_yaw_deg: numOr("#grasp-yaw", 0),
    gripper: { open_width_mm: numOr("#grip-open", null), grip_width_mm: numOr("#grip-close", null),
      force_n: numOr("#grip-force", null) },
  };
}

let graspTimer = null, graspAsk = 0;
function showGrasp() {
  clearTimeout(graspTimer);
  graspTimer = setTimeout(async () => {
    if (!teach.model) return;
    const ask = ++graspAsk;
    try {
      const r = await api("POST", "/pick/grasp", { recipe: draftRecipe() });
      if (ask !== graspAsk) return;  // a newer edit asked again
      teach.grasp = r.grasps[0] || null;
      const g = teach.grasp;
      $("#teach-grasp").className = g && g.problem ? "error" : "muted";
      $("#teach-grasp").textContent = !g ? (r.unavailable || "not drawn")
        : (g.problem || `the fingers open ${fmt(g.open_mm, 1)} mm and close on `
          + `${g.material_mm === null ? "?" : fmt(g.material_mm, 1)} mm of part along ${fmt(g.closing_deg, 0)}° on screen`);
      $("#teach-canvas").dataset.grasp = g ? g.fingers_px.flat().map((x) => x.toFixed(1)).join(",") : "";
    } catch (e) {
      if (ask !== graspAsk) return;
      teach.grasp = null;
      $("#teach-grasp").className = "error";
      $("#teach-grasp").textContent = e.message;
    }
    teachDraw();
  }, 200);
}
for (const id of ["#grasp-x", "#grasp-y", "#grasp-yaw", "#grip-open", "#grip-close", "#recipe-plane-z"]) {
  $(id).addEventListener("input", showGrasp);
}

function imagePoint(ev) {
  const c = $("#teach-canvas");
  const rect = c.getBoundingClientRect();
  const x = (ev.clientX - rect.left) * c.width / rect.width, y = (ev.clientY - rect.top) * c.height / rect.height;
  return [Math.max(-0.5, Math.min(c.width - 0.5, x - 0.5)), Math.max(-0.5, Math.min(c.height - 0.5, y - 0.5))];
}

function setRoi(roi) {
  teach.roi = roi;
  teach.model = null; teach.preview = null; teach.grasp = null;
  $("#recipe-form").hidden = true;
  $("#teach-button").disabled = !roi;
  $("#teach-roi").textContent = roi ? `region U ${fmt(roi[0], 0)}, V ${fmt(roi[1], 0)}, W ${fmt(roi[2], 0)}, H ${fmt(roi[3], 0)} px`
    : "no region drawn";
  $("#teach-canvas").dataset.roi = roi ? roi.map((x) => x.toFixed(1)).join(",") : "";
  teachDraw();
}

$("#teach-canvas").addEventListener("pointerdown", (ev) => {
  if (!teach.image) return;
  const [u, v] = imagePoint(ev);
  teach.drag = [u, v, 0, 0];
  teach.start = [u, v];
  $("#teach-canvas").setPointerCapture(ev.pointerId);
});
$("#teach-canvas").addEventListener("pointermove", (ev) => {
  if (!teach.drag) return;
  const [u, v] = imagePoint(ev);
  const [u0, v0] = teach.start;
  teach.drag = [Math.min(u, u0), Math.min(v, v0), Math.abs(u - u0), Math.abs(v - v0)];
  teachDraw();
});
$("#teach-canvas").addEventListener("pointerup", () => {
  if (!teach.drag) return;
  const r = teach.drag;
  teach.drag = null;
  setRoi(r[2] >= 8 && r[3] >= 8 ? r : null);
});

$("#teach-grab").addEventListener("click", async () => {
  $("#teach-error").textContent = "";
  try {
    teach.image = (await grabBitmap("png")).bitmap;
    $("#teach-canvas").dataset.size = `${teach.image.width}x${teach.image.height}`;
    setRoi(null);
    $("#teach-status").textContent = "drag a rectangle around the part";
  } catch (e) { $("#teach-error").textContent = `picture: ${e.message}`; }
});

$("#teach-button").addEventListener("click", async () => {
  if (!teach.roi) return;
  $("#teach-error").textContent = "";
  $("#teach-button").disabled = true;
  $("#teach-status").textContent = "teaching…";
  try {
    const body = { camera_id: state.cameraId, roi: teach.roi.map((x) => Math.round(x * 10) / 10),
      mode: $("#teach-mode").value, name: $("#recipe-name").value || "part" };
    if (body.mode === "shape") {  // (a blob model is taught from the grey value, with no rim)
      body.colour = $("#teach-colour").value;
      if ($("#teach-rim").checked) body.refine = "rim";
    }
    const model = await api("POST", "/pick/teach?preview=true", body);
    teach.preview = model.preview;
    delete model.preview;
    teach.model = model;
    const s = teach.preview.summary;
    $("#teach-status").textContent = `taught ${s.name} (${s.mode}): `
      + (s.edge_points !== undefined ? `${s.edge_points} edge points` : `blob of ${fmt(s.area_px, 0)} px`)
      + `; reference point (${fmt(s.reference_px[0], 1)}, ${fmt(s.reference_px[1], 1)}) px`;
    $("#teach-canvas").dataset.edges = String(teach.preview.edges_px.length);
    $("#recipe-form").hidden = false;
    teachDraw();
    showGrasp();
  } catch (e) {
    $("#teach-error").textContent = `teach: ${e.message}`;
  } finally {
    $("#teach-button").disabled = !teach.roi;
  }
});

// ---------------------------------------------------------------- recipe: pose, gripper, save

$("#recipe-pose-button").addEventListener("click", async () => {
  try {
    const s = await api("GET", `/robots/${encodeURIComponent(state.robotId)}/state`);
    const p = s.pose_ur;
    teach.pose = [p.x_m, p.y_m, p.z_m, p.rx_rad, p.ry_rad, p.rz_rad];
    $("#recipe-pose").textContent = `x ${fmt(p.x_m * 1e3, 1)}, y ${fmt(p.y_m * 1e3, 1)}, z ${fmt(p.z_m * 1e3, 1)} mm · `
      + `rotation vector ${fmt(p.rx_rad, 3)}, ${fmt(p.ry_rad, 3)}, ${fmt(p.rz_rad, 3)} rad (${state.robotId})`;
    showGrasp();
  } catch (e) { $("#teach-error").textContent = `robot pose: ${e.message}`; }
});

const num = (sel) => ($(sel).value === "" ? null : Number($(sel).value));

$("#recipe-id").addEventListener("input", () => {
  $("#recipe-exists").hidden = true;
  $("#recipe-new-version").checked = false;
});

$("#recipe-form").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  if (!teach.model) return;
  $("#teach-error").textContent = "";
  const recipeId = Number($("#recipe-id").value);
  const existing = stored.find((r) => r.recipe_id === recipeId);
  if (existing && !$("#recipe-new-version").checked) {
    // Never over a recipe by default: an existing number must be asked for (a production recipe's place
    // section and gripper device are then carried over to the new version).
    $("#recipe-exists-id").textContent = String(recipeId);
    $("#recipe-exists").hidden = false;
    $("#teach-error").textContent = `recipe ${recipeId} (${existing.name}) exists: tick the box to save a new version `
      + "of it, or choose another number";
    return;
  }
  teach.model.name = $("#recipe-name").value;  // the part is named after the recipe it is saved in
  let kept = {};
  if (existing) {
    const old = (await api("GET", `/recipes/${recipeId}`)).data;
    kept = { place: old.place ?? null, search: old.search };
    if (old.gripper && old.gripper.device) kept.device = old.gripper.device;
  }
  const recipe = draftRecipe();
  if (kept.place) recipe.place = kept.place;
  if (kept.search) recipe.search = kept.search;
  if (kept.device) recipe.gripper.device = kept.device;
  try {
    const r = await api("POST", "/recipes", { recipe_id: recipeId, recipe });
    $("#recipe-status").textContent = `recipe ${r.recipe_id} "${r.name}" saved as version ${r.version}`
      + (teach.pose ? " with its capture pose" : " (no capture pose: picks are taken from wherever the robot is)")
      + (recipe.place ? "" : "; for production add its place section and gripper device in the Recipes tab");
    $("#recipe-new-version").checked = false;
    $("#recipe-exists").hidden = true;
    await refreshRecipes(r.recipe_id);
  } catch (e) { $("#teach-error").textContent = `save: ${e.message}`; }
});

// ---------------------------------------------------------------- pick test

let stored = [];  // the recipes as last listed (GET /recipes)

export async function refreshRecipes(select) {
  if (!state.token) return;
  try {
    const recipes = await api("GET", "/recipes");
    stored = recipes;
    // A new recipe gets a new number by default: the next after the highest stored (never recipe 1 over one).
    const next = recipes.length ? Math.min(65535, Math.max(...recipes.map((r) => r.recipe_id)) + 1) : 1;
    if ($("#recipe-id").value === "" || recipes.some((r) => r.recipe_id === Number($("#recipe-id").value)
        && !$("#recipe-new-version").checked)) $("#recipe-id").value = String(next);
    const sel = $("#pick-recipe");
    const keep = select ?? (sel.value === "" ? null : Number(sel.value));
    sel.replaceChildren(...recipes.map((r) => new Option(`${r.recipe_id} ${r.name} (v${r.version})`, String(r.recipe_id))));
    if (keep !== null && recipes.some((r) => r.recipe_id === keep)) sel.value = String(keep);
    $("#pick-recipes").textContent = recipes.length
      ? `recipes: ${recipes.map((r) => `${r.recipe_id} ${r.name} (v${r.version})`).join(", ")}`
      : (has("engineer") ? "no recipes stored yet: teach a part above"
        : "no recipes stored yet: an engineer teaches a part and saves a recipe");
    $("#pick-button").disabled = !recipes.length;
  } catch (e) { $("#pick-recipes").textContent = e.message; }
}

$("#pick-form").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  const button = $("#pick-button");
  button.disabled = true;
  $("#pick-error").textContent = "";
  $("#pick-reason").textContent = "";
  $("#pick-status").textContent = "picking…";
  try {
    const body = { recipe_id: Number($("#pick-recipe").value), move: has("engineer") && $("#pick-move").checked };
    const answer = await api("POST", "/pick", body);
    state.lastPick = answer;
    const rejected = answer.rejected || [];
    $("#pick-status").textContent = `${answer.picks.length} pick(s) · frame ${answer.frame_id} · calibration `
      + `${answer.calibration.kind} #${answer.calibration.id} · ${fmt(answer.latency_ms.total, 0)} ms`
      + (rejected.length ? ` · ${rejected.length} candidate(s) rejected by the verification` : "")
      + (answer.moved ? " · robot moved to the best pick" : "");
    $("#pick-reason").textContent = answer.reason || "";
    const tbody = $("#pick-table tbody");
    tbody.replaceChildren();
    answer.picks.forEach((p, k) => {
      const tr = document.createElement("tr");
      const pp = p.pick_pose || {};
      const sig = (p.uncertainty && p.uncertainty.sigma_mm) || [];
      // part_yaw_deg: the turn from the teach image, counter-clockwise on screen (0: as taught)
      const sy = p.uncertainty && p.uncertainty.sigma_yaw_deg;
      const yaw = fmt(p.part_yaw_deg, 2) + (sy === null || sy === undefined ? "" : ` ± ${fmt(sy, 2)}`);
      const cells = [k + 1, p.part, fmt(p.u_px, 1), fmt(p.v_px, 1), fmt(p.score, 3), fmt(pp.x_mm, 2), fmt(pp.y_mm, 2),
        fmt(pp.z_mm, 2), yaw, sig.length ? fmt(Math.max(sig[0], sig[1]), 3) : "–",
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

document.addEventListener("cellctl:tab", (e) => { if (e.detail === "pick") refreshRecipes(); });
