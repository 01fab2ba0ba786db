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

Imperfect optics (issue 11)
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
    r2 = np.linspace(0.0, r_corner, 101) ** 2
    slope = 1.0 + 3.0 * camera.k1 * r2 + 5.0 * camera.k2 * r2 * r2  # d/dr of r (1 + k1 r^2 + k2 r^4)
    if np.any(slope <= 0.0):
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
