"""The attitude of a whole sequence: one attitude per snapshot, the body rate,
and the attitude at the reference time averaged over all snapshots.

Model.  Over a sequence (tens of seconds) the spacecraft turns at a
constant body rate ``w`` (rad/s, camera axes).  A fixed direction seen from a
frame turning at ``w`` moves as ``dv/dt = -w x v``, so::

    R(t) = exp(-[w]x (t - t_ref)) exp([c]x) R0

where ``R0`` is the identification's attitude at the reference snapshot and
``c`` a small correction of it.  Each snapshot ``i`` with at least two
identified stars gives its own attitude ``R_i`` (Wahba) with covariance
``P_i`` (:func:`app.attitude.wahba.wahba_covariance`); ``(c, w)`` minimise

    sum_i  r_i^T P_i^-1 r_i,   r_i = log(R_i R(t_i)^T)  (a small rotation vector)

by Gauss-Newton.  The fit's covariance is the inverse of the normal matrix,
inflated by the reduced chi-square when that exceeds 1 (real data with
unmodelled errors), so the stated uncertainties stay honest.  ``exp([c]x) R0``
is Liebe's "accumulated average": every snapshot contributes to the attitude
at the reference time, its noise falling as 1/sqrt(snapshots).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.attitude.rotations import propagate, rotation_from_rotvec, rotvec_from_rotation, solve_wahba
from app.attitude.wahba import wahba_covariance


@dataclass(frozen=True, eq=False)
class SnapshotAttitude:
    position: int  # snapshot position in the sequence
    dt_s: float  # time since the reference snapshot
    rotation: np.ndarray  # ICRS -> camera, from this snapshot's stars alone
    covariance: np.ndarray  # (3, 3) rad^2, camera frame
    n_stars: int


@dataclass(frozen=True, eq=False)
class SequenceFit:
    rotation: np.ndarray  # attitude at the reference time, averaged over the sequence
    covariance: np.ndarray  # (3, 3) rad^2 of that attitude (camera frame)
    rate_rad_s: np.ndarray  # (3,) body rate in camera axes
    rate_covariance: np.ndarray  # (3, 3) (rad/s)^2
    snapshots: tuple[SnapshotAttitude, ...]
    chi2_reduced: float

    def attitude_at(self, dt_s: float) -> np.ndarray:
        """The fitted attitude ``dt_s`` seconds after the reference time."""
        return propagate(self.rotation, self.rate_rad_s, dt_s)


def snapshot_attitude(body: np.ndarray, ref: np.ndarray, sigma_rad: np.ndarray, *, position: int = 0,
                      dt_s: float = 0.0, reject_sigmas: float = 5.0, min_stars: int = 3) -> SnapshotAttitude | None:
    """Wahba attitude of one snapshot, dropping pairs beyond ``reject_sigmas``.

    None with fewer than ``min_stars`` consistent stars: two stars always fit
    exactly, so a mixed-up pair could not be noticed.
    """
    (found,) = wahba_per_snapshot(body[None], ref[None], sigma_rad[None], positions=[position], dt_s=[dt_s],
                                  reject_sigmas=reject_sigmas, min_stars=min_stars)
    return found


def wahba_per_snapshot(body: np.ndarray, ref: np.ndarray, sigma_rad: np.ndarray, *, positions, dt_s,
                       reject_sigmas: float = 5.0, min_stars: int = 3) -> list[SnapshotAttitude | None]:
    """:func:`snapshot_attitude` of many snapshots at once.

    ``body`` and ``ref`` are (S, N, 3), ``sigma_rad`` (S, N) with ``inf``
    where a snapshot has fewer than N sightings.
    """
    sigma_rad = np.asarray(sigma_rad, dtype=float)
    weight = 1.0 / sigma_rad ** 2
    keep = np.isfinite(sigma_rad)
    limit = reject_sigmas * sigma_rad * np.sqrt(2)
    for _ in range(3):
        R = solve_wahba(body, ref, np.where(keep, weight, 0.0))
        resid = np.linalg.norm(body - np.einsum("sij,snj->sni", R, ref), axis=2)
        new_keep = np.isfinite(sigma_rad) & (resid <= limit) & (keep.sum(axis=1) >= min_stars)[:, None]
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
    n_kept = keep.sum(axis=1)
    R = solve_wahba(body, ref, np.where(keep, weight, 0.0))
    cov = wahba_covariance(body, np.where(keep, sigma_rad, np.inf))
    usable = ((n_kept >= min_stars) & np.isfinite(cov).all(axis=(1, 2))).tolist()  # one test for all snapshots
    return [SnapshotAttitude(position=int(p), dt_s=float(t), rotation=R[k], covariance=cov[k], n_stars=int(n_kept[k]))
            if usable[k] else None
            for k, (p, t) in enumerate(zip(positions, dt_s))]


#: Gauss-Newton stops once a step moves the attitude (rad) and the rate (rad/s)
#: by less than this: ~2e-5 arcsec, far below any star camera's noise, and
#: above the ~1e-13 floor of the rotation-vector arithmetic.
CONVERGED_STEP = 1e-10

#: A snapshot whose attitude misses the fitted model by more than this chi-square
#: (3 degrees of freedom; 16.3 is the 99.9 % point) is dropped and the fit redone.
SNAPSHOT_REJECT_CHI2 = 16.3


def fit_constant_rate(snaps: list[SnapshotAttitude], R0: np.ndarray, rate_guess: np.ndarray | None = None,
                      iterations: int = 8) -> SequenceFit | None:
    """Fit ``(c, w)``, dropping snapshots that disagree with the rest (a mixed-up track).

    None with fewer than two usable snapshot attitudes.
    """
    snaps = list(snaps)
    while True:
        fit, chi2_each = _fit_once(snaps, R0, rate_guess, iterations)
        if fit is None:
            return None
        worst = int(np.argmax(chi2_each))
        if chi2_each[worst] <= SNAPSHOT_REJECT_CHI2 or len(snaps) <= 3:
            return fit
        del snaps[worst]
        rate_guess = fit.rate_rad_s


def _fit_once(snaps: list[SnapshotAttitude], R0: np.ndarray, rate_guess: np.ndarray | None,
              iterations: int) -> tuple[SequenceFit | None, np.ndarray]:
    """One Gauss-Newton fit of ``(c, w)``; also each snapshot's chi-square.

    The Jacobian of ``r_i`` for small residuals: ``dr_i/dc = -exp(-[w]x dt_i)``
    (``c`` stays tiny) and ``dr_i/dw = dt_i J_l(-w dt_i)``, with ``J_l`` the
    left Jacobian of SO(3): turns of several degrees over a sequence would
    otherwise slow Gauss-Newton's convergence to a linear crawl.
    """
    if len(snaps) < 2 or len({round(s.dt_s, 9) for s in snaps}) < 2:
        return None, np.zeros(0)
    R_obs = np.stack([s.rotation for s in snaps])
    dt = np.array([s.dt_s for s in snaps])
    # Whitening: W_i^T W_i = P_i^-1, so |W_i r_i|^2 = r_i^T P_i^-1 r_i.
    W = np.swapaxes(np.linalg.cholesky(np.linalg.inv(np.stack([s.covariance for s in snaps]))), 1, 2)
    c = np.zeros(3)
    w = np.zeros(3) if rate_guess is None else np.asarray(rate_guess, dtype=float).copy()

    def residuals_and_jacobian(c, w):
        phi = -w[None, :] * dt[:, None]
        # Rodrigues and its inverse in numpy (app.attitude.rotations): scipy's Rotation objects cost more
        # than the arithmetic here, and Gauss-Newton asks for them every iteration.
        turn = rotation_from_rotvec(phi)  # (S, 3, 3)
        pred = turn @ (rotation_from_rotvec(c) @ R0)
        r = rotvec_from_rotation(R_obs @ np.swapaxes(pred, 1, 2))  # (S, 3)
        J = np.concatenate([-turn, dt[:, None, None] * left_jacobian(phi)], axis=2)  # (S, 3, 6)
        return np.einsum("sij,sj->si", W, r).reshape(-1), np.einsum("sij,sjk->sik", W, J).reshape(-1, 6)

    for _ in range(iterations):
        f, J = residuals_and_jacobian(c, w)
        delta, *_ = np.linalg.lstsq(J, -f, rcond=None)
        c, w = c + delta[:3], w + delta[3:]
        if np.max(np.abs(delta)) < CONVERGED_STEP:
            break
    f, J = residuals_and_jacobian(c, w)
    dof = max(1, len(f) - 6)
    chi2_red = float(f @ f / dof)
    try:
        cov = np.linalg.inv(J.T @ J) * max(1.0, chi2_red)
    except np.linalg.LinAlgError:
        return None, np.zeros(0)
    rotation = rotation_from_rotvec(c) @ R0
    fit = SequenceFit(rotation=rotation, covariance=cov[:3, :3], rate_rad_s=w,
                      rate_covariance=cov[3:, 3:], snapshots=tuple(snaps), chi2_reduced=chi2_red)
    return fit, (f.reshape(-1, 3) ** 2).sum(axis=1)


def left_jacobian(phi: np.ndarray) -> np.ndarray:
    """(S, 3, 3) left Jacobians of SO(3) at rotation vectors ``phi`` (S, 3):
    ``exp(phi + d) ~ exp([J_l(phi) d]x) exp(phi)``, with
    ``J_l = I + (1 - cos t)/t^2 [phi]x + (t - sin t)/t^3 [phi]x^2``, t = |phi|.
    """
    t = np.linalg.norm(phi, axis=1)
    small = t < 1e-6
    ts = np.where(small, 1.0, t)
    a = np.where(small, 0.5 - t ** 2 / 24, (1 - np.cos(ts)) / ts ** 2)
    b = np.where(small, 1 / 6 - t ** 2 / 120, (ts - np.sin(ts)) / ts ** 3)
    K = np.zeros((len(phi), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -phi[:, 2], phi[:, 1], -phi[:, 0]
    K -= np.swapaxes(K, 1, 2)
    return np.eye(3) + a[:, None, None] * K + b[:, None, None] * (K @ K)


def rate_from_motion(motion: np.ndarray, dt_s: np.ndarray) -> np.ndarray | None:
    """A first guess of the body rate from extraction's inter-snapshot motion (v_ref = M_i v_i).

    ``R_i = M_i^T R_ref = exp(-[w]x dt_i) R_ref``, so ``log(M_i) = w dt_i``:
    a least-squares slope through the origin.
    """
    ok = np.isfinite(motion).all(axis=(1, 2)) & (np.abs(dt_s) > 0)
    if ok.sum() < 1:
        return None
    phi = rotvec_from_rotation(motion[ok])
    t = dt_s[ok]
    return (phi * t[:, None]).sum(axis=0) / (t @ t)
