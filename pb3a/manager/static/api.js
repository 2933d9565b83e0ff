// The manager's HTTP API, as the page uses it: JSON in and out, errors as ApiError.
// The token travels in the HttpOnly cookie set by GET /?token=..., so no header is needed.

/** A refused or failed request: the server's message, its problems and status. */
export class ApiError extends Error {
  constructor(status, message, problems) {
    super(message);
    this.status = status;
    this.problems = problems || [];
  }
}

// JSON has no inf or nan: such a float travels as {"$float": "inf"} ("-inf", "nan"),
// TOML's words for it, both ways (as a number it was written null, which drops a key)
const NON_FINITE = "$float";

/** `value` as JSON text, a float that is not finite as {"$float": "inf"}. */
export function toJson(value) {
  return JSON.stringify(value, (key, item) => (typeof item === "number" && !Number.isFinite(item)
    ? {[NON_FINITE]: Number.isNaN(item) ? "nan" : item > 0 ? "inf" : "-inf"} : item));
}

/** JSON text as values, {"$float": "inf"} as Infinity (and -Infinity, NaN). */
export function fromJson(text) {
  return JSON.parse(text, (key, item) => {
    if (item === null || typeof item !== "object" || Array.isArray(item)) return item;
    const keys = Object.keys(item);
    if (keys.length !== 1 || keys[0] !== NON_FINITE) return item;
    return {inf: Infinity, "-inf": -Infinity, nan: NaN}[item[NON_FINITE]] ?? item;
  });
}

// A text shown to a person writes such a float as TOML does, a bare word. This mark
// stands for one while JSON.stringify writes the text; it begins with a NUL, which
// nobody types
const WORD_MARK = "\u0000pb3a-float:";

/** `value` as JSON text for a person to read or edit, a float that is not finite as
 * TOML writes it (inf, -inf, nan): JSON.stringify wrote it null, and an edited list
 * of them went back as nulls. `fromEditableJson` reads it back. */
export function toEditableJson(value, indent) {
  const text = JSON.stringify(value, (key, item) => (typeof item === "number" && !Number.isFinite(item)
    ? WORD_MARK + (Number.isNaN(item) ? "nan" : item > 0 ? "inf" : "-inf") : item), indent);
  return text === undefined ? text
    : text.replace(/"\\u0000pb3a-float:(-?inf|nan)"/g, (mark, word) => word);
}

/** JSON text, with inf, -inf and nan as bare words (outside strings), as values. */
export function fromEditableJson(text) {
  // strings are matched whole first, so a word inside one is left as it is
  return fromJson(text.replace(/"(?:[^"\\]|\\.)*"|(-?\binf\b|\bnan\b)/g,
    (match, word) => (word ? toJson(word === "nan" ? NaN : word === "inf" ? Infinity : -Infinity) : match)));
}

const TIMEOUT_MS = 30000;   // a migration or a launch may take seconds, never this long

async function request(method, path, body) {
  const controller = new AbortController();
  const timer = setTimeout(() => controller.abort(), TIMEOUT_MS);
  let response;
  try {
    response = await fetch(path, {
      method,
      credentials: "same-origin",
      signal: controller.signal,
      headers: body === undefined ? {} : {"Content-Type": "application/json"},
      body: body === undefined ? undefined : toJson(body),
    });
  } catch (error) {
    const why = error.name === "AbortError" ? `no answer in ${TIMEOUT_MS / 1000} s`
                                            : "the manager cannot be reached";
    throw new ApiError(0, `${method} ${path}: ${why}`);
  } finally {
    clearTimeout(timer);
  }
  const type = response.headers.get("Content-Type") || "";
  const text = await response.text();
  const payload = type.includes("json") ? fromJson(text) : text;
  if (!response.ok) {
    const message = (payload && payload.error) || `${method} ${path}: HTTP ${response.status}`;
    throw new ApiError(response.status, message, payload && payload.problems);
  }
  return payload;
}

const q = (name) => encodeURIComponent(name).replaceAll("%2F", "/");

export const api = {
  system: () => request("GET", "/api/system"),
  layout: () => request("GET", "/api/layout"),
  stats: () => request("GET", "/api/stats"),
  classes: () => request("GET", "/api/classes"),
  state: (name, path = "") =>
    request("GET", `/api/modules/${q(name)}/state${path ? `?path=${encodeURIComponent(path)}` : ""}`),
  setState: (name, fields) => request("POST", `/api/modules/${q(name)}/state`, fields),
  keepOffer: (name) => request("GET", `/api/modules/${q(name)}/keep`),
  keep: (name, fields, revision) => request("POST", `/api/modules/${q(name)}/keep`, {fields, revision}),
  migrate: (name, to) => request("POST", `/api/modules/${q(name)}/migrate`, {to}),
  swaps: (name) => request("GET", `/api/modules/${q(name)}/swaps`),
  swap: (name, cls) => request("POST", `/api/modules/${q(name)}/swap`, {class: cls}),
  addModule: (spec) => request("POST", "/api/modules", spec),
  removeModule: (name, force = false) => request("DELETE", `/api/modules/${q(name)}${force ? "?force=1" : ""}`),
  link: (spec) => request("POST", "/api/links", spec),
  reload: (module) => request("POST", "/api/reload", {module}),
  restart: (name) => request("POST", `/api/modules/${q(name)}/restart`, {}),
  document: () => request("GET", "/api/document"),
  putDocument: (system, revision) => request("PUT", "/api/document", {system, revision}),
  open: (name, toml) => request("POST", "/api/document/open", {name, toml}),
  checkLink: (src, dst) => request("POST", "/api/document/check-link", {src, dst}),
  save: (path, overwrite = false) => request("POST", "/api/document/save",
                                             {...(path ? {path} : {}), ...(overwrite ? {overwrite} : {})}),
  launch: () => request("POST", "/api/document/launch", {}),
  stop: () => request("POST", "/api/system/stop", {}),
};

/** The URL of a module's 2-D array as a PNG (the server answers it fresh each time). */
export function imageUrl(path, bust) {
  return `${path}${path.includes("?") ? "&" : "?"}t=${bust}`;
}
