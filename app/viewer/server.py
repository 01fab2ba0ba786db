"""The 3D view: a viser server in the API's process, one view per console session.

Each browser client of the viser server is a view of its own (viser's
per-client ``client.scene`` and ``client.gui``): it draws the console
session named in the address it was opened at (``GET
/api/viewer?session=ID`` gives it; the session rides in the websocket
address, :func:`app.workflow.view_state.address_for_session`), so several
consoles have their 3D views open at once, each showing its own sequence,
rank and magnitude limit.  At most :data:`MAX_3D_VIEWS` clients are drawn;
one more is told so.  A client at the bare address draws the session of the
console that opened its 3D tab last (:attr:`ViewStateStore.followed`).

What a view shows (scene units: see :mod:`app.viewer.scene`):

* the celestial sphere (shared by all views): constellation labels (a few
  dozen) and the celestial equator; its own catalogue stars as point
  clouds, one per magnitude class so brighter stars are bigger dots, down
  to its session's magnitude limit;
* for its session's candidate: the camera frustum, the current pattern's
  rays onto the sphere (green when the candidate matched the point, orange
  otherwise), a small clickable sphere at the end of each ray (click: take
  that track out of the pattern), grey spheres for tracks taken out (click:
  put back), the matched catalogue stars highlighted and named.

Its GUI has Prev / Next, the magnitude slider and Confirm (operator name,
optional comment), acting on its session.  Confirm takes the credible best
candidate only; a confirmation that needs the console's second step
(another rank, or one replacing the sequence's verdict) is sent to that
session's console (:func:`confirm_from_3d`,
:func:`app.workflow.view.request_confirmation`), which opens that step.
Status codes are shown in the console's words (:data:`STATUS_TEXT`).
Every action goes through :mod:`app.workflow`, the same code the REST API
runs, and a poll thread redraws a view whenever its session's state or the
archive behind it changes, so a console and its view stay in step without
talking to each other.

Security: viser's websocket has no authentication, so it is bound to
127.0.0.1 whatever the API's host.  The panel's text is Markdown, which
viser renders with raw HTML allowed, so every string that comes from
telemetry or from a person (sequence id, spacecraft, operator, error
messages quoting input) goes through :func:`markdown_text` and is shown as
the characters it is, never as markup.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass

import numpy as np

from app.timefmt import parse_utc
from app.viewer import scene as geo
from app.workflow import AppContext, archive, confirm as confirming, search as searching, view
from app.workflow.documents import ViewerDocument
from app.workflow.errors import WorkflowError
from app.workflow.review import review
from app.workflow.view_state import (DEFAULT_SESSION, MAX_3D_VIEWS, ViewerClients, address_for_session,
                                      session_in_address)

log = logging.getLogger(__name__)

#: Loopback only: the viser websocket accepts anyone who can reach it.
VIEWER_HOST = "127.0.0.1"
#: Characters that start markup in CommonMark (all ASCII punctuation may be backslash-escaped there).
_MARKDOWN_PUNCTUATION = frozenset("!\"#$%&'()*+,-./:;<=>?@[\\]^_`{|}~")
#: A sequence's status in the console's words (static/js/queue.js STATUS_TEXT); the others read as they are.
STATUS_TEXT = {"no_match": "no match", "rejected": "no valid attitude"}


def status_text(status: str | None) -> str:
    """A status as the console shows it: "no match", "no valid attitude", "identified" (plain text)."""
    return STATUS_TEXT.get(status, status or "unknown")


def _time_text(text: str | None) -> str:
    """An API time as the console prints it (static/js/dom.js fmtTime): ``2026-11-23 18:57:41Z``."""
    return parse_utc(text).strftime("%Y-%m-%d %H:%M:%SZ") if text else "-"


def _verdict_text(confirmed, rejected) -> str:
    """The sequence's current verdict in the console's words (static/js/decision.js describeCurrent), as Markdown."""
    if confirmed is not None:
        return (f"attitude #{confirmed.id} (rank {confirmed.rank}) confirmed by {markdown_text(confirmed.operator)} "
                f"at {markdown_text(_time_text(confirmed.confirmed_at))}")
    return (f"\"no valid attitude\" recorded by {markdown_text(rejected.operator)} at "
            f"{markdown_text(_time_text(rejected.rejected_at))}: {markdown_text(rejected.reason)}")


def _comment_taken(before, after) -> bool:
    """Whether a Confirm between these two view states stored the comment typed (a new confirmation) or sent
    it to the console (a new confirmation request)."""
    def number(doc):
        return None if doc.confirm_request is None else doc.confirm_request.number
    return after.confirmation_id != before.confirmation_id or number(after) != number(before)


def _credibility_text(verdict) -> str:
    """Whether the rank shown is the credible best, as the console's verdict line says it (Markdown): the
    panel's Confirm takes only that one in one click."""
    if verdict is None:
        return ""
    if verdict.credible:
        return "**Credible**: Confirm takes it."
    return (f"**Not credible** ({markdown_text('; '.join(verdict.reasons))}): Confirm sends it to the console's "
            "second step.")


def confirm_from_3d(ctx: AppContext, sequence: int | None, rank: int | None, operator: str,
                    comment: str | None, session: str | None = None) -> str:
    """What the 3D view's Confirm does, and the panel's answer (Markdown).

    The panel has one click and no second step: it confirms the credible
    best candidate only.  A confirmation that needs the second step (a rank
    that is not the credible best, whose reason the audit record keeps, or
    one that would replace the sequence's verdict) is sent to the console
    drawing ``session`` (default: the one the 3D view at the bare address draws): the request
    goes into that session's view state
    (:func:`app.workflow.view.request_confirmation`), and the console opens
    its second step for that rank.  The panel says so in an operator's words
    (the API's would name request fields).
    """
    if sequence is None or rank is None:
        return "Nothing to confirm: no candidate is shown."
    judged = review(ctx, sequence)
    verdict = next((v for v in judged.candidates if v.rank == rank), None)
    confirmed, rejected = judged.confirmation, judged.rejection
    this_one = confirmed is not None and confirmed.search_id == judged.search_id and confirmed.rank == rank
    if verdict is not None and not this_one and (not verdict.credible or confirmed or rejected):
        session = ctx.view.followed if session is None else session
        view.request_confirmation(ctx, sequence, rank, judged.search_id, session=session, comment=comment)
        why = (f"Rank {rank} is not the credible best candidate ({markdown_text('; '.join(verdict.reasons))})."
               if not verdict.credible else
               f"Rank {rank} would replace the sequence's verdict: {_verdict_text(confirmed, rejected)}.")
        # No console opened this 3D view (its default session): no console reads it, so it is not "sent".
        where = "Confirm it in the console" if session == DEFAULT_SESSION else "Sent to the console"
        step = "asks for the reason, which the audit record keeps" if not verdict.credible \
            else "asks you to confirm the replacement"
        kept = "" if not comment else (" The comment typed here goes with it, into the console's comment box."
                                       if session != DEFAULT_SESSION else
                                       " The comment typed here is not sent: type it in the console.")
        return f"{why} {where}: its second step {step}.{kept}"
    if not operator:
        return "**Error:** enter the operator's name before confirming."
    result, stored = confirming.record_confirmation(ctx, sequence, rank, operator, comment)
    if not stored:  # this very candidate was the verdict already: maybe another operator's, just before
        return (f"Rank {result.rank} was confirmed already by {markdown_text(result.operator)} at "
                f"{markdown_text(_time_text(result.confirmed_at))} (attitude #{result.id}); nothing new stored.")
    return f"Confirmed rank {result.rank} as attitude #{result.id} by {markdown_text(operator)}."


def markdown_text(value) -> str:
    """``value`` as Markdown that displays exactly its characters: no HTML, links, emphasis or blocks.

    CommonMark lets every ASCII punctuation character be escaped with a
    backslash and then treats it as a literal character, so escaping all of
    them leaves nothing that could open a tag, a link, emphasis, code or an
    entity; line breaks become spaces so no new block can start.  ``&``,
    ``<`` and ``>`` are written as character references, which stay literal
    text even for a renderer that passes raw HTML through.
    """
    text = " ".join(str(value).splitlines())
    out = []
    for ch in text:
        if ch == "&":
            out.append("&amp;")
        elif ch == "<":
            out.append("&lt;")
        elif ch == ">":
            out.append("&gt;")
        elif ch in _MARKDOWN_PUNCTUATION:
            out.append("\\" + ch)
        else:
            out.append(ch)
    return "".join(out)
#: How often the view re-reads the shared state (seconds).
POLL_S = 0.3
STAR_COLOUR = (235, 235, 245)
LABEL_OFFSET = 1.03
MATCHED_COLOUR = (255, 214, 10)
RAY_MATCHED = (64, 220, 120)
RAY_UNMATCHED = (255, 140, 40)
EXCLUDED_COLOUR = (120, 120, 130)
FRUSTUM_COLOUR = (90, 180, 255)


@dataclass(frozen=True)
class SkyModel:
    """The catalogue as the view draws it: ICRS directions, magnitudes, HIP numbers, label anchors."""

    vectors: np.ndarray
    mag: np.ndarray
    hip: np.ndarray
    anchors: list

    @classmethod
    def load(cls) -> "SkyModel":
        from app.catalogue import constellations, load_catalogue

        catalogue = load_catalogue()
        vectors = catalogue.mean_vectors()
        bright = np.flatnonzero(catalogue.mag <= geo.LABEL_MAG_LIMIT)
        names = constellations(vectors[bright])
        anchors = geo.constellation_anchors(vectors[bright], catalogue.mag[bright], names)
        return cls(vectors=vectors, mag=np.asarray(catalogue.mag), hip=np.asarray(catalogue.hip), anchors=anchors)

    def vectors_of(self, hips) -> np.ndarray:
        index = {int(h): i for i, h in enumerate(self.hip)}
        rows = [index[int(h)] for h in hips if int(h) in index]
        return self.vectors[rows] if rows else np.zeros((0, 3))


def _selection(doc) -> tuple:
    """What the 3D view shows, as far as a message about it goes: the console drawn, its sequence, search, rank."""
    return (doc.session, doc.sequence, doc.search_id, doc.rank)


def panel_title(sequence_id, spacecraft: str | None, status: str) -> str:
    """The panel's first line: the sequence (bold), its spacecraft and status, all shown as text."""
    return (f"**{markdown_text(sequence_id)}** ({markdown_text(spacecraft or 'unknown spacecraft')}), "
            f"status {markdown_text(status_text(status))}")


def refusal_text(limit: int) -> str:
    """What a 3D view past the bound shows instead of a scene (Markdown)."""
    return (f"**This server draws at most {limit} 3D views at once, and {limit} are open** (consoles' 3D view "
            "tabs and 3D view browser tabs). Close one of them, then reload this page.")


#: What a 3D view of a console session the server has forgotten shows (Markdown).
SESSION_ENDED_TEXT = ("**The console session this 3D view drew has ended.** Open the 3D view again from a console's "
                      "3D view tab.")


def _session_of_client(server, client_id: int) -> str | None:
    """The console session named in the address a viser client connected its websocket to (None: none named).

    viser 1.1.1 (pinned) gives a client handle no access to its address;
    its websocket server keeps each live connection, whose handshake
    request carries the path and query the page connected to.  ValueError
    for a malformed session id; a connection already gone reads as none.
    """
    connection = server._websock_server._live_connections.get(client_id)
    return None if connection is None or connection.request is None else session_in_address(connection.request.path)


class Panel:
    """One 3D view: a viser client's own GUI and candidate scene, drawing one console session.

    ``session`` None means the session :attr:`ViewStateStore.followed` names
    (the 3D view at the bare address).  Every action writes that session, so
    Prev / Next / Confirm of this view land in the console that opened it.
    """

    def __init__(self, viewer: "Viewer", client, session: str | None) -> None:
        self._viewer = viewer
        self._ctx = viewer.context
        self._sky = viewer.sky
        self.client = client
        self.session = session
        self._drawn_key = None
        self._message_about = None  # the selection the panel's message was written for (_selection)
        self._drawn_mag = None
        self._camera_key = None
        self._candidate_nodes: list = []
        self._build_gui()

    def current_session(self) -> str:
        """The session this view draws now."""
        return self._ctx.view.followed if self.session is None else self.session

    def _document(self):
        return view.view_document(self._ctx, self.current_session())

    # --- GUI ----------------------------------------------------------------
    def _build_gui(self) -> None:
        gui = self.client.gui
        self._info = gui.add_markdown("No sequence selected yet: open one in the console.")
        self._prev = gui.add_button("Prev", hint="previous candidate (rank - 1)")
        self._next = gui.add_button("Next", hint="next candidate (rank + 1)")
        self._mag = gui.add_slider("Faintest mag", min=1.0, max=7.0, step=0.5,
                                   initial_value=float(min(7.0, max(1.0, self._ctx.view.get(self.current_session()).mag))))
        self._operator = gui.add_text("Operator", initial_value="")
        self._operator_from_console = ""  # the name last taken from the console (kept while nobody edits it)
        self._comment = gui.add_text("Comment", initial_value="")
        self._confirm = gui.add_button("Confirm", color="green", hint="confirm the candidate shown")
        self._message = gui.add_markdown("")
        self._gui = [self._info, self._prev, self._next, self._mag, self._operator, self._comment, self._confirm,
                     self._message]
        self._prev.on_click(lambda event: self._step(-1))
        self._next.on_click(lambda event: self._step(+1))
        self._confirm.on_click(lambda event: self._confirm_shown())

        @self._mag.on_update
        def _(event) -> None:
            if event.client is None:  # our own update from the session's state: nothing to write
                return
            self._act(lambda: self._write_view({"mag": float(self._mag.value)}))

    def release(self, text: str) -> None:
        """Stop drawing: the panel and the candidate go, ``text`` says why (the client stays connected)."""
        self._clear_candidate()
        for handle in self._gui:
            try:
                handle.remove()
            except Exception:  # the client left meanwhile
                pass
        self.client.gui.add_markdown(text)

    def _act(self, action) -> None:
        """Run a GUI action; its error is shown in the panel instead of being lost in a thread."""
        try:
            message = action()
        except WorkflowError as exc:
            message = f"**Error:** {markdown_text(exc.detail)}"
        except Exception as exc:  # keep the view alive whatever went wrong
            log.exception("3D view action failed")
            message = f"**Error:** {markdown_text(exc)}"
        self._message.content = message or ""
        try:  # what the message is about: it goes when another candidate, sequence or console is drawn
            self._message_about = _selection(self._document())
        except Exception:
            self._message_about = None
        self._viewer.wake()

    def _write_view(self, changes: dict) -> str:
        view.set_view(self._ctx, changes, "viewer", self.current_session())
        return ""

    def _step(self, delta: int) -> None:
        def action() -> str:
            doc = self._document()
            if doc.sequence is None or not doc.n_candidates:
                return "No candidates to step through: search the sequence first."
            rank = min(max(1, (doc.rank or 1) + delta), doc.n_candidates)
            if rank == doc.rank:
                return f"Already at rank {rank} of {doc.n_candidates}."
            return self._write_view({"rank": rank})
        self._act(action)

    def _confirm_shown(self) -> None:
        def action() -> str:
            doc = self._document()
            said = confirm_from_3d(self._ctx, doc.sequence, doc.rank, self._operator.value.strip(),
                                   self._comment.value.strip() or None, doc.session)
            if _comment_taken(doc, view.view_document(self._ctx, doc.session)):
                self._comment.value = ""  # as the console's: never carried into the next confirmation
            return said
        self._act(action)

    def _toggle(self, definition_change) -> None:
        def action() -> str:
            doc = self._document()
            if doc.sequence is None:
                return "No sequence shown."
            definition = archive.current_pattern(self._ctx, doc.sequence).definition
            archive.set_pattern(self._ctx, doc.sequence, definition_change(definition), None)
            return "Pattern changed: search again to identify the new pattern."
        self._act(action)

    # --- scene --------------------------------------------------------------
    def refresh(self, doc) -> None:
        """Redraw what changed in the session's state ``doc`` since the last call."""
        key = (doc.session, doc.sequence, doc.search_id, doc.rank, doc.pattern_version, doc.confirmation_id,
               doc.status)
        if doc.mag != self._drawn_mag:
            self._draw_stars(doc.mag)
            self._mag.value = float(min(7.0, max(1.0, doc.mag)))
        if key != self._drawn_key:
            self._draw_candidate(doc)
            self._drawn_key = key
        if self._message_about is not None and _selection(doc) != self._message_about:
            self._message.content = ""  # it was about what was drawn before
            self._message_about = None
        self._follow_operator(doc.operator)

    def _follow_operator(self, name: str | None) -> None:
        """The Operator field takes the name typed in the console it draws, unless someone typed another here."""
        if name and self._operator.value.strip() in ("", self._operator_from_console) and name != self._operator.value:
            self._operator.value = name
            self._operator_from_console = name

    def _draw_stars(self, mag_limit: float) -> None:
        for k, rows in enumerate(geo.magnitude_classes(self._sky.mag, mag_limit)):
            points = geo.SPHERE_RADIUS * self._sky.vectors[rows] if len(rows) else np.zeros((1, 3))
            self.client.scene.add_point_cloud(f"/sky/stars/class{k}", points, STAR_COLOUR,
                                              point_size=geo.MAG_CLASS_SIZES[k], point_shape="circle",
                                              visible=bool(len(rows)))
        self._drawn_mag = mag_limit

    def _clear_candidate(self) -> None:
        for node in self._candidate_nodes:
            try:
                node.remove()
            except Exception:  # already gone with its parent
                pass
        self._candidate_nodes = []

    def _draw_candidate(self, doc) -> None:
        self._clear_candidate()
        if doc.sequence is None:
            self._info.content = "No sequence selected yet: open one in the console."
            return
        row = archive.require_sequence(self._ctx, doc.sequence)
        title = panel_title(row.sequence_id or row.id, row.spacecraft, row.status)
        if doc.search_id is None or doc.rank is None:
            self._info.content = f"{title}\n\nNot searched yet, or no candidate."
            return
        search, result = searching.latest_search(self._ctx, row.id)
        candidate = searching.candidate_of(search, result, doc.rank)
        item = archive.loaded(self._ctx, row)
        camera = item.sequence.camera
        rotation = candidate.rotation
        scene = self.client.scene
        pose = geo.frustum_pose(rotation, camera)
        self._candidate_nodes.append(scene.add_camera_frustum(
            "/candidate/frustum", fov=pose.fov_rad, aspect=pose.aspect, scale=2.5, color=FRUSTUM_COLOUR,
            wxyz=pose.wxyz, thickness=2.0, thickness_units="screen"))

        points = archive.pattern_document(item, self._ctx.storage.current_pattern(row.id)).points
        matched_tracks = {m.track for m in candidate.matches}
        self._draw_pattern(rotation, camera, points, matched_tracks)
        self._draw_excluded(rotation, camera, item, {p.track for p in points})

        hips = [m.hip for m in candidate.matches]
        matched = self._sky.vectors_of(hips)
        if len(matched):
            self._candidate_nodes.append(scene.add_point_cloud(
                "/candidate/matched", geo.SPHERE_RADIUS * matched, MATCHED_COLOUR, point_size=0.2,
                point_shape="rounded"))
        for m in candidate.matches:
            vector = self._sky.vectors_of([m.hip])
            if m.name and len(vector):
                self._candidate_nodes.append(scene.add_label(
                    f"/candidate/names/{m.hip}", m.name, position=tuple(geo.SPHERE_RADIUS * 1.01 * vector[0]),
                    anchor="bottom-left", font_screen_scale=0.9))
        boresight = rotation[2]
        self._candidate_nodes.append(scene.add_label(
            "/candidate/rank", f"rank {doc.rank} of {doc.n_candidates}",
            position=tuple(geo.SPHERE_RADIUS * 0.7 * boresight), anchor="top-center"))
        verdict = next((v for v in review(self._ctx, row.id).candidates if v.rank == doc.rank), None)
        self._info.content = (
            f"{title}\n\nRank **{doc.rank} of {doc.n_candidates}**: RA {candidate.ra_deg:.3f}°, "
            f"Dec {candidate.dec_deg:.3f}°, roll {candidate.roll_deg:.3f}°  \n"
            f"deviation {candidate.deviation_arcsec}″, false-match probability "
            f"{candidate.false_match_probability:.3g}, {len(hips)} of {len(points)} points matched  \n"
            + _credibility_text(verdict)
            + ("" if doc.confirmation_id is None else f"  \nconfirmed as attitude #{doc.confirmation_id}"))
        camera_key = (doc.session, doc.sequence, doc.search_id, doc.rank)
        if camera_key != self._camera_key:
            self._point_camera(boresight)
            self._camera_key = camera_key

    def _draw_pattern(self, rotation, camera, points: list, matched_tracks: set) -> None:
        xy = np.array([[p.x, p.y] for p in points], dtype=float).reshape(-1, 2)
        directions = geo.pixel_directions(rotation, camera, xy)
        colours = np.array([RAY_MATCHED if p.track in matched_tracks and p.track is not None
                            else RAY_UNMATCHED for p in points], dtype=np.uint8).reshape(-1, 3)
        scene = self.client.scene
        if len(points):
            self._candidate_nodes.append(scene.add_line_segments(
                "/candidate/rays", geo.ray_segments(directions),
                np.repeat(colours[:, None, :], 2, axis=1), thickness=1.5, thickness_units="screen"))
        manual_index = 0
        for i, (point, direction) in enumerate(zip(points, directions)):
            track = point.track
            handle = scene.add_icosphere(f"/candidate/pattern/{i}", radius=0.09, color=tuple(int(c) for c in colours[i]),
                                         position=tuple(geo.SPHERE_RADIUS * direction), subdivisions=2)
            if track is None:
                index = manual_index
                manual_index += 1
                handle.on_click(lambda event, index=index: self._toggle(
                    lambda d: geo.remove_manual_point(d, index)))
            else:
                handle.on_click(lambda event, track=track: self._toggle(lambda d: geo.toggle_track(d, track)))
            self._candidate_nodes.append(handle)

    def _draw_excluded(self, rotation, camera, item, in_pattern: set) -> None:
        """Grey spheres for tracks the operator took out, at their automatic pattern positions."""
        scene = self.client.scene
        automatic = item.extraction.pattern
        for track, xy in zip(automatic.track_ids.tolist(), automatic.xy):
            if track < 0 or track in in_pattern or not np.all(np.isfinite(xy)):
                continue
            direction = geo.pixel_directions(rotation, camera, [xy])[0]
            handle = scene.add_icosphere(f"/candidate/excluded/{track}", radius=0.07, color=EXCLUDED_COLOUR,
                                         position=tuple(geo.SPHERE_RADIUS * direction), subdivisions=2)
            handle.on_click(lambda event, track=track: self._toggle(lambda d: geo.toggle_track(d, track)))
            self._candidate_nodes.append(handle)

    def _point_camera(self, boresight: np.ndarray) -> None:
        """Look at the candidate's field on the sphere from halfway out along the boresight.

        The camera orbits the field centre, so dragging shows the frustum and
        rays from the side while the field stays in view.
        """
        self.client.camera.position = tuple(0.45 * geo.SPHERE_RADIUS * boresight)
        self.client.camera.look_at = tuple(geo.SPHERE_RADIUS * boresight)


class Viewer:
    """The running 3D view of one :class:`app.workflow.AppContext`: one :class:`Panel` per admitted client.

    Each browser client of the viser server is admitted with the console
    session named in its address (:class:`ViewerClients`, at most
    :data:`MAX_3D_VIEWS`) and gets its own GUI and candidate scene; the sky
    (constellation names, equator) is shared.  One poll thread reads each
    drawn session's state once a round and redraws the panels whose state
    changed.  A client past the bound, or naming a malformed session, is
    told why and drawn nothing; a panel goes when its client leaves or its
    session ends (the view-state store forgot it).
    """

    def __init__(self, context, server, sky: SkyModel, max_views: int = MAX_3D_VIEWS) -> None:
        self.context = context
        self.sky = sky
        self._server = server
        self.clients = ViewerClients(max_views)
        self._panels: dict[int, Panel] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._wake = threading.Event()
        server.gui.configure_theme(dark_mode=True, show_logo=False, show_share_button=False,
                                   brand_color=(90, 180, 255))
        self._draw_static()
        context.view.on_forget(self._session_ended)
        server.on_client_connect(self._connected)
        server.on_client_disconnect(self._disconnected)
        self._thread = threading.Thread(target=self._poll, name="viewer-poll", daemon=True)
        self._thread.start()

    # --- life cycle ---------------------------------------------------------
    @classmethod
    def start(cls, context, port: int) -> "Viewer":
        import viser

        sky = SkyModel.load()
        server = viser.ViserServer(host=VIEWER_HOST, port=port, label="Star pattern 3D view", verbose=False)
        try:
            return cls(context, server, sky)
        except BaseException:
            server.stop()
            raise

    @property
    def port(self) -> int:
        """The port viser really listens on (it moves to the next free one when asked for a busy one)."""
        return int(self._server.get_port())

    def describe(self, session: str | None = None) -> ViewerDocument:
        """Where the 3D view listens; its ``url`` opens a view of ``session`` (None: the bare address)."""
        base = f"http://{VIEWER_HOST}:{self.port}/"
        return ViewerDocument(available=True, url=address_for_session(base, session), host=VIEWER_HOST,
                              port=self.port, session=session, views=len(self.clients),
                              max_views=self.clients.limit)

    def wake(self) -> None:
        """Redraw now rather than at the next poll."""
        self._wake.set()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout=2.0)
        self._server.stop()

    # --- clients ------------------------------------------------------------
    def _connected(self, client) -> None:
        try:
            session = _session_of_client(self._server, client.client_id)
        except ValueError as exc:
            client.gui.add_markdown(f"**This 3D view's address is not one a console opens:** {markdown_text(exc)}. "
                                    "Open the 3D view from a console's 3D view tab.")
            return
        if not self.clients.attach(client.client_id, session):
            client.gui.add_markdown(refusal_text(self.clients.limit))
            return
        panel = Panel(self, client, session)
        with self._lock:
            self._panels[client.client_id] = panel
        self._wake.set()

    def _disconnected(self, client) -> None:
        self.clients.detach(client.client_id)
        with self._lock:
            self._panels.pop(client.client_id, None)

    def _session_ended(self, session: str) -> None:
        for client_id in self.clients.end_session(session):
            with self._lock:
                panel = self._panels.pop(client_id, None)
            if panel is not None:
                try:
                    panel.release(SESSION_ENDED_TEXT)
                except Exception:  # its client left meanwhile
                    log.exception("3D view could not release a panel")

    # --- scene --------------------------------------------------------------
    def _draw_static(self) -> None:
        scene = self._server.scene
        scene.set_up_direction("+z")
        for name, vector in self.sky.anchors:
            scene.add_label(f"/sky/constellations/{name}", name, position=tuple(geo.SPHERE_RADIUS * LABEL_OFFSET
                                                                              * vector), font_screen_scale=0.8)
        t = np.linspace(0, 2 * np.pi, 121)
        ring = geo.SPHERE_RADIUS * np.column_stack([np.cos(t), np.sin(t), np.zeros_like(t)])
        scene.add_line_segments("/sky/equator", np.stack([ring[:-1], ring[1:]], axis=1), (60, 70, 110),
                                thickness=0.02)
        scene.add_label("/sky/ncp", "North celestial pole", position=(0.0, 0.0, geo.SPHERE_RADIUS * LABEL_OFFSET))

    def _poll(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                panels = list(self._panels.values())
            documents = {}  # each session is read once a round, however many views draw it
            for panel in panels:
                try:
                    session = panel.current_session()
                    if session not in documents:
                        documents[session] = view.view_document(self.context, session)
                    panel.refresh(documents[session])
                except Exception:  # a bad record or a client gone must not kill the view; try again next time
                    log.exception("3D view could not draw a session's state")
            self._wake.wait(POLL_S)
            self._wake.clear()


def start_viewer(context, port: int) -> Viewer | None:
    """Start the 3D view on 127.0.0.1:``port`` (or the next free port); None, logged, if it cannot start.

    The API must keep serving without the 3D view, so nothing raised here
    reaches the caller.
    """
    try:
        viewer = Viewer.start(context, port)
    except Exception:
        log.exception("the 3D view (viser) could not start; serving without it")
        return None
    log.info("3D view on http://%s:%d/", VIEWER_HOST, viewer.port)
    return viewer
