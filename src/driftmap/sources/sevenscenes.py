"""Microsoft 7-Scenes sequences (Kinect v1 RGB-D with KinectFusion ground truth).

Layout of a sequence folder (``seq-01/`` in the official archives)::

    frame-NNNNNN.depth.png   uint16 depth in millimetres; 0 and 65535 mean "no reading"
    frame-NNNNNN.pose.txt    4x4 camera-to-world T_world_camera (ground truth, KinectFusion)
    frame-NNNNNN.color.jpg   colour, NOT registered to the depth image (never attached to points)
    camera-intrinsics.txt    optional 3x3 K; default fx = fy = 585, cx = 320, cy = 240 (640x480)

``frame_id`` is the number in the file name. 7-Scenes has no time stamps: ``stamp_ns`` is
``frame_id * 33_333_333`` (the Kinect's nominal 30 Hz). Frames carry no pose estimate
(``PoseSource.NONE``) unless ``poses_from_ground_truth=True``.
"""

from __future__ import annotations

import logging
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from driftmap import geometry
from driftmap.errors import SourceError, TransformError
from driftmap.frame import Frame, PinholeIntrinsics, PoseEstimate, PoseSource
from driftmap.sources.base import register_source
from driftmap.sources.cloud_folder import frame_number, numbered_files, opener_for, pose_or_none
from driftmap.sources.depth_folder import (
    KINECT_RANGE_M,
    NOMINAL_30HZ_PERIOD_NS,
    DepthFolderSource,
    intrinsics_from_option,
    intrinsics_named,
)
from driftmap.sources.stamps import nominal_stamp_ns
from driftmap.trajectory import Trajectory

logger = logging.getLogger(__name__)

DEFAULT_INTRINSICS = PinholeIntrinsics(fx=585.0, fy=585.0, cx=320.0, cy=240.0, width=640, height=480)
INTRINSICS_FILE = "camera-intrinsics.txt"


def _loadtxt(file: Path) -> NDArray[np.float64]:
    """``np.loadtxt`` of a small matrix file; an empty file reads as an empty array (the shape check names it),
    without numpy's warning."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return np.loadtxt(file, ndmin=2)


def read_pose_txt(file: Path, frame_id: int) -> NDArray[np.float64]:
    """A 7-Scenes ``frame-NNNNNN.pose.txt``: 4x4 camera-to-world, validated as rigid (projected onto SO(3))."""
    try:
        T = _loadtxt(file)
    except FileNotFoundError:
        raise SourceError(f"{file}: ground-truth pose of frame {frame_id} not found") from None
    except (OSError, ValueError) as exc:
        raise SourceError(f"{file}: cannot read the pose of frame {frame_id} ({exc})") from exc
    if T.shape != (4, 4):
        raise SourceError(f"{file}: pose of frame {frame_id} must be a 4x4 matrix, got shape {T.shape}")
    try:
        return geometry.as_rigid(T, f"{file} (frame {frame_id} pose)")
    except TransformError as exc:
        raise SourceError(str(exc)) from exc


def _read_intrinsics_txt(file: Path) -> PinholeIntrinsics:
    try:
        K = _loadtxt(file)
    except (OSError, ValueError) as exc:
        raise SourceError(f"{file}: cannot read the camera matrix ({exc})") from exc
    if K.shape != (3, 3) or K[2].tolist() != [0.0, 0.0, 1.0]:
        raise SourceError(f"{file}: expected a 3x3 camera matrix with last row [0 0 1], got {K.tolist()}")
    if K[0, 1] != 0 or K[1, 0] != 0:
        logger.warning("%s: skew %g in the camera matrix is ignored (a pinhole camera without skew is assumed)",
                       file, K[0, 1] if K[0, 1] != 0 else K[1, 0])
    return intrinsics_named(file, fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2], width=640, height=480)


class SevenScenes(DepthFolderSource):
    """A 7-Scenes sequence folder (see the module docstring for the layout).

    Options:
        min_depth_m, max_depth_m: valid depth range; defaults 0.2 and 4.0 m (the Kinect v1 in these sequences
            reports nothing at or beyond 4 m: the largest reading in redkitchen is 3.975 m).
        intrinsics: override ``camera-intrinsics.txt`` (PinholeIntrinsics, mapping, sequence or JSON path).
        depth_scale: units per metre (1000: millimetres).
        sensor_range_m: measurable range for the depth-scale check (Kinect-class 0.3..10 m; None: off).
        poses_from_ground_truth: frames carry the ``pose.txt`` ground truth (``PoseSource.GROUND_TRUTH``).
        color: not supported -- the colour camera is not registered to depth; ``True`` raises.
    """

    format_name = "7scenes"

    def __init__(
        self,
        path: str | Path,
        *,
        min_depth_m: float = 0.2,
        max_depth_m: float = 4.0,
        intrinsics: Any = None,
        depth_scale: float = 1000.0,
        sensor_range_m: tuple[float, float] | None = KINECT_RANGE_M,
        poses_from_ground_truth: bool = False,
        color: bool = False,
        pixel_stride: int = 1,
        frames: str | slice | None = None,
        lenient: bool = False,
    ):
        super().__init__(path, pixel_stride=pixel_stride, frames=frames, lenient=lenient)
        if color:
            raise SourceError(
                f"{self.path}: 7-Scenes colour images are not registered to the depth images (different camera, "
                f"no extrinsics), so they cannot colour the points; open without color=True"
            )
        self._set_depth_units(depth_scale, min_depth_m, max_depth_m, sensor_range_m)
        self.poses_from_ground_truth = poses_from_ground_truth
        intrinsics_file = self.path / INTRINSICS_FILE
        if intrinsics is not None:
            self.intrinsics = intrinsics_from_option(intrinsics, str(self.path))
        elif intrinsics_file.is_file():
            self.intrinsics = _read_intrinsics_txt(intrinsics_file)
        else:
            logger.info("%s: no %s; using the 7-Scenes default fx=fy=585, cx=320, cy=240", self.path, INTRINSICS_FILE)
            self.intrinsics = DEFAULT_INTRINSICS
        self._frames = numbered_files(self.path, "7-Scenes depth", pattern="frame-*.depth.png", lenient=lenient)
        for frame_id, file in self._frames:  # nominal 30 Hz stamps of the file numbers must be stamps
            nominal_stamp_ns(frame_id, NOMINAL_30HZ_PERIOD_NS, str(file))
        self.missing_depth: list[tuple[int, Path]] = self._find_missing_depth()
        """``(frame_id, depth file)`` of frames the sequence numbers (a gap in the numbering, or a pose / colour
        file) without a depth image: they are not frames of this source (``--frames`` counts the others);
        iterating over a selection that spans them logs a warning naming them."""

    def _find_missing_depth(self) -> list[tuple[int, Path]]:
        depth_ids = {frame_id for frame_id, _ in self._frames}
        numbered = set(range(min(depth_ids), max(depth_ids) + 1))
        for file in self.path.glob("frame-*.*"):
            if file.name.endswith((".pose.txt", ".color.jpg", ".color.png")):
                number = frame_number(file.name.split(".")[0])
                if number is not None:
                    numbered.add(number)
        return [(i, self.path / f"frame-{i:06d}.depth.png") for i in sorted(numbered - depth_ids)]

    def __iter__(self) -> Iterator[Frame]:
        indices = self._indices()
        if self.missing_depth and len(indices):
            # the frames missing inside the selected stretch (and before / after it when it starts / ends the run)
            lo = -1 if indices[0] == 0 else self._frames[indices[0]][0]
            hi = None if indices[-1] == len(self._frames) - 1 else self._frames[indices[-1]][0]
            inside = [(i, f) for i, f in self.missing_depth if i > lo and (hi is None or i < hi)]
            if inside:
                shown = "; ".join(f"frame {i} ({f} {_not_a_depth_file(f)})" for i, f in inside[:5])
                logger.warning("%s: %d frame(s) of the sequence have no depth image and are left out: %s%s "
                               "(--frames START:STOP:STEP counts the frames that have one)", self.path, len(inside),
                               shown, f"; and {len(inside) - 5} more" if len(inside) > 5 else "")
        yield from super().__iter__()

    def _count(self) -> int:
        return len(self._frames)

    def _frame_id(self, index: int) -> int:
        return self._frames[index][0]

    def _stamp_ns(self, index: int) -> int:
        return self._frames[index][0] * NOMINAL_30HZ_PERIOD_NS

    def pose_file(self, frame_id: int) -> Path:
        return self.path / f"frame-{frame_id:06d}.pose.txt"

    def _depth_entry(self, index: int) -> tuple[int, int, Path]:
        frame_id, file = self._frames[index]
        return frame_id, frame_id * NOMINAL_30HZ_PERIOD_NS, file

    def _pose_estimate(self, index: int) -> PoseEstimate:
        if not self.poses_from_ground_truth:
            return pose_or_none(None, PoseSource.NONE)
        frame_id = self._frames[index][0]
        return pose_or_none(read_pose_txt(self.pose_file(frame_id), frame_id), PoseSource.GROUND_TRUTH)

    def ground_truth(self) -> Trajectory:
        """``pose.txt`` poses ``T_world_camera`` of the selected frames (``frame_ids`` set).

        A missing or malformed pose file raises :class:`SourceError`; in lenient mode the frame is left out
        of the trajectory with a logged reason.
        """
        ids, poses = [], []
        for i in self._indices():
            frame_id = self._frames[i][0]
            try:
                poses.append(read_pose_txt(self.pose_file(frame_id), frame_id))
            except SourceError as exc:
                if not self.lenient:
                    raise
                logger.warning("%s: frame %d left out of the ground truth: %s", self.path, frame_id, exc)
                continue
            ids.append(frame_id)
        frame_ids = np.array(ids, dtype=np.int64)
        return Trajectory(frame_ids * NOMINAL_30HZ_PERIOD_NS, np.array(poses).reshape(-1, 4, 4), frame_ids)

    def describe(self) -> dict[str, Any]:
        return {**super().describe(), "ground_truth": True, "estimate": None}


def _not_a_depth_file(file: Path) -> str:
    """Why a frame's depth image is not there: ``"missing"``, or what stands in its place."""
    try:
        if file.is_dir():
            return "is a folder, not a file"
        if file.is_symlink():
            return "is a symlink that leads to no file"
        if file.exists():
            return "is not a regular file"
    except OSError as exc:
        return f"cannot be looked at: {exc.strerror or exc}"
    return "missing"


def _detect(path: Path) -> bool:
    try:
        return path.is_dir() and next(path.glob("frame-*.depth.png"), None) is not None
    except OSError:
        return False


register_source("7scenes", _detect, opener_for(SevenScenes),
                "Microsoft 7-Scenes sequence (frame-NNNNNN.depth.png mm, .pose.txt camera-to-world)")
