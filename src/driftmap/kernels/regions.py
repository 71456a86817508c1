"""Compiled per-query steps of the surface decisions (:mod:`driftmap.decisions.surface`): a region's points selected
from the points gathered around it -- which lie inside, and those points and their frames compacted -- in one pass
instead of a numpy mask, two ``compress`` calls and their temporaries. (A compiled median of the offsets was slower than
``np.median``'s introselect and is not used.)

Each kernel computes what the numpy expressions it replaces compute, in the same float64 arithmetic (numba compiles
without fast-math: no fused multiply-add, and ``np.sqrt`` is correctly rounded in both), so the same points are
selected in the same order; tests/test_kernels_regions.py checks them against the
numpy expressions. They release the GIL, so that queries answered in several threads overlap here.
"""

from __future__ import annotations

import numba
import numpy as np

from driftmap.kernels.queries import in_map_order


@numba.njit(cache=True, nogil=True)
def _compact(pts, fids, mask, m):  # pragma: no cover - compiled
    p_in = np.empty((m, 3))
    f_in = np.empty(m, np.int64)
    j = 0
    for i in range(len(mask)):
        if mask[i]:
            p_in[j, 0], p_in[j, 1], p_in[j, 2] = pts[i, 0], pts[i, 1], pts[i, 2]
            f_in[j] = fids[i]
            j += 1
    return mask, p_in, f_in


@numba.njit(cache=True, nogil=True)
def select_box(pts, fids, lo, hi):  # pragma: no cover - compiled
    """``mask = (lo <= p) & (p <= hi)`` on every axis (float64 ``pts``; NaN never inside), ``pts[mask]`` and
    ``fids[mask]``."""
    n = len(pts)
    mask = np.empty(n, np.bool_)
    m = 0
    for i in range(n):
        x, y, z = pts[i, 0], pts[i, 1], pts[i, 2]
        ok = x >= lo[0] and x <= hi[0] and y >= lo[1] and y <= hi[1] and z >= lo[2] and z <= hi[2]
        mask[i] = ok
        m += ok
    return _compact(pts, fids, mask, m)


@numba.njit(cache=True, nogil=True)
def select_cylinder(pts, fids, centre, radius):  # pragma: no cover - compiled
    """``mask = (sqrt(dx*dx + dy*dy) <= radius) & (|z - centre_z| <= radius)`` (a vertical cylinder of height
    ``2 radius``; float64 ``pts``; NaN never inside), ``pts[mask]`` and ``fids[mask]``."""
    n = len(pts)
    mask = np.empty(n, np.bool_)
    m = 0
    for i in range(n):
        dx = pts[i, 0] - centre[0]
        dy = pts[i, 1] - centre[1]
        ok = np.sqrt(dx * dx + dy * dy) <= radius and abs(pts[i, 2] - centre[2]) <= radius
        mask[i] = ok
        m += ok
    return _compact(pts, fids, mask, m)


@numba.njit(cache=True, nogil=True)
def gather_with_voxels(points, order, rows, frame_ids, voxel_rows, positions):  # pragma: no cover - compiled
    """:func:`driftmap.kernels.queries.gather_in_map_order` (the points at ``positions`` of a cell-sorted index in
    map order, float64, and their frames) and each one's ``voxel_rows`` entry (its normal voxel's row)."""
    at = in_map_order(order, positions)
    n = len(at)
    pts = np.empty((n, 3))
    fids = np.empty(n, np.int64)
    vox = np.empty(n, np.int64)
    for i in range(n):
        j = at[i]
        for k in range(3):
            pts[i, k] = np.float64(points[j, k])
        fids[i] = frame_ids[rows[j]]
        vox[i] = voxel_rows[j]
    return pts, fids, vox
