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
    if body.ndim == 2:  # one attitude (a candidate asks for one at a time): a product, not an einsum's parse
        return _inverse_3x3((w.sum() * np.eye(3) - (body.T * w) @ body).tolist())
    info = w.sum(axis=-1)[..., None, None] * np.eye(3) - np.einsum("...n,...ni,...nj->...ij", w, body, body)
    # The inverse by cofactors, stack-wide (numpy's inverse raises for the whole stack on one
    # singular matrix; a 3x3 adjugate is also cheaper than its call overhead).
    a, b, c = info[..., 0, 0], info[..., 0, 1], info[..., 0, 2]
    d, e, f = info[..., 1, 0], info[..., 1, 1], info[..., 1, 2]
    g, h, i = info[..., 2, 0], info[..., 2, 1], info[..., 2, 2]
    adjugate = np.stack([e * i - f * h, c * h - b * i, b * f - c * e,
                         f * g - d * i, a * i - c * g, c * d - a * f,
                         d * h - e * g, b * g - a * h, a * e - b * d], axis=-1).reshape(info.shape)
    det = a * adjugate[..., 0, 0] + b * adjugate[..., 1, 0] + c * adjugate[..., 2, 0]
    # A singular information matrix (fewer than two usable directions): inf, not a huge number.
    well_posed = np.abs(det) > 1e-12 * np.abs(a + e + i) ** 3
    with np.errstate(all="ignore"):
        cov = adjugate / np.where(well_posed, det, np.nan)[..., None, None]
    bad = ~well_posed | ~np.isfinite(cov).all(axis=(-2, -1)) | (np.diagonal(cov, axis1=-2, axis2=-1) < 0).any(axis=-1)
    cov[bad] = np.inf
    return cov


def cross_boresight_and_roll_sigma(cov: np.ndarray) -> tuple[float, float]:
    """(per-axis cross-boresight 1-sigma, roll 1-sigma), radians, from a camera-frame covariance."""
    return float(np.sqrt((cov[0, 0] + cov[1, 1]) / 2)), float(np.sqrt(cov[2, 2]))


def _inverse_3x3(m: list[list[float]]) -> np.ndarray:
    """:func:`wahba_covariance`'s inverse of one information matrix, in Python floats.

    The same IEEE operations in the same order as the stack-wide code,
    without a dozen numpy calls on nine numbers: a candidate asks for one
    covariance at a time.
    """
    (a, b, c), (d, e, f), (g, h, i) = m
    adjugate = [[e * i - f * h, c * h - b * i, b * f - c * e],
                [f * g - d * i, a * i - c * g, c * d - a * f],
                [d * h - e * g, b * g - a * h, a * e - b * d]]
    det = a * adjugate[0][0] + b * adjugate[1][0] + c * adjugate[2][0]
    if not abs(det) > 1e-12 * abs(a + e + i) ** 3:
        return np.full((3, 3), np.inf)
    cov = np.array(adjugate) / det
    if not np.isfinite(cov).all() or (np.diagonal(cov) < 0).any():
        return np.full((3, 3), np.inf)
    return cov
