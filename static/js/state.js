// What the console knows: its session id and the state shared by its modules.
import { store, stored } from "./dom.js";

// Each browser tab is a console session with its own selection on the server (GET/PUT
// /api/view?session=...). The id lives in the tab's sessionStorage, so a reload keeps it and
// another tab or browser gets its own; ?session=... in the address opens a given session.
function sessionId() {
  const valid = (s) => typeof s === "string" && /^[A-Za-z0-9_-]{1,64}$/.test(s);
  const fromUrl = new URL(location.href).searchParams.get("session");
  let id = valid(fromUrl) ? fromUrl : stored(sessionStorage, "starid-session");
  if (!valid(id)) {
    // getRandomValues works on plain http too (randomUUID needs a secure context).
    const bytes = crypto.getRandomValues(new Uint8Array(12));
    id = "c-" + [...bytes].map((b) => b.toString(16).padStart(2, "0")).join("");
  }
  store(sessionStorage, "starid-session", id);
  return id;
}

export const SESSION = sessionId();

export const state = {
  detail: null,          // GET /api/sequences/{id} of the sequence shown
  review: null,          // GET /api/sequences/{id}/review: candidate verdicts, the sequence's verdict
  view: null,            // the candidate view shown (GET .../candidates/{rank})
  drawn: null,           // what drawSky drew (hits, labels) for tooltips and clicks
  rank: null,
  mag: 6.0,
  seqOffset: 0,
  attOffset: 0,
  queueIds: [],          // ids of the work queue page shown, in order (keys j / k)
  openedFrom: null,      // {id, ids}: the queue page as it was when sequence id was opened (j / k step through it)
  viewRevision: -1,      // newest revision of this session's view state applied or written
  busy: 0,               // actions in flight: the poll does not apply state meanwhile
  sentComment: null,     // the comment the 3D view sent with its confirmation request, while in the comment box
  commentFor: null,      // the candidate ("sequence/search/rank") the comment box's text was typed or sent for
  authRequired: false,
};
