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

Then where the default's time goes: the same frames solved once more by the default search with a wall-clock
timer around each of the functions :data:`STAGES` names (wrapped where they are called from for this pass only,
then put back), mean ms per frame; the search's own Python is what ``identify`` spends outside its stages.
"""

from __future__ import annotations

import contextlib
import math
import os
import time
from collections import defaultdict

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


#: (module, function, what it does), timed where the search calls it; ``identify``'s own stages first.
STAGES = (
    ("app.identification.engine", "build_candidate", "building and scoring the candidates an operator steps through"),
    ("app.identification.engine", "refine_many", "refining the best hypotheses"),
    ("app.identification.engine", "check_pair_hypotheses", "checking the first edge's hypotheses as they are made"),
    ("app.identification.engine", "refine_optics", "the optics fit of the candidates"),
    ("app.identification.engine", "prepare_pattern", "the pattern and the star field of its hour"),
    ("app.identification.hypotheses", "ordered_pattern_edges", "the pattern's Delaunay edges"),
    ("app.identification.hypotheses", "bright_pair_hypotheses", "generating the hypotheses' rows"),
    ("app.identification.engine", "focal_estimate", "the bright triangles' focal-length lookup"),
    ("app.identification", "image_centre_radec", "the image centre's fit"),
    ("app.identification", "extract", "extraction"),
    ("app.identification", "fit_sequence", "the sequence fit"),
    ("app.identification", "fit_sequence_camera", "the sequence's optics over every snapshot"),
)
#: The stages above that run inside the search (``identify``): the rest of its time is its own Python.
IN_IDENTIFY = 8


@contextlib.contextmanager
def _stage_timers(spent: dict):
    """Each of :data:`STAGES` (and ``identify``) wrapped with a timer adding its wall seconds to ``spent``, then put
    back as it was."""
    import importlib

    targets = [(importlib.import_module(m), f, label) for m, f, label in STAGES]
    targets.append((importlib.import_module("app.identification"), "identify", "identify"))
    originals = [(module, name, getattr(module, name)) for module, name, _ in targets]

    def timed(function, label):
        def wrapper(*args, **kwargs):
            t0 = time.perf_counter()
            try:
                return function(*args, **kwargs)
            finally:
                spent[label] += time.perf_counter() - t0
        return wrapper

    try:
        for (module, name, label), (_, _, function) in zip(targets, originals):
            setattr(module, name, timed(function, label))
        yield spent
    finally:
        for module, name, function in originals:
            setattr(module, name, function)


def stage_split(sequences, sky) -> dict:
    """Mean wall ms per frame of each of :data:`STAGES` in the default search of ``sequences``, the search's own
    Python (``identify`` less its stages) and the total."""
    spent = defaultdict(float)
    total = 0.0
    with _stage_timers(spent):
        for sequence in sequences:
            t0 = time.perf_counter()
            solve_sequence(sequence, sky)
            total += time.perf_counter() - t0
    n = len(sequences)
    inside = sum(spent[label] for _, _, label in STAGES[:IN_IDENTIFY])
    return {"stages": [{"stage": label, "function": f"{module.rsplit('.', 1)[-1]}.{name}",
                        "ms": round(spent[label] / n * 1e3, 3)} for module, name, label in STAGES],
            "search_python_ms": round(max(0.0, spent["identify"] - inside) / n * 1e3, 3),
            "total_ms": round(total / n * 1e3, 3)}


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
    rows, splits = {}, {}
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
        splits[scenario] = stage_split(sequences, sky)
    return {"camera": CAMERA_NAME, "seed": seed, "rows": rows, "stage_split": splits,
            "load_average_before": load_before, "load_average_after": round(os.getloadavg()[0], 2)}


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
    splits = result.get("stage_split", {})
    if splits:
        single, sequence = splits["single"], splits.get("nominal")

        def row(label: str, a: float, b: float | None) -> str:
            return f"{label:<88} {a:>7.2f} {b if b is not None else float('nan'):>9.2f}"

        lines += ["", "where the default's time goes (wall ms per frame, mean; a timer around each function):",
                  f"{'stage':<88} {'single':>7} {'sequence':>9}"]
        for k, stage in enumerate(single["stages"]):
            lines.append(row(f"{stage['stage']} ({stage['function']})", stage["ms"],
                             sequence["stages"][k]["ms"] if sequence else None))
        lines.append(row("the search's own Python (identify less its stages)", single["search_python_ms"],
                         sequence["search_python_ms"] if sequence else None))
        lines.append(row("total", single["total_ms"], sequence["total_ms"] if sequence else None))
    return "\n".join(lines)
