"""Fit the camera's optics together with the attitude; calibrate one camera over many observations.

Real star cameras have a focal length known to ~1-5 % and radial distortion
nobody declared.  Given stars already identified -- measured pixels
``z_i`` matched to catalogue unit vectors ``s_i`` (ICRS) -- these functions
find the attitude and the optics that put the catalogue where the stars were
seen, with honest uncertainties.  Pure numpy over arrays; no I/O.

Model
-----
The camera model of :mod:`app.camera`.  With ``R`` the attitude (ICRS ->
camera) and ``v = R s`` the star in the camera frame::

    a = v_x / v_z,  b = v_y / v_z,  r^2 = a^2 + b^2
    d = 1 + k1 r^2 + k2 r^4
    h(v; c) = (cx + f a d,  cy + f b d)        c = (f, k1, k2, cx, cy), any subset fitted

The attitude is corrected on the left by a small rotation ``theta`` (radians,
about the camera axes)::

    R(theta) = exp([theta]x) R0,   v(theta) = v + theta x v + O(theta^2)

Residuals, weighted by the measurement noise sigma (pixels, isotropic,
Gaussian), two per star::

    e_i = (h(R s_i; c) - z_i) / sigma

and the minimised cost is ``chi2 = sum |e_i|^2 + sum_k ((c_k - mu_k) / s_k)^2``
(the second sum: optional Gaussian priors, see :func:`default_priors`).

Jacobians (analytic; ``d' = k1 + 2 k2 r^2``)::

    d(a, b)/d theta = [[-a b,      1 + a^2, -b],
                       [-(1 + b^2), a b,     a]]      (from d v / d theta = -[v]x)
    d h / d(a, b)  = f [[d + 2 a^2 d', 2 a b d'], [2 a b d', d + 2 b^2 d']]
    d h / d f  = d (a, b),   d h / d k1 = f r^2 (a, b),   d h / d k2 = f r^4 (a, b)
    d h / d cx = (1, 0),     d h / d cy = (0, 1)

Solution: Gauss-Newton on the normal equations ``N delta = -g`` (``N = J^T J``
plus the priors' precisions, ``g = J^T e`` plus the priors' gradient), with
step halving when a step does not lower chi2; the rotation is re-linearised
about the new estimate after each step.  Covariance: ``N^-1`` at the solution
(the linearised Cramer-Rao bound for Gaussian noise).

Many observations (:func:`calibrate`): one camera ``c`` shared by all, one
attitude ``theta_j`` per observation (a snapshot).  ``N`` is an arrow matrix:
``[[U, W], [W^T, V]]`` with ``V`` block diagonal (3x3 per observation).  The
attitudes are eliminated with the Schur complement, as the points are in
bundle adjustment (Triggs, McLauchlan, Hartley, Fitzgibbon, "Bundle
adjustment -- a modern synthesis", 2000, section 6.1; Hartley & Zisserman,
*Multiple View Geometry*, A6.3)::

    S = U - sum_j W_j V_j^-1 W_j^T,   S delta_c = -g_c + sum_j W_j V_j^-1 g_j
    delta_theta_j = -V_j^-1 (g_j + W_j^T delta_c)

and ``S^-1`` is the covariance of the camera with the attitudes marginalised.
Cost per iteration: linear in the number of stars (3200 observations of 8
stars: a few ms).

What the data determine (narrow fields)
---------------------------------------
* ``f`` scales the pattern about the principal point; no rotation does that,
  so it is determined by any 3 stars (1 sigma ~ sigma_px / separation).
* ``k1`` moves stars by ``f k1 r^3``, in the same direction as a change of
  ``f`` (``f r``), so the two separate only through the spread of radii in
  the field; ``k2`` (``f r^5``) is nearly collinear with both on a 20 deg
  field and is poorly determined even from thousands of stars.
* ``cx``, ``cy``: moving the principal point moves every star by the same
  pixels, which a rotation about the camera's y (x) axis also does, to first
  order in the field angle: such a rotation moves a star by ``f (1 + a^2)``
  along x and ``f a b`` along y per radian, so the two differ only by
  ``(a^2, a b)`` times the shift -- at most ``r^2 ~ 0.05`` of it on the 20 deg
  camera.  With a free attitude per snapshot the principal point is seen only
  through that second-order term: sigma ~ ``sigma_px / (0.012
  sqrt(n_stars))`` on the 20 deg camera.  From one snapshot of 8-10 stars
  that is 8-17 px (useless); from 50 sequences of 16 snapshots (~7400 stars)
  it is 0.3-0.4 px.  The term is even under ``(a, b) -> (-a, -b)`` while the
  focal length and k1 terms are odd, so fitting the principal point does not
  weaken them.

Measured with the simulator (:mod:`app.simulate`, true optics; 20 deg camera
752 x 582, focal length declared 3 % short of the truth, k1 = 0.20, i.e. ~1 %
of the field radius at the corner, 0.3 px noise plus integer pixels, ~9
stars per snapshot, matched by the simulator's truth, initial attitudes from
Wahba with the declared camera; RMS of error/sigma over 20 trials 0.9-1.2,
0.75-0.8 for the k2 fit from 200 sequences)::

    sequences  fitted            sigma f      sigma k1          sigma cx, cy
       20      f, k1, cx, cy     0.17 px      0.0032 (1.6 %)    0.5, 0.6 px
       50      f, k1, cx, cy     0.10 px      0.0020 (1.0 %)    0.3, 0.4 px
      200      f, k1, cx, cy     0.05 px      0.0010 (0.5 %)    0.15, 0.2 px
       50      + k2              0.20 px      0.0085 (4.2 %)    0.3, 0.4 px

(``k2`` is nearly collinear with ``k1`` and ``f`` over a 20 deg field: its
own sigma is ~0.19 from 50 sequences, and fitting it multiplies that of k1
by four.)

Related public work: tetra3/cedar-solve estimate the field of view per solve
(a scale only); astrometry.net's SIP polynomials fit distortion per image
with a WCS; the LOST star tracker asks for on-orbit focal length and
distortion estimation.  Nothing here is copied from them.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from app.attitude.rotations import matmul3, rodrigues, rotation_from_rotvec
from app.camera import Camera
from app.compiled import njit, warm_up_with

#: The optical parameters that can be fitted, in the order used in vectors
#: and covariances (names as in the telemetry camera object).
PARAMETERS = ("focal_length_px", "k1", "k2", "cx", "cy")
#: Short names accepted wherever parameter names are given.
ALIASES = {"f": "focal_length_px"}
ROTATION_NAMES = ("rot_x", "rot_y", "rot_z")

#: Stars needed before a parameter is fitted from one snapshot (see :func:`parameters_for`).
MIN_STARS_FOR_FOCAL_LENGTH = 3
MIN_STARS_FOR_K1 = 6
#: An observation takes part in a calibration only with this many inlier stars.
MIN_STARS_PER_OBSERVATION = 3
#: Median of the length of a 2-D standard normal vector (Rayleigh): sqrt(2 ln 2).
_RAYLEIGH_MEDIAN = math.sqrt(2.0 * math.log(2.0))
#: Gauss-Newton stops when a step would lower chi2 by less than this (the
#: parameters are then within ~sqrt(1e-6) = 0.001 sigma of the minimum).
_CHI2_TOLERANCE = 1e-6
_MAX_ITERATIONS = 50
#: Largest condition number (after equilibration) of a solvable system.
_MAX_CONDITION = 1e12


# --- names and priors --------------------------------------------------------

def parameter_names(names: Iterable[str]) -> tuple[str, ...]:
    """Canonical names (``"f"`` -> ``"focal_length_px"``) in :data:`PARAMETERS` order; ValueError if unknown."""
    wanted = set()
    for name in names:
        canonical = ALIASES.get(name, name)
        if canonical not in PARAMETERS:
            raise ValueError(f"unknown camera parameter {name!r}; choose from "
                             + ", ".join(("f",) + PARAMETERS))
        wanted.add(canonical)
    return tuple(p for p in PARAMETERS if p in wanted)


def parameters_for(n_stars: int) -> tuple[str, ...]:
    """Which optical parameters one snapshot of ``n_stars`` matched stars can afford to fit.

    * ``focal_length_px`` from 3 stars: 6 residuals for 3 rotation angles and
      the scale, and the scale is well separated from any rotation;
    * ``k1`` from 6 stars: it is strongly correlated with the focal length
      over a narrow field and separates only through the spread of radii;
      measured on the 20 deg camera at 0.3 px noise, sigma(k1) is ~0.21 with
      3 stars, ~0.10 with 4, ~0.07 with 6, ~0.05 with 8-10 (k1 = 0.20 moves
      the corner by 1 %).  Six stars leave 12 - 5 = 7 residual degrees of
      freedom to check the match with;
    * never ``cx``, ``cy`` or ``k2``: from one snapshot the principal point
      trades off against the attitude (sigma 8-17 px with 8-10 stars), and
      k2 against k1; they come from :func:`calibrate` over many snapshots.

    Fitting the focal length alone while the lens has undeclared distortion
    gives an *effective* focal length (k1 = 0.20 on the 20 deg camera biases
    it by ~0.4 %, ten times its sigma): good for matching, not a calibration.
    """
    if n_stars >= MIN_STARS_FOR_K1:
        return ("focal_length_px", "k1")
    if n_stars >= MIN_STARS_FOR_FOCAL_LENGTH:
        return ("focal_length_px",)
    return ()


def default_priors(camera: Camera, names: Iterable[str]) -> dict[str, tuple[float, float]]:
    """Weak Gaussian priors ``name -> (mean, sigma)`` from what the camera declares.

    * focal length: the declared value, sigma = ``camera.focal_tolerance``
      times it (the *bound* used as one sigma: weak on purpose; a few stars
      beat it at once, it only keeps a fit of 3-4 stars from wandering);
    * k1, k2: the declared value, sigma = ``k1_bound`` (``k2_bound``) when
      the camera declares one; no prior otherwise;
    * cx, cy: none.
    """
    priors: dict[str, tuple[float, float]] = {}
    for name in parameter_names(names):
        if name == "focal_length_px":
            priors[name] = (camera.focal_length_px, camera.focal_tolerance * camera.focal_length_px)
        elif name == "k1" and camera.k1_bound:
            priors[name] = (camera.k1, camera.k1_bound)
        elif name == "k2" and camera.k2_bound:
            priors[name] = (camera.k2, camera.k2_bound)
    return priors


def _prior_arrays(priors: Mapping[str, tuple[float, float]] | None, names: tuple[str, ...]
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(means, precisions 1/sigma^2) over ``names``; precision 0 where there is no prior."""
    mean = np.zeros(len(names))
    precision = np.zeros(len(names))
    for key, (mu, sigma) in (priors or {}).items():
        name = ALIASES.get(key, key)
        if name not in names:
            continue  # a prior on a parameter not fitted is irrelevant
        if not (math.isfinite(mu) and math.isfinite(sigma) and sigma > 0):
            raise ValueError(f"prior on {key}: need a finite mean and sigma > 0, got ({mu}, {sigma})")
        k = names.index(name)
        mean[k], precision[k] = mu, 1.0 / sigma ** 2
    return mean, precision


def _camera_vector(camera: Camera, names: tuple[str, ...]) -> np.ndarray:
    optics = camera.optics()
    return np.array([optics[n] for n in names], dtype=float)


def _with_vector(camera: Camera, names: tuple[str, ...], values: np.ndarray) -> Camera:
    return camera.with_optics(**{n: float(v) for n, v in zip(names, values)})


# --- projection and its Jacobians ----------------------------------------------

def project_with_jacobians(v_cam: np.ndarray, camera: Camera, names: tuple[str, ...]
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixels of camera-frame vectors and the Jacobians of the module docstring.

    Returns ``xy`` (n, 2), ``d xy / d theta`` (n, 2, 3) for a left rotation
    correction, and ``d xy / d c`` (n, 2, len(names)) for the named optical
    parameters.  Same projection as :meth:`Camera.vectors_to_pixels`; the
    vectors must be in front of the camera.
    """
    v = np.asarray(v_cam, dtype=float).reshape(-1, 3)
    a, b = v[:, 0] / v[:, 2], v[:, 1] / v[:, 2]
    r2 = a * a + b * b
    f, k1, k2 = camera.focal_length_px, camera.k1, camera.k2
    d = 1.0 + k1 * r2 + k2 * r2 * r2
    d_prime = k1 + 2.0 * k2 * r2  # d d / d (r^2)
    n = len(a)
    # The same elements as np.column_stack / np.stack would assemble, written in place (this runs once
    # per Gauss-Newton step of every candidate's optics fit).
    xy = np.empty((n, 2))
    xy[:, 0], xy[:, 1] = camera.cx + f * a * d, camera.cy + f * b * d

    # d(a, b)/d theta, then the chain through the distortion.
    ab_theta = np.empty((n, 2, 3))
    ab_theta[:, 0, 0], ab_theta[:, 0, 1], ab_theta[:, 0, 2] = -a * b, 1.0 + a * a, -b
    ab_theta[:, 1, 0], ab_theta[:, 1, 1], ab_theta[:, 1, 2] = -(1.0 + b * b), a * b, a
    h = np.empty((n, 2, 2))
    h[:, 0, 0], h[:, 0, 1] = d + 2 * a * a * d_prime, 2 * a * b * d_prime
    h[:, 1, 0], h[:, 1, 1] = 2 * a * b * d_prime, d + 2 * b * b * d_prime
    h_ab = f * h
    j_theta = h_ab @ ab_theta

    ones, zeros = np.ones_like(a), np.zeros_like(a)
    columns = {
        "focal_length_px": (a * d, b * d),
        "k1": (f * r2 * a, f * r2 * b),
        "k2": (f * r2 * r2 * a, f * r2 * r2 * b),
        "cx": (ones, zeros),
        "cy": (zeros, ones),
    }
    j_cam = np.zeros((len(a), 2, len(names)))
    for k, name in enumerate(names):
        j_cam[:, 0, k], j_cam[:, 1, k] = columns[name]
    return xy, j_theta, j_cam


def _rotate_left(rotations: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """``exp([theta_j]x) R_j`` for a stack of rotations (m, 3, 3) and rotation vectors (m, 3)."""
    return rotation_from_rotvec(theta) @ rotations  # scipy's Rotation, to rounding, at a fifth of the cost


def _solve_spd(matrix: np.ndarray, rhs: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray]:
    """Solve a symmetric positive definite system; also return its inverse.

    The matrix is equilibrated first (unit diagonal): focal length in pixels,
    k1 dimensionless and angles in radians differ by orders of magnitude.
    ValueError, naming ``what``, if the system is singular or nearly so.
    """
    if matrix.shape[0] == 0:
        return np.zeros(0), np.zeros((0, 0))
    scale = np.sqrt(np.diag(matrix))
    if not np.all(scale > 0):
        raise ValueError(f"{what}: a parameter has no influence on the residuals")
    unit = matrix / np.outer(scale, scale)
    singular = np.linalg.svd(unit, compute_uv=False)  # np.linalg.cond(unit), without its wrapper
    with np.errstate(divide="ignore", invalid="ignore"):
        condition = singular[0] / singular[-1]
    if condition > _MAX_CONDITION:
        raise ValueError(f"{what}: the parameters are not separately determined by these stars "
                         "(fit fewer parameters or add priors)")
    inverse_unit = np.linalg.inv(unit)
    inverse = inverse_unit / np.outer(scale, scale)
    return inverse @ rhs, inverse


# --- the shared Gauss-Newton over (camera, attitudes) --------------------------

@dataclass(frozen=True)
class Observation:
    """Matched stars of one snapshot (or of any set of stars seen with one attitude).

    ``sequence`` optionally names the sequence it comes from, so that a
    calibration can say how many sequences it used, and ``snapshot`` the
    snapshot's position in it.
    """

    xy: np.ndarray            # (n, 2) measured pixels
    star_vectors: np.ndarray  # (n, 3) ICRS unit vectors of the matched stars
    rotation: np.ndarray      # (3, 3) initial ICRS -> camera rotation
    sigma_px: float           # centroid noise, pixels
    sequence: str | None = None
    snapshot: int | None = None


@dataclass
class _Stars:
    """All stars of all observations, concatenated in observation order."""

    xy: np.ndarray          # (n, 2) measured pixels
    vectors: np.ndarray     # (n, 3) ICRS unit vectors
    owner: np.ndarray       # (n,) observation index, non-decreasing
    inv_sigma: np.ndarray   # (n,) 1 / sigma_px of the star's observation
    starts: np.ndarray      # (m,) first star of each observation

    @property
    def n_observations(self) -> int:
        return len(self.starts)


def _stars_from(observations: Sequence) -> tuple[_Stars, np.ndarray, list]:
    """Validated, concatenated stars; the initial rotations (m, 3, 3); the sequence labels."""
    xy_parts, vec_parts, owner, inv_sigma, rotations, labels = [], [], [], [], [], []
    for j, obs in enumerate(observations):
        obs = obs if isinstance(obs, Observation) else Observation(*obs)
        xy, vectors, rotation = _one_observation(obs.xy, obs.star_vectors, obs.rotation, obs.sigma_px, j)
        xy_parts.append(xy)
        vec_parts.append(vectors)
        owner.append(np.full(len(xy), j))
        inv_sigma.append(np.full(len(xy), 1.0 / obs.sigma_px))
        rotations.append(rotation)
        labels.append(obs.sequence)
    if not xy_parts:
        raise ValueError("no observations")
    owner_all = np.concatenate(owner)
    starts = np.flatnonzero(np.r_[True, owner_all[1:] != owner_all[:-1]])
    stars = _Stars(np.concatenate(xy_parts), np.concatenate(vec_parts), owner_all,
                   np.concatenate(inv_sigma), starts)
    return stars, np.array(rotations), labels


def _one_observation(xy, star_vectors, rotation, sigma_px, j: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Observation ``j``'s pixels, unit star vectors and rotation, checked (a ValueError says what is wrong
    with which observation).  A single snapshot's fit calls it alone: several times a solve, where the
    many-observation bookkeeping of :func:`_stars_from` cost twice the fit."""
    xy = np.ascontiguousarray(xy, dtype=float).reshape(-1, 2)
    vectors = np.asarray(star_vectors, dtype=float).reshape(-1, 3)
    if len(xy) != len(vectors):
        raise ValueError(f"observation {j}: {len(xy)} pixel positions but {len(vectors)} star vectors")
    if len(xy) == 0:
        raise ValueError(f"observation {j}: no stars")
    if not (math.isfinite(sigma_px) and sigma_px > 0):
        raise ValueError(f"observation {j}: sigma_px must be > 0, got {sigma_px!r}")
    if not (np.isfinite(xy).all() and np.isfinite(vectors).all()):
        raise ValueError(f"observation {j}: pixel positions and star vectors must be finite")
    vectors = vectors / np.sqrt((vectors * vectors).sum(axis=1))[:, None]
    return xy, vectors, np.ascontiguousarray(rotation, dtype=float).reshape(3, 3)


def _camera_frame(stars: _Stars, rotations: np.ndarray) -> np.ndarray:
    v = np.einsum("nij,nj->ni", rotations[stars.owner], stars.vectors)
    if np.any(v[:, 2] <= 1e-6):
        raise ValueError("a matched star is behind the camera (or 90 deg off the boresight) "
                         "with the given attitude")
    return v


def _normalised_residuals(stars: _Stars, rotations: np.ndarray, camera: Camera) -> np.ndarray:
    """(n, 2) residuals (model - measured) in units of sigma."""
    xy, _ = camera.vectors_to_pixels(_camera_frame(stars, rotations))
    return (xy - stars.xy) * stars.inv_sigma[:, None]


def _chi2(stars, rotations, camera, weight, names, prior_mean, prior_precision) -> float:
    e = _normalised_residuals(stars, rotations, camera)
    values = _camera_vector(camera, names)
    return float(np.sum(weight[:, None] * e * e) + np.sum(prior_precision * (values - prior_mean) ** 2))


@dataclass
class _Normal:
    """The normal equations (see the module docstring), one (3 + p) block per observation.

    ``blocks[j]`` is observation j's ``J_j^T J_j`` over (theta_j, camera) and
    ``gradients[j]`` its ``J_j^T e_j``; the arrow matrix's blocks are views
    of them, the priors added to the camera's.
    """

    blocks: np.ndarray      # (m, 3 + p, 3 + p)
    gradients: np.ndarray   # (m, 3 + p)
    prior_precision: np.ndarray  # (p,)
    prior_gradient: np.ndarray   # (p,)

    @property
    def V(self) -> np.ndarray:  # (m, 3, 3) attitude blocks
        return self.blocks[:, :3, :3]

    @property
    def W(self) -> np.ndarray:  # (m, p, 3) camera-attitude blocks
        return self.blocks[:, 3:, :3]

    @property
    def U(self) -> np.ndarray:  # (p, p) camera block, priors included
        return self.blocks[:, 3:, 3:].sum(axis=0) + np.diag(self.prior_precision)

    @property
    def g_t(self) -> np.ndarray:  # (m, 3) attitude gradients
        return self.gradients[:, :3]

    @property
    def g_c(self) -> np.ndarray:  # (p,) camera gradient, priors included
        return self.gradients[:, 3:].sum(axis=0) + self.prior_gradient


def _normal_equations(stars, rotations, camera, weight, names, prior_mean, prior_precision) -> _Normal:
    xy, j_theta, j_cam = project_with_jacobians(_camera_frame(stars, rotations), camera, names)
    e = (xy - stars.xy) * (stars.inv_sigma * weight)[:, None]
    # Weight 0 (rejected stars) or 1, folded into Jacobians and residuals as sqrt(w) = w.
    jacobian = np.concatenate([j_theta, j_cam], axis=2) * (weight * stars.inv_sigma)[:, None, None]
    blocks = np.einsum("nki,nkj->nij", jacobian, jacobian)
    gradients = np.einsum("nki,nk->ni", jacobian, e)
    if stars.n_observations > 1:
        blocks = np.add.reduceat(blocks, stars.starts, axis=0)
        gradients = np.add.reduceat(gradients, stars.starts, axis=0)
    else:
        blocks, gradients = blocks.sum(axis=0, keepdims=True), gradients.sum(axis=0, keepdims=True)
    values = _camera_vector(camera, names)
    return _Normal(blocks, gradients, prior_precision, prior_precision * (values - prior_mean))


def _attitude_inverses(V: np.ndarray, active: np.ndarray) -> np.ndarray:
    """(Pseudo-)inverses of the 3x3 attitude blocks; zero for observations not taking part.

    The pseudo-inverse leaves alone a rotation the stars cannot see (all on
    one line through the boresight: the roll about it); such a direction
    does not couple to the camera either, so the camera's system is unharmed.
    """
    blocks = np.where(active[:, None, None], V, np.eye(3))
    # np.linalg.pinv(blocks, rcond=1e-12, hermitian=True), step by step: the same numbers without the
    # wrappers' checks, which cost more than the 3x3 decompositions.  Its svd(hermitian=True) is eigh
    # with the eigenvalues' magnitudes sorted descending and their signs moved into vt; the same here,
    # with fancy indexing for take_along_axis (bit for bit: checked on thousands of random blocks).
    w, u = np.linalg.eigh(blocks)
    rows = np.arange(len(w))[:, None]
    order = np.argsort(np.abs(w), axis=-1)[:, ::-1]
    s = np.abs(w)[rows, order]
    sign = np.copysign(1.0, w)[rows, order]
    u = u[rows[:, :, None], np.arange(3)[None, :, None], order[:, None, :]]
    vt = np.swapaxes(u * sign[..., None, :], -1, -2).conjugate()
    large = s > 1e-12 * np.amax(s, axis=-1, keepdims=True)
    s = np.divide(1, s, where=large, out=s)
    s[~large] = 0
    inverse = np.matmul(np.swapaxes(vt, -1, -2), np.multiply(s[..., None], np.swapaxes(u, -1, -2)))
    return np.where(active[:, None, None], inverse, 0.0)


def _reduced_camera_system(normal: _Normal, active: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(S, rhs, V^-1): the camera's system with the attitudes eliminated (Schur complement)."""
    v_inv = _attitude_inverses(normal.V, active)
    w_v_inv = np.einsum("mpi,mij->mpj", normal.W, v_inv)
    S = normal.U - np.einsum("mpj,mqj->pq", w_v_inv, normal.W)
    rhs = -normal.g_c + np.einsum("mpj,mj->p", w_v_inv, normal.g_t)
    return S, rhs, v_inv


def _newton_step(normal: _Normal, active: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The Gauss-Newton step (delta_c (p,), delta_theta (m, 3)): ``N delta = -g``, the attitudes eliminated
    (:func:`_reduced_camera_system`).  (One snapshot's fit is the compiled :func:`_fit_one_kernel`.)"""
    S, rhs, v_inv = _reduced_camera_system(normal, active)
    delta_c, _ = _solve_spd(S, rhs, "camera fit")
    return delta_c, -np.einsum("mij,mj->mi", v_inv, normal.g_t + np.einsum("mpi,p->mi", normal.W, delta_c))


@dataclass
class _Solution:
    camera: Camera
    rotations: np.ndarray       # (m, 3, 3)
    camera_covariance: np.ndarray
    normal: _Normal
    chi2: float
    iterations: int


def _gauss_newton(stars: _Stars, rotations: np.ndarray, camera: Camera, names: tuple[str, ...],
                  weight: np.ndarray, active: np.ndarray,
                  priors: Mapping[str, tuple[float, float]] | None) -> _Solution:
    """Minimise chi2 over the named optical parameters and one small rotation per active observation."""
    prior_mean, prior_precision = _prior_arrays(priors, names)
    chi2 = _chi2(stars, rotations, camera, weight, names, prior_mean, prior_precision)
    for iteration in range(1, _MAX_ITERATIONS + 1):
        normal = _normal_equations(stars, rotations, camera, weight, names, prior_mean, prior_precision)
        delta_c, delta_t = _newton_step(normal, active)
        # chi2(delta) ~ chi2 + 2 g.delta + delta.N.delta, so the Gauss-Newton step
        # delta = -N^-1 g should lower chi2 by -g.delta.
        predicted = -(normal.g_c @ delta_c + np.sum(normal.g_t * delta_t))
        step = 1.0
        values = _camera_vector(camera, names)
        for _halving in range(12):
            trial_camera = _with_vector(camera, names, values + step * delta_c)
            trial_rotations = _rotate_left(rotations, step * delta_t)
            try:
                trial_chi2 = _chi2(stars, trial_rotations, trial_camera, weight, names,
                                   prior_mean, prior_precision)
            except ValueError:  # a star behind the camera: far too long a step
                trial_chi2 = math.inf
            if trial_chi2 <= chi2 + 1e-12 * max(1.0, chi2):
                break
            step *= 0.5
        else:
            break  # no step lowers chi2: at the minimum to numerical precision
        camera, rotations = trial_camera, trial_rotations
        chi2 = trial_chi2
        if predicted < _CHI2_TOLERANCE:
            break
    normal = _normal_equations(stars, rotations, camera, weight, names, prior_mean, prior_precision)
    S, _, _ = _reduced_camera_system(normal, active)
    _, covariance = _solve_spd(S, np.zeros(len(names)), "camera fit")
    return _Solution(camera, rotations, covariance, normal, chi2, iteration)


def _residual_lengths_px(stars: _Stars, rotations: np.ndarray, camera: Camera) -> np.ndarray:
    xy, _ = camera.vectors_to_pixels(_camera_frame(stars, rotations))
    return np.linalg.norm(xy - stars.xy, axis=1)


def _rms(lengths: np.ndarray, mask: np.ndarray) -> float:
    return float(np.sqrt(np.mean(lengths[mask] ** 2))) if np.any(mask) else math.nan


# --- one snapshot: the compiled Gauss-Newton ---------------------------------------

#: Where each optical parameter sits in the kernel's optics vector (f, k1, k2, cx, cy) = PARAMETERS' order.
_OPTICS_INDEX = {name: k for k, name in enumerate(PARAMETERS)}
#: Why the kernel stopped (0: converged); the messages of the ValueErrors they become.
_FIT_FAILURES = {
    1: "a matched star is behind the camera (or 90 deg off the boresight) with the given attitude",
    2: "{what}: a parameter has no influence on the residuals",
    3: "{what}: the parameters are not separately determined by these stars (fit fewer parameters or add priors)",
}


@njit
def _star_in_camera(R, vectors, i):
    """(a, b, v_z) of star ``i``: ``v = R s``, its gnomonic coordinates ``v_x / v_z``, ``v_y / v_z`` (module
    docstring) and its depth (at most 0: behind the camera)."""
    vx = R[0, 0] * vectors[i, 0] + R[0, 1] * vectors[i, 1] + R[0, 2] * vectors[i, 2]
    vy = R[1, 0] * vectors[i, 0] + R[1, 1] * vectors[i, 1] + R[1, 2] * vectors[i, 2]
    vz = R[2, 0] * vectors[i, 0] + R[2, 1] * vectors[i, 1] + R[2, 2] * vectors[i, 2]
    return vx / vz, vy / vz, vz


@njit
def _fit_chi2(xy, vectors, inv_sigma, R, optics, fitted, prior_mean, prior_precision):
    """chi2 of one snapshot (data and priors), inf when a star is behind the camera (:func:`_chi2`)."""
    f, k1, k2, cx, cy = optics[0], optics[1], optics[2], optics[3], optics[4]
    total = 0.0
    for i in range(xy.shape[0]):
        a, b, vz = _star_in_camera(R, vectors, i)
        if vz <= 1e-6:
            return np.inf
        r2 = a * a + b * b
        d = 1.0 + k1 * r2 + k2 * r2 * r2
        ex = (cx + f * (a * d) - xy[i, 0]) * inv_sigma
        ey = (cy + f * (b * d) - xy[i, 1]) * inv_sigma
        total += ex * ex + ey * ey
    for k in range(fitted.shape[0]):
        off = optics[fitted[k]] - prior_mean[k]
        total += prior_precision[k] * off * off
    return total


@njit
def _fit_normal(xy, vectors, inv_sigma, R, optics, fitted, prior_mean, prior_precision):
    """The (3 + p) normal equations of one snapshot, priors included: (N, g) of the module docstring."""
    f, k1, k2, cx, cy = optics[0], optics[1], optics[2], optics[3], optics[4]
    q = 3 + fitted.shape[0]
    N = np.zeros((q, q))
    g = np.zeros(q)
    J = np.empty((2, q))
    for i in range(xy.shape[0]):
        a, b, _ = _star_in_camera(R, vectors, i)
        r2 = a * a + b * b
        d = 1.0 + k1 * r2 + k2 * r2 * r2
        dp = k1 + 2.0 * k2 * r2
        e0 = (cx + f * a * d - xy[i, 0]) * inv_sigma
        e1 = (cy + f * b * d - xy[i, 1]) * inv_sigma
        h00, h01 = f * (d + 2 * a * a * dp), f * (2 * a * b * dp)
        h10, h11 = f * (2 * a * b * dp), f * (d + 2 * b * b * dp)
        t00, t01, t02 = -a * b, 1.0 + a * a, -b
        t10, t11, t12 = -(1.0 + b * b), a * b, a
        J[0, 0], J[0, 1], J[0, 2] = h00 * t00 + h01 * t10, h00 * t01 + h01 * t11, h00 * t02 + h01 * t12
        J[1, 0], J[1, 1], J[1, 2] = h10 * t00 + h11 * t10, h10 * t01 + h11 * t11, h10 * t02 + h11 * t12
        for k in range(fitted.shape[0]):
            p = fitted[k]
            if p == 0:
                J[0, 3 + k], J[1, 3 + k] = a * d, b * d
            elif p == 1:
                J[0, 3 + k], J[1, 3 + k] = f * r2 * a, f * r2 * b
            elif p == 2:
                J[0, 3 + k], J[1, 3 + k] = f * r2 * r2 * a, f * r2 * r2 * b
            elif p == 3:
                J[0, 3 + k], J[1, 3 + k] = 1.0, 0.0
            else:
                J[0, 3 + k], J[1, 3 + k] = 0.0, 1.0
        for r in range(q):
            J[0, r] *= inv_sigma
            J[1, r] *= inv_sigma
        for r in range(q):
            g[r] += J[0, r] * e0 + J[1, r] * e1
            for c in range(q):
                N[r, c] += J[0, r] * J[0, c] + J[1, r] * J[1, c]
    for k in range(fitted.shape[0]):
        N[3 + k, 3 + k] += prior_precision[k]
        g[3 + k] += prior_precision[k] * (optics[fitted[k]] - prior_mean[k])
    return N, g


@njit
def _fit_inverse(N):
    """(status, N^-1) as :func:`_solve_spd`: equilibrated, refused beyond :data:`_MAX_CONDITION` (status 3) or
    with a parameter of no influence (status 2)."""
    q = N.shape[0]
    scale = np.empty(q)
    for r in range(q):
        if not N[r, r] > 0:
            return 2, N
        scale[r] = np.sqrt(N[r, r])
    unit = np.empty((q, q))
    for r in range(q):
        for c in range(q):
            unit[r, c] = N[r, c] / (scale[r] * scale[c])
    singular = np.linalg.svd(unit)[1]
    if not singular[0] / singular[q - 1] <= _MAX_CONDITION:
        return 3, N
    inverse = np.linalg.inv(unit)
    for r in range(q):
        for c in range(q):
            inverse[r, c] /= scale[r] * scale[c]
    return 0, inverse


@njit
def _rotate_left_one(theta0, theta1, theta2, R):
    """``exp([theta]x) R`` (Rodrigues, :func:`app.attitude.rotations.rodrigues`)."""
    return matmul3(rodrigues(theta0, theta1, theta2), R)


@njit
def _fit_one_kernel(xy, vectors, inv_sigma, R0, optics0, fitted, prior_mean, prior_precision):
    """Gauss-Newton over one snapshot's attitude and the ``fitted`` optics (indices into (f, k1, k2, cx, cy)).

    The steps of the module docstring with step halving, stopping when a
    step would lower chi2 by less than :data:`_CHI2_TOLERANCE`.  Returns
    (status (0 or a key of :data:`_FIT_FAILURES`), at which stage (0 the
    start, 1 a step, 2 the covariance), rotation, optics, chi2, iterations,
    covariance (3 + p) over (theta, fitted optics), rms of the residuals in
    pixels).
    """
    R = R0.copy()
    optics = optics0.copy()
    p = fitted.shape[0]
    empty = np.zeros((3 + p, 3 + p))
    chi2 = _fit_chi2(xy, vectors, inv_sigma, R, optics, fitted, prior_mean, prior_precision)
    if chi2 == np.inf:
        return 1, 0, R, optics, chi2, 0, empty, np.nan
    iteration = 0
    for iteration in range(1, _MAX_ITERATIONS + 1):
        N, g = _fit_normal(xy, vectors, inv_sigma, R, optics, fitted, prior_mean, prior_precision)
        status, inverse = _fit_inverse(N)
        if status:
            return status, 1, R, optics, chi2, iteration, empty, np.nan
        delta = np.zeros(3 + p)
        predicted = 0.0
        for r in range(3 + p):
            for c in range(3 + p):
                delta[r] -= inverse[r, c] * g[c]
        for r in range(3 + p):
            predicted -= g[r] * delta[r]
        step = 1.0
        accepted = False
        trial_optics = optics.copy()
        trial_R = R
        trial_chi2 = chi2
        for _halving in range(12):
            for k in range(p):
                trial_optics[fitted[k]] = optics[fitted[k]] + step * delta[3 + k]
            trial_R = _rotate_left_one(step * delta[0], step * delta[1], step * delta[2], R)
            trial_chi2 = _fit_chi2(xy, vectors, inv_sigma, trial_R, trial_optics, fitted, prior_mean,
                                   prior_precision)
            if trial_chi2 <= chi2 + 1e-12 * max(1.0, chi2):
                accepted = True
                break
            step *= 0.5
        if not accepted:
            break  # no step lowers chi2: at the minimum to numerical precision
        R, optics, chi2 = trial_R, trial_optics, trial_chi2
        if predicted < _CHI2_TOLERANCE:
            break
    N, g = _fit_normal(xy, vectors, inv_sigma, R, optics, fitted, prior_mean, prior_precision)
    status, covariance = _fit_inverse(N)
    if status:
        return status, 2, R, optics, chi2, iteration, empty, np.nan
    total = 0.0
    for i in range(xy.shape[0]):
        a, b, _ = _star_in_camera(R, vectors, i)
        r2 = a * a + b * b
        d = 1.0 + optics[1] * r2 + optics[2] * r2 * r2
        dx, dy = optics[3] + optics[0] * (a * d) - xy[i, 0], optics[4] + optics[0] * (b * d) - xy[i, 1]
        total += dx * dx + dy * dy
    return 0, 0, R, optics, chi2, iteration, covariance, np.sqrt(total / xy.shape[0])


# --- one snapshot: attitude and camera -------------------------------------------

@dataclass(frozen=True)
class CameraAttitudeFit:
    """The result of :func:`fit_attitude_and_camera`.

    ``covariance`` is over ``covariance_names``: the small rotation
    ``rot_x, rot_y, rot_z`` (radians, about the camera axes, applied on the
    left of ``rotation``) then the fitted optical parameters.
    """

    rotation: np.ndarray
    camera: Camera
    parameters: tuple[str, ...]
    sigma: dict[str, float]
    rotation_sigma_rad: np.ndarray
    covariance: np.ndarray
    covariance_names: tuple[str, ...]
    rms_px: float          # root mean square of the residual vectors' lengths
    chi2: float            # data and priors
    dof: int               # 2 n_stars + n_priors - 3 - n_parameters
    n_stars: int
    priors: dict[str, tuple[float, float]] = field(default_factory=dict)

    def to_dict(self) -> dict:
        """The candidate's ``camera_fit``: fitted values, their 1-sigma, ``rms_px``."""
        optics = self.camera.optics()
        out = {name: optics[name] for name in self.parameters}
        out["sigma"] = dict(self.sigma)
        out["rms_px"] = self.rms_px
        return out


def fit_attitude_and_camera(xy: np.ndarray, star_vectors: np.ndarray, rotation0: np.ndarray,
                            camera: Camera, sigma_px: float, *, fit: Iterable[str] | None = None,
                            priors: Mapping[str, tuple[float, float]] | None = None) -> CameraAttitudeFit:
    """Attitude and optics of one snapshot from its matched stars (least squares in pixels).

    ``xy`` (n, 2) measured pixels, ``star_vectors`` (n, 3) their ICRS unit
    vectors (apparent places), ``rotation0`` (3, 3) an initial ICRS -> camera
    rotation (e.g. Wahba's with the declared camera), ``camera`` the
    declared camera (start values and the parameters not fitted),
    ``sigma_px`` the centroid noise.  ``fit``: the optical parameters to
    fit (``"f"`` or ``"focal_length_px"``, ``"k1"``, ``"k2"``, ``"cx"``,
    ``"cy"``); None: :func:`parameters_for` the number of stars.
    ``priors``: ``name -> (mean, sigma)``; None: :func:`default_priors`
    (the declared focal length within its tolerance, k1/k2 within their
    bounds), ``{}``: none.  No outlier rejection here: the matches are
    taken as given.

    Raises ValueError for inconsistent shapes, fewer residuals than
    unknowns, or parameters the stars cannot separate.
    """
    names = parameter_names(parameters_for(len(np.atleast_2d(xy))) if fit is None else fit)
    priors = default_priors(camera, names) if priors is None else dict(priors)
    xy, vectors, rotation0 = _one_observation(xy, star_vectors, rotation0, sigma_px)
    n = len(xy)
    n_priors = sum(1 for key in priors if ALIASES.get(key, key) in names)
    dof = 2 * n + n_priors - 3 - len(names)
    if 2 * n < 3 + len(names) - n_priors or n < 2:
        raise ValueError(f"{n} stars cannot fix the attitude and {len(names)} optical parameter(s)")
    prior_mean, prior_precision = _prior_arrays(priors, names)
    optics = camera.optics()
    status, stage, rotation, values, chi2, _, covariance, rms_px = _fit_one_kernel(
        xy, vectors, 1.0 / float(sigma_px), rotation0,
        np.array([optics[name] for name in PARAMETERS]), np.array([_OPTICS_INDEX[name] for name in names]),
        prior_mean, prior_precision)
    if status:
        raise ValueError(_FIT_FAILURES[status].format(what="attitude and camera fit" if stage == 2 else "camera fit"))
    sig = np.sqrt(np.diag(covariance))
    return CameraAttitudeFit(
        rotation=rotation, camera=camera.with_optics(**{name: values[_OPTICS_INDEX[name]] for name in names}),
        parameters=names, sigma={name: float(s) for name, s in zip(names, sig[3:])}, rotation_sigma_rad=sig[:3],
        covariance=covariance, covariance_names=ROTATION_NAMES + names,
        rms_px=float(rms_px), chi2=float(chi2), dof=dof, n_stars=n, priors=priors)


@warm_up_with
def _warm_up_fit() -> None:
    """Compile :func:`_fit_one_kernel` for the types every optics fit passes."""
    camera = Camera(width=100, height=100, focal_length_px=500.0, cx=49.5, cy=49.5)
    vectors = np.array([[0.01, 0.02, 1.0], [-0.03, 0.01, 1.0], [0.02, -0.04, 1.0], [-0.01, -0.02, 1.0]])
    vectors /= np.linalg.norm(vectors, axis=1, keepdims=True)
    xy, _ = camera.with_optics(focal_length_px=505.0).vectors_to_pixels(vectors)
    fit_attitude_and_camera(xy, vectors, np.eye(3), camera, 0.3, fit=("f",))


# --- many observations: calibration ----------------------------------------------

@dataclass(frozen=True)
class Calibration:
    """The result of :func:`calibrate`.

    ``covariance`` is over ``parameters`` (attitudes marginalised), already
    multiplied by ``chi2_reduced`` when that exceeds 1.  ``rotations`` and
    ``inliers`` follow the input observations (a rotation is None for an
    observation that took no part).
    """

    camera: Camera
    parameters: tuple[str, ...]
    sigma: dict[str, float]
    covariance: np.ndarray
    observations_used: int
    sequences_used: int
    stars_used: int
    stars_rejected: int
    rms_px_before: float
    rms_px_after: float
    chi2_reduced: float
    rotations: list
    inliers: list
    rounds: int            # fits made (outlier rejection rounds)
    #: The attitudes refitted for ``camera0`` alone (what ``rms_px_before`` is measured with).
    rotations_before: list = field(default_factory=list)

    def to_dict(self) -> dict:
        """The calibration's JSON: camera, sigma, counts, rms before and after."""
        return {
            "camera": self.camera.to_dict(),
            "sigma": dict(self.sigma),
            "parameters": list(self.parameters),
            "covariance": self.covariance.tolist(),
            "sequences_used": self.sequences_used,
            "observations_used": self.observations_used,
            "stars_used": self.stars_used,
            "stars_rejected": self.stars_rejected,
            "rms_px_before": self.rms_px_before,
            "rms_px_after": self.rms_px_after,
            "chi2_reduced": self.chi2_reduced,
        }


def robust_scale(lengths: np.ndarray) -> float:
    """Robust sigma of 2-D residuals from their lengths: median / sqrt(2 ln 2) (Rayleigh).

    Unaffected by up to half of the stars being outliers.
    """
    return float(np.median(lengths) / _RAYLEIGH_MEDIAN)


def _inlier_mask(lengths_sigma: np.ndarray, stars: _Stars, weight: np.ndarray, active: np.ndarray,
                 reject_sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """(star mask, observation mask) after one round of rejection.

    The threshold is ``reject_sigma`` robust sigmas (scale from every star of
    the observations taking part).  A star below it is (re)admitted.  Above
    it, only the *worst* star of each observation is rejected per round: one
    wrong match pulls its snapshot's attitude and so smears residuals over
    the good stars of that snapshot, which come back once it is out.  An
    observation left with fewer than 3 inliers leaves the fit for good.
    """
    in_active = active[stars.owner]
    threshold = reject_sigma * robust_scale(lengths_sigma[in_active])
    included = weight > 0
    masked = np.where(included, lengths_sigma, -np.inf)
    worst = np.maximum.reduceat(masked, stars.starts)[stars.owner]
    is_worst = included & (masked >= worst)
    keep = in_active & ((lengths_sigma <= threshold) | (included & ~is_worst))
    counts = np.bincount(stars.owner[keep], minlength=stars.n_observations)
    active = active & (counts >= MIN_STARS_PER_OBSERVATION)
    return keep & active[stars.owner], active


def calibrate(observations: Sequence, camera0: Camera, *,
              parameters: Iterable[str] = ("f", "cx", "cy", "k1", "k2"),
              reject_sigma: float | None = 5.0,
              priors: Mapping[str, tuple[float, float]] | None = None,
              max_rounds: int = 20) -> Calibration:
    """One camera fitted over many observations, each with its own attitude.

    ``observations``: :class:`Observation` or tuples ``(xy (n, 2),
    star_vectors (n, 3), rotation (3, 3), sigma_px[, sequence])`` -- the
    matched stars of a snapshot, an initial attitude (from identification)
    and the centroid noise.  ``camera0``: the declared camera (start values;
    the parameters not fitted are kept).  ``parameters``: what to fit.
    ``priors``: ``name -> (mean, sigma)``, none by default (the data
    dominate).

    The joint least-squares problem (module docstring) is solved by
    Gauss-Newton with the attitudes eliminated (Schur complement).  Outliers
    (mismatched stars, blends, ghosts that slipped through): after each fit,
    the worst star of each observation is left out if its residual exceeds
    ``reject_sigma`` robust sigmas, stars back below it are readmitted, and
    the fit repeated until the set of inliers settles (at most ``max_rounds``
    fits); None: no rejection.  Observations with fewer than 3 inliers are
    dropped.

    Uncertainties: the camera block of the inverse normal matrix with the
    attitudes marginalised, multiplied by the reduced chi-square when that
    exceeds 1 (noise larger than the stated ``sigma_px``, integer pixel
    rounding, unmodelled effects), so the sigmas stay honest.

    ``rms_px_before``: the inliers' rms residual (length of the 2-D residual)
    with ``camera0`` and the attitudes refitted for it; ``rms_px_after``:
    with the fitted camera.

    Accuracy (module docstring, "Measured"): from 50 sequences of the 20 deg
    camera, focal length to ~0.005 % (0.1 px), k1 to ~1 % (4 % when k2 is
    fitted too), principal point to 0.3-0.4 px.  On a field this narrow k2
    is barely determined; ``parameters=("f", "k1", "cx", "cy")`` is the
    better choice unless the lens is known to need k2.  Run time: ~0.35 s
    for 200 sequences x 16 snapshots x ~9 stars.
    """
    names = parameter_names(parameters)
    if reject_sigma is not None and not reject_sigma > 0:
        raise ValueError(f"reject_sigma must be > 0 or None, got {reject_sigma!r}")
    stars, rotations, labels = _stars_from(observations)
    counts = np.bincount(stars.owner, minlength=stars.n_observations)
    active = counts >= MIN_STARS_PER_OBSERVATION
    if not np.any(active):
        raise ValueError(f"no observation has {MIN_STARS_PER_OBSERVATION} or more stars")
    weight = active[stars.owner].astype(float)

    solution = _gauss_newton(stars, rotations, camera0, names, weight, active, priors)
    rounds = 1
    for _round in range(max_rounds - 1 if reject_sigma is not None else 0):
        lengths_sigma = np.linalg.norm(
            _normalised_residuals(stars, solution.rotations, solution.camera), axis=1)
        keep, new_active = _inlier_mask(lengths_sigma, stars, weight, active, reject_sigma)
        if np.array_equal(keep, weight > 0) and np.array_equal(new_active, active):
            break  # the inliers have settled
        if not np.any(new_active):
            raise ValueError(f"outlier rejection left no observation with {MIN_STARS_PER_OBSERVATION} "
                             "or more stars")
        weight, active = keep.astype(float), new_active
        solution = _gauss_newton(stars, solution.rotations, solution.camera, names, weight, active, priors)
        rounds += 1

    inliers = weight > 0
    n_used = int(inliers.sum())
    prior_count = sum(1 for key in (priors or {}) if ALIASES.get(key, key) in names)
    dof = 2 * n_used + prior_count - 3 * int(active.sum()) - len(names)
    chi2_reduced = solution.chi2 / dof if dof > 0 else math.nan
    covariance = solution.camera_covariance * (chi2_reduced if chi2_reduced > 1 else 1.0)

    # The declared camera's rms, each attitude refitted for it: fitting only attitudes.
    before = _gauss_newton(stars, solution.rotations, camera0, (), weight, active, None)
    rms_before = _rms(_residual_lengths_px(stars, before.rotations, camera0), inliers)
    rms_after = _rms(_residual_lengths_px(stars, solution.rotations, solution.camera), inliers)

    used_labels = {labels[j] for j in np.flatnonzero(active)}
    sequences_used = (len(used_labels) if all(labels[j] is not None for j in np.flatnonzero(active))
                      else int(active.sum()))
    return Calibration(
        camera=solution.camera, parameters=names,
        sigma={n: float(s) for n, s in zip(names, np.sqrt(np.diag(covariance)))},
        covariance=covariance, observations_used=int(active.sum()), sequences_used=sequences_used,
        stars_used=n_used, stars_rejected=int(len(inliers) - n_used),
        rms_px_before=rms_before, rms_px_after=rms_after, chi2_reduced=float(chi2_reduced),
        rotations=[solution.rotations[j] if active[j] else None for j in range(stars.n_observations)],
        inliers=np.split(inliers, stars.starts[1:]), rounds=rounds,
        rotations_before=[before.rotations[j] if active[j] else None for j in range(stars.n_observations)])


def residual_vectors(observation: Observation, rotation: np.ndarray, camera: Camera) -> np.ndarray:
    """(n, 2) measured minus predicted pixels of an observation's stars at ``rotation`` through ``camera``."""
    predicted, _ = camera.vectors_to_pixels(np.asarray(observation.star_vectors) @ np.asarray(rotation).T)
    return np.asarray(observation.xy, dtype=float) - predicted
