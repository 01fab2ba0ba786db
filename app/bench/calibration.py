"""Calibration honesty benchmark: are a calibration's errors as small as its stated sigmas, and centred?

One calibration (:mod:`app.bench.camera`) shows an error beside its sigma;
whether the sigmas can be trusted, and whether the fit leans one way, shows
only over many.  Each of ``n`` trials simulates 20 sequences of the 20 deg
camera whose true optics have the focal length 3 % long and k1 at 1 % of the
field radius at the corner (independent draws per trial), identifies them
with the pipeline, and fits the camera's focal length, principal point and
k1 (:data:`app.workflow.calibrate.DEFAULT_PARAMETERS`) two ways:

* ``identified tracks``: from the sightings of the tracks identification
  matched, the first fit of :func:`app.workflow.calibrate.fit`;
* ``re-associated``: every source associated again through the fitted
  camera and refitted, what :func:`~app.workflow.calibrate.fit` returns.

Per parameter: the pull (fitted minus true, over the stated sigma), its mean
with the mean's standard error, and its rms.  Honest sigmas give an rms
near 1; an unbiased fit a mean within about two standard errors of 0.
"""

from __future__ import annotations

import time

import numpy as np

from app.bench.camera import CORNER_DISTORTION, _true_camera
from app.camera import CAMERAS
from app.camera_fit import parameter_names
from app.identification import IDENTIFIED, SearchOptions, Sky, solve_sequence
from app.simulate import simulate_sequence
from app.workflow.calibrate import DEFAULT_PARAMETERS, IdentifiedSequence, fit
from app.workflow.errors import Invalid

SEQUENCES_PER_TRIAL = 20
FOCAL_ERROR = 0.03
PARAMETERS = parameter_names(DEFAULT_PARAMETERS)
WAYS = ("identified tracks", "re-associated")


def _pulls(camera, sigma: dict, truth) -> dict[str, float]:
    fitted, true = camera.optics(), truth.optics()
    return {name: (fitted[name] - true[name]) / sigma[name] for name in PARAMETERS}


def run_trial(sky: Sky, trial: int, seed: int) -> dict[str, dict[str, float]] | None:
    """The pulls of both ways in one trial (None when too few sequences identified)."""
    camera = CAMERAS["tubsat-752x582-20deg"]
    truth = _true_camera(camera, FOCAL_ERROR, CORNER_DISTORTION)
    rng = np.random.default_rng([seed, trial, 1601])
    identified = []
    for i in range(SEQUENCES_PER_TRIAL):
        sequence, _ = simulate_sequence(rng, camera, "nominal", true_camera=truth)
        solved = solve_sequence(sequence, sky, options=SearchOptions())
        if solved.solution.status == IDENTIFIED:
            identified.append(IdentifiedSequence.from_solved(str(i), solved, sky))
    try:
        fitted = fit(identified, camera, sky)
    except Invalid:
        return None
    first, final = fitted.first, fitted.calibration
    return {WAYS[0]: _pulls(first.camera, first.sigma, truth), WAYS[1]: _pulls(final.camera, final.sigma, truth)}


def run(n_sequences: int = 60, seed: int = 1) -> dict:
    """``n_sequences`` is the number of trials here (each of :data:`SEQUENCES_PER_TRIAL` sequences)."""
    sky = Sky()
    t0 = time.perf_counter()
    trials = [p for p in (run_trial(sky, k, seed) for k in range(n_sequences)) if p is not None]
    rows = []
    for way in WAYS:
        row = {"way": way, "trials": len(trials)}
        for name in PARAMETERS:
            pulls = np.array([t[way][name] for t in trials])
            row[name] = {"mean": round(float(pulls.mean()), 2),
                         "stderr": round(float(pulls.std(ddof=1) / np.sqrt(len(pulls))), 2) if len(pulls) > 1 else None,
                         "rms": round(float(np.sqrt(np.mean(pulls ** 2))), 2)}
        rows.append(row)
    return {"rows": rows, "sequences_per_trial": SEQUENCES_PER_TRIAL, "seconds": round(time.perf_counter() - t0, 1)}


def format_table(result: dict) -> str:
    lines = [f"Pulls (fitted - true) / sigma over trials of {result['sequences_per_trial']} sequences, 20 deg camera, "
             f"focal length {FOCAL_ERROR:.0%} long, k1 at {CORNER_DISTORTION:.0%} of the field radius:",
             f"{'fit from':<18} {'trials':>6} " + " ".join(f"{name:>22}" for name in PARAMETERS),
             f"{'':<18} {'':>6} " + " ".join(f"{'mean (+-se)   rms':>22}" for _ in PARAMETERS)]
    for row in result["rows"]:
        cells = [f"{row[n]['mean']:+6.2f} (+-{row[n]['stderr'] or 0:.2f})  {row[n]['rms']:5.2f}" for n in PARAMETERS]
        lines.append(f"{row['way']:<18} {row['trials']:>6} " + " ".join(f"{c:>22}" for c in cells))
    lines.append("(honest sigmas: rms near 1; unbiased: mean within about 2 standard errors of 0)")
    return "\n".join(lines)
