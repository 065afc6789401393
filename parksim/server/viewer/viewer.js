// ParkSim viewer: the four fisheye views, the BEV and a minimap at the current pose, driven with the keyboard
// or the mouse. Each step is one GET /render (npz: every view, the BEV and, when asked, depth).
// State is exposed as window.viewerState (frames shown, pose, scene info, last latency) for the end-to-end test.

import { parseNpz } from "./npz.js";
import { DEPTH_RANGE_M, drawDepth, drawDepthLegend, drawRGB } from "./draw.js";
import { Minimap } from "./minimap.js";
import { clampPose, coverage, startPose } from "./scene.js";

// The API key, when the server has one: opened as /#api_key=KEY. A fragment never reaches the server (nor proxies'
// and servers' logs); it is kept for this tab in sessionStorage and taken out of the address bar and history.
const KEY_ITEM = "parksim.apiKey";
const given = new URLSearchParams(location.hash.slice(1)).get("api_key");
if (given) {
  sessionStorage.setItem(KEY_ITEM, given);
  history.replaceState(null, "", location.pathname + location.search);
}
const apiKey = sessionStorage.getItem(KEY_ITEM);
const state = { scene: null, info: null, pose: { x: 0, y: 0, yaw: 0 }, frames: 0, latencyMs: null, busy: false,
                dirty: false, depth: false, depthShown: false, coverage: null, clamped: false };
window.viewerState = state;
let minimap = null;

const $ = (id) => document.getElementById(id);
const headers = () => (apiKey ? { "X-API-Key": apiKey } : {});
const wrap = (a) => (Math.abs(a) <= Math.PI ? a : Math.atan2(Math.sin(a), Math.cos(a)));

async function failure(r, path) {
  const body = await r.json().catch(() => ({ detail: r.statusText }));
  const hint = r.status === 401 ? " (open the viewer as /#api_key=KEY)" : "";
  return new Error(`${path}: ${r.status} ${body.detail}${hint}`);
}

async function getJSON(path) {
  const r = await fetch(path, { headers: headers() });
  if (!r.ok) throw await failure(r, path);
  return r.json();
}

function poseText(p) {
  return `${p.x.toFixed(3)},${p.y.toFixed(3)},${p.yaw.toFixed(4)}`;
}

// Pose, coverage warning and minimap for the current pose (at once, without waiting for the render).
function showPose() {
  const p = state.pose;
  state.coverage = coverage(state.info, p);
  $("pose").textContent = `pose x=${p.x.toFixed(2)} m y=${p.y.toFixed(2)} m yaw=${(p.yaw * 180 / Math.PI).toFixed(1)}\u00b0`;
  const warnings = state.coverage.covered ? [] : [state.coverage.text];
  if (state.clamped) warnings.push(`At the edge of what the server renders (scene bounds + ${state.info.pose_margin_m} m).`);
  $("coverage").textContent = warnings.join(" ");
  $("coverage").hidden = !warnings.length;
  minimap.draw(p, state.coverage.covered);
}

function showFrame(arrays) {
  for (const fig of document.querySelectorAll("#views figure")) {
    const name = fig.dataset.camera;
    drawRGB(fig.querySelector("canvas.rgb"), arrays.get(`images/${name}`));
    const depth = arrays.get(`depth/${name}`);
    if (depth) drawDepth(fig.querySelector("canvas.depth"), depth);
    fig.classList.toggle("show-depth", Boolean(depth));
  }
  drawRGB($("bev"), arrays.get("bev"));
  state.depthShown = arrays.has(`depth/${state.info.cameras[0]}`);
}

// One GET /render for the current pose; poses that arrive meanwhile are coalesced into the next one.
// A 503 (queue full, render timed out) is retried after the server's Retry-After.
async function refresh() {
  if (state.busy) { state.dirty = true; return; }
  state.busy = true;
  state.dirty = false;
  let retryS = null;
  const query = new URLSearchParams({ pose: poseText(state.pose), scene: state.scene, scale: $("scale").value,
                                      bev: "true", depth: String(state.depth), format: "npz" });
  const start = performance.now();
  try {
    const r = await fetch(`/render?${query}`, { headers: headers() });
    if (r.status === 503) retryS = Number(r.headers.get("Retry-After")) || 1;
    if (!r.ok) throw await failure(r, "/render");
    const arrays = parseNpz(await r.arrayBuffer());
    showFrame(arrays);
    state.latencyMs = performance.now() - start;
    state.frames += 1;
    const t = JSON.parse(arrays.get("meta").data).timings_ms;
    const server = Object.entries(t).map(([k, v]) => `${k} ${v.toFixed(0)}`).join(", ");
    $("latency").textContent = `latency ${state.latencyMs.toFixed(0)} ms (1 request; server ms: ${server})`;
    $("error").textContent = "";
  } catch (e) {
    $("error").textContent = e.message + (retryS === null ? "" : ` (retrying in ${retryS} s)`);
  }
  state.busy = false;
  if (state.dirty) refresh();
  else if (retryS !== null) setTimeout(() => { if (!state.busy) refresh(); }, 1000 * retryS);
}

function setPose(pose) {
  const { pose: held, clamped } = clampPose(state.info, { ...pose, yaw: wrap(pose.yaw) });
  state.pose = held;
  state.clamped = clamped;
  showPose();
  refresh();
}

// Drive in the ego frame: ``forward`` and ``left`` (m), ``turn`` (rad, counter-clockwise).
function move(forward, left, turn) {
  const p = state.pose;
  setPose({ x: p.x + forward * Math.cos(p.yaw) - left * Math.sin(p.yaw),
            y: p.y + forward * Math.sin(p.yaw) + left * Math.cos(p.yaw), yaw: p.yaw + turn });
}

const KEYS = {
  ArrowUp: [0.5, 0, 0], KeyW: [0.5, 0, 0], ArrowDown: [-0.5, 0, 0], KeyS: [-0.5, 0, 0],
  ArrowLeft: [0, 0, 0.0873], KeyA: [0, 0, 0.0873], ArrowRight: [0, 0, -0.0873], KeyD: [0, 0, -0.0873],
  KeyQ: [0, 0.5, 0], KeyE: [0, -0.5, 0],
};

document.addEventListener("keydown", (ev) => {
  const step = KEYS[ev.code];
  if (!step || !state.info || ev.target.tagName === "SELECT") return;
  ev.preventDefault();
  move(...step);
});

// Pointer drags on ``canvas``: ``onDrag(ev, start, turn)`` with the pose and event at the press;
// shift or the right button turns instead of moving.
function draggable(canvas, onDrag) {
  let press = null;
  canvas.addEventListener("contextmenu", (ev) => ev.preventDefault());
  canvas.addEventListener("pointerdown", (ev) => {
    if (!state.info) return;
    canvas.setPointerCapture(ev.pointerId);
    press = { ev, pose: { ...state.pose }, turn: ev.shiftKey || ev.button === 2 };
    onDrag(ev, press);
  });
  canvas.addEventListener("pointermove", (ev) => { if (press) onDrag(ev, press); });
  const release = () => { press = null; };
  canvas.addEventListener("pointerup", release);
  canvas.addEventListener("pointercancel", release);
}

// The BEV is ego-centred: a drag pulls the ground with the cursor (drag down = drive forward);
// a turning drag spins the ground about the image centre.
function dragBEV(ev, press) {
  const canvas = $("bev");
  const r = canvas.getBoundingClientRect();
  const { bev } = state.info;
  const mPerPx = (bev.width * bev.m_per_px) / r.width;
  const p = press.pose;
  if (press.turn) {
    const angle = (e) => Math.atan2(-(e.clientY - r.top - r.height / 2), e.clientX - r.left - r.width / 2);
    if (ev !== press.ev) setPose({ ...p, yaw: p.yaw - (angle(ev) - angle(press.ev)) });
    return;
  }
  const forward = (ev.clientY - press.ev.clientY) * mPerPx, left = (ev.clientX - press.ev.clientX) * mPerPx;
  if (forward || left) {
    setPose({ x: p.x + forward * Math.cos(p.yaw) - left * Math.sin(p.yaw),
              y: p.y + forward * Math.sin(p.yaw) + left * Math.cos(p.yaw), yaw: p.yaw });
  }
}

// On the minimap the ego goes where the cursor is; a turning drag points it at the cursor.
function dragMinimap(ev, press) {
  const [x, y] = minimap.toWorld(ev);
  const p = state.pose;
  if (press.turn) {
    if (Math.hypot(x - p.x, y - p.y) > 1e-6) setPose({ ...p, yaw: Math.atan2(y - p.y, x - p.x) });
  } else {
    setPose({ x, y, yaw: p.yaw });
  }
}

// One figure per camera of the scene: its colour view and, when depth is on, its depth view.
function buildViews(cameras) {
  $("views").replaceChildren(...cameras.map((name) => {
    const fig = document.createElement("figure");
    fig.dataset.camera = name;
    fig.innerHTML = `<canvas class="rgb"></canvas><canvas class="depth"></canvas><figcaption></figcaption>`;
    fig.querySelector("canvas.rgb").id = `cam-${name}`;
    fig.querySelector("canvas.depth").id = `depth-${name}`;
    fig.querySelector("figcaption").textContent = name;
    return fig;
  }));
}

async function selectScene(id) {
  const info = await getJSON(`/scenes/${encodeURIComponent(id)}`);
  state.scene = id;
  state.info = info;
  minimap = new Minimap($("minimap"), info);
  buildViews(info.cameras);
  setPose(startPose(info));
}

async function main() {
  try {
    drawDepthLegend($("depth-legend"));
    $("depth-range").textContent = `${DEPTH_RANGE_M[0]} m \u2192 ${DEPTH_RANGE_M[1]} m (log), black: nothing`;
    draggable($("bev"), dragBEV);
    draggable($("minimap"), dragMinimap);
    const { scenes } = await getJSON("/scenes");
    for (const s of scenes) $("scene").add(new Option(`${s.id} (${s.gaussians} Gaussians)`, s.id));
    $("scene").addEventListener("change", (ev) => selectScene(ev.target.value));
    $("scale").addEventListener("change", refresh);
    $("depth").addEventListener("change", (ev) => { state.depth = ev.target.checked; refresh(); });
    await selectScene(scenes[0].id);
  } catch (e) {
    $("error").textContent = e.message;
  }
}

main();
