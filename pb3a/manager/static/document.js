// The configuration being edited (FILE mode): the TOML as JSON, changed here and put
// back whole with PUT /api/document, which checks it as `pb3a check` does and answers
// the problems (kept, not refused, so a half-built system can be saved).
//
// The document's own names are its top-level entries ([modules.NAME]: a class or a
// macro instance); the schematic draws the modules they expand to, a macro's as
// "instance/child". `entryOf` maps one to the other.

import {api, ApiError, toJson} from "./api.js";
import * as fmt from "./format.js";

const NAME = /^[A-Za-z0-9_-]+$/;       // what `pb3a check` takes as a module or macro name

/** The module part of a link end ("robot.in" -> "robot"). */
export const moduleOf = (end) => String(end).slice(0, String(end).lastIndexOf("."));
const portOf = (end) => String(end).slice(String(end).lastIndexOf(".") + 1);

/** The document entry a drawn module belongs to ("chain/scale" -> "chain"). */
export const entryOf = (path) => path.split("/")[0];

/** The entries of the document that differ between `a` and `b` (two of its systems), by
 * name: "modules.scale", "nodes.a", "macros.stage", "link ticker.out -> scale.x",
 * "name". */
function changedEntries(a, b) {
  const changed = new Set();
  const isTable = (value) => value !== null && typeof value === "object" && !Array.isArray(value);
  for (const key of new Set([...Object.keys(a || {}), ...Object.keys(b || {})])) {
    const [x, y] = [a?.[key], b?.[key]];
    if (isTable(x) && isTable(y) || isTable(x) && y === undefined || x === undefined && isTable(y)) {
      for (const name of new Set([...Object.keys(x || {}), ...Object.keys(y || {})])) {
        if (toJson(x?.[name]) !== toJson(y?.[name])) changed.add(`${key}.${name}`);
      }
    } else if (Array.isArray(x) || Array.isArray(y)) {
      const texts = (list) => new Set((Array.isArray(list) ? list : []).map(toJson));
      const [xs, ys] = [texts(x), texts(y)];
      for (const text of [...xs].filter((t) => !ys.has(t)).concat([...ys].filter((t) => !xs.has(t)))) {
        const item = JSON.parse(text);
        changed.add(item?.from && item?.to ? `link ${item.from} -> ${item.to}` : `${key} ${text}`);
      }
    } else if (toJson(x) !== toJson(y)) {
      changed.add(key);
    }
  }
  return changed;
}

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
    this.base = null;                // the system as last read, before the changes made here
    this.putting = null;             // the put under way, which the next one waits for
    this.unsent = [];                // changes made here that no put has sent yet
    this.edits = 0;                  // changes made here (a refused one is not counted)
  }

  async load() {
    this.take(await api.document());
    return this;
  }

  /** The server's document; the changes made here since the last put was sent are
   * made again on it (they are not in it yet). */
  take(answer) {
    this.path = answer.path ?? this.path;
    this.system = answer.system || {};
    this.base = structuredClone(this.system);
    this.system.modules ??= {};
    this.system.links ??= [];
    this.problems = answer.problems || [];
    this.revision = answer.revision;
    for (const {change} of this.unsent) {
      try {
        change(this.system);
      } catch (error) {
        console.warn("a change made while the document was being saved no longer applies", error);
      }
    }
  }

  /**
   * Change the document by `change(system)` (which throws, before changing anything,
   * for a change it refuses) and put it back; answers what `change` answers once the
   * put that sends it is answered, or that put's error. Puts go one after another,
   * each with the revision the one before it answered, and each sends every change
   * made since the one before. A change made while a put is on its way is made again
   * on that put's answer, which replaces this copy: made on the copy alone, the answer
   * dropped it, and the next put sent the document without it (two quick edits: the
   * second lost, both "saved"). A put that fails fails the changes it sent; the
   * document is read again and the changes not yet sent are made on it. A 412 (another
   * page changed the document since it was read here) is no failure when the entries
   * the changes touch are not among those the other page changed: they are made again
   * on the document as it is now and put once more. When one is, they fail (and the
   * changes not yet sent with them) with a 412 naming it.
   */
  edit(change) {
    const result = change(this.system);
    this.edits += 1;
    const sent = new Promise((resolve, reject) => {
      this.unsent.push({change, resolve: () => resolve(result), reject});
    });
    this.putting = (this.putting || Promise.resolve()).then(() => this.#send());
    return sent;
  }

  /** The put of every change not sent yet (it settles them; it never rejects). */
  async #send(again = false) {
    const sending = this.unsent;
    if (!sending.length) return;             // a put before this one sent them
    this.unsent = [];
    try {
      this.take(await api.putDocument(this.system, this.revision));
      for (const one of sending) one.resolve();
    } catch (error) {
      if (error.status === 412 && !again) {
        const retry = await this.#onStale(sending, error);
        if (retry) return this.#send(true);
        return;
      }
      const failed = error.status === 412 ? [...sending, ...this.unsent.splice(0)] : sending;
      try {
        await this.load();                   // (what the server holds, the rest made again)
      } catch (reading) {
        console.warn("the document could not be read again", reading);
      }
      for (const one of failed) one.reject(error);
    }
  }

  /** After a 412: read the document; if no entry these changes touch was changed by
   * the other page, make them again on it and answer true (put them once more); else
   * fail them, and those made since, with a 412 naming the entries, and answer false. */
  async #onStale(sending, error) {
    let fresh;
    try {
      fresh = await api.document();
    } catch (reading) {
      console.warn("the document could not be read again", reading);
      for (const one of [...sending, ...this.unsent.splice(0)]) one.reject(error);
      return false;
    }
    const theirs = changedEntries(this.base, fresh.system || {});
    const both = [...changedEntries(this.base, this.system)].filter((entry) => theirs.has(entry));
    if (!both.length) {
      this.unsent = [...sending, ...this.unsent];
      this.take(fresh);                       // (the changes made again on it)
      return true;
    }
    const failed = [...sending, ...this.unsent.splice(0)];
    this.take(fresh);
    const refusal = new ApiError(412, `${both.join(", ")} changed in another page since this one `
      + "read the document: this edit was not made; the page shows the document as it is now");
    for (const one of failed) one.reject(refusal);
    return false;
  }

  nodes() {
    return Object.keys(this.system.nodes || {});
  }

  macros() {
    return this.system.macros || {};
  }

  /** A name no entry of `system` has yet: `base`, else `base2`, `base3`, ... */
  freeName(base, system = this.system) {
    let name = base || "module";
    for (let i = 2; name in system.modules; i += 1) name = `${base}${i}`;
    return name;
  }

  /** A name for a new module of this class ("examples.pipeline:FastScale" -> fast_scale). */
  nameFor(cls, system = this.system) {
    return this.freeName(fmt.shortClass(cls).replace(/([a-z0-9])([A-Z])/g, "$1_$2").toLowerCase(),
                         system);
  }

  place(cls, node) {
    return this.edit((system) => {
      const name = this.nameFor(cls, system);
      system.modules[name] = node ? {class: cls, node} : {class: cls};
      return name;
    });
  }

  /** A new instance of one of the document's macros. */
  placeMacro(macro, node) {
    return this.edit((system) => {
      if (!(macro in (system.macros || {}))) throw new Error(`the document defines no macro ${macro}`);
      const name = this.freeName(macro, system);
      system.modules[name] = node ? {macro, node} : {macro};
      return name;
    });
  }

  async link(src, dst) {
    const check = await api.checkLink(src, dst);
    if (!check.ok) return check;
    await this.edit((system) => system.links.push({from: src, to: dst}));
    return check;
  }

  setNode(name, node) {
    return this.edit((system) => { entryIn(system, name).node = node; });
  }

  setState(name, fields) {
    return this.edit((system) => {
      const module = entryIn(system, name);
      module.state = {...(module.state || {}), ...fields};
    });
  }

  setPeriod(name, period) {
    return this.edit((system) => {
      const module = entryIn(system, name);
      if (period === null) delete module.period;
      else module.period = period;
    });
  }

  /** Give entry `name` a fixed rate (true), the period slept after each step (false),
   * or its class's own (null: the key left out). */
  setFixedRate(name, fixed) {
    return this.edit((system) => {
      const module = entryIn(system, name);
      if (fixed === null) delete module.fixed_rate;
      else module.fixed_rate = fixed;
    });
  }

  remove(name) {
    return this.edit((system) => {
      entryIn(system, name);
      delete system.modules[name];
      system.links = system.links.filter((l) => ![l.from, l.to].some((end) => moduleOf(end) === name));
    });
  }

  /** Give an entry a new name; the links that name it follow. */
  async rename(name, to) {
    this.module(name);
    to = to.trim();
    if (to === name) return name;
    checkName(to, "a module name");
    return this.edit((system) => {
      entryIn(system, name);
      if (to in system.modules) throw new Error(`there is a module ${to} already: choose another name`);
      system.modules = Object.fromEntries(Object.entries(system.modules)
        .map(([key, entry]) => [key === name ? to : key, entry]));
      const follow = (end) => (moduleOf(end) === name ? `${to}.${portOf(end)}` : end);
      system.links = system.links.map((l) => ({...l, from: follow(l.from), to: follow(l.to)}));
      return to;
    });
  }

  /**
   * Make the entries `names` one macro: a [macros.MACRO] table holding them, the links
   * between them, an export for each of their ports linked from outside; and an
   * instance of it in their place (on their node, if they share one), the outside
   * links now ending on its exports. Answers the instance's name.
   */
  group(names, macro) {
    checkName(macro, "a macro name");
    return this.edit((system) => {
      if (macro in (system.macros || {})) throw new Error(`there is a macro ${macro} already: choose another name`);
      const members = [...new Set(names)].filter((name) => name in system.modules);
      if (!members.length) throw new Error("select the modules to group first");
      const inside = new Set(members);
      const nodes = new Set(members.map((name) => system.modules[name].node ?? ""));
      const node = nodes.size === 1 ? [...nodes][0] : "";
      const children = {};
      for (const name of members) {
        const {...entry} = system.modules[name];
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
      const instance = this.freeName(macro, system);
      const inner = [], outer = [];
      for (const link of system.links) {
        const from = inside.has(moduleOf(link.from)), to = inside.has(moduleOf(link.to));
        if (from && to) inner.push(link);
        else if (from) outer.push({...link, from: `${instance}.${exportOf(link.from)}`});
        else if (to) outer.push({...link, to: `${instance}.${exportOf(link.to)}`});
        else outer.push(link);
      }
      const definition = {modules: children};
      if (inner.length) definition.links = inner;
      if (Object.keys(exports).length) definition.exports = exports;
      system.macros = {...(system.macros || {}), [macro]: definition};
      for (const name of members) delete system.modules[name];
      system.modules[instance] = node ? {macro, node} : {macro};
      system.links = outer;
      return instance;
    });
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
  setOverride(path, fields) {
    const instance = entryOf(path), key = path.slice(instance.length + 1);
    return this.edit((system) => {
      const entry = entryIn(system, instance);
      if (!entry.macro || !key) throw new Error(`${path} is not a module inside a macro instance`);
      entry.state = {...(entry.state || {}), [key]: {...(entry.state?.[key] || {}), ...fields}};
    });
  }

  /** Drop an instance's override of one field (or of all of a module's, without `field`). */
  clearOverride(instance, key, field) {
    return this.edit((system) => {
      const entry = entryIn(system, instance);
      const own = {...(entry.state?.[key] || {})};
      if (field === undefined) for (const name of Object.keys(own)) delete own[name];
      else delete own[field];
      const state = {...(entry.state || {})};
      if (Object.keys(own).length) state[key] = own;
      else delete state[key];
      if (Object.keys(state).length) entry.state = state;
      else delete entry.state;
    });
  }

  addNode(name) {
    return this.edit((system) => { system.nodes = {...(system.nodes || {}), [name]: {}}; });
  }

  module(name) {
    return entryIn(this.system, name);
  }
}

/** The entry `name` of `system`; an error saying what to change for a drawn module
 * that is part of a macro instance. */
function entryIn(system, name) {
  const module = system.modules[name];
  if (!module) {
    throw new Error(`${name} is part of a macro: change its macro instance ${entryOf(name)}, ` +
                    "or the macro's entry in the file");
  }
  return module;
}
