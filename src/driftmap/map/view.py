"""The map view: world-frame points of stored frames in one pose revision, re-transformed incrementally.

Sensor-frame points stay where they are (in the store's segment files, or the frames' own arrays); the view
holds one float32 (N, 3) array of world points plus a small per-frame table. By default sensor points are
read from the segment files piece by piece (``pread`` into a small per-thread buffer) whenever frames are
(re-)transformed, so nothing but the world points stays resident; ``release_pages=False`` memory-maps the
segments and keeps the touched pages mapped instead (the sensor points then stay resident too). Moving to
another revision (:meth:`MapView.apply`) re-transforms only the frames whose pose changed, always from
their sensor-frame points (never world-to-world), so after any chain of corrections and rollbacks the
map equals, point for point, the map built from scratch with the final poses.
"""

from __future__ import annotations

import logging
import mmap
import os
import sys
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numba
import numpy as np
from numpy.typing import NDArray

from driftmap import geometry
from driftmap.errors import ConfigError, EmptyExportError, EmptyStoreError, StoreError
from driftmap.frame import Frame
from driftmap.kernels.points import (
    INF_KEY,
    PIECE_IN,
    QUERY_BALL,
    QUERY_BOX,
    classify_pieces,
    first_at_squared_distance,
    frame_bounds,
    nearest_bounds,
    nearest_pieces,
    nearest_run,
    query_count,
    query_count_run,
    query_fill,
    query_fill_run,
    read_frame_bounds,
    read_transform_pieces,
    transform_pieces,
)
from driftmap.map.fusion import write_cloud
from driftmap.map.piece_index import PieceIndex, parallel_pass
from driftmap.map.segment_reads import OpenFiles, SensorBuffer
from driftmap.map.view_types import (  # re-exported: the view's result types
    ChangeSet,
    FrameChange,
    FusedMap,
    Nearest,
    QueryResult,
    displacements,
    vec3_arg,
    z_range_arg,
)
from driftmap.preprocess.cloud import RegionOfInterest
from driftmap.store.guards import atomic_output, refuse_inside_store
from driftmap.voxels import first_per_key, floor_coords, voxel_keys

if TYPE_CHECKING:
    from driftmap.store.frame_store import FrameStore

logger = logging.getLogger(__name__)

#: Poses whose 4x4 matrices differ by no more than this (max abs entry) count as unchanged: none, every change is
#: applied (a rebuild places each frame at its exact pose, so must an update; a loop closure may move a camera at 0 by
#: 4e-20 m, which puts a voxel-boundary point into another voxel).
POSE_EPSILON = 0.0
#: Sensor payloads are (read and) transformed in pieces of at most this many bytes, shared out among the
#: threads; a piece read from a segment file fits in the reading core's cache (one buffer per thread).
READ_PIECE_BYTES = 256 << 10
#: Whether sensor points can be read with ``pread`` (POSIX, 64-bit file offsets); else they are memory-mapped.
CAN_PREAD = os.name == "posix" and sys.maxsize > 2**32
#: Queries see each frame's world points as pieces of this many consecutive points (the last one shorter), each with
#: its own world box: a query reads only the pieces its region overlaps and copies those inside it whole.
QUERY_PIECE_POINTS = 2048
#: Query passes over fewer points than this run on the calling thread: a pass costs ~0.4 ns per point on one core,
#: launching a parallel region ~0.2 ms.
QUERY_PARALLEL_POINTS = 1 << 20

NEAREST_MAX_COORDINATE_M = 1e150  # nearest(): a position farther out (or not finite) is refused: squares overflow


class MapView:
    """World points of a set of frames in one pose revision.

    Build it with :meth:`from_store` (sensor points from the store's segments) or :meth:`from_frames`
    (points held by the frames). ``revision`` is the revision currently materialised.

    ``release_pages=True`` (default): sensor points are read from the segment files (``pread``) into a small
    buffer per thread whenever frames are transformed; no sensor page stays in the process, so a loaded map
    costs little more than its world points. ``False``: the segments are memory-mapped and the sensor pages
    stay mapped after use: somewhat faster (no copy out of the page cache), about twice the memory (see
    docs/store.md). Where ``pread`` is not available (:data:`CAN_PREAD`) both modes map the segments.
    """

    def __init__(self, *, store: FrameStore | None = None, release_pages: bool = True, deskew: bool = True):
        self._store = store
        self._release_pages = release_pages
        self.deskew = deskew
        """Place frames with per-point times with the revision's continuous trajectory (:mod:`driftmap.preprocess.deskew`)."""
        self._timed = np.zeros(0, bool)
        self._frame_times: dict[int, NDArray[np.int64]] = {}
        self.deskew_problems: dict[int, str] = {}
        """Frames with per-point times placed rigidly instead, and why (a flagged frame, never an abort)."""
        self._buffers: list[SensorBuffer] = []
        self._buffer_index: dict[object, int] = {}
        self._scratch = np.zeros((0, 0), np.float32)
        self.frame_ids = np.zeros(0, np.int64)
        self.stamps_ns = np.zeros(0, np.int64)
        self._buf = np.zeros(0, np.int64)
        self._start = np.zeros(0, np.int64)
        self._stride = np.zeros(0, np.int64)
        self._count = np.zeros(0, np.int64)
        self._offsets = np.zeros(1, np.int64)
        self._T = np.zeros((0, 4, 4))
        self._boxes = np.zeros((0, 6), np.float32)
        self._world = np.zeros((0, 3), np.float32)
        self._index: dict[int, int] = {}
        self._piece_index = PieceIndex(QUERY_PIECE_POINTS)  # the queries' per-piece boxes, updated by the queries themselves
        self.revision = 0

    # ------------------------------------------------------------------------------------------ building

    @classmethod
    def from_store(cls, store: FrameStore, revision: int, *, release_pages: bool = True, deskew: bool = True) -> MapView:
        view = cls(store=store, release_pages=release_pages, deskew=deskew)
        view.revision = revision
        view.refresh()
        return view

    @classmethod
    def from_frames(cls, frames: Iterable[Frame], poses: dict[int, NDArray[np.float64]] | None = None, *,
                    deskew: bool = True) -> MapView:
        """A view over in-memory frames, placed with their own poses (or ``poses[frame_id]``)."""
        view = cls(deskew=deskew)
        frames = list(frames)
        view._frame_times = {int(f.frame_id): f.attributes.time_offset_ns for f in frames
                             if f.attributes.time_offset_ns is not None}
        ids = [int(f.frame_id) for f in frames]
        if len(set(ids)) != len(ids):
            dup = sorted({i for i in ids if ids.count(i) > 1})
            raise StoreError(f"from_frames: frame id(s) {dup[:10]} given more than once")
        if poses is not None:
            missing = [i for i in ids if i not in poses]
            if missing:
                raise StoreError(f"from_frames: no pose for frame(s) {missing[:10]} in `poses` ({len(missing)} missing)")
        placed = np.array([f.T_world_sensor if poses is None else poses[f.frame_id] for f in frames],
                          dtype=np.float64).reshape(-1, 4, 4)
        geometry.require_rigid_stack(placed, ids, "from_frames")
        view._add(
            ids,
            [f.stamp_ns for f in frames],
            [view._register(np.ascontiguousarray(f.points_sensor).reshape(-1), None) for f in frames],
            [0] * len(frames),
            [3] * len(frames),
            [f.n_points for f in frames],
            placed,
        )
        return view

    def _register(self, flat: NDArray[np.float32], mm: mmap.mmap | None) -> int:
        key = id(mm) if mm is not None else id(flat)
        if key not in self._buffer_index:
            self._buffer_index[key] = len(self._buffers)
            self._buffers.append(SensorBuffer(flat, mm))
        return self._buffer_index[key]

    def _register_file(self, path: Path) -> int:
        key = ("file", str(path))
        if key not in self._buffer_index:
            self._buffer_index[key] = len(self._buffers)
            self._buffers.append(SensorBuffer(None, None, path))
        return self._buffer_index[key]

    def refresh(self) -> list[int]:
        """Add the store's frames the view's revision places (``FrameStore.members``) that it does not hold yet."""
        if self._store is None:
            return []
        stored = self._store.members(self.revision)
        if len(stored) == len(self.frame_ids):  # the view only ever holds the revision's frames
            return []
        new = [int(f) for f in stored[~np.isin(stored, self.frame_ids)]]
        if not new:
            return []
        ids, stamps, bufs, starts, strides, counts = [], [], [], [], [], []
        for fid in new:
            ref = self._store.frame_ref(fid)
            if ref.payload_copy is None and ref.point_stride % 4 == 0 and self._release_pages and CAN_PREAD:
                b, start, stride = self._register_file(ref.segment), ref.payload_offset, ref.point_stride // 4
            elif ref.payload_copy is None and ref.payload_offset % 4 == 0 and ref.point_stride % 4 == 0:
                mm = self._store.payload_map(ref)
                flat = np.frombuffer(mm, dtype="<f4", count=len(mm) // 4)
                b, start = self._register(flat, mm), ref.payload_offset // 4
                stride = ref.point_stride // 4
            else:  # compressed or unaligned payload: one private copy of the xyz columns
                points = self._store.frame(fid).points_sensor
                b, start, stride = self._register(np.ascontiguousarray(points).reshape(-1), None), 0, 3
            ids.append(fid)
            stamps.append(int(ref.info["stamp_ns"]))
            bufs.append(b)
            starts.append(start)
            strides.append(stride)
            counts.append(ref.n_points)
        all_poses = self._store.poses(self.revision)
        rows = np.searchsorted(self._store.frame_ids, np.asarray(ids))
        self._add(ids, stamps, bufs, starts, strides, counts, all_poses[rows])
        return ids

    def _add(self, ids: Sequence[int], stamps: Sequence[int], bufs: Sequence[int], starts: Sequence[int],
             strides: Sequence[int], counts: Sequence[int], poses: NDArray[np.float64]) -> None:
        for fid in ids:
            if fid in self._index:
                raise StoreError(f"frame {fid} is already in the map")
        m0, n0 = len(self.frame_ids), int(self._offsets[-1])
        counts_arr = np.asarray(counts, dtype=np.int64)
        self.frame_ids = np.concatenate([self.frame_ids, np.asarray(ids, dtype=np.int64)])
        self.stamps_ns = np.concatenate([self.stamps_ns, np.asarray(stamps, dtype=np.int64)])
        self._buf = np.concatenate([self._buf, np.asarray(bufs, dtype=np.int64)])
        self._start = np.concatenate([self._start, np.asarray(starts, dtype=np.int64)])
        self._stride = np.concatenate([self._stride, np.asarray(strides, dtype=np.int64)])
        self._count = np.concatenate([self._count, counts_arr])
        self._offsets = np.concatenate([self._offsets, n0 + np.cumsum(counts_arr)])
        self._T = np.concatenate([self._T, np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)])
        self._boxes = np.concatenate([self._boxes, np.zeros((len(ids), 6), np.float32)])
        self._timed = np.concatenate([self._timed, np.array([self._has_times(int(f)) for f in ids], dtype=bool)])
        for k, fid in enumerate(ids):
            self._index[int(fid)] = m0 + k
        n_total = int(self._offsets[-1])
        if n_total > len(self._world):
            grown = np.empty((max(n_total, int(len(self._world) * 1.5)), 3), np.float32)
            grown[:n0] = self._world[:n0]
            self._world = grown
        new_rows = np.arange(m0, len(self.frame_ids))
        self._transform(np.union1d(new_rows, self._deskew_neighbours(new_rows)))

    # ------------------------------------------------------------------------------------------ core

    def _pieces(self, rows: NDArray[np.int64], start_unit: int) -> tuple[NDArray[np.int64], ...]:
        """Cut the payloads of ``rows`` (all from one source) into pieces of at most :data:`READ_PIECE_BYTES` (an
        empty frame gets one empty piece). Returns per piece its source start (in the source's units: floats,
        or bytes for a file, ``start_unit`` bytes per float), point count, row and map offset (points), plus
        the index of every row's first piece."""
        stride = self._stride[rows]
        count = self._count[rows]
        per_piece = np.maximum(1, READ_PIECE_BYTES // (4 * stride))
        n_pieces = np.maximum(1, -(-count // per_piece))
        first = np.concatenate([[0], np.cumsum(n_pieces)[:-1]])
        owner = np.repeat(np.arange(rows.size), n_pieces)
        skip = (np.arange(int(n_pieces.sum())) - first[owner]) * per_piece[owner]
        piece_rows = rows[owner]
        starts = self._start[piece_rows] + skip * stride[owner] * start_unit
        counts = np.minimum(per_piece[owner], count[owner] - skip)
        return starts, counts, piece_rows, self._offsets[piece_rows] + skip, first

    def _thread_scratch(self, strides: NDArray[np.int64]) -> NDArray[np.float32]:
        """One read buffer per thread, large enough for any piece of points with these strides."""
        n_threads = numba.get_num_threads()
        n_floats = max(READ_PIECE_BYTES // 4, int(strides.max(initial=0)))
        if self._scratch.shape[0] != n_threads or self._scratch.shape[1] < n_floats:
            self._scratch = np.empty((n_threads, n_floats), np.float32)
        return self._scratch

    def _check_read(self, path: Path, fds: NDArray[np.int32], got: NDArray[np.int64], offsets: NDArray[np.int64],
                    counts: NDArray[np.int64], piece_rows: NDArray[np.int64]) -> None:
        """Raise :class:`StoreError` naming the segment, frame and offset of the first piece not read whole."""
        expected = 4 * counts * self._stride[piece_rows]
        bad = np.flatnonzero(got != expected)
        if bad.size == 0:
            return
        p = int(bad[0])
        frame_id = int(self.frame_ids[piece_rows[p]])
        try:
            n = len(os.pread(int(fds[0]), int(expected[p]), int(offsets[p])))
            why = f"the file ends after {n} of them"
        except OSError as exc:
            why = str(exc)
        raise StoreError(f"{path}: frame {frame_id}: cannot read {int(expected[p])} bytes of sensor points at offset "
                         f"{int(offsets[p])}: {why}")

    def _transform(self, rows: NDArray[np.int64]) -> None:
        """Re-transform the given frames (map rows) from their sensor points with ``self._T``."""
        if rows.size == 0:
            return
        world = self._world.reshape(-1)
        buffers = np.unique(self._buf[rows])
        for k, b in enumerate(buffers):
            try:
                self._transform_buffer(rows, int(b), world)
            except StoreError:
                # this buffer's frames and those of the buffers not reached yet hold stale world points:
                # a NaN pose makes any later apply re-transform them
                self._T[rows[np.isin(self._buf[rows], buffers[k:])]] = np.nan
                raise
        if self.deskew:
            for r in rows[self._timed[rows]]:
                self._deskew_row(int(r))

    # ------------------------------------------------------------------------------------------ deskew

    def _has_times(self, frame_id: int) -> bool:
        if frame_id in self._frame_times:
            return True
        if self._store is None:
            return False
        fields = self._store.frame_info(frame_id)["points"]["fields"]
        return any(f["name"] == "time_offset_ns" for f in fields)

    def _times(self, frame_id: int) -> tuple[NDArray[np.float32], NDArray[np.int64]]:
        if frame_id in self._frame_times:
            r = self._index[frame_id]
            flat = self._buffers[int(self._buf[r])].flat
            start, stride, n = int(self._start[r]), int(self._stride[r]), int(self._count[r])
            pts = flat[start:start + n * stride].reshape(n, stride)[:, :3]
            return pts, self._frame_times[frame_id]
        frame = self._store.frame(frame_id)  # type: ignore[union-attr]
        return frame.points_sensor, frame.attributes.time_offset_ns  # type: ignore[return-value]

    def _time_order(self) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        order = np.argsort(self.stamps_ns, kind="stable")
        rank = np.empty_like(order)
        rank[order] = np.arange(len(order))
        return order, rank

    def _deskew_neighbours(self, rows: NDArray[np.int64]) -> NDArray[np.int64]:
        """Frames with per-point times whose deskew uses one of ``rows`` (the frames just before or after them)."""
        if not self.deskew or not self._timed.any() or rows.size == 0:
            return np.zeros(0, np.int64)
        order, rank = self._time_order()
        k = rank[rows]
        near = np.concatenate([order[np.clip(k - 1, 0, len(order) - 1)], order[np.clip(k + 1, 0, len(order) - 1)]])
        near = np.unique(near)
        return near[self._timed[near]]

    def _deskew_row(self, r: int) -> None:
        """Re-place frame row ``r`` from its sensor points and per-point times with the view's trajectory."""
        from driftmap.preprocess.deskew import deskew_to_world, scan_motion

        fid = int(self.frame_ids[r])
        pts, offsets = self._times(fid)
        if len(pts) == 0:
            return
        order, rank = self._time_order()
        span = int(np.ptp(offsets)) if len(offsets) else 0
        motion, why = scan_motion(self.stamps_ns, self._T, r, order, rank, span)
        if motion is None:
            if self.deskew_problems.get(fid) != why:
                logger.warning("frame %d: not deskewed (placed with its pose alone): %s", fid, why)
            self.deskew_problems[fid] = why
            return
        self.deskew_problems.pop(fid, None)
        world = deskew_to_world(pts, offsets, self._T[r], motion)
        a, b = int(self._offsets[r]), int(self._offsets[r + 1])
        self._world[a:b] = world
        self._boxes[r, :3] = world.min(axis=0)
        self._boxes[r, 3:] = world.max(axis=0)

    def _transform_buffer(self, rows: NDArray[np.int64], b: int, world: NDArray[np.float32]) -> None:
        """Re-transform the frames of ``rows`` whose sensor points live in buffer ``b``."""
        buffer = self._buffers[int(b)]
        sel = rows[self._buf[rows] == b]
        sel = sel[np.argsort(self._start[sel], kind="stable")]  # sequential reads of each segment
        starts, counts, piece_rows, dst, first = self._pieces(sel, 1 if buffer.path is None else 4)
        strides = self._stride[piece_rows]
        boxes = np.empty((starts.size, 6), np.float32)
        if buffer.path is None:
            transform_pieces(buffer.flat, starts, strides, counts, piece_rows, self._T, world, dst, boxes,
                             numba.get_num_threads())
        else:
            scratch = self._thread_scratch(strides)
            with OpenFiles(buffer.path, min(len(scratch), starts.size)) as fds:
                got = read_transform_pieces(fds, starts, strides, counts, piece_rows, self._T, world, dst, scratch,
                                            boxes)
                self._check_read(buffer.path, fds, got, starts, counts, piece_rows)
        self._boxes[sel, :3] = np.minimum.reduceat(boxes[:, :3], first)
        self._boxes[sel, 3:] = np.maximum.reduceat(boxes[:, 3:], first)

    def apply(self, revision: int, *, voxel_size_m: float | None = None, poses: NDArray[np.float64] | None = None) -> ChangeSet:
        """Move the map to ``revision``: re-transform only the frames whose pose changed.

        Returns per moved frame its displacement and world boxes before and after (and, with
        ``voxel_size_m``, the voxel keys it occupied before and after). Frames the target places that the view lacks
        are added after (:meth:`refresh`; not in the changes); frames it does not place are a :class:`StoreError`.
        """
        if voxel_size_m is not None and not voxel_size_m > 0:
            raise ConfigError(f"voxel_size_m must be positive, got {voxel_size_m}")
        if poses is None:
            if self._store is None:
                raise StoreError("this map has no store; pass the target poses explicitly")
            ledger = self._store.ledger
            if (outside := self.frame_ids[~np.isin(self.frame_ids, ledger.members(revision))]).size:
                raise StoreError(f"{self._store.path}: revision {revision} does not place frames {outside[:5].tolist()} "
                                 f"({outside.size}) of the view: take a new view (MapView.from_store)")
            rows = np.searchsorted(ledger.frame_ids, self.frame_ids)
            target = ledger.poses(revision)[rows]
        else:
            target = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
            if len(target) != len(self.frame_ids):
                raise StoreError(f"apply: {len(target)} poses for {len(self.frame_ids)} frames")
            geometry.require_rigid_stack(target, self.frame_ids, "apply")
        moved = np.flatnonzero(~np.all(np.abs(target - self._T) <= POSE_EPSILON, axis=(1, 2)))  # NaN: stale, redo
        moved = np.union1d(moved, self._deskew_neighbours(moved)).astype(np.int64)  # their scans' motion changed
        before_boxes = self._boxes[moved].copy()
        before_voxels = [self._voxels(r, voxel_size_m) for r in moved] if voxel_size_m else None
        old_T = self._T[moved].copy()
        self._T[moved] = target[moved]
        self._transform(moved)
        translation_m, rotation_deg = displacements(old_T, target[moved])
        changes = []
        for k, r in enumerate(moved):
            changes.append(FrameChange(
                frame_id=int(self.frame_ids[r]),
                stamp_ns=int(self.stamps_ns[r]),
                translation_m=float(translation_m[k]),
                rotation_deg=float(rotation_deg[k]),
                box_before_m=before_boxes[k].reshape(2, 3),
                box_after_m=self._boxes[r].reshape(2, 3).copy(),
                voxels_before=None if before_voxels is None else before_voxels[k],
                voxels_after=self._voxels(r, voxel_size_m) if voxel_size_m else None,
            ))
        result = ChangeSet(self.revision, revision, changes, voxel_size_m)
        logger.info("map: revision %d -> %d re-transformed %d of %d frames (%d points)", self.revision, revision,
                    len(moved), len(self.frame_ids), int(self._count[moved].sum()))
        self.revision = revision
        if poses is None and (added := self.refresh()):  # frames the target places that the view did not hold
            logger.info("map: revision %d adds %d frames (%d..%d)", revision, len(added), min(added), max(added))
        return result

    def changed_since(self, revision: int) -> ChangeSet:
        """The frames whose pose differs between ``revision`` and the map's current revision, with the
        regions they occupied then (conservative boxes: transformed sensor-frame bounds) and now."""
        if self._store is None:
            raise StoreError("this map has no store")
        ledger = self._store.ledger
        old = ledger.poses(revision)[np.searchsorted(ledger.frame_ids, self.frame_ids)]
        moved = np.flatnonzero(~np.all(np.abs(old - self._T) <= POSE_EPSILON, axis=(1, 2)))
        sensor_boxes = self._sensor_boxes(moved)
        translation_m, rotation_deg = displacements(old[moved], self._T[moved])
        changes = []
        for k, r in enumerate(moved):
            lo, hi = sensor_boxes[k, :3].astype(np.float64), sensor_boxes[k, 3:].astype(np.float64)
            corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
            world = corners @ old[r, :3, :3].T + old[r, :3, 3]
            changes.append(FrameChange(
                frame_id=int(self.frame_ids[r]), stamp_ns=int(self.stamps_ns[r]),
                translation_m=float(translation_m[k]),
                rotation_deg=float(rotation_deg[k]),
                box_before_m=np.stack([world.min(0), world.max(0)]).astype(np.float32),
                box_after_m=self._boxes[r].reshape(2, 3).copy(),
            ))
        return ChangeSet(revision, self.revision, changes)

    def _sensor_boxes(self, rows: NDArray[np.int64]) -> NDArray[np.float32]:
        out = np.empty((rows.size, 6), np.float32)
        for b in np.unique(self._buf[rows]) if rows.size else []:
            sel = np.flatnonzero(self._buf[rows] == b)
            buffer = self._buffers[int(b)]
            r = rows[sel]
            if buffer.path is None:
                boxes = np.empty((sel.size, 6), np.float32)
                frame_bounds(buffer.flat, self._start[r], self._stride[r], self._count[r], boxes)
                out[sel] = boxes
                continue
            starts, counts, piece_rows, _, first = self._pieces(r, 4)
            strides = self._stride[piece_rows]
            boxes = np.empty((starts.size, 6), np.float32)
            scratch = self._thread_scratch(strides)
            with OpenFiles(buffer.path, min(len(scratch), starts.size)) as fds:
                got = read_frame_bounds(fds, starts, strides, counts, scratch, boxes)
                self._check_read(buffer.path, fds, got, starts, counts, piece_rows)
            out[sel, :3] = np.minimum.reduceat(boxes[:, :3], first)
            out[sel, 3:] = np.maximum.reduceat(boxes[:, 3:], first)
        return out

    def _voxels(self, row: int, voxel_size_m: float) -> NDArray[np.int64]:
        if not voxel_size_m > 0:
            raise ConfigError(f"voxel_size_m must be positive, got {voxel_size_m}")
        pts = self.frame_points_world(int(self.frame_ids[row]))
        keys = floor_coords(pts[np.isfinite(pts).all(axis=1)], voxel_size_m)
        if len(keys) == 0:
            return keys
        first = first_per_key(voxel_keys(keys, None))  # in key order, as np.unique(return_index=True)
        return keys[first]

    # ------------------------------------------------------------------------------------------ access

    @property
    def n_points(self) -> int:
        return int(self._offsets[-1])

    @property
    def points_world(self) -> NDArray[np.float32]:
        """(N, 3) float32 world points of every frame, frame after frame (a read-only view)."""
        view = self._world[: self.n_points]
        view.flags.writeable = False
        return view

    def point_frame_ids(self) -> NDArray[np.int64]:
        """The frame id of every point (provenance), aligned with :attr:`points_world`."""
        return np.repeat(self.frame_ids, self._count)

    def frame_points_world(self, frame_id: int) -> NDArray[np.float32]:
        r = self._row(frame_id)
        view = self._world[self._offsets[r] : self._offsets[r + 1]]
        view.flags.writeable = False
        return view

    def pose(self, frame_id: int) -> NDArray[np.float64]:
        return self._T[self._row(frame_id)].copy()

    def frame_box_m(self, frame_id: int) -> NDArray[np.float32]:
        return self._boxes[self._row(frame_id)].reshape(2, 3).copy()

    def _row(self, frame_id: int) -> int:
        try:
            return self._index[int(frame_id)]
        except KeyError:
            raise StoreError(f"frame {frame_id} is not in the map") from None

    # ------------------------------------------------------------------------------------------ queries

    def _select(self, kind: int, q: NDArray[np.float64]) -> QueryResult:
        """The points that match the query ``kind``/``q`` (see :mod:`driftmap.kernels.points`), in map order: the pieces are sorted
        out by their boxes, then the pieces partly inside are counted and all are copied (two compiled passes)."""
        index = self._piece_index.update(len(self.frame_ids), self._offsets, self._T, self._world,
                                         piece_points=QUERY_PIECE_POINTS, parallel_min_points=QUERY_PARALLEL_POINTS)
        cls = np.empty(index.n_pieces, np.int8)
        classify_pieces(index.boxes, index.clean, kind, q, cls)
        sel = np.flatnonzero(cls)
        if sel.size == 0:
            return QueryResult(np.zeros((0, 3), np.float32), np.zeros(0, np.int64))
        starts, stops, whole = index.starts[sel], index.stops[sel], cls[sel] == PIECE_IN
        counts = stops - starts  # right for the whole pieces; the others are counted
        part = np.flatnonzero(~whole)
        if part.size:
            n_part = np.empty(part.size, np.int64)
            p_starts, p_stops = starts[part], stops[part]
            if parallel_pass(part.size, int((p_stops - p_starts).sum()), QUERY_PARALLEL_POINTS):
                query_count(self._world, p_starts, p_stops, kind, q, n_part, numba.get_num_threads())
            else:
                query_count_run(self._world, p_starts, p_stops, kind, q, n_part, 0, part.size)
            counts[part] = n_part
        hit = np.flatnonzero(counts)  # the pieces without a match are not read again
        dst = np.concatenate([[0], np.cumsum(counts[hit])]).astype(np.int64)
        points = np.empty((int(dst[-1]), 3), np.float32)
        ids = np.empty(int(dst[-1]), np.int64)
        if hit.size:
            piece_ids = self.frame_ids[index.rows[sel[hit]]]
            args = (self._world, starts[hit], stops[hit], whole[hit], piece_ids, kind, q, dst, points, ids)
            if parallel_pass(hit.size, 4 * int(dst[-1]), QUERY_PARALLEL_POINTS):
                query_fill(*args, numba.get_num_threads())
            else:
                query_fill_run(*args, 0, hit.size)
        return QueryResult(points, ids)

    def query_box(self, min_m: Sequence[float], max_m: Sequence[float], *,
                  z_range_m: tuple[float, float] | None = None) -> QueryResult:
        """Points inside an axis-aligned world box (inclusive: ``min_m <= p <= max_m`` per axis, compared in
        float64), with ``z_range_m=(lo, hi)`` also ``lo <= z <= hi``. Points come in map order (frame by frame
        in the order the frames were added, each frame's points in their stored order) with their frame ids;
        points with a NaN coordinate never match."""
        lo, hi = vec3_arg("query_box", "min_m", min_m), vec3_arg("query_box", "max_m", max_m)
        if z_range_m is not None:
            z_lo, z_hi = z_range_arg("query_box", z_range_m)
            lo[2], hi[2] = max(lo[2], z_lo), min(hi[2], z_hi)
        return self._select(QUERY_BOX, np.concatenate([lo, hi]))

    def query_radius(self, center_m: Sequence[float], radius_m: float, *,
                     z_range_m: tuple[float, float] | None = None) -> QueryResult:
        """Points within ``radius_m`` of a world position (``((x-cx)^2 + (y-cy)^2) + (z-cz)^2 <= radius_m^2`` in
        float64), with ``z_range_m=(lo, hi)`` only those with ``lo <= z <= hi`` (a height band, world frame).
        Order and provenance as :meth:`query_box`."""
        c = vec3_arg("query_radius", "center_m", center_m)
        if not radius_m >= 0:
            raise ConfigError(f"query_radius: radius_m must be a number >= 0, got {radius_m}")
        if (np.isfinite(radius_m) and radius_m > NEAREST_MAX_COORDINATE_M) or not np.all(
                np.abs(c) <= NEAREST_MAX_COORDINATE_M):  # (hostile trial 29 B2, W4: radius**2 raised OverflowError)
            raise ConfigError(f"query_radius: center_m and radius_m must lie within +-{NEAREST_MAX_COORDINATE_M:g} m "
                              f"(squares would overflow; radius_m inf takes every point), got {c.tolist()}, "
                              f"{radius_m}")
        z_lo, z_hi = (-np.inf, np.inf) if z_range_m is None else z_range_arg("query_radius", z_range_m)
        return self._select(QUERY_BALL, np.array([c[0], c[1], c[2], radius_m**2, z_lo, z_hi], np.float64))

    def nearest(self, position_m: Sequence[float], *, z_range_m: tuple[float, float] | None = None) -> Nearest:
        """The map point closest to a world position (clearance); with ``z_range_m=(lo, hi)`` the closest point
        with ``lo <= z <= hi`` (world frame), e.g. the nearest obstacle above the floor.

        Only pieces of points whose box is nearer than the best point found so far are read. Of equally near
        points, the one in the frame whose world box is nearest wins (ties as ``np.argsort`` orders them), then
        the first in that frame. Points with a NaN coordinate are left out. Raises :class:`StoreError` when no
        point qualifies."""
        q = vec3_arg("nearest", "position_m", position_m)
        if not np.all(np.abs(q) <= NEAREST_MAX_COORDINATE_M):  # squared distances would overflow to inf
            raise ConfigError(f"nearest: position_m must be finite, within +-{NEAREST_MAX_COORDINATE_M:g} m, got "
                              f"{q.tolist()}")
        z_lo, z_hi = (-np.inf, np.inf) if z_range_m is None else z_range_arg("nearest", z_range_m)
        index = self._piece_index.update(len(self.frame_ids), self._offsets, self._T, self._world,
                                         piece_points=QUERY_PIECE_POINTS, parallel_min_points=QUERY_PARALLEL_POINTS)
        bounds = np.empty(index.n_pieces)
        nearest_bounds(index.boxes, q, z_lo, z_hi, bounds)
        order = np.argsort(bounds, kind="stable")
        order = order[: np.searchsorted(bounds[order], np.inf)]  # pieces with no (usable) point last: left out
        no_points = "nearest: the map has no points" + ("" if z_range_m is None else f" with z in {z_range_m}")
        if order.size == 0:
            raise StoreError(no_points)
        starts, stops = index.starts[order], index.stops[order]
        keys = np.full(order.size, INF_KEY, np.int64)  # int64 bits of the smallest squared distances
        if parallel_pass(order.size, int((stops - starts).sum()), QUERY_PARALLEL_POINTS):
            nearest_pieces(self._world, starts, stops, bounds[order], q, z_lo, z_hi, keys, numba.get_num_threads())
        else:
            nearest_run(self._world, starts, stops, bounds[order], q, z_lo, z_hi, keys, 0, 1)
        frame_key = np.full(len(self.frame_ids), INF_KEY, np.int64)
        np.minimum.at(frame_key, index.rows[order], keys)
        distance = np.sqrt(frame_key.view(np.float64))
        best = distance.min()
        if not np.isfinite(best):
            raise StoreError(no_points)
        # ties: the frame whose world box is nearest (the order the frames were searched in before the pieces had
        # boxes of their own), then its first point at that squared distance
        b = self._boxes.astype(np.float64)
        gap = np.maximum(0.0, np.maximum(b[:, :3] - q, q - b[:, 3:]))
        frame_order = np.argsort(np.where(self._count > 0, np.linalg.norm(gap, axis=1), np.inf))
        row = int(frame_order[np.flatnonzero(distance[frame_order] == best)[0]])
        d2 = frame_key[row : row + 1].view(np.float64)[0]
        i = first_at_squared_distance(self._world, self._offsets[row], self._offsets[row + 1], q, z_lo, z_hi, d2)
        return Nearest(float(best), self._world[i].copy(), int(self.frame_ids[row]))

    # ------------------------------------------------------------------------------------------ export

    def fused(self, voxel_size_m: float | None = None, roi: RegionOfInterest | None = None) -> FusedMap:
        """Voxel-deduplicated map (centroid per voxel) with per-voxel provenance; points inside ``roi``
        (world-frame ROI) are kept at full resolution. Without ``voxel_size_m`` every finite point is kept.
        Non-finite points (NaN/inf, e.g. organised clouds) are left out and counted in a debug log."""
        if voxel_size_m is not None and not voxel_size_m > 0:
            raise ConfigError(f"voxel_size_m must be positive, got {voxel_size_m}")
        pts = self.points_world
        ids = self.point_frame_ids()
        finite = np.isfinite(pts).all(axis=1)
        if not finite.all():
            logger.debug("fused(): %d non-finite points left out", int(len(pts) - finite.sum()))
            pts, ids = pts[finite], ids[finite]
        keep = np.zeros(len(pts), bool)
        if roi is not None:
            if not roi.in_world:
                raise ConfigError("fused(): the region of interest must be in the world frame")
            keep = roi.contains(pts.astype(np.float64))
        if voxel_size_m is None:
            offsets = np.arange(len(pts) + 1, dtype=np.int64)
            return FusedMap(pts.copy(), offsets, ids, None, int(keep.sum()))
        rest = ~keep
        p, f = pts[rest], ids[rest]
        _, inverse, counts = np.unique(voxel_keys(p, voxel_size_m), return_inverse=True, return_counts=True)
        centroids = np.stack([np.bincount(inverse, weights=p[:, k].astype(np.float64)) for k in range(3)], axis=1) / counts[:, None]
        frame_rank = np.searchsorted(self._sorted_ids(), f)
        pairs = np.sort(inverse.astype(np.int64) * len(self.frame_ids) + frame_rank)
        pairs = pairs[np.r_[True, pairs[1:] != pairs[:-1]]]  # numpy 2.4's hash-based np.unique is ~100x slower here
        voxel_of_pair = pairs // len(self.frame_ids)
        prov_ids = self._sorted_ids()[pairs % len(self.frame_ids)]
        prov_offsets = np.concatenate([[0], np.cumsum(np.bincount(voxel_of_pair, minlength=len(counts)))])
        n_roi = int(keep.sum())
        if n_roi:
            centroids = np.concatenate([centroids, pts[keep]])
            prov_ids = np.concatenate([prov_ids, ids[keep]])
            prov_offsets = np.concatenate([prov_offsets, prov_offsets[-1] + np.arange(1, n_roi + 1)])
        return FusedMap(centroids.astype(np.float32), prov_offsets.astype(np.int64), prov_ids.astype(np.int64), voxel_size_m, n_roi)

    def _sorted_ids(self) -> NDArray[np.int64]:
        return np.sort(self.frame_ids)

    def export(self, path: str | Path, *, voxel_size_m: float | None = None, roi: RegionOfInterest | None = None,
               provenance: bool = False) -> Path:
        """Write the map as PLY or PCD (Open3D); with ``provenance`` also ``<path>.provenance.npz``."""
        return self.write(path, voxel_size_m=voxel_size_m, roi=roi, provenance=provenance)[0]

    def write(self, path: str | Path, *, voxel_size_m: float | None = None, roi: RegionOfInterest | None = None,
              provenance: bool = False) -> tuple[Path, int]:
        """:meth:`export`, also returning how many points the file holds (after voxel fusion).

        The input is checked first: a view without frames is an :class:`~driftmap.errors.EmptyStoreError` ("store X
        has no frames in revision N"), a map without a finite point an :class:`~driftmap.errors.EmptyExportError`;
        a path inside a store folder is refused (:func:`driftmap.store.refuse_inside_store`). Each file is written
        under a temporary name and renamed into place when complete: a failed export leaves no partial file, and an
        existing file survives a failed overwrite."""
        fused = self.fused_for_export(path, voxel_size_m=voxel_size_m, roi=roi)
        return self.write_fused(path, fused, provenance=provenance)

    def fused_for_export(self, path: str | Path, *, voxel_size_m: float | None = None,
                         roi: RegionOfInterest | None = None) -> FusedMap:
        """What :meth:`write` checks before it writes, and the fused map it would write (same errors): a caller
        writing several files checks them all first (``export`` writes nothing when one output would fail)."""
        path = Path(path)
        if path.suffix.lower() not in (".ply", ".pcd"):
            raise ConfigError(f"{path}: map export supports .ply and .pcd")
        refuse_inside_store(path, "map export path")
        if len(self.frame_ids) == 0:
            where = f"store {self._store.path}" if self._store is not None else "the map"
            raise EmptyStoreError(f"{where} has no frames in revision {self.revision}: no map to export (nothing "
                                  f"written to {path})", store=None if self._store is None else self._store.path,
                                  revision=self.revision)
        fused = self.fused(voxel_size_m, roi)
        if len(fused.points_world) == 0:
            raise EmptyExportError(f"{path}: the map of revision {self.revision} has no point to write ({len(self.frame_ids)} "
                                   f"frames, none with a finite point{' in the region' if roi is not None else ''}); "
                                   f"nothing written")
        return fused

    @staticmethod
    def write_fused(path: str | Path, fused: FusedMap, *, provenance: bool = False) -> tuple[Path, int]:
        """Write what :meth:`fused_for_export` returned (its per-voxel provenance beside it with ``provenance``)."""
        path = Path(path)
        if not provenance:
            return write_cloud(path, fused.points_world), len(fused.points_world)
        side = Path(str(path) + ".provenance.npz")
        with atomic_output(side, "map provenance file") as tmp_side:
            with open(tmp_side, "wb") as fh:  # a file object: savez does not append ".npz" to the temporary name
                np.savez_compressed(fh, offsets=fused.provenance_offsets, frame_ids=fused.provenance_frame_ids)
            out = write_cloud(path, fused.points_world)  # the map first: a failed map leaves no new provenance file
        return out, len(fused.points_world)
