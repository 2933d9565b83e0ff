// A module's ports in the inspector, each with a menu that links it: the keyboard's
// way to do what dragging from an output to an input does.

import {h} from "./dom.js";
import {menuButton} from "./menu.js";

/**
 * name: the module; info: its entry in /api/system; links: the system's links;
 * candidates(dir): [[module, port, spec], ...] the ports of the other direction it may
 * link to; link(src, dst): make the link (checked and refused as a drag's would be).
 */
export function portsPanel(name, info, links, candidates, link) {
  const rows = [];
  const fed = (end) => links.filter((l) => l.dst === end).map((l) => l.src);
  const feeds = (end) => links.filter((l) => l.src === end).map((l) => l.dst);
  for (const [port, spec] of Object.entries(info.inputs || {})) {
    const end = `${name}.${port}`;
    const from = fed(end);
    rows.push(row("in", port, spec, from.length ? `← ${from.join(", ")}` : "not fed",
      candidates && menuButton("Link from ▸", () => candidates("out").map(([m, p, s]) => ({
        label: `${m}.${p}`, value: `${m}.${p}`, title: s.type, act: () => link(`${m}.${p}`, end)})),
      {empty: "no output to link from", name: `link ${end}`})));
  }
  for (const [port, spec] of Object.entries(info.outputs || {})) {
    const end = `${name}.${port}`;
    const to = feeds(end);
    rows.push(row("out", port, spec, to.length ? `→ ${to.join(", ")}` : "not linked",
      candidates && menuButton("Link to ▸", () => candidates("in").map(([m, p, s]) => ({
        label: `${m}.${p}${fed(`${m}.${p}`).length ? " (fed)" : ""}`, value: `${m}.${p}`,
        title: s.type, act: () => link(end, `${m}.${p}`)})),
      {empty: "no input to link to", name: `link ${end}`})));
  }
  if (!rows.length) return null;
  // closed unless the user opened it last time: the state below keeps its room
  const details = h("details", {class: "ports", open: portsOpen}, [
    h("summary", {}, [h("span", {class: "ports-title"}, `Ports · ${rows.length}`),
                      h("span", {class: "muted small-text"}, " · their links, as menus")]),
    ...rows]);
  details.addEventListener("toggle", () => { portsOpen = details.open; });
  return details;
}

let portsOpen = false;     // whether the last ports list shown was open

function row(dir, port, spec, peers, menu) {
  return h("div", {class: `port-row ${dir}`, dataset: {port}}, [
    h("span", {class: `chip ${dir}`, title: spec.policy ? `policy ${spec.policy}` : ""}, `${port}: ${spec.type}`),
    h("span", {class: "port-peers muted mono"}, peers),
    menu,
  ]);
}
