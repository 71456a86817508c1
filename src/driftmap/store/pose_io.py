"""Pose files in and out of a store: a TUM, KITTI, Redwood ``.log`` or ``4x4`` file imported as a new revision
(``FrameStore.import_poses``), a revision's poses exported as TUM or KITTI (``FrameStore.export_trajectory``), and
the warnings about a new revision that looks wrong (it changes nothing, or moves frames too far)."""

from __future__ import annotations

import enum
import logging
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from driftmap.errors import ConfigError, EmptyStoreError, StoreError, parse_enum
from driftmap.frame import PoseSource
from driftmap.store.guards import refuse_inside_store
from driftmap.store.ledger import PoseLedger
from driftmap.store.pose_match import PoseMatch, PoseMatchMode, match_pose_rows, stamp_ranges_text
from driftmap.store.revision import SAME_POSE_DEG, SAME_POSE_M, PoseDiff, Revision
from driftmap.store.values import id_sample
from driftmap.trajectory import Trajectory, has_stamps, read_trajectory, write_kitti, write_tum

logger = logging.getLogger(__name__)


class PoseFileStore(Protocol):
    """The part of a :class:`~driftmap.store.frame_store.FrameStore` that pose files read and write (the frame store
    imports this module, so it names only what it uses)."""

    path: Path
    ledger: PoseLedger

    @property
    def head(self) -> int: ...

    def poses(self, revision: int | None = None) -> NDArray[np.float64]: ...

    def diff(self, a: int, b: int) -> PoseDiff: ...

    def add_revision(self, poses: Mapping[int, NDArray[np.float64]], *, source: PoseSource | str,
                     parent: int | None = None, propagate: bool = True, note: str = "") -> Revision: ...


class TrajectoryFormat(enum.Enum):
    """Pose-file formats of ``correct`` / ``export`` (export writes TUM and KITTI only)."""

    TUM = "tum"
    KITTI = "kitti"
    REDWOOD = "redwood"
    MATRIX_4X4 = "4x4"
    EUROC = "euroc"


def import_poses(store: PoseFileStore, file: str | Path, *, format: TrajectoryFormat | str, match: PoseMatchMode | str | None,
                 max_dt_ns: int, source: PoseSource | str, propagate: bool, kitti_frame: str,
                 calib_file: str | Path | None,
                 rows_in_sensor_frame: Callable[[Trajectory, str], Trajectory] | None) -> tuple[Revision, PoseMatch]:
    """:meth:`FrameStore.import_poses <driftmap.store.frame_store.FrameStore.import_poses>`."""
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
    if match is None and mode is PoseMatchMode.INDEX and fmt is not TrajectoryFormat.REDWOOD:
        refuse_rows_per_stored_frame(store, file, trajectory)
    if rows_in_sensor_frame is not None:
        trajectory = rows_in_sensor_frame(trajectory, fmt.value)
    ledger = store.ledger
    matched = match_pose_rows(trajectory, fmt.value, ledger.frame_ids, ledger.stamps_ns, match=mode, max_dt_ns=max_dt_ns,
                              where=str(file))
    if not matched.poses:
        why = f" ({stamp_ranges_text(trajectory, ledger.stamps_ns)})" if mode is PoseMatchMode.STAMP else ""
        raise StoreError(f"{file}: no row matched a stored frame (match by {mode.value}){why}; nothing imported")
    if stamped and mode is PoseMatchMode.INDEX and matched.rows:
        _warn_about_index_match(store, file, trajectory, matched, max_dt_ns)
    if matched.unmatched_rows:
        logger.warning("%s: %d rows matched no stored frame and were ignored", file, len(matched.unmatched_rows))
    if matched.unmatched_frames:
        logger.warning("%s: %d stored frames had no row (%s)", file, len(matched.unmatched_frames),
                       "propagated from the matched frames" if propagate else "they keep their poses")
    revision = store.add_revision(matched.poses, source=source, propagate=propagate, note=f"imported from {Path(file).name}")
    warn_about_revision(store, revision, str(file), far=True)
    return revision, matched


def refuse_rows_per_stored_frame(store: PoseFileStore, file: str | Path, trajectory: Trajectory) -> None:
    """Refuse a file that looks written one row per *stored* frame (a KITTI export of a sliced store) when it is
    to be read as one row per frame *id* (an explicit ``match="index"`` takes the rows as frame ids all the same)."""
    ids = store.ledger.frame_ids
    if len(trajectory) == len(ids) and len(ids) > 1 and not np.array_equal(ids, np.arange(len(ids))):
        raise StoreError(
            f"{file}: {len(trajectory)} rows for the {len(ids)} stored frames, but matching by index takes row i "
            f"as frame_id i and the stored ids are {id_sample(ids)}, not 0..{len(ids) - 1}: the rows look like one "
            f"per stored frame. Use a TUM file matched by stamp (driftmap export --format tum writes one), or match "
            f"by index explicitly if row i really is frame_id i")


def _warn_about_index_match(store: PoseFileStore, file: str | Path, trajectory: Trajectory, matched: PoseMatch,
                            max_dt_ns: int) -> None:
    """Rows taken as frame ids although the file has stamps: say so when the stamps tell another story."""
    ledger = store.ledger
    fids = np.fromiter(matched.rows, dtype=np.int64)
    rows = np.fromiter(matched.rows.values(), dtype=np.int64)
    dt_ns = np.abs(trajectory.stamps_ns[rows] - ledger.stamps_ns[np.searchsorted(ledger.frame_ids, fids)])
    if float(np.median(dt_ns)) > max_dt_ns:
        logger.warning("%s: matched by index (row i = frame_id i), but the rows' stamps differ from their frames' "
                       "by %.3f s (median): is the file for these frames? (match by stamp to use the stamps)",
                       file, float(np.median(dt_ns)) / 1e9)


def warn_about_revision(store: PoseFileStore, revision: Revision, what: str, *, far: bool = False) -> None:
    """Warnings about a new revision, which is recorded all the same (the history says it was made):

    - it moves no frame beyond text round-off (the same rule ``driftmap revisions`` counts changes with);
    - ``far``: it moves frames farther than half its parent's trajectory spans (at least 1 m), so the pose
      file was most likely for other frames (``rollback`` undoes it).
    """
    diff = store.diff(revision.parent_id, revision.revision_id)
    same_frames = np.array_equal(store.ledger.members(revision.parent_id), store.ledger.members(revision.revision_id))
    if diff.n_changed == 0 and same_frames:
        logger.warning("%s: every pose equals revision %d's within %g um / %g deg: the new revision changes no "
                       "pose", what, revision.parent_id, SAME_POSE_M * 1e6, SAME_POSE_DEG)
        return
    if not far:
        return
    rows = np.searchsorted(store.ledger.frame_ids, diff.frame_ids)  # the frames both revisions place
    parent_poses = store.poses(revision.parent_id)[rows]
    before = parent_poses[:, :3, 3]
    span = float(np.linalg.norm(before.max(axis=0) - before.min(axis=0))) if len(before) else 0.0
    if diff.max_translation_m > max(1.0, 0.5 * span):
        if _moves_all_rigidly(parent_poses, store.poses(revision.revision_id)[rows]):
            logger.warning("%s: revision %d moves every frame by one rigid transform (up to %.2f m): the map is "
                           "re-anchored, no frame moves relative to another (no correction of drift)", what,
                           revision.revision_id, diff.max_translation_m)
            return
        logger.warning("%s: revision %d moves frames by up to %.2f m, while revision %d's trajectory spans %.2f m: "
                       "is the file for these frames? (driftmap rollback STORE --to %d undoes it)", what,
                       revision.revision_id, diff.max_translation_m, revision.parent_id, span, revision.parent_id)


RIGID_MOVE_M, RIGID_MOVE_DEG = 1e-3, 0.01
"""Relative poses of consecutive frames kept within these: the revision moved the map as one rigid body."""


def _moves_all_rigidly(before: NDArray[np.float64], after: NDArray[np.float64]) -> bool:
    """Every consecutive pair of frames keeps its relative pose (within :data:`RIGID_MOVE_M` and
    :data:`RIGID_MOVE_DEG`: text round-off of a rewritten file): the new poses are the old ones moved by one rigid transform of the world (a re-anchoring,
    which ``correct`` reports as such), so frames far from where they were are no sign of a file for other frames."""
    if len(before) < 2:
        return False
    rel_before = np.linalg.inv(before[:-1]) @ before[1:]
    rel_after = np.linalg.inv(after[:-1]) @ after[1:]
    change = np.linalg.inv(rel_before) @ rel_after
    cos = np.clip((np.trace(change[:, :3, :3], axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    return bool(np.all(np.linalg.norm(change[:, :3, 3], axis=1) <= RIGID_MOVE_M)
                and np.all(np.degrees(np.arccos(cos)) <= RIGID_MOVE_DEG))


def export_trajectory(store: PoseFileStore, file: str | Path, *, revision: int | None,
                      format: TrajectoryFormat | str, frame_ids: Sequence[int] | None = None) -> Path:
    """:meth:`FrameStore.export_trajectory <driftmap.store.frame_store.FrameStore.export_trajectory>`."""
    fmt = parse_enum(TrajectoryFormat, format, f"{file}: format")
    if fmt not in (TrajectoryFormat.TUM, TrajectoryFormat.KITTI):
        raise ConfigError(f"{file}: trajectories are exported as tum or kitti, not {fmt.value}")
    ledger = store.ledger
    rev = store.head if revision is None else revision
    ledger.revision(rev)  # StoreError naming the revision and the valid range
    ids = ledger.members(rev)  # the frames the revision places (not those stored after it)
    if frame_ids is not None:  # a subset (a merged store's session), in store order
        wanted = np.unique(np.asarray(frame_ids, dtype=np.int64))
        rows = np.searchsorted(ids, wanted)
        if len(wanted) and (rows.max() >= len(ids) or not np.array_equal(ids[np.minimum(rows, len(ids) - 1)], wanted)):
            raise ConfigError(f"{file}: frame ids {id_sample(np.setdiff1d(wanted, ids))} are not in store {store.path}"
                              f"'s revision {rev}")
        ids = ids[rows]
    if fmt is TrajectoryFormat.KITTI and not np.array_equal(ids, np.arange(len(ids))):
        # KITTI has neither stamps nor ids: the readers (correct, build --poses, diagnose --gt) take row i as
        # frame_id i, so this file does not read back onto these frames
        logger.warning("%s: KITTI export writes one row per stored frame, but the frame ids are %s (not 0..%d): "
                       "reading it back takes row i as frame_id i; export TUM (with stamps) to round-trip",
                       file, id_sample(ids), len(ids) - 1)
    rows = np.searchsorted(ledger.frame_ids, ids)
    if len(ids) == 0:
        raise EmptyStoreError(f"store {store.path} has no frames in revision {rev}: no trajectory to export "
                              f"(nothing written to {file})", store=store.path, revision=rev)
    poses = store.poses(rev)[rows]
    traj = Trajectory(ledger.stamps_ns[rows].copy(), poses, ids.copy())
    file = Path(file)
    refuse_inside_store(file, "trajectory export")  # never into a store folder (any store)
    # written under a temporary name and renamed into place (write_tum / write_kitti)
    (write_tum if fmt is TrajectoryFormat.TUM else write_kitti)(file, traj)
    return file
