"""Where the server's CPU-bound work runs: extraction and identification.

Python runs one thread at a time per process, so searches computed in the
server's own threads take turns on one core while the other idles, and
every request waits behind them.  :class:`ComputePool` runs that work in
worker processes instead (``spawn``ed: safe beside the server's threads, and
nothing of the server - sockets, the database - is inherited).  Each worker
builds its own :class:`app.identification.Sky` once, at start-up (about a
second; the server loads its own first, so that on a first start the index
cache the workers read exists), and a job carries only its sequence and
pattern.

With ``processes=0`` (tests, or a server given its own ``Sky``) the same
jobs run in a thread pool with the server's ``Sky``.

Job functions take the ``Sky`` as a keyword argument ``sky``; in a worker
process it is filled in from :data:`worker_context`.
"""

from __future__ import annotations

import multiprocessing
import os
import threading
import time
from concurrent.futures import Executor, Future, ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Callable


@dataclass
class WorkerContext:
    """The application context of one worker process, built at its start-up."""

    sky: Any  # app.identification.Sky


#: Set in each worker process by :func:`_start_worker`; None in the server itself.
worker_context: WorkerContext | None = None


#: How often a worker checks that the server is still there, seconds.
PARENT_CHECK_S = 1.0


def _start_worker() -> None:
    global worker_context
    from app.identification import Sky

    _exit_with_parent(os.getppid())
    worker_context = WorkerContext(sky=Sky())


def _exit_with_parent(parent_pid: int) -> None:
    """Exit when the server dies: after a SIGKILL nobody shuts the pool down, and an orphaned
    worker would wait for jobs forever."""
    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(PARENT_CHECK_S)
        os._exit(0)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def _in_worker(fn: Callable, args: tuple, kwargs: dict):
    if worker_context is None:
        raise RuntimeError("the worker process was not initialised")
    return fn(*args, sky=worker_context.sky, **kwargs)


def _ready() -> bool:
    return worker_context is not None


class ComputePool:
    """``processes`` worker processes (or, with 0, ``threads`` threads sharing ``sky``)."""

    def __init__(self, processes: int, *, threads: int = 1, sky: Any = None) -> None:
        self.processes = max(0, int(processes))
        self._threads = max(1, threads)
        self._sky = sky
        self._executor: Executor
        if self.processes:
            self._executor = ProcessPoolExecutor(max_workers=self.processes,
                                                 mp_context=multiprocessing.get_context("spawn"),
                                                 initializer=_start_worker)
        else:
            if sky is None:
                raise ValueError("a thread pool needs the server's Sky")
            self._executor = ThreadPoolExecutor(max_workers=self._threads, thread_name_prefix="compute")

    @property
    def kind(self) -> str:
        """What the pool is, in words (``/api/health`` shows it)."""
        return f"{self.processes} processes" if self.processes else f"{self._threads} threads"

    def submit(self, fn: Callable, *args, **kwargs) -> Future:
        """Run ``fn(*args, sky=<Sky>, **kwargs)`` in the pool."""
        if self.processes:
            return self._executor.submit(_in_worker, fn, args, kwargs)
        return self._executor.submit(fn, *args, sky=self._sky, **kwargs)

    def warm_up(self) -> None:
        """Start every worker now (each loads the catalogue), so the first searches do not wait."""
        if self.processes:
            for _ in range(self.processes):
                self._executor.submit(_ready)

    def shutdown(self) -> None:
        self._executor.shutdown(wait=False, cancel_futures=True)
