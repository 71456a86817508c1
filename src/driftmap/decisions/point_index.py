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

    def _runs(self, a: NDArray[np.int64], b: NDArray[np.int64], columns: NDArray[np.int64] | None = None,
              keys: NDArray[np.int64] | None = None) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """Start and stop (into the sorted points, or into ``keys``) of the cells ``a .. b`` (inclusive), one run per
        (x, y) column (or per given column, (M, 2), over z ``a[2] .. b[2]``)."""
        keys = self.keys if keys is None else keys
        if columns is None:
            i, j = np.meshgrid(np.arange(a[0], b[0] + 1), np.arange(a[1], b[1] + 1), indexing="ij")
            i, j = i.ravel(), j.ravel()
        else:
            i, j = columns[:, 0], columns[:, 1]
        # a query may reach beyond the grid, where no point lies: its columns there are empty, its z range clipped
        inside = (i >= _CELL_LO) & (i <= _CELL_HI) & (j >= _CELL_LO) & (j <= _CELL_HI)
        if b[2] < _CELL_LO or a[2] > _CELL_HI or a[2] > b[2]:
            inside[:] = False
        za, zb = np.clip([a[2], b[2]], _CELL_LO, _CELL_HI)
        starts, stops = np.zeros(len(i), np.int64), np.zeros(len(i), np.int64)
        ii, jj = i[inside], j[inside]
        starts[inside] = np.searchsorted(keys, _pack(ii, jj, np.full_like(ii, za)), "left")
        stops[inside] = np.searchsorted(keys, _pack(ii, jj, np.full_like(ii, zb)), "right")
        return starts, stops

    @staticmethod
    def _gather(starts: NDArray[np.int64], stops: NDArray[np.int64]) -> NDArray[np.int64]:
        """The sorted positions of the runs, concatenated."""
        n = stops - starts
        keep = n > 0
        starts, n = starts[keep], n[keep]
        total = int(n.sum())
        if total == 0:
            return np.zeros(0, np.int64)
        shift = np.repeat(starts - np.concatenate([[0], np.cumsum(n)[:-1]]), n)
        return shift + np.arange(total, dtype=np.int64)

    def _result(self, at: NDArray[np.int64]) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """The points at sorted positions ``at``, in map order, as float64, and their frames."""
        g = np.sort(self.order[at]).astype(np.int64)  # their indices in the view: map order
        per_frame = np.diff(np.searchsorted(g, self.starts))  # g is sorted: each frame's points are one run of it
        return self.world[g].astype(np.float64), np.repeat(self.frame_ids, per_frame)

    def _in_box(self, at: NDArray[np.int64], lo: NDArray[np.float64], hi: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Which of the sorted positions ``at`` hold a point with ``lo <= p <= hi`` (compared in float64: ``lo`` and
        ``hi`` are float64 arrays, their items float64 scalars, so the float32 coordinates are promoted)."""
        p = self.points[at]
        inside = (p[:, 0] >= lo[0]) & (p[:, 0] <= hi[0])
        inside &= (p[:, 1] >= lo[1]) & (p[:, 1] <= hi[1])
        inside &= (p[:, 2] >= lo[2]) & (p[:, 2] <= hi[2])
        return inside

    # ------------------------------------------------------------------------------------------- queries
    def box(self, lo: NDArray[np.float64], hi: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """The points with ``lo <= p <= hi`` (per axis, float64) and their frames, in map order."""
        lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
        if np.any(hi < lo):
            return np.zeros((0, 3)), np.zeros(0, np.int64)
        at = self._gather(*self._runs(*self._cell_range(lo, hi)))
        return self._result(at[self._in_box(at, lo, hi)])

    def ball(self, centre: NDArray[np.float64], radius_m: float) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """The points with ``dx*dx + dy*dy + dz*dz <= radius_m**2`` (float64) and their frames, in map order."""
        c = np.asarray(centre, dtype=np.float64)
        at = self._gather(*self._runs(*self._cell_range(c - radius_m, c + radius_m)))
        p = self.points[at]
        dx, dy, dz = p[:, 0] - c[0], p[:, 1] - c[1], p[:, 2] - c[2]  # float64 (c's items are float64 scalars)
        return self._result(at[dx * dx + dy * dy + dz * dz <= radius_m**2])

    def frames_in_box(self, lo: NDArray[np.float64], hi: NDArray[np.float64]) -> NDArray[np.int64]:
        """The frames (sorted) with a point in the box ``lo .. hi``: every frame of a cell lying wholly inside it
        (floor(p / cell) strictly between the box's corner cells on every axis), and of the points of the border
        cells those of the other frames that pass the box test."""
        lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
        if np.any(hi < lo):
            return np.zeros(0, np.int64)
        a, b = self._cell_range(lo, hi)
        found = np.zeros(len(self.frame_ids), bool)
        if np.all(b - a >= 2):  # inner cells: a + 1 .. b - 1 on every axis (their points are inside the box)
            found[self.pair_rows[self._gather(*self._runs(a + 1, b - 1, keys=self.pair_keys))]] = True
            ii, jj = np.meshgrid(np.arange(a[0], b[0] + 1), np.arange(a[1], b[1] + 1), indexing="ij")
            ii, jj = ii.ravel(), jj.ravel()
            rim = (ii == a[0]) | (ii == b[0]) | (jj == a[1]) | (jj == b[1])
            cols_rim = np.column_stack([ii[rim], jj[rim]])
            cols_in = np.column_stack([ii[~rim], jj[~rim]])
            border = [self._runs(a, b, cols_rim),  # the rim columns, whole
                      self._runs(a, np.array([b[0], b[1], a[2]]), cols_in),  # the bottom and top cells of the rest
                      self._runs(np.array([a[0], a[1], b[2]]), b, cols_in)]
            at = self._gather(np.concatenate([s for s, _ in border]), np.concatenate([t for _, t in border]))
        else:
            at = self._gather(*self._runs(a, b))
        at = at[~found[self.rows[at]]]
        if len(at):
            found[self.rows[at[self._in_box(at, lo, hi)]]] = True
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
