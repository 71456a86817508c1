"""Rigid-transform helpers.

Conventions: a transform ``T_a_b`` is a 4x4 float64 matrix that maps points expressed in frame ``b`` into
frame ``a`` (``p_a = T_a_b @ p_b``); transforms compose left to right, ``T_a_c = T_a_b @ T_b_c``.
Rotations use scipy's :class:`~scipy.spatial.transform.Rotation`; quaternions are named by their order
(``quat_xyzw`` as in TUM files, ``quat_wxyz`` where a library wants that).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from driftmap.errors import GeometryError, TransformError

#: Tolerance on ``R^T R - I`` (max abs entry) and on ``det(R) - 1`` for a matrix to count as rigid.
#: Real files are written with limited precision (7-Scenes poses are off by up to 4e-4), so a matrix within
#: the tolerance is accepted and its rotation projected onto SO(3); anything further off is rejected.
RIGID_TOLERANCE = 1e-3
MAX_TRANSLATION_M = 1e9
"""No pose of a map lies farther than this from its origin (a million km; Earth-centred coordinates are ~6.4e6 m):
beyond it a pose is a unit or arithmetic error, and float32 world points would overflow (``max change inf m``)."""


_EYE3 = np.eye(3)
_EYE3.setflags(write=False)


def identity() -> NDArray[np.float64]:
    """A fresh 4x4 identity (never use a shared module-level array as a default)."""
    return np.eye(4)


def as_rigid(T: ArrayLike, name: str = "transform", *, tolerance: float = RIGID_TOLERANCE) -> NDArray[np.float64]:
    """Validate ``T`` as a rigid 4x4 transform and return it as a read-only float64 copy.

    A rotation block within ``tolerance`` of orthonormal is replaced by the nearest rotation matrix (SVD
    projection onto SO(3)), so every stored pose is exactly rigid. Raises :class:`TransformError` naming ``name`` when the shape is wrong, an entry is not finite, the
    rotation block is not orthonormal with determinant +1, or the last row is not ``[0, 0, 0, 1]``.
    """
    M = np.array(T, dtype=np.float64, copy=True)
    if M.shape != (4, 4):
        raise TransformError(f"{name}: expected a 4x4 matrix, got shape {M.shape}")
    if not np.all(np.isfinite(M)):
        raise TransformError(f"{name}: contains NaN or inf")
    if float(np.max(np.abs(M[:3, 3]))) > MAX_TRANSLATION_M:
        raise TransformError(f"{name}: translation {M[:3, 3].tolist()} m is beyond {MAX_TRANSLATION_M:g} m from the "
                             f"origin (a unit error? poses are in metres)")
    last = M[3].tolist()
    if max(abs(last[0]), abs(last[1]), abs(last[2]), abs(last[3] - 1.0)) > tolerance:
        raise TransformError(f"{name}: last row must be [0, 0, 0, 1], got {last}")
    R = M[:3, :3]
    ortho_err = float(np.max(np.abs(R.T @ R - _EYE3)))
    if ortho_err > tolerance:
        raise TransformError(f"{name}: rotation block is not orthonormal (max |R^T R - I| = {ortho_err:.3g})")
    (a, b, c), (d, e, f), (g, h, i) = R.tolist()
    det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
    if abs(det - 1.0) > tolerance:
        raise TransformError(f"{name}: rotation block has determinant {det:.6g}, expected +1 (a reflection?)")
    M[3] = (0.0, 0.0, 0.0, 1.0)
    if ortho_err > 1e-12:
        U, _, Vt = np.linalg.svd(R)
        M[:3, :3] = U @ Vt
    M.setflags(write=False)
    return M


def rigid_stack_problems(poses: ArrayLike, *, tolerance: float = RIGID_TOLERANCE) -> tuple[NDArray[np.int64], str | None]:
    """Vectorised rigidity check of an (N, 4, 4) stack (not modified): the rows that are not rigid, and what is
    wrong with the first of them (``None`` when all are). A rigid row is finite, its rotation block is within
    ``tolerance`` of SO(3) (as :func:`as_rigid` checks) and its last row is exactly ``[0, 0, 0, 1]``."""
    T = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    if len(T) == 0:
        return np.zeros(0, np.int64), None
    R = T[:, :3, :3]
    finite = np.all(np.isfinite(T), axis=(1, 2))
    last_row = np.all(T[:, 3] == (0.0, 0.0, 0.0, 1.0), axis=1)
    with np.errstate(invalid="ignore"):
        ortho = np.max(np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)), axis=(1, 2))
        det = np.linalg.det(np.where(finite[:, None, None], R, 0.0))
    with np.errstate(invalid="ignore"):
        near = np.max(np.abs(T[:, :3, 3]), axis=1) <= MAX_TRANSLATION_M
    ok = finite & last_row & (ortho <= tolerance) & (np.abs(det - 1.0) <= tolerance) & near
    bad = np.flatnonzero(~ok)
    if bad.size == 0:
        return bad, None
    i = bad[0]
    reason = (
        "contains NaN or inf"
        if not finite[i]
        else f"last row is {T[i, 3].tolist()}, expected [0, 0, 0, 1]"
        if not last_row[i]
        else f"translation {T[i, :3, 3].tolist()} m is beyond {MAX_TRANSLATION_M:g} m from the origin (a unit error?)"
        if not near[i]
        else f"rotation block is not a rotation (max |R^T R - I| = {ortho[i]:.3g}, det = {det[i]:.6g})"
    )
    return bad, reason


def require_rigid_stack(poses: ArrayLike, frame_ids: ArrayLike, what: str) -> None:
    """:class:`TransformError` naming ``what`` and the frame of the first non-rigid row (see
    :func:`rigid_stack_problems`), and how many rows are bad."""
    bad, reason = rigid_stack_problems(poses)
    if bad.size:
        frame = int(np.asarray(frame_ids).reshape(-1)[bad[0]])
        raise TransformError(f"{what}: pose of frame {frame} {reason} ({bad.size} bad pose(s) in all)")


def invert(T: NDArray[np.float64]) -> NDArray[np.float64]:
    """Inverse of a rigid transform or a (..., 4, 4) stack of them (uses ``R^T``, not a general matrix inverse)."""
    T = np.asarray(T, dtype=np.float64)
    R_t = np.swapaxes(T[..., :3, :3], -1, -2)
    out = np.zeros(T.shape, dtype=np.float64)
    out[..., :3, :3] = R_t
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", R_t, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def make_transform(rotation: ArrayLike | Rotation | None = None, translation_m: ArrayLike | None = None) -> NDArray[np.float64]:
    """Build ``T`` from a 3x3 rotation (or a scipy Rotation) and a translation in metres."""
    T = np.eye(4)
    if rotation is not None:
        T[:3, :3] = rotation.as_matrix() if isinstance(rotation, Rotation) else np.asarray(rotation, dtype=np.float64)
    if translation_m is not None:
        T[:3, 3] = np.asarray(translation_m, dtype=np.float64)
    return T


def from_tum(translation_m: ArrayLike, quat_xyzw: ArrayLike) -> NDArray[np.float64]:
    """Transform from a TUM-style translation and ``(qx, qy, qz, qw)`` quaternion."""
    return make_transform(Rotation.from_quat(np.asarray(quat_xyzw, dtype=np.float64)), translation_m)


def to_tum(T: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(translation_m, quat_xyzw)`` of a rigid transform."""
    return np.array(T[:3, 3]), Rotation.from_matrix(T[:3, :3]).as_quat()


def transform_points(T: NDArray[np.float64], points: NDArray[np.floating]) -> NDArray[np.float32]:
    """Apply ``T`` to an (N, 3) array; the product is computed in float64 and returned as float32."""
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise GeometryError(f"points: expected shape (N, 3), got {pts.shape}")
    R = np.asarray(T[:3, :3], dtype=np.float64)
    t = np.asarray(T[:3, 3], dtype=np.float64)
    return (pts.astype(np.float64, copy=False) @ R.T + t).astype(np.float32)


def rotate_vectors(T: NDArray[np.float64], vectors: NDArray[np.floating]) -> NDArray[np.float32]:
    """Apply only the rotation of ``T`` to (N, 3) direction vectors (normals)."""
    v = np.asarray(vectors, dtype=np.float64)
    return (v @ np.asarray(T[:3, :3]).T).astype(np.float32)


def translation_distance_m(T_a: NDArray[np.float64], T_b: NDArray[np.float64]) -> float:
    """Distance between the origins of two poses, in metres."""
    return float(np.linalg.norm(T_a[:3, 3] - T_b[:3, 3]))


def relative_rotation_angle_rad(R_a: ArrayLike, R_b: ArrayLike) -> NDArray[np.float64]:
    """Angle of ``R_a^T R_b`` for (..., 3, 3) rotations (or the rotation blocks of (..., 4, 4) poses), in radians:
    ``atan2`` of the sine and cosine parts, so it stays precise for tiny angles (unlike ``arccos`` of the trace)."""
    A = np.asarray(R_a, dtype=np.float64)[..., :3, :3]
    B = np.asarray(R_b, dtype=np.float64)[..., :3, :3]
    R = np.swapaxes(A, -1, -2) @ B
    sin_part = 0.5 * np.linalg.norm(
        np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], axis=-1), axis=-1
    )
    cos_part = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    return np.arctan2(sin_part, cos_part)


def rotation_angle_deg(T_a: NDArray[np.float64], T_b: NDArray[np.float64]) -> float:
    """Angle of the relative rotation between two poses, in degrees (precise for tiny angles too)."""
    return float(np.degrees(relative_rotation_angle_rad(T_a, T_b)))


# --------------------------------------------------------------------------------------------------------------
# SE(3) exponential / logarithm and interpolation
#
# A twist ``xi = [rho, phi]`` (6,) holds the translational part ``rho`` (metres) first and the rotation vector
# ``phi`` (radians) second; ``T = exp(xi)`` has ``R = exp(hat(phi))`` and ``t = V(phi) @ rho``. Every function
# below also accepts a leading batch of shape (..., 6) or (..., 4, 4) and works on it without a Python loop.
# --------------------------------------------------------------------------------------------------------------

#: Below this rotation angle (radians) the SE(3) coefficients use their Taylor series instead of the closed form.
_SMALL_ANGLE_RAD = 1e-3


def _hat(phi: NDArray[np.float64]) -> NDArray[np.float64]:
    """Skew-symmetric (..., 3, 3) matrices of (..., 3) vectors: ``hat(a) @ b == cross(a, b)``."""
    x, y, z = phi[..., 0], phi[..., 1], phi[..., 2]
    o = np.zeros_like(x)
    return np.stack(
        [np.stack([o, -z, y], axis=-1), np.stack([z, o, -x], axis=-1), np.stack([-y, x, o], axis=-1)], axis=-2
    )


def se3_exp(xi: ArrayLike) -> NDArray[np.float64]:
    """``T = exp(xi)`` for a twist ``xi = [rho(3), phi(3)]`` (or a (..., 6) stack); exact ``I`` for ``xi = 0``.

    ``R = I + A W + B W^2`` and ``V = I + B W + C W^2`` with ``W = hat(phi)``, ``theta = |phi|``,
    ``A = sin(theta)/theta``, ``B = (1 - cos(theta))/theta^2``, ``C = (theta - sin(theta))/theta^3``; small
    angles use the Taylor series of ``A``, ``B``, ``C`` so there is no division by (almost) zero.
    """
    xi = np.asarray(xi, dtype=np.float64)
    if xi.shape[-1:] != (6,):
        raise GeometryError(f"se3_exp: expected a twist of shape (..., 6), got {xi.shape}")
    rho, phi = xi[..., :3], xi[..., 3:]
    theta = np.linalg.norm(phi, axis=-1)
    theta2 = theta * theta
    small = theta < _SMALL_ANGLE_RAD
    th = np.where(small, 1.0, theta)  # a safe divisor; the small-angle entries use the series below
    A = np.where(small, 1.0 - theta2 / 6.0 + theta2 * theta2 / 120.0, np.sin(th) / th)
    B = np.where(small, 0.5 - theta2 / 24.0 + theta2 * theta2 / 720.0, 2.0 * np.sin(th / 2.0) ** 2 / th**2)
    C = np.where(small, 1.0 / 6.0 - theta2 / 120.0 + theta2 * theta2 / 5040.0, (th - np.sin(th)) / th**3)
    W = _hat(phi)
    W2 = W @ W
    eye = np.eye(3)
    R = eye + A[..., None, None] * W + B[..., None, None] * W2
    V = eye + B[..., None, None] * W + C[..., None, None] * W2
    T = np.zeros(xi.shape[:-1] + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = np.einsum("...ij,...j->...i", V, rho)
    T[..., 3, 3] = 1.0
    return T


def se3_log(T: ArrayLike) -> NDArray[np.float64]:
    """Twist ``[rho(3), phi(3)]`` with ``exp(xi) == T`` (or a (..., 6) stack for (..., 4, 4)); ``|phi| <= pi``.

    The rotation vector comes from scipy (robust up to and at ``pi``); ``rho = V^-1 t`` with
    ``V^-1 = I - W/2 + D W^2``, ``D = (1 - (theta/2) cot(theta/2)) / theta^2`` (Taylor series near zero).
    """
    T = np.asarray(T, dtype=np.float64)
    if T.shape[-2:] != (4, 4):
        raise GeometryError(f"se3_log: expected (..., 4, 4) transforms, got {T.shape}")
    batch = T.shape[:-2]
    phi = Rotation.from_matrix(T[..., :3, :3].reshape(-1, 3, 3)).as_rotvec().reshape(batch + (3,))
    theta = np.linalg.norm(phi, axis=-1)
    theta2 = theta * theta
    small = theta < _SMALL_ANGLE_RAD
    half = np.where(small, 1.0, theta) / 2.0
    D = np.where(
        small,
        1.0 / 12.0 + theta2 / 720.0 + theta2 * theta2 / 30240.0,
        (1.0 - half * np.cos(half) / np.sin(half)) / (4.0 * half * half),
    )
    W = _hat(phi)
    V_inv = np.eye(3) - 0.5 * W + D[..., None, None] * (W @ W)
    rho = np.einsum("...ij,...j->...i", V_inv, T[..., :3, 3])
    return np.concatenate([rho, phi], axis=-1)


def interpolate_se3(T_a: ArrayLike, T_b: ArrayLike, alpha: ArrayLike) -> NDArray[np.float64]:
    """``T_a @ exp(alpha * log(inv(T_a) @ T_b))``: constant-velocity (screw) motion from ``T_a`` (alpha 0)
    to ``T_b`` (alpha 1). ``alpha`` may be a scalar or an (N,) array; ``T_a``/``T_b`` (4, 4) or (N, 4, 4)
    stacks broadcast against it. ``alpha = 0`` returns ``T_a`` exactly; the relative rotation must be < pi.
    """
    T_a = np.asarray(T_a, dtype=np.float64)
    T_b = np.asarray(T_b, dtype=np.float64)
    alpha = np.asarray(alpha, dtype=np.float64)
    delta = se3_log(invert(T_a) @ T_b)
    xi = alpha[..., None] * delta
    return T_a @ se3_exp(xi)
