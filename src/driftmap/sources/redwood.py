"""Redwood-style RGB-D folders (Redwood indoor scenes, ICL-NUIM in Redwood layout, Open3D test data).

Layout::

    depth/NNNNN.png          uint16 depth, millimetres (depth_scale 1000); 0 = no reading
    color/NNNNN.jpg          colour, registered to depth (optional; only read with color=True)
    rgbd.match               optional "depth/NNNNN.png color/NNNNN.jpg" pairs, in frame order
    camera_*.json            Open3D PinholeCameraIntrinsic JSON (width, height, column-major intrinsic_matrix)
    trajectory.log           ground truth T_world_camera (Redwood .log), frame id = first number of each block
    odometry.log             optional estimate T_world_camera -> frames carry it as PoseSource.ODOMETRY

``frame_id`` is the number in the depth file name. The format has no time stamps: ``stamp_ns`` is
``frame_id * 33_333_333`` (nominal 30 Hz). The RGB-D helpers the 7-Scenes and TUM sources share (16-bit PNG
reading, Open3D intrinsics JSON, the Kinect-class range check of the depth scale) live in
:mod:`driftmap.sources.depth_folder`; this module re-exports them as it always did.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from driftmap.errors import SourceError
from driftmap.frame import PinholeIntrinsics, PoseEstimate, PoseSource
from driftmap.sources.base import register_source
from driftmap.sources.cloud_folder import frame_number, numbered_files, opener_for, pose_or_none
from driftmap.sources.depth_folder import (  # re-exported: the RGB-D helpers this module has always offered
    FOCAL_RANGE_PX,  # noqa: F401
    KINECT_RANGE_M,
    MAX_OUT_OF_RANGE_FRACTION,  # noqa: F401
    NOMINAL_30HZ_PERIOD_NS,
    PNG_SIGNATURE,  # noqa: F401
    DepthFolderSource,
    check_sensor_range,  # noqa: F401
    checked_intrinsics,  # noqa: F401
    frame_errors_named,  # noqa: F401
    intrinsics_from_option,
    intrinsics_named,  # noqa: F401
    intrinsics_problem,  # noqa: F401
    png_size_problem,  # noqa: F401
    read_color_image,
    read_depth_png,  # noqa: F401
    read_open3d_intrinsics,
)
from driftmap.sources.stamps import nominal_stamp_ns, read_pose_file
from driftmap.trajectory import Trajectory, read_lines, read_redwood_log

logger = logging.getLogger(__name__)

#: Open3D's ``PinholeCameraIntrinsicParameters.PrimeSenseDefault`` (also the TUM / ROS default).
PRIMESENSE_DEFAULT = PinholeIntrinsics(fx=525.0, fy=525.0, cx=319.5, cy=239.5, width=640, height=480)


# ---- the Redwood source -----------------------------------------------------------------------------------------


INTRINSICS_JSON_NAMES = ("camera_primesense.json", "camera_intrinsic.json", "intrinsic.json")
"""The intrinsics JSON names a Redwood folder uses, in order of preference; any other ``*.json`` with an
``intrinsic_matrix`` is a candidate too."""


def _intrinsics_json_candidates(folder: Path) -> list[Path]:
    """Every intrinsics JSON of the folder: the :data:`INTRINSICS_JSON_NAMES` that exist, in that order, then the
    other ``*.json`` files that hold an ``intrinsic_matrix``, sorted."""
    found = [folder / n for n in INTRINSICS_JSON_NAMES if (folder / n).is_file()]
    for candidate in sorted(folder.glob("*.json")):
        if candidate.name in INTRINSICS_JSON_NAMES:
            continue
        try:
            if "intrinsic_matrix" in json.loads(candidate.read_text()):
                found.append(candidate)
        except (OSError, ValueError, TypeError, RecursionError):
            continue
    return found


def _camera_tuple(intrinsics: PinholeIntrinsics) -> tuple[float, ...]:
    i = intrinsics
    return (i.fx, i.fy, i.cx, i.cy, i.width, i.height)


def _read_folder_intrinsics(folder: Path) -> tuple[Path, PinholeIntrinsics] | None:
    """The intrinsics JSON of the folder and its values; two JSONs that give different values are refused naming
    both (which camera is it?); a second JSON with the same values, or one that does not read, is ignored (the
    unreadable one with a warning)."""
    candidates = _intrinsics_json_candidates(folder)
    if not candidates:
        return None
    chosen = candidates[0]
    intrinsics = read_open3d_intrinsics(chosen)
    for other in candidates[1:]:
        try:
            values = read_open3d_intrinsics(other)
        except SourceError as exc:
            logger.warning("%s: ignored (the intrinsics come from %s): %s", other, chosen.name, exc)
            continue
        if _camera_tuple(values) != _camera_tuple(intrinsics):
            def show(i: PinholeIntrinsics) -> str:
                return f"fx={i.fx:g} fy={i.fy:g} cx={i.cx:g} cy={i.cy:g} {i.width}x{i.height}"

            raise SourceError(
                f"{folder}: two intrinsics JSONs with different values: {chosen} ({show(intrinsics)}) and {other} "
                f"({show(values)}); remove the wrong one or choose with --intrinsics FILE (intrinsics=)"
            )
        logger.debug("%s: same intrinsics as %s", other, chosen)
    return chosen, intrinsics


def read_redwood_poses(file: Path) -> Trajectory:
    """A Redwood ``.log`` (``trajectory.log``, ``odometry.log``) whose blocks each name a different frame id.

    :func:`driftmap.trajectory.read_redwood_log` keeps the blocks as written; the source looks poses up by frame id,
    so a frame id named by two blocks would silently take one of the two poses. It is refused instead, naming the
    file, the frame id and the header lines of both blocks (as a TUM stamp written twice with two poses is)."""
    traj = read_pose_file(read_redwood_log, file)
    ids = traj.frame_ids.tolist() if traj.frame_ids is not None else []
    first: dict[int, int] = {}
    for block, frame_id in enumerate(ids):
        if frame_id not in first:
            first[frame_id] = block
            continue
        # the header line of block b is the (5 b)-th non-empty line (read_redwood_log's own layout)
        headers = [n for n, line in enumerate(read_lines(file, "Redwood .log trajectory"), start=1) if line.strip()][::5]
        raise SourceError(
            f"{file}:{headers[block]}: frame id {frame_id} is named by two pose blocks, at lines "
            f"{headers[first[frame_id]]} and {headers[block]} (each 'i j n' header must name a different frame; "
            f"which pose is frame {frame_id}'s?)"
        )
    return traj


class RedwoodRgbd(DepthFolderSource):
    """A Redwood-layout RGB-D folder (see the module docstring for the layout).

    Ground truth (``trajectory.log``) is only exposed through :meth:`ground_truth`; ``odometry.log``, when
    present, is the frames' estimate (``PoseSource.ODOMETRY``), else they carry ``PoseSource.NONE``.

    Options:
        intrinsics: overrides the JSON (PinholeIntrinsics, mapping, sequence or JSON path); without either,
            Open3D's PrimeSense default 525/525/319.5/239.5 is used with a warning.
        depth_scale: units per metre (default 1000: Redwood and ICL-NUIM PNGs are millimetres).
        min_depth_m, max_depth_m: valid depth range (defaults 0.2, 5.0).
        sensor_range_m: measurable range for the depth-scale check (default Kinect-class 0.3..10 m; None: off).
        color: attach the registered colour image as per-point colour.
        trajectory, odometry: file names of the ground truth and of the estimate inside the folder.
        poses_from_ground_truth: frames carry the ground truth (``PoseSource.GROUND_TRUTH``) instead.
    """

    format_name = "redwood"
    depth_sensor_name = "depth_camera"

    def __init__(
        self,
        path: str | Path,
        *,
        intrinsics: Any = None,
        depth_scale: float = 1000.0,
        min_depth_m: float = 0.2,
        max_depth_m: float = 5.0,
        sensor_range_m: tuple[float, float] | None = KINECT_RANGE_M,
        color: bool = False,
        trajectory: str = "trajectory.log",
        odometry: str = "odometry.log",
        poses_from_ground_truth: bool = False,
        pixel_stride: int = 1,
        frames: str | slice | None = None,
        lenient: bool = False,
    ):
        super().__init__(path, pixel_stride=pixel_stride, frames=frames, lenient=lenient)
        if not self.path.is_dir():
            raise SourceError(f"{self.path}: no such folder")
        self._set_depth_units(depth_scale, min_depth_m, max_depth_m, sensor_range_m)
        if depth_scale != 1000.0:
            logger.warning("%s: depth_scale=%g, but Redwood / ICL-NUIM depth PNGs are millimetres (1000)",
                           self.path, depth_scale)
        self.color = color
        self.poses_from_ground_truth = poses_from_ground_truth
        self.intrinsics_file: Path | None = None
        self.intrinsics = self._resolve_intrinsics(intrinsics)
        self._entries = self._read_entries(lenient)
        self._read_poses(trajectory, odometry)

    def _resolve_intrinsics(self, value: Any) -> PinholeIntrinsics:
        if value is not None:
            if isinstance(value, (str, Path)):
                self.intrinsics_file = Path(value)
            return intrinsics_from_option(value, str(self.path))
        found = _read_folder_intrinsics(self.path)
        if found is not None:
            self.intrinsics_file, intrinsics = found
            return intrinsics
        logger.warning("%s: no intrinsics JSON; using the PrimeSense default 525/525/319.5/239.5", self.path)
        return PRIMESENSE_DEFAULT

    def _read_entries(self, lenient: bool) -> list[tuple[int, Path, Path | None]]:
        """``(frame id, depth file, colour file)`` per frame: from ``rgbd.match`` (depth + colour pairs in frame
        order) or the numbered depth PNGs; frame numbers must increase and make stamps."""
        match_file = self.path / "rgbd.match"
        if match_file.is_file():
            entries = self._read_match_file(match_file)
        else:
            color_dir = self.path / "color"
            colors = {}
            if color_dir.is_dir():
                colors = dict(numbered_files(color_dir, "Redwood colour", suffixes=(".jpg", ".png")))
            entries = [(n, f, colors.get(n)) for n, f in numbered_files(self.path / "depth", "Redwood depth",
                                                                        suffixes=(".png",), lenient=lenient)]
        ids = [e[0] for e in entries]
        for frame_id, depth_file, _ in entries:  # nominal 30 Hz stamps of the file numbers must be stamps
            nominal_stamp_ns(frame_id, NOMINAL_30HZ_PERIOD_NS, str(depth_file))
        for k in range(1, len(ids)):
            if ids[k] <= ids[k - 1]:
                what = str(match_file) if match_file.is_file() else str(self.path / "depth")
                raise SourceError(
                    f"{what}: frame {ids[k]} comes after frame {ids[k - 1]} (frame numbers must increase)"
                )
        return entries

    def _read_match_file(self, match_file: Path) -> list[tuple[int, Path, Path | None]]:
        entries: list[tuple[int, Path, Path | None]] = []
        for lineno, line in enumerate(read_lines(match_file, "Redwood rgbd.match"), start=1):
            parts = line.split()
            if not parts or parts[0].startswith("#"):
                continue
            depth_file = self.path / parts[0]
            number = frame_number(depth_file.name)
            if number is None:
                raise SourceError(f"{match_file}:{lineno}: no frame number in {parts[0]!r}")
            entries.append((number, depth_file, self.path / parts[1] if len(parts) > 1 else None))
        if not entries:
            raise SourceError(f"{match_file}: no frames listed")
        return entries

    def _read_poses(self, trajectory: str, odometry: str) -> None:
        """The ground truth (``trajectory``) and the estimate (``odometry``) by frame id, when the files exist."""
        ids = [e[0] for e in self._entries]
        self.trajectory_file = self.path / trajectory
        self._gt: dict[int, NDArray[np.float64]] | None = None
        if self.trajectory_file.is_file():
            gt = read_redwood_poses(self.trajectory_file)
            self._gt = dict(zip(gt.frame_ids.tolist(), gt.poses, strict=True))
            missing = [i for i in ids if i not in self._gt]
            if missing:
                logger.warning("%s: %d of %d frames have no ground-truth pose (first: frame %d)",
                               self.trajectory_file, len(missing), len(ids), missing[0])
        elif self.poses_from_ground_truth:
            raise SourceError(f"{self.trajectory_file}: ground truth not found (poses_from_ground_truth=True, build --poses-from-source)")
        self.odometry_file = self.path / odometry
        self._odometry: dict[int, NDArray[np.float64]] | None = None
        if self.odometry_file.is_file():
            odo = read_redwood_poses(self.odometry_file)
            self._odometry = dict(zip(odo.frame_ids.tolist(), odo.poses, strict=True))

    def _count(self) -> int:
        return len(self._entries)

    def _frame_id(self, index: int) -> int:
        return self._entries[index][0]

    def _stamp_ns(self, index: int) -> int:
        return self._entries[index][0] * NOMINAL_30HZ_PERIOD_NS

    def _depth_entry(self, index: int) -> tuple[int, int, Path]:
        frame_id, depth_file, _ = self._entries[index]
        return frame_id, frame_id * NOMINAL_30HZ_PERIOD_NS, depth_file

    def _pose_estimate(self, index: int) -> PoseEstimate:
        frame_id = self._entries[index][0]
        if self.poses_from_ground_truth:
            if self._gt is None or frame_id not in self._gt:
                raise SourceError(f"{self.trajectory_file}: no ground-truth pose for frame {frame_id}")
            return pose_or_none(self._gt[frame_id], PoseSource.GROUND_TRUTH)
        if self._odometry is not None:
            if frame_id not in self._odometry:
                raise SourceError(f"{self.odometry_file}: no odometry pose for frame {frame_id}")
            return pose_or_none(self._odometry[frame_id], PoseSource.ODOMETRY)
        return pose_or_none(None, PoseSource.NONE)

    def _color(self, index: int) -> NDArray[np.uint8] | None:
        if not self.color:
            return None
        frame_id, _, color_file = self._entries[index]
        if color_file is None:
            raise SourceError(f"{self.path}: no colour image for frame {frame_id} (color=True)")
        return read_color_image(color_file, frame_id)

    def _trajectory(self, poses: dict[int, NDArray[np.float64]] | None) -> Trajectory | None:
        if poses is None:
            return None
        ids = [self._entries[i][0] for i in self._indices() if self._entries[i][0] in poses]
        return Trajectory(
            np.array(ids, dtype=np.int64) * NOMINAL_30HZ_PERIOD_NS,
            np.array([poses[i] for i in ids], dtype=np.float64).reshape(-1, 4, 4),
            np.array(ids, dtype=np.int64),
        )

    def ground_truth(self) -> Trajectory | None:
        """``trajectory.log`` poses ``T_world_camera`` of the selected frames that have one (``frame_ids`` set)."""
        return self._trajectory(self._gt)

    def odometry(self) -> Trajectory | None:
        """``odometry.log`` poses of the selected frames, or ``None`` without the file."""
        return self._trajectory(self._odometry)

    def describe(self) -> dict[str, Any]:
        return {
            **super().describe(),
            "ground_truth": self._gt is not None,
            "estimate": "odometry.log" if self._odometry is not None else None,
        }


def _detect(path: Path) -> bool:
    try:
        if not (path.is_dir() and (path / "depth").is_dir()):
            return False
        if (path / "depth.txt").exists() or (path / "synthetic.json").exists():
            return False  # TUM, driftmap synthetic
        return (
            (path / "rgbd.match").is_file()
            or next(path.glob("*.log"), None) is not None
            or next(path.glob("camera*.json"), None) is not None
        )
    except OSError:
        return False


register_source("redwood", _detect, opener_for(RedwoodRgbd),
                "Redwood / ICL-NUIM RGB-D folder (depth/*.png mm, camera JSON, trajectory.log, odometry.log)")

