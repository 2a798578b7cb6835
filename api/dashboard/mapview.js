// The map: an SVG in metres (x east, y north) with pan and zoom.
//
// Convention: layers under #world are drawn in map-frame metres and placed by one
// transform (y flipped), so panning only rewrites that transform; markers (points of a
// fixed size on screen) are redrawn in screen pixels. Every layer carries data-count
// (or data-points, data-cells, ...) with what it shows, for tests and for humans.

import { el, fmt, linearTicks, title } from "./plots.js";

export const CLUSTER_COLOURS = [
  "#4e79a7", "#f28e2b", "#e15759", "#59a14f", "#b07aa1", "#9c755f",
  "#17becf", "#edc948", "#ff9da7", "#76b7b2", "#8c564b", "#bcbd22",
];
// Robots: no violet (that is the places' colour), dark enough for 1.5 px lines on white.
export const ROBOT_COLOURS = ["#0b5cad", "#c2410c", "#15803d", "#be185d", "#a16207", "#0f766e", "#4b5563"];
/** Place labels (P<id>) are drawn when at most this many places are visible; else hover. */
const PLACE_LABELS_MAX = 12;

export const clusterColour = (c) => CLUSTER_COLOURS[((c % CLUSTER_COLOURS.length) + CLUSTER_COLOURS.length) % CLUSTER_COLOURS.length];

const MARGIN = { left: 46, right: 8, top: 8, bottom: 24 };
/** The view's scale [px/m] stays within these. */
const clampScale = (s) => Math.min(Math.max(s, 0.05), 5000);
const SIGMAS = 2;

/** Half-axes (2σ) and angle (radians, counter-clockwise from +x) of a 2x2 covariance. */
export function ellipse2(cov) {
  const [[a, b], [, c]] = cov;
  const mid = (a + c) / 2;
  const r = Math.hypot((a - c) / 2, b);
  const l1 = Math.max(mid + r, 0);
  const l2 = Math.max(mid - r, 0);
  return { rx: SIGMAS * Math.sqrt(l1), ry: SIGMAS * Math.sqrt(l2), angle: 0.5 * Math.atan2(2 * b, a - c), l1, l2 };
}

function bounds(points) {
  let [x0, y0, x1, y1] = [Infinity, Infinity, -Infinity, -Infinity];
  for (const [x, y] of points) {
    if (!Number.isFinite(x) || !Number.isFinite(y)) continue;
    if (x < x0) x0 = x;
    if (x > x1) x1 = x;
    if (y < y0) y0 = y;
    if (y > y1) y1 = y;
  }
  return x0 <= x1 ? { x0, y0, x1, y1 } : null;
}

export class MapView {
  constructor(svg) {
    this.svg = svg;
    this.q = (id) => svg.querySelector(`#${id}`);
    this.view = { cx: 0, cy: 0, s: 40 };
    this.autoFit = true;
    this.data = {
      landmarks: [], ghosts: [], grid: null, trajectories: {}, poseEllipses: [],
      places: [], transitions: [], robotColour: () => ROBOT_COLOURS[0],
    };
    this._frame = 0;
    this._installInteraction();
    new ResizeObserver(() => this.redraw({ world: false })).observe(svg);
  }

  // ------------------------------------------------------------------ geometry
  _size() {
    const w = this.svg.clientWidth || 800;
    const h = this.svg.clientHeight || 500;
    return { w, h, pw: w - MARGIN.left - MARGIN.right, ph: h - MARGIN.top - MARGIN.bottom };
  }
  sx(x) {
    const { pw } = this._size();
    return MARGIN.left + pw / 2 + (x - this.view.cx) * this.view.s;
  }
  sy(y) {
    const { ph } = this._size();
    return MARGIN.top + ph / 2 - (y - this.view.cy) * this.view.s;
  }
  toWorld(px, py) {
    const { pw, ph } = this._size();
    return [
      this.view.cx + (px - MARGIN.left - pw / 2) / this.view.s,
      this.view.cy - (py - MARGIN.top - ph / 2) / this.view.s,
    ];
  }

  fit() {
    const d = this.data;
    const pts = [];
    for (const rows of Object.values(d.trajectories)) for (const p of rows) pts.push([p.x, p.y]);
    for (const l of d.landmarks) pts.push([l.x, l.y], [l.observed_from.x, l.observed_from.y]);
    for (const g of d.ghosts) pts.push([g.x, g.y]);
    for (const p of d.places) pts.push([p.x, p.y]);
    const b = bounds(pts);
    if (!b) return;
    const { pw, ph } = this._size();
    const span = Math.max(b.x1 - b.x0, b.y1 - b.y0, 1);
    this.view.cx = (b.x0 + b.x1) / 2;
    this.view.cy = (b.y0 + b.y1) / 2;
    this.view.s = 0.9 * Math.min(pw / Math.max(b.x1 - b.x0, span * 0.05, 1), ph / Math.max(b.y1 - b.y0, span * 0.05, 1));
  }

  zoomAt(factor, px, py) {
    const [wx, wy] = this.toWorld(px, py);
    this.view.s = clampScale(this.view.s * factor);
    this._pin(wx, wy, px, py);
    this.autoFit = false;
    this.redraw({ world: false });
  }

  /** Move the view so that the world point (wx, wy) [m] is at (px, py) on screen. */
  _pin(wx, wy, px, py) {
    const { pw, ph } = this._size();
    this.view.cx = wx - (px - MARGIN.left - pw / 2) / this.view.s;
    this.view.cy = wy + (py - MARGIN.top - ph / 2) / this.view.s;
  }

  /** A pointer's position in the SVG's own pixels (inside its border). */
  _local(e) {
    const r = this.svg.getBoundingClientRect();
    return [e.clientX - r.left - this.svg.clientLeft, e.clientY - r.top - this.svg.clientTop];
  }

  /**
   * Drag with one pointer pans; two pointers (a pinch) keep the map point under their
   * midpoint under it while their spread scales the view. Each move is applied against
   * the pointers' previous positions, so the map stays under the fingers.
   */
  _installInteraction() {
    const svg = this.svg;
    const pointers = new Map();
    const mid = (p) => [(p[0][0] + p[1][0]) / 2, (p[0][1] + p[1][1]) / 2];
    const spread = (p) => Math.hypot(p[0][0] - p[1][0], p[0][1] - p[1][1]);
    svg.addEventListener("pointerdown", (e) => {
      svg.setPointerCapture(e.pointerId);
      pointers.set(e.pointerId, this._local(e));
      svg.classList.add("dragging");
    });
    const end = (e) => {
      pointers.delete(e.pointerId);
      if (!pointers.size) svg.classList.remove("dragging");
    };
    svg.addEventListener("pointerup", end);
    svg.addEventListener("pointercancel", end);
    svg.addEventListener("pointermove", (e) => {
      if (!pointers.has(e.pointerId)) return;
      const before = [...pointers.values()].slice(0, 2);
      pointers.set(e.pointerId, this._local(e));
      const after = [...pointers.values()].slice(0, 2);
      if (after.length === 2) {
        const [wx, wy] = this.toWorld(...mid(before));
        if (spread(before) > 0) this.view.s = clampScale((this.view.s * spread(after)) / spread(before));
        this._pin(wx, wy, ...mid(after));
      } else {
        const [wx, wy] = this.toWorld(...before[0]);
        this._pin(wx, wy, ...after[0]);
      }
      this.autoFit = false;
      this.redraw({ world: false });
    });
    svg.addEventListener("wheel", (e) => {
      e.preventDefault();
      this.zoomAt(Math.exp(-e.deltaY * 0.0015), ...this._local(e));
    }, { passive: false });
  }

  // ------------------------------------------------------------------ drawing
  /** Redraw on the next animation frame; `world` also rebuilds the metre layers. */
  redraw({ world = true } = {}) {
    this._worldDirty = this._worldDirty || world;
    if (this._frame) return;
    this._frame = requestAnimationFrame(() => {
      this._frame = 0;
      if (this.autoFit) this.fit();
      if (this._worldDirty) this._drawWorld();
      this._worldDirty = false;
      this._place();
      this._drawAxes();
      this._drawMarkers();
    });
  }

  /** Draw now (tests and screenshots read the DOM right after data changes). */
  flush() {
    if (this._frame) cancelAnimationFrame(this._frame);
    this._frame = 0;
    if (this.autoFit) this.fit();
    this._drawWorld();
    this._worldDirty = false;
    this._place();
    this._drawAxes();
    this._drawMarkers();
  }

  _place() {
    const { pw, ph } = this._size();
    const s = this.view.s;
    const tx = MARGIN.left + pw / 2 - this.view.cx * s;
    const ty = MARGIN.top + ph / 2 + this.view.cy * s;
    this.q("world").setAttribute("transform", `matrix(${s},0,0,${-s},${tx},${ty})`);
    const clip = this.q("plot-clip-rect");
    clip.setAttribute("x", MARGIN.left);
    clip.setAttribute("y", MARGIN.top);
    clip.setAttribute("width", Math.max(pw, 1));
    clip.setAttribute("height", Math.max(ph, 1));
  }

  _drawAxes() {
    const g = this.q("axes");
    g.replaceChildren();
    g.setAttribute("class", "axis");
    const { w, h, pw, ph } = this._size();
    const [x0, y0] = this.toWorld(MARGIN.left, MARGIN.top + ph);
    const [x1, y1] = this.toWorld(MARGIN.left + pw, MARGIN.top);
    const n = Math.max(2, Math.round(pw / 90));
    const step = linearTicks(x0, x1, n);
    for (const t of step) {
      const x = this.sx(t);
      el("line", { class: "tick", x1: x, x2: x, y1: MARGIN.top, y2: MARGIN.top + ph }, g);
      el("text", { x, y: h - 8, "text-anchor": "middle" }, g).textContent = fmt(t);
    }
    const dx = step.length > 1 ? step[1] - step[0] : 1;
    const ny = Math.max(2, Math.round((y1 - y0) / dx));
    for (const t of linearTicks(y0, y1, ny)) {
      const y = this.sy(t);
      el("line", { class: "tick", x1: MARGIN.left, x2: MARGIN.left + pw, y1: y, y2: y }, g);
      el("text", { x: MARGIN.left - 4, y: y + 4, "text-anchor": "end" }, g).textContent = fmt(t);
    }
    el("path", { class: "frame", d: `M${MARGIN.left},${MARGIN.top}V${MARGIN.top + ph}H${MARGIN.left + pw}` }, g);
    el("text", { x: w - MARGIN.right, y: h - 8 - 12, "text-anchor": "end" }, g).textContent = "x [m]";
    el("text", { x: MARGIN.left + 4, y: MARGIN.top + 12 }, g).textContent = "y [m]";
  }

  _drawWorld() {
    const d = this.data;
    // coverage grid: explored cells shaded by count; holes (count 0) highlighted
    const cov = this.q("layer-coverage");
    const grid = d.grid;
    if (grid !== this._drawnGrid) this._drawGrid(cov, grid); // up to 200 x 200 cells: only when new
    this._drawnGrid = grid;
    this._drawRest(d);
  }

  _drawGrid(cov, grid) {
    cov.replaceChildren();
    let cells = 0;
    if (grid && grid.width) {
      const max = grid.counts.flat().reduce((m, v) => (v !== null && v > m ? v : m), 1);
      grid.counts.forEach((row, iy) => row.forEach((n, ix) => {
        if (n === null) return;
        cells += 1;
        const attrs = {
          x: grid.origin.x + ix * grid.cell_m, y: grid.origin.y + iy * grid.cell_m,
          width: grid.cell_m, height: grid.cell_m,
        };
        const r = n === 0
          ? el("rect", { ...attrs, class: "hole" }, cov)
          : el("rect", { ...attrs, class: "cell", fill: `rgba(26, 127, 55, ${(0.08 + 0.32 * n / max).toFixed(3)})` }, cov);
        title(r, n === 0
          ? `hole: no live landmark observed from within ${grid.radius_m} m of this cell`
          : `${n} live landmark(s) observed from within ${grid.radius_m} m`);
      }));
    }
    cov.dataset.cells = String(cells);
    cov.dataset.holes = String(grid ? grid.holes.length : 0);
  }

  _drawRest(d) {
    // trajectories
    const tr = this.q("layer-trajectories");
    tr.replaceChildren();
    let points = 0;
    for (const [robot, rows] of Object.entries(d.trajectories)) {
      points += rows.length;
      const line = el("polyline", {
        class: "traj", stroke: d.robotColour(robot), "data-robot": robot, "data-points": rows.length,
        points: rows.map((p) => `${p.x.toFixed(3)},${p.y.toFixed(3)}`).join(" "),
      }, tr);
      title(line, `${robot}: ${rows.length} poses`);
    }
    tr.dataset.points = String(points);
    tr.dataset.robots = String(Object.keys(d.trajectories).length);

    // 2σ pose ellipses at intervals
    const pe = this.q("layer-pose-ellipses");
    pe.replaceChildren();
    for (const p of d.poseEllipses) {
      const e = ellipse2(p.covariance);
      el("ellipse", {
        class: "pose-ellipse", cx: p.x, cy: p.y, rx: e.rx, ry: e.ry, stroke: d.robotColour(p.robot),
        transform: `rotate(${(e.angle * 180) / Math.PI} ${p.x} ${p.y})`,
      }, pe);
    }
    pe.dataset.count = String(d.poseEllipses.length);

    // observation-position mean E(X) -> landmark, coloured by cluster
    const joins = this.q("layer-joins");
    joins.replaceChildren();
    const le = this.q("layer-landmark-ellipses");
    le.replaceChildren();
    for (const l of d.landmarks) {
      el("line", {
        class: "join", x1: l.observed_from.x, y1: l.observed_from.y, x2: l.x, y2: l.y,
        stroke: clusterColour(l.cluster),
      }, joins);
      if (l.covariance) {
        const e = ellipse2(l.covariance);
        el("ellipse", {
          class: "lm-ellipse", cx: l.x, cy: l.y, rx: e.rx, ry: e.ry, "data-id": l.id,
          transform: `rotate(${(e.angle * 180) / Math.PI} ${l.x} ${l.y})`,
        }, le);
      }
    }
    joins.dataset.count = String(d.landmarks.length);
    le.dataset.count = String(le.childElementCount);

    // transitions between places
    const tg = this.q("layer-transitions");
    tg.replaceChildren();
    const byId = new Map(d.places.map((p) => [String(p.id), p]));
    let drawn = 0;
    for (const t of d.transitions) {
      const a = byId.get(String(t.from));
      const b = byId.get(String(t.to));
      if (!a || !b) continue;
      drawn += 1;
      title(el("line", { class: "transition", x1: a.x, y1: a.y, x2: b.x, y2: b.y }, tg),
        `transition ${t.from} → ${t.to}${t.count != null ? ` (${t.count}×)` : ""}`);
    }
    tg.dataset.count = String(drawn);
  }

  _drawMarkers() {
    const d = this.data;
    const { w, h } = this._size();
    const visible = (x, y) => x > -20 && y > -20 && x < w + 20 && y < h + 20;

    const gh = this.q("layer-ghosts");
    gh.replaceChildren();
    for (const g of d.ghosts) {
      const [x, y] = [this.sx(g.x), this.sy(g.y)];
      const c = el("circle", { class: "ghost", cx: x.toFixed(1), cy: y.toFixed(1), r: 4.5, "data-id": g.landmark_id }, gh);
      if (!visible(x, y)) c.setAttribute("visibility", "hidden");
      title(c, `marginalised landmark ${g.landmark_id} (label ${g.label}), archived at frame ${g.frame_id ?? g.frame}` +
        `${g.removals > 1 ? ` (removed ${g.removals} times)` : ""}, ${g.policy} policy: ${g.reason}`);
    }
    gh.dataset.count = String(d.ghosts.length);

    const ob = this.q("layer-observed");
    ob.replaceChildren();
    const clusters = new Set();
    for (const l of d.landmarks) {
      clusters.add(l.cluster);
      const c = el("circle", {
        class: "observed", cx: this.sx(l.observed_from.x).toFixed(1), cy: this.sy(l.observed_from.y).toFixed(1),
        r: 3.5, fill: clusterColour(l.cluster), "data-cluster": l.cluster, "data-id": l.id,
      }, ob);
      title(c, `E(X) of landmark ${l.id}: mean robot position it was observed from ` +
        `(${l.observed_from.x.toFixed(2)}, ${l.observed_from.y.toFixed(2)}) m, n = ${l.observed_from.n}, cluster ${l.cluster}`);
    }
    ob.dataset.count = String(d.landmarks.length);
    ob.dataset.clusters = String(clusters.size);

    const pl = this.q("layer-places");
    pl.replaceChildren();
    const shown = d.places.filter((p) => visible(this.sx(p.x), this.sy(p.y))).length;
    for (const p of d.places) {
      const [x, y] = [this.sx(p.x), this.sy(p.y)];
      const g = el("g", { class: "place-marker", "data-id": p.id }, pl);
      if (!visible(x, y)) g.setAttribute("visibility", "hidden");
      const sq = el("rect", { class: "place", x: (x - 4).toFixed(1), y: (y - 4).toFixed(1), width: 8, height: 8 }, g);
      if (Number.isFinite(p.theta)) { // the reference pose's heading
        el("line", {
          class: "place-heading", x1: x, y1: y, x2: x + 11 * Math.cos(p.theta), y2: y - 11 * Math.sin(p.theta),
        }, g);
      }
      if (shown <= PLACE_LABELS_MAX) el("text", { class: "place-label", x: x + 6, y: y - 6 }, g).textContent = `P${p.id}`;
      title(sq, `place ${p.id}: reference pose (${p.x.toFixed(2)}, ${p.y.toFixed(2)}) m` +
        (Number.isFinite(p.theta) ? `, θ ${((p.theta * 180) / Math.PI).toFixed(0)}°` : "") +
        (p.landmarks != null ? `, ${p.landmarks} landmarks` : "") +
        (p.robot != null ? `, learnt by ${p.robot}` : "") + (p.frame != null ? ` at frame ${p.frame}` : ""));
    }
    pl.dataset.count = String(d.places.length);
    pl.dataset.labels = String(pl.querySelectorAll("text.place-label").length);
    pl.dataset.transitions = String(d.transitions.length);

    const lm = this.q("layer-landmarks");
    lm.replaceChildren();
    for (const l of d.landmarks) {
      const c = el("circle", {
        class: "landmark", cx: this.sx(l.x).toFixed(1), cy: this.sy(l.y).toFixed(1), r: 4.5,
        "data-id": l.id, "data-cluster": l.cluster,
      }, lm);
      const sig = l.covariance ? ellipse2(l.covariance) : null;
      title(c, `landmark ${l.id} (label ${l.label}) at (${l.x.toFixed(2)}, ${l.y.toFixed(2)}) m` +
        (l.information != null ? `, I = ${fmt(l.information)} 1/m²` : "") +
        (sig ? `, 2σ ${sig.rx.toFixed(2)} × ${sig.ry.toFixed(2)} m` : "") + `, cluster ${l.cluster}`);
    }
    lm.dataset.count = String(d.landmarks.length);

    const rb = this.q("layer-robots");
    rb.replaceChildren();
    let robots = 0;
    for (const [robot, rows] of Object.entries(d.trajectories)) {
      const p = rows[rows.length - 1];
      if (!p) continue;
      robots += 1;
      const [x, y] = [this.sx(p.x), this.sy(p.y)];
      const deg = (-p.theta * 180) / Math.PI;
      title(el("path", {
        class: "robot", d: "M9,0L-6,5.5L-3,0L-6,-5.5Z", fill: d.robotColour(robot),
        transform: `translate(${x.toFixed(1)} ${y.toFixed(1)}) rotate(${deg.toFixed(1)})`, "data-robot": robot,
      }, rb), `${robot}: seq ${p.seq} at (${p.x.toFixed(2)}, ${p.y.toFixed(2)}) m, θ ${(p.theta * 180 / Math.PI).toFixed(0)}°`);
    }
    rb.dataset.count = String(robots);
  }
}
