"""Compiled hot loops of the per-group statistics (numba): sums per group id of several weight rows in one pass,
the sums of the outer products of unit normals per group, and each point's dot product with its group's axis.

The double-wall detector (:mod:`driftmap.diagnostics.surfaces`, :mod:`driftmap.diagnostics.layers`) spends its time
in these: dozens of ``np.bincount`` calls over the same group ids, each a full pass over every sample (with two more
passes for its bounds check), and gathers of small per-group tables. Here one pass reads the ids once and adds every
weight row. Each group's sum is accumulated in point order, as ``np.bincount`` does, and the products and dot
products are evaluated in numpy's order (no fast-math, no fused multiply-add), so every result is bit for bit the
numpy expression it replaces (tests/test_kernels_groups.py checks that on real and random data;
benchmarks/bench_diagnostics.py measures the detector).
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def _row_sums(ids, n, weights):  # pragma: no cover - compiled
    k, m = weights.shape
    out = np.zeros((n, k))
    for i in range(m):
        g = ids[i]
        if g < 0 or g >= n:
            raise IndexError("group id out of range")
        for j in range(k):
            out[g, j] += weights[j, i]
    return out


@numba.njit(cache=True, nogil=True)
def _sums(ids, n, weights):  # pragma: no cover - compiled
    out = np.zeros(n)
    for i in range(ids.shape[0]):
        g = ids[i]
        if g < 0 or g >= n:
            raise IndexError("group id out of range")
        out[g] += weights[i]
    return out


@numba.njit(cache=True, nogil=True)
def _counts(ids, n):  # pragma: no cover - compiled
    out = np.zeros(n)
    for i in range(ids.shape[0]):
        g = ids[i]
        if g < 0 or g >= n:
            raise IndexError("group id out of range")
        out[g] += 1.0
    return out


@numba.njit(cache=True, nogil=True)
def _outer_sums(ids, n, columns):  # pragma: no cover - compiled
    out = np.zeros((n, 3, 3))
    for i in range(ids.shape[0]):
        g = ids[i]
        if g < 0 or g >= n:
            raise IndexError("group id out of range")
        x = columns[0, i]
        y = columns[1, i]
        z = columns[2, i]
        out[g, 0, 0] += x * x
        out[g, 0, 1] += x * y
        out[g, 0, 2] += x * z
        out[g, 1, 1] += y * y
        out[g, 1, 2] += y * z
        out[g, 2, 2] += z * z
    for g in range(n):
        out[g, 1, 0] = out[g, 0, 1]
        out[g, 2, 0] = out[g, 0, 2]
        out[g, 2, 1] = out[g, 1, 2]
    return out


@numba.njit(cache=True, nogil=True)
def _dot_gathered(columns, table, offsets, ids):  # pragma: no cover - compiled
    m = ids.shape[0]
    n = table.shape[1]
    out = np.empty(m)
    for i in range(m):
        g = ids[i]
        if g < 0 or g >= n:
            raise IndexError("group id out of range")
        out[i] = columns[0, i] * table[0, g] + columns[1, i] * table[1, g] + columns[2, i] * table[2, g] - offsets[g]
    return out


@numba.njit(cache=True, nogil=True)
def _plane_cells(columns, index, ids, normal, u, v, offsets, cell_m, k):  # pragma: no cover - compiled
    m = ids.shape[0]
    n_columns = columns.shape[1]
    n = normal.shape[1]
    along = np.empty(m)
    keys = np.empty(m, np.int64)
    half = k // 2
    for i in range(m):
        g = ids[i]
        if g < 0 or g >= n:
            raise IndexError("group id out of range")
        p = index[i]
        if p < 0 or p >= n_columns:
            raise IndexError("point index out of range")
        x = columns[0, p]
        y = columns[1, p]
        z = columns[2, p]
        along[i] = x * normal[0, g] + y * normal[1, g] + z * normal[2, g] - offsets[0, g]
        du = x * u[0, g] + y * u[1, g] + z * u[2, g] - offsets[1, g]
        dv = x * v[0, g] + y * v[1, g] + z * v[2, g] - offsets[2, g]
        cu = min(max(np.int64(np.floor(du / cell_m)) + half, 0), k - 1)
        cv = min(max(np.int64(np.floor(dv / cell_m)) + half, 0), k - 1)
        keys[i] = (g * k + cu) * k + cv
    return along, keys


@numba.njit(cache=True, nogil=True)
def _min_max(ids, n, values):  # pragma: no cover - compiled
    lo = np.full(n, np.inf)
    hi = np.full(n, -np.inf)
    for i in range(ids.shape[0]):
        g = ids[i]
        if g < 0 or g >= n:
            raise IndexError("group id out of range")
        x = values[i]
        if x < lo[g]:
            lo[g] = x
        if x > hi[g]:
            hi[g] = x
    return lo, hi


@numba.njit(cache=True, nogil=True)
def _cell_residuals(c, n, offsets, frames):  # pragma: no cover - compiled
    m = c.shape[0]
    count = np.zeros(n)
    total = np.zeros(n)
    f1 = np.zeros(n)
    f2 = np.zeros(n)
    for i in range(m):
        k = c[i]
        if k < 0 or k >= n:
            raise IndexError("cell id out of range")
        f = np.float64(frames[i])
        count[k] += 1.0
        total[k] += offsets[i]
        f1[k] += f
        f2[k] += f * f
    mean = np.empty(n)
    multi = np.empty(n, np.bool_)
    for k in range(n):
        d = max(count[k], 1.0)
        mean[k] = total[k] / d
        a = f1[k] / d
        multi[k] = (f2[k] / d - a * a) > 1e-9
    residual = np.empty(m)
    valid = np.empty(m, np.bool_)
    for i in range(m):
        residual[i] = offsets[i] - mean[c[i]]
        valid[i] = multi[c[i]]
    return residual, valid


@numba.njit(cache=True, nogil=True)
def _layer_purity_counts(c, g, n_groups, offsets, layer, shared, mid, sign_sep, expect):  # pragma: no cover - compiled
    n_cells = shared.shape[0]
    on_shared = np.zeros(n_groups)
    on_layer = np.zeros(n_groups)
    expected = np.zeros(n_groups)
    for i in range(c.shape[0]):
        k = c[i]
        j = g[i]
        if k < 0 or k >= n_cells or j < 0 or j >= n_groups:
            raise IndexError("cell or group id out of range")
        if not shared[k] or layer[i] < 0:
            continue
        on_shared[j] += 1.0
        s = 1.0 if layer[i] == 1 else -1.0
        if (offsets[i] - mid[k]) * s * sign_sep[j] > 0:
            on_layer[j] += 1.0
        expected[j] += expect[j]
    return on_shared, on_layer, expected


@numba.njit(cache=True, nogil=True)
def _voxel_coords(columns, size_m):  # pragma: no cover - compiled
    m = columns.shape[1]
    coords = np.empty((3, m), np.int64)
    lo = np.full(3, np.iinfo(np.int64).max)
    hi = np.full(3, np.iinfo(np.int64).min)
    for i in range(m):
        for a in range(3):
            x = columns[a, i]
            if not np.isfinite(x):
                return coords, lo, hi, False
            c = np.int64(np.floor(x / size_m))
            coords[a, i] = c
            lo[a] = min(lo[a], c)
            hi[a] = max(hi[a], c)
    return coords, lo, hi, True


@numba.njit(cache=True, nogil=True)
def _pack(coords, lo, span1, span2):  # pragma: no cover - compiled
    m = coords.shape[1]
    keys = np.empty(m, np.int64)
    for i in range(m):
        keys[i] = ((coords[0, i] - lo[0]) * span1 + (coords[1, i] - lo[1])) * span2 + (coords[2, i] - lo[2])
    return keys


def _ids(ids: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(ids, dtype=np.int64)


def group_row_sums(ids: np.ndarray, n: int, weights: np.ndarray) -> np.ndarray:
    """Per group ``0 .. n-1`` the sum of every row of ``weights`` ((k, N), one weight per point and row) over the
    points with that group id: a (k, n) float64 array, row ``j`` equal to ``np.bincount(ids, weights[j], minlength=n)``.
    An id outside ``0 .. n-1`` raises :class:`IndexError`."""
    w = np.ascontiguousarray(weights, dtype=np.float64)
    if w.ndim != 2 or w.shape[1] != len(ids):
        raise ValueError(f"weights must be (k, {len(ids)}), got {w.shape}")
    return np.ascontiguousarray(_row_sums(_ids(ids), int(n), w).T)


def group_sums(ids: np.ndarray, n: int, weights: np.ndarray | None = None) -> np.ndarray:
    """Per group ``0 .. n-1``: the count of ``ids`` (or the sum of ``weights``) as float64, equal to
    ``np.bincount(ids, weights, minlength=n)``. An id outside ``0 .. n-1`` raises :class:`IndexError`."""
    if weights is None:
        return _counts(_ids(ids), int(n))
    w = np.ascontiguousarray(weights, dtype=np.float64)
    if w.shape != (len(ids),):
        raise ValueError(f"weights must be ({len(ids)},), got {w.shape}")
    return _sums(_ids(ids), int(n), w)


def group_outer_sums(ids: np.ndarray, n: int, columns: np.ndarray) -> np.ndarray:
    """Per group the (3, 3) sum of ``c c^T`` over the (3, N) ``columns`` of its points: (n, 3, 3), every entry equal
    to ``np.bincount(ids, columns[a] * columns[b], minlength=n)``."""
    c = np.ascontiguousarray(columns, dtype=np.float64)
    if c.shape != (3, len(ids)):
        raise ValueError(f"columns must be (3, {len(ids)}), got {c.shape}")
    return _outer_sums(_ids(ids), int(n), c)


def dot_gathered(columns: np.ndarray, table: np.ndarray, ids: np.ndarray, offsets: np.ndarray | None = None) -> np.ndarray:
    """Per point ``i``: ``columns[:, i] . table[ids[i]] - offsets[ids[i]]`` for (3, N) ``columns`` and a small (G, 3)
    ``table`` (offsets 0 when not given), evaluated as ``c0 * t0 + c1 * t1 + c2 * t2 - o`` in that order."""
    c = np.ascontiguousarray(columns, dtype=np.float64)
    t = np.ascontiguousarray(np.asarray(table, dtype=np.float64).T)
    if c.shape != (3, len(ids)) or t.shape[0] != 3:
        raise ValueError(f"columns must be (3, {len(ids)}) and table (G, 3), got {c.shape} and {t.T.shape}")
    off = np.zeros(t.shape[1]) if offsets is None else np.ascontiguousarray(offsets, dtype=np.float64)
    return _dot_gathered(c, t, off, _ids(ids))


def plane_cells(columns: np.ndarray, ids: np.ndarray, normal: np.ndarray, u: np.ndarray, v: np.ndarray,
                center: np.ndarray, cell_m: float, k: int, index: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per point ``columns[:, index[i]]`` of the (3, M) ``columns`` (``index`` 0 .. N-1 when not given: every
    column), in group ``ids[i]`` (per group: a unit ``normal``, tangent axes ``u``,
    ``v`` and a ``center``, each (G, 3)): its offset from the centre along the normal, and its lateral cell key
    ``(g * k + cu) * k + cv`` with ``cu = clip(floor(((p - c) . u) / cell_m) + k // 2, 0, k - 1)`` (and ``cv`` along
    ``v``), the dot products taken as :func:`dot_gathered` does (``p . a - c . a``)."""
    c = np.ascontiguousarray(columns, dtype=np.float64)
    every = index is None
    index = np.arange(len(ids)) if every else _ids(index)
    if c.shape[0] != 3 or index.shape != (len(ids),) or (every and c.shape[1] != len(ids)):
        raise ValueError(f"columns must be (3, M) with one index per id ({len(ids)}), got {c.shape} and {index.shape}")
    axes = [np.ascontiguousarray(np.asarray(a, dtype=np.float64).T) for a in (normal, u, v)]
    offsets = np.ascontiguousarray(np.stack([np.einsum("ij,ij->i", center, a) for a in (normal, u, v)]))
    return _plane_cells(c, index, _ids(ids), axes[0], axes[1], axes[2], offsets, float(cell_m), int(k))


def group_min_max(ids: np.ndarray, n: int, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per group ``0 .. n-1`` the smallest and the largest of the finite ``values`` of its points (``inf`` and
    ``-inf`` for a group without points): ``np.minimum.at`` / ``np.maximum.at`` into ``inf`` / ``-inf``."""
    x = np.ascontiguousarray(values, dtype=np.float64)
    if x.shape != (len(ids),):
        raise ValueError(f"values must be ({len(ids)},), got {x.shape}")
    if not np.isfinite(x).all():
        raise ValueError("group_min_max: values must be finite")
    return _min_max(_ids(ids), int(n), x)


def cell_residuals(cells: np.ndarray, n_cells: int, offsets: np.ndarray, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per point: its offset minus the mean offset of its cell (``cells`` 0 .. n_cells-1), and whether that cell
    holds more than one distinct frame (the variance of the points' frame numbers above 1e-9). Equal to the numpy
    ``o - bincount(c, o)[c] / max(bincount(c)[c], 1)`` and ``(E[f^2] - E[f]^2 > 1e-9)[c]``."""
    o = np.ascontiguousarray(offsets, dtype=np.float64)
    f = np.ascontiguousarray(frames, dtype=np.int64)
    if o.shape != (len(cells),) or f.shape != (len(cells),):
        raise ValueError(f"offsets and frames must be ({len(cells)},), got {o.shape} and {f.shape}")
    return _cell_residuals(_ids(cells), int(n_cells), o, f)


def layer_purity_counts(cells: np.ndarray, groups: np.ndarray, n_groups: int, offsets: np.ndarray, layer: np.ndarray,
                        shared: np.ndarray, mid: np.ndarray, sign_sep: np.ndarray,
                        expect: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The double-wall detector's time-purity counts per group: points in a ``shared`` cell whose frame has a
    layer (``layer`` 0 / 1, -1 none), those of them on their frame's side of the cell's midpoint ``mid`` (offset
    minus midpoint, times +1 for layer 1 / -1 for layer 0, times the group's ``sign_sep`` > 0), and the sum of the
    group's ``expect`` over them."""
    return _layer_purity_counts(_ids(cells), _ids(groups), int(n_groups), np.ascontiguousarray(offsets, dtype=np.float64),
                                np.ascontiguousarray(layer, dtype=np.int8), np.ascontiguousarray(shared, dtype=np.bool_),
                                np.ascontiguousarray(mid, dtype=np.float64), np.ascontiguousarray(sign_sep, dtype=np.float64),
                                np.ascontiguousarray(expect, dtype=np.float64))


def voxel_coords_bounds(columns: np.ndarray, voxel_size_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Integer voxel coordinates ``floor(x / voxel_size_m)`` of the (3, N) ``columns`` as a (3, N) int64 array, with
    their smallest and largest value per axis; None when a coordinate is not finite (the caller's numpy path then
    names the error) or the columns are neither float32 nor float64. Equal to :func:`driftmap.voxels.voxel_coord_columns`."""
    c = np.asarray(columns)
    if c.dtype not in (np.float32, np.float64):
        return None
    # numpy divides float32 coordinates by a Python float in float32 (NEP 50): the same here
    coords, lo, hi, finite = _voxel_coords(np.ascontiguousarray(c), c.dtype.type(voxel_size_m))
    return (coords, lo, hi) if finite else None


def pack_coords(coords: np.ndarray, lo: tuple[int, int, int], span: tuple[int, int, int]) -> np.ndarray:
    """Keys ``((c0 - l0) * s1 + (c1 - l1)) * s2 + (c2 - l2)`` of (3, N) voxel coordinates on a grid from ``lo`` with
    ``span`` voxels per axis (:meth:`driftmap.voxels.VoxelGrid.pack` without its range check)."""
    return _pack(np.ascontiguousarray(coords, dtype=np.int64), np.asarray(lo, np.int64), int(span[1]), int(span[2]))
