// Operator console: wires the panels to the REST API and to this console's own view state.
//
// Each browser tab is a session (state.js) whose selection (sequence, candidate rank,
// magnitude limit) is stored on the server (PUT /api/view?session=...) and polled back every
// second, so the 3D view opened from this console follows it and its Next/Prev come back
// here, while other consoles keep their own selection. Nothing moves under the operator's
// hands: another console's search or pattern edit of the same sequence is announced, and a
// confirmation names the search it was made on. Every action ends in a visible result or error.
import * as api from "./api.js";
import { $, ASSUMED_TIME, el, toast, errorText, fmt, fmtProbability, fmtTime, moved, plural, sequenceTime, snapshotName,
  store, stored } from "./dom.js";
import { FrameView } from "./frame.js";
import { SnapshotPlayer } from "./player.js";
import { drawSky, hitAt } from "./sky.js";
import { SESSION, state } from "./state.js";
import { loadAttitudes, loadSequences, loadSpacecraft, markSelected, noteSearched, setupQueue,
  statusText } from "./queue.js";
import { cancelSteps, commentIsFor, confirmClick, confirmSentFrom, dropStaleComment, openReject, renderCandidates,
  setupDecision, verdictSummary } from "./decision.js";
import { calibrate, showCalibration } from "./calibration.js";

const POLL_MS = 1000;
const QUEUE_REFRESH_MS = 4000;
const viewPath = (extra = "") => `/api/view?session=${encodeURIComponent(SESSION)}${extra}`;

// A track in or out of the pattern: what a click on it does in the player and in the frame panel.
const onToggleTrack = (track) => editPattern((def) => toggleTrack(def, track), `track T${track}`);
const player = new SnapshotPlayer({
  onToggleTrack,
  onPick: (snapshot, x, y) => editPattern((def) => ({ ...def, manual_points: [...(def.manual_points || []), { snapshot, x, y }] }),
    `a point at (${x}, ${y}) of ${snapshotName(snapshot, { snapshots: state.detail?.telemetry.snapshots })}`),
  onRemoveManual: (k) => editPattern((def) => ({ ...def, manual_points: def.manual_points.filter((_, i) => i !== k) }),
    `hand-picked point ${k}`),
  onMessage: (text) => toast(text),
  onShow: (index) => frameView.show(index),   // the frame panel follows the snapshot shown
});
const frameView = new FrameView({ onToggleTrack, onMessage: (text) => toast(text) });

// ---------------------------------------------------------------- helpers

async function action(label, fn) {
  state.busy++;
  try {
    return await fn();
  } catch (err) {
    toast(`${label} failed: ${errorText(err)}`, "error");
    return undefined;
  } finally {
    state.busy--;
  }
}

// A queue of asynchronous steps: each starts once the one before is done, whether it failed or not.
function oneAtATime() {
  let last = Promise.resolve();
  return (step) => {
    const done = last.then(step);
    last = done.catch(() => {});
    return done;
  };
}

// This console's writes of its view state go out one at a time, in the order made: two in flight can reach the
// server in either order (a sequence opened, and Next pressed before its write was answered: the rank written
// first, then the new sequence's rank 1 over it, the session left on another rank than the console shows).
const inWriteOrder = oneAtATime();

function writeView(changes) {
  return inWriteOrder(async () => {
    try {
      const doc = await api.put(viewPath(), changes);
      state.viewRevision = Math.max(state.viewRevision, doc.revision);
    } catch (err) {
      toast(`Could not store this console's selection: ${errorText(err)}`, "error");
    }
  });
}

// The same rule as app/viewer/scene.py toggle_track: with every track selected (include null)
// membership is the exclusion list, otherwise the inclusion list.
function toggleTrack(def, track) {
  const exclude = new Set(def.exclude_tracks || []);
  if (def.include_tracks === null || def.include_tracks === undefined) {
    if (exclude.has(track)) exclude.delete(track); else exclude.add(track);
    return { ...def, exclude_tracks: [...exclude].sort((a, b) => a - b), include_tracks: null };
  }
  const include = new Set(def.include_tracks);
  if (include.has(track)) include.delete(track); else include.add(track);
  exclude.delete(track);
  return { ...def, include_tracks: [...include].sort((a, b) => a - b), exclude_tracks: [...exclude] };
}

// ---------------------------------------------------------------- health and operator

async function checkHealth() {
  const badge = $("health");
  try {
    const h = await api.get("/api/health");
    badge.textContent = h.status === "ok" ? `ready · ${h.index.stars} stars` : `degraded`;
    badge.className = `health ${h.status === "ok" ? "ok" : "bad"}`;
    if (h.auth_required_for_writes !== state.authRequired) {
      state.authRequired = h.auth_required_for_writes;
      $("token").hidden = !state.authRequired;
      if (state.authRequired) await identify();
    }
  } catch (err) {
    badge.textContent = "server unreachable";
    badge.className = "health bad";
  }
}

// Off loopback every write needs a token and the token names the operator: the name field
// then shows the token's operator, read-only. On loopback the name typed is remembered here.
async function identify() {
  api.setToken($("token").value);
  const name = $("operator");
  if (!state.authRequired) { name.readOnly = false; return; }
  try {
    const me = await api.get("/api/operator");
    name.value = me.operator || "";
    name.readOnly = true;
    shareOperator();
    name.placeholder = me.operator ? "" : "enter your token";
  } catch (err) {
    name.value = "";
    toast(`The token is not valid: ${errorText(err)}`, "error");
  }
}

// The operator's name goes with this console's view session, so that the 3D view drawing it confirms
// under the same name (its own Operator field takes it).
function shareOperator() {
  return writeView({ operator: $("operator").value.trim() || null });
}

function setupOperator() {
  const name = $("operator"), token = $("token");
  name.value = stored(localStorage, "starid-operator", "");
  name.addEventListener("change", () => {
    if (!name.readOnly) store(localStorage, "starid-operator", name.value.trim());
    shareOperator();
  });
  // The token is kept for this tab only (sessionStorage), never in localStorage.
  token.value = stored(sessionStorage, "starid-token", "");
  api.setToken(token.value);
  token.addEventListener("change", () => { store(sessionStorage, "starid-token", token.value.trim()); identify(); });
}

// ---------------------------------------------------------------- the selected sequence

// The operator's moves (opening a sequence, stepping or choosing its candidates) are made one at a time, in
// the order given, each on what the one before left: a Next pressed while a sequence opens steps the sequence
// being opened, not the one it replaces (which the opening then reset to rank 1: the Next was lost).  (Not the
// writes' queue: a move waits for its own writes.)
const inTurn = oneAtATime();

function selectSequence(id) {
  return inTurn(() => openSequence(id));
}

async function openSequence(id) {
  moved();
  await action("Opening the sequence", async () => {
    cancelSteps();
    await loadDetail(id, { fresh: true });
    state.openedFrom = { id, ids: [...state.queueIds] };   // the queue as it was: what j/k step through
    state.rank = state.detail.search && state.detail.search.candidates.length ? 1 : null;
    await writeView({ sequence: id });
    await showCandidate();
  });
}

// How often loadDetail reads again when the sequence and its verdicts name different searches.
const CONSISTENT_READS = 5;

async function loadDetail(id, { fresh = false } = {}) {
  // The two reads are one state only when they name the same search: a search finishing between them
  // (an upload's queued search) would pair its candidates with the verdicts of none, and the view
  // polling would see nothing left to change. Read both again until they agree.
  let detail, review;
  for (let read = 0; read < CONSISTENT_READS; read++) {
    [detail, review] = await Promise.all([api.get(`/api/sequences/${id}`), api.get(`/api/sequences/${id}/review`)]);
    if ((detail.search?.search_id ?? null) === (review.search_id ?? null)) break;
  }
  // A comment is about the sequence it was typed for: another sequence starts without it.
  if (state.detail?.id !== detail.id) $("comment").value = "";
  state.detail = detail;
  state.review = review;
  $("empty-hint").hidden = true;
  $("workspace").hidden = false;
  if (fresh) $("change-notice").hidden = true;
  // One line each, cut with an ellipsis (the whole text in the tooltip): a long id or file name must not push
  // the panels below, and the operator's Next with them, down a line.
  for (const [id, text] of [
    ["seq-title", detail.sequence_id || `sequence #${detail.id}`],
    ["seq-meta", `#${detail.id} · ${detail.spacecraft || "unknown spacecraft"} · ${detail.camera.name || "camera"} · ` +
      `${plural(detail.n_snapshots, "snapshot")} ${detail.telemetry.time_assumed ? `with no time (${ASSUMED_TIME})`
        : `from ${fmtTime(detail.first_time)}`}${detail.filename ? ` · ${detail.filename}` : ""}`]]) {
    $(id).textContent = text;
    $(id).title = text;
  }
  const badge = $("seq-status");
  badge.textContent = statusText(detail.status);
  badge.className = `badge ${detail.status}`;
  $("seq-verdict").textContent = $("seq-verdict").title = verdictSummary();
  markSelected(id);
  noteSearched([detail]);   // its upload line, if it still says a search is queued
  if (detail.spacecraft !== state.calibrationShown) {
    state.calibrationShown = detail.spacecraft;
    action("Loading the camera calibration", () => showCalibration(detail.spacecraft));
  }
  frameView.setSequence(detail);   // first: the player's snapshot then shows in the frame panel
  player.setSequence(detail);
  renderPattern();
  renderSearchSummary();
  return detail;
}

// A pattern point's position in the reference snapshot. A track seen only in other snapshots is carried
// there by the fitted motion, and may then lie outside the sensor: said, so that it does not read as an error.
function positionCell(point, camera) {
  const outside = point.x !== null && point.y !== null && (point.x < -0.5 || point.x > camera.width - 0.5 ||
    point.y < -0.5 || point.y > camera.height - 0.5);
  return el("td", outside ? { class: "outside", title: "outside the sensor in the reference snapshot: this track " +
      "was seen in other snapshots and carried here by the fitted motion" } : {},
    `${fmt(point.x, 1)}, ${fmt(point.y, 1)}`, outside ? el("span", { class: "dim" }, " (off sensor)") : null);
}

function renderPattern() {
  const d = state.detail;
  const pattern = d.pattern;
  const inPattern = new Map(pattern.points.filter((p) => p.track !== null).map((p) => [p.track, p]));
  const automatic = d.extraction.pattern;   // every track the automatic pattern could use
  const rows = [];
  const seen = new Set();
  const row = (track, shown, current) => el("tr", { class: current ? "" : "out", dataset: { track } },
    el("td", {}, el("input", { type: "checkbox", checked: !!current, "aria-label": `track ${track} in pattern`,
      onchange: () => editPattern((def) => toggleTrack(def, track), `track T${track}`) })),
    el("td", {}, el("span", { class: "swatch", style: `background:hsla(${((track * 137.508) % 360).toFixed(1)}, 85%, 62%, 1)` }), `T${track}`),
    el("td", {}, shown.sightings), positionCell(shown, d.telemetry.camera), el("td", {}, fmt(shown.brightness, 0)));
  for (const p of automatic) {
    if (p.track === null) continue;
    seen.add(p.track);
    const current = inPattern.get(p.track);
    rows.push(row(p.track, current || p, current));
  }
  // Tracks in the pattern that the automatic one leaves out (included explicitly).
  for (const [track, p] of inPattern) if (!seen.has(track)) rows.push(row(track, p, p));
  (pattern.definition.manual_points || []).forEach((m, k) => {
    rows.push(el("tr", { class: "manual", dataset: { manual: k } },
      el("td", {}, el("button", { class: "small", title: "remove this point",
        onclick: () => editPattern((def) => ({ ...def, manual_points: def.manual_points.filter((_, i) => i !== k) }), `hand-picked point ${k}`) }, "×")),
      el("td", {}, `◆ hand ${k}`), el("td", { title: `picked in ${snapshotName(m.snapshot, { snapshots: d.telemetry.snapshots, count: true })}` }, `snap. ${m.snapshot}`), el("td", {}, `${fmt(m.x, 1)}, ${fmt(m.y, 1)}`), el("td", {}, "")));
  });
  $("pattern-rows").replaceChildren(...rows);
  notePatternMore();
  $("pattern-caption").textContent = `version ${pattern.version ?? "-"} (${pattern.kind}${pattern.operator ? `, ${pattern.operator}` : ""}): ` +
    `${pattern.points.length} points, reference ${snapshotName(pattern.reference_snapshot, { snapshots: d.telemetry.snapshots })}`;
}

// "N rows: scroll the table for M more" under a pattern table longer than its box.  The box takes what its card
// (the snapshots' height) leaves under the search box and above the notes, so this is counted again whenever
// its size changes (another sequence's notes, the prior's fields shown): see setupSearch.
function notePatternMore() {
  const wrap = $("pattern-wrap");
  if (!wrap.clientHeight) return;   // not laid out (the other tab shown): counted when it is
  const rows = [...$("pattern-rows").children];
  const hiddenRows = rows.filter((r) => r.offsetTop + r.offsetHeight > wrap.scrollTop + wrap.clientHeight + 1).length;
  $("pattern-more").hidden = !hiddenRows;
  $("pattern-more").textContent = `${rows.length} rows: scroll the table for ${hiddenRows} more`;
}

// A search method as the method menu names it ("triangle features", not "tf").
function methodName(method) {
  const option = [...$("search-method").options].find((o) => o.value === method);
  return option ? option.textContent.replace(/\s*\(.*\)$/, "").toLowerCase() : method.replace("_", " ");
}

// A search replaces the sequence's candidates and its status: said before an identified search is replaced by
// one of another method (the method menu keeps its choice from sequence to sequence, and another method is
// no second opinion here: its answer becomes the sequence's).
function renderSearchReplaces() {
  const s = state.detail?.search, method = $("search-method").value;
  const box = $("search-replaces");
  box.hidden = !(s && s.status === "identified" && s.method !== method);
  if (!box.hidden) {
    box.textContent = `Searching by ${methodName(method)} replaces the identified candidates of search #${s.search_id} ` +
      `(${methodName(s.method)}): the sequence's status becomes what it finds.`;
  }
}

function renderSearchSummary() {
  renderSearchReplaces();
  const s = state.detail.search;
  const stale = s && s.pattern_version !== state.detail.pattern.version;
  const box = $("search-summary");
  box.classList.toggle("stale", !!stale);
  box.textContent = s
    ? `Latest search: ${statusText(s.status)} by ${methodName(s.method)}, ${plural(s.candidates.length, "candidate")} in ` +
      `${Math.round(s.elapsed_ms)} ms (pattern version ${s.pattern_version})` +
      `${stale ? ` - STALE: the pattern is at version ${state.detail.pattern.version} now; search again` : ""}.` +
      (s.notes || []).filter((note) => note.trim()).map((note) => ` ${sentence(note)}`).join("")
    : "Not searched yet.";
}

// A search note as a sentence of the summary: the notes are clauses in lower case ("the pattern's bright
// triangles ..."), each said after a full stop, so each starts with a capital and ends with one.
function sentence(note) {
  const text = note.trim();
  return `${text.charAt(0).toUpperCase()}${text.slice(1)}${/[.!?]$/.test(text) ? "" : "."}`;
}

async function editPattern(change, what) {
  const d = state.detail;
  if (!d) return;
  await action("Changing the pattern", async () => {
    const definition = change(structuredClone(d.pattern.definition));
    await api.put(`/api/sequences/${d.id}/pattern`, {
      exclude_tracks: definition.exclude_tracks || [], include_tracks: definition.include_tracks ?? null,
      manual_points: definition.manual_points || [], operator: $("operator").value.trim() || null,
    });
    await loadDetail(d.id);
    renderCandidates();
    drawCandidate();   // the candidates are stale now: their matches are drawn as doubtful
    toast(`Pattern version ${state.detail.pattern.version}: ${what} changed, ${state.detail.pattern.points.length} points. ` +
      "Press Search to identify it.");
  });
}

async function resetPattern() {
  const d = state.detail;
  if (!d) return;
  await action("Resetting the pattern", async () => {
    await api.post(`/api/sequences/${d.id}/pattern/reset`, { operator: $("operator").value.trim() || null });
    await loadDetail(d.id);
    renderCandidates();
    toast(`Pattern reset to the automatic one (version ${state.detail.pattern.version}, ${state.detail.pattern.points.length} points)`);
  });
}

// ---------------------------------------------------------------- search

function searchBody() {
  const method = $("search-method").value;
  if (method !== "tracking" || $("prior-last").checked) return { method };
  const number = (id) => { const v = $(id).value.trim(); return v === "" ? NaN : Number(v); };
  const prior = { ra_deg: number("prior-ra"), dec_deg: number("prior-dec"), roll_deg: number("prior-roll"),
    sigma_deg: number("prior-sigma") };
  for (const [key, id] of [["ra_deg", "prior-ra"], ["dec_deg", "prior-dec"], ["roll_deg", "prior-roll"], ["sigma_deg", "prior-sigma"]]) {
    if (!Number.isFinite(prior[key])) {
      $(id).focus();
      throw new api.ApiError(0, `the prior needs a number in ${id.replace("prior-", "")}`);
    }
  }
  // RA is asked in [0, 360): 360 and negative values are the same directions.
  prior.ra_deg = ((prior.ra_deg % 360) + 360) % 360;
  return { method, prior };
}

async function runSearch() {
  const d = state.detail;
  if (!d) return;
  const button = $("search");
  if (button.disabled) return;
  button.disabled = true;
  button.textContent = "Searching...";
  await action("The search", async () => {
    const result = await api.post(`/api/sequences/${d.id}/search`, searchBody());
    cancelSteps();
    await loadDetail(d.id, { fresh: true });
    state.rank = result.candidates.length ? 1 : null;
    await writeView({ sequence: d.id, rank: state.rank });
    await showCandidate();
    $("candidate-card").scrollIntoView({ block: "start" });
    await loadSequences();
    toast(`Search done: ${statusText(result.status)}, ${result.candidates.length} candidates` +
      `${result.reused ? " (unchanged pattern: the stored search)" : ""}`, result.status === "identified" ? "ok" : "error");
  });
  button.disabled = false;
  button.textContent = "Search";
}

function setupSearch() {
  const method = $("search-method");
  method.value = stored(localStorage, "starid-method", "bright_pair");
  const showPrior = () => { $("prior-box").hidden = method.value !== "tracking"; };
  method.addEventListener("change", () => {
    store(localStorage, "starid-method", method.value);
    showPrior();
    if (state.detail) renderSearchReplaces();
  });
  showPrior();
  // In the next frame: the count shows or hides a line, which changes the box again.
  new ResizeObserver(() => requestAnimationFrame(notePatternMore)).observe($("pattern-wrap"));
  // ... and as the table scrolls: the rows still below, none once its end is reached.
  $("pattern-wrap").addEventListener("scroll", () => requestAnimationFrame(notePatternMore), { passive: true });
  for (const id of ["prior-ra", "prior-dec", "prior-roll", "prior-sigma"]) {
    $(id).addEventListener("input", () => { $("prior-given").checked = true; });
  }
  $("prior-from-candidate").addEventListener("click", () => {
    // The shown rank's candidate of the latest search: its detail is current as soon as the search is (the
    // candidate's view, with its sky, arrives a request later; a click between took no prior and a
    // tracking search then found nothing).
    const c = state.detail?.search?.candidates?.[(state.rank ?? 1) - 1] ?? state.view?.candidate;
    if (!c) { toast("No candidate shown to start from", "error"); return; }
    $("prior-ra").value = fmt(c.ra_deg, 4); $("prior-dec").value = fmt(c.dec_deg, 4); $("prior-roll").value = fmt(c.roll_deg, 3);
    $("prior-given").checked = true;
  });
  $("search").addEventListener("click", runSearch);
}

// ---------------------------------------------------------------- candidate view

async function showCandidate() {
  const d = state.detail;
  const hasCandidates = !!(d && d.search && d.search.candidates.length);
  if (hasCandidates && !(state.rank >= 1 && state.rank <= d.search.candidates.length)) state.rank = 1;
  if (!hasCandidates) state.rank = null;
  dropStaleComment();   // typed for another candidate: it goes with it
  // Without candidates the decision panel stays: "no valid attitude" is still a verdict to give.
  $("candidate-body").hidden = !d;
  $("candidate-body").classList.toggle("empty", !hasCandidates);
  $("candidate-empty").hidden = hasCandidates;
  $("candidate-empty").textContent = !d || !d.search ? "No search yet: press Search."
    : `The latest search found no candidate (${statusText(d.search.status)}): edit the pattern and search again, ` +
      "or record that there is no valid attitude.";
  $("cand-rank").textContent = hasCandidates ? `rank ${state.rank} of ${d.search.candidates.length}` : "";
  $("cand-prev").disabled = !hasCandidates || state.rank <= 1;
  $("cand-next").disabled = !hasCandidates || state.rank >= d.search.candidates.length;
  if (!hasCandidates) { state.view = null; renderCandidates(); return; }
  renderCandidates();
  const view = await api.get(`/api/sequences/${d.id}/candidates/${state.rank}?mag=${state.mag}`);
  state.view = view;
  drawCandidate();
}

function drawCandidate() {
  const view = state.view;
  if (!view) return;
  const verdict = state.review?.candidates.find((v) => v.rank === view.rank);
  state.drawn = drawSky($("sky-canvas"), view, {
    names: $("show-names").checked, constellations: $("show-constellations").checked, edge: $("show-edge").checked,
    credible: !!verdict?.credible, highlight: player.highlight ?? undefined,
  });
  $("sky-canvas").dataset.credible = String(!!verdict?.credible);
  $("sky-canvas").dataset.view = `${view.rank}/${view.sky.mag_limit}`;   // the rank and magnitude limit drawn
  $("residual-factor").textContent = `×${state.drawn.factor}`;
  // What was drawn where, for whoever inspects the page (the browser tests check labels never overlap).
  $("sky-canvas").dataset.labels = JSON.stringify(state.drawn.labels.map(({ x, y, w, h, text, kind, owner }) =>
    ({ x, y, w, h, text, kind, owner })));
  $("sky-canvas").dataset.points = JSON.stringify(state.drawn.hits.filter((h) => h.kind === "point")
    .map(({ x, y, track, index, pinned }) => ({ x, y, track, index, pinned })));
  const c = view.candidate;
  const facts = [
    ["rank", `${view.rank} of ${view.n_candidates}`, "ranked by matched points, then false-match probability"],
    ["search", `${statusText(view.status)} (the sequence's search, not this candidate)`, "the status of the whole search"],
    ["deviation", `${fmt(c.deviation_arcsec, 1)}″ (${fmt(c.deviation_px_per_point, 3)} px/point)`,
      "sum over the pattern points of the angle to the nearest catalogue star under this attitude; per point in pixels"],
    ["false match", fmtProbability(c.false_match_probability),
      "probability that a chance alignment of catalogue stars fits as well; 'identified' needs at most 1e-6"],
    ["matched", `${c.n_matched} of ${view.sky.pattern_points.length} points` +
      (c.planets.length ? `, and ${c.planets.length} to ${c.planets.map((p) => p.name).join(", ")} (a planet: no catalogue star, ` +
        "so the deviation counts its point as unmatched)" : ""),
      "pattern points with a catalogue star (a planet explains a point without one)"],
    ...(c.rms_arcsec === null || c.rms_arcsec === undefined ? [] : [["residual",
      `${fmt(c.rms_arcsec, 1)}″ RMS over the ${c.n_matched} matched stars`,
      "how far the matched stars lie from where this attitude puts them: the answer's precision (the deviation " +
      "above also counts the points that no star explains, faint stars beyond the catalogue among them)"]]),
    ["RA, Dec", `${c.ra_deg.toFixed(4)}°, ${c.dec_deg.toFixed(4)}°`, "boresight"],
    ["roll", `${c.roll_deg.toFixed(4)}°`, "position angle of the image's up direction, from north through east"],
    ["field", `${view.sky.center.constellation}, ${sequenceTime(view.reference_time, state.detail?.telemetry)}`,
      "constellation at the centre, reference time"],
  ];
  if (c.fov_deg !== null && c.fov_deg !== undefined) facts.push(["field of view",
    `${c.fov_deg.toFixed(3)}° (f ${fmt(c.focal_length_px, 1)} px)`,
    "the horizontal field of view this candidate was found with: fitted on its stars, or found by the search " +
    "when the optics were unknown"]);
  if (c.centre_ra_deg !== null && c.centre_ra_deg !== undefined) facts.push(["image centre",
    `${c.centre_ra_deg.toFixed(4)}°, ${c.centre_dec_deg.toFixed(4)}°`,
    "RA, Dec of the image's centre pixel (astrometry.net's reference point); RA, Dec above are the boresight's"]);
  if (c.camera_fit) facts.push(["optics", opticsText(c.camera_fit, c.fov_deg !== null && c.fov_deg !== undefined),
    "optics fitted with this attitude (focal length from 3 stars, k1 from 6); 'used': the declared camera was " +
    "rejected by the stars, or the pattern was found at another focal length"]);
  $("cand-facts").replaceChildren(...facts.flatMap(([k, v, why]) => [el("dt", { title: why }, k), el("dd", { title: why }, v)]));
  const matches = view.sky.pattern_points.map((p) => {
    const target = p.name || (p.hip !== null ? `HIP ${p.hip}` : p.planet ? `planet ${p.planet}` : "unmatched");
    return `${p.track !== null ? `T${p.track}` : `hand ${p.hand}`} → ${target}${p.residual_arcsec !== null ? ` (${fmt(p.residual_arcsec, 1)}″)` : ""}`;
  });
  $("cand-matches").textContent = matches.join(" · ");
}

function opticsText(fit, foundFocalLength = false) {
  const parts = [];
  if (fit.focal_length_px !== null) parts.push(`f ${fmt(fit.focal_length_px, 1)} ± ${fmt(fit.sigma.focal_length_px, 1)} px`);
  if (fit.k1 !== null) parts.push(`k1 ${fmt(fit.k1, 4)} ± ${fmt(fit.sigma.k1, 4)}`);
  return `${parts.join(", ")}; rms ${fmt(fit.rms_px, 2)} px over the ${fit.over}; ${fit.adopted ? "used" : foundFocalLength ? "not used: the field of view above is kept" : "declared camera kept"}`;
}

function goToRank(rank) {
  return inTurn(() => showRank(rank));
}

async function showRank(rank) {
  const d = state.detail;
  if (!d || !d.search || !d.search.candidates.length) return;
  rank = Math.min(Math.max(1, rank), d.search.candidates.length);
  if (rank === state.rank) return;
  moved();
  await action("Showing the candidate", async () => {
    cancelSteps();
    state.rank = rank;
    renderCandidates();
    await writeView({ rank });   // first, so the 3D view moves with the console
    await showCandidate();
  });
}

function stepCandidate(delta) {
  return inTurn(async () => {
    const d = state.detail;
    if (!d || !d.search || !d.search.candidates.length) return;
    const rank = Math.min(Math.max(1, state.rank + delta), d.search.candidates.length);
    if (rank === state.rank) {
      toast(delta > 0 ? "This is the last candidate" : "This is the first candidate", "ok", { untilMove: true });
      return;
    }
    await showRank(rank);
  });
}

// The words for another console's search replacing the candidates shown (state.rank already set).
function replacedBy(searchId) {
  return `a new search (#${searchId}) replaced the candidates shown; ` +
    (state.rank ? `back at rank ${state.rank}` : "it found no candidates");
}

// What another console changed, in the notice over the sequence's header card; any step this console had open
// is closed (it was about what was shown before). The page is not scrolled to it, nor moved by it: it comes at
// any moment, under an operator's pointer, and it is on screen wherever the page is (setupNotice).
function announceChange(what) {
  const notice = $("change-notice");
  notice.hidden = false;   // shown first: a live region's new words are read only when it is shown
  // It lies over the header card and so hides the sequence's name: it says whose it is.
  const d = state.detail;
  const whose = d ? ` on ${d.sequence_id || d.filename || "sequence"} (#${d.id})` : "";
  $("change-notice-text").textContent = `Changed by another console${whose}: ${what}.`;
  cancelSteps();
  $("comment").value = "";   // it was about what was shown before, as the closed step's reason was
}

// The change notice takes no place in the page (static/console.css .notice-anchor): it lies over the sequence's
// header card, beside its status and verdict, and stays just under the top bar when the page is scrolled, then
// only as tall and wide as its words ("stuck"). Its place follows the sizes of the top bar, of the header card
// and of the verdict. It goes with this console's verdict, with another sequence opened, or with its button.
function setupNotice() {
  const root = document.documentElement.style;
  const anchor = document.querySelector(".notice-anchor"), topbar = document.querySelector(".topbar");
  const header = document.querySelector(".seq-header"), verdict = document.querySelector(".seq-verdict");
  // Held under the top bar: the header card, just under the anchor in the page, has gone up past it.
  const stuck = () => anchor.classList.toggle("stuck",
    header.getBoundingClientRect().top < anchor.getBoundingClientRect().top - 0.5);
  const place = () => {
    const h = header.getBoundingClientRect(), v = verdict.getBoundingClientRect();
    root.setProperty("--topbar-height", `${Math.ceil(topbar.getBoundingClientRect().height)}px`);
    if (!h.width) return;   // no sequence open yet
    root.setProperty("--seq-header-height", `${h.height}px`);
    root.setProperty("--notice-right", `${Math.max(0, h.right - v.left + 12)}px`);
    stuck();
  };
  const observer = new ResizeObserver(place);
  for (const box of [topbar, header, verdict]) observer.observe(box);
  window.addEventListener("scroll", stuck, { passive: true });
  $("change-notice-close").addEventListener("click", () => { $("change-notice").hidden = true; });
}

// After this console's confirmation or rejection (or its refusal): the verdict, the lists and the 3D
// view agree. A refusal can mean another console's search replaced the candidates before the view
// polling noticed; then the new search is shown from rank 1, announced as the polling would have.
async function afterVerdict() {
  const d = state.detail;
  const shownSearch = d.search?.search_id ?? null;
  const detail = await loadDetail(d.id);
  const newSearch = detail.search?.search_id ?? null;
  if (newSearch !== shownSearch) {
    state.rank = detail.search?.candidates.length ? 1 : null;
    announceChange(replacedBy(newSearch));
    await writeView({ sequence: d.id, rank: state.rank });
    await showCandidate();
  } else {
    renderCandidates();
  }
  await Promise.all([loadAttitudes(), loadSequences()]);
}

function setupSkyCanvas() {
  const canvas = $("sky-canvas"), tip = $("sky-tip");
  const toCanvas = (e) => {
    const rect = canvas.getBoundingClientRect();
    return [(e.clientX - rect.left) * canvas.width / rect.width, (e.clientY - rect.top) * canvas.height / rect.height];
  };
  canvas.addEventListener("mousemove", (e) => {
    const hit = state.drawn && hitAt(state.drawn, ...toCanvas(e));
    if (!hit) { tip.hidden = true; canvas.style.cursor = ""; return; }
    tip.textContent = hit.text;
    tip.hidden = false;
    const rect = canvas.getBoundingClientRect();
    tip.style.left = `${Math.min(e.clientX - rect.left + 14, rect.width - 220)}px`;
    tip.style.top = `${e.clientY - rect.top + 14}px`;
    canvas.style.cursor = hit.kind === "point" && hit.track !== null ? "pointer" : "";
  });
  canvas.addEventListener("mouseleave", () => { tip.hidden = true; });
  canvas.addEventListener("click", (e) => {
    const hit = state.drawn && hitAt(state.drawn, ...toCanvas(e));
    if (!hit || hit.kind !== "point" || hit.track === null) return;
    player.showTrack(hit.track);
    drawCandidate();
    $("player-card").scrollIntoView({ block: "nearest" });
    toast(`T${hit.track} is ringed in the snapshots`);
  });
}

function setupCandidate() {
  $("cand-prev").addEventListener("click", () => stepCandidate(-1));
  $("cand-next").addEventListener("click", () => stepCandidate(+1));
  for (const id of ["show-names", "show-constellations", "show-edge"]) $(id).addEventListener("change", drawCandidate);
  const slider = $("mag-slider");
  slider.addEventListener("input", () => { $("mag-label").textContent = Number(slider.value).toFixed(1); });
  slider.addEventListener("change", () => action("Changing the magnitude limit", async () => {
    state.mag = Number(slider.value);
    await writeView({ mag: state.mag });
    await showCandidate();
  }));
  setupSkyCanvas();
  setupDecision({ goToRank, afterVerdict });
}

// ---------------------------------------------------------------- keyboard and help

function toggleHelp(show) {
  const help = $("help");
  help.hidden = show === undefined ? !help.hidden : !show;
  if (!help.hidden) $("help-close").focus();
}

// j/k: the next or previous sequence of the queue as it was when this one was opened. A verdict moves
// the sequence itself (confirmed work goes to the end of "needs an operator first"): stepping from where
// it went would jump into finished work instead of to the sequence that followed it.
function nextSequence(delta) {
  return inTurn(() => openNext(delta));
}

function openNext(delta) {
  const ids = state.queueIds;
  if (!ids.length) return;
  const current = state.detail?.id;
  const seen = state.openedFrom?.id === current ? state.openedFrom.ids : ids;
  const at = current === undefined ? -1 : seen.indexOf(current);
  let next = at < 0 ? ids[0] : null;
  for (let k = at + delta; at >= 0 && k >= 0 && k < seen.length; k += delta) {
    if (seen[k] !== current && ids.includes(seen[k])) { next = seen[k]; break; }
  }
  // Nothing beyond it in the queue as it was (a filter since widened, say): the list as it is now.
  const now = ids.indexOf(current);
  if (next === null && now >= 0 && ids[now + delta] !== undefined) next = ids[now + delta];
  if (next === null) {
    toast(delta > 0 ? "Last sequence of this page" : "First sequence of this page", "ok", { untilMove: true });
    return;
  }
  return openSequence(next);
}

function setupKeys() {
  $("help-open").addEventListener("click", () => toggleHelp(true));
  $("help-close").addEventListener("click", () => toggleHelp(false));
  $("help").addEventListener("click", (e) => { if (e.target === $("help")) toggleHelp(false); });
  document.addEventListener("keydown", (e) => {
    if (e.key === "Escape") { toggleHelp(false); cancelSteps(); return; }
    const t = e.target;
    const typing = t instanceof HTMLInputElement || t instanceof HTMLTextAreaElement || t instanceof HTMLSelectElement;
    if (typing || e.altKey || e.ctrlKey || e.metaKey) return;
    if (e.key === "?") { e.preventDefault(); toggleHelp(); return; }
    if (!$("help").hidden || $("panel-work").hidden) return;
    const keys = {
      ArrowRight: () => stepCandidate(+1), ArrowLeft: () => stepCandidate(-1),
      s: runSearch, " ": () => player.togglePlay(), c: confirmClick, r: openReject,
      j: () => nextSequence(+1), k: () => nextSequence(-1),
    };
    if (keys[e.key]) { e.preventDefault(); keys[e.key](); return; }
    if (/^[1-9]$/.test(e.key)) { e.preventDefault(); goToRank(Number(e.key)); }
  });
}

// ---------------------------------------------------------------- this session's view state

async function pollView() {
  if (state.busy) return;
  let doc;
  try { doc = await api.get(viewPath()); } catch { return; /* the health badge reports an unreachable server */ }
  if (state.busy) return;
  note3D();
  await followView(doc);
  await takeRequest(doc);
}

// What the view state read says changed (elsewhere, or by the 3D view drawing this session): shown and announced.
async function followView(doc) {
  const d = state.detail, review = state.review;
  const selectionChanged = doc.revision > state.viewRevision;   // only the 3D view writes this session besides us
  const sameSequence = d && doc.sequence === d.id;
  const searchChanged = sameSequence && doc.search_id !== (d.search ? d.search.search_id : null);
  const patternChanged = sameSequence && doc.pattern_version !== d.pattern.version;
  const verdictChanged = sameSequence && (doc.confirmation_id !== (review?.confirmation?.id ?? null) ||
    doc.rejection_id !== (review?.rejection?.id ?? null));
  if (!selectionChanged && !searchChanged && !patternChanged && !verdictChanged) return;
  state.viewRevision = Math.max(state.viewRevision, doc.revision);
  await action("Following the archive", async () => {
    if (doc.sequence === null) return;
    if (!d || doc.sequence !== d.id || searchChanged || patternChanged || verdictChanged) await loadDetail(doc.sequence);
    if (doc.mag !== state.mag) {
      state.mag = doc.mag;
      $("mag-slider").value = doc.mag;
      $("mag-label").textContent = doc.mag.toFixed(1);
    }
    if (selectionChanged) state.rank = doc.rank;
    else if (searchChanged) {
      state.rank = doc.n_candidates ? 1 : null;
      // The session's rank was of the search replaced (or none, before a first search): written, so that the
      // session (and the 3D view drawing it) shows the rank this console shows.
      if (doc.rank !== state.rank) await writeView({ rank: state.rank });
    }
    // Announce what changed elsewhere rather than swap it silently.
    const notes = [];
    if (searchChanged && !d?.search) toast(`${d?.sequence_id || "The sequence"} was searched: ${statusText(doc.status)}`);
    else if (searchChanged) notes.push(replacedBy(doc.search_id));
    if (patternChanged && !searchChanged) notes.push(`the pattern changed elsewhere (version ${doc.pattern_version}): the candidates are stale until a new search`);
    if (verdictChanged) notes.push(`the sequence's verdict changed: ${verdictSummary()}`);
    if (notes.length) announceChange(notes.join("; "));
    await showCandidate();
    if (verdictChanged || searchChanged) await Promise.all([loadAttitudes(), loadSequences()]);
  });
}

// The 3D view's Confirm of a rank that needs the second step (not the credible best, or replacing the
// sequence's verdict) is sent to the console it draws: this session's view state carries the request
// (`confirm_request`, app/workflow/view.py request_confirmation), and the console opens its second step
// for that rank on its Sequence tab, once per request.
let lastRequest = null;   // the number of the request last seen (null: none read yet; 0: there was none)

async function takeRequest(doc) {
  const request = doc.confirm_request;
  const number = request ? request.number : 0;
  const first = lastRequest === null;
  if (number === lastRequest) return;
  lastRequest = number;
  // The first read only learns where the requests stand: one older than this page is not replayed.
  if (first || !request) return;
  await action("Taking the 3D view's confirmation", async () => {
    const d = state.detail;
    if (!d || request.sequence !== d.id || (d.search?.search_id ?? null) !== request.search_id) {
      toast(`The 3D view asked to confirm rank ${request.rank} of sequence #${request.sequence}, which this ` +
        "console no longer shows as it was: open it and confirm it here", "error");
      return;
    }
    await openPanel("panel-work");
    if (request.rank !== state.rank) {
      cancelSteps();
      state.rank = request.rank;
      await writeView({ rank: request.rank });
      await showCandidate();
    }
    confirmSentFrom("the 3D view");
    // The comment typed with it in the 3D view, unless this console's box holds one of its own already.
    const box = $("comment");
    if (request.comment && !box.value.trim()) {
      box.value = request.comment;
      state.sentComment = request.comment;   // cleared with the step it came for (cancelSteps)
      commentIsFor();
    }
    else if (request.comment && box.value.trim() !== request.comment) {
      toast("The 3D view's comment was not put in the comment box, which holds yours: " + request.comment);
    }
  });
}

// ---------------------------------------------------------------- 3D view tab

function note3D() {
  if ($("panel-3d").hidden || !$("viewer-frame").dataset.url) return;
  const url = $("viewer-frame").dataset.url;
  // Each console has its own 3D view: the address names this session (GET /api/viewer?session=...).
  $("viewer-note").replaceChildren(el("span", {}, "Draws this console's selection (other consoles have their own). " +
    "Also at ", el("a", { href: url, target: "_blank", rel: "noopener" }, url),
    " (this machine only); its Next / Prev / Confirm act on this console."));
}

// The operator's name for this console's 3D view, and the 3D view at the bare address drawing this console.
async function follow3D() {
  try {
    await shareOperator();
    await api.put("/api/viewer", { session: SESSION });
    note3D();
  } catch (err) {
    toast(`The 3D view cannot follow this console: ${errorText(err)}`, "error");
  }
}

// Each tab keeps its own scroll position: the 3D view opens at its top (not at the depth the operator
// had scrolled to in the sequence tab, where it showed an empty panel), and coming back finds the
// sequence tab where it was left.
const scrolled = {};

async function openPanel(panelId) {
  const from = document.querySelector(".tab.active")?.dataset.panel;
  if (from === panelId) return;
  if (from) scrolled[from] = window.scrollY;
  for (const tab of document.querySelectorAll(".tab")) {
    const active = tab.dataset.panel === panelId;
    tab.classList.toggle("active", active);
    tab.setAttribute("aria-selected", active);
    $(tab.dataset.panel).hidden = !active;
  }
  window.scrollTo(0, scrolled[panelId] ?? 0);
  if (panelId !== "panel-3d") return;
  try {
    const info = await api.get(`/api/viewer?session=${encodeURIComponent(SESSION)}`);
    if (!info.available) { $("viewer-note").textContent = info.detail || "The 3D view is not running."; return; }
    // The address of a 3D view drawing this console's session (the 3D view at the bare address draws the
    // console that opened its 3D tab last: follow3D).
    const url = info.url;
    $("viewer-frame").dataset.url = url;
    await follow3D();
    if ($("viewer-frame").src !== url) $("viewer-frame").src = url;
  } catch (err) {
    $("viewer-note").textContent = `The 3D view is not available: ${errorText(err)}`;
  }
}

function setup3D() {
  for (const tab of document.querySelectorAll(".tab")) tab.addEventListener("click", () => openPanel(tab.dataset.panel));
}

// ---------------------------------------------------------------- start

async function start() {
  setupOperator();
  setupQueue({ select: selectSequence });
  setupSearch();
  setupCandidate();
  setupKeys();
  setup3D();
  setupNotice();
  $("reset-pattern").addEventListener("click", resetPattern);
  $("pick-mode").addEventListener("change", (e) => player.setPicking(e.target.checked));
  $("calibrate-button").addEventListener("click", () => action("Calibrating the camera", async () => {
    const doc = await calibrate($("operator").value);
    if (doc) toast(`Calibration version ${doc.version} stored: later uploads without a camera block use it`);
  }));
  document.body.dataset.session = SESSION;
  await Promise.all([checkHealth(), loadSequences(), loadAttitudes(), loadSpacecraft()]);
  await pollView();   // a reloaded tab finds its own selection again
  setInterval(pollView, POLL_MS);
  setInterval(() => { if (!state.busy) loadSequences({ periodic: true }); }, QUEUE_REFRESH_MS);
  setInterval(checkHealth, 15000);
  document.body.dataset.ready = "1";
}

start();
