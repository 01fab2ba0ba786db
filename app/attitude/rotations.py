"""Rotations between the ICRS and the camera frame, and Wahba's problem.

``R`` (a "rotation_matrix" everywhere in this project) maps ICRS unit
vectors to camera-frame unit vectors: ``v_cam = R @ v_icrs``.  Its rows are
the camera axes expressed in ICRS; row 2 is the boresight.

RA, Dec and roll of an attitude
-------------------------------
RA and Dec are the boresight's (+z).  Roll is the position angle of the
image's "up" direction (-y, towards smaller row numbers) measured from
celestial north through east.  At roll 0, north is up and east is to the
left (-x), as on a sky chart seen from inside the sphere.

Quaternions are scalar-last ``[x, y, z, w]`` with ``w >= 0`` (scipy's
convention), representing the same rotation as ``R``.
"""

from __future__ import annotations

import math

import numpy as np

from app.compiled import njit, warm_up_with


def rotation_from_radec_roll(ra_deg: float, dec_deg: float, roll_deg: float) -> np.ndarray:
    """The ICRS -> camera rotation for a boresight (RA, Dec) and a roll, all in degrees."""
    ra, dec, roll = np.radians([ra_deg, dec_deg, roll_deg])
    z = np.array([np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)])
    east = np.array([-np.sin(ra), np.cos(ra), 0.0])
    north = np.cross(z, east)
    up = np.cos(roll) * north + np.sin(roll) * east  # = -y
    y = -up
    x = np.cross(y, z)
    return np.vstack([x, y, z])


def radec_roll_from_rotation(R: np.ndarray) -> tuple[float, float, float]:
    """Inverse of :func:`rotation_from_radec_roll`: (ra, dec, roll) in degrees.

    RA in [0, 360), roll in [0, 360).  At the celestial poles, where north is
    undefined, RA is taken as 0 and roll is measured from the ICRS +y axis.
    """
    R = np.asarray(R, dtype=float)
    z = R[2]
    dec = np.degrees(np.arcsin(np.clip(z[2], -1.0, 1.0)))
    ra = np.degrees(np.arctan2(z[1], z[0])) % 360.0
    ra_r = np.radians(ra)
    east = np.array([-np.sin(ra_r), np.cos(ra_r), 0.0])
    north = np.cross(z, east)
    up = -R[1]
    roll = np.degrees(np.arctan2(up @ east, up @ north)) % 360.0
    return float(ra), float(dec), float(roll)


def quaternion_from_rotation(R: np.ndarray) -> np.ndarray:
    """Scalar-last unit quaternion of ``R`` with a non-negative scalar part."""
    from scipy.spatial.transform import Rotation  # imported when needed: start-up does not need it

    q = Rotation.from_matrix(np.asarray(R, dtype=float)).as_quat()
    return -q if q[3] < 0 else q


def rotation_from_quaternion(q) -> np.ndarray:
    """Scalar-last quaternion -> rotation matrix."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat(np.asarray(q, dtype=float)).as_matrix()


def angle_between(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Angle (radians) between unit vectors, row by row; accurate for tiny angles."""
    u = np.asarray(u, dtype=float)
    v = np.asarray(v, dtype=float)
    return np.arctan2(np.linalg.norm(np.cross(u, v), axis=-1), np.sum(u * v, axis=-1))


def rotation_angle_between(R1: np.ndarray, R2: np.ndarray) -> float:
    """Angle (radians) of the rotation that takes attitude ``R1`` to ``R2``."""
    return float(rotation_angles_between(np.asarray(R1)[None], R2)[0])


def rotation_angles_between(stack: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Angles (radians) of the rotations taking each attitude of ``stack`` (n, 3, 3) to ``R``."""
    c = (np.einsum("nij,ij->n", stack, R) - 1.0) / 2.0  # trace(S_n R^T) = sum(S_n * R)
    return np.arccos(np.clip(c, -1.0, 1.0))


def boresight_and_roll_error(R_est: np.ndarray, R_true: np.ndarray) -> tuple[float, float]:
    """(boresight error, roll error about the boresight), both in radians.

    Boresight error is the angle between the two +z axes; roll error the
    angle between the two +x axes after the boresight difference is removed.
    """
    bore = float(angle_between(R_est[2], R_true[2]))
    dR = R_est @ np.asarray(R_true).T  # true camera frame -> estimated camera frame
    roll = float(abs(np.arctan2(dR[0, 1] - dR[1, 0], dR[0, 0] + dR[1, 1])))
    return bore, roll


def solve_wahba(body: np.ndarray, ref: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """The rotation R minimising sum w_i |body_i - R ref_i|^2 (SVD method, Markley 1988).

    ``body`` are unit vectors in the camera frame, ``ref`` the matching ICRS
    unit vectors, both (N, 3) with N >= 2.  With B = sum w_i body_i ref_i^T =
    U S V^T the optimum is R = U diag(1, 1, det U det V) V^T.  Stacks of
    problems work too: (..., N, 3) vectors and (..., N) weights give
    (..., 3, 3); a zero weight leaves a pair out.
    """
    body = np.asarray(body, dtype=float)
    ref = np.asarray(ref, dtype=float)
    w = np.ones(body.shape[:-1]) if weights is None else np.asarray(weights, dtype=float)
    B = np.swapaxes(body * w[..., None], -1, -2) @ ref
    U, _, Vt = np.linalg.svd(B)
    # det U det V = det(U V^T); where it is -1, U diag(1, 1, -1) V^T = U V^T - 2 u3 v3^T.
    # (Not the sign of det B: with two vectors B has rank 2 and that sign is rounding noise.)
    R = U @ Vt
    improper = np.linalg.det(R) < 0
    return R - 2.0 * improper[..., None, None] * (U[..., :, 2, None] * Vt[..., None, 2, :])


def rotation_from_pair(b1: np.ndarray, b2: np.ndarray, r1: np.ndarray, r2: np.ndarray) -> np.ndarray:
    """The rotation mapping r1 exactly onto b1 and the great circle r1-r2 onto b1-b2.

    The seed's construction (004, "Numerical Problems"): build an orthonormal
    triad from each pair as (u, n, w) with n = normalize(u x v) and w = n x u,
    avoiding the unstable v - u (u.v) for the small angles between stars;
    then ``R = T_b T_r^T``.  Works on stacks: b1, b2, r1, r2 may be (N, 3)
    (or broadcast to it), giving (N, 3, 3); the thousands of catalogue pairs
    of a hypothesis batch go through one compiled loop
    (:func:`_rotations_from_pairs`).
    """
    b1, b2, r1, r2 = (np.asarray(x, dtype=float) for x in (b1, b2, r1, r2))
    shape = np.broadcast_shapes(b1.shape, b2.shape, r1.shape, r2.shape)
    flat = [np.ascontiguousarray(np.broadcast_to(x, shape)).reshape(-1, 3) for x in (b1, b2, r1, r2)]
    for x in flat:  # all read-only (a broadcast copied is writable, one that was not a view): one compilation
        x.flags.writeable = False
    return _rotations_from_pairs(*flat).reshape(shape[:-1] + (3, 3))


@njit
def pair_triad(u0, u1, u2, v0, v1, v2):
    """The triad (u, n, w) of a pair (:func:`rotation_from_pair`), its columns as nine numbers: no array, for
    kernels that make one per hypothesis (:func:`app.identification.cells.check_pairs_kernel`)."""
    n0, n1, n2 = u1 * v2 - u2 * v1, u2 * v0 - u0 * v2, u0 * v1 - u1 * v0
    norm = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
    n0, n1, n2 = n0 / norm, n1 / norm, n2 / norm
    return u0, u1, u2, n0, n1, n2, n1 * u2 - n2 * u1, n2 * u0 - n0 * u2, n0 * u1 - n1 * u0


@njit
def triads_rotation(b, r):
    """``T_b T_r^T`` of two triads (:func:`pair_triad`'s nine numbers), row by row as nine numbers."""
    return (b[0] * r[0] + b[3] * r[3] + b[6] * r[6], b[0] * r[1] + b[3] * r[4] + b[6] * r[7],
            b[0] * r[2] + b[3] * r[5] + b[6] * r[8],
            b[1] * r[0] + b[4] * r[3] + b[7] * r[6], b[1] * r[1] + b[4] * r[4] + b[7] * r[7],
            b[1] * r[2] + b[4] * r[5] + b[7] * r[8],
            b[2] * r[0] + b[5] * r[3] + b[8] * r[6], b[2] * r[1] + b[5] * r[4] + b[8] * r[7],
            b[2] * r[2] + b[5] * r[5] + b[8] * r[8])


@njit
def rotation_into(out, R):
    """Write :func:`triads_rotation`'s nine numbers (row by row) into the (3, 3) array ``out``."""
    out[0, 0], out[0, 1], out[0, 2] = R[0], R[1], R[2]
    out[1, 0], out[1, 1], out[1, 2] = R[3], R[4], R[5]
    out[2, 0], out[2, 1], out[2, 2] = R[6], R[7], R[8]


@njit
def _rotations_from_pairs(b1, b2, r1, r2):
    """:func:`rotation_from_pair` of (N, 3) stacks: (N, 3, 3)."""
    N = b1.shape[0]
    out = np.empty((N, 3, 3))
    for k in range(N):
        R = triads_rotation(pair_triad(b1[k, 0], b1[k, 1], b1[k, 2], b2[k, 0], b2[k, 1], b2[k, 2]),
                            pair_triad(r1[k, 0], r1[k, 1], r1[k, 2], r2[k, 0], r2[k, 1], r2[k, 2]))
        rotation_into(out[k], R)
    return out


@njit
def rodrigues(x, y, z):
    """``exp([phi]x)`` of one rotation vector ``(x, y, z)``, compiled (:func:`rotation_from_rotvec`'s
    formula: ``cos t I + a [phi]x + b phi phi^T`` with ``a = h cos(t/2)``, ``b = h^2 / 2``,
    ``h = sin(t/2) / (t/2)``)."""
    t = np.sqrt(x * x + y * y + z * z)
    h = np.sin(t / 2) / (t / 2) if t > 0 else 1.0
    a, b, c = h * np.cos(t / 2), 0.5 * h * h, np.cos(t)
    R = np.empty((3, 3))
    R[0, 0], R[0, 1], R[0, 2] = c + b * x * x, b * x * y - a * z, b * x * z + a * y
    R[1, 0], R[1, 1], R[1, 2] = b * x * y + a * z, c + b * y * y, b * y * z - a * x
    R[2, 0], R[2, 1], R[2, 2] = b * x * z - a * y, b * y * z + a * x, c + b * z * z
    return R


@njit
def matmul3(A, B):
    """A B of two 3 x 3 matrices, compiled and written out (numba's matrix product and array expressions
    cost seconds of compilation on the first run after an install)."""
    C = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            C[i, j] = A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j]
    return C


@njit
def svd_3x3(B):
    """``(U, S, V^T)`` of a 3 x 3 matrix, singular values descending: one-sided Jacobi.

    Why not LAPACK's.  Wahba's problem is solved a few hundred times a
    search (refinements, their subset and leave-one-out fits, the
    extraction's link fits), and LAPACK's SVD costs ~2.7 us a call from
    compiled code where these plane rotations take ~1 us.  One-sided Jacobi
    also has high *relative* accuracy (Demmel & Veselic 1992): the singular
    vectors of the small singular values, which fix a narrow field's roll,
    come out as accurate as the data allow (against a 40-digit SVD: 5e-13
    where LAPACK's gave 1.2e-11, on patterns 0.2 deg across).

    Columns ``p, q`` of ``W = B V`` are rotated until orthogonal, ``V``
    accumulating the rotations; then ``S_k = |W_k|`` and ``U_k = W_k / S_k``.
    A rank-deficient ``B`` gets ``U`` completed to an orthonormal basis.
    """
    W = B.copy()
    V = np.zeros((3, 3))
    V[0, 0], V[1, 1], V[2, 2] = 1.0, 1.0, 1.0
    for _sweep in range(12):
        rotated = False
        for pair in range(3):
            p, q = (0, 1) if pair == 0 else ((0, 2) if pair == 1 else (1, 2))
            a = W[0, p] * W[0, p] + W[1, p] * W[1, p] + W[2, p] * W[2, p]
            b = W[0, q] * W[0, q] + W[1, q] * W[1, q] + W[2, q] * W[2, q]
            g = W[0, p] * W[0, q] + W[1, p] * W[1, q] + W[2, p] * W[2, q]
            if g == 0.0 or abs(g) <= 1e-17 * np.sqrt(a * b):
                continue
            rotated = True
            zeta = (b - a) / (2.0 * g)
            t = (1.0 if zeta >= 0 else -1.0) / (abs(zeta) + np.sqrt(1.0 + zeta * zeta))
            c = 1.0 / np.sqrt(1.0 + t * t)
            s = c * t
            for r in range(3):
                wp, wq = W[r, p], W[r, q]
                W[r, p], W[r, q] = c * wp - s * wq, s * wp + c * wq
                vp, vq = V[r, p], V[r, q]
                V[r, p], V[r, q] = c * vp - s * vq, s * vp + c * vq
        if not rotated:
            break
    norms = np.empty(3)
    for k in range(3):
        norms[k] = np.sqrt(W[0, k] * W[0, k] + W[1, k] * W[1, k] + W[2, k] * W[2, k])
    # Descending order of three numbers, written out (a sort costs seconds of compilation, a first run's).
    order = np.empty(3, dtype=np.int64)
    first = 0 if norms[0] >= norms[1] and norms[0] >= norms[2] else (1 if norms[1] >= norms[2] else 2)
    last = 2 if norms[2] < norms[0] and norms[2] < norms[1] else (1 if norms[1] < norms[0] else 0)
    if first == last:  # all three equal
        first, last = 0, 2
    order[0], order[1], order[2] = first, 3 - first - last, last
    U, S, Vt = np.zeros((3, 3)), np.empty(3), np.empty((3, 3))
    for j in range(3):
        k = order[j]
        S[j] = norms[k]
        for r in range(3):
            Vt[j, r] = V[r, k]
            if norms[k] > 0:
                U[r, j] = W[r, k] / norms[k]
    if not S[0] > 0:
        U[0, 0] = 1.0
    if not S[1] > 0:  # any unit vector square to U_0: from the axis least along it
        axis = 0
        for r in range(1, 3):
            if abs(U[r, 0]) < abs(U[axis, 0]):
                axis = r
        for r in range(3):
            U[r, 1] = (1.0 if r == axis else 0.0) - U[axis, 0] * U[r, 0]
        n = np.sqrt(U[0, 1] * U[0, 1] + U[1, 1] * U[1, 1] + U[2, 1] * U[2, 1])
        for r in range(3):
            U[r, 1] /= n
    if not S[2] > 0:
        U[0, 2] = U[1, 0] * U[2, 1] - U[2, 0] * U[1, 1]
        U[1, 2] = U[2, 0] * U[0, 1] - U[0, 0] * U[2, 1]
        U[2, 2] = U[0, 0] * U[1, 1] - U[1, 0] * U[0, 1]
    return U, S, Vt


@njit
def wahba_rotation(B):
    """The rotation R minimising ``sum_i w_i |b_i - R r_i|^2`` from its attitude profile ``B = sum_i w_i b_i
    r_i^T`` (compiled: :func:`solve_wahba`'s SVD method, through :func:`svd_3x3`): ``R = U diag(1, 1, d)
    V^T`` with ``d = det(U V^T)``; where ``U V^T`` is a reflection, the axis of the smallest singular value
    is flipped (``U V^T - 2 u_3 v_3^T``)."""
    U, _, Vt = svd_3x3(B)
    R = np.empty((3, 3))
    for r in range(3):
        for c in range(3):
            R[r, c] = U[r, 0] * Vt[0, c] + U[r, 1] * Vt[1, c] + U[r, 2] * Vt[2, c]
    if (R[0, 0] * (R[1, 1] * R[2, 2] - R[1, 2] * R[2, 1]) - R[0, 1] * (R[1, 0] * R[2, 2] - R[1, 2] * R[2, 0])
            + R[0, 2] * (R[1, 0] * R[2, 1] - R[1, 1] * R[2, 0])) < 0:
        for r in range(3):
            for c in range(3):
                R[r, c] -= 2.0 * U[r, 2] * Vt[2, c]
    return R


@warm_up_with
def _warm_up_svd() -> None:
    wahba_rotation(np.eye(3))


@warm_up_with
def _warm_up_pairs() -> None:
    """Compile :func:`_rotations_from_pairs` (its four stacks always read-only: :func:`rotation_from_pair`) for one
    pattern pair against many catalogue pairs, and stacks on both sides (the focal scan's, the extraction's)."""
    e = np.eye(3)
    rotation_from_pair(e[0], e[1], e[:2], e[1:])
    rotation_from_pair(e[:2], e[1:], e[:2], e[1:])


def rotation_from_rotvec(phi: np.ndarray) -> np.ndarray:
    """``exp([phi]x)``: the rotation matrices (..., 3, 3) of rotation vectors ``phi`` (..., 3) (Rodrigues).

    ``Rotation.from_rotvec(phi).as_matrix()``; one rotation vector (an
    optics fit's trial step, a sequence fit's correction) in Python floats,
    to rounding (~1e-16) and at a quarter of the cost of scipy's object
    (whose Cython does stacks faster than a dozen numpy calls would).
    ``R = cos t I + a [phi]x + b phi phi^T`` with ``t = |phi|``, ``a = sin t
    / t`` and ``b = (1 - cos t) / t^2``, both from ``h = sin(t/2) / (t/2)``
    (no cancellation for small t, 1 at t = 0): ``a = h cos(t/2)``, ``b =
    h^2 / 2``.
    """
    phi = np.asarray(phi, dtype=float)
    if phi.size != 3:
        from scipy.spatial.transform import Rotation

        return Rotation.from_rotvec(phi.reshape(-1, 3)).as_matrix().reshape(phi.shape[:-1] + (3, 3))
    x, y, z = phi.reshape(3).tolist()
    t = math.sqrt(x * x + y * y + z * z)
    h = math.sin(t / 2) / (t / 2) if t > 0 else 1.0
    a, b, c = h * math.cos(t / 2), 0.5 * h * h, math.cos(t)
    return np.array([[c + b * x * x, b * x * y - a * z, b * x * z + a * y],
                     [b * x * y + a * z, c + b * y * y, b * y * z - a * x],
                     [b * x * z - a * y, b * y * z + a * x, c + b * z * z]]).reshape(phi.shape[:-1] + (3, 3))


def rotvec_from_rotation(R: np.ndarray) -> np.ndarray:
    """``log(R)``: the rotation vectors (..., 3) of rotation matrices (..., 3, 3), the inverse of
    :func:`rotation_from_rotvec`.

    ``Rotation.from_matrix(R).as_rotvec()`` to rounding for the rotations
    of a few degrees or less it is used on (a sequence fit's residuals and
    inter-snapshot motions), at a third of its cost: the antisymmetric part
    of R is ``sin t n``, the trace ``1 + 2 cos t``.  That axis loses
    accuracy as t nears 180 degrees, so angles beyond 2 rad go to scipy.
    """
    R = np.asarray(R, dtype=float)
    s = np.empty(R.shape[:-1])
    s[..., 0] = R[..., 2, 1] - R[..., 1, 2]
    s[..., 1] = R[..., 0, 2] - R[..., 2, 0]
    s[..., 2] = R[..., 1, 0] - R[..., 0, 1]
    s *= 0.5
    sin_t = np.sqrt(s[..., 0] * s[..., 0] + s[..., 1] * s[..., 1] + s[..., 2] * s[..., 2])
    t = np.arctan2(sin_t, 0.5 * (R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1.0))
    if (t > 2.0).any():
        from scipy.spatial.transform import Rotation

        return Rotation.from_matrix(R.reshape(-1, 3, 3)).as_rotvec().reshape(R.shape[:-1])
    s *= np.divide(t, sin_t, out=np.ones_like(t), where=sin_t > 0)[..., None]
    return s


def propagate(rotation: np.ndarray, rate_rad_s, dt_s: float) -> np.ndarray:
    """The attitude ``dt_s`` seconds later of a frame turning at the constant body rate ``rate_rad_s``.

    A fixed direction seen from a frame turning at ``w`` (rad/s, body axes)
    moves as ``dv/dt = -w x v``, so ``R(t + dt) = exp(-[w]x dt) R(t)``
    (``rotation`` maps ICRS to the body frame, as everywhere here).
    """
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(-np.asarray(rate_rad_s, dtype=float) * dt_s).as_matrix() @ np.asarray(rotation)
