// The configuration being edited (FILE mode): the TOML as JSON, changed here and put
// back whole with PUT /api/document, which checks it as `pb3a check` does and answers
// the problems (kept, not refused, so a half-built system can be saved).

import {api} from "./api.js";
import * as fmt from "./format.js";

export class EditedDocument {
  constructor() {
    this.path = null;
    this.system = {name: "untitled", modules: {}, links: []};
    this.problems = [];
  }

  async load() {
    this.take(await api.document());
    return this;
  }

  take(answer) {
    this.path = answer.path ?? this.path;
    this.system = answer.system || {};
    this.system.modules ??= {};
    this.system.links ??= [];
    this.problems = answer.problems || [];
  }

  async put() {
    this.take(await api.putDocument(this.system));
  }

  nodes() {
    return Object.keys(this.system.nodes || {});
  }

  /** A name for a new module of this class that no module has yet. */
  freeName(cls) {
    const base = fmt.shortClass(cls).replace(/([a-z0-9])([A-Z])/g, "$1_$2").toLowerCase() || "module";
    let name = base;
    for (let i = 2; name in this.system.modules; i += 1) name = `${base}${i}`;
    return name;
  }

  async place(cls, node) {
    const name = this.freeName(cls);
    this.system.modules[name] = node ? {class: cls, node} : {class: cls};
    await this.put();
    return name;
  }

  async link(src, dst) {
    const check = await api.checkLink(src, dst);
    if (!check.ok) return check;
    this.system.links.push({from: src, to: dst});
    await this.put();
    return check;
  }

  async setNode(name, node) {
    this.module(name).node = node;
    await this.put();
  }

  async setState(name, fields) {
    const module = this.module(name);
    module.state = {...(module.state || {}), ...fields};
    await this.put();
  }

  async setPeriod(name, period) {
    const module = this.module(name);
    if (period === null) delete module.period;
    else module.period = period;
    await this.put();
  }

  async remove(name) {
    delete this.system.modules[name];
    this.system.links = this.system.links.filter((l) =>
      ![l.from, l.to].some((end) => end.slice(0, end.lastIndexOf(".")) === name));
    await this.put();
  }

  async addNode(name) {
    this.system.nodes = {...(this.system.nodes || {}), [name]: {}};
    await this.put();
  }

  module(name) {
    const module = this.system.modules[name];
    if (!module) {
      throw new Error(`${name} is part of a macro: open the macro's entry in the file to change it`);
    }
    return module;
  }
}
