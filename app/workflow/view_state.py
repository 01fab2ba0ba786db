"""The view state of each console session: which sequence, candidate rank and magnitude limit it shows.

Every browser tab of the console is a *session* with its own selection
(two operators, or two tabs, must not move each other's
sequence).  A console names its session in every ``GET``/``PUT /api/view``
(``?session=...``, a random id the tab keeps in its sessionStorage).  Each
3D view (a browser client of the viser server) draws the session named in
the address the console opened it at, so several consoles each have their
own 3D view at once: :class:`ViewerClients` keeps which client draws which
session, at most :data:`MAX_3D_VIEWS` of them.  A 3D view opened at the
bare address names no session and draws :attr:`ViewStateStore.followed`,
the session of the console that opened its 3D tab last (``PUT
/api/viewer``); a request without a session means that one too.  So a 3D
view and the console that opened it stay two windows onto one selection,
while other consoles keep theirs.

``revision`` grows by one on every write to a session, so a reader only
compares one integer to know whether anything changed.

The records live in the application context (one per server process): they
are presentation state, not archive data, and must not outlive the server
or be replayed by a restore.  Sessions nobody wrote to for a long time are
forgotten first once there are :data:`MAX_SESSIONS` of them; a forgotten
session has ended, and the 3D views drawing it are released
(:meth:`ViewStateStore.on_forget`, :meth:`ViewerClients.end_session`).
"""

from __future__ import annotations

import math
import re
import threading
from collections import OrderedDict
from dataclasses import dataclass, replace
from datetime import datetime, timezone
from urllib.parse import parse_qs, urlencode, urlsplit

from app.workflow.text import operator_name_problem

#: Magnitude limit of a fresh view (Hp), and the range the sky-section endpoint accepts.
DEFAULT_MAG = 6.0
MAG_MIN, MAG_MAX = -2.0, 7.0
#: Who may have made a write, for the record.
WRITERS = ("console", "viewer", "server")
#: The session of clients that name none (scripts, the 3D view before any console opened it).
DEFAULT_SESSION = "shared"
#: What a session id may look like: the console makes UUIDs; scripts may choose a name.
SESSION_PATTERN = r"^[A-Za-z0-9_-]{1,64}$"
_SESSION_RE = re.compile(SESSION_PATTERN)
#: Sessions kept in memory (a few hundred bytes each); the least recently used go first.
MAX_SESSIONS = 1000
#: 3D views drawn at once (browser clients of the viser server): each is redrawn by the server's poll thread
#: from the archive, on a machine that also searches, so their number is bounded.
MAX_3D_VIEWS = 8


@dataclass(frozen=True)
class ConfirmRequest:
    """A confirmation the 3D view sends to the console of its session: a rank whose confirmation needs the
    console's second step (a reason, or the replacement of the verdict), which the 3D panel does not have."""

    sequence: int
    rank: int
    search_id: int | None  # the search whose rank it is: a console showing another search does not take it
    number: int  # the revision of the session's write that sent it (set by the store): each is taken once
    comment: str | None = None  # typed in the 3D view: the console puts it in its comment box


@dataclass(frozen=True)
class ViewState:
    """One immutable snapshot of a session's view."""

    sequence: int | None = None  # archive id of the sequence shown, None before any choice
    rank: int | None = None  # candidate rank of its latest search, None when there is none
    mag: float = DEFAULT_MAG  # faintest catalogue star drawn (Hp)
    revision: int = 0  # +1 per write
    updated_by: str = "server"
    updated_at: datetime | None = None
    session: str = DEFAULT_SESSION
    operator: str | None = None  # the name typed in this session's console: the 3D view confirms under it
    confirm_request: ConfirmRequest | None = None  # the 3D view's latest, for this session's console


_UNSET = object()


class ViewStateStore:
    """Thread-safe holder of every session's :class:`ViewState` and of the session the bare-address 3D view draws.

    ``update`` changes only the fields it is given (``None`` is a value: it
    clears a field), so the console setting the rank never undoes a
    magnitude change the 3D view just made.  ``session=None`` everywhere
    means the session the bare-address 3D view follows (:attr:`followed`).
    """

    def __init__(self, max_sessions: int = MAX_SESSIONS) -> None:
        self._states: OrderedDict[str, ViewState] = OrderedDict()
        self._followed = DEFAULT_SESSION
        self._max = max_sessions
        self._lock = threading.Lock()
        self._forget_listeners: list = []

    def on_forget(self, listener) -> None:
        """Call ``listener(session)`` for every session forgotten from now on (after the write that pushed it
        out, outside the store's lock): that session has ended."""
        self._forget_listeners.append(listener)

    @property
    def followed(self) -> str:
        """The session the bare-address 3D view draws (and that requests without a session read and write)."""
        with self._lock:
            return self._followed

    def follow(self, session: str) -> str:
        """Make the 3D view at its bare address draw ``session`` from now on; ValueError for a malformed id."""
        session = check_session(session)
        with self._lock:
            self._followed = session
            return session

    def _resolve(self, session: str | None) -> str:
        return self._followed if session is None else check_session(session)

    def get(self, session: str | None = None) -> ViewState:
        """The session's state (a fresh one, not stored, for a session that never wrote)."""
        with self._lock:
            name = self._resolve(session)
            return self._states.get(name) or ViewState(session=name)

    def request_confirmation(self, session: str | None, sequence: int, rank: int, search_id: int | None,
                             comment: str | None = None) -> ViewState:
        """Send a confirmation of ``rank`` of ``sequence`` (and the comment typed with it) to the session's
        console (one write by the 3D view)."""
        sequence, rank = _optional_positive_int("sequence", sequence), _optional_positive_int("rank", rank)
        if sequence is None or rank is None:
            raise ValueError("a confirmation request names a sequence and a rank")
        return self.update(session=session, confirm_request=ConfirmRequest(sequence, rank, search_id, number=0,
                                                                                  comment=comment),
                           updated_by="viewer")

    def update(self, *, session: str | None = None, sequence=_UNSET, rank=_UNSET, mag=_UNSET, operator=_UNSET,
               confirm_request=_UNSET, updated_by: str = "server") -> ViewState:
        """Apply the given fields to one session as one write; ValueError for a value out of its range."""
        changes = {}
        if sequence is not _UNSET:
            changes["sequence"] = _optional_positive_int("sequence", sequence)
        if rank is not _UNSET:
            changes["rank"] = _optional_positive_int("rank", rank)
        if mag is not _UNSET:
            changes["mag"] = check_mag(mag)
        if operator is not _UNSET:
            changes["operator"] = check_operator(operator)
        if confirm_request is not _UNSET:
            if confirm_request is not None and not isinstance(confirm_request, ConfirmRequest):
                raise ValueError(f"not a confirmation request: {confirm_request!r}")
            changes["confirm_request"] = confirm_request
        if updated_by not in WRITERS:
            raise ValueError(f"unknown writer {updated_by!r}")
        forgotten = []
        with self._lock:
            name = self._resolve(session)
            old = self._states.get(name) or ViewState(session=name)
            if changes.get("confirm_request") is not None:  # numbered by the write that sends it: taken once
                changes["confirm_request"] = replace(changes["confirm_request"], number=old.revision + 1)
            state = replace(old, **changes, revision=old.revision + 1, updated_by=updated_by,
                            updated_at=datetime.now(timezone.utc))
            self._states[name] = state
            self._states.move_to_end(name)
            while len(self._states) > self._max:
                oldest = next(iter(self._states))
                if oldest == self._followed:  # the bare-address 3D view's session is kept
                    self._states.move_to_end(oldest)
                    oldest = next(iter(self._states))
                self._states.pop(oldest)
                forgotten.append(oldest)
        for ended in forgotten:
            for listener in self._forget_listeners:
                listener(ended)
        return state

    def sessions(self) -> int:
        with self._lock:
            return len(self._states)


def check_operator(value) -> str | None:
    """An operator's name for a session (None or blank: none); ValueError as :mod:`app.workflow.text` says."""
    if value is None or not str(value).strip():
        return None
    name = str(value).strip()
    problem = operator_name_problem(name)
    if problem:
        raise ValueError(f"operator: {problem}")
    return name


def check_session(value) -> str:
    """``value`` as a session id; ValueError saying what one looks like."""
    if not isinstance(value, str) or not _SESSION_RE.match(value):
        raise ValueError(f"a session id is 1-64 letters, digits, '-' or '_', not {value!r}")
    return value


def _optional_positive_int(name: str, value) -> int | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{name} must be a positive integer or null, not {value!r}")
    return int(value)


def check_mag(value) -> float:
    """``value`` as a float magnitude limit in [MAG_MIN, MAG_MAX]; ValueError if it is not a finite number."""
    try:
        mag = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"mag must be a number, not {value!r}") from None
    if not math.isfinite(mag) or not MAG_MIN <= mag <= MAG_MAX:
        raise ValueError(f"mag must be within {MAG_MIN}..{MAG_MAX}, not {value!r}")
    return mag


class ViewerClients:
    """Which console session each 3D view (a viser client, by its id) draws: at most ``limit`` at once.

    A client is admitted with the session named in its address, or ``None``
    for the bare address (it draws :attr:`ViewStateStore.followed`).  Past
    the bound it is refused and the caller shows it why; it is never
    admitted later by itself (a reload asks again).  A client leaves when its
    browser tab or frame closes (:meth:`detach`), and all the clients of a
    session leave when the session ends (:meth:`end_session`).  Pure
    bookkeeping, thread-safe: drawing is the viewer's.
    """

    def __init__(self, limit: int = MAX_3D_VIEWS) -> None:
        if limit < 1:
            raise ValueError(f"a 3D view bound is at least 1, not {limit!r}")
        self.limit = limit
        self._session_of: dict[int, str | None] = {}
        self._lock = threading.Lock()

    def attach(self, client: int, session: str | None) -> bool:
        """Admit ``client`` drawing ``session`` (None: the followed one); False when ``limit`` clients are
        drawn already.  ValueError for a malformed session id."""
        session = None if session is None else check_session(session)
        with self._lock:
            if client not in self._session_of and len(self._session_of) >= self.limit:
                return False
            self._session_of[client] = session
            return True

    def detach(self, client: int) -> bool:
        """Forget ``client`` (its tab closed); whether it was admitted."""
        with self._lock:
            return self._session_of.pop(client, _UNSET) is not _UNSET

    def end_session(self, session: str) -> list[int]:
        """Forget every client drawing ``session`` (the session ended) and return them, in admission order."""
        with self._lock:
            gone = [client for client, name in self._session_of.items() if name == session]
            for client in gone:
                del self._session_of[client]
            return gone

    def session_of(self, client: int) -> str | None:
        """The session ``client`` draws (None: the followed one); KeyError for a client not admitted."""
        with self._lock:
            return self._session_of[client]

    def clients_of(self, session: str | None) -> list[int]:
        """The admitted clients drawing ``session`` (None: those at the bare address), in admission order."""
        with self._lock:
            return [client for client, name in self._session_of.items() if name == session]

    def __len__(self) -> int:
        with self._lock:
            return len(self._session_of)


def session_in_address(address: str) -> str | None:
    """The console session named in a 3D view's websocket address (``ws://host:port/?session=ID``): None when it
    names none; ValueError for a malformed id or for two different ones."""
    names = set(parse_qs(urlsplit(address).query, keep_blank_values=True).get("session", []))
    if len(names) > 1:
        raise ValueError(f"the 3D view's address names {len(names)} sessions: {sorted(names)!r}")
    return check_session(names.pop()) if names else None


def address_for_session(http_base: str, session: str | None) -> str:
    """The 3D view's page address for a console ``session`` (None: the bare address).

    viser's page connects its websocket to the address in its ``websocket``
    parameter (the page's own address without its query otherwise), so the
    session rides in that websocket address's query, where
    :func:`session_in_address` reads it back on the server.
    """
    if session is None:
        return http_base
    socket = "ws" + http_base.removeprefix("http") + "?" + urlencode({"session": check_session(session)})
    return http_base + "?" + urlencode({"websocket": socket})
