"""Folders of PLY / PCD scans, one cloud per file, read with Open3D.

Layout::

    <folder>/scan_000000.pcd, scan_000001.pcd, ...   (or .ply; any name with a number in it)
    [a pose file given with poses=...]                TUM / KITTI / EuRoC / Redwood .log, row k = k-th cloud

Files are ordered by the last number in their name, which is also the ``frame_id``. Without a pose file
the frames carry no estimate (``PoseSource.NONE``); with one, row ``k`` of it is the estimate of the
``k``-th cloud (``PoseSource.LOG``). Stamps come from the pose file when it has real stamps (TUM, EuRoC),
else they are ``frame_id * period_ns``.

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

from driftmap.errors import SourceError, TransformError
from driftmap.frame import Frame, PointAttributes, PoseEstimate, PoseSource, Provenance, SensorKind
from driftmap.sources.base import FrameSource, register_source
from driftmap.trajectory import Trajectory, detect_trajectory_format, read_trajectory

logger = logging.getLogger(__name__)

CLOUD_SUFFIXES = (".ply", ".pcd")
DEFAULT_PERIOD_NS = 100_000_000
"""Nominal 10 Hz (a spinning LiDAR) for folders whose stamps are not known."""

_NUMBER = re.compile(r"(\d+)")


# ---- helpers shared by the data-set sources ---------------------------------------------------------------------


def frame_number(name: str | Path) -> int | None:
    """The last run of digits in a file name without its final suffix (``frame-000640.depth.png`` -> 640,
    ``000007.bin`` -> 7, ``scan_12.pcd`` -> 12), or ``None`` when it has none."""
    found = _NUMBER.findall(Path(name).stem)
    return int(found[-1]) if found else None


def numbered_files(
    folder: Path, what: str, *, pattern: str | None = None, suffixes: Sequence[str] | None = None
) -> list[tuple[int, Path]]:
    """``(frame number, path)`` of the files in ``folder`` matching a glob ``pattern`` or ending in one of
    ``suffixes`` (case-insensitive), ordered by number.

    Raises :class:`SourceError` when the folder is missing, has no such file, a name has no number or two
    files carry the same number.
    """
    if not folder.is_dir():
        raise SourceError(f"{folder}: no such folder ({what})")
    if pattern is not None:
        candidates = [f for f in folder.glob(pattern) if f.is_file()]
    else:
        lowered = tuple(s.lower() for s in suffixes or ())
        candidates = [f for f in folder.iterdir() if f.name.lower().endswith(lowered) and f.is_file()]
    found: dict[int, Path] = {}
    for file in candidates:
        number = frame_number(file.name)
        if number is None:
            raise SourceError(f"{file}: no frame number in the file name ({what})")
        if number in found:
            first, second = sorted((found[number], file))
            raise SourceError(f"{first} and {second}: both are frame {number} ({what})")
        found[number] = file
    if not found:
        raise SourceError(f"{folder}: no {pattern or ' / '.join(suffixes or ())} files ({what})")
    return sorted(found.items())


def check_increasing_stamps(
    stamps_ns: Sequence[int],
    frame_ids: Sequence[int | str],
    what: str,
    *,
    lenient: bool,
    skipped: list[tuple[int, str]] | None = None,
) -> list[int]:
    """Positions to keep so that stamps strictly increase.

    A duplicate or earlier stamp raises :class:`SourceError` naming ``what`` (the file) and the two frames;
    in lenient mode the later frame is dropped with a logged reason (and recorded in ``skipped``).
    ``frame_ids`` name the entries: an int ``n`` reads "frame n", a string is used as it is ("row 7").
    """

    def name(k: int) -> str:
        return f"frame {frame_ids[k]}" if isinstance(frame_ids[k], (int, np.integer)) else str(frame_ids[k])

    keep: list[int] = []
    for k, stamp in enumerate(stamps_ns):
        if keep and stamp <= stamps_ns[keep[-1]]:
            prev = keep[-1]
            kind = "duplicate stamp" if stamp == stamps_ns[prev] else "stamp goes back in time"
            reason = (
                f"{what}: {kind}: {name(k)} has stamp_ns {stamp}, {name(prev)} before it has stamp_ns {stamps_ns[prev]}"
            )
            if not lenient:
                raise SourceError(reason)
            logger.warning("%s (%s skipped)", reason, name(k))
            if skipped is not None:
                skipped.append((k, reason))
            continue
        keep.append(k)
    return keep


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


class CloudFolder(FrameSource):
    """A folder of ``.ply`` / ``.pcd`` scans (points in the sensor frame), ordered by the number in the name.

    Options:
        poses: optional pose file (TUM, KITTI, EuRoC or Redwood ``.log``; ``poses_format`` to skip detection);
            row ``k`` is ``T_world_sensor`` of the ``k``-th cloud, carried as ``PoseSource.LOG``.
        sensor_kind: ``"lidar"`` (default) or ``"depth_camera"``; sensor_name: defaults to the kind.
        period_ns: stamp step when the pose file has no stamps (or there is none): ``frame_id * period_ns``.
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
        period_ns: int = DEFAULT_PERIOD_NS,
        poses_from_ground_truth: bool = False,
        frames: str | slice | None = None,
        lenient: bool = False,
    ):
        super().__init__(str(path), frames=frames, lenient=lenient)
        self.path = Path(path)
        if poses_from_ground_truth:
            raise SourceError(f"{self.path}: a folder of clouds has no ground truth; give a pose file with poses=")
        try:
            self.sensor_kind = SensorKind(sensor_kind)
        except ValueError:
            raise SourceError(
                f"{self.path}: sensor_kind {sensor_kind!r}; expected one of {', '.join(k.value for k in SensorKind)}"
            ) from None
        self.sensor_name = sensor_name or self.sensor_kind.value
        self.sensor_frame = sensor_frame or self.sensor_name
        if int(period_ns) <= 0:
            raise SourceError(f"{self.path}: period_ns must be positive, got {period_ns}")
        files = numbered_files(self.path, "point-cloud folder", suffixes=CLOUD_SUFFIXES)
        ids = [n for n, _ in files]
        self.poses_path = None if poses is None else Path(poses)
        self._poses: Trajectory | None = None
        stamps = [n * int(period_ns) for n in ids]
        stamps_what = f"{self.path} (nominal stamps frame_id * {int(period_ns)} ns)"
        if self.poses_path is not None:
            if not self.poses_path.is_file():
                raise SourceError(f"{self.poses_path}: pose file not found")
            fmt = poses_format or detect_trajectory_format(self.poses_path)
            self._poses = read_trajectory(self.poses_path, fmt)
            if len(self._poses) < len(files):
                raise SourceError(
                    f"{self.poses_path}: {len(self._poses)} poses for {len(files)} clouds; the first cloud without "
                    f"a pose is {files[len(self._poses)][1].name} (frame {files[len(self._poses)][0]})"
                )
            if len(self._poses) > len(files):
                logger.warning("%s: %d poses for %d clouds; the extra rows are ignored",
                               self.poses_path, len(self._poses), len(files))
            if fmt in ("tum", "euroc"):
                stamps = [int(s) for s in self._poses.stamps_ns[: len(files)]]
                stamps_what = str(self.poses_path)
        keep = check_increasing_stamps(stamps, ids, stamps_what, lenient=lenient, skipped=self.skipped)
        # (frame id, file, stamp, pose row)
        self._entries = [(ids[k], files[k][1], stamps[k], k) for k in keep]

    def _count(self) -> int:
        return len(self._entries)

    def _frame_id(self, index: int) -> int:
        return self._entries[index][0]

    def _stamp_ns(self, index: int) -> int:
        return self._entries[index][2]

    def read_cloud(self, index: int) -> tuple[NDArray[np.float32], PointAttributes]:
        """Points (float32, as stored) and attributes (intensity, colours, normals) of the cloud at ``index``."""
        frame_id, file, _, _ = self._entries[index]
        if not file.is_file():
            raise SourceError(f"{file}: cloud of frame {frame_id} not found")
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            cloud = o3d.t.io.read_point_cloud(str(file))
        if "positions" not in cloud.point or cloud.point["positions"].shape[0] == 0:
            raise SourceError(f"{file}: no points could be read (frame {frame_id}; corrupt or empty cloud)")
        points = cloud.point["positions"].numpy().astype(np.float32, copy=False)
        if not np.all(np.isfinite(points)):
            bad = int(np.count_nonzero(~np.all(np.isfinite(points), axis=1)))
            logger.warning("%s: dropping %d points with NaN/inf coordinates (frame %d)", file, bad, frame_id)
        finite = np.all(np.isfinite(points), axis=1)
        attrs: dict[str, Any] = {}
        if "intensity" in cloud.point:
            attrs["intensity"] = cloud.point["intensity"].numpy().reshape(-1).astype(np.float32)
        if "colors" in cloud.point:
            colors = cloud.point["colors"].numpy()
            if colors.dtype != np.uint8:  # Open3D reads colours as floats in 0..1
                colors = np.clip(np.rint(colors.astype(np.float64) * 255.0), 0, 255).astype(np.uint8)
            attrs["color_rgb"] = colors
        if "normals" in cloud.point:
            attrs["normal_sensor"] = cloud.point["normals"].numpy().astype(np.float32)
        if not finite.all():
            points = points[finite]
            attrs = {k: v[finite] for k, v in attrs.items()}
        return points, PointAttributes(**attrs)

    def _load(self, index: int) -> Frame:
        frame_id, file, stamp_ns, row = self._entries[index]
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
        return {**super().describe(), "sensor_kind": self.sensor_kind.value,
                "poses": None if self.poses_path is None else str(self.poses_path)}


def _has_cloud_files(path: Path) -> bool:
    with os.scandir(path) as it:
        return any(entry.name.lower().endswith(CLOUD_SUFFIXES) and entry.is_file() for entry in it)


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
