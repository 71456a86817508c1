"""The numba kernels of the volumetric layers: integrate one frame into (or, with ``sign = -1``, take it out of) the
occupancy counts and the TSDF sums of a dense grid.

Why kernels of our own: OctoMap (the reference for occupancy) and Open3D's VoxelBlockGrid (the reference for the
TSDF) can only add observations; a pose correction needs the old contribution of a frame taken out exactly. Both
kernels therefore accumulate integers -- one hit or miss count per frame and voxel, a fixed-point TSDF sum and an
observation count -- whose sums do not depend on the order of the frames, so that de-integrating a frame and
integrating it again at its corrected pose gives bit for bit the grid a rebuild gives. They reproduce the
libraries' semantics and are tested equal to them on the same rays / images (tests/test_volume.py) and benchmarked
against them (benchmarks/bench_volume.py).

Coordinates: points and origins in *lattice units* (``p / voxel_size_m``: independent of the grid, so that a frame
traced again after the grid grew visits exactly the same voxels); ``origin_index`` (the grid's first lattice voxel)
and ``shape`` place the grid, and grid voxel ``(x, y, z)`` is the flat index ``(x * ny + y) * nz + z``.
"""

from __future__ import annotations

import math

import numba
import numpy as np

TSDF_QUANTUM = float(2**24)
"""The TSDF (normalised to -1..1) is summed as ``round(tsdf * TSDF_QUANTUM)`` in int64: exact, order-free sums."""


@numba.njit(cache=True, nogil=True)
def _flat(ix: int, iy: int, iz: int, ny: int, nz: int) -> int:
    return (ix * ny + iy) * nz + iz


# longer than 80 lines: one compiled loop (Amanatides-Woo voxel traversal of every ray, the per-frame marks and the
# miss list in one pass); split into helpers numba would inline them anyway, and the traversal state is shared
@numba.njit(cache=True, nogil=True)
def occupancy_update(origin: np.ndarray, ends: np.ndarray, is_hit: np.ndarray, origin_index: np.ndarray,
                     shape: np.ndarray, hits: np.ndarray, misses: np.ndarray, mark: np.ndarray, token: int, sign: int,
                     hit_flats: np.ndarray, miss_flats: np.ndarray) -> tuple[int, int]:
    """Add (``sign`` 1) or remove (-1) one frame's occupancy evidence, OctoMap's ``insertPointCloud`` semantics
    (``computeUpdate``): the voxel of every end with ``is_hit`` gets one hit; every voxel a ray passes through from
    the origin's voxel up to (not including) its end's voxel gets one miss, unless the frame hits it; each voxel counts
    at most once per frame (``mark`` holds ``2 token`` for this frame's hits, ``2 token + 1`` for its misses: a fresh
    ``token`` per call). A ray whose end is not a hit (beyond the max range: its end is the truncated end) carves
    only. Voxels outside the grid are skipped. The hit voxels are written to ``hit_flats``, the missed ones to
    ``miss_flats`` as far as it has room (the caller finds the rest by ``mark``); returns
    ``(n_hit_voxels, n_miss_voxels)``."""
    nx, ny, nz = shape[0], shape[1], shape[2]
    gx0, gy0, gz0 = origin_index[0], origin_index[1], origin_index[2]
    hit_tag = 2 * token
    miss_tag = 2 * token + 1
    n_hit = 0
    for n in range(ends.shape[0]):
        if not is_hit[n]:
            continue
        ix = int(math.floor(ends[n, 0])) - gx0
        iy = int(math.floor(ends[n, 1])) - gy0
        iz = int(math.floor(ends[n, 2])) - gz0
        if ix < 0 or iy < 0 or iz < 0 or ix >= nx or iy >= ny or iz >= nz:
            continue
        f = _flat(ix, iy, iz, ny, nz)
        if mark[f] != hit_tag:
            mark[f] = hit_tag
            hits[f] += sign
            hit_flats[n_hit] = f
            n_hit += 1
    ox, oy, oz = origin[0], origin[1], origin[2]
    kx0 = int(math.floor(ox))
    ky0 = int(math.floor(oy))
    kz0 = int(math.floor(oz))
    n_miss = 0
    for n in range(ends.shape[0]):
        dx = ends[n, 0] - ox
        dy = ends[n, 1] - oy
        dz = ends[n, 2] - oz
        ex = int(math.floor(ends[n, 0]))
        ey = int(math.floor(ends[n, 1]))
        ez = int(math.floor(ends[n, 2]))
        if ex == kx0 and ey == ky0 and ez == kz0:
            continue  # the same voxel: nothing to carve (OctoMap's computeRayKeys)
        length = math.sqrt(dx * dx + dy * dy + dz * dz)
        dx /= length
        dy /= length
        dz /= length
        kx, ky, kz = kx0, ky0, kz0
        # Amanatides & Woo, as OctoMap's computeRayKeys: the origin's voxel first, then each voxel crossed
        sx = 1 if dx > 0 else (-1 if dx < 0 else 0)
        sy = 1 if dy > 0 else (-1 if dy < 0 else 0)
        sz = 1 if dz > 0 else (-1 if dz < 0 else 0)
        inf = math.inf
        tmx = ((kx + 0.5) + sx * 0.5 - ox) / dx if sx != 0 else inf
        tmy = ((ky + 0.5) + sy * 0.5 - oy) / dy if sy != 0 else inf
        tmz = ((kz + 0.5) + sz * 0.5 - oz) / dz if sz != 0 else inf
        tdx = 1.0 / abs(dx) if sx != 0 else inf
        tdy = 1.0 / abs(dy) if sy != 0 else inf
        tdz = 1.0 / abs(dz) if sz != 0 else inf
        while True:
            if 0 <= kx - gx0 < nx and 0 <= ky - gy0 < ny and 0 <= kz - gz0 < nz:
                f = _flat(kx - gx0, ky - gy0, kz - gz0, ny, nz)
                m = mark[f]
                if m != hit_tag and m != miss_tag:
                    mark[f] = miss_tag
                    misses[f] += sign
                    if n_miss < miss_flats.shape[0]:
                        miss_flats[n_miss] = f
                    n_miss += 1
            if tmx < tmy:
                if tmx < tmz:
                    kx += sx
                    tmx += tdx
                else:
                    kz += sz
                    tmz += tdz
            elif tmy < tmz:
                ky += sy
                tmy += tdy
            else:
                kz += sz
                tmz += tdz
            if kx == ex and ky == ey and kz == ez:
                break
            if min(tmx, min(tmy, tmz)) > length:  # numerical safety, as OctoMap
                break
    return n_hit, n_miss


@numba.njit(cache=True, nogil=True, parallel=True)
def tsdf_projective(depth_m: np.ndarray, fx: float, fy: float, cx: float, cy: float, world_to_camera: np.ndarray,
                    blocks: np.ndarray, block_resolution: int, origin_index: np.ndarray, shape: np.ndarray,
                    voxel_size_m: float, truncation_m: float, depth_max_m: float, tsdf_sum: np.ndarray,
                    tsdf_count: np.ndarray, sign: int) -> int:
    """Add (``sign`` 1) or remove (-1) one depth image's TSDF, Open3D's ``VoxelBlockGrid.integrate`` semantics, in
    its float32 arithmetic: every lattice sample ``i * voxel_size_m`` of the given ``blocks`` (lattice block
    coordinates, :data:`~driftmap.volume.grid.BLOCK_RESOLUTION` voxels each) is moved into the camera frame and
    projected; the pixel it falls in (coordinates truncated, inside the image) gives ``sdf = depth - z``, used when
    ``0 < depth <= depth_max_m``, ``z > 0`` and ``sdf >= -truncation_m``, clipped to ``truncation_m`` and divided by
    it. Each use adds ``round(sdf * TSDF_QUANTUM)`` and one count. Returns the number of samples updated."""
    h, w = depth_m.shape
    ny, nz = shape[1], shape[2]
    R = block_resolution
    vs = np.float32(voxel_size_m)
    trunc = np.float32(truncation_m)
    dmax = np.float32(depth_max_m)
    fx32, fy32, cx32, cy32 = np.float32(fx), np.float32(fy), np.float32(cx), np.float32(cy)
    E = world_to_camera.astype(np.float32)
    wm1 = np.float32(w - 1)
    hm1 = np.float32(h - 1)
    updated = 0
    for b in numba.prange(blocks.shape[0]):  # blocks are distinct: no two threads touch one sample
        for xv in range(R):
            x = blocks[b, 0] * R + xv
            gx = x - origin_index[0]
            if gx < 0 or gx >= shape[0]:
                continue
            for yv in range(R):
                y = blocks[b, 1] * R + yv
                gy = y - origin_index[1]
                if gy < 0 or gy >= ny:
                    continue
                for zv in range(R):
                    z = blocks[b, 2] * R + zv
                    gz = z - origin_index[2]
                    if gz < 0 or gz >= nz:
                        continue
                    wx = np.float32(x) * vs
                    wy = np.float32(y) * vs
                    wz = np.float32(z) * vs
                    xc = E[0, 0] * wx + E[0, 1] * wy + E[0, 2] * wz + E[0, 3]
                    yc = E[1, 0] * wx + E[1, 1] * wy + E[1, 2] * wz + E[1, 3]
                    zc = E[2, 0] * wx + E[2, 1] * wy + E[2, 2] * wz + E[2, 3]
                    if zc <= 0:
                        continue
                    inv_z = np.float32(1.0) / zc
                    u = fx32 * xc * inv_z + cx32
                    v = fy32 * yc * inv_z + cy32
                    if not (u >= 0 and v >= 0 and u <= wm1 and v <= hm1):
                        continue
                    d = depth_m[int(v), int(u)]
                    sdf = d - zc
                    if d <= 0 or d > dmax or sdf < -trunc:
                        continue
                    if sdf > trunc:
                        sdf = trunc
                    sdf = sdf / trunc
                    f = _flat(gx, gy, gz, ny, nz)
                    tsdf_sum[f] += sign * np.int64(round(float(sdf) * TSDF_QUANTUM))
                    tsdf_count[f] += sign
                    updated += 1
    return updated


@numba.njit(cache=True, nogil=True)
def tsdf_rays(origin: np.ndarray, ends: np.ndarray, origin_index: np.ndarray, shape: np.ndarray, truncation_vox: float,
              tsdf_sum: np.ndarray, tsdf_count: np.ndarray, sign: int) -> int:
    """Add (``sign`` 1) or remove (-1) the TSDF of a scan's rays (LiDAR: no depth image to project into): along each
    ray, every lattice sample of the voxels the ray crosses within ``truncation_vox`` of its end (voxel units) gets
    ``sdf = range - (sample - origin) . direction``, clipped to the truncation and divided by it, as one more
    observation. Returns the number of updates."""
    ny, nz = shape[1], shape[2]
    updated = 0
    for n in range(ends.shape[0]):
        dx = ends[n, 0] - origin[0]
        dy = ends[n, 1] - origin[1]
        dz = ends[n, 2] - origin[2]
        rng = math.sqrt(dx * dx + dy * dy + dz * dz)
        if rng <= 0:
            continue
        dx /= rng
        dy /= rng
        dz /= rng
        t0 = max(0.0, rng - truncation_vox)
        t1 = rng + truncation_vox
        # walk the voxels of the segment [t0, t1] (Amanatides & Woo from the segment's start)
        px = origin[0] + t0 * dx
        py = origin[1] + t0 * dy
        pz = origin[2] + t0 * dz
        kx = int(math.floor(px))
        ky = int(math.floor(py))
        kz = int(math.floor(pz))
        sx = 1 if dx > 0 else (-1 if dx < 0 else 0)
        sy = 1 if dy > 0 else (-1 if dy < 0 else 0)
        sz = 1 if dz > 0 else (-1 if dz < 0 else 0)
        inf = math.inf
        tmx = t0 + ((kx + 0.5) + sx * 0.5 - px) / dx if sx != 0 else inf
        tmy = t0 + ((ky + 0.5) + sy * 0.5 - py) / dy if sy != 0 else inf
        tmz = t0 + ((kz + 0.5) + sz * 0.5 - pz) / dz if sz != 0 else inf
        tdx = 1.0 / abs(dx) if sx != 0 else inf
        tdy = 1.0 / abs(dy) if sy != 0 else inf
        tdz = 1.0 / abs(dz) if sz != 0 else inf
        while True:
            gx, gy, gz = kx - origin_index[0], ky - origin_index[1], kz - origin_index[2]
            if 0 <= gx < shape[0] and 0 <= gy < ny and 0 <= gz < nz:
                s = (kx - origin[0]) * dx + (ky - origin[1]) * dy + (kz - origin[2]) * dz
                sdf = rng - s
                if sdf >= -truncation_vox:
                    if sdf > truncation_vox:
                        sdf = truncation_vox
                    f = _flat(gx, gy, gz, ny, nz)
                    tsdf_sum[f] += sign * np.int64(round(sdf / truncation_vox * TSDF_QUANTUM))
                    tsdf_count[f] += sign
                    updated += 1
            t = min(tmx, min(tmy, tmz))
            if t > t1:
                break
            if tmx < tmy:
                if tmx < tmz:
                    kx += sx
                    tmx += tdx
                else:
                    kz += sz
                    tmz += tdz
            elif tmy < tmz:
                ky += sy
                tmy += tdy
            else:
                kz += sz
                tmz += tdz
    return updated
