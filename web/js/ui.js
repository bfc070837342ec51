// DOM helpers for the side panel: elements, labelled sliders and pickers, colour conversion
// between the API's linear RGB and the colour input's sRGB hex.

import { srgbOetf, srgbEotf } from "./math.js";

/** el("div", {class: "x", onclick: f}, child, "text", ...) */
export function el(tag, attrs = {}, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (v === undefined || v === null || v === false) continue;
    if (k.startsWith("on")) e.addEventListener(k.slice(2), v);
    else if (k === "class") e.className = v;
    else if (k === "text") e.textContent = v;
    else if (k in e && typeof v !== "string") e[k] = v;
    else e.setAttribute(k, v === true ? "" : v);
  }
  for (const c of children.flat()) {
    if (c === null || c === undefined || c === false) continue;
    e.append(c instanceof Node ? c : document.createTextNode(String(c)));
  }
  return e;
}

/**
 * A labelled range input with a live read-out. `opts`: { id, label, min, max, step, value,
 * format(v), oninput(v), title }.
 */
export function slider(opts) {
  const out = el("output", { class: "val" }, opts.format(opts.value));
  const input = el("input", {
    type: "range", id: opts.id, min: opts.min, max: opts.max, step: opts.step,
    value: String(opts.value), title: opts.title,
    "aria-label": opts.label,
  });
  input.addEventListener("input", (ev) => {
    const v = parseFloat(input.value);
    out.textContent = opts.format(v);
    opts.oninput(v, ev);
  });
  const row = el("label", { class: "row slider" }, el("span", { class: "lab" }, opts.label), input, out);
  row.set = (v) => {
    input.value = String(v);
    out.textContent = opts.format(v);
  };
  row.input = input;
  return row;
}

/** A labelled select. `options`: [[value, text], ...]. */
export function picker(opts) {
  const sel = el("select", { id: opts.id, "aria-label": opts.label, title: opts.title },
    opts.options.map(([v, t]) => el("option", { value: v }, t)));
  sel.value = opts.value;
  sel.addEventListener("change", () => opts.onchange(sel.value));
  const row = el("label", { class: "row" }, el("span", { class: "lab" }, opts.label), sel);
  row.select = sel;
  return row;
}

/** Three number inputs for a vector; `onchange(v)` on edit. */
export function vec3Input(label, value, onchange, step = 0.01) {
  const inputs = value.map((x, k) => {
    const i = el("input", { type: "number", step: String(step), value: fmt(x), "aria-label": `${label} ${"xyz"[k]}` });
    i.addEventListener("change", () => {
      const v = inputs.map((j) => parseFloat(j.value));
      if (v.every(Number.isFinite)) onchange(v);
    });
    return i;
  });
  const row = el("div", { class: "row vec" }, el("span", { class: "lab" }, label), el("span", { class: "xyz" }, inputs));
  row.set = (v) => v.forEach((x, k) => {
    if (document.activeElement !== inputs[k]) inputs[k].value = fmt(x);
  });
  return row;
}

export const fmt = (x) => (Math.abs(x) < 1e-9 ? "0" : (+x.toFixed(3)).toString());

/** Linear RGB (any scale) → {hex of the normalised colour, scalar = max channel}. */
export function splitColour(rgb) {
  const m = Math.max(rgb[0], rgb[1], rgb[2]);
  if (!(m > 0)) return { hex: "#ffffff", power: 0 };
  const hex = "#" + rgb.map((c) => Math.round(srgbOetf(c / m) * 255).toString(16).padStart(2, "0")).join("");
  return { hex, power: m };
}

/** sRGB hex and a scalar → linear RGB. */
export function joinColour(hex, power) {
  const c = [1, 3, 5].map((i) => srgbEotf(parseInt(hex.slice(i, i + 2), 16) / 255));
  const m = Math.max(...c);
  return m > 0 ? c.map((x) => (x / m) * power) : [power, power, power];
}

/** A log-scale slider position (log10) ↔ value. */
export const logPos = (v) => Math.log10(Math.max(v, 1e-6));
export const fromLogPos = (p) => Math.pow(10, p);

export function download(name, blob) {
  const a = el("a", { href: URL.createObjectURL(blob), download: name });
  document.body.append(a);
  a.click();
  setTimeout(() => {
    URL.revokeObjectURL(a.href);
    a.remove();
  }, 1000);
}
