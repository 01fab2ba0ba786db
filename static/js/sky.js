// Candidate view: the sky section of one candidate (GET .../candidates/{rank}) on a canvas.
// Stars sized by magnitude, the pattern points over their matched stars with exaggerated
// residual vectors, the generating edge, star names, constellation and planet labels.
import { $ } from "./dom.js";

// Residual vectors are drawn this many times longer than they are, chosen from 1-2-5 steps so
// the longest one is about TARGET_RESIDUAL_CSS canvas pixels.
const TARGET_RESIDUAL_CSS = 28;

export function exaggeration(points, scale) {
  const longest = Math.max(0, ...points.filter((p) => p.residual_x !== null)
    .map((p) => Math.hypot(p.residual_x, p.residual_y) * scale));
  if (longest <= 0) return 1;
  const raw = TARGET_RESIDUAL_CSS / longest;
  const decade = 10 ** Math.floor(Math.log10(raw));
  const step = [1, 2, 5, 10].find((s) => s * decade >= raw * 0.999) * decade;
  return Math.max(1, step);
}

export function starRadius(mag) {
  // Brighter (smaller mag) stars are bigger: about 7 px at mag 0 down to 1 px at mag 6.5.
  return Math.max(1, 7 - mag * 0.95);
}

export function drawSky(canvas, view, options) {
  const ctx = canvas.getContext("2d");
  const sky = view.sky;
  const b = sky.bounds;
  const scale = canvas.width / (b.x_max - b.x_min);
  canvas.height = Math.round((b.y_max - b.y_min) * scale);
  const P = (x, y) => [(x - b.x_min) * scale, (y - b.y_min) * scale];
  ctx.fillStyle = "#05070b";
  ctx.fillRect(0, 0, canvas.width, canvas.height);

  // The sensor, inside the section's margin.
  const [sx0, sy0] = P(-0.5, -0.5);
  const [sx1, sy1] = P(sky.sensor.width - 0.5, sky.sensor.height - 0.5);
  ctx.strokeStyle = "#2f3b4d"; ctx.lineWidth = 1; ctx.setLineDash([6, 4]);
  ctx.strokeRect(sx0, sy0, sx1 - sx0, sy1 - sy0);
  ctx.setLineDash([]);

  if (options.constellations) {
    ctx.font = "600 13px system-ui, sans-serif";
    ctx.fillStyle = "rgba(120,160,220,0.55)";
    for (const c of sky.constellations) {
      if (c.x === null || c.y === null) continue;
      const [cx, cy] = P(c.x, c.y);
      ctx.fillText(c.constellation, cx - 12, cy - 12);
    }
  }

  ctx.font = "11px system-ui, sans-serif";
  for (const s of sky.stars) {
    if (s.x === null || s.y === null) continue;
    const [cx, cy] = P(s.x, s.y);
    ctx.fillStyle = s.matched ? "#ffd43b" : "#e6ebf2";
    ctx.beginPath(); ctx.arc(cx, cy, starRadius(s.mag), 0, 2 * Math.PI); ctx.fill();
    if (options.names && s.name) {
      ctx.fillStyle = s.matched ? "#ffe8a3" : "#9fb0c4";
      ctx.fillText(s.name, cx + starRadius(s.mag) + 3, cy + 4);
    }
  }

  for (const p of sky.planets) {
    if (p.x === null || p.y === null) continue;
    const [cx, cy] = P(p.x, p.y);
    ctx.strokeStyle = "#ff922b"; ctx.lineWidth = 2;
    ctx.beginPath(); ctx.arc(cx, cy, 8, 0, 2 * Math.PI); ctx.stroke();
    ctx.fillStyle = "#ff922b"; ctx.font = "600 12px system-ui, sans-serif";
    ctx.fillText(p.name, cx + 10, cy - 8);
  }

  if (options.edge && sky.generating_edge) {
    const [a, c] = sky.generating_edge.points;
    if (a.x !== null && c.x !== null) {
      const [ax, ay] = P(a.x, a.y), [cx, cy] = P(c.x, c.y);
      ctx.strokeStyle = "#cc5de8"; ctx.lineWidth = 2; ctx.setLineDash([8, 5]);
      ctx.beginPath(); ctx.moveTo(ax, ay); ctx.lineTo(cx, cy); ctx.stroke();
      ctx.setLineDash([]);
    }
  }

  const factor = exaggeration(sky.pattern_points, scale);
  for (const p of sky.pattern_points) {
    if (p.x === null || p.y === null) continue;
    const [cx, cy] = P(p.x, p.y);
    const matched = p.hip !== null || p.planet !== null;
    ctx.strokeStyle = matched ? "#3fb950" : "#ff6b6b"; ctx.lineWidth = 1.6;
    ctx.beginPath(); ctx.arc(cx, cy, 9, 0, 2 * Math.PI); ctx.stroke();
    if (p.residual_x !== null) {
      ctx.strokeStyle = "#63e6be"; ctx.lineWidth = 2;
      ctx.beginPath(); ctx.moveTo(cx, cy);
      ctx.lineTo(cx + p.residual_x * factor * scale, cy + p.residual_y * factor * scale); ctx.stroke();
    }
  }
  return factor;
}

export function candidateFacts(view) {
  const c = view.candidate;
  const rows = [
    ["rank", `${view.rank} of ${view.n_candidates}`],
    ["status", view.status],
    ["deviation", c.deviation_arcsec === null ? "-" : `${c.deviation_arcsec.toFixed(1)}″ (${(c.deviation_px_per_point ?? NaN).toFixed(3)} px/point)`],
    ["false match", c.false_match_probability === null ? "-" : c.false_match_probability.toExponential(2)],
    ["matched", `${c.n_matched ?? c.matches.length} of ${view.sky.pattern_points.length} points`],
    ["RA, Dec", `${c.ra_deg.toFixed(4)}°, ${c.dec_deg.toFixed(4)}°`],
    ["roll", `${c.roll_deg.toFixed(4)}°`],
    ["field", `${view.sky.center.constellation}, ${view.reference_time}`],
  ];
  return rows;
}

export const skyCanvas = () => $("sky-canvas");
