// The schematic: nodes as regions, modules as boxes inside the node they run on (inputs
// left, outputs right), links as paths with their live figures. Laid out by the server
// (/api/layout, from Graphviz); this draws it, keeps the figures live, and turns
// gestures into requests: click a module (select; with Shift, add to the selection),
// drag it onto another node (move it), drag from an output to an input (link), drop a
// class or a macro from the browser (place). Modules and macro titles take the focus
// (Tab), Enter or Space selects, so nothing needs a pointer.

import {s} from "./dom.js";
import * as fmt from "./format.js";

const HEADER = 24;          // a module box's title band, above its ports
const PORT_R = 4.5;
const DRAG_THRESHOLD = 4;   // pixels a press moves before it counts as a drag
const PAD = 24;             // around the drawing, in layout pixels
const MAX_ZOOM = 1.4;       // a fitted small system is magnified this much at most
const MAX_SHRINK = 3.5;     // and a large one shrunk this much at most: still legible
const PLACEABLE = ["application/x-pb3a-class", "application/x-pb3a-macro"];   // dropped from the browser

export class Schematic {
  /**
   * svg: the <svg> element to draw in.
   * actions: {select(name, {add}), migrate(name, node), connect(src, dst),
   *           place(cls, node, at), placeMacro(macro, node)}
   */
  constructor(svg, actions) {
    this.svg = svg;
    this.actions = actions;
    this.system = null;
    this.layout = null;
    this.boxes = new Map();      // module -> {group, rect, status, figures, ports}
    this.links = new Map();      // key -> {path, label, text}
    this.clusters = new Map();   // node -> {group, rect, badge, figures}
    this.collapsed = new Set();  // macros shown as one box
    this.frames = new Map();     // "macro@node" -> the frame drawn around its modules there
    this.selected = null;
    this.marked = new Set();     // the other modules selected with it (Shift-click)
    this.previous = null;        // the last stats, for rates of steps and events
    this.view = null;            // the viewBox {x, y, w, h}
    this.fitted = true;
    this.layers = {};
    this.bindViewGestures();
    window.addEventListener("resize", () => { if (this.fitted && this.layout) this.fit(); });
  }

  // -- structure -------------------------------------------------------------------
  render(system, layout) {
    const before = new Map([...this.boxes].map(([name, box]) => [name, {...box.at, node: box.info.node}]));
    const focused = this.svg.contains(document.activeElement) ? focusKey(document.activeElement) : null;
    this.system = system;
    this.layout = layout;            // in the page's pixels, every node included (the server's)
    this.svg.replaceChildren();
    this.boxes.clear();
    this.links.clear();
    this.clusters.clear();
    this.svg.append(s("defs", {}, [
      s("marker", {id: "arrow", viewBox: "0 0 10 10", refX: 9, refY: 5, markerWidth: 7,
                   markerHeight: 7, orient: "auto-start-reverse"},
        s("path", {d: "M 0 0 L 10 5 L 0 10 z", class: "arrow-head"})),
    ]));
    for (const name of ["clusters", "frames", "links", "modules", "labels", "drag"]) {
      this.layers[name] = this.svg.appendChild(s("g", {class: `layer-${name}`}));
    }
    for (const [node, box] of Object.entries(layout.clusters || {})) this.drawCluster(node, box);
    for (const [name, info] of Object.entries(system.modules)) {
      const box = layout.modules?.[name];
      if (box) this.drawModule(name, info, box);
    }
    this.drawMacros();
    for (const link of system.links) this.drawLink(link);
    this.setView(this.fitted || !this.view ? this.fullView() : this.view);
    // A module that moved to another node glides from where it was to where it is now.
    for (const [name, box] of this.boxes) {
      const was = before.get(name);
      if (was && was.node !== box.info.node) this.glide(box, was);
    }
    if (this.selected && !this.boxes.has(this.selected) && !this.system.macros?.[this.selected]) {
      this.selected = null;
    }
    this.markSelected();
    // the keyboard user keeps their place through a redraw (a fold, a change of structure)
    if (focused) this.svg.querySelector(focused)?.focus();
  }

  drawCluster(node, box) {
    const info = this.system.nodes?.[node] || {};
    const group = s("g", {class: "cluster", dataset: {node}});
    const rect = s("rect", {x: box.x, y: box.y, width: box.w, height: box.h, rx: 16});
    const title = s("text", {x: box.x + 14, y: box.y + 20, class: "cluster-title"}, node);
    const editing = this.system.mode === "editing";      // nothing runs yet: no health
    const idle = this.system.mode !== "running";        // (nor once it has stopped)
    const badge = s("text", {x: box.x + box.w - 12, y: box.y + 20, class: "cluster-badge",
                             "text-anchor": "end"}, idle ? "" : info.up === false ? "lost" : "up");
    const figures = s("text", {x: box.x + 14, y: box.y + 36, class: "cluster-figures"}, "");
    const reach = s("text", {x: box.x + 14, y: box.y + 50, class: "cluster-figures"},
                    info.address ? `${info.address}` : editing ? "will run in the launcher"
                                                               : "in the launcher");
    group.append(s("title", {}, `node ${node}${info.address ? ` at ${info.address}` : " (embedded)"}`),
                 rect, title, badge, figures, reach);
    if (box.empty) {
      group.append(s("text", {x: box.x + box.w / 2, y: box.y + box.h / 2 + 14, class: "cluster-empty",
                              "text-anchor": "middle"}, "no module runs here"));
    }
    this.layers.clusters.append(group);
    this.clusters.set(node, {group, rect, badge, figures, reach, box});
    group.classList.toggle("lost", info.up === false);
  }

  drawModule(name, info, box) {
    const hidden = this.hiddenBy(name);
    const group = s("g", {class: `module kind-${info.kind || "module"}`, dataset: {module: name},
                          tabindex: 0, role: "button",
                          "aria-label": `module ${name}, ${fmt.shortClass(info.class)}, on node ${info.node}`});
    group.style.transform = `translate(${box.x}px, ${box.y}px)`;
    const rect = s("rect", {class: "module-box", width: box.w, height: box.h, rx: 9});
    const band = s("path", {class: "module-band",
                            d: `M0 ${HEADER} V9 a9 9 0 0 1 9 -9 H${box.w - 9} a9 9 0 0 1 9 9 V${HEADER} Z`});
    const status = s("circle", {class: "status-dot", cx: 12, cy: HEADER / 2, r: 4});
    const title = s("text", {class: "module-title", x: 22, y: HEADER / 2 + 4},
                    clip(fmt.leaf(name), box.w - 30));
    const tip = s("title", {}, `${name}\n${info.class}\nnode ${info.node}` +
                               (info.macro ? `\nin macro ${info.macro}` : ""));
    const cls = s("text", {class: "module-class", x: box.w / 2, y: box.h - 8,
                           "text-anchor": "middle"}, clip(fmt.shortClass(info.class), box.w - 16));
    const figures = s("text", {class: "module-figures", x: box.w / 2, y: box.h - 21,
                               "text-anchor": "middle"}, "");
    group.append(tip, rect, band, status, title, cls, figures);
    const ports = {};
    const side = (names, x, dir) => names.forEach((port, i) => {
      const y = HEADER + (i + 0.5) * (box.h - HEADER - 24) / names.length;
      const spec = (dir === "in" ? info.inputs : info.outputs)[port] || {};
      const dot = s("circle", {class: `port port-${dir}`, cx: x, cy: y, r: PORT_R,
                               dataset: {port: `${name}.${port}`, dir}},
                    s("title", {}, `${name}.${port}: ${spec.type || "?"}` +
                                   (spec.policy ? ` (${spec.policy})` : "")));
      const label = s("text", {class: "port-label", x: dir === "in" ? x + 8 : x - 8, y: y + 3.5,
                               "text-anchor": dir === "in" ? "start" : "end"}, port);
      group.append(label, dot);
      ports[`${dir}:${port}`] = {x, y};
    });
    side(Object.keys(info.inputs || {}), 0, "in");
    side(Object.keys(info.outputs || {}), box.w, "out");
    if (hidden) group.style.display = "none";
    this.layers.modules.append(group);
    const entry = {group, rect, figures, status, ports, at: {x: box.x, y: box.y}, box, info};
    this.boxes.set(name, entry);
    this.bindDrag(group, name, info.node, entry.at);
    this.bindKeys(group, name);
  }

  /** Macros: a dashed frame around each macro's modules on a node, with a toggle that
   * folds them into one box (links then end on its edge). */
  drawMacros() {
    this.frames = new Map();
    const macros = this.system.macros || {};
    for (const macro of Object.keys(macros).sort((a, b) => a.length - b.length)) {
      const groups = new Map();
      for (const child of macros[macro]) {
        const box = this.boxes.get(child);
        if (!box) continue;
        const node = box.info.node;
        if (!groups.has(node)) groups.set(node, []);
        groups.get(node).push(box);
      }
      for (const [node, boxes] of groups) {
        const outer = this.hiddenBy(macros[macro][0]);
        if (outer && outer !== macro) continue;            // inside a larger folded macro
        // the server's frame (a cluster Graphviz made room for), else one around the boxes
        const given = this.layout.macros?.[macro]?.[node];
        const x0 = given ? given.x : Math.min(...boxes.map((b) => b.at.x)) - 10;
        const y0 = given ? given.y : Math.min(...boxes.map((b) => b.at.y)) - 22;
        const x1 = given ? given.x + given.w : Math.max(...boxes.map((b) => b.at.x + b.box.w)) + 10;
        const y1 = given ? given.y + given.h : Math.max(...boxes.map((b) => b.at.y + b.box.h)) + 10;
        const folded = this.collapsed.has(macro);
        const frame = {x: x0, y: y0, w: folded ? Math.min(x1 - x0, 190) : x1 - x0,
                       h: folded ? 64 : y1 - y0};
        const group = s("g", {class: `macro ${folded ? "folded" : ""}`, dataset: {macro}});
        const toggle = s("text", {x: frame.x + 8, y: frame.y + 16, class: "macro-toggle", tabindex: 0,
                                  role: "button", "aria-expanded": String(!folded),
                                  "aria-label": `${folded ? "open" : "close"} macro ${macro}`,
                                  dataset: {toggle: macro}}, folded ? "▸" : "▾");
        const title = s("text", {x: frame.x + 22, y: frame.y + 15, class: "macro-title", tabindex: 0,
                                 role: "button", "aria-label": `macro ${macro} on node ${node}`,
                                 dataset: {title: macro}},
                        `${macro}${folded ? ` · ${boxes.length} modules` : ""}`);
        group.append(s("rect", {x: frame.x, y: frame.y, width: frame.w, height: frame.h, rx: 12}),
                     toggle, title);
        toggle.addEventListener("pointerdown", (ev) => ev.stopPropagation());
        toggle.addEventListener("click", () => this.toggleMacro(macro));
        toggle.addEventListener("keydown", (ev) => {
          if (ev.key === "Enter" || ev.key === " ") { ev.preventDefault(); this.toggleMacro(macro); }
        });
        this.bindKeys(title, macro);
        // a macro moves as one: its title, or the whole box when it is folded
        this.bindDrag(folded ? group : title, macro, node, {x: 0, y: 0}, group);
        this.layers.frames.append(group);
        this.frames.set(`${macro}@${node}`, {...frame, group});
      }
    }
  }

  toggleMacro(macro, open) {
    const folded = open === undefined ? !this.collapsed.has(macro) : !open;
    if (folded === this.collapsed.has(macro)) return;
    if (folded) this.collapsed.add(macro);
    else this.collapsed.delete(macro);
    this.render(this.system, this.layout);
    if (this.lastStats) this.update(this.lastStats);
  }

  isFolded(macro) {
    return this.collapsed.has(macro);
  }

  /** The outermost folded macro that hides this module, or null. */
  hiddenBy(name) {
    let outer = null;
    for (const macro of this.collapsed) {
      if ((this.system.macros?.[macro] || []).includes(name) &&
          (outer === null || macro.length < outer.length)) outer = macro;
    }
    return outer;
  }

  /** Where a link ends on a module: its port, or the edge of the folded macro around it. */
  endpoint(end, dir) {
    const name = moduleOf(end), port = end.slice(name.length + 1);
    const box = this.boxes.get(name);
    if (!box) return null;
    const macro = this.hiddenBy(name);
    if (macro) {
      const frame = this.frames.get(`${macro}@${box.info.node}`);
      if (frame) return {x: dir === "out" ? frame.x + frame.w : frame.x, y: frame.y + frame.h / 2};
    }
    const at = box.ports[`${dir}:${port}`] || {x: dir === "out" ? box.box.w : 0, y: box.box.h / 2};
    return {x: box.at.x + at.x, y: box.at.y + at.y};
  }

  drawLink(link) {
    const a = this.endpoint(link.src, "out"), b = this.endpoint(link.dst, "in");
    if (!a || !b) return;
    const fold = this.hiddenBy(moduleOf(link.src));
    if (fold && fold === this.hiddenBy(moduleOf(link.dst))) return;      // inside one fold
    const folded = this.hiddenBy(moduleOf(link.src)) || this.hiddenBy(moduleOf(link.dst));
    const route = folded ? null
      : b.x < a.x + 20 ? this.backRoute(a, b, moduleOf(link.src), moduleOf(link.dst))
      : routed(this.layout.links?.[link.key]?.points, a, b);
    const d = route ? route.d : curve(a, b);
    const path = s("path", {class: "link", d, "marker-end": "url(#arrow)", dataset: {link: link.key}},
                   s("title", {}, `${link.key} (${link.policy})`));
    const mid = route ? route.mid : bezierMid(a, b);
    mid.y -= 12;                                      // above the path, clear of the ports
    const text = s("text", {class: "link-text", x: mid.x, y: mid.y + 3.5, "text-anchor": "middle"},
                   link.policy);
    const bg = s("rect", {class: "link-label-bg", rx: 6, height: 15, y: mid.y - 8});
    const label = s("g", {class: "link-label", dataset: {link: link.key}}, [bg, text]);
    this.layers.links.append(path);
    this.layers.labels.append(label);
    this.links.set(link.key, {path, label, text, bg, mid});
    this.sizeLabel(this.links.get(link.key));
  }

  /** A link whose input lies left of its output: out to the right, along under both
   * modules, and into the input from the left, instead of through the boxes. */
  backRoute(a, b, src, dst) {
    const bottom = (name) => {
      const box = this.boxes.get(name);
      return box ? box.at.y + box.box.h : Math.max(a.y, b.y);
    };
    const y = Math.max(bottom(src), bottom(dst)) + 18;
    const r = 26;
    const d = `M${a.x},${a.y} C${a.x + r},${a.y} ${a.x + r},${y} ${a.x},${y} ` +
              `L${b.x},${y} C${b.x - r},${y} ${b.x - r},${b.y} ${b.x},${b.y}`;
    return {d, mid: {x: b.x + (a.x - b.x) * 0.7, y: y + 4}};
  }

  sizeLabel(entry) {
    const width = 6.2 * entry.text.textContent.length + 12;   // no layout read: fast
    entry.bg.setAttribute("x", entry.mid.x - width / 2);
    entry.bg.setAttribute("width", width);
  }

  glide(box, from) {
    const group = box.group;
    group.style.transition = "none";
    group.style.transform = `translate(${from.x}px, ${from.y}px)`;
    group.getBoundingClientRect();                  // the start, before the transition
    group.style.transition = "transform 0.7s cubic-bezier(.2,.8,.2,1)";
    group.style.transform = `translate(${box.at.x}px, ${box.at.y}px)`;
    this.flash(box.group.dataset.module);
  }

  /** Draw the eye to a module (moved, swapped, restarted). */
  flash(name) {
    const box = this.boxes.get(name);
    if (!box) return;
    box.group.classList.remove("flash");
    box.group.getBoundingClientRect();
    box.group.classList.add("flash");
    setTimeout(() => box.group.classList.remove("flash"), 2000);
  }

  /** Show `name` (a module or a macro instance) as selected, with `marked` beside it. */
  select(name, marked = []) {
    this.selected = name;
    this.marked = new Set(marked);
    this.markSelected();
  }

  markSelected() {
    for (const [name, box] of this.boxes) {
      box.group.classList.toggle("selected", name === this.selected || this.marked.has(name));
    }
    for (const group of this.layers.frames?.children || []) {
      const macro = group.dataset.macro;
      group.classList.toggle("selected", macro === this.selected || this.marked.has(macro));
    }
  }

  // -- live figures ------------------------------------------------------------------
  update(stats) {
    this.lastStats = stats;
    const dt = this.previous ? Math.max(stats.time - this.previous.time, 1e-3) : null;
    for (const [name, box] of this.boxes) {
      const m = stats.modules?.[name];
      if (!m) continue;
      setClass(box.group, "status", m.status);
      const was = this.previous?.modules?.[name];
      let text = m.status === "failed" ? "failed" : "";
      if (m.status !== "failed" && dt && was) {
        const steps = (m.steps - was.steps) / dt, events = (m.events - was.events) / dt;
        text = events > steps ? `${fmt.rate(events)} calls` : steps > 0 ? `${fmt.rate(steps)} steps`
             : m.status;
      } else if (m.status !== "failed") {
        text = m.status;
      }
      const longCall = fmt.longCall(m);
      if (longCall) text = longCall;         // stuck, or slow: which call, for how long
      if (m.silent) text = "silent";         // its worker did not answer: no figures
      if (m.errors) text += ` · ${m.errors} err`;
      setText(box.figures, text);
      box.group.classList.toggle("silent", !!m.silent);
      box.group.classList.toggle("in-long-call", !!longCall && !m.silent);
      box.group.classList.toggle("has-errors", m.errors > 0);
      box.group.classList.toggle("on-lost-node", stats.nodes?.[m.node]?.up === false);
      const tip = box.group.querySelector("title");
      const error = m.last_error ? `\nlast error: ${m.last_error}` : "";
      const silent = m.silent ? " (silent: its worker did not answer)" : "";
      const calling = longCall ? ` (${longCall})` : "";
      setText(tip, `${name}\n${m.cls}\nnode ${m.node} · ${m.status}${silent}${calling}${error}`);
    }
    for (const [key, entry] of this.links) {
      const l = stats.links?.[key];
      if (!l) continue;
      let text = `${fmt.rate(l.rate)} · ${fmt.seconds(l.latency)}`;
      if (l.drops) text += ` · ${fmt.count(l.drops)} dropped`;
      if (l.link_failures) text += ` · ${l.link_failures} lost`;
      if (setText(entry.text, text)) this.sizeLabel(entry);
      entry.path.classList.toggle("flowing", l.rate > 0);
      entry.path.classList.toggle("dropping", l.drops > (this.previous?.links?.[key]?.drops ?? l.drops));
      entry.label.classList.toggle("dropping", l.drops > 0);
      entry.path.classList.toggle("failing", l.link_failures > 0);
    }
    for (const [node, entry] of this.clusters) {
      const n = stats.nodes?.[node];
      if (!n) continue;
      entry.group.classList.toggle("lost", !n.up);
      setText(entry.badge, n.up ? "up" : "lost");
      const parts = [];
      if (n.cpu !== null && n.cpu !== undefined) parts.push(`CPU ${fmt.percent(n.cpu)}`);
      if (n.memory_total) {
        parts.push(`mem ${fmt.gib(n.memory_total - (n.memory_available ?? 0))}/${fmt.gib(n.memory_total)} GiB`);
      }
      setText(entry.figures, n.up ? parts.join(" · ") : "no figures while it is lost");
      setText(entry.reach, !n.up ? `lost${n.silent_s ? ` · silent ${fmt.seconds(n.silent_s)}` : ""}`
                         : n.address ? `RTT ${fmt.seconds(n.rtt)}` : "in the launcher");
    }
    this.previous = stats;
  }

  // -- gestures ----------------------------------------------------------------------
  toSvg(event) {
    const point = new DOMPoint(event.clientX, event.clientY);
    return point.matrixTransform(this.svg.getScreenCTM().inverse());
  }

  nodeAt(point) {
    for (const [node, entry] of this.clusters) {
      const b = entry.box;
      if (point.x >= b.x && point.x <= b.x + b.w && point.y >= b.y && point.y <= b.y + b.h) return node;
    }
    return null;
  }

  /** Enter or Space selects (with Shift: adds to the selection), as a click does. */
  bindKeys(element, name) {
    element.addEventListener("keydown", (ev) => {
      if (ev.target !== element || (ev.key !== "Enter" && ev.key !== " ")) return;
      ev.preventDefault();
      this.actions.select(name, {add: ev.shiftKey});
    });
  }

  /**
   * Press on `handle` and release: select `name`. Press and drag: `moved` (the handle
   * unless told) follows the pointer from `rest` (its resting translation); released on
   * another node than `node`, `name` is migrated there.
   */
  bindDrag(handle, name, node, rest, moved = null) {
    const element = moved || handle;
    handle.addEventListener("pointerdown", (down) => {
      if (down.button !== 0) return;
      down.stopPropagation();
      const port = down.target.closest(".port");
      if (port && port.dataset.dir === "out") return this.dragLink(down, port.dataset.port);
      const start = this.toSvg(down);
      const add = down.shiftKey || down.ctrlKey || down.metaKey;
      let dragging = false, target = null;
      handle.setPointerCapture(down.pointerId);
      const move = (ev) => {
        const p = this.toSvg(ev);
        if (!dragging && Math.hypot(p.x - start.x, p.y - start.y) < DRAG_THRESHOLD) return;
        dragging = true;
        element.classList.add("dragging");
        element.style.transition = "none";
        element.style.transform = `translate(${rest.x + p.x - start.x}px, ${rest.y + p.y - start.y}px)`;
        target = this.nodeAt(p);
        for (const [each, entry] of this.clusters) {
          entry.group.classList.toggle("drop-target", each === target && each !== node);
        }
      };
      // (on the window: the release reaches it also when a redraw took the handle away
      // between press and release, which lost the click)
      const up = () => {
        window.removeEventListener("pointermove", move);
        window.removeEventListener("pointerup", up);
        window.removeEventListener("pointercancel", up);
        element.classList.remove("dragging");
        for (const entry of this.clusters.values()) entry.group.classList.remove("drop-target");
        if (!dragging) return this.actions.select(name, {add});
        if (target && target !== node) {
          element.classList.add("moving");
          this.actions.migrate(name, target).finally(() => {
            element.classList.remove("moving");
            snapBack(element, rest);
          });
        } else {
          snapBack(element, rest);
        }
      };
      window.addEventListener("pointermove", move);
      window.addEventListener("pointerup", up);
      window.addEventListener("pointercancel", up);
    });
  }

  /** From an output port: a line follows the pointer; released on an input, it links. */
  dragLink(down, src) {
    const a = this.endpoint(src, "out");
    const line = s("path", {class: "link drawing", d: curve(a, a)});
    this.layers.drag.append(line);
    this.svg.classList.add("linking");
    const move = (ev) => line.setAttribute("d", curve(a, this.toSvg(ev)));
    const up = (ev) => {
      window.removeEventListener("pointermove", move);
      window.removeEventListener("pointerup", up);
      this.svg.classList.remove("linking");
      line.remove();
      const hit = document.elementFromPoint(ev.clientX, ev.clientY)?.closest?.(".port-in");
      if (hit) this.actions.connect(src, hit.dataset.port);
    };
    window.addEventListener("pointermove", move);
    window.addEventListener("pointerup", up);
  }

  /** Pan by dragging the background; zoom with the wheel around the pointer. */
  bindViewGestures() {
    this.svg.addEventListener("pointerdown", (down) => {
      if (down.button !== 0 || down.target.closest(".module, .macro-title, .macro.folded")) return;
      const start = {x: down.clientX, y: down.clientY}, view = {...this.view};
      const scale = this.view.w / this.svg.clientWidth;
      const move = (ev) => {
        this.fitted = false;
        this.setView({...view, x: view.x - (ev.clientX - start.x) * scale,
                      y: view.y - (ev.clientY - start.y) * scale});
      };
      const up = () => {
        window.removeEventListener("pointermove", move);
        window.removeEventListener("pointerup", up);
      };
      window.addEventListener("pointermove", move);
      window.addEventListener("pointerup", up);
    });
    this.svg.addEventListener("wheel", (ev) => {
      if (!this.view) return;
      ev.preventDefault();
      const p = this.toSvg(ev);
      const k = Math.exp(ev.deltaY * 0.0015);
      const v = this.view;
      this.fitted = false;
      this.setView({x: p.x - (p.x - v.x) * k, y: p.y - (p.y - v.y) * k, w: v.w * k, h: v.h * k});
    }, {passive: false});
    this.svg.addEventListener("dragover", (ev) => {
      if (PLACEABLE.some((type) => ev.dataTransfer.types.includes(type))) ev.preventDefault();
    });
    this.svg.addEventListener("drop", (ev) => {
      const cls = ev.dataTransfer.getData("application/x-pb3a-class");
      const macro = ev.dataTransfer.getData("application/x-pb3a-macro");
      if (!cls && !macro) return;
      ev.preventDefault();
      const at = this.toSvg(ev);
      if (cls) this.actions.place(cls, this.nodeAt(at), at);
      else this.actions.placeMacro(macro, this.nodeAt(at));
    });
  }

  /** The whole drawing, centred, magnified little (a small system keeps the type size of
   * a large one) and shrunk only so far that a module's name can still be read. */
  fullView() {
    const w = (this.layout?.width || 400) + 2 * PAD, h = (this.layout?.height || 300) + 2 * PAD;
    const cw = this.svg.clientWidth || w, ch = this.svg.clientHeight || h;
    const k = Math.min(Math.max(w / cw, h / ch, 1 / MAX_ZOOM), MAX_SHRINK);
    // what does not fit starts at the top left (the user pans); the rest is centred
    const x = cw * k >= w ? -PAD - (cw * k - w) / 2 : -PAD;
    const y = ch * k >= h ? -PAD - (ch * k - h) / 2 : -PAD;
    return {x, y, w: cw * k, h: ch * k};
  }

  fit() {
    this.fitted = true;
    this.setView(this.fullView());
  }

  setView(view) {
    this.view = view;
    this.svg.setAttribute("viewBox", `${view.x} ${view.y} ${view.w} ${view.h}`);
  }
}

/** A selector that finds the same focusable part of the drawing after a redraw. */
function focusKey(element) {
  for (const key of ["module", "toggle", "title"]) {
    const value = element.dataset?.[key];
    if (value !== undefined) return `[data-${key}="${CSS.escape(value)}"]`;
  }
  return null;
}

function snapBack(element, rest) {
  element.style.transition = "transform 0.25s ease-out";
  element.style.transform = `translate(${rest.x}px, ${rest.y}px)`;
}

function moduleOf(end) {
  return end.slice(0, end.lastIndexOf("."));
}

/** Graphviz's spline for a link (cubic Bézier segments: 1 + 3n points, maybe followed by
 * the arrowhead's tip), its ends moved
 * onto the ports this page draws (with their neighbouring control points, so the
 * tangents stay); null when there is none to follow. */
function routed(points, a, b) {
  if (points && points.length >= 5 && (points.length - 2) % 3 === 0) {
    points = points.slice(0, -1);          // the arrowhead's tip, after the spline's end
  }
  if (!points || points.length < 4 || (points.length - 1) % 3 !== 0) return null;
  const p = points.map(([x, y]) => ({x, y}));
  const far = (q, r) => Math.hypot(q.x - r.x, q.y - r.y);
  if (far(p[0], a) + far(p.at(-1), b) > far(p[0], b) + far(p.at(-1), a)) p.reverse();   // a back edge
  const last = p.length - 1;
  const da = {x: a.x - p[0].x, y: a.y - p[0].y}, db = {x: b.x - p[last].x, y: b.y - p[last].y};
  p[0] = a;
  p[1] = {x: p[1].x + da.x, y: p[1].y + da.y};
  p[last - 1] = {x: p[last - 1].x + db.x, y: p[last - 1].y + db.y};
  p[last] = b;
  let d = `M${p[0].x},${p[0].y}`;
  for (let i = 1; i < p.length; i += 3) {
    d += ` C${p[i].x},${p[i].y} ${p[i + 1].x},${p[i + 1].y} ${p[i + 2].x},${p[i + 2].y}`;
  }
  const k = 3 * Math.floor((p.length - 1) / 6);    // the middle segment starts at p[k]
  const q = [p[k], p[k + 1], p[k + 2], p[k + 3]];
  const mid = {x: (q[0].x + 3 * q[1].x + 3 * q[2].x + q[3].x) / 8,
               y: (q[0].y + 3 * q[1].y + 3 * q[2].y + q[3].y) / 8};
  return {d, mid};
}

function curve(a, b) {
  const dx = Math.max(40, Math.abs(b.x - a.x) / 2);
  return `M${a.x},${a.y} C${a.x + dx},${a.y} ${b.x - dx},${b.y} ${b.x},${b.y}`;
}

function bezierMid(a, b) {
  const dx = Math.max(40, Math.abs(b.x - a.x) / 2);
  // B(0.5) = (P0 + 3 P1 + 3 P2 + P3) / 8
  return {x: (a.x + 3 * (a.x + dx) + 3 * (b.x - dx) + b.x) / 8, y: (a.y + b.y) / 2};
}

function clip(text, width) {
  const fits = Math.max(3, Math.floor(width / 7));
  return text.length > fits ? `${text.slice(0, fits - 1)}…` : text;
}

/** Set a text node's content only when it changed (no layout work otherwise). */
function setText(node, text) {
  if (node.textContent === text) return false;
  node.textContent = text;
  return true;
}

function setClass(node, prefix, value) {
  for (const name of [...node.classList]) {
    if (name.startsWith(`${prefix}-`) && name !== `${prefix}-${value}`) node.classList.remove(name);
  }
  node.classList.add(`${prefix}-${value}`);
}
