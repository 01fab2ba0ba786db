// The attitude timeline of a spacecraft (GET /api/spacecraft/{name}/timeline) drawn as SVG: a lane of the
// sequences (first to last snapshot, by status), then RA, Dec, roll and the body rate at each attitude's
// epoch with their 1-sigma, on one time axis; gaps, overlaps and jumps marked across them and listed.
// Clicking a point selects its sequence in this tab's console session (PUT /api/view) and opens the console.
import * as api from "./api.js";
import { $, el, errorText, fmtTime, plural, stored, toast } from "./dom.js";
import { SESSION } from "./state.js";

const SVG = "http://www.w3.org/2000/svg";
const MARGIN = { left: 78, right: 24, top: 10, bottom: 34 };
const LANE_H = 46;
const PANEL_H = 118;
const PANEL_GAP = 14;
// The quantities drawn, each in a panel of its own. `wrap`: an angle whose line is not drawn across 0/360.
const PANELS = [
  { key: "ra", label: "RA (deg)", value: (p) => p.ra_deg, sigma: (p) => p.sigma_ra_deg, wrap: 360 },
  { key: "dec", label: "Dec (deg)", value: (p) => p.dec_deg, sigma: (p) => p.sigma_dec_deg },
  { key: "roll", label: "Roll (deg)", value: (p) => p.roll_deg, sigma: (p) => p.sigma_roll_deg, wrap: 360 },
  { key: "rate", label: "Body rate (deg/s)", value: (p) => p.rate_deg_s, sigma: (p) => p.sigma_rate_deg_s },
];
const STATUS_TEXT = { confirmed: "confirmed", identified: "identified", ambiguous: "ambiguous", no_match: "no match",
  rejected: "no valid attitude", new: "not searched" };

const ms = (text) => Date.parse(text);

function svg(tag, attrs = {}, ...children) {
  const node = document.createElementNS(SVG, tag);
  for (const [key, value] of Object.entries(attrs)) {
    if (value === undefined || value === null) continue;
    if (key.startsWith("on")) node.addEventListener(key.slice(2), value);
    else node.setAttribute(key, value);
  }
  for (const child of children) if (child) node.append(child);
  return node;
}

const title = (text) => svg("title", {}, text);

// A step of 1, 2 or 5 times a power of ten giving about `n` intervals over `span`.
function niceStep(span, n) {
  const raw = span / n, power = 10 ** Math.floor(Math.log10(raw));
  return [1, 2, 5, 10].map((m) => m * power).find((s) => s >= raw) || raw;
}

// Steps of the time axis, seconds: the first giving at most 8 ticks is used.
const TIME_STEPS = [1, 2, 5, 10, 15, 30, 60, 120, 300, 600, 900, 1800, 3600, 7200, 10800, 21600, 43200, 86400,
  172800, 604800, 2592000, 31536000];

function timeTicks(t0, t1) {
  // Beyond the table (a span of more than 8 years), a round number of years: never more than 8 labels.
  const years = (t1 - t0) / (1000 * TIME_STEPS.at(-1));
  const step = 1000 * (TIME_STEPS.find((s) => (t1 - t0) / (1000 * s) <= 8) || TIME_STEPS.at(-1) * niceStep(years, 8));
  const ticks = [];
  for (let t = Math.ceil(t0 / step) * step; t <= t1; t += step) ticks.push(t);
  return { ticks, step };
}

function timeLabel(t, step) {
  const iso = new Date(t).toISOString();
  if (step >= 86400000) return iso.slice(0, 10);
  return step >= 60000 ? iso.slice(11, 16) : iso.slice(11, 19);
}

// The sentence about one sequence: what the detail line and the point's tooltip say.
function describe(p) {
  const who = p.by ? ` by ${p.by}` : (p.search_id ? ` (search ${p.search_id}, ${p.method})` : "");
  const head = `#${p.sequence} ${p.sequence_id || p.filename || ""} · ${STATUS_TEXT[p.status] || p.status}${who}`;
  const span = `${fmtTime(p.start)} to ${fmtTime(p.end)}, ${plural(p.n_snapshots, "snapshot")}`;
  if (p.ra_deg === null) return `${head} · ${span}${p.reason ? ` · reason: ${p.reason}` : ""}`;
  const pm = (v, s, d) => `${v.toFixed(d)}${s === null ? "" : ` ± ${s.toPrecision(2)}`}`;
  const rate = p.rate_deg_s === null ? "no rate fitted" : `rate ${pm(p.rate_deg_s, p.sigma_rate_deg_s, 5)} deg/s`;
  return `${head} · ${span} · at ${fmtTime(p.epoch)}: RA ${pm(p.ra_deg, p.sigma_ra_deg, 4)}, ` +
    `Dec ${pm(p.dec_deg, p.sigma_dec_deg, 4)}, roll ${pm(p.roll_deg, p.sigma_roll_deg, 3)} deg (rank ${p.rank}), ${rate}`;
}

// Select sequence `id` (and the candidate drawn) in this tab's console session, then open the console on it.
async function openInConsole(p) {
  try {
    await api.put(`/api/view?session=${encodeURIComponent(SESSION)}`,
      p.rank === null ? { sequence: p.sequence } : { sequence: p.sequence, rank: p.rank });
    location.href = `/?session=${encodeURIComponent(SESSION)}`;
  } catch (err) {
    toast(`Could not open sequence #${p.sequence} in the console: ${errorText(err)}`, "error");
  }
}

// The y range of a panel: its values with their 1-sigma, padded by 8 % (1 unit when all are equal).
function valueRange(points, panel) {
  const lows = [], highs = [];
  for (const p of points) {
    const v = panel.value(p), s = panel.sigma(p) || 0;
    if (v === null) continue;
    lows.push(v - s); highs.push(v + s);
  }
  if (!lows.length) return [0, 1];
  let lo = Math.min(...lows), hi = Math.max(...highs);
  const pad = hi > lo ? 0.08 * (hi - lo) : 1;
  return [lo - pad, hi + pad];
}

function drawPanel(root, doc, panel, top, x, width) {
  const points = doc.points.filter((p) => panel.value(p) !== null);
  const [y0, y1] = valueRange(points, panel);
  const bottom = top + PANEL_H;
  const y = (v) => bottom - (v - y0) / (y1 - y0) * PANEL_H;
  const g = svg("g", { class: "tl-panel", "data-key": panel.key, "data-y0": y0, "data-y1": y1, "data-top": top,
    "data-bottom": bottom });
  g.append(svg("rect", { x: MARGIN.left, y: top, width, height: PANEL_H, class: "tl-frame" }));
  const step = niceStep(y1 - y0, 4);
  for (let v = Math.ceil(y0 / step) * step; v <= y1; v += step) {
    g.append(svg("line", { x1: MARGIN.left, x2: MARGIN.left + width, y1: y(v), y2: y(v), class: "tl-grid" }),
      svg("text", { x: MARGIN.left - 6, y: y(v) + 4, class: "tl-tick", "text-anchor": "end" },
        document.createTextNode(Number(v.toPrecision(6)).toString())));
  }
  g.append(svg("text", { x: 14, y: top + PANEL_H / 2, class: "tl-axis-label",
    transform: `rotate(-90 14 ${top + PANEL_H / 2})`, "text-anchor": "middle" }, document.createTextNode(panel.label)));
  // The 1-sigma band and the line through consecutive attitudes (broken where an angle wraps, and at gaps).
  const gapStarts = new Set(doc.flags.filter((f) => f.kind === "gap").map((f) => f.later));
  let run = [];
  const runs = [run];
  points.forEach((p, i) => {
    const prev = points[i - 1];
    if (prev && (gapStarts.has(p.sequence) || (panel.wrap && Math.abs(panel.value(p) - panel.value(prev)) > panel.wrap / 2))) {
      run = []; runs.push(run);
    }
    run.push(p);
  });
  for (const r of runs.filter((r) => r.length)) {
    const upper = r.map((p) => `${x(ms(p.epoch))},${y(panel.value(p) + (panel.sigma(p) || 0))}`);
    const lower = r.map((p) => `${x(ms(p.epoch))},${y(panel.value(p) - (panel.sigma(p) || 0))}`).reverse();
    g.append(svg("polygon", { points: [...upper, ...lower].join(" "), class: "tl-band" }));
    if (r.length > 1) g.append(svg("polyline", { points: r.map((p) => `${x(ms(p.epoch))},${y(panel.value(p))}`).join(" "),
      class: "tl-line" }));
  }
  for (const p of points) {
    const cx = x(ms(p.epoch)), v = panel.value(p), s = panel.sigma(p);
    if (s) g.append(svg("line", { x1: cx, x2: cx, y1: y(v - s), y2: y(v + s), class: "tl-errorbar" }));
    g.append(svg("circle", { cx, cy: y(v), r: 4.5, class: `tl-point status-${p.status}`, tabindex: 0,
      "data-sequence": p.sequence, "data-value": v, "data-epoch": p.epoch,
      onclick: () => openInConsole(p), onkeydown: (e) => { if (e.key === "Enter") openInConsole(p); },
      onmouseenter: () => { $("tl-detail").textContent = describe(p); } }, title(describe(p))));
  }
  root.append(g);
  return bottom;
}

// The lane of sequences: a bar from first to last snapshot and a marker at the epoch, coloured by status.
function drawLane(root, doc, x) {
  const top = MARGIN.top, mid = top + LANE_H / 2;
  const g = svg("g", { class: "tl-lane" });
  g.append(svg("text", { x: MARGIN.left - 6, y: mid + 4, class: "tl-tick", "text-anchor": "end" },
    document.createTextNode("sequences")));
  doc.points.forEach((p, i) => {
    const row = mid + (i % 2 ? 7 : -7);   // alternate rows, so that overlapping bars stay apart
    const x0 = x(ms(p.start)), x1 = Math.max(x(ms(p.end)), x0 + 2), cx = x(ms(p.epoch));
    const marker = p.ra_deg !== null
      ? svg("circle", { cx, cy: row, r: 4, class: `tl-point status-${p.status}` })
      : (p.status === "new" ? svg("circle", { cx, cy: row, r: 3, class: "tl-cross status-new" })
        : svg("path", { d: `M${cx - 4} ${row - 4}L${cx + 4} ${row + 4}M${cx + 4} ${row - 4}L${cx - 4} ${row + 4}`,
          class: `tl-cross status-${p.status}` }));
    g.append(svg("g", { class: `tl-seq status-${p.status}`, "data-sequence": p.sequence, tabindex: 0,
      onclick: () => openInConsole(p), onkeydown: (e) => { if (e.key === "Enter") openInConsole(p); },
      onmouseenter: () => { $("tl-detail").textContent = describe(p); } },
    svg("rect", { x: x0, y: row - 3, width: x1 - x0, height: 6, class: "tl-bar" }), marker, title(describe(p))));
  });
  root.append(g);
  return top + LANE_H;
}

// Gaps and overlaps as shaded spans over every panel; jumps as a dashed line at the later attitude's epoch.
function drawFlags(root, doc, x, top, bottom) {
  const byId = new Map(doc.points.map((p) => [p.sequence, p]));
  const g = svg("g", { class: "tl-flags-drawn" });
  for (const f of doc.flags) {
    const later = byId.get(f.later);
    const t = ms(later.start);
    if (f.kind === "gap" || f.kind === "overlap") {
      const [a, b] = f.kind === "gap" ? [t - 1000 * f.seconds, t] : [t, t + 1000 * f.seconds];
      g.append(svg("rect", { x: x(a), y: top, width: Math.max(x(b) - x(a), 2), height: bottom - top,
        class: `tl-${f.kind}`, "data-later": f.later }, title(f.text)));
    } else {
      const cx = x(ms(later.epoch));
      g.append(svg("line", { x1: cx, x2: cx, y1: top, y2: bottom, class: "tl-jump", "data-later": f.later },
        title(f.text)), svg("text", { x: cx + 4, y: top + 12, class: "tl-jump-label" },
        document.createTextNode(`jump ${f.angle_deg.toPrecision(3)}°`)));
    }
  }
  root.prepend(g);   // under the points, which stay clickable
}

function draw(doc) {
  const chart = $("tl-chart");
  chart.replaceChildren();
  if (!doc.points.length) {
    chart.append(el("p", { class: "hint" }, "No sequence of this spacecraft has a first snapshot in this range."));
    return;
  }
  const width = Math.max(chart.clientWidth - 24, 600) - MARGIN.left - MARGIN.right;
  let t0 = Math.min(...doc.points.map((p) => ms(p.start)));
  let t1 = Math.max(...doc.points.map((p) => Math.max(ms(p.end), ms(p.epoch))));
  const pad = Math.max((t1 - t0) * 0.02, 1000);
  t0 -= pad; t1 += pad;
  const x = (t) => MARGIN.left + (t - t0) / (t1 - t0) * width;
  const height = MARGIN.top + LANE_H + PANELS.length * (PANEL_H + PANEL_GAP) + MARGIN.bottom;
  const root = svg("svg", { id: "tl-svg", width: width + MARGIN.left + MARGIN.right, height, "data-t0": t0,
    "data-t1": t1, "data-left": MARGIN.left, "data-right": MARGIN.left + width, role: "img",
    "aria-label": `attitude timeline of ${doc.spacecraft}` });
  let top = drawLane(root, doc, x) + PANEL_GAP / 2;
  const panelsTop = top;
  for (const panel of PANELS) top = drawPanel(root, doc, panel, top, x, width) + PANEL_GAP;
  const bottom = top - PANEL_GAP;
  const { ticks, step } = timeTicks(t0, t1);
  for (const t of ticks) {
    root.append(svg("line", { x1: x(t), x2: x(t), y1: bottom, y2: bottom + 5, class: "tl-grid" }),
      svg("text", { x: x(t), y: bottom + 18, class: "tl-tick", "text-anchor": "middle" },
        document.createTextNode(timeLabel(t, step))));
  }
  root.append(svg("text", { x: MARGIN.left + width, y: bottom + 31, class: "tl-axis-label", "text-anchor": "end" },
    document.createTextNode(`UTC, ${new Date(t0).toISOString().slice(0, 10)} to ${new Date(t1).toISOString().slice(0, 10)}`)));
  drawFlags(root, doc, x, MARGIN.top, bottom);
  root.dataset.panelsTop = panelsTop;
  chart.append(root);
}

function listFlags(doc) {
  const byId = new Map(doc.points.map((p) => [p.sequence, p]));
  $("tl-flag-count").textContent = doc.flags.length ? `(${doc.flags.length})` : "";
  $("tl-flags").replaceChildren(...(doc.flags.length ? doc.flags.map((f) => el("li", { class: `flag-${f.kind}` },
    f.text, " ", el("button", { class: "small", onclick: () => openInConsole(byId.get(f.later)) },
      `open #${f.later}`)))
    : [el("li", { class: "dim" }, "none in this range")]));
}

function summary(doc) {
  const count = (kind) => doc.flags.filter((f) => f.kind === kind).length;
  const range = doc.start || doc.end
    ? `first snapshots from ${fmtTime(doc.start) === "-" ? "the beginning" : fmtTime(doc.start)} to ` +
      `${doc.end ? fmtTime(doc.end) : "now"}`
    : `the newest ${plural(doc.points.length, "sequence")} of ${doc.total} with a time`;
  const drawn = doc.points.filter((p) => p.ra_deg !== null).length;
  return `${doc.spacecraft}: ${plural(doc.points.length, "sequence")} (${range}), ${drawn} with an attitude · ` +
    `${plural(count("gap"), "gap")}, ${plural(count("overlap"), "overlap")}, ${plural(count("jump"), "jump")}`;
}

// The query of the form; the address keeps it, so a reload or a shared link shows the same timeline.
function formQuery() {
  const q = new URLSearchParams({ spacecraft: $("tl-spacecraft").value });
  for (const [id, name] of [["tl-start", "start"], ["tl-end", "end"], ["tl-limit", "limit"], ["tl-gap", "gap_s"]]) {
    const v = $(id).value.trim();
    if (v) q.set(name, v);
  }
  return q;
}

async function show() {
  const q = formQuery();
  history.replaceState(null, "", `?${q}`);
  const name = q.get("spacecraft");
  q.delete("spacecraft");
  $("tl-title").textContent = name;
  document.body.dataset.ready = "";
  try {
    const doc = await api.get(`/api/spacecraft/${encodeURIComponent(name)}/timeline?${q}`);
    $("tl-summary").textContent = summary(doc);
    $("tl-summary").classList.remove("error-text");
    draw(doc);
    listFlags(doc);
  } catch (err) {
    $("tl-summary").textContent = errorText(err);
    $("tl-summary").classList.add("error-text");
    $("tl-chart").replaceChildren();
    $("tl-flags").replaceChildren();
  }
  document.body.dataset.ready = "1";
}

async function start() {
  api.setToken(stored(sessionStorage, "starid-token", ""));   // the console's token in this tab, for PUT /api/view
  const params = new URL(location.href).searchParams;
  let names = [];
  try {
    names = (await api.get("/api/spacecraft")).filter((n) => n.name !== null);
  } catch (err) {
    toast(`Could not list the spacecraft: ${errorText(err)}`, "error");
  }
  const wanted = params.get("spacecraft");
  if (wanted && !names.some((n) => n.name === wanted)) names.unshift({ name: wanted, sequences: 0 });
  $("tl-spacecraft").replaceChildren(...names.map((n) => el("option", { value: n.name }, `${n.name} (${n.sequences})`)));
  if (wanted) $("tl-spacecraft").value = wanted;
  for (const [id, name] of [["tl-start", "start"], ["tl-end", "end"], ["tl-limit", "limit"], ["tl-gap", "gap_s"]]) {
    if (params.get(name)) $(id).value = params.get(name);
  }
  $("tl-form").addEventListener("submit", (e) => { e.preventDefault(); show(); });
  $("tl-console").href = `/?session=${encodeURIComponent(SESSION)}`;
  if (!names.length) {
    $("tl-summary").textContent = "The archive holds no sequence of a named spacecraft yet.";
    document.body.dataset.ready = "1";
    return;
  }
  await show();
}

start();
