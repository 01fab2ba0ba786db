"""Simulated TUBSAT snapshot sequences with their truth.

What the sensor is modelled to do
---------------------------------
Each snapshot time ``t_i`` the camera has the attitude ``R_i`` (ICRS ->
camera, see :mod:`app.attitude`).  The spacecraft turns at a constant body
rate ``w`` (rad/s, camera axes): a fixed direction seen from a frame turning
at ``w`` moves as ``dv/dt = -w x v``, hence::

    R_i = exp(-[w]x (t_i - t_ref)) R_ref

with ``R_ref`` the attitude of the middle snapshot (a requested pointing is
that snapshot's, so a target stays in view through the sequence).

Stars are the Hipparcos-2 stars (:func:`app.catalogue.load_catalogue`) at
their apparent places at ``t_i`` (proper motion + aberration), planets are
at their ephemeris places (:mod:`app.planets`).  Both are projected with
``camera.vectors_to_pixels`` -- or, when the true optics differ from the
declared camera (``true_camera``, below), with the true camera's.  Then, per
snapshot:

* detection: a source of magnitude ``m`` is seen with probability
  ``1 / (1 + exp((m - m_lim) / 0.15))`` (50 % at the camera's limiting
  magnitude, 96 % half a magnitude brighter);
* brightness: ``b = 255 * 10**(-0.4 (m - m_sat))`` with ``m_sat = m_lim - 4``,
  times log-normal noise of sigma 0.25 (~25 %), saturated at 255 and
  rounded to an integer >= 1;
* position: Gaussian noise (sigma 0.3 px) then rounding to whole pixels,
  as the TUBSAT sensor reports integers (both configurable, :class:`SensorModel`);
* the sensor reports the ``max_sources`` (10) brightest sources; ghosts
  (spikes from transmission or thermal errors, once each, random place and
  brightness) and hot pixels (one fixed integer pixel, steady brightness, in
  most snapshots) take their slots first, the sky fills the rest;
* the order of the reported sources is shuffled (the format does not sort).

Earth in view: no stars, no planets; bright blobs (clouds, glints) that
drift each with its own velocity, so no rigid motion links them.

Imperfect optics
---------------------------
Real focal lengths are known to ~1-5 % and lenses have radial distortion
nobody declared.  ``true_camera`` (built by :func:`true_optics`) is the camera
that really projects the sky; the telemetry still declares ``camera``.  Its
focal length is ``f_declared * (1 + focal_error)``, its distortion ``k1``,
``k2`` (absolute values, replacing the declared ones) and its principal point
may be offset.  The truth file then carries ``"true_camera"``: its
``focal_length_px``, ``cx``, ``cy``, ``k1``, ``k2``.

Distortion "as a fraction of the field radius": the model moves a point at
normalised radius ``r`` (``r = distance from the principal point / f``) outwards
by the fraction ``k1 r^2 + k2 r^4`` of that distance.  At the sensor corner,
``r = half-diagonal / f`` (:attr:`Camera.corner_radius`), so a corner moved by
the fraction ``p`` needs ``k1 = p / r^2``: 1 % is k1 = 0.20 on the 20 deg
camera (r = 0.223, ~4.8 px at the corner), 0.066 on the 30 deg one (r = 0.388,
~4.2 px) -- :func:`k1_for_corner_distortion`.

Everything random comes from the ``rng`` passed in, so a seed fixes the
output byte for byte (true optics draw nothing random: the same seed gives
the same sky, only projected differently).
"""

from __future__ import annotations

import json
import math
import warnings
from dataclasses import dataclass, field
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from app.attitude import propagate, quaternion_from_rotation, radec_roll_from_rotation, rotation_from_radec_roll
from app.camera import CAMERAS, Camera
from app.catalogue import load_catalogue
from app.planets import TYPICAL_MAGNITUDES, planet_vectors, sun_vector
from app.telemetry.model import Sequence, Snapshot
from app.timefmt import utc_text

#: Scenario name -> one-line description.
SCENARIOS: dict[str, str] = {
    "clean": "random pointing and body rate, no ghost, no hot pixel (noise and dropouts only)",
    "nominal": "random pointing and body rate, 0-1 ghost per snapshot, no hot pixel",
    "ghosts": "random pointing, 1-3 ghosts in every snapshot and 0-2 hot pixels",
    "ghosts3": "random pointing, exactly 3 ghosts in every snapshot and 0-2 hot pixels (the worst case benchmarked)",
    "planet": "boresight near a bright planet (Venus, Mars, Jupiter or Saturn) well away from the Sun",
    "earth": "the Earth fills the view: no stars, only drifting bright blobs (no match must be claimed)",
    "sparse": "a sparse field: only the 4-5 brightest stars of the view are detected (as with a less "
              "sensitive sensor), all in view through the whole sequence, slow rate",
    "single": "one snapshot only, random pointing",
    "big-dipper": "pointing at the Big Dipper (RA 178 deg, Dec 56 deg), as in the TUBSAT paper's figure",
}

#: Planets bright enough to be "the planet in view" of the planet scenario.
BRIGHT_PLANETS = ("venus", "mars", "jupiter", "saturn")
#: A star sensor looks no closer to the Sun than this (degrees); Mercury,
#: never more than 28 deg from the Sun, is only asked for at 20 deg.
SUN_EXCLUSION_DEG = 40.0
MERCURY_SUN_EXCLUSION_DEG = 20.0
BIG_DIPPER_RADEC_DEG = (178.0, 56.0)

#: Limits of the simulated optical errors (validated by :func:`true_optics`).
MAX_FOCAL_ERROR = 0.2            # fraction of the declared focal length
MAX_DISTORTION_COEFFICIENT = 1.0  # |k1|, |k2| (the telemetry's k bounds go to 1 too)
MAX_CORNER_DISTORTION = 0.1      # |k1 r^2 + k2 r^4| at the sensor corner: 10 % of the radius

_SIM_START = datetime(1990, 1, 1, tzinfo=timezone.utc)
_SIM_END = datetime(2030, 1, 1, tzinfo=timezone.utc)


@dataclass(frozen=True)
class SensorModel:
    """The sensor's imperfections (defaults: a TUBSAT-class sensor)."""

    max_sources: int = 10
    position_sigma_px: float = 0.3
    integer_pixels: bool = True
    brightness_log_sigma: float = 0.25
    #: Sources brighter than (limiting magnitude - this) saturate at 255.
    saturation_below_limit_mag: float = 4.0
    #: Width of the detection fall-off around the limiting magnitude.
    dropout_width_mag: float = 0.15
    #: Hot pixels are reported in each snapshot with this probability.
    hot_pixel_presence: float = 0.9
    #: Sky sources closer than this (pixels) blur into one spot, reported at
    #: their brightness-weighted centre with their summed brightness.
    blend_radius_px: float = 2.0


@dataclass(frozen=True)
class _Plan:
    """Per-scenario choices, fixed before any snapshot is drawn."""

    ghosts_per_snapshot: tuple[int, int]  # inclusive range
    hot_pixels: tuple[int, int]
    motion_px_per_snapshot: tuple[float, float]
    earth: bool = False
    sparse_stars: tuple[int, int] | None = None


_PLANS: dict[str, _Plan] = {
    "clean": _Plan((0, 0), (0, 0), (3.0, 30.0)),
    "nominal": _Plan((0, 1), (0, 0), (3.0, 30.0)),
    "ghosts": _Plan((1, 3), (0, 2), (3.0, 30.0)),
    "ghosts3": _Plan((3, 3), (0, 2), (3.0, 30.0)),
    "planet": _Plan((0, 1), (0, 0), (3.0, 15.0)),
    "earth": _Plan((0, 1), (0, 0), (3.0, 30.0), earth=True),
    "sparse": _Plan((0, 1), (0, 0), (2.0, 8.0), sparse_stars=(4, 5)),
    "single": _Plan((0, 1), (0, 0), (3.0, 30.0)),
    "big-dipper": _Plan((0, 1), (0, 0), (3.0, 15.0)),
}


# --- small pure functions ---------------------------------------------------

def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A rotation matrix uniform on SO(3): a normalised 4-D Gaussian is a uniform unit quaternion."""
    q = rng.normal(size=4)
    return Rotation.from_quat(q / np.linalg.norm(q)).as_matrix()


def random_unit_vector(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def attitude_at(R_ref: np.ndarray, body_rate: np.ndarray, dt_s: float) -> np.ndarray:
    """``exp(-[w]x dt) R_ref``: the attitude ``dt_s`` seconds after ``R_ref`` at body rate ``w``."""
    return propagate(R_ref, body_rate, dt_s)


def pixel_motion_per_radian(camera: Camera, axis: np.ndarray) -> float:
    """Median pixel displacement over the sensor per radian of turn about ``axis`` (camera frame).

    Evaluated on a 5x5 grid of sensor points for a small turn; the motion
    is linear in the angle at these sizes.
    """
    gx, gy = np.meshgrid(np.linspace(0, camera.width - 1, 5), np.linspace(0, camera.height - 1, 5))
    grid = np.column_stack([gx.ravel(), gy.ravel()])
    angle = 1e-4
    moved, _ = camera.vectors_to_pixels(
        camera.pixels_to_vectors(grid) @ Rotation.from_rotvec(-angle * axis).as_matrix().T)
    return float(np.median(np.linalg.norm(moved - grid, axis=1)) / angle)


def body_rate_for_motion(camera: Camera, axis: np.ndarray, pixels_per_snapshot: float,
                         spacing_s: float) -> np.ndarray:
    """Body rate (rad/s, camera frame) about ``axis`` moving the sky by the given pixels per snapshot."""
    axis = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    return axis * pixels_per_snapshot / (pixel_motion_per_radian(camera, axis) * spacing_s)


def detection_probability(mag: np.ndarray, limit: float, width: float) -> np.ndarray:
    """Logistic fall-off: 1 for bright sources, 1/2 at the limiting magnitude."""
    return 1.0 / (1.0 + np.exp((np.asarray(mag, dtype=float) - limit) / width))


def brightness_from_magnitude(mag: np.ndarray, saturation_mag: float) -> np.ndarray:
    """``255 * 10**(-0.4 (m - m_sat))``, saturated at 255 (the 8-bit sensor's ceiling)."""
    return np.minimum(255.0, 255.0 * 10.0 ** (-0.4 * (np.asarray(mag, dtype=float) - saturation_mag)))


def random_time(rng: np.random.Generator) -> datetime:
    """A UTC time uniform in 1990-2030, to the millisecond."""
    span_ms = int((_SIM_END - _SIM_START).total_seconds() * 1000)
    return _SIM_START + timedelta(milliseconds=int(rng.integers(span_ms)))


def snapshot_times(start: datetime, n: int, spacing_ms: int) -> list[datetime]:
    return [start + timedelta(milliseconds=i * spacing_ms) for i in range(n)]


def k1_for_corner_distortion(camera: Camera, fraction: float) -> float:
    """The k1 that moves the sensor corner by ``fraction`` of its distance from the principal point.

    ``k1 r^2 = fraction`` with ``r`` = :attr:`Camera.corner_radius`
    (half-diagonal / f): 0.01 ("1 % of the field radius") gives k1 = 0.20 on
    the 20 deg camera.
    """
    return float(fraction) / camera.corner_radius ** 2


def true_optics(camera: Camera, *, focal_error: float = 0.0, k1: float | None = None,
                k2: float | None = None, cx_offset: float = 0.0, cy_offset: float = 0.0) -> Camera:
    """The camera that really projects the sky when ``camera`` is what the telemetry declares.

    Focal length ``f * (1 + focal_error)``; ``k1``, ``k2`` replace the
    declared coefficients (None: keep them); principal point moved by
    ``cx_offset``, ``cy_offset`` pixels.  Raises ValueError, saying which and
    why, for a focal error outside +-0.2, a coefficient outside +-1, a
    distortion larger than 10 % of the radius at the sensor corner or not
    monotonic out to it, or a principal point outside the central half of the
    sensor.
    """
    values = {"focal_error": focal_error, "k1": k1, "k2": k2, "cx_offset": cx_offset, "cy_offset": cy_offset}
    for key, value in values.items():
        if value is not None and not math.isfinite(value):
            raise ValueError(f"{key} must be a finite number, got {value!r}")
    if not -MAX_FOCAL_ERROR <= focal_error <= MAX_FOCAL_ERROR:
        raise ValueError(f"focal_error must be between -{MAX_FOCAL_ERROR:g} and {MAX_FOCAL_ERROR:g} "
                         f"(a fraction: 0.03 is 3 %), got {focal_error:g}")
    for key in ("k1", "k2"):
        if values[key] is not None and abs(values[key]) > MAX_DISTORTION_COEFFICIENT:
            raise ValueError(f"{key} must be within +-{MAX_DISTORTION_COEFFICIENT:g}, got {values[key]:g}")
    for key, size in (("cx_offset", camera.width), ("cy_offset", camera.height)):
        if abs(values[key]) > size / 4:
            raise ValueError(f"{key} must be within +-{size / 4:g} px (the principal point stays in the "
                             f"central half of the sensor), got {values[key]:g}")
    true = camera.with_optics(focal_length_px=camera.focal_length_px * (1.0 + focal_error),
                              cx=camera.cx + cx_offset, cy=camera.cy + cy_offset, k1=k1, k2=k2)
    _check_distortion(true)
    return true


def _check_distortion(camera: Camera) -> None:
    """The radial map r -> r (1 + k1 r^2 + k2 r^4) must stay small and increasing out to the corner."""
    r_corner = camera.corner_radius
    corner = camera.k1 * r_corner ** 2 + camera.k2 * r_corner ** 4
    if abs(corner) > MAX_CORNER_DISTORTION:
        raise ValueError(f"k1 = {camera.k1:g}, k2 = {camera.k2:g} move the sensor corner by {100 * corner:.1f} % "
                         f"of its radius; at most {100 * MAX_CORNER_DISTORTION:g} % is simulated "
                         f"(1 % is k1 = {k1_for_corner_distortion(camera, 0.01):.3g} for this camera)")
    if camera.fold_radius <= r_corner:
        raise ValueError(f"k1 = {camera.k1:g}, k2 = {camera.k2:g} fold the image over before the sensor corner")


def true_camera_truth(camera: Camera, true_camera: Camera | None) -> dict | None:
    """The truth file's ``true_camera`` entry, or None when the true optics are the declared ones."""
    if true_camera is None or true_camera.optics() == camera.optics():
        return None
    return {key: float(value) for key, value in true_camera.optics().items()}


# --- the simulation -----------------------------------------------------------

@dataclass
class _SkySources:
    """Light sources of one snapshot before the sensor's selection."""

    xy: list[np.ndarray] = field(default_factory=list)  # true pixel positions
    brightness: list[float] = field(default_factory=list)  # noise-free
    p_detect: list[float] = field(default_factory=list)
    labels: list[dict] = field(default_factory=list)

    def add(self, xy, brightness, p_detect, label) -> None:
        self.xy.append(np.asarray(xy, dtype=float))
        self.brightness.append(float(brightness))
        self.p_detect.append(float(p_detect))
        self.labels.append(label)


def _label(kind: str, obj: str, hip: int | None = None, planet: str | None = None) -> dict:
    return {"kind": kind, "hip": hip, "planet": planet, "object": obj}


def _in_view(camera: Camera, v_cam: np.ndarray, margin: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    xy, front = camera.vectors_to_pixels(v_cam)
    return xy, front & camera.on_sensor(xy, margin=margin)


def _choose_planet_pointing(rng, camera, planet, start_time, duration_s):
    """(start time, R_ref, planet) with the planet near the boresight at the middle snapshot."""
    for _ in range(200):
        t0 = start_time or random_time(rng)
        t_mid = t0 + timedelta(seconds=duration_s / 2)
        sun = sun_vector(t_mid)
        places = planet_vectors(t_mid)
        candidates = [planet] if planet else list(BRIGHT_PLANETS)
        names = [p for p in candidates
                 if math.degrees(math.acos(np.clip(places[p] @ sun, -1, 1)))
                 >= (MERCURY_SUN_EXCLUSION_DEG if p == "mercury" else SUN_EXCLUSION_DEG)]
        if start_time is not None and not names:
            names = candidates  # the caller fixed the time: take the planet wherever it is
        if names:
            name = names[int(rng.integers(len(names)))]
            break
    else:  # pragma: no cover - within 200 random times a planet is away from the Sun
        raise RuntimeError("no bright planet away from the Sun")
    # Offset the boresight from the planet by up to 30 % of the half height,
    # so the planet is not always dead centre.
    target = places[name]
    offset = rng.uniform(0, 0.3) * (camera.height / 2) / camera.focal_length_px
    side = np.cross(target, random_unit_vector(rng))
    side /= np.linalg.norm(side)
    boresight = target * math.cos(offset) + side * math.sin(offset)
    ra = math.degrees(math.atan2(boresight[1], boresight[0])) % 360.0
    dec = math.degrees(math.asin(np.clip(boresight[2], -1, 1)))
    return t0, rotation_from_radec_roll(ra, dec, rng.uniform(0, 360)), name


def _star_sightings(camera, stars, rotations, times):
    """Per snapshot: (indices into ``stars``, true pixel positions) of the stars on the sensor."""
    out = []
    for R, t in zip(rotations, times):
        with warnings.catch_warnings():
            # Times after the bundled leap-second table (simulations run to
            # 2030): ERFA extrapolates and warns; the Earth's velocity for
            # aberration is unaffected at any level that matters.
            warnings.filterwarnings("ignore", message=".*dubious year")
            v_icrs = stars.apparent_vectors(t)
        xy, ok = _in_view(camera, v_icrs @ R.T)
        idx = np.flatnonzero(ok)
        out.append((idx, xy[idx]))
    return out


def _choose_sparse_stars(rng, camera, stars, sightings, n_snapshots, wanted: tuple[int, int]):
    """Indices of the k (in ``wanted``) brightest stars on the sensor in every snapshot, or None.

    A sparse field is one where few stars are bright enough to detect, so the
    stars kept are the brightest of the view; no brighter star is left out
    (leaving random ones out would model missing stars, another situation).
    """
    counts = np.zeros(len(stars), dtype=int)
    for idx, xy in sightings:
        inner = camera.on_sensor(xy, margin=2.0)
        counts[idx[inner]] += 1
    # Half a magnitude inside the limit: detected in ~all snapshots.
    bright = stars.mag <= camera.limiting_magnitude - 0.5
    always = np.flatnonzero((counts == n_snapshots) & bright)
    k = int(rng.integers(wanted[0], wanted[1] + 1))
    if len(always) < k:
        return None
    brightest = always[np.argsort(stars.mag[always], kind="stable")[:k]]
    # Any star brighter than the k-th that is seen in some snapshot would be
    # detected too: such a field is not sparse, draw another.
    faintest_kept = stars.mag[brightest].max()
    if np.any((counts > 0) & (stars.mag < faintest_kept) & ~np.isin(np.arange(len(stars)), brightest)):
        return None
    return set(int(i) for i in brightest)


def _earth_sources(rng, camera, n_snapshots) -> list[_SkySources]:
    """Clouds and glints: blobs each drifting at its own velocity, plus one-off glints."""
    n_blobs = int(rng.integers(6, 13))
    start = rng.uniform([0, 0], [camera.width - 1, camera.height - 1], size=(n_blobs, 2))
    heading = rng.uniform(0, 2 * np.pi, n_blobs)
    speed = rng.uniform(0, 25, n_blobs)  # pixels per snapshot, unrelated from blob to blob
    velocity = np.column_stack([np.cos(heading), np.sin(heading)]) * speed[:, None]
    level = rng.uniform(80, 255, n_blobs)
    out = []
    for i in range(n_snapshots):
        sky = _SkySources()
        # Clouds change shape: their centroid wanders by a pixel or two.
        xy = start + velocity * i + rng.normal(0, 1.5, size=(n_blobs, 2))
        for k in np.flatnonzero(camera.on_sensor(xy) & (rng.random(n_blobs) < 0.85)):
            sky.add(xy[k], level[k], 1.0, _label("earth", f"earth:{k}"))
        for g in range(int(rng.integers(0, 3))):
            sky.add(rng.uniform([0, 0], [camera.width - 1, camera.height - 1]), rng.uniform(150, 255),
                    1.0, _label("earth", f"earth:glint:{i}:{g}"))
        out.append(sky)
    return out


def _blend(true_xy, seen_xy, measured, detected, labels, radius):
    """Merge detected sources closer than ``radius`` into their brightest member (in place).

    The brightest keeps its label (with ``blend_of`` listing the others) and
    gets the brightness-weighted centre and the summed brightness; the others
    are marked undetected.  Returns the (possibly updated) labels.
    """
    idx = np.flatnonzero(detected)
    if len(idx) < 2 or radius <= 0:
        return labels
    d = np.linalg.norm(true_xy[idx, None, :] - true_xy[None, idx, :], axis=2)
    close = np.argwhere(np.triu(d < radius, k=1))
    for a, b in close:
        i, j = idx[a], idx[b]
        if not (detected[i] and detected[j]):
            continue
        keep, drop = (i, j) if measured[i] >= measured[j] else (j, i)
        w = measured[[keep, drop]]
        seen_xy[keep] = (seen_xy[keep] * w[0] + seen_xy[drop] * w[1]) / w.sum()
        measured[keep] = w.sum()
        detected[drop] = False
        labels[keep] = {**labels[keep], "blend_of": labels[keep].get("blend_of", []) + [labels[drop]["object"]]}
    return labels


def _measure_snapshot(rng, camera, sensor, sky: _SkySources, ghosts: int,
                      hot_pixels: list[tuple[np.ndarray, float]], snapshot_index: int):
    """The sensor's report of one snapshot: (xy (n, 2), brightness (n,), labels), shuffled."""
    xy_list, b_list, labels = [], [], []
    # Hot pixels: a fixed pixel, steady brightness (a few % flicker).
    for h, (pixel, level) in enumerate(hot_pixels):
        if rng.random() < sensor.hot_pixel_presence:
            xy_list.append(pixel.astype(float))
            b_list.append(level * (1 + rng.normal(0, 0.03)))
            labels.append(_label("hot_pixel", f"hot:{h}"))
    # Ghosts: once, anywhere, any brightness.
    for g in range(ghosts):
        xy_list.append(rng.uniform([0, 0], [camera.width - 1, camera.height - 1]))
        b_list.append(rng.uniform(5, 255))
        labels.append(_label("ghost", f"ghost:{snapshot_index}:{g}"))
    slots = max(0, sensor.max_sources - len(labels))

    n = len(sky.labels)
    if n and slots:
        true_xy = np.array(sky.xy).reshape(n, 2)
        seen_xy = true_xy + rng.normal(0, sensor.position_sigma_px, size=(n, 2))
        measured = np.array(sky.brightness) * np.exp(rng.normal(0, sensor.brightness_log_sigma, n))
        detected = (rng.random(n) < np.array(sky.p_detect))
        sky_labels = _blend(true_xy, seen_xy, measured, detected, list(sky.labels), sensor.blend_radius_px)
        # Keep the centroid within [0, size - 1] so rounding stays on the sensor.
        detected &= camera.on_sensor(seen_xy, margin=0.5)
        candidates = np.flatnonzero(detected)
        # Brightest first; saturated ties broken at random.
        order = np.lexsort((rng.random(len(candidates)), -np.minimum(measured[candidates], 255.0)))
        for j in candidates[order][:slots]:
            xy_list.append(seen_xy[j])
            b_list.append(measured[j])
            labels.append(sky_labels[j])

    xy = np.array(xy_list, dtype=float).reshape(-1, 2)
    if sensor.integer_pixels:
        xy = np.round(xy)
    brightness = np.clip(np.round(np.array(b_list, dtype=float)), 1.0, 255.0)
    perm = rng.permutation(len(labels))
    return xy[perm], brightness[perm], [labels[p] for p in perm]


def simulate_sequence(rng: np.random.Generator, camera: Camera, scenario: str = "nominal", *,
                      n_snapshots: int = 16, pointing: tuple[float, float, float] | None = None,
                      start_time: datetime | None = None, sequence_id: str | None = None,
                      planet: str | None = None, sensor: SensorModel = SensorModel(),
                      true_camera: Camera | None = None) -> tuple[Sequence, dict]:
    """One simulated sequence and its truth (a JSON-serialisable dict).

    ``pointing`` (RA, Dec, roll in degrees) is the attitude of the middle
    snapshot; ``planet`` pins the planet of the "planet" scenario.  The
    "single" scenario always has one snapshot.  ``true_camera`` (see
    :func:`true_optics`; same sensor size) projects the sky while the
    sequence declares ``camera``; the truth then has ``"true_camera"``.
    Raises ValueError for an unknown scenario or planet, a snapshot count
    outside 1..64, or a true camera of another size.
    """
    if scenario not in SCENARIOS:
        raise ValueError(f"unknown scenario {scenario!r}; choose from {', '.join(SCENARIOS)}")
    if planet is not None and planet not in TYPICAL_MAGNITUDES:
        raise ValueError(f"unknown planet {planet!r}; choose from {', '.join(TYPICAL_MAGNITUDES)}")
    if scenario == "single":
        n_snapshots = 1
    if not 1 <= int(n_snapshots) <= 64:
        raise ValueError("n_snapshots must be between 1 and 64")
    if start_time is not None and (start_time.tzinfo is None or not 1900 <= start_time.year <= 2098):
        # 1900-2099 is where the telemetry format and the built-in ephemeris are valid.
        raise ValueError("start_time must be a timezone-aware UTC time in 1900..2098")
    if true_camera is not None and (true_camera.width, true_camera.height) != (camera.width, camera.height):
        raise ValueError("true_camera must have the declared camera's sensor size")
    # Where light really lands; the declared camera still decides everything
    # the operator chose (sensor size, magnitude limit, motion per snapshot).
    optics = camera if true_camera is None else true_camera
    plan = _PLANS[scenario]
    limit = camera.limiting_magnitude
    if sequence_id is None:
        sequence_id = f"sim-{scenario}-{int(rng.integers(16 ** 6)):06x}"

    spacing_ms = int(rng.integers(1000, 3001))
    duration_s = (n_snapshots - 1) * spacing_ms / 1000.0
    motion = rng.uniform(*plan.motion_px_per_snapshot)
    body_rate = body_rate_for_motion(camera, random_unit_vector(rng), motion, spacing_ms / 1000.0)
    stars = load_catalogue().brighter_than(limit + 0.5)  # fainter: < 4 % detection chance

    target_planet = None
    for _attempt in range(100):  # the sparse scenario may redraw the field
        if scenario == "planet" and pointing is None:
            t0, R_ref, target_planet = _choose_planet_pointing(rng, camera, planet, start_time, duration_s)
        else:
            t0 = start_time or random_time(rng)
            if pointing is not None:
                R_ref = rotation_from_radec_roll(*pointing)
            elif scenario == "big-dipper":
                R_ref = rotation_from_radec_roll(*BIG_DIPPER_RADEC_DEG, rng.uniform(0, 360))
            else:
                R_ref = random_rotation(rng)
        t0 = t0.astimezone(timezone.utc)
        times = snapshot_times(t0, n_snapshots, spacing_ms)
        ref = n_snapshots // 2
        rotations = [attitude_at(R_ref, body_rate, (t - times[ref]).total_seconds()) for t in times]
        if plan.earth:
            break
        sightings = _star_sightings(optics, stars, rotations, times)
        keep = None
        if plan.sparse_stars:
            keep = _choose_sparse_stars(rng, camera, stars, sightings, n_snapshots, plan.sparse_stars)
            if keep is None:
                continue
        break
    else:  # pragma: no cover - a field with 4 bright stars turns up within a few draws
        raise RuntimeError("could not draw a sparse field")

    if plan.earth:
        skies = _earth_sources(rng, camera, n_snapshots)
    else:
        saturation = limit - sensor.saturation_below_limit_mag
        skies = []
        for (idx, xy), R, t in zip(sightings, rotations, times):
            sky = _SkySources()
            p = detection_probability(stars.mag[idx], limit, sensor.dropout_width_mag)
            b = brightness_from_magnitude(stars.mag[idx], saturation)
            for j, i in enumerate(idx):
                if keep is None or int(i) in keep:
                    hip = int(stars.hip[i])
                    sky.add(xy[j], b[j], p[j], _label("star", f"hip:{hip}", hip=hip))
            if plan.sparse_stars is None:
                names = list(TYPICAL_MAGNITUDES)
                vecs = planet_vectors(t)
                pxy, ok = _in_view(optics, np.array([vecs[n] for n in names]) @ R.T)
                for k in np.flatnonzero(ok):
                    mag = TYPICAL_MAGNITUDES[names[k]]
                    sky.add(pxy[k], brightness_from_magnitude(mag, saturation),
                            detection_probability(mag, limit, sensor.dropout_width_mag),
                            _label("planet", f"planet:{names[k]}", planet=names[k]))
            skies.append(sky)

    n_hot = int(rng.integers(plan.hot_pixels[0], plan.hot_pixels[1] + 1))
    hot_pixels = [(np.array([rng.integers(camera.width), rng.integers(camera.height)]),
                   float(rng.uniform(20, 255))) for _ in range(n_hot)]

    snapshots, truth_sources = [], []
    for i, (t, sky) in enumerate(zip(times, skies)):
        n_ghosts = int(rng.integers(plan.ghosts_per_snapshot[0], plan.ghosts_per_snapshot[1] + 1))
        xy, brightness, labels = _measure_snapshot(rng, camera, sensor, sky, n_ghosts, hot_pixels, i)
        snapshots.append(Snapshot(index=i, time=t, xy=xy, brightness=brightness))
        truth_sources.append(labels)

    sequence = Sequence(sequence_id=sequence_id, spacecraft="SIM-TUBSAT", camera=camera,
                        snapshots=tuple(snapshots))
    truth = {
        "sequence_id": sequence_id,
        "camera": camera.name,
        "scenario": scenario,
        "times": [utc_text(t) for t in times],
        # 12 decimals (1e-12 rad, 2e-7 arcsec) keep the truth files small.
        "rotation_matrices": [np.round(R, 12).tolist() for R in rotations],
        "quaternions": [np.round(quaternion_from_rotation(R), 12).tolist() for R in rotations],
        "radec_roll_deg": [np.round(radec_roll_from_rotation(R), 10).tolist() for R in rotations],
        "body_rate_rad_s": body_rate.tolist(),
        "sources": truth_sources,
    }
    if target_planet:
        truth["target_planet"] = target_planet
    true_optics_truth = true_camera_truth(camera, true_camera)
    if true_optics_truth is not None:
        truth["true_camera"] = true_optics_truth
    return sequence, truth


def truth_matched_stars(sequence: Sequence, truth: dict) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """Per snapshot with star sources: (position in the sequence, pixels (n, 2), ICRS unit vectors (n, 3)).

    The sources the truth labels as stars (blends included: they are what a
    real matcher would pair), with their catalogue stars' apparent places at
    the snapshot's time -- the matched stars a perfect identification would
    hand to :func:`app.camera_fit.calibrate`.
    """
    catalogue = load_catalogue()
    rows = catalogue.index_of_hip()
    out = []
    for position, (snapshot, labels) in enumerate(zip(sequence.snapshots, truth["sources"])):
        picked = [(k, rows[label["hip"]]) for k, label in enumerate(labels) if label["kind"] == "star"]
        if not picked:
            continue
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*dubious year")  # see _star_sightings
            vectors = catalogue.apparent_vectors(snapshot.time)
        sources, stars = zip(*picked)
        out.append((position, snapshot.xy[list(sources)], vectors[list(stars)]))
    return out


# --- files -----------------------------------------------------------------

def to_json_text(obj, inline_depth: int = 3) -> str:
    """JSON indented by nesting level; containers at ``inline_depth`` and deeper, and lists
    of plain numbers, on one line.

    Keeps files small and readable: one source or one matrix row per line.
    """
    def is_number_list(o):
        return isinstance(o, list) and all(isinstance(v, (int, float)) for v in o)

    def render(o, depth):
        if depth >= inline_depth or not isinstance(o, (dict, list)) or not o or is_number_list(o):
            return json.dumps(o, separators=(", ", ": "))
        pad, inner = "  " * depth, "  " * (depth + 1)
        if isinstance(o, dict):
            items = [f"{inner}{json.dumps(k)}: {render(v, depth + 1)}" for k, v in o.items()]
            return "{\n" + ",\n".join(items) + "\n" + pad + "}"
        return "[\n" + ",\n".join(inner + render(v, depth + 1) for v in o) + "\n" + pad + "]"

    return render(obj, 0) + "\n"


def camera_cycle(camera_name: str | None, i: int) -> Camera:
    """The named camera, or the i-th of :data:`CAMERAS` in turn when no name is given."""
    if camera_name is None:
        names = list(CAMERAS)
        return CAMERAS[names[i % len(names)]]
    if camera_name not in CAMERAS:
        raise ValueError(f"unknown camera {camera_name!r}; choose from {', '.join(CAMERAS)}")
    return CAMERAS[camera_name]


def write_simulation(outdir: Path, n: int, seed: int, camera_name: str | None, scenario: str, *,
                     name: str | None = None, csv: bool = False, planet: str | None = None,
                     start_time: datetime | None = None, focal_error: float = 0.0,
                     k1: float | None = None, k2: float | None = None,
                     corner_distortion: float | None = None,
                     cx_offset: float = 0.0, cy_offset: float = 0.0) -> list[Path]:
    """Write ``n`` sequences as ``<id>.json`` (or ``<id>.csv``) plus ``<id>.truth.json``.

    Sequence ``i`` draws from ``default_rng([seed, i])``, so it does not
    depend on ``n`` and the files are the same byte for byte for a seed.
    Ids are ``sim-<seed>-<i>`` or, with ``name``, ``name`` (n == 1) or
    ``name-<i>``.  Returns the paths written.

    ``focal_error``, ``k1``, ``k2``, ``cx_offset``, ``cy_offset``: the true
    optics differ from the declared camera (:func:`true_optics`);
    ``corner_distortion`` gives k1 per camera as the fraction of the field
    radius the sensor corner moves in the true optics
    (:func:`k1_for_corner_distortion` of the true focal length and principal
    point; not with ``k1``).
    """
    if n < 1:
        raise ValueError("n must be at least 1")
    if name is not None and (not name or Path(name).name != name or name.startswith(".")):
        raise ValueError(f"name {name!r} must be a plain file name (no directory, not hidden)")
    if scenario not in SCENARIOS:
        raise ValueError(f"unknown scenario {scenario!r}; choose from {', '.join(SCENARIOS)}")
    if k1 is not None and corner_distortion is not None:
        raise ValueError("give k1 or corner_distortion, not both")

    def true_camera_of(camera: Camera) -> Camera:
        k1_true = k1
        if corner_distortion is not None:  # the corner of the true optics (focal error, offsets applied)
            undistorted = true_optics(camera, focal_error=focal_error, cx_offset=cx_offset, cy_offset=cy_offset)
            k1_true = k1_for_corner_distortion(undistorted, corner_distortion)
        return true_optics(camera, focal_error=focal_error, k1=k1_true, k2=k2,
                           cx_offset=cx_offset, cy_offset=cy_offset)

    # Validate before writing anything: every camera the run will use.
    for i in range(min(n, len(CAMERAS))):
        true_camera_of(camera_cycle(camera_name, i))
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in range(n):
        camera = camera_cycle(camera_name, i)
        if name:
            sequence_id = name if n == 1 else f"{name}-{i:04d}"
        else:
            sequence_id = f"sim-{seed}-{i:04d}"
        sequence, truth = simulate_sequence(np.random.default_rng([seed, i]), camera, scenario,
                                            sequence_id=sequence_id, planet=planet,
                                            start_time=start_time, true_camera=true_camera_of(camera))
        if csv:
            from app.telemetry.formats import dump_csv

            data_path = outdir / f"{sequence_id}.csv"
            data_path.write_text(dump_csv(sequence), encoding="utf-8")
        else:
            data_path = outdir / f"{sequence_id}.json"
            data_path.write_text(to_json_text(sequence.to_json_dict(), inline_depth=4), encoding="utf-8")
        truth_path = outdir / f"{sequence_id}.truth.json"
        truth_path.write_text(to_json_text(truth), encoding="utf-8")
        paths += [data_path, truth_path]
    return paths


# --- full frames ---------------------------------------------------
#
# A star camera's whole picture instead of its spot list: every catalogue star in view drawn with a
# Gaussian point-spread function integrated over the pixels, its flux from its magnitude, on a sky
# background, with photon (shot) noise, read noise, a bias, fixed hot pixels and an optional
# satellite trail, quantised to 8 or 16 bits.  The pointing, times and body rate are those of
# simulate_sequence (same rng, so a seed fixes everything); the truth lists every rendered source
# with its exact position.  Nothing here changes what the functions above produce.

#: The Hipparcos-2 catalogue bundled here ends at Hp 7.0: fainter stars cannot be drawn.
CATALOGUE_FAINT_LIMIT = 7.0


@dataclass(frozen=True)
class FrameModel:
    """How a frame is exposed and read out (defaults: a 16-bit CMOS star camera, slightly defocused).

    Fluxes are in electrons; ``detection_limit_mag`` (None: the camera's limiting magnitude + 0.5,
    at most 6.5) is where a star's signal-to-noise ratio is :data:`DETECTION_SNR` in the PSF's
    noise-equivalent area ``4 pi sigma^2``; the zero point follows from it (:meth:`zero_point_e`).
    """

    psf_sigma_px: float = 1.2
    sky_e: float = 200.0              # sky (and dark) background per pixel per exposure
    read_noise_e: float = 10.0
    gain_e_per_adu: float = 2.0
    bias_adu: float = 100.0
    bits: int = 16
    detection_limit_mag: float | None = None
    #: Stars drawn down to this far below the detection limit (they are part of the noise floor).
    render_below_limit_mag: float = 1.0
    #: Hot pixels of this camera: how many, and their excess level in ADU (uniform range).
    n_hot_pixels: int = 6
    hot_pixel_adu: tuple[float, float] = (1500.0, 20000.0)
    #: Seed of the hot pixels' places: one camera keeps its hot pixels from pass to pass.
    hot_pixel_seed: int = 15
    #: Exposure time written to FITS headers (seconds); the times given are mid-exposure.
    exposure_s: float = 0.2
    #: How far every star's image moves during the exposure (px), and which way (degrees from +x towards
    #: +y): a fixed tripod under the turning sky, a spacecraft turning.  Each star is then a trail of that
    #: length centred on its mid-exposure place; 0: points.
    smear_px: float = 0.0
    smear_angle_deg: float = 0.0

    def noise_area_px(self) -> float:
        return 4.0 * math.pi * self.psf_sigma_px ** 2

    def background_variance_e(self) -> float:
        """Per pixel: sky shot noise + read noise (+ quantisation, small at gain 2)."""
        return self.sky_e + self.read_noise_e ** 2 + self.gain_e_per_adu ** 2 / 12.0

    def snr(self, flux_e) -> np.ndarray:
        """Signal-to-noise ratio of a star of ``flux_e`` electrons (CCD equation, PSF noise area)."""
        flux = np.asarray(flux_e, dtype=float)
        return flux / np.sqrt(flux + self.noise_area_px() * self.background_variance_e())

    def flux_for_snr(self, snr: float) -> float:
        """The flux (electrons) whose :meth:`snr` is ``snr``: F^2 = s^2 (F + A v)."""
        a = self.noise_area_px() * self.background_variance_e()
        s2 = snr * snr
        return float((s2 + math.sqrt(s2 * s2 + 4.0 * s2 * a)) / 2.0)

    def limit_mag(self, camera: Camera) -> float:
        if self.detection_limit_mag is not None:
            return float(self.detection_limit_mag)
        return min(6.5, camera.limiting_magnitude + 0.5)

    def zero_point_e(self, camera: Camera) -> float:
        """Electrons from a star of magnitude 0: ``flux(m) = zero_point * 10**(-0.4 m)``."""
        return self.flux_for_snr(DETECTION_SNR) * 10.0 ** (0.4 * self.limit_mag(camera))

    def flux_e(self, mag, camera: Camera) -> np.ndarray:
        return self.zero_point_e(camera) * 10.0 ** (-0.4 * np.asarray(mag, dtype=float))

    def saturation_adu(self) -> int:
        return 2 ** self.bits - 1


#: Signal-to-noise ratio that defines the detection limit of :class:`FrameModel`.
DETECTION_SNR = 5.0


def _pixel_fractions(centre: float, sigma: float, first: int, n: int) -> np.ndarray:
    """Fraction of a 1-D Gaussian (centre, sigma) falling in pixels first..first+n-1 (pixel k spans k-0.5..k+0.5)."""
    from scipy.special import erf

    edges = np.arange(first, first + n + 1, dtype=float) - 0.5
    cdf = 0.5 * (1.0 + erf((edges - centre) / (sigma * math.sqrt(2.0))))
    return np.diff(cdf)


def add_point_sources(image: np.ndarray, xy: np.ndarray, flux: np.ndarray, sigma: float) -> None:
    """Add Gaussian point sources (pixel-integrated, in the project's pixel convention) to ``image`` in place."""
    height, width = image.shape
    half = int(math.ceil(5.0 * sigma)) + 1
    for (x, y), f in zip(np.asarray(xy, dtype=float).reshape(-1, 2), np.asarray(flux, dtype=float)):
        x0, y0 = int(math.floor(x)) - half, int(math.floor(y)) - half
        n = 2 * half + 2
        xa, ya = max(0, x0), max(0, y0)
        xb, yb = min(width, x0 + n), min(height, y0 + n)
        if xa >= xb or ya >= yb:
            continue
        fx = _pixel_fractions(x, sigma, xa, xb - xa)
        fy = _pixel_fractions(y, sigma, ya, yb - ya)
        image[ya:yb, xa:xb] += f * np.outer(fy, fx)


def add_trail(image: np.ndarray, start: np.ndarray, end: np.ndarray, flux: float, sigma: float) -> None:
    """A trail (a satellite's, a smeared star's): ``flux`` electrons spread evenly along the segment
    start-end, blurred by the PSF."""
    length = float(np.linalg.norm(np.asarray(end, float) - np.asarray(start, float)))
    n = max(2, int(length * 4))
    t = np.linspace(0.0, 1.0, n)[:, None]
    points = np.asarray(start, float) * (1 - t) + np.asarray(end, float) * t
    add_point_sources(image, points, np.full(n, flux / n), sigma)


def camera_hot_pixels(camera: Camera, model: FrameModel) -> list[tuple[int, int, float]]:
    """The camera's hot pixels (x, y, excess ADU): fixed by ``model.hot_pixel_seed`` and the sensor size."""
    rng = np.random.default_rng([model.hot_pixel_seed, camera.width, camera.height])
    out = []
    for _ in range(model.n_hot_pixels):
        x, y = int(rng.integers(2, camera.width - 2)), int(rng.integers(2, camera.height - 2))
        out.append((x, y, float(rng.uniform(*model.hot_pixel_adu))))
    return out


def render_frame(rng: np.random.Generator, camera: Camera, xy: np.ndarray, flux_e: np.ndarray,
                 model: FrameModel = FrameModel(), *, hot_pixels: list[tuple[int, int, float]] | None = None,
                 trail: tuple[np.ndarray, np.ndarray, float] | None = None) -> np.ndarray:
    """One exposure as unsigned integers (``model.bits``): sources at ``xy`` (pixels) with ``flux_e``
    electrons, sky, shot and read noise, bias, hot pixels (x, y, ADU), an optional trail
    (start, end, electrons), clipped at the saturation level."""
    electrons = np.full((camera.height, camera.width), model.sky_e, dtype=float)
    if model.smear_px > 0:
        half = 0.5 * model.smear_px * np.array([math.cos(math.radians(model.smear_angle_deg)),
                                                 math.sin(math.radians(model.smear_angle_deg))])
        for centre, f in zip(np.asarray(xy, dtype=float).reshape(-1, 2), np.asarray(flux_e, dtype=float)):
            add_trail(electrons, centre - half, centre + half, f, model.psf_sigma_px)
    else:
        add_point_sources(electrons, xy, flux_e, model.psf_sigma_px)
    if trail is not None:
        add_trail(electrons, trail[0], trail[1], trail[2], model.psf_sigma_px)
    counts = rng.poisson(electrons).astype(float) + rng.normal(0.0, model.read_noise_e, electrons.shape)
    adu = model.bias_adu + counts / model.gain_e_per_adu
    for x, y, level in hot_pixels or ():
        adu[y, x] += level
    return np.clip(np.round(adu), 0, model.saturation_adu()).astype(np.uint16 if model.bits > 8 else np.uint8)


def simulate_frames(rng: np.random.Generator, camera: Camera, *, n_frames: int = 4,
                    pointing: tuple[float, float, float] | None = None, start_time: datetime | None = None,
                    sequence_id: str | None = None, true_camera: Camera | None = None,
                    model: FrameModel = FrameModel(), trail: bool = False,
                    hot_pixels: bool = True) -> tuple[list[np.ndarray], list[datetime], dict]:
    """Rendered frames of one pass, their (mid-exposure) times and the truth.

    The attitudes, times and body rate are drawn by :func:`simulate_sequence` (scenario "clean",
    ``n_frames`` snapshots, the same ``pointing``/``start_time``/``true_camera``); its spot lists
    are not used.  Every star to ``model.limit_mag + model.render_below_limit_mag`` (at most the
    catalogue's Hp 7.0) is drawn where the true optics put it.  ``trail``: a satellite crosses
    one frame.  The truth is simulate_sequence's (times, rotations, body rate, true camera) plus,
    per frame, ``frame_sources``: every drawn star (hip, mag, x, y, flux_e, snr), the hot pixels
    (x, y, adu) and the trail (start, end); plus ``frame_model`` and ``detection_limit_mag``.
    """
    from dataclasses import asdict

    if not 1 <= int(n_frames) <= 64:
        raise ValueError("n_frames must be between 1 and 64")
    _, truth = simulate_sequence(rng, camera, "clean", n_snapshots=n_frames, pointing=pointing,
                                 start_time=start_time, sequence_id=sequence_id, true_camera=true_camera)
    optics = camera if true_camera is None else true_camera
    times = [datetime.fromisoformat(t.replace("Z", "+00:00")) for t in truth["times"]]
    rotations = [np.array(R) for R in truth["rotation_matrices"]]
    limit = model.limit_mag(camera)
    stars = load_catalogue().brighter_than(min(CATALOGUE_FAINT_LIMIT, limit + model.render_below_limit_mag))
    sightings = _star_sightings(optics, stars, rotations, times)
    hot = camera_hot_pixels(camera, model) if hot_pixels else []
    trail_frame = int(rng.integers(n_frames)) if trail else -1
    frames, per_frame = [], []
    for i, (idx, xy) in enumerate(sightings):
        flux = model.flux_e(stars.mag[idx], camera)
        streak = None
        if i == trail_frame:
            # Across most of the sensor at a random angle, as bright as a 3rd-magnitude star per 10 px.
            centre = np.array([camera.width, camera.height]) * rng.uniform(0.3, 0.7, 2)
            angle = rng.uniform(0, math.pi)
            half = 0.4 * min(camera.width, camera.height)
            step = np.array([math.cos(angle), math.sin(angle)]) * half
            streak = (centre - step, centre + step, float(model.flux_e(3.0, camera)) * 2 * half / 10.0)
        frames.append(render_frame(rng, camera, xy, flux, model, hot_pixels=hot, trail=streak))
        sources = [{"kind": "star", "hip": int(stars.hip[k]), "mag": round(float(stars.mag[k]), 3),
                    "x": float(p[0]), "y": float(p[1]), "flux_e": float(f), "snr": float(model.snr(f))}
                   for k, p, f in zip(idx, xy, flux)]
        sources += [{"kind": "hot_pixel", "x": float(x), "y": float(y), "adu": level} for x, y, level in hot]
        if streak is not None:
            sources.append({"kind": "trail", "start": streak[0].tolist(), "end": streak[1].tolist(),
                            "flux_e": streak[2]})
        per_frame.append(sources)
    truth = {**truth, "frame_sources": per_frame, "detection_limit_mag": limit,
             "frame_model": {key: (list(value) if isinstance(value, tuple) else value)
                             for key, value in asdict(model).items()}}
    truth.pop("sources", None)  # the spot lists' labels: not what the frames show
    return frames, times, truth


def frames_fits_bytes(frames: list[np.ndarray], times: list[datetime], *, camera: Camera | None = None,
                      sequence_id: str | None = None, spacecraft: str | None = None,
                      exposure_s: float = 0.2, pixel_size_um: float = 4.8) -> bytes:
    """A multi-extension FITS file: an empty primary HDU (``SEQID``, ``SPACECRA``; with ``camera`` its
    focal length as ``FOCALLEN`` in mm for pixels of ``XPIXSZ`` = ``pixel_size_um``) and one image
    extension per frame, the first stored row being the sensor's top row (``ROWORDER =
    'TOP-DOWN'``), ``DATE-OBS`` the start of the exposure and ``EXPTIME`` its length."""
    import io

    from astropy.io import fits

    primary = fits.PrimaryHDU()
    if sequence_id:
        primary.header["SEQID"] = (sequence_id, "tubsat sequence id")
    if spacecraft:
        primary.header["SPACECRA"] = (spacecraft, "spacecraft")
    if camera is not None:
        primary.header["FOCALLEN"] = (float(camera.focal_length_px) * pixel_size_um / 1000.0, "focal length, mm")
        primary.header["XPIXSZ"] = (pixel_size_um, "pixel width, um")
        primary.header["YPIXSZ"] = (pixel_size_um, "pixel height, um")
    hdus = [primary]
    for i, (frame, t) in enumerate(zip(frames, times)):
        hdu = fits.ImageHDU(frame, name=f"FRAME{i}")
        start = t - timedelta(seconds=exposure_s / 2)
        hdu.header["DATE-OBS"] = (start.strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3], "UTC start of exposure")
        hdu.header["EXPTIME"] = (exposure_s, "exposure, s")
        hdu.header["ROWORDER"] = ("TOP-DOWN", "first stored row is the sensor's top row")
        hdus.append(hdu)
    stream = io.BytesIO()
    fits.HDUList(hdus).writeto(stream)
    return stream.getvalue()


def frame_png_bytes(frame: np.ndarray) -> bytes:
    """One frame as a PNG (16-bit greyscale for 16-bit frames, 8-bit otherwise); row 0 on top."""
    import io

    from PIL import Image

    stream = io.BytesIO()
    array = np.ascontiguousarray(frame)
    image = Image.fromarray(array.astype(np.uint16) if array.dtype != np.uint8 else array)
    image.save(stream, format="PNG")
    return stream.getvalue()


def frames_sidecar(files: list[str], times: list[datetime], camera: Camera, *, sequence_id: str | None = None,
                   spacecraft: str | None = None) -> dict:
    """The ``tubsat-frames/1`` sidecar (docs/formats.md) naming each file with its time and the camera."""
    doc: dict = {"format": "tubsat-frames/1"}
    if sequence_id:
        doc["sequence_id"] = sequence_id
    if spacecraft:
        doc["spacecraft"] = spacecraft
    doc["camera"] = camera.to_dict()
    doc["frames"] = [{"file": name, "time": utc_text(t)} for name, t in zip(files, times)]
    return doc


def write_frames(outdir: Path, n: int, seed: int, camera_name: str | None, *, form: str = "fits",
                 n_frames: int = 4, name: str | None = None, start_time: datetime | None = None,
                 trail: bool = False, focal_error: float = 0.0, k1: float | None = None) -> list[Path]:
    """Write ``n`` rendered passes: ``<id>.fits`` (one extension per frame, times and optics in its
    headers) or ``<id>/frame-NN.png`` plus
    ``<id>/frames.json`` (the sidecar), and ``<id>.truth.json``.  Pass ``i`` draws from
    ``default_rng([seed, i, 15])``.  Returns the paths written."""
    if form not in ("fits", "png"):
        raise ValueError("form must be 'fits' or 'png'")
    if n < 1:
        raise ValueError("n must be at least 1")
    if name is not None and (not name or Path(name).name != name or name.startswith(".")):
        raise ValueError(f"name {name!r} must be a plain file name (no directory, not hidden)")
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in range(n):
        camera = camera_cycle(camera_name, i)
        true_camera = true_optics(camera, focal_error=focal_error, k1=k1)
        sequence_id = (name if n == 1 else f"{name}-{i:04d}") if name else f"frames-{seed}-{i:04d}"
        frames, times, truth = simulate_frames(np.random.default_rng([seed, i, 15]), camera, n_frames=n_frames,
                                               sequence_id=sequence_id, start_time=start_time,
                                               true_camera=true_camera, trail=trail)
        if form == "fits":
            data_path = outdir / f"{sequence_id}.fits"
            # Self-contained: times, optics, sequence id and spacecraft in the headers.
            data_path.write_bytes(frames_fits_bytes(frames, times, camera=camera, sequence_id=sequence_id,
                                                    spacecraft="SIM-TUBSAT"))
            paths.append(data_path)
        else:
            folder = outdir / sequence_id
            folder.mkdir(exist_ok=True)
            files = [f"frame-{k:02d}.png" for k in range(len(frames))]
            for file, frame in zip(files, frames):
                (folder / file).write_bytes(frame_png_bytes(frame))
                paths.append(folder / file)
            sidecar_path = folder / "frames.json"
            sidecar_path.write_text(to_json_text(frames_sidecar(files, times, camera, sequence_id=sequence_id,
                                                                spacecraft="SIM-TUBSAT")), encoding="utf-8")
            paths.append(sidecar_path)
        truth_path = outdir / f"{sequence_id}.truth.json"
        truth_path.write_text(to_json_text(truth), encoding="utf-8")
        paths.append(truth_path)
    return paths
