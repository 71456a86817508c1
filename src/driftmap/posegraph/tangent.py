"""Tangent ordering of SE(3) 6-vectors, and the checks every information matrix goes through.

driftmap (and g2o, and :func:`driftmap.geometry.se3_log`) orders ``[translation, rotation]``; GTSAM's
``Pose3`` orders ``[rotation, translation]``. See the :mod:`driftmap.posegraph` docstring.
"""

from __future__ import annotations

import enum

import numpy as np
from numpy.typing import ArrayLike, NDArray

from driftmap.errors import PoseGraphError

__all__ = [
    "TangentOrder",
    "check_information",
    "information_from_gtsam",
    "information_to_gtsam",
    "reorder_6x6",
]


class TangentOrder(enum.Enum):
    """Order of the six components of an SE(3) tangent vector, covariance or information matrix."""

    TRANSLATION_ROTATION = "translation_rotation"
    """``[tx, ty, tz, rx, ry, rz]``: driftmap, g2o files, :func:`driftmap.geometry.se3_log`."""
    ROTATION_TRANSLATION = "rotation_translation"
    """``[rx, ry, rz, tx, ty, tz]``: GTSAM ``Pose3`` (``Pose3.Logmap``, ``Pose3`` noise models)."""


_SWAP_HALVES = np.array([3, 4, 5, 0, 1, 2])


def reorder_6x6(matrix: ArrayLike, from_order: TangentOrder, to_order: TangentOrder) -> NDArray[np.float64]:
    """Re-express a 6x6 covariance **or** information matrix in another tangent ordering.

    The orders differ by swapping the translation and rotation halves, i.e. ``M' = P M P^T`` with a
    permutation ``P``; since ``(P M P^T)^-1 = P M^-1 P^T`` the same function serves covariances and
    information matrices. Returns a new float64 array.
    """
    M = np.array(matrix, dtype=np.float64, copy=True)
    if M.shape != (6, 6):
        raise PoseGraphError(f"reorder_6x6: expected a 6x6 matrix, got shape {M.shape}")
    if not isinstance(from_order, TangentOrder) or not isinstance(to_order, TangentOrder):
        raise PoseGraphError("reorder_6x6: from_order and to_order must be TangentOrder members")
    if from_order is to_order:
        return M
    return M[np.ix_(_SWAP_HALVES, _SWAP_HALVES)]


def information_to_gtsam(information_6x6: ArrayLike) -> NDArray[np.float64]:
    """Information in driftmap order ``[translation, rotation]`` -> GTSAM ``Pose3`` order ``[rotation, translation]``."""
    return reorder_6x6(information_6x6, TangentOrder.TRANSLATION_ROTATION, TangentOrder.ROTATION_TRANSLATION)


def information_from_gtsam(information_6x6_gtsam: ArrayLike) -> NDArray[np.float64]:
    """Information in GTSAM ``Pose3`` order ``[rotation, translation]`` -> driftmap order ``[translation, rotation]``."""
    return reorder_6x6(information_6x6_gtsam, TangentOrder.ROTATION_TRANSLATION, TangentOrder.TRANSLATION_ROTATION)


def check_information(information: ArrayLike, what: str) -> NDArray[np.float64]:
    """A validated, read-only copy of a 6x6 information matrix (``[translation, rotation]`` order): finite,
    symmetric (to 1e-9 relative; symmetrised), positive definite. ``what`` prefixes the error message."""
    info = np.array(information, dtype=np.float64, copy=True)
    if info.shape != (6, 6):
        raise PoseGraphError(f"{what}: information must be 6x6 ([translation, rotation] order), got shape {info.shape}")
    if not np.all(np.isfinite(info)):
        raise PoseGraphError(f"{what}: information contains NaN or inf")
    scale = float(np.abs(info).max())
    if float(np.abs(info - info.T).max()) > 1e-9 * max(scale, 1.0):
        raise PoseGraphError(f"{what}: information matrix is not symmetric")
    info = 0.5 * (info + info.T)
    try:
        np.linalg.cholesky(info)
    except np.linalg.LinAlgError:
        raise PoseGraphError(f"{what}: information matrix is not positive definite") from None
    info.setflags(write=False)
    return info
