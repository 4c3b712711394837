// The xyzcyl web viewer (docs/viewer.md): a scene's Gaussians drawn by Spark over three.js, its input cameras as
// frustums, a drive's trajectory and actors' boxes, and a button that asks the server for its own (CPU) render of the
// current view. The page's JSON (#xyzcyl-scene) comes from GET /v1/scenes/{id}/viewer (server/viewer/__init__.py).
import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";
import { SparkRenderer, SplatMesh } from "@sparkjsdev/spark";

const data = JSON.parse(document.getElementById("xyzcyl-scene").textContent);
const $ = (id) => document.getElementById(id);
const fail = window.xyzcylFail;

// ------------------------------------------------------------------------------------------- frames (the one place)
// The scene's frame (ego) is x forward, y left, z up, metres; three.js is y up. Everything the page draws from the
// scene (Gaussians, frustums, trajectory, boxes) is a child of `world`, whose matrix EGO_TO_THREE takes ego (x, y, z)
// to three.js (y, z, x): +X left, +Y up, +Z forward, glTF's axes as the glTF export writes them (the server sends
// runtime.exports' matrix: data.frames). A splat file in another frame (SPZ: RUB) is placed in ego by its own matrix
// (data.splats[i].to_ego). A camera's cam_to_ego has OpenCV axes (x right, y down, z forward); a three.js camera looks
// along its -z with y up: CV_TO_GL flips y and z. So a view's three.js camera matrix is
// EGO_TO_THREE * cam_to_ego * CV_TO_GL, and back: cam_to_ego = EGO_TO_THREE^-1 * matrixWorld * CV_TO_GL.
const rows4 = (m) => new THREE.Matrix4().set(...m.flat());        // 4x4 row-major nested list -> Matrix4
const EGO_TO_THREE = rows4(data.frames.ego_to_three);
const THREE_TO_EGO = EGO_TO_THREE.clone().invert();
const CV_TO_GL = new THREE.Matrix4().makeScale(1, -1, -1);
const NEAR = 0.05, FAR = 5000;     // metres

const rowMajor = (m) => { const e = m.elements; return [0, 1, 2, 3].flatMap((r) => [0, 1, 2, 3].map((c) => e[c * 4 + r])); };

// A pinhole camera from OpenCV intrinsics: K's pixel-centre convention (the centre of pixel column u is at x = u), for
// a drawing buffer of width x height pixels. Spark projects each Gaussian's centre through this matrix and takes its
// focal lengths from [0][0], [1][1], so an off-centre principal point is drawn where the CPU renderer draws it.
class KCamera extends THREE.PerspectiveCamera {
  constructor() { super(50, 1, NEAR, FAR); this.K = null; this.size = [1, 1]; }
  setK(K, width, height) { this.K = K; this.size = [width, height]; this.updateProjectionMatrix(); }
  updateProjectionMatrix() {
    if (!this.K) { super.updateProjectionMatrix(); return; }
    const [[fx, , cx], [, fy, cy]] = this.K, [w, h] = this.size, n = this.near, f = this.far;
    this.projectionMatrix.set(
      2 * fx / w, 0, 1 - 2 * (cx + 0.5) / w, 0,
      0, 2 * fy / h, 2 * (cy + 0.5) / h - 1, 0,
      0, 0, -(f + n) / (f - n), -2 * f * n / (f - n),
      0, 0, -1, 0);
    this.projectionMatrixInverse.copy(this.projectionMatrix).invert();
  }
}

// K of a camera imaging at width x height (runtime.camera.Camera.resized: u -> s (u + 1/2) - 1/2)
function resizedK(K, fromW, fromH, w, h) {
  const sx = w / fromW, sy = h / fromH;
  return [[sx * K[0][0], 0, sx * (K[0][2] + 0.5) - 0.5], [0, sy * K[1][1], sy * (K[1][2] + 0.5) - 0.5], [0, 0, 1]];
}

// a camera without K (equirectangular): a 60 degree pinhole along its axis
function cameraK(cam) {
  if (cam.K) return cam.K;
  const f = 0.5 * cam.width / Math.tan(Math.PI / 6);
  return [[f, 0, (cam.width - 1) / 2], [0, f, (cam.height - 1) / 2], [0, 0, 1]];
}

// ------------------------------------------------------------------------------------------- page state
const fixed = data.view.width !== null;           // ?width=/&height=: a view of exactly that many pixels
const canvas = $("canvas");
const renderer = new THREE.WebGLRenderer({ canvas, antialias: false, alpha: false, preserveDrawingBuffer: true });
renderer.setClearColor(0x000000, 1);
renderer.setPixelRatio(fixed ? 1 : window.devicePixelRatio || 1);
const scene = new THREE.Scene();
const world = new THREE.Group();
world.matrixAutoUpdate = false;
world.matrix.copy(EGO_TO_THREE);
scene.add(world);
const camera = new KCamera();
const controls = new OrbitControls(camera, canvas);
controls.enableDamping = false;
controls.screenSpacePanning = true;
let view = { cam: null, K: null, width: 1, height: 1 };   // the K the canvas draws with, at its buffer size
let needsRender = true, time = data.time.start;

// Spark's settings are chosen to draw as the CPU renderer does (docs/viewer.md "What it draws"): a 0.3 px screen-space
// blur without opacity compensation (the 3DGS convention; Spark's default compensates: its blurAmount), depth (z)
// sorting rather than radial, 3 sigma extents, the same 1/255 alpha floor; float32 centres (extSplats) for metres-
// large scenes; no level of detail.
const spark = new SparkRenderer({ renderer, preBlurAmount: 0.3, blurAmount: 0.0, sortRadial: false, maxStdDev: 3.0,
                                  minAlpha: 1 / 255, accumExtSplats: true, enableLod: false,
                                  onDirty: () => { needsRender = true; } });
scene.add(spark);

// ------------------------------------------------------------------------------------------- sizing and views
function fitCanvas() {
  // the canvas keeps the view's aspect ratio (exactly width x height pixels with ?width=/&height=)
  const cam = view.cam;
  let w, h;
  if (fixed) { w = data.view.width; h = data.view.height; }
  else {
    const aspect = view.width / view.height, W = window.innerWidth, H = window.innerHeight;
    if (W / H > aspect) { h = H; w = Math.round(H * aspect); } else { w = W; h = Math.round(W / aspect); }
  }
  renderer.setSize(w, h, true);
  const buf = renderer.getDrawingBufferSize(new THREE.Vector2());
  const K = cam ? resizedK(cameraK(cam), cam.width, cam.height, buf.x, buf.y) : view.K;
  view = { ...view, K, width: buf.x, height: buf.y };
  camera.setK(K, buf.x, buf.y);
  const ours = $("ours");
  ours.style.width = `${w}px`; ours.style.height = `${h}px`;
  needsRender = true;
}

function goToCamera(name) {
  const cam = data.cameras.find((c) => c.name === name) || data.cameras[0];
  view = { cam, K: cameraK(cam), width: cam.width, height: cam.height };
  const M = EGO_TO_THREE.clone().multiply(rows4(cam.cam_to_ego)).multiply(CV_TO_GL);
  M.decompose(camera.position, camera.quaternion, camera.scale);
  camera.updateMatrixWorld(true);
  // the orbit centre: 10 m ahead
  const ahead = new THREE.Vector3(0, 0, -1).applyQuaternion(camera.quaternion);
  controls.target.copy(camera.position).addScaledVector(ahead, 10);
  $("camera").value = cam.name;
  // the view's own camera's frustum would outline the canvas's border: hidden until the view moves
  frustums.children.forEach((f, i) => { f.visible = data.cameras[i] !== cam; });
  fitCanvas();
  hideOurs();
}

// the view moved away from the input camera: every frustum shows, our render (of the old view) goes
function moved() {
  frustums.children.forEach((f) => { f.visible = true; });
  hideOurs();
  needsRender = true;
}

// The current view as the API's render query: cam_to_ego (OpenCV axes, ego frame) and K at the canvas's buffer size
// (at most 1920 pixels a side: the render is the CPU's work), the time with actors.
function renderQuery() {
  camera.updateMatrixWorld(true);
  const T = THREE_TO_EGO.clone().multiply(camera.matrixWorld).multiply(CV_TO_GL);
  const s = Math.min(1, 1920 / Math.max(view.width, view.height));
  const w = Math.max(1, Math.round(view.width * s)), h = Math.max(1, Math.round(view.height * s));
  const K = resizedK(view.K, view.width, view.height, w, h);
  const q = new URLSearchParams({ cam_to_ego: rowMajor(T).map((v) => +v.toFixed(9)).join(","), fx: K[0][0],
                                  fy: K[1][1], cx: K[0][2], cy: K[1][2], width: w, height: h, format: "jpeg" });
  if (data.actors) q.set("time", time);
  return `${data.links.render}?${q}`;
}

// ------------------------------------------------------------------------------------------- what the scene shows
function frustum(cam, depth) {
  const K = cameraK(cam), T = rows4(cam.cam_to_ego);
  const corner = (u, v) => new THREE.Vector3((u - K[0][2]) / K[0][0] * depth, (v - K[1][2]) / K[1][1] * depth, depth)
    .applyMatrix4(T);
  const o = new THREE.Vector3().setFromMatrixPosition(T);
  const c = [corner(-0.5, -0.5), corner(cam.width - 0.5, -0.5), corner(cam.width - 0.5, cam.height - 0.5),
             corner(-0.5, cam.height - 0.5)];
  const up = corner((cam.width - 1) / 2, -0.5 - 0.25 * cam.height);      // a tick above the top edge: image up
  const pts = [o, c[0], o, c[1], o, c[2], o, c[3], c[0], c[1], c[1], c[2], c[2], c[3], c[3], c[0], c[0], up, up, c[1]];
  return new THREE.LineSegments(new THREE.BufferGeometry().setFromPoints(pts),
                                new THREE.LineBasicMaterial({ color: 0xffcc33 }));
}

const frustums = new THREE.Group();
for (const cam of data.cameras) frustums.add(frustum(cam, 1.0));
world.add(frustums);

const trajectory = new THREE.Group();
if (data.trajectory.length > 1) {
  const pts = data.trajectory.map((p) => new THREE.Vector3(...p));
  trajectory.add(new THREE.Line(new THREE.BufferGeometry().setFromPoints(pts),
                                new THREE.LineBasicMaterial({ color: 0x33ccff })));
  trajectory.add(new THREE.Points(new THREE.BufferGeometry().setFromPoints(pts),
                                  new THREE.PointsMaterial({ color: 0x33ccff, size: 4, sizeAttenuation: false })));
  world.add(trajectory);
} else {
  $("trajectory-toggle").hidden = true;
}

const boxes = new THREE.Group();
world.add(boxes);
const boxEdges = new THREE.EdgesGeometry(new THREE.BoxGeometry(1, 1, 1));
let actorsAsked = 0;
async function showActors() {
  const asked = ++actorsAsked;
  const r = await fetch(`${data.links.actors}?time=${time}`);
  if (!r.ok) { status(`actors: ${r.status} ${await errorText(r)}`); return; }
  const doc = await r.json();
  if (asked !== actorsAsked) return;          // a newer time was asked meanwhile
  boxes.clear();
  for (const a of doc.actors) {
    if (!a.pose) continue;
    const box = new THREE.LineSegments(boxEdges, new THREE.LineBasicMaterial({ color: a.tracked ? 0xff5577 : 0xaa88ff }));
    box.matrixAutoUpdate = false;
    box.matrix.copy(rows4([a.pose.slice(0, 4), a.pose.slice(4, 8), a.pose.slice(8, 12), a.pose.slice(12, 16)]))
      .multiply(new THREE.Matrix4().makeScale(...a.size));
    boxes.add(box);
  }
  needsRender = true;
}

// ------------------------------------------------------------------------------------------- our render
function status(text) { $("status").textContent = text; }
async function errorText(r) {
  try { const b = await r.json(); return b.error ? b.error.message : JSON.stringify(b); } catch { return r.statusText; }
}
function hideOurs() { $("ours").hidden = true; $("show-ours").checked = false; $("show-ours").disabled = true; }
async function askOurs() {
  const q = renderQuery(), t0 = performance.now();
  status("rendering on the server...");
  const r = await fetch(q);
  if (!r.ok) { status(`our render: ${r.status} ${await errorText(r)}`); return; }
  const img = $("ours");
  const old = img.src;
  img.src = URL.createObjectURL(await r.blob());
  if (old.startsWith("blob:")) URL.revokeObjectURL(old);
  img.hidden = false;
  $("show-ours").disabled = false; $("show-ours").checked = true;
  status(`our render: ${((performance.now() - t0) / 1000).toFixed(1)} s (C: flip between the two)`);
}

// ------------------------------------------------------------------------------------------- controls
for (const cam of data.cameras) $("camera").add(new Option(cam.name, cam.name));
$("camera").onchange = () => goToCamera($("camera").value);
$("reset").onclick = () => goToCamera($("camera").value);
$("render").onclick = () => askOurs();
$("show-ours").onchange = () => { $("ours").hidden = !$("show-ours").checked; };
$("show-frustums").onchange = () => { frustums.visible = $("show-frustums").checked; needsRender = true; };
$("show-trajectory").onchange = () => { trajectory.visible = $("show-trajectory").checked; needsRender = true; };
controls.addEventListener("change", moved);
window.addEventListener("resize", () => { if (!fixed) fitCanvas(); });

if (data.actors) {
  const slider = $("time");
  $("time-row").hidden = false;
  slider.min = data.time.start; slider.max = data.time.end; slider.step = Math.max(1e-3, data.time.step / 4);
  slider.value = time;
  const label = () => { $("time-label").textContent = `+${(time - data.time.start).toFixed(2)} s`; };
  label();
  let pending = null;
  slider.oninput = () => {
    time = +slider.value; label(); hideOurs();
    clearTimeout(pending); pending = setTimeout(showActors, 80);
  };
}
const actorsShown = data.actors ? showActors() : Promise.resolve();

const held = new Set();
window.addEventListener("keydown", (e) => {
  if (e.target instanceof HTMLInputElement || e.target instanceof HTMLSelectElement) return;
  const k = e.key.toLowerCase();
  if ("wasdqe".includes(k) && k.length === 1) held.add(k);
  else if (k === "r") goToCamera($("camera").value);
  else if (k === "c" && !$("show-ours").disabled) { $("show-ours").click(); }
  else if (k === "h") document.body.classList.toggle("bare");
  else if (k === "f") $("show-frustums").click();
  if (e.shiftKey) held.add("shift");
});
window.addEventListener("keyup", (e) => { held.delete(e.key.toLowerCase()); if (!e.shiftKey) held.delete("shift"); });
window.addEventListener("blur", () => held.clear());

function fly(dt) {
  if (!["w", "a", "s", "d", "q", "e"].some((k) => held.has(k))) return;
  const speed = (held.has("shift") ? 15 : 4) * dt;      // metres per second
  const fwd = new THREE.Vector3(), right = new THREE.Vector3(), up = new THREE.Vector3(0, 1, 0);
  camera.getWorldDirection(fwd);
  right.crossVectors(fwd, up).normalize();
  const move = new THREE.Vector3();
  if (held.has("w")) move.add(fwd); if (held.has("s")) move.sub(fwd);
  if (held.has("d")) move.add(right); if (held.has("a")) move.sub(right);
  if (held.has("e")) move.add(up); if (held.has("q")) move.sub(up);
  move.multiplyScalar(speed);
  camera.position.add(move); controls.target.add(move);
  moved();
}

// ------------------------------------------------------------------------------------------- the Gaussians
// The scene's Gaussians: SPZ from GET .../export?format=spz where the server has it, else the 3DGS PLY of
// GET .../gaussians (SPZ is about a tenth of the bytes; it bakes a drive's actors in at its first frame, the PLY is
// the static scene). Any other failure is shown.
async function fetchSplats() {
  for (const s of data.splats) {
    status(`loading the Gaussians (${s.format})...`);
    const r = await fetch(s.url);
    if (r.ok) return { bytes: new Uint8Array(await r.arrayBuffer()), format: s.format, to_ego: s.to_ego };
    if (r.status === 422 && s !== data.splats[data.splats.length - 1]) continue;   // not offered here: the next one
    throw new Error(`GET ${s.url}: ${r.status} ${await errorText(r)}`);
  }
  throw new Error("no Gaussians format was offered");
}

// the view drawn with the Gaussians sorted for it (a few frames without another redraw)
const drawn = () => spark.activeSplats > 0 && !spark.sorting && !spark.sortDirty && !needsRender && idleFrames > 3;
// a promise of the next time the view is drawn so (for screenshots after a scripted move)
function settled() {
  return new Promise((resolve) => { const check = () => (drawn() ? resolve() : requestAnimationFrame(check)); check(); });
}

const state = { ready: false, splats: 0, format: null, loadSeconds: null };
let mesh = null, lastT = performance.now(), idleFrames = 0;
function loop(t) {
  requestAnimationFrame(loop);
  fly(Math.min(0.1, (t - lastT) / 1000)); lastT = t;
  if (needsRender) { needsRender = false; renderer.render(scene, camera); idleFrames = 0; }
  else idleFrames++;
  // ready: the Gaussians loaded, sorted for this view and drawn (a few frames without another redraw)
  if (!state.ready && mesh && mesh.isInitialized && drawn()) {
    state.ready = true;
    document.body.dataset.state = "ready";
    status(`${state.splats.toLocaleString()} Gaussians (${state.format}, ${state.loadSeconds.toFixed(1)} s)`);
  }
}

async function start() {
  $("title").textContent = data.name || data.id;
  goToCamera(data.view.camera || data.cameras[0].name);
  requestAnimationFrame(loop);
  const t0 = performance.now();
  const got = await fetchSplats();
  await actorsShown;
  mesh = new SplatMesh({ fileBytes: got.bytes, fileType: got.format, extSplats: true });
  mesh.matrixAutoUpdate = false;
  mesh.matrix.copy(rows4(got.to_ego));
  world.add(mesh);
  await mesh.initialized;
  state.splats = mesh.numSplats ?? (mesh.extSplats ? mesh.extSplats.numSplats : 0);
  state.format = got.format;
  state.loadSeconds = (performance.now() - t0) / 1000;
  needsRender = true;
}

// a scripted view (screenshots): the camera at `eye` looking at `target`, both in the scene's frame (ego, metres), upright
function lookAt(eye, target) {
  camera.position.fromArray(eye).applyMatrix4(EGO_TO_THREE);
  controls.target.fromArray(target).applyMatrix4(EGO_TO_THREE);
  camera.up.set(0, 1, 0);
  camera.lookAt(controls.target);
  camera.updateMatrixWorld(true);
  moved();
}

// what the page shows besides the Gaussians (tests, scripts)
function summary() {
  return { frustums: frustums.children.length, trajectory: data.trajectory.length > 1 ? data.trajectory.length : 0,
           boxes: boxes.children.length, time: data.actors ? time : null,
           slider: data.actors ? [+$("time").min, +$("time").max] : null };
}

window.xyzcylViewer = { state, data, renderQuery, goToCamera, lookAt, settled, summary, camera, controls, world, spark,
                        redraw: () => { needsRender = true; } };
start().catch((e) => fail(`The viewer could not show scene ${data.id}: ${e.message || e}`));
