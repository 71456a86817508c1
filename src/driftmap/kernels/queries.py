"""Compiled hot loops of the decisions' per-query work (numba): the points of a box or a ball and the frames of a box
read from a point index sorted by cell (:mod:`driftmap.decisions.point_index`), the footprint sweep's smallest signed
distances (:mod:`driftmap.decisions.space`), the unknown voxels of boxes and of a cylinder's columns from a
summed-volume table, a region's voxel means and the neighbourhood covariances of its border voxels' normals
(:mod:`driftmap.decisions.voxel_normals`), the points gathered back into map order, each point's normal turned
towards its sensor (:mod:`driftmap.decisions.surface`) and the per-frame medians of the frame spread
(:mod:`driftmap.decisions.evidence`).

Each kernel does what the numpy (or SciPy) expressions it replaces do, in the same float64 arithmetic (float32
coordinates promoted, no fused multiply-add: numba compiles without fast-math; sums in numpy's order, see
:func:`pairwise_sum`), so the points it selects and the values it computes are the same floats;
tests/test_kernels_queries.py checks them against the numpy expressions. Matrix products (BLAS) and eigen
decompositions (LAPACK) stay in numpy: their rounding is the library's.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def _column_runs(keys, i0, i1, j0, j1, za, zb, cell_lo, cell_hi, l0, l1, l2, s1, s2):  # pragma: no cover - compiled
    """Start and stop (into the sorted ``keys``) of the cells ``(i, j, za .. zb)`` of every column ``i0 .. i1`` x
    ``j0 .. j1`` (i outer, j inner); columns and z cut to the key grid ``cell_lo .. cell_hi``."""
    n_cols = max(i1 - i0 + 1, 0) * max(j1 - j0 + 1, 0)
    starts = np.zeros(n_cols, np.int64)
    stops = np.zeros(n_cols, np.int64)
    if zb < cell_lo or za > cell_hi or za > zb:
        return starts, stops
    za, zb = max(za, cell_lo), min(zb, cell_hi)
    c = 0
    for i in range(i0, i1 + 1):
        for j in range(j0, j1 + 1):
            if cell_lo <= i <= cell_hi and cell_lo <= j <= cell_hi:
                base = ((i - l0) * s1 + (j - l1)) * s2
                starts[c] = np.searchsorted(keys, base + (za - l2), side="left")
                stops[c] = np.searchsorted(keys, base + (zb - l2), side="right")
            c += 1
    return starts, stops


@numba.njit(cache=True, nogil=True)
def _positions(points, starts, stops, a, b, radius2, ball):  # pragma: no cover - compiled
    """The sorted positions ``at`` in the runs ``starts .. stops`` whose point passes the test: with ``ball``,
    ``dx*dx + dy*dy + dz*dz <= radius2`` about the centre ``a`` (float64, summed left to right); else ``a <= p <= b``
    on every axis (float64)."""
    total = 0
    for c in range(len(starts)):
        total += max(stops[c] - starts[c], 0)
    out = np.empty(total, np.int64)
    n = 0
    for c in range(len(starts)):
        for at in range(starts[c], stops[c]):
            x, y, z = np.float64(points[at, 0]), np.float64(points[at, 1]), np.float64(points[at, 2])
            if ball:
                dx, dy, dz = x - a[0], y - a[1], z - a[2]
                keep = dx * dx + dy * dy + dz * dz <= radius2
            else:
                keep = x >= a[0] and x <= b[0] and y >= a[1] and y <= b[1] and z >= a[2] and z <= b[2]
            if keep:
                out[n] = at
                n += 1
    return out[:n]


@numba.njit(cache=True, nogil=True)
def _members(points, order, starts, stops, a, b, radius2, ball):  # pragma: no cover - compiled
    """``order[at]`` of the positions :func:`_positions` selects."""
    at = _positions(points, starts, stops, a, b, radius2, ball)
    out = np.empty(len(at), np.int64)
    for i in range(len(at)):
        out[i] = order[at[i]]
    return out


@numba.njit(cache=True, nogil=True)
def box_members(points, order, starts, stops, lo, hi):  # pragma: no cover - compiled
    """``order[at]`` of the positions in the runs whose point has ``lo <= p <= hi`` on every axis (float64)."""
    return _members(points, order, starts, stops, lo, hi, 0.0, False)


@numba.njit(cache=True, nogil=True)
def ball_members(points, order, starts, stops, centre, radius2):  # pragma: no cover - compiled
    """``order[at]`` of the positions in the runs whose point has ``dx*dx + dy*dy + dz*dz <= radius2``."""
    return _members(points, order, starts, stops, centre, centre, radius2, True)


@numba.njit(cache=True, nogil=True)
def box_positions(points, starts, stops, lo, hi):  # pragma: no cover - compiled
    """The positions in the runs whose point has ``lo <= p <= hi`` on every axis (float64)."""
    return _positions(points, starts, stops, lo, hi, 0.0, False)


@numba.njit(cache=True, nogil=True)
def ball_positions(points, starts, stops, centre, radius2):  # pragma: no cover - compiled
    """The positions in the runs whose point has ``dx*dx + dy*dy + dz*dz <= radius2``."""
    return _positions(points, starts, stops, centre, centre, radius2, True)


def column_runs(keys: np.ndarray, a: np.ndarray, b: np.ndarray, cell_lo: int, cell_hi: int,
                lo: tuple[int, int, int], span: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The runs of the cells ``a .. b`` (inclusive) in ``keys`` packed on the grid ``lo``/``span``, one per (x, y)
    column (numpy's ``meshgrid(..., indexing="ij")`` order)."""
    return _column_runs(keys, int(a[0]), int(b[0]), int(a[1]), int(b[1]), int(a[2]), int(b[2]), int(cell_lo),
                        int(cell_hi), int(lo[0]), int(lo[1]), int(lo[2]), int(span[1]), int(span[2]))


@numba.njit(cache=True, nogil=True)
def _frames_in_box(keys, points, rows, pair_keys, pair_rows, n_rows, a, b, lo, hi, cell_lo, cell_hi, l0, l1, l2,
                   s1, s2):  # pragma: no cover - compiled
    found = np.zeros(n_rows, np.bool_)
    if b[2] < cell_lo or a[2] > cell_hi or a[2] > b[2]:
        return found
    za, zb = max(a[2], cell_lo), min(b[2], cell_hi)
    inner = b[0] - a[0] >= 2 and b[1] - a[1] >= 2 and b[2] - a[2] >= 2
    if inner:  # every frame of a cell wholly inside the box (cells a + 1 .. b - 1 on every axis)
        for i in range(max(a[0] + 1, cell_lo), min(b[0] - 1, cell_hi) + 1):
            for j in range(max(a[1] + 1, cell_lo), min(b[1] - 1, cell_hi) + 1):
                base = ((i - l0) * s1 + (j - l1)) * s2
                s = np.searchsorted(pair_keys, base + (max(a[2] + 1, cell_lo) - l2), side="left")
                t = np.searchsorted(pair_keys, base + (min(b[2] - 1, cell_hi) - l2), side="right")
                for k in range(s, t):
                    found[pair_rows[k]] = True
    for i in range(max(a[0], cell_lo), min(b[0], cell_hi) + 1):
        for j in range(max(a[1], cell_lo), min(b[1], cell_hi) + 1):
            base = ((i - l0) * s1 + (j - l1)) * s2
            rim = (not inner) or i == a[0] or i == b[0] or j == a[1] or j == b[1]
            for part in range(1 if rim else 2):  # a rim column whole, another its bottom and top cells
                z_lo = za if rim or part == 0 else zb
                z_hi = zb if rim or part == 1 else za
                s = np.searchsorted(keys, base + (z_lo - l2), side="left")
                t = np.searchsorted(keys, base + (z_hi - l2), side="right")
                for at in range(s, t):
                    r = rows[at]
                    if found[r]:
                        continue
                    x, y, z = np.float64(points[at, 0]), np.float64(points[at, 1]), np.float64(points[at, 2])
                    if x >= lo[0] and x <= hi[0] and y >= lo[1] and y <= hi[1] and z >= lo[2] and z <= hi[2]:
                        found[r] = True
    return found


def frames_in_box(keys: np.ndarray, points: np.ndarray, rows: np.ndarray, pair_keys: np.ndarray, pair_rows: np.ndarray,
                  n_rows: int, a: np.ndarray, b: np.ndarray, lo: np.ndarray, hi: np.ndarray, cell_lo: int, cell_hi: int,
                  grid_lo: tuple[int, int, int], span: tuple[int, int, int]) -> np.ndarray:
    """Per frame row, whether a point of it lies in the box ``lo .. hi`` (float64 test), the box's cells being
    ``a .. b``: the frames of the cells wholly inside from the (cell, frame) pairs, the points of the border cells
    tested (those of frames not found yet)."""
    return _frames_in_box(keys, points, rows, pair_keys, pair_rows, int(n_rows), np.asarray(a, np.int64),
                          np.asarray(b, np.int64), np.asarray(lo, np.float64), np.asarray(hi, np.float64),
                          int(cell_lo), int(cell_hi), int(grid_lo[0]), int(grid_lo[1]), int(grid_lo[2]), int(span[1]),
                          int(span[2]))


# ------------------------------------------------------------------------------------------------ footprints
@numba.njit(cache=True, nogil=True)
def group_balls(samples, need, group, bound, r_max, d_centre, cap, surface, reach, nearest, is_box, s0, s1, s2
                ):  # pragma: no cover - compiled
    """Per group of ``group`` consecutive rows of ``need`` (footprint placements): the mean of its samples (summed
    in row order, then divided) and the radius around it that holds every surface point that can give a placement
    its smallest signed distance. That is ``within = spread + bound + r_max + min(largest d_centre, cap)``
    (``spread``: the largest distance of a sample from the mean), cut to ``limit + spread + bound + r_max`` where
    ``limit`` is the largest over the placements of the smallest value (signed distance less reach) the group's
    nearest points (``nearest``) give it: a point p gives a placement at least ``|p - mean| - spread - bound - reach(p)``, so one farther away gives no
    placement less than its limit (nor ties with it). The cut is made only when every one of those nearest points lies
    inside ``within`` (surely: by a margin of rounding), so that the limit bounds the smallest value over that ball."""
    n_groups = (len(need) + group - 1) // group
    centres = np.zeros((n_groups, 3))
    radius = np.zeros(n_groups)
    for g in range(n_groups):
        a, b = g * group, min((g + 1) * group, len(need))
        for k in range(3):
            s = 0.0
            for r in range(a, b):
                s += samples[need[r], k]
            centres[g, k] = s / (b - a)
        spread = 0.0
        far = -np.inf
        for r in range(a, b):
            dx = samples[need[r], 0] - centres[g, 0]
            dy = samples[need[r], 1] - centres[g, 1]
            dz = samples[need[r], 2] - centres[g, 2]
            spread = max(spread, np.sqrt(dx * dx + dy * dy + dz * dz))
            far = max(far, d_centre[need[r]])
        within = spread + bound + r_max + min(far, cap)
        radius[g] = within
        inside = True
        for r in range(a, b):
            m = nearest[need[r]]
            dx = surface[m, 0] - centres[g, 0]
            dy = surface[m, 1] - centres[g, 1]
            dz = surface[m, 2] - centres[g, 2]
            inside = inside and np.sqrt(dx * dx + dy * dy + dz * dz) <= within - 1e-9
        if not inside:
            continue
        limit = -np.inf
        for r in range(a, b):
            row = need[r]
            best = np.inf
            for t in range(a, b):
                m = nearest[need[t]]
                best = min(best, _signed(surface[m, 0], surface[m, 1], surface[m, 2], samples[row, 0], samples[row, 1],
                                         samples[row, 2], is_box, s0, s1, s2) - reach[m])
            limit = max(limit, best)
        radius[g] = min(within, limit + spread + bound + r_max + 1e-9)
    return centres, radius


@numba.njit(cache=True, nogil=True)
def _signed(px, py, pz, cx, cy, cz, is_box, s0, s1, s2):  # pragma: no cover - compiled
    """The footprint's signed distance (as ``space.footprint_signed_distances``) of one point to one placement: a
    box of half sizes ``s0, s1, s2``, or a cylinder of radius ``s0`` and half height ``s1``."""
    if is_box:
        d0 = abs(px - cx) - s0
        d1 = abs(py - cy) - s1
        d2 = abs(pz - cz) - s2
        deepest = max(max(d0, d1), d2)
        m0, m1, m2 = max(d0, 0.0), max(d1, 0.0), max(d2, 0.0)
        out = np.sqrt(m0 * m0 + m1 * m1 + m2 * m2)
    else:
        d0 = np.hypot(px - cx, py - cy) - s0
        d1 = abs(pz - cz) - s1
        deepest = max(d0, d1)
        m0, m1 = max(d0, 0.0), max(d1, 0.0)
        out = np.sqrt(m0 * m0 + m1 * m1)
    return deepest if deepest <= 0 else out


@numba.njit(cache=True, nogil=True)
def group_minima(samples, need, group, surface, reach, cand, cand_starts, is_box, s0, s1, s2, signed, nearest
                 ):  # pragma: no cover - compiled
    """Per sample of each group: the smallest signed distance of the footprint to the group's candidate surface
    points ``cand[cand_starts[g]:cand_starts[g + 1]]`` less their reach, and the first candidate giving it (written
    into ``signed`` / ``nearest``; a group without candidates is left as it is)."""
    n_groups = len(cand_starts) - 1
    for g in range(n_groups):
        c0, c1 = cand_starts[g], cand_starts[g + 1]
        if c1 == c0:
            continue
        for r in range(g * group, min((g + 1) * group, len(need))):
            row = need[r]
            cx, cy, cz = samples[row, 0], samples[row, 1], samples[row, 2]
            best = np.inf
            at = -1
            for c in range(c0, c1):
                j = cand[c]
                v = _signed(surface[j, 0], surface[j, 1], surface[j, 2], cx, cy, cz, is_box, s0, s1, s2) - reach[j]
                if at < 0 or v < best:
                    best, at = v, j
            signed[row] = best
            nearest[row] = at


# ------------------------------------------------------------------------------------------------ unknown voxels
@numba.njit(cache=True, nogil=True)
def _sat_box(sat, o, shape, l0, l1, l2, h0, h1, h2):  # pragma: no cover - compiled
    """Unknown voxels in the lattice box ``l .. h`` (inclusive) from the summed-volume table ``sat``; voxels outside
    the grid (origin ``o``, ``shape``) count as unknown."""
    size = max(h0 - l0 + 1, 0) * max(h1 - l1 + 1, 0) * max(h2 - l2 + 1, 0)
    a0, b0 = min(max(l0 - o[0], 0), shape[0]), min(max(h0 - o[0] + 1, 0), shape[0])
    a1, b1 = min(max(l1 - o[1], 0), shape[1]), min(max(h1 - o[1] + 1, 0), shape[1])
    a2, b2 = min(max(l2 - o[2], 0), shape[2]), min(max(h2 - o[2] + 1, 0), shape[2])
    inside = max(b0 - a0, 0) * max(b1 - a1, 0) * max(b2 - a2, 0)
    total = 0
    if inside > 0:
        total = (np.int64(sat[b0, b1, b2]) - np.int64(sat[a0, b1, b2]) - np.int64(sat[b0, a1, b2])
                 - np.int64(sat[b0, b1, a2]) + np.int64(sat[a0, a1, b2]) + np.int64(sat[a0, b1, a2])
                 + np.int64(sat[b0, a1, a2]) - np.int64(sat[a0, a1, a2]))
    return total + (size - inside)


@numba.njit(cache=True, nogil=True)
def unknown_in_boxes(sat, origin, shape, lo, hi):  # pragma: no cover - compiled
    """Per lattice box ``lo[k] .. hi[k]`` (inclusive), its unknown voxels (:func:`_sat_box`)."""
    out = np.empty(len(lo), np.int64)
    for k in range(len(lo)):
        out[k] = _sat_box(sat, origin, shape, lo[k, 0], lo[k, 1], lo[k, 2], hi[k, 0], hi[k, 1], hi[k, 2])
    return out


@numba.njit(cache=True, nogil=True)
def _gap(cell, x, vs):  # pragma: no cover - compiled
    return max(max(cell * vs - x, x - (cell + 1) * vs), 0.0)


@numba.njit(cache=True, nogil=True)
def unknown_in_cylinders(sat, origin, shape, samples, lo, hi, vs, radius2):  # pragma: no cover - compiled
    """Per placement of a vertical cylinder (centre ``samples[s]``, lattice bounding box ``lo[s] .. hi[s]``): the
    unknown voxels of the columns of its box whose square comes within the radius (``gap_x**2 + gap_y**2 <=
    radius2``), between its box's z bounds."""
    out = np.zeros(len(samples), np.int64)
    n = 0
    for s in range(len(samples)):
        n = max(n, max(hi[s, 0] - lo[s, 0], hi[s, 1] - lo[s, 1]) + 1)
    for s in range(len(samples)):
        total = 0
        for di in range(n):
            cx = lo[s, 0] + di
            if cx > hi[s, 0]:
                continue
            gx = _gap(cx, samples[s, 0], vs)
            for dj in range(n):
                cy = lo[s, 1] + dj
                if cy > hi[s, 1]:
                    continue
                gy = _gap(cy, samples[s, 1], vs)
                if gx * gx + gy * gy <= radius2:
                    total += _sat_box(sat, origin, shape, cx, cy, lo[s, 2], cx, cy, hi[s, 2])
        out[s] = total
    return out


# ------------------------------------------------------------------------------------------------ voxel means
@numba.njit(cache=True, nogil=True)
def _packed_cells(points, cell_m):  # pragma: no cover - compiled
    """The points' cubes of ``cell_m`` on the world lattice (floor of coordinate / size): the smallest cell and the
    dims of their bounding box, and each point's cell packed into it (x slowest). At least one point."""
    n = len(points)
    cells = np.empty((n, 3), np.int64)
    for i in range(n):
        for k in range(3):
            cells[i, k] = np.int64(np.floor(points[i, k] / cell_m))
    base = np.empty(3, np.int64)
    dims = np.empty(3, np.int64)
    for k in range(3):
        lo, hi = cells[0, k], cells[0, k]
        for i in range(1, n):
            lo = min(lo, cells[i, k])
            hi = max(hi, cells[i, k])
        base[k], dims[k] = lo, hi - lo + 1
    packed = np.empty(n, np.int64)
    for i in range(n):
        packed[i] = ((cells[i, 0] - base[0]) * dims[1] + (cells[i, 1] - base[1])) * dims[2] + (cells[i, 2] - base[2])
    return base, dims, packed


@numba.njit(cache=True, nogil=True)
def voxel_cells(pts, voxel_m, dense_per_point):  # pragma: no cover - compiled
    """The mean point of every occupied ``voxel_m`` voxel of the world lattice (ordered by lattice cell, x slowest),
    each point's voxel and each voxel's lattice cell, as ``decisions.voxel_normals.voxel_cells`` computes them: the
    sums in point order (``np.bincount``'s), then divided by the count."""
    n = len(pts)
    base, dims, packed = _packed_cells(pts, voxel_m)
    inv = np.empty(n, np.int64)
    if dims[0] * dims[1] * dims[2] <= dense_per_point * n:
        rank = np.zeros(dims[0] * dims[1] * dims[2], np.int64)
        for i in range(n):
            rank[packed[i]] = 1
        m = 0
        for c in range(len(rank)):
            if rank[c]:
                rank[c] = m
                m += 1
            else:
                rank[c] = -1
        uniq = np.empty(m, np.int64)
        for c in range(len(rank)):
            if rank[c] >= 0:
                uniq[rank[c]] = c
        for i in range(n):
            inv[i] = rank[packed[i]]
    else:
        order = np.argsort(packed)
        m = 0
        for j in range(n):
            if j == 0 or packed[order[j]] != packed[order[j - 1]]:
                m += 1
        uniq = np.empty(m, np.int64)
        m = -1
        for j in range(n):
            if j == 0 or packed[order[j]] != packed[order[j - 1]]:
                m += 1
                uniq[m] = packed[order[j]]
            inv[order[j]] = m
        m += 1
    sums = np.zeros((m, 3))
    counts = np.zeros(m, np.int64)
    for i in range(n):
        v = inv[i]
        counts[v] += 1
        for k in range(3):
            sums[v, k] += pts[i, k]
    lattice = np.empty((m, 3), np.int64)
    for v in range(m):
        for k in range(3):
            sums[v, k] = sums[v, k] / counts[v]
        c = uniq[v]
        lattice[v, 2] = c % dims[2] + base[2]
        lattice[v, 1] = (c // dims[2]) % dims[1] + base[1]
        lattice[v, 0] = c // (dims[1] * dims[2]) + base[0]
    return sums, inv, lattice


# ------------------------------------------------------------------------------------------------ voxel normals
@numba.njit(cache=True, nogil=True)
def pairwise_sum(values, n):  # pragma: no cover - compiled
    """``np.add.reduce`` of ``values[:n]`` as numpy sums a contiguous float64 row: pairwise, with 8 running sums in
    blocks of up to 128 (numpy's ``pairwise_sum``), so that the result is the same float."""
    if n < 8:
        res = 0.0
        for i in range(n):
            res += values[i]
        return res
    if n <= 128:
        r0, r1, r2, r3 = values[0], values[1], values[2], values[3]
        r4, r5, r6, r7 = values[4], values[5], values[6], values[7]
        i = 8
        while i < n - n % 8:
            r0 += values[i]
            r1 += values[i + 1]
            r2 += values[i + 2]
            r3 += values[i + 3]
            r4 += values[i + 4]
            r5 += values[i + 5]
            r6 += values[i + 6]
            r7 += values[i + 7]
            i += 8
        res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
        while i < n:
            res += values[i]
            i += 1
        return res
    half = n // 2
    half -= half % 8
    return pairwise_sum(values, half) + pairwise_sum(values[half:], n - half)


@numba.njit(cache=True, nogil=True)
def _cell_table(points, cell_m):  # pragma: no cover - compiled
    """The points binned into cubes of ``cell_m`` (a dense table over their bounding box): per cell (packed x
    slowest), where its points start in ``order`` (and the end, last); the smallest cell and the table's dims."""
    n = len(points)
    base, dims, packed = _packed_cells(points, cell_m)
    starts = np.zeros(dims[0] * dims[1] * dims[2] + 1, np.int64)
    for i in range(n):
        starts[packed[i] + 1] += 1
    for c in range(1, len(starts)):
        starts[c] += starts[c - 1]
    fill = starts[:-1].copy()
    order = np.empty(n, np.int64)
    for i in range(n):
        order[fill[packed[i]]] = i
        fill[packed[i]] += 1
    return order, starts, base, dims


@numba.njit(cache=True, nogil=True)
def _sorted_by_distance(d2, idx, n):  # pragma: no cover - compiled
    """Sort the first ``n`` candidates by squared distance ``d2`` (ties by index), in place: an insertion sort (a
    neighbourhood holds tens of them)."""
    for i in range(1, n):
        dv, iv = d2[i], idx[i]
        j = i - 1
        while j >= 0 and (d2[j] > dv or (d2[j] == dv and idx[j] > iv)):
            d2[j + 1], idx[j + 1] = d2[j], idx[j]
            j -= 1
        d2[j + 1], idx[j + 1] = dv, iv


@numba.njit(cache=True, nogil=True)
def _outside(lo_m, hi_m, x):  # pragma: no cover - compiled
    """How far ``x`` lies outside ``lo_m .. hi_m`` (0 inside)."""
    return max(max(lo_m - x, x - hi_m), 0.0)


@numba.njit(cache=True, nogil=True)
def knn_covariances(points, at, k, radius_m, bound2, max_cells_per_axis=64):  # pragma: no cover - compiled
    """The covariances of ``points[at]``'s neighbourhoods and their sizes, as ``preprocess.cloud._knn_covariances``
    computes them from a SciPy ``cKDTree`` query (``k`` nearest with squared distance below ``bound2``, the square
    of ``distance_upper_bound``; of those, the ones within ``radius_m``; sorted by distance, the point itself
    included): the offsets from the point, ``min(k, len(points))`` columns with the missing ones zero, summed as
    numpy sums a row (:func:`pairwise_sum`), ``sum(x*y) / n - mean_x * mean_y``; fewer than 3 neighbours: the
    identity. The neighbours are searched in a table of cubes about half the radius wide (at most
    ``max_cells_per_axis`` per axis), in the cells that come within the radius of the point."""
    m = len(at)
    cov = np.zeros((m, 3, 3))
    counts = np.zeros(m, np.int64)
    if m == 0:
        return cov, counts
    kk = min(k, len(points))
    extent = 0.0
    for d in range(3):
        extent = max(extent, points[:, d].max() - points[:, d].min())
    cell_m = max(0.5 * radius_m * (1.0 + 1e-6), extent / max_cells_per_axis)
    span = np.int64(np.floor(radius_m / cell_m)) + 1  # a point within the radius is at most this many cells away
    reach2 = bound2 * (1.0 + 1e-6)  # the cells' distance test is conservative by this much
    order, starts, base, dims = _cell_table(points, cell_m)
    cand_d2 = np.empty(len(points))
    cand_i = np.empty(len(points), np.int64)
    cols = np.zeros((9, kk))  # x, y, z, xx, yy, zz, xy, xz, yz per neighbour column
    for q in range(m):
        p = at[q]
        px, py, pz = points[p, 0], points[p, 1], points[p, 2]
        c0 = np.int64(np.floor(px / cell_m)) - base[0]
        c1 = np.int64(np.floor(py / cell_m)) - base[1]
        c2 = np.int64(np.floor(pz / cell_m)) - base[2]
        n_cand = 0
        for i in range(max(c0 - span, 0), min(c0 + span, dims[0] - 1) + 1):
            gx = _outside((base[0] + i) * cell_m, (base[0] + i + 1) * cell_m, px)
            for j in range(max(c1 - span, 0), min(c1 + span, dims[1] - 1) + 1):
                gy = _outside((base[1] + j) * cell_m, (base[1] + j + 1) * cell_m, py)
                if gx * gx + gy * gy > reach2:
                    continue
                row = (i * dims[1] + j) * dims[2]
                s = starts[row + max(c2 - span, 0)]
                t = starts[row + min(c2 + span, dims[2] - 1) + 1]
                for at_c in range(s, t):
                    o = order[at_c]
                    dx, dy, dz = px - points[o, 0], py - points[o, 1], pz - points[o, 2]
                    d2 = dx * dx + dy * dy + dz * dz
                    if d2 < bound2 and np.sqrt(d2) <= radius_m:
                        cand_d2[n_cand] = d2
                        cand_i[n_cand] = o
                        n_cand += 1
        _sorted_by_distance(cand_d2, cand_i, n_cand)
        n = min(n_cand, kk)
        cols[:, :] = 0.0
        for c in range(n):
            o = cand_i[c]
            x, y, z = points[o, 0] - px, points[o, 1] - py, points[o, 2] - pz
            cols[0, c], cols[1, c], cols[2, c] = x, y, z
            cols[3, c], cols[4, c], cols[5, c] = x * x, y * y, z * z
            cols[6, c], cols[7, c], cols[8, c] = x * y, x * z, y * z
        counts[q] = n
        if n < 3:
            for d in range(3):
                cov[q, d, d] = 1.0
            continue
        inv = 1.0 / max(n, 1)
        mx, my, mz = pairwise_sum(cols[0], kk) * inv, pairwise_sum(cols[1], kk) * inv, pairwise_sum(cols[2], kk) * inv
        cov[q, 0, 0] = pairwise_sum(cols[3], kk) * inv - mx * mx
        cov[q, 1, 1] = pairwise_sum(cols[4], kk) * inv - my * my
        cov[q, 2, 2] = pairwise_sum(cols[5], kk) * inv - mz * mz
        cov[q, 0, 1] = cov[q, 1, 0] = pairwise_sum(cols[6], kk) * inv - mx * my
        cov[q, 0, 2] = cov[q, 2, 0] = pairwise_sum(cols[7], kk) * inv - mx * mz
        cov[q, 1, 2] = cov[q, 2, 1] = pairwise_sum(cols[8], kk) * inv - my * mz
    return cov, counts


# ------------------------------------------------------------------------------------------------ map order
RADIX_BITS = 12
"""radix_sort: the bits sorted per pass (4,096 buckets: two passes for indices below 16.7M)"""


@numba.njit(cache=True, nogil=True)
def radix_sort(values, low_bit):  # pragma: no cover - compiled
    """Non-negative int64 ``values`` sorted by their bits from ``low_bit`` up (least significant digit first,
    :data:`RADIX_BITS` per pass; stable, so that the bits below ``low_bit`` keep their order where those above
    tie), in time linear in their number."""
    n = len(values)
    out = values.copy()
    if n < 2:
        return out
    top = out.max()
    tmp = np.empty(n, np.int64)
    buckets = 1 << RADIX_BITS
    mask = buckets - 1
    count = np.empty(buckets + 1, np.int64)
    shift = low_bit
    while (top >> shift) > 0:
        count[:] = 0
        for i in range(n):
            count[((out[i] >> shift) & mask) + 1] += 1
        for b in range(1, buckets + 1):
            count[b] += count[b - 1]
        for i in range(n):
            d = (out[i] >> shift) & mask
            tmp[count[d]] = out[i]
            count[d] += 1
        out, tmp = tmp, out
        shift += RADIX_BITS
    return out


@numba.njit(cache=True, nogil=True)
def in_map_order(order, positions):  # pragma: no cover - compiled
    """``positions`` sorted by ``order[positions]`` (distinct map indices): each packed with its map index above bit
    32 and sorted by those bits (:func:`radix_sort`; a comparison sort of the packed values below 2,048 of them,
    where the radix's buckets would cost more), or argsorted when an index does not fit 32 bits."""
    n = len(positions)
    if len(order) >= 1 << 31:
        keys = np.empty(n, np.int64)
        for i in range(n):
            keys[i] = order[positions[i]]
        return positions[np.argsort(keys, kind="mergesort")]
    packed = np.empty(n, np.int64)
    for i in range(n):
        packed[i] = (np.int64(order[positions[i]]) << 32) | positions[i]
    packed = np.sort(packed) if n < 2048 else radix_sort(packed, 32)
    out = np.empty(n, np.int64)
    for i in range(n):
        out[i] = packed[i] & 0xFFFFFFFF
    return out


@numba.njit(cache=True, nogil=True)
def gather_in_map_order(points, order, rows, frame_ids, positions):  # pragma: no cover - compiled
    """The points at ``positions`` of a cell-sorted index (``points``; ``order``: each one's index in map order;
    ``rows``: its frame's row in ``frame_ids``) in map order, as float64, and each one's frame: ``positions``
    sorted by ``order`` (:func:`in_map_order`), the rows read from the index's own arrays (a region's cells are a
    few contiguous runs of them: cache-friendly, where the map-order points are spread over every frame)."""
    at = in_map_order(order, positions)
    n = len(at)
    pts = np.empty((n, 3))
    fids = np.empty(n, np.int64)
    for i in range(n):
        for k in range(3):
            pts[i, k] = np.float64(points[at[i], k])
        fids[i] = frame_ids[rows[at[i]]]
    return pts, fids


# ------------------------------------------------------------------------------------------------ frame spread
@numba.njit(cache=True, nogil=True)
def _median(values):  # pragma: no cover - compiled
    """``np.median`` of ``values`` (not empty): the middle value, or the mean of the two middle ones
    (``(lo + hi) / 2.0``): selected (``np.partition``; the upper middle, then the largest below it), sorted when a
    value is NaN (they sort last)."""
    c = len(values)
    k = c // 2
    if np.isnan(values).any():
        part = np.sort(values)
        lo, hi = part[(c - 1) // 2], part[k]
    else:
        part = np.partition(values, k)
        hi = part[k]
        lo = hi
        if c % 2 == 0:
            lo = part[0]
            for i in range(1, k):
                lo = max(lo, part[i])
    return lo if c % 2 == 1 else (lo + hi) / 2.0


@numba.njit(cache=True, nogil=True)
def group_medians(values, groups, first_id, n_ids, min_count):  # pragma: no cover - compiled
    """The median of ``values`` per group id (``first_id .. first_id + n_ids - 1``, ascending) of the groups with at
    least ``min_count`` members: the middle value, or the mean of the two middle ones (``(lo + hi) / 2.0``), as
    ``np.median`` gives it. A counting sort by group, then each group's median (:func:`_median`)."""
    counts = np.zeros(n_ids + 1, np.int64)
    for i in range(len(groups)):
        counts[groups[i] - first_id + 1] += 1
    for g in range(1, n_ids + 1):
        counts[g] += counts[g - 1]
    fill = counts[:-1].copy()
    by_group = np.empty(len(values))
    for i in range(len(values)):
        g = groups[i] - first_id
        by_group[fill[g]] = values[i]
        fill[g] += 1
    out = np.empty(n_ids)
    n_out = 0
    for g in range(n_ids):
        s, c = counts[g], counts[g + 1] - counts[g]
        if c == 0 or c < min_count:
            continue
        out[n_out] = _median(by_group[s:s + c])
        n_out += 1
    return out[:n_out]


# ------------------------------------------------------------------------------------------------ point normals
@numba.njit(cache=True, nogil=True)
def oriented_point_normals(voxel_normals, voxel_of, points, sensors, sensor_of):  # pragma: no cover - compiled
    """Per point, its voxel's normal (``voxel_normals[voxel_of[i]]``, promoted to float64) turned towards its
    sensor (``sensors[sensor_of[i]]``: negated where ``n . (sensor - p) < 0``, the dot product summed as
    ``np.einsum("ij,ij->i", ...)`` sums three columns: the same float), and whether that normal is finite."""
    n = len(voxel_of)
    out = np.empty((n, 3))
    ok = np.empty(n, np.bool_)
    for i in range(n):
        v, s = voxel_of[i], sensor_of[i]
        nx, ny, nz = np.float64(voxel_normals[v, 0]), np.float64(voxel_normals[v, 1]), np.float64(voxel_normals[v, 2])
        dx, dy, dz = sensors[s, 0] - points[i, 0], sensors[s, 1] - points[i, 1], sensors[s, 2] - points[i, 2]
        dot = (nx * dx + nz * dz) + ny * dy  # einsum's order for three columns (the first and third, then the second)
        if dot < 0:
            nx, ny, nz = -nx, -ny, -nz
        out[i, 0], out[i, 1], out[i, 2] = nx, ny, nz
        ok[i] = np.isfinite(nx) and np.isfinite(ny) and np.isfinite(nz)
    return out, ok
