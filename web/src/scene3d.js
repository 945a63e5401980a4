// The 3D scene (three.js): renderer, camera and controls, the entities' markers, labels and
// trails, the scene's meshes, the transmitter and the beam cones.
import * as THREE from 'three';
import { OrbitControls } from 'three/examples/jsm/controls/OrbitControls.js';
import { PLYLoader } from 'three/examples/jsm/loaders/PLYLoader.js';
import { lastIndexAtOrBefore } from './plots.js';
import { $, PALETTE, S, note } from './state.js';

const TYPE_COLOR = { UAV: 0xffa726, CAR: 0x42a5f5, VEHICLE: 0x42a5f5, PEDESTRIAN: 0x66bb6a, PERSON: 0x66bb6a };
export const LOS_COLOR = { true: 0x43d17a, false: 0xff5252, null: 0x9e9e9e };
export const BEAM_HALF_ANGLE = THREE.MathUtils.degToRad(6); // illustrative width, not the array's pattern

// ---------------------------------------------------------------- three.js
// A software rasteriser (SwiftShader, llvmpipe: no GPU) spends most of a frame on
// multisampling: without a GPU the view renders without it.
export const SOFTWARE_GL = (() => {
  try {
    const gl = document.createElement('canvas').getContext('webgl2');
    const ext = gl && gl.getExtension('WEBGL_debug_renderer_info');
    const name = ext ? String(gl.getParameter(ext.UNMASKED_RENDERER_WEBGL)) : '';
    gl && gl.getExtension('WEBGL_lose_context')?.loseContext();
    return /swiftshader|llvmpipe|softpipe|software/i.test(name);
  } catch (e) { return false; }
})();
const container = $('scene');
export const renderer = new THREE.WebGLRenderer({ antialias: !SOFTWARE_GL });
renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
container.appendChild(renderer.domElement);
export const scene = new THREE.Scene();
scene.background = new THREE.Color(0x10141b);
THREE.Object3D.DEFAULT_UP.set(0, 0, 1);
export const camera = new THREE.PerspectiveCamera(50, 1, 1, 20000);
camera.up.set(0, 0, 1);
camera.position.set(-600, -700, 500);
export const controls = new OrbitControls(camera, renderer.domElement);
controls.target.set(-150, 50, 0);
controls.addEventListener('change', () => { S.dirty = true; });
scene.add(new THREE.HemisphereLight(0xdfe8ff, 0x3a4030, 1.2));
const sun = new THREE.DirectionalLight(0xffffff, 1.6);
sun.position.set(-300, -200, 800);
scene.add(sun);
const world = new THREE.Group(); scene.add(world);
const trails = new THREE.Group(); scene.add(trails);
const beams = new THREE.Group(); scene.add(beams);
export const viewGroup = new THREE.Group(); scene.add(viewGroup);
export const layerGroup = new THREE.Group(); scene.add(layerGroup); // view.* images: shown or hidden together

export function resize() {
  const w = container.clientWidth, h = container.clientHeight;
  renderer.setSize(w, h, false);
  camera.aspect = w / Math.max(1, h);
  camera.updateProjectionMatrix();
  S.dirty = true; S.plotsDirty = true;
}
window.addEventListener('resize', resize);

export function labelSprite(text, color = '#ffffff') {
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
export function entity(id, type) {
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

export function addPoints(e, pts) {
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

// ---------------------------------------------------------------- scene meshes
export function loadScene(info) {
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

export function reframe() {
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
export function setupTx(tx) {
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
export const Y = new THREE.Vector3(0, 1, 0);
const beamGeom = new THREE.ConeGeometry(1, 1, 20, 1, true).rotateX(Math.PI).translate(0, 0.5, 0); // apex at origin, opens along +y

export const beamPool = [];
const beamAxis = new THREE.BufferGeometry().setFromPoints([new THREE.Vector3(0, 0, 0), new THREE.Vector3(0, 1, 0)]);
export function beamObject(i) {
  if (!beamPool[i]) {
    const cone = new THREE.Mesh(beamGeom, new THREE.MeshBasicMaterial({ transparent: true, opacity: 0.28, depthWrite: false, side: THREE.DoubleSide }));
    const line = new THREE.Line(beamAxis, new THREE.LineBasicMaterial());
    cone.position.copy(S.txPos); line.position.copy(S.txPos);
    beams.add(cone); beams.add(line);
    beamPool[i] = { cone, line };
  }
  return beamPool[i];
}

export function radioAt(ue, step) {
  const r = S.radio.get(ue);
  if (!r) return null;
  const i = lastIndexAtOrBefore(r.steps, step);
  if (i < 0 || r.steps[i] !== step) return null;
  return { thr: r.thr[i], snr: r.snr[i], los: r.los[i], pair: r.pair[i] };
}

export function scaleMarkers(camPos) {
  for (const e of S.entities.values()) {
    if (!e.mesh.visible) continue;
    const s = Math.max(1, camPos.distanceTo(e.mesh.position) * 0.012);
    e.mesh.scale.setScalar(s);
  }
  if (txObj) txObj.scale.setScalar(Math.max(1, camPos.distanceTo(txObj.position) * 0.012));
}
