// The camera calibration card: the spacecraft's current calibration (GET /api/spacecraft/{name}/calibrations),
// a button that fits a new one from the archive (POST .../calibrate), and the residual map over the
// sensor: the mean measured-minus-predicted vector of the stars in each cell, with the declared camera
// (orange) and with the fitted one (green), drawn exaggerated so a pixel shows.
import * as api from "./api.js";
import { $, el, fmt, fmtTime } from "./dom.js";

const COLOURS = { before: "#ff922b", after: "#3fb950", sensor: "#5c6b80", text: "#9fb0c4" };

let spacecraft = null;

// The card follows the spacecraft of the sequence shown.
export async function showCalibration(name) {
  spacecraft = name || null;
  $("calibration-card").hidden = !spacecraft;
  if (!spacecraft) return;
  $("calibration-spacecraft").textContent = spacecraft;
  // The history (200 even when empty) rather than .../camera (404 without a calibration): the newest is current.
  const history = await api.get(`/api/spacecraft/${encodeURIComponent(spacecraft)}/calibrations`);
  render(history.length ? history[history.length - 1] : null);
}

export async function calibrate(operator) {
  if (!spacecraft) return null;
  const doc = await api.post(`/api/spacecraft/${encodeURIComponent(spacecraft)}/calibrate`, { operator: operator || null });
  render(doc);
  return doc;
}

function render(doc) {
  const facts = $("calibration-facts");
  const canvas = $("residual-canvas");
  canvas.hidden = !doc?.residual_map;
  $("residual-legend").hidden = !doc?.residual_map;
  if (!doc) {
    facts.replaceChildren(el("p", { class: "dim" }, "No calibration yet: files of this spacecraft without a camera block " +
      "use the default camera. Calibrate once a few sequences are identified or confirmed."));
    return;
  }
  const rows = Object.entries(doc.sigma).map(([name, sigma]) =>
    el("tr", {}, el("td", {}, name), el("td", { class: "num" }, fmt(doc.camera[name], name === "k1" || name === "k2" ? 5 : 2)),
      el("td", { class: "num dim" }, `± ${fmt(sigma, 3)}`)));
  facts.replaceChildren(
    el("p", {}, `version ${doc.version} · ${doc.operator || "anonymous"} · ${fmtTime(doc.created_at)}`),
    el("p", { class: "dim" }, `${doc.sequences_used} sequences, ${doc.stars_used} stars (${doc.stars_rejected} rejected); ` +
      `rms ${fmt(doc.rms_px_before, 2)} px with the declared camera → ${fmt(doc.rms_px_after, 2)} px`),
    el("table", { class: "calibration" }, el("tbody", {}, rows)),
    ...(doc.notes || []).map((note) => el("p", { class: "dim" }, note)));
  if (doc.residual_map) drawResiduals(canvas, doc.residual_map);
}

// Arrows from each cell's centre, the same exaggeration for both so they compare.
export function drawResiduals(canvas, map) {
  const ctx = canvas.getContext("2d");
  const scale = Math.min(canvas.width / map.width, canvas.height / map.height);
  const ox = (canvas.width - map.width * scale) / 2, oy = (canvas.height - map.height * scale) / 2;
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  ctx.strokeStyle = COLOURS.sensor;
  ctx.strokeRect(ox, oy, map.width * scale, map.height * scale);
  const longest = Math.max(1e-9, ...map.cells.map((c) => Math.hypot(c.dx_before, c.dy_before)),
    ...map.cells.map((c) => Math.hypot(c.dx_after, c.dy_after)));
  const cell = Math.min(map.width / map.columns, map.height / map.rows) * scale;
  const factor = (0.45 * cell) / longest;  // the longest arrow fills about half a cell
  for (const c of map.cells) {
    const x = ox + (c.x + 0.5) * scale, y = oy + (c.y + 0.5) * scale;
    arrow(ctx, x, y, c.dx_before * factor, c.dy_before * factor, COLOURS.before);
    arrow(ctx, x, y, c.dx_after * factor, c.dy_after * factor, COLOURS.after);
  }
  $("residual-legend").textContent = `arrows ×${fmt(factor / scale, 0)}: orange with the declared camera, ` +
    `green with the calibrated one`;
  canvas.dataset.factor = String(factor / scale);
}

function arrow(ctx, x, y, dx, dy, colour) {
  const length = Math.hypot(dx, dy);
  ctx.strokeStyle = ctx.fillStyle = colour;
  ctx.lineWidth = 1.5;
  ctx.beginPath(); ctx.moveTo(x, y); ctx.lineTo(x + dx, y + dy); ctx.stroke();
  if (length < 3) return;
  const ux = dx / length, uy = dy / length, head = Math.min(6, length / 2);
  ctx.beginPath();
  ctx.moveTo(x + dx, y + dy);
  ctx.lineTo(x + dx - head * (ux - 0.5 * uy), y + dy - head * (uy + 0.5 * ux));
  ctx.lineTo(x + dx - head * (ux + 0.5 * uy), y + dy - head * (uy - 0.5 * ux));
  ctx.closePath(); ctx.fill();
}
