"""app/compiled.py (issue 27): kernels compiled once, kept in the project's cache, said in one log line."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

MODULE = '''
from app.compiled import njit, warm_up_with


@njit
def twice(x):
    return 2.0 * x


@warm_up_with
def _warm():
    twice(1.5)
'''

RUN = '''
import json, logging, sys
logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
sys.path.insert(0, sys.argv[1])
import tiny_kernels
from app.compiled import warm_up
first, again = warm_up(), warm_up()
print(json.dumps({"first": first, "again": again, "value": tiny_kernels.twice(4.0)}))
'''


def _run(tmp_path: Path, program: str = RUN, **env_extra: str) -> tuple[dict, str]:
    """``program`` in a fresh interpreter, its kernel cache in ``tmp_path``: its last line's JSON and its log."""
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env.update(STARID_CACHE_DIR=str(tmp_path / "cache"), **env_extra)
    done = subprocess.run([sys.executable, "-c", program, str(tmp_path)], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=180)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1]), done.stderr


def test_a_first_run_compiles_once_says_so_in_one_line_and_the_next_loads_the_cache(tmp_path):
    (tmp_path / "tiny_kernels.py").write_text(MODULE)
    report, log = _run(tmp_path)
    assert report["value"] == 8.0
    assert report["first"]["compiled"] == 1 and report["first"]["loaded"] == 0
    assert report["again"] == report["first"]  # once a process: the second call does nothing
    said = [line for line in log.splitlines() if "numba kernels" in line or "compiled kernels" in line]
    assert len(said) == 1 and said[0].startswith("WARNING compiled 1 numba kernels in "), log
    # Kept in the project's cache directory (NUMBA_CACHE_DIR unset), where the next process finds it.
    assert list((tmp_path / "cache" / "numba").rglob("*.nbi"))
    report, log = _run(tmp_path)
    assert report["first"]["compiled"] == 0 and report["first"]["loaded"] == 1
    assert "WARNING" not in log and sum("loaded 1 compiled kernels" in line for line in log.splitlines()) == 1


SHARED_BASE = '''
from app.compiled import njit, warm_up_with


@njit
def first(x):
    return 1.0 * x


@warm_up_with
def _warm_first():  # the others' prerequisite: their kernels call this one
    first(1.5)
'''

SHARED_MODULE = '''
import os
import time
from pathlib import Path

import shared_base
from app.compiled import njit, warm_up_with


@njit
def middle(x):
    return 2.0 * shared_base.first(x)


@njit
def last(x):
    return 3.0 * shared_base.first(x)


def _last_taken() -> bool:
    """Whether another process holds _warm_last's lock, or has compiled it (its cache index is written)."""
    import fcntl

    directory = Path(os.environ["NUMBA_CACHE_DIR"])
    if list(directory.rglob("*last*.nbi")):
        return True
    with open(directory / f"warm-up.{__name__}._warm_last.lock", "a") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return True
        fcntl.flock(lock, fcntl.LOCK_UN)
        return False


@warm_up_with
def _warm_middle():  # the first process's second pick, held until a helper has taken the last
    middle(1.5)
    deadline = time.monotonic() + 60.0
    while not _last_taken():
        if time.monotonic() > deadline:
            raise RuntimeError("no helper took the last warm-up within 60 s")
        time.sleep(0.01)


@warm_up_with
def _warm_last():  # a helper's pick once the first is done
    last(1.5)
'''

SHARED_RUN = '''
import json, logging, sys
logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
sys.path.insert(0, sys.argv[1])
import shared_base as b, shared_kernels as k
from app.compiled import warm_up
report = warm_up()
print(json.dumps({"report": report, "values": [b.first(4.0), k.middle(4.0), k.last(4.0)],
                  "compiled_here": [sum(f.stats.cache_misses.values()) for f in (b.first, k.middle, k.last)],
                  "loaded_here": [sum(f.stats.cache_hits.values()) for f in (b.first, k.middle, k.last)]}))
'''


def test_a_first_run_shares_the_compiling_with_a_helper_process_and_the_next_starts_none(tmp_path):
    """Three warm-ups, two processes: the first process takes the prerequisite (the kernel the others call) then
    the middle; its helper waits for the prerequisite to be done, then takes the last, loading the kernel it calls
    from the cache (compiled once in all: three kernels, not four); the first process then loads the last.  (Its
    middle warm-up holds on until the helper has the last, so that the sharing is not left to how fast a process
    starts.)"""
    (tmp_path / "shared_base.py").write_text(SHARED_BASE)
    (tmp_path / "shared_kernels.py").write_text(SHARED_MODULE)

    def run() -> tuple[dict, str]:
        return _run(tmp_path, SHARED_RUN, STARID_COMPILE_PROCESSES="2")

    out, log = run()
    assert out["values"] == [4.0, 8.0, 12.0]
    assert out["compiled_here"] == [1, 1, 0] and out["loaded_here"] == [0, 0, 1]  # the helper compiled the last
    assert out["report"]["compiled"] == 3 and out["report"]["loaded"] == 0 and out["report"]["processes"] == 2
    said = [line for line in log.splitlines() if "numba kernels" in line or "compiled kernels" in line]
    assert len(said) == 1 and said[0].startswith("WARNING compiled 3 numba kernels in ") and "on 2 cores" in said[0]
    # The cache now holds them as their sources are: the next process loads them, alone.
    out, log = run()
    assert out["report"] == {**out["report"], "compiled": 0, "loaded": 3, "processes": 1}
    assert sum("loaded 3 compiled kernels" in line for line in log.splitlines()) == 1


def test_a_warm_up_waits_for_the_warm_ups_of_the_kernels_its_kernels_call_the_longest_chain_first():
    """The prerequisites read from the kernels' code (a kernel named as a global, or read from a module) against
    the modules' imports checked by hand: the refinement's kernels call the cell maps' and the rotations', the
    cell maps' the rotations', the rotations' none; the rotations start the longest chain."""
    import app.identification  # noqa: F401  (registers every kernel module's warm-up)
    from app.compiled import _called_kernels, _kernels, _prerequisites, _priorities, _warm_ups

    def named(functions) -> set[str]:
        return {f"{f.__module__}.{f.__name__}" for f in functions}

    prerequisites = _prerequisites(_warm_ups)
    priority = _priorities(_warm_ups, prerequisites)
    by_name = {f"{f.__module__}.{f.__name__}": f for f in _warm_ups}
    rotations = {"app.attitude.rotations._warm_up_svd", "app.attitude.rotations._warm_up_pairs"}
    assert not prerequisites[by_name["app.attitude.rotations._warm_up_svd"]]
    assert named(prerequisites[by_name["app.identification.cells._warm_up_cells"]]) == rotations
    assert named(prerequisites[by_name["app.identification.verify._warm_up_refine"]]) == {
        "app.identification.cells._warm_up_cells", *rotations}
    assert not prerequisites[by_name["app.identification.focal_scan._warm_up_scan"]]
    assert max(_warm_ups, key=priority.get).__module__ == "app.attitude.rotations"
    # (A kernel read from a module, `shared_base.first(x)`, is the helper test's: no kernel of ours calls one so.)
    refine = next(k for k in _kernels if k.py_func.__name__ == "_refine_kernel")
    assert {"_look_up", "_assign_kernel", "_wahba_kernel"} <= {k.py_func.__name__ for k in _called_kernels(refine)}
    for function, needs in prerequisites.items():  # registered before: no cycle can stall a first run
        assert all(_warm_ups.index(need) < _warm_ups.index(function) for need in needs)


def test_searches_call_every_kernel_only_with_types_the_warm_up_compiled():
    """A kernel called with other argument types (a read-only view, a strided array) compiles again inside a
    search, outside the warm-up's one log line and against the search's clock (a first run's first answers).
    Solving every kind of frame after the warm-up must compile nothing."""
    import numpy as np

    from app.bench.peer import _no_match_frame
    from app.camera import CAMERAS
    from app.compiled import _kernels, warm_up
    from app.identification import Sky, solve_sequence
    from app.simulate import simulate_sequence, true_optics

    warm_up()  # the imports above registered every kernel module's warm-up
    before = {kernel: len(kernel.signatures) for kernel in _kernels}
    # One type signature each at most (none: called only from other kernels, loaded with them): a kernel called
    # with a read-only view in one place and a writable array in another compiles twice (0.3-0.4 s each).
    assert {k.py_func.__qualname__: n for k, n in before.items() if n > 1} == {}
    sky = Sky()
    rng = np.random.default_rng(8)
    camera = CAMERAS["tubsat-752x582-20deg"]
    sequences = [simulate_sequence(rng, camera, scenario)[0] for scenario in ("single", "nominal", "ghosts", "sparse")]
    sequences.append(simulate_sequence(rng, camera, "single", true_camera=true_optics(camera, focal_error=0.04))[0])
    sequences.append(simulate_sequence(rng, CAMERAS["liebe-576x604-30deg"], "nominal")[0])
    sequences += [_no_match_frame(rng, camera, "noise"), _no_match_frame(rng, camera, "earth")]
    for sequence in sequences:
        solve_sequence(sequence, sky)
    compiled_again = {kernel.py_func.__qualname__: kernel.signatures[before[kernel]:]
                      for kernel in _kernels if len(kernel.signatures) > before[kernel]}
    assert not compiled_again


def test_a_warm_up_held_too_long_by_another_process_is_run_here_after_the_bound(tmp_path, monkeypatch, caplog):
    """The first process waits for a warm-up another holds (its helper compiling it) at most WARM_UP_WAIT_S,
    then stops its helpers and runs it itself, saying so: a stuck holder never stalls a start."""
    import fcntl
    import logging
    import time

    import app.compiled as compiled

    ran = []

    def _warm_held():
        ran.append(True)

    class Process:  # a helper's process as far as the bound sees it
        killed = False

        def kill(self):
            Process.killed = True

    monkeypatch.setattr(compiled, "WARM_UP_WAIT_S", 0.3)
    with open(tmp_path / f"warm-up.{_warm_held.__module__}.{_warm_held.__qualname__}.lock", "a") as held:
        fcntl.flock(held, fcntl.LOCK_EX)  # another open file: flock conflicts as with another process
        t0 = time.monotonic()
        with caplog.at_level(logging.WARNING, logger="app.compiled"):
            compiled._take_turns([_warm_held], tmp_path, [compiled._Helper(Process(), None, None)])
        waited = time.monotonic() - t0
    assert ran == [True] and Process.killed and 0.3 <= waited < 5.0
    assert "._warm_held: held by another process, or waiting for one, for 0 s: compiled here" in caplog.text


RUN_LAZY = '''
import json, logging, sys
logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
sys.path.insert(0, sys.argv[1])
import tiny_kernels
from app.compiled import warm_up
report = warm_up(eager=False)
before = sum(tiny_kernels.twice.stats.cache_hits.values()) + sum(tiny_kernels.twice.stats.cache_misses.values())
value = tiny_kernels.twice(4.0)
print(json.dumps({"report": report, "before_call": before, "value": value,
                  "loaded_at_call": sum(tiny_kernels.twice.stats.cache_hits.values()),
                  "compiled_at_call": sum(tiny_kernels.twice.stats.cache_misses.values())}))
'''


def test_a_search_s_warm_up_compiles_a_stale_cache_at_once_and_leaves_a_complete_one_to_load_as_used(tmp_path):
    """warm_up(eager=False), a search's own call: with no cache it compiles every kernel before the search (one
    line); with the cache complete it loads nothing itself, and a kernel loads from the cache at its first
    call (nothing compiled there)."""
    (tmp_path / "tiny_kernels.py").write_text(MODULE)

    def run() -> tuple[dict, str]:
        return _run(tmp_path, RUN_LAZY)

    first, log = run()
    assert first["report"]["compiled"] == 1 and not first["report"].get("cached") and first["value"] == 8.0
    assert first["before_call"] == 1 and first["compiled_at_call"] == 1  # compiled by the warm-up, before the call
    assert sum("compiled 1 numba kernels in" in line for line in log.splitlines()) == 1
    second, log = run()
    assert second["report"] == {**second["report"], "cached": True, "compiled": 0, "loaded": 0}
    assert second["before_call"] == 0  # nothing loaded by the warm-up ...
    assert second["loaded_at_call"] == 1 and second["compiled_at_call"] == 0 and second["value"] == 8.0  # ... at the call
    assert sum("each loads at its first call" in line for line in log.splitlines()) == 1 and "WARNING" not in log
