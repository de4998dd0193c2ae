// Live tab: the camera view with the last pick's matches, the robot's state, Stop.
import { $, LIVE_PAUSE_MS, ROBOT_PERIOD_MS, api, deg, fmt, grabBitmap, has, sleep, state } from "./core.js";


export function drawPicks(ctx, pick) {
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

export async function liveLoop(session) {
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

export async function robotLoop(session) {
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
        // A Stop latches the robot: nothing moves it until an engineer resumes.
        $("#rs-latched").textContent = s.latched ? "yes: latched by Stop, resume to move again" : "no";
        $("#rs-latched").className = s.latched ? "error" : "";
        $("#robot-resume").hidden = !s.latched || !has("engineer");
        $("#robot-state").dataset.xMm = String(p.x_m * 1e3);
        if ($("#robot-status").dataset.unavailable) {  // clear only our own outage note: a Stop's or a
          $("#robot-status").textContent = "";          // resume's answer stays until the next click
          delete $("#robot-status").dataset.unavailable;
        }
        await showLatch(s.latched, session);
        if (!s.latched) setBadge(`${state.robotId} ${s.moving ? "moving" : s.mode}`, true);
      } catch (e) {
        $("#robot-status").textContent = `robot ${state.robotId} unavailable: ${e.message}`;
        $("#robot-status").dataset.unavailable = "yes";
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

// The latch shows in the header on every tab (robotLoop runs whatever the tab): the badge says who
// stopped the robot, and an engineer gets Resume beside the header's Stop.
async function showLatch(latched, session) {
  $("#header-resume").hidden = !latched || !has("engineer");
  document.body.dataset.latched = latched ? "yes" : "no";
  if (!latched) return;
  let by = "";
  try {
    const m = await api("GET", `/robots/${encodeURIComponent(state.robotId)}/motion`);
    if (session !== state.session) return;
    by = m.latched_by ? ` by ${m.latched_by}` : "";
  } catch (_) { /* the badge still says latched */ }
  setBadge(`${state.robotId} STOPPED${by}: latched, no motion until an engineer resumes`, false);
  $("#robot-badge").classList.add("latched");
}

async function resumeRobot(status) {
  if (!state.robotId) { status("resume: the robot list is still loading, try again"); return; }
  try {
    await api("POST", `/robots/${encodeURIComponent(state.robotId)}/resume`);
    status("resumed: the robot may move again");
  } catch (e) { status(`resume failed: ${e.message}`); }
}

$("#header-resume").addEventListener("click", () => resumeRobot((t) => { $("#robot-badge").title = t; }));

// ---------------------------------------------------------------- named poses (engineer)

export async function loadPoses(robotId) {
  const robots = await api("GET", "/robots");
  const id = robotId || state.robotId || (robots[0] && robots[0].id);  // at log-in the devices load meanwhile
  const robot = robots.find((r) => r.id === id);
  const names = Object.keys((robot && robot.poses) || {});
  $("#pose-select").replaceChildren(...names.map((n) => new Option(n, n)));
  $("#pose-go").disabled = names.length === 0;
  $("#pose-go").title = names.length ? "a checked linear move to the named pose (POST /robots/{id}/move)"
    : "this robot has no named poses (robots.<id>.poses in cell.yaml)";
}

$("#pose-go").addEventListener("click", async () => {
  const name = $("#pose-select").value;
  if (!name) return;
  const status = $("#pose-status");
  status.textContent = `moving to ${name}…`;
  status.className = "muted";
  try {
    await api("POST", `/robots/${encodeURIComponent(state.robotId)}/move`, { named_pose: name, speed_m_s: 0.1 });
    status.textContent = `at ${name}`;
  } catch (e) {
    status.textContent = `move to ${name} failed: ${e.code}: ${e.message}`;
    status.className = "error";
  }
});
// Resume shows only once the robot's state says it is latched (robotLoop), and only to an engineer:
// not by role at log-in, before any robot is known (a click then had no robot to resume).
document.addEventListener("cellctl:login", () => {
  $("#robot-resume").hidden = true;
  $("#header-resume").hidden = true;
  loadPoses().catch(() => {});
});
$("#robot-select").addEventListener("change", (e) => { loadPoses(e.target.value).catch(() => {}); });

// Stop works from the first moment after log-in: until the robot list has loaded (nothing is
// selected yet) it stops every robot of the cell — stopping too much is safe, a lost Stop is not.
async function stopRobot() {
  const status = (t) => { $("#robot-status").textContent = t; $("#robot-badge").title = t; };
  try {
    const ids = state.robotId ? [state.robotId] : (await api("GET", "/robots")).map((r) => r.id);
    await Promise.all(ids.map((id) => api("POST", `/robots/${encodeURIComponent(id)}/stop`)));
    status(`stop sent to ${ids.join(", ")}`);
  } catch (e) { status(`stop failed: ${e.code}: ${e.message}`); }
}

$("#robot-stop").addEventListener("click", stopRobot);
$("#header-stop").addEventListener("click", stopRobot);

$("#robot-resume").addEventListener("click", () => resumeRobot((t) => { $("#robot-status").textContent = t; }));
