"""The g2o file format: reading 3D (``VERTEX_SE3:QUAT`` / ``EDGE_SE3:QUAT``) and 2D (``VERTEX_SE2`` /
``EDGE_SE2``, lifted into the z = 0 plane of SE(3)) files into a pose graph, and writing 3D files at full
double precision. The information matrices of g2o files are in driftmap order ``[translation, rotation]``."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Protocol

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from driftmap import geometry
from driftmap.errors import PoseGraphError
from driftmap.posegraph.factors import gtsam_call
from driftmap.posegraph.measurements import Edge
from driftmap.posegraph.robust import RobustKernel
from driftmap.posegraph.tangent import information_from_gtsam

__all__ = [
    "PLANAR_OUT_OF_PLANE_INFORMATION",
    "G2oTarget",
    "g2o_is_3d",
    "lift_information_2d",
    "lift_pose2",
    "read_g2o_into",
    "write_g2o",
]

#: Information (1 / variance) given to the out-of-plane components ``tz, rx, ry`` when a 2D (SE2) g2o file is
#: lifted into SE(3): a stiff constraint that keeps the graph in the plane (sigma 1 mm / 1 mrad), so the lifted
#: problem has the same optimum and the same error as the 2D one.
PLANAR_OUT_OF_PLANE_INFORMATION = 1e6


class G2oTarget(Protocol):
    """What :func:`read_g2o_into` fills: a :class:`~driftmap.posegraph.graph.PoseGraph` (the graph module imports
    this one, so the reader names only the three methods it calls)."""

    def add_node(self, key: int, T_world_x: ArrayLike) -> None: ...

    def add_odometry(self, key_from: int, key_to: int, T_from_to: ArrayLike, information_6x6: ArrayLike, *,
                     robust: RobustKernel = ..., robust_param: float | None = None) -> Edge: ...

    def add_loop(self, key_from: int, key_to: int, T_from_to: ArrayLike, information_6x6: ArrayLike, *,
                 robust: RobustKernel = ..., robust_param: float | None = None) -> Edge: ...


def read_g2o_into(
    graph: G2oTarget, path: Path, *, loop_robust: RobustKernel, loop_robust_param: float | None
) -> bool:
    """Add the nodes, then the edges, of the g2o file ``path`` to ``graph``; returns whether the file is 3D.

    An edge with ``key_to == key_from + 1`` is odometry, any other one a loop with ``loop_robust`` (see
    :meth:`PoseGraph.from_g2o`).
    """
    is3d = g2o_is_3d(path)
    graph_in, values_in = gtsam_call(f"reading {path}", lambda: gtsam.readG2o(str(path), is3d))
    keys = sorted(int(k) for k in values_in.keys())  # noqa: SIM118 -- gtsam.Values is not a Python mapping
    for key in keys:
        T = values_in.atPose3(key).matrix() if is3d else lift_pose2(values_in.atPose2(key))
        graph.add_node(key, T)
    between = gtsam.BetweenFactorPose3 if is3d else gtsam.BetweenFactorPose2
    for i in range(graph_in.size()):
        factor = graph_in.at(i)
        if not isinstance(factor, between):
            raise PoseGraphError(f"{path}: factor {i} is a {type(factor).__name__}, expected {between.__name__}")
        key_from, key_to = (int(k) for k in factor.keys())  # noqa: SIM118 -- a GTSAM factor's keys
        info_gtsam = np.asarray(factor.noiseModel().information(), dtype=np.float64)
        if is3d:
            T_from_to = factor.measured().matrix()
            information = information_from_gtsam(info_gtsam)
        else:
            T_from_to = lift_pose2(factor.measured())
            information = lift_information_2d(info_gtsam)
        if key_to == key_from + 1:
            graph.add_odometry(key_from, key_to, T_from_to, information)
        else:
            graph.add_loop(key_from, key_to, T_from_to, information, robust=loop_robust,
                           robust_param=None if loop_robust is RobustKernel.NONE else loop_robust_param)
    return is3d


def write_g2o(path: Path, nodes: Mapping[int, NDArray[np.float64]], edges: Sequence[Edge]) -> None:
    """Nodes in key order, then the edges, as ``VERTEX_SE3:QUAT`` / ``EDGE_SE3:QUAT`` lines (``%.17g``)."""
    iu = np.triu_indices(6)
    lines = []
    for key in sorted(nodes):
        lines.append(f"VERTEX_SE3:QUAT {key} " + _g2o_pose(nodes[key]))
    for edge in edges:
        info = " ".join(f"{v:.17g}" for v in edge.information_6x6[iu])
        lines.append(f"EDGE_SE3:QUAT {edge.key_from} {edge.key_to} {_g2o_pose(edge.T_from_to)} {info}")
    try:
        path.write_text("\n".join(lines) + "\n")
    except OSError as exc:
        raise PoseGraphError(f"cannot write {path}: {exc}") from exc


def _g2o_pose(T: NDArray[np.float64]) -> str:
    t = T[:3, 3]
    q = Rotation.from_matrix(T[:3, :3]).as_quat()  # x, y, z, w as g2o wants
    return " ".join(f"{v:.17g}" for v in (*t, *q))


def g2o_is_3d(path: Path) -> bool:
    """Whether a g2o file holds SE3 (``True``) or SE2 (``False``) lines; raises on neither or both."""
    kinds = set()
    try:
        with path.open() as fh:
            for line in fh:
                tag = line.split(maxsplit=1)[0] if line.strip() else ""
                if tag.startswith(("VERTEX_SE3", "EDGE_SE3")):
                    kinds.add("3d")
                elif tag.startswith(("VERTEX_SE2", "EDGE_SE2")):
                    kinds.add("2d")
    except OSError as exc:
        raise PoseGraphError(f"cannot read g2o file {path}: {exc}") from exc
    if not kinds:
        raise PoseGraphError(f"{path}: no VERTEX_SE2/SE3 or EDGE_SE2/SE3 lines, not a g2o pose graph")
    if len(kinds) > 1:
        raise PoseGraphError(f"{path}: mixes 2D (SE2) and 3D (SE3) lines")
    return "3d" in kinds


def lift_pose2(pose: gtsam.Pose2) -> NDArray[np.float64]:
    """A GTSAM ``Pose2`` as a 4x4 transform in the z = 0 plane (rotation about z)."""
    return geometry.make_transform(Rotation.from_euler("z", pose.theta()), [pose.x(), pose.y(), 0.0])


def lift_information_2d(info_xyt: NDArray[np.float64]) -> NDArray[np.float64]:
    """3x3 information in GTSAM ``Pose2`` order ``[x, y, theta]`` -> 6x6 driftmap order, stiff out of plane."""
    info = np.diag([0.0, 0.0, PLANAR_OUT_OF_PLANE_INFORMATION, PLANAR_OUT_OF_PLANE_INFORMATION,
                    PLANAR_OUT_OF_PLANE_INFORMATION, 0.0])
    idx = np.array([0, 1, 5])  # tx, ty, rz
    info[np.ix_(idx, idx)] = info_xyt
    return info
