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
    info = w.sum(axis=-1)[..., None, None] * np.eye(3) - np.einsum("...n,...ni,...nj->...ij", w, body, body)
    # The inverse by cofactors, stack-wide: columns r1 x r2, r2 x r0, r0 x r1 over det = r0 . (r1 x r2).
    r0, r1, r2 = info[..., 0, :], info[..., 1, :], info[..., 2, :]
    adjugate = np.stack([np.cross(r1, r2), np.cross(r2, r0), np.cross(r0, r1)], axis=-1)
    det = np.einsum("...i,...i->...", r0, adjugate[..., 0])
    # A singular information matrix (fewer than two usable directions): inf, not a huge number.
    well_posed = np.abs(det) > 1e-12 * np.abs(np.trace(info, axis1=-2, axis2=-1)) ** 3
    with np.errstate(all="ignore"):
        cov = adjugate / np.where(well_posed, det, np.nan)[..., None, None]
    bad = ~well_posed | ~np.all(np.isfinite(cov), axis=(-2, -1)) | np.any(np.diagonal(cov, axis1=-2, axis2=-1) < 0,
                                                                          axis=-1)
    cov[bad] = np.inf
    return cov


def cross_boresight_and_roll_sigma(cov: np.ndarray) -> tuple[float, float]:
    """(per-axis cross-boresight 1-sigma, roll 1-sigma), radians, from a camera-frame covariance."""
    return float(np.sqrt((cov[0, 0] + cov[1, 1]) / 2)), float(np.sqrt(cov[2, 2]))
