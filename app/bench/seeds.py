"""Liebe's tables reproduced with this project's engines (seed 000).

* **Table 2** - success of the initial estimate (lost-in-space) in six
  error situations, for the bright-pair method and the triangle-feature
  (TF) method side by side with the paper's figures.
* **Table 3** - accuracy of the predictional estimate (tracking from a
  prior attitude) in the same situations.
* **Fig. 2** - mean number of stars in the field.

The set-up is Liebe's: the 576 x 604 pixel, 30 deg camera
(``CAMERAS["liebe-576x604-30deg"]``), stars to magnitude 4.5 (Hipparcos Hp),
single snapshots with 1/5-pixel centroids (Gaussian, sigma 0.2 px per axis,
no integer rounding), at a random attitude (uniform on SO(3)).  Each trial
is made directly from the catalogue (independent of :mod:`app.simulate`):
apparent places at :data:`OBSERVATION_TIME`, ``camera.vectors_to_pixels``,
stars closer than :data:`BLEND_PX` merged into their brightness-weighted
centroid (the sensor cannot split them), brightness ``10**(-0.4 m)`` with
25 % log-normal noise.  Then the situation's errors:

* *false star*: one extra point anywhere on the sensor, as bright as a
  random star of magnitude 1.5 to 4.5;
* *out of tolerance*: beyond Liebe's 3 arcmin largest position error - a
  random star of the field displaced by 4 to 8 arcmin in a random direction;
* *missing*: a random star of the field removed.

The engine runs with every point of the pattern (:data:`MAX_PATTERN_POINTS`)
and Liebe's tolerance limit as its match tolerance (:data:`MATCH_TOLERANCE_PX`).
Success of an initial estimate: the first candidate's boresight lies within
:data:`SUCCESS_BORESIGHT_DEG` (0.1 deg) of the truth.  Trials are paired:
both methods see the same patterns.

Table 3 figure (``pe_arcsec``): the mean boresight error, arcsec, of the
predictional estimate over the trials it answered correctly (within 0.1
deg): Liebe's Fig. 18 gives "the average" of the per-trial accuracy, 14.6",
the figure of his Table 3's first row.  ``pe_rms_arcsec``, the RMS of the
same errors, is reported beside it (it weighs the few-star fields' large
errors more: ~15 % above the mean for 2-D Gaussian errors); ``pe_failures``
counts the trials answered wrongly.  The predictional estimate is
:func:`app.identification.identify_near_prior` from a prior attitude off the truth
by a random rotation of up to :data:`PRIOR_OFFSET_DEG`; when that module is
not installed, the bright-pair initial estimate refined by Wahba over all
its matched stars stands in (``pe_method`` says which).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from datetime import datetime, timezone

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from app.attitude import boresight_and_roll_error
from app.camera import CAMERAS, Camera
from app.catalogue import load_catalogue
from app.extraction.model import Pattern

CAMERA_NAME = "liebe-576x604-30deg"
STAR_MAG_LIMIT = 4.5
CENTROID_SIGMA_PX = 0.2
BRIGHTNESS_LOG_SIGMA = 0.25
OUT_OF_TOLERANCE_ARCMIN = (4.0, 8.0)
FALSE_STAR_MAG = (1.5, 4.5)
BLEND_PX = 2.0
OBSERVATION_TIME = datetime(2025, 1, 1, tzinfo=timezone.utc)
SUCCESS_BORESIGHT_DEG = 0.1
PRIOR_OFFSET_DEG = 1.0
#: Liebe's imager uses every star it registers, so the engine may too.
MAX_PATTERN_POINTS = 40
#: A point matches a star within Liebe's tolerance limit, his 3 arcmin largest
#: position error (0.94 px here), not the engine's 1.5 px made for whole-pixel
#: TUBSAT centroids.
MATCH_TOLERANCE_PX = 1.0
METHODS = ("bright_pair", "tf")


@dataclass(frozen=True)
class Situation:
    name: str
    paper_ie: float  # Table 2: probability of a correct initial estimate
    paper_pe_arcsec: float  # Table 3: accuracy of the predictional estimate
    false_stars: int = 0
    out_of_tolerance: int = 0
    missing: int = 0


SITUATIONS = (
    Situation("all stars included and inside the tolerance limits", 0.946, 14.6),
    Situation("1 false star", 0.852, 15.4, false_stars=1),
    Situation("1 star outside the tolerance limits", 0.852, 14.7, out_of_tolerance=1),
    Situation("2 stars outside the tolerance limits", 0.786, 16.7, out_of_tolerance=2),
    Situation("1 star outside the tolerance limits and 1 false star", 0.720, 19.4, false_stars=1,
              out_of_tolerance=1),
    Situation("1 star missing", 0.884, 14.6, missing=1),
)
PAPER_STARS_IN_FIELD = 18.9


@dataclass(frozen=True, eq=False)
class StarSky:
    """Apparent places and magnitudes of the stars the camera registers."""

    vectors: np.ndarray  # (n, 3) ICRS
    mag: np.ndarray  # (n,)

    @classmethod
    def at(cls, t: datetime, mag_limit: float = STAR_MAG_LIMIT) -> "StarSky":
        cat = load_catalogue().brighter_than(mag_limit)
        return cls(vectors=cat.apparent_vectors(t), mag=cat.mag.copy())


# --------------------------------------------------------------------------
# Making single-snapshot patterns
# --------------------------------------------------------------------------
def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A rotation uniform on SO(3)."""
    return Rotation.random(random_state=rng).as_matrix()


def stars_on_sensor(sky: StarSky, R: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """True pixel positions and magnitudes of the stars the camera sees with attitude ``R``."""
    cam = sky.vectors @ R.T
    near = cam[:, 2] > np.cos(np.radians(40.0))  # cheap cut before projecting
    xy, front = camera.vectors_to_pixels(cam[near])
    on = front & camera.on_sensor(xy)
    return xy[on], sky.mag[near][on]


def blend_close(xy: np.ndarray, flux: np.ndarray, radius_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Merge sources closer than ``radius_px`` into one at their flux-weighted centroid, fluxes summed."""
    if len(xy) < 2:
        return xy, flux
    pairs = cKDTree(xy).query_pairs(radius_px, output_type="ndarray")
    if len(pairs) == 0:
        return xy, flux
    group = np.arange(len(xy))
    for i, j in pairs:  # few pairs: union by relabelling
        group[group == group[j]] = group[i]
    labels, inv = np.unique(group, return_inverse=True)
    total = np.bincount(inv, weights=flux)
    centre = np.column_stack([np.bincount(inv, weights=flux * xy[:, k]) / total for k in (0, 1)])
    return centre, total


def make_trial(rng: np.random.Generator, sky: StarSky, camera: Camera,
               situation: Situation) -> tuple[Pattern, np.ndarray, int]:
    """One single-snapshot pattern in ``situation``: (pattern, true rotation, stars in the field)."""
    R = random_rotation(rng)
    xy, mag = stars_on_sensor(sky, R, camera)
    n_field = len(xy)
    flux = 10.0 ** (-0.4 * mag)
    xy, flux = blend_close(xy, flux, BLEND_PX)
    xy = xy + rng.normal(0.0, CENTROID_SIGMA_PX, xy.shape)
    # Errors touch distinct stars of the field.
    chosen = rng.permutation(len(xy))
    out = chosen[:situation.out_of_tolerance]
    missing = chosen[situation.out_of_tolerance:situation.out_of_tolerance + situation.missing]
    if len(out):
        shift_px = np.radians(rng.uniform(*OUT_OF_TOLERANCE_ARCMIN, len(out)) / 60.0) / camera.pixel_scale_rad
        theta = rng.uniform(0, 2 * np.pi, len(out))
        xy[out] += shift_px[:, None] * np.column_stack([np.cos(theta), np.sin(theta)])
    keep = np.setdiff1d(np.arange(len(xy)), missing)
    xy, flux = xy[keep], flux[keep]
    if situation.false_stars:
        k = situation.false_stars
        false_xy = np.column_stack([rng.uniform(-0.5, camera.width - 0.5, k), rng.uniform(-0.5, camera.height - 0.5, k)])
        xy = np.vstack([xy, false_xy])
        flux = np.concatenate([flux, 10.0 ** (-0.4 * rng.uniform(*FALSE_STAR_MAG, k))])
    # Displaced stars may have left the sensor.
    inside = camera.on_sensor(xy)
    xy, flux = xy[inside], flux[inside]
    order = rng.permutation(len(xy))  # a sensor reports in no particular order
    xy, flux = xy[order], flux[order] * np.exp(rng.normal(0.0, BRIGHTNESS_LOG_SIGMA, len(xy)))
    m = len(xy)
    pattern = Pattern(track_ids=np.arange(m), xy=xy, vectors=camera.pixels_to_vectors(xy),
                      brightness=flux, sightings=np.ones(m, dtype=int), sigma_px=np.full(m, CENTROID_SIGMA_PX))
    return pattern, R, n_field


def perturbed_rotation(rng: np.random.Generator, R: np.ndarray, max_angle_deg: float) -> np.ndarray:
    """``R`` turned about a random axis by an angle uniform in [0, max_angle_deg)."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    return Rotation.from_rotvec(axis * np.radians(rng.uniform(0.0, max_angle_deg))).as_matrix() @ R


def boresight_error_deg(solution, R_true: np.ndarray) -> float:
    """Boresight error of the first candidate, degrees (inf without one)."""
    if not solution.candidates:
        return float("inf")
    bore, _ = boresight_and_roll_error(solution.candidates[0].rotation_matrix, R_true)
    return float(np.degrees(bore))


# --------------------------------------------------------------------------
# The benchmark
# --------------------------------------------------------------------------
def _tracker():
    """Tracking mode from a prior (:func:`app.identification.identify_near_prior`)."""
    from app.identification import identify_near_prior

    return identify_near_prior


def run_situation(id_sky, star_sky: StarSky, camera: Camera, situation: Situation, n: int, seed: int,
                  options, track) -> dict:
    from app.identification import identify

    rng = np.random.default_rng([seed, SITUATIONS.index(situation)])
    ok = {m: 0 for m in METHODS}
    ms = {m: [] for m in METHODS}
    pe_err, pe_fail, n_field = [], 0, []
    t = OBSERVATION_TIME
    for _ in range(n):
        pattern, R, k = make_trial(rng, star_sky, camera, situation)
        n_field.append(k)
        ie = {}
        for method in METHODS:
            t0 = time.perf_counter()
            ie[method] = identify(pattern, camera, t, id_sky, options=options, method=method)
            ms[method].append((time.perf_counter() - t0) * 1000)
            ok[method] += boresight_error_deg(ie[method], R) <= SUCCESS_BORESIGHT_DEG
        if track is not None:
            prior = perturbed_rotation(rng, R, PRIOR_OFFSET_DEG)
            pe = track(pattern, camera, t, id_sky, prior, prior_sigma_deg=PRIOR_OFFSET_DEG, options=options)
        else:
            pe = ie["bright_pair"]
        err = boresight_error_deg(pe, R)
        if err <= SUCCESS_BORESIGHT_DEG:
            pe_err.append(err * 3600)
        else:
            pe_fail += 1
    return {"situation": situation.name, "ie": {m: ok[m] / n for m in METHODS},
            "ms_median": {m: float(np.median(ms[m])) for m in METHODS},
            "pe_mean_arcsec": float(np.mean(pe_err)) if pe_err else None,
            "pe_rms_arcsec": float(np.sqrt(np.mean(np.square(pe_err)))) if pe_err else None,
            "pe_failures": pe_fail, "stars_in_field": n_field}


def stars_in_cone_mean(star_sky: StarSky, half_angle_deg: float, n: int, rng: np.random.Generator) -> float:
    """Mean number of stars within a cone of ``half_angle_deg`` around random directions (Liebe's Fig. 2)."""
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    counts = cKDTree(star_sky.vectors).query_ball_point(axes, 2 * np.sin(np.radians(half_angle_deg) / 2),
                                                        return_length=True)
    return float(np.mean(counts))


def run(n_sequences: int = 500, seed: int = 1) -> dict:
    """Tables 2 and 3 and Fig. 2 with ``n_sequences`` trials per situation."""
    from app.identification import SearchOptions, Sky
    from app.identification.triangle_features import TFParameters, database_for

    if n_sequences < 1:
        raise ValueError("n_sequences must be at least 1")
    camera = CAMERAS[CAMERA_NAME]
    id_sky = Sky()
    t0 = time.perf_counter()
    db = database_for(TFParameters.for_camera(camera, catalogue_mag_limit=id_sky.index.mag_limit), id_sky.index)
    tf_load_s = time.perf_counter() - t0
    star_sky = StarSky.at(OBSERVATION_TIME)
    options = SearchOptions(max_points=MAX_PATTERN_POINTS, match_tolerance_px=MATCH_TOLERANCE_PX)
    track = _tracker()
    rows = [run_situation(id_sky, star_sky, camera, s, n_sequences, seed, options, track) for s in SITUATIONS]
    in_field = [k for r in rows for k in r["stars_in_field"]]
    return {
        "table2": [{"situation": s.name, "paper": s.paper_ie, "bright_pair": round(r["ie"]["bright_pair"], 4),
                    "tf": round(r["ie"]["tf"], 4)} for s, r in zip(SITUATIONS, rows)],
        "table3": [{"situation": s.name, "paper": s.paper_pe_arcsec,
                    "pe_arcsec": None if r["pe_mean_arcsec"] is None else round(r["pe_mean_arcsec"], 2),
                    "pe_rms_arcsec": None if r["pe_rms_arcsec"] is None else round(r["pe_rms_arcsec"], 2)}
                   for s, r in zip(SITUATIONS, rows)],
        "stars_in_field_mean": round(float(np.mean(in_field)), 2),
        # Extras: how the figures were made.
        "trials_per_situation": n_sequences,
        "pe_method": "track" if track is not None else "ie_refined",
        "pe_failures": [r["pe_failures"] for r in rows],
        "time_ms_median": [{m: round(r["ms_median"][m], 2) for m in METHODS} for r in rows],
        "stars_in_30deg_circle_mean": round(stars_in_cone_mean(star_sky, 15.0, 10000,
                                                               np.random.default_rng([seed, 77])), 2),
        "catalogue_stars": int(len(star_sky.mag)),
        "tf_database": {"stars": db.n_stars, "constellations": int(len(db.nbc_star)), "entries": db.n_entries,
                        "megabytes": round(db.nbytes / 1e6, 2), "build_s": round(db.build_s, 3),
                        "load_s": round(tf_load_s, 3)},
    }


def format_table(result: dict) -> str:
    def f(v, fmt):
        return format(v, fmt) if v is not None else "-"

    n = result.get("trials_per_situation", "?")
    lines = [f"Liebe's Table 2: correct initial estimate (top-1 boresight within {SUCCESS_BORESIGHT_DEG} deg), "
             f"{n} trials per situation, 30 deg camera, stars to Hp {STAR_MAG_LIMIT}",
             f"{'situation':<54} {'paper':>6} {'bright_pair':>11} {'tf':>6} {'ms bp':>6} {'ms tf':>6}"]
    for row, ms in zip(result["table2"], result.get("time_ms_median", [{}] * len(result["table2"]))):
        lines.append(f"{row['situation']:<54} {row['paper']:>6.3f} {row['bright_pair']:>11.3f} {row['tf']:>6.3f} "
                     f"{f(ms.get('bright_pair'), '.1f'):>6} {f(ms.get('tf'), '.1f'):>6}")
    lines += ["", f"Liebe's Table 3: accuracy of the predictional estimate (boresight error, arcsec: the "
                  f"mean, the paper's 'average', and the RMS; method: {result.get('pe_method', '?')})",
              f"{'situation':<54} {'paper':>6} {'mean':>6} {'RMS':>6} {'failed':>6}"]
    for row, fails in zip(result["table3"], result.get("pe_failures", [None] * len(result["table3"]))):
        lines.append(f"{row['situation']:<54} {row['paper']:>6.1f} {f(row['pe_arcsec'], '.1f'):>6} "
                     f"{f(row.get('pe_rms_arcsec'), '.1f'):>6} {f(fails, 'd'):>6}")
    lines += ["", f"Liebe's Fig. 2: mean stars in the field {result['stars_in_field_mean']:.1f} on the "
                  f"576x604 sensor (paper: {PAPER_STARS_IN_FIELD} in a 30 deg circle; here "
                  f"{f(result.get('stars_in_30deg_circle_mean'), '.1f')} in that circle, "
                  f"{result.get('catalogue_stars', '?')} catalogue stars to Hp {STAR_MAG_LIMIT}, Liebe's 1107)"]
    db = result.get("tf_database")
    if db:
        lines.append(f"TF database: {db['stars']} stars, {db['constellations']} neighbour constellations, "
                     f"{db['entries']} entries ({db['megabytes']} MB), built in {db['build_s']} s")
    return "\n".join(lines)
