// cellctl operator page: what every tab shares — helpers, the session state, the REST API (with
// the operator's bearer token, kept in sessionStorage), job event streams, roles, tabs, and the one
// camera request queue. Plain ES module, no build step, nothing loaded from elsewhere.
// Job events (SSE) are read with fetch + a stream reader, since EventSource cannot send the token.

export const RANK = { viewer: 0, operator: 1, engineer: 2 };
export const TOKEN_KEY = "cellctl.token";
export const LIVE_PAUSE_MS = 400;     // pause between live frames (the next request starts when one is drawn)
export const ROBOT_PERIOD_MS = 1000;

export const $ = (sel, root = document) => root.querySelector(sel);
export const $$ = (sel, root = document) => Array.from(root.querySelectorAll(sel));
export const sleep = (ms) => new Promise((resolve) => setTimeout(resolve, ms));
export const fmt = (v, digits = 2) => (v === null || v === undefined || Number.isNaN(Number(v))) ? "–" : Number(v).toFixed(digits);
export const deg = (rad) => rad * 180 / Math.PI;

export const state = {
  token: null, who: null, session: 0, tab: "live",
  cameraId: null, robotId: null, lastPick: null, pickUrl: null,
};

// Set by main.js (logging out lives there; a 401 from any call lands in it).
export const hooks = { unauthorized: (_message) => {} };

// ---------------------------------------------------------------- API

export class ApiError extends Error {
  constructor(status, code, message) { super(message); this.status = status; this.code = code; }
}

export async function api(method, path, body, opts = {}) {
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
    if (r.status === 401 && !opts.token) { hooks.unauthorized("Your token is no longer accepted: log in again."); }
    throw new ApiError(r.status, code, message);
  }
  if (opts.raw) return r;
  return (r.headers.get("content-type") || "").includes("json") ? r.json() : r.text();
}

// Server-sent events over fetch: calls onEvent(kind, data, id) per event until the stream ends.
export async function readEvents(jobId, onEvent, signal) {
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
export async function followJob(job, onEvent, isCurrent) {
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

export async function startRoutine(name, params) {
  return api("POST", `/routines/${encodeURIComponent(name)}`, params);
}

export function has(role) { return state.who && RANK[state.who.role] >= RANK[role]; }

export function applyRoles() {
  for (const el of $$("[data-min-role]")) el.hidden = !has(el.dataset.minRole);
  if ($("nav button.active").hidden) showTab("live");
}

// Tabs announce themselves: each tab module listens for "cellctl:tab" to refresh what it shows.
export function showTab(name) {
  state.tab = name;
  for (const b of $$("#tabs button")) b.classList.toggle("active", b.dataset.tab === name);
  for (const s of $$(".tab")) s.hidden = s.id !== `tab-${name}`;
  document.dispatchEvent(new CustomEvent("cellctl:tab", { detail: name }));
}

// One camera request at a time from this page: a slow camera is not made slower by piling up grabs.
let cameraQueue = Promise.resolve();

export function grabBitmap(format) {
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
export async function waitCameraAvailable(timeoutMs) {
  const deadline = performance.now() + timeoutMs;
  for (;;) {
    const cams = await api("GET", "/cameras");
    const cam = cams.find((c) => c.id === state.cameraId);
    if (!cam || cam.available || performance.now() > deadline) return;
    await sleep(500);
  }
}
