/* stsdic view RESULT.h5: the field over the frame, the slider, point values and histories. */
"use strict";

const PICK_COLOURS = ["#ffb020", "#22d3ee"];

STS.ResultPage = class {
  constructor(meta) {
    this.meta = meta;
    this.n = meta.n_points;
    this.ref = new Float32Array(meta.points); // (N, 2) reference x, y px
    this.row = 0;
    this.field = meta.default_field;
    this.minZncc = meta.has_zncc ? meta.min_zncc : -1;
    this.scope = "movie"; // colour limits: movie | frame | manual
    this.deformed = meta.kind === "2d";
    this.showImage = !!meta.image;
    this.opacity = 0.75;
    this.picks = []; // [{point, history}]
    this.completed = "1".repeat(meta.n_rows);
    this.playing = false;
    this.fps = 5;
    this.drawn = { row: -1, field: null };
    this.img = null;
    this.values = null; this.pos = null; this.lim = null;
    this.hoverPoint = -1;
    this.yaw = -0.6; this.pitch = 0.5;
  }

  async start() {
    this.maps = await STS.getJSON("/api/colormaps");
    this.buildControls();
    this.buildSide();
    this.buildTransport();
    this.canvas = document.getElementById("canvas");
    this.view = new STS.Viewport(this.canvas, () => this.draw());
    this.setWorld();
    this.bindStage();
    window.addEventListener("resize", () => { this.view.fit(); this.draw(); this.drawChart(); });
    document.addEventListener("keydown", (ev) => this.key(ev));
    await this.pollProgress();
    const last = this.completed.lastIndexOf("1"); // the last finished frame, as 'stsdic plot'
    await this.setRow(last >= 0 ? last : 0);
    document.body.dataset.ready = "1";
    this.timer = setInterval(() => this.pollProgress(), 2000);
  }

  /* ---------------------------------------------------------------- layout */
  buildControls() {
    const m = this.meta, c = document.getElementById("controls");
    const sel = STS.el("select", { id: "field", onchange: (e) => this.setField(e.target.value) });
    const groups = {};
    for (const f of m.fields) {
      const g = f.name.endsWith("_std") ? "predicted std" : ["status", "zncc", "iterations",
        "m", "reprojection_error"].includes(f.name) ? "quality" : "fields";
      (groups[g] = groups[g] || []).push(f);
    }
    for (const [g, fs] of Object.entries(groups)) {
      const og = STS.el("optgroup", { label: g });
      for (const f of fs) og.append(STS.el("option", { value: f.name, text: f.label }));
      sel.append(og);
    }
    sel.value = this.field;
    const seg = STS.el("div", { class: "seg", id: "scope" });
    for (const [k, t] of [["movie", "movie"], ["frame", "frame"], ["manual", "manual"]]) {
      seg.append(STS.el("button", { "data-scope": k, text: t, onclick: () => this.setScope(k) }));
    }
    this.loIn = STS.el("input", { type: "number", step: "any", id: "lim-lo",
      onchange: () => this.setScope("manual") });
    this.hiIn = STS.el("input", { type: "number", step: "any", id: "lim-hi",
      onchange: () => this.setScope("manual") });
    const zn = STS.el("input", { type: "number", id: "min-zncc", step: "0.05", min: "-1",
      max: "1", value: String(this.minZncc),
      onchange: (e) => { this.minZncc = Number(e.target.value); this.reload(true); } });
    const op = STS.el("input", { type: "range", min: "0", max: "1", step: "0.05",
      value: String(this.opacity), oninput: (e) => { this.opacity = Number(e.target.value);
        this.draw(); } });
    c.append(
      STS.el("h3", { text: "Field" }), sel,
      STS.el("h3", { text: "Colour limits" }), seg,
      STS.el("label", { class: "row" }, STS.el("span", { text: "low" }), this.loIn),
      STS.el("label", { class: "row" }, STS.el("span", { text: "high" }), this.hiIn),
      STS.el("div", { class: "hint", id: "lim-note" }),
      STS.el("h3", { text: "Display" }),
      STS.el("label", { class: "row" }, STS.el("span", { text: "opacity" }), op));
    if (m.has_zncc) {
      c.append(STS.el("label", { class: "row" }, STS.el("span", { text: "min ZNCC" }), zn));
    }
    if (m.kind === "2d") {
      const cfg = STS.el("div", { class: "seg" },
        STS.el("button", { id: "cfg-def", text: "deformed", onclick: () => this.setDeformed(true) }),
        STS.el("button", { id: "cfg-ref", text: "reference", onclick: () => this.setDeformed(false) }));
      c.append(STS.el("div", { class: "hint", text: "points drawn where they are" }), cfg);
    }
    if (m.image) {
      c.append(STS.el("label", { class: "row" }, STS.el("span", { text: "image" }),
        STS.el("input", { type: "checkbox", checked: "", onchange: (e) => {
          this.showImage = e.target.checked; this.draw(); } })));
    }
    c.append(STS.el("button", { text: "fit view", onclick: () => { this.view.fit(); this.draw(); } }));
    c.append(STS.el("h3", { text: "Keys" }), STS.el("div", { class: "hint" },
      "← → frame, space play, wheel zoom, drag pan, click a point: history, second click: compare"));
    this.markScope();
  }

  buildSide() {
    const s = document.getElementById("side");
    this.pointBox = STS.el("div", { id: "point" },
      STS.el("div", { class: "hint", text: "Point at the pointer: move over the field." }));
    this.chart = STS.el("canvas", { class: "chart", id: "chart" });
    this.legend = STS.el("div", { class: "legend", id: "legend" });
    this.chart.addEventListener("click", (ev) => this.chartClick(ev));
    this.statsBox = STS.el("div", { class: "bars", id: "stats" });
    this.summaryBox = STS.el("table", { class: "kv", id: "summary" });
    s.append(STS.el("h3", { text: "History" }), this.legend, this.chart,
      STS.el("div", { class: "hint" }, "click a point on the field (a second click compares; ",
        STS.el("button", { text: "clear", id: "clear-picks", onclick: () => this.clearPicks() }), ")"));
    if (this.meta.has_shape) {
      this.shape = STS.el("canvas", { class: "shape", id: "shape" });
      s.append(STS.el("h3", { text: "3-D shape (mm), drag to turn" }), this.shape);
      this.bindShape();
    }
    s.append(STS.el("h3", { text: "Point" }), this.pointBox);
    document.getElementById("controls").append(STS.el("h3", { text: "This frame" }), this.statsBox,
      STS.el("h3", { text: "Run" }), this.summaryBox);
    this.fillSummary(this.meta.summary);
  }

  buildTransport() {
    const t = document.getElementById("transport"), m = this.meta;
    this.playBtn = STS.el("button", { class: "play", id: "play", text: "▶",
      title: "play / pause (space)", onclick: () => this.togglePlay() });
    this.slider = STS.el("input", { type: "range", id: "slider", min: "0",
      max: String(m.n_rows - 1), step: "1", value: "0",
      oninput: (e) => this.setRow(Number(e.target.value)) });
    this.frameLabel = STS.el("span", { class: "frame", id: "frame-label" });
    const fps = STS.el("select", { id: "fps", onchange: (e) => { this.fps = Number(e.target.value); } });
    for (const f of [1, 2, 5, 10, 20, 30]) fps.append(STS.el("option", { value: String(f), text: `${f} fps` }));
    fps.value = String(this.fps);
    t.append(
      STS.el("button", { text: "|◀", title: "first frame", onclick: () => this.setRow(this.finishedRows()[0] || 0) }),
      STS.el("button", { text: "◀", title: "previous frame", onclick: () => this.step(-1) }),
      this.playBtn,
      STS.el("button", { text: "▶|", title: "next frame", onclick: () => this.step(1) }),
      this.slider, this.frameLabel, fps);
  }

  fillSummary(lines) {
    this.summaryBox.replaceChildren(...lines.map(([k, v]) =>
      STS.el("tr", {}, STS.el("td", { text: k }), STS.el("td", { text: v }))));
  }

  setWorld() {
    const m = this.meta;
    if (m.image) { this.view.setWorld(-0.5, -0.5, m.image.width - 0.5, m.image.height - 0.5); return; }
    let x0 = Infinity, y0 = Infinity, x1 = -Infinity, y1 = -Infinity;
    for (let i = 0; i < this.n; i++) {
      x0 = Math.min(x0, this.ref[2 * i]); x1 = Math.max(x1, this.ref[2 * i]);
      y0 = Math.min(y0, this.ref[2 * i + 1]); y1 = Math.max(y1, this.ref[2 * i + 1]);
    }
    const [cx, cy] = m.cell;
    this.view.setWorld(x0 - cx, y0 - cy, x1 + cx, y1 + cy);
  }

  /* ---------------------------------------------------------------- state */
  finishedRows() {
    const out = [];
    for (let i = 0; i < this.completed.length; i++) if (this.completed[i] === "1") out.push(i);
    return out;
  }

  async pollProgress() {
    let p;
    try { p = await STS.getJSON("/api/progress"); } catch (e) { STS.message(e.message, true); return; }
    const grew = p.completed !== this.completed;
    this.completed = p.completed;
    const badge = document.getElementById("badge");
    const live = p.finished < p.n_rows;
    badge.textContent = live ? `${p.finished} of ${p.n_rows} frames finished — following the file`
      : `${p.n_rows} frames`;
    badge.className = "badge " + (live ? "live" : "done");
    badge.dataset.finished = String(p.finished);
    if (!live && this.timer) { clearInterval(this.timer); this.timer = null; }
    if (grew && this.values) {
      this.lim = null; // the movie's limits change as rows come in
      await this.reload(false);
      for (const pk of this.picks) await this.loadHistory(pk);
      this.drawChart();
      this.fillSummary((await STS.getJSON("/api/meta")).summary);
    }
  }

  setField(name) {
    this.field = name; this.lim = null;
    document.getElementById("field").value = name;
    this.reload(true);
  }
  setScope(k) {
    this.scope = k;
    if (k !== "manual") this.lim = null; // typed limits start from the ones shown
    this.markScope();
    this.reload(false);
  }
  setDeformed(on) { this.deformed = on; this.markScope(); this.reload(false); }
  markScope() {
    for (const b of document.querySelectorAll("#scope button")) {
      b.classList.toggle("on", b.dataset.scope === this.scope);
    }
    if (this.scope === "manual") document.getElementById("lim-note").textContent = "typed";
    const d = document.getElementById("cfg-def"), r = document.getElementById("cfg-ref");
    if (d) { d.classList.toggle("on", this.deformed); r.classList.toggle("on", !this.deformed); }
  }

  step(k) {
    const rows = this.finishedRows();
    if (!rows.length) return;
    let i = rows.findIndex((r) => r >= this.row);
    if (i < 0) i = rows.length - 1;
    if (rows[i] !== this.row && k > 0) i -= 1;
    i = Math.min(rows.length - 1, Math.max(0, i + k));
    return this.setRow(rows[i]);
  }

  key(ev) {
    if (ev.target.tagName === "INPUT" && ev.target.type !== "range") return;
    if (ev.key === "ArrowRight") { ev.preventDefault(); this.step(1); }
    else if (ev.key === "ArrowLeft") { ev.preventDefault(); this.step(-1); }
    else if (ev.key === " ") { ev.preventDefault(); this.togglePlay(); }
  }

  togglePlay() {
    this.playing = !this.playing;
    this.playBtn.textContent = this.playing ? "⏸" : "▶";
    if (this.playing) this.playLoop();
  }

  async playLoop() {
    while (this.playing) {
      const t0 = performance.now();
      const rows = this.finishedRows();
      if (!rows.length) break;
      const next = rows.find((r) => r > this.row);
      await this.setRow(next === undefined ? rows[0] : next);
      const wait = 1000 / this.fps - (performance.now() - t0);
      if (wait > 0) await new Promise((r) => setTimeout(r, wait));
    }
  }

  async setRow(row) {
    this.row = row;
    this.slider.value = String(row);
    const m = this.meta;
    const t = m.times[row];
    this.frameLabel.textContent = `frame ${m.frames[row]}  (${row + 1}/${m.n_rows})` +
      (m.time_label !== "time (frame)" && t !== null ? `  t = ${STS.fmt(t)}` : "");
    await this.reload(false);
  }

  /* fetch what the current row and field need, then draw */
  async reload(limitsToo) {
    const row = this.row, field = this.field, m = this.meta;
    const token = (this.token = (this.token || 0) + 1);
    const q = `row=${row}&min_zncc=${this.minZncc}`;
    try {
      const jobs = [STS.getF32(`/api/field?name=${encodeURIComponent(field)}&${q}`),
        this.deformed ? STS.getF32(`/api/positions?row=${row}`) : null,
        this.showImage || m.image ? this.frameImage(row) : null,
        STS.getJSON(`/api/stats?${q}`)];
      if (limitsToo || !this.lim || this.scope === "frame") {
        const scope = this.scope === "frame" ? `&row=${row}` : "";
        if (this.scope !== "manual" || !this.lim) {
          jobs.push(STS.getJSON(`/api/limits?name=${encodeURIComponent(field)}&min_zncc=${this.minZncc}${scope}`));
        }
      }
      if (m.has_shape) jobs.push(STS.getF32(`/api/shape?row=${row}`).then((s) => { this.xyz = s; }));
      const [vals, pos, img, stats, lim] = await Promise.all(jobs);
      if (token !== this.token) return; // a later request wins
      this.values = vals;
      this.pos = pos;
      this.cells = pos ? this.cellEdges(pos) : null;
      if (img !== null) this.img = img || null; // a failed load keeps the last image
      if (lim && !(lim instanceof Float32Array) && lim.cmap) this.setLimits(lim);
      this.fillStats(stats);
      this.draw();
      this.drawChart();
      if (this.shape) this.drawShape();
      if (this.hoverPoint >= 0) this.showPoint(this.hoverPoint);
      this.drawn = { row, field };
      document.getElementById("stage").dataset.row = String(row);
      document.getElementById("stage").dataset.field = field;
      STS.message("");
    } catch (e) {
      if (token === this.token) STS.message(e.message, true);
    }
  }

  setLimits(lim) {
    if (this.scope === "manual" && this.lim) {
      lim = Object.assign({}, this.lim);
    }
    this.lim = lim;
    if (this.scope !== "manual") {
      this.loIn.value = STS.fmt(lim.lo, 4); this.hiIn.value = STS.fmt(lim.hi, 4);
    }
    const note = document.getElementById("lim-note");
    note.textContent = lim.cmap === "status" ? "status codes" : this.scope === "movie"
      ? `from ${lim.rows} finished frame(s) spread over the movie`
      : this.scope === "frame" ? "from this frame" : "typed";
  }

  limits() {
    if (this.scope === "manual" && this.lim && this.lim.cmap !== "status") {
      const lo = Number(this.loIn.value), hi = Number(this.hiIn.value);
      if (Number.isFinite(lo) && Number.isFinite(hi) && hi > lo) return Object.assign({}, this.lim, { lo, hi });
    }
    return this.lim;
  }

  async frameImage(row) {
    const m = this.meta;
    if (!m.image) return null;
    const k = m.frames[row];
    if (k < 0 || k >= m.image.frames) return undefined; // no image of this frame: none drawn
    const img = await STS.loadImage(`/api/image?frame=${k}`);
    // the next frame's image, fetched ahead for playback
    const nxt = m.frames[row + 1];
    if (nxt !== undefined && nxt < m.image.frames) STS.loadImage(`/api/image?frame=${nxt}`);
    return img;
  }

  fillStats(st) {
    const rows = [];
    const done = st.finished;
    rows.push(STS.el("div", { class: "hint", id: "usable",
      text: done ? `usable: ${STS.fmt(st.usable, 3)} % of ${this.n} points` : "this frame is not finished yet" }));
    for (const s of this.maps.status) {
      const pct = st.status[s.name];
      if (pct === undefined || (pct === 0 && !["converged", "max_iter"].includes(s.name))) continue;
      const fill = STS.el("div", { class: "fill" });
      fill.style.width = `${Math.max(0.5, pct)}%`;
      fill.style.background = s.colour;
      rows.push(STS.el("div", { class: "bar" }, STS.el("span", { text: s.name.replace("_", " ") }),
        STS.el("div", {}, fill), STS.el("span", { class: "pct", text: `${STS.fmt(pct, 3)} %` })));
    }
    this.statsBox.replaceChildren(...rows);
  }

  /* ---------------------------------------------------------------- the stage */
  draw() {
    const ctx = STS.fitCanvas(this.canvas), v = this.view;
    const W = this.canvas.clientWidth, H = this.canvas.clientHeight;
    ctx.fillStyle = "#0b0d10";
    ctx.fillRect(0, 0, W, H);
    const m = this.meta;
    if (m.image && this.showImage && this.img) {
      ctx.imageSmoothingEnabled = v.s < 1;
      const [x, y] = v.toCanvas(-0.5, -0.5);
      ctx.drawImage(this.img, x, y, m.image.width * v.s, m.image.height * v.s);
    } else if (!m.image) {
      const w = v.world, [x, y] = v.toCanvas(w.x0, w.y0);
      ctx.fillStyle = "#1a1e24";
      ctx.fillRect(x, y, (w.x1 - w.x0) * v.s, (w.y1 - w.y0) * v.s);
    }
    const lim = this.limits();
    STS.drawColourbar(document.getElementById("colorbar"), this.maps, lim);
    if (!this.values || !lim) return;
    const [cw, ch] = m.cell, pw = cw * v.s, ph = ch * v.s;
    const pts = this.deformed && this.pos ? this.pos : this.ref;
    const cells = this.deformed && this.pos ? this.cells : null;
    ctx.globalAlpha = this.opacity;
    const cache = new Map();
    for (let i = 0; i < this.n; i++) {
      const val = this.values[i];
      if (Number.isNaN(val)) continue;
      const [cx, cy] = v.toCanvas(pts[2 * i], pts[2 * i + 1]);
      if (cx < -pw || cy < -ph || cx > W + pw || cy > H + ph) continue;
      const key = lim.cmap === "status" ? val : Math.round(((val - lim.lo) / (lim.hi - lim.lo || 1)) * 255);
      let col = cache.get(key);
      if (col === undefined) {
        const c = STS.colourOf(this.maps, lim, val);
        col = `rgb(${c[0]},${c[1]},${c[2]})`;
        cache.set(key, col);
      }
      ctx.fillStyle = col;
      if (cells) { // the cell as the motion deformed it: a parallelogram
        const ax = cells[4 * i] * v.s / 2, ay = cells[4 * i + 1] * v.s / 2;
        const bx = cells[4 * i + 2] * v.s / 2, by = cells[4 * i + 3] * v.s / 2;
        ctx.beginPath();
        ctx.moveTo(cx - ax - bx, cy - ay - by); ctx.lineTo(cx + ax - bx, cy + ay - by);
        ctx.lineTo(cx + ax + bx, cy + ay + by); ctx.lineTo(cx - ax + bx, cy - ay + by);
        ctx.closePath(); ctx.fill();
        ctx.strokeStyle = col; ctx.lineWidth = 0.6; ctx.stroke();
      } else {
        ctx.fillRect(cx - pw / 2, cy - ph / 2, pw + 0.5, ph + 0.5);
      }
    }
    ctx.globalAlpha = 1;
    // picked points and the point under the pointer
    this.picks.forEach((pk, j) => this.mark(ctx, pts, pk.point, PICK_COLOURS[j], j ? "B" : "A"));
    if (this.hoverPoint >= 0) {
      const [cx, cy] = v.toCanvas(pts[2 * this.hoverPoint], pts[2 * this.hoverPoint + 1]);
      ctx.strokeStyle = "#fff"; ctx.lineWidth = 1.5;
      ctx.strokeRect(cx - pw / 2, cy - ph / 2, pw, ph);
    }
    const note = document.getElementById("stage-note");
    note.textContent = this.completed[this.row] === "1" ? "" : "this frame is not finished yet";
  }

  /* the deformed cell of every grid point: its edge vectors (px) along the grid's x and y,
     from the neighbours' positions (central differences; one-sided at the edge; the
     reference cell where there is no neighbour) */
  cellEdges(pos) {
    const g = this.meta.grid, [sx, sy] = this.meta.cell, out = new Float32Array(4 * this.n);
    if (!g) {
      for (let i = 0; i < this.n; i++) { out[4 * i] = sx; out[4 * i + 3] = sy; }
      return out;
    }
    if (!this.gridIndex) {
      this.gridIndex = new Int32Array(g.nx * g.ny).fill(-1);
      for (let i = 0; i < this.n; i++) this.gridIndex[g.iy[i] * g.nx + g.ix[i]] = i;
    }
    const at = (ix, iy) => (ix < 0 || iy < 0 || ix >= g.nx || iy >= g.ny) ? -1 : this.gridIndex[iy * g.nx + ix];
    const edge = (i, a, b, k) => { // (pos[b] - pos[a]) / (index distance), component k
      const d = (a === i || b === i) ? 1 : 2;
      return (pos[2 * b + k] - pos[2 * a + k]) / d;
    };
    for (let i = 0; i < this.n; i++) {
      const ix = g.ix[i], iy = g.iy[i];
      const l = at(ix - 1, iy), r = at(ix + 1, iy), u = at(ix, iy - 1), d = at(ix, iy + 1);
      const xa = l >= 0 ? l : i, xb = r >= 0 ? r : i, ya = u >= 0 ? u : i, yb = d >= 0 ? d : i;
      if (xa !== xb) { out[4 * i] = edge(i, xa, xb, 0); out[4 * i + 1] = edge(i, xa, xb, 1); }
      else { out[4 * i] = sx; out[4 * i + 1] = 0; }
      if (ya !== yb) { out[4 * i + 2] = edge(i, ya, yb, 0); out[4 * i + 3] = edge(i, ya, yb, 1); }
      else { out[4 * i + 2] = 0; out[4 * i + 3] = sy; }
    }
    return out;
  }

  mark(ctx, pts, k, colour, label) {
    const [cx, cy] = this.view.toCanvas(pts[2 * k], pts[2 * k + 1]);
    ctx.strokeStyle = "#000"; ctx.lineWidth = 4;
    ctx.beginPath(); ctx.arc(cx, cy, 7, 0, 2 * Math.PI); ctx.stroke();
    ctx.strokeStyle = colour; ctx.lineWidth = 2;
    ctx.beginPath(); ctx.arc(cx, cy, 7, 0, 2 * Math.PI); ctx.stroke();
    ctx.font = "bold 12px system-ui, sans-serif";
    ctx.fillStyle = "#000"; ctx.fillText(label, cx + 10, cy - 7);
    ctx.fillStyle = colour; ctx.fillText(label, cx + 9, cy - 8);
  }

  nearest(x, y) {
    const pts = this.deformed && this.pos ? this.pos : this.ref;
    let best = -1, bd = Infinity;
    for (let i = 0; i < this.n; i++) {
      const dx = pts[2 * i] - x, dy = pts[2 * i + 1] - y, d = dx * dx + dy * dy;
      if (d < bd) { bd = d; best = i; }
    }
    const reach = 0.75 * Math.max(this.meta.cell[0], this.meta.cell[1]);
    return bd <= reach * reach ? best : -1;
  }

  bindStage() {
    const stage = document.getElementById("stage"), tip = document.getElementById("tooltip");
    let down = null;
    this.canvas.addEventListener("mousedown", (ev) => {
      down = { x: ev.clientX, y: ev.clientY, moved: false };
    });
    window.addEventListener("mouseup", (ev) => {
      if (down && !down.moved && ev.target === this.canvas) {
        const [x, y] = this.view.fromEvent(ev);
        const k = this.nearest(x, y);
        if (k >= 0) this.pick(k);
      }
      down = null;
      stage.classList.remove("panning");
    });
    this.canvas.addEventListener("mousemove", (ev) => {
      if (down) {
        const dx = ev.clientX - down.x, dy = ev.clientY - down.y;
        if (down.moved || Math.abs(dx) + Math.abs(dy) > 3) {
          down.moved = true;
          stage.classList.add("panning");
          this.view.pan(dx, dy);
          down.x = ev.clientX; down.y = ev.clientY;
          return;
        }
      }
      const [x, y] = this.view.fromEvent(ev);
      const k = this.nearest(x, y);
      const r = stage.getBoundingClientRect();
      if (k < 0) { tip.classList.add("hidden"); } else {
        const val = this.values ? this.values[k] : NaN;
        const f = this.meta.fields.find((ff) => ff.name === this.field);
        tip.textContent = `#${k} (${STS.fmt(this.ref[2 * k])}, ${STS.fmt(this.ref[2 * k + 1])}) px  ` +
          `${this.field} = ${this.field === "status" ? this.statusName(val) : STS.fmt(val)}` +
          (f && f.unit && f.unit !== "-" && this.field !== "status" ? ` ${f.unit}` : "");
        tip.classList.remove("hidden");
        const px = ev.clientX - r.left, py = ev.clientY - r.top; // kept inside the stage
        const left = px + 14 + tip.offsetWidth > r.width ? px - 14 - tip.offsetWidth : px + 14;
        const top = py + 12 + tip.offsetHeight > r.height ? py - 12 - tip.offsetHeight : py + 12;
        tip.style.left = `${Math.max(0, left)}px`;
        tip.style.top = `${Math.max(0, top)}px`;
      }
      if (k !== this.hoverPoint) {
        this.hoverPoint = k;
        this.draw();
        if (k >= 0) this.showPoint(k);
      }
    });
    this.canvas.addEventListener("mouseleave", () => { tip.classList.add("hidden"); });
  }

  statusName(code) {
    const s = this.maps.status.find((c) => c.code === code);
    return s ? s.name : "—";
  }

  async showPoint(k) {
    const token = (this.ptoken = (this.ptoken || 0) + 1);
    let p;
    try { p = await STS.getJSON(`/api/point?row=${this.row}&point=${k}`); } catch (e) { return; }
    if (token !== this.ptoken) return;
    const rows = [STS.el("tr", {}, STS.el("td", { text: "point" }),
      STS.el("td", { class: "num", text: `#${p.point} at (${STS.fmt(p.x)}, ${STS.fmt(p.y)}) px` }))];
    rows.push(STS.el("tr", {}, STS.el("td", { text: "frame" }),
      STS.el("td", { class: "num", text: String(this.meta.frames[p.row]) })));
    for (const f of this.meta.fields) {
      const v = p.values[f.name];
      if (v === undefined) continue;
      const text = f.name === "status" ? `${v} ${p.status_name || ""}` : STS.fmt(v);
      const tr = STS.el("tr", { "data-field": f.name }, STS.el("td", { text: f.label }),
        STS.el("td", { class: "num", text }));
      if (f.name === this.field) tr.className = "current";
      rows.push(tr);
    }
    const table = STS.el("table", { class: "kv", id: "point-table", "data-point": String(p.point) }, ...rows);
    this.pointBox.replaceChildren(table);
  }

  /* ---------------------------------------------------------------- histories */
  async pick(k) {
    if (this.picks.length >= 2) this.picks = [];
    const pk = { point: k, history: null };
    this.picks.push(pk);
    this.draw();
    await this.loadHistory(pk);
    this.drawChart();
  }

  clearPicks() { this.picks = []; this.draw(); this.drawChart(); }

  async loadHistory(pk) {
    pk.history = await STS.getJSON(`/api/history?point=${pk.point}&name=${encodeURIComponent(this.field)}&min_zncc=${this.minZncc}`);
    pk.field = this.field;
  }

  chartBox() {
    const W = this.chart.clientWidth, H = this.chart.clientHeight;
    return { l: 58, r: W - 10, t: 10, b: H - 32, W, H };
  }

  chartClick(ev) {
    if (!this.chartX) return;
    const r = this.chart.getBoundingClientRect(), bx = this.chartBox();
    const tx = this.chartX.lo + ((ev.clientX - r.left - bx.l) / (bx.r - bx.l)) * (this.chartX.hi - this.chartX.lo);
    const times = this.meta.times;
    let best = 0;
    for (let i = 0; i < times.length; i++) {
      if (times[i] !== null && Math.abs(times[i] - tx) < Math.abs(times[best] - tx)) best = i;
    }
    if (this.completed[best] === "1") this.setRow(best);
  }

  drawChart() {
    const ctx = STS.fitCanvas(this.chart), b = this.chartBox();
    ctx.clearRect(0, 0, b.W, b.H);
    const picks = this.picks.filter((p) => p.history);
    this.legend.replaceChildren(...picks.map((p, j) => STS.el("span", {},
      (() => { const s = STS.el("span", { class: "sw" }); s.style.background = PICK_COLOURS[j]; return s; })(),
      `${j ? "B" : "A"}: #${p.point} (${STS.fmt(p.history.x)}, ${STS.fmt(p.history.y)})` +
      (p.history.std ? ` ± ${p.history.std_name}` : ""))));
    this.chart.dataset.points = picks.map((p) => p.point).join(",");
    if (picks.some((p) => p.field !== this.field)) {
      // the field changed: fetch the histories again
      Promise.all(picks.map((p) => this.loadHistory(p))).then(() => this.drawChart());
      return;
    }
    ctx.font = "11px system-ui, sans-serif";
    ctx.fillStyle = "#8d97a5";
    if (!picks.length) {
      ctx.textAlign = "center";
      ctx.fillText("click a point on the field to plot its history", b.W / 2, b.H / 2);
      ctx.textAlign = "left";
      this.chartX = null;
      return;
    }
    const times = picks[0].history.times;
    let xlo = Infinity, xhi = -Infinity, ylo = Infinity, yhi = -Infinity;
    for (const t of times) if (t !== null) { xlo = Math.min(xlo, t); xhi = Math.max(xhi, t); }
    for (const p of picks) {
      p.history.values.forEach((v, i) => {
        if (v === null) return;
        const s = p.history.std ? (p.history.std[i] || 0) : 0;
        ylo = Math.min(ylo, v - s); yhi = Math.max(yhi, v + s);
      });
    }
    if (!Number.isFinite(ylo)) { ylo = -1; yhi = 1; }
    if (yhi - ylo < 1e-12) { ylo -= 0.5 * Math.abs(ylo || 1); yhi += 0.5 * Math.abs(yhi || 1); }
    const pad = 0.06 * (yhi - ylo); ylo -= pad; yhi += pad;
    if (xhi <= xlo) { xhi = xlo + 1; }
    this.chartX = { lo: xlo, hi: xhi };
    const X = (t) => b.l + ((t - xlo) / (xhi - xlo)) * (b.r - b.l);
    const Y = (v) => b.b - ((v - ylo) / (yhi - ylo)) * (b.b - b.t);
    // grid, ticks
    ctx.strokeStyle = "#262c35"; ctx.lineWidth = 1;
    ctx.fillStyle = "#8d97a5";
    ctx.textAlign = "right";
    for (const t of STS.ticks(ylo, yhi, 5)) {
      ctx.beginPath(); ctx.moveTo(b.l, Y(t)); ctx.lineTo(b.r, Y(t)); ctx.stroke();
      ctx.fillText(STS.fmt(t, 3), b.l - 4, Y(t) + 4);
    }
    ctx.textAlign = "center";
    for (const t of STS.ticks(xlo, xhi, 6)) {
      ctx.beginPath(); ctx.moveTo(X(t), b.t); ctx.lineTo(X(t), b.b); ctx.stroke();
      ctx.fillText(STS.fmt(t, 4), X(t), b.b + 13);
    }
    ctx.fillText(this.meta.time_label, (b.l + b.r) / 2, b.H - 4);
    ctx.save(); ctx.translate(11, (b.t + b.b) / 2); ctx.rotate(-Math.PI / 2);
    ctx.fillText(picks[0].history.label, 0, 0); ctx.restore();
    ctx.strokeStyle = "#3b4350"; ctx.strokeRect(b.l, b.t, b.r - b.l, b.b - b.t);
    // the current frame
    const tc = times[this.row];
    if (tc !== null) {
      ctx.strokeStyle = "#e5e7eb"; ctx.setLineDash([3, 3]);
      ctx.beginPath(); ctx.moveTo(X(tc), b.t); ctx.lineTo(X(tc), b.b); ctx.stroke();
      ctx.setLineDash([]);
    }
    picks.forEach((p, j) => {
      const h = p.history, col = PICK_COLOURS[j];
      if (h.std) { // the +- 1 std band, in runs of finite values
        ctx.fillStyle = col + "40";
        let run = [];
        const flush = () => {
          if (run.length) {
            ctx.beginPath();
            run.forEach((i, n) => { const f = n ? ctx.lineTo.bind(ctx) : ctx.moveTo.bind(ctx); f(X(times[i]), Y(h.values[i] + h.std[i])); });
            for (let n = run.length - 1; n >= 0; n--) ctx.lineTo(X(times[run[n]]), Y(h.values[run[n]] - h.std[run[n]]));
            ctx.closePath(); ctx.fill();
          }
          run = [];
        };
        h.values.forEach((v, i) => { if (v !== null && h.std[i] !== null && times[i] !== null) run.push(i); else flush(); });
        flush();
      }
      ctx.strokeStyle = col; ctx.lineWidth = 1.6;
      ctx.beginPath();
      let pen = false;
      h.values.forEach((v, i) => {
        if (v === null || times[i] === null) { pen = false; return; }
        if (pen) ctx.lineTo(X(times[i]), Y(v)); else ctx.moveTo(X(times[i]), Y(v));
        pen = true;
      });
      ctx.stroke();
      if (h.values.length <= 200) {
        ctx.fillStyle = col;
        h.values.forEach((v, i) => { if (v !== null) ctx.fillRect(X(times[i]) - 1.5, Y(v) - 1.5, 3, 3); });
      }
    });
  }

  /* ---------------------------------------------------------------- 3-D shape (stereo) */
  bindShape() {
    let down = null;
    this.shape.addEventListener("mousedown", (ev) => { down = [ev.clientX, ev.clientY]; });
    window.addEventListener("mouseup", () => { down = null; });
    window.addEventListener("mousemove", (ev) => {
      if (!down) return;
      this.yaw += (ev.clientX - down[0]) * 0.01;
      this.pitch = Math.max(-1.5, Math.min(1.5, this.pitch + (ev.clientY - down[1]) * 0.01));
      down = [ev.clientX, ev.clientY];
      this.drawShape();
    });
  }

  drawShape() {
    const ctx = STS.fitCanvas(this.shape), W = this.shape.clientWidth, H = this.shape.clientHeight;
    ctx.clearRect(0, 0, W, H);
    const xyz = this.xyz, lim = this.limits();
    if (!xyz || !lim) return;
    let c = [0, 0, 0], n = 0;
    for (let i = 0; i < this.n; i++) {
      if (Number.isNaN(xyz[3 * i])) continue;
      c[0] += xyz[3 * i]; c[1] += xyz[3 * i + 1]; c[2] += xyz[3 * i + 2]; n++;
    }
    if (!n) return;
    c = c.map((a) => a / n);
    if (!this.shapeScale) {
      let r = 0;
      for (let i = 0; i < this.n; i++) {
        if (Number.isNaN(xyz[3 * i])) continue;
        r = Math.max(r, Math.hypot(xyz[3 * i] - c[0], xyz[3 * i + 1] - c[1], xyz[3 * i + 2] - c[2]));
      }
      this.shapeScale = 0.42 * Math.min(W, H) / (r || 1);
      this.shapeCentre = c;
    }
    c = this.shapeCentre;
    const cy = Math.cos(this.yaw), sy = Math.sin(this.yaw), cp = Math.cos(this.pitch), sp = Math.sin(this.pitch);
    const proj = (x, y, z) => { // camera frame: X right, Y down, Z away; turn about the centre
      const x1 = cy * x - sy * z, z1 = sy * x + cy * z;
      const y2 = cp * y - sp * z1, z2 = sp * y + cp * z1;
      return [W / 2 + this.shapeScale * x1, H / 2 + this.shapeScale * y2, z2];
    };
    const order = [];
    for (let i = 0; i < this.n; i++) {
      if (Number.isNaN(xyz[3 * i])) continue;
      const p = proj(xyz[3 * i] - c[0], xyz[3 * i + 1] - c[1], xyz[3 * i + 2] - c[2]);
      order.push([p[2], p[0], p[1], i]);
    }
    order.sort((a, b) => b[0] - a[0]);
    for (const [, x, y, i] of order) {
      const col = STS.colourOf(this.maps, lim, this.values ? this.values[i] : NaN) || [110, 110, 110];
      ctx.fillStyle = `rgb(${col[0]},${col[1]},${col[2]})`;
      ctx.beginPath(); ctx.arc(x, y, 3.2, 0, 2 * Math.PI); ctx.fill();
    }
    // the axes triad
    const o = [34, H - 30], L = 22;
    [["X", [1, 0, 0], "#ef4444"], ["Y", [0, 1, 0], "#22c55e"], ["Z", [0, 0, 1], "#3b82f6"]].forEach(([name, d, col]) => {
      const p = proj(d[0], d[1], d[2]);
      const dx = (p[0] - W / 2) / this.shapeScale, dy = (p[1] - H / 2) / this.shapeScale;
      ctx.strokeStyle = col; ctx.lineWidth = 2;
      ctx.beginPath(); ctx.moveTo(o[0], o[1]); ctx.lineTo(o[0] + L * dx, o[1] + L * dy); ctx.stroke();
      ctx.fillStyle = col; ctx.font = "11px system-ui, sans-serif";
      ctx.fillText(name, o[0] + (L + 6) * dx - 3, o[1] + (L + 6) * dy + 4);
    });
    ctx.fillStyle = "#8d97a5";
    ctx.fillText(`${lim.label} at frame ${this.meta.frames[this.row]}`, 8, 14);
  }
};
