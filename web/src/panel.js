// The side panel of a step: its time and status, the entities shown with their link, the
// latest events, and the camera frame of the step.
import { lastIndexAtOrBefore } from './plots.js';
import { $, S, esc } from './state.js';
import { radioAt } from './scene3d.js';

export function updateInfo(step) {
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

let frameLoading = false;
const frameFailures = new Map(); // topic@step -> failed loads
export function currentFrame() { if (S.index >= 0) updateFrame(S.steps[S.index]); }
// A frame loads off-screen and replaces the shown one once decoded: the panel never shows
// a half-loaded or broken image, and the frame it shows is always the step it names. A
// frame the server could not give keeps the last one and is asked again, a few times; a
// step reached while a frame loads gets its own once that one is done.
export function updateFrame(step) {
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
