// The deform live view: the tissue grid deformed and coloured by |u|, the tool, the force.
// Frames arrive over a WebSocket from `deform live --serve`; the tool positions go back the
// same way. Every number shown is also put on #readout as data- attributes (for tests).
// A force tool (mesh.kind 'force'): the handle sets the load (1 grid unit = 1 N), each frame
// answers the tool's mean displacement, and the arrow shows the load at the moved tool.
import * as THREE from 'three';
import { OrbitControls } from '/vendor/OrbitControls.js';

const STEP = 0.2; // grid units per key press
const wsPort = document.querySelector('meta[name="ws-port"]').content;
const $ = (id) => document.getElementById(id);
const readout = $('readout');

// Viridis-like colour map: |u| / max → colour, and the same stops on the colour bar.
const STOPS = ['#440154', '#3b528b', '#21918c', '#5ec962', '#fde725'].map((c) => new THREE.Color(c));
$('colorbar').style.background =
  `linear-gradient(to top, ${STOPS.map((c) => '#' + c.getHexString()).join(', ')})`;
function colour(s, out) {
  const x = Math.min(Math.max(s, 0), 1) * (STOPS.length - 1);
  const i = Math.min(Math.floor(x), STOPS.length - 2);
  return out.copy(STOPS[i]).lerp(STOPS[i + 1], x - i);
}

const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
renderer.setPixelRatio(window.devicePixelRatio);
$('view').appendChild(renderer.domElement);
const scene = new THREE.Scene();
scene.background = new THREE.Color('#eef0f3');
const camera = new THREE.PerspectiveCamera(45, 1, 0.1, 1000);
camera.up.set(0, 0, 1);
const controls = new OrbitControls(camera, renderer.domElement);
scene.add(new THREE.AmbientLight(0xffffff, 0.6));
const light = new THREE.DirectionalLight(0xffffff, 1.2);
light.position.set(10, -10, 20);
scene.add(light);

let mesh = null;       // the grid: rest positions, springs, tool nodes
let tissue = null;     // { points, lines, positions, colours }
let last = null;       // the newest frame
let toolU = [0, 0, 0]; // where the user wants the tool (sent), grid units
// Whether this page has moved the tool since it connected. Until it has, the handle follows the
// server's tool: after a reload, or in a second tab, the tool is where the frames say, not at
// rest (the mesh and the readout already show it moved).
let moved = false;
let paused = false;
let socket = null;
const toolGroup = new THREE.Group();
const toolTip = new THREE.Mesh(new THREE.SphereGeometry(0.28, 24, 16),
  new THREE.MeshStandardMaterial({ color: '#e5484d' }));
const shaft = new THREE.Mesh(new THREE.CylinderGeometry(0.07, 0.07, 4, 12),
  new THREE.MeshStandardMaterial({ color: '#c9ced6', metalness: 0.6, roughness: 0.3 }));
shaft.rotation.x = Math.PI / 2;
shaft.position.z = 2;
toolGroup.add(toolTip, shaft);
scene.add(toolGroup);
// The force arrow: a solid shaft and head (a line would be 1 px wide), along +y, turned to F.
const arrowMaterial = new THREE.MeshStandardMaterial({ color: '#f76b15' });
const arrow = new THREE.Group();
const arrowShaft = new THREE.Mesh(new THREE.CylinderGeometry(0.07, 0.07, 1, 12), arrowMaterial);
const arrowHead = new THREE.Mesh(new THREE.ConeGeometry(0.2, 0.45, 16), arrowMaterial);
arrow.add(arrowShaft, arrowHead);
scene.add(arrow);
function pointArrow(direction, length) {
  const shaft = Math.max(length - 0.45, 0.05);
  arrowShaft.scale.set(1, shaft, 1);
  arrowShaft.position.y = shaft / 2;
  arrowHead.position.y = shaft + 0.225;
  arrow.quaternion.setFromUnitVectors(new THREE.Vector3(0, 1, 0), direction);
}

function resize() {
  renderer.setSize(window.innerWidth, window.innerHeight);
  camera.aspect = window.innerWidth / window.innerHeight;
  camera.updateProjectionMatrix();
}
window.addEventListener('resize', resize);
resize();

function rest(p) {
  const [nx, ny, nz] = mesh.grid;
  const [i, j, k] = mesh.nodes[p];
  return [i - (nx - 1) / 2, j - (ny - 1) / 2, k - (nz - 1) / 2];
}

function buildMesh(m) {
  mesh = m;
  const force = forceTool();
  $('tool-label').textContent = force ? 'tool load f' : 'tool u';
  $('force-label').textContent = force ? 'tool motion ū' : 'force F';
  $('norm-label').textContent = force ? '|ū|' : '|F|';
  readout.dataset.kind = force ? 'force' : 'displacement';
  if (tissue) { scene.remove(tissue.points, tissue.lines); }
  const n = m.nodes.length;
  const index = new Map(m.nodes.map(([i, j, k], p) => [`${i},${j},${k}`, p]));
  // Only the nodes whose displacement arrives (`--field surface|stride:K`), and the springs
  // between two of them: a surface field draws the box's outside, not an inside at rest.
  const shown = m.shown || m.nodes.map(() => true);
  const springs = [];
  m.nodes.forEach(([i, j, k], p) => {
    if (!shown[p]) return;
    for (const [di, dj, dk] of [[1, 0, 0], [0, 1, 0], [0, 0, 1]]) {
      const q = index.get(`${i + di},${j + dj},${k + dk}`);
      if (q !== undefined && shown[q]) springs.push(p, q);
    }
  });
  const positions = new Float32Array(3 * n);
  const colours = new Float32Array(3 * n);
  for (let p = 0; p < n; p++) positions.set(rest(p), 3 * p);
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute('position', new THREE.BufferAttribute(positions, 3));
  geometry.setAttribute('color', new THREE.BufferAttribute(colours, 3));
  const lineGeometry = geometry.clone();
  lineGeometry.setIndex(springs);
  geometry.setIndex(m.nodes.map((_, p) => p).filter((p) => shown[p]));
  const lines = new THREE.LineSegments(lineGeometry,
    new THREE.LineBasicMaterial({ vertexColors: true, transparent: true, opacity: 0.8 }));
  const points = new THREE.Points(geometry, new THREE.PointsMaterial({ size: 0.2, vertexColors: true }));
  scene.add(lines, points);
  tissue = { points, lines, positions, colours };
  const size = Math.max(...m.grid);
  camera.position.set(size * 1.3, -size * 1.7, size * 1.1);
  controls.target.set(0, 0, 0);
  controls.update();
  paint();
}

// Deformed positions and colours from the newest frame.
function paint() {
  if (!mesh || !tissue) return;
  const n = mesh.nodes.length;
  const u = last ? last.u : null;
  const norm = (p) => (u ? Math.hypot(u[3 * p], u[3 * p + 1], u[3 * p + 2]) : 0);
  let max = 0;
  for (let p = 0; p < n; p++) max = Math.max(max, norm(p));
  const c = new THREE.Color();
  for (let p = 0; p < n; p++) {
    const r = rest(p);
    for (let d = 0; d < 3; d++) tissue.positions[3 * p + d] = r[d] + (u ? u[3 * p + d] : 0);
    colour(max > 0 ? norm(p) / max : 0, c);
    tissue.colours.set([c.r, c.g, c.b], 3 * p);
  }
  for (const obj of [tissue.points, tissue.lines]) {
    obj.geometry.attributes.position.array.set(tissue.positions);
    obj.geometry.attributes.color.array.set(tissue.colours);
    obj.geometry.attributes.position.needsUpdate = true;
    obj.geometry.attributes.color.needsUpdate = true;
  }
  const t = rest(mesh.tools[0]);
  toolGroup.position.set(t[0] + toolU[0], t[1] + toolU[1], t[2] + toolU[2]);
  readout.dataset.handle = toolU.join(',');
  if (last) {
    // Displacement tool: the force at the tool. Force tool: the load at the moved tool.
    const force = forceTool();
    const f = new THREE.Vector3(...(force ? last.tool : last.force));
    const at = force ? last.force : last.tool;
    const solved = new THREE.Vector3(t[0] + at[0], t[1] + at[1], t[2] + at[2]);
    arrow.position.copy(solved);
    arrow.visible = f.length() > 0;
    if (arrow.visible) pointArrow(f.clone().normalize(), Math.min(0.8 + 1.5 * Math.log1p(f.length()), 5));
    $('colorbar-max').textContent = max.toExponential(2);
  }
}

const fmt = (v) => v.map((x) => x.toFixed(3)).join(', ');
const forceTool = () => mesh && mesh.kind === 'force';
function show(f) {
  last = f;
  if (!moved) toolU = f.tool.slice();
  const unit = forceTool() ? 'm' : 'N';
  $('solver').textContent = (f.solver.startsWith('host') ? 'host f64 reference' : 'target (QEMU / board)')
    + (f.solver.endsWith('(dynamic)') ? ', dynamic: one time step per frame' : '');
  $('tool').textContent = forceTool() ? `(${fmt(f.tool)}) N` : `(${fmt(f.tool)})`;
  $('force').textContent = `(${f.force.map((x) => x.toExponential(3)).join(', ')}) ${unit}`;
  $('force-norm').textContent = `${f.force_norm.toExponential(4)} ${unit}`;
  $('fps').textContent = f.fps.toFixed(0);
  $('cycles').textContent = f.cycles == null ? '–' : f.cycles.toLocaleString('en');
  $('rate').textContent = f.frames_per_s_at_100mhz == null ? '–'
    : `${f.frames_per_s_at_100mhz.toFixed(0)} frames/s`;
  $('iterations').textContent = f.iterations;
  $('lag').textContent = `${f.dropped} / ${f.lag_ms.toFixed(0)} ms`;
  paused = f.paused;
  $('pause').textContent = paused ? 'Resume' : 'Pause';
  Object.assign(readout.dataset, {
    frame: f.frame, solver: f.solver, tool: f.tool.join(','), force: f.force.join(','),
    forceNorm: f.force_norm, uMax: f.u_max, iterations: f.iterations,
    cycles: f.cycles ?? '', dropped: f.dropped, paused: f.paused, fps: f.fps, lagMs: f.lag_ms,
  });
  paint();
}

function send(message) {
  if (socket && socket.readyState === WebSocket.OPEN) socket.send(JSON.stringify(message));
}
function moveTool(u) {
  moved = true;
  toolU = u;
  readout.dataset.requested = u.join(',');
  paint();
  send({ type: 'tool', u });
}

function connect() {
  socket = new WebSocket(`ws://${location.hostname}:${wsPort}/`);
  moved = false;
  socket.onopen = () => { $('status').textContent = 'connected'; readout.dataset.connected = 'true'; };
  socket.onclose = () => {
    $('status').textContent = 'disconnected — reconnecting…';
    readout.dataset.connected = 'false';
    setTimeout(connect, 1000);
  };
  socket.onmessage = (event) => {
    const m = JSON.parse(event.data);
    if (m.type === 'mesh') buildMesh(m);
    else if (m.type === 'frame') show(m);
    else if (m.type === 'error') {
      $('status').textContent = `server: ${m.message}`;
      readout.dataset.error = m.message;
    }
  };
}
connect();

$('pause').onclick = () => send({ type: 'pause', paused: !paused });
$('reset').onclick = () => { moved = true; toolU = [0, 0, 0]; paint(); send({ type: 'reset' }); };
const KEYS = {
  ArrowLeft: [0, -STEP], a: [0, -STEP], ArrowRight: [0, STEP], d: [0, STEP],
  s: [1, -STEP], w: [1, STEP], ArrowDown: [2, -STEP], ArrowUp: [2, STEP],
};
window.addEventListener('keydown', (e) => {
  if (e.key === ' ') { $('pause').click(); e.preventDefault(); return; }
  if (e.key === 'r') { $('reset').click(); return; }
  const k = KEYS[e.key];
  if (!k) return;
  e.preventDefault();
  const u = toolU.slice();
  u[k[0]] = Math.round((u[k[0]] + k[1]) * 1000) / 1000;
  moveTool(u);
});

// Dragging the tool: along the plane through it that faces the camera.
const raycaster = new THREE.Raycaster();
const plane = new THREE.Plane();
let dragging = false;
function ray(e) {
  const r = renderer.domElement.getBoundingClientRect();
  const p = new THREE.Vector2(((e.clientX - r.left) / r.width) * 2 - 1, -((e.clientY - r.top) / r.height) * 2 + 1);
  raycaster.setFromCamera(p, camera);
}
renderer.domElement.addEventListener('pointerdown', (e) => {
  ray(e);
  if (raycaster.intersectObject(toolTip).length === 0) return;
  dragging = true;
  controls.enabled = false;
  plane.setFromNormalAndCoplanarPoint(camera.getWorldDirection(new THREE.Vector3()), toolGroup.position);
  renderer.domElement.setPointerCapture(e.pointerId);
});
renderer.domElement.addEventListener('pointermove', (e) => {
  if (!dragging || !mesh) return;
  ray(e);
  const hit = raycaster.ray.intersectPlane(plane, new THREE.Vector3());
  if (!hit) return;
  const t = rest(mesh.tools[0]);
  moveTool([hit.x - t[0], hit.y - t[1], hit.z - t[2]].map((v) => Math.round(v * 1000) / 1000));
});
renderer.domElement.addEventListener('pointerup', () => { dragging = false; controls.enabled = true; });

const projected = new THREE.Vector3();
function animate() {
  requestAnimationFrame(animate);
  controls.update();
  renderer.render(scene, camera);
  // Where the tool is on the screen (CSS pixels), for tests that drag it.
  projected.copy(toolGroup.position).project(camera);
  const r = renderer.domElement.getBoundingClientRect();
  readout.dataset.toolScreen = [r.left + (projected.x + 1) / 2 * r.width,
    r.top + (1 - projected.y) / 2 * r.height].map((v) => v.toFixed(1)).join(',');
}
animate();
