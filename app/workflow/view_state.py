"""The shared view state: which sequence, candidate rank and magnitude limit operators look at.

The browser console and the 3D view are two windows onto one selection.
Neither talks to the other: both write this small record (the console
through ``PUT /api/view``, the viser GUI directly in-process) and both read
it back (the console polls ``GET /api/view`` about once a second, the 3D
view polls the store in its own thread).  ``revision`` grows by one on
every write, so a reader only has to compare one integer to know whether
anything changed.

The record lives in the application context (one per server process): it is
a presentation state, not archive data, and it must not outlive the server
or be replayed by a restore.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, replace
from datetime import datetime, timezone

#: Magnitude limit of a fresh view (Hp), and the range the sky-section endpoint accepts.
DEFAULT_MAG = 6.0
MAG_MIN, MAG_MAX = -2.0, 7.0
#: Who may have made a write, for the record.
WRITERS = ("console", "viewer", "server")


@dataclass(frozen=True)
class ViewState:
    """One immutable snapshot of the shared view."""

    sequence: int | None = None  # archive id of the sequence shown, None before any choice
    rank: int | None = None  # candidate rank of its latest search, None when there is none
    mag: float = DEFAULT_MAG  # faintest catalogue star drawn (Hp)
    revision: int = 0  # +1 per write
    updated_by: str = "server"
    updated_at: datetime | None = None



_UNSET = object()


class ViewStateStore:
    """Thread-safe holder of the current :class:`ViewState`.

    ``update`` changes only the fields it is given (``None`` is a value: it
    clears a field), so the console setting the rank never undoes a
    magnitude change the 3D view just made.
    """

    def __init__(self) -> None:
        self._state = ViewState()
        self._lock = threading.Lock()

    def get(self) -> ViewState:
        with self._lock:
            return self._state

    def update(self, *, sequence=_UNSET, rank=_UNSET, mag=_UNSET, updated_by: str = "server") -> ViewState:
        """Apply the given fields as one write; ValueError for a value out of its range."""
        changes = {}
        if sequence is not _UNSET:
            changes["sequence"] = _optional_positive_int("sequence", sequence)
        if rank is not _UNSET:
            changes["rank"] = _optional_positive_int("rank", rank)
        if mag is not _UNSET:
            changes["mag"] = check_mag(mag)
        if updated_by not in WRITERS:
            raise ValueError(f"unknown writer {updated_by!r}")
        with self._lock:
            self._state = replace(self._state, **changes, revision=self._state.revision + 1,
                                  updated_by=updated_by, updated_at=datetime.now(timezone.utc))
            return self._state


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
