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
from scipy.spatial.transform import Rotation

from app.attitude.rotations import solve_wahba
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
        return Rotation.from_rotvec(-self.rate_rad_s * dt_s).as_matrix() @ self.rotation


def snapshot_attitude(body: np.ndarray, ref: np.ndarray, sigma_rad: np.ndarray, *, position: int = 0,
                      dt_s: float = 0.0, reject_sigmas: float = 5.0) -> SnapshotAttitude | None:
    """Wahba attitude of one snapshot, dropping pairs beyond ``reject_sigmas`` once; None if < 2 stars."""
    keep = np.ones(len(body), dtype=bool)
    for _ in range(2):
        if keep.sum() < 2:
            return None
        R = solve_wahba(body[keep], ref[keep], 1.0 / sigma_rad[keep] ** 2)
        resid = np.linalg.norm(body - ref @ R.T, axis=1)
        new_keep = resid <= reject_sigmas * sigma_rad * np.sqrt(2)
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
    if keep.sum() < 2:
        return None
    R = solve_wahba(body[keep], ref[keep], 1.0 / sigma_rad[keep] ** 2)
    cov = wahba_covariance(body[keep], sigma_rad[keep])
    if not np.all(np.isfinite(cov)):
        return None
    return SnapshotAttitude(position=position, dt_s=dt_s, rotation=R, covariance=cov, n_stars=int(keep.sum()))


def _residuals(params: np.ndarray, R0: np.ndarray, snaps: list[SnapshotAttitude]) -> np.ndarray:
    c, w = params[:3], params[3:]
    base = Rotation.from_rotvec(c).as_matrix() @ R0
    out = []
    for s in snaps:
        pred = Rotation.from_rotvec(-w * s.dt_s).as_matrix() @ base
        out.append(Rotation.from_matrix(s.rotation @ pred.T).as_rotvec())
    return np.concatenate(out)


def fit_constant_rate(snaps: list[SnapshotAttitude], R0: np.ndarray, rate_guess: np.ndarray | None = None,
                      iterations: int = 6) -> SequenceFit | None:
    """Fit ``(c, w)`` of the module's model; None with fewer than two snapshot attitudes."""
    if len(snaps) < 2 or len({round(s.dt_s, 9) for s in snaps}) < 2:
        return None
    # Whitening: W_i = chol(P_i^-1) so that |W_i r_i|^2 = r_i^T P_i^-1 r_i.
    whiten = [np.linalg.cholesky(np.linalg.inv(s.covariance)).T for s in snaps]

    def white(params):
        r = _residuals(params, R0, snaps).reshape(-1, 3)
        return np.concatenate([W @ ri for W, ri in zip(whiten, r)])

    params = np.concatenate([np.zeros(3), np.zeros(3) if rate_guess is None else rate_guess])
    for _ in range(iterations):
        f0 = white(params)
        J = np.empty((len(f0), 6))
        for k in range(6):
            step = np.zeros(6)
            step[k] = 1e-7 if k < 3 else 1e-8
            J[:, k] = (white(params + step) - f0) / step[k]
        delta, *_ = np.linalg.lstsq(J, -f0, rcond=None)
        params = params + delta
        if np.max(np.abs(delta)) < 1e-12:
            break
    f = white(params)
    dof = max(1, len(f) - 6)
    chi2_red = float(f @ f / dof)
    try:
        cov = np.linalg.inv(J.T @ J) * max(1.0, chi2_red)
    except np.linalg.LinAlgError:
        return None
    rotation = Rotation.from_rotvec(params[:3]).as_matrix() @ R0
    return SequenceFit(rotation=rotation, covariance=cov[:3, :3], rate_rad_s=params[3:].copy(),
                       rate_covariance=cov[3:, 3:], snapshots=tuple(snaps), chi2_reduced=chi2_red)


def rate_from_motion(motion: np.ndarray, dt_s: np.ndarray) -> np.ndarray | None:
    """A first guess of the body rate from extraction's inter-snapshot motion (v_ref = M_i v_i).

    ``R_i = M_i^T R_ref = exp(-[w]x dt_i) R_ref``, so ``log(M_i) = w dt_i``:
    a least-squares slope through the origin.
    """
    ok = np.array([np.all(np.isfinite(M)) for M in motion]) & (np.abs(dt_s) > 0)
    if ok.sum() < 1:
        return None
    phi = Rotation.from_matrix(motion[ok]).as_rotvec()
    t = dt_s[ok]
    return (phi * t[:, None]).sum(axis=0) / (t @ t)
