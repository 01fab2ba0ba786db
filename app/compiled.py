"""Compiled kernels: numba's ``njit`` with its on-disk cache, and the one warm-up that compiles them.

Why numba.  The identification's inner steps (an optics fit's Gauss-Newton,
the nearest star of every point of every hypothesis, a refinement's
re-matching) are loops over a dozen points where each numpy call costs
microseconds of overhead whatever the data (the floor numpy set).  numba
compiles them to machine code from the Python source: wheels for every
platform we support, no compiler on the user's machine.

Where the compiled code is kept.  ``njit(cache=True)`` keeps each kernel's
machine code on disk, so only the first run after an install compiles.
The cache goes to ``$NUMBA_CACHE_DIR`` when set, else to the project's cache
directory (``settings().cache_dir / "numba"``): an installed package's
directory may be read-only, and the project's other derived data (the
bright-pair index, the cell maps) live there too.  The variable is set here,
before numba is first imported.

Compiling.  Each kernel module registers a warm-up (:func:`warm_up_with`: a
call of each kernel on tiny inputs of the types the program uses).
:func:`warm_up` runs them all once per process and says in ONE log line
whether it compiled (the first run after an install: 32-36 s of CPU for
the 49 kernels of 2026-11-25, more with each new one) or loaded the cache
(0.2-0.3 s, most of it numba setting itself up for its first kernel).
:func:`app.identification.identify` warms up before its search's clock
starts; a server's compute pool (:mod:`app.workflow.compute`) warms up in
its workers, or in a thread of its own, while the server answers.
Processes warming up at once take turns (a lock file in the cache
directory): the first compiles, the others load what it wrote.
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
import time
from pathlib import Path
from typing import Callable, Iterator

from app.config import settings

log = logging.getLogger(__name__)

if not os.environ.get("NUMBA_CACHE_DIR"):
    os.environ["NUMBA_CACHE_DIR"] = str(settings().cache_dir / "numba")

import numba  # noqa: E402  (after NUMBA_CACHE_DIR: numba reads it when imported)

_warm_ups: list[Callable[[], None]] = []
_kernels: list = []
_warm_lock = threading.Lock()
_warmed = False
_report: dict = {}


def njit(function):
    """``numba.njit(cache=True)`` of ``function``, registered for :func:`warm_up`'s report.

    ``error_model="numpy"``: a float division by zero gives inf or nan as numpy's does (the kernels replace
    numpy code), not Python's ZeroDivisionError.
    """
    kernel = numba.njit(cache=True, error_model="numpy")(function)
    _kernels.append(kernel)
    return kernel


def warm_up_with(function: Callable[[], None]) -> Callable[[], None]:
    """Register ``function`` (no arguments: calls of a module's kernels on tiny inputs) for :func:`warm_up`."""
    _warm_ups.append(function)
    return function


def warm_up(say: bool = True) -> dict:
    """Compile (or load from the cache) every registered kernel, once per process; one log line says which.

    Returns ``{"seconds": ..., "compiled": n kernels compiled now, "loaded": n loaded from the cache}``.
    ``say=False`` leaves the log line to the caller (:func:`describe`): a
    worker process has no log of its own and reports to its server.
    """
    global _warmed, _report
    if _warmed:
        return _report
    with _warm_lock:
        if _warmed:  # another thread warmed them while this one waited
            return _report
        t0 = time.perf_counter()
        with _one_process_at_a_time():
            for function in list(_warm_ups):
                function()
        _report = {"seconds": time.perf_counter() - t0,
                   "compiled": sum(sum(k.stats.cache_misses.values()) for k in _kernels),
                   "loaded": sum(sum(k.stats.cache_hits.values()) for k in _kernels)}
        _warmed = True
        if say:
            log.log(logging.WARNING if _report["compiled"] else logging.INFO, "%s", describe(_report))
        return _report


def describe(report: dict) -> str:
    """:func:`warm_up`'s report in words: compiled (the first run after an install) or loaded from the cache."""
    if report["compiled"]:
        return (f"compiled {report['compiled']} numba kernels in {report['seconds']:.1f} s (the first run after "
                f"an install; kept in {os.environ['NUMBA_CACHE_DIR']})")
    return f"loaded {report['loaded']} compiled kernels from {os.environ['NUMBA_CACHE_DIR']} in {report['seconds']:.2f} s"


@contextlib.contextmanager
def _one_process_at_a_time() -> Iterator[None]:
    """An exclusive lock on the cache directory while warming up: the processes starting together (a server's
    workers, a batch's) compile one after the other, the first writing the cache the others then load.

    Not a lock per warm-up, letting processes compile different warm-ups at once: the kernels call one another,
    so several processes compiled the same callees, and three processes on two cores took 78 s to be warm
    against 37 s taking turns (one run each on a busy machine, 2026-11-25)."""
    try:
        import fcntl
    except ImportError:  # not POSIX: each process compiles for itself
        yield
        return
    directory = Path(os.environ["NUMBA_CACHE_DIR"])
    try:
        directory.mkdir(parents=True, exist_ok=True)
        lock = open(directory / "warm-up.lock", "a")
    except OSError:  # a read-only cache: nothing to share
        yield
        return
    with lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
