// The deviation map in the plate's own frame (target frame, mm; y up): axes in mm, an orientation
// mark at the origin, the defects numbered, the template frames, the outline of each conveyor station
// of a plate measured at stations, zoom and pan, the value under the pointer. A click (not a drag)
// asks the page to put a template through that point.
import { getJSON } from "./api.js";

// the SVG namespace, read from the page's own <svg> (the map's) when a map is made
let SVG = null;
const ZOOM_STEP = 1.5;

function el(name, attrs = {}, text) {
  const node = document.createElementNS(SVG, name);
  for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, String(v));
  if (text !== undefined) node.textContent = text;
  return node;
}

/** Round tick values over [lo, hi]: steps of 1, 2, 2.5 or 5 times a power of ten. */
export function niceTicks(lo, hi, maxTicks = 7) {
  const raw = (hi - lo) / maxTicks;
  const power = 10 ** Math.floor(Math.log10(raw));
  const step = [1, 2, 2.5, 5, 10].map((m) => m * power).find((s) => s >= raw);
  const out = [];
  for (let v = Math.ceil(lo / step) * step; v <= hi + 1e-9; v += step) out.push(Math.abs(v) < 1e-9 ? 0 : v);
  return out;
}

/** Where a defect's numbered badge goes: up and to the right of its place, or, when that would touch
 * a badge already placed, the nearest of 8 directions on growing rings that does not (a leader line
 * joins it to its place). All in SVG units; ``placed`` the badges' centres so far. */
export function badgePlace(x, y, r, unit, placed) {
  const free = (px, py) => placed.every(([qx, qy]) => Math.hypot(px - qx, py - qy) >= 2.2 * r);
  for (let ring = 1; ring <= 6; ring++) {
    const dist = 4 * unit * Math.SQRT2 * ring;
    for (let k = 0; k < 8; k++) {
      const a = -Math.PI / 4 + (k * Math.PI) / 4; // first up-right (SVG y down), then round
      const px = x + dist * Math.cos(a), py = y + dist * Math.sin(a);
      if (free(px, py)) return [px, py];
    }
  }
  return [x + 4 * unit, y - 4 * unit];
}

function signed(v, digits) {
  return `${v >= 0 ? "+" : "−"}${Math.abs(v).toFixed(digits)}`;
}

export class PlateMap {
  constructor(figure, { onPick } = {}) {
    this.figure = figure;
    this.svg = figure.querySelector("svg");
    SVG = this.svg.namespaceURI;
    this.readout = figure.querySelector(".map-readout");
    this.onPick = onPick;
    this.frames = [];
    this.picked = null;
  }

  async load() {
    this.data = await getJSON(this.figure.dataset.src);
    const [x0, x1, y0, y1] = this.data.extent_mm;
    this.full = { x: x0, y: y0, w: x1 - x0, h: y1 - y0 };
    this.view = { ...this.full };
    this.layers();
    this.bind();
    this.render();
    this.figure.dataset.ready = "true";
    return this;
  }

  // Static content lives in mm with y flipped (SVG y = -plate y); the axes are redrawn per view.
  layers() {
    const { x0_mm: x0, extent_mm: e } = this.data;
    this.content = el("g", { class: "map-content" });
    // Under the map's cells: what shows through an unmeasured (transparent) cell, as the legend says.
    this.content.append(el("rect", {
      class: "map-unmeasured", x: x0, y: -e[3], width: e[1] - e[0], height: e[3] - e[2],
    }));
    this.content.append(el("image", {
      href: this.figure.dataset.png, x: x0, y: -e[3], width: e[1] - e[0], height: e[3] - e[2],
      preserveAspectRatio: "none",
    }));
    this.stationLayer = el("g", { class: "map-stations" });
    this.frameLayer = el("g", { class: "map-frames" });
    this.markLayer = el("g", { class: "map-marks" });
    this.content.append(this.stationLayer, this.frameLayer, this.markLayer);
    // the plate's drawing stays inside the plot area when zoomed (the axes' margin is not the map)
    const clipId = `${this.figure.id || "plate-map"}-clip`;
    this.clipRect = el("rect");
    const clip = el("clipPath", { id: clipId });
    clip.append(this.clipRect);
    const defs = el("defs");
    defs.append(clip);
    this.content.setAttribute("clip-path", `url(#${clipId})`);
    this.axes = el("g", { class: "map-axes" });
    this.svg.replaceChildren(defs, this.content, this.axes);
  }

  /** Template frame lines: [{x1, y1, x2, y2, label, kind}] in target mm. */
  setFrames(frames) {
    this.frames = frames;
    if (this.data) this.render();
  }

  setPicked(point) {
    this.picked = point;
    if (this.data) this.render();
  }

  valueAt(x, y) {
    const { x0_mm: x0, y0_mm: y0, cell_mm: cell, nx, ny, deviation_mm: grid } = this.data;
    const i = Math.floor((x - x0) / cell);
    const j = Math.floor((y - y0) / cell);
    if (i < 0 || j < 0 || i >= nx || j >= ny) return null;
    return grid[j][i];
  }

  // The view box: the visible plate rectangle plus a margin for the axes' labels, in SVG units.
  viewBox() {
    const { x, y, w, h } = this.view;
    const pad = 0.11 * Math.max(w, h);
    return [x - pad, -(y + h) - 0.04 * Math.max(w, h), w + 1.15 * pad, h + pad + 0.04 * Math.max(w, h)];
  }

  /** Show the same plate rectangle as another map (the compare page keeps its maps together). */
  follow(view) {
    this.view = { ...view };
    this.figure.dataset.zoom = (this.full.w / view.w).toFixed(2);
    this.render(false);
  }

  render(tell = true) {
    if (tell && this.onView) this.onView(this.view);
    const box = this.viewBox();
    this.svg.setAttribute("viewBox", box.join(" "));
    const { x, y, w, h } = this.view;
    for (const [k, v] of Object.entries({ x, y: -(y + h), width: w, height: h })) this.clipRect.setAttribute(k, String(v));
    const unit = Math.max(this.view.w, this.view.h) / 100; // 1 % of the view, in mm
    this.drawStations(unit);
    this.drawFrames(unit);
    this.drawMarks(unit);
    this.drawAxes(unit);
  }

  /** Each station's outline (where its image frame lies on the plate, target mm) and its number, at
   * the map's left edge a quarter of the way up the part of the plate only that station sees (clear
   * of the overlaps, and of the edge names at the middle of the sides). */
  drawStations(unit) {
    const [x0, , y0, y1] = this.data.extent_mm;
    const stations = (this.data.stations || []).filter((s) => s.outline_mm);
    const spans = stations.map((s) => {
      const ys = s.outline_mm.map(([, y]) => y);
      return [Math.min(...ys), Math.max(...ys)];
    });
    const outlines = stations.map((s, k) => {
      const g = el("g", { class: "map-station", "data-station": s.index });
      g.append(el("polygon", { points: s.outline_mm.map(([x, y]) => `${x},${-y}`).join(" ") }));
      const [lo, hi] = spans[k];
      let own = [Math.max(lo, spans[k - 1]?.[1] ?? lo, y0), Math.min(hi, spans[k + 1]?.[0] ?? hi, y1)];
      if (own[0] >= own[1]) own = [Math.max(lo, y0), Math.min(hi, y1)];
      const y = own[0] + 0.25 * (own[1] - own[0]);
      g.append(
        el("text", { x: x0 + unit, y: -y, "font-size": 2.6 * unit, "dominant-baseline": "central" }, `station ${s.index}`),
        el("title", {}, `station ${s.index}: travel ${s.travel_mm.toFixed(1)} mm (encoder ${s.travel_encoder_mm.toFixed(1)} mm)`),
      );
      return g;
    });
    this.stationLayer.replaceChildren(...outlines);
  }

  drawFrames(unit) {
    const lines = this.frames.map((f) => {
      const g = el("g", { class: `map-frame-line ${f.kind}` });
      g.append(el("line", { x1: f.x1, y1: -f.y1, x2: f.x2, y2: -f.y2, "stroke-width": 0.3 * unit }));
      g.append(el("text", { x: f.x2 + unit, y: -f.y2, "font-size": 2.4 * unit, "dominant-baseline": "central" }, f.label));
      return g;
    });
    this.frameLayer.replaceChildren(...lines);
  }

  drawMarks(unit) {
    const marks = [];
    // orientation: the target's origin and its x and y axes
    const len = 8 * unit;
    const o = el("g", { class: "map-origin" });
    o.append(
      el("line", { x1: 0, y1: 0, x2: len, y2: 0, "stroke-width": 0.35 * unit }),
      el("line", { x1: 0, y1: 0, x2: 0, y2: -len, "stroke-width": 0.35 * unit }),
      el("path", { d: `M ${len + 1.5 * unit} 0 l ${-1.8 * unit} ${-unit} v ${2 * unit} z` }),
      el("path", { d: `M 0 ${-len - 1.5 * unit} l ${-unit} ${1.8 * unit} h ${2 * unit} z` }),
      el("text", { x: len + 2.2 * unit, y: 0, "font-size": 3 * unit, "dominant-baseline": "central" }, "x"),
      el("text", { x: 0, y: -len - 2.6 * unit, "font-size": 3 * unit, "text-anchor": "middle" }, "y"),
    );
    o.append(el("title", {}, "origin: the target's centre (x 0, y 0)"));
    marks.push(o, this.edgeNames(unit));
    const placed = []; // badge centres so far (SVG units): a clustered defect's badge moves aside
    for (const d of this.data.defects) {
      if (!d.centroid_mm) continue;
      const [x, y] = d.centroid_mm;
      const g = el("g", { class: "map-defect", "data-defect": d.id, "data-x": x, "data-y": y });
      const r = 2.4 * unit;
      const [lx, ly] = badgePlace(x, -y, r, unit, placed);
      placed.push([lx, ly]);
      g.append(
        el("title", {}, `defect ${d.id}: peak ${signed(d.peak_mm, 1)} mm at x ${x.toFixed(0)}, y ${y.toFixed(0)} mm`),
        el("circle", { class: "spot", cx: x, cy: -y, r: 0.9 * unit }),
        el("line", { x1: x, y1: -y, x2: lx, y2: ly, "stroke-width": 0.25 * unit }),
        el("circle", { class: "badge", cx: lx, cy: ly, r, "stroke-width": 0.25 * unit }),
        el("text", { x: lx, y: ly, "font-size": 2.8 * unit, "text-anchor": "middle", "dominant-baseline": "central" }, String(d.id)),
      );
      marks.push(g);
    }
    if (this.cursor) { // the keyboard's read point
      const [x, y] = this.cursor;
      const g = el("g", { class: "map-cursor" });
      g.append(
        el("line", { x1: x - 2 * unit, y1: -y, x2: x + 2 * unit, y2: -y, "stroke-width": 0.35 * unit }),
        el("line", { x1: x, y1: -y - 2 * unit, x2: x, y2: -y + 2 * unit, "stroke-width": 0.35 * unit }),
      );
      marks.push(g);
    }
    if (this.picked) {
      const [x, y] = this.picked;
      marks.push(el("circle", { class: "map-picked", cx: x, cy: -y, r: 1.2 * unit, "stroke-width": 0.4 * unit }));
    }
    this.markLayer.replaceChildren(...marks);
  }

  /** The plate's edges named as in the templates and the report: A where y is smallest, then
   * counter-clockwise (B at the largest x, C at the largest y, D at the smallest x). */
  edgeNames(unit) {
    const [x0, x1, y0, y1] = this.data.extent_mm;
    const cx = (x0 + x1) / 2, cy = (y0 + y1) / 2, size = 2.6 * unit;
    const g = el("g", { class: "map-edges" });
    g.append(
      el("text", { "data-edge": "A", x: cx, y: -y0 - 0.8 * unit, "font-size": size, "text-anchor": "middle" }, "edge A"),
      el("text", { "data-edge": "B", x: x1 - 0.8 * unit, y: -cy, "font-size": size, "text-anchor": "end", "dominant-baseline": "central" }, "edge B"),
      el("text", { "data-edge": "C", x: cx, y: -y1 + 0.8 * unit, "font-size": size, "text-anchor": "middle", "dominant-baseline": "hanging" }, "edge C"),
      el("text", { "data-edge": "D", x: x0 + 0.8 * unit, y: -cy, "font-size": size, "dominant-baseline": "central" }, "edge D"),
    );
    return g;
  }

  drawAxes(unit) {
    const { x, y, w, h } = this.view;
    const nodes = [];
    const base = -y + 1.2 * unit; // just below the plate's lowest visible y
    const left = x - 1.2 * unit;
    nodes.push(el("line", { class: "axis-line", x1: x, y1: base, x2: x + w, y2: base, "stroke-width": 0.15 * unit }));
    nodes.push(el("line", { class: "axis-line", x1: left, y1: -y, x2: left, y2: -(y + h), "stroke-width": 0.15 * unit }));
    for (const t of niceTicks(x, x + w)) {
      nodes.push(el("line", { class: "tick", x1: t, y1: base, x2: t, y2: base + unit, "stroke-width": 0.15 * unit }));
      nodes.push(el("text", { class: "tick-x", x: t, y: base + 3.4 * unit, "font-size": 2.6 * unit, "text-anchor": "middle" }, t.toFixed(0)));
    }
    for (const t of niceTicks(y, y + h)) {
      nodes.push(el("line", { class: "tick", x1: left - unit, y1: -t, x2: left, y2: -t, "stroke-width": 0.15 * unit }));
      nodes.push(el("text", { class: "tick-y", x: left - 1.6 * unit, y: -t, "font-size": 2.6 * unit, "text-anchor": "end", "dominant-baseline": "central" }, t.toFixed(0)));
    }
    nodes.push(el("text", { class: "axis-name", x: x + w, y: base + 6.6 * unit, "font-size": 2.6 * unit, "text-anchor": "end" }, "x, mm"));
    nodes.push(el("text", { class: "axis-name", x: left - 1.6 * unit, y: -(y + h) - 1.6 * unit, "font-size": 2.6 * unit, "text-anchor": "end" }, "y, mm"));
    this.axes.replaceChildren(...nodes);
  }

  /** The plate point (target mm) under a client position. */
  toPlate(clientX, clientY) {
    const m = this.svg.getScreenCTM();
    if (!m) return null;
    const p = new DOMPoint(clientX, clientY).matrixTransform(m.inverse());
    return [p.x, -p.y];
  }

  zoom(factor, centre) {
    const [cx, cy] = centre ?? [this.view.x + this.view.w / 2, this.view.y + this.view.h / 2];
    const w = Math.min(this.full.w * 1.5, Math.max(this.full.w / 40, this.view.w / factor));
    const h = w * (this.full.h / this.full.w);
    const fx = (cx - this.view.x) / this.view.w, fy = (cy - this.view.y) / this.view.h;
    this.view = { x: cx - fx * w, y: cy - fy * h, w, h };
    this.figure.dataset.zoom = (this.full.w / w).toFixed(2);
    this.render();
  }

  fit() {
    this.view = { ...this.full };
    this.figure.dataset.zoom = "1.00";
    this.render();
  }

  show(point) {
    if (!point) return;
    const [x, y] = point;
    const v = this.valueAt(x, y);
    const where = `x ${x.toFixed(0)} mm, y ${y.toFixed(0)} mm`;
    if (v === null) {
      this.readout.textContent = `${where}: not measured`;
      return;
    }
    const tol = this.data.tolerance_mm;
    const band = Math.abs(v) <= tol ? "within tolerance" : v > 0 ? "above the target, beyond tolerance" : "below the target, beyond tolerance";
    this.readout.textContent = `${where}: ${signed(v, 2)} mm (${band})`;
    this.readout.dataset.value = String(v);
  }

  /** Keyboard: arrows move the read point (Shift: ten times further), Enter or Space puts a
   * template through it, Home goes back to the plate's centre. */
  bindKeys() {
    this.svg.setAttribute("tabindex", "0");
    const centre = () => [this.full.x + this.full.w / 2, this.full.y + this.full.h / 2];
    this.svg.addEventListener("focus", () => {
      this.cursor ??= centre();
      this.show(this.cursor);
      this.render(false);
    });
    this.svg.addEventListener("keydown", (event) => {
      const step = (event.shiftKey ? 10 : 1) * Math.max(this.data.cell_mm, this.full.w / 100);
      const moves = { ArrowLeft: [-step, 0], ArrowRight: [step, 0], ArrowUp: [0, step], ArrowDown: [0, -step] };
      if (event.key in moves || event.key === "Home") {
        event.preventDefault();
        const [dx, dy] = moves[event.key] ?? [0, 0];
        const [x, y] = event.key === "Home" ? centre() : this.cursor ?? centre();
        const { x: x0, y: y0, w, h } = this.full;
        this.cursor = [Math.min(x0 + w, Math.max(x0, x + dx)), Math.min(y0 + h, Math.max(y0, y + dy))];
        this.show(this.cursor);
        this.render(false);
      } else if ((event.key === "Enter" || event.key === " ") && this.cursor && this.onPick) {
        event.preventDefault();
        if (this.valueAt(...this.cursor) !== null) this.onPick(this.cursor);
      }
    });
  }

  bind() {
    this.bindKeys();
    let drag = null;
    this.figure.querySelectorAll("[data-zoom]").forEach((button) => {
      button.addEventListener("click", () => {
        const how = button.dataset.zoom;
        if (how === "fit") this.fit();
        else this.zoom(how === "in" ? ZOOM_STEP : 1 / ZOOM_STEP);
      });
    });
    this.svg.addEventListener("wheel", (event) => {
      event.preventDefault();
      this.zoom(event.deltaY < 0 ? ZOOM_STEP : 1 / ZOOM_STEP, this.toPlate(event.clientX, event.clientY));
    }, { passive: false });
    this.svg.addEventListener("pointerdown", (event) => {
      // a drag pans: its moves are read in the view it started from
      const inverse = this.svg.getScreenCTM()?.inverse();
      if (inverse) drag = { x: event.clientX, y: event.clientY, view: { ...this.view }, inverse, moved: false };
    });
    this.svg.addEventListener("pointermove", (event) => {
      if (drag && (drag.moved || Math.abs(event.clientX - drag.x) + Math.abs(event.clientY - drag.y) > 4)) {
        drag.moved = true;
        const a = new DOMPoint(drag.x, drag.y).matrixTransform(drag.inverse);
        const b = new DOMPoint(event.clientX, event.clientY).matrixTransform(drag.inverse);
        this.view = { ...drag.view, x: drag.view.x - (b.x - a.x), y: drag.view.y + (b.y - a.y) };
        this.render();
        return;
      }
      this.show(this.toPlate(event.clientX, event.clientY));
    });
    this.svg.addEventListener("pointerup", (event) => {
      const click = drag && !drag.moved;
      drag = null;
      if (!click || !this.onPick) return;
      const point = this.toPlate(event.clientX, event.clientY);
      if (point && this.valueAt(...point) !== null) this.onPick(point);
    });
    this.svg.addEventListener("pointerleave", () => { drag = null; });
  }
}
