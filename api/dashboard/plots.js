// Small SVG helpers shared by the map and the time plots: elements, ticks, line plots.

export const SVG_NS = "http://www.w3.org/2000/svg";

/** A new SVG element with attributes (numbers are written as they are). */
export function el(name, attrs = {}, parent = null) {
  const node = document.createElementNS(SVG_NS, name);
  for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, String(v));
  if (parent) parent.appendChild(node);
  return node;
}

/** A hover title (tooltip) on an SVG element. */
export function title(node, text) {
  el("title", {}, node).textContent = text;
  return node;
}

/** "Nice" linear ticks covering [lo, hi], about `count` of them. */
export function linearTicks(lo, hi, count = 6) {
  if (!(hi > lo)) return [lo];
  const raw = (hi - lo) / Math.max(1, count);
  const mag = 10 ** Math.floor(Math.log10(raw));
  const step = [1, 2, 5, 10].map((m) => m * mag).find((s) => s >= raw) ?? 10 * mag;
  const out = [];
  for (let v = Math.ceil(lo / step) * step; v <= hi + step * 1e-9; v += step) {
    out.push(Math.abs(v) < step * 1e-9 ? 0 : v);
  }
  return out;
}

/** Decade ticks for a log axis over [lo, hi] (both > 0). */
export function logTicks(lo, hi) {
  const out = [];
  for (let e = Math.floor(Math.log10(lo)); e <= Math.ceil(Math.log10(hi)); e++) {
    const v = 10 ** e;
    if (v >= lo * 0.999 && v <= hi * 1.001) out.push(v);
  }
  return out.length >= 2 ? out : [lo, hi];
}

/** A short label for a tick value. */
export function fmt(v) {
  if (v === 0) return "0";
  const a = Math.abs(v);
  if (a >= 1e4 || a < 1e-2) return v.toExponential(0).replace("e+", "e");
  return String(Number(v.toPrecision(3)));
}

/**
 * Draw a line plot into `svg`: `series` = [{name, colour, points: [[x, y], ...]}].
 * Options: {logY, xLabel, yLabel}. Points with y <= 0 are dropped on a log axis.
 * Sets data-points (all points drawn) and data-series on the svg.
 */
export function linePlot(svg, series, { logY = false, xLabel = "", yLabel = "" } = {}) {
  svg.replaceChildren();
  const w = svg.clientWidth || 400;
  const h = svg.clientHeight || 140;
  svg.setAttribute("viewBox", `0 0 ${w} ${h}`);
  const m = { left: 48, right: 8, top: 18, bottom: 28 };
  const kept = series.map((s) => ({
    ...s,
    points: s.points.filter(([x, y]) => Number.isFinite(x) && Number.isFinite(y) && (!logY || y > 0)),
  }));
  const all = kept.flatMap((s) => s.points);
  svg.dataset.points = String(all.length);
  svg.dataset.series = String(kept.filter((s) => s.points.length).length);
  if (!all.length) {
    el("text", { x: w / 2, y: h / 2, "text-anchor": "middle" }, svg).textContent = "no data yet";
    return;
  }
  let [x0, x1, y0, y1] = [Infinity, -Infinity, Infinity, -Infinity];
  for (const [x, y] of all) {
    x0 = Math.min(x0, x);
    x1 = Math.max(x1, x);
    y0 = Math.min(y0, y);
    y1 = Math.max(y1, y);
  }
  if (x1 === x0) x1 = x0 + 1;
  if (logY) {
    y0 = 10 ** Math.floor(Math.log10(y0));
    y1 = 10 ** Math.ceil(Math.log10(y1));
    if (y1 <= y0) y1 = y0 * 10;
  } else {
    y0 = Math.min(0, y0);
    if (y1 <= y0) y1 = y0 + 1;
    y1 *= 1.05;
  }
  const sx = (x) => m.left + ((x - x0) / (x1 - x0)) * (w - m.left - m.right);
  const sy = logY
    ? (y) => h - m.bottom - ((Math.log10(y) - Math.log10(y0)) / (Math.log10(y1) - Math.log10(y0))) * (h - m.top - m.bottom)
    : (y) => h - m.bottom - ((y - y0) / (y1 - y0)) * (h - m.top - m.bottom);
  for (const t of logY ? logTicks(y0, y1) : linearTicks(y0, y1, 4)) {
    el("line", { class: "tick", x1: m.left, x2: w - m.right, y1: sy(t), y2: sy(t) }, svg);
    el("text", { x: m.left - 4, y: sy(t) + 4, "text-anchor": "end" }, svg).textContent = fmt(t);
  }
  for (const t of linearTicks(x0, x1, 5)) {
    const x = sx(t);
    const label = Number.isInteger(t) && Math.abs(t) < 1e6 ? String(t) : fmt(t); // frame numbers in full
    // a label that would run past the right edge ends at its tick instead
    const anchor = x + 3.5 * label.length > w ? "end" : "middle";
    el("text", { x, y: h - m.bottom + 14, "text-anchor": anchor }, svg).textContent = label;
  }
  el("path", { class: "frame", d: `M${m.left},${m.top}V${h - m.bottom}H${w - m.right}` }, svg);
  if (xLabel) el("text", { x: w - m.right, y: h - 4, "text-anchor": "end" }, svg).textContent = xLabel;
  if (yLabel) el("text", { x: m.left, y: 11 }, svg).textContent = yLabel;
  const named = kept.filter((s) => s.name && s.points.length);
  let lx = w - m.right - named.reduce((sum, s) => sum + 18 + 6.5 * s.name.length, 0);
  for (const s of kept) {
    if (!s.points.length) continue;
    const d = s.points.map(([x, y], i) => `${i ? "L" : "M"}${sx(x).toFixed(1)},${sy(y).toFixed(1)}`).join("");
    el("path", {
      d, fill: "none", stroke: s.colour, "stroke-width": 1.3, "stroke-dasharray": s.dash ?? "none",
      "data-name": s.name ?? "",
    }, svg);
    if (!s.name || !s.points.length) continue;
    el("rect", { x: lx, y: 4, width: 10, height: 3, fill: s.colour }, svg);
    el("text", { x: lx + 13, y: 10 }, svg).textContent = s.name;
    lx += 18 + 6.5 * s.name.length;
  }
}
