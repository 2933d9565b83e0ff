// Custom displays a module declares for its state (`displays = {"error": "plot", ...}`):
// a plot over time, a gauge between a minimum and a maximum, a live image.

import {h, s} from "./dom.js";
import * as fmt from "./format.js";
import {imageUrl} from "./api.js";

const HISTORY = 240;          // samples kept for a plot (2 minutes at 0.5 s)
const SERIES = 8;             // series drawn from a 1-D array
const COLOURS = ["#2563eb", "#db2777", "#16a34a", "#ea580c", "#7c3aed", "#0891b2", "#ca8a04", "#475569"];

/** A number or a small 1-D array, plotted over the time this page has watched it. */
export class Plot {
  constructor() {
    this.samples = [];        // [time, [values]]
    this.element = h("div", {class: "display plot"});
  }

  push(view) {
    let values;
    if (view.type === "int" || view.type === "float") values = [view.value];
    else if (view.type === "ndarray" && Array.isArray(view.value)) values = view.value.flat().slice(0, SERIES);
    else if (view.type === "ndarray") values = [view.summary?.mean];
    else return;
    // a null is a float that is not finite (inf, nan): a gap in its line, not a 0
    this.samples.push([performance.now() / 1000, values.map((v) => v === null ? NaN : Number(v))]);
    if (this.samples.length > HISTORY) this.samples.shift();
    this.draw();
  }

  draw() {
    const W = 320, H = 110, L = 50, B = 16;
    const all = this.samples.flatMap(([, v]) => v).filter(Number.isFinite);
    if (!all.length) return;
    let lo = Math.min(...all), hi = Math.max(...all);
    if (hi === lo) { hi += Math.abs(hi) * 0.1 || 1; lo -= Math.abs(lo) * 0.1 || 1; }
    const t0 = this.samples[0][0], t1 = Math.max(this.samples.at(-1)[0], t0 + 1);
    const x = (t) => L + (W - L - 6) * (t - t0) / (t1 - t0);
    const y = (v) => 6 + (H - B - 12) * (1 - (v - lo) / (hi - lo));
    const width = this.samples[0][1].length;
    const lines = [];
    for (let i = 0; i < width; i += 1) {
      // one polyline per run of finite values: a value that is not one leaves a gap
      const runs = [[]];
      for (const [t, v] of this.samples) {
        if (Number.isFinite(v[i])) runs.at(-1).push(`${x(t).toFixed(1)},${y(v[i]).toFixed(1)}`);
        else if (runs.at(-1).length) runs.push([]);
      }
      for (const run of runs.filter((r) => r.length)) {
        lines.push(s("polyline", {points: run.join(" "), fill: "none", stroke: COLOURS[i % COLOURS.length],
                                  "stroke-width": 1.8, "stroke-linejoin": "round"}));
      }
    }
    const last = this.samples.at(-1)[1];
    this.element.replaceChildren(s("svg", {viewBox: `0 0 ${W} ${H}`, class: "plot-svg"}, [
      s("line", {x1: L, x2: W - 6, y1: y(lo), y2: y(lo), class: "axis"}),
      s("line", {x1: L, x2: L, y1: 6, y2: H - B - 6, class: "axis"}),
      s("text", {x: L - 5, y: y(hi) + 4, "text-anchor": "end", class: "tick"}, fmt.tick(hi)),
      s("text", {x: L - 5, y: y(lo) + 4, "text-anchor": "end", class: "tick"}, fmt.tick(lo)),
      s("text", {x: W - 6, y: H - 2, "text-anchor": "end", class: "tick"},
        `last ${(t1 - t0).toFixed(0)} s · now ${last.map((v) => Number.isFinite(v) ? fmt.number(v) : "–").join(", ")}`),
      ...lines,
    ]));
  }
}

/** A number between a minimum and a maximum, as a dial. */
export class Gauge {
  constructor(min, max) {
    this.min = Number(min ?? 0);
    this.max = Number(max ?? 1);
    this.element = h("div", {class: "display gauge"});
  }

  push(view) {
    const raw = view.type === "ndarray" ? view.summary?.mean : view.value;
    const value = raw === null || raw === undefined ? NaN : Number(raw);    // null: inf or nan
    const span = this.max - this.min || 1;
    const f = Number.isFinite(value) ? Math.min(1, Math.max(0, (value - this.min) / span)) : 0;
    const R = 52, cx = 70, cy = 64;
    const at = (k) => [cx - R * Math.cos(Math.PI * k), cy - R * Math.sin(Math.PI * k)];
    const [ex, ey] = at(f);
    const [sx, sy] = at(0), [tx, ty] = at(1);
    const tone = f > 0.9 ? "#dc2626" : f > 0.7 ? "#ea580c" : "#2563eb";
    this.element.replaceChildren(s("svg", {viewBox: "0 0 140 84", class: "gauge-svg"}, [
      s("path", {d: `M${sx},${sy} A${R},${R} 0 0 1 ${tx},${ty}`, class: "gauge-track"}),
      // no value, no arc: a gauge at its minimum would say the value is the minimum
      Number.isFinite(value) ? s("path", {d: `M${sx},${sy} A${R},${R} 0 0 1 ${ex.toFixed(2)},${ey.toFixed(2)}`,
                                          class: "gauge-value", stroke: tone}) : null,
      s("text", {x: cx, y: cy - 8, "text-anchor": "middle", class: "gauge-number"},
        Number.isFinite(value) ? fmt.number(value) : "–"),
      s("text", {x: sx, y: cy + 16, "text-anchor": "middle", class: "tick"}, fmt.number(this.min)),
      s("text", {x: tx, y: cy + 16, "text-anchor": "middle", class: "tick"}, fmt.number(this.max)),
    ]));
  }
}

// Viridis at nine stops (perceptually even, legible to colour-blind readers): the grey
// levels of the server's PNG (min..max) are drawn through it.
const VIRIDIS = [[68, 1, 84], [71, 44, 122], [59, 81, 139], [44, 113, 142], [33, 144, 141],
                 [39, 173, 129], [92, 200, 99], [170, 220, 50], [253, 231, 37]];
const LUT = Array.from({length: 256}, (_, g) => {
  const f = g / 255 * (VIRIDIS.length - 1), i = Math.min(Math.floor(f), VIRIDIS.length - 2);
  const t = f - i;
  return VIRIDIS[i].map((c, k) => Math.round(c + (VIRIDIS[i + 1][k] - c) * t));
});

/** A 2-D array as a picture, fetched anew each refresh and drawn in colour; the old one
 * stays until the new one has loaded, so it never flickers. */
export class LiveImage {
  constructor(large) {
    this.canvas = h("canvas", {class: `state-image ${large ? "large" : ""}`});
    this.scale = h("div", {class: "image-scale"});
    this.element = h("div", {class: "display image"}, [this.canvas, this.scale]);
    this.loading = false;
  }

  push(view) {
    if (!view.image || this.loading) return;
    this.loading = true;
    const next = new Image();
    next.onload = () => { this.draw(next, view.summary); this.loading = false; };
    next.onerror = () => { this.loading = false; };
    next.src = imageUrl(view.image, Date.now());
  }

  draw(image, summary) {
    const {width, height} = image;
    if (this.canvas.width !== width || this.canvas.height !== height) {
      this.canvas.width = width;
      this.canvas.height = height;
    }
    const context = this.canvas.getContext("2d", {willReadFrequently: true});
    context.drawImage(image, 0, 0);
    const pixels = context.getImageData(0, 0, width, height);
    const data = pixels.data;
    for (let i = 0; i < data.length; i += 4) {
      const [r, g, b] = LUT[data[i]];
      data[i] = r; data[i + 1] = g; data[i + 2] = b;
    }
    context.putImageData(pixels, 0, 0);
    this.canvas.classList.add("drawn");
    if (summary) {
      this.scale.replaceChildren(h("span", {}, fmt.number(summary.min)), h("i"),
                                 h("span", {}, fmt.number(summary.max)));
    }
  }
}

/** The display a module declared for a field ({"kind": "plot" | "gauge" | "image", ...}). */
export function makeDisplay(spec) {
  if (!spec) return null;
  if (spec.kind === "plot") return new Plot();
  if (spec.kind === "gauge") return new Gauge(spec.min, spec.max);
  if (spec.kind === "image") return new LiveImage(true);
  return null;
}
