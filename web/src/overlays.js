// What plugins draw on the scene through view.* messages: points, lines, labels and image
// layers (PNG ground overlays the server serves only when a message names them).
import * as THREE from 'three';
import { S, note } from './state.js';
import { labelSprite, layerGroup, viewGroup } from './scene3d.js';

let viewKey = '';
export function drawView(step) {
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
    // One THREE.Points per colour and size, whatever the number of points (a LiDAR sweep is
    // thousands): one draw call each instead of one per point.
    const clouds = new Map(); // color|size -> [x, y, z, ...]
    for (const p of Array.isArray(d.points) ? d.points : []) {
      if (typeof p.x !== 'number' || typeof p.y !== 'number') continue;
      const key = safeCss(p.color) + '|' + (p.size || 6);
      if (!clouds.has(key)) clouds.set(key, []);
      clouds.get(key).push(p.x, p.y, p.z || 0);
      if (p.label) { const l = labelSprite(String(p.label), safeCss(p.color)); l.position.set(p.x, p.y, p.z || 0); viewGroup.add(l); }
      n++;
    }
    for (const [key, xyz] of clouds) {
      const [css, size] = key.split('|');
      const g = new THREE.BufferGeometry().setAttribute('position', new THREE.Float32BufferAttribute(xyz, 3));
      viewGroup.add(new THREE.Points(g, new THREE.PointsMaterial({ color: safeColor(css), size: Number(size), sizeAttenuation: false })));
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
  S.drawnViewObjects = viewGroup.children.length;
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
