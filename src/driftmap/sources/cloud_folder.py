"""Folders of PLY / PCD scans, one cloud per file, read with Open3D.

Layout::

    <folder>/scan_000000.pcd, scan_000001.pcd, ...   (or .ply; any name with a number in it, or names that are stamps)
    [times.txt | timestamps.txt | stamps.txt]        optional stamps, seconds, one line per cloud
    [a pose file given with poses=...]                TUM / KITTI / EuRoC / Redwood .log / 4x4, row k = k-th cloud

Files are ordered by the last number in their name, which is also the ``frame_id``; names that are stamps
(``1630577758.569490.pcd``) are ordered by stamp and the ``frame_id`` is the index in that order. Without a pose
file the frames carry no estimate (``PoseSource.NONE``); with one, row ``k`` of it is the estimate of the
``k``-th cloud (``PoseSource.LOG``). Where the stamps come from is :class:`CloudFolder`'s precedence
(docs/sources-datasets.md); normals and per-point times are checked by :mod:`driftmap.sources.point_fields`.

Files that are not frames are never read nor counted, in this folder or any folder of frames a source here reads
(:func:`is_ignored_file`): hidden files (names starting with ``.``) and temporary files (``*.tmp.*``, as the
``.map.pcd.297cc9cf.tmp.pcd`` an interrupted ``driftmap export`` leaves behind); they are logged at debug level and
listed by ``describe()["ignored_files"]``.

This module also holds the small helpers every folder-of-numbered-files source here shares: numbering,
stamp-order checks and option validation.
"""

from __future__ import annotations

import inspect
import logging
import os
import re
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from driftmap.errors import ConfigError, NotACloudFile, SourceError, TransformError
from driftmap.frame import Frame, PointAttributes, PoseEstimate, PoseSource, Provenance, SensorKind
from driftmap.sources.base import FrameSource, register_source, same_file_or_copy
from driftmap.sources.cloud_headers import CloudHeader, check_cloud_file
from driftmap.sources.point_fields import (
    POINT_TIME_FIELDS,
    checked_intensity,
    checked_normals,
    measured_points,
    point_time_offsets_ns,
)
from driftmap.sources.stamps import (
    MAX_STAMP_NS,
    STAMP_FILE_NAMES,
    check_increasing_stamps,
    check_pose_file_stamps,
    check_seconds_period,
    name_stamp_ns,
    nominal_stamp_ns,
    period_problem,
    read_pose_file,
    read_times,
    rows_for_frames,
    stamps_from_file_names,
)
from driftmap.trajectory import Trajectory, detect_trajectory_format, has_stamps, read_trajectory

logger = logging.getLogger(__name__)

CLOUD_SUFFIXES = (".ply", ".pcd")
DEFAULT_PERIOD_NS = 100_000_000
"""Nominal 10 Hz (a spinning LiDAR) for folders whose stamps are not known."""

_NUMBER = re.compile(r"([0-9]+)")


# ---- helpers shared by the data-set sources ---------------------------------------------------------------------


def frame_number(name: str | Path) -> int | None:
    """The last run of digits in a file name without its final suffix (``frame-000640.depth.png`` -> 640,
    ``000007.bin`` -> 7, ``scan_12.pcd`` -> 12), or ``None`` when it has none."""
    found = _NUMBER.findall(Path(name).stem)
    return int(found[-1]) if found else None


def is_ignored_file(name: str | Path) -> bool:
    """A file in a folder of frames that is not a frame: a hidden file (the name starts with ``.``) or a temporary
    file (``*.tmp.*``: driftmap writes files under ``.<name>.<random>.tmp<suffix>`` and renames them when complete;
    a killed run leaves them behind)."""
    name = Path(name).name
    return name.startswith(".") or ".tmp." in name.lower()


def without_ignored(paths: Sequence[Path], what: str, ignored: list[Path] | None = None) -> list[Path]:
    """``paths`` without the files :func:`is_ignored_file` leaves out (logged at debug level naming ``what``, and
    appended to ``ignored`` when given)."""
    left_out = [p for p in paths if is_ignored_file(p)]
    if not left_out:
        return list(paths)
    logger.debug("%s: %d hidden or temporary file(s) are not frames and are ignored: %s", what, len(left_out),
                 ", ".join(sorted(p.name for p in left_out)))
    if ignored is not None:
        ignored.extend(p for p in left_out if p not in ignored)
    return [p for p in paths if not is_ignored_file(p)]


def numbered_files(
    folder: Path, what: str, *, pattern: str | None = None, suffixes: Sequence[str] | None = None,
    lenient: bool = False, ignored: list[Path] | None = None,
) -> list[tuple[int, Path]]:
    """``(frame number, path)`` of the files in ``folder`` matching a glob ``pattern`` or ending in one of
    ``suffixes`` (case-insensitive), ordered by number. Hidden and temporary files (:func:`is_ignored_file`) are
    left out (and appended to ``ignored``).

    Raises :class:`SourceError` when the folder is missing, has no such file, a name has no number (or one too
    large for a frame id) or two files carry the same number. A name that matches but is a symlink loop or a
    dangling symlink raises naming the link and where it leads (lenient: left out with a warning).
    """
    if not folder.is_dir():
        raise SourceError(f"{folder}: no such folder ({what})")
    if pattern is not None:
        matching = list(folder.glob(pattern))
    else:
        lowered = tuple(s.lower() for s in suffixes or ())
        matching = [f for f in folder.iterdir() if f.name.lower().endswith(lowered)]
    candidates = frame_files(without_ignored(matching, f"{folder} ({what})", ignored), what, lenient=lenient)
    found: dict[int, Path] = {}
    for file in candidates:
        number = frame_number(file.name)
        if number is None:
            raise SourceError(f"{file}: no frame number in the file name ({what})")
        if number > MAX_FRAME_NUMBER:
            raise SourceError(f"{file}: the number {number} in the file name is too large for a frame id "
                              f"(at most {MAX_FRAME_NUMBER}) ({what})")
        if number in found:
            first, second = sorted((found[number], file))
            raise SourceError(f"{first} and {second}: both are frame {number} ({what})")
        found[number] = file
    if not found:
        raise SourceError(f"{folder}: no {pattern or ' / '.join(suffixes or ())} files ({what})")
    return sorted(found.items())


MAX_FRAME_NUMBER = 2**63 - 1
"""Frame ids are int64 (the store's ledger)."""


def frame_files(paths: Sequence[Path], what: str, *, lenient: bool = False) -> list[Path]:
    """The regular files among ``paths`` (names that match a source's frame files). A name that is a symlink loop
    or a dangling symlink raises :class:`SourceError` naming the link and the chain (lenient: a warning, left out);
    a folder named like a frame file is not a frame: left out with a warning saying it is a folder, not a file;
    other non-files (sockets, devices) are left out silently."""
    out = []
    for file in paths:
        if file.is_file():
            out.append(file)
            continue
        problem = broken_link_problem(file)
        if problem is None:
            if file.is_dir():
                logger.warning("%s: is a folder, not a file (%s); it is not a frame and is left out", file, what)
            continue
        if not lenient:
            raise SourceError(f"{problem} ({what})")
        logger.warning("%s (%s); the file is left out", problem, what)
    return out


def broken_link_problem(path: Path) -> str | None:
    """What is wrong with a symlink that does not lead to a file (a loop, a dangling link), naming the chain;
    ``None`` when ``path`` is not such a link."""
    if not path.is_symlink():
        return None
    chain = [path]
    seen = {os.path.abspath(path)}
    current = path
    while current.is_symlink():
        try:
            target = Path(os.readlink(current))
        except OSError as exc:
            return f"{path}: symlink cannot be read ({exc.strerror})"
        current = target if target.is_absolute() else current.parent / target
        chain.append(current)
        key = os.path.abspath(current)
        if key in seen or len(chain) > 40:
            return f"{path}: symlink loop ({' -> '.join(str(c) for c in chain)})"
        seen.add(key)
    if not current.exists():
        return f"{path}: dangling symlink ({' -> '.join(str(c) for c in chain)}, which does not exist)"
    return None  # a link to a folder or another existing non-file: not a frame file, as a folder of that name


def opener_for(cls: type[FrameSource]) -> Callable[..., FrameSource]:
    """An opener for :func:`register_source` that rejects unknown options with a :class:`SourceError`."""
    params = inspect.signature(cls.__init__).parameters
    accepted = sorted(name for name, p in params.items() if p.kind is inspect.Parameter.KEYWORD_ONLY)

    def open_(path: str | Path, **options: Any) -> FrameSource:
        unknown = sorted(set(options) - set(accepted))
        if unknown:
            raise SourceError(
                f"{path}: unknown option(s) {', '.join(unknown)} for format {cls.format_name!r}; "
                f"accepted: {', '.join(accepted)}"
            )
        return cls(path, **options)

    open_.__doc__ = cls.__doc__
    open_.accepted_options = frozenset(accepted)  # type: ignore[attr-defined]
    return open_


def pose_or_none(T_world_sensor: NDArray[np.float64] | None, source: PoseSource) -> PoseEstimate:
    """``PoseEstimate(T, source)`` or, without a pose, identity marked ``PoseSource.NONE``."""
    if T_world_sensor is None:
        return PoseEstimate(np.eye(4), source=PoseSource.NONE)
    return PoseEstimate(T_world_sensor, source=source)


# ---- the cloud-folder source ------------------------------------------------------------------------------------

#: files beside the clouds that may be a pose file whose stamps are the clouds' stamps (4x4 blocks with stamps)
_POSE_FILE_SUFFIXES = (".csv", ".txt", ".log")


def _cloud_paths(folder: Path, *, lenient: bool = False, ignored: list[Path] | None = None) -> list[Path]:
    if not folder.is_dir():
        return []
    clouds = [f for f in folder.iterdir() if f.name.lower().endswith(CLOUD_SUFFIXES)]
    return sorted(frame_files(without_ignored(clouds, f"{folder} (point-cloud folder)", ignored), "point-cloud folder",
                              lenient=lenient))


def _read_checked_cloud(file: Path, frame_id: int) -> tuple[Any, CloudHeader]:
    """The Open3D tensor cloud of a PCD / PLY file whose header was checked against its bytes first
    (:func:`driftmap.sources.cloud_headers.check_cloud_file`), and whose point count is then checked against the
    header: a header that lies about sizes never reaches Open3D's reader (which trusts it). Returns the cloud and the
    checked header."""
    if not file.is_file():
        raise SourceError(f"{file}: cloud of frame {frame_id} not found")
    try:
        header = check_cloud_file(file)
    except NotACloudFile as exc:
        raise SourceError(f"{file}: no points could be read (frame {frame_id}; corrupt or empty cloud: "
                          f"{exc.reason})") from exc
    except SourceError as exc:
        raise SourceError(f"{exc} (frame {frame_id})") from exc
    if header.n_points == 0:
        raise SourceError(f"{file}: the header says the cloud has no points (frame {frame_id})")
    try:
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            cloud = o3d.t.io.read_point_cloud(str(file))
    except RuntimeError as exc:
        raise SourceError(f"{file}: Open3D cannot read the cloud of frame {frame_id} ({exc})") from exc
    n_read = cloud.point["positions"].shape[0] if "positions" in cloud.point else 0
    if n_read == 0:
        raise SourceError(f"{file}: no points could be read (frame {frame_id}; corrupt or empty cloud)")
    if n_read != header.n_points:
        raise SourceError(f"{file}: Open3D read {n_read} points of frame {frame_id}, the header says "
                          f"{header.n_points}: corrupt data")
    if header.dtype is not None and header.encoding in ("binary", "binary_little_endian", "binary_big_endian"):
        _check_positions_match_bytes(file, frame_id, header, cloud.point["positions"].numpy())
    return cloud, header


def _check_positions_match_bytes(file: Path, frame_id: int, header: CloudHeader, positions: NDArray) -> None:
    """The coordinates Open3D read are the ones the binary data holds (bit for bit, as float32)."""
    assert header.dtype is not None
    raw = np.memmap(file, dtype=header.dtype, mode="r", offset=header.data_offset, shape=(header.n_points,))
    try:
        for k, axis in enumerate("xyz"):
            expected = np.asarray(raw[axis], dtype=np.float32)
            got = positions[:, k].astype(np.float32, copy=False)
            if not np.array_equal(expected, got, equal_nan=True):
                bad = int(np.flatnonzero(~((expected == got) | (np.isnan(expected) & np.isnan(got))))[0])
                raise SourceError(f"{file}: the reader's {axis} of point {bad} of frame {frame_id} is {got[bad]!r}, the "
                                  f"file holds {expected[bad]!r}: the cloud was not read as written")
    finally:
        del raw


def _ply_properties(file: Path) -> list[str]:
    """The vertex property names a PLY header declares (empty when it cannot be read)."""
    names: list[str] = []
    try:
        with file.open("rb") as fh:
            element = None
            for _ in range(1000):
                line = fh.readline()
                if not line or line.strip() == b"end_header":
                    break
                parts = line.decode("ascii", "replace").split()
                if parts[:1] == ["element"] and len(parts) >= 2:
                    element = parts[1]
                elif parts[:1] == ["property"] and element == "vertex" and len(parts) >= 3 and parts[1] != "list":
                    names.append(parts[-1])
    except OSError:
        return []
    return names


class CloudFolder(FrameSource):
    """A folder of ``.ply`` / ``.pcd`` scans (points in the sensor frame), ordered by the number in the name, or
    by the stamp when the names are stamps.

    Options:
        poses: optional pose file (TUM, KITTI, EuRoC, Redwood ``.log`` or 4x4 blocks; ``poses_format`` to skip
            detection); row ``k`` is ``T_world_sensor`` of the ``k``-th cloud, carried as ``PoseSource.LOG``.
        sensor_kind: ``"lidar"`` (default) or ``"depth_camera"``; sensor_name: defaults to the kind.
        period_ns: stamps ``frame_id * period_ns`` for a folder without stamps of its own (refused with a
            :class:`ConfigError` when it has some).

    Stamps, first that applies (``describe()["stamps"]`` says which): (a) the ``poses`` file when its rows have
    stamps (TUM, EuRoC, 4x4 with stamps); (b) file names that are stamps
    (:func:`driftmap.sources.stamps.name_stamp_ns`: s with a fraction, ms, us or ns; then the frame ids are the
    files' indices in stamp order); (c) a stamp file in the folder (``times.txt``, ``timestamps.txt``,
    ``stamps.txt``: seconds, one line per cloud or per frame number); (d) a pose file in the folder whose 4x4
    blocks carry stamps (BALM's ``alidarPose.csv``): its stamps only, never its poses; (e) ``period_ns``;
    (f) the nominal 10 Hz, with a warning.
    """

    format_name = "cloud_folder"

    def __init__(
        self,
        path: str | Path,
        *,
        poses: str | Path | None = None,
        poses_format: str | None = None,
        sensor_kind: str | SensorKind = SensorKind.LIDAR,
        sensor_name: str | None = None,
        sensor_frame: str | None = None,
        period_ns: int | None = None,
        poses_from_ground_truth: bool = False,
        frames: str | slice | None = None,
        lenient: bool = False,
    ):
        super().__init__(str(path), frames=frames, lenient=lenient)
        self.path = Path(path)
        if poses_from_ground_truth:
            raise SourceError(f"{self.path}: a folder of clouds has no ground truth to place the clouds with (build "
                              f"--poses-from-source; poses_from_ground_truth=True in the library): give their pose "
                              f"file with --poses FILE instead (poses= in the library)")
        try:
            self.sensor_kind = SensorKind(sensor_kind)
        except ValueError:
            raise SourceError(
                f"{self.path}: sensor_kind {sensor_kind!r}; expected one of {', '.join(k.value for k in SensorKind)}"
            ) from None
        self.sensor_name = sensor_name or self.sensor_kind.value
        self.sensor_frame = sensor_frame or self.sensor_name
        if period_ns is not None and int(period_ns) <= 0:
            raise SourceError(f"{self.path}: period_ns must be positive, got {period_ns}")
        self._nominal_period_ns: int | None = None
        self.ignored_files: list[Path] = []
        """Hidden and temporary files among the clouds, not read (:func:`is_ignored_file`)."""
        named = stamps_from_file_names(_cloud_paths(self.path, lenient=lenient, ignored=self.ignored_files),
                                       f"{self.path} (point-cloud folder)")
        if named is not None:
            files = [(k, file) for k, (_, file) in enumerate(named[0])]
        else:
            files = numbered_files(self.path, "point-cloud folder", suffixes=CLOUD_SUFFIXES, lenient=lenient,
                                   ignored=self.ignored_files)
        ids = [n for n, _ in files]
        self.poses_path = None if poses is None else Path(poses)
        self._poses: Trajectory | None = None
        poses_fmt = None
        if self.poses_path is not None:
            if not self.poses_path.is_file():
                raise SourceError(f"{self.poses_path}: pose file not found")
            poses_fmt = poses_format or detect_trajectory_format(self.poses_path)
            self._poses = read_pose_file(read_trajectory, self.poses_path, poses_fmt)
            if len(self._poses) < len(files):
                raise SourceError(
                    f"{self.poses_path}: {len(self._poses)} poses for {len(files)} clouds; the first cloud without "
                    f"a pose is {files[len(self._poses)][1].name} (frame {files[len(self._poses)][0]})"
                )
            if len(self._poses) > len(files):
                logger.warning("%s: %d poses for %d clouds; the extra rows are ignored",
                               self.poses_path, len(self._poses), len(files))
        stamps, self.stamps_origin, stamps_what = self._stamps(ids, named, poses_fmt, period_ns)
        keep = check_increasing_stamps(stamps, ids, stamps_what, lenient=lenient, skipped=self.skipped)
        # (frame id, file, stamp, pose row)
        self._entries = [(ids[k], files[k][1], stamps[k], k) for k in keep]

    def _stamps(self, ids: list[int], named: tuple[list[tuple[int, Path]], str] | None, poses_fmt: str | None,
                period_ns: int | None) -> tuple[list[int], str, str]:
        """The clouds' stamps, where they come from (``describe()["stamps"]``) and what to name in messages."""
        found: tuple[list[int], str, str] | None = None
        if self._poses is not None and poses_fmt is not None and has_stamps(self._poses, poses_fmt):
            assert self.poses_path is not None
            stamps = check_pose_file_stamps(self.poses_path, poses_fmt, self._poses.stamps_ns[: len(ids)].tolist())
            found = (stamps, self.poses_path.name, str(self.poses_path))
        elif named is not None:
            found = ([s for s, _ in named[0]], f"file names ({named[1]})", f"{self.path} (stamps in the file names)")
        else:
            found = self._stamp_file(ids) or self._pose_file_stamps(ids)
        if found is not None:
            if period_ns is not None:
                raise ConfigError(f"period_ns={int(period_ns)} (--period-s {int(period_ns) / 1e9:g}): {self.path} has "
                                  f"stamps of its own ({found[1]}); they are used: remove the option")
            logger.info("%s: frame stamps from %s", self.path, found[2])
            return found
        if period_ns is not None:
            origin = f"period {int(period_ns) / 1e9:g} s (period_ns / --period-s)"
            return self._nominal(ids, int(period_ns)), origin, f"{self.path} (stamps frame_id * {int(period_ns)} ns)"
        stamps = self._nominal(ids, DEFAULT_PERIOD_NS)
        logger.warning("%s: no stamps in the folder; they are assumed: frame_id * %d ns (nominal 10 Hz). Give them with "
                       "a stamp file beside the clouds (%s: seconds, one line per cloud), the scan period "
                       "(--period-s SECONDS; period_ns= in the library) or, in the library, a pose file with stamps "
                       "(poses=)", self.path, DEFAULT_PERIOD_NS,
                       " / ".join(STAMP_FILE_NAMES))
        return stamps, "assumed 10 Hz", f"{self.path} (nominal stamps frame_id * {DEFAULT_PERIOD_NS} ns)"

    def _nominal(self, ids: list[int], period_ns: int) -> list[int]:
        """``frame_id * period_ns`` per cloud. A stamp out of the int64 range (a frame number from a file name that
        is a stamp) is kept here and refused when its frame is read (:meth:`_checked_stamp_ns`)."""
        self._nominal_period_ns = period_ns
        return [n * period_ns for n in ids]

    def _checked_stamp_ns(self, frame_id: int, file: Path, stamp_ns: int) -> int:
        """The frame's stamp; one out of range (only nominal stamps can be) raises :class:`SourceError` naming the
        file and, when the file names are stamps that were not taken as stamps, why (:func:`nominal_stamp_ns`)."""
        if 0 <= stamp_ns <= MAX_STAMP_NS:
            return stamp_ns
        try:
            return nominal_stamp_ns(frame_id, self._nominal_period_ns or 1, str(file))
        except SourceError as exc:
            files = [f for _, f, _, _ in self._entries]
            raise SourceError(f"{exc}{self._names_not_stamps_reason(files)}") from None

    def _names_not_stamps_reason(self, files: list[Path]) -> str:
        """Why file names that are stamps were taken as frame numbers (``""`` when they are not all stamps)."""
        parsed = [name_stamp_ns(f.name) for f in files]
        n_stamps = sum(p is not None for p in parsed)
        if n_stamps < len(parsed):
            return (f" (only {n_stamps} of the {len(parsed)} file names are stamps, so all are taken as frame numbers; "
                    f"name every file by its stamp, or give the stamps with a stamp file (times.txt) beside the "
                    f"clouds, or poses= in the library)"
                    if n_stamps else "")
        units = sorted({p[1] for p in parsed if p is not None})
        if len(units) > 1:
            return f" (the file names are stamps of different units, {', '.join(units)}, so they were not used as stamps)"
        problem = period_problem(sorted(p[0] for p in parsed if p is not None))
        return (f" (the file names are stamps in {units[0]}, but {problem}, so they were not used as stamps; give the "
                f"stamps with a stamp file (times.txt) beside the clouds (or poses= in the library), or rename the "
                f"files to frame numbers)"
                if problem else "")

    def _stamp_file(self, ids: list[int]) -> tuple[list[int], str, str] | None:
        """(c) ``times.txt`` / ``timestamps.txt`` / ``stamps.txt``: a file that does not fit the clouds raises."""
        present = [self.path / name for name in STAMP_FILE_NAMES if (self.path / name).is_file()]
        if not present:
            return None
        if len(present) > 1:
            raise SourceError(f"{present[0]} and {present[1]}: two stamp files for the clouds of {self.path}; keep one")
        file = present[0]
        times = read_times(file)
        fit = rows_for_frames(len(times), ids)
        if fit is None:
            raise SourceError(f"{file}: {len(times)} stamps for {len(ids)} clouds (frames {ids[0]}..{ids[-1]}); a stamp "
                              f"file needs one line per cloud, or one per frame number of the whole sequence")
        check_seconds_period(times, file, f"its {len(times)} rows (for the {len(ids)} clouds)")
        stamps = [times[r] for r in fit[0]]
        return stamps, file.name, f"{file} ({fit[1]})"

    def _pose_file_stamps(self, ids: list[int]) -> tuple[list[int], str, str] | None:
        """(d) a pose file beside the clouds whose 4x4 blocks carry stamps (not its poses): used when exactly one
        fits the clouds; a file that does not fit is logged and left alone."""
        usable: list[tuple[list[int], str, str]] = []
        for file in sorted(self.path.iterdir()):
            if (not file.name.lower().endswith(_POSE_FILE_SUFFIXES) or file.name in STAMP_FILE_NAMES
                    or is_ignored_file(file)
                    or not file.is_file() or (self.poses_path is not None and same_file_or_copy(file, self.poses_path))):
                continue
            try:
                if detect_trajectory_format(file) != "4x4":
                    continue
                traj = read_pose_file(read_trajectory, file, "4x4")
            except (SourceError, OSError, UnicodeDecodeError, ValueError) as exc:
                logger.debug("%s: not a pose file with stamps (%s)", file, exc)
                continue
            if not has_stamps(traj, "4x4"):
                continue
            fit = rows_for_frames(len(traj), ids)
            if fit is None:
                logger.warning("%s: its %d stamped poses do not fit the %d clouds (frames %d..%d) of %s; its stamps "
                               "are not used", file, len(traj), len(ids), ids[0], ids[-1], self.path)
                continue
            try:
                stamps = check_pose_file_stamps(file, "4x4", [int(traj.stamps_ns[r]) for r in fit[0]])
            except SourceError as exc:
                logger.warning("%s; its stamps are not used for the clouds of %s", exc, self.path)
                continue
            problem = period_problem(stamps)
            if problem is not None:
                logger.warning("%s: its stamps are not used for the clouds of %s: %s", file, self.path, problem)
                continue
            usable.append((stamps, file.name, f"{file} (only the stamps of its 4x4 poses, {fit[1]}; its poses are used "
                                              f"only when given with build --poses FILE, poses= in the library)"))
        if len(usable) > 1:
            logger.warning("%s: %s all carry stamps for the clouds; none is used (keep only the right one beside the "
                           "clouds, or pass it with poses= in the library)",
                           self.path, ", ".join(u[1] for u in usable))
            return None
        return usable[0] if usable else None

    def _count(self) -> int:
        return len(self._entries)

    def _frame_id(self, index: int) -> int:
        return self._entries[index][0]

    def _stamp_ns(self, index: int) -> int:
        return self._entries[index][2]

    def read_cloud(self, index: int) -> tuple[NDArray[np.float32], PointAttributes]:
        """Points (float32, as stored) and attributes (intensity, colours, normals, per-point times) of the cloud
        at ``index``; normals and times only when they pass :mod:`driftmap.sources.point_fields`' checks. Points with
        a NaN / inf coordinate, exactly at the sensor origin (no return) or too far are dropped; a cloud without a point
        left raises :class:`SourceError` naming the file (:func:`~driftmap.sources.point_fields.measured_points`)."""
        frame_id, file, stamp_ns, _ = self._entries[index]
        what = f"{file} (frame {frame_id})"
        cloud, header = _read_checked_cloud(file, frame_id)
        self._note_viewpoint(header)
        positions = cloud.point["positions"].numpy()
        points = positions.astype(np.float32, copy=False)
        finite = np.all(np.isfinite(positions), axis=1)
        if not finite.all():
            logger.warning("%s: dropping %d points with NaN/inf coordinates (frame %d)", file,
                           int(np.count_nonzero(~finite)), frame_id)
        # as written (float64 data is checked before the cast to float32): no return, too far, no point left
        keep = measured_points(positions, what)

        def kept(values: NDArray) -> NDArray:
            return values if keep is None else values[keep]

        attrs: dict[str, Any] = {}
        if "intensity" in cloud.point:
            attrs["intensity"] = checked_intensity(kept(cloud.point["intensity"].numpy().reshape(-1)), what)
        if "colors" in cloud.point:
            colors = cloud.point["colors"].numpy()
            if colors.dtype != np.uint8:  # Open3D reads colours as floats in 0..1
                colors = np.clip(np.rint(colors.astype(np.float64) * 255.0), 0, 255).astype(np.uint8)
            attrs["color_rgb"] = kept(colors)
        if "normals" in cloud.point:
            attrs["normal_sensor"] = checked_normals(kept(cloud.point["normals"].numpy()), what, self._warned)
        time_field = next((f for f in POINT_TIME_FIELDS if f in cloud.point), None)
        if time_field is not None:
            values = kept(cloud.point[time_field].numpy().reshape(-1))
            attrs["time_offset_ns"] = point_time_offsets_ns(values, stamp_ns, time_field, what)
        elif file.suffix.lower() == ".ply":
            dropped = [f for f in _ply_properties(file) if f in POINT_TIME_FIELDS]
            if dropped:
                logger.warning("%s: per-point time property %r not used: Open3D's PLY reader skips its type "
                               "(it reads int, uchar, uint8, uint16, float, double; not uint / uint32)", what, dropped[0])
        return kept(points), PointAttributes(**attrs)

    def _note_viewpoint(self, header: CloudHeader) -> None:
        """Warn once per folder about a PCD whose ``VIEWPOINT`` is not the identity: it is not applied (the points
        are taken as they are written, in the sensor's frame; docs/sources-datasets.md)."""
        if header.viewpoint is None or "viewpoint" in self._warned:
            return
        self._warned.add("viewpoint")
        logger.warning("%s: VIEWPOINT %s is not the identity (0 0 0 1 0 0 0); it is not applied: the points are "
                       "taken in the frame they are written in, as the sensor's. If they are in another frame (a map "
                       "frame, the viewpoint being the sensor's pose in it), transform them into the sensor's frame "
                       "first (other files of %s alike are not warned about)", header.file,
                       " ".join(header.viewpoint), self.path)

    def _load(self, index: int) -> Frame:
        frame_id, file, stamp_ns, row = self._entries[index]
        stamp_ns = self._checked_stamp_ns(frame_id, file, stamp_ns)
        points, attributes = self.read_cloud(index)
        T = None if self._poses is None else self._poses.poses[row]
        try:
            pose = pose_or_none(T, PoseSource.LOG)
        except TransformError as exc:
            raise SourceError(f"{self.poses_path}: pose row {row + 1} (frame {frame_id}) is not rigid: {exc}") from exc
        return Frame(
            frame_id=frame_id,
            stamp_ns=stamp_ns,
            sensor_name=self.sensor_name,
            sensor_kind=self.sensor_kind,
            points_sensor=points,
            pose=pose,
            attributes=attributes,
            provenance=Provenance(str(file.resolve()), frame_id),
            sensor_frame=self.sensor_frame,
        )

    def poses(self) -> Trajectory | None:
        """The pose file's poses for the selected clouds (``frame_ids`` set), or ``None`` without one."""
        if self._poses is None:
            return None
        idx = list(self._indices())
        rows = [self._entries[i][3] for i in idx]
        return Trajectory(
            np.array([self._entries[i][2] for i in idx], dtype=np.int64),
            self._poses.poses[rows],
            np.array([self._entries[i][0] for i in idx], dtype=np.int64),
        )

    def describe(self) -> dict[str, Any]:
        out = {**super().describe(), "sensor_kind": self.sensor_kind.value,
               "poses": None if self.poses_path is None else str(self.poses_path), "stamps": self.stamps_origin}
        if self.ignored_files:
            out["ignored_files"] = sorted(f.name for f in self.ignored_files)
        return out


def _has_cloud_files(path: Path) -> bool:
    with os.scandir(path) as it:
        return any(entry.name.lower().endswith(CLOUD_SUFFIXES) and not is_ignored_file(entry.name) and entry.is_file()
                   for entry in it)


def _detect(path: Path) -> bool:
    """A folder with .ply / .pcd files that no other registered format claims (a data-set folder with a
    fused map saved into it stays that data set)."""
    try:
        if not (path.is_dir() and _has_cloud_files(path)):
            return False
        from driftmap.sources.base import registered_formats

        for name, spec in registered_formats().items():
            if name == "cloud_folder":
                continue
            try:
                if spec.detect(path):
                    return False
            except Exception:  # another detector's failure must not hide this format
                continue
        return True
    except OSError:
        return False


register_source("cloud_folder", _detect, opener_for(CloudFolder),
                "a folder of .ply / .pcd scans numbered in their names (Open3D), optional pose file")
