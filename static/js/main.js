// Operator console: wires the panels to the REST API and to the shared view state.
//
// The selection (sequence, candidate rank, magnitude limit) is stored on the server
// (PUT /api/view) and polled back every second (GET /api/view), so the 3D view and
// other consoles follow each other. Every action ends in a visible result or error.
import * as api from "./api.js";
import { $, el, toast, errorText, trackColour, fmt, fmtTime } from "./dom.js";
import { SnapshotPlayer } from "./player.js";
import { drawSky, candidateFacts } from "./sky.js";

const PAGE_SIZE = 8;
const ATTITUDE_PAGE = 6;
const POLL_MS = 1000;

const state = {
  detail: null,          // GET /api/sequences/{id}
  view: null,            // the last candidate view shown
  rank: null,
  mag: 6.0,
  seqOffset: 0,
  attOffset: 0,
  viewRevision: -1,      // newest shared-state revision applied or written
  busy: 0,               // actions in flight: the poll does not apply state meanwhile
};

const player = new SnapshotPlayer({
  onToggleTrack: (track) => editPattern((def) => toggleTrack(def, track), `track T${track}`),
  onPick: (snapshot, x, y) => editPattern((def) => ({ ...def, manual_points: [...(def.manual_points || []), { snapshot, x, y }] }),
    `a point at (${x}, ${y}) of snapshot ${snapshot + 1}`),
  onRemoveManual: (k) => editPattern((def) => ({ ...def, manual_points: def.manual_points.filter((_, i) => i !== k) }),
    `hand-picked point ${k + 1}`),
  onMessage: (text) => toast(text),
});

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

async function writeView(changes) {
  try {
    const doc = await api.put("/api/view", changes);
    state.viewRevision = Math.max(state.viewRevision, doc.revision);
  } catch (err) {
    toast(`Could not share the selection with the 3D view: ${errorText(err)}`, "error");
  }
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

// ---------------------------------------------------------------- health

async function checkHealth() {
  const badge = $("health");
  try {
    const h = await api.get("/api/health");
    badge.textContent = h.status === "ok" ? `ready · ${h.index.stars} stars` : `degraded`;
    badge.className = `health ${h.status === "ok" ? "ok" : "bad"}`;
  } catch (err) {
    badge.textContent = "server unreachable";
    badge.className = "health bad";
  }
}

// ---------------------------------------------------------------- upload

function setupUpload() {
  const zone = $("dropzone"), input = $("file-input");
  input.addEventListener("change", () => { uploadFiles([...input.files]); input.value = ""; });
  zone.addEventListener("keydown", (e) => { if (e.key === "Enter" || e.key === " ") input.click(); });
  for (const type of ["dragenter", "dragover"]) {
    zone.addEventListener(type, (e) => { e.preventDefault(); zone.classList.add("over"); });
  }
  for (const type of ["dragleave", "drop"]) {
    zone.addEventListener(type, (e) => { e.preventDefault(); zone.classList.remove("over"); });
  }
  zone.addEventListener("drop", (e) => uploadFiles([...(e.dataTransfer?.files || [])]));
}

async function uploadFiles(files) {
  if (!files.length) return;
  const list = $("upload-list");
  let lastStored = null, failures = 0;
  // One at a time: the server validates and extracts each; the list shows each result next to its file.
  for (const file of files) {
    const bar = el("progress", { max: 1, value: 0 });
    const result = el("div", {}, "uploading...");
    list.prepend(el("li", { class: "upload-item", dataset: { file: file.name } },
      el("div", { class: "name" }, file.name), bar, result));
    try {
      const { status, body } = await api.uploadFile(file, (f) => { bar.value = f; });
      bar.value = 1;
      result.className = "ok";
      result.textContent = status === 201
        ? `stored as #${body.id}: ${body.pattern.points.length} pattern points`
        : `already stored as #${body.id}`;
      lastStored = body.id;
    } catch (err) {
      failures++;
      bar.remove();
      result.className = "error";
      result.replaceChildren(el("div", {}, err.detail),
        err.problems.length ? el("ul", { class: "problems" },
          err.problems.map((p) => el("li", {}, el("code", {}, p.location), ": ", p.message))) : null);
    }
  }
  toast(failures ? `${files.length - failures} of ${files.length} files uploaded; see the errors next to the files`
    : `${files.length} file${files.length > 1 ? "s" : ""} uploaded`, failures ? "error" : "ok");
  await loadSequences();
  if (lastStored !== null) await selectSequence(lastStored);
}

// ---------------------------------------------------------------- sequence list

async function loadSequences() {
  const status = $("filter-status").value, spacecraft = $("filter-spacecraft").value.trim();
  const query = new URLSearchParams({ offset: state.seqOffset, limit: PAGE_SIZE });
  if (status) query.set("status", status);
  if (spacecraft) query.set("spacecraft", spacecraft);
  try {
    const page = await api.get(`/api/sequences?${query}`);
    const list = $("sequence-list");
    list.replaceChildren(...page.items.map((s) => el("li", {
      class: state.detail && state.detail.id === s.id ? "selected" : "",
      dataset: { id: s.id }, tabindex: 0,
      onclick: () => selectSequence(s.id),
      onkeydown: (e) => { if (e.key === "Enter") selectSequence(s.id); },
    }, el("span", { class: "mono" }, s.sequence_id || `#${s.id}`),
    el("span", { class: `badge ${s.status}` }, s.status.replace("_", " ")),
    el("span", { class: "sub" }, `#${s.id} · ${s.spacecraft || "unknown spacecraft"} · ${fmtTime(s.first_time)}`))));
    if (!page.items.length) list.replaceChildren(el("li", { class: "dim" }, page.total ? "no more" : "no sequences match"));
    const last = Math.min(page.total, state.seqOffset + page.items.length);
    $("seq-page-info").textContent = page.total ? `${state.seqOffset + 1}-${last} of ${page.total}` : "0";
    $("seq-prev-page").disabled = state.seqOffset === 0;
    $("seq-next-page").disabled = last >= page.total;
  } catch (err) {
    toast(`Could not list the sequences: ${errorText(err)}`, "error");
  }
}

function setupSequenceList() {
  let debounce = null;
  $("filter-status").addEventListener("change", () => { state.seqOffset = 0; loadSequences(); });
  $("filter-spacecraft").addEventListener("input", () => {
    clearTimeout(debounce);
    debounce = setTimeout(() => { state.seqOffset = 0; loadSequences(); }, 300);
  });
  $("seq-prev-page").addEventListener("click", () => { state.seqOffset = Math.max(0, state.seqOffset - PAGE_SIZE); loadSequences(); });
  $("seq-next-page").addEventListener("click", () => { state.seqOffset += PAGE_SIZE; loadSequences(); });
}

// ---------------------------------------------------------------- attitudes

async function loadAttitudes() {
  try {
    const page = await api.get(`/api/attitudes?offset=${state.attOffset}&limit=${ATTITUDE_PAGE}`);
    $("attitude-list").replaceChildren(...page.items.map((a) => el("tr", {
      class: a.current ? "" : "superseded", dataset: { id: a.id },
      title: `attitude ${a.id}, rank ${a.rank}, confirmed ${fmtTime(a.confirmed_at)}${a.comment ? `: ${a.comment}` : ""}`,
    },
    el("td", {}, a.sequence_id || `#${a.sequence}`), el("td", {}, fmt(a.ra_deg, 3)), el("td", {}, fmt(a.dec_deg, 3)),
    el("td", {}, fmt(a.roll_deg, 2)), el("td", {}, a.operator),
    el("td", {}, el("a", { href: a.apm_url, download: "", class: "apm-link" }, "APM"), " ",
      a.aem_url ? el("a", { href: a.aem_url, download: "", class: "aem-link" }, "AEM") : null))));
    if (!page.items.length) $("attitude-list").replaceChildren(el("tr", {}, el("td", { colspan: 6, class: "dim" }, "none yet")));
    const last = Math.min(page.total, state.attOffset + page.items.length);
    $("att-page-info").textContent = page.total ? `${state.attOffset + 1}-${last} of ${page.total}` : "";
    $("att-prev-page").disabled = state.attOffset === 0;
    $("att-next-page").disabled = last >= page.total;
  } catch (err) {
    toast(`Could not list the confirmed attitudes: ${errorText(err)}`, "error");
  }
}

// ---------------------------------------------------------------- the selected sequence

async function selectSequence(id) {
  await action("Opening the sequence", async () => {
    await loadDetail(id);
    await writeView({ sequence: id });
    state.rank = state.detail.search && state.detail.search.candidates.length ? 1 : null;
    await showCandidate();
  });
}

async function loadDetail(id) {
  const detail = await api.get(`/api/sequences/${id}`);
  state.detail = detail;
  $("empty-hint").hidden = true;
  $("workspace").hidden = false;
  $("seq-title").textContent = detail.sequence_id || `sequence #${detail.id}`;
  $("seq-meta").textContent = `#${detail.id} · ${detail.spacecraft || "unknown spacecraft"} · ${detail.camera.name || "camera"} · ` +
    `${detail.n_snapshots} snapshots from ${fmtTime(detail.first_time)} · ${detail.filename || ""}`;
  const badge = $("seq-status");
  badge.textContent = detail.status.replace("_", " ");
  badge.className = `badge ${detail.status}`;
  for (const li of $("sequence-list").children) li.classList.toggle("selected", Number(li.dataset.id) === id);
  player.setSequence(detail);
  renderPattern();
  renderSearchSummary();
  return detail;
}

function renderPattern() {
  const d = state.detail;
  const pattern = d.pattern;
  const inPattern = new Map(pattern.points.filter((p) => p.track !== null).map((p) => [p.track, p]));
  const automatic = d.extraction.pattern;   // every track the automatic pattern could use
  const rows = [];
  const seen = new Set();
  for (const p of automatic) {
    if (p.track === null) continue;
    seen.add(p.track);
    const current = inPattern.get(p.track);
    const shown = current || p;
    rows.push(el("tr", { class: current ? "" : "out", dataset: { track: p.track } },
      el("td", {}, el("input", { type: "checkbox", checked: !!current, "aria-label": `track ${p.track} in pattern`,
        onchange: () => editPattern((def) => toggleTrack(def, p.track), `track T${p.track}`) })),
      el("td", {}, el("span", { class: "swatch", style: `background:${trackColour(p.track)}` }), `T${p.track}`),
      el("td", {}, shown.sightings), el("td", {}, `${fmt(shown.x, 1)}, ${fmt(shown.y, 1)}`), el("td", {}, fmt(shown.brightness, 0))));
  }
  // Tracks in the pattern that the automatic one leaves out (included explicitly).
  for (const [track, p] of inPattern) {
    if (seen.has(track)) continue;
    rows.push(el("tr", { dataset: { track } },
      el("td", {}, el("input", { type: "checkbox", checked: true, "aria-label": `track ${track} in pattern`,
        onchange: () => editPattern((def) => toggleTrack(def, track), `track T${track}`) })),
      el("td", {}, `T${track}`), el("td", {}, p.sightings), el("td", {}, `${fmt(p.x, 1)}, ${fmt(p.y, 1)}`), el("td", {}, fmt(p.brightness, 0))));
  }
  (pattern.definition.manual_points || []).forEach((m, k) => {
    rows.push(el("tr", { class: "manual", dataset: { manual: k } },
      el("td", {}, el("button", { class: "small", title: "remove this point",
        onclick: () => editPattern((def) => ({ ...def, manual_points: def.manual_points.filter((_, i) => i !== k) }), `hand-picked point ${k + 1}`) }, "×")),
      el("td", {}, `◆ hand ${k + 1}`), el("td", {}, `snap. ${m.snapshot + 1}`), el("td", {}, `${fmt(m.x, 1)}, ${fmt(m.y, 1)}`), el("td", {}, "")));
  });
  $("pattern-rows").replaceChildren(...rows);
  $("pattern-caption").textContent = `version ${pattern.version ?? "-"} (${pattern.kind}${pattern.operator ? `, ${pattern.operator}` : ""}): ` +
    `${pattern.points.length} points, reference snapshot ${pattern.reference_snapshot + 1}`;
}

function renderSearchSummary() {
  const s = state.detail.search;
  const stale = s && s.pattern_version !== state.detail.pattern.version;
  $("search-summary").textContent = s
    ? `Latest search: ${s.status.replace("_", " ")}, ${s.candidates.length} candidates in ${Math.round(s.elapsed_ms)} ms ` +
      `(pattern version ${s.pattern_version})${stale ? " - the pattern changed since: search again" : ""}. ${(s.notes || []).join("; ")}`
    : "Not searched yet.";
}

async function editPattern(change, what) {
  const d = state.detail;
  if (!d) return;
  await action("Changing the pattern", async () => {
    const definition = change(structuredClone(d.pattern.definition));
    const doc = await api.put(`/api/sequences/${d.id}/pattern`, {
      exclude_tracks: definition.exclude_tracks || [], include_tracks: definition.include_tracks ?? null,
      manual_points: definition.manual_points || [], operator: $("operator").value.trim() || null,
    });
    d.pattern = doc;
    player.setSequence(d);
    renderPattern();
    renderSearchSummary();
    toast(`Pattern version ${doc.version}: ${what} changed, ${doc.points.length} points. Press Search to identify it.`);
  });
}

async function resetPattern() {
  const d = state.detail;
  if (!d) return;
  await action("Resetting the pattern", async () => {
    d.pattern = await api.post(`/api/sequences/${d.id}/pattern/reset`, { operator: $("operator").value.trim() || null });
    player.setSequence(d);
    renderPattern();
    renderSearchSummary();
    toast(`Pattern reset to the automatic one (version ${d.pattern.version}, ${d.pattern.points.length} points)`);
  });
}

async function runSearch() {
  const d = state.detail;
  if (!d) return;
  const button = $("search");
  button.disabled = true;
  button.textContent = "Searching...";
  await action("The search", async () => {
    const result = await api.post(`/api/sequences/${d.id}/search`, {});
    await loadDetail(d.id);
    state.rank = result.candidates.length ? 1 : null;
    await writeView({ sequence: d.id, rank: state.rank });
    await showCandidate();
    $("candidate-card").scrollIntoView({ block: "start" });
    await loadSequences();
    toast(`Search done: ${result.status.replace("_", " ")}, ${result.candidates.length} candidates`,
      result.status === "identified" ? "ok" : "error");
  });
  button.disabled = false;
  button.textContent = "Search";
}

// ---------------------------------------------------------------- candidate view

async function showCandidate() {
  const d = state.detail;
  const hasCandidates = !!(d && d.search && d.search.candidates.length);
  if (hasCandidates && !(state.rank >= 1 && state.rank <= d.search.candidates.length)) state.rank = 1;
  $("candidate-body").hidden = !hasCandidates;
  $("candidate-empty").hidden = hasCandidates;
  $("candidate-empty").textContent = !d || !d.search ? "No search yet: press Search."
    : `The latest search found no candidate (${d.search.status.replace("_", " ")}).`;
  $("cand-rank").textContent = hasCandidates ? `rank ${state.rank} of ${d.search.candidates.length}` : "";
  $("cand-prev").disabled = !hasCandidates || state.rank <= 1;
  $("cand-next").disabled = !hasCandidates || state.rank >= d.search.candidates.length;
  $("confirm").textContent = hasCandidates ? `Confirm rank ${state.rank}` : "Confirm";
  renderConfirmed();
  if (!hasCandidates) return;
  const view = await api.get(`/api/sequences/${d.id}/candidates/${state.rank}?mag=${state.mag}`);
  state.view = view;
  drawCandidate();
}

function drawCandidate() {
  const view = state.view;
  if (!view) return;
  const factor = drawSky($("sky-canvas"), view, {
    names: $("show-names").checked, constellations: $("show-constellations").checked, edge: $("show-edge").checked,
  });
  const facts = candidateFacts(view);
  facts.push(["residuals", `drawn × ${factor} (green lines)`]);
  $("cand-facts").replaceChildren(...facts.flatMap(([k, v]) => [el("dt", {}, k), el("dd", {}, v)]));
  const matches = view.sky.pattern_points.map((p) => {
    const target = p.name || (p.hip !== null ? `HIP ${p.hip}` : p.planet ? `planet ${p.planet}` : "unmatched");
    return `${p.track !== null ? `T${p.track}` : "hand"} → ${target}${p.residual_arcsec !== null ? ` (${fmt(p.residual_arcsec, 1)}″)` : ""}`;
  });
  $("cand-matches").textContent = matches.join(" · ");
}

async function stepCandidate(delta) {
  const d = state.detail;
  if (!d || !d.search || !d.search.candidates.length) return;
  const rank = Math.min(Math.max(1, state.rank + delta), d.search.candidates.length);
  if (rank === state.rank) {
    toast(delta > 0 ? "This is the last candidate" : "This is the first candidate");
    return;
  }
  await action("Showing the candidate", async () => {
    state.rank = rank;
    await writeView({ rank });   // first, so the 3D view moves with the console
    await showCandidate();
  });
}

function renderConfirmed() {
  const d = state.detail;
  const box = $("confirmed");
  const c = d && d.confirmation;
  if (!c) { box.hidden = true; return; }
  box.hidden = false;
  box.replaceChildren(
    el("div", {}, el("strong", {}, `Confirmed: attitude #${c.id}`), ` (rank ${c.rank} of search ${c.search_id})`),
    el("div", { class: "dim" }, `by ${c.operator} at ${fmtTime(c.confirmed_at)}${c.comment ? ` - "${c.comment}"` : ""}`),
    el("div", { class: "mono" }, `RA ${fmt(c.ra_deg, 4)}°  Dec ${fmt(c.dec_deg, 4)}°  roll ${fmt(c.roll_deg, 4)}°`),
    el("div", {}, el("a", { href: c.apm_url, download: "", id: "confirmed-apm" }, "Download APM"),
      c.aem_url ? el("a", { href: c.aem_url, download: "", id: "confirmed-aem" }, "Download AEM") : null));
}

async function confirmCandidate(e) {
  e.preventDefault();
  const d = state.detail;
  if (!d || !state.rank) return;
  const operator = $("operator").value.trim();
  if (!operator) {
    toast("Enter the operator's name to confirm", "error");
    $("operator").focus();
    return;
  }
  await action("The confirmation", async () => {
    const c = await api.post(`/api/sequences/${d.id}/confirm`, { rank: state.rank, operator, comment: $("comment").value.trim() || null });
    await loadDetail(d.id);
    renderConfirmed();
    $("confirmed").scrollIntoView({ block: "nearest" });
    await Promise.all([loadAttitudes(), loadSequences()]);
    toast(`Attitude #${c.id} confirmed by ${c.operator}: RA ${fmt(c.ra_deg, 3)}°, Dec ${fmt(c.dec_deg, 3)}°, roll ${fmt(c.roll_deg, 2)}°`);
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
  $("confirm-form").addEventListener("submit", confirmCandidate);
  document.addEventListener("keydown", (e) => {
    const t = e.target;
    const typing = t instanceof HTMLInputElement || t instanceof HTMLTextAreaElement || t instanceof HTMLSelectElement;
    if (typing || e.altKey || e.ctrlKey || e.metaKey || $("panel-work").hidden) return;
    if (e.key === "ArrowRight") { e.preventDefault(); stepCandidate(+1); }
    if (e.key === "ArrowLeft") { e.preventDefault(); stepCandidate(-1); }
  });
}

// ---------------------------------------------------------------- shared view state

async function pollView() {
  if (state.busy) return;
  let doc;
  try { doc = await api.get("/api/view"); } catch { return; /* the health badge reports an unreachable server */ }
  if (state.busy) return;
  const d = state.detail;
  const selectionChanged = doc.revision > state.viewRevision;
  const archiveChanged = d && doc.sequence === d.id && (doc.pattern_version !== d.pattern.version ||
    doc.search_id !== (d.search ? d.search.search_id : null) || doc.confirmation_id !== (d.confirmation ? d.confirmation.id : null));
  if (!selectionChanged && !archiveChanged) return;
  state.viewRevision = Math.max(state.viewRevision, doc.revision);
  await action("Following the 3D view", async () => {
    if (doc.sequence === null) return;
    if (!d || doc.sequence !== d.id || archiveChanged) await loadDetail(doc.sequence);
    if (doc.mag !== state.mag) {
      state.mag = doc.mag;
      $("mag-slider").value = doc.mag;
      $("mag-label").textContent = doc.mag.toFixed(1);
    }
    state.rank = doc.rank;
    await showCandidate();
    if (archiveChanged) await Promise.all([loadAttitudes(), loadSequences()]);
  });
}

// ---------------------------------------------------------------- 3D view tab

async function setup3D() {
  let loaded = false;
  const open = async (panelId) => {
    for (const tab of document.querySelectorAll(".tab")) {
      const active = tab.dataset.panel === panelId;
      tab.classList.toggle("active", active);
      tab.setAttribute("aria-selected", active);
      $(tab.dataset.panel).hidden = !active;
    }
    if (panelId === "panel-3d" && !loaded) {
      try {
        const info = await api.get("/api/viewer");
        if (info.available) {
          $("viewer-frame").src = info.url;
          $("viewer-note").replaceChildren("Also at ", el("a", { href: info.url, target: "_blank", rel: "noopener" }, info.url),
            " (this machine only). Next / Prev / Confirm there change the selection here.");
          loaded = true;
        } else {
          $("viewer-note").textContent = info.detail || "The 3D view is not running.";
        }
      } catch (err) {
        $("viewer-note").textContent = `The 3D view is not available: ${errorText(err)}`;
      }
    }
  };
  for (const tab of document.querySelectorAll(".tab")) tab.addEventListener("click", () => open(tab.dataset.panel));
}

// ---------------------------------------------------------------- start

async function start() {
  setupUpload();
  setupSequenceList();
  setupCandidate();
  setup3D();
  $("search").addEventListener("click", runSearch);
  $("reset-pattern").addEventListener("click", resetPattern);
  $("pick-mode").addEventListener("change", (e) => player.setPicking(e.target.checked));
  $("att-prev-page").addEventListener("click", () => { state.attOffset = Math.max(0, state.attOffset - ATTITUDE_PAGE); loadAttitudes(); });
  $("att-next-page").addEventListener("click", () => { state.attOffset += ATTITUDE_PAGE; loadAttitudes(); });
  await Promise.all([checkHealth(), loadSequences(), loadAttitudes()]);
  await pollView();
  setInterval(pollView, POLL_MS);
  setInterval(checkHealth, 15000);
}

start();
