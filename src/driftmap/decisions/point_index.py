"""The map points the decisions read, indexed once per revision: the full-resolution points of the map view (with
``range_limited_points``, only those within the volume's max range of their sensor, the depth the layers trust as
hits), sorted into cubic cells so that a box or a ball is answered from the cells it overlaps.

It answers exactly what :meth:`MapView.query_box` / :meth:`MapView.query_radius` followed by the range cut answer
(the same float64 comparisons, the points in map order: frame by frame, each frame's points in their stored order),
without reading a point of the cells a query does not overlap and without a range test per query;
:meth:`PointIndex.frames_in_box` gives only the frames with a point in a box, testing only the points of the cells on
the box's border whose frame no inner cell holds (the inner cells' frames come from the (cell, frame) pairs). Built by :func:`point_index` and cached on the layers until they
change (``DecisionContext`` reads it; ``decide.prepare`` builds it before the first query).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from driftmap.kernels.queries import ball_positions, box_positions, column_runs, frames_in_box, gather_in_map_order
from driftmap.kernels.regions import gather_with_voxels
from driftmap.kernels.spread import frame_spread
from driftmap.voxels import ABSOLUTE_GRID

if TYPE_CHECKING:
    from driftmap.map.view import MapView
    from driftmap.volume.layers import VolumeLayers

CELL_M = 0.05
"""the index's cell side (m): a grasp ROI or a 5 cm ball overlaps a few dozen cells, a 1 m explore box 8,000"""
CHUNK_POINTS = 1 << 20
_CELL_LO, _CELL_HI = ABSOLUTE_GRID.lo[0], ABSOLUTE_GRID.hi[0]
"""the cells the index keys hold per axis (:data:`~driftmap.voxels.ABSOLUTE_GRID`: +-52 km at 5 cm)"""


def _pack(i: NDArray[np.int64], j: NDArray[np.int64], k: NDArray[np.int64]) -> NDArray[np.int64]:
    """Cell keys on the absolute grid (sorted keys run z fastest, then y, then x); a :class:`ConfigError` for a
    cell beyond it (a map that far from its origin)."""
    return ABSOLUTE_GRID.pack((i, j, k), "the decisions' point index (5 cm cells)")


def in_range_mask(points: NDArray[np.float64], frame_rows: NDArray[np.int64], origins: NDArray[np.float64],
                  max_range_m: float) -> NDArray[np.bool_]:
    """Which points lie within ``max_range_m`` of their frame's sensor origin (``origins[frame_rows]``), computed as
    ``np.linalg.norm(points - origin, axis=1) <= max_range_m``."""
    d = points - origins[frame_rows]
    return np.sqrt(np.add.reduce(d * d, axis=1)) <= max_range_m


@dataclass
class PointIndex:
    """The points sorted by cell (module docstring)."""

    keys: NDArray[np.int64]
    """per sorted point, its packed cell (ascending)"""
    points: NDArray[np.float32]
    """(N, 3) world points, in cell order"""
    order: NDArray[np.integer]
    """per sorted point, its index in the view's points (map order; int32 below 2**31 points)"""
    rows: NDArray[np.int32]
    """per sorted point, its frame's row in :attr:`frame_ids`"""
    frame_ids: NDArray[np.int64]
    cell_m: float
    world: NDArray[np.float32]
    """the view's points (a reference, not a copy): the results are read from them in map order"""
    starts: NDArray[np.int64]
    """per frame row, where its points start in :attr:`world` (and the end, last)"""
    pair_keys: NDArray[np.int64] | None = None
    """per (cell, frame) holding points, the cell (ascending; the frames of a cell ascending)"""
    pair_rows: NDArray[np.int32] | None = None
    """per (cell, frame), the frame's row"""

    def __post_init__(self) -> None:
        if len(self.points):  # the cells the points occupy: a query's cell range is cut to them
            self._extent = (np.floor(self.points.min(axis=0).astype(np.float64) / self.cell_m).astype(np.int64),
                            np.floor(self.points.max(axis=0).astype(np.float64) / self.cell_m).astype(np.int64))
        else:
            self._extent = (np.zeros(3, np.int64), np.full(3, -1, np.int64))  # a range nothing falls in
        if self.pair_keys is None:
            first = np.ones(len(self.keys), bool)
            first[1:] = (self.keys[1:] != self.keys[:-1]) | (self.rows[1:] != self.rows[:-1])
            self.pair_keys, self.pair_rows = self.keys[first], self.rows[first]

    @classmethod
    def build(cls, view: MapView, max_range_m: float | None, cell_m: float = CELL_M) -> PointIndex:
        world = view.points_world
        frame_ids = np.asarray(view.frame_ids, dtype=np.int64)
        counts = np.array([len(view.frame_points_world(int(f))) for f in frame_ids], dtype=np.int64)
        rows = np.repeat(np.arange(len(frame_ids), dtype=np.int32), counts)
        origins = (np.stack([view.pose(int(f))[:3, 3] for f in frame_ids]) if len(frame_ids)
                   else np.zeros((0, 3)))
        sel, keys = [], []
        for start in range(0, len(world), CHUNK_POINTS):  # chunks bound the float64 copies
            pts = np.asarray(world[start:start + CHUNK_POINTS], dtype=np.float64)
            keep = np.all(np.isfinite(pts), axis=1)  # a NaN point matches no query and is in no range
            if max_range_m is not None:
                keep &= in_range_mask(pts, rows[start:start + CHUNK_POINTS], origins, float(max_range_m))
            cells = np.floor(pts[keep] / cell_m).astype(np.int64)
            sel.append(start + np.flatnonzero(keep))
            keys.append(_pack(cells[:, 0], cells[:, 1], cells[:, 2]))
        sel_a = np.concatenate(sel) if sel else np.zeros(0, np.int64)
        keys_a = np.concatenate(keys) if keys else np.zeros(0, np.int64)
        by_cell = np.argsort(keys_a, kind="stable")  # map order within a cell
        order = sel_a[by_cell]
        return cls(keys_a[by_cell], np.ascontiguousarray(world[order]),
                   order.astype(np.int32) if len(world) < 2**31 else order, rows[order], frame_ids, float(cell_m),
                   world, np.concatenate([[0], np.cumsum(counts)]).astype(np.int64))

    @property
    def nbytes(self) -> int:
        return int(self.keys.nbytes + self.points.nbytes + self.order.nbytes + self.rows.nbytes
                   + self.pair_keys.nbytes + self.pair_rows.nbytes)

    # ------------------------------------------------------------------------------------------- cells
    def _cell_range(self, lo: NDArray[np.float64], hi: NDArray[np.float64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """The cells of the box ``lo .. hi`` that points occupy at all (cut to their extent, so that a box far
        larger than the map costs what the map does; empty, ``a > b``, when it misses them)."""
        e_lo, e_hi = self._extent
        a = np.floor(np.maximum(lo, (e_lo - 1) * self.cell_m) / self.cell_m).astype(np.int64)
        b = np.floor(np.minimum(hi, (e_hi + 2) * self.cell_m) / self.cell_m).astype(np.int64)
        return np.maximum(a, e_lo - 1), np.minimum(b, e_hi + 1)

    def _column_runs(self, a: NDArray[np.int64], b: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """:meth:`_runs` of the cells ``a .. b``, one per (x, y) column (compiled)."""
        return column_runs(self.keys, a, b, _CELL_LO, _CELL_HI, ABSOLUTE_GRID.lo, ABSOLUTE_GRID.span)

    def _gather(self, positions: NDArray[np.int64]) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """The points at ``positions`` of the cell-sorted arrays (any order), in map order, as float64, and their frames
        (compiled: a radix sort of their map indices, the rows read from the sorted arrays)."""
        return gather_in_map_order(self.points, self.order, self.rows, self.frame_ids, positions)

    # ------------------------------------------------------------------------------------------- queries
    def box(self, lo: NDArray[np.float64], hi: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """The points with ``lo <= p <= hi`` (per axis, float64) and their frames, in map order."""
        lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
        if np.any(hi < lo):
            return np.zeros((0, 3)), np.zeros(0, np.int64)
        return self._gather(box_positions(self.points, *self._column_runs(*self._cell_range(lo, hi)), lo, hi))

    def box_with_voxels(self, lo: NDArray[np.float64], hi: NDArray[np.float64], voxel_rows: NDArray[np.integer]
                        ) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.int64]]:
        """:meth:`box` and each point's entry of ``voxel_rows`` (one per index point, in the index's cell order)."""
        lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
        if np.any(hi < lo):
            return np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0, np.int64)
        positions = box_positions(self.points, *self._column_runs(*self._cell_range(lo, hi)), lo, hi)
        return gather_with_voxels(self.points, self.order, self.rows, self.frame_ids, voxel_rows, positions)

    def ball(self, centre: NDArray[np.float64], radius_m: float) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """The points with ``dx*dx + dy*dy + dz*dz <= radius_m**2`` (float64) and their frames, in map order."""
        c = np.asarray(centre, dtype=np.float64)
        runs = self._column_runs(*self._cell_range(c - radius_m, c + radius_m))
        return self._gather(ball_positions(self.points, *runs, c, float(radius_m) ** 2))

    def spread(self, centre: NDArray[np.float64], radius_m: float, normal: NDArray[np.float64] | None,
               min_count: int) -> float | None:
        """The frame spread (m) of the points of :meth:`ball` around ``centre`` along ``normal`` (None: fitted to
        them), as :mod:`driftmap.decisions.evidence` defines it, in one compiled pass
        (:func:`driftmap.kernels.spread.frame_spread`); None where it cannot be measured."""
        c = np.asarray(centre, dtype=np.float64)
        positions = ball_positions(self.points, *self._column_runs(*self._cell_range(c - radius_m, c + radius_m)), c,
                                   float(radius_m) ** 2)
        fit = normal is None
        n = np.zeros(3) if fit else np.ascontiguousarray(normal, dtype=np.float64).reshape(3)
        value = frame_spread(self.points, self.rows, len(self.frame_ids), positions, c, n, fit, int(min_count))
        return None if np.isnan(value) else float(value)

    def frames_in_box(self, lo: NDArray[np.float64], hi: NDArray[np.float64]) -> NDArray[np.int64]:
        """The frames (sorted) with a point in the box ``lo .. hi``: every frame of a cell lying wholly inside it
        (floor(p / cell) strictly between the box's corner cells on every axis), and of the points of the border
        cells those of the other frames that pass the box test (compiled)."""
        lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
        if np.any(hi < lo):
            return np.zeros(0, np.int64)
        a, b = self._cell_range(lo, hi)
        found = frames_in_box(self.keys, self.points, self.rows, self.pair_keys, self.pair_rows, len(self.frame_ids),
                              a, b, lo, hi, _CELL_LO, _CELL_HI, ABSOLUTE_GRID.lo, ABSOLUTE_GRID.span)
        return self.frame_ids[found]  # frame_ids in view order; sorted below by the caller's np.unique


def point_index(layers: VolumeLayers, range_limited: bool) -> PointIndex:
    """The decisions' :class:`PointIndex` of the layers' map view (points within the volume's max range of their
    sensor when ``range_limited`` and the volume has one); cached on the layers until they change."""
    max_range = layers.config.max_range_m if range_limited else None
    key = f"decisions_point_index_{max_range}"
    hit = layers.cache.get(key)
    if hit is not None and hit[0] == layers.version:
        return hit[1]
    assert layers.view is not None
    index = PointIndex.build(layers.view, None if max_range is None else float(max_range))
    for k in [k for k in layers.cache if k.startswith("decisions_point_index_")]:
        del layers.cache[k]  # one index at a time: a stale one holds ~30 bytes per point
    layers.cache[key] = (layers.version, index)
    return index
