// A menu button: the keyboard and pointer alternative to a gesture ("Move to node ▸",
// "Link to ▸"). Click, Enter, Space or ArrowDown opens it; the arrows move between its
// items, Enter picks one, Escape closes it and gives the focus back to its button.

import {h} from "./dom.js";

/**
 * label: the button's text; items(): [{label, act, disabled?, title?}], asked each time
 * the menu opens (so it lists what is true then); empty: what to say when there is none.
 */
export function menuButton(label, items, {empty = "nothing to choose", name = label} = {}) {
  const button = h("button", {type: "button", class: "small menu-button", "aria-haspopup": "menu",
                              "aria-expanded": "false", dataset: {menu: name}}, label);
  const list = h("ul", {class: "menu", role: "menu", hidden: true, "aria-label": name});
  const wrap = h("div", {class: "menu-wrap"}, [button, list]);
  const entries = () => [...list.querySelectorAll("[role=menuitem]:not([disabled])")];
  const outside = (ev) => { if (!wrap.contains(ev.target)) close(false); };
  const close = (refocus) => {
    if (list.hidden) return;
    list.hidden = true;
    button.setAttribute("aria-expanded", "false");
    document.removeEventListener("pointerdown", outside, true);
    if (refocus) button.focus();
  };
  const open = () => {
    const choices = items();
    list.replaceChildren(...(choices.length ? choices.map((item) => h("li", {role: "none"},
      h("button", {type: "button", role: "menuitem", class: "menu-item", disabled: item.disabled,
                   title: item.title, dataset: {value: item.value ?? item.label},
                   onclick: () => { close(true); item.act(); }}, item.label)))
      : [h("li", {role: "none", class: "muted menu-empty"}, empty)]));
    list.hidden = false;
    button.setAttribute("aria-expanded", "true");
    document.addEventListener("pointerdown", outside, true);
    entries()[0]?.focus();
  };
  button.addEventListener("click", () => (list.hidden ? open() : close(true)));
  button.addEventListener("keydown", (ev) => {
    if (ev.key === "ArrowDown" && list.hidden) { ev.preventDefault(); open(); }
  });
  list.addEventListener("keydown", (ev) => {
    const all = entries(), at = all.indexOf(document.activeElement);
    if (ev.key === "ArrowDown" || ev.key === "ArrowUp") {
      ev.preventDefault();
      const step = ev.key === "ArrowDown" ? 1 : -1;
      all[(at + step + all.length) % all.length]?.focus();
    } else if (ev.key === "Home" || ev.key === "End") {
      ev.preventDefault();
      (ev.key === "Home" ? all[0] : all.at(-1))?.focus();
    } else if (ev.key === "Escape") {
      ev.preventDefault();
      ev.stopPropagation();                 // closes the menu, not the inspector
      close(true);
    } else if (ev.key === "Tab") {
      close(false);
    }
  });
  return wrap;
}
