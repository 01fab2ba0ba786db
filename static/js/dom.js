// Small DOM helpers shared by the console modules.

export const $ = (id) => document.getElementById(id);

// el("li", {class: "x", onclick: f}, "text", child, ...): an element with attributes and children.
export function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [key, value] of Object.entries(attrs)) {
    if (value === undefined || value === null || value === false) continue;
    if (key.startsWith("on")) node.addEventListener(key.slice(2), value);
    else if (key === "class") node.className = value;
    else if (key === "dataset") Object.assign(node.dataset, value);
    else node.setAttribute(key, value === true ? "" : value);
  }
  for (const child of children.flat()) {
    if (child === null || child === undefined || child === false) continue;
    node.append(child instanceof Node ? child : String(child));
  }
  return node;
}

let toastTimer = null;
// Show the result of an action (kind "ok" or "error") for a few seconds; errors stay longer.
export function toast(message, kind = "ok") {
  const box = $("toast");
  box.textContent = message;
  box.className = `toast ${kind}`;
  box.hidden = false;
  clearTimeout(toastTimer);
  toastTimer = setTimeout(() => { box.hidden = true; }, kind === "error" ? 9000 : 3500);
}

export function errorText(err) {
  if (!err) return "unknown error";
  const lines = [err.detail || err.message || String(err)];
  for (const p of err.problems || []) lines.push(`${p.location}: ${p.message}`);
  return lines.join("\n");
}

// A colour per track id, spread around the hue circle by the golden angle.
export function trackColour(track, alpha = 1) {
  const hue = (track * 137.508) % 360;
  return `hsla(${hue.toFixed(1)}, 85%, 62%, ${alpha})`;
}

export const fmt = (value, digits = 3) => (value === null || value === undefined || Number.isNaN(value))
  ? "-" : Number(value).toFixed(digits);

export function fmtTime(text) {
  return text ? text.replace("T", " ").replace(/\.\d+Z$/, "Z") : "-";
}
