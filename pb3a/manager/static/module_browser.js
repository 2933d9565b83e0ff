// The module browser: the classes on the import path and on the module servers
// (/api/classes), with their ports, types and public state, and the macros the edited
// document defines; drag one onto a node, or press its "+".

import {h} from "./dom.js";
import * as fmt from "./format.js";

export class ModuleBrowser {
  /** actions: {place(cls), placeMacro(macro)} for a click on a "+" (placed on a node of
   * the page's choosing). */
  constructor(root, filter, actions) {
    this.root = root;
    this.filter = filter;
    this.actions = actions;
    this.classes = [];
    this.macros = {};            // the document's [macros.NAME] tables, while editing
    filter.addEventListener("input", () => this.draw());
  }

  set(catalog) {
    this.classes = catalog.classes || [];
    this.problems = catalog.problems || [];
    this.draw();
  }

  /** The document's macros (FILE mode), listed above the classes. */
  setMacros(macros) {
    this.macros = macros || {};
    this.draw();
  }

  byName(cls) {
    return this.classes.find((c) => c.class === cls);
  }

  draw() {
    const words = this.filter.value.toLowerCase().split(/\s+/).filter(Boolean);
    const groups = new Map();
    for (const info of this.classes) {
      const text = `${info.class} ${info.doc || ""}`.toLowerCase();
      if (!words.every((w) => text.includes(w))) continue;
      const pkg = info.class.split(":")[0];
      if (!groups.has(pkg)) groups.set(pkg, []);
      groups.get(pkg).push(info);
    }
    const out = [];
    const macros = Object.entries(this.macros).filter(([name]) =>
      words.every((w) => `macro ${name}`.toLowerCase().includes(w)));
    if (macros.length) {
      out.push(h("h3", {}, "Macros in this document"));
      for (const [name, definition] of macros) out.push(this.macroEntry(name, definition));
    }
    for (const [pkg, infos] of [...groups].sort()) {
      out.push(h("h3", {class: "mono"}, pkg));
      for (const info of infos) out.push(this.entry(info));
    }
    if (!out.length || (!groups.size && this.classes.length)) out.push(h("p", {class: "muted"}, this.classes.length ? "No class matches." : "No classes found."));
    for (const problem of this.problems || []) out.push(h("p", {class: "problem"}, problem));
    this.root.replaceChildren(...out);
  }

  macroEntry(name, definition) {
    const children = Object.keys(definition?.modules || {});
    const exports = Object.entries(definition?.exports || {});
    const add = h("button", {class: "icon ghost", type: "button", title: `place an instance of ${name}`,
                             "aria-label": `place macro ${name}`}, "+");
    add.addEventListener("click", () => this.actions.placeMacro(name));
    const card = h("div", {class: "class-card macro-card", draggable: "true", dataset: {macro: name}}, [
      h("div", {class: "class-head"}, [h("strong", {}, name), h("span", {class: "kind"}, "macro"), add]),
      h("p", {class: "doc"}, `${children.length} module${children.length === 1 ? "" : "s"}: ${children.join(", ")}`),
      h("div", {class: "chips"}, exports.map(([key, end]) => h("span", {class: "chip", title: end}, `${key} → ${end}`))),
    ]);
    card.addEventListener("dragstart", (ev) => {
      ev.dataTransfer.setData("application/x-pb3a-macro", name);
      ev.dataTransfer.effectAllowed = "copy";
    });
    return card;
  }

  entry(info) {
    const ports = (dir, ports) => Object.entries(ports || {}).map(([name, p]) =>
      h("span", {class: `chip ${dir}`, title: p.policy ? `policy ${p.policy}` : ""}, `${name}: ${p.type}`));
    const state = Object.entries(info.state || {}).map(([name, st]) =>
      h("span", {class: "chip state"}, `${name} = ${typeof st.default === "string" ? st.default : JSON.stringify(st.default)}`));
    const add = h("button", {class: "icon ghost", type: "button", title: "place it",
                             "aria-label": `place ${fmt.shortClass(info.class)}`}, "+");
    add.addEventListener("click", () => this.actions.place(info.class));
    const card = h("div", {class: `class-card kind-${info.kind}`, draggable: "true", dataset: {class: info.class}}, [
      h("div", {class: "class-head"}, [
        h("strong", {}, fmt.shortClass(info.class)),
        info.kind !== "module" ? h("span", {class: "kind"}, info.kind) : null,
        info.origin && info.origin !== "path" ? h("span", {class: "kind", title: info.origin}, "served") : null,
        add,
      ]),
      info.doc ? h("p", {class: "doc"}, info.doc) : null,
      h("div", {class: "chips"}, [...ports("in", info.inputs), ...ports("out", info.outputs), ...state]),
    ]);
    card.addEventListener("dragstart", (ev) => {
      ev.dataTransfer.setData("application/x-pb3a-class", info.class);
      ev.dataTransfer.effectAllowed = "copy";
    });
    return card;
  }
}
