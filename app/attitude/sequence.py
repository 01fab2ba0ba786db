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

from app.attitude.rotations import (matmul3, propagate, rodrigues, rotation_from_rotvec, rotvec_from_rotation,
                                    solve_wahba)
from app.attitude.wahba import wahba_covariance
from app.compiled import njit, warm_up_with


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
    """One Gauss-Newton fit of ``(c, w)`` (:func:`_gauss_newton`); also each snapshot's chi-square."""
    if len(snaps) < 2 or len({round(s.dt_s, 9) for s in snaps}) < 2:
        return None, np.zeros(0)
    R_obs = np.stack([s.rotation for s in snaps])
    dt = np.array([s.dt_s for s in snaps])
    # Whitening: W_i^T W_i = P_i^-1, so |W_i r_i|^2 = r_i^T P_i^-1 r_i.
    W = np.ascontiguousarray(np.swapaxes(np.linalg.cholesky(np.linalg.inv(np.stack([s.covariance for s in snaps]))),
                                         1, 2))
    w0 = np.zeros(3) if rate_guess is None else np.asarray(rate_guess, dtype=float)
    c, w, f, J = _gauss_newton(R_obs, dt, W, np.ascontiguousarray(R0, dtype=float), w0, iterations, CONVERGED_STEP)
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


# --- the compiled Gauss-Newton ------------------------------------------------------------------

@njit
def _log(R):
    """``log(R)``, the rotation vector of one rotation matrix, at any angle: through its unit quaternion
    (Shepperd's choice of the largest component, so no division loses accuracy), ``2 atan2(|v|, s) v/|v|``."""
    trace = R[0, 0] + R[1, 1] + R[2, 2]
    if trace >= R[0, 0] and trace >= R[1, 1] and trace >= R[2, 2]:
        s = np.sqrt(1.0 + trace) / 2
        x, y, z = (R[2, 1] - R[1, 2]) / (4 * s), (R[0, 2] - R[2, 0]) / (4 * s), (R[1, 0] - R[0, 1]) / (4 * s)
    elif R[0, 0] >= R[1, 1] and R[0, 0] >= R[2, 2]:
        x = np.sqrt(1.0 + 2 * R[0, 0] - trace) / 2
        s, y, z = (R[2, 1] - R[1, 2]) / (4 * x), (R[0, 1] + R[1, 0]) / (4 * x), (R[0, 2] + R[2, 0]) / (4 * x)
    elif R[1, 1] >= R[2, 2]:
        y = np.sqrt(1.0 + 2 * R[1, 1] - trace) / 2
        s, x, z = (R[0, 2] - R[2, 0]) / (4 * y), (R[0, 1] + R[1, 0]) / (4 * y), (R[1, 2] + R[2, 1]) / (4 * y)
    else:
        z = np.sqrt(1.0 + 2 * R[2, 2] - trace) / 2
        s, x, y = (R[1, 0] - R[0, 1]) / (4 * z), (R[0, 2] + R[2, 0]) / (4 * z), (R[1, 2] + R[2, 1]) / (4 * z)
    if s < 0:
        s, x, y, z = -s, -x, -y, -z
    v = np.sqrt(x * x + y * y + z * z)
    out = np.zeros(3)
    if v > 0:
        k = 2.0 * np.arctan2(v, s) / v
        out[0], out[1], out[2] = k * x, k * y, k * z
    return out


@njit
def left_jacobian(x, y, z):
    """The left Jacobian of SO(3) at the rotation vector ``phi = (x, y, z)``:
    ``exp(phi + d) ~ exp([J_l(phi) d]x) exp(phi)``, with
    ``J_l = I + (1 - cos t)/t^2 [phi]x + (t - sin t)/t^3 [phi]x^2``, t = |phi|."""
    t = np.sqrt(x * x + y * y + z * z)
    if t < 1e-6:
        a, b = 0.5 - t * t / 24, 1 / 6 - t * t / 120
    else:
        a, b = (1 - np.cos(t)) / (t * t), (t - np.sin(t)) / (t * t * t)
    K = np.zeros((3, 3))
    K[0, 1], K[0, 2], K[1, 2] = -z, y, -x
    K[1, 0], K[2, 0], K[2, 1] = z, -y, x
    KK = matmul3(K, K)
    J = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            J[i, j] = a * K[i, j] + b * KK[i, j] + (1.0 if i == j else 0.0)
    return J


@njit
def _residuals_and_jacobian(R_obs, dt, W, R0, c, w):
    """Whitened residuals (3S,) ``W_i log(R_i R(t_i)^T)`` and their Jacobian (3S, 6) in ``(c, w)``:
    ``dr_i/dc = -exp(-[w]x dt_i)`` (``c`` stays tiny) and ``dr_i/dw = dt_i J_l(-w dt_i)``."""
    S = dt.shape[0]
    f = np.empty(3 * S)
    J = np.empty((3 * S, 6))
    base = matmul3(rodrigues(c[0], c[1], c[2]), R0)
    for i in range(S):
        px, py, pz = -w[0] * dt[i], -w[1] * dt[i], -w[2] * dt[i]
        turn = rodrigues(px, py, pz)
        pred = matmul3(turn, base)
        misfit = np.empty((3, 3))
        for r in range(3):
            for k in range(3):
                misfit[r, k] = R_obs[i, r, 0] * pred[k, 0] + R_obs[i, r, 1] * pred[k, 1] + R_obs[i, r, 2] * pred[k, 2]
        r = _log(misfit)
        jl = left_jacobian(px, py, pz)
        for a in range(3):
            f[3 * i + a] = W[i, a, 0] * r[0] + W[i, a, 1] * r[1] + W[i, a, 2] * r[2]
            for k in range(3):
                J[3 * i + a, k] = -(W[i, a, 0] * turn[0, k] + W[i, a, 1] * turn[1, k] + W[i, a, 2] * turn[2, k])
                J[3 * i + a, 3 + k] = dt[i] * (W[i, a, 0] * jl[0, k] + W[i, a, 1] * jl[1, k] + W[i, a, 2] * jl[2, k])
    return f, J


@njit
def _normal_step(f, J):
    """The Gauss-Newton step ``delta`` solving ``J^T J delta = -J^T f`` (6 unknowns) by Cholesky, the normal
    matrix first scaled to a unit diagonal (its columns mix radians and radians per second)."""
    n = 6
    N = np.zeros((n, n))
    g = np.zeros(n)
    for row in range(J.shape[0]):
        for a in range(n):
            g[a] -= J[row, a] * f[row]
            for b in range(a + 1):
                N[a, b] += J[row, a] * J[row, b]
    scale = np.empty(n)
    for a in range(n):
        scale[a] = 1.0 / np.sqrt(N[a, a]) if N[a, a] > 0 else 1.0
    L = np.zeros((n, n))
    for a in range(n):
        for b in range(a + 1):
            total = N[a, b] * scale[a] * scale[b]
            for k in range(b):
                total -= L[a, k] * L[b, k]
            if a == b:
                L[a, a] = np.sqrt(total) if total > 0 else np.nan
            else:
                L[a, b] = total / L[b, b]
    y = np.empty(n)
    for a in range(n):
        total = g[a] * scale[a]
        for k in range(a):
            total -= L[a, k] * y[k]
        y[a] = total / L[a, a]
    delta = np.empty(n)
    for a in range(n - 1, -1, -1):
        total = y[a]
        for k in range(a + 1, n):
            total -= L[k, a] * delta[k]
        delta[a] = total / L[a, a]
    for a in range(n):
        delta[a] *= scale[a]
    return delta


@njit
def _gauss_newton(R_obs, dt, W, R0, w0, iterations, converged):
    """``(c, w, f, J)``: Gauss-Newton from ``(0, w0)``, stopping once a step moves both by less than
    ``converged``; the residuals and Jacobian at the end.  The left Jacobian keeps turns of several degrees
    over a sequence from slowing it to a linear crawl."""
    c = np.zeros(3)
    w = w0.copy()
    for _ in range(iterations):
        f, J = _residuals_and_jacobian(R_obs, dt, W, R0, c, w)
        delta = _normal_step(f, J)
        largest = 0.0
        for k in range(6):
            if not abs(delta[k]) <= largest:  # nan too
                largest = abs(delta[k])
        if not largest < np.inf:  # nan or inf: a singular normal matrix (the caller's inverse says so)
            break
        for k in range(3):
            c[k] += delta[k]
            w[k] += delta[3 + k]
        if largest < converged:
            break
    f, J = _residuals_and_jacobian(R_obs, dt, W, R0, c, w)
    return c, w, f, J


@warm_up_with
def _warm_up_gauss_newton() -> None:
    R = np.stack([np.eye(3), np.eye(3)])
    _gauss_newton(R, np.array([0.0, 1.0]), np.stack([np.eye(3), np.eye(3)]) * 1e3, np.eye(3), np.zeros(3), 2, 1e-10)


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
