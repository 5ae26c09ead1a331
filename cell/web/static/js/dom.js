// Building the page's markup from script: text always goes in as text (never parsed as HTML), so nothing
// the cell returns (a termination reason, a log line, a file name) can inject markup.

/** An element: `h("a", {href: "#/", class: "x", onclick: f}, "text", child, ...)`. Attributes that are
 *  false, null or undefined are left out; `on<event>` ones become listeners. */
export function h(tag, attrs = {}, ...children) {
  const element = document.createElement(tag);
  for (const [name, value] of Object.entries(attrs || {})) {
    if (value === false || value === null || value === undefined) continue;
    if (name.startsWith("on") && typeof value === "function") {
      element.addEventListener(name.slice(2), value);
    } else {
      element.setAttribute(name, value === true ? "" : String(value));
    }
  }
  append(element, children);
  return element;
}

/** Append children (elements, text, arrays of them; null and false skipped). */
export function append(parent, children) {
  for (const child of children.flat(Infinity)) {
    if (child === null || child === undefined || child === false) continue;
    parent.append(child instanceof Node ? child : document.createTextNode(String(child)));
  }
  return parent;
}

/** Replace an element's children. */
export function replace(parent, ...children) {
  parent.replaceChildren();
  return append(parent, children);
}

/** A number with `digits` decimals and its unit, or "–" when there is none. */
export function fmt(value, digits = 3, unit = "") {
  if (value === null || value === undefined || Number.isNaN(value)) return "–";
  return `${Number(value).toFixed(digits)}${unit ? ` ${unit}` : ""}`;
}

/** A byte count for people. */
export function bytes(n) {
  if (n < 1024) return `${n} B`;
  if (n < 1024 ** 2) return `${(n / 1024).toFixed(1)} kB`;
  return `${(n / 1024 ** 2).toFixed(1)} MB`;
}

/** A date-time of the API in the browser's local time (`short`: date and minutes, compactly). */
export function when(iso, short = false) {
  if (!iso) return "–";
  return new Date(iso).toLocaleString(undefined, short ? { dateStyle: "short", timeStyle: "short" } : {});
}
