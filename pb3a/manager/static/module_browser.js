// The module browser: the classes on the import path and on the module servers
// (/api/classes), with their ports, types and public state; drag one onto a node.

import {h} from "./dom.js";
import * as fmt from "./format.js";

export class ModuleBrowser {
  /** actions: {place(cls)} for a click on a class's "+" (placed on a node of its own choosing). */
  constructor(root, filter, actions) {
    this.root = root;
    this.filter = filter;
    this.actions = actions;
    this.classes = [];
    filter.addEventListener("input", () => this.draw());
  }

  set(catalog) {
    this.classes = catalog.classes || [];
    this.problems = catalog.problems || [];
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
    for (const [pkg, infos] of [...groups].sort()) {
      out.push(h("h3", {class: "mono"}, pkg));
      for (const info of infos) out.push(this.entry(info));
    }
    if (!out.length) out.push(h("p", {class: "muted"}, this.classes.length ? "No class matches." : "No classes found."));
    for (const problem of this.problems || []) out.push(h("p", {class: "problem"}, problem));
    this.root.replaceChildren(...out);
  }

  entry(info) {
    const ports = (dir, ports) => Object.entries(ports || {}).map(([name, p]) =>
      h("span", {class: `chip ${dir}`, title: p.policy ? `policy ${p.policy}` : ""}, `${name}: ${p.type}`));
    const state = Object.entries(info.state || {}).map(([name, st]) =>
      h("span", {class: "chip state"}, `${name} = ${typeof st.default === "string" ? st.default : JSON.stringify(st.default)}`));
    const add = h("button", {class: "icon ghost", type: "button", title: "place it"}, "+");
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
