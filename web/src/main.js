// CAVIAR view: the run's scene in 3D, a timeline, and plots. Talks only to the server
// that served it (same origin): /api/run, /api/data, /api/events (SSE), /api/frame, /api/layer, /mesh/N.
import * as THREE from 'three';
import { OrbitControls } from 'three/examples/jsm/controls/OrbitControls.js';
import { PLYLoader } from 'three/examples/jsm/loaders/PLYLoader.js';
import { LinePlot, EventPlot, lastIndexAtOrBefore } from './plots.js';

const PALETTE = ['#4fc3f7', '#ffb74d', '#ba68c8', '#81c784', '#f06292', '#fff176', '#4db6ac', '#e57373', '#9575cd', '#aed581'];
const TYPE_COLOR = { UAV: 0xffa726, CAR: 0x42a5f5, VEHICLE: 0x42a5f5, PEDESTRIAN: 0x66bb6a, PERSON: 0x66bb6a };
const LOS_COLOR = { true: 0x43d17a, false: 0xff5252, null: 0x9e9e9e };
const BEAM_HALF_ANGLE = THREE.MathUtils.degToRad(6); // illustrative width, not the array's pattern

const $ = (id) => document.getElementById(id);

// ---------------------------------------------------------------- state
const S = {
  info: null,
  steps: [], times: [],          // recorded steps (ascending) and their virtual times
  index: -1,                      // the shown step's index into steps
  playing: false, speed: 1, playT: 0,
  follow: true,                   // live runs: stay on the newest step
  status: {},
  next: [0, 0],                   // first message / timing step not yet received
  entities: new Map(),            // id -> entity
  radio: new Map(),               // ue -> {steps, thr, snr, los, pair}
  events: [],
  view: [],
  timings: new Map(),             // module -> {steps, ms}
  frames: new Map(),              // topic -> steps[]
  frameTopic: null,
  framePrefixes: [],              // frame topic prefixes, most wanted first (contract)
  frameShown: null,
  dirty: true, plotsDirty: true,
  renders: 0, meshesLoaded: 0, meshesTotal: 0,
  loadedAt: null, ready: false, error: null,
  drawnBeams: [], drawnView: 0,
  drawnLayers: 0, layersLoaded: 0, layerBox: null, // image layers of view.* messages (ground overlays)
  ms: { step: null, plots: null, render: null }, // moving averages of the frame's parts
};

// ---------------------------------------------------------------- three.js
// A software rasteriser (SwiftShader, llvmpipe: no GPU) spends most of a frame on
// multisampling: without a GPU the view renders without it.
const SOFTWARE_GL = (() => {
  try {
    const gl = document.createElement('canvas').getContext('webgl2');
    const ext = gl && gl.getExtension('WEBGL_debug_renderer_info');
    const name = ext ? String(gl.getParameter(ext.UNMASKED_RENDERER_WEBGL)) : '';
    gl && gl.getExtension('WEBGL_lose_context')?.loseContext();
    return /swiftshader|llvmpipe|softpipe|software/i.test(name);
  } catch (e) { return false; }
})();
const container = $('scene');
const renderer = new THREE.WebGLRenderer({ antialias: !SOFTWARE_GL });
renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
container.appendChild(renderer.domElement);
const scene = new THREE.Scene();
scene.background = new THREE.Color(0x10141b);
THREE.Object3D.DEFAULT_UP.set(0, 0, 1);
const camera = new THREE.PerspectiveCamera(50, 1, 1, 20000);
camera.up.set(0, 0, 1);
camera.position.set(-600, -700, 500);
const controls = new OrbitControls(camera, renderer.domElement);
controls.target.set(-150, 50, 0);
controls.addEventListener('change', () => { S.dirty = true; });
scene.add(new THREE.HemisphereLight(0xdfe8ff, 0x3a4030, 1.2));
const sun = new THREE.DirectionalLight(0xffffff, 1.6);
sun.position.set(-300, -200, 800);
scene.add(sun);
const world = new THREE.Group(); scene.add(world);
const trails = new THREE.Group(); scene.add(trails);
const beams = new THREE.Group(); scene.add(beams);
const viewGroup = new THREE.Group(); scene.add(viewGroup);
const layerGroup = new THREE.Group(); scene.add(layerGroup); // view.* images: shown or hidden together

function resize() {
  const w = container.clientWidth, h = container.clientHeight;
  renderer.setSize(w, h, false);
  camera.aspect = w / Math.max(1, h);
  camera.updateProjectionMatrix();
  S.dirty = true; S.plotsDirty = true;
}
window.addEventListener('resize', resize);

function labelSprite(text, color = '#ffffff') {
  const c = document.createElement('canvas');
  const ctx = c.getContext('2d');
  const font = '600 28px sans-serif';
  ctx.font = font;
  const w = Math.ceil(ctx.measureText(text).width) + 12;
  c.width = w; c.height = 40;
  ctx.font = font;
  ctx.fillStyle = 'rgba(10,12,16,0.65)'; ctx.fillRect(0, 0, w, 40);
  ctx.fillStyle = color; ctx.textBaseline = 'middle'; ctx.fillText(text, 6, 21);
  const tex = new THREE.CanvasTexture(c);
  tex.colorSpace = THREE.SRGBColorSpace;
  const sp = new THREE.Sprite(new THREE.SpriteMaterial({ map: tex, depthTest: false, sizeAttenuation: false }));
  const hgt = 0.035;
  sp.scale.set((hgt * w) / 40, hgt, 1);
  sp.center.set(-0.08, -0.2);
  sp.renderOrder = 10;
  return sp;
}

function markerGeometry(type) {
  const t = type.toUpperCase();
  if (t === 'UAV') { const g = new THREE.OctahedronGeometry(1); g.scale(1.2, 1.2, 0.6); return g; }
  if (t === 'CAR' || t === 'VEHICLE') return new THREE.BoxGeometry(1.6, 0.9, 0.7);
  if (t === 'PEDESTRIAN' || t === 'PERSON') return new THREE.CylinderGeometry(0.35, 0.35, 1.4, 10).rotateX(Math.PI / 2);
  return new THREE.SphereGeometry(0.8, 14, 10);
}

// ---------------------------------------------------------------- entities
function entity(id, type) {
  let e = S.entities.get(id);
  if (e) return e;
  const color = TYPE_COLOR[type.toUpperCase()] ?? new THREE.Color(PALETTE[S.entities.size % PALETTE.length]).getHex();
  const mesh = new THREE.Mesh(markerGeometry(type), new THREE.MeshLambertMaterial({ color }));
  mesh.visible = false;
  const label = labelSprite(id);
  label.visible = false;
  const cap = 256;
  const geom = new THREE.BufferGeometry();
  geom.setAttribute('position', new THREE.BufferAttribute(new Float32Array(cap * 3), 3));
  geom.setDrawRange(0, 0);
  const trail = new THREE.Line(geom, new THREE.LineBasicMaterial({ color, transparent: true, opacity: 0.8, depthTest: false }));
  trail.frustumCulled = false;
  trail.renderOrder = 5; // paths stay visible behind buildings
  e = { id, type, color, steps: [], xyz: new Float32Array(cap * 3), n: 0, mesh, label, trail, shown: -1 };
  scene.add(mesh); scene.add(label); trails.add(trail);
  S.entities.set(id, e);
  return e;
}

function addPoints(e, pts) {
  for (const [s, x, y, z] of pts) {
    if (e.n && s <= e.steps[e.n - 1]) continue;
    if (e.n * 3 >= e.xyz.length) {
      const bigger = new Float32Array(e.xyz.length * 2);
      bigger.set(e.xyz);
      e.xyz = bigger;
    }
    e.steps.push(s);
    e.xyz.set([x, y, z], e.n * 3);
    e.n++;
  }
  const attr = e.trail.geometry.getAttribute('position');
  if (attr.array.length < e.xyz.length) {
    e.trail.geometry.setAttribute('position', new THREE.BufferAttribute(e.xyz, 3));
  } else {
    attr.array.set(e.xyz.subarray(0, e.n * 3));
    attr.needsUpdate = true;
  }
  e.shown = -2;
}

// ---------------------------------------------------------------- data
function merge(d) {
  const prevMsg = S.next[0];
  if (d.status) S.status = d.status;
  const last = S.steps.length ? S.steps[S.steps.length - 1] : -1;
  const newSteps = d.steps.filter(([s]) => s > last);
  // steps may come from timings before messages: keep the list sorted
  if (d.steps.some(([s]) => s <= last && !stepKnown(s))) {
    const all = new Map(S.steps.map((s, i) => [s, S.times[i]]));
    for (const [s, t] of d.steps) all.set(s, t);
    const sorted = [...all.entries()].sort((a, b) => a[0] - b[0]);
    S.steps = sorted.map((x) => x[0]); S.times = sorted.map((x) => x[1]);
  } else {
    for (const [s, t] of newSteps) { S.steps.push(s); S.times.push(t); }
  }
  for (const [id, e] of Object.entries(d.entities || {})) addPoints(entity(id, e.type), e.p);
  for (const [ue, rows] of Object.entries(d.radio || {})) {
    let r = S.radio.get(ue);
    if (!r) { r = { steps: [], thr: [], snr: [], los: [], pair: [] }; S.radio.set(ue, r); }
    for (const [s, thr, snr, los, pair] of rows) {
      if (r.steps.length && s <= r.steps[r.steps.length - 1]) continue;
      r.steps.push(s); r.thr.push(thr); r.snr.push(snr); r.los.push(los); r.pair.push(pair);
    }
  }
  for (const ev of d.events || []) if (ev.step >= prevMsg) S.events.push(ev);
  for (const v of d.view || []) if (v.step >= prevMsg) S.view.push(v);
  for (const [m, rows] of Object.entries(d.timings || {})) {
    let t = S.timings.get(m);
    if (!t) { t = { steps: [], ms: [] }; S.timings.set(m, t); }
    for (const [s, ms] of rows) {
      if (t.steps.length && s <= t.steps[t.steps.length - 1]) continue;
      t.steps.push(s); t.ms.push(ms);
    }
  }
  for (const [topic, steps] of Object.entries(d.frames || {})) {
    const f = S.frames.get(topic) || [];
    for (const s of steps) if (!f.length || s > f[f.length - 1]) f.push(s);
    S.frames.set(topic, f);
  }
  if (d.next) S.next = d.next;
  S.plotsDirty = true; S.seriesDirty = true;
}

function stepKnown(s) {
  const i = lastIndexAtOrBefore(S.steps, s);
  return i >= 0 && S.steps[i] === s;
}

// ---------------------------------------------------------------- scene meshes
function loadScene(info) {
  const meshes = info.scene.meshes;
  S.meshesTotal = meshes.length;
  const loader = new PLYLoader();
  const box = new THREE.Box3();
  meshes.forEach((m) => {
    loader.load(m.url, (geom) => {
      geom.computeBoundingBox();
      const bb = geom.boundingBox;
      const flat = bb.max.z - bb.min.z < 0.5;
      const metal = /metal/i.test(m.material);
      const color = flat ? 0x3d5a3a : metal ? 0x5c6bc0 : 0xc9ccd1;
      if (!geom.getAttribute('normal')) geom.computeVertexNormals();
      const mesh = new THREE.Mesh(geom, new THREE.MeshLambertMaterial({ color, side: THREE.DoubleSide, flatShading: true }));
      mesh.name = m.id;
      if (m.matrix) {
        mesh.matrixAutoUpdate = false;
        mesh.matrix.set(...m.matrix);
      }
      world.add(mesh);
      mesh.updateMatrixWorld(true);
      if (!flat) box.union(new THREE.Box3().setFromObject(mesh));
      S.meshesLoaded++;
      if (S.meshesLoaded === meshes.length) { S.sceneBox = box; reframe(); }
      S.dirty = true;
    }, undefined, () => { S.meshesLoaded++; note(`mesh ${m.id} could not be loaded`); });
  });
}

function reframe() {
  // the entities' paths and the Tx where there are entities, else the whole scene, else the image layers
  if (S.entities.size) frame(new THREE.Box3());
  else if (S.sceneBox && !S.sceneBox.isEmpty()) frame(S.sceneBox.clone());
  else frame(S.layerBox ? S.layerBox.clone() : new THREE.Box3());
}

function frame(box) {
  // fit the scene, the Tx and the entities' paths
  for (const e of S.entities.values()) for (let i = 0; i < e.n; i++) box.expandByPoint(new THREE.Vector3(e.xyz[3 * i], e.xyz[3 * i + 1], e.xyz[3 * i + 2]));
  if (S.txPos) box.expandByPoint(S.txPos);
  if (box.isEmpty()) return;
  const c = box.getCenter(new THREE.Vector3());
  const size = Math.max(250, box.getSize(new THREE.Vector3()).length());
  controls.target.copy(c);
  camera.position.set(c.x - 0.2 * size, c.y - 0.45 * size, c.z + 0.85 * size);
  camera.far = size * 20; camera.near = Math.max(0.5, size / 2000);
  camera.updateProjectionMatrix();
  controls.update();
  S.dirty = true;
}

let txObj = null;
function setupTx(tx) {
  if (!tx) return;
  S.txPos = new THREE.Vector3(...tx.position);
  txObj = new THREE.Group();
  const mast = new THREE.Mesh(new THREE.ConeGeometry(1, 2.5, 4).rotateX(Math.PI / 2).translate(0, 0, -1.25), new THREE.MeshLambertMaterial({ color: 0xff3d3d }));
  txObj.add(mast);
  txObj.position.copy(S.txPos);
  scene.add(txObj);
  const l = labelSprite('Tx', '#ff8a80');
  l.position.copy(S.txPos);
  scene.add(l);
}

// ---------------------------------------------------------------- showing a step
const Y = new THREE.Vector3(0, 1, 0);
const beamGeom = new THREE.ConeGeometry(1, 1, 20, 1, true).rotateX(Math.PI).translate(0, 0.5, 0); // apex at origin, opens along +y

const beamPool = [];
const beamAxis = new THREE.BufferGeometry().setFromPoints([new THREE.Vector3(0, 0, 0), new THREE.Vector3(0, 1, 0)]);
function beamObject(i) {
  if (!beamPool[i]) {
    const cone = new THREE.Mesh(beamGeom, new THREE.MeshBasicMaterial({ transparent: true, opacity: 0.28, depthWrite: false, side: THREE.DoubleSide }));
    const line = new THREE.Line(beamAxis, new THREE.LineBasicMaterial());
    cone.position.copy(S.txPos); line.position.copy(S.txPos);
    beams.add(cone); beams.add(line);
    beamPool[i] = { cone, line };
  }
  return beamPool[i];
}

function radioAt(ue, step) {
  const r = S.radio.get(ue);
  if (!r) return null;
  const i = lastIndexAtOrBefore(r.steps, step);
  if (i < 0 || r.steps[i] !== step) return null;
  return { thr: r.thr[i], snr: r.snr[i], los: r.los[i], pair: r.pair[i] };
}

function showStep() {
  if (S.index < 0 || !S.steps.length) return;
  const t0 = performance.now();
  const step = S.steps[S.index];
  const camPos = camera.position;
  for (const e of S.entities.values()) {
    const k = lastIndexAtOrBefore(e.steps, step);
    e.mesh.visible = e.label.visible = k >= 0;
    e.trail.geometry.setDrawRange(0, k + 1);
    if (k < 0) continue;
    e.mesh.position.set(e.xyz[3 * k], e.xyz[3 * k + 1], e.xyz[3 * k + 2]);
    e.label.position.copy(e.mesh.position);
    e.k = k;
  }
  // beams: Tx -> each UE with a radio message at this step (objects reused across steps)
  S.drawnBeams = [];
  let nb = 0;
  if (S.txPos) {
    for (const [ue] of S.radio) {
      const e = S.entities.get(ue);
      const r = radioAt(ue, step);
      if (!r || !e || !e.mesh.visible) continue;
      const to = e.mesh.position.clone().sub(S.txPos);
      const len = to.length();
      if (len < 1e-6) continue;
      const b = beamObject(nb++);
      const color = LOS_COLOR[String(r.los)] ?? LOS_COLOR.null;
      b.cone.material.color.setHex(color);
      b.line.material.color.setHex(color);
      b.cone.quaternion.setFromUnitVectors(Y, to.normalize());
      const rad = len * Math.tan(BEAM_HALF_ANGLE);
      b.cone.scale.set(rad, len, rad);
      b.line.quaternion.copy(b.cone.quaternion);
      b.line.scale.set(1, len, 1);
      b.cone.visible = b.line.visible = true;
      S.drawnBeams.push({ ue, los: r.los, pair: r.pair });
    }
  }
  for (let i = nb; i < beamPool.length; i++) beamPool[i].cone.visible = beamPool[i].line.visible = false;
  drawView(step);
  scaleMarkers(camPos);
  updateInfo(step);
  updateFrame(step);
  S.plotsDirty = true;
  S.dirty = true;
  S.ms.step = avg(S.ms.step, performance.now() - t0);
}

function avg(a, x) { return a === null ? x : 0.9 * a + 0.1 * x; }

function scaleMarkers(camPos) {
  for (const e of S.entities.values()) {
    if (!e.mesh.visible) continue;
    const s = Math.max(1, camPos.distanceTo(e.mesh.position) * 0.012);
    e.mesh.scale.setScalar(s);
  }
  if (txObj) txObj.scale.setScalar(Math.max(1, camPos.distanceTo(txObj.position) * 0.012));
}

let viewKey = '';
function drawView(step) {
  // latest view.* message of each (source, topic) at or before the step
  const latest = new Map();
  for (let i = 0; i < S.view.length; i++) {
    const v = S.view[i];
    if (v.step > step) continue;
    const k = v.source + '|' + v.topic;
    const p = latest.get(k);
    if (p === undefined || S.view[p].step <= v.step) latest.set(k, i);
  }
  const key = [...latest.values()].sort().join(',');
  if (key === viewKey) return;
  viewKey = key;
  viewGroup.clear();
  clearLayers();
  let n = 0;
  for (const i of latest.values()) {
    const d = S.view[i].data || {};
    for (const im of Array.isArray(d.images) ? d.images : []) if (addLayer(im)) n++;
    for (const p of Array.isArray(d.points) ? d.points : []) {
      if (typeof p.x !== 'number' || typeof p.y !== 'number') continue;
      const g = new THREE.BufferGeometry().setAttribute('position', new THREE.Float32BufferAttribute([p.x, p.y, p.z || 0], 3));
      viewGroup.add(new THREE.Points(g, new THREE.PointsMaterial({ color: safeColor(p.color), size: p.size || 6, sizeAttenuation: false })));
      if (p.label) { const l = labelSprite(String(p.label), safeCss(p.color)); l.position.set(p.x, p.y, p.z || 0); viewGroup.add(l); }
      n++;
    }
    for (const ln of Array.isArray(d.lines) ? d.lines : []) {
      const pts = (Array.isArray(ln.points) ? ln.points : []).filter((q) => Array.isArray(q) && q.length >= 2).map((q) => new THREE.Vector3(q[0], q[1], q[2] || 0));
      if (pts.length < 2) continue;
      viewGroup.add(new THREE.Line(new THREE.BufferGeometry().setFromPoints(pts), new THREE.LineBasicMaterial({ color: safeColor(ln.color) })));
      n++;
    }
    for (const lb of Array.isArray(d.labels) ? d.labels : []) {
      if (typeof lb.x !== 'number' || typeof lb.y !== 'number') continue;
      const l = labelSprite(String(lb.text ?? ''), safeCss(lb.color)); l.position.set(lb.x, lb.y, lb.z || 0); viewGroup.add(l);
      n++;
    }
  }
  S.drawnView = n;
  S.drawnLayers = layerGroup.children.filter((o) => o.isMesh).length;
}

// Image layers: a PNG of the run directory (served by /api/layer only if a view.* message
// names it) on a horizontal plane at height z over extent [x0, x1, y0, y1]; its first row
// is the north edge (y1). One pixel per texel, no smoothing: a map's cells stay cells.
const layerTextures = new Map(); // file -> texture (loaded once)
function layerTexture(file) {
  let tex = layerTextures.get(file);
  if (!tex) {
    tex = new THREE.TextureLoader().load(`/api/layer?file=${encodeURIComponent(file)}`,
      () => { S.layersLoaded++; S.dirty = true; },
      undefined, () => note(`image layer ${file} could not be loaded`));
    tex.colorSpace = THREE.SRGBColorSpace;
    tex.magFilter = THREE.NearestFilter;
    tex.minFilter = THREE.LinearFilter;
    tex.generateMipmaps = false;
    layerTextures.set(file, tex);
  }
  return tex;
}

function addLayer(im) {
  const ex = im && im.extent;
  if (typeof im?.file !== 'string' || !/\.png$/i.test(im.file) || !Array.isArray(ex) || ex.length !== 4
      || !ex.every(Number.isFinite)) return false;
  const [x0, x1, y0, y1] = ex;
  if (!(x1 > x0 && y1 > y0)) return false;
  const z = Number.isFinite(im.z) ? im.z : 0;
  const opacity = Number.isFinite(im.opacity) ? Math.min(1, Math.max(0, im.opacity)) : 0.6;
  const mat = new THREE.MeshBasicMaterial({ map: layerTexture(im.file), transparent: true, opacity, side: THREE.DoubleSide, depthWrite: false });
  const plane = new THREE.Mesh(new THREE.PlaneGeometry(x1 - x0, y1 - y0), mat); // in xy: horizontal, +y is the image's top
  plane.position.set((x0 + x1) / 2, (y0 + y1) / 2, z);
  plane.renderOrder = 1;
  layerGroup.add(plane);
  S.layerBox = (S.layerBox || new THREE.Box3()).union(new THREE.Box3(new THREE.Vector3(x0, y0, z), new THREE.Vector3(x1, y1, z)));
  if (im.label) { const l = labelSprite(String(im.label)); l.position.set(x0, y1, z); layerGroup.add(l); }
  return true;
}

function clearLayers() {
  for (const o of layerGroup.children) {
    o.geometry?.dispose();
    if (o.isSprite) o.material.map?.dispose();
    o.material?.dispose(); // layer textures stay cached
  }
  layerGroup.clear();
  S.layerBox = null;
}

function safeCss(c) { return typeof c === 'string' && /^#[0-9a-fA-F]{3,8}$/.test(c) ? c : '#ffeb3b'; }
function safeColor(c) { return new THREE.Color(safeCss(c).slice(0, 7)); }

function updateInfo(step) {
  const t = S.times[S.index];
  const st = S.status.status || (S.status.waiting ? 'waiting' : '?');
  $('stepinfo').textContent = `step ${step} / ${S.steps[S.steps.length - 1]}  ·  t = ${t.toFixed(2)} s  ·  ${st}`;
  $('timeline').max = String(Math.max(0, S.steps.length - 1));
  $('timeline').value = String(S.index);
  const rows = [];
  for (const e of S.entities.values()) {
    if (!e.mesh.visible) continue;
    const p = e.mesh.position;
    const r = radioAt(e.id, step);
    let s = `<b style="color:#${e.color.toString(16).padStart(6, '0')}">${esc(e.id)}</b> ${esc(e.type)} (${p.x.toFixed(1)}, ${p.y.toFixed(1)}, ${p.z.toFixed(1)})`;
    if (r) {
      if (r.thr !== null) s += ` · ${r.thr.toFixed(1)} Mbit/s`;
      if (r.snr !== null) s += ` · SNR ${r.snr.toFixed(1)} dB`;
      s += r.los === null ? ' · LOS ?' : r.los ? ' · <span class="los">LOS</span>' : ' · <span class="nlos">NLOS</span>';
      if (r.pair !== null) s += ` · beam pair ${r.pair}`;
    }
    rows.push(s);
    if (rows.length >= 8) break;
  }
  const more = S.entities.size - rows.length;
  $('entities').innerHTML = rows.join('<br>') + (more > 0 ? `<br><i>${more} more</i>` : '');
  const recent = S.events.filter((e) => e.step <= step).slice(-5).reverse();
  $('events').innerHTML = recent.length ? recent.map((e) => `<div>${e.time.toFixed(1)} s <b>${esc(e.topic)}</b> ${esc(e.text)}</div>`).join('') : '<i>no event yet</i>';
}

function esc(s) { return String(s).replace(/[&<>"']/g, (c) => ({ '&': '&amp;', '<': '&lt;', '>': '&gt;', '"': '&quot;', "'": '&#39;' }[c])); }

let frameLoading = false;
const frameFailures = new Map(); // topic@step -> failed loads
function currentFrame() { if (S.index >= 0) updateFrame(S.steps[S.index]); }
// A frame loads off-screen and replaces the shown one once decoded: the panel never shows
// a half-loaded or broken image, and the frame it shows is always the step it names. A
// frame the server could not give keeps the last one and is asked again, a few times; a
// step reached while a frame loads gets its own once that one is done.
function updateFrame(step) {
  const topic = S.frameTopic;
  if (!topic) return;
  const steps = S.frames.get(topic) || [];
  const i = lastIndexAtOrBefore(steps, step);
  const fs = i >= 0 ? steps[i] : null;
  if (fs === S.frameShown || frameLoading) return;
  if (fs === null) { $('frame').removeAttribute('src'); $('framenote').textContent = `${topic}: no frame yet`; S.frameShown = null; return; }
  const key = `${topic}@${fs}`;
  if ((frameFailures.get(key) || 0) >= 3) return;
  frameLoading = true;
  const next = new Image();
  next.id = 'frame';
  next.alt = '';
  next.onload = () => {
    frameLoading = false;
    if (topic !== S.frameTopic) return;
    $('frame').replaceWith(next);
    S.frameShown = fs;
    $('framenote').textContent = `${topic} · step ${fs}`;
    currentFrame(); // the step moved on while this one loaded
  };
  next.onerror = () => {
    frameLoading = false;
    frameFailures.set(key, (frameFailures.get(key) || 0) + 1);
    $('frame').classList.add('stale'); // the last frame stays, dimmed, under a note saying so
    $('framenote').textContent = `${topic}: frame of step ${fs} unavailable`;
    setTimeout(currentFrame, 300);
  };
  next.src = `/api/frame?topic=${encodeURIComponent(topic)}&step=${fs}`;
}

// ---------------------------------------------------------------- plots
const plotBox = $('plots');
const thrPlot = new LinePlot(plotBox, 'throughput per UE', 'Mbit/s');
const snrPlot = new LinePlot(plotBox, 'SNR per UE', 'dB');
const evPlot = new EventPlot(plotBox, 'events', '');
const timePlot = new LinePlot(plotBox, 'wall time per module per step', 'ms');
timePlot.empty = 'no timings';
timePlot.robust = true;
const plots = [thrPlot, snrPlot, evPlot, timePlot];

// Which topics hold what is the plugins' to say (their view contract, in /api/run): the
// page names no domain topic of its own.
function applyContract(c) {
  c = c || {};
  const list = (xs) => (xs || []).join(', ');
  const none = (what) => `no ${what} topic declared (no plugin's view contract)`;
  thrPlot.empty = (c.throughput || []).length ? `no ${list(c.throughput)}` : none('throughput');
  snrPlot.empty = (c.link || []).length ? `no SNR recorded (${list(c.link)})` : none('link');
  const ev = [...(c.event_prefixes || []).map((p) => p + '*'), ...(c.event_topics || [])];
  evPlot.empty = ev.length ? `no event (${ev.join(', ')})` : 'no event';
  S.framePrefixes = c.frame_prefixes || [];
  if (!S.frameTopic) {
    $('framenote').textContent = S.framePrefixes.length
      ? `no frames recorded (${S.framePrefixes.map((p) => p + '*').join(' / ')})` : none('frame');
  }
  for (const p of plots) p.dirty = true;
}

function frameRank(topic) {
  const i = S.framePrefixes.findIndex((p) => topic.startsWith(p));
  return i < 0 ? S.framePrefixes.length : i;
}

function stepTime(s) {
  const i = lastIndexAtOrBefore(S.steps, s);
  return i >= 0 ? S.times[i] : 0;
}

function rebuildSeries() {
  const ues = [...S.radio.keys()];
  const color = (k, i) => { const e = S.entities.get(k); return e ? '#' + e.color.toString(16).padStart(6, '0') : PALETTE[i % PALETTE.length]; };
  thrPlot.setSeries(ues.map((u, i) => { const r = S.radio.get(u); return { name: u, color: color(u, i), x: r.steps.map(stepTime), y: r.thr }; }).filter((s) => s.y.some((v) => v !== null)));
  snrPlot.setSeries(ues.map((u, i) => { const r = S.radio.get(u); return { name: u, color: color(u, i), x: r.steps.map(stepTime), y: r.snr }; }).filter((s) => s.y.some((v) => v !== null)));
  const byTopic = new Map();
  for (const e of S.events) { if (!byTopic.has(e.topic)) byTopic.set(e.topic, []); byTopic.get(e.topic).push(e.time); }
  evPlot.setSeries([...byTopic.entries()].map(([t, xs], i) => ({ name: t, color: PALETTE[(i + 3) % PALETTE.length], x: xs, y: [] })));
  timePlot.setSeries([...S.timings.entries()].map(([m, t], i) => ({ name: m, color: PALETTE[i % PALETTE.length], x: t.steps.map(stepTime), y: t.ms })));
  const x0 = S.times.length ? S.times[0] : 0, x1 = S.times.length ? S.times[S.times.length - 1] : 1;
  for (const p of plots) p.setRange(x0, Math.max(x1, x0 + 1e-6));
  if (!S.frameTopic && S.frames.size) {
    const topics = [...S.frames.keys()].sort((a, b) => (frameRank(a) - frameRank(b)) || a.localeCompare(b));
    S.frameTopic = topics[0];
    $('framenote').textContent = S.frameTopic;
    currentFrame(); // the step was shown before its frames' topic was known
  }
  S.seriesDirty = false;
}

// ---------------------------------------------------------------- timeline and playback
function setIndex(i, fromUser = false) {
  if (!S.steps.length) return;
  i = Math.max(0, Math.min(S.steps.length - 1, i | 0));
  if (fromUser) S.follow = i === S.steps.length - 1;
  $('follow').checked = S.follow;
  if (i === S.index && !fromUser) return;
  S.index = i;
  S.playT = S.times[i];
  showStep();
}

$('timeline').addEventListener('input', (ev) => { S.playing = false; syncPlay(); setIndex(+ev.target.value, true); });
$('play').addEventListener('click', () => {
  S.playing = !S.playing;
  if (S.playing && S.index >= S.steps.length - 1) setIndex(0, true);
  if (S.playing) S.follow = false;
  syncPlay();
});
$('speed').addEventListener('change', (ev) => { S.speed = +ev.target.value; });
$('layers').addEventListener('change', (ev) => { layerGroup.visible = ev.target.checked; S.dirty = true; });
$('follow').addEventListener('change', (ev) => { S.follow = ev.target.checked; if (S.follow) { S.playing = false; syncPlay(); setIndex(S.steps.length - 1); } });
function syncPlay() { $('play').textContent = S.playing ? '❚❚ pause' : '▶ play'; }
window.addEventListener('keydown', (ev) => {
  if (ev.target.tagName === 'SELECT') return;
  if (ev.key === ' ') { $('play').click(); ev.preventDefault(); }
});

// ---------------------------------------------------------------- loop
let lastT = performance.now();
function loop(now) {
  const dt = Math.min(0.25, (now - lastT) / 1000);
  lastT = now;
  if (S.playing && S.steps.length) {
    S.playT += dt * S.speed;
    const i = lastIndexAtOrBefore(S.times, S.playT);
    if (i >= S.steps.length - 1) {
      setIndex(S.steps.length - 1);
      if (!live()) S.playing = false; else { S.playing = false; S.follow = true; }
      syncPlay();
    } else if (i !== S.index) { const t = S.playT; setIndex(i); S.playT = t; }
  }
  if (S.seriesDirty) rebuildSeries();
  if (S.plotsDirty) {
    const x = S.index >= 0 ? S.times[S.index] : null;
    const t0 = performance.now();
    for (const p of plots) { p.cursor = x; p.draw(); }
    S.plotsDirty = false;
    S.ms.plots = avg(S.ms.plots, performance.now() - t0);
  }
  if (S.dirty) {
    controls.update();
    scaleMarkers(camera.position);
    const t0 = performance.now();
    renderer.render(scene, camera);
    S.renders++;
    S.ms.render = avg(S.ms.render, performance.now() - t0);
    S.dirty = false;
  }
  requestAnimationFrame(loop);
}

function live() { return S.status.status === 'running' || S.status.waiting; }

function note(msg) { const n = $('notes'); n.textContent = (n.textContent ? n.textContent + ' · ' : '') + msg; }

// ---------------------------------------------------------------- start
async function getJSON(url) {
  const r = await fetch(url, { cache: 'no-store' });
  if (!r.ok) throw new Error(`${url}: HTTP ${r.status}`);
  return r.json();
}

function afterData() {
  const wasEmpty = S.index < 0;
  if (S.follow || wasEmpty) setIndex(S.follow ? S.steps.length - 1 : 0);
  else { $('timeline').max = String(Math.max(0, S.steps.length - 1)); updateInfo(S.steps[S.index]); }
  $('follow').disabled = !live();
  $('livebadge').textContent = live() ? 'LIVE' : (S.status.status || '');
  $('livebadge').className = live() ? 'badge live' : 'badge';
  if (S.status.error) $('error').textContent = `run error: ${S.status.error}`;
}

async function start() {
  resize();
  requestAnimationFrame(loop);
  try {
    const info = await getJSON('/api/run');
    S.info = info;
    document.title = `CAVIAR view · ${info.name}`;
    $('runname').textContent = info.name;
    $('runpath').textContent = info.run_dir;
    applyContract(info.contract);
    setupTx(info.tx);
    if (!info.tx) note('no transmitter position in the config: no Tx, no beams');
    else note(`Tx from ${info.tx.origin}`);
    note(`scene ${info.scene.name}${info.scene.xml ? '' : ' (not found: no meshes)'}`);
    note('beam cone: Tx → served UE, 6° half-width, illustrative (the steering angle is not recorded)');
    note('markers not to scale');
    loadScene(info);
    const d = await getJSON('/api/data?since=0');
    S.status = d.status;
    S.follow = d.status.status === 'running' || !!d.status.waiting;
    merge(d);
    S.loadedAt = performance.now();
    afterData();
    reframe();
    S.ready = true;
    if (live()) connect();
  } catch (err) {
    S.error = String(err);
    $('error').textContent = String(err);
  }
}

function connect() {
  const es = new EventSource(`/api/events?since=${S.next[0]}&tsince=${S.next[1]}`);
  es.onmessage = (ev) => {
    const d = JSON.parse(ev.data);
    merge(d);
    afterData();
    if (!live()) es.close();
  };
  es.onerror = () => {
    if (!live()) es.close();
  };
}

// Read-only state for tests and scripts.
window.caviarView = Object.freeze({
  get ready() { return S.ready; },
  get error() { return S.error; },
  get step() { return S.index >= 0 ? S.steps[S.index] : null; },
  get time() { return S.index >= 0 ? S.times[S.index] : null; },
  get index() { return S.index; },
  get nSteps() { return S.steps.length; },
  get lastStep() { return S.steps.length ? S.steps[S.steps.length - 1] : null; },
  get status() { return S.status.status ?? null; },
  get live() { return live(); },
  get following() { return S.follow; },
  get playing() { return S.playing; },
  get entityCount() { let n = 0; for (const e of S.entities.values()) if (e.mesh.visible) n++; return n; },
  get entities() {
    const o = {};
    for (const e of S.entities.values()) if (e.mesh.visible) o[e.id] = [e.mesh.position.x, e.mesh.position.y, e.mesh.position.z];
    return o;
  },
  get beams() { return S.drawnBeams.map((b) => ({ ...b })); },
  get viewPrimitives() { return S.drawnView; },
  get imageLayers() { return S.drawnLayers; },
  get imageLayersShown() { return layerGroup.visible ? S.drawnLayers : 0; },
  get imageLayersLoaded() { return S.layersLoaded; },
  // where the scene point (x, y, z) is on the page (CSS pixels), as last rendered
  project(x, y, z) {
    camera.updateMatrixWorld();
    const v = new THREE.Vector3(x, y, z).project(camera);
    const r = renderer.domElement.getBoundingClientRect();
    return [r.left + (v.x + 1) / 2 * r.width, r.top + (1 - v.y) / 2 * r.height];
  },
  get meshesLoaded() { return S.meshesLoaded; },
  get meshesTotal() { return S.meshesTotal; },
  get renders() { return S.renders; },
  get frameMs() { return { ...S.ms }; },
  get softwareGL() { return SOFTWARE_GL; },
  get events() { return S.events.length; },
  get frameTopic() { return S.frameTopic; },
  get frameShown() { return S.frameShown; },
});

start();
