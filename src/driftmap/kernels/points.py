"""Compiled hot loops of the points (numba): depth back-projection,: per-frame rigid transforms and bounds, and the map queries (below).

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

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

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




# ---------------------------------------------------------------------------------------------- queries
#
# Box, ball and nearest-point queries over the world points (an (N, 3) float32 array), in *pieces*: runs of at most
# ``view.QUERY_PIECE_POINTS`` consecutive points of one frame, each with its own world box (``piece_boxes``), so a
# query reads only the pieces whose box it overlaps, and copies the pieces inside it whole. A point is compared in
# float64 exactly as the numpy expressions the queries were first written with (``np.all((p >= lo) & (p <= hi),
# axis=1)`` and ``np.sum((p - c) ** 2, axis=1) <= r**2``, whose three squares numpy adds left to right; no fastmath,
# so no fused multiply-add either): the results are the same bit for bit; a point with a NaN coordinate never
# matches. Rounding is monotonic, so a bound computed the same way from a box corner bounds every point in the box.
# Each piece is taken as a contiguous 1-D slice indexed from 0 (no negative-index wraparound in the loop), so LLVM
# vectorises the counting and minimum loops. The kernels have a serial form (``*_run``, called from Python for
# small queries: launching a parallel region costs ~0.2 ms) and a parallel one over runs of pieces. ``q`` holds the
# query: kind ``QUERY_BOX``: min (0:3) and max (3:6) corner, inclusive; kind ``QUERY_BALL``: centre (0:3), squared
# radius (3), z band (4:6, inclusive; -inf, inf for none).

QUERY_BOX = 0
QUERY_BALL = 1
#: ``classify_pieces``: no point of the piece can match / some may / all do.
PIECE_OUT = 0
PIECE_PART = 1
PIECE_IN = 2
#: The bits of float64 +inf: squared distances (>= 0, or NaN) compare as these int64 keys as they do as floats,
#: and an integer minimum vectorises without fastmath (a float minimum needs the no-NaN flag).
INF_KEY = np.int64(0x7FF0000000000000)
_ABS_BITS = np.int64(0x7FFFFFFFFFFFFFFF)


@intrinsic
def _bits(typingctx, d):
    """The IEEE bits of a float64 as an int64."""
    if d != types.float64:
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(64))

    return types.int64(d), codegen


@intrinsic
def _float_of_bits(typingctx, k):
    """The float64 whose IEEE bits are the int64 ``k``."""
    if k != types.int64:
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.DoubleType())

    return types.float64(k), codegen


@numba.njit(cache=True, nogil=True)
def _piece_box(p, box):  # pragma: no cover - compiled
    """Min (0:3) and max (3:6) of the points of the flat xyz slice ``p`` that have no NaN coordinate (+-inf when
    none); returns whether no point has a NaN coordinate."""
    lo0 = np.inf; lo1 = np.inf; lo2 = np.inf  # noqa: E702
    hi0 = -np.inf; hi1 = -np.inf; hi2 = -np.inf  # noqa: E702
    nan_seen = False
    for i in range(p.size // 3):
        x = np.float64(p[3 * i]); y = np.float64(p[3 * i + 1]); z = np.float64(p[3 * i + 2])  # noqa: E702
        nan_seen = nan_seen | (x != x) | (y != y) | (z != z)
        lo0 = _fmin(lo0, x); hi0 = _fmax(hi0, x)  # noqa: E702
        lo1 = _fmin(lo1, y); hi1 = _fmax(hi1, y)  # noqa: E702
        lo2 = _fmin(lo2, z); hi2 = _fmax(hi2, z)  # noqa: E702
    box[0] = np.float32(lo0); box[1] = np.float32(lo1); box[2] = np.float32(lo2)  # noqa: E702
    box[3] = np.float32(hi0); box[4] = np.float32(hi1); box[5] = np.float32(hi2)  # noqa: E702
    if nan_seen:
        _bounds_ignoring_nan(p, 3, p.size // 3, box)
    return not nan_seen


@numba.njit(cache=True, nogil=True)
def piece_boxes_run(world, starts, stops, boxes, clean, p0, p1):  # pragma: no cover - compiled
    """Per piece ``p0 <= p < p1`` (points ``world[starts[p]:stops[p]]``): its box and whether it has no NaN point."""
    for p in range(p0, p1):
        clean[p] = _piece_box(world[starts[p]:stops[p]].reshape(-1), boxes[p])


@numba.njit(parallel=True, cache=True, nogil=True)
def piece_boxes(world, starts, stops, boxes, clean, n_threads):  # pragma: no cover - compiled
    """:func:`piece_boxes_run` of all pieces, ``n_threads`` threads taking equal runs of them."""
    n_pieces = starts.size
    n_threads = max(1, min(n_threads, n_pieces))
    for t in numba.prange(n_threads):
        piece_boxes_run(world, starts, stops, boxes, clean, t * n_pieces // n_threads, (t + 1) * n_pieces // n_threads)


@numba.njit(cache=True, nogil=True)
def classify_pieces(boxes, clean, kind, q, out):  # pragma: no cover - compiled
    """Per piece box: :data:`PIECE_OUT` (no point in it can match the query), :data:`PIECE_IN` (every point does:
    the whole box is inside and the piece has no NaN point) or :data:`PIECE_PART`."""
    for p in range(boxes.shape[0]):
        lo0 = np.float64(boxes[p, 0]); lo1 = np.float64(boxes[p, 1]); lo2 = np.float64(boxes[p, 2])  # noqa: E702
        hi0 = np.float64(boxes[p, 3]); hi1 = np.float64(boxes[p, 4]); hi2 = np.float64(boxes[p, 5])  # noqa: E702
        if kind == QUERY_BOX:
            if not ((lo0 <= q[3]) & (hi0 >= q[0]) & (lo1 <= q[4]) & (hi1 >= q[1]) & (lo2 <= q[5]) & (hi2 >= q[2])):
                out[p] = PIECE_OUT
            elif clean[p] & (lo0 >= q[0]) & (hi0 <= q[3]) & (lo1 >= q[1]) & (hi1 <= q[4]) & (lo2 >= q[2]) \
                    & (hi2 <= q[5]):
                out[p] = PIECE_IN
            else:
                out[p] = PIECE_PART
            continue
        # ball: the box's nearest and farthest offsets per axis (a point's offset lies between them)
        if not ((lo0 <= hi0) & (lo2 <= q[5]) & (hi2 >= q[4])):
            out[p] = PIECE_OUT
            continue
        a0 = lo0 - q[0]; a1 = lo1 - q[1]; a2 = lo2 - q[2]  # noqa: E702
        b0 = hi0 - q[0]; b1 = hi1 - q[1]; b2 = hi2 - q[2]  # noqa: E702
        g0 = max(0.0, a0, -b0); g1 = max(0.0, a1, -b1); g2 = max(0.0, a2, -b2)  # noqa: E702
        if not (g0 * g0 + g1 * g1 + g2 * g2 <= q[3]):
            out[p] = PIECE_OUT
            continue
        e0 = max(-a0, b0); e1 = max(-a1, b1); e2 = max(-a2, b2)  # noqa: E702
        inside = (e0 * e0 + e1 * e1 + e2 * e2 <= q[3]) & (lo2 >= q[4]) & (hi2 <= q[5])
        out[p] = PIECE_IN if clean[p] & inside else PIECE_PART


@numba.njit(cache=True, nogil=True, inline="always")
def _matches(p, i, kind, q):  # pragma: no cover - compiled
    """Whether point ``i`` of the flat xyz slice ``p`` matches the query."""
    x = np.float64(p[3 * i]); y = np.float64(p[3 * i + 1]); z = np.float64(p[3 * i + 2])  # noqa: E702
    if kind == QUERY_BOX:
        return (q[0] <= x) & (x <= q[3]) & (q[1] <= y) & (y <= q[4]) & (q[2] <= z) & (z <= q[5])
    dx = x - q[0]; dy = y - q[1]; dz = z - q[2]  # noqa: E702
    return (dx * dx + dy * dy + dz * dz <= q[3]) & (q[4] <= z) & (z <= q[5])


@numba.njit(cache=True, nogil=True)
def _count_piece(p, kind, q):  # pragma: no cover - compiled
    n = 0
    for i in range(p.size // 3):
        n += np.int64(_matches(p, i, kind, q))
    return n


@numba.njit(cache=True, nogil=True)
def _fill_piece(p, kind, q, out, o):  # pragma: no cover - compiled
    """Copy the matching points of the flat xyz slice ``p`` to ``out`` (flat) from point ``o`` on."""
    for i in range(p.size // 3):
        if _matches(p, i, kind, q):
            out[3 * o] = p[3 * i]
            out[3 * o + 1] = p[3 * i + 1]
            out[3 * o + 2] = p[3 * i + 2]
            o += 1


@numba.njit(cache=True, nogil=True)
def query_count_run(world, starts, stops, kind, q, counts, p0, p1):  # pragma: no cover - compiled
    """``counts[p]`` = how many of the points ``world[starts[p]:stops[p]]`` match the query, for ``p0 <= p < p1``."""
    for p in range(p0, p1):
        counts[p] = _count_piece(world[starts[p]:stops[p]].reshape(-1), kind, q)


@numba.njit(cache=True, nogil=True)
def query_fill_run(world, starts, stops, whole, piece_ids, kind, q, dst_offsets, out, out_ids,
                   p0, p1):  # pragma: no cover - compiled
    """Copy the matching points of pieces ``p0 <= p < p1`` (in order; all of them where ``whole[p]``) to ``out``
    ((M, 3) float32) from row ``dst_offsets[p]`` on, and ``piece_ids[p]`` (the frame id) to those rows of
    ``out_ids``."""
    flat = out.reshape(-1)
    for p in range(p0, p1):
        o = dst_offsets[p]
        end = dst_offsets[p + 1]
        piece = world[starts[p]:stops[p]].reshape(-1)
        if whole[p]:
            flat[3 * o:3 * end] = piece
        else:
            _fill_piece(piece, kind, q, flat, o)
        out_ids[o:end] = piece_ids[p]


@numba.njit(parallel=True, cache=True, nogil=True)
def query_count(world, starts, stops, kind, q, counts, n_threads):  # pragma: no cover - compiled
    """:func:`query_count_run` of all pieces, ``n_threads`` threads taking equal runs of them."""
    n_pieces = starts.size
    n_threads = max(1, min(n_threads, n_pieces))
    for t in numba.prange(n_threads):
        p0, p1 = t * n_pieces // n_threads, (t + 1) * n_pieces // n_threads
        query_count_run(world, starts, stops, kind, q, counts, p0, p1)


@numba.njit(parallel=True, cache=True, nogil=True)
def query_fill(world, starts, stops, whole, piece_ids, kind, q, dst_offsets, out, out_ids,
               n_threads):  # pragma: no cover - compiled
    """:func:`query_fill_run` of all pieces, ``n_threads`` threads taking runs of about equal output."""
    n_pieces = starts.size
    n_threads = max(1, min(n_threads, n_pieces))
    total = dst_offsets[n_pieces]
    cuts = np.searchsorted(dst_offsets[:n_pieces], np.arange(n_threads + 1) * total // n_threads)
    cuts[0] = 0
    cuts[n_threads] = n_pieces
    for t in numba.prange(n_threads):
        query_fill_run(world, starts, stops, whole, piece_ids, kind, q, dst_offsets, out, out_ids, cuts[t], cuts[t + 1])


@numba.njit(cache=True, nogil=True)
def nearest_bounds(boxes, q, z_lo, z_hi, out):  # pragma: no cover - compiled
    """Per piece box: a lower bound of the distance from ``q`` of its points with ``z_lo <= z <= z_hi`` (the box's
    z range cut to the band), computed as the point distances are; +inf when the box holds no such point."""
    for p in range(boxes.shape[0]):
        lo2 = max(np.float64(boxes[p, 2]), z_lo)
        hi2 = min(np.float64(boxes[p, 5]), z_hi)
        if not ((boxes[p, 0] <= boxes[p, 3]) & (lo2 <= hi2)):
            out[p] = np.inf
            continue
        g0 = max(0.0, np.float64(boxes[p, 0]) - q[0], q[0] - np.float64(boxes[p, 3]))
        g1 = max(0.0, np.float64(boxes[p, 1]) - q[1], q[1] - np.float64(boxes[p, 4]))
        g2 = max(0.0, lo2 - q[2], q[2] - hi2)
        out[p] = np.sqrt(g0 * g0 + g1 * g1 + g2 * g2)


@numba.njit(cache=True, nogil=True)
def _min_key_piece(p, q0, q1, q2, z_lo, z_hi):  # pragma: no cover - compiled
    """The smallest squared distance ``((x-q0)^2 + (y-q1)^2) + (z-q2)^2`` (float64) of the points of the flat
    xyz slice ``p`` with ``z_lo <= z <= z_hi``, as int64 bits (:data:`INF_KEY` when none; NaNs sort above)."""
    m = INF_KEY
    for i in range(p.size // 3):
        z = np.float64(p[3 * i + 2])
        dx = np.float64(p[3 * i]) - q0
        dy = np.float64(p[3 * i + 1]) - q1
        dz = z - q2
        d2 = dx * dx + dy * dy + dz * dz
        outside = np.int64(z < z_lo) | np.int64(z > z_hi)
        m = min(m, (_bits(d2) & _ABS_BITS) | (-outside & INF_KEY))
    return m


@numba.njit(cache=True, nogil=True)
def nearest_run(world, starts, stops, bounds, q, z_lo, z_hi, piece_min, t, n_threads):  # pragma: no cover
    """Thread ``t`` of ``n_threads``: the pieces ``t, t + n_threads, ...`` in the order given, ``bounds`` ascending
    (a lower bound of the distance from ``q`` of every point of the piece). ``piece_min[p]`` receives the int64
    key (:func:`_min_key_piece`) of the smallest squared distance of the piece's points in the z band; the thread
    stops at the first of its pieces whose bound exceeds the best distance it has seen (the pieces it does not
    visit keep what ``piece_min`` held)."""
    best_m = np.inf
    for p in range(t, starts.size, n_threads):
        if bounds[p] > best_m:
            break
        key = _min_key_piece(world[starts[p]:stops[p]].reshape(-1), q[0], q[1], q[2], z_lo, z_hi)
        piece_min[p] = key
        if key < INF_KEY:
            best_m = min(best_m, np.sqrt(_float_of_bits(key)))


@numba.njit(parallel=True, cache=True, nogil=True)
def nearest_pieces(world, starts, stops, bounds, q, z_lo, z_hi, piece_min, n_threads):  # pragma: no cover
    """:func:`nearest_run` on ``n_threads`` threads (each prunes with the best distance it has seen itself)."""
    n_threads = max(1, min(n_threads, starts.size))
    for t in numba.prange(n_threads):
        nearest_run(world, starts, stops, bounds, q, z_lo, z_hi, piece_min, t, n_threads)


@numba.njit(cache=True, nogil=True)
def first_at_squared_distance(world, start, stop, q, z_lo, z_hi, d2_min):  # pragma: no cover - compiled
    """The first point index in ``start <= i < stop`` in the z band whose squared distance from ``q`` (computed
    as in :func:`_min_key_piece`) equals ``d2_min``; -1 if none."""
    p = world[start:stop].reshape(-1)
    for i in range(p.size // 3):
        z = np.float64(p[3 * i + 2])
        dx = np.float64(p[3 * i]) - q[0]
        dy = np.float64(p[3 * i + 1]) - q[1]
        dz = z - q[2]
        if (dx * dx + dy * dy + dz * dz == d2_min) & (z_lo <= z) & (z <= z_hi):
            return start + i
    return -1
