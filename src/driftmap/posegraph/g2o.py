"""The g2o file format: reading 3D (``VERTEX_SE3:QUAT`` / ``EDGE_SE3:QUAT``) and 2D (``VERTEX_SE2`` /
``EDGE_SE2``, lifted into the z = 0 plane of SE(3)) files into a pose graph, and writing 3D files at full
double precision. The information matrices of g2o files are in driftmap order ``[translation, rotation]``."""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Protocol

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from driftmap import geometry
from driftmap.errors import OutputWriteError, PoseGraphError
from driftmap.posegraph.factors import gtsam_call
from driftmap.posegraph.measurements import MAX_NODE_KEY, Edge
from driftmap.posegraph.robust import RobustKernel
from driftmap.posegraph.tangent import information_from_gtsam
from driftmap.store.guards import atomic_output, refuse_inside_store

__all__ = [
    "PLANAR_OUT_OF_PLANE_INFORMATION",
    "NON_PD_CHOICES",
    "G2oTarget",
    "check_g2o_lines",
    "g2o_is_3d",
    "lift_information_2d",
    "lift_pose2",
    "read_g2o_into",
    "write_g2o",
]

logger = logging.getLogger(__name__)

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

    def add_prior(self, key: int) -> object: ...


def read_g2o_into(
    graph: G2oTarget, path: Path, *, loop_robust: RobustKernel, loop_robust_param: float | None,
    non_pd_information: str = "refuse",
) -> bool:
    """Add the nodes, then the edges, of the g2o file ``path`` to ``graph``; returns whether the file is 3D.

    An edge with ``key_to == key_from + 1`` is odometry, any other one a loop with ``loop_robust`` (see
    :meth:`PoseGraph.from_g2o`).
    """
    is3d = g2o_is_3d(path)
    fixed = check_g2o_lines(path, non_pd_information=non_pd_information)
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
    for key in fixed:  # g2o's FIX: these nodes hold their initial pose (instead of the default prior's lowest key)
        graph.add_prior(key)
    return is3d


_G2O_LAYOUT = {  # tag: (ids, pose numbers, information numbers: the upper triangle of a k x k matrix)
    "VERTEX_SE3:QUAT": (1, 7, 0),
    "EDGE_SE3:QUAT": (2, 7, 21),
    "VERTEX_SE2": (1, 3, 0),
    "EDGE_SE2": (2, 3, 6),
}
MAX_G2O_ID = MAX_NODE_KEY  # a g2o id becomes a node key
"""The largest vertex id read (GTSAM keys are unsigned 64-bit; driftmap's are signed)."""


NON_PD_CHOICES = ("refuse", "gtsam")
"""``non_pd_information``: an edge whose information matrix is not positive definite is refused, or read as
``gtsam.readG2o`` reads it (the Cholesky factor ``R`` of its lower triangle, taken without a check, as ``R^T R``:
another matrix; the shared ``cubicle.g2o`` has 5021 such edges of 16869), with a warning counting them."""


def check_g2o_lines(path: Path, *, non_pd_information: str = "refuse") -> list[int]:
    """Check every line of a g2o file before GTSAM reads it (GTSAM trusts the text: a negative id wraps to a huge
    key, a short line reads as NaN, a matrix that is not positive definite is factorised into another one that is
    (hostile trial 25 B1), a non-unit quaternion is normalised); returns the ids of its ``FIX`` lines.

    Each vertex / edge line must hold exactly its numbers; ids are whole numbers ``0 .. 2**63 - 1``; every number is
    finite; a quaternion is unit length within 1e-3 (as in trajectory files); an edge's information matrix (its upper
    triangle, g2o order) is positive definite. A ``FIX`` line's ids must be vertices of the file. Lines of other
    tags (landmarks, parameters) are not read: a warning counts them. Every error is a
    :class:`~driftmap.errors.PoseGraphError` naming ``path:line``."""
    vertices: set[int] = set()
    fixed: list[tuple[int, int]] = []
    infos: list[tuple[int, str, list[float]]] = []
    edges: list[tuple[int, str, list[int]]] = []
    other: dict[str, int] = {}
    try:
        with path.open(encoding="utf-8", errors="replace") as fh:
            for lineno, line in enumerate(fh, 1):
                tokens = line.split()
                if not tokens or tokens[0].startswith("#"):
                    continue
                tag, rest = tokens[0], tokens[1:]
                if tag == "FIX":
                    fixed.extend((lineno, _g2o_id(path, lineno, t)) for t in rest)
                    continue
                if tag not in _G2O_LAYOUT:
                    other[tag] = other.get(tag, 0) + 1
                    continue
                n_ids, n_pose, n_info = _G2O_LAYOUT[tag]
                if len(rest) != n_ids + n_pose + n_info:
                    raise PoseGraphError(f"{path}:{lineno}: a {tag} line holds {n_ids} id(s), {n_pose} pose numbers"
                                         f"{f' and {n_info} information numbers' if n_info else ''}; this one holds "
                                         f"{len(rest)} values")
                ids = [_g2o_id(path, lineno, t) for t in rest[:n_ids]]
                try:
                    values = [float(t) for t in rest[n_ids:]]
                except ValueError:
                    raise PoseGraphError(f"{path}:{lineno}: {tag} {' '.join(rest[:n_ids])}: not a number among "
                                         f"{' '.join(rest[n_ids:])!r}") from None
                what = f"{path}:{lineno}: {tag} {' -> '.join(map(str, ids))}"
                if not all(np.isfinite(values)):
                    raise PoseGraphError(f"{what}: holds NaN or inf")
                if n_pose == 7:
                    norm = float(np.linalg.norm(values[3:7]))
                    if abs(norm - 1.0) > 1e-3:
                        raise PoseGraphError(f"{what}: quaternion has norm {norm:.4f}, expected 1")
                if n_info:
                    if ids[0] == ids[1]:
                        raise PoseGraphError(f"{what}: an edge must join two different vertices")
                    infos.append((lineno, what, values[n_pose:]))
                    edges.append((lineno, what, ids))
                else:
                    vertices.add(ids[0])
    except OSError as exc:
        raise PoseGraphError(f"cannot read g2o file {path}: {exc}") from exc
    if non_pd_information not in NON_PD_CHOICES:
        raise PoseGraphError(f"non_pd_information must be one of {', '.join(NON_PD_CHOICES)}, got "
                             f"{non_pd_information!r}")
    not_pd = _not_positive_definite(infos)
    if not_pd and non_pd_information == "refuse":
        what, smallest = not_pd[0]
        raise PoseGraphError(f"{what}: the information matrix is not positive definite (smallest eigenvalue "
                             f"{smallest:.3g}; {len(not_pd)} of {len(infos)} edges are not); g2o gives its upper "
                             f"triangle row by row. To read such a file as gtsam.readG2o does (another matrix: the "
                             f"R^T R of a Cholesky factor taken without a check), pass non_pd_information='gtsam'")
    if not_pd:
        logger.warning("%s: %d of %d edges' information matrices are not positive definite (first: %s); read as "
                       "gtsam.readG2o reads them (R^T R of an unchecked Cholesky factor: other matrices)", path,
                       len(not_pd), len(infos), not_pd[0][0])
    for _, what, ids in edges:
        missing = [k for k in ids if k not in vertices]
        if missing:
            raise PoseGraphError(f"{what}: no vertex {missing[0]} in the file")
    for lineno, key in fixed:
        if key not in vertices:
            raise PoseGraphError(f"{path}:{lineno}: FIX {key}: no vertex {key} in the file")
    if other:
        logger.warning("%s: %s not read (driftmap reads VERTEX_SE3:QUAT / EDGE_SE3:QUAT / VERTEX_SE2 / EDGE_SE2 and "
                       "FIX)", path, ", ".join(f"{n} {tag} line{'s' if n > 1 else ''}" for tag, n in other.items()))
    return sorted({key for _, key in fixed})


def _g2o_id(path: Path, lineno: int, token: str) -> int:
    try:
        key = int(token)
    except ValueError:
        key = -1
    if not 0 <= key <= MAX_G2O_ID:
        raise PoseGraphError(f"{path}:{lineno}: id {token!r} is not a whole number 0 .. 2**63 - 1")
    return key


def _not_positive_definite(infos: list[tuple[int, str, list[float]]]) -> list[tuple[str, float]]:
    """The edges whose information (upper triangle, row-major) is not positive definite, in file order, with their
    smallest eigenvalue: eigenvalues of all at once, a Cholesky factorisation confirming each suspect (a badly
    conditioned matrix's smallest eigenvalue may round to <= 0)."""
    found: list[tuple[int, str, float]] = []
    for n_info in (21, 6):
        group = [(lineno, what, v) for lineno, what, v in infos if len(v) == n_info]
        if not group:
            continue
        k = 6 if n_info == 21 else 3
        iu = np.triu_indices(k)
        mats = np.zeros((len(group), k, k))
        mats[:, iu[0], iu[1]] = np.array([v for _, _, v in group])
        mats = mats + np.triu(mats, 1).transpose(0, 2, 1)
        smallest = np.linalg.eigvalsh(mats)[:, 0]
        for i in np.flatnonzero(smallest <= 0):
            try:
                np.linalg.cholesky(mats[i])
            except np.linalg.LinAlgError:
                found.append((group[i][0], group[i][1], float(smallest[i])))
    return [(what, smallest) for _, what, smallest in sorted(found)]


def write_g2o(path: Path, nodes: Mapping[int, NDArray[np.float64]], edges: Sequence[Edge]) -> None:
    """Nodes in key order, then the edges, as ``VERTEX_SE3:QUAT`` / ``EDGE_SE3:QUAT`` lines (``%.17g``)."""
    iu = np.triu_indices(6)
    lines = []
    for key in sorted(nodes):
        lines.append(f"VERTEX_SE3:QUAT {key} " + _g2o_pose(nodes[key]))
    for edge in edges:
        info = " ".join(f"{v:.17g}" for v in edge.information_6x6[iu])
        lines.append(f"EDGE_SE3:QUAT {edge.key_from} {edge.key_to} {_g2o_pose(edge.T_from_to)} {info}")
    refuse_inside_store(path, "PoseGraph.to_g2o")  # hostile trial 25 B7: it wrote over a store's segment
    try:
        with atomic_output(path, "PoseGraph.to_g2o", guard=False) as tmp:
            tmp.write_text("\n".join(lines) + "\n")
    except OutputWriteError as exc:
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
