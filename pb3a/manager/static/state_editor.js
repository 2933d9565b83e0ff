// The State Editor: a module's state by reflection (the server's views of each field),
// refreshed while the module runs; numbers, strings and booleans in typed fields, lists
// and dicts that open level by level (and take a whole new value as JSON), numpy arrays
// with shape, dtype and summary (small ones editable, 2-D ones as an image), and the
// custom displays the module declares.

import {fromEditableJson, toEditableJson} from "./api.js";
import {h} from "./dom.js";
import * as fmt from "./format.js";
import {LiveImage, makeDisplay} from "./displays.js";

const CONTAINERS = new Set(["list", "tuple", "dict"]);
const SCALARS = new Set(["int", "float", "str", "bool", "none"]);

export class StateEditor {
  /**
   * root: the element the fields go in.
   * actions: {apply(fields) -> Promise<state view>, drill(path) -> Promise<state view>,
   *           current() -> Promise<state view>, error(err)}
   */
  constructor(root, actions) {
    this.root = root;
    this.actions = actions;
    this.rows = new Map();       // field -> {signature, element, refresh(view), display}
    this.open = new Set();       // paths of the containers the user opened
    this.displays = {};
    this.awaited = null;         // what pending() handed out, until a view is drawn
    this.subject = null;         // whose state the fields are (see shows()), or null
  }

  /** Show these fields (a state view), with the module's declared displays; `subject`
   * says whose state they are (see `shows`). */
  show(view, displays, subject = null) {
    this.displays = displays || {};
    this.subject = subject;
    this.rows.clear();
    this.open.clear();
    this.root.replaceChildren();
    this.update(view);
  }

  /** No fields yet, a line in their place saying why (being read, or a problem): the
   * next update draws them all anew, rows of an earlier view are not kept out of sight.
   * Returns a token that `awaits(token)` tells apart until a view is drawn; `subject`
   * says whose state the view to come is (see `shows`). */
  pending(message, displays, problem = false, subject = null) {
    this.displays = displays || {};
    this.subject = subject;
    this.rows.clear();
    this.open.clear();
    this.root.replaceChildren(h("p", {class: problem ? "problem state-problem" : "muted"}, message));
    this.awaited = {};
    return this.awaited;
  }

  /** Whether no view was drawn since pending() gave this token: a read answered after
   * the live feed drew the fields (and the user began to edit them) must not draw them
   * anew, which dropped what was typed and a field's "applied" mark. */
  awaits(token) {
    return token !== null && this.awaited === token;
  }

  /** Whether the fields of `subject`'s state are drawn (by a read or the live feed),
   * with or without a problem line above them (a refresh that failed meanwhile, as one
   * does while the module restarts): read again, the state is drawn into them; put back
   * to "Reading its state…" they flickered (after a Restart the live feed drew them
   * first). */
  shows(subject) {
    return subject !== null && this.subject === subject && this.awaited === null
      && !!this.root.querySelector(":scope > [data-field]");
  }

  /** No fields and no line: nothing of one module's state is shown (several selected). */
  clear() {
    this.subject = null;
    this.awaited = null;
    this.rows.clear();
    this.open.clear();
    this.root.replaceChildren();
  }

  /** Refresh in place: what the user is typing is kept; a field whose kind changed is
   * drawn anew. */
  update(view) {
    this.awaited = null;
    const fields = view.fields || {};
    if (!Object.keys(fields).length) {
      this.root.replaceChildren(h("p", {class: "muted"}, "This module has no state."));
      this.rows.clear();
      return;
    }
    this.root.querySelector(":scope > p.muted")?.remove();
    for (const [name, field] of Object.entries(fields)) {
      const signature = signatureOf(field);
      let row = this.rows.get(name);
      if (!row || row.signature !== signature) {
        const fresh = this.makeRow(name, field, signature);
        if (row) row.element.replaceWith(fresh.element);
        else this.root.append(fresh.element);
        this.rows.set(name, fresh);
        row = fresh;
      }
      row.refresh(field);
      row.display?.push(field);
    }
    for (const [name, row] of this.rows) {
      if (!(name in fields)) { row.element.remove(); this.rows.delete(name); }
    }
  }

  /** Say above the fields why the last refresh failed (null: it did not). */
  problem(message) {
    let line = this.root.querySelector(":scope > .state-problem");
    if (!message) return line?.remove();
    line ??= this.root.insertAdjacentElement("afterbegin", h("p", {class: "problem state-problem"}));
    line.textContent = message;
  }

  makeRow(name, field, signature) {
    const message = h("div", {class: "field-message"});
    const element = h("div", {class: `field type-${field.type}`, dataset: {field: name}});
    const commit = (value) => this.commit(name, value, element, message);
    const refuse = (words) => { message.textContent = words; element.classList.add("refused"); };
    let editor;
    if (SCALARS.has(field.type)) editor = scalarEditor(name, field, commit, refuse);
    else if (field.type === "ndarray") editor = arrayEditor(field, commit, this.displays[name]);
    else if (CONTAINERS.has(field.type)) editor = this.containerEditor(name, field, commit);
    else editor = objectViewer(field);
    element.append(...[
      h("div", {class: "field-head"}, [
        h("label", {class: "field-name", title: name}, name),
        h("span", {class: "field-type"}, typeLabel(field)),
        editor.inline,
      ]),
      editor.below,
      message,
    ].filter(Boolean));
    const display = field.type === "ndarray" && this.displays[name]?.kind === "image"
      ? null : makeDisplay(this.displays[name]);
    if (display) element.append(display.element);
    return {signature, element, refresh: editor.refresh, display};
  }

  async commit(name, value, element, message) {
    element.classList.add("applying");
    message.textContent = "";
    element.classList.remove("refused");
    try {
      const view = await this.actions.apply({[name]: value});
      element.classList.remove("applying");
      element.classList.add("applied");
      setTimeout(() => element.classList.remove("applied"), 1200);
      this.update(view);
      // set, but the module did not answer a read of its state in time (a long step)
      if (view?.read_back === false) message.textContent = `set; not read back yet: ${view.read_back_error}`;
      return true;
    } catch (error) {
      element.classList.remove("applying");
      element.classList.add("refused");
      message.textContent = error.message;
      this.actions.error(error, false);
      // refused: the field shows what the module or document holds again (the editor
      // puts it back when it is told false), not the value that was not taken
      try {
        this.update(await this.actions.current());
      } catch (reading) {
        console.warn("the state could not be read again", reading);
      }
      return false;
    }
  }

  /** A list, tuple or dict: opens level by level; an editable one takes a new value as
   * JSON in a text box. */
  containerEditor(name, field, commit) {
    const tree = h("div", {class: "tree"});
    let editing = false;
    const edit = h("button", {class: "small ghost", type: "button"}, "Edit as JSON");
    const box = h("div", {class: "json-edit", hidden: true});
    let latest = field;
    edit.addEventListener("click", () => {
      const value = plainValue(latest);
      if (value === undefined) return;
      editing = true;
      const area = h("textarea", {rows: 6, spellcheck: "false"}, toEditableJson(value, 1));
      const apply = h("button", {class: "small primary", type: "button"}, "Apply");
      const cancel = h("button", {class: "small ghost", type: "button"}, "Cancel");
      const close = () => { editing = false; box.hidden = true; box.replaceChildren(); };
      cancel.addEventListener("click", close);
      apply.addEventListener("click", async () => {
        let parsed;
        try {
          parsed = fromEditableJson(area.value);
        } catch (error) {
          this.actions.error(new Error(`${name}: not valid JSON (${error.message})`), true);
          return;
        }
        if (await commit(parsed)) close();
      });
      box.replaceChildren(area, h("div", {class: "row-actions"}, [cancel, apply]));
      box.hidden = false;
      area.focus();
    });
    const refresh = (view) => {
      latest = view;
      edit.hidden = !view.editable || plainValue(view) === undefined;
      if (!editing) tree.replaceChildren(this.items(name, view));
    };
    return {inline: edit, below: h("div", {}, [tree, box]), refresh};
  }

  /** The items of a container at `path`, with the ones the user opened opened. */
  items(path, view) {
    if (view.truncated || !view.items) {
      const more = h("button", {class: "small ghost", type: "button"}, "Load this level");
      more.addEventListener("click", async () => {
        try {
          // the server answers a container's items as the fields below the path
          const deeper = await this.actions.drill(path);
          more.replaceWith(this.items(path, {type: view.type, length: view.length,
                                             items: deeper.fields || {}, more: deeper.more}));
        } catch (error) {
          this.actions.error(error, true);
        }
      });
      return h("div", {class: "tree-level"}, more);
    }
    const list = h("ul", {class: "tree-level"});
    for (const [key, item] of Object.entries(view.items)) {
      const itemPath = `${path}.${key}`;
      if (CONTAINERS.has(item.type)) {
        const details = h("details", {open: this.open.has(itemPath)}, [
          h("summary", {}, [h("span", {class: "tree-key"}, key), " ",
                            h("span", {class: "field-type"}, typeLabel(item))]),
        ]);
        details.addEventListener("toggle", () => {
          if (details.open) {
            this.open.add(itemPath);
            if (details.children.length === 1) details.append(this.items(itemPath, item));
          } else {
            this.open.delete(itemPath);
          }
        });
        if (details.open) details.append(this.items(itemPath, item));
        list.append(h("li", {}, details));
      } else {
        list.append(h("li", {}, [h("span", {class: "tree-key"}, key), " ",
                                 h("span", {class: `tree-value type-${item.type}`}, leafText(item))]));
      }
    }
    if (view.more) list.append(h("li", {class: "muted"}, `… ${view.more} more`));
    return list;
  }

  /** Fields an edited document gives a module (FILE mode): its class's state with the
   * values the document sets, as views the editor shows like live ones. */
  static documentView(classInfo, initial) {
    const fields = {};
    for (const [name, spec] of Object.entries(classInfo?.state || {})) {
      const value = name in (initial || {}) ? initial[name] : spec.default;
      fields[name] = viewOf(value, spec.type);
    }
    for (const [name, value] of Object.entries(initial || {})) {
      if (!(name in fields)) fields[name] = viewOf(value, null);
    }
    return {fields};
  }
}

// -- editors --------------------------------------------------------------------------

function scalarEditor(name, field, commit, refuse) {
  if (field.type === "bool") {
    const box = h("input", {type: "checkbox", class: "switch", disabled: !field.editable});
    let held = !!field.value;
    box.addEventListener("change", async () => { if (!await commit(box.checked)) box.checked = held; });
    return {inline: box, below: null,
            refresh: (view) => { held = !!view.value; if (document.activeElement !== box) box.checked = held; }};
  }
  if (field.type === "none") {
    return {inline: h("span", {class: "muted mono"}, "None"), below: null, refresh: () => {}};
  }
  const numeric = field.type === "int" || field.type === "float";
  const input = h("input", {type: "text", class: `value ${numeric ? "mono num" : ""}`,
                            inputmode: numeric ? "decimal" : "text", spellcheck: "false",
                            disabled: !field.editable, autocomplete: "off"});
  let dirty = false;
  let applied = false;       // applied, nothing typed since: refreshed though it has focus
  let shown = null;
  let sending = null;        // the text being sent: Enter fires "change" too, one POST
  input.addEventListener("input", () => { dirty = true; applied = false; input.classList.add("dirty"); });
  const send = async () => {
    if (!dirty || sending === input.value) return;
    let value = input.value;
    if (numeric) {
      // a float takes inf, -inf and nan too (as the field shows them); an int does not
      value = fmt.parseNumber(input.value);
      if (value === undefined || (field.type === "int" && !Number.isInteger(value))) {
        const takes = field.type === "int" ? "a whole number" : "a number (or inf, -inf, nan)";
        input.classList.add("invalid");
        input.title = takes;
        refuse(`state '${name}' takes ${takes}, got ${input.value.trim() || "nothing"}`);
        return;
      }
    }
    input.classList.remove("invalid");
    sending = input.value;
    try {
      const taken = await commit(value);
      dirty = false;
      applied = taken;
      input.classList.remove("dirty");
      if (!taken) input.value = shown;     // refused: what is held, not what was refused
    } finally {
      sending = null;
    }
  };
  input.addEventListener("keydown", (ev) => {
    if (ev.key === "Enter") send();
    if (ev.key === "Escape") { dirty = false; input.classList.remove("dirty", "invalid"); input.value = shown; input.blur(); }
  });
  input.addEventListener("change", send);
  const refresh = (view) => {
    // JSON has no inf or nan: such a float comes as null with its text, shown marked
    const nonFinite = numeric && view.value === null && typeof view.text === "string";
    shown = nonFinite ? view.text : !numeric ? String(view.value)
      : field.type === "float" && Number.isInteger(view.value) ? view.value.toFixed(1) : fmt.number(view.value);
    input.classList.toggle("nonfinite", nonFinite);
    if (nonFinite) input.title = "not a finite number";
    else if (input.title === "not a finite number") input.title = "";
    // (focused after Enter applied it, it showed that value for good, whatever changed)
    if (!dirty && (applied || document.activeElement !== input)) input.value = shown;
  };
  return {inline: input, below: null, refresh};
}

function arrayEditor(field, commit, display) {
  const summary = h("div", {class: "array-summary mono"});
  const below = h("div", {class: "array"}, summary);
  let grid = null;
  if (field.editable && Array.isArray(field.value) && field.shape.length <= 2) {
    grid = arrayGrid(field, commit);
    below.append(grid.element);
  }
  let image = null;
  if (field.image) {
    image = new LiveImage(display?.kind === "image");
    below.append(image.element);
  }
  const refresh = (view) => {
    const sm = view.summary || {};
    summary.textContent = ["min", "max", "mean"].filter((k) => k in sm)
      .map((k) => `${k} ${fmt.number(sm[k])}`).join(" · ");
    grid?.refresh(view);
    image?.push(view);
  };
  return {inline: null, below, refresh};
}

/** A small array's values as a grid of number fields, applied together: the cells
 * typed in as typed (a float cell takes inf, -inf and nan too), the others as held.
 * (Every cell was sent as shown, six digits, and a NaN, shown empty, as 0.) */
function arrayGrid(field, commit) {
  const rows = field.shape.length === 2 ? field.shape[0] : 1;
  const integer = field.dtype.startsWith("int") || field.dtype.startsWith("uint");
  const boolean = field.dtype === "bool";
  const inputs = [];
  const edited = new Set();
  let held = [];
  const table = h("table", {class: "array-grid"});
  for (let r = 0; r < rows; r += 1) {
    const tr = h("tr");
    const width = field.shape.length === 2 ? field.shape[1] : field.shape[0] ?? 1;
    for (let c = 0; c < width; c += 1) {
      const index = inputs.length;
      const input = h("input", {type: "text", class: "mono", spellcheck: "false"});
      input.addEventListener("input", () => { edited.add(index); dirty = true; apply.disabled = false; });
      input.addEventListener("keydown", (ev) => { if (ev.key === "Enter") send(); });
      inputs.push(input);
      tr.append(h("td", {}, input));
    }
    table.append(tr);
  }
  let dirty = false;
  const apply = h("button", {class: "small primary", type: "button", disabled: true}, "Apply array");
  // a flag: true or false in any case, or 1 or 0 (anything else, "yes" say, is refused:
  // all but "true" was sent as false, unsaid)
  const flag = (text) => ({true: true, 1: true, false: false, 0: false})[text.trim().toLowerCase()];
  const typed = (input) => boolean ? flag(input.value) : fmt.parseNumber(input.value);
  const send = async () => {
    const values = inputs.map((input, i) => edited.has(i) ? typed(input) : held[i]);
    if (values.some((v) => v === undefined || (integer && !Number.isInteger(v)))) {
      table.classList.add("invalid");
      return;
    }
    table.classList.remove("invalid");
    const nested = field.shape.length === 2
      ? Array.from({length: rows}, (_, r) => values.slice(r * field.shape[1], (r + 1) * field.shape[1]))
      : field.shape.length === 0 ? values[0] : values;
    const taken = await commit(nested);
    dirty = false;
    edited.clear();
    apply.disabled = true;
    if (!taken && latest) refresh(latest, true);     // refused: what is held again
  };
  apply.addEventListener("click", send);
  let latest = null;
  const refresh = (view, force = false) => {
    latest = view;
    if (!force && (dirty || inputs.includes(document.activeElement))) return;
    // JSON has no inf or nan: such a cell comes as null, its word in `nonfinite`
    const words = view.nonfinite ?? {};
    const flat = [view.value].flat(Infinity);
    held = flat.map((v, i) => i in words ? fmt.parseNumber(words[i]) : v);
    inputs.forEach((input, i) => {
      input.value = boolean ? String(flat[i]) : words[i] ?? fmt.number(flat[i]);
      input.classList.toggle("nonfinite", i in words);
    });
  };
  return {element: h("div", {}, [table, h("div", {class: "row-actions"}, apply)]), refresh};
}

function objectViewer(field) {
  const code = h("code", {class: "repr"});
  return {inline: null, below: code,
          refresh: (view) => { code.textContent = view.repr ?? view.class ?? ""; }};
}

// -- views ----------------------------------------------------------------------------

function signatureOf(view) {
  if (view.type === "ndarray") return `ndarray ${view.dtype} ${view.shape} ${view.editable} ${!!view.image}`;
  return `${view.type} ${view.editable}`;
}

function typeLabel(view) {
  if (view.type === "ndarray") return `${view.dtype} [${view.shape.join(" × ")}]`;
  if (CONTAINERS.has(view.type)) return `${view.type} · ${view.length ?? Object.keys(view.items || {}).length}`;
  if (view.type === "object") return view.class || "object";
  return view.type;
}

function leafText(view) {
  if (view.type === "str") return JSON.stringify(view.value);
  if (view.type === "none") return "None";
  if (view.type === "bool") return view.value ? "True" : "False";
  if (view.type === "float" && view.value === null && view.text) return view.text;    // inf, nan
  if (view.type === "float" && Number.isInteger(view.value)) return view.value.toFixed(1);
  if (view.type === "int" || view.type === "float") return fmt.number(view.value);
  if (view.type === "ndarray") {
    const sm = view.summary || {};
    return `${view.dtype} [${view.shape.join(" × ")}]` + ("mean" in sm ? ` mean ${fmt.number(sm.mean)}` : "");
  }
  return view.repr ?? view.class ?? view.type;
}

/** The JSON value of a view, when the view holds all of it (else undefined). */
function plainValue(view) {
  if (view.type === "float" && view.value === null && view.text) {          // inf, nan
    return {inf: Infinity, "-inf": -Infinity, nan: NaN}[view.text];
  }
  if (SCALARS.has(view.type)) return view.type === "none" ? null : view.value;
  if (view.type === "ndarray") return Array.isArray(view.value) || "value" in view ? view.value : undefined;
  if (!CONTAINERS.has(view.type) || view.truncated || view.more || !view.items) return undefined;
  const entries = Object.entries(view.items).map(([k, v]) => [k, plainValue(v)]);
  if (entries.some(([, v]) => v === undefined)) return undefined;
  return view.type === "dict" ? Object.fromEntries(entries) : entries.map(([, v]) => v);
}

function viewOf(value, type) {
  if (typeof value === "number" && !Number.isFinite(value)) {      // as a live view has it
    return {type: "float", value: null, editable: true,
            text: Number.isNaN(value) ? "nan" : value > 0 ? "inf" : "-inf"};
  }
  const kind = value === null ? "none" : typeof value === "boolean" ? "bool"
    : typeof value === "number" ? (type === "float" || !Number.isInteger(value) ? "float" : "int")
    : typeof value === "string" ? "str" : Array.isArray(value) ? "list" : "dict";
  if (SCALARS.has(kind)) return {type: kind, value, editable: true};
  const items = {};
  for (const [k, v] of Object.entries(value)) items[k] = viewOf(v, null);
  return {type: kind, length: Object.keys(items).length, items, editable: true};
}
