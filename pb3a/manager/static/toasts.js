// Messages that come and go in a corner: what an action did, and errors from the API in
// words a user can act on (with the server's list of problems).

import {h} from "./dom.js";

export class Toasts {
  constructor(root) {
    this.root = root;
  }

  /** tone: "ok" | "error" | "info"; actions: [[label, callback, "danger"?], ...] */
  show(tone, title, {lines = [], actions = [], seconds = tone === "error" ? 12 : 5} = {}) {
    const close = h("button", {class: "icon ghost", type: "button", title: "dismiss"}, "✕");
    const toast = h("div", {class: `toast ${tone}`, role: tone === "error" ? "alert" : "status"}, [
      h("div", {class: "toast-head"}, [h("strong", {}, title), close]),
      lines.length ? h("ul", {}, lines.map((line) => h("li", {}, line))) : null,
      actions.length ? h("div", {class: "row-actions"}, actions.map(([label, act, style = ""]) =>
        h("button", {type: "button", class: `small ${style}`.trim(), onclick: () => { remove(); act(); }}, label))) : null,
    ]);
    const remove = () => toast.remove();
    close.addEventListener("click", remove);
    this.root.append(toast);
    while (this.root.children.length > 5) this.root.firstElementChild.remove();
    if (seconds) setTimeout(remove, seconds * 1000);
    return toast;
  }

  error(error, actions = []) {
    const problems = (error.problems || []).filter((p) => p !== error.message);
    return this.show("error", error.message || String(error), {lines: problems, actions});
  }
}
