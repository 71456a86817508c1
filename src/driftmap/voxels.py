"""Voxel keys: integer voxel coordinates packed into one int64 per point, and what is built on them (dense ids,
one point per voxel, per-voxel means). The one implementation the map, the viewer and the diagnostics share.

A point ``p`` lies in voxel ``floor(p / voxel_size_m)`` (:func:`voxel_coords`; the division runs in the points'
own dtype, so float32 points give the float32 voxel a float32 map has always used). Three integer coordinates
become one key on a :class:`VoxelGrid`, a box of ``span`` voxels per axis starting at ``lo``, packed in mixed
radix ``((c0 - lo0) * span1 + (c1 - lo1)) * span2 + (c2 - lo2)``. Keys therefore sort like ``(x, y, z)``
tuples, whatever the grid: the ids below (ranks of the distinct keys) do not depend on which grid packed them.

Two grids, for two kinds of caller (pick with ``grid=`` of :func:`voxel_keys`):

* the **bounding grid** of the points at hand (``grid=None``, :meth:`VoxelGrid.around`): any extent whose box
  holds fewer than ``2**62`` voxels; keys compare only within that one call (the map's voxel fusion and change
  sets, the diagnostics' surface groups and coverage);
* the **absolute grid** :data:`ABSOLUTE_GRID`: 21 bits per axis around the origin (coordinates in
  ``[-2**20, 2**20)``, about +-105 km at 10 cm voxels); keys compare across calls, chunks and point sets (the
  viewer's chunked downsampling, double-wall voxels looked up by map points).

Coordinates a grid cannot hold raise :class:`~driftmap.errors.ConfigError` (use a larger voxel size), a point
with a NaN or infinite coordinate :class:`~driftmap.errors.GeometryError`; nothing wraps or clips silently. Every function is vectorised (numpy sorts and bincounts, no Python loop over points).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from driftmap.errors import ConfigError, GeometryError

KEY_BITS_PER_AXIS = 21
"""Bits per axis of :data:`ABSOLUTE_GRID` (three axes fill 63 bits of an int64)."""
ABSOLUTE_HALF_RANGE = 1 << (KEY_BITS_PER_AXIS - 1)
"""Voxel coordinates on :data:`ABSOLUTE_GRID` lie in ``[-ABSOLUTE_HALF_RANGE, ABSOLUTE_HALF_RANGE)`` per axis."""
BOUNDING_GRID_MAX_VOXELS = 2**62
"""A bounding grid (:meth:`VoxelGrid.around`) must hold fewer voxels than this: keys stay below ``2**62``."""
_INT64_KEY_LIMIT = 2**63
_COORD_LIMIT = float(2**62)
"""|voxel coordinate| below this: ``floor(p / voxel_size_m)`` fits int64 with room for the grids' spans."""
_DENSE_SPAN_PER_KEY = 16
_DENSE_SPAN_MIN = 1 << 22

Coords = NDArray[np.int64] | Sequence[NDArray[np.int64]]
"""Integer voxel coordinates: an (N, 3) array, or three (N,) columns (faster for large N: no strided access)."""


def _columns(coords: Coords) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """Three int64 columns (no copy for int64 input; narrower integers are widened so keys cannot overflow)."""
    if isinstance(coords, np.ndarray):
        if coords.ndim != 2 or coords.shape[1] != 3:
            raise GeometryError(f"voxel coordinates: expected an (N, 3) array, got shape {coords.shape}")
        coords = coords.astype(np.int64, copy=False)
        return coords[:, 0], coords[:, 1], coords[:, 2]
    cols = tuple(np.asarray(c, dtype=np.int64) for c in coords)
    if len(cols) != 3 or len({len(c) for c in cols}) != 1:
        raise GeometryError("voxel coordinates: expected three columns of equal length")
    return cols[0], cols[1], cols[2]


def _check_finite(values: NDArray[np.floating]) -> None:
    if not np.isfinite(values).all():
        bad = int(np.count_nonzero(~np.isfinite(values).reshape(len(values), -1).all(axis=1)))
        raise GeometryError(f"voxel coordinates: {bad} points are not finite (NaN or inf); leave them out first")


def _check_voxel_size(voxel_size_m: float) -> None:
    if not (voxel_size_m > 0 and math.isfinite(voxel_size_m)):
        raise ConfigError(f"voxel_size_m must be positive and finite, got {voxel_size_m}")


def voxel_coords(points: ArrayLike, voxel_size_m: float) -> NDArray[np.int64]:
    """(N, 3) int64 voxel coordinates ``floor(points / voxel_size_m)``.

    The division runs in the points' dtype (float32 points, a Python float size: float32), as every caller did
    before this module existed. A non-finite point has no voxel: :class:`GeometryError` (leave them out first). A
    voxel size so small that a coordinate leaves +-2^62 (or, in float32, rounds to 0) is a :class:`ConfigError`:
    the cast to int64 would wrap silently (hostile trial 24 B2: ``--voxel-size-m 1e-100`` gave a 1-point map)."""
    _check_voxel_size(voxel_size_m)
    p = np.asarray(points)
    if p.ndim != 2 or p.shape[1] != 3:
        raise GeometryError(f"voxel_coords: expected (N, 3) points, got shape {p.shape}")
    _check_finite(p)
    return floor_coords(p, voxel_size_m)


def floor_coords(values: NDArray[np.floating], voxel_size_m: float) -> NDArray[np.int64]:
    """``floor(values / voxel_size_m)`` as int64 (finite ``values``), a :class:`ConfigError` where a result would
    leave +-2^62 or the size rounds to 0 in the values' dtype: the cast would wrap silently."""
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        q = np.floor(values / voxel_size_m)
    if q.size and not (-_COORD_LIMIT < q.min() and q.max() < _COORD_LIMIT):  # also inf / NaN from a size of 0
        raise ConfigError(f"voxel_size_m {voxel_size_m:g} is too small for these points (their voxel coordinates "
                          f"reach {max(abs(float(q.min())), abs(float(q.max()))):.3g}, beyond +-2^62, or the size "
                          f"rounds to 0 in {values.dtype}): use a larger voxel size")
    return q.astype(np.int64)


def voxel_coord_columns(columns: Sequence[NDArray[np.floating]], voxel_size_m: float) -> list[NDArray[np.int64]]:
    """:func:`voxel_coords` of three coordinate columns (e.g. the rows of a (3, N) array), one column each."""
    _check_voxel_size(voxel_size_m)
    if len(columns) != 3:
        raise GeometryError(f"voxel_coord_columns: expected 3 columns, got {len(columns)}")
    for col in columns:
        _check_finite(col)
    return [floor_coords(np.asarray(col), voxel_size_m) for col in columns]


@dataclass(frozen=True)
class VoxelGrid:
    """A box of voxels: ``span[a]`` voxels along axis ``a`` from voxel coordinate ``lo[a]``.

    :meth:`pack` numbers its voxels ``0 .. n_voxels - 1`` in ``(x, y, z)`` order; :meth:`unpack` inverts it."""

    lo: tuple[int, int, int]
    span: tuple[int, int, int]

    def __post_init__(self) -> None:
        if len(self.lo) != 3 or len(self.span) != 3 or min(self.span) < 1:
            raise ConfigError(f"VoxelGrid: need 3 lower corners and 3 spans >= 1, got lo={self.lo}, span={self.span}")
        if self.n_voxels > _INT64_KEY_LIMIT:
            raise ConfigError(f"VoxelGrid: {self.n_voxels} voxels do not fit int64 keys")

    @property
    def n_voxels(self) -> int:
        return self.span[0] * self.span[1] * self.span[2]

    @property
    def hi(self) -> tuple[int, int, int]:
        """The last voxel coordinate per axis (inclusive)."""
        return (self.lo[0] + self.span[0] - 1, self.lo[1] + self.span[1] - 1, self.lo[2] + self.span[2] - 1)

    @classmethod
    def around(cls, coords: Coords, what: str = "voxel grid") -> VoxelGrid:
        """The smallest grid holding ``coords`` (at least one voxel per axis when empty). Raises
        :class:`ConfigError` naming ``what`` when it would hold :data:`BOUNDING_GRID_MAX_VOXELS` voxels or more
        (a voxel size far too small for the extent)."""
        cols = _columns(coords)
        if len(cols[0]) == 0:
            return cls((0, 0, 0), (1, 1, 1))
        return cls.between([int(c.min()) for c in cols], [int(c.max()) for c in cols], what)

    @classmethod
    def between(cls, lo: Sequence[int], hi: Sequence[int], what: str = "voxel grid") -> VoxelGrid:
        """The grid from voxel coordinates ``lo`` to ``hi`` (inclusive, per axis); :class:`ConfigError` as
        :meth:`around`."""
        lo = tuple(int(a) for a in lo)
        span = tuple(int(h) - lo_a + 1 for h, lo_a in zip(hi, lo))
        if float(span[0]) * float(span[1]) * float(span[2]) >= float(BOUNDING_GRID_MAX_VOXELS):
            raise ConfigError(f"{what}: voxel grid too large to index ({span[0]} x {span[1]} x {span[2]} voxels; "
                              "voxel_size_m too small for the map extent)")
        return cls(lo, span)  # type: ignore[arg-type]

    def pack(self, coords: Coords, what: str = "voxel keys") -> NDArray[np.int64]:
        """One int64 key per coordinate triple; :class:`ConfigError` naming ``what`` for any triple outside."""
        cols = _columns(coords)
        if len(cols[0]):
            los = [int(c.min()) for c in cols]
            his = [int(c.max()) for c in cols]
            if any(a < b for a, b in zip(los, self.lo)) or any(a > b for a, b in zip(his, self.hi)):
                raise ConfigError(f"{what}: voxel coordinates {tuple(los)}..{tuple(his)} leave the key grid "
                                  f"{self.lo}..{self.hi}: the map spans too many voxels along an axis; use a larger "
                                  "voxel size")
        return self._pack(cols)

    def _pack(self, cols: tuple[NDArray[np.int64], ...]) -> NDArray[np.int64]:
        (l0, l1, l2), (_, s1, s2) = self.lo, self.span
        if len(cols[0]) == 0:
            return np.zeros(0, np.int64)
        return ((cols[0] - l0) * s1 + (cols[1] - l1)) * s2 + (cols[2] - l2)

    def unpack(self, keys: ArrayLike) -> NDArray[np.int64]:
        """(N, 3) voxel coordinates of keys made by :meth:`pack` on this grid."""
        k = np.asarray(keys, dtype=np.int64)
        (l0, l1, l2), (_, s1, s2) = self.lo, self.span
        return np.stack([k // (s1 * s2) + l0, (k // s2) % s1 + l1, k % s2 + l2], axis=-1)


ABSOLUTE_GRID = VoxelGrid((-ABSOLUTE_HALF_RANGE,) * 3, (2 * ABSOLUTE_HALF_RANGE,) * 3)  # type: ignore[arg-type]
"""The fixed grid around the origin (21 bits per axis): keys compare across calls; its key is
``(c0 + 2**20) << 42 | (c1 + 2**20) << 21 | (c2 + 2**20)``."""


def voxel_keys(points_or_coords: ArrayLike | Coords, voxel_size_m: float | None = None, *,
               grid: VoxelGrid | None = None, what: str = "voxel keys") -> NDArray[np.int64]:
    """One int64 key per point identifying its voxel.

    ``voxel_size_m`` given: ``points_or_coords`` are (N, 3) points (:func:`voxel_coords`); None: they already are
    integer voxel coordinates ((N, 3) or three columns). ``grid`` None packs on the bounding grid of these points
    (keys compare within this call only; :meth:`VoxelGrid.around`), else on ``grid`` (e.g. :data:`ABSOLUTE_GRID`,
    keys compare across calls; coordinates outside raise :class:`ConfigError`)."""
    coords = points_or_coords if voxel_size_m is None else voxel_coords(points_or_coords, voxel_size_m)  # type: ignore[arg-type]
    if grid is None:
        return keys_on_bounding_grid(coords, what)[0]  # type: ignore[arg-type]
    return grid.pack(coords, what)  # type: ignore[arg-type]


def keys_on_bounding_grid(coords: Coords, what: str = "voxel keys") -> tuple[NDArray[np.int64], VoxelGrid]:
    """Keys of integer voxel coordinates on their bounding grid, and that grid (to unpack the keys or pack
    neighbours' coordinates later). :class:`ConfigError` naming ``what`` as :meth:`VoxelGrid.around`."""
    cols = _columns(coords)
    grid = VoxelGrid.around(cols, what)
    return grid._pack(cols), grid


def dense_ids(keys: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """``(ids, unique_keys)``: each key's rank among the distinct keys (0..U-1, in key order) and those keys.

    Equal to ``np.unique(keys, return_inverse=True)`` (swapped), but without sorting when the keys are
    non-negative and their span is small (at most ``max(16 N, 2**22)``): a bitmap of the span instead."""
    if len(keys) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    span = int(keys.max()) + 1
    if span <= max(_DENSE_SPAN_PER_KEY * len(keys), _DENSE_SPAN_MIN) and int(keys.min()) >= 0:
        mark = np.zeros(span, bool)
        mark[keys] = True
        uniq = np.flatnonzero(mark)
        remap = np.empty(span, np.int32)
        remap[uniq] = np.arange(len(uniq), dtype=np.int32)
        return remap[keys].astype(np.int64), uniq
    uniq, inverse = np.unique(keys, return_inverse=True)
    return inverse.astype(np.int64), uniq


def first_per_key(keys: NDArray[np.int64]) -> NDArray[np.int64]:
    """Index of the first entry (in array order) of every distinct key, listed in key order (as the index
    ``np.unique(keys, return_index=True)`` returns)."""
    if len(keys) == 0:
        return np.zeros(0, np.int64)
    order = np.argsort(keys, kind="stable")
    first = np.ones(len(order), bool)
    first[1:] = keys[order][1:] != keys[order][:-1]
    return order[first]


def random_per_key(keys: NDArray[np.int64], rng: np.random.Generator) -> NDArray[np.int64]:
    """Index of one entry of every distinct key chosen at random (a fair representative: no frame favoured)."""
    perm = rng.permutation(len(keys))
    return perm[first_per_key(keys[perm])]


def first_point_per_voxel(points: ArrayLike, voxel_size_m: float) -> NDArray[np.int64]:
    """Index of the first point (in array order) of every occupied voxel, sorted: a downsampling that keeps
    real points (and so their provenance). Equal to ``np.unique(floor(points / voxel_size_m), axis=0,
    return_index=True)[1]`` sorted."""
    p = np.asarray(points)
    if len(p) == 0:
        _check_voxel_size(voxel_size_m)
        return np.zeros(0, np.int64)
    return np.sort(first_per_key(voxel_keys(p, voxel_size_m)))


@dataclass(frozen=True)
class VoxelMeans:
    """Per occupied voxel (in key order) the mean of the points in it; per point its voxel."""

    centroids_m: NDArray[np.float64]
    """(V, 3) float64 mean position of each voxel's points."""
    point_voxel: NDArray[np.int64]
    """(N,) the voxel (row of ``centroids_m``) of every point."""
    counts: NDArray[np.int64]
    """(V,) points per voxel."""

    def mean_of(self, values: ArrayLike) -> NDArray[np.float64]:
        """Per voxel, the float64 mean of a per-point attribute ((N,) or (N, k): intensities, normals, ...)."""
        v = np.asarray(values, dtype=np.float64)
        flat = v.reshape(len(v), -1)
        V = len(self.counts)
        out = np.stack([np.bincount(self.point_voxel, weights=flat[:, k], minlength=V) for k in range(flat.shape[1])],
                       axis=1) / self.counts[:, None]
        return out.reshape((V,) + v.shape[1:])


def voxel_means(points: ArrayLike, voxel_size_m: float) -> VoxelMeans:
    """One averaged point per occupied voxel (voxels in key order): the voxel ids of :func:`dense_ids`, then
    float64 sums per voxel (``np.bincount``, column by column) over the counts."""
    p = np.asarray(points)
    ids, uniq = dense_ids(voxel_keys(p, voxel_size_m))
    V = len(uniq)
    counts = np.bincount(ids, minlength=V).astype(np.int64)
    sums = [np.bincount(ids, weights=p[:, k].astype(np.float64), minlength=V) for k in range(3)]
    return VoxelMeans(np.stack(sums, axis=1).reshape(V, 3) / counts[:, None], ids, counts)
