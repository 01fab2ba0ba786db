"""The floor of this engine: ``python -m app bench --suite floor [--n N] [--seed S] [--json]``.

How fast the search itself is, without what only an operator or a report needs.  The same simulated
frames of the 20 deg camera (``N`` single snapshots, default 100, and ``N * 3 // 5`` 16-snapshot
sequences) are solved in turn by four searches, each frame by all four before the next (so a slow
moment of the machine falls on all of them alike):

1. the default;
2. one candidate and three refinements (no alternatives for Next/Prev: ``SearchOptions(max_candidates=1,
   max_refinements=3)``);
3. ... and no optics fit of the candidate (``fit_optics=False``);
4. ... and no image centre (``image_centre=False``).

Figures: CPU time (``process_time``) per frame, median and p95, and each search's median over the
default's; every stripped search must name the default's best answer (the same status and attitude
within 1 arcsec), which the suite counts.  The peer bench (:mod:`app.bench.peer`) holds the ratios to
cedar-solve; this suite says which of them the search itself can reach.
"""

from __future__ import annotations

import math
import os
import time

import numpy as np

from app.camera import CAMERAS
from app.identification import SearchOptions, Sky, solve_sequence
from app.simulate import simulate_sequence

CAMERA_NAME = "tubsat-752x582-20deg"
#: (label, search options), the default first
SEARCHES = (
    ("default", SearchOptions()),
    ("one candidate, three refinements", SearchOptions(max_candidates=1, max_refinements=3)),
    ("... and no optics fit", SearchOptions(max_candidates=1, max_refinements=3, fit_optics=False)),
    ("... and no image centre", SearchOptions(max_candidates=1, max_refinements=3, fit_optics=False,
                                              image_centre=False)),
)


def _solve(sequence, sky, options: SearchOptions):
    """(CPU ms, the solution) of one search."""
    t0 = time.process_time()
    solved = solve_sequence(sequence, sky, options=options)
    return (time.process_time() - t0) * 1e3, solved.solution


def _same_answer(a, b) -> bool:
    """The same status and, when there is one, a best attitude within 1 arcsec (boresight and roll)."""
    if a.status != b.status or bool(a.candidates) != bool(b.candidates):
        return False
    if not a.candidates:
        return True
    Ra, Rb = a.candidates[0].rotation_matrix, b.candidates[0].rotation_matrix
    cosine = (float(np.trace(np.asarray(Ra) @ np.asarray(Rb).T)) - 1.0) / 2.0
    return math.degrees(math.acos(max(-1.0, min(1.0, cosine)))) * 3600.0 < 1.0


def run(n_sequences: int = 100, seed: int = 1) -> dict:
    camera = CAMERAS[CAMERA_NAME]
    sky = Sky()
    load_before = round(os.getloadavg()[0], 2)
    rows = {}
    for scenario, n in (("single", n_sequences), ("nominal", max(1, n_sequences * 3 // 5))):
        rng = np.random.default_rng([seed, 16, 0, scenario == "single"])
        sequences = [simulate_sequence(rng, camera, scenario)[0] for _ in range(n)]
        for _, options in SEARCHES:  # warm: imports and the first hour's star field, for every search
            _solve(sequences[0], sky, options)
        times = {label: [] for label, _ in SEARCHES}
        same = {label: 0 for label, _ in SEARCHES}
        for sequence in sequences:
            reference = None
            for label, options in SEARCHES:
                ms, solution = _solve(sequence, sky, options)
                times[label].append(ms)
                reference = reference or solution
                same[label] += _same_answer(solution, reference)
        default_median = float(np.median(times["default"]))
        rows[scenario] = [{"search": label, "n": n, "median_ms": round(float(np.median(times[label])), 2),
                           "p95_ms": round(float(np.percentile(times[label], 95)), 2),
                           "of_default": round(float(np.median(times[label])) / default_median, 2),
                           "same_answer": same[label]} for label, _ in SEARCHES]
    return {"camera": CAMERA_NAME, "seed": seed, "rows": rows, "load_average_before": load_before,
            "load_average_after": round(os.getloadavg()[0], 2)}


def format_table(result: dict) -> str:
    lines = [f"camera {result['camera']}, seed {result['seed']}; load average {result['load_average_before']} "
             f"before, {result['load_average_after']} after (2 cores); CPU ms per frame", "",
             f"{'frames':<9} {'search':<34} {'n':>4} {'median':>7} {'p95':>7} {'of default':>11} {'same answer':>12}"]
    for scenario, rows in result["rows"].items():
        label = "single" if scenario == "single" else "sequence"
        for r in rows:
            lines.append(f"{label:<9} {r['search']:<34} {r['n']:>4} {r['median_ms']:>7.2f} {r['p95_ms']:>7.2f} "
                         f"{r['of_default']:>11.2f} {r['same_answer']:>8}/{r['n']}")
    lines.append("(same answer: the default's status and best attitude within 1 arcsec; the peer's times are "
                 "in bench --suite peer)")
    return "\n".join(lines)
