"""Matching the rows of a trajectory file to stored frames: by stamp (nearest within a tolerance, a row never
given to two frames) or by index (row i is frame_id i; a Redwood ``.log`` names its frames)."""

from __future__ import annotations

import enum
import logging
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from driftmap.errors import DriftmapError, StoreError, parse_enum
from driftmap.store.values import as_int
from driftmap.trajectory import Trajectory

logger = logging.getLogger(__name__)


class PoseMatchMode(enum.Enum):
    """How rows of a trajectory file are matched to stored frames."""

    STAMP = "stamp"  #: nearest stamp within a tolerance
    INDEX = "index"  #: row i (0-based data row) is frame_id i


@dataclass(frozen=True, slots=True)
class PoseMatch:
    """Result of :func:`match_trajectory`: ``poses`` (``frame_id -> T``) and ``rows`` (``frame_id -> file row``)
    for the matched frames, the file rows that matched no stored frame and the stored frames with no row."""

    poses: dict[int, NDArray[np.float64]]
    unmatched_rows: list[int]
    unmatched_frames: list[int]
    rows: dict[int, int] = field(default_factory=dict)

    @property
    def n_matched(self) -> int:
        return len(self.poses)


INDEX_HINT = "match the rows by their order instead (`driftmap correct --match index`: data row i is frame_id i)"
"""What :func:`match_trajectory` suggests when stamps cannot tell frames apart (``correct``'s way; a caller with
another way out passes its own ``index_hint``)."""


def match_pose_rows(
    trajectory: Trajectory,
    format: str,
    frame_ids: ArrayLike,
    stamps_ns: ArrayLike | None,
    *,
    match: PoseMatchMode | str,
    max_dt_ns: int = 10_000_000,
    where: str = "the pose file",
    index_hint: str = INDEX_HINT,
) -> PoseMatch:
    """:func:`match_trajectory` for a pose file read as ``format`` (``correct``, ``diagnose --gt``): a Redwood
    ``.log`` names its frames (the ``i`` of each ``i j n`` line), so ``match="index"`` takes those ids rather than
    the row numbers; every other format as :func:`match_trajectory` (``index``: row i is frame_id i)."""
    mode = parse_enum(PoseMatchMode, match, "unknown pose match mode", StoreError)
    if format == "redwood" and mode is PoseMatchMode.INDEX:
        ids = np.asarray(frame_ids, dtype=np.int64).reshape(-1)
        named = trajectory.frame_ids if trajectory.frame_ids is not None else np.arange(len(trajectory))
        return match_trajectory(Trajectory(np.asarray(named, dtype=np.int64), trajectory.poses, trajectory.frame_ids),
                                ids, ids, match=PoseMatchMode.STAMP, max_dt_ns=0)  # the same id, exactly
    return match_trajectory(trajectory, frame_ids, stamps_ns, match=mode, max_dt_ns=max_dt_ns, where=where,
                            index_hint=index_hint)


def stamp_ranges_text(trajectory: Trajectory, stamps_ns: ArrayLike) -> str:
    """The file's and the frames' stamp ranges, for a message about stamps that do not meet."""
    def span(values: NDArray[np.int64]) -> str:
        return f"{values.min() / 1e9:.3f}..{values.max() / 1e9:.3f} s" if values.size else "none"
    return (f"the file's stamps span {span(np.asarray(trajectory.stamps_ns, dtype=np.int64))}, the frames' "
            f"{span(np.asarray(stamps_ns, dtype=np.int64))}")


def match_trajectory(
    trajectory: Trajectory,
    frame_ids: ArrayLike,
    stamps_ns: ArrayLike | None,
    *,
    match: PoseMatchMode | str,
    max_dt_ns: int = 10_000_000,
    where: str = "the pose file",
    index_hint: str = INDEX_HINT,
) -> PoseMatch:
    """Match the rows of ``trajectory`` to stored frames (``frame_ids`` with their ``stamps_ns``).

    ``match="index"``: row i is the pose of frame_id i (``stamps_ns`` is not used), so a full-length file
    serves a store built from a slice; rows for ids not stored are reported in ``unmatched_rows``.
    ``match="stamp"``: each frame takes the row with the nearest stamp (halfway between two rows: the earlier
    one) if ``|dt| <= max_dt_ns``; a row is never given to two frames (the closer one keeps it, ties to the
    lower frame id; the other frame is unmatched rather than moved to its second-best row).
    """
    mode = parse_enum(PoseMatchMode, match, "unknown pose match mode", StoreError)
    ids = np.asarray(frame_ids, dtype=np.int64).reshape(-1)
    if len(np.unique(ids)) != len(ids):
        raise StoreError("match_trajectory: frame_ids contain duplicates")
    n_rows = len(trajectory)

    if mode is PoseMatchMode.INDEX:
        ok = (ids >= 0) & (ids < n_rows)
        frame_idx = np.flatnonzero(ok)
        row_of = ids[ok]
    else:
        if stamps_ns is None:
            raise StoreError("match_trajectory: matching by stamp needs the frames' stamps_ns")
        stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
        if len(stamps) != len(ids):
            raise StoreError(f"match_trajectory: {len(ids)} frame ids but {len(stamps)} stamps")
        max_dt = as_int(max_dt_ns, "max_dt_ns")
        if max_dt < 0:
            raise StoreError(f"max_dt_ns must be >= 0, got {max_dt}")
        refuse_conflicting_rows(trajectory, where)
        _refuse_shared_stamps(ids, stamps, min(SHARED_STAMP_NS, max_dt), where, index_hint)
        if n_rows == 0 or len(ids) == 0:
            frame_idx, row_of = np.zeros(0, dtype=np.intp), np.zeros(0, dtype=np.intp)
        else:
            frame_idx, row_of = _nearest_rows(np.asarray(trajectory.stamps_ns, dtype=np.int64), ids, stamps, max_dt)
            _warn_ties(np.asarray(trajectory.stamps_ns, dtype=np.int64), ids, stamps, frame_idx, row_of, where)

    used = np.zeros(n_rows, dtype=bool)
    used[row_of] = True
    unmatched = np.ones(len(ids), dtype=bool)
    unmatched[frame_idx] = False
    matched_ids = ids[frame_idx].tolist()
    result = PoseMatch(
        poses={
            fid: np.array(trajectory.poses[r], dtype=np.float64)
            for fid, r in zip(matched_ids, row_of.tolist(), strict=True)
        },
        unmatched_rows=np.flatnonzero(~used).tolist(),
        unmatched_frames=np.sort(ids[unmatched]).tolist(),
        rows=dict(zip(matched_ids, row_of.tolist(), strict=True)),
    )
    logger.debug(
        "matched %d of %d frames to %d trajectory rows by %s (%d rows unmatched)",
        result.n_matched, len(ids), n_rows, mode.value, len(result.unmatched_rows),
    )
    return result


SHARED_STAMP_NS = 1_000_000
"""Two stored frames whose stamps are closer than this (1 ms, faster than any depth camera or LiDAR runs) cannot be
told apart by a row's stamp: matching by stamp is refused (sessions of a merged store that share their stamps)."""


def _refuse_shared_stamps(ids: NDArray[np.int64], stamps: NDArray[np.int64], within_ns: int, where: str,
                          index_hint: str = "") -> None:
    """Refuse stored frames whose stamps are closer than ``within_ns`` (the tolerance, at most
    :data:`SHARED_STAMP_NS`), or equal: a row cannot tell which of them it is for."""
    order = np.argsort(stamps, kind="stable")
    gaps = np.diff(stamps[order])
    close = np.flatnonzero((gaps < within_ns) | (gaps == 0))
    if close.size:
        a, b = int(ids[order[close[0]]]), int(ids[order[close[0] + 1]])
        raise StoreError(f"{where}: cannot match rows to frames by stamp: {close.size} pair(s) of stored frames have "
                         f"stamps less than {max(within_ns, 1) / 1e6:g} ms apart (frames {a} and {b}: "
                         f"{int(stamps[order[close[0]]])} and {int(stamps[order[close[0] + 1]])} ns), so a row "
                         f"cannot tell which it is for; {index_hint or INDEX_HINT}")


def _nearest_rows(row_stamps: NDArray[np.int64], ids: NDArray[np.int64], stamps: NDArray[np.int64],
                  max_dt: int) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """The frames (positions in ``ids``, sorted) matched by stamp and their rows (see :func:`match_trajectory`)."""
    n_rows = len(row_stamps)
    by_stamp = np.argsort(row_stamps, kind="stable")
    sorted_stamps = row_stamps[by_stamp]
    j = np.searchsorted(sorted_stamps, stamps)
    left, right = np.clip(j - 1, 0, n_rows - 1), np.clip(j, 0, n_rows - 1)
    dt_left, dt_right = np.abs(stamps - sorted_stamps[left]), np.abs(sorted_stamps[right] - stamps)
    take_right = dt_right < dt_left
    row = by_stamp[np.where(take_right, right, left)]
    dt = np.where(take_right, dt_right, dt_left)
    candidates = np.flatnonzero(dt <= max_dt)
    # one row per frame at most: per row keep the closest frame (then the lowest id)
    order = candidates[np.lexsort((ids[candidates], dt[candidates], row[candidates]))]
    first = np.ones(len(order), dtype=bool)
    first[1:] = row[order][1:] != row[order][:-1]
    frame_idx = np.sort(order[first])
    return frame_idx, row[frame_idx]


def _warn_ties(row_stamps: NDArray[np.int64], ids: NDArray[np.int64], stamps: NDArray[np.int64],
               frame_idx: NDArray[np.intp], row_of: NDArray[np.intp], where: str) -> None:
    """A warning naming the matched rows that lie exactly as close to another frame as to theirs (the order rule
    chose between them: a guess; hostile trial 26 W6). (A tolerance of half the spacing alone is common -- TUM's 20 ms at
    30 Hz -- and not warned about.)"""
    if len(stamps) < 2 or len(frame_idx) == 0:
        return
    by_stamp = np.sort(stamps)
    spacing = float(np.median(np.diff(by_stamp)))
    row_t = row_stamps[row_of]
    dt = np.abs(stamps[frame_idx] - row_t)
    j = np.searchsorted(by_stamp, row_t)
    tie = np.zeros(len(frame_idx), dtype=bool)
    for k in (j - 1, j, j + 1):  # the frames around each row's stamp
        ok = (k >= 0) & (k < len(by_stamp))
        other = by_stamp[np.clip(k, 0, len(by_stamp) - 1)]
        tie |= ok & (other != stamps[frame_idx]) & (np.abs(other - row_t) == dt)
    if tie.any():
        first = int(np.flatnonzero(tie)[0])
        logger.warning("%s: %d pose row(s) lie exactly as far from two frames (first: stamp %d ns, matched to "
                       "frame %d, %.3g ms from each): which frame each belongs to is a guess; give a --max-dt-ms below "
                       "half the frames' spacing (%.3g ms) or rows stamped at the frames", where, int(tie.sum()),
                       int(row_t[first]), int(ids[frame_idx[first]]), dt[first] / 1e6, spacing / 2e6)


def refuse_conflicting_rows(trajectory: Trajectory, where: str, error: type[DriftmapError] = StoreError) -> None:
    """Two rows with one stamp but different poses leave a frame at that instant with two poses: refused (``error``),
    naming the rows by their lines in the file where the reader kept them (else 1-based among the pose rows), wherever
    they are in the file. The same row written twice (the TUM fr2_desk ground truth has one) is fine."""
    stamps = np.asarray(trajectory.stamps_ns, dtype=np.int64)
    order = np.argsort(stamps, kind="stable")
    for i in np.flatnonzero(np.diff(stamps[order]) == 0).tolist():
        k, j = sorted((int(order[i]), int(order[i + 1])))
        a, b = trajectory.poses[k], trajectory.poses[j]
        if not np.allclose(a, b, rtol=0.0, atol=1e-9):
            moved = float(np.linalg.norm(a[:3, 3] - b[:3, 3]))
            lines = trajectory.source_lines
            rows = (f"the pose rows on lines {int(lines[k])} and {int(lines[j])}" if lines is not None
                    else f"pose rows {k + 1} and {j + 1}")
            raise error(f"{where}: {rows} share the stamp {int(stamps[k])} ns but give different "
                        f"poses ({moved:.3g} m apart): which one is the frame's? Remove one of them")
