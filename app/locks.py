"""Exclusive locks on files of the cache directory, for derived data several processes may want at once.

A server's workers, a batch's Dask workers and a CLI started beside a
server each load the bright-pair index, the cell maps and the compiled
kernels from the cache directory, and on a first run each would build them.
Holding the lock of what it builds, the first process builds it; the others
wait, then load what it wrote (each build writes through a temporary file
and an atomic rename, so a reader never sees half a file either way).

A POSIX ``flock`` on a file beside the data: released by the kernel when
the process dies, so a crash never leaves a stale lock.  Where there is none
to take (not POSIX, a read-only directory) every process works for itself.
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Iterator


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
