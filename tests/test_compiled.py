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


def _run(tmp_path: Path) -> tuple[dict, str]:
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env["STARID_CACHE_DIR"] = str(tmp_path / "cache")
    done = subprocess.run([sys.executable, "-c", RUN, str(tmp_path)], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=120)
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
