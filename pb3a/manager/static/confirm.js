// Asking before something that cannot be undone (removing a module): a modal dialog
// that keeps the focus, answers true only for its confirm button, and starts on Cancel
// so that a stray Enter changes nothing.

import {h} from "./dom.js";

/** Resolves to true when the user confirms, false on Cancel, Escape or a click outside. */
export function confirmAction(title, detail, confirmLabel) {
  const cancel = h("button", {type: "button", class: "ghost", value: "cancel"}, "Cancel");
  const ok = h("button", {type: "button", class: "danger", value: "ok"}, confirmLabel);
  const dialog = h("dialog", {class: "confirm", "aria-label": title}, [
    h("h2", {}, title),
    detail ? h("p", {class: "muted"}, detail) : null,
    h("div", {class: "row-actions"}, [cancel, ok]),
  ]);
  document.body.append(dialog);
  return new Promise((resolve) => {
    const finish = (answer) => { dialog.close(); dialog.remove(); resolve(answer); };
    cancel.addEventListener("click", () => finish(false));
    ok.addEventListener("click", () => finish(true));
    dialog.addEventListener("cancel", (ev) => { ev.preventDefault(); finish(false); });
    dialog.addEventListener("click", (ev) => { if (ev.target === dialog) finish(false); });
    dialog.showModal();
    cancel.focus();
  });
}
