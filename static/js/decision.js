// Judging and deciding: the candidates side by side, each candidate's verdict, and the guard
// rails of a confirmation. Confirming what is not the credible best (or replacing a verdict)
// takes a second, explicit step; "no valid attitude" needs a reason. The server applies the
// same rules (409 without override_reason / supersede), so the console only makes them visible.
import * as api from "./api.js";
import { $, el, toast, errorText, fmt, fmtProbability, fmtTime } from "./dom.js";
import { state } from "./state.js";

let hooks = { goToRank: async () => {}, afterVerdict: async () => {} };

export function setupDecision(h) {
  hooks = h;
  $("confirm").addEventListener("click", confirmClick);
  $("confirm-override").addEventListener("click", () => sendConfirmation(true));
  $("override-cancel").addEventListener("click", cancelSteps);
  $("reject-open").addEventListener("click", openReject);
  $("reject-confirm").addEventListener("click", sendRejection);
  $("reject-cancel").addEventListener("click", cancelSteps);
  $("comment").addEventListener("input", commentIsFor);
}

// The comment box's text is about the candidate it was typed for (or sent with from the 3D view): it goes
// when another candidate is shown, another rank or another search's, as a step opened for that one does,
// so that a comment never lands on a confirmation it was not written for.
const shownCandidate = () => `${state.detail?.id}/${state.detail?.search?.search_id ?? null}/${state.rank}`;
export function commentIsFor() { state.commentFor = shownCandidate(); }
export function dropStaleComment() {
  if ($("comment").value && state.commentFor !== shownCandidate()) $("comment").value = "";
}

const verdictOf = (rank) => state.review?.candidates.find((v) => v.rank === rank) || null;
const currentVerdict = () => state.review?.confirmation || state.review?.rejection || null;
// A verdict as the API names it, to replace that one only (`replaces`).
const verdictRef = (v) => ({ kind: v.confirmed_at ? "attitude" : "rejection", id: v.id });
// Whether the candidate shown is the sequence's confirmed attitude already.
function shownIsConfirmed() {
  const c = state.review?.confirmation;
  return !!c && c.search_id === state.review.search_id && c.rank === state.rank;
}

// Who confirmed an attitude and when (UTC), for the words that name a confirmation given already: it may be
// another operator's, landed between this console's look and its click.
const confirmedBy = (c) => `by ${c.operator} at ${fmtTime(c.confirmed_at)}`;

function describeCurrent(r = state.review) {
  // Who gave it and when (UTC), then what: the words every refusal and second step name a verdict in.
  const c = r.confirmation, j = r.rejection;
  if (c) return `attitude #${c.id} (rank ${c.rank}) confirmed by ${c.operator} at ${fmtTime(c.confirmed_at)}`;
  if (j) return `"no valid attitude" recorded by ${j.operator} at ${fmtTime(j.rejected_at)} ("${j.reason}")`;
  return "";
}

// ---------------------------------------------------------------- candidates side by side

export function renderCandidates() {
  const d = state.detail, review = state.review;
  const candidates = d?.search?.candidates || [];
  const rows = candidates.map((c) => {
    const v = verdictOf(c.rank);
    const credible = v?.credible;
    // Signed: a rank below 1 may match fewer points with a smaller deviation.
    const gap = v ? `${v.deviation_gap_arcsec >= 0 ? "+" : ""}${fmt(v.deviation_gap_arcsec, 0)}″` : "-";
    const gapTitle = v ? `deviation ${gap} vs rank 1; ` +
      `${v.odds_vs_best === null ? "" : `10^${fmt(v.odds_vs_best, 1)} times likelier to be chance; `}` +
      `attitude ${fmt(v.separation_from_best_deg, 2)}° away` : "";
    return el("tr", {
      class: `${c.rank === state.rank ? "selected" : ""} ${credible ? "credible" : "doubtful"}`,
      dataset: { rank: c.rank }, tabindex: 0, "aria-selected": c.rank === state.rank ? "true" : "false",
      title: credible ? "credible best: confirm with one click" : `needs a reason to confirm: ${(v?.reasons || []).join("; ")}`,
      onclick: () => hooks.goToRank(c.rank),
      onkeydown: (e) => { if (e.key === "Enter") hooks.goToRank(c.rank); },
    },
    el("td", {}, `${c.rank} `, el("span", { class: credible ? "ok-mark" : "warn-mark" }, credible ? "✓" : "⚠")),
    el("td", {}, fmt(c.deviation_arcsec, 0)), el("td", {}, fmt(c.deviation_px_per_point, 2)),
    el("td", {}, `${c.n_matched}/${d.search.pattern.length}`), el("td", {}, fmtProbability(c.false_match_probability)),
    el("td", {}, fmt(c.ra_deg, 2)), el("td", {}, fmt(c.dec_deg, 2)), el("td", {}, fmt(c.roll_deg, 1)),
    el("td", { title: gapTitle }, c.rank === 1 ? "-" : gap));
  });
  $("candidate-rows").replaceChildren(...rows);
  // Keep the selected row in view by scrolling the table only: the page must not move.
  const selected = $("candidate-rows").querySelector("tr.selected"), wrap = $("candidate-rows").closest(".table-wrap");
  if (selected && wrap) {
    const top = selected.offsetTop - wrap.querySelector("thead").offsetHeight;
    if (top < wrap.scrollTop || selected.offsetTop + selected.offsetHeight > wrap.scrollTop + wrap.clientHeight) {
      wrap.scrollTop = Math.max(0, top);
    }
  }
  renderContradiction();
  renderVerdict();
  renderDecision();
  renderAudit();
  return review;
}

// A focal length the stars contradict: nothing found with it is credible, so the search never looks there,
// and this is where an operator looks first (above the verdict), whether or not any candidate is shown.
function renderContradiction() {
  const box = $("focal-contradiction");
  const found = state.detail?.search?.focal_length_contradiction;
  box.hidden = !found;
  if (!found) { box.replaceChildren(); return; }
  const text = found.note.charAt(0).toUpperCase() + found.note.slice(1);
  box.replaceChildren(el("strong", {}, "⚠ The stars contradict the declared focal length"), el("div", {}, `${text}.`));
}

export function renderVerdict() {
  const box = $("cand-verdict");
  const v = verdictOf(state.rank);
  if (!v) { box.replaceChildren(); box.className = "verdict"; return; }
  box.className = `verdict ${v.credible ? "credible" : "doubtful"}`;
  box.replaceChildren(v.credible
    ? el("div", {}, el("strong", {}, `✓ Rank ${v.rank} is credible`),
      ` - the best candidate of an identified search (at most ${fmtProbability(state.review.identified_probability)} ` +
      "likely by chance, no rival)")
    : el("div", {}, el("strong", {}, `⚠ Rank ${v.rank} is not credible`),
      el("ul", { class: "reasons" }, v.reasons.map((r) => el("li", {}, r)))));
}

// ---------------------------------------------------------------- the decision

export function renderDecision() {
  const button = $("confirm");
  const v = verdictOf(state.rank);
  const current = currentVerdict();
  button.classList.remove("done", "warn");
  if (!v) {
    button.disabled = true;
    button.textContent = "Confirm";
  } else if (shownIsConfirmed()) {
    button.disabled = true;
    button.classList.add("done");
    button.textContent = `Confirmed ✓ (attitude #${state.review.confirmation.id})`;
  } else {
    button.disabled = false;
    const second = current || !v.credible;
    if (second) button.classList.add("warn");
    button.textContent = current ? `Supersede with rank ${state.rank}…` : `Confirm rank ${state.rank}${second ? "…" : ""}`;
  }
  $("reject-open").disabled = !state.detail;
  $("reject-open").textContent = state.review?.rejection ? "No valid attitude (recorded)…" : "No valid attitude…";
  renderConfirmed();
}

export function cancelSteps() {
  $("override-step").hidden = true;
  $("reject-step").hidden = true;
  // A comment the 3D view sent with its request was about that rank's confirmation: it goes with the step
  // (unless the operator has made it theirs by editing it).
  if (state.sentComment !== null && $("comment").value === state.sentComment) $("comment").value = "";
  state.sentComment = null;
}

// The first step: confirm at once when the candidate is the credible best and nothing is to be
// replaced, otherwise show what the confirmation would override and ask for the second step.
export async function confirmClick() {
  const v = verdictOf(state.rank);
  if (!v || shownIsConfirmed()) {
    const c = state.review?.confirmation;
    if (shownIsConfirmed()) toast(`Rank ${state.rank} is confirmed already ${confirmedBy(c)} (attitude #${c.id})`);
    return;
  }
  if (!operatorName()) return;
  if (v.credible && !currentVerdict()) { await sendConfirmation(false); return; }
  openOverrideStep(v);
}

// The second step for the rank shown: what the confirmation would override, the reason field when the
// candidate is not the credible best; `sender` names where the confirmation was asked for, if not here.
function openOverrideStep(v, sender = null) {
  cancelSteps();
  const current = currentVerdict();
  const reasons = [...(v.credible ? [] : v.reasons)];
  if (current) reasons.push(`replaces the current verdict: ${describeCurrent()}`);
  const sent = sender ? ` (sent from ${sender})` : "";
  $("override-title").textContent = v.credible ? `Replace the verdict with rank ${state.rank}${sent}?`
    : `Rank ${state.rank}${sent} is not the credible best: confirm anyway?`;
  $("override-reasons").replaceChildren(...reasons.map((r) => el("li", {}, r)));
  $("override-reason").hidden = v.credible;
  $("override-reason").value = "";
  $("confirm-override").textContent = current ? "Supersede" : "Confirm anyway";
  $("override-step").hidden = false;
  (v.credible ? $("confirm-override") : $("override-reason")).focus();
  $("override-step").scrollIntoView({ block: "nearest" });
}

// A confirmation of the rank shown asked for elsewhere (the 3D view's Confirm, whose panel has no second
// step): the second step opens here, and nothing is confirmed without the operator's click in it.
export function confirmSentFrom(sender) {
  const v = verdictOf(state.rank);
  if (!v) return;
  const from = sender.charAt(0).toUpperCase() + sender.slice(1);   // the toast's first word
  if (shownIsConfirmed()) {
    const c = state.review.confirmation;
    toast(`${from} asked to confirm rank ${state.rank}: it is confirmed already ${confirmedBy(c)} (attitude #${c.id})`);
    return;
  }
  if (v.credible && !currentVerdict()) {   // the credible best since: one click here confirms it, as there
    toast(`${from} asked to confirm rank ${state.rank}, the credible best: press Confirm to confirm it`);
    return;
  }
  openOverrideStep(v, sender);
  const ask = v.credible ? "confirm replacing the verdict" : "give the reason to confirm it anyway";
  toast(`${from} sent rank ${state.rank} here: ${ask}`, "warn");   // an instruction: read whole
}

function operatorName() {
  const operator = $("operator").value.trim();
  if (!operator && !state.authRequired) {
    toast("Enter your name (Operator, top right) to confirm", "error");
    $("operator").focus();
    return null;
  }
  return operator || "token";
}

// A verdict refused (409) because another console gave one first, said in this console's words (the server's
// name the API's supersede field), before the reload, which may announce the change in the notice over the page
// (its state as it then is). Other refusals (a search replaced: `searchId` no longer the latest) keep the server's.
async function sayRefused(err, d, done, again, failed, searchId = null) {
  const key = (v) => v && JSON.stringify(verdictRef(v));
  const seen = currentVerdict();
  const review = await api.get(`/api/sequences/${d.id}/review`).catch(() => null);
  const now = review && (review.confirmation || review.rejection);
  toast(now && key(now) !== key(seen) && (searchId === null || review.search_id === searchId)
    ? `Not ${done}: another console gave the verdict first: ${describeCurrent(review)}. To replace it, ${again} ` +
      "(the replaced verdict stays in the audit trail)"
    : `${failed}: ${errorText(err)}`, "error");
}

async function sendConfirmation(secondStep) {
  const d = state.detail, v = verdictOf(state.rank);
  if (!d || !v || !operatorName()) return;
  const body = { rank: state.rank, operator: $("operator").value.trim() || null,
    comment: $("comment").value.trim() || null, search_id: d.search.search_id };
  if (secondStep) {
    if (!v.credible) {
      const reason = $("override-reason").value.trim();
      if (!reason) { toast("Give the reason for confirming this candidate anyway", "error"); $("override-reason").focus(); return; }
      body.override_reason = reason;
    }
    if (currentVerdict()) Object.assign(body, { supersede: true, replaces: verdictRef(currentVerdict()) });
  }
  state.busy++;
  try {
    const { status, body: c } = await api.requestWithStatus("POST", `/api/sequences/${d.id}/confirm`, body);
    $("comment").value = "";   // stored with this confirmation; not to be carried into a later one
    $("change-notice").hidden = true;   // what another console changed before is what this verdict was given on
    cancelSteps();
    await hooks.afterVerdict();
    $("confirmed").scrollIntoView({ block: "nearest" });
    // 200: this very candidate was the verdict already, maybe another operator's landed just before.
    const stored = status === 201;
    toast(stored
      ? `Attitude #${c.id} confirmed by ${c.operator}: RA ${fmt(c.ra_deg, 3)}°, Dec ${fmt(c.dec_deg, 3)}°, roll ${fmt(c.roll_deg, 2)}°`
      : `Rank ${c.rank} was confirmed already ${confirmedBy(c)} (attitude #${c.id}); nothing new stored`,
    stored ? "ok" : "warn");
  } catch (err) {
    if (err.status !== 409) {
      toast(`The confirmation failed: ${errorText(err)}`, "error");
      return;
    }
    // Someone else's verdict or search: the step asked about what was; show what is.
    await sayRefused(err, d, "confirmed", "confirm again", "The confirmation failed", body.search_id);
    cancelSteps();
    await hooks.afterVerdict();
  } finally {
    state.busy--;
  }
}

export function openReject() {
  if (!state.detail) return;
  if (!operatorName()) return;
  cancelSteps();
  const current = currentVerdict();
  $("reject-note").textContent = current
    ? `This replaces the current verdict: ${describeCurrent()}. The earlier record stays in the audit trail.`
    : "Every candidate is wrong (the Earth, a ghost pattern, too few stars...): the sequence gets no attitude.";
  $("reject-reason").value = "";
  $("reject-step").hidden = false;
  $("reject-reason").focus();
  $("reject-step").scrollIntoView({ block: "nearest" });
}

async function sendRejection() {
  const d = state.detail;
  const reason = $("reject-reason").value.trim();
  if (!reason) { toast("Give the reason why there is no valid attitude", "error"); $("reject-reason").focus(); return; }
  const seen = currentVerdict();   // replaced only if still the verdict: another operator's is never replaced unseen
  const body = { reason, operator: $("operator").value.trim() || null, supersede: !!seen,
    ...(seen ? { replaces: verdictRef(seen) } : {}) };
  state.busy++;
  try {
    const { status, body: r } = await api.requestWithStatus("POST", `/api/sequences/${d.id}/reject`, body);
    $("change-notice").hidden = true;   // as after a confirmation
    cancelSteps();
    await hooks.afterVerdict();
    toast(status === 201 ? `Recorded: no valid attitude for ${d.sequence_id || `#${d.id}`} (${r.operator})`
      : `"No valid attitude" was recorded already by ${r.operator}`);
  } catch (err) {
    if (err.status !== 409) {
      toast(`Recording "no valid attitude" failed: ${errorText(err)}`, "error");
      return;
    }
    // Another console's verdict came first: show it, to decide again knowing it.
    await sayRefused(err, d, "recorded", "record it again", 'Recording "no valid attitude" failed');
    cancelSteps();
    await hooks.afterVerdict();
  } finally {
    state.busy--;
  }
}

// ---------------------------------------------------------------- the verdict given

export function renderConfirmed() {
  const box = $("confirmed");
  const r = state.review;
  const c = r?.confirmation, j = r?.rejection;
  if (!c && !j) { box.hidden = true; return; }
  box.hidden = false;
  box.className = `confirmed ${c ? "" : "rejected"}`;
  const parts = (...items) => items.filter((x) => x !== null && x !== undefined);
  if (c) {
    box.replaceChildren(...parts(
      el("div", {}, el("strong", {}, `Confirmed: attitude #${c.id}`), ` (rank ${c.rank} of search ${c.search_id})`),
      el("div", { class: "dim" }, `by ${c.operator} at ${fmtTime(c.confirmed_at)}${c.comment ? ` - "${c.comment}"` : ""}`),
      c.override_reason ? el("div", { class: "override" }, `override: ${c.override_reason}`) : null,
      el("div", { class: "mono" }, `RA ${fmt(c.ra_deg, 4)}°  Dec ${fmt(c.dec_deg, 4)}°  roll ${fmt(c.roll_deg, 4)}°`),
      el("div", {}, el("a", { href: c.apm_url, download: "", id: "confirmed-apm" }, "Download APM"),
        c.aem_url ? el("a", { href: c.aem_url, download: "", id: "confirmed-aem" }, "Download AEM") : null,
        el("a", { href: c.acm_url, download: "", id: "confirmed-acm" }, "Download ACM"))));
  } else {
    box.replaceChildren(...parts(
      el("div", {}, el("strong", {}, "No valid attitude"), ` (rejection #${j.id})`),
      el("div", { class: "dim" }, `by ${j.operator} at ${fmtTime(j.rejected_at)}`),
      el("div", { class: "reason" }, j.reason)));
  }
}

function renderAudit() {
  const entries = state.review?.audit || [];
  $("audit").hidden = entries.length === 0;
  $("audit-list").replaceChildren(...entries.map((e) => el("li", { class: e.current ? "current" : "old" },
    `${fmtTime(e.at)} ${e.operator}: `,
    e.kind === "confirmed" ? `confirmed rank ${e.rank} (attitude #${e.id})` : `no valid attitude`,
    e.reason ? ` - ${e.reason}` : "", e.current ? " (current)" : "")));
}

export function verdictSummary() {
  const r = state.review;
  if (!r) return "";
  if (r.confirmation) return `confirmed by ${r.confirmation.operator}, attitude #${r.confirmation.id}`;
  if (r.rejection) return `no valid attitude (${r.rejection.operator})`;
  return r.search_id ? "awaiting a verdict" : "not searched yet";
}
