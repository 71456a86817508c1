"""What every decision reads from the map, and what it reports about its evidence: the contributing frames, the
stamp of the newest, the revision that set each frame's pose, and the uncertainty.

The **uncertainty** of a decision (metres) is the larger of

- the *frame spread* at its evidence point: the map points within ``spread_radius_m`` of the point are grouped by
  the frame that measured them; each frame with at least ``spread_min_points`` of them places the surface at the
  median of its points' offsets along the surface normal; the spread is the distance between the nearest and the
  farthest of these placements. On a consistent map it is the depth noise of a frame's median (a few mm); where the
  frames' poses disagree -- drift, a wrong loop, a step -- it is how far apart they put the surface the decision
  hinges on. It is the pose uncertainty of the contributing frames as it shows at the point, measured from the data;
- the *pose marginal* at its evidence point, where the revision's poses came from an optimised pose graph (the
  loop closure stores GTSAM's marginal covariance of every keyframe with its revision; a frame between keyframes
  takes its nearest keyframe's): each contributing frame's 6x6 covariance propagated to the evidence point
  (``J = R [I, -[p]x]``, ``p`` the point in the frame's sensor frame), the square root of the largest eigenvalue
  of ``J Sigma J^T``, the median over the contributing frames (the gauge is the first keyframe: it says how well
  the graph places the evidence relative to where the map starts);
- the separation of the largest double wall ``diagnose`` flagged within ``double_wall_reach_m`` of the query's
  region, when a diagnosis of the revision is given.

None when neither can be measured (fewer than two frames near the evidence and no diagnosis in reach).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from driftmap.decisions.point_index import PointIndex, point_index
from driftmap.decisions.settings import DecideConfig
from driftmap.decisions.walls import DoubleWall, walls_in_reach
from driftmap.kernels.queries import group_medians as _group_medians

if TYPE_CHECKING:
    from driftmap.map.view import MapView
    from driftmap.store.frame_store import FrameStore
    from driftmap.volume.layers import VolumeLayers


@dataclass
class DecisionContext:
    """The map of one revision as the deciders read it (layers, map view, frame stamps and poses)."""

    store: FrameStore
    revision: int
    layers: VolumeLayers
    config: DecideConfig
    double_walls: list[DoubleWall] = field(default_factory=list)
    _stamps: dict[int, int] = field(default_factory=dict)
    _origins: dict[int, NDArray[np.float64]] = field(default_factory=dict)
    _pose_revision: dict[int, int] | None = None
    _covariances: dict[int, NDArray[np.float64]] | None = None
    _point_index: PointIndex | None = None
    _spread: dict[tuple[bytes, bytes | None], float | None] = field(default_factory=dict)
    """frame spreads already measured, by evidence point and normal (queries often share an evidence point)"""

    def __post_init__(self) -> None:
        ids = np.asarray(self.store.frame_ids, dtype=np.int64)
        self._stamps = dict(zip(ids.tolist(), np.asarray(self.store.ledger.stamps_ns).tolist()))

    @property
    def view(self) -> MapView:
        assert self.layers.view is not None
        return self.layers.view

    @property
    def voxel_m(self) -> float:
        return float(self.layers.grid.voxel_size_m)

    @property
    def max_range_m(self) -> float | None:
        r = self.layers.config.max_range_m
        return None if r is None else float(r)

    # ------------------------------------------------------------------------------------------- points
    def origin(self, frame_id: int) -> NDArray[np.float64]:
        o = self._origins.get(frame_id)
        if o is None:
            o = self._origins[frame_id] = self.view.pose(frame_id)[:3, 3].copy()
        return o

    def points_in_box(self, lo: NDArray[np.float64], hi: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """Full-resolution map points (float64) inside the world box (inclusive) and their frames, in map order; with
        ``range_limited_points`` only those within the volume's max range of their sensor (the depth the layers
        trust as hits). From the :class:`~driftmap.decisions.point_index.PointIndex` of the revision: the same
        points as ``view.query_box`` followed by the range cut."""
        return self.point_index.box(lo, hi)

    def points_in_ball(self, center: NDArray[np.float64], radius_m: float) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """As :meth:`points_in_box`, within ``radius_m`` of ``center`` (``view.query_radius``)."""
        return self.point_index.ball(center, radius_m)

    def frames_in_box(self, lo: NDArray[np.float64], hi: NDArray[np.float64]) -> NDArray[np.int64]:
        """The frames of :meth:`points_in_box`, without gathering the points."""
        return self.point_index.frames_in_box(lo, hi)

    @property
    def point_index(self) -> PointIndex:
        if self._point_index is None:
            self._point_index = point_index(self.layers, self.config.range_limited_points)
        return self._point_index

    def prepare_shared(self) -> None:
        """Build what the queries would otherwise build on first use (the point index, the frames' pose revisions,
        the pose covariances; the layers' structures are :func:`~driftmap.decisions.decide.prepare`'s), so that
        queries answered in several threads only read it."""
        _ = self.point_index
        self.pose_revisions([])
        self.covariances()

    def covariances(self) -> dict[int, NDArray[np.float64]]:
        """The revision's pose covariances by frame (read from the ledger once)."""
        if self._covariances is None:
            self._covariances = self.store.ledger.covariances(self.revision)
        return self._covariances

    # ------------------------------------------------------------------------------------------- frames
    def frames_report(self, frames: NDArray[np.int64] | list[int]) -> tuple[list[int], int | None]:
        """Sorted unique frame ids and the stamp of the newest (None without frames)."""
        ids = np.unique(np.asarray(frames, dtype=np.int64).ravel()).tolist()  # sorted, as Python ints
        stamps = [self._stamps[f] for f in ids if f in self._stamps]
        return ids, (max(stamps) if stamps else None)

    def pose_revisions(self, frames: list[int]) -> list[int]:
        """For each frame, the revision in this revision's ancestry that last set its pose (0: the poses that
        produced the frames)."""
        if self._pose_revision is None:
            self._pose_revision = self._ancestry_pose_revisions()
        return [self._pose_revision.get(int(f), 0) for f in frames]

    def _ancestry_pose_revisions(self) -> dict[int, int]:
        by_id = {r.revision_id: r for r in self.store.revisions}
        out: dict[int, int] = {}
        rev = by_id.get(self.revision)
        while rev is not None and rev.parent_id is not None:
            for f in (*rev.set_directly.keys(), *rev.propagated.keys()):
                out.setdefault(int(f), rev.revision_id)
            rev = by_id.get(rev.parent_id)
        return out

    # -------------------------------------------------------------------------------------- uncertainty
    def frame_spread_m(self, point: NDArray[np.float64] | None, normal: NDArray[np.float64] | None = None) -> float | None:
        """How far apart the frames near ``point`` place the surface along ``normal`` (fitted when None)."""
        if point is None:
            return None
        key = (np.asarray(point, dtype=np.float64).tobytes(),
               None if normal is None else np.asarray(normal, dtype=np.float64).tobytes())
        if key not in self._spread:
            self._spread[key] = self._frame_spread_m(point, normal)
        return self._spread[key]

    def _frame_spread_m(self, point: NDArray[np.float64], normal: NDArray[np.float64] | None) -> float | None:
        """:meth:`PointIndex.spread` (compiled); :func:`frame_spread_numpy` is the same in numpy."""
        return self.point_index.spread(point, self.config.spread_radius_m, normal, self.config.spread_min_points)

    def pose_marginal_m(self, point: NDArray[np.float64] | None, frames: list[int]) -> float | None:
        """The median over ``frames`` of the pose covariance propagated to ``point`` (module docstring); None
        without a point or without frames whose pose carries a covariance."""
        known = self.covariances()
        covs = [(f, known[f]) for f in frames if f in known]
        if point is None or not covs:
            return None
        T = np.stack([self.view.pose(f) for f, _ in covs])
        R = T[:, :3, :3]
        p = np.einsum("nji,nj->ni", R, np.asarray(point, dtype=np.float64) - T[:, :3, 3])  # R^T (x - t)
        skew = np.zeros((len(p), 3, 3))
        skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -p[:, 2], p[:, 1], -p[:, 0]
        skew -= skew.transpose(0, 2, 1)
        J = R @ np.concatenate([np.broadcast_to(np.eye(3), skew.shape), -skew], axis=2)  # (n, 3, 6)
        S = J @ np.stack([c for _, c in covs]) @ J.transpose(0, 2, 1)
        return float(np.median(np.sqrt(np.clip(np.linalg.eigvalsh(S)[:, -1], 0.0, None))))

    def uncertainty(self, lo: NDArray[np.float64], hi: NDArray[np.float64], point: NDArray[np.float64] | None,
                    normal: NDArray[np.float64] | None = None,
                    frames: list[int] | None = None) -> tuple[float | None, dict, list[DoubleWall]]:
        """The decision's uncertainty (module docstring), its parts, and the double walls in reach."""
        spread = self.frame_spread_m(point, normal)
        marginal = self.pose_marginal_m(point, frames or [])
        walls = walls_in_reach(self.double_walls, lo, hi, self.config.double_wall_reach_m)
        wall_m = max((w.separation_m for w in walls), default=None)
        parts = {"frame_spread_m": spread, "double_wall_separation_m": wall_m, "pose_marginal_m": marginal}
        values = [v for v in (spread, wall_m, marginal) if v is not None]
        return (max(values) if values else None), parts, walls

    def finish(self, decision: str, failure: str | None, lo: NDArray[np.float64], hi: NDArray[np.float64],
               point: NDArray[np.float64] | None, frames: NDArray[np.int64] | list[int],
               normal: NDArray[np.float64] | None = None) -> dict:
        """The fields every decision shares: frames, freshness, uncertainty, the failure label (a passing decision
        with a double wall in reach is labelled ``double_wall_nearby``)."""
        ids, newest = self.frames_report(frames)
        unc, parts, walls = self.uncertainty(lo, hi, point, normal, ids)
        if failure is None and walls:
            failure = "double_wall_nearby"
        return {"decision": decision, "failure_label": failure, "frames": ids, "stamp_ns_newest": newest,
                "uncertainty": unc, "evidence_m": point,
                "details": {"uncertainty_parts": parts, "frame_pose_revisions": self.pose_revisions(ids),
                            "double_walls_in_reach": [w.to_json() for w in walls]}}


def frame_spread_numpy(pts: NDArray[np.float64], fids: NDArray[np.int64], point: NDArray[np.float64],
                       normal: NDArray[np.float64] | None, min_count: int) -> float | None:
    """The frame spread (module docstring) of the points ``pts`` (measured by the frames ``fids``) around ``point``
    along ``normal`` (None: the smallest principal axis of the points), in numpy: what
    :func:`driftmap.kernels.spread.frame_spread` computes (to a few units of rounding; the reference of its test)."""
    if len(pts) < 2 * min_count:
        return None
    if normal is None:
        centred = pts - pts.mean(axis=0)
        normal = np.linalg.eigh(centred.T @ centred)[1][:, 0]
    offsets = (pts - point) @ np.asarray(normal, dtype=np.float64)
    placed = group_medians(offsets, fids, min_count)
    if len(placed) < 2:
        return None
    return float(placed.max() - placed.min())


def unique_ids(ids: NDArray[np.int64]) -> NDArray[np.int64]:
    """``np.unique(ids)`` (sorted int64) of frame ids: from a count table when they span a small range."""
    ids = np.asarray(ids, dtype=np.int64)
    if len(ids) == 0:
        return ids
    lo, hi = int(ids.min()), int(ids.max())
    if hi - lo <= 4 * len(ids) + 4096:
        return np.flatnonzero(np.bincount(ids - lo)) + lo
    return np.unique(ids)


def id_ranks(ids: NDArray[np.int64], uniq: NDArray[np.int64]) -> NDArray[np.int64]:
    """Each id's position in ``uniq`` (sorted, holding every id: ``np.searchsorted(uniq, ids)``), from a lookup table
    when they span a small range (a binary search per id costs tens of times more)."""
    ids = np.asarray(ids, dtype=np.int64)
    if len(ids) == 0 or len(uniq) == 0:
        return np.zeros(len(ids), np.int64)
    lo, hi = int(uniq[0]), int(uniq[-1])
    if hi - lo <= 4 * len(ids) + 4096:
        table = np.zeros(hi - lo + 1, np.int64)
        table[uniq - lo] = np.arange(len(uniq))
        return table.take(ids - lo)
    return np.searchsorted(uniq, ids)


def group_medians(values: NDArray[np.float64], groups: NDArray[np.int64], min_count: int) -> NDArray[np.float64]:
    """The median of ``values`` per group (``np.median``'s value: the middle one, or the mean of the two middle
    ones) of the groups with at least ``min_count`` members, in ascending group order. Ids spanning a small range:
    a compiled counting sort by group, each group's values sorted (:func:`driftmap.kernels.queries.group_medians`);
    else the values sorted, then stably by group (a radix sort of the groups' ranks when they fit 16 bits), as
    ``np.lexsort((values, groups))``."""
    groups = np.asarray(groups, dtype=np.int64)
    if len(groups) and int(groups.max()) - int(groups.min()) <= 4 * len(groups) + 4096:  # a count table (compiled)
        first = int(groups.min())
        return _group_medians(np.ascontiguousarray(values, dtype=np.float64), groups, first,
                              int(groups.max()) - first + 1, int(min_count))
    uniq = unique_ids(groups)
    if len(uniq) <= 1 << 16:
        by_value = np.argsort(values)
        rank = id_ranks(groups, uniq).astype(np.uint16)
        order = by_value[np.argsort(rank[by_value], kind="stable")]
    else:
        order = np.lexsort((values, groups))
    v, g = values[order], groups[order]
    starts = np.flatnonzero(np.concatenate([[True], g[1:] != g[:-1]])) if len(g) else np.zeros(0, np.int64)
    counts = np.diff(np.append(starts, len(g)))
    keep = counts >= min_count
    starts, counts = starts[keep], counts[keep]
    lo, hi = v[starts + (counts - 1) // 2], v[starts + counts // 2]
    return np.where(counts % 2 == 1, lo, (lo + hi) / 2.0)
