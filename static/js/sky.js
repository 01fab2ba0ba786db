// Candidate view: the sky section of one candidate (GET .../candidates/{rank}) on a canvas.
// Stars sized by magnitude, the pattern points over their matched stars with exaggerated
// residual vectors and their track labels (T3, the player's names), the generating edge,
// star, planet and constellation labels placed so that none overlaps another nor comes near a
// point's circle, and north and east arrows. A point whose circle would be cut by the canvas edge
// is drawn whole, pinned inside it, with an arrow to where it lies. drawSky returns what it drew so the page can explain it (tooltips, clicks).
import { trackColour } from "./dom.js";

// Residual vectors are drawn this many times longer than they are, chosen from 1-2-5 steps so
// the longest one is about TARGET_RESIDUAL_CSS canvas pixels.
const TARGET_RESIDUAL_CSS = 28;
export const POINT_RADIUS = 9;
// Every label but a point's own keeps this far (canvas pixels) from a pattern point's circle: the circle's
// stroke (3.5 px wide when ringed) and a gap that reads as one. Box-to-box tests let a constellation's name sit
// on the circle's rim ("Lyn" touching T3 in 05-earth).
export const CIRCLE_CLEARANCE = 4;
// A point whose circle would not fit whole on the canvas (off the sensor, past the section's margin: a track
// seen only in other snapshots, carried to the reference one) is drawn pinned this far inside the canvas
// edge, its rim leaving room for an arrow towards where it lies.
export const PIN_ROOM = 10;
export const COLOURS = {
  matched: "#3fb950", doubtful: "#e3b341", unmatched: "#ff6b6b", residual: "#63e6be", edge: "#cc5de8",
  planet: "#ff922b", star: "#e6ebf2", matchedStar: "#ffd43b", compass: "#9ec5fe",
};

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

// Image directions of celestial north and east at the boresight, as unit [dx, dy] in pixels
// (x right, y down), from the candidate's rotation R (ICRS -> camera, rows = camera axes).
// North is the great circle towards the pole, east = pole x boresight (towards growing RA).
export function northEast(R) {
  const b = R[2];
  const pole = [0, 0, 1];
  const dot = (u, v) => u[0] * v[0] + u[1] * v[1] + u[2] * v[2];
  const north = pole.map((p, i) => p - dot(pole, b) * b[i]);
  const east = [pole[1] * b[2] - pole[2] * b[1], pole[2] * b[0] - pole[0] * b[2], pole[0] * b[1] - pole[1] * b[0]];
  const image = (v) => {
    const x = dot(R[0], v), y = dot(R[1], v), n = Math.hypot(x, y);
    return n > 1e-9 ? [x / n, y / n] : null;   // null: the boresight is at a pole, no north
  };
  return { north: image(north), east: image(east) };
}

// Whether box b (x, y, w, h) overlaps obstacle o: a box like it, or a circle {cx, cy, r}, which a box
// overlaps when its nearest point is closer than r to the centre.
export function blocks(o, b) {
  if (o.r === undefined) return o.x < b.x + b.w && b.x < o.x + o.w && o.y < b.y + b.h && b.y < o.y + o.h;
  const dx = Math.max(b.x - o.cx, 0, o.cx - b.x - b.w), dy = Math.max(b.y - o.cy, 0, o.cy - b.y - b.h);
  return dx * dx + dy * dy < o.r * o.r;
}

// Where a pattern point's circle of radius r is drawn on a width x height canvas: where it is when it fits
// whole, else pinned PIN_ROOM inside the nearest edges ({x, y, pinned}).
export function chartPosition(cx, cy, r, width, height) {
  const fits = cx - r >= 0 && cy - r >= 0 && cx + r <= width && cy + r <= height;
  if (fits) return { x: cx, y: cy, pinned: false };
  const clamp = (v, hi) => Math.min(Math.max(v, r + PIN_ROOM), hi - r - PIN_ROOM);
  return { x: clamp(cx, width), y: clamp(cy, height), pinned: true };
}

// Greedy label placement: each label (in priority order) takes the first of a few positions
// around its anchor that stays on the canvas and overlaps no label placed before it nor any
// obstacle (pattern circles with their clearance, the compass); a label with no free position is left out.
export function placeLabels(ctx, requests, obstacles, width, height) {
  const placed = [];
  for (const r of [...requests].sort((a, b) => a.priority - b.priority)) {
    ctx.font = r.font;
    const w = Math.ceil(ctx.measureText(r.text).width) + 2, h = r.size + 2;
    // Close around the anchor first; labels that must not be dropped (track names) may also go
    // further out, with a leader line back to their point; an area's name (a constellation's, at the
    // middle of its stars) may move a little further, with no line: it names no one point.
    const rings = r.keep ? [r.radius + 3, r.radius + 12, r.radius + 24]
      : r.kind === "constellation" ? [r.radius + 3, r.radius + 14] : [r.radius + 3];
    let done = false;
    for (const gap of rings) {
      const spots = [
        [r.x + gap, r.y - h / 2], [r.x - gap - w, r.y - h / 2], [r.x - w / 2, r.y - gap - h],
        [r.x - w / 2, r.y + gap], [r.x + gap * 0.7, r.y - gap * 0.7 - h], [r.x - gap * 0.7 - w, r.y + gap * 0.7],
        [r.x + gap * 0.7, r.y + gap * 0.7], [r.x - gap * 0.7 - w, r.y - gap * 0.7 - h],
      ];
      for (const [x, y] of spots) {
        const box = { x, y, w, h };
        if (x < 0 || y < 0 || x + w > width || y + h > height) continue;
        if (placed.some((p) => blocks(p, box))) continue;
        // An obstacle never blocks the label of its own point (owner); unowned ones block every label.
        if (obstacles.some((o) => (o.owner === undefined || o.owner !== r.owner) && blocks(o, box))) continue;
        placed.push({ ...box, text: r.text, kind: r.kind, owner: r.owner });
        if (gap > r.radius + 3 && r.keep) {
          const cx = Math.min(Math.max(r.x, x), x + w), cy = Math.min(Math.max(r.y, y), y + h);
          const d = Math.hypot(cx - r.x, cy - r.y) || 1;
          ctx.strokeStyle = r.colour; ctx.lineWidth = 1;
          ctx.beginPath(); ctx.moveTo(r.x + (cx - r.x) * r.radius / d, r.y + (cy - r.y) * r.radius / d);
          ctx.lineTo(cx, cy); ctx.stroke();
        }
        ctx.fillStyle = r.colour;
        ctx.textBaseline = "top";
        ctx.fillText(r.text, x + 1, y + 1);
        done = true;
        break;
      }
      if (done) break;
    }
  }
  ctx.textBaseline = "alphabetic";
  return placed;
}

// A filled arrowhead just outside a pinned circle's rim, pointing along (dx, dy): the way to the point.
function offChartArrow(ctx, cx, cy, dx, dy, colour) {
  const n = Math.hypot(dx, dy) || 1, ux = dx / n, uy = dy / n;
  const base = POINT_RADIUS + 2, tip = POINT_RADIUS + PIN_ROOM - 1;
  ctx.fillStyle = colour;
  ctx.beginPath();
  ctx.moveTo(cx + ux * tip, cy + uy * tip);
  ctx.lineTo(cx + ux * base - uy * 4, cy + uy * base + ux * 4);
  ctx.lineTo(cx + ux * base + uy * 4, cy + uy * base - ux * 4);
  ctx.closePath(); ctx.fill();
}

function arrow(ctx, x, y, dx, dy, length, label) {
  const ex = x + dx * length, ey = y + dy * length;
  ctx.beginPath(); ctx.moveTo(x, y); ctx.lineTo(ex, ey); ctx.stroke();
  const a = Math.atan2(dy, dx);
  ctx.beginPath();
  ctx.moveTo(ex, ey);
  ctx.lineTo(ex - 7 * Math.cos(a - 0.45), ey - 7 * Math.sin(a - 0.45));
  ctx.lineTo(ex - 7 * Math.cos(a + 0.45), ey - 7 * Math.sin(a + 0.45));
  ctx.closePath(); ctx.fill();
  ctx.fillText(label, ex + dx * 9 - 4, ey + dy * 9 + 4);
}

// options: {names, constellations, edge, credible (the candidate's verdict), highlight (a track)}.
// Returns {factor, labels (placed boxes), hits (what tooltips and clicks can find)}.
export function drawSky(canvas, view, options) {
  const ctx = canvas.getContext("2d");
  const sky = view.sky;
  const b = sky.bounds;
  const scale = canvas.width / (b.x_max - b.x_min);
  canvas.height = Math.round((b.y_max - b.y_min) * scale);
  const W = canvas.width, H = canvas.height;
  const P = (x, y) => [(x - b.x_min) * scale, (y - b.y_min) * scale];
  const hits = [];
  const requests = [];
  const obstacles = [];
  ctx.fillStyle = "#05070b";
  ctx.fillRect(0, 0, W, H);

  // The sensor, inside the section's margin.
  const [sx0, sy0] = P(-0.5, -0.5);
  const [sx1, sy1] = P(sky.sensor.width - 0.5, sky.sensor.height - 0.5);
  ctx.strokeStyle = "#2f3b4d"; ctx.lineWidth = 1; ctx.setLineDash([6, 4]);
  ctx.strokeRect(sx0, sy0, sx1 - sx0, sy1 - sy0);
  ctx.setLineDash([]);

  if (options.constellations) {
    for (const c of sky.constellations) {
      if (c.x === null || c.y === null) continue;
      const [cx, cy] = P(c.x, c.y);
      requests.push({ text: c.constellation, x: cx, y: cy, radius: 6, font: "600 13px system-ui, sans-serif",
        size: 13, colour: "rgba(120,160,220,0.6)", priority: 50, kind: "constellation" });
    }
  }

  for (const s of sky.stars) {
    if (s.x === null || s.y === null) continue;
    const [cx, cy] = P(s.x, s.y);
    const r = starRadius(s.mag);
    ctx.fillStyle = s.matched ? COLOURS.matchedStar : COLOURS.star;
    ctx.beginPath(); ctx.arc(cx, cy, r, 0, 2 * Math.PI); ctx.fill();
    hits.push({ x: cx, y: cy, r: Math.max(r, 4), kind: "star",
      text: `${s.name || `HIP ${s.hip}`} (${s.constellation}), Hp ${s.mag.toFixed(2)}` +
        `${s.matched ? ", matched" : ""}` });
    if (options.names && s.name) {
      requests.push({ text: s.name, x: cx, y: cy, radius: r, font: "11px system-ui, sans-serif", size: 11,
        colour: s.matched ? "#ffe8a3" : "#9fb0c4", priority: s.matched ? 20 : 30 + s.mag, kind: "star",
        owner: s.matched ? `p${s.pattern_index}` : undefined });
    }
  }

  for (const p of sky.planets) {
    if (p.x === null || p.y === null) continue;
    const [cx, cy] = P(p.x, p.y);
    ctx.strokeStyle = COLOURS.planet; ctx.lineWidth = 2;
    ctx.beginPath(); ctx.arc(cx, cy, 8, 0, 2 * Math.PI); ctx.stroke();
    hits.push({ x: cx, y: cy, r: 9, kind: "planet", text: `planet ${p.name}` });
    requests.push({ text: p.name, x: cx, y: cy, radius: 8, font: "600 12px system-ui, sans-serif", size: 12,
      colour: COLOURS.planet, priority: 15, kind: "planet",
      owner: p.pattern_index === null ? undefined : `p${p.pattern_index}` });
  }

  // Where each pattern point's circle goes: where it lies, or pinned inside the canvas (chartPosition).
  const drawnAt = new Map();
  for (const p of sky.pattern_points) {
    if (p.x !== null && p.y !== null) drawnAt.set(p.index, chartPosition(...P(p.x, p.y), POINT_RADIUS, W, H));
  }

  if (options.edge && sky.generating_edge) {
    const [i, j] = sky.generating_edge.pattern_indices ?? [];
    const [a, c] = [drawnAt.get(i), drawnAt.get(j)];
    if (a && c) {
      ctx.strokeStyle = COLOURS.edge; ctx.lineWidth = 2; ctx.setLineDash([8, 5]);
      ctx.beginPath(); ctx.moveTo(a.x, a.y); ctx.lineTo(c.x, c.y); ctx.stroke();
      ctx.setLineDash([]);
    }
  }

  const factor = exaggeration(sky.pattern_points, scale);
  for (const p of sky.pattern_points) {
    if (!drawnAt.has(p.index)) continue;
    const [tx, ty] = P(p.x, p.y);
    const { x: cx, y: cy, pinned } = drawnAt.get(p.index);
    const matched = p.hip !== null || p.planet !== null;
    // A match of a candidate that is not credible is drawn as doubtful, never as a green "match".
    const colour = !matched ? COLOURS.unmatched : options.credible ? COLOURS.matched : COLOURS.doubtful;
    ctx.strokeStyle = colour; ctx.lineWidth = options.highlight !== undefined && p.track === options.highlight ? 3.5 : 1.6;
    ctx.setLineDash(matched && !options.credible ? [4, 3] : []);
    ctx.beginPath(); ctx.arc(cx, cy, POINT_RADIUS, 0, 2 * Math.PI); ctx.stroke();
    ctx.setLineDash([]);
    // Pinned: an arrow from its rim towards where it lies, off the canvas.
    if (pinned) offChartArrow(ctx, cx, cy, tx - cx, ty - cy, colour);
    if (p.residual_x !== null) {
      ctx.strokeStyle = COLOURS.residual; ctx.lineWidth = 2;
      ctx.beginPath(); ctx.moveTo(cx, cy);
      ctx.lineTo(cx + p.residual_x * factor * scale, cy + p.residual_y * factor * scale); ctx.stroke();
    }
    const label = p.track !== null ? `T${p.track}` : `hand ${p.hand}`;
    const target = p.name || (p.hip !== null ? `HIP ${p.hip}` : p.planet ? `planet ${p.planet}` : "no star");
    hits.push({ x: cx, y: cy, r: POINT_RADIUS + 2, kind: "point", track: p.track, index: p.index, pinned,
      text: `${label} → ${target}` + (p.residual_arcsec !== null ? `, residual ${p.residual_arcsec.toFixed(1)}″` : "") +
        (pinned ? `; off the chart at (${p.x.toFixed(0)}, ${p.y.toFixed(0)}) px of the reference snapshot: ` +
          "drawn at the edge, the arrow points to it" : "") +
        (p.track !== null ? " (click: show it in the snapshots)" : "") });
    obstacles.push({ cx, cy, r: POINT_RADIUS + (pinned ? PIN_ROOM : CIRCLE_CLEARANCE), owner: `p${p.index}` });
    // Same colour as the track in the snapshot player, so T3 here is T3 there.
    requests.push({ text: label, x: cx, y: cy, radius: POINT_RADIUS, font: "600 11px system-ui, sans-serif", size: 11,
      colour: p.track !== null ? trackColour(p.track) : "#ffe066", priority: 10, kind: "track", owner: `p${p.index}`,
      keep: true });
  }

  // North and east at the field centre, in the top-left corner, on a dark disc of their own.
  const compass = northEast(view.candidate.rotation_matrix);
  const ox = 44, oy = 44;
  obstacles.push({ x: 0, y: 0, w: 90, h: 90 });
  ctx.fillStyle = "rgba(10,14,20,0.85)";
  ctx.beginPath(); ctx.arc(ox, oy, 40, 0, 2 * Math.PI); ctx.fill();
  ctx.strokeStyle = COLOURS.compass; ctx.fillStyle = COLOURS.compass; ctx.lineWidth = 2;
  ctx.font = "700 13px system-ui, sans-serif";
  if (compass.north) arrow(ctx, ox, oy, compass.north[0], compass.north[1], 26, "N");
  if (compass.east) arrow(ctx, ox, oy, compass.east[0], compass.east[1], 18, "E");

  const labels = placeLabels(ctx, requests, obstacles, W, H);
  return { factor, labels, hits, compass, scale };
}

// The thing under canvas pixel (x, y) among drawSky's hits: pattern points first, then planets, stars.
export function hitAt(drawn, x, y) {
  const order = { point: 0, planet: 1, star: 2 };
  let best = null;
  for (const h of drawn.hits) {
    const d = Math.hypot(h.x - x, h.y - y);
    if (d > h.r + 3) continue;
    if (!best || order[h.kind] < order[best.h.kind] || (order[h.kind] === order[best.h.kind] && d < best.d)) best = { h, d };
  }
  return best ? best.h : null;
}
