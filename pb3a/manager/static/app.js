// The ModuleManager page: a running system (or a document being edited) drawn live,
// with the State Editor beside it. It wires the views to the API and the live feed;
// each view lives in its own module.

import {api, ApiError, toEditableJson, toJson} from "./api.js";
import {confirmAction} from "./confirm.js";
import {h} from "./dom.js";
import {EditedDocument, entryOf} from "./document.js";
import {EventList} from "./events.js";
import * as fmt from "./format.js";
import {LiveFeed} from "./live.js";
import {menuButton} from "./menu.js";
import {ModuleBrowser} from "./module_browser.js";
import {portsPanel} from "./ports.js";
import {Schematic} from "./schematic.js";
import {StateEditor} from "./state_editor.js";
import {Toasts} from "./toasts.js";

const $ = (id) => document.getElementById(id);

class Manager {
  constructor() {
    this.system = null;
    this.layout = null;
    this.selected = null;          // the module or macro instance the inspector shows
    this.selection = new Set();    // everything selected (Shift-click adds), the last one shown
    this.document = null;          // an EditedDocument in FILE mode
    this.entering = false;         // a mode being entered: select() leaves the inspector to it
    this.structures = Promise.resolve();   // the structures being shown, one at a time
    this.macroDrawn = null;        // what the inspector last drew for a macro instance
    this.lastMove = new Map();     // module -> its last MigrationReport, shown in the inspector
    this.updates = 0;              // live updates drawn, and what the last one cost (ms)
    this.drawMs = null;
    this.feedErrors = {};          // the live feed's last error shown per source, until it comes
    this.toasts = new Toasts($("toasts"));
    this.schematic = new Schematic($("schematic"), {
      select: (name, how) => this.select(name, how),
      migrate: (name, node) => this.migrate(name, node),
      connect: (src, dst) => this.connect(src, dst),
      place: (cls, node) => this.place(cls, node),
      placeMacro: (macro, node) => this.placeMacro(macro, node),
    });
    this.events = new EventList($("events"), $("event-count"));
    this.editor = new StateEditor($("state-fields"), {
      apply: (fields) => this.applyState(fields),
      drill: (path) => api.state(this.selected, path),
      current: async () => (this.mode() === "editing" ? this.documentState(this.selected)
                                                      : api.state(this.selected)),
      error: (error, loud) => { if (loud) this.toasts.error(error); },
    });
    this.browser = new ModuleBrowser($("classes"), $("class-filter"), {
      place: (cls) => this.place(cls, null),
      placeMacro: (macro) => this.placeMacro(macro, null),
    });
    this.live = new LiveFeed({
      hello: (m) => {
        this.feedErrors = {};
        this.setStructure(m.system, m.layout);
        for (const event of m.events || []) this.events.add(event, false);   // before this page
      },
      system: (m) => { delete this.feedErrors.structure; this.setStructure(m.system, m.layout); },
      stats: (m) => this.onStats(m),
      event: (m) => this.onEvent(m.event),
      state: (m) => this.onState(m),
      error: (m) => this.onFeedError(m),
      status: (up) => this.onConnection(up),
    });
    $("fit").addEventListener("click", () => this.schematic.fit());
    $("inspector-close").addEventListener("click", () => this.select(null));
    $("toggle-browser").addEventListener("click", () => this.toggleBrowser());
    $("save").addEventListener("click", () => this.save());
    $("open").addEventListener("click", () => $("open-file").click());
    $("open-file").addEventListener("change", () => this.open($("open-file")));
    $("launch").addEventListener("click", () => this.launch());
    $("stop").addEventListener("click", () => this.stop());
    $("add-node").addEventListener("click", () => this.addNode());
    // back from the editor where a class was written: the module browser lists it
    window.addEventListener("focus", () => { if (!$("browser").hidden) this.loadClasses(); });
    document.addEventListener("keydown", (ev) => {
      if (ev.target.closest("input, textarea, select, dialog")) return;
      if (ev.key === "Escape") this.select(null);
      if (ev.key === "Delete" && this.selected) this.requestRemove(this.selected);
    });
  }

  mode() {
    return this.system?.mode ?? "running";
  }

  isMacro(name) {
    return !!this.system?.macros && name in this.system.macros;
  }

  exists(name) {
    return name in (this.system?.modules || {}) || this.isMacro(name);
  }

  /** A document entry (a module or macro instance of its own), not a part of a macro. */
  isEntry(name) {
    return this.mode() === "editing" && !!this.document?.system.modules[name];
  }

  async start() {
    try {
      const [system, layout] = await Promise.all([api.system(), api.layout()]);
      await this.setStructure(system, layout);
    } catch (error) {
      this.toasts.error(error);
    }
    this.live.open();
  }

  // -- structure and live figures ---------------------------------------------------
  /** Show ``system`` and its layout once those before it are shown: one at a time, in
   * the order they came. Two that overlapped (the feed's and Stop's own answer) took
   * turns at their awaits, and the older one, ending last, drew the State Editor as of
   * its mode. */
  setStructure(system, layout) {
    this.structures = this.structures
      .then(() => this.showStructure(system, layout))
      .catch((error) => this.toasts.error(error));
    return this.structures;
  }

  async showStructure(system, layout) {
    // a structure older than the one shown (the feed's "stopping", say, after Stop's own
    // answer said "editing") is not taken: it would undo the newer mode
    if (system.mode_change < (this.system?.mode_change ?? 0)) return;
    const before = this.system?.mode;
    const modeChanged = before !== system.mode;
    // a system launched anew numbers its events from 1 (a Stop and a Launch may both
    // come between two of the feed's looks: then only the launch's number changes)
    if (modeChanged || this.system?.launch !== system.launch) this.events.last = 0;
    if (modeChanged && system.mode !== "running") {
      // the last run's figures are no one's now (kept, a stopped system's modules stayed
      // green with their last rates, and its inspector said "running")
      this.stats = null;
      this.schematic.lastStats = this.schematic.previous = null;
    }
    this.system = system;
    this.layout = layout;
    document.body.dataset.mode = system.mode;
    $("system-name").textContent = system.name || "untitled";
    $("mode").textContent = system.mode;
    $("mode").className = `mode-badge ${system.mode}`;
    $("address").textContent = system.address || "";
    // an attached system that stopped where it ran: why, and that it is looked for again
    $("stopped-note").hidden = system.mode !== "stopped";
    $("stopped-note").textContent = system.mode === "stopped"
      ? `${(system.stopped || "The system has stopped").replace(/\.?$/, ".")} The manager connects to ` +
        `${system.address || "its address"} again when a system runs there.` : "";
    const launched = system.mode === "running" && system.stoppable;   // from the document
    $("document-actions").hidden = system.mode !== "editing";
    $("launch-actions").hidden = system.mode !== "editing";
    // (saved while it runs: the document as launched, with the values kept in it)
    $("save-actions").hidden = !(system.mode === "editing" || launched);
    $("running-actions").hidden = !launched;
    if (modeChanged) {
      // a module selected before the mode is entered is drawn once, by the select below
      this.entering = true;
      try {
        await this.enterMode(system.mode, {launched, before});
      } finally {
        this.entering = false;
      }
    }
    if (this.document) this.browser.setMacros(this.document.macros());
    this.schematic.render(system, layout);
    const gone = [...this.selection].filter((name) => !this.exists(name));
    if (gone.length) {
      for (const name of gone) this.selection.delete(name);
      this.select([...this.selection].at(-1) ?? null);
    } else if (modeChanged && this.selected) {
      // launched (or back to editing): the State Editor shows the other mode's state,
      // and the live feed watches the module only once it runs
      this.select(this.selected);
    } else if (this.selected) {
      this.describeSelected();
    }
    this.showProblems();
  }

  /** Enter ``mode`` (``launched``: a system launched from the document runs; ``before``:
   * the mode the page showed, if any). */
  async enterMode(mode, {launched = false, before} = {}) {
    if (mode === "editing") {
      this.document = await new EditedDocument().load().catch((error) => { this.toasts.error(error); return null; });
      $("save-path").value = this.document?.path || "";
      $("browser").hidden = false;
    } else {
      this.document = null;
      // Save writes the launched document: the box says its file, as while editing (a
      // page opened on the running system, or reloaded, never saw it; one launched here
      // keeps what the box said)
      if (launched && before !== "editing") await this.showDocumentPath();
    }
    if (mode === "editing" || !$("browser").hidden) await this.loadClasses();
  }

  /** Put the document's file into the save box (empty when it has none: Save asks). */
  async showDocumentPath() {
    try {
      $("save-path").value = (await api.document()).path || "";
    } catch (error) {
      this.toasts.error(error);
    }
  }

  async loadClasses() {
    try {
      this.browser.set(await api.classes());
    } catch (error) {
      this.toasts.error(error);
    }
  }

  toggleBrowser() {
    const panel = $("browser");
    panel.hidden = !panel.hidden;
    if (!panel.hidden && !this.browser.classes.length) this.loadClasses();
  }

  onStats(message) {
    const start = performance.now();
    this.schematic.update({...message.stats, time: message.time});
    this.drawMs = performance.now() - start;       // the page's share of an update
    this.updates += 1;
    $("cost").textContent = `${fmt.clock(message.time)} · server ` +
      `${message.cost_ms?.toFixed?.(1) ?? "?"} ms · page ${this.drawMs.toFixed(1)} ms`;
    $("cost").title = "the last update: when, what gathering it took on the server, " +
      "and what drawing it took in this page";
    this.stats = message.stats;
    delete this.feedErrors.stats;
    if (this.selected) this.describeSelected();
  }

  /** The server could not read the stats, events or structure this time; it tries
   * again, more slowly while it fails. Shown once per source until that source comes
   * through (one remembered for all: the stats' and the events' errors took turns, and
   * each was shown anew). */
  onFeedError(message) {
    const source = message.source ?? "";
    if (message.error === this.feedErrors[source]) return;
    this.feedErrors[source] = message.error;
    this.toasts.error(new Error(message.error));
  }

  /** A refresh of the watched module's state, or why it could not be read (it may be
   * gone, or slow to answer): the fields stay, the reason shows above them. */
  onState(message) {
    if (message.module !== this.selected || this.mode() !== "running") return;
    if (message.state) this.editor.update(message.state);
    this.editor.problem(message.state ? null : message.error || "its state could not be read");
  }

  onEvent(event) {
    delete this.feedErrors.events;
    this.events.add(event);
    if (event.kind.startsWith("module_") || event.kind === "migration_failed") this.schematic.flash(event.subject);
    if (event.kind === "module_swapped" && event.subject === this.selected) this.select(this.selected);
  }

  onConnection(up) {
    const badge = $("connection");
    badge.textContent = up ? "live" : "reconnecting…";
    badge.classList.toggle("up", up);
  }

  showProblems() {
    const box = $("problems");
    const problems = this.document?.problems || [];
    box.hidden = this.mode() !== "editing" || !problems.length;
    box.replaceChildren(h("strong", {}, `${problems.length} problem${problems.length === 1 ? "" : "s"} (pb3a check)`),
                        h("ul", {}, problems.map((p) => h("li", {}, p))));
  }

  // -- the inspector and its State Editor --------------------------------------------
  /** Show `name` (a module or a macro instance) in the inspector; with `add`, add it to
   * the selection (or take it out) instead. */
  async select(name, {add = false} = {}) {
    if (add && name) {
      if (this.selection.has(name)) this.selection.delete(name);
      else this.selection.add(name);
    } else {
      this.selection = new Set(name ? [name] : []);
    }
    name = [...this.selection].at(-1) ?? null;
    this.selected = name;
    this.schematic.select(name, [...this.selection]);
    $("swap-picker").hidden = true;
    $("keep-picker").hidden = true;
    if (!name) {
      $("inspector-body").hidden = true;
      $("inspector-empty").hidden = false;
      this.live.watch(null);
      return;
    }
    // a launch or a stop under way: setStructure selects it again once the mode is entered
    // (drawn now, it was drawn anew then, what was typed in it and its marks lost)
    if (this.entering) return;
    $("inspector-empty").hidden = true;
    $("inspector-body").hidden = false;
    $("inspector-name").textContent = this.selection.size > 1 ? `${this.selection.size} selected` : name;
    this.macroDrawn = null;
    this.describeSelected();
    this.drawActions(name);
    if (this.selection.size > 1 || this.isMacro(name)) {
      this.live.watch(null);
      this.editor.clear();
      return;
    }
    const displays = this.system.modules[name]?.displays;
    if (this.mode() === "editing") {
      this.editor.show(this.documentState(name), displays);
      return;
    }
    if (this.mode() === "stopping" || this.mode() === "stopped") {   // (no state to read)
      this.live.watch(null);
      this.editor.pending(this.mode() === "stopping" ? "The system is stopping…"
                          : "The system has stopped.", displays);
      return;
    }
    this.live.watch(name);
    const subject = this.stateSubject(name);
    if (this.editor.shows(subject)) {
      // selected again (after Restart, say) with the fields of this same state drawn,
      // the live feed's: read into them, not from nothing ("Reading its state…" in their
      // place a moment, then drawn anew, was a flicker that lost what was typed), and
      // the reason a refresh of the feed's failed meanwhile, if any, goes
      try {
        const view = await api.state(name);
        if (this.selected === name && this.editor.shows(subject)) {
          this.editor.update(view);
          this.editor.problem(null);
        }
      } catch (error) {
        if (this.selected === name && this.editor.shows(subject)) this.editor.pending(error.message, displays, true, subject);
      }
      return;
    }
    const reading = this.editor.pending("Reading its state…", displays, false, subject);
    try {
      const view = await api.state(name);
      // (not when the live feed drew the fields first: this answer is no newer, and
      // drawn anew the fields lost what was typed in them and their applied marks)
      if (this.selected === name && this.editor.awaits(reading)) this.editor.show(view, displays, subject);
    } catch (error) {
      // the live feed's next state draws the fields (once it can be read again)
      if (this.selected === name && this.editor.awaits(reading)) this.editor.pending(error.message, displays, true, subject);
    }
  }

  /** Whose state the State Editor shows for running module `name`: the module in this
   * launch and mode, of its class and displays. Fields drawn for the same subject are
   * read into again; another one (another module, a launch, a swap to another class) is
   * read from nothing, "Reading its state…" in the fields' place. */
  stateSubject(name) {
    const info = this.system.modules[name];
    return JSON.stringify([name, this.system.mode, this.system.mode_change ?? null,
                           this.system.launch ?? null, info?.class ?? null,
                           info?.displays ?? null]);
  }

  describeSelected() {
    const name = this.selected;
    if (this.selection.size > 1) {
      $("inspector-meta").replaceChildren(h("span", {class: "mono"}, [...this.selection].join(", ")));
      $("inspector-extra").replaceChildren();
      return;
    }
    if (this.isMacro(name)) return this.describeMacro(name);
    const info = this.system.modules[name];
    if (!info) return;
    const live = this.stats?.modules?.[name];
    // (the stats' while it runs: a period the module sets itself is no event, so the
    // structure is not sent again for it)
    const period = live && "period" in live ? live.period : info.period;
    // "0.02 fixed" and the periods it skipped, as `pb3a status` shows a fixed rate
    const fixed = (live ? live.fixed_rate : info.fixed_rate) && period !== null && period !== undefined;
    const overruns = fixed && live?.overruns ? ` (overruns ${live.overruns})` : "";
    const status = live ? live.status : this.mode() === "editing" ? "not launched" : "";
    const meta = [
      h("span", {class: "mono"}, info.class),
      h("span", {}, ["on ", h("strong", {}, live?.node ?? info.node ?? "the default node")]),
      status ? h("span", {class: `status status-${live?.silent ? "silent" : status}`},
                 (live?.silent ? `${status} (silent: its worker does not answer)` : status) + overruns) : null,
      fmt.longCall(live) ? h("span", {class: "status status-in-long-call"}, fmt.longCall(live)) : null,
      period !== null && period !== undefined
        ? h("span", {}, `period ${fmt.seconds(period)}${fixed ? " fixed" : ""}`) : null,
      info.macro ? h("span", {}, `in macro ${info.macro}`) : null,
      this.mode() === "editing" && name.includes("/")
        ? h("span", {}, `its state here is what instance ${entryOf(name)} sets`) : null,
    ];
    $("inspector-meta").replaceChildren(...meta.filter(Boolean));
    const box = $("period");
    if (box && this.mode() === "running" && document.activeElement !== box) box.value = period ?? "";
    const extra = [];
    if (live?.last_error) extra.push(h("div", {class: "problem"}, `${live.errors} errors · last: ${live.last_error}`));
    const move = this.lastMove.get(name);
    if (move) {
      extra.push(h("div", {class: "move-report"}, [
        h("strong", {}, `Moved ${move.source} → ${move.destination}`),
        ` · paused ${fmt.seconds(move.pause_s)} · ${fmt.bytes(move.state_bytes)} of state · ${move.links} links`,
      ]));
    }
    $("inspector-extra").replaceChildren(...extra);
  }

  drawActions(name) {
    const button = (label, act, tone = "") =>
      h("button", {type: "button", class: `small ${tone}`, onclick: act}, label);
    const actions = [];
    let ports = null;
    if (this.selection.size > 1) {
      actions.push(...this.groupForm());
    } else if (this.isMacro(name)) {
      actions.push(...this.macroActions(name, button));
    } else if (this.mode() === "running") {
      actions.push(this.moveMenu(name));
      actions.push(button("Restart", () => this.restart(name),
                          this.stats?.modules?.[name]?.status === "failed" ? "primary" : ""));
      actions.push(button("Swap class…", () => this.openSwaps(name)));
      actions.push(button("Reload code", () => this.reload(name)));
      actions.push(h("label", {class: "inline"}, ["Period ", this.periodInput(name, (value) => {
        if (value === null) return this.toasts.error(new Error("period: a number of seconds ≥ 0 (a running module's cannot be emptied)"));
        this.setPeriod(name, value);
      })]));
      if (this.system.stoppable) {          // launched from the document: it can keep state
        const keep = button("Keep in document", () => this.openKeep(name));
        keep.id = "keep";
        keep.title = "write the values tuned here into the document's state for this module";
        actions.push(keep);
      }
      actions.push(button("Remove", () => this.requestRemove(name), "danger"));
      ports = this.ports(name, (m) => m !== name);
    } else if (this.isEntry(name)) {
      const period = this.periodInput(name, (value) => this.editDocument(() => this.document.setPeriod(name, value)));
      actions.push(this.moveMenu(name), this.renameControl(name),
                   h("label", {class: "inline"}, ["Period ", period]),
                   h("label", {class: "inline"}, ["Fixed rate ", this.fixedRateInput(name)]),
                   button("Remove", () => this.requestRemove(name), "danger"));
      // a document links its own entries: a macro's modules through the macro's exports
      ports = this.ports(name, (m) => m !== name && !m.includes("/"));
    } else if (this.mode() === "editing") {
      actions.push(button(`Macro ${entryOf(name)}`, () => this.select(entryOf(name))));
    }
    $("inspector-actions").replaceChildren(...actions);
    $("inspector-ports").replaceChildren(...[ports].filter(Boolean));
  }

  /** The Period box of module `name`: its period as configured or set, empty for its
   * class's own, which the placeholder says (it said "event-driven" whatever the class's
   * was); `apply(seconds or null)` once a number ≥ 0, or nothing, is entered. */
  periodInput(name, apply) {
    const own = this.browser.byName(this.system.modules[name]?.class)?.period;
    const set = this.mode() === "editing" ? this.document.system.modules[name]?.period
                                          : this.system.modules[name]?.period;
    const period = h("input", {type: "text", class: "small mono", id: "period",
                               placeholder: own === undefined ? "its class's"
                                 : own === null ? "event-driven" : `${own} (its class's)`,
                               value: set ?? "", "aria-label": "period in seconds", size: 8});
    period.addEventListener("change", () => {
      const text = period.value.trim();
      const value = text === "" ? null : Number(text);
      if (value !== null && !(value >= 0)) return this.toasts.error(new Error("period: a number of seconds ≥ 0, or empty for its class's"));
      apply(value);
    });
    return period;
  }

  /** The Fixed rate choice of document entry `name`: its class's own (which the choice
   * says, as the Period box's placeholder says its period), yes (`fixed_rate = true`:
   * each step due a period after the last one began) or no (the period slept after each
   * step); its class's own leaves the key out of the document. */
  fixedRateInput(name) {
    const own = this.browser.byName(this.system.modules[name]?.class)?.fixed_rate;
    const set = this.document.system.modules[name]?.fixed_rate;
    const choice = h("select", {class: "small", id: "fixed-rate", "aria-label": "fixed rate",
                                title: "yes: each step is due a period after the last one began, "
                                  + "late periods skipped and counted as overruns; no: the period is slept after each step"}, [
      h("option", {value: ""}, own === undefined ? "its class's" : `its class's (${own ? "yes" : "no"})`),
      h("option", {value: "yes"}, "yes"),
      h("option", {value: "no"}, "no"),
    ]);
    choice.value = set === true ? "yes" : set === false ? "no" : "";
    choice.addEventListener("change", () => {
      const fixed = choice.value === "" ? null : choice.value === "yes";
      this.editDocument(() => this.document.setFixedRate(name, fixed));
    });
    return choice;
  }

  /** Set running module `name`'s period live; the structure the feed sends after its
   * `module_retimed` event shows it. */
  async setPeriod(name, seconds) {
    try {
      await api.setState(name, {period: seconds});
      this.toasts.show("ok", `${name} steps every ${fmt.seconds(seconds)}`);
    } catch (error) {
      this.toasts.error(error);
    }
  }

  /** "Move to node ▸": the keyboard's way to drag a module (or a macro) to a node. */
  moveMenu(name) {
    const here = this.stats?.modules?.[name]?.node ?? this.system.modules[name]?.node ??
                 this.document?.system.modules[name]?.node;
    return menuButton("Move to node ▸", () => Object.keys(this.system.nodes || {}).map((node) => ({
      label: node === here ? `${node} (here)` : node, value: node, disabled: node === here,
      act: () => this.migrate(name, node)})), {empty: "no node to move to", name: "move to node"});
  }

  ports(name, linkable) {
    const candidates = (dir) => Object.entries(this.system.modules)
      .filter(([m]) => linkable(m))
      .flatMap(([m, info]) => Object.entries((dir === "in" ? info.inputs : info.outputs) || {})
        .map(([port, spec]) => [m, port, spec]));
    return portsPanel(name, this.system.modules[name], this.system.links || [], candidates,
                      (src, dst) => this.connect(src, dst));
  }

  /** "Rename…": a field in place of the button; Enter renames, Escape leaves it. */
  renameControl(name) {
    const open = h("button", {type: "button", class: "small", id: "rename"}, "Rename…");
    open.addEventListener("click", () => {
      const input = h("input", {type: "text", class: "small mono", id: "rename-input", value: name,
                                "aria-label": `new name for ${name}`, size: 12, spellcheck: "false"});
      input.addEventListener("keydown", (ev) => {
        if (ev.key === "Enter") this.rename(name, input.value);
        if (ev.key === "Escape") { ev.stopPropagation(); input.replaceWith(open); open.focus(); }
      });
      open.replaceWith(input);
      input.select();
    });
    return open;
  }

  /** With several modules selected while editing: make them one macro. */
  groupForm() {
    if (this.mode() !== "editing") {
      return [h("p", {class: "muted"}, "Grouping into a macro is done in the document being edited.")];
    }
    const input = h("input", {type: "text", class: "small mono", id: "macro-name", placeholder: "macro name",
                              "aria-label": "name of the new macro", size: 12, spellcheck: "false"});
    const go = () => this.group([...this.selection], input.value.trim());
    input.addEventListener("keydown", (ev) => { if (ev.key === "Enter") go(); });
    return [input, h("button", {type: "button", class: "small primary", id: "group", onclick: go}, "Group into macro")];
  }

  macroActions(macro, button) {
    const folded = this.schematic.isFolded(macro);
    const actions = [h("button", {type: "button", class: "small", id: "macro-fold", onclick: () => {
      this.schematic.toggleMacro(macro);
      this.drawActions(macro);
    }}, folded ? "Open" : "Close")];
    if (this.mode() === "running" || this.isEntry(macro)) actions.push(this.moveMenu(macro));
    if (this.isEntry(macro)) {
      actions.push(this.renameControl(macro), button("Remove", () => this.requestRemove(macro), "danger"));
    }
    return actions;
  }

  /** A macro instance: what it is, its modules (each opens in the inspector), and the
   * state it sets on them (its overrides), each of which can be dropped. */
  describeMacro(macro) {
    const modules = this.system.macros[macro] || [];
    const entry = this.isEntry(macro) ? this.document.system.modules[macro] : null;
    const nodes = [...new Set(modules.map((m) => this.stats?.modules?.[m]?.node ?? this.system.modules[m]?.node))];
    // redrawn only when it changed: a refresh must not take the focus from its buttons
    const drawn = toJson([macro, modules, nodes, entry]);
    if (drawn === this.macroDrawn) return;
    this.macroDrawn = drawn;
    $("inspector-meta").replaceChildren(...[
      h("span", {}, ["macro instance", entry ? [" of ", h("strong", {}, entry.macro)] : ""]),
      h("span", {}, `${modules.length} module${modules.length === 1 ? "" : "s"}`),
      h("span", {}, ["on ", h("strong", {}, nodes.join(", ") || "–")]),
    ]);
    const list = h("ul", {class: "macro-modules"}, modules.map((m) => h("li", {}, h("button", {
      type: "button", class: "small ghost mono", dataset: {child: m}, onclick: () => this.select(m)},
      m.slice(macro.length + 1)))));
    const extra = [h("h3", {}, "Modules"), list];
    const overrides = Object.entries(entry?.state || {});
    if (entry) {
      extra.push(h("h3", {}, "State it sets on them"));
      extra.push(overrides.length ? h("ul", {class: "overrides"}, overrides.flatMap(([key, fields]) =>
        Object.entries(fields || {}).map(([field, value]) => h("li", {dataset: {override: `${key}.${field}`}}, [
          h("span", {class: "mono"}, `${key}.${field} = ${toEditableJson(value)}`),
          h("button", {type: "button", class: "icon ghost", title: "drop this override",
                       "aria-label": `drop ${key}.${field}`,
                       onclick: () => this.editDocument(() => this.document.clearOverride(macro, key, field))}, "✕"),
        ]))))
        : h("p", {class: "muted"}, "None: select one of its modules to set its state for this instance."));
    }
    $("inspector-extra").replaceChildren(...extra);
  }

  documentState(name) {
    const module = this.document?.system.modules[name];
    const info = this.browser.byName(this.system.modules[name]?.class);
    return StateEditor.documentView(info, module ? module.state : this.document?.macroChildState(name));
  }

  async applyState(fields) {
    const name = this.selected;
    if (this.mode() === "editing") {
      // a module inside a macro instance: the instance's override, not the macro's own
      const edit = this.isEntry(name) ? () => this.document.setState(name, fields)
                                      : () => this.document.setOverride(name, fields);
      await this.editDocument(edit, true);
      return this.documentState(name);
    }
    return api.setState(name, fields);
  }

  // -- changing it -------------------------------------------------------------------
  async migrate(name, node) {
    if (this.mode() === "editing") return this.editDocument(() => this.document.setNode(name, node));
    const pending = this.toasts.show("info", `Moving ${name} to ${node}…`, {seconds: 0});
    try {
      const report = await api.migrate(name, node);
      this.lastMove.set(name, report);
      this.toasts.show("ok", `${name} moved ${report.source} → ${report.destination}`, {
        lines: [`paused ${fmt.seconds(report.pause_s)} · ${fmt.bytes(report.state_bytes)} of state · ${report.links} links rewired`],
      });
      if (this.selected === name) this.describeSelected();
      await this.refreshStructure();
    } catch (error) {
      this.toasts.error(error);
    } finally {
      pending.remove();
    }
  }

  async openSwaps(name) {
    const picker = $("swap-picker");
    picker.hidden = false;
    picker.replaceChildren(h("p", {class: "muted"}, "Finding classes whose ports fit…"));
    try {
      const {classes} = await api.swaps(name);
      const current = this.system.modules[name].class;
      const choices = classes.filter((c) => c !== current);
      picker.replaceChildren(
        h("div", {class: "picker-head"}, [h("strong", {}, "Swap to"),
          h("button", {type: "button", class: "icon ghost", onclick: () => { picker.hidden = true; }}, "✕")]),
        choices.length
          ? h("ul", {class: "choices"}, choices.map((cls) => h("li", {}, h("button", {
              type: "button", class: "choice mono", dataset: {class: cls},
              onclick: () => this.swap(name, cls)}, cls))))
          : h("p", {class: "muted"}, "No other class on the import path has ports that fit."),
      );
    } catch (error) {
      picker.replaceChildren(h("p", {class: "problem"}, error.message));
    }
  }

  /** "Keep in document": the module's settings whose live value differs from what the
   * document gives it, each with a box (ticked: those tuned here; all when none was);
   * "Keep" writes the ticked ones into the document (Save writes the file). */
  async openKeep(name) {
    const picker = $("keep-picker");
    $("swap-picker").hidden = true;
    picker.hidden = false;
    picker.replaceChildren(h("p", {class: "muted"}, "Comparing its live state with the document…"));
    let offer;
    try {
      offer = await api.keepOffer(name);
    } catch (error) {
      picker.replaceChildren(h("p", {class: "problem"}, error.message));
      return;
    }
    if (this.selected !== name) return;
    const changes = Object.entries(offer.changes);
    const anyTuned = changes.some(([, change]) => change.tuned);
    const boxes = changes.map(([field, change]) => {
      const box = h("input", {type: "checkbox", dataset: {keep: field}});
      box.checked = anyTuned ? change.tuned : true;
      return [field, change, box];
    });
    const head = h("div", {class: "picker-head"}, [h("strong", {}, "Keep in document"),
      h("button", {type: "button", class: "icon ghost", "aria-label": "close", onclick: () => { picker.hidden = true; }}, "✕")]);
    const readOuts = Object.keys(offer.not_kept);
    const note = readOuts.length
      ? h("p", {class: "muted", title: Object.entries(offer.not_kept).map(([f, why]) => `${f}: ${why}`).join("\n")},
          `not kept (read-outs): ${readOuts.join(", ")}`) : null;
    if (!boxes.length) {
      picker.replaceChildren(head, h("p", {class: "muted"}, "Its settings are what the document gives it already."),
                             ...[note].filter(Boolean));
      return;
    }
    const go = h("button", {type: "button", class: "small primary keep-go", id: "keep-go"}, "Keep");
    go.addEventListener("click", () => this.keep(name, boxes.filter(([, , box]) => box.checked).map(([field]) => field), offer.revision));
    picker.replaceChildren(head,
      h("div", {class: "keep-fields"}, boxes.map(([field, change, box]) => h("label", {}, [
        box, h("span", {class: "mono"}, field),
        h("span", {class: "mono was"}, toEditableJson(change.document)), "→",
        h("span", {class: "mono"}, toEditableJson(change.live)),
        change.tuned ? h("span", {class: "muted"}, "tuned here") : ""]))),
      go, ...[note].filter(Boolean));
  }

  async keep(name, fields, revision) {
    if (!fields.length) return this.toasts.error(new Error("tick the fields to keep"));
    try {
      const answer = await api.keep(name, fields, revision);
      $("keep-picker").hidden = true;
      const kept = Object.entries(answer.kept).map(([field, value]) => `${field} = ${toEditableJson(value)}`);
      this.toasts.show("ok", kept.length ? `Kept in the document: ${name}` : `Nothing to keep for ${name}`, {
        lines: kept.length ? [kept.join(", "), "Save writes the file"] : [],
      });
    } catch (error) {
      // another page or a script changed the document meanwhile: offer again on the new one
      if (error.status === 412) return this.openKeep(name);
      this.toasts.error(error);
    }
  }

  async swap(name, cls) {
    try {
      const {kept} = await api.swap(name, cls);
      $("swap-picker").hidden = true;
      this.toasts.show("ok", `${name} is now ${fmt.shortClass(cls)}`,
                       {lines: [kept.length ? `state kept: ${kept.join(", ")}` : "no state kept"]});
      await this.refreshStructure();
      if (this.selected === name) this.select(name);
    } catch (error) {
      this.toasts.error(error);
    }
  }

  /** Start a module afresh (a failed one too), as `pb3a restart` does. */
  async restart(name) {
    try {
      await api.restart(name);
      this.toasts.show("ok", `Restarted ${name}`);
      await this.refreshStructure();
      if (this.selected === name) this.select(name);
    } catch (error) {
      this.toasts.error(error);
    }
  }

  /** Drop the cached code of the module's file everywhere, then swap each module whose
   * class comes from that file to the same class: the new code runs, the state is kept. */
  async reload(name) {
    const module = this.system.modules[name].class.split(":")[0];
    const users = Object.entries(this.system.modules).filter(([, info]) => info.class.startsWith(`${module}:`));
    try {
      await api.reload(module);
      for (const [user, info] of users) await api.swap(user, info.class);
      this.toasts.show("ok", `Reloaded ${module}`, {lines: [`new code in ${users.map(([user]) => user).join(", ")}`]});
      await this.refreshStructure();
      if (this.selected === name) this.select(name);
    } catch (error) {
      this.toasts.error(error);
    }
  }

  /** Remove a module (or a macro instance of the document), after asking. */
  async requestRemove(name) {
    const running = this.mode() === "running";
    if (!running && !this.isEntry(name)) {
      return this.toasts.error(new Error(`${name} is part of macro ${entryOf(name)}: remove the instance, or change the macro`));
    }
    if (running && this.isMacro(name)) {
      return this.toasts.error(new Error(`remove the modules of macro ${name} one by one`));
    }
    const what = this.isMacro(name) ? "macro instance" : "module";
    const detail = running ? "It stops now; its links go with it." : "Its links go with it.";
    if (!await confirmAction(`Remove ${what} ${name}?`, detail, "Remove")) return;
    if (!running) {
      await this.editDocument(() => this.document.remove(name));
      return;
    }
    await this.removeRunning(name);
  }

  /** Remove a running module. One that does not answer its stop in time (a 504: frozen
   * in a call, its worker stopped) is left as it was; the error offers to kill its
   * worker, which sends the remove again with force. */
  async removeRunning(name, force = false) {
    const pending = force ? this.toasts.show("info", `Removing ${name}: its worker is killed if it does not answer…`, {seconds: 0}) : null;
    try {
      await api.removeModule(name, force);
      this.toasts.show("ok", `Removed ${name}`);
      await this.refreshStructure();
    } catch (error) {
      const offer = error.status === 504 && !force ? [["Kill its worker", () => this.removeRunning(name, true), "danger"]] : [];
      this.toasts.error(error, offer);
    } finally {
      pending?.remove();
    }
  }

  async rename(name, to) {
    let renamed = null;
    await this.editDocument(async () => { renamed = await this.document.rename(name, to); });
    if (renamed && renamed !== name) {
      this.toasts.show("ok", `Renamed ${name} → ${renamed}`);
      await this.select(renamed);
    }
  }

  async group(names, macro) {
    let instance = null;
    await this.editDocument(async () => { instance = await this.document.group(names.map(entryOf), macro); });
    if (instance) {
      this.toasts.show("ok", `Grouped ${names.length} modules into macro ${macro}`, {lines: [`instance ${instance}`]});
      await this.select(instance);
    }
  }

  async placeMacro(macro, node) {
    if (this.mode() !== "editing") return this.toasts.error(new Error("macros are placed in the document being edited"));
    const target = node ?? this.document.nodes()[0];
    let name = null;
    await this.editDocument(async () => { name = await this.document.placeMacro(macro, target); });
    if (name) this.toasts.show("ok", `Placed macro ${macro} as ${name}${target ? ` on ${target}` : ""}`);
  }

  async connect(src, dst, replace = false) {
    if (this.mode() === "editing") {
      return this.editDocument(async () => {
        const check = await this.document.link(src, dst);
        if (!check.ok) this.toasts.error(new ApiError(409, check.message));
        else this.toasts.show("ok", `Linked ${src} → ${dst}`);
      });
    }
    try {
      await api.link({src, dst, replace});
      this.toasts.show("ok", `${replace ? "Relinked" : "Linked"} ${src} → ${dst}`);
      await this.refreshStructure();
    } catch (error) {
      const offer = error.status === 409 && !replace ? [["Replace its link", () => this.connect(src, dst, true)]] : [];
      this.toasts.error(error, offer);
    }
  }

  async place(cls, node) {
    if (this.mode() === "editing") {
      const target = node ?? this.document.nodes()[0];
      return this.editDocument(async () => {
        const name = await this.document.place(cls, target);
        this.toasts.show("ok", `Placed ${name}${target ? ` on ${target}` : ""}`);
      });
    }
    const base = fmt.shortClass(cls).toLowerCase();
    let name = base;
    for (let i = 2; name in this.system.modules; i += 1) name = `${base}${i}`;
    try {
      await api.addModule(node ? {name, class: cls, node} : {name, class: cls});
      this.toasts.show("ok", `Added ${name}${node ? ` on ${node}` : ""}`);
      await this.refreshStructure();
    } catch (error) {
      this.toasts.error(error);
    }
  }

  async addNode() {
    const nodes = this.document.nodes();
    let name = "a";
    for (let i = 0; nodes.includes(name); i += 1) name = String.fromCharCode(98 + i);
    await this.editDocument(() => this.document.addNode(name));
  }

  /** Change the document, then draw what the server now makes of it. */
  async editDocument(change, rethrow = false) {
    const edits = this.document.edits;
    try {
      await change();
    } catch (error) {
      this.toasts.error(error);
      if (rethrow) throw error;
      // refused here, so nothing changed: drawn anew, the page lost what was typed in a
      // field to mend, and a menu opened meanwhile closed under the pointer
      if (this.document.edits === edits) return;
    }
    await this.refreshStructure();
    if (this.selected) {
      this.drawActions(this.selected);
      this.describeSelected();
    }
  }

  async refreshStructure() {
    try {
      const [system, layout] = await Promise.all([api.system(), api.layout()]);
      await this.setStructure(system, layout);
    } catch (error) {
      this.toasts.error(error);
    }
  }

  /** Send the .toml file chosen in the file picker; the server checks it as `pb3a check`
   * does and, if it passes, makes it the document. Its problems are shown otherwise, and
   * the document stays as it was. The browser gives no path: Save asks for one. */
  async open(input) {
    const file = input.files[0];
    input.value = "";                  // so that choosing the same file again reads it again
    if (!file) return;
    try {
      const answer = await api.open(file.name, await file.text());
      this.document.take(answer);
      this.document.path = answer.path;
      $("save-path").value = "";
      this.toasts.show("ok", `Opened ${file.name}`, {lines: ["Save writes it where the box says"]});
    } catch (error) {
      this.toasts.error(error);
      return;
    }
    await this.refreshStructure();
    await this.loadClasses();          // its module servers may offer other classes
  }

  async save(overwrite = false) {
    const path = $("save-path").value.trim() || undefined;
    try {
      const answer = await api.save(path, overwrite);
      this.toasts.show("ok", `Saved ${answer.path ?? path ?? this.document.path}`);
    } catch (error) {
      // the file says what this page never read (edited on disk since): ask first
      if (error.status === 409 && !overwrite
          && await confirmAction("Overwrite the file?", `${error.message}: saving loses what it ` +
                                 "says now.", "Overwrite")) {
        return this.save(true);
      }
      this.toasts.error(error);
    }
  }

  /** Stop the system launched from this page, after asking; the page edits its document again. */
  async stop() {
    if (!await confirmAction(`Stop ${this.system.name}?`, "Every module stops; what they " +
                             "hold now is lost. The document stays as it was launched, with what was kept in it.", "Stop")) return;
    try {
      await api.stop();
      this.toasts.show("ok", `${this.system.name} stopped`);
      await this.refreshStructure();
    } catch (error) {
      this.toasts.error(error);
    }
  }

  async launch() {
    const pending = this.toasts.show("info", "Launching…", {seconds: 0});
    try {
      await api.launch();
      this.toasts.show("ok", `${this.system.name} is running`);
      await this.refreshStructure();
    } catch (error) {
      this.toasts.error(error);
    } finally {
      pending.remove();
    }
  }
}

const manager = new Manager();
window.pb3aManager = manager;      // for a console user or a test that wants to look inside
manager.start();
