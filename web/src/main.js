// CAVIAR view: the run's scene in 3D, a timeline, and plots. Talks only to the server
// that served it (same origin): /api/run, /api/data, /api/events (SSE), /api/frame, /api/layer, /mesh/N.
// This module holds the data merged from the server, the step shown, the plots, the timeline
// and the page's loop; the scene is scene3d.js, view.* drawings overlays.js, the side panel
// panel.js, the shared state state.js.
import * as THREE from 'three';
import { LinePlot, EventPlot, lastIndexAtOrBefore } from './plots.js';
import { $, PALETTE, S, avg, note } from './state.js';
import {
  BEAM_HALF_ANGLE, LOS_COLOR, SOFTWARE_GL, Y, addPoints, beamObject, beamPool, camera, controls, entity,
  layerGroup, loadScene, radioAt, reframe, renderer, resize, scaleMarkers, scene, setupTx,
} from './scene3d.js';
import { drawView } from './overlays.js';
import { currentFrame, updateFrame, updateInfo } from './panel.js';

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
  get viewObjects() { return S.drawnViewObjects; },
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
