"""Derived data in the cache directory: arrays kept on disk, and processes taking turns to build them.

A server's workers, a batch's Dask workers and a CLI started beside a
server each load the bright-pair index, the cell maps and the compiled
kernels from the cache directory, and on a first run each would build them.
Holding the lock of what it builds (:func:`exclusive`), the first process
builds it; the others wait, then load what it wrote.  Arrays are written
through a temporary file and an atomic rename (:func:`keep_arrays`), so a
reader never sees half a file, and a file that cannot be read is made again,
never trusted (:func:`kept_arrays`).

The lock is a POSIX ``flock`` on a file beside the data: released by the
kernel when the process dies, so a crash never leaves a stale lock.  Where
there is none to take (not POSIX, a read-only directory) every process works
for itself, and a cache that cannot be written is only said in the log.
"""

from __future__ import annotations

import contextlib
import logging
import os
import zipfile
from pathlib import Path
from typing import Iterator

import numpy as np

log = logging.getLogger(__name__)


@contextlib.contextmanager
def exclusive(path: Path) -> Iterator[bool]:
    """Hold an exclusive lock on ``path`` (created if missing) for the block; yields whether there is one."""
    try:
        import fcntl
    except ImportError:  # not POSIX
        yield False
        return
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        handle = open(path, "a")
    except OSError:  # a read-only cache: nothing to share
        yield False
        return
    with handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield True
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def kept_arrays(path: Path) -> dict[str, np.ndarray] | None:
    """The arrays kept at ``path`` (an ``.npz``); None when there are none, or they cannot be read (said in the
    log: the caller makes them again)."""
    try:
        with np.load(path) as z:
            return {k: z[k] for k in z.files}
    except FileNotFoundError:
        return None
    except (OSError, KeyError, ValueError, zipfile.BadZipFile) as exc:
        log.warning("cache %s unreadable (%s); making it again", path, exc)
        return None


def keep_arrays(path: Path, **arrays) -> None:
    """Write ``arrays`` to ``path`` (an ``.npz``) through a temporary file of this process and an atomic
    rename; a cache that cannot be written is said in the log, not raised."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".{os.getpid()}.tmp.npz")  # one per process: two may write at once
        np.savez(tmp, **arrays)
        tmp.replace(path)  # atomic: a concurrent reader never sees half a file
    except OSError as exc:
        log.info("cache %s not written (%s)", path, exc)
