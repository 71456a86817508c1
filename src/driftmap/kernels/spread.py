"""The frame spread of a decision's evidence point in one compiled pass (:mod:`driftmap.decisions.evidence`): the
points of a ball read straight from the point index's cell-sorted arrays, the surface normal fitted to them when the
decision gives none (the eigenvector of the smallest eigenvalue of their centred scatter matrix), each point's offset
along it, the median offset per frame (:func:`driftmap.kernels.queries.group_medians`) and the distance between the
nearest and the farthest of those medians.

Unlike the other query kernels it does not repeat numpy's rounding step for step: the points are summed in the
index's cell order (not map order), and the scatter matrix, its eigenvectors and the offsets are computed here, not by
BLAS / LAPACK through numpy. The spread it returns differs from the numpy expression's by a few units of rounding
(tests/test_kernels_spread.py bounds it at 1e-12 m); the per-frame medians are order-independent, so a normal given
by the decision leaves only the offsets' rounding. In exchange a decision's spread holds the GIL for one call instead
of a dozen numpy steps (answered in threads, queries overlap here).
"""

from __future__ import annotations

import numba
import numpy as np

from driftmap.kernels.queries import group_medians


@numba.njit(cache=True, nogil=True)
def frame_spread(points, rows, n_rows, positions, point, normal, fit_normal, min_count):  # pragma: no cover - compiled
    """The frame spread (m) of the index points at ``positions`` (``points``: float32 (N, 3) world points; ``rows``:
    each one's frame row, ``0 .. n_rows - 1``) around ``point`` (float64): their offsets ``(p - point) . n`` along
    ``normal`` (``fit_normal``: the eigenvector of the smallest eigenvalue of the points' centred scatter matrix
    instead), the median per frame of the frames with at least ``min_count`` points, the largest median less the
    smallest. NaN with fewer than ``2 * min_count`` points or fewer than two such frames."""
    n = len(positions)
    if n < 2 * min_count or n == 0:
        return np.nan
    pts = np.empty((n, 3))
    groups = np.empty(n, np.int64)
    for i in range(n):
        at = positions[i]
        for k in range(3):
            pts[i, k] = np.float64(points[at, k])
        groups[i] = rows[at]
    nx, ny, nz = normal[0], normal[1], normal[2]
    if fit_normal:
        mx, my, mz = 0.0, 0.0, 0.0
        for i in range(n):
            mx += pts[i, 0]
            my += pts[i, 1]
            mz += pts[i, 2]
        mx, my, mz = mx / n, my / n, mz / n
        s = np.zeros((3, 3))
        for i in range(n):
            dx, dy, dz = pts[i, 0] - mx, pts[i, 1] - my, pts[i, 2] - mz
            s[0, 0] += dx * dx
            s[0, 1] += dx * dy
            s[0, 2] += dx * dz
            s[1, 1] += dy * dy
            s[1, 2] += dy * dz
            s[2, 2] += dz * dz
        s[1, 0], s[2, 0], s[2, 1] = s[0, 1], s[0, 2], s[1, 2]
        vectors = np.linalg.eigh(s)[1]
        nx, ny, nz = vectors[0, 0], vectors[1, 0], vectors[2, 0]
    offsets = np.empty(n)
    px, py, pz = point[0], point[1], point[2]
    for i in range(n):
        offsets[i] = (pts[i, 0] - px) * nx + (pts[i, 1] - py) * ny + (pts[i, 2] - pz) * nz
    placed = group_medians(offsets, groups, 0, n_rows, min_count)
    if len(placed) < 2:
        return np.nan
    return placed.max() - placed.min()
