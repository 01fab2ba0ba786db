"""Where the server's CPU-bound work runs: extraction and identification.

Python runs one thread at a time per process, so searches computed in the
server's own threads take turns on one core while the other idles, and
every request waits behind them.  :class:`ComputePool` runs that work in
worker processes instead (``spawn``ed: safe beside the server's threads, and
nothing of the server - sockets, the database - is inherited).  Each worker
builds its own :class:`app.identification.Sky` once, at start-up (about a
second; the server loads its own first, so that on a first start the index
cache the workers read exist), and a job carries only its sequence and
pattern.

**Kernels first, while the server answers.**  Every worker, bulk ones too
(an extraction needs them), loads the compiled kernels
(:func:`app.compiled.warm_up`: 0.2-0.5 s from their cache; on the first
start after an install one worker compiles them, 30-60 s on two busy
cores, and the others load what it wrote) before it says it is ready, and
takes no job before: a job is timed from when it is sent, and compiling
inside it would run it past its hard limit.  The server does not wait for
them: :attr:`ComputePool.kernels_ready` is a
future done once every lane has a ready worker (one log line says so,
compiled or loaded, and when), and a request that needs the pool waits for
it first, its time-out counted from then (:mod:`app.api.routes.common`), so
nothing fails for a compilation while health, the console and the archive
answer at once.

The pool is written out here rather than taken from
:class:`concurrent.futures.ProcessPoolExecutor` because the server needs
four things that executor cannot give:

* **Lanes.**  Interactive work (searches, ordinary uploads) runs on the
  ``processes`` workers; large uploads (:data:`BULK`) run on their own
  ``bulk_processes`` workers, which load no catalogue and run only on CPU
  time nothing else wants (``SCHED_IDLE``), so that a client sending
  worst-case files occupies at most those and ordinary searches keep their
  speed.
* **Deadlines.**  :meth:`ComputePool.submit_within` gives a job the time by
  which its answer is useless; a job still waiting then is dropped
  (:class:`JobExpired`) instead of occupying a worker for a client that
  already got its 503.
* **A hard limit.**  A job running longer than its hard limit (``hard_limit_s``
  for jobs with a deadline, :data:`UNDATED_HARD_LIMIT_S` for the others) has
  its worker killed and replaced (:class:`JobKilled`): every piece of work
  has a bound even where the code it runs has none.
* **A life-cycle that ends with the server.**  Workers are started from the
  pool's own thread, which lives as long as the pool, and ask Linux to
  SIGKILL them when that thread's process dies (``PR_SET_PDEATHSIG``); a
  watcher thread also compares the parent's pid with the server's, which
  covers a server killed while the worker was still starting.  Nothing
  here uses multiprocessing queues or semaphores (only pipes), so a normal
  stop leaves nothing for the resource tracker to report.

With ``processes=0`` (tests, or a server given its own ``Sky``) the same
jobs run in threads of the server with the server's ``Sky``.

Job functions take the ``Sky`` as a keyword argument ``sky`` (None in a
bulk worker, which loads none).
"""

from __future__ import annotations

import collections
import itertools
import logging
import multiprocessing
import os
import pickle
import signal
import socket
import threading
import time
import traceback
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from multiprocessing.connection import wait as wait_for_connections
from typing import Any, Callable

from app.workflow.errors import Busy

log = logging.getLogger(__name__)

#: Searches and ordinary uploads.
INTERACTIVE = "interactive"
#: Large uploads: their own workers, at a lower CPU priority.
BULK = "bulk"
LANES = (INTERACTIVE, BULK)

#: How often a worker checks that the server is still its parent, seconds.
PARENT_CHECK_S = 0.2
#: CPU priority of the bulk workers (added niceness) where the idle scheduling class is not available.
BULK_NICENESS = 19
#: A worker that fails to start is started again after this many seconds, doubling up to the cap.
RESTART_BACKOFF_S = (0.5, 30.0)
#: A worker stopped by SIGINT or SIGTERM before it could ignore them is replaced after this many seconds: the
#: same stop reached the server (Ctrl-C in a terminal, a service manager), which is shutting down meanwhile.
STOPPED_WHILE_STARTING_S = 5.0
#: How long a request waits for :attr:`ComputePool.kernels_ready` at most, seconds: a first start compiled the
#: 49 kernels of 2026-11-25 in 37-65 s on two busy cores (32-36 s of CPU), and each new kernel adds to that.
WARM_UP_TIMEOUT_S = 300.0
#: The modules whose import registers every compiled kernel's warm-up (:func:`app.compiled.warm_up_with`).
KERNEL_MODULES = ("app.identification",)
#: Default hard limit of one job, as a multiple of the search time-out (STARID_SEARCH_TIMEOUT_S).
HARD_LIMIT_FACTOR = 3.0
#: Hard limit of a job submitted without a deadline (background work, or callers with budgets of
#: their own such as reading image frames, 60 s by default): generous, but a bound.
UNDATED_HARD_LIMIT_S = 300.0

_PR_SET_PDEATHSIG = 1


class JobExpired(Busy):
    """The job's deadline passed before a worker was free for it; it never ran."""


class JobKilled(Busy):
    """The job ran past the pool's hard limit; its worker was killed and replaced."""


class WorkerLost(RuntimeError):
    """The worker process died while running the job (a crash, or the pool shutting down)."""


# ---------------------------------------------------------------------------
# The worker process
# ---------------------------------------------------------------------------

@dataclass
class WorkerContext:
    """The application context of one worker process, built at its start-up."""

    sky: Any  # app.identification.Sky, or None in a bulk worker


#: Set in each worker process by :func:`_worker_main`; None in the server itself.
worker_context: WorkerContext | None = None


def _die_with_server(server_pid: int) -> None:
    """Exit when the server dies: after a SIGKILL nobody stops the workers, and an orphan would wait forever.

    The kernel's parent-death signal acts at once; the watcher thread is the
    fallback for a server that died before the signal was asked for (then
    the parent is already someone else) and for systems without prctl.
    """
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
    except (OSError, AttributeError):
        pass
    if os.getppid() != server_pid:
        os._exit(0)

    def watch() -> None:
        while os.getppid() == server_pid:
            time.sleep(PARENT_CHECK_S)
        os._exit(0)

    threading.Thread(target=watch, name="server-watch", daemon=True).start()


def _sendable_error(exc: BaseException) -> BaseException:
    """``exc`` if it survives pickling, else a RuntimeError with its text; the worker's traceback as a note."""
    try:
        exc.add_note("in the worker process:\n" + "".join(traceback.format_exception(exc)).rstrip())
    except Exception:  # noqa: BLE001 - a note is a courtesy
        pass
    try:
        pickle.loads(pickle.dumps(exc))
        return exc
    except Exception:  # noqa: BLE001 - custom exceptions often cannot be rebuilt from their args
        return RuntimeError(f"{type(exc).__name__}: {exc}")


def _lower_priority(niceness: int) -> None:
    """Run only on CPU time nothing else wants: Linux's SCHED_IDLE class, else the lowest nice level.

    A bulk worker busy with a worst-case file must not slow the searches down:
    with nice 10 it still took a tenth of a core from them whenever both ran.
    """
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except (AttributeError, OSError):
        os.nice(niceness)


def _worker_main(conn, server_pid: int, load_sky: bool, niceness: int, kernel_modules: tuple[str, ...]) -> None:
    """A worker's life: set up, say ready (with the kernels' warm-up report), then run one job at a time until
    told to stop or orphaned."""
    global worker_context
    _die_with_server(server_pid)
    # A Ctrl-C or a service manager's SIGTERM reaches the whole process group, workers included: the
    # server alone decides, and stops its workers (or they die with it), so that a stop is not taken for
    # a worker's crash (a warning and a replacement started while shutting down).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    if niceness:
        _lower_priority(niceness)
    # The compiled kernels, before the worker says it is ready: loaded from their cache (0.2-0.3 s), or
    # compiled on the first run after an install.  Compiling while a job waits would run it past its hard
    # limit (a worker killed mid-compilation, measured).  The server logs the report: a worker has no log.
    # Before the catalogue: on a first start the server builds the indexes meanwhile.
    warmed = _warm_up_kernels(kernel_modules, say=False)
    sky = None
    if load_sky:
        from app.identification import Sky

        # From the cache the server made (narrow fields need Hp 8); on a first start, once the server has
        # built it (the index's lock, app.cache).
        sky = Sky().with_every_depth()
    conn.send(("ready", warmed))
    worker_context = WorkerContext(sky=sky)
    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):  # the server closed its end: nothing more will come
            return
        if message is None:
            return
        job_id, fn, args, kwargs = message
        try:
            reply = (job_id, True, fn(*args, sky=sky, **kwargs))
        except BaseException as exc:  # noqa: BLE001 - every failure goes back to the caller
            reply = (job_id, False, _sendable_error(exc))
        try:
            conn.send(reply)
        except (EOFError, OSError):
            return
        except Exception as exc:  # noqa: BLE001 - an unpicklable result
            conn.send((job_id, False, RuntimeError(f"the result could not be sent back: {exc}")))


def _warm_up_kernels(kernel_modules: tuple[str, ...], say: bool) -> dict | None:
    """Import ``kernel_modules`` (registering their kernels' warm-ups) and warm them up; None when there are none."""
    if not kernel_modules:
        return None
    import importlib

    for name in kernel_modules:
        importlib.import_module(name)
    from app.compiled import warm_up

    return warm_up(say=say)


# ---------------------------------------------------------------------------
# The pool, in the server
# ---------------------------------------------------------------------------

@dataclass(eq=False)
class _Job:
    id: int
    fn: Callable
    args: tuple
    kwargs: dict
    future: Future
    lane: str
    deadline: float | None  # time.monotonic() after which the job is not started
    limit_s: float  # the job's worker is killed once it has run this long


@dataclass(eq=False)
class _Worker:
    lane: str
    process: Any  # multiprocessing.Process
    conn: Any  # the server's end of the pipe
    ready: bool = False
    warm_up: dict | None = None  # the kernels' warm-up report it sent with "ready"
    job: _Job | None = None
    started: float = 0.0  # when the current job was sent
    stopping: bool = False


@dataclass(eq=False)
class _Lane:
    name: str
    size: int
    load_sky: bool
    niceness: int
    queue: collections.deque = field(default_factory=collections.deque)
    failures: int = 0  # workers of this lane that died before they were ready, in a row
    restart_at: float = 0.0


class ComputePool:
    """``processes`` interactive and ``bulk_processes`` bulk worker processes (or, with 0, threads sharing ``sky``).

    ``hard_limit_s``: a job running longer has its worker killed (default
    :data:`HARD_LIMIT_FACTOR` times the configured search time-out);
    ``load_sky`` False starts interactive workers without a catalogue (tests
    of the pool itself).  ``kernel_modules``: what every worker (or, with
    threads, the pool's own warm-up thread) imports and warms up before
    :attr:`kernels_ready`; by default the product's kernels
    (:data:`KERNEL_MODULES`) where the catalogue is loaded, none in a pool
    without one.
    """

    def __init__(self, processes: int, *, threads: int = 1, sky: Any = None, bulk_processes: int | None = None,
                 hard_limit_s: float | None = None, load_sky: bool = True,
                 kernel_modules: tuple[str, ...] | None = None) -> None:
        from app.config import settings

        config = settings()
        if kernel_modules is None:
            kernel_modules = KERNEL_MODULES if (load_sky if processes else sky is not None) else ()
        self._started = time.monotonic()
        #: Done (with :func:`app.compiled.warm_up`'s report, summed over the workers) once every lane has a worker
        #: with its kernels loaded; failed with :class:`WorkerLost` if the pool stops first.  Marked running at
        #: once, so that a waiter giving up (an asyncio wrapper cancelled) cannot cancel it for everyone.
        self.kernels_ready: Future = Future()
        self.kernels_ready.set_running_or_notify_cancel()
        #: When :attr:`kernels_ready` was done (``time.monotonic()``); None before.
        self.ready_at: float | None = None
        self.processes = max(0, int(processes))
        self._threads = max(1, threads)
        self._sky = sky
        self.hard_limit_s = float(hard_limit_s if hard_limit_s is not None
                                  else HARD_LIMIT_FACTOR * config.search_timeout_s)
        bulk = config.bulk_workers if bulk_processes is None else bulk_processes
        self.bulk_processes = max(1, int(bulk)) if self.processes else 0
        # Re-entrant: a future's done-callback runs in the thread that completes it and may submit again.
        self._lock = threading.RLock()
        self._closing = False
        self._ids = itertools.count(1)
        if not self.processes:
            if sky is None:
                raise ValueError("a thread pool needs the server's Sky")
            self._executors = {INTERACTIVE: ThreadPoolExecutor(max_workers=self._threads, thread_name_prefix="compute"),
                               BULK: ThreadPoolExecutor(max_workers=1, thread_name_prefix="compute-bulk")}
            threading.Thread(target=self._warm_up_here, args=(kernel_modules,), name="compile-kernels",
                             daemon=True).start()
            return
        self._kernel_modules = kernel_modules
        self._context = multiprocessing.get_context("spawn")
        self._lanes = {INTERACTIVE: _Lane(INTERACTIVE, self.processes, load_sky, 0),
                       BULK: _Lane(BULK, self.bulk_processes, False, BULK_NICENESS)}
        self._workers: list[_Worker] = []
        self._wake_read, self._wake_write = socket.socketpair()
        self._wake_read.setblocking(False)
        self._dispatcher = threading.Thread(target=self._run, name="compute-pool", daemon=True)
        self._dispatcher.start()

    @property
    def kind(self) -> str:
        """What the pool is, in words (``/api/health`` shows it)."""
        return f"{self.processes} processes" if self.processes else f"{self._threads} threads"

    # --- submitting ---------------------------------------------------------
    def submit(self, fn: Callable, *args, **kwargs) -> Future:
        """Run ``fn(*args, sky=<Sky>, **kwargs)`` on the interactive lane, without a deadline.

        Its hard limit is :data:`UNDATED_HARD_LIMIT_S` (or the pool's, if longer).
        """
        return self.submit_within(fn, *args, lane=INTERACTIVE, deadline=None, **kwargs)

    def submit_within(self, fn: Callable, *args, lane: str = INTERACTIVE, deadline: float | None = None,
                      **kwargs) -> Future:
        """Run ``fn(*args, sky=<Sky>, **kwargs)`` on ``lane`` unless ``deadline`` (``time.monotonic()``)
        passes before a worker is free for it (then the future fails with :class:`JobExpired`).

        Cancelling the future before the job starts removes it from the queue.
        A job with a deadline is killed after the pool's ``hard_limit_s``, one
        without after :data:`UNDATED_HARD_LIMIT_S`.
        """
        if lane not in LANES:
            raise ValueError(f"unknown lane {lane!r}")
        if not self.processes:
            return self._executors[lane].submit(_run_in_thread, fn, args, kwargs, deadline, self._sky)
        future: Future = Future()
        with self._lock:
            if self._closing:
                raise RuntimeError("the compute pool is shut down")
            limit = self.hard_limit_s if deadline is not None else max(self.hard_limit_s, UNDATED_HARD_LIMIT_S)
            self._lanes[lane].queue.append(_Job(next(self._ids), fn, args, kwargs, future, lane, deadline, limit))
        self._wake()
        return future

    @property
    def ready(self) -> bool:
        """Whether the kernels are ready (:attr:`kernels_ready`): jobs submitted now start as soon as a worker is free."""
        return self.kernels_ready.done() and self.kernels_ready.exception() is None

    # --- the kernels --------------------------------------------------------
    def _warm_up_here(self, kernel_modules: tuple[str, ...]) -> None:
        """A thread pool's warm-up, in a thread of the server: jobs that need the kernels meanwhile wait for them
        in :func:`app.compiled.warm_up`."""
        try:
            self._kernels_are_ready(_warm_up_kernels(kernel_modules, say=False))
        except Exception as exc:  # noqa: BLE001 - logged; a job's own call of warm_up then says what fails
            log.exception("the compiled kernels could not be loaded")
            self.kernels_ready.set_exception(exc)

    def _kernels_are_ready(self, report: dict | None) -> None:
        """Resolve :attr:`kernels_ready` with ``report`` and say in one log line what it took."""
        from app.compiled import describe

        where = (f"worker processes: {self.processes} search, {self.bulk_processes} bulk" if self.processes
                 else "threads of the server")
        said = f"; {describe(report)}" if report else ""
        log.log(logging.WARNING if report and report["compiled"] else logging.INFO,
                "compute ready %.1f s after start (%s)%s", time.monotonic() - self._started, where, said)
        self.ready_at = time.monotonic()
        self.kernels_ready.set_result(report)

    def _lanes_ready(self) -> None:
        """Resolve :attr:`kernels_ready` once every lane has a ready worker (under the lock)."""
        if self.kernels_ready.done():
            return
        ready = [w for w in self._workers if w.ready]
        if all(any(w.lane == lane for w in ready) for lane in self._lanes):
            reports = [w.warm_up for w in ready if w.warm_up]
            # Compiling is work done once (by whichever worker came first); loading, each worker's own copy.
            self._kernels_are_ready({"seconds": max(r["seconds"] for r in reports),
                                     "compiled": sum(r["compiled"] for r in reports),
                                     "loaded": max(r["loaded"] for r in reports),
                                     "processes": max(r.get("processes", 1) for r in reports)} if reports else None)

    def pids(self) -> list[int]:
        """Process ids of the live workers (tests and diagnostics)."""
        if not self.processes:
            return []
        with self._lock:
            return [w.process.pid for w in self._workers if w.process.pid is not None]

    # --- stopping -----------------------------------------------------------
    def shutdown(self, timeout_s: float = 5.0) -> None:
        """Stop: queued jobs are cancelled, running ones get ``timeout_s`` to finish, then their workers are killed.

        Returns once every worker process has exited (or, at worst, has been
        SIGKILLed and reaped), so nothing outlives a normal stop.
        """
        if not self.processes:
            for executor in self._executors.values():
                executor.shutdown(wait=False, cancel_futures=True)
            return  # a warm-up still running ends with the process (a daemon thread)
        with self._lock:
            if self._closing:
                return
            self._closing = True
            self._stop_deadline = time.monotonic() + timeout_s
            if not self.kernels_ready.done():  # nobody waits for a start that will not come
                self.kernels_ready.set_exception(WorkerLost("the compute pool stopped before its workers were ready"))
        self._wake()
        self._dispatcher.join(timeout_s + 10.0)
        if self._dispatcher.is_alive():  # never expected: the dispatcher kills what does not stop
            log.error("the compute pool's dispatcher did not stop within %.0f s", timeout_s + 10.0)

    # --- the dispatcher thread ----------------------------------------------
    def _wake(self) -> None:
        try:
            self._wake_write.send(b"\0")
        except (BlockingIOError, OSError):  # already woken (buffer full) or closing
            pass

    def _run(self) -> None:
        try:
            with self._lock:
                for lane in self._lanes.values():
                    for _ in range(lane.size):
                        self._start_worker(lane)
            while True:
                with self._lock:
                    if self._closing and self._stop_step():
                        break
                    if not self._closing:
                        self._restart_missing()
                        self._dispatch()
                    waits = [self._wake_read] + [w.conn for w in self._workers] + \
                            [w.process.sentinel for w in self._workers]
                    timeout = self._next_check()
                ready = wait_for_connections(waits, timeout)
                with self._lock:
                    for item in ready:
                        if item is self._wake_read:
                            self._drain_wake()
                        else:
                            worker = next((w for w in self._workers if item is w.conn or item == w.process.sentinel),
                                          None)
                            if worker is not None:
                                self._serve(worker)
                    self._enforce_hard_limit()
        except Exception:  # noqa: BLE001 - must never die silently: log, fail what waits, kill what runs
            log.exception("the compute pool's dispatcher failed")
            with self._lock:
                self._closing = True
                self._fail_everything(WorkerLost("the compute pool failed; see the server log"))
        finally:
            self._wake_read.close()
            self._wake_write.close()

    def _drain_wake(self) -> None:
        try:
            while self._wake_read.recv(4096):
                pass
        except (BlockingIOError, OSError):
            pass

    def _start_worker(self, lane: _Lane) -> None:
        server_end, worker_end = self._context.Pipe(duplex=True)
        process = self._context.Process(target=_worker_main, name=f"starid-{lane.name}-worker",
                                        args=(worker_end, os.getpid(), lane.load_sky, lane.niceness,
                                              self._kernel_modules),
                                        daemon=True)
        process.start()
        worker_end.close()  # the worker holds its own copy: EOF here means the worker is gone
        self._workers.append(_Worker(lane.name, process, server_end))

    def _restart_missing(self) -> None:
        now = time.monotonic()
        for lane in self._lanes.values():
            missing = lane.size - sum(1 for w in self._workers if w.lane == lane.name)
            if missing > 0 and now >= lane.restart_at:
                for _ in range(missing):
                    self._start_worker(lane)

    def _dispatch(self) -> None:
        now = time.monotonic()
        for lane in self._lanes.values():
            idle = [w for w in self._workers if w.lane == lane.name and w.ready and w.job is None and not w.stopping]
            while lane.queue and idle:
                job = lane.queue.popleft()
                if not job.future.set_running_or_notify_cancel():
                    continue  # cancelled while it waited
                if job.deadline is not None and now > job.deadline:
                    job.future.set_exception(JobExpired(
                        "the work waited for a free worker past its time-out and was not started"))
                    continue
                worker = idle.pop()
                try:
                    worker.conn.send((job.id, job.fn, job.args, job.kwargs))
                except (pickle.PicklingError, TypeError, AttributeError) as exc:
                    job.future.set_exception(exc)
                    idle.append(worker)
                    continue
                except OSError:  # the worker died just now: _serve will replace it
                    job.future.set_exception(WorkerLost("the worker process died before the job started"))
                    continue
                worker.job, worker.started = job, now
            # Jobs whose deadline passed while every worker was busy are answered now, not when one frees up.
            for job in [j for j in lane.queue if j.deadline is not None and now > j.deadline]:
                lane.queue.remove(job)
                if job.future.set_running_or_notify_cancel():
                    job.future.set_exception(JobExpired(
                        "the work waited for a free worker past its time-out and was not started"))

    def _next_check(self) -> float:
        """Seconds until the next deadline, hard limit or restart the dispatcher must act on (at most 1)."""
        now = time.monotonic()
        moments = [now + 1.0]
        moments += [w.started + w.job.limit_s for w in self._workers if w.job is not None]
        moments += [j.deadline for lane in self._lanes.values() for j in lane.queue if j.deadline is not None]
        moments += [lane.restart_at for lane in self._lanes.values() if lane.restart_at > now]
        if self._closing:
            moments.append(self._stop_deadline)
        return max(0.0, min(moments) - now) + 0.001

    def _serve(self, worker: _Worker) -> None:
        """A worker's pipe is readable or its process ended: take its message, or bury it."""
        try:
            while worker.conn.poll():
                message = worker.conn.recv()
                if message[0] == "ready":
                    worker.ready, worker.warm_up = True, message[1]
                    self._lanes[worker.lane].failures = 0
                    self._lanes_ready()
                    continue
                job_id, ok, value = message
                job, worker.job = worker.job, None
                if job is None or job.id != job_id:
                    log.error("compute worker %s answered a job it was not given", worker.process.pid)
                    continue
                if ok:
                    job.future.set_result(value)
                else:
                    job.future.set_exception(value)
                if worker.stopping:
                    self._send_stop(worker)
        except (EOFError, OSError):
            self._bury(worker, "died")
        except Exception as exc:  # noqa: BLE001 - e.g. a result that cannot be unpickled here
            job, worker.job = worker.job, None
            if job is not None:
                job.future.set_exception(RuntimeError(f"the worker's answer could not be read: {exc}"))
        if worker.process.exitcode is not None and worker in self._workers:
            self._bury(worker, f"exited with code {worker.process.exitcode}")

    def _bury(self, worker: _Worker, how: str) -> None:
        """Forget a worker whose process ended: fail its job, count a failed start, schedule its replacement."""
        if worker not in self._workers:
            return
        self._workers.remove(worker)
        worker.conn.close()
        worker.process.join(timeout=1.0)
        lane = self._lanes[worker.lane]
        if worker.job is not None:
            worker.job.future.set_exception(WorkerLost(f"the worker process {how} while running the job"))
            worker.job = None
        if not self._closing:
            if not worker.ready and -(worker.process.exitcode or 0) in (signal.SIGINT, signal.SIGTERM):
                # A stop sent to every process (Ctrl-C, a service manager) reached this worker before it could
                # ignore it: the server got it too and is stopping.  Replaced later, if it is not.
                lane.restart_at = time.monotonic() + STOPPED_WHILE_STARTING_S
                log.info("compute worker %s (%s) was stopped by a signal while starting; another starts in %.0f s "
                         "unless the server is stopping", worker.process.pid, worker.lane, STOPPED_WHILE_STARTING_S)
                return
            if not worker.ready:
                lane.failures += 1
                low, high = RESTART_BACKOFF_S
                lane.restart_at = time.monotonic() + min(high, low * 2 ** (lane.failures - 1))
            log.warning("compute worker %s (%s) %s; starting another", worker.process.pid, worker.lane, how)

    def _kill(self, worker: _Worker) -> None:
        try:
            worker.process.kill()
        except (OSError, ValueError, AttributeError):
            pass
        worker.process.join(timeout=5.0)

    def _enforce_hard_limit(self) -> None:
        now = time.monotonic()
        for worker in [w for w in self._workers if w.job is not None and now - w.started > w.job.limit_s]:
            job = worker.job
            worker.job = None
            log.error("a %s job ran past its hard limit of %.0f s: killing worker %s", worker.lane,
                      job.limit_s, worker.process.pid)
            self._kill(worker)
            job.future.set_exception(JobKilled(
                f"the work ran past its hard limit of {job.limit_s:.0f} s and was stopped"))
            worker.ready = True  # not a start failure: replace it at once
            self._bury(worker, "was killed")

    def _send_stop(self, worker: _Worker) -> None:
        worker.stopping = True
        try:
            worker.conn.send(None)
        except OSError:
            pass

    def _fail_everything(self, error: BaseException) -> None:
        if not self.kernels_ready.done():
            self.kernels_ready.set_exception(error)
        for lane in self._lanes.values():
            while lane.queue:
                job = lane.queue.popleft()
                if job.future.set_running_or_notify_cancel():
                    job.future.set_exception(error)
        for worker in list(self._workers):
            if worker.job is not None:
                worker.job.future.set_exception(error)
                worker.job = None
            self._kill(worker)
            worker.conn.close()
        self._workers.clear()

    def _stop_step(self) -> bool:
        """One step of a shutdown; True once every worker has exited."""
        for lane in self._lanes.values():
            while lane.queue:
                lane.queue.popleft().future.cancel()
        for worker in list(self._workers):
            if worker.process.exitcode is not None:
                self._workers.remove(worker)
                worker.conn.close()
                worker.process.join(timeout=1.0)
                if worker.job is not None:
                    worker.job.future.set_exception(WorkerLost("the server stopped while the job ran"))
            elif worker.job is None and not worker.stopping:
                self._send_stop(worker)
        if self._workers and time.monotonic() >= self._stop_deadline:
            self._fail_everything(WorkerLost("the server stopped while the job ran"))
        return not self._workers


def _run_in_thread(fn: Callable, args: tuple, kwargs: dict, deadline: float | None, sky: Any):
    """A thread pool job: the same deadline rule as the worker processes."""
    if deadline is not None and time.monotonic() > deadline:
        raise JobExpired("the work waited for a free worker past its time-out and was not started")
    return fn(*args, sky=sky, **kwargs)
