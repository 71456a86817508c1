"""Compiled hot loops of the map (numba): per-frame rigid transforms and bounds.

Each point is transformed with its frame's pose in float64 arithmetic and rounded to float32 once, so the
result equals ``geometry.transform_points`` (numpy, float64) to float32 rounding. The work is cut into
*pieces* (at most ``view.READ_PIECE_BYTES`` of one frame's payload each) that the threads share out in equal
runs; a frame's box is the min/max over its pieces. The xyz-only loop (stride 3 floats) is written so LLVM vectorises it: the box
is tracked on the float64 values with ``llvm.minnum``/``maxnum`` (rounding to float32 is monotonic, so the
rounded min/max equal the min/max of the rounded points). Sources are either arrays in memory (frames' own
points, memory-mapped segments) or read straight from a segment file with ``pread`` into a small per-thread
buffer (:func:`read_transform_pieces`), so no sensor page stays mapped in the process.
"""

from __future__ import annotations

import os

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

if "NUMBA_THREADING_LAYER" not in os.environ:
    # numba's own work queue is always available (the TBB layer warns about old TBB builds)
    numba.config.THREADING_LAYER = "workqueue"

#: ``ssize_t pread(int fd, void *buf, size_t count, off_t offset)`` from the C library (POSIX, 64-bit off_t).
_pread = types.ExternalFunction("pread", types.intp(types.intc, types.uintp, types.uintp, types.int64))


def _min_max_intrinsic(name: str):
    """``llvm.minnum``/``maxnum`` with the no-NaN/no-signed-zero flags, so the loop vectoriser turns a loop
    that tracks a running min/max into a vector reduction. The flags make a NaN argument undefined: loops
    using these also record whether they saw a NaN and then redo the box without them."""

    @intrinsic
    def impl(typingctx, a, b):
        if not (isinstance(a, types.Float) and a == b):
            return None

        def codegen(context, builder, signature, args):
            t = args[0].type
            suffix = "f32" if t == ir.FloatType() else "f64"
            fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(t, [t, t]), f"llvm.{name}.{suffix}")
            return builder.call(fn, args, fastmath=("nnan", "nsz"))

        return a(a, b), codegen

    return impl


_fmin = _min_max_intrinsic("minnum")
_fmax = _min_max_intrinsic("maxnum")


@numba.njit(cache=True, nogil=True)
def _transform_xyz(src, dst, T, box):  # pragma: no cover - compiled
    """``dst[3i:3i+3] = float32(T @ src[3i:3i+3])`` for contiguous xyz (1-D float32 arrays of equal length);
    ``box`` receives the min (0:3) and max (3:6) of the written points (NaN points are left out)."""
    r00 = T[0, 0]; r01 = T[0, 1]; r02 = T[0, 2]; t0 = T[0, 3]  # noqa: E702
    r10 = T[1, 0]; r11 = T[1, 1]; r12 = T[1, 2]; t1 = T[1, 3]  # noqa: E702
    r20 = T[2, 0]; r21 = T[2, 1]; r22 = T[2, 2]; t2 = T[2, 3]  # noqa: E702
    lo0 = np.inf; lo1 = np.inf; lo2 = np.inf  # noqa: E702
    hi0 = -np.inf; hi1 = -np.inf; hi2 = -np.inf  # noqa: E702
    nan_seen = False
    for i in range(dst.size // 3):
        x = np.float64(src[3 * i]); y = np.float64(src[3 * i + 1]); z = np.float64(src[3 * i + 2])  # noqa: E702
        wx = r00 * x + r01 * y + r02 * z + t0
        wy = r10 * x + r11 * y + r12 * z + t1
        wz = r20 * x + r21 * y + r22 * z + t2
        dst[3 * i] = np.float32(wx)
        dst[3 * i + 1] = np.float32(wy)
        dst[3 * i + 2] = np.float32(wz)
        nan_seen = nan_seen | (wx != wx) | (wy != wy) | (wz != wz)
        lo0 = _fmin(lo0, wx); hi0 = _fmax(hi0, wx)  # noqa: E702
        lo1 = _fmin(lo1, wy); hi1 = _fmax(hi1, wy)  # noqa: E702
        lo2 = _fmin(lo2, wz); hi2 = _fmax(hi2, wz)  # noqa: E702
    box[0] = np.float32(lo0); box[1] = np.float32(lo1); box[2] = np.float32(lo2)  # noqa: E702
    box[3] = np.float32(hi0); box[4] = np.float32(hi1); box[5] = np.float32(hi2)  # noqa: E702
    if nan_seen:
        _bounds_ignoring_nan(dst, 3, dst.size // 3, box)


@numba.njit(cache=True, nogil=True)
def _bounds_ignoring_nan(src, step, n, box):  # pragma: no cover - compiled
    """Min/max of ``src[i * step + (0, 1, 2)]`` over the points whose three coordinates are numbers."""
    lo0 = np.inf; lo1 = np.inf; lo2 = np.inf  # noqa: E702
    hi0 = -np.inf; hi1 = -np.inf; hi2 = -np.inf  # noqa: E702
    for i in range(n):
        x = src[i * step]; y = src[i * step + 1]; z = src[i * step + 2]  # noqa: E702
        if x == x and y == y and z == z:
            lo0 = min(lo0, x); lo1 = min(lo1, y); lo2 = min(lo2, z)  # noqa: E702
            hi0 = max(hi0, x); hi1 = max(hi1, y); hi2 = max(hi2, z)  # noqa: E702
    box[0] = lo0; box[1] = lo1; box[2] = lo2  # noqa: E702
    box[3] = hi0; box[4] = hi1; box[5] = hi2  # noqa: E702


@numba.njit(cache=True, nogil=True)
def _transform_strided(src, step, n, dst, T, box):  # pragma: no cover - compiled
    """As :func:`_transform_xyz` for points every ``step`` floats (interleaved attributes)."""
    r00 = T[0, 0]; r01 = T[0, 1]; r02 = T[0, 2]; t0 = T[0, 3]  # noqa: E702
    r10 = T[1, 0]; r11 = T[1, 1]; r12 = T[1, 2]; t1 = T[1, 3]  # noqa: E702
    r20 = T[2, 0]; r21 = T[2, 1]; r22 = T[2, 2]; t2 = T[2, 3]  # noqa: E702
    lo0 = np.inf; lo1 = np.inf; lo2 = np.inf  # noqa: E702
    hi0 = -np.inf; hi1 = -np.inf; hi2 = -np.inf  # noqa: E702
    nan_seen = False
    for i in range(n):
        k = i * step
        x = np.float64(src[k]); y = np.float64(src[k + 1]); z = np.float64(src[k + 2])  # noqa: E702
        wx = r00 * x + r01 * y + r02 * z + t0
        wy = r10 * x + r11 * y + r12 * z + t1
        wz = r20 * x + r21 * y + r22 * z + t2
        dst[3 * i] = np.float32(wx)
        dst[3 * i + 1] = np.float32(wy)
        dst[3 * i + 2] = np.float32(wz)
        nan_seen = nan_seen | (wx != wx) | (wy != wy) | (wz != wz)
        lo0 = _fmin(lo0, wx); hi0 = _fmax(hi0, wx)  # noqa: E702
        lo1 = _fmin(lo1, wy); hi1 = _fmax(hi1, wy)  # noqa: E702
        lo2 = _fmin(lo2, wz); hi2 = _fmax(hi2, wz)  # noqa: E702
    box[0] = np.float32(lo0); box[1] = np.float32(lo1); box[2] = np.float32(lo2)  # noqa: E702
    box[3] = np.float32(hi0); box[4] = np.float32(hi1); box[5] = np.float32(hi2)  # noqa: E702
    if nan_seen:
        _bounds_ignoring_nan(dst, 3, n, box)


@numba.njit(cache=True, nogil=True)
def _transform_piece(src, step, n, dst, T, box):  # pragma: no cover - compiled
    if step == 3:
        _transform_xyz(src[: 3 * n], dst, T, box)
    else:
        _transform_strided(src, step, n, dst, T, box)


@numba.njit(cache=True, nogil=True)
def _read_full(fd, address, nbytes, offset):  # pragma: no cover - compiled
    """``pread`` until ``nbytes`` are read; returns the bytes read (fewer at the end of the file) or -1."""
    done = 0
    while done < nbytes:
        got = _pread(fd, address + done, nbytes - done, offset + done)
        if got < 0:
            return -1
        if got == 0:
            break
        done += got
    return done


@numba.njit(parallel=True, cache=True, nogil=True)
def transform_pieces(src, starts, strides, counts, rows, T, dst, dst_offsets, boxes,
                     n_threads):  # pragma: no cover - compiled
    """Piece ``p``: ``counts[p]`` points from the flat float32 ``src`` at ``starts[p]``, one every ``strides[p]``
    floats, transformed with ``T[rows[p]]`` into the flat float32 ``dst`` from point ``dst_offsets[p]`` on;
    ``boxes[p]`` receives their world min (0:3) and max (3:6). ``n_threads`` threads take equal runs of pieces."""
    n_pieces = starts.size
    n_threads = min(n_threads, n_pieces)
    for t in numba.prange(n_threads):
        for p in range(t * n_pieces // n_threads, (t + 1) * n_pieces // n_threads):
            n = counts[p]
            o = dst_offsets[p]
            piece = src[starts[p]:starts[p] + n * strides[p]]
            _transform_piece(piece, strides[p], n, dst[3 * o:3 * (o + n)], T[rows[p]], boxes[p])


@numba.njit(parallel=True, cache=True, nogil=True)
def read_transform_pieces(fds, file_offsets, strides, counts, rows, T, dst, dst_offsets, scratch,
                          boxes):  # pragma: no cover - compiled
    """As :func:`transform_pieces`, the source points of piece ``p`` read (``pread``) at byte ``file_offsets[p]``
    of a file into the reading thread's row of ``scratch`` (float32). Thread ``t`` reads its run of pieces
    from ``fds[t]`` (one open file per thread keeps each thread's reads sequential for the kernel's
    read-ahead). Returns per piece the bytes read; a piece not read whole (-1 on an error) is not transformed."""
    n_pieces = file_offsets.size
    n_threads = min(fds.size, scratch.shape[0], n_pieces)
    got = np.zeros(n_pieces, np.int64)
    for t in numba.prange(n_threads):
        buf = scratch[t]
        for p in range(t * n_pieces // n_threads, (t + 1) * n_pieces // n_threads):
            n = counts[p]
            step = strides[p]
            got[p] = -1 if n * step > buf.size else _read_full(fds[t], buf.ctypes.data, 4 * n * step, file_offsets[p])
            if got[p] == 4 * n * step:
                o = dst_offsets[p]
                _transform_piece(buf, step, n, dst[3 * o:3 * (o + n)], T[rows[p]], boxes[p])
    return got


@numba.njit(parallel=True, cache=True, nogil=True)
def frame_bounds(src, starts, strides, counts, boxes):  # pragma: no cover - compiled
    """Per-frame min/max of the source points (sensor frame; points with a NaN coordinate left out)."""
    for j in numba.prange(starts.size):
        _bounds_ignoring_nan(src[starts[j]:starts[j] + counts[j] * strides[j]], strides[j], counts[j], boxes[j])


@numba.njit(parallel=True, cache=True, nogil=True)
def read_frame_bounds(fds, file_offsets, strides, counts, scratch, boxes):  # pragma: no cover - compiled
    """:func:`frame_bounds` of pieces read from a file as in :func:`read_transform_pieces`; returns the bytes read."""
    n_pieces = file_offsets.size
    n_threads = min(fds.size, scratch.shape[0], n_pieces)
    got = np.zeros(n_pieces, np.int64)
    for t in numba.prange(n_threads):
        buf = scratch[t]
        for p in range(t * n_pieces // n_threads, (t + 1) * n_pieces // n_threads):
            n = counts[p]
            step = strides[p]
            got[p] = -1 if n * step > buf.size else _read_full(fds[t], buf.ctypes.data, 4 * n * step, file_offsets[p])
            if got[p] == 4 * n * step:
                _bounds_ignoring_nan(buf, step, n, boxes[p])
    return got


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
