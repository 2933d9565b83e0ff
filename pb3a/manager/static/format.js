// How figures read on the page: rates, durations, bytes, percentages, times of day.

export function rate(perSecond) {
  if (perSecond === null || perSecond === undefined) return "–";
  if (perSecond >= 1000) return `${(perSecond / 1000).toFixed(1)}k/s`;
  if (perSecond >= 10) return `${perSecond.toFixed(0)}/s`;
  return `${perSecond.toFixed(1)}/s`;
}

export function seconds(value) {
  if (value === null || value === undefined || Number.isNaN(value)) return "–";
  if (value < 1e-3) return `${(value * 1e6).toFixed(0)} µs`;
  if (value < 1) return `${(value * 1e3).toFixed(value < 0.01 ? 2 : 1)} ms`;
  return `${value.toFixed(2)} s`;
}

// A call this long is shown beside a module's status, as `pb3a status` shows it.
const LONG_CALL_S = 1;

/** "in step for 12 s" for a module in a call that has lasted a second or more, else "". */
export function longCall(module) {
  return module?.calling && module.calling_s >= LONG_CALL_S
    ? `in ${module.calling} for ${module.calling_s.toFixed(0)} s` : "";
}

export function bytes(value) {
  if (value === null || value === undefined) return "–";
  const units = ["B", "KiB", "MiB", "GiB", "TiB"];
  let i = 0;
  while (value >= 1024 && i < units.length - 1) { value /= 1024; i += 1; }
  return `${value.toFixed(value >= 10 || i === 0 ? 0 : 1)} ${units[i]}`;
}

/** Bytes in GiB, with one decimal below 10. */
export function gib(value) {
  const g = value / 2 ** 30;
  return g >= 10 ? g.toFixed(0) : g.toFixed(1);
}

export function percent(value) {
  return value === null || value === undefined ? "–" : `${value.toFixed(0)}%`;
}

export function count(value) {
  if (value >= 1e6) return `${(value / 1e6).toFixed(1)}M`;
  if (value >= 1e4) return `${(value / 1e3).toFixed(0)}k`;
  return String(value);
}

export function clock(epochSeconds) {
  return new Date(epochSeconds * 1000).toLocaleTimeString([], {hour12: false});
}

/** A number as a field shows it: short, but every digit a user typed survives. */
export function number(value) {
  if (value === null || value === undefined) return "";
  if (Number.isInteger(value)) return String(value);
  return Math.abs(value) >= 1e5 || (Math.abs(value) < 1e-3 && value !== 0)
    ? value.toExponential(4) : String(Number(value.toPrecision(6)));
}

const SPECIAL = new Map([["inf", Infinity], ["+inf", Infinity], ["-inf", -Infinity],
                         ["infinity", Infinity], ["+infinity", Infinity],
                         ["-infinity", -Infinity], ["nan", NaN]]);

/** The number typed in a field: a decimal, or inf, -inf, nan (as a field shows them);
 * undefined when the text is no number. */
export function parseNumber(text) {
  const typed = String(text).trim().toLowerCase();
  if (SPECIAL.has(typed)) return SPECIAL.get(typed);
  const value = Number(typed);
  return typed === "" || !Number.isFinite(value) ? undefined : value;
}

/** An axis label: three significant digits. */
export function tick(value) {
  return Math.abs(value) >= 1e4 || (Math.abs(value) < 1e-2 && value !== 0)
    ? value.toExponential(1) : String(Number(value.toPrecision(3)));
}

/** The part of a "package.module:Class" name a person looks for first. */
export function shortClass(cls) {
  if (!cls) return "";
  const [module, name] = cls.includes(":") ? cls.split(":") : ["", cls];
  return name || module.split(".").pop();
}

/** The last part of a module path ("robot/mapper" -> "mapper"). */
export function leaf(name) {
  return name.split("/").pop();
}
