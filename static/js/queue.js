// The work queue side of the console: uploads (searched automatically when asked), the sequence
// list (filter, search, order: what needs an operator first), confirmed attitudes and the bulk AEM.
import * as api from "./api.js";
import { FOLDER_SIDECAR, SIDECAR_SUFFIX, frameFields, isFits, isImage, isSidecar, uploadFrames } from "./frames-upload.js";
import { $, el, toast, errorText, fmt, fmtTime, plural, store, stored } from "./dom.js";
import { state } from "./state.js";

const PAGE_SIZE = 20;
const ATTITUDE_PAGE = 6;
// Files the simulator writes beside its telemetry: the answer, not telemetry (the CLI skips them too).
const TRUTH_SUFFIX = ".truth.json";
const STATUS_TEXT = { no_match: "no match", rejected: "no valid attitude" };
export const statusText = (s) => STATUS_TEXT[s] || s;

let onSelect = () => {};
let lastQueueKey = "";
// Each listing asked for takes a number; an answer is shown only while its number is the latest, so a slow
// answer to an earlier filter, order or page never replaces the answer to the one now in the controls.
const asked = { sequences: 0, attitudes: 0 };

export function setupQueue({ select }) {
  onSelect = select;
  setupUpload();
  const reload = () => { state.seqOffset = 0; loadSequences(); };
  let debounce = null;
  $("filter-status").addEventListener("change", reload);
  $("filter-spacecraft").addEventListener("change", reload);
  $("sort-order").addEventListener("change", () => { store(localStorage, "starid-order", $("sort-order").value); reload(); });
  $("sort-order").value = stored(localStorage, "starid-order", "queue");
  $("filter-search").addEventListener("input", () => { clearTimeout(debounce); debounce = setTimeout(reload, 250); });
  $("seq-prev-page").addEventListener("click", () => { state.seqOffset = Math.max(0, state.seqOffset - PAGE_SIZE); loadSequences(); });
  $("seq-next-page").addEventListener("click", () => { state.seqOffset += PAGE_SIZE; loadSequences(); });
  $("att-prev-page").addEventListener("click", () => { state.attOffset = Math.max(0, state.attOffset - ATTITUDE_PAGE); loadAttitudes(); });
  $("att-next-page").addEventListener("click", () => { state.attOffset += ATTITUDE_PAGE; loadAttitudes(); });
  $("bulk-form").addEventListener("submit", bulkExport);
}

// ---------------------------------------------------------------- upload

function setupUpload() {
  const zone = $("dropzone"), input = $("file-input"), auto = $("auto-search");
  auto.checked = stored(localStorage, "starid-auto-search", "1") === "1";
  auto.addEventListener("change", () => store(localStorage, "starid-auto-search", auto.checked ? "1" : "0"));
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
  const search = $("auto-search").checked;
  const skipped = files.filter((f) => f.name.toLowerCase().endsWith(TRUTH_SUFFIX));
  // Images go together as one pass, with their sidecar; everything else is a spot list.
  const images = files.filter((f) => !skipped.includes(f) && isImage(f));
  const sidecars = files.filter((f) => !skipped.includes(f) && isSidecar(f));
  const spotLists = files.filter((f) => !skipped.includes(f) && !images.includes(f) && !sidecars.includes(f));
  for (const file of skipped) skippedLine(list, file.name, "skipped: a simulator's truth file (the answer), not telemetry");
  const results = [];
  // One at a time: the server validates and extracts each; the list shows each result next to its file.
  // A JSON dropped with images may have been meant as their sidecar: if it is no telemetry, say how one is named.
  const sidecarHint = images.length ? "Dropped with images: a JSON is read as their sidecar only when named " +
    `${FOLDER_SIDECAR} or IMAGE${SIDECAR_SUFFIX} (format tubsat-frames/1); this one was read as telemetry.` : null;
  for (const file of spotLists) {
    results.push(await uploadLine(list, { file: file.name }, file.name,
      (progress) => api.uploadFile(file, progress, { search }),
      (status, body) => [status === 201 ? `stored as #${body.id}: ${body.pattern.points.length} pattern points`
        : `already stored as #${body.id}`, queued(search, status, body)], null,
      file.name.toLowerCase().endsWith(".json") ? sidecarHint : null));
  }
  if (!images.length) {
    for (const file of sidecars) skippedLine(list, file.name, "skipped: a frames sidecar, but no images were dropped with it");
  } else if (sidecars.length || images.every(isFits)) {
    results.push(await uploadPass(list, images, sidecars, search));
  } else {
    // Photographs chosen together are so many photographs (as `solve a.jpg b.jpg` takes them), not one pass
    // of a camera: two skies taken for one made every star a ghost and the pass no match (a photograph
    // trial). A pass comes with its frames.json, or as FITS frames, which carry their times.
    for (const image of images) results.push(await uploadPass(list, [image], [], search));
  }
  const done = results.filter((r) => r !== null), failures = results.length - done.length;
  const note = skipped.length ? `; ${plural(skipped.length, "truth file")} skipped` : "";
  // A pass of frames (or each photograph) counts as one upload, beside the spot-list files.
  const unit = images.length ? "upload" : "file";
  toast(failures ? `${done.length} of ${results.length} ${unit}s stored${note}; see the errors next to the files`
    : `${plural(done.length, unit)} stored${note}`, failures ? "error" : "ok");   // not "1 upload uploaded"
  await Promise.all([loadSequences(), loadSpacecraft()]);
  if (done.length) await onSelect(done.at(-1).id);
}

function skippedLine(list, name, why) {
  list.prepend(el("li", { class: "upload-item skipped", dataset: { file: name } },
    el("div", { class: "name" }, name), el("div", { class: "dim" }, why)));
}

// Whether the server queued a search of this upload (asked for, and the sequence new or never searched):
// the words in a span of their own, which noteSearched turns into the search's outcome once it is known.
function queued(search, status, body) {
  if (!search || (status !== 201 && body.sequence.status !== "new")) return "";
  return el("span", { class: "search-state", dataset: { sequence: body.id } },
    status === 201 ? ", search queued" : ", never searched: search queued");
}

// Sequences as the console just read them (the work queue's page, the sequence opened): an upload line
// still saying "search queued" says what came of that search once the sequence has left "new". The
// queued search's outcome, said once: a later verdict is the work queue's to show.
export function noteSearched(sequences) {
  for (const s of sequences) {
    if (s.status === "new") continue;
    for (const span of document.querySelectorAll(`.upload-list .search-state[data-sequence="${s.id}"]`)) {
      span.textContent = `, searched: ${statusText(s.status)}`;
      delete span.dataset.sequence;
      span.dataset.status = s.status;
    }
  }
}

// One line of the upload list: the name, a progress bar, then the result or the error with its
// located problems. send(progress) resolves {status, body}; describe(status, body) gives the result's
// parts (text, the queued search's span); resolves {id, created} or null (failed), with ``hintOnError`` under
// the error.
async function uploadLine(list, dataset, name, send, describe, waiting = null, hintOnError = null) {
  const bar = el("progress", { max: 1, value: 0 });
  const result = el("div", {}, "uploading...");
  list.prepend(el("li", { class: "upload-item", dataset }, el("div", { class: "name", title: name }, name), bar, result));
  try {
    const { status, body } = await send((f) => {
      bar.value = f;
      if (f >= 1 && waiting) result.textContent = waiting;
    });
    bar.value = 1;
    result.className = "ok";
    result.replaceChildren(...describe(status, body));
    // The server's word on other stored uploads of the same spacecraft and sequence id (the same telemetry
    // in other bytes, or a re-downlink): worth a look before two operators work on two copies.
    if (body.note) result.after(el("div", { class: "upload-note" }, body.note));
    return { id: body.id, created: status === 201 };
  } catch (err) {
    bar.remove();
    result.className = "error";
    // (replaceChildren would print a null as the text "null": only the nodes there are.)
    result.replaceChildren(el("div", {}, err.headline ?? err.detail), ...(err.problems.length ? [el("ul", { class: "problems" },
      err.problems.map((p) => el("li", {}, el("code", {}, p.location), ": ", p.message)))] : []));
    if (hintOnError) result.after(el("div", { class: "upload-note" }, hintOnError));
    return null;
  }
}

// The images of one drop as one pass (POST /api/frames), with their sidecar and the card's fields.
async function uploadPass(list, images, sidecars, search) {
  const names = images.map((f) => f.name);
  const shown = names.length > 3 ? [...names.slice(0, 2), `${names.length - 2} more`] : names;
  const label = `${plural(images.length, "image")}: ${shown.join(", ")}` +
    (sidecars.length ? ` + ${sidecars.map((f) => f.name).join(", ")}` : "");
  const fields = frameFields();
  const check = fields instanceof api.ApiError ? fields
    : sidecars.length > 1 ? new api.ApiError(422, "several sidecars: drop the frames of one pass at a time",
      sidecars.map((f) => ({ location: f.name, message: "one frames.json per pass" })))
    : null;
  const outcome = await uploadLine(list, { file: names[0], kind: "frames" }, label,
    (progress) => check ? Promise.reject(check) : uploadFrames(images, sidecars[0] || null, fields, progress, { search }),
    (status, body) => {
      const frames = body.sequence.n_snapshots ?? images.length;
      const sources = body.extraction.sources.reduce((n, s) => n + s.length, 0);
      const name = `#${body.id} ${body.sequence.sequence_id || ""}`.trim();
      return [status === 201 ? `${plural(frames, "frame")} → ${name}, ${sources} sources` : `already stored as ${name}`,
        queued(search, status, body)];
    }, "reading the frames and detecting the stars...");
  return outcome;
}

// ---------------------------------------------------------------- sequence list

// periodic: a refresh nobody asked for; it waits while the pointer or the focus is on the list, so a
// re-ordered queue never moves a row away under the operator's click.
export async function loadSequences({ periodic = false } = {}) {
  const list = $("sequence-list");
  if (periodic && (list.matches(":hover") || list.contains(document.activeElement))) return;
  const query = new URLSearchParams({ offset: state.seqOffset, limit: PAGE_SIZE, order: $("sort-order").value });
  const status = $("filter-status").value, spacecraft = $("filter-spacecraft").value, search = $("filter-search").value.trim();
  if (status) query.set("status", status);
  if (spacecraft) query.set("spacecraft", spacecraft);
  if (search) query.set("search", search);
  const ticket = ++asked.sequences;
  let page;
  try {
    page = await api.get(`/api/sequences?${query}`);
  } catch (err) {
    if (ticket === asked.sequences) toast(`Could not list the sequences: ${errorText(err)}`, "error");
    return;
  }
  if (ticket !== asked.sequences) return;
  state.queueIds = page.items.map((s) => s.id);
  noteSearched(page.items);   // before the unchanged-page return: a line may have been added since
  // Redrawn only when something changed, so a periodic refresh never moves a row under the pointer.
  const key = JSON.stringify([page, state.detail?.id]);
  if (key === lastQueueKey) return;
  lastQueueKey = key;
  list.replaceChildren(...page.items.map((s) => el("li", {
    class: state.detail && state.detail.id === s.id ? "selected" : "",
    dataset: { id: s.id, status: s.status }, tabindex: 0,
    onclick: () => onSelect(s.id),
    onkeydown: (e) => { if (e.key === "Enter") onSelect(s.id); },
  }, el("span", { class: "mono seq-name", title: s.filename || "" }, s.sequence_id || `#${s.id}`),
  el("span", { class: `badge ${s.status}` }, statusText(s.status)),
  // Minutes are enough to tell passes apart, and keep the line to one line in a narrow sidebar.
  // No first time: its frames carried none (solved at an assumed time, which is no time to list it by).
  el("span", { class: "sub", title: s.first_time ? fmtTime(s.first_time) : "no time: the frames carried none" },
    `#${s.id} · ${s.spacecraft || "unknown spacecraft"} · ` +
    `${s.first_time ? fmtTime(s.first_time).slice(0, 16) : "no time"}`))));
  if (!page.items.length) list.replaceChildren(el("li", { class: "dim" }, page.total ? "no more" : "no sequences match"));
  const last = Math.min(page.total, state.seqOffset + page.items.length);
  $("seq-page-info").textContent = page.total ? `${state.seqOffset + 1}-${last} of ${page.total}` : "0";
  $("seq-prev-page").disabled = state.seqOffset === 0;
  $("seq-next-page").disabled = last >= page.total;
}

export function markSelected(id) {
  for (const li of $("sequence-list").children) li.classList.toggle("selected", Number(li.dataset.id) === id);
}

export async function loadSpacecraft() {
  try {
    const names = await api.get("/api/spacecraft");
    for (const select of [$("filter-spacecraft"), $("bulk-spacecraft")]) {
      const keep = select.value;
      const first = select.id === "filter-spacecraft" ? [el("option", { value: "" }, "any spacecraft")] : [];
      select.replaceChildren(...first, ...names.filter((n) => n.name !== null)
        .map((n) => el("option", { value: n.name }, `${n.name} (${n.sequences})`)));
      if ([...select.options].some((o) => o.value === keep)) select.value = keep;
    }
  } catch (err) {
    toast(`Could not list the spacecraft: ${errorText(err)}`, "error");
  }
}

// ---------------------------------------------------------------- attitudes

export async function loadAttitudes() {
  const ticket = ++asked.attitudes;
  try {
    const page = await api.get(`/api/attitudes?offset=${state.attOffset}&limit=${ATTITUDE_PAGE}`);
    if (ticket !== asked.attitudes) return;
    // Two lines per attitude: the numbers get a column of their own and are never cut.
    $("attitude-list").replaceChildren(...page.items.map((a) => el("tr", {
      class: a.current ? "" : "superseded", dataset: { id: a.id },
      title: `attitude ${a.id}, rank ${a.rank}, confirmed ${fmtTime(a.confirmed_at)}` +
        `${a.current ? "" : a.withdrawn_by ? " (withdrawn: no valid attitude)" : " (superseded)"}` +
        `${a.override_reason ? `; override: ${a.override_reason}` : ""}${a.comment ? `; ${a.comment}` : ""}`,
    },
    el("td", { class: "who" }, el("div", { class: "seq-name" }, a.sequence_id || `#${a.sequence}`),
      el("div", { class: "dim" }, a.operator)),
    el("td", { class: "num" }, el("div", {}, `RA ${fmt(a.ra_deg, 3)}`), el("div", {}, `Dec ${fmt(a.dec_deg, 3)}`),
      el("div", {}, `roll ${fmt(a.roll_deg, 2)}`)),
    el("td", { class: "files" }, el("a", { href: a.apm_url, download: "", class: "apm-link" }, "APM"),
      a.aem_url ? el("a", { href: a.aem_url, download: "", class: "aem-link" }, "AEM") : null))));
    if (!page.items.length) $("attitude-list").replaceChildren(el("tr", {}, el("td", { colspan: 3, class: "dim" }, "none yet")));
    const last = Math.min(page.total, state.attOffset + page.items.length);
    $("att-page-info").textContent = page.total ? `${state.attOffset + 1}-${last} of ${page.total}` : "";
    $("att-prev-page").disabled = state.attOffset === 0;
    $("att-next-page").disabled = last >= page.total;
  } catch (err) {
    if (ticket === asked.attitudes) toast(`Could not list the confirmed attitudes: ${errorText(err)}`, "error");
  }
}

// ---------------------------------------------------------------- bulk AEM

function bulkExport(e) {
  e.preventDefault();
  const spacecraft = $("bulk-spacecraft").value;
  if (!spacecraft) { toast("Choose a spacecraft to export", "error"); return; }
  const query = new URLSearchParams({ spacecraft });
  // datetime-local has no zone; the archive's times are UTC, and so are these.
  for (const [id, key] of [["bulk-start", "start"], ["bulk-end", "end"]]) {
    if ($(id).value) query.set(key, `${$(id).value}Z`);
  }
  download(`/api/attitudes/aem?${query}`);
}

// Fetch first, so that an empty range gives the server's sentence instead of a broken download.
async function download(path) {
  try {
    const response = await fetch(path);
    if (!response.ok) {
      const body = await response.json().catch(() => ({}));
      toast(`No AEM: ${body.detail || response.statusText}`, "error");
      return;
    }
    const name = /filename="([^"]+)"/.exec(response.headers.get("Content-Disposition") || "")?.[1] || "attitudes.aem";
    const url = URL.createObjectURL(await response.blob());
    const a = el("a", { href: url, download: name, hidden: true });
    document.body.append(a);
    a.click();
    a.remove();
    setTimeout(() => URL.revokeObjectURL(url), 10000);
    toast(`Downloaded ${name}`);
  } catch (err) {
    toast(`The AEM export failed: ${errorText(err)}`, "error");
  }
}
