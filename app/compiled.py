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
whether it compiled (the first run after an install: 24-25 s of CPU for
the 57 kernels of 2026-11-26, in one process) or loaded the cache (0.2-0.3 s, most of it
numba setting itself up for its first kernel).
:func:`app.identification.identify` warms up before its search's clock
starts; a server's compute pool (:mod:`app.workflow.compute`) warms up in
its workers, or in a thread of its own, while the server answers.

Compiling on every core.  A process that expects to compile (the cache
does not hold its kernels' sources as they are: :func:`_cache_current`)
starts helper processes, one per further core (:data:`MAX_COMPILE_PROCESSES`
in all), and they share the warm-ups out (:func:`_take_turns`): each takes
the next warm-up no one holds (a lock file per warm-up) whose prerequisites
are done (a marker file per warm-up: the kernels its kernels call are in the
cache, so that no process compiles a callee again), the longest chain of
kernels first; the first process then loads the ones its helpers compiled.
Other processes warming up at once (a server's second worker) wait on a lock
of the cache directory and load what the first wrote.
"""

from __future__ import annotations

import contextlib
import logging
import os
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Callable, Iterator

from app.config import settings
from app.cache import exclusive

log = logging.getLogger(__name__)

if not os.environ.get("NUMBA_CACHE_DIR"):
    os.environ["NUMBA_CACHE_DIR"] = str(settings().cache_dir / "numba")

import numba  # noqa: E402  (after NUMBA_CACHE_DIR: numba reads it when imported)

_warm_ups: list[Callable[[], None]] = []
_kernels: list = []
_warm_lock = threading.Lock()
_warmed = False
_report: dict = {}

#: Processes compiling at once on a first run (the first and its helpers) by default: one a core, at most this many
#: (more share the warm-ups thinner and compile more callees twice).
MAX_COMPILE_PROCESSES = 4
#: How long a helper is waited for once the first process is done (it only loads by then), seconds.
HELPER_GRACE_S = 60.0
#: How long the first process waits for a warm-up another process holds, seconds (the slowest compiles in
#: ~7 s on a 2-core machine); and how often it looks.
WARM_UP_WAIT_S = 300.0
LOCK_POLL_S = 0.02
#: A compile helper's niceness: on a server's first start the helpers compile on the CPU the server's own
#: index build leaves (the health answered at 27.8 s instead of 15 when they competed; measured 2026-11-26);
#: on idle cores it changes nothing.
HELPER_NICENESS = 10


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


def warm_up(say: bool = True, eager: bool = True) -> dict:
    """Compile (or load from the cache) every registered kernel, once per process; one log line says which.

    Returns ``{"seconds": ..., "compiled": n, "loaded": n, "processes": n}``:
    the kernels compiled now (by this process or its helpers), those this
    process loaded from a cache written before (each kernel a helper
    compiled is loaded here once, not counted), and how many processes
    compiled.  ``say=False`` leaves the log line to the caller
    (:func:`describe`): a worker process has no log of its own and reports
    to its server.

    ``eager=False`` (a search's own call, :func:`app.identification.solve_sequence`): when the cache holds
    every kernel as its source is now (:func:`_cache_current`), none is loaded here; each loads from the cache
    at its first call (~10 ms; a nominal sequence's solve uses 15 of 24), and the report says ``"loaded": 0,
    "cached": True``: a fresh process's first sequence took 0.31-0.32 s instead of 0.36-0.38 (its answer 0.96 s
    after launch, 2026-11-26).  Otherwise (a first run) as eager: every kernel compiled now, before the
    search's clock.  A server's workers and a batch's warm up eagerly: they start once and answer many.
    """
    global _warmed, _report
    if _warmed or (_report.get("cached") and not eager):
        return _report
    with _warm_lock:
        if _warmed or (_report.get("cached") and not eager):  # another thread warmed them while this one waited
            return _report
        t0 = time.perf_counter()
        directory = Path(os.environ["NUMBA_CACHE_DIR"])
        if not eager and not _report and _cache_current(directory):
            _report = {"seconds": time.perf_counter() - t0, "compiled": 0, "loaded": 0, "processes": 1,
                       "cached": True}
            if say:
                log.info("%s", describe(_report))
            return _report
        functions = list(_warm_ups)
        with _cache_lock() as directory:
            helpers = []
            if directory is not None and not _cache_current(directory):
                _forget_done(directory)
                helpers = _start_helpers(functions)
            if helpers:
                _take_turns(functions, directory, helpers)
            else:  # alone (no cache to share, or its other users wait on its lock): in order, callees first
                for function in functions:
                    function()
            helpers_compiled, processes = sum(_joined(helper) for helper in helpers), 1 + len(helpers)
            if directory is not None:
                _write_stamp(directory)
        own_hits = sum(sum(k.stats.cache_hits.values()) for k in _kernels)
        _report = {"seconds": time.perf_counter() - t0,
                   "compiled": sum(sum(k.stats.cache_misses.values()) for k in _kernels) + helpers_compiled,
                   "loaded": max(0, own_hits - helpers_compiled), "processes": processes}
        _warmed = True
        if say:
            log.log(logging.WARNING if _report["compiled"] else logging.INFO, "%s", describe(_report))
        return _report


def describe(report: dict) -> str:
    """:func:`warm_up`'s report in words: compiled (the first run after an install) or loaded from the cache."""
    if report.get("cached"):
        return f"the compiled kernels are in {os.environ['NUMBA_CACHE_DIR']}: each loads at its first call"
    if report["compiled"]:
        on = f" on {report['processes']} cores" if report.get("processes", 1) > 1 else ""
        return (f"compiled {report['compiled']} numba kernels in {report['seconds']:.1f} s{on} (the first run "
                f"after an install; kept in {os.environ['NUMBA_CACHE_DIR']})")
    return f"loaded {report['loaded']} compiled kernels from {os.environ['NUMBA_CACHE_DIR']} in {report['seconds']:.2f} s"


@contextlib.contextmanager
def _cache_lock() -> Iterator[Path | None]:
    """An exclusive lock on the cache directory while warming up (yields the directory; None when there is no
    cache to share): the processes starting together (a server's workers, a batch's) warm up one after the
    other, the first (with its helpers) writing the cache the others then load.

    Not the warm-up locks alone, letting every process take warm-ups at once: the kernels call one another,
    so several processes compiled the same callees, and three processes on two cores took 78 s to be warm
    against 37 s taking turns (one run each on a busy machine, 2026-11-25).  Only the first process's own
    helpers share its warm-ups (:func:`_take_turns`)."""
    directory = Path(os.environ["NUMBA_CACHE_DIR"])
    with exclusive(directory / "warm-up.lock") as locked:
        yield directory if locked else None


@dataclass(frozen=True)
class _Helper:
    """A compile helper process and the temporary files its output goes to."""

    process: subprocess.Popen
    out: IO[str]
    err: IO[str]


def _take_turns(functions: list[Callable[[], None]], directory: Path, helpers: list[_Helper], *,
                own: bool = True) -> None:
    """Run the warm-ups ``functions``, sharing them with the other processes compiling now.

    Each turn takes, of the warm-ups whose prerequisites are done (:func:`_prerequisites`: compiling a caller
    before its callees are in the cache compiles them again in this process), the one with the longest chain
    of kernels after it (:func:`_priorities`: the first run's time is its critical path's, the refinement's
    and the focal estimate's behind the cell maps' and the rotations'), and runs it holding its lock file,
    then marks it done (:func:`_done_marker`).  ``own`` (the first process, ``helpers`` its helpers) runs
    every warm-up: one another process marked done loads from the cache it wrote, whenever; a helper
    (``own=False``) runs only those no one has done.

    Bounded: with no turn to take for :data:`WARM_UP_WAIT_S` (another process holding a warm-up, or a
    prerequisite, that long), the first process stops its helpers and runs the rest here; a helper stops.
    """
    prerequisites = _prerequisites(functions)
    priority = _priorities(functions, prerequisites)
    remaining = sorted(functions, key=lambda function: -priority[function])  # stable: registration order next
    deadline = time.monotonic() + WARM_UP_WAIT_S
    while remaining:
        for function in remaining:
            done = _done_marker(function, directory).exists()
            if done and not own:
                remaining.remove(function)
                break
            if not done and not all(_done_marker(p, directory).exists() for p in prerequisites[function]):
                continue
            if _run_holding_its_lock(function, directory, rerun_done=own):
                remaining.remove(function)
                break
        else:  # every warm-up left is held by another process or waits for one
            if time.monotonic() < deadline:
                time.sleep(LOCK_POLL_S)
                continue
            if own:
                for helper in helpers:
                    helper.process.kill()
                log.warning("%s: held by another process, or waiting for one, for %.0f s: compiled here",
                            ", ".join(f"{f.__module__}.{f.__qualname__}" for f in remaining), WARM_UP_WAIT_S)
                for function in remaining:
                    function()
            return
        deadline = time.monotonic() + WARM_UP_WAIT_S


def _run_holding_its_lock(function: Callable[[], None], directory: Path, rerun_done: bool) -> bool:
    """Run ``function`` holding its lock file and mark it done; False (not run) when another process holds it.
    Found done once held (another process finished it meanwhile): run again only if ``rerun_done`` (a load)."""
    import fcntl

    with open(directory / f"warm-up.{function.__module__}.{function.__qualname__}.lock", "a") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:  # another process compiles it now
            return False
        try:
            marker = _done_marker(function, directory)
            if rerun_done or not marker.exists():
                function()
                marker.touch()
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
    return True


def _done_marker(function: Callable[[], None], directory: Path) -> Path:
    """The file saying a process has run ``function`` since the first process found the cache stale (and
    removed them all: :func:`_forget_done`): its kernels are in the cache."""
    return directory / f"warm-up.{function.__module__}.{function.__qualname__}.done"


def _forget_done(directory: Path) -> None:
    for marker in directory.glob("warm-up.*.done"):
        with contextlib.suppress(OSError):
            marker.unlink()


def _prerequisites(functions: list[Callable[[], None]]) -> dict[Callable[[], None], list[Callable[[], None]]]:
    """Each warm-up's prerequisites: the warm-ups, registered before it, of the other modules whose kernels
    its module's kernels call (:func:`_called_kernels`).  Modules, not kernels: a warm-up's kernels are known
    once it has run.  Only earlier ones: the registration order (the modules' import order) breaks a cycle."""
    of_module: dict[str, list[Callable[[], None]]] = {}
    for function in functions:
        of_module.setdefault(function.__module__, []).append(function)
    calls: dict[str, set[str]] = {}
    for kernel in _kernels:
        module = kernel.py_func.__module__
        calls.setdefault(module, set()).update(k.py_func.__module__ for k in _called_kernels(kernel))
    out = {}
    for position, function in enumerate(functions):
        earlier = functions[:position]
        called = calls.get(function.__module__, set()) - {function.__module__}
        out[function] = [f for module in called for f in of_module.get(module, []) if f in earlier]
    return out


def _priorities(functions: list[Callable[[], None]],
                prerequisites: dict[Callable[[], None], list[Callable[[], None]]]) -> dict[Callable[[], None], float]:
    """Each warm-up's critical path, counted in kernels: its own and those of the longest chain of warm-ups
    waiting on it (``prerequisites``: :func:`_prerequisites`).  A warm-up's own are its module's, shared
    among the module's warm-ups: a kernel takes 0.1-0.5 s of CPU to compile (measured 2026-11-26), a count
    is near enough to order them."""
    kernels: dict[str, int] = {}
    for kernel in _kernels:
        kernels[kernel.py_func.__module__] = kernels.get(kernel.py_func.__module__, 0) + 1
    warm_ups: dict[str, int] = {}
    for function in functions:
        warm_ups[function.__module__] = warm_ups.get(function.__module__, 0) + 1
    after: dict[Callable[[], None], float] = {}
    for function in reversed(functions):  # a warm-up's dependents are registered after it
        waiting = [after[f] for f in functions if function in prerequisites[f]]
        own = kernels.get(function.__module__, 0) / warm_ups[function.__module__]
        after[function] = own + max(waiting, default=0.0)
    return after


def _called_kernels(kernel) -> set:
    """The kernels ``kernel``'s code calls: a global that is a kernel, or a kernel read from a module global
    (``module.kernel(...)``), in its bytecode and its nested functions'."""
    import dis
    import types

    codes, found = [kernel.py_func.__code__], set()
    namespace, kernels = kernel.py_func.__globals__, {id(k): k for k in _kernels}
    while codes:
        code = codes.pop()
        codes += [c for c in code.co_consts if isinstance(c, types.CodeType)]
        module = None
        for instruction in dis.get_instructions(code):
            if instruction.opname == "LOAD_GLOBAL":
                value = namespace.get(instruction.argval)
                module = value if isinstance(value, types.ModuleType) else None
                if id(value) in kernels:
                    found.add(kernels[id(value)])
            elif instruction.opname in ("LOAD_ATTR", "LOAD_METHOD") and module is not None:
                value = getattr(module, instruction.argval, None)
                module = value if isinstance(value, types.ModuleType) else None
                if id(value) in kernels:
                    found.add(kernels[id(value)])
            else:
                module = None
    return found - {kernel}


def _compile_processes() -> int:
    """How many processes compile on a first run: ``STARID_COMPILE_PROCESSES`` when set, else one per core this
    process may use, at most :data:`MAX_COMPILE_PROCESSES`."""
    if settings().compile_processes:
        return settings().compile_processes
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cores = os.cpu_count() or 1
    return max(1, min(cores, MAX_COMPILE_PROCESSES))


def _start_helpers(functions: list[Callable[[], None]]) -> list[_Helper]:
    """Start :func:`_compile_processes` - 1 helper processes taking warm-ups from ``functions``' modules
    (:func:`helper_main`); none where they cannot start (said in the log: this process compiles alone).

    Their output goes to temporary files, not pipes: a helper writing more than a pipe holds (numba's
    warnings) while it holds a warm-up would wait for a reader that waits for the warm-up."""
    import tempfile

    modules = list(dict.fromkeys(f.__module__ for f in functions))
    path = os.pathsep.join(os.path.abspath(p) if p else os.getcwd() for p in sys.path)
    env = {**os.environ, "PYTHONPATH": path}
    helpers = []
    for _ in range(_compile_processes() - 1):
        out, err = tempfile.TemporaryFile("w+"), tempfile.TemporaryFile("w+")
        try:
            process = subprocess.Popen([sys.executable, "-c", _HELPER, *modules], env=env, stdout=out, stderr=err,
                                       text=True)
        except OSError as exc:
            out.close()
            err.close()
            log.warning("a compile helper could not start (%s): compiling in one process", exc)
            break
        helpers.append(_Helper(process, out, err))
    return helpers


#: A helper's program: import the kernel modules named, take warm-ups, print how many kernels it compiled.
_HELPER = "import sys; from app.compiled import helper_main; helper_main(sys.argv[1:])"


def helper_main(modules: list[str]) -> None:
    """A compile helper (:func:`_start_helpers`): import ``modules``, take the warm-ups no other process has
    done (:func:`_take_turns`), print ``{"compiled": n}``."""
    import importlib
    import json

    if hasattr(os, "nice"):
        os.nice(HELPER_NICENESS)
    for name in modules:
        importlib.import_module(name)
    _take_turns(list(_warm_ups), Path(os.environ["NUMBA_CACHE_DIR"]), [], own=False)
    print(json.dumps({"compiled": sum(sum(k.stats.cache_misses.values()) for k in _kernels)}), flush=True)
    # Gone at once: the interpreter's teardown (numba freeing its compiled code) took 0.3-0.5 s that the first
    # process waited for (2026-11-26); everything it made is on disk.
    os._exit(0)


def _joined(helper: _Helper) -> int:
    """Wait for a helper (at most :data:`HELPER_GRACE_S`: every warm-up is done by now, it only finishes
    loading); the kernels it compiled (0 if it failed: said in the log)."""
    import json

    try:
        helper.process.wait(timeout=HELPER_GRACE_S)
    except subprocess.TimeoutExpired:
        helper.process.kill()
        helper.process.wait()
    out, err = helper.out, helper.err
    with out, err:
        out.seek(0)
        err.seek(0)
        lines = out.read().strip().splitlines()
        try:
            return int(json.loads(lines[-1])["compiled"])
        except (ValueError, KeyError, IndexError):
            log.warning("a compile helper failed (exit %s): %s", helper.process.returncode, err.read().strip()[-500:])
            return 0


def _kernel_sources() -> dict[str, list[float]]:
    """Each kernel's source file with its modification time and size: what numba's cache is keyed by."""
    sources = {}
    for kernel in _kernels:
        path = kernel.py_func.__code__.co_filename
        with contextlib.suppress(OSError):
            stat = os.stat(path)
            sources[path] = [stat.st_mtime, stat.st_size]
    return sources


def _stamp_file(directory: Path) -> Path:
    return directory / "warm-up.stamp.json"


def _read_stamp(directory: Path) -> dict:
    import json

    try:
        stamp = json.loads(_stamp_file(directory).read_text())
    except (OSError, ValueError):
        return {}
    return stamp if isinstance(stamp, dict) and stamp.get("versions") == _versions() else {}


def _versions() -> list[str]:
    return [numba.__version__, sys.version]


def _cache_current(directory: Path) -> bool:
    """Whether the last warm-up with this cache saw every kernel source as it is now (then this one loads, not
    compiles: no helpers).  Wrong only if the cache files went and the stamp stayed: one process compiles."""
    known = _read_stamp(directory).get("sources", {})
    return all(known.get(path) == stat for path, stat in _kernel_sources().items())


def _write_stamp(directory: Path) -> None:
    """Note the kernel sources the cache now holds (merged with other processes' kernel sets)."""
    import json

    stamp = _read_stamp(directory)
    stamp = {"versions": _versions(), "sources": {**stamp.get("sources", {}), **_kernel_sources()}}
    temporary = directory / f"warm-up.stamp.{os.getpid()}.tmp"
    with contextlib.suppress(OSError):
        temporary.write_text(json.dumps(stamp))
        os.replace(temporary, _stamp_file(directory))
