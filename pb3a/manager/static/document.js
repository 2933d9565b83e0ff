// The configuration being edited (FILE mode): the TOML as JSON, changed here and put
// back whole with PUT /api/document, which checks it as `pb3a check` does and answers
// the problems (kept, not refused, so a half-built system can be saved).
//
// The document's own names are its top-level entries ([modules.NAME]: a class or a
// macro instance); the schematic draws the modules they expand to, a macro's as
// "instance/child". `entryOf` maps one to the other.

import {api} from "./api.js";
import * as fmt from "./format.js";

const NAME = /^[A-Za-z0-9_-]+$/;       // what `pb3a check` takes as a module or macro name

/** The module part of a link end ("robot.in" -> "robot"). */
export const moduleOf = (end) => String(end).slice(0, String(end).lastIndexOf("."));
const portOf = (end) => String(end).slice(String(end).lastIndexOf(".") + 1);

/** The document entry a drawn module belongs to ("chain/scale" -> "chain"). */
export const entryOf = (path) => path.split("/")[0];

function checkName(name, what) {
  if (!NAME.test(name || "")) {
    throw new Error(`${what} ${JSON.stringify(name ?? "")}: use letters, digits, '_' and '-' only`);
  }
}

export class EditedDocument {
  constructor() {
    this.path = null;
    this.system = {name: "untitled", modules: {}, links: []};
    this.problems = [];
    this.revision = undefined;       // the document's, as last read (sent back with a put)
    this.putting = null;             // the put under way, which the next one waits for
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
    this.revision = answer.revision;
  }

  /** Put the document back; if another page changed it meanwhile (412), the change
   * made here is dropped and the document read again, and the error says so. Puts go
   * one after another, each with the revision the one before it answered. */
  put() {
    const putting = (this.putting || Promise.resolve()).catch(() => {}).then(async () => {
      try {
        this.take(await api.putDocument(this.system, this.revision));
      } catch (error) {
        if (error.status === 412) await this.load();
        throw error;
      }
    });
    this.putting = putting;
    return putting;
  }

  nodes() {
    return Object.keys(this.system.nodes || {});
  }

  macros() {
    return this.system.macros || {};
  }

  /** A name no entry has yet: `base`, else `base2`, `base3`, ... */
  freeName(base) {
    let name = base || "module";
    for (let i = 2; name in this.system.modules; i += 1) name = `${base}${i}`;
    return name;
  }

  /** A name for a new module of this class ("examples.pipeline:FastScale" -> fast_scale). */
  nameFor(cls) {
    return this.freeName(fmt.shortClass(cls).replace(/([a-z0-9])([A-Z])/g, "$1_$2").toLowerCase());
  }

  async place(cls, node) {
    const name = this.nameFor(cls);
    this.system.modules[name] = node ? {class: cls, node} : {class: cls};
    await this.put();
    return name;
  }

  /** A new instance of one of the document's macros. */
  async placeMacro(macro, node) {
    if (!(macro in this.macros())) throw new Error(`the document defines no macro ${macro}`);
    const name = this.freeName(macro);
    this.system.modules[name] = node ? {macro, node} : {macro};
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
    this.module(name);
    delete this.system.modules[name];
    this.system.links = this.system.links.filter((l) => ![l.from, l.to].some((end) => moduleOf(end) === name));
    await this.put();
  }

  /** Give an entry a new name; the links that name it follow. */
  async rename(name, to) {
    this.module(name);
    to = to.trim();
    if (to === name) return name;
    checkName(to, "a module name");
    if (to in this.system.modules) throw new Error(`there is a module ${to} already: choose another name`);
    this.system.modules = Object.fromEntries(Object.entries(this.system.modules)
      .map(([key, entry]) => [key === name ? to : key, entry]));
    const follow = (end) => (moduleOf(end) === name ? `${to}.${portOf(end)}` : end);
    this.system.links = this.system.links.map((l) => ({...l, from: follow(l.from), to: follow(l.to)}));
    await this.put();
    return to;
  }

  /**
   * Make the entries `names` one macro: a [macros.MACRO] table holding them, the links
   * between them, an export for each of their ports linked from outside; and an
   * instance of it in their place (on their node, if they share one), the outside
   * links now ending on its exports. Answers the instance's name.
   */
  async group(names, macro) {
    checkName(macro, "a macro name");
    if (macro in this.macros()) throw new Error(`there is a macro ${macro} already: choose another name`);
    const members = [...new Set(names)].filter((name) => name in this.system.modules);
    if (!members.length) throw new Error("select the modules to group first");
    const inside = new Set(members);
    const nodes = new Set(members.map((name) => this.system.modules[name].node ?? ""));
    const node = nodes.size === 1 ? [...nodes][0] : "";
    const children = {};
    for (const name of members) {
      const {...entry} = this.system.modules[name];
      if (node) delete entry.node;            // the instance's node is theirs
      children[name] = entry;
    }
    const exports = {};
    const exportOf = (end) => {
      const known = Object.keys(exports).find((key) => exports[key] === end);
      if (known) return known;
      let key = portOf(end);
      for (let i = 1; key in exports; i += 1) key = `${moduleOf(end)}_${portOf(end)}${i > 1 ? i : ""}`;
      exports[key] = end;
      return key;
    };
    const instance = this.freeName(macro);
    const inner = [], outer = [];
    for (const link of this.system.links) {
      const from = inside.has(moduleOf(link.from)), to = inside.has(moduleOf(link.to));
      if (from && to) inner.push(link);
      else if (from) outer.push({...link, from: `${instance}.${exportOf(link.from)}`});
      else if (to) outer.push({...link, to: `${instance}.${exportOf(link.to)}`});
      else outer.push(link);
    }
    const definition = {modules: children};
    if (inner.length) definition.links = inner;
    if (Object.keys(exports).length) definition.exports = exports;
    this.system.macros = {...this.macros(), [macro]: definition};
    for (const name of members) delete this.system.modules[name];
    this.system.modules[instance] = node ? {macro, node} : {macro};
    this.system.links = outer;
    await this.put();
    return instance;
  }

  /**
   * The state the document gives a module inside a macro instance ("chain/scale"):
   * the macro's own, then what the instances around it set (the outer one wins); null
   * when `path` names no such module.
   */
  macroChildState(path) {
    const parts = path.split("/");
    let entry = this.system.modules[parts[0]];
    const layers = [];                        // [an instance's state table, the key under it]
    let i = 1;
    for (; entry?.macro && i < parts.length; i += 1) {
      layers.push([entry.state || {}, parts.slice(i).join("/")]);
      entry = this.macros()[entry.macro]?.modules?.[parts[i]];
    }
    if (!entry || entry.macro || i !== parts.length || parts.length < 2) return null;
    const state = {...(entry.state || {})};
    for (const [own, key] of layers.reverse()) Object.assign(state, own[key] || {});
    return state;
  }

  /** Set state on a module inside a macro instance, as the instance's override
   * (`state = { "child" = { field = value } }`), leaving the macro as it is. */
  async setOverride(path, fields) {
    const instance = entryOf(path), key = path.slice(instance.length + 1);
    const entry = this.module(instance);
    if (!entry.macro || !key) throw new Error(`${path} is not a module inside a macro instance`);
    entry.state = {...(entry.state || {}), [key]: {...(entry.state?.[key] || {}), ...fields}};
    await this.put();
  }

  /** Drop an instance's override of one field (or of all of a module's, without `field`). */
  async clearOverride(instance, key, field) {
    const entry = this.module(instance);
    const own = {...(entry.state?.[key] || {})};
    if (field === undefined) for (const name of Object.keys(own)) delete own[name];
    else delete own[field];
    const state = {...(entry.state || {})};
    if (Object.keys(own).length) state[key] = own;
    else delete state[key];
    if (Object.keys(state).length) entry.state = state;
    else delete entry.state;
    await this.put();
  }

  async addNode(name) {
    this.system.nodes = {...(this.system.nodes || {}), [name]: {}};
    await this.put();
  }

  module(name) {
    const module = this.system.modules[name];
    if (!module) {
      throw new Error(`${name} is part of a macro: change its macro instance ${entryOf(name)}, ` +
                      "or the macro's entry in the file");
    }
    return module;
  }
}
