"""The star camera model: pixels <-> unit vectors in the camera frame.

Conventions (used everywhere in this project):

* pixel x = column to the right, y = row downward, (0, 0) is the centre of
  the top-left pixel;
* camera frame: +x along +column, +y along +row, +z along the boresight out
  of the camera (so x, y, z is right-handed);
* pinhole with optional radial distortion on the normalised coordinates::

      a = X/Z, b = Y/Z, r^2 = a^2 + b^2
      d = 1 + k1 r^2 + k2 r^4
      u = cx + f * a * d,  v = cy + f * b * d

A declared camera may also say how well it is known: the focal
length to a fraction ``focal_length_tolerance`` (default
:data:`DEFAULT_FOCAL_LENGTH_TOLERANCE` when not declared) and bounds on the
undeclared distortion, ``|k1| <= k1_bound``, ``|k2| <= k2_bound`` (None:
unknown).  These describe the *declaration*, not the optics: projection
ignores them.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

import numpy as np

from app.compiled import njit, warm_up_with

#: Focal length uncertainty (fraction) assumed when a camera declares none:
#: lab calibrations give ~1 %, thermal drift and lens replacements a few %.
DEFAULT_FOCAL_LENGTH_TOLERANCE = 0.05
#: Most Newton steps of the undistortion (it converges to rounding in 3-5 wherever the distortion
#: keeps the radius increasing, which any usable lens does across its sensor).
_UNDISTORT_STEPS = 8


@njit
def _pixels_to_vectors(xy, f, cx, cy, k1, k2):
    """:meth:`Camera.pixels_to_vectors`, one point at a time (a dozen numpy calls on a few points cost a
    search ~0.1 ms each time a pattern is seen through new optics).

    The distortion is radial: ``rho (1 + k1 rho^2 + k2 rho^4) = rho_d`` is solved for the undistorted
    radius by Newton's method (quadratic convergence: 3-5 steps to rounding where a fixed-point iteration
    needed 20, and never converged for strong distortion), then ``(a_d, b_d)`` scaled by ``rho / rho_d``.
    """
    out = np.empty((xy.shape[0], 3))
    for i in range(xy.shape[0]):
        a = (xy[i, 0] - cx) / f
        b = (xy[i, 1] - cy) / f
        if k1 != 0.0 or k2 != 0.0:
            rho_d = np.hypot(a, b)
            rho = rho_d
            for _ in range(_UNDISTORT_STEPS):
                r2 = rho * rho
                step = (rho * (1.0 + k1 * r2 + k2 * r2 * r2) - rho_d) / (1.0 + 3.0 * k1 * r2 + 5.0 * k2 * r2 * r2)
                rho -= step
                if not abs(step) > 1e-15 * rho:
                    break
            scale = rho / rho_d if rho_d > 0 else 1.0
            a, b = a * scale, b * scale
        norm = np.sqrt((a * a + b * b) + 1.0)
        out[i, 0], out[i, 1], out[i, 2] = a / norm, b / norm, 1.0 / norm
    return out


def fold_radius(k1: float, k2: float) -> float:
    """Normalised (pinhole) radius beyond which the distortion ``k1``, ``k2`` folds the image over (inf if never).

    The radial map ``r -> r (1 + k1 r^2 + k2 r^4)`` increases while its
    slope ``1 + 3 k1 r^2 + 5 k2 r^4`` is positive; past the first radius
    where the slope vanishes, directions further off axis land nearer
    the centre again (barrel distortion, ``k1 < 0``: at ``r^2 = -1 / (3
    k1)`` when ``k2 = 0``), and a star 60 deg off a 20 deg field's axis
    would land on its sensor.  The slope is a quadratic in ``u = r^2``:
    its smallest positive root.  A usable lens folds nowhere on its sensor
    (the telemetry's and the simulator's checks).
    """
    k1, k2 = float(k1), float(k2)
    if k2 == 0.0:
        return math.inf if k1 >= 0.0 else math.sqrt(-1.0 / (3.0 * k1))
    disc = 9.0 * k1 * k1 - 20.0 * k2
    if disc < 0.0:
        return math.inf  # the slope never vanishes (k2 > 0)
    roots = [u for u in ((-3.0 * k1 - sign * math.sqrt(disc)) / (10.0 * k2) for sign in (1.0, -1.0)) if u > 0.0]
    return math.sqrt(min(roots)) if roots else math.inf


@warm_up_with
def _warm_up_pixels() -> None:
    _pixels_to_vectors(np.zeros((1, 2)), 100.0, 1.0, 1.0, 0.1, 0.0)


@dataclass(frozen=True)
class Camera:
    """A pinhole star camera with optional radial distortion."""

    width: int
    height: int
    focal_length_px: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    name: str | None = None
    # Faintest magnitude (Hipparcos Hp) the sensor detects; None: derive one.
    mag_limit: float | None = None
    # How well the declaration is known (None: not declared).
    #: Largest plausible fractional error of ``focal_length_px`` (0.01: known to 1 %).
    focal_length_tolerance: float | None = None
    #: Bounds on the absolute values of the true k1, k2.
    k1_bound: float | None = None
    k2_bound: float | None = None
    #: The focal length is not known at all (a photograph with no optics given): ``focal_length_px`` is a
    #: nominal value for display, and identification searches the field of view from
    #: :data:`app.identification.scale_free.FOV_RANGE_DEG` (:mod:`app.identification.scale_free`).
    focal_length_unknown: bool = False

    # --- derived figures -------------------------------------------------
    @property
    def pixel_scale_rad(self) -> float:
        """Angle subtended by one pixel at the centre of the field."""
        return 1.0 / self.focal_length_px

    @property
    def pixel_scale_arcsec(self) -> float:
        return math.degrees(self.pixel_scale_rad) * 3600.0

    @property
    def fov_deg(self) -> tuple[float, float]:
        """Full horizontal and vertical field of view (pinhole, degrees)."""
        return (
            2 * math.degrees(math.atan(self.width / 2 / self.focal_length_px)),
            2 * math.degrees(math.atan(self.height / 2 / self.focal_length_px)),
        )

    @property
    def diagonal_fov_rad(self) -> float:
        """Largest angle between two points of the sensor."""
        corners = np.array([[-0.5, -0.5], [self.width - 0.5, self.height - 0.5],
                            [self.width - 0.5, -0.5], [-0.5, self.height - 0.5]])
        v = self.pixels_to_vectors(corners)
        return max(float(np.arccos(np.clip(v[0] @ v[1], -1, 1))),
                   float(np.arccos(np.clip(v[2] @ v[3], -1, 1))))

    @property
    def focal_tolerance(self) -> float:
        """The declared focal length tolerance, or :data:`DEFAULT_FOCAL_LENGTH_TOLERANCE`."""
        if self.focal_length_tolerance is None:
            return DEFAULT_FOCAL_LENGTH_TOLERANCE
        return float(self.focal_length_tolerance)

    @property
    def focal_length_rough(self) -> bool:
        """Whether the focal length is known only roughly: declared with a tolerance wider than a calibrated
        camera's (:data:`DEFAULT_FOCAL_LENGTH_TOLERANCE`), as a field of view given by hand or read from a file's
        header is (``app.frames.assemble.FOV_FOCAL_TOLERANCE``: 10 % and more)."""
        return not self.focal_length_unknown and self.focal_tolerance > DEFAULT_FOCAL_LENGTH_TOLERANCE

    @property
    def corner_radius(self) -> float:
        """Normalised (pinhole) radius of the sensor corner farthest from the principal point.

        The radius ``r`` of the distortion model at that corner: radial
        distortion displaces the corner by the fraction ``k1 r^2 + k2 r^4``
        of its distance from the principal point.
        """
        dx = max(self.cx + 0.5, self.width - 0.5 - self.cx)
        dy = max(self.cy + 0.5, self.height - 0.5 - self.cy)
        return math.hypot(dx, dy) / self.focal_length_px

    @property
    def limiting_magnitude(self) -> float:
        """The configured limit, or one derived from the field of view.

        A TUBSAT-class sensor reports the ~10 brightest sources, so the limit
        that matters is the magnitude at which a field this size holds a few
        dozen stars: 30 deg -> 4.5 (Liebe's imager), 20 deg -> 5.5,
        12 deg -> 6.5.  Linear in log(field area), clipped to the catalogue.
        """
        if self.mag_limit is not None:
            return float(self.mag_limit)
        fx, fy = self.fov_deg
        area = fx * fy
        # 30x31 deg ~ 930 deg^2 -> 4.5, 12x12 deg ~ 144 deg^2 -> 6.5
        limit = 4.5 + (math.log10(930.0) - math.log10(area)) * (2.0 / math.log10(930.0 / 144.0))
        return float(min(9.0, max(3.5, round(limit, 1))))

    def to_dict(self) -> dict:
        """The telemetry camera object: optional fields only when set (k1, k2 when non-zero)."""
        d = asdict(self)
        return {k: v for k, v in d.items() if v is not None and not (k in ("k1", "k2") and v == 0.0)
                and not (k == "focal_length_unknown" and not v)}

    def with_optics(self, focal_length_px: float | None = None, cx: float | None = None,
                    cy: float | None = None, k1: float | None = None, k2: float | None = None) -> Camera:
        """A copy with the given optical parameters changed (None: keep), everything else kept."""
        changes = {key: float(value) for key, value in
                   (("focal_length_px", focal_length_px), ("cx", cx), ("cy", cy), ("k1", k1), ("k2", k2))
                   if value is not None}
        return replace(self, **changes)

    def known_at(self, focal_length_px: float, tolerance: float) -> Camera:
        """This camera with a focal length now known to ``tolerance`` (a fraction): a camera whose focal
        length was unknown, once the stars have fixed one."""
        return replace(self, focal_length_px=float(focal_length_px), focal_length_tolerance=float(tolerance),
                       focal_length_unknown=False)

    def optics(self) -> dict:
        """The parameters that decide where a star lands: focal_length_px, cx, cy, k1, k2."""
        return {"focal_length_px": self.focal_length_px, "cx": self.cx, "cy": self.cy,
                "k1": self.k1, "k2": self.k2}

    # --- projection ------------------------------------------------------
    def _distort(self, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r2 = a * a + b * b
        d = 1.0 + self.k1 * r2 + self.k2 * r2 * r2
        return a * d, b * d

    def pixels_to_vectors(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) pixel coordinates -> (N, 3) unit vectors in the camera frame."""
        xy = np.ascontiguousarray(xy, dtype=float).reshape(-1, 2)
        return _pixels_to_vectors(xy, float(self.focal_length_px), float(self.cx), float(self.cy), float(self.k1),
                                  float(self.k2))

    @property
    def fold_radius(self) -> float:
        """Normalised radius beyond which this camera's distortion folds the image over (:func:`fold_radius`)."""
        return fold_radius(self.k1, self.k2)

    def vectors_to_pixels(self, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) camera-frame vectors -> ((N, 2) pixels, (N,) imaged mask).

        Points behind the camera (z <= 0), or beyond the :attr:`fold_radius`
        of a distorted camera (where the model would fold them back onto the
        sensor), get NaN pixels and False.
        """
        v = np.asarray(v, dtype=float).reshape(-1, 3)
        front = v[:, 2] > 1e-9
        fold = self.fold_radius
        if math.isfinite(fold):
            with np.errstate(invalid="ignore"):
                front &= v[:, 0] * v[:, 0] + v[:, 1] * v[:, 1] < (fold * v[:, 2]) ** 2
        z = np.where(front, v[:, 2], np.nan)
        a, b = self._distort(v[:, 0] / z, v[:, 1] / z)
        xy = np.column_stack([self.cx + self.focal_length_px * a,
                              self.cy + self.focal_length_px * b])
        return xy, front

    def on_sensor(self, xy: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """True for pixel positions inside the sensor (shrunk by ``margin``)."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        with np.errstate(invalid="ignore"):
            return ((xy[:, 0] >= -0.5 + margin) & (xy[:, 0] <= self.width - 0.5 - margin)
                    & (xy[:, 1] >= -0.5 + margin) & (xy[:, 1] <= self.height - 0.5 - margin))


def _camera_for_fov(name: str, width: int, height: int, hfov_deg: float, mag_limit: float) -> Camera:
    f = (width / 2) / math.tan(math.radians(hfov_deg / 2))
    return Camera(width=width, height=height, focal_length_px=round(f, 1),
                  cx=(width - 1) / 2, cy=(height - 1) / 2, name=name, mag_limit=mag_limit)


#: Named camera models; the first is the default camera used when a
#: telemetry file carries no camera block.
CAMERAS: dict[str, Camera] = {
    c.name: c
    for c in (
        _camera_for_fov("tubsat-752x582-20deg", 752, 582, 20.0, 5.5),
        _camera_for_fov("liebe-576x604-30deg", 576, 604, 30.0, 4.5),
        _camera_for_fov("narrow-1024x1024-12deg", 1024, 1024, 12.0, 6.5),
    )
}
DEFAULT_CAMERA_NAME = "tubsat-752x582-20deg"
