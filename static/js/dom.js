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
// Show the result of an action (kind "ok", "warn" or "error") in the status line of the header. The
// status line has its own place in the sticky header, so it never covers a list or a link. A message is
// read where it appears, wrapped: an "ok" whole, up to a few lines (console.css: a longer one scrolls in
// its box), a warning or an error by its first line (further lines, located problems, are in the title
// and the message log), growing the header and staying longer.
// `untilMove`: a message about where the operator is ("Last sequence of this page"), which goes when
// they move (moved()).
export function toast(message, kind = "ok", { untilMove = false } = {}) {
  const box = $("toast");
  box.textContent = kind === "ok" ? message : message.split("\n")[0];
  box.title = message;
  box.className = `toast ${kind}`;
  box.dataset.untilMove = untilMove ? "1" : "";
  box.hidden = false;
  const log = $("message-log");
  if (log) {
    const now = new Date().toISOString();   // UTC, written as every other time of the console (fmtTime)
    log.prepend(el("li", { class: kind }, el("time", { datetime: now }, fmtTime(now)), " ", message));
    while (log.children.length > 30) log.lastChild.remove();
  }
  clearTimeout(toastTimer);
  toastTimer = setTimeout(() => { box.hidden = true; }, kind === "ok" ? 5000 : 12000);
}

// The operator moved to another sequence or candidate: a message about where they were goes with it.
export function moved() {
  const box = $("toast");
  if (!box.dataset.untilMove) return;
  box.dataset.untilMove = "";
  box.hidden = true;
  clearTimeout(toastTimer);
}

// "1 candidate", "3 candidates".
export const plural = (n, word) => `${n} ${word}${n === 1 ? "" : "s"}`;

export function errorText(err) {
  if (!err) return "unknown error";
  const lines = [err.headline || err.detail || err.message || String(err)];
  // A problem the reason already says (a refusal whose reason is its one problem) is not said twice.
  for (const p of err.problems || []) if (!lines[0].includes(p.message)) lines.push(`${p.location}: ${p.message}`);
  return lines.join("\n");
}

// A colour per track id, spread around the hue circle by the golden angle.
export function trackColour(track, alpha = 1) {
  const hue = (track * 137.508) % 360;
  return `hsla(${hue.toFixed(1)}, 85%, 62%, ${alpha})`;
}

// Where a w×h label of a marker of radius r at (cx, cy) goes on a canvas `width` wide: the box's top-left
// corner. Beside the marker's upper right as usual (`gap` from it, its bottom `above` the centre); a source
// at the sensor's edge would have its name cut there, so the label goes to the marker's left when it runs
// past the right edge and below the marker when it runs past the top.
export function placeLabel({ cx, cy, r, w, h, width, gap = 2, above = 0 }) {
  let x = cx + r + gap, y = cy - above - h;
  if (x + w > width) x = cx - r - gap - w;
  if (y < 0) y = cy + r + gap;
  return { x, y, w, h };
}

export const fmt = (value, digits = 3) => (value === null || value === undefined || Number.isNaN(value))
  ? "-" : Number(value).toFixed(digits);

// A probability as an operator reads it: 5.3e-27, 0.013, 1.
export function fmtProbability(p) {
  if (p === null || p === undefined) return "-";
  if (p === 0) return "0";
  return p >= 0.001 ? String(Number(p.toPrecision(2))) : p.toExponential(1);
}

export function fmtTime(text) {
  return text ? text.replace("T", " ").replace(/\.\d+Z$/, "Z") : "-";
}

// A time of a sequence whose frames carried none (its telemetry's time_assumed): solved at an assumed time,
// J2000.0 and 1 s apart, which is said wherever a time of it is shown, never passed off as the observation's.
export const ASSUMED_TIME = "assumed: the frames carried no time; stars at mean places, no planets";
export function sequenceTime(text, telemetry) {
  return telemetry?.time_assumed ? `${text} (${ASSUMED_TIME})` : text;
}

// A snapshot named as the CLI and the API name it: by its 0-based position in the file (snapshots[2],
// "reference_snapshot": 2), which is also its "index" in files numbered from 0. Given the sequence's
// telemetry snapshots, `count` adds its position in words that cannot be taken for the index, and a file
// numbering its snapshots otherwise has that index said too: "snapshot 2 (3 of 16, reference)".
export function snapshotName(position, { snapshots = null, reference = null, count = false } = {}) {
  const fileIndex = snapshots?.[position]?.index;
  const notes = [count && snapshots ? `${position + 1} of ${snapshots.length}` : null,
    position === reference ? "reference" : null,
    fileIndex !== undefined && fileIndex !== null && fileIndex !== position ? `index ${fileIndex} in the file` : null];
  const said = notes.filter(Boolean);
  return `snapshot ${position}${said.length ? ` (${said.join(", ")})` : ""}`;
}

// Browser storage that never throws (private windows, disabled storage): the console still works.
export function stored(storage, key, fallback = null) {
  try { const v = storage.getItem(key); return v === null ? fallback : v; } catch { return fallback; }
}
export function store(storage, key, value) {
  try { storage.setItem(key, value); } catch { /* not kept: only a convenience */ }
}
