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

import contextlib
import enum
import errno
import fcntl
import json
import logging
import mmap
import os
import re
import shutil
import time
import uuid
import zlib
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from driftmap import __version__, geometry
from driftmap.errors import (
    ConfigError,
    DriftmapError,
    EmptyStoreError,
    FrameRejectedError,
    GeometryError,
    StoreError,
    parse_enum,
)
from driftmap.frame import Frame, PoseEstimate, PoseSource
from driftmap.store.guards import (
    READ_HINT,
    RECOVER_HINT,
    RESUME_HINT,
    SEGMENT_FILE,
    refuse_inside_store,
    store_io_error,
)
from driftmap.store.ledger import (
    SAME_POSE_DEG,
    SAME_POSE_M,
    PoseDiff,
    PoseLedger,
    PoseMatch,
    PoseMatchMode,
    Revision,
    _preview,
    match_pose_rows,
    stamp_ranges_text,
)
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
from driftmap.trajectory import Trajectory, has_stamps, read_trajectory, write_kitti, write_tum

logger = logging.getLogger(__name__)

FORMAT_NAME = "driftmap-store"
FORMAT_VERSION = 1
MANIFEST = "store.json"
LOCK_FILE = "writer.lock"
_SEGMENT_NAME = re.compile(r"segment-(\d+)\.")


class StoreCorruptError(StoreError):
    """A store file is truncated or damaged; names the file and the byte offset."""

    def __init__(self, message: str, *, path: Path, offset: int | None):
        super().__init__(message)
        self.path = path
        self.offset = offset


class TrajectoryFormat(enum.Enum):
    """Pose-file formats of ``correct`` / ``export`` (export writes TUM and KITTI only)."""

    TUM = "tum"
    KITTI = "kitti"
    REDWOOD = "redwood"
    MATRIX_4X4 = "4x4"


@dataclass(frozen=True)
class DataLoss:
    """What damage took from a store's frames and revisions (declared by ``recover``), and what it did to the
    revisions that survived.

    ``frame_ids``: the lost frames (named by a stored revision, held by no segment; a lost frame that nothing
    names cannot be identified once its bytes are gone). ``revision_ids``: the revisions whose record is gone; a
    stand-in without poses of its own (parent: the revision before it) holds each one's id. ``trimmed``: revision
    -> the lost frames whose poses it no longer holds (it keeps all its other poses). ``orphaned``: revision ->
    its lost parent (the frames it does not set now take the stand-in's poses, those of the revision before).
    """

    frame_ids: tuple[int, ...] = ()
    revision_ids: tuple[int, ...] = ()
    trimmed: Mapping[int, tuple[int, ...]] = field(default_factory=dict, hash=False)
    orphaned: Mapping[int, int] = field(default_factory=dict, hash=False)

    def __bool__(self) -> bool:
        return bool(self.frame_ids or self.revision_ids)

    def only(self, frame_ids: set[int], revision_ids: set[int]) -> DataLoss:
        """The part of this loss that concerns ``frame_ids`` and ``revision_ids``."""
        trimmed = {r: mine for r, lost in self.trimmed.items() if (mine := tuple(f for f in lost if f in frame_ids))}
        return DataLoss(tuple(f for f in self.frame_ids if f in frame_ids),
                        tuple(r for r in self.revision_ids if r in revision_ids), trimmed,
                        {r: p for r, p in self.orphaned.items() if p in revision_ids})

    def __str__(self) -> str:
        parts = []
        if self.frame_ids:
            parts.append(f"frames {_preview(self.frame_ids)} are lost")
        parts += [f"revision {r} lost the poses of {_preview(lost)}" for r, lost in sorted(self.trimmed.items())]
        if self.revision_ids:
            parts.append(f"the records of revisions {_preview(self.revision_ids)} are lost (a stand-in with the poses of "
                         f"the revision before holds each one's place)")
        for r, p in sorted(self.orphaned.items()):
            base = p - 1
            while base in self.revision_ids:
                base -= 1
            parts.append(f"revision {r}: its parent {p} is lost, the frames it does not set take revision {base}'s poses")
        return "; ".join(parts) or "nothing lost"


@dataclass(frozen=True)
class RecoveryEvent:
    """What opening or recovering a store had to drop or repair.

    For a segment: the frames and revision records it kept and the bytes that were not carried over (an
    unfinished tail, damaged chunks). For ``store.json`` and for the ``data_lost`` record: the frames and
    revisions (revision 0 included, as ``driftmap revisions`` lists them) of the recovered store. ``loss``: the
    frames and revisions this recovery found lost (see :class:`DataLoss`).
    """

    segment: str
    action: str
    frames_kept: int
    revisions_kept: int
    dropped_bytes: int
    detail: str
    loss: DataLoss | None = None

    def __str__(self) -> str:
        text = f"{self.segment}: {self.action}: kept {self.frames_kept} frames and {self.revisions_kept} revisions"
        if self.dropped_bytes:
            text += f", dropped {self.dropped_bytes} bytes"
        if self.loss:
            text += f"; {self.loss}"
        return f"{text} ({self.detail})"


def _without_frames(rev: Revision, lost: list[int]) -> Revision:
    """``rev`` without the poses of the lost frames (every other field and pose unchanged)."""
    gone = set(lost)
    note = f"{rev.note} " if rev.note else ""
    return Revision(rev.revision_id, rev.parent_id, rev.source, rev.created_ns,
                    f"{note}[recovery: poses of {len(gone)} lost frame(s) removed]",
                    {k: v for k, v in rev.set_directly.items() if k not in gone},
                    {k: v for k, v in rev.propagated.items() if k not in gone}, rev.restores)


def _lost_ids(event: dict[str, Any], file: Path) -> tuple[set[int], set[int]]:
    """The frame and revision ids a ``data_lost`` event declares lost."""
    ids = []
    for key in ("frame_ids", "revision_ids"):
        value = event.get(key)
        if not isinstance(value, list) or any(isinstance(i, bool) or not isinstance(i, int) for i in value):
            raise StoreCorruptError(f"{file}: malformed {EVENT_DATA_LOST} record ({key} must be a list of integers)",
                                    path=file, offset=None)
        ids.append(set(value))
    return ids[0], ids[1]


def _fsync_dir(path: Path) -> None:
    dir_fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)


def _keep_copy(file: Path, copy: Path) -> None:
    """Keep ``file``'s bytes as ``copy`` (a hard link, else a copy) while ``file`` itself stays in place."""
    try:
        os.link(file, copy)
    except OSError:
        tmp = copy.with_name(copy.name + ".tmp")
        shutil.copyfile(file, tmp)
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, copy)


def _free_name(path: Path) -> Path:
    """``path``, or ``path.1``, ``path.2``, ... : the first that does not exist (never overwrite a kept file)."""
    candidate, n = path, 0
    while candidate.exists():
        n += 1
        candidate = path.with_name(f"{path.name}.{n}")
    return candidate


def _decode_frame(ref: StoredFrameRef, mm: mmap.mmap | None) -> Frame | str:
    """The frame ``ref`` points at, or why it cannot be read back. Returns instead of raising, so that no exception
    (traceback) keeps a view of the mapped segment alive."""
    n, stride = ref.n_points, ref.point_stride
    payload = np.frombuffer(iter_payload_bytes(ref, mm), dtype=np.uint8)
    if len(payload) != n * stride:
        return f"{len(payload)} payload bytes, {n * stride} expected"
    try:
        if stride == 12:
            points = payload.view("<f4").reshape(n, 3)
        else:
            points = np.ascontiguousarray(payload.reshape(n, stride)[:, :12]).view("<f4").reshape(n, 3)
        attributes = unpack_attributes(payload, n, stride, ref.info["points"]["fields"])
        return frame_from_info(ref.info, points, attributes)
    except (DriftmapError, KeyError, TypeError, ValueError, ArithmeticError, AttributeError) as exc:
        return f"stored metadata cannot be read back ({type(exc).__name__}: {exc})"


def _segment_index(name: str) -> int:
    return int(name[len("segment-"):].split(".")[0])


def _segment_files(folder: Path) -> list[Path]:
    """The ``segment-NNNNNN.mcap`` files of a store folder, in index order."""
    files = [f for f in folder.iterdir() if SEGMENT_FILE.fullmatch(f.name)] if folder.is_dir() else []
    return sorted(files, key=lambda f: _segment_index(f.name))


def _id_sample(ids: NDArray[np.int64]) -> str:
    """``0, 5, 10, ..., 95`` for messages."""
    shown = ", ".join(str(int(i)) for i in ids[:3])
    return f"{shown}, ..., {int(ids[-1])}" if len(ids) > 4 else ", ".join(str(int(i)) for i in ids)


def _atomic_write_json(path: Path, data: dict[str, Any]) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w") as fh:
        json.dump(data, fh, indent=1)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)
    _fsync_dir(path.parent)


@dataclass
class _Segment:
    name: str
    state: str
    bytes: int | None
    scan: SegmentScan | None = None
    mm: mmap.mmap | None = None


class FrameStore:
    """Every frame with the pose estimate that produced it, plus every pose revision; nothing overwritten.

    Open with :meth:`create` or :meth:`open`; use as a context manager (or call :meth:`close`) so the
    writer's segment is finished with an MCAP summary.
    """

    def __init__(self, path: Path, mode: str, manifest: dict[str, Any], *, fsync: bool = False):
        self.path = path
        self.mode = mode
        self._manifest = manifest
        self._fsync = fsync
        self._segments: list[_Segment] = [_Segment(s["name"], s["state"], s.get("bytes")) for s in manifest["segments"]]
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
            if path.exists() and any(path.iterdir()):
                raise StoreError(f"{path}: exists and is not empty; open it instead of creating it")
        except OSError as exc:
            raise store_io_error(exc, path, "looking at the store folder", path, hint) from exc
        try:
            path.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise StoreError(f"{path}: cannot create the store directory ({exc.strerror or exc})") from exc
        manifest = {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "store_uuid": uuid.uuid4().hex,
            "created_ns": time.time_ns(),
            "driftmap_version": __version__,
            "segments": [],
        }
        try:
            _atomic_write_json(path / MANIFEST, manifest)
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
        manifest = cls._read_manifest(path)
        store = cls(path, mode, manifest, fsync=fsync)
        try:
            if mode == "a":
                store._acquire_lock()
            store._load(verify=verify)
        except BaseException:
            store._release()
            raise
        return store

    @staticmethod
    def _read_manifest(path: Path, *, hint: bool = True) -> dict[str, Any]:
        """The manifest; a missing or unreadable one is a StoreCorruptError (``hint``: saying how to rebuild it)."""
        file = path / MANIFEST
        if path.is_file():
            raise StoreError(f"{path}: is a file, not a driftmap store (a store is a folder holding {MANIFEST} and "
                             f"segment-NNNNNN.mcap files)")
        fix = f"; run `driftmap recover {path}` to rebuild it from the segments" if hint else ""
        try:
            manifest = json.loads(file.read_bytes())
        except FileNotFoundError as exc:
            segments = sorted(path.glob("segment-*.mcap")) if path.is_dir() else []
            if segments:
                raise StoreCorruptError(f"{file}: missing, but {path} holds {len(segments)} segment file(s){fix}",
                                        path=file, offset=None) from exc
            raise StoreError(f"{path}: not a driftmap store ({MANIFEST} missing)") from exc
        except IsADirectoryError as exc:
            raise StoreCorruptError(f"{file}: is a folder, not the manifest{fix}", path=file, offset=None) from exc
        except OSError as exc:  # permissions, an I/O error: the file may be fine
            raise store_io_error(exc, file, "reading the manifest", path, READ_HINT) from exc
        except (ValueError, RecursionError) as exc:  # not JSON, not UTF-8, absurd numbers or nesting
            raise StoreCorruptError(f"{file}: unreadable manifest ({exc}){fix}", path=file, offset=None) from exc
        if not isinstance(manifest, dict):
            raise StoreCorruptError(f"{file}: unreadable manifest (a JSON {type(manifest).__name__}, not an object){fix}",
                                    path=file, offset=None)
        if manifest.get("format") != FORMAT_NAME:
            raise StoreError(f"{file}: format {manifest.get('format')!r} is not {FORMAT_NAME!r}")
        if manifest.get("version") != FORMAT_VERSION:
            raise StoreError(f"{file}: store format version {manifest.get('version')} is not supported "
                             f"(this driftmap reads version {FORMAT_VERSION})")
        segments = manifest.get("segments")
        shape_ok = (isinstance(manifest.get("store_uuid"), str) and isinstance(segments, list)
                    and all(isinstance(seg, dict) and isinstance(seg.get("name"), str) and isinstance(seg.get("state"), str)
                            and isinstance(seg.get("bytes"), (int, type(None))) for seg in segments))
        if not shape_ok:
            raise StoreCorruptError(f"{file}: unreadable manifest (store_uuid or the segment list is missing or malformed){fix}",
                                    path=file, offset=None)
        names = [seg["name"] for seg in segments]
        for seg in segments:
            # a name is joined to the store folder: only segment-NNNNNN.mcap (no "/", no "..") may be used
            size = seg.get("bytes")
            if (not SEGMENT_FILE.fullmatch(seg["name"]) or seg["state"] not in ("open", "closed")
                    or isinstance(size, bool) or (size is not None and size < 0)):
                raise StoreCorruptError(f"{file}: unreadable manifest (segment entry {seg!r} is malformed){fix}",
                                        path=file, offset=None)
        if len(set(names)) != len(names):
            raise StoreCorruptError(f"{file}: unreadable manifest (a segment is listed twice){fix}", path=file, offset=None)
        indexes = [_segment_index(n) for n in names]
        if indexes != sorted(indexes):  # segments are replayed in this order: a revision follows the frames it names
            raise StoreCorruptError(f"{file}: unreadable manifest (segments listed out of order: {names}){fix}",
                                    path=file, offset=None)
        if not isinstance(manifest.get("lost_segments", []), list):
            raise StoreCorruptError(f"{file}: unreadable manifest (lost_segments is not a list){fix}", path=file, offset=None)
        return manifest

    @staticmethod
    def _manifest_from_segments(path: Path, why: str, lost_segments: list[str] | None = None) -> dict[str, Any]:
        """A manifest for the ``segment-NNNNNN.mcap`` files of ``path``; every readable one must name the same store.

        A segment that was not closed cleanly is listed as open, so recovery rewrites it. ``lost_segments``: the
        names an earlier recovery recorded as lost (kept)."""
        files = _segment_files(path)
        if not files:
            raise StoreError(f"{why}; no segment files in {path} to rebuild it from")
        uuids: dict[str, list[str]] = {}
        segments = []
        for file in files:
            scan = scan_segment(file, verify=True, stop_on_error=False)
            if scan.store_uuid is not None:
                uuids.setdefault(scan.store_uuid, []).append(file.name)
            clean = scan.complete and not scan.problem and not scan.damaged_chunks
            segments.append({"name": file.name, "state": "closed" if clean else "open", "bytes": scan.size if clean else None})
        if len(uuids) != 1:
            found = "; ".join(f"{u}: {', '.join(n)}" for u, n in uuids.items()) or "none"
            raise StoreError(f"{why}; cannot rebuild it: the segments of {path} must name exactly one store (found {found})")
        (store_uuid,) = uuids
        return {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "store_uuid": store_uuid,
            "created_ns": min(f.stat().st_mtime_ns for f in files),
            "driftmap_version": __version__,
            "segments": segments,
            "rebuilt_ns": time.time_ns(),
            "rebuilt_because": why,
            **({"lost_segments": list(lost_segments)} if lost_segments else {}),
        }

    def _unlisted_segments(self) -> list[str]:
        """Segment files in the folder that the manifest does not list: a manifest that is damaged or was replaced
        by an older copy, or a segment recorded as lost that is back (opening would silently miss their frames)."""
        known = {s.name for s in self._segments}
        return [f.name for f in _segment_files(self.path) if f.name not in known]

    def _acquire_lock(self) -> None:
        """Take the writer lock (``writer.lock``, flock'ed): appending needs write access, reading never takes it."""
        lock = self.path / LOCK_FILE
        hint = (f"appending needs write access to the store folder (reading does not: FrameStore.open(path) / "
                f"`driftmap info {self.path}`)")
        try:
            fh = open(lock, "a+")
        except OSError as exc:
            raise store_io_error(exc, lock, "taking the writer lock", self.path, hint) from exc
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            fh.close()
            if exc.errno in (errno.EAGAIN, errno.EACCES):
                raise StoreError(f"{self.path}: another process is appending to this store") from exc
            raise store_io_error(exc, lock, "taking the writer lock", self.path, hint) from exc
        try:
            fh.seek(0)
            fh.truncate()
            fh.write(f"{os.getpid()}\n")
            fh.flush()
        except OSError as exc:  # the pid is informative only, but a full disk now fails every append later
            with contextlib.suppress(OSError):
                fcntl.flock(fh.fileno(), fcntl.LOCK_UN)
                fh.close()
            raise store_io_error(exc, lock, "writing the writer lock", self.path, RESUME_HINT) from exc
        self._lock_fh = fh

    def _writer_alive(self) -> bool:
        """True if some process holds the writer lock (never true for the writer itself). Needs no write access:
        the lock file is opened read-only, and one that is missing or cannot be opened means no writer is known."""
        if self._lock_fh is not None:
            return False
        lock = self.path / LOCK_FILE
        try:
            fd = os.open(lock, os.O_RDONLY)
        except FileNotFoundError:
            return False
        except OSError as exc:
            logger.debug("%s: cannot open the writer lock to see whether a writer is alive (%s)", lock, exc)
            return False
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except OSError as exc:
            return exc.errno in (errno.EAGAIN, errno.EACCES)
        else:
            fcntl.flock(fd, fcntl.LOCK_UN)
            return False
        finally:
            os.close(fd)

    def _load(self, *, verify: bool) -> None:
        live_writer = self._writer_alive()
        fix = f"; run `driftmap recover {self.path}`"
        try:
            unlisted = self._unlisted_segments()
        except OSError as exc:
            raise store_io_error(exc, self.path, "listing the segments", self.path, READ_HINT) from exc
        if unlisted:
            raise StoreCorruptError(f"{self.path / MANIFEST}: does not list {_preview(unlisted)}, which the store folder "
                                    f"holds (a damaged manifest, or an older copy of it?){fix}",
                                    path=self.path / MANIFEST, offset=None)
        scans: list[SegmentScan] = []
        for seg in self._segments:
            file = self.path / seg.name
            if not file.exists():
                if seg is self._segments[-1] and seg.state == "open" and live_writer:
                    continue  # a live writer is starting this segment (listed first, then created)
                raise StoreCorruptError(f"{file}: segment listed in the manifest is missing{fix}", path=file, offset=None)
            try:
                scan = scan_segment(file, verify=verify)
            except OSError as exc:
                raise store_io_error(exc, file, "reading the segment", self.path, READ_HINT) from exc
            if scan.store_uuid is not None and scan.store_uuid != self._manifest["store_uuid"]:
                raise StoreCorruptError(f"{file}: belongs to store {scan.store_uuid}, but {MANIFEST} is that of store "
                                        f"{self._manifest['store_uuid']}{fix}", path=file, offset=None)
            if seg.state == "closed":
                if seg.bytes is not None and scan.size != seg.bytes:
                    raise StoreCorruptError(
                        f"{file}: closed segment is {scan.size} bytes, the manifest says {seg.bytes} "
                        f"(truncated or appended to at offset {min(scan.size, seg.bytes)}); run `driftmap recover {self.path}`",
                        path=file, offset=min(scan.size, seg.bytes))
                if scan.problem or not scan.complete:
                    raise StoreCorruptError(
                        f"{file}: damaged at offset {scan.problem_offset}: {scan.problem or 'no end of data'}; "
                        f"run `driftmap recover {self.path}`", path=file, offset=scan.problem_offset)
            elif scan.problem and seg is not self._segments[-1]:
                raise StoreCorruptError(f"{file}: damaged at offset {scan.problem_offset}: {scan.problem}; run "
                                        f"`driftmap recover {self.path}`", path=file, offset=scan.problem_offset)
            elif scan.problem and not live_writer:
                dropped = scan.size - scan.valid_bytes
                logger.warning("%s: the writer stopped mid-append; %d trailing bytes at offset %d are an unfinished "
                               "frame and are dropped (%s)", file, dropped, scan.valid_bytes, scan.problem)
                self.recovery_events.append(RecoveryEvent(seg.name, "crashed writer: unfinished tail dropped",
                                                          len(scan.frames), len(scan.revisions), dropped, scan.problem))
            seg.scan = scan
            scans.append(scan)
        self.loss = self._replay(scans, strict=True)[0]
        if self.loss:
            logger.info("%s: recorded losses: %s", self.path, self.loss)
        if self.mode == "a":
            try:
                self._recover_open_segments()
            except OSError as exc:
                raise store_io_error(exc, getattr(exc, "filename", None) or self.path, "recovering a segment left open by "
                                     "a writer that stopped", self.path, RECOVER_HINT) from exc

    def _replay(self, scans: list[SegmentScan], *, strict: bool) -> tuple[DataLoss, set[int], set[int]]:
        """Add the scanned segments' frames and revisions to this (empty) store, in store order (a revision refers
        to frames and revisions stored before it).

        A revision that names frames no segment holds is read without their poses, and a gap before a revision's
        id is filled with stand-ins, as far as the store's ``data_lost`` events declare those frames and revisions
        lost. Anything undeclared raises :class:`StoreCorruptError` (``strict``) or is treated the same way and
        returned (``recover`` declares it). Returns the loss, the undeclared frame ids and revision ids.
        """
        declared_frames: set[int] = set()
        declared_revisions: set[int] = set()
        for scan in scans:
            for event in scan.data_lost:
                frames, revisions = _lost_ids(event, scan.path)
                declared_frames |= frames
                declared_revisions |= revisions
        new_frames: set[int] = set()
        new_revisions: set[int] = set()
        named_lost: set[int] = set()
        stand_ins: list[int] = []
        trimmed: dict[int, tuple[int, ...]] = {}
        orphaned: dict[int, int] = {}
        fix = f"; run `driftmap recover {self.path}`"
        for scan in scans:
            for ref in scan.frames:
                if ref.frame_id in self._refs:
                    raise StoreCorruptError(f"{scan.path}: frame {ref.frame_id} stored twice", path=scan.path,
                                            offset=ref.payload_offset)
                try:
                    self.ledger.add_frame(ref.frame_id, int(ref.info["stamp_ns"]),
                                          np.asarray(ref.info["pose"]["T_world_sensor"], dtype=np.float64).reshape(4, 4),
                                          ref.info["pose"].get("source"))
                except (StoreError, GeometryError, ValueError, TypeError, KeyError) as exc:
                    raise StoreCorruptError(f"{scan.path}: frame {ref.frame_id}: damaged metadata ({exc}){fix}",
                                            path=scan.path, offset=ref.payload_offset) from exc
                self._refs[ref.frame_id] = ref
            for rev_json in scan.revisions:
                try:
                    rev = Revision.from_json(rev_json)
                except StoreError as exc:
                    raise StoreCorruptError(f"{scan.path}: {exc}", path=scan.path, offset=None) from exc
                rid, head = rev.revision_id, self.ledger.head
                if rid <= head:
                    raise StoreCorruptError(f"{scan.path}: revision {rid} is stored again after revision {head}",
                                            path=scan.path, offset=None)
                gap = list(range(head + 1, rid))
                undeclared = [r for r in gap if r not in declared_revisions]
                if undeclared and strict:
                    raise StoreCorruptError(
                        f"{scan.path}: revision {rid} follows revision {head}: no segment holds revisions "
                        f"{_preview(undeclared)} (lost with a damaged or missing segment?){fix}", path=scan.path, offset=None)
                new_revisions.update(undeclared)
                for r in gap:
                    # created_ns: that of the revision after the gap (the lost one was made no later)
                    self.ledger.commit(Revision(r, r - 1, PoseSource.NONE, rev.created_ns,
                                                f"[recovery: stand-in for lost revision {r}, with the poses of revision {r - 1}]"))
                    stand_ins.append(r)
                changed = rev.changed_frame_ids
                absent = changed[~np.isin(changed, self.ledger.frame_ids)].tolist()
                if absent:
                    undeclared = [f for f in absent if f not in declared_frames]
                    if undeclared and strict:
                        raise StoreCorruptError(
                            f"{scan.path}: revision {rid} holds poses of frames {_preview(undeclared)}, which no segment "
                            f"of the store holds (lost with a damaged or missing segment?){fix}", path=scan.path, offset=None)
                    new_frames.update(undeclared)
                    named_lost.update(absent)
                    trimmed[rid] = tuple(absent)
                    rev = _without_frames(rev, absent)
                if rev.parent_id in stand_ins:
                    orphaned[rid] = int(rev.parent_id)
                try:
                    self.ledger.commit(rev)
                except StoreError as exc:
                    raise StoreCorruptError(f"{scan.path}: {exc}{fix}", path=scan.path, offset=None) from exc
        lost_frames = sorted(f for f in named_lost | declared_frames if f not in self.ledger)
        return DataLoss(tuple(lost_frames), tuple(stand_ins), trimmed, orphaned), new_frames, new_revisions

    def _recover_open_segments(self) -> None:
        """Rewrite segments left open by a crashed writer into clean, closed segments."""
        for index, seg in enumerate(self._segments):
            if seg.state != "open":
                continue
            file = self.path / seg.name
            scan = seg.scan
            assert scan is not None
            bad = self._unreadable_frames(scan)
            if bad:  # not what a crash leaves behind: never repaired behind the user's back
                raise StoreCorruptError(f"{file}: frames {_preview(f for f, _ in bad)} cannot be read back ({bad[0][1]}); "
                                        f"run `driftmap recover {self.path}`", path=file, offset=None)
            tmp = file.with_name(file.name + ".recovering")
            tmp.unlink(missing_ok=True)
            writer = SegmentWriter(tmp, index, self._manifest["store_uuid"], fsync=True)
            try:
                self._copy_scan_into(scan, writer)
                size = writer.close()
            except BaseException:
                writer.abandon()
                tmp.unlink(missing_ok=True)
                raise
            if scan.valid_bytes < scan.size:
                with open(file, "rb") as src, open(self.path / f"{Path(seg.name).stem}.dropped-tail.bin", "wb") as dst:
                    src.seek(scan.valid_bytes)
                    dst.write(src.read())
            os.replace(tmp, file)
            seg.state, seg.bytes = "closed", size
            seg.scan = scan_segment(file, verify=False)
            self._refs.update({ref.frame_id: ref for ref in seg.scan.frames})
            self._write_manifest()
            logger.info("%s: recovered %d frames and %d revisions into a closed segment", file, len(scan.frames), len(scan.revisions))
            self.recovery_events.append(RecoveryEvent(seg.name, "rewritten as a closed segment", len(scan.frames),
                                                      len(scan.revisions), scan.size - scan.valid_bytes,
                                                      scan.problem or "writer did not close the segment"))

    def _copy_scan_into(self, scan: SegmentScan, writer: SegmentWriter) -> list[tuple[int, str]]:
        """Copy the scanned frames (bit for bit) and revisions into ``writer``; returns (frame id, reason) of the
        frames whose stored metadata cannot be read back (they are not copied)."""
        skipped: list[tuple[int, str]] = []
        with open(scan.path, "rb") as fh:
            mm = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) if scan.size else None
            try:
                items: list[tuple[int, str, Any]] = [(r.payload_offset, "frame", r) for r in scan.frames]
                for rev in scan.revisions:
                    items.append((-1, "revision", rev))
                # frames keep their file order; revisions go after the frames they may refer to
                for _, kind, item in sorted(items, key=lambda x: (x[1] == "revision", x[0])):
                    if kind == "frame":
                        frame = _decode_frame(item, mm)
                        if isinstance(frame, str):
                            logger.warning("%s: frame %d: %s: not copied", scan.path, item.frame_id, frame)
                            skipped.append((item.frame_id, frame))
                            continue
                        writer.append_frame(frame, check=False)  # as stored, bit for bit
                    else:
                        writer.append_revision(item, int(item["created_ns"]))
            finally:
                if mm is not None:
                    mm.close()
        return skipped

    def _unreadable_frames(self, scan: SegmentScan) -> list[tuple[int, str]]:
        """(frame id, reason) of the scanned frames that cannot be read back as stored: metadata that does not
        rebuild a :class:`Frame`, or a point payload whose CRC32 is not the one the metadata recorded. (Opening
        checks only what it needs and the chunk CRCs; this is the rest, run by ``recover``.)"""
        bad = []
        if not scan.frames:
            return bad
        with open(scan.path, "rb") as fh:
            mm = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)
        try:
            for ref in scan.frames:
                try:
                    frame_from_info(ref.info, np.zeros((0, 3), np.float32),
                                    unpack_attributes(np.zeros(0, np.uint8), 0, ref.point_stride, ref.info["points"]["fields"]))
                except (DriftmapError, KeyError, TypeError, ValueError, ArithmeticError, AttributeError) as exc:
                    bad.append((ref.frame_id, f"unreadable metadata ({type(exc).__name__}: {exc})"))
                    continue
                payload = iter_payload_bytes(ref, mm)
                problem = ("the point payload is cut short" if len(payload) != ref.n_points * ref.point_stride else
                           "the point payload's CRC32 is not the one its metadata recorded"
                           if zlib.crc32(payload) != ref.info["points"]["crc32"] else None)
                del payload
                if problem is not None:
                    bad.append((ref.frame_id, problem))
        finally:
            with contextlib.suppress(BufferError):
                mm.close()
        return bad

    def _write_manifest(self) -> None:
        self._manifest["segments"] = [{"name": s.name, "state": s.state, "bytes": s.bytes} for s in self._segments]
        _atomic_write_json(self.path / MANIFEST, self._manifest)

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
            return cls._recover(path)
        except OSError as exc:  # whatever step it was: every step so far is complete, the next run goes on from there
            raise store_io_error(exc, exc.filename or path, "recovering the store", path, RECOVER_HINT) from exc

    @classmethod
    def _recover(cls, path: Path) -> list[RecoveryEvent]:
        events: list[RecoveryEvent] = []
        rebuilt_because: str | None = None
        try:
            manifest = cls._read_manifest(path, hint=False)
        except StoreCorruptError as exc:
            rebuilt_because = str(exc)
            manifest = cls._manifest_from_segments(path, rebuilt_because)
        else:  # readable, but does it describe the segments in the folder?
            listed = cls(path, "r", manifest)
            unlisted = listed._unlisted_segments()
            strangers = [s.name for s in listed._segments if (path / s.name).exists()
                         and read_store_uuid(path / s.name) not in (None, manifest["store_uuid"])]
            if unlisted or strangers:
                rebuilt_because = (f"{path / MANIFEST}: " + (f"does not list {_preview(unlisted)}" if unlisted else
                                   f"names store {manifest['store_uuid']}, its segments {_preview(strangers)} another"))
                lost = [n for n in manifest.get("lost_segments", []) if isinstance(n, str)]
                manifest = cls._manifest_from_segments(path, rebuilt_because, lost)
        store = cls(path, "a", manifest, fsync=True)
        store._acquire_lock()
        kept_manifest = ""
        current = path / MANIFEST
        try:
            if rebuilt_because is not None:
                if (path / MANIFEST).exists():
                    damaged_manifest = _free_name(path / (MANIFEST + ".damaged"))
                    os.replace(path / MANIFEST, damaged_manifest)
                    kept_manifest = f" (damaged original kept as {damaged_manifest.name})"
                store._write_manifest()
            known_frames: set[int] = set()
            scans: list[SegmentScan] = []
            damage: list[str] = []
            for index, seg in enumerate(store._segments):
                file = current = path / seg.name
                if not file.exists():
                    events.append(RecoveryEvent(seg.name, "missing segment removed from the manifest", 0, 0, 0,
                                                "file not found: its frames and revisions are lost"))
                    damage.append(f"{seg.name} missing")
                    seg.state = "missing"
                    continue
                scan = scan_segment(file, verify=True, stop_on_error=False)
                twice = [r.frame_id for r in scan.frames if r.frame_id in known_frames]
                unreadable = store._unreadable_frames(scan)
                healthy = (seg.state == "closed" and scan.complete and not scan.problem and not scan.damaged_chunks
                           and scan.size == seg.bytes and not twice and not unreadable)
                if not healthy:
                    was_open = seg.state != "closed"
                    dropped = {f for f, _ in unreadable}  # never copied: a fresh CRC would make them look intact
                    scan.frames = [r for r in scan.frames if r.frame_id not in known_frames and r.frame_id not in dropped]
                    tmp = current = file.with_name(file.name + ".recovering")
                    tmp.unlink(missing_ok=True)
                    writer = SegmentWriter(tmp, index, manifest["store_uuid"], fsync=True)
                    try:
                        skipped = unreadable + store._copy_scan_into(scan, writer)
                        for event in scan.data_lost:
                            writer.append_event(event, int(event.get("recovered_ns", 0)))
                        size = writer.close()
                    except BaseException:
                        writer.abandon()
                        raise
                    if skipped:
                        lost_ids = {f for f, _ in skipped}
                        scan.frames = [r for r in scan.frames if r.frame_id not in lost_ids]
                    current = file
                    damaged = _free_name(file.with_name(file.name + ".damaged"))
                    _keep_copy(file, damaged)
                    os.replace(tmp, file)  # atomic: the segment is never missing, whenever recovery stops
                    _fsync_dir(path)
                    seg.state, seg.bytes = "closed", size
                    store._write_manifest()
                    problems = [f"{why} at offset {off}" for off, why in scan.damaged_chunks]
                    if scan.problem:
                        problems.append(f"{scan.problem} at offset {scan.problem_offset}")
                    if twice:
                        problems.append(f"frames {_preview(twice)} are stored in an earlier segment too (the later copies "
                                        f"were dropped)")
                    problems += [f"frame {f}: {why}" for f, why in skipped]
                    detail = "; ".join(problems) or ("segment was not closed" if was_open else "size differs from the manifest")
                    damage.append(f"{seg.name}: {detail}")
                    tail = 0 if scan.complete else scan.size - scan.valid_bytes
                    events.append(RecoveryEvent(seg.name, f"rewritten (damaged original kept as {damaged.name})",
                                                len(scan.frames), len(scan.revisions), tail + scan.damaged_bytes, detail))
                    scan = scan_segment(file, verify=False)  # the frames now live in the rewritten file
                known_frames.update(r.frame_id for r in scan.frames)
                scans.append(scan)
            missing = [s.name for s in store._segments if s.state == "missing"]
            if missing:
                store._segments = [s for s in store._segments if s.state != "missing"]
                lost_segments = [n for n in store._manifest.get("lost_segments", []) if isinstance(n, str)]
                store._manifest["lost_segments"] = lost_segments + missing
                store._write_manifest()
            # what the damage took from the revisions that survived: declared in a data_lost event of its own
            replayed = cls(path, "r", store._manifest)
            loss, new_frames, new_revisions = replayed._replay(scans, strict=False)
            if new_frames or new_revisions:
                because = "; ".join(damage) or "stored revisions name frames or follow revisions that no segment holds"
                now = time.time_ns()
                current = path / f"segment-{store._next_segment_index():06d}.mcap"
                writer = store._writable()
                writer.append_event({"event": EVENT_DATA_LOST, "recovered_ns": now, "frame_ids": sorted(new_frames),
                                     "revision_ids": sorted(new_revisions), "because": because}, now)
                store._writer = None
                store._segments[-1].state, store._segments[-1].bytes = "closed", writer.close()
                store._write_manifest()
                events.append(RecoveryEvent(store._segments[-1].name, f"recorded the loss in a {EVENT_DATA_LOST} event",
                                            len(replayed), len(replayed.revisions), 0, because,
                                            loss.only(new_frames, new_revisions)))
        except OSError as exc:
            raise store_io_error(exc, exc.filename or current, "recovering the store", path, RECOVER_HINT) from exc
        finally:
            if store._writer is not None:
                store._writer.abandon()
            store._release()
        try:
            with cls.open(path, verify=False) as check:
                n_frames, n_revisions = len(check), len(check.revisions)
        except StoreError as exc:
            raise StoreCorruptError(f"{path}: recovery could not make the store readable: {exc}",
                                    path=path, offset=getattr(exc, "offset", None)) from exc
        if rebuilt_because is not None:
            events.insert(0, RecoveryEvent(MANIFEST, f"rebuilt from {len(manifest['segments'])} segments{kept_manifest}",
                                           n_frames, n_revisions, 0, rebuilt_because))
        for event in events:
            logger.info("recover %s: %s", path, event)  # returned to the caller, who reports them
        return events

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
        if self._writer is not None and self._writer.broken is not None:
            raise StoreError(f"{self._writer.path}: cannot go on {what}: an earlier write to this segment failed "
                             f"({self._writer.broken}); close the store: {RESUME_HINT.format(store=self.path)}")
        if self._writer is None:
            try:
                index = self._next_segment_index()
            except OSError as exc:
                raise store_io_error(exc, self.path, f"listing the segments ({what})", self.path) from exc
            name = f"segment-{index:06d}.mcap"
            self._segments.append(_Segment(name, "open", None))
            try:
                self._write_manifest()
            except OSError as exc:
                self._segments.pop()  # the manifest on disk is the one before (written atomically)
                raise store_io_error(exc, self.path / MANIFEST, f"starting segment {name} ({what})", self.path) from exc
            try:
                self._writer = SegmentWriter(self.path / name, index, self._manifest["store_uuid"], fsync=self._fsync)
            except OSError as exc:
                self._forget_unstarted_segment(name)
                raise store_io_error(exc, self.path / name, f"starting the segment ({what})", self.path) from exc
        return self._writer

    def _forget_unstarted_segment(self, name: str) -> None:
        """After a new segment could not be started: take it off the manifest again if its file was never made
        (a listed segment that does not exist would read as data lost); else it stays, ``open``, for recovery."""
        file = self.path / name
        if file.exists():
            return
        self._segments = [seg for seg in self._segments if seg.name != name]
        try:
            self._write_manifest()
        except OSError as exc:
            logger.warning("%s: could not take the unstarted segment %s off the manifest (%s); run `driftmap recover "
                           "%s`", self.path / MANIFEST, name, exc, self.path)

    def _next_segment_index(self) -> int:
        """One past the highest segment index in use: listed, removed by recovery, or any ``segment-N.*`` file
        (kept damaged copies, an orphan of an interrupted recovery), so a new segment never takes a used name."""
        names = [s.name for s in self._segments] + [n for n in self._manifest.get("lost_segments", []) if isinstance(n, str)]
        names += [f.name for f in self.path.glob("segment-*")]
        return max((int(m.group(1)) for n in names if (m := _SEGMENT_NAME.match(n))), default=-1) + 1

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
        check_frame_for_store(frame, str(self.path))
        fid = int(frame.frame_id)
        if fid in self.ledger:
            raise StoreError(f"{self.path}: frame {fid} is already stored; frame ids must be unique")
        try:  # what the ledger will check after the write, checked before it (Frame already makes poses rigid)
            T = geometry.as_rigid(frame.pose.T_world_sensor, f"{self.path}: frame {fid}: pose.T_world_sensor")
            source = parse_enum(PoseSource, frame.pose.source, f"{self.path}: frame {fid}: pose.source", StoreError)
        except (GeometryError, StoreError) as exc:
            raise FrameRejectedError(str(exc), frame_id=fid, field="pose") from exc
        writer = self._writable(f"appending frame {fid}")
        try:
            payload_offset, info = writer.append_frame(frame, check=False)
        except OSError as exc:
            raise store_io_error(exc, writer.path, f"appending frame {fid}", self.path) from exc
        self.ledger.add_frame(fid, frame.stamp_ns, T, source)
        self._refs[fid] = StoredFrameRef(info, writer.path, payload_offset)

    def frame_info(self, frame_id: int) -> dict[str, Any]:
        """The stored metadata of a frame (JSON-like dict)."""
        return self._ref(frame_id).info

    def _ref(self, frame_id: int) -> StoredFrameRef:
        try:
            return self._refs[int(frame_id)]
        except KeyError:
            raise StoreError(f"{self.path}: no frame {frame_id} in the store") from None

    def _segment_map(self, segment: Path, min_size: int = 0) -> mmap.mmap:
        """A read-only map of a segment; remapped when the segment has grown past ``min_size``.

        Arrays handed out earlier keep their (older, smaller) mapping alive; nothing is copied.
        """
        for seg in self._segments:
            if self.path / seg.name == segment:
                if seg.mm is None or len(seg.mm) < min_size:
                    try:
                        with open(segment, "rb") as fh:
                            seg.mm = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)
                    except (OSError, ValueError) as exc:  # ValueError: an empty file cannot be mapped
                        if isinstance(exc, OSError):
                            raise store_io_error(exc, segment, "mapping the segment", self.path, READ_HINT) from exc
                        raise StoreCorruptError(f"{segment}: empty; run `driftmap recover {self.path}`", path=segment,
                                                offset=0) from exc
                    if len(seg.mm) < min_size:
                        raise StoreCorruptError(f"{segment}: {len(seg.mm)} bytes, but a frame's points end at offset "
                                                f"{min_size} (truncated after the store was opened?); run `driftmap "
                                                f"recover {self.path}`", path=segment, offset=len(seg.mm))
                return seg.mm
        raise StoreError(f"{segment}: not a segment of {self.path}")

    def _frame_from_ref(self, ref: StoredFrameRef, mm: mmap.mmap | None) -> Frame:
        """The frame ``ref`` points at; metadata or a payload that cannot be read back is a
        :class:`StoreCorruptError` naming the segment and the frame (``driftmap recover`` drops such frames)."""
        frame = _decode_frame(ref, mm)
        if isinstance(frame, str):  # raised here, where no view of the mapped segment is alive (it could not be closed)
            raise StoreCorruptError(f"{ref.segment}: frame {ref.frame_id}: {frame}; run `driftmap recover {self.path}`",
                                    path=ref.segment, offset=ref.payload_offset)
        return frame

    def frame(self, frame_id: int, revision: int | None = None) -> Frame:
        """A stored frame (points copied out of the store), with its pose in ``revision`` (default 0)."""
        ref = self._ref(frame_id)
        frame = self._frame_from_ref(ref, None if ref.payload_copy is not None else self.payload_map(ref))
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
        return self._segment_map(ref.segment, ref.payload_offset + ref.n_points * ref.point_stride)

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

    def poses(self, revision: int | None = None) -> NDArray[np.float64]:
        """(M, 4, 4) ``T_world_sensor`` of every frame (in ``frame_ids`` order) in a revision (default head)."""
        return self.ledger.poses(self.head if revision is None else revision)

    def _persist(self, revision: Revision) -> Revision:
        writer = self._writable(f"storing revision {revision.revision_id}")
        try:
            writer.append_revision(revision.to_json(), revision.created_ns)
        except OSError as exc:
            raise store_io_error(exc, writer.path, f"storing pose revision {revision.revision_id}", self.path,
                                 "the frames and revisions stored before it are intact; free space (or fix the device), "
                                 "run `driftmap recover {store}` and make the correction again") from exc
        return self.ledger.commit(revision)

    def add_revision(self, poses: Mapping[int, NDArray[np.float64]], *, source: PoseSource | str, parent: int | None = None,
                     propagate: bool = True, note: str = "") -> Revision:
        """Store a correction as a new revision. Poses given for a subset of frames (keyframes) propagate to
        the others when ``propagate`` (see :meth:`PoseLedger.plan_correction`)."""
        self._writable()
        source = parse_enum(PoseSource, source, f"{self.path}: add_revision source")
        revision = self.ledger.plan_correction(poses, source=source, parent=parent, propagate=propagate, note=note)
        return self._persist(revision)

    def rollback(self, to: int, *, note: str = "") -> Revision:
        """A new revision whose poses equal revision ``to`` (nothing is deleted; a warning when the head already
        has those poses)."""
        self._writable()
        revision = self._persist(self.ledger.plan_rollback(to, note=note))
        self._warn_about(revision, f"{self.path}: rolling back to revision {to}")
        return revision

    def _warn_about(self, revision: Revision, what: str, *, far: bool = False) -> None:
        """Warnings about a new revision, which is recorded all the same (the history says it was made):

        - it moves no frame beyond text round-off (the same rule ``driftmap revisions`` counts changes with);
        - ``far``: it moves frames farther than half its parent's trajectory spans (at least 1 m), so the pose
          file was most likely for other frames (``rollback`` undoes it).
        """
        diff = self.diff(revision.parent_id, revision.revision_id)
        if diff.n_changed == 0:
            logger.warning("%s: every pose equals revision %d's within %g um / %g deg: the new revision changes no "
                           "pose", what, revision.parent_id, SAME_POSE_M * 1e6, SAME_POSE_DEG)
            return
        if not far:
            return
        before = self.poses(revision.parent_id)[:, :3, 3]
        span = float(np.linalg.norm(before.max(axis=0) - before.min(axis=0))) if len(before) else 0.0
        if diff.max_translation_m > max(1.0, 0.5 * span):
            logger.warning("%s: revision %d moves frames by up to %.2f m, while revision %d's trajectory spans %.2f m: "
                           "is the file for these frames? (driftmap rollback STORE --to %d undoes it)", what,
                           revision.revision_id, diff.max_translation_m, revision.parent_id, span, revision.parent_id)

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
        fmt = parse_enum(TrajectoryFormat, format, f"{file}: format")
        source = parse_enum(PoseSource, source, f"{file}: source")
        asked = None if match is None else parse_enum(PoseMatchMode, match, f"{file}: match")
        if fmt is not TrajectoryFormat.KITTI and (kitti_frame != "auto" or calib_file is not None):
            raise ConfigError(f"{file}: kitti_frame / calib_file apply to KITTI pose files only (format {fmt.value})")
        if fmt is TrajectoryFormat.KITTI and asked is PoseMatchMode.STAMP:
            raise ConfigError(f"{file}: KITTI pose files have no stamps (row i is frame_id i): match by index")
        trajectory = read_trajectory(file, fmt.value)
        stamped = has_stamps(trajectory, fmt.value)
        mode = asked or (PoseMatchMode.STAMP if stamped else PoseMatchMode.INDEX)
        if mode is PoseMatchMode.STAMP and not stamped:
            raise ConfigError(f"{file}: this {fmt.value} pose file has no stamps ("
                              + ("its blocks end in 0 0 0 1: block i is frame_id i" if fmt is TrajectoryFormat.MATRIX_4X4
                                 else "it names its frames by id") + "): match by index")
        ids = self.ledger.frame_ids
        if (match is None and mode is PoseMatchMode.INDEX and fmt is not TrajectoryFormat.REDWOOD
                and len(trajectory) == len(ids) and len(ids) > 1 and not np.array_equal(ids, np.arange(len(ids)))):
            # the signature of a file written one row per *stored* frame (a KITTI export of a sliced store), read
            # as one row per frame *id*; an explicit match="index" takes the rows as frame ids all the same
            raise StoreError(
                f"{file}: {len(trajectory)} rows for the {len(ids)} stored frames, but matching by index takes row i "
                f"as frame_id i and the stored ids are {_id_sample(ids)}, not 0..{len(ids) - 1}: the rows look like one "
                f"per stored frame. Use a TUM file matched by stamp (driftmap export --format tum writes one), or match "
                f"by index explicitly if row i really is frame_id i")
        if rows_in_sensor_frame is not None:
            trajectory = rows_in_sensor_frame(trajectory, fmt.value)
        matched = match_pose_rows(trajectory, fmt.value, self.ledger.frame_ids, self.ledger.stamps_ns, match=mode,
                                  max_dt_ns=max_dt_ns)
        if not matched.poses:
            why = f" ({stamp_ranges_text(trajectory, self.ledger.stamps_ns)})" if mode is PoseMatchMode.STAMP else ""
            raise StoreError(f"{file}: no row matched a stored frame (match by {mode.value}){why}; nothing imported")
        if stamped and mode is PoseMatchMode.INDEX and matched.rows:
            # rows taken as frame ids although the file has stamps: say so when the stamps tell another story
            fids = np.fromiter(matched.rows, dtype=np.int64)
            rows = np.fromiter(matched.rows.values(), dtype=np.int64)
            dt_ns = np.abs(trajectory.stamps_ns[rows] - self.ledger.stamps_ns[np.searchsorted(self.ledger.frame_ids, fids)])
            if float(np.median(dt_ns)) > max_dt_ns:
                logger.warning("%s: matched by index (row i = frame_id i), but the rows' stamps differ from their frames' "
                               "by %.3f s (median): is the file for these frames? (match by stamp to use the stamps)",
                               file, float(np.median(dt_ns)) / 1e9)
        if matched.unmatched_rows:
            logger.warning("%s: %d rows matched no stored frame and were ignored", file, len(matched.unmatched_rows))
        if matched.unmatched_frames:
            logger.warning("%s: %d stored frames had no row (%s)", file, len(matched.unmatched_frames),
                           "propagated from the matched frames" if propagate else "they keep their poses")
        revision = self.add_revision(matched.poses, source=source, propagate=propagate, note=f"imported from {Path(file).name}")
        self._warn_about(revision, str(file), far=True)
        return revision, matched

    def export_trajectory(self, file: str | Path, *, revision: int | None = None,
                          format: TrajectoryFormat | str = TrajectoryFormat.TUM) -> Path:
        """Write the poses of a revision: TUM with the frames' stamps, or KITTI one row per stored frame in
        frame order (which reads back as row i = frame_id i only when the ids are 0..N-1: a warning otherwise)."""
        fmt = parse_enum(TrajectoryFormat, format, f"{file}: format")
        if fmt not in (TrajectoryFormat.TUM, TrajectoryFormat.KITTI):
            raise ConfigError(f"{file}: trajectories are exported as tum or kitti, not {fmt.value}")
        ids = self.ledger.frame_ids
        if fmt is TrajectoryFormat.KITTI and not np.array_equal(ids, np.arange(len(ids))):
            # KITTI has neither stamps nor ids: the readers (correct, build --poses, diagnose --gt) take row i as
            # frame_id i, so this file does not read back onto these frames
            logger.warning("%s: KITTI export writes one row per stored frame, but the frame ids are %s (not 0..%d): "
                           "reading it back takes row i as frame_id i; export TUM (with stamps) to round-trip",
                           file, _id_sample(ids), len(ids) - 1)
        rev = self.head if revision is None else revision
        self.ledger.revision(rev)  # StoreError naming the revision and the valid range
        if len(ids) == 0:
            raise EmptyStoreError(f"store {self.path} has no frames in revision {rev}: no trajectory to export "
                                  f"(nothing written to {file})", store=self.path, revision=rev)
        poses = self.poses(rev)
        traj = Trajectory(self.ledger.stamps_ns.copy(), poses, ids.copy())
        file = Path(file)
        refuse_inside_store(file, "trajectory export")  # never into a store folder (any store)
        # written under a temporary name and renamed into place (write_tum / write_kitti)
        (write_tum if fmt is TrajectoryFormat.TUM else write_kitti)(file, traj)
        return file

    # ------------------------------------------------------------------------------------------ maps

    def map(self, revision: int | None = None) -> Any:
        """A :class:`driftmap.map.view.MapView` of this store's frames in ``revision`` (default head)."""
        from driftmap.map.view import MapView

        return MapView.from_store(self, self.head if revision is None else revision)

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
                if writer.broken is not None:
                    logger.warning("%s: left open after a failed write (%s); its frames are intact, and the next writer "
                                   "(driftmap build ... --resume) or `driftmap recover %s` finishes it", writer.path,
                                   writer.broken, self.path)
                    writer.abandon()
                    return
                try:
                    size = writer.close()
                except OSError as exc:
                    raise store_io_error(exc, writer.path, "finishing the segment (summary and footer)", self.path) from exc
                seg = next(s for s in self._segments if s.name == writer.path.name)
                seg.state, seg.bytes = "closed", size
                try:
                    self._write_manifest()
                except OSError as exc:
                    raise store_io_error(exc, self.path / MANIFEST, f"recording {seg.name} as closed", self.path) from exc
        finally:
            self._release()
            self._closed = True

    def _release(self) -> None:
        for seg in self._segments:
            if seg.mm is not None:
                with contextlib.suppress(BufferError):
                    seg.mm.close()
                seg.mm = None
        if self._lock_fh is not None:
            with contextlib.suppress(OSError):
                fcntl.flock(self._lock_fh.fileno(), fcntl.LOCK_UN)
            with contextlib.suppress(OSError):
                self._lock_fh.close()
            self._lock_fh = None

    def __enter__(self) -> FrameStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"FrameStore({str(self.path)!r}, mode={self.mode!r}, frames={len(self)}, revisions={len(self.revisions)})"

