"""Sequence attitude, uncertainty and tracking benchmark.

* Calibration of the reported 1-sigma: over simulated 16-snapshot
  sequences solved end to end, the error of the averaged attitude at the
  reference time, as a small rotation in the camera frame, is divided by the
  reported sigma of each axis; the RMS of those ratios should be 1 (within
  +-20 %) for the two cross-boresight axes and for roll.
* Rate: the fraction of sequences whose body rate lies within 3 sigma of the
  truth on every axis (Gaussian expectation 99.2 %), and by the Mahalanobis
  distance (chi-square with 3 degrees of freedom at the 3-sigma level, 99.73 %).
* Tracking mode: single snapshots with >= 2 stars, a prior off by a random
  rotation of up to 1 deg (1-sigma 1 deg): fraction correct (boresight within
  0.1 deg, roll within 0.5 deg), fraction identified and wrong, and the time
  per snapshot; and the same with priors 10 deg wide, off by up to 10 deg
  (searched lost in space, the prior keeping what it allows).
"""

from __future__ import annotations

import time
from datetime import datetime, timedelta, timezone

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from app.bench.identification import is_correct
from app.camera import CAMERAS
from app.extraction import extract
from app.identification import Sky, solve_sequence
from app.identification.near_prior import identify_near_prior as track
from app.simulate import simulate_sequence


def _calibration(sky: Sky, n: int, seed: int) -> dict:
    ratios, rate_axis_ok, rate_maha_ok, used = [], [], [], 0
    cams = list(CAMERAS.values())
    rng = np.random.default_rng([seed, 61])
    for k in range(n):
        sequence, truth = simulate_sequence(rng, cams[k % len(cams)], "nominal")
        solved = solve_sequence(sequence, sky)
        fit = solved.sequence_fits.get(1)
        ref = solved.extraction.reference
        R_true = np.asarray(truth["rotation_matrices"][ref])
        if fit is None or not is_correct(fit.rotation, R_true)[0]:
            continue
        used += 1
        err = Rotation.from_matrix(R_true @ fit.rotation.T).as_rotvec()
        ratios.append(err / np.sqrt(np.diag(fit.covariance)))
        w_err = fit.rate_rad_s - np.asarray(truth["body_rate_rad_s"])
        rate_axis_ok.append(bool(np.all(np.abs(w_err) <= 3 * np.sqrt(np.diag(fit.rate_covariance)))))
        maha = float(w_err @ np.linalg.solve(fit.rate_covariance, w_err))
        rate_maha_ok.append(maha <= chi2.ppf(0.9973, 3))
    r = np.array(ratios)
    return {
        "sequences": n, "used": used,
        "error_over_sigma_rms": {"x": round(float(np.sqrt(np.mean(r[:, 0] ** 2))), 3),
                                 "y": round(float(np.sqrt(np.mean(r[:, 1] ** 2))), 3),
                                 "roll": round(float(np.sqrt(np.mean(r[:, 2] ** 2))), 3)} if used else None,
        "rate_within_3sigma_every_axis": round(float(np.mean(rate_axis_ok)), 4) if used else None,
        "rate_within_3sigma_mahalanobis": round(float(np.mean(rate_maha_ok)), 4) if used else None,
    }


def _tracking(sky: Sky, n: int, seed: int, sigma_deg: float = 1.0) -> dict:
    rng = np.random.default_rng([seed, 62])
    cams = list(CAMERAS.values())
    ok, wrong, times, tried = 0, 0, [], 0
    # Tracking follows one spacecraft through a pass: snapshots seconds apart,
    # so the apparent star field (cached per hour) is shared, as in operations.
    start = datetime(2024, 6, 1, 12, 0, tzinfo=timezone.utc)
    for k in range(n):
        camera = cams[k % len(cams)]
        sequence, truth = simulate_sequence(rng, camera, "single", start_time=start + timedelta(seconds=3 * k % 3000))
        pattern = extract(sequence).pattern
        stars = sum(s["kind"] == "star" for s in truth["sources"][0])
        if stars < 2:
            continue
        tried += 1
        R = np.asarray(truth["rotation_matrices"][0])
        axis = rng.normal(size=3)
        off = np.radians(rng.uniform(0, sigma_deg))
        prior = Rotation.from_rotvec(axis / np.linalg.norm(axis) * off).as_matrix() @ R
        t0 = time.perf_counter()
        sol = track(pattern, camera, sequence.snapshots[0].time, sky, prior, prior_sigma_deg=sigma_deg)
        times.append(time.perf_counter() - t0)
        right = bool(sol.best is not None and is_correct(sol.best.rotation_matrix, R)[0])
        ok += right
        wrong += sol.status == "identified" and not right
    return {"sigma_deg": sigma_deg, "snapshots": tried, "correct": round(ok / tried, 5) if tried else None,
            "identified_wrong": wrong,
            "time_ms_median": round(float(np.median(times)) * 1000, 3) if times else None,
            "time_ms_p95": round(float(np.percentile(times, 95)) * 1000, 3) if times else None}


def run(n_sequences: int = 500, seed: int = 1) -> dict:
    sky = Sky()
    return {"calibration": _calibration(sky, n_sequences, seed),
            "tracking": _tracking(sky, max(n_sequences, 1000), seed),
            "tracking_wide": _tracking(sky, max(n_sequences // 2, 300), seed, sigma_deg=10.0)}


def format_table(result: dict) -> str:
    c = result["calibration"]
    lines = [f"sequence fit over {c['used']} correctly identified of {c['sequences']} simulated sequences:"]
    if c["error_over_sigma_rms"]:
        e = c["error_over_sigma_rms"]
        lines.append(f"  RMS(error / reported sigma): x {e['x']:.3f}  y {e['y']:.3f}  roll {e['roll']:.3f}"
                     "   (1.000 = honest; the goal is 0.8-1.2)")
        lines.append(f"  body rate within 3 sigma: every axis {c['rate_within_3sigma_every_axis']:.4f}, "
                     f"Mahalanobis {c['rate_within_3sigma_mahalanobis']:.4f}")
    for t in (result["tracking"], result["tracking_wide"]):
        lines.append(f"tracking mode (prior {t['sigma_deg']:g} deg wide, off by up to that) over {t['snapshots']} single "
                     f"snapshots with >= 2 stars: correct {t['correct']}, identified and wrong {t['identified_wrong']}, "
                     f"median {t['time_ms_median']} ms, p95 {t['time_ms_p95']} ms")
    return "\n".join(lines)
