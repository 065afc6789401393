// ParkSim viewer: the four fisheye views and the BEV at the current pose, driven with the keyboard.
// State is exposed as window.viewerState (frames shown, pose, last latency) for the end-to-end test.
"use strict";

const CAMERAS = ["front", "rear", "left", "right"];
const VIEWS = [...CAMERAS, "bev"];
const apiKey = new URLSearchParams(location.search).get("api_key");
const state = { scene: null, pose: { x: 0, y: 0, yaw: 0 }, frames: 0, latencyMs: null, busy: false, dirty: false };
window.viewerState = state;

const $ = (id) => document.getElementById(id);

async function getJSON(path) {
  const r = await fetch(path, { headers: apiKey ? { "X-API-Key": apiKey } : {} });
  const body = await r.json();
  if (!r.ok) throw new Error(`${path}: ${r.status} ${body.detail}`);
  return body;
}

function poseText() {
  const p = state.pose;
  return `${p.x.toFixed(3)},${p.y.toFixed(3)},${p.yaw.toFixed(4)}`;
}

function loadImage(img, url) {
  return new Promise((resolve, reject) => {
    img.onload = () => resolve();
    img.onerror = () => reject(new Error(`failed to load ${url}`));
    img.src = url;
  });
}

async function refresh() {
  if (state.busy) { state.dirty = true; return; }
  state.busy = true;
  state.dirty = false;
  const query = new URLSearchParams({ pose: poseText(), scene: state.scene, scale: $("scale").value });
  if (apiKey) query.set("api_key", apiKey);
  const start = performance.now();
  try {
    await Promise.all(VIEWS.map((v) => loadImage($(`img-${v}`), `/render/${v}.jpeg?${query}`)));
    state.latencyMs = performance.now() - start;
    state.frames += 1;
    $("latency").textContent = `latency ${state.latencyMs.toFixed(0)} ms (5 images)`;
    $("error").textContent = "";
  } catch (e) {
    $("error").textContent = `${e.message}: the pose may be outside the scene`;
  }
  $("pose").textContent = `pose x=${state.pose.x.toFixed(2)} m y=${state.pose.y.toFixed(2)} m ` +
    `yaw=${(state.pose.yaw * 180 / Math.PI).toFixed(1)}\u00b0`;
  state.busy = false;
  if (state.dirty) refresh();
}

function move(forward, left, turn) {
  const p = state.pose;
  p.x += forward * Math.cos(p.yaw) - left * Math.sin(p.yaw);
  p.y += forward * Math.sin(p.yaw) + left * Math.cos(p.yaw);
  p.yaw = Math.atan2(Math.sin(p.yaw + turn), Math.cos(p.yaw + turn));
  refresh();
}

const KEYS = {
  ArrowUp: [0.5, 0, 0], KeyW: [0.5, 0, 0], ArrowDown: [-0.5, 0, 0], KeyS: [-0.5, 0, 0],
  ArrowLeft: [0, 0, 0.0873], KeyA: [0, 0, 0.0873], ArrowRight: [0, 0, -0.0873], KeyD: [0, 0, -0.0873],
  KeyQ: [0, 0.5, 0], KeyE: [0, -0.5, 0],
};

document.addEventListener("keydown", (ev) => {
  const step = KEYS[ev.code];
  if (!step || ev.target.tagName === "SELECT") return;
  ev.preventDefault();
  move(...step);
});

async function selectScene(id) {
  const info = await getJSON(`/scenes/${encodeURIComponent(id)}`);
  state.scene = id;
  const lanes = info.map && info.map.garage && info.map.garage.lanes;
  const [x0, x1] = info.bounds.x;
  const [y0, y1] = info.bounds.y;
  state.pose = { x: x0 + 0.3 * (x1 - x0), y: lanes && lanes.length ? lanes[0] : (y0 + y1) / 2, yaw: 0 };
  refresh();
}

async function main() {
  try {
    const { scenes } = await getJSON("/scenes");
    for (const s of scenes) $("scene").add(new Option(`${s.id} (${s.gaussians} Gaussians)`, s.id));
    $("scene").addEventListener("change", (ev) => selectScene(ev.target.value));
    $("scale").addEventListener("change", refresh);
    await selectScene(scenes[0].id);
  } catch (e) {
    $("error").textContent = e.message;
  }
}

main();
