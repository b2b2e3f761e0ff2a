/* stsdic view: what both pages share (requests, numbers, colours, the image viewport). */
"use strict";

const STS = {};

STS.el = function (tag, attrs, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (k === "class") e.className = v;
    else if (k === "text") e.textContent = v;
    else if (k.startsWith("on")) e.addEventListener(k.slice(2), v);
    else e.setAttribute(k, v);
  }
  for (const c of children) if (c != null) e.append(c);
  return e;
};

STS.getJSON = async function (url, opts) {
  const r = await fetch(url, opts);
  const data = await r.json();
  if (!r.ok) throw new Error(data.error || r.statusText);
  return data;
};

STS.getF32 = async function (url) {
  const r = await fetch(url);
  if (!r.ok) {
    let msg = r.statusText;
    try { msg = (await r.json()).error || msg; } catch (e) { /* not JSON */ }
    throw new Error(msg);
  }
  return new Float32Array(await r.arrayBuffer());
};

STS.message = function (text, error) {
  const m = document.getElementById("message");
  m.textContent = text || "";
  m.className = "message" + (error ? " error" : "");
};

/* a number for people: 4 significant digits, exponent outside 1e-3 .. 1e5 */
STS.fmt = function (v, digits) {
  if (v === null || v === undefined || Number.isNaN(v)) return "—";
  if (typeof v !== "number") return String(v);
  const a = Math.abs(v);
  if (a !== 0 && (a < 1e-3 || a >= 1e5)) return v.toExponential((digits || 4) - 1);
  return Number(v.toPrecision(digits || 4)).toString();
};

/* round tick values covering [lo, hi] */
STS.ticks = function (lo, hi, n) {
  const span = hi - lo;
  if (!(span > 0)) return [lo];
  const raw = span / Math.max(1, n || 5);
  const mag = Math.pow(10, Math.floor(Math.log10(raw)));
  const step = [1, 2, 2.5, 5, 10].map((s) => s * mag).find((s) => s >= raw) || raw;
  const out = [];
  for (let t = Math.ceil(lo / step) * step; t <= hi + step * 1e-9; t += step) {
    out.push(Math.abs(t) < step * 1e-9 ? 0 : t);
  }
  return out;
};

/* colour of a value: [r, g, b] or null (not drawn) */
STS.colourOf = function (maps, lim, v) {
  if (v === null || Number.isNaN(v)) return null;
  if (lim.cmap === "status") {
    const s = maps.status.find((c) => c.code === v);
    return s ? STS.hexRGB(s.colour) : [120, 120, 120];
  }
  const lut = maps[lim.cmap];
  let t = (v - lim.lo) / (lim.hi - lim.lo || 1);
  t = Math.min(1, Math.max(0, t));
  return lut[Math.min(lut.length - 1, Math.floor(t * lut.length))];
};

STS.hexRGB = function (hex) {
  const n = parseInt(hex.slice(1), 16);
  return [(n >> 16) & 255, (n >> 8) & 255, n & 255];
};

/* a canvas sized to its CSS box at the screen's pixel ratio; returns its 2-D context */
STS.fitCanvas = function (canvas) {
  const dpr = window.devicePixelRatio || 1;
  const w = Math.max(1, Math.round(canvas.clientWidth * dpr));
  const h = Math.max(1, Math.round(canvas.clientHeight * dpr));
  if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; }
  const ctx = canvas.getContext("2d");
  ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
  return ctx;
};

/* the colour bar: the map, its ticks and its label (quantity and unit) */
STS.drawColourbar = function (canvas, maps, lim) {
  const ctx = STS.fitCanvas(canvas);
  const W = canvas.clientWidth, H = canvas.clientHeight;
  ctx.clearRect(0, 0, W, H);
  if (!lim) return;
  const x = 10, w = 16, y0 = 16, y1 = H - 16;
  ctx.font = "11px system-ui, sans-serif";
  ctx.fillStyle = "#d9dee5";
  if (lim.cmap === "status") {
    const n = maps.status.length, hh = (y1 - y0) / n;
    maps.status.forEach((s, i) => {
      ctx.fillStyle = s.colour;
      ctx.fillRect(x, y0 + i * hh, w, hh - 1);
      ctx.fillStyle = "#d9dee5";
      ctx.save();
      ctx.translate(x + w + 4, y0 + i * hh + hh / 2 + 4);
      ctx.font = "10px system-ui, sans-serif";
      ctx.fillText(s.name.replace("_", " "), 0, 0);
      ctx.restore();
    });
    return;
  }
  const lut = maps[lim.cmap];
  for (let i = 0; i < y1 - y0; i++) {
    const c = lut[Math.floor((1 - i / (y1 - y0)) * (lut.length - 1))];
    ctx.fillStyle = `rgb(${c[0]},${c[1]},${c[2]})`;
    ctx.fillRect(x, y0 + i, w, 1.5);
  }
  ctx.strokeStyle = "#596270";
  ctx.strokeRect(x + 0.5, y0 + 0.5, w - 1, y1 - y0 - 1);
  ctx.fillStyle = "#d9dee5";
  for (const t of STS.ticks(lim.lo, lim.hi, 6)) {
    const y = y1 - ((t - lim.lo) / (lim.hi - lim.lo)) * (y1 - y0);
    ctx.fillRect(x + w, y, 4, 1);
    ctx.fillText(STS.fmt(t, 3), x + w + 6, y + 4);
  }
  ctx.save();
  ctx.translate(W - 6, (y0 + y1) / 2);
  ctx.rotate(-Math.PI / 2);
  ctx.textAlign = "center";
  ctx.font = "12px system-ui, sans-serif";
  ctx.fillText(lim.label, 0, 0);
  ctx.restore();
};

/* The image viewport: image px <-> canvas px with zoom (wheel) and pan (drag). */
STS.Viewport = class {
  constructor(canvas, onChange) {
    this.canvas = canvas;
    this.onChange = onChange;
    this.s = 1; this.ox = 0; this.oy = 0;
    this.world = { x0: -0.5, y0: -0.5, x1: 99.5, y1: 99.5 };
    canvas.addEventListener("wheel", (ev) => {
      ev.preventDefault();
      const r = canvas.getBoundingClientRect();
      const mx = ev.clientX - r.left, my = ev.clientY - r.top;
      const k = Math.exp(-ev.deltaY * 0.0015);
      this.ox = mx - (mx - this.ox) * k;
      this.oy = my - (my - this.oy) * k;
      this.s *= k;
      this.onChange();
    }, { passive: false });
  }
  setWorld(x0, y0, x1, y1) { this.world = { x0, y0, x1, y1 }; this.fit(); }
  fit() {
    const W = this.canvas.clientWidth, H = this.canvas.clientHeight, w = this.world;
    const s = Math.min(W / (w.x1 - w.x0), H / (w.y1 - w.y0)) * 0.97;
    this.s = s;
    this.ox = (W - s * (w.x1 - w.x0)) / 2 - s * w.x0;
    this.oy = (H - s * (w.y1 - w.y0)) / 2 - s * w.y0;
  }
  toCanvas(x, y) { return [this.ox + this.s * x, this.oy + this.s * y]; }
  toImage(cx, cy) { return [(cx - this.ox) / this.s, (cy - this.oy) / this.s]; }
  /* page (client) coordinates of image point (x, y): for tests and tooltips */
  toClient(x, y) {
    const r = this.canvas.getBoundingClientRect();
    const [cx, cy] = this.toCanvas(x, y);
    return [r.left + cx, r.top + cy];
  }
  fromEvent(ev) {
    const r = this.canvas.getBoundingClientRect();
    return this.toImage(ev.clientX - r.left, ev.clientY - r.top);
  }
  pan(dx, dy) { this.ox += dx; this.oy += dy; this.onChange(); }
};

/* load an image; resolves with it (or null when it fails) */
STS.loadImage = function (url) {
  return new Promise((resolve) => {
    const img = new Image();
    img.onload = () => resolve(img);
    img.onerror = () => resolve(null);
    img.src = url;
  });
};

window.addEventListener("DOMContentLoaded", async () => {
  try {
    const meta = await STS.getJSON("/api/meta");
    document.getElementById("file-name").textContent = meta.file || (meta.inputs || []).join(" ");
    if (meta.mode === "draw") window.stsdicView = new STS.DrawPage(meta);
    else window.stsdicView = new STS.ResultPage(meta);
    await window.stsdicView.start();
  } catch (e) {
    STS.message(String(e.message || e), true);
    throw e;
  }
});
