"""What a pose graph is made of: node keys, relative-pose edges (odometry or loop) and absolute priors.

Each measurement validates itself on construction; its information matrix is in driftmap order
``[translation, rotation]`` (see :mod:`driftmap.posegraph.tangent`).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from driftmap import geometry
from driftmap.errors import DriftmapError, PoseGraphError
from driftmap.posegraph.robust import RobustKernel, default_robust_param
from driftmap.posegraph.tangent import check_information

__all__ = [
    "DEFAULT_PRIOR_SIGMA_M",
    "DEFAULT_PRIOR_SIGMA_RAD",
    "Edge",
    "EdgeKind",
    "Prior",
    "check_key",
    "checked_pose",
    "default_prior_information",
]

#: Standard deviations of the default prior that fixes the gauge on the lowest node key (see
#: :meth:`PoseGraph.optimize`). The prior is the only absolute constraint, so its residual is zero at the
#: optimum whatever its strength; "tight" only has to beat the rest of the graph, not be infinite.
DEFAULT_PRIOR_SIGMA_M = 1e-4
DEFAULT_PRIOR_SIGMA_RAD = 1e-4


class EdgeKind(enum.Enum):
    """What an edge measures."""

    ODOMETRY = "odometry"
    """Consecutive-frame odometry: trusted, never down-weighted by GNC (a known inlier)."""
    LOOP = "loop"
    """A loop closure: may be wrong, robust by default, diagnosed in :attr:`PoseGraphResult.loop_residuals`."""


MAX_NODE_KEY = 2**63 - 1
"""The largest pose-graph node key (a frame id)."""


def check_key(key: object, what: str) -> int:
    """``key`` as an ``int`` if it is an integer ``0 .. 2**63 - 1`` (a frame id; GTSAM's keys take no more, the g2o
    reader's ids neither); ``what`` prefixes the error message."""
    if isinstance(key, bool) or not isinstance(key, (int, np.integer)) or not 0 <= key <= MAX_NODE_KEY:
        # (hostile trial 28 B4: 2**64 was taken and optimize() raised GTSAM's raw TypeError)
        raise PoseGraphError(f"{what}: node keys must be integers 0 .. 2**63 - 1 (frame ids), got {key!r}")
    return int(key)


def default_prior_information() -> NDArray[np.float64]:
    """Information of the default prior (:data:`DEFAULT_PRIOR_SIGMA_M`, :data:`DEFAULT_PRIOR_SIGMA_RAD`)."""
    sigmas = np.array([DEFAULT_PRIOR_SIGMA_M] * 3 + [DEFAULT_PRIOR_SIGMA_RAD] * 3)
    return np.diag(1.0 / sigmas**2)


def checked_pose(T: ArrayLike, what: str) -> NDArray[np.float64]:
    """``T`` as a validated rigid 4x4 transform (:func:`driftmap.geometry.as_rigid`), failures as :class:`PoseGraphError`."""
    try:
        return geometry.as_rigid(T, what)
    except DriftmapError as exc:
        raise PoseGraphError(str(exc)) from exc


def _checked_robust_param(kernel: RobustKernel, param: float | None, what: str) -> float | None:
    """The kernel width an edge keeps: ``None`` without a kernel, else ``param`` or the kernel's default."""
    if kernel is RobustKernel.NONE:
        if param is not None:
            raise PoseGraphError(f"{what}: robust_param given without a robust kernel")
        return None
    width = default_robust_param(kernel) if param is None else float(param)
    if not (math.isfinite(width) and width > 0.0):
        raise PoseGraphError(f"{what}: robust_param must be a positive number, got {param!r}")
    return width


@dataclass(frozen=True, slots=True)
class Edge:
    """A relative-pose measurement between two nodes.

    ``T_from_to`` is the measured ``inv(T_world_from) @ T_world_to``. ``information_6x6`` is its inverse
    covariance in **driftmap order** ``[translation(3), rotation(3)]`` (metres, radians), expressed in the
    ``to`` frame's tangent space (right perturbation: ``T_from_to_true = T_from_to @ exp(xi)``), exactly as
    a g2o ``EDGE_SE3:QUAT`` line stores it. ``robust_param`` is the kernel width ``k`` in whitened units
    (``None`` -> :func:`default_robust_param`); it must be ``None`` for :attr:`RobustKernel.NONE`.
    """

    key_from: int
    key_to: int
    T_from_to: NDArray[np.float64]
    information_6x6: NDArray[np.float64]
    kind: EdgeKind
    robust: RobustKernel = RobustKernel.NONE
    robust_param: float | None = None

    def __post_init__(self) -> None:
        key_from = check_key(self.key_from, "Edge.key_from")
        key_to = check_key(self.key_to, "Edge.key_to")
        what = f"edge {key_from}->{key_to}"
        if key_from == key_to:
            raise PoseGraphError(f"{what}: an edge must join two different nodes")
        object.__setattr__(self, "key_from", key_from)
        object.__setattr__(self, "key_to", key_to)
        object.__setattr__(self, "T_from_to", checked_pose(self.T_from_to, f"{what}: T_from_to"))
        object.__setattr__(self, "information_6x6", check_information(self.information_6x6, what))
        if not isinstance(self.kind, EdgeKind):
            raise PoseGraphError(f"{what}: kind must be an EdgeKind, got {self.kind!r}")
        if not isinstance(self.robust, RobustKernel):
            raise PoseGraphError(f"{what}: robust must be a RobustKernel, got {self.robust!r}")
        object.__setattr__(self, "robust_param", _checked_robust_param(self.robust, self.robust_param, what))


@dataclass(frozen=True, slots=True)
class Prior:
    """An absolute pose measurement ``T_world_x`` of node ``key``; information in ``[translation, rotation]`` order."""

    key: int
    T_world_x: NDArray[np.float64]
    information_6x6: NDArray[np.float64]

    def __post_init__(self) -> None:
        key = check_key(self.key, "Prior.key")
        object.__setattr__(self, "key", key)
        object.__setattr__(self, "T_world_x", checked_pose(self.T_world_x, f"prior on node {key}: T_world_x"))
        object.__setattr__(self, "information_6x6", check_information(self.information_6x6, f"prior on node {key}"))
