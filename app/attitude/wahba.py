"""The covariance of a Wahba (QUEST / q-method / SVD) attitude estimate.

Shuster's measurement model (as used by FUSE, seed 001): each measured
camera-frame unit vector is ``b_i = R r_i + noise`` with the noise isotropic
in the plane perpendicular to ``b_i``, 1-sigma ``s_i`` radians.  For the
optimal weights ``w_i = 1 / s_i^2`` the error of the estimate, written as a
small rotation ``dtheta`` in the camera frame (``R_true = exp([dtheta]x) R_est``),
has covariance::

    P = [ sum_i w_i (I - b_i b_i^T) ]^-1

Components 0 and 1 are the cross-boresight errors (about camera x and y),
component 2 the roll about the boresight.
"""

from __future__ import annotations

import numpy as np

from app.compiled import njit, warm_up_with


def wahba_covariance(body: np.ndarray, sigma_rad: np.ndarray) -> np.ndarray:
    """(3, 3) covariance (rad^2) of the attitude from vectors ``body`` (N, 3) with 1-sigma ``sigma_rad`` (N,).

    Needs at least two non-parallel vectors; with fewer the information
    matrix is singular and the result holds ``inf``.  Stacks work too:
    (..., N, 3) and (..., N) give (..., 3, 3); an infinite sigma leaves a
    vector out.
    """
    body = np.asarray(body, dtype=float)
    w = 1.0 / np.asarray(sigma_rad, dtype=float) ** 2
    if body.ndim == 1:
        body, w = body.reshape(-1, 3), w.reshape(-1)
    if body.ndim == 2:  # one attitude (a candidate asks for one at a time, six a search): compiled, 1 us not 23
        return _covariance_of_one(np.ascontiguousarray(body), np.ascontiguousarray(w))
    # A stack (a sequence fit's snapshots): one compiled inverse per attitude.
    body, w = np.broadcast_arrays(body, w[..., None])
    stack = np.array(body.reshape(-1, *body.shape[-2:]))  # writable copies: the one signature compiled
    weights = np.array(w[..., 0].reshape(-1, body.shape[-2]))
    cov = np.empty((len(stack), 3, 3))
    for k in range(len(stack)):
        cov[k] = _covariance_of_one(stack[k], weights[k])
    return cov.reshape(body.shape[:-2] + (3, 3))


def cross_boresight_and_roll_sigma(cov: np.ndarray) -> tuple[float, float]:
    """(per-axis cross-boresight 1-sigma, roll 1-sigma), radians, from a camera-frame covariance."""
    return float(np.sqrt((cov[0, 0] + cov[1, 1]) / 2)), float(np.sqrt(cov[2, 2]))


@njit
def _covariance_of_one(body: np.ndarray, w: np.ndarray) -> np.ndarray:
    """:func:`wahba_covariance` of one attitude: ``body`` (N, 3), weights ``w`` (N,) = 1 / sigma^2.

    The information matrix summed point by point, inverted by its adjugate
    (cheaper than a call of a general inverse on nine numbers); a singular
    one (fewer than two usable directions) gives ``inf``, not a huge number.
    """
    info = np.zeros((3, 3))
    total = 0.0
    for n in range(body.shape[0]):
        total += w[n]
        for i in range(3):
            for j in range(3):
                info[i, j] -= w[n] * body[n, i] * body[n, j]
    for i in range(3):
        info[i, i] += total
    a, b, c = info[0, 0], info[0, 1], info[0, 2]
    d, e, f = info[1, 0], info[1, 1], info[1, 2]
    g, h, k = info[2, 0], info[2, 1], info[2, 2]
    adjugate = np.empty((3, 3))
    adjugate[0, 0], adjugate[0, 1], adjugate[0, 2] = e * k - f * h, c * h - b * k, b * f - c * e
    adjugate[1, 0], adjugate[1, 1], adjugate[1, 2] = f * g - d * k, a * k - c * g, c * d - a * f
    adjugate[2, 0], adjugate[2, 1], adjugate[2, 2] = d * h - e * g, b * g - a * h, a * e - b * d
    det = a * adjugate[0, 0] + b * adjugate[1, 0] + c * adjugate[2, 0]
    cov = np.full((3, 3), np.inf)
    # A singular information matrix (fewer than two usable directions): inf, not a huge number.
    if not abs(det) > 1e-12 * abs(a + e + k) ** 3:
        return cov
    for i in range(3):
        for j in range(3):
            value = adjugate[i, j] / det
            if not np.isfinite(value) or (i == j and value < 0):
                return np.full((3, 3), np.inf)
            cov[i, j] = value
    return cov


@warm_up_with
def _warm_up_covariance() -> None:
    """Compile the one-attitude covariance for the arrays a candidate passes (contiguous float rows)."""
    wahba_covariance(np.array([[0.0, 0.0, 1.0], [0.1, 0.0, 0.995]]), np.array([1e-4, 1e-4]))
