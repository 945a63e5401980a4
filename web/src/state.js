// The view's state (what the server sent, what is shown) and small page helpers, shared
// by the page's modules.

export const PALETTE = ['#4fc3f7', '#ffb74d', '#ba68c8', '#81c784', '#f06292', '#fff176', '#4db6ac', '#e57373', '#9575cd', '#aed581'];

export const $ = (id) => document.getElementById(id);

// ---------------------------------------------------------------- state
export const S = {
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
  drawnBeams: [], drawnView: 0, drawnViewObjects: 0,
  drawnLayers: 0, layersLoaded: 0, layerBox: null, // image layers of view.* messages (ground overlays)
  ms: { step: null, plots: null, render: null }, // moving averages of the frame's parts
};

export function avg(a, x) { return a === null ? x : 0.9 * a + 0.1 * x; }

// A line in the notes under the scene.
export function note(msg) { const n = $('notes'); n.textContent = (n.textContent ? n.textContent + ' · ' : '') + msg; }

export function esc(s) { return String(s).replace(/[&<>"']/g, (c) => ({ '&': '&amp;', '<': '&lt;', '>': '&gt;', '"': '&quot;', "'": '&#39;' }[c])); }
