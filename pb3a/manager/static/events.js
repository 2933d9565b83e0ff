// The event list: moves (and moves that failed), swaps, restarts, periods set, failures,
// lost nodes, adds and removes, as they happen (also those an agent makes), newest first.

import {h} from "./dom.js";
import * as fmt from "./format.js";

const KEEP = 200;

const LOOK = {
  module_moved: ["move", "moved"],
  migration_failed: ["failure", "move failed"],
  module_swapped: ["swap", "swapped"],
  module_restarted: ["restart", "restarted"],
  module_retimed: ["other", "retimed"],
  module_failed: ["failure", "failed"],
  module_failed_over: ["failure", "failed over"],
  module_lost: ["failure", "lost"],
  module_added: ["add", "added"],
  module_removed: ["remove", "removed"],
  link_added: ["link", "linked"],
  link_removed: ["link", "unlinked"],
  node_lost: ["failure", "node lost"],
  node_joined: ["add", "node joined"],
};

function describe(event) {
  const d = event.detail || {};
  switch (event.kind) {
    case "module_moved":
      return `${d.source} → ${d.destination}, paused ${fmt.seconds(d.pause_s)}`;
    case "migration_failed":
      return `${d.source} → ${d.destination}: ${d.error}`;
    case "module_swapped":
      return `now ${fmt.shortClass(d.cls)}${d.kept?.length ? `, kept ${d.kept.join(", ")}` : ""}`;
    case "module_failed_over":
      return `from ${d.source ?? "?"} to ${d.destination ?? "?"}`;
    case "module_lost":
      return `with node ${d.node}: ${d.reason}`;
    case "module_retimed":
      return `every ${fmt.seconds(d.period)}`;
    case "module_restarted":
      return [d.node && `on ${d.node}`, d.reason,
              d.from_checkpoint === false && "with its configured state: no checkpoint"]
        .filter(Boolean).join(", ");
    case "node_lost":
      return [d.modules?.length && `with ${d.modules.join(", ")}`,
              d.arriving?.length && `${d.arriving.join(", ")} on the way there`]
        .filter(Boolean).join("; ");
    case "module_added":
      return d.node ? `on ${d.node}` : "";
    case "module_removed":       // (removed with force: its worker killed, with why)
      return d.killed ? `${d.reason} (pid ${d.pid})` : "";
    default:
      return Object.entries(d).map(([k, v]) => `${k} ${typeof v === "object" ? JSON.stringify(v) : v}`)
        .join(", ");
  }
}

export class EventList {
  constructor(list, counter) {
    this.list = list;
    this.counter = counter;
    this.seen = 0;
    this.last = 0;          // the newest event's number: one sent again (a reconnection) is shown once
  }

  /** Show ``event`` on top; ``fresh``: highlighted for a moment (not one from before the page). */
  add(event, fresh = true) {
    if (event.seq <= this.last) return;
    this.last = event.seq;
    const [tone, verb] = LOOK[event.kind] || ["other", event.kind.replaceAll("_", " ")];
    const item = h("li", {class: `event tone-${tone}${fresh ? " fresh" : ""}`, dataset: {kind: event.kind}}, [
      h("time", {}, fmt.clock(event.time)),
      h("span", {class: "event-kind"}, verb),
      h("span", {class: "event-subject"}, event.subject),
      h("span", {class: "event-detail"}, describe(event)),
    ]);
    this.list.querySelector(".empty")?.remove();
    this.list.prepend(item);
    setTimeout(() => item.classList.remove("fresh"), 1500);
    while (this.list.children.length > KEEP) this.list.lastElementChild.remove();
    this.seen += 1;
    this.counter.textContent = String(this.seen);
  }
}
