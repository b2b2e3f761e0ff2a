/* stsdic view FRAMES: draw the box (--roi) and polygons (regions, holes) of the --mask. */
"use strict";

const DRAW_STYLE = {
  box: { stroke: "#facc15", fill: "rgba(250, 204, 21, 0.06)" },
  region: { stroke: "#22c55e", fill: "rgba(34, 197, 94, 0.22)" },
  hole: { stroke: "#ef4444", fill: "rgba(239, 68, 68, 0.35)" },
};

STS.DrawPage = class {
  constructor(meta) {
    this.meta = meta;
    this.tool = "box";
    this.box = null; // [x0, y0, x1, y1] px
    this.polygons = []; // {kind, points: [[x, y], ...]}
    this.current = null; // the polygon being drawn
    this.cursor = null;
    this.preview = null; // grid points of the last save
    this.history = [];
  }

  async start() {
    document.getElementById("badge").textContent = `reference frame ${this.meta.reference}`;
    document.getElementById("badge").className = "badge done";
    document.getElementById("colorbar").classList.add("hidden");
    document.getElementById("transport").classList.add("hidden");
    document.getElementById("stage-wrap").style.gridTemplateColumns = "1fr 0";
    this.canvas = document.getElementById("canvas");
    this.view = new STS.Viewport(this.canvas, () => this.draw());
    this.buildControls();
    this.buildSide();
    const im = this.meta.image;
    this.view.setWorld(-0.5, -0.5, im.width - 0.5, im.height - 0.5);
    this.img = await STS.loadImage(`/api/image?frame=${this.meta.reference}`);
    this.bind();
    window.addEventListener("resize", () => { this.view.fit(); this.draw(); });
    this.draw();
    document.body.dataset.ready = "1";
  }

  buildControls() {
    const c = document.getElementById("controls");
    const tools = STS.el("div", { class: "tools", id: "tools" });
    for (const [k, t, key] of [["box", "Box (--roi)", "B"], ["region", "Region polygon", "R"],
      ["hole", "Hole polygon", "H"]]) {
      tools.append(STS.el("button", { "data-tool": k, onclick: () => this.setTool(k) },
        `${t} `, STS.el("kbd", { text: key })));
    }
    this.stepIn = STS.el("input", { type: "number", id: "step", min: "1", value: String(this.meta.step) });
    this.subsetIn = STS.el("input", { type: "number", id: "subset", min: "5", step: "2", value: String(this.meta.subset) });
    c.append(STS.el("h3", { text: "Draw" }), tools,
      STS.el("div", { class: "hint" }, "Box: drag. Polygon: click the vertices, ",
        STS.el("kbd", { text: "Enter" }), " or double-click closes, ", STS.el("kbd", { text: "Esc" }),
        " drops it. Vertices snap to pixel centres. Wheel zooms, right-drag pans."),
      STS.el("h3", { text: "Edit" }),
      STS.el("div", { class: "seg" },
        STS.el("button", { text: "undo", id: "undo", onclick: () => this.undo() }),
        STS.el("button", { text: "clear", id: "clear", onclick: () => this.clear() }),
        STS.el("button", { text: "fit", onclick: () => { this.view.fit(); this.draw(); } })),
      STS.el("h3", { text: "Grid preview" }),
      STS.el("label", { class: "row" }, STS.el("span", { text: "step (px)" }), this.stepIn),
      STS.el("label", { class: "row" }, STS.el("span", { text: "subset (px)" }), this.subsetIn),
      STS.el("h3", { text: "Save" }),
      STS.el("button", { text: "Save mask and command", id: "save", class: "on", onclick: () => this.save() }),
      STS.el("div", { class: "hint", text: `mask: ${this.meta.mask_out}` }));
    this.setTool("box");
  }

  buildSide() {
    const s = document.getElementById("side");
    this.shapesBox = STS.el("table", { class: "kv", id: "shapes" });
    this.cmd = STS.el("textarea", { class: "cmd", id: "command", readonly: "",
      placeholder: "the 'stsdic run' command appears here after Save" });
    this.saveNote = STS.el("div", { class: "hint", id: "save-note" });
    this.coords = STS.el("div", { class: "hint", id: "coords", text: "x, y: —" });
    s.append(STS.el("h3", { text: "Pointer" }), this.coords,
      STS.el("h3", { text: "Region" }), this.shapesBox,
      STS.el("h3", { text: "Run command" }), this.cmd,
      STS.el("button", { text: "copy", onclick: () => navigator.clipboard && navigator.clipboard.writeText(this.cmd.value) }),
      this.saveNote,
      STS.el("h3", { text: "Rule" }),
      STS.el("div", { class: "hint", text: "A pixel is measured when it lies in a region " +
        "polygon (or there is none) and in no hole; a polygon holds the pixels inside it and " +
        "on its outline. The box becomes --roi (inclusive); grid points inside it and on " +
        "the mask are measured." }));
    this.listShapes();
  }

  setTool(k) {
    this.tool = k;
    this.current = null;
    for (const b of document.querySelectorAll("#tools button")) b.classList.toggle("on", b.dataset.tool === k);
    this.draw();
  }

  snap(p) { return [Math.round(p[0]), Math.round(p[1])]; }

  clampPt(p) {
    const im = this.meta.image;
    return [Math.min(im.width - 1, Math.max(0, p[0])), Math.min(im.height - 1, Math.max(0, p[1]))];
  }

  remember() { this.history.push(JSON.stringify({ box: this.box, polygons: this.polygons })); }

  undo() {
    if (this.current) { this.current = null; this.draw(); return; }
    const last = this.history.pop();
    if (!last) return;
    const s = JSON.parse(last);
    this.box = s.box; this.polygons = s.polygons;
    this.preview = null;
    this.listShapes(); this.draw();
  }

  clear() { this.remember(); this.box = null; this.polygons = []; this.current = null; this.preview = null; this.listShapes(); this.draw(); }

  closePolygon() {
    if (!this.current) return;
    if (this.current.points.length >= 3) {
      this.remember();
      this.polygons.push(this.current);
    }
    this.current = null;
    this.preview = null;
    this.listShapes(); this.draw();
  }

  bind() {
    const cv = this.canvas;
    let drag = null, pan = null;
    cv.addEventListener("contextmenu", (ev) => ev.preventDefault());
    cv.addEventListener("mousedown", (ev) => {
      if (ev.button === 2 || ev.button === 1) { pan = [ev.clientX, ev.clientY]; return; }
      const p = this.clampPt(this.snap(this.view.fromEvent(ev)));
      if (this.tool === "box") { drag = { from: p, to: p }; this.dragging = drag; }
    });
    window.addEventListener("mousemove", (ev) => {
      if (pan) { this.view.pan(ev.clientX - pan[0], ev.clientY - pan[1]); pan = [ev.clientX, ev.clientY]; return; }
      if (ev.target !== cv && !drag) return;
      const p = this.clampPt(this.snap(this.view.fromEvent(ev)));
      this.cursor = p;
      this.coords.textContent = `x, y: ${p[0]}, ${p[1]} px`;
      if (drag) drag.to = p;
      this.draw();
    });
    window.addEventListener("mouseup", (ev) => {
      if (pan) { pan = null; return; }
      if (!drag) return;
      const p = this.clampPt(this.snap(this.view.fromEvent(ev)));
      drag.to = p;
      const [a, b] = [drag.from, drag.to];
      if (a[0] !== b[0] && a[1] !== b[1]) {
        this.remember();
        this.box = [Math.min(a[0], b[0]), Math.min(a[1], b[1]), Math.max(a[0], b[0]), Math.max(a[1], b[1])];
        this.preview = null;
      }
      drag = null; this.dragging = null;
      this.listShapes(); this.draw();
    });
    cv.addEventListener("click", (ev) => {
      if (this.tool === "box" || ev.button !== 0) return;
      const p = this.clampPt(this.snap(this.view.fromEvent(ev)));
      if (!this.current) this.current = { kind: this.tool, points: [] };
      const pts = this.current.points;
      const last = pts[pts.length - 1];
      if (pts.length >= 3) { // a click on the first vertex closes
        const [fx, fy] = this.view.toCanvas(pts[0][0], pts[0][1]);
        const [cx, cy] = this.view.toCanvas(p[0], p[1]);
        if (Math.hypot(fx - cx, fy - cy) < 6) { this.closePolygon(); return; }
      }
      if (!last || last[0] !== p[0] || last[1] !== p[1]) pts.push(p);
      this.draw();
    });
    cv.addEventListener("dblclick", (ev) => { ev.preventDefault(); this.closePolygon(); });
    document.addEventListener("keydown", (ev) => {
      if (ev.target.tagName === "INPUT" || ev.target.tagName === "TEXTAREA") return;
      if (ev.key === "Enter") this.closePolygon();
      else if (ev.key === "Escape") { this.current = null; this.draw(); }
      else if (ev.key === "b" || ev.key === "B") this.setTool("box");
      else if (ev.key === "r" || ev.key === "R") this.setTool("region");
      else if (ev.key === "h" || ev.key === "H") this.setTool("hole");
      else if ((ev.ctrlKey || ev.metaKey) && ev.key === "z") this.undo();
    });
  }

  listShapes() {
    const rows = [];
    rows.push(STS.el("tr", {}, STS.el("td", { text: "box (--roi)" }),
      STS.el("td", { class: "num", text: this.box ? this.box.join(" ") : "none: the whole image" })));
    this.polygons.forEach((p, i) => rows.push(STS.el("tr", {}, STS.el("td", { text: `${p.kind} ${i + 1}` }),
      STS.el("td", { class: "num", text: `${p.points.length} vertices` }))));
    if (!this.polygons.length) rows.push(STS.el("tr", {}, STS.el("td", { text: "mask" }),
      STS.el("td", { text: "none (no polygon)" })));
    this.shapesBox.replaceChildren(...rows);
  }

  path(ctx, pts, close) {
    ctx.beginPath();
    pts.forEach((p, i) => {
      const [x, y] = this.view.toCanvas(p[0], p[1]);
      if (i) ctx.lineTo(x, y); else ctx.moveTo(x, y);
    });
    if (close) ctx.closePath();
  }

  draw() {
    const ctx = STS.fitCanvas(this.canvas), v = this.view, im = this.meta.image;
    const W = this.canvas.clientWidth, H = this.canvas.clientHeight;
    ctx.fillStyle = "#0b0d10"; ctx.fillRect(0, 0, W, H);
    if (this.img) {
      ctx.imageSmoothingEnabled = v.s < 1;
      const [x, y] = v.toCanvas(-0.5, -0.5);
      ctx.drawImage(this.img, x, y, im.width * v.s, im.height * v.s);
    }
    // regions, then holes over them
    for (const kind of ["region", "hole"]) {
      for (const p of this.polygons.filter((q) => q.kind === kind)) {
        const st = DRAW_STYLE[kind];
        this.path(ctx, p.points, true);
        ctx.fillStyle = st.fill; ctx.fill();
        ctx.strokeStyle = st.stroke; ctx.lineWidth = 2; ctx.stroke();
      }
    }
    const box = this.dragging ? [Math.min(this.dragging.from[0], this.dragging.to[0]), Math.min(this.dragging.from[1], this.dragging.to[1]),
      Math.max(this.dragging.from[0], this.dragging.to[0]), Math.max(this.dragging.from[1], this.dragging.to[1])] : this.box;
    if (box) {
      const [x0, y0] = v.toCanvas(box[0], box[1]), [x1, y1] = v.toCanvas(box[2], box[3]);
      ctx.fillStyle = DRAW_STYLE.box.fill; ctx.fillRect(x0, y0, x1 - x0, y1 - y0);
      ctx.setLineDash([6, 4]); ctx.strokeStyle = DRAW_STYLE.box.stroke; ctx.lineWidth = 2;
      ctx.strokeRect(x0, y0, x1 - x0, y1 - y0); ctx.setLineDash([]);
      ctx.fillStyle = DRAW_STYLE.box.stroke; ctx.font = "12px system-ui, sans-serif";
      ctx.fillText(`roi ${box.join(" ")}`, x0 + 4, y0 - 6);
    }
    if (this.current) {
      const st = DRAW_STYLE[this.current.kind];
      const pts = this.cursor ? [...this.current.points, this.cursor] : this.current.points;
      this.path(ctx, pts, false);
      ctx.strokeStyle = st.stroke; ctx.lineWidth = 2; ctx.setLineDash([4, 3]); ctx.stroke(); ctx.setLineDash([]);
      ctx.fillStyle = st.stroke;
      for (const p of this.current.points) {
        const [x, y] = v.toCanvas(p[0], p[1]);
        ctx.fillRect(x - 3, y - 3, 6, 6);
      }
    }
    if (this.preview) {
      ctx.fillStyle = "#38bdf8";
      const r = Math.max(1.2, Math.min(3, v.s * 1.5));
      for (let i = 0; i < this.preview.length; i += 2) {
        const [x, y] = v.toCanvas(this.preview[i], this.preview[i + 1]);
        ctx.fillRect(x - r, y - r, 2 * r, 2 * r);
      }
    }
  }

  async save() {
    const body = { roi: this.box, polygons: this.polygons, step: Number(this.stepIn.value),
      subset: Number(this.subsetIn.value) };
    try {
      const out = await STS.getJSON("/api/region", { method: "POST",
        headers: { "Content-Type": "application/json" }, body: JSON.stringify(body) });
      this.cmd.value = out.command;
      this.preview = out.points;
      this.saveNote.textContent = (out.mask ? `wrote ${out.mask} (${out.mask_pixels} pixels to measure); ` : "no mask (no polygon); ") +
        `${out.n_points} grid points at step ${body.step} (the run may drop a few near the image border to leave room for the motion)`;
      this.saveNote.dataset.saved = "1";
      STS.message("");
      this.draw();
    } catch (e) {
      STS.message(e.message, true);
      this.saveNote.textContent = e.message;
    }
  }
};
