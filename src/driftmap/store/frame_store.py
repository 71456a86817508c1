"""The frame store: an append-only directory of MCAP segments holding every frame in its sensor frame,
with all its metadata and every pose revision.

Layout::

    STORE/
      store.json             manifest: format, version, uuid, segments and their state (open / closed)
      segment-000000.mcap    frames and revisions, one chunk per append (see driftmap.store.segment)
      segment-000001.mcap    a later writer session appends to a new segment
      writer.lock            held (flock) by the one process that appends

Crash safety: every append is flushed as a complete chunk before it counts. A writer killed mid-append
leaves its segment ``open`` in the manifest with at most one incomplete chunk at its end. The next
writer that opens the store recovers that segment automatically: it rewrites the complete chunks into
a clean, closed segment and keeps the dropped tail bytes in ``segment-NNNNNN.dropped-tail.bin``.
A *closed* segment that is truncated or damaged is never repaired silently: opening raises
:class:`StoreCorruptError` naming the file and offset; ``FrameStore.recover(path)`` (``driftmap recover``)
salvages every intact frame and revision into a new segment and keeps the damaged file beside it.

Losses. Revision records are never rewritten to fit the frames that survived: a revision stored in an intact
segment may still name frames a damaged (or deleted) segment took with it, and a revision may follow one whose
record is gone. ``recover`` finds both and appends a ``data_lost`` event (in a new segment of its own) naming
those frames and revisions. Opening then reads every revision without the poses of the lost frames (its other
poses are kept, even if none are left: it is history), puts a stand-in without poses of its own (parent: the
revision before it) in the place of each lost revision so later ids still mean the same revisions, and
reports all of it in ``FrameStore.loss`` (:class:`DataLoss`). A revision naming a missing frame, or a gap in
the revision ids, that no ``data_lost`` event declares is damage nobody has looked at: opening raises
:class:`StoreCorruptError` asking for ``driftmap recover``.
"""
from __future__ import annotations

import logging
import mmap
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from driftmap.errors import (
    ConfigError,
    DriftmapError,
    EmptyStoreError,
    FrameRejectedError,
    GeometryError,
    StoreCorruptError,
    StoreError,
    parse_enum,
)
from driftmap.frame import Frame, PoseEstimate, PoseSource
from driftmap.store.damage import DataLoss, RecoveryEvent
from driftmap.store.guards import READ_HINT, RECOVER_HINT, RESUME_HINT, refuse_inside_store, store_io_error
from driftmap.store.layout import FORMAT_NAME, LOCK_FILE, MANIFEST, SEGMENT_FILE, TMP_SUFFIX
from driftmap.store.ledger import (
    SAME_POSE_DEG,
    SAME_POSE_M,
    PoseDiff,
    PoseLedger,
    PoseMatch,
    PoseMatchMode,
    Revision,
    match_pose_rows,
    stamp_ranges_text,
)
from driftmap.store.lock import acquire_writer_lock, release_writer_lock, writer_alive
from driftmap.store.manifest import (
    FORMAT_VERSION,
    SegmentEntry,
    entries_of,
    new_manifest,
    read_manifest,
    write_manifest,
)
from driftmap.store.opening import load_segments
from driftmap.store.values import as_int
from driftmap.store.pose_io import TrajectoryFormat, export_trajectory, import_poses, warn_about_revision
from driftmap.store.reading import frame_from_ref, release_maps, segment_map
from driftmap.store.recovery import recover_open_segments, recover_store
from driftmap.store.segment import (
    EVENT_DATA_LOST,
    SegmentScan,
    SegmentWriter,
    StoredFrameRef,
    check_frame_for_store,
    frame_from_info,
    iter_payload_bytes,
    read_store_uuid,
    scan_segment,
    unpack_attributes,
)
from driftmap.store.writing import (
    check_new_frame,
    finish_segment,
    refuse_broken,
    start_segment,
    write_frame,
    write_revision,
)
from driftmap.trajectory import Trajectory, has_stamps, read_trajectory, write_kitti, write_tum

#: what this module offers: FrameStore and its types, and (as before the store was split into modules of one concept
#: each) the names it used to define or import
__all__ = [
    "EVENT_DATA_LOST", "FORMAT_NAME", "FORMAT_VERSION", "LOCK_FILE", "MANIFEST", "READ_HINT", "RECOVER_HINT",
    "RESUME_HINT", "SAME_POSE_DEG", "SAME_POSE_M", "SEGMENT_FILE", "ConfigError", "DataLoss", "DriftmapError",
    "EmptyStoreError", "Frame", "FrameRejectedError", "FrameStore", "GeometryError", "PoseDiff", "PoseEstimate",
    "PoseLedger", "PoseMatch", "PoseMatchMode", "PoseSource", "RecoveryEvent", "Revision", "SegmentScan",
    "SegmentWriter", "StoreCorruptError", "StoreError", "StoredFrameRef", "Trajectory", "TrajectoryFormat",
    "check_frame_for_store", "frame_from_info", "has_stamps", "iter_payload_bytes", "match_pose_rows", "parse_enum",
    "read_store_uuid", "read_trajectory", "refuse_inside_store", "scan_segment", "stamp_ranges_text", "store_io_error",
    "unpack_attributes", "write_kitti", "write_tum",
]

logger = logging.getLogger(__name__)



def creation_leftovers(path: str | Path) -> list[Path]:
    """The files of a store creation that was killed before its manifest was renamed into place (``store.json.tmp``,
    ``writer.lock``), when the folder holds nothing else: no frame was ever stored, so they may be removed.
    Empty for any other folder."""
    path = Path(path)
    own = {MANIFEST + TMP_SUFFIX, LOCK_FILE}
    try:
        if not path.is_dir():
            return []
        entries = list(path.iterdir())
    except OSError:
        return []
    if not entries or any(p.name not in own or not p.is_file() for p in entries):
        return []
    return sorted(entries)

class FrameStore:
    """Every frame with the pose estimate that produced it, plus every pose revision; nothing overwritten.

    Open with :meth:`create` or :meth:`open`; use as a context manager (or call :meth:`close`) so the
    writer's segment is finished with an MCAP summary.

    The store is this facade over modules of one concept each: the manifest (:mod:`~driftmap.store.manifest`),
    the writer lock (:mod:`~driftmap.store.lock`), opening (:mod:`~driftmap.store.opening`), the write session
    (:mod:`~driftmap.store.writing`), reading frames back (:mod:`~driftmap.store.reading`), recovery
    (:mod:`~driftmap.store.recovery`) and pose files (:mod:`~driftmap.store.pose_io`).
    """

    def __init__(self, path: Path, mode: str, manifest: dict[str, Any], *, fsync: bool = False):
        self.path = path
        self.mode = mode
        self._manifest = manifest
        self._fsync = fsync
        self._segments: list[SegmentEntry] = entries_of(manifest)
        self._refs: dict[int, StoredFrameRef] = {}
        self.ledger = PoseLedger()
        self._writer: SegmentWriter | None = None
        self._lock_fh: Any = None
        self.recovery_events: list[RecoveryEvent] = []
        self.loss = DataLoss()
        """The frames and revisions this store lost to damage, as ``recover`` declared them (empty: none)."""
        self._closed = False

    # ------------------------------------------------------------------------------------------ opening

    @classmethod
    def create(cls, path: str | Path, *, fsync: bool = False) -> FrameStore:
        """Create a new, empty store directory (it must not exist or be empty) and open it for appending."""
        path = Path(path)
        hint = "nothing was stored; fix that and run the command again"
        try:
            if path.exists() and not path.is_dir():
                raise StoreError(f"{path}: exists and is a file, not a store directory")
            leftovers = creation_leftovers(path)
            if leftovers:  # a create killed before its manifest was in place: no frame was ever stored
                logger.warning("%s: removing what an interrupted store creation left (%s)", path,
                               ", ".join(p.name for p in leftovers))
                for p in leftovers:
                    p.unlink()
            if path.exists() and any(path.iterdir()):
                raise StoreError(f"{path}: exists and is not empty; open it instead of creating it")
        except OSError as exc:
            raise store_io_error(exc, path, "looking at the store folder", path, hint) from exc
        try:
            path.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise StoreError(f"{path}: cannot create the store directory ({exc.strerror or exc})") from exc
        manifest = new_manifest()
        try:
            write_manifest(path, manifest, [])
        except OSError as exc:
            raise store_io_error(exc, path / MANIFEST, "writing the manifest of a new store", path, hint) from exc
        store = cls(path, "a", manifest, fsync=fsync)
        store._acquire_lock()
        return store

    @classmethod
    def open(cls, path: str | Path, mode: str = "r", *, verify: bool = True, fsync: bool = False) -> FrameStore:
        """Open an existing store for reading (``"r"``) or appending (``"a"``).

        ``verify`` checks every chunk's CRC (reads all bytes once). A segment left open by a writer that
        crashed is recovered automatically when opening for appending, and read up to its last complete
        frame when opening for reading (a reader may also follow a live writer this way).
        """
        path = Path(path)
        if mode not in ("r", "a"):
            raise StoreError(f"mode must be 'r' or 'a', got {mode!r}")
        manifest = read_manifest(path)
        store = cls(path, mode, manifest, fsync=fsync)
        try:
            if mode == "a":
                store._acquire_lock()
            store._load(verify=verify)
        except BaseException:
            store._release()
            raise
        return store

    def _acquire_lock(self) -> None:
        """Take the writer lock: appending needs write access, reading never takes it."""
        self._lock_fh = acquire_writer_lock(self.path)

    def _load(self, *, verify: bool) -> None:
        live_writer = self._lock_fh is None and writer_alive(self.path)  # never true for the writer itself
        self.loss, events = load_segments(self.path, self._manifest["store_uuid"], self._segments, self.ledger,
                                          self._refs, verify=verify, live_writer=live_writer)
        self.recovery_events += events
        if self.mode == "a":
            try:
                self.recovery_events += recover_open_segments(self.path, self._manifest, self._segments, self._refs)
            except OSError as exc:
                raise store_io_error(exc, getattr(exc, "filename", None) or self.path, "recovering a segment left open by "
                                     "a writer that stopped", self.path, RECOVER_HINT) from exc

    def _write_manifest(self) -> None:
        write_manifest(self.path, self._manifest, self._segments)

    @classmethod
    def recover(cls, path: str | Path) -> list[RecoveryEvent]:
        """Salvage every intact frame and revision of a damaged store; returns what was done (nothing: ``[]``).

        - An unreadable or missing ``store.json`` is rebuilt from the segments (each names its store); the
          damaged one is kept as ``store.json.damaged``.
        - Each damaged segment (truncated, damaged chunks, left open) is rewritten from its intact chunks; the
          damaged file is kept beside it as ``<name>.damaged``. A missing segment is removed from the manifest.
        - Revision records are kept as they are. The frames that stored revisions name but no segment holds any
          more, and the revisions whose records are gone (a gap in the ids), are declared in a ``data_lost`` event
          appended in a new segment: opening then reads each revision without the poses of the lost frames and
          puts stand-ins in the place of lost revisions (see the module docstring and :class:`DataLoss`). The
          event returned for it says which frames were lost and which revisions lost what.

        Every step is a complete file written beside the old one and renamed into place, with the manifest
        written after it, so an interrupted recovery is finished by running it again. Idempotent: on a healthy
        store (or a second run) it returns ``[]``. Raises :class:`StoreCorruptError` if the store still does not
        open afterwards.
        """
        path = Path(path)
        try:
            return recover_store(path)
        except OSError as exc:  # whatever step it was: every step so far is complete, the next run goes on from there
            raise store_io_error(exc, exc.filename or path, "recovering the store", path, RECOVER_HINT) from exc

    # ------------------------------------------------------------------------------------------ frames

    @property
    def frame_ids(self) -> NDArray[np.int64]:
        return self.ledger.frame_ids

    def __len__(self) -> int:
        return self.ledger.n_frames

    def __contains__(self, frame_id: int) -> bool:
        return frame_id in self.ledger

    def _writable(self, what: str = "appending") -> SegmentWriter:
        """The segment writer of this session (a new segment is started, and listed in the manifest, on first use).

        An ``OSError`` is a :class:`StoreIOError` naming the file; a writer broken by an earlier failed write
        refuses (see :class:`SegmentWriter`)."""
        if self._closed:
            raise StoreError(f"{self.path}: store is closed")
        if self.mode != "a":
            raise StoreError(f"{self.path}: opened read-only; open with mode='a' to append")
        refuse_broken(self.path, self._writer, what)
        if self._writer is None:
            self._writer = start_segment(self.path, self._manifest, self._segments, fsync=self._fsync, what=what)
        return self._writer

    def append(self, frame: Frame) -> None:
        """Store a frame (sensor-frame points and metadata) with the pose that produced it (revision 0).

        Every value is checked before anything is written (:func:`driftmap.store.segment.check_frame_for_store`:
        a stamp that is not an integer in ``0 .. 2**63 - 1`` ns, a non-finite or non-rigid pose, an infinite point
        coordinate, ... are a :class:`~driftmap.errors.FrameRejectedError` naming the frame and the field; NaN
        points are stored, the map leaves them out), and so is a duplicate ``frame_id``. After a refused frame the
        store goes on as before (append the next one, or close it).

        A failed write (disk full, I/O error) is a :class:`~driftmap.errors.StoreIOError` naming the segment file:
        the frames before it stay intact, the unfinished record is cut off, and the segment is left ``open`` for
        the next writer (``driftmap build ... --resume``) or ``driftmap recover`` to finish; this session takes no
        more appends.
        """
        fid, T, source = check_new_frame(self.path, self.ledger, frame)
        writer = self._writable(f"appending frame {fid}")
        payload_offset, info = write_frame(self.path, writer, frame, fid)
        self.ledger.add_frame(fid, frame.stamp_ns, T, source)
        self._refs[fid] = StoredFrameRef(info, writer.path, payload_offset)

    def frame_info(self, frame_id: int) -> dict[str, Any]:
        """The stored metadata of a frame (JSON-like dict)."""
        return self._ref(frame_id).info

    def _ref(self, frame_id: int) -> StoredFrameRef:
        try:
            return self._refs[as_int(frame_id, "frame_id")]
        except KeyError:
            raise StoreError(f"{self.path}: no frame {frame_id} in the store") from None

    def frame(self, frame_id: int, revision: int | None = None) -> Frame:
        """A stored frame (points copied out of the store), with its pose in ``revision`` (default 0)."""
        ref = self._ref(frame_id)
        frame = frame_from_ref(self.path, ref, None if ref.payload_copy is not None else self.payload_map(ref))
        if revision:
            T = self.ledger.pose(revision, frame.frame_id)
            rev = self.ledger.revision(revision)
            frame = frame.with_pose(PoseEstimate(T, revision=revision, source=rev.source, world_frame=frame.pose.world_frame))
        return frame

    def iter_frames(self, revision: int | None = None) -> Iterator[Frame]:
        for frame_id in self.frame_ids:
            yield self.frame(int(frame_id), revision)

    def payload_map(self, ref: StoredFrameRef) -> mmap.mmap:
        """The mapped segment holding a frame's payload (large enough to contain it)."""
        return segment_map(self.path, self._segments, ref.segment, ref.payload_offset + ref.n_points * ref.point_stride)

    def frame_ref(self, frame_id: int) -> StoredFrameRef:
        """Where a frame's metadata and point payload live."""
        return self._ref(frame_id)

    # ------------------------------------------------------------------------------------------ poses

    @property
    def revisions(self) -> list[Revision]:
        return self.ledger.revisions

    @property
    def head(self) -> int:
        return self.ledger.head

    @property
    def uuid(self) -> str:
        """The store's id (``store_uuid`` of its manifest): what a file made from it (a diagnosis) names it by."""
        return str(self._manifest["store_uuid"])

    def poses(self, revision: int | None = None) -> NDArray[np.float64]:
        """(M, 4, 4) ``T_world_sensor`` of every frame (in ``frame_ids`` order) in a revision (default head)."""
        return self.ledger.poses(self.head if revision is None else revision)

    def members(self, revision: int | None = None) -> NDArray[np.int64]:
        """Sorted ids of the frames a revision (default head) places (:meth:`PoseLedger.members
        <driftmap.store.ledger.PoseLedger.members>`: a revision made before frames were appended does not hold them)."""
        return self.ledger.members(self.head if revision is None else revision)

    def _persist(self, revision: Revision) -> Revision:
        write_revision(self.path, self._writable(f"storing revision {revision.revision_id}"), revision)
        return self.ledger.commit(revision)

    def add_revision(self, poses: Mapping[int, NDArray[np.float64]], *, source: PoseSource | str, parent: int | None = None,
                     propagate: bool = True, note: str = "",
                     covariances: Mapping[int, NDArray[np.float64]] | None = None) -> Revision:
        """Store a correction as a new revision. Poses given for a subset of frames (keyframes) propagate to
        the others when ``propagate`` (see :meth:`PoseLedger.plan_correction`); ``covariances``: the 6x6
        uncertainty of given poses (:class:`~driftmap.store.revision.Revision`, e.g. a pose graph's marginals)."""
        self._writable()
        source = parse_enum(PoseSource, source, f"{self.path}: add_revision source")
        revision = self.ledger.plan_correction(poses, source=source, parent=parent, propagate=propagate, note=note,
                                               covariances=covariances)
        return self._persist(revision)

    def rollback(self, to: int, *, note: str = "") -> Revision:
        """A new revision whose poses equal revision ``to`` (nothing is deleted; a warning when the head already
        has those poses)."""
        planned = self.ledger.plan_rollback(to, note=note)  # a bad target is refused before a segment is started
        revision = self._persist(planned)  # (hostile trial 20 W5: each refusal left an empty segment)
        warn_about_revision(self, revision, f"{self.path}: rolling back to revision {to}")
        return revision

    def diff(self, a: int, b: int) -> PoseDiff:
        return self.ledger.diff(a, b)

    def import_poses(self, file: str | Path, *, format: TrajectoryFormat | str = TrajectoryFormat.TUM,
                     match: PoseMatchMode | str | None = None, max_dt_ns: int = 10_000_000,
                     source: PoseSource | str = PoseSource.EXTERNAL_FILE, propagate: bool = True,
                     kitti_frame: str = "auto", calib_file: str | Path | None = None,
                     rows_in_sensor_frame: Callable[[Trajectory, str], Trajectory] | None = None) -> tuple[Revision, PoseMatch]:
        """Import a TUM, KITTI, Redwood ``.log`` or ``4x4`` pose file as a new revision.

        Files with stamps (TUM, 4x4 blocks with stamps) match by stamp (``max_dt_ns`` tolerance) unless
        ``match='index'``; files without (KITTI, 4x4 blocks without stamps) match by index: row i is the pose of
        ``frame_id`` i; a Redwood ``.log`` by the frame ids it names. Rows for frames not in the store are ignored and
        reported in the returned :class:`PoseMatch`; stored frames without a row are propagated from the
        matched ones (``propagate``) or keep their pose.

        The rows are taken as the frames' ``T_world_sensor``, or converted to it by ``rows_in_sensor_frame(trajectory,
        format)``: the store does not know the data sets its frames come from, so the rules for a KITTI sequence's
        cam0 ``poses.txt`` on its Velodyne scans (``kitti_frame`` ``auto`` | ``velodyne`` | ``cam0``, ``calib_file``)
        or the synthetic log's camera files on its LiDAR live above it:
        :func:`driftmap.pipeline.pose_files.import_pose_file` (``driftmap correct``) passes them.
        """
        return import_poses(self, file, format=format, match=match, max_dt_ns=max_dt_ns, source=source,
                            propagate=propagate, kitti_frame=kitti_frame, calib_file=calib_file,
                            rows_in_sensor_frame=rows_in_sensor_frame)

    def export_trajectory(self, file: str | Path, *, revision: int | None = None,
                          format: TrajectoryFormat | str = TrajectoryFormat.TUM,
                          frame_ids: Sequence[int] | None = None) -> Path:
        """Write the poses of a revision: TUM with the frames' stamps, or KITTI one row per stored frame in
        frame order (which reads back as row i = frame_id i only when the ids are 0..N-1: a warning otherwise).
        ``frame_ids``: only these frames (in store order; e.g. one session of a merged store). A path inside a
        store folder is refused; the file is written under a temporary name and renamed into place."""
        return export_trajectory(self, file, revision=revision, format=format, frame_ids=frame_ids)

    # ------------------------------------------------------------------------------------------ closing

    def size_bytes(self) -> int:
        return sum((self.path / s.name).stat().st_size for s in self._segments if (self.path / s.name).exists())

    def close(self) -> None:
        """Finish this session's segment (MCAP summary and footer), record it ``closed`` and release the lock.

        After a failed write the segment cannot be finished: it is left ``open`` (its complete chunks intact) for
        the next writer or ``driftmap recover``, with a warning, and closing succeeds. A failure to finish it
        now (disk full) is a :class:`~driftmap.errors.StoreIOError` naming the file; the lock is released and the
        segment is left the same way."""
        if self._closed:
            return
        try:
            writer, self._writer = self._writer, None
            if writer is not None:
                finish_segment(self.path, self._manifest, self._segments, writer)
        finally:
            self._release()
            self._closed = True

    def abandon(self) -> None:
        """Release the store without finishing its segment and without the "left open" warning: for a scratch store
        its caller removes next (a merge that failed writes nothing it would leave behind)."""
        if self._closed:
            return
        try:
            writer, self._writer = self._writer, None
            if writer is not None:
                writer.abandon()
        finally:
            self._release()
            self._closed = True

    def discard_session(self) -> bool:
        """Take back everything this writer session stored and release the store: the segment it started is taken
        off the manifest (written atomically) and its file removed; the earlier segments are never touched, so the
        store is as it was opened. For an all-or-nothing append that failed before it was complete (``merge
        --append``). A crash inside leaves the segment listed (or, between the two steps, unlisted): the next writer
        or ``driftmap recover`` keeps its frames as after any interrupted append. Returns whether anything was
        discarded."""
        if self._closed:
            return False
        writer, self._writer = self._writer, None
        try:
            if writer is None:
                return False
            writer.abandon()
            self._segments[:] = [s for s in self._segments if s.name != writer.path.name]
            try:
                self._write_manifest()
                writer.path.unlink(missing_ok=True)
            except OSError as exc:
                raise store_io_error(exc, getattr(exc, "filename", None) or self.path, "discarding an unfinished "
                                     "append", self.path, RECOVER_HINT) from exc
            logger.info("%s: discarded the unfinished segment %s", self.path, writer.path.name)
            return True
        finally:
            self._release()
            self._closed = True

    def _release(self) -> None:
        release_maps(self._segments)
        if self._lock_fh is not None:
            release_writer_lock(self._lock_fh)
            self._lock_fh = None

    def __enter__(self) -> FrameStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"FrameStore({str(self.path)!r}, mode={self.mode!r}, frames={len(self)}, revisions={len(self.revisions)})"
