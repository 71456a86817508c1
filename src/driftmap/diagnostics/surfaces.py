"""Surface groups: the placed samples sorted by voxel, by the voxel's dominant own-frame normal (and a second
one) and by the side the sensor was on, each group cut into small lateral cells across its normal.

A group is one piece of surface seen by many frames; a cell is the place on it where those frames' offsets
along the normal are compared. The double-wall detector (:mod:`driftmap.diagnostics.layers`), the attribution
(:mod:`driftmap.diagnostics.attribution`) and the perturbation scoring all work on these groups.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from driftmap.diagnostics.samples import PlacedCloud
from driftmap.kernels.groups import (
    dot_gathered,
    group_outer_sums,
    group_row_sums,
    group_sums,
    pack_coords,
    plane_cells,
    voxel_coords_bounds,
)
from driftmap.voxels import VoxelGrid, dense_ids, keys_on_bounding_grid, voxel_coord_columns


@dataclass(frozen=True)
class SurfaceGroups:
    """Points sorted into surface groups (voxel x dominant normal x sensor side) and lateral cells."""

    voxel_size_m: float
    point_index: NDArray[np.int64]
    """Index into the placed cloud of every grouped point."""
    group: NDArray[np.int64]
    cell: NDArray[np.int64]
    offset_m: NDArray[np.float64]
    """Offset along the group normal from the group centroid."""
    n_groups: int
    n_cells: int
    normals: NDArray[np.float64]
    centers_m: NDArray[np.float64]
    n_points: NDArray[np.float64]
    cell_group: NDArray[np.int64]


def _dominant_axis(ids: NDArray[np.int64], n: int, normals: NDArray[np.float64]) -> NDArray[np.float64]:
    """Per group, the axis the (3, N) normal columns cluster around (sign-free: top eigenvector of sum n n^T)."""
    _, vec = np.linalg.eigh(group_outer_sums(ids, n, normals))
    return vec[:, :, 2]


def _tangent_basis(n: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    helper = np.where(np.abs(n[:, [0]]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    u = np.cross(n, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return u, np.cross(n, u)


def voxel_ids(columns: NDArray[np.floating], size_m: float) -> tuple[NDArray[np.int64], NDArray[np.int64], VoxelGrid]:
    """Per point of the (3, N) coordinate ``columns``: its voxel id (0 .. V-1, voxels in key order, i.e. sorted
    like their ``(x, y, z)`` coordinates), the V voxel keys and the bounding grid they are packed on
    (:mod:`driftmap.voxels`)."""
    what = f"surface groups at {size_m} m"
    found = voxel_coords_bounds(columns, size_m) if len(columns[0]) and size_m > 0 and math.isfinite(size_m) else None
    if found is None:  # empty, or the numpy path names what is wrong
        keys, grid = keys_on_bounding_grid(voxel_coord_columns(columns, size_m), what)
    else:
        coords, lo, hi = found
        grid = VoxelGrid.between(lo, hi, what)
        keys = pack_coords(coords, grid.lo, grid.span)
    vox, vox_keys = dense_ids(keys)
    return vox, vox_keys, grid


def _voxel_surfaces(vox: NDArray[np.int64], n_vox: int, Nw: NDArray[np.float64], cos_max: float,
                    second_surface: bool) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """Per point: its surface in its voxel (0: the dominant normal, 1: the second one, -1: neither) and the
    side the sensor was on (the sign of its normal along the surface's axis)."""
    axis1 = _dominant_axis(vox, n_vox, Nw)
    c1 = dot_gathered(Nw, axis1, vox)
    surface = np.where(np.abs(c1) >= cos_max, 0, -1)
    side = c1 > 0
    if second_surface:
        rest = np.flatnonzero(surface < 0)
        vox_r, Nw_r = vox[rest], Nw.take(rest, axis=1)
        axis2 = _dominant_axis(vox_r, n_vox, Nw_r)
        c2 = dot_gathered(Nw_r, axis2, vox_r)
        ok2 = np.abs(c2) >= cos_max
        surface[rest[ok2]] = 1
        side[rest] = np.where(ok2, c2 > 0, side[rest])
    return surface, side


def surface_groups(cloud: PlacedCloud, size_m: float, *, normal_max_angle_deg: float = 20.0, second_surface: bool = True,
                   min_points: int = 40, cell_fraction: float = 0.25, max_cell_m: float | None = None,
                   join_faces: bool = True) -> SurfaceGroups:
    """Group the samples by voxel, by the voxel's dominant own-frame normal (and a second one) and by the side
    the sensor was on; cut every group into lateral cells of ``cell_fraction * size_m``.

    With ``join_faces`` a surface that lies close to a voxel face along its normal (both groups' centroids within
    0.35 voxel of it) is one group across that face: otherwise the face cuts the noise band of the surface (and of
    the layers of a double wall) along the normal, the layer means are truncated towards each other and the
    separation reads short (or the two layers land in two groups and are not seen at all)."""
    P, Nw = cloud.world_columns  # (3, N) columns
    n_pts = P.shape[1]
    cos_max = math.cos(math.radians(normal_max_angle_deg))
    vox, vox_keys, grid = voxel_ids(P, size_m)
    n_vox = int(vox.max()) + 1 if len(vox) else 0
    surface, side = _voxel_surfaces(vox, n_vox, Nw, cos_max, second_surface)
    use = np.flatnonzero(surface >= 0)
    g, g_keys = dense_ids(vox[use] * 4 + surface[use] * 2 + side[use])
    G = int(g.max()) + 1 if len(g) else 0
    # per group: point count, sum of normals, sum of positions (points in no group go to the extra bin G)
    g_all = np.full(n_pts, G, np.int64)
    g_all[use] = g
    cnt = group_sums(g, G)
    n_sum = group_row_sums(g_all, G + 1, Nw)[:, :G].T
    p_sum = group_row_sums(g_all, G + 1, P)[:, :G].T
    label = np.arange(G, dtype=np.int64)
    if join_faces and G:
        label, n_lab = _join_across_faces(cnt, n_sum, p_sum, g_keys, vox_keys, grid, size_m, cos_max)
        if n_lab < G:
            G = n_lab
            cnt = group_sums(label, G, cnt)
            n_sum = np.stack([group_sums(label, G, n_sum[:, k]) for k in range(3)], axis=1)
            p_sum = np.stack([group_sums(label, G, p_sum[:, k]) for k in range(3)], axis=1)
    big = cnt >= min_points
    final = np.where(big, np.cumsum(big) - 1, -1)[label]  # first-pass group -> kept group (-1: too few points)
    g = final[g]
    keep = g >= 0
    use, g = use[keep], g[keep]
    G = int(big.sum())
    cnt = cnt[big]
    normal = n_sum[big]
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    center = p_sum[big] / np.maximum(cnt, 1)[:, None]
    offset, c, C, cell_group = _lateral_cells(P, use, g, G, normal, center, size_m, cell_fraction, max_cell_m)
    return SurfaceGroups(size_m, use, g, c, offset, G, C, normal, center, cnt, cell_group)


def _lateral_cells(P: NDArray[np.float64], use: NDArray[np.int64], g: NDArray[np.int64], G: int, normal: NDArray[np.float64],
                   center: NDArray[np.float64], size_m: float, cell_fraction: float,
                   max_cell_m: float | None) -> tuple[NDArray[np.float64], NDArray[np.int64], int, NDArray[np.int64]]:
    """Each grouped point (``P[:, use]``)'s offset along its group normal (from the centroid) and its lateral cell: a square of
    ``cell_fraction * size_m`` (at most ``max_cell_m``) in the group's tangent plane. Returns the offsets, the
    cell per point, the number of cells and the group of every cell."""

    cell_m = size_m * cell_fraction if max_cell_m is None else min(size_m * cell_fraction, max_cell_m)
    K = int(math.ceil(2.0 * math.sqrt(6.0) * size_m / cell_m)) + 2  # a group joined across a face spans 1 x 1 x 2 voxels
    u, v = _tangent_basis(normal) if G else (np.zeros((0, 3)), np.zeros((0, 3)))
    # the offset from the centroid along the normal; the cell in the tangent plane (u, v)
    o, cell_keys = plane_cells(P, g, normal, u, v, center, cell_m, K, index=use)
    c, _ = dense_ids(cell_keys)
    C = int(c.max()) + 1 if len(c) else 0
    cell_group = np.zeros(C, np.int64)
    cell_group[c] = g
    return o, c, C, cell_group


def _join_across_faces(cnt: NDArray[np.float64], n_sum: NDArray[np.float64], p_sum: NDArray[np.float64],
                      g_keys: NDArray[np.int64], vox_keys: NDArray[np.int64], grid: VoxelGrid, size_m: float,
                      cos_max: float, margin: float = 0.35, max_tilt_deg: float = 10.0) -> tuple[NDArray[np.int64], int]:
    """Join the group pairs that are one surface cut by a voxel face along its normal.

    Groups (keys ``g_keys`` = ``vox * 4 + surface * 2 + side``, ``vox`` indexing the voxel keys ``vox_keys`` on
    ``grid``; per-group point counts and sums of normals and positions) in voxels adjacent along the grid axis
    ``a`` closest to their normal are joined when their normals agree within the grouping angle, both centroids lie
    within ``margin`` voxels of the shared face and ``a`` is the closest axis of both. A centroid is near one face
    at most (``margin < 0.5``), so a joined group spans two voxels at most (usually a pair of groups; the first and
    second surface of one voxel may both join the same neighbour). Returns a label per group and the number of
    labels."""
    G = len(g_keys)
    normal = n_sum / np.maximum(np.linalg.norm(n_sum, axis=1, keepdims=True), 1e-12)
    center = p_sum / np.maximum(cnt, 1)[:, None]
    vk = grid.unpack(vox_keys[g_keys // 4])  # the group's voxel coordinates
    axis = np.argmax(np.abs(normal), axis=1)
    rows = np.arange(G)
    frac = center[rows, axis] / size_m - vk[rows, axis]  # 0 .. 1 inside the voxel along the axis
    aligned = np.abs(normal[rows, axis]) >= math.cos(math.radians(max_tilt_deg))  # the face cuts along the normal
    near_hi, near_lo = aligned & (frac >= 1.0 - margin), aligned & (frac <= margin)
    src = np.flatnonzero(near_hi & (vk[rows, axis] + 1 <= np.array(grid.hi)[axis]))
    identity = (np.arange(G, dtype=np.int64), G)
    if not len(src):
        return identity
    nb = vk[src].copy()
    nb[np.arange(len(src)), axis[src]] += 1
    nb_key = grid.pack(nb)
    nb_vox = np.searchsorted(vox_keys, nb_key)
    nb_vox_ok = (nb_vox < len(vox_keys)) & (vox_keys[np.minimum(nb_vox, len(vox_keys) - 1)] == nb_key)
    best, best_dot = np.full(len(src), -1, np.int64), np.full(len(src), -np.inf)
    for sub in range(4):  # surface 0/1 x side 0/1 in the neighbouring voxel
        sub_key = nb_vox * 4 + sub
        h = np.minimum(np.searchsorted(g_keys, sub_key), G - 1)
        dot = np.einsum("ij,ij->i", normal[src], normal[h])
        ok = nb_vox_ok & (g_keys[h] == sub_key) & near_lo[h] & (axis[h] == axis[src]) & (dot >= cos_max) & (dot > best_dot)
        best = np.where(ok, h, best)
        best_dot = np.where(ok, dot, best_dot)
    pair = best >= 0
    if not pair.any():
        return identity
    A = coo_matrix((np.ones(int(pair.sum())), (src[pair], best[pair])), shape=(G, G))
    n_lab, labels = connected_components(A, directed=False)
    return labels.astype(np.int64), int(n_lab)
