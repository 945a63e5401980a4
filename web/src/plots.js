// Small canvas plots: lines over time with a cursor, and event markers.
// The series are drawn once into an off-screen canvas; moving the cursor only blits it.

const PAD = { l: 46, r: 8, t: 18, b: 18 };

function niceTicks(lo, hi, n) {
  const span = hi - lo || 1;
  const step0 = span / Math.max(1, n);
  const mag = Math.pow(10, Math.floor(Math.log10(step0)));
  const step = [1, 2, 5, 10].map((m) => m * mag).find((s) => s >= step0) || step0;
  const out = [];
  for (let v = Math.ceil(lo / step) * step; v <= hi + 1e-9 * span; v += step) out.push(v);
  return out;
}

function fmt(v) {
  const a = Math.abs(v);
  if (a >= 1e4 || (a > 0 && a < 1e-2)) return v.toExponential(1);
  return a >= 100 ? v.toFixed(0) : a >= 10 ? v.toFixed(1) : v.toFixed(2);
}

export class LinePlot {
  constructor(parent, title, unit) {
    this.box = document.createElement('div');
    this.box.className = 'plot';
    this.canvas = document.createElement('canvas');
    this.box.appendChild(this.canvas);
    parent.appendChild(this.box);
    this.title = title;
    this.unit = unit;
    this.series = []; // {name, color, x: number[], y: (number|null)[]}
    this.x0 = 0; this.x1 = 1;
    this.cursor = null;
    this.cache = document.createElement('canvas');
    this.dirty = true;
    this.empty = '';
  }

  setSeries(series) { this.series = series; this.dirty = true; }
  setRange(x0, x1) { if (x0 !== this.x0 || x1 !== this.x1) { this.x0 = x0; this.x1 = x1; this.dirty = true; } }

  _size() {
    const dpr = window.devicePixelRatio || 1;
    const w = Math.max(50, Math.floor(this.box.clientWidth * dpr));
    const h = Math.max(40, Math.floor(this.box.clientHeight * dpr));
    if (this.canvas.width !== w || this.canvas.height !== h) {
      this.canvas.width = w; this.canvas.height = h;
      this.cache.width = w; this.cache.height = h;
      this.dirty = true;
    }
    return dpr;
  }

  _yrange() {
    let lo = Infinity, hi = -Infinity;
    for (const s of this.series) for (const v of s.y) if (v !== null && v > -300) { if (v < lo) lo = v; if (v > hi) hi = v; }
    if (this.robust && isFinite(hi)) {
      // a few outliers (a module's last step writing its report) would flatten the rest
      const all = [];
      for (const s of this.series) for (const v of s.y) if (v !== null) all.push(v);
      all.sort((a, b) => a - b);
      const q = all[Math.floor(0.99 * (all.length - 1))] * 1.5;
      if (q > 0 && q < hi) { hi = q; this.clipped = true; } else this.clipped = false;
    }
    if (!isFinite(lo)) return [0, 1];
    if (lo === hi) { lo -= 1; hi += 1; }
    const p = (hi - lo) * 0.06;
    return [lo - p, hi + p];
  }

  _render(dpr) {
    const c = this.cache.getContext('2d');
    const W = this.cache.width, H = this.cache.height;
    c.setTransform(1, 0, 0, 1, 0, 0);
    c.clearRect(0, 0, W, H);
    c.scale(dpr, dpr);
    const w = W / dpr, h = H / dpr;
    const pw = w - PAD.l - PAD.r, ph = h - PAD.t - PAD.b;
    const [y0, y1] = this._yrange();
    this.map = { w, h, pw, ph, y0, y1 };
    const X = (x) => PAD.l + ((x - this.x0) / ((this.x1 - this.x0) || 1)) * pw;
    const Y = (y) => PAD.t + (1 - (y - y0) / ((y1 - y0) || 1)) * ph;
    c.font = '10px sans-serif';
    c.fillStyle = '#9aa4b2';
    c.strokeStyle = '#2a3140';
    c.lineWidth = 1;
    for (const t of niceTicks(y0, y1, 3)) {
      const yy = Math.round(Y(t)) + 0.5;
      c.beginPath(); c.moveTo(PAD.l, yy); c.lineTo(PAD.l + pw, yy); c.stroke();
      c.textAlign = 'right'; c.textBaseline = 'middle'; c.fillText(fmt(t), PAD.l - 4, yy);
    }
    c.textAlign = 'center'; c.textBaseline = 'top';
    for (const t of niceTicks(this.x0, this.x1, 4)) c.fillText(fmt(t), X(t), PAD.t + ph + 3);
    c.textAlign = 'left'; c.textBaseline = 'top'; c.fillStyle = '#d0d6e0';
    c.fillText(`${this.title} (${this.unit})${this.clipped ? ' · y clipped at 1.5× p99' : ''}`, 4, 3);
    if (!this.series.length && this.empty) {
      c.fillStyle = '#7a8494'; c.textAlign = 'center'; c.textBaseline = 'middle';
      c.fillText(this.empty, PAD.l + pw / 2, PAD.t + ph / 2);
    }
    c.save();
    c.beginPath(); c.rect(PAD.l, PAD.t, pw, ph); c.clip();
    for (const s of this.series) {
      c.strokeStyle = s.color; c.lineWidth = 1.2; c.beginPath();
      let pen = false;
      for (let i = 0; i < s.x.length; i++) {
        const v = s.y[i];
        if (v === null || v <= -300) { pen = false; continue; }
        const px = X(s.x[i]), py = Y(v);
        if (pen) c.lineTo(px, py); else { c.moveTo(px, py); pen = true; }
      }
      c.stroke();
    }
    c.restore();
    this.dirty = false;
  }

  draw() {
    const dpr = this._size();
    if (this.dirty) this._render(dpr);
    const c = this.canvas.getContext('2d');
    c.setTransform(1, 0, 0, 1, 0, 0);
    c.clearRect(0, 0, this.canvas.width, this.canvas.height);
    c.drawImage(this.cache, 0, 0);
    if (this.cursor === null || !this.map) return;
    c.scale(dpr, dpr);
    const { pw } = this.map;
    const x = PAD.l + ((this.cursor - this.x0) / ((this.x1 - this.x0) || 1)) * pw;
    c.strokeStyle = '#ffffffaa'; c.lineWidth = 1;
    c.beginPath(); c.moveTo(x, PAD.t); c.lineTo(x, this.map.h - PAD.b); c.stroke();
    // legend with the values at the cursor
    c.font = '10px sans-serif'; c.textAlign = 'right'; c.textBaseline = 'top';
    let yy = 3;
    const shown = this.series.slice(0, 6);
    for (const s of shown) {
      const i = lastIndexAtOrBefore(s.x, this.cursor);
      const v = i >= 0 ? s.y[i] : null;
      c.fillStyle = s.color;
      c.fillText(`${s.name} ${v === null || v <= -300 ? '–' : fmt(v)}`, this.map.w - PAD.r, yy);
      yy += 11;
    }
    if (this.series.length > shown.length) { c.fillStyle = '#9aa4b2'; c.fillText(`+${this.series.length - shown.length} more`, this.map.w - PAD.r, yy); }
  }
}

export function lastIndexAtOrBefore(xs, x) {
  let lo = 0, hi = xs.length - 1, ans = -1;
  while (lo <= hi) {
    const m = (lo + hi) >> 1;
    if (xs[m] <= x) { ans = m; lo = m + 1; } else hi = m - 1;
  }
  return ans;
}

export class EventPlot extends LinePlot {
  // rows: [{name, color, x: number[]}]
  _yrange() { return [0, Math.max(1, this.series.length)]; }
  _render(dpr) {
    const c = this.cache.getContext('2d');
    const W = this.cache.width, H = this.cache.height;
    c.setTransform(1, 0, 0, 1, 0, 0); c.clearRect(0, 0, W, H); c.scale(dpr, dpr);
    const w = W / dpr, h = H / dpr;
    const pw = w - PAD.l - PAD.r, ph = h - PAD.t - PAD.b;
    this.map = { w, h, pw, ph };
    const X = (x) => PAD.l + ((x - this.x0) / ((this.x1 - this.x0) || 1)) * pw;
    c.font = '10px sans-serif'; c.fillStyle = '#d0d6e0'; c.textAlign = 'left'; c.textBaseline = 'top';
    c.fillText(this.title, 4, 3);
    c.fillStyle = '#9aa4b2'; c.textAlign = 'center';
    for (const t of niceTicks(this.x0, this.x1, 4)) c.fillText(fmt(t), X(t), PAD.t + ph + 3);
    if (!this.series.length) {
      c.fillStyle = '#7a8494'; c.textBaseline = 'middle'; c.fillText(this.empty, PAD.l + pw / 2, PAD.t + ph / 2);
    }
    const rowH = ph / Math.max(1, this.series.length);
    this.series.forEach((s, r) => {
      const yy = PAD.t + rowH * (r + 0.5);
      c.fillStyle = '#9aa4b2'; c.textAlign = 'right'; c.textBaseline = 'middle';
      c.fillText(s.name.replace(/^(mission|caviar\.episode|ai)\./, ''), PAD.l - 4, yy);
      c.fillStyle = s.color;
      for (const x of s.x) { c.beginPath(); c.arc(X(x), yy, 3, 0, 2 * Math.PI); c.fill(); }
    });
    this.dirty = false;
  }
  draw() {
    const dpr = this._size();
    if (this.dirty) this._render(dpr);
    const c = this.canvas.getContext('2d');
    c.setTransform(1, 0, 0, 1, 0, 0);
    c.clearRect(0, 0, this.canvas.width, this.canvas.height);
    c.drawImage(this.cache, 0, 0);
    if (this.cursor === null || !this.map) return;
    c.scale(dpr, dpr);
    const x = PAD.l + ((this.cursor - this.x0) / ((this.x1 - this.x0) || 1)) * this.map.pw;
    c.strokeStyle = '#ffffffaa'; c.beginPath(); c.moveTo(x, PAD.t); c.lineTo(x, this.map.h - PAD.b); c.stroke();
  }
}
