"""Compiled hot loops of the map (numba): per-frame rigid transforms and bounds.

Each frame's points are transformed with its own pose in float64 arithmetic and rounded to float32 once,
so the result equals ``geometry.transform_points`` (numpy, float64) to float32 rounding. Frames are
processed in parallel (``prange``); sources may be strided (interleaved attributes) views into mapped
store segments.
"""

from __future__ import annotations

import os

import numba
import numpy as np

if "NUMBA_THREADING_LAYER" not in os.environ:
    # numba's own work queue is always available (the TBB layer warns about old TBB builds)
    numba.config.THREADING_LAYER = "workqueue"


@numba.njit(parallel=True, cache=True, nogil=True)
def transform_frames(src, starts, strides, counts, T, dst, dst_offsets, boxes):  # pragma: no cover - compiled
    """``dst[dst_offsets[j] + i] = T[j] @ src[starts[j] + i * strides[j] + (0, 1, 2)]`` for every frame j.

    ``src`` is a flat float32 buffer (indices in float32 units), ``dst`` an (N, 3) float32 array;
    ``boxes[j]`` receives the world-space min (0:3) and max (3:6) of frame j.
    """
    for j in numba.prange(starts.size):
        r00 = T[j, 0, 0]; r01 = T[j, 0, 1]; r02 = T[j, 0, 2]; t0 = T[j, 0, 3]  # noqa: E702
        r10 = T[j, 1, 0]; r11 = T[j, 1, 1]; r12 = T[j, 1, 2]; t1 = T[j, 1, 3]  # noqa: E702
        r20 = T[j, 2, 0]; r21 = T[j, 2, 1]; r22 = T[j, 2, 2]; t2 = T[j, 2, 3]  # noqa: E702
        lo0 = np.inf; lo1 = np.inf; lo2 = np.inf  # noqa: E702
        hi0 = -np.inf; hi1 = -np.inf; hi2 = -np.inf  # noqa: E702
        s = starts[j]
        step = strides[j]
        o = dst_offsets[j]
        for i in range(counts[j]):
            k = s + i * step
            x = np.float64(src[k]); y = np.float64(src[k + 1]); z = np.float64(src[k + 2])  # noqa: E702
            wx = np.float32(r00 * x + r01 * y + r02 * z + t0)
            wy = np.float32(r10 * x + r11 * y + r12 * z + t1)
            wz = np.float32(r20 * x + r21 * y + r22 * z + t2)
            dst[o + i, 0] = wx
            dst[o + i, 1] = wy
            dst[o + i, 2] = wz
            lo0 = min(lo0, wx); lo1 = min(lo1, wy); lo2 = min(lo2, wz)  # noqa: E702
            hi0 = max(hi0, wx); hi1 = max(hi1, wy); hi2 = max(hi2, wz)  # noqa: E702
        boxes[j, 0] = lo0; boxes[j, 1] = lo1; boxes[j, 2] = lo2  # noqa: E702
        boxes[j, 3] = hi0; boxes[j, 4] = hi1; boxes[j, 5] = hi2  # noqa: E702


@numba.njit(parallel=True, cache=True, nogil=True)
def frame_bounds(src, starts, strides, counts, boxes):  # pragma: no cover - compiled
    """Per-frame min/max of the source points (sensor frame)."""
    for j in numba.prange(starts.size):
        lo0 = np.inf; lo1 = np.inf; lo2 = np.inf  # noqa: E702
        hi0 = -np.inf; hi1 = -np.inf; hi2 = -np.inf  # noqa: E702
        s = starts[j]
        step = strides[j]
        for i in range(counts[j]):
            k = s + i * step
            x = src[k]; y = src[k + 1]; z = src[k + 2]  # noqa: E702
            lo0 = min(lo0, x); lo1 = min(lo1, y); lo2 = min(lo2, z)  # noqa: E702
            hi0 = max(hi0, x); hi1 = max(hi1, y); hi2 = max(hi2, z)  # noqa: E702
        boxes[j, 0] = lo0; boxes[j, 1] = lo1; boxes[j, 2] = lo2  # noqa: E702
        boxes[j, 3] = hi0; boxes[j, 4] = hi1; boxes[j, 5] = hi2  # noqa: E702


@numba.njit(cache=True, nogil=True)
def backproject_uint16(flat, lut, rays, min_code, max_code, valid_out, points_out):  # pragma: no cover - compiled
    """One pass over a uint16 depth image (flattened, row-major): mark valid pixels, write their points
    ``rays[i] * z`` into ``points_out`` in pixel order, count the rejection reasons.

    ``lut`` maps a code to metres (0 = invalid), ``rays`` is (n, 3) float32 ``((u-cx)/fx, (v-cy)/fy, 1)``.
    Returns (n_valid, n_zero, n_no_reading, n_below, n_beyond).
    """
    n_valid = 0
    n_zero = 0
    n_sentinel = 0
    n_below = 0
    n_beyond = 0
    for i in range(flat.size):
        code = flat[i]
        z = lut[code]
        if z != 0:
            points_out[n_valid, 0] = rays[i, 0] * z
            points_out[n_valid, 1] = rays[i, 1] * z
            points_out[n_valid, 2] = z
            valid_out[i] = True
            n_valid += 1
        else:
            valid_out[i] = False
            if code == 0:
                n_zero += 1
            elif code == 65535:
                n_sentinel += 1
            elif code < min_code:
                n_below += 1
            elif code >= max_code:
                n_beyond += 1
    return n_valid, n_zero, n_sentinel, n_below, n_beyond
