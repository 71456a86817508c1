"""TUM RGB-D benchmark sequences (``rgbd_dataset_freiburgN_*`` folders).

Layout::

    depth.txt          "stamp_s depth/<stamp>.png" per line ('#' comments): the frames, in time order
    depth/*.png        uint16 depth, 5000 units per metre (depth_scale 5000); 0 = no reading
    rgb.txt, rgb/*.png colour, registered 1:1 to depth by the OpenNI driver (only read with color=True)
    groundtruth.txt    TUM trajectory (motion capture) of the colour camera's optical centre = ground truth

``frame_id`` is the line index of the frame in ``depth.txt`` (TUM has no frame numbers); ``stamp_ns`` is
the depth stamp. Ground truth is associated to each depth stamp by the nearest ground-truth stamp within
``gt_tolerance_ns`` (default 20 ms, like TUM's ``associate.py``); frames without a match are reported
(``frames_without_ground_truth``) and left out of :meth:`TumRgbd.ground_truth`.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from driftmap.errors import SourceError
from driftmap.frame import PinholeIntrinsics, PoseEstimate, PoseSource
from driftmap.sources.base import register_source
from driftmap.sources.cloud_folder import opener_for, pose_or_none
from driftmap.sources.depth_folder import KINECT_RANGE_M, DepthFolderSource, intrinsics_from_option, read_color_image
from driftmap.sources.stamps import check_increasing_stamps, check_seconds_period, parse_stamp_s, read_pose_file
from driftmap.trajectory import Trajectory, read_lines, read_tum

logger = logging.getLogger(__name__)

TUM_DEPTH_SCALE = 5000.0
DEFAULT_GT_TOLERANCE_NS = 20_000_000

#: Calibrated colour-camera intrinsics per recording setup (the depth images are registered to the colour
#: camera), from the TUM RGB-D "intrinsic camera calibration" page; distortion is ignored.
TUM_INTRINSICS = {
    "fr1": PinholeIntrinsics(fx=517.3, fy=516.5, cx=318.6, cy=255.3, width=640, height=480),
    "fr2": PinholeIntrinsics(fx=520.9, fy=521.0, cx=325.1, cy=249.7, width=640, height=480),
    "fr3": PinholeIntrinsics(fx=535.4, fy=539.2, cx=320.1, cy=247.6, width=640, height=480),
}
#: The generic Kinect / ROS default TUM recommends when no sequence-specific calibration is used.
TUM_GENERIC_INTRINSICS = PinholeIntrinsics(fx=525.0, fy=525.0, cx=319.5, cy=239.5, width=640, height=480)

_SETUP = re.compile(r"(?:freiburg|fr)([123])(?![0-9])", re.IGNORECASE)


def tum_setup(name: str) -> str | None:
    """``"fr1"`` / ``"fr2"`` / ``"fr3"`` from a sequence name like ``rgbd_dataset_freiburg2_desk``."""
    match = _SETUP.search(name)
    return f"fr{match.group(1)}" if match else None


def read_file_list(file: Path) -> list[tuple[int, str, int]]:
    """``(stamp_ns, relative path, line number)`` of a TUM ``depth.txt`` / ``rgb.txt``; stamps checked by
    :func:`driftmap.sources.stamps.parse_stamp_s` (errors name ``file:line``), and their steps by
    :func:`driftmap.sources.stamps.check_seconds_period` (a list in milliseconds is refused)."""
    if not file.is_file():
        raise SourceError(f"{file}: not found")
    lines = read_lines(file, "TUM file list")  # SourceError for unreadable or non-UTF-8 text, naming the line
    out = []
    for lineno, line in enumerate(lines, start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        if len(parts) < 2:
            raise SourceError(f"{file}:{lineno}: expected 'stamp_s file', got {line!r}")
        out.append((parse_stamp_s(parts[0], f"{file}:{lineno}"), parts[1], lineno))
    if not out:
        raise SourceError(f"{file}: no entries")
    check_seconds_period([stamp for stamp, _, _ in out], file, f"its {len(out)} entries")
    return out


def associate_nearest(
    query_ns: NDArray[np.int64], reference_ns: NDArray[np.int64], tolerance_ns: int
) -> NDArray[np.int64]:
    """Index of the nearest ``reference_ns`` stamp for each query (``-1`` when farther than ``tolerance_ns``).

    ``reference_ns`` must be sorted ascending.
    """
    query = np.asarray(query_ns, dtype=np.int64)
    ref = np.asarray(reference_ns, dtype=np.int64)
    if ref.size == 0:
        return np.full(query.shape, -1, dtype=np.int64)
    right = np.clip(np.searchsorted(ref, query), 0, ref.size - 1)
    left = np.clip(right - 1, 0, ref.size - 1)
    pick = np.where(np.abs(ref[left] - query) <= np.abs(ref[right] - query), left, right)
    return np.where(np.abs(ref[pick] - query) <= tolerance_ns, pick, -1)


class TumRgbd(DepthFolderSource):
    """A TUM RGB-D sequence folder (see the module docstring).

    Options:
        intrinsics: PinholeIntrinsics, mapping, sequence, Open3D JSON path, or ``"fr1"``/``"fr2"``/``"fr3"``/
            ``"generic"``. Default: the calibration of the setup named in the folder name (freiburg1/2/3),
            else the generic 525/525/319.5/239.5 with a logged warning.
        depth_scale: units per metre (TUM: 5000).
        min_depth_m, max_depth_m: valid depth range (defaults 0.2, 5.0).
        sensor_range_m: measurable range for the depth-scale check (Kinect-class 0.3..10 m; None: off).
        gt_tolerance_ns: largest stamp difference for a ground-truth (and colour) match (20 ms).
        color: attach the nearest colour image (registered to depth) as per-point colour.
        poses_from_ground_truth: frames carry the associated ground truth (``PoseSource.GROUND_TRUTH``);
            a frame without a match then raises (lenient: is skipped).
    """

    format_name = "tum"
    depth_sensor_frame = "camera_rgb_optical_frame"  # depth is registered to the colour camera

    def __init__(
        self,
        path: str | Path,
        *,
        intrinsics: Any = None,
        depth_scale: float = TUM_DEPTH_SCALE,
        min_depth_m: float = 0.2,
        max_depth_m: float = 5.0,
        sensor_range_m: tuple[float, float] | None = KINECT_RANGE_M,
        gt_tolerance_ns: int = DEFAULT_GT_TOLERANCE_NS,
        color: bool = False,
        poses_from_ground_truth: bool = False,
        pixel_stride: int = 1,
        frames: str | slice | None = None,
        lenient: bool = False,
    ):
        super().__init__(path, pixel_stride=pixel_stride, frames=frames, lenient=lenient)
        if not self.path.is_dir():
            raise SourceError(f"{self.path}: no such folder")
        self._set_depth_units(depth_scale, min_depth_m, max_depth_m, sensor_range_m)
        self.gt_tolerance_ns = int(gt_tolerance_ns)
        self.color = color
        self.poses_from_ground_truth = poses_from_ground_truth
        self.intrinsics = self._resolve_intrinsics(intrinsics)

        depth_list = self.path / "depth.txt"
        listed = read_file_list(depth_list)
        # frame id = position in depth.txt; stamps must increase (lenient: later offenders are dropped)
        stamps = [s for s, _, _ in listed]
        keep = check_increasing_stamps(stamps, list(range(len(listed))), str(depth_list), lenient=lenient,
                                       skipped=self.skipped)
        self._entries: list[tuple[int, int, Path]] = [(k, listed[k][0], self.path / listed[k][1]) for k in keep]
        frame_stamps = np.array([e[1] for e in self._entries], dtype=np.int64)
        self._associate_ground_truth(frame_stamps, listed, lenient)
        self._rgb: list[Path | None] = [None] * len(self._entries)
        if color:
            self._associate_colour(frame_stamps)

    def _associate_ground_truth(self, frame_stamps: NDArray[np.int64], listed: list[tuple[int, str, int]],
                                lenient: bool) -> None:
        """The ground-truth pose nearest each frame's stamp within ``gt_tolerance_ns`` (``groundtruth.txt``);
        the frames without one are listed (:attr:`frames_without_ground_truth`) and logged."""
        self.groundtruth_file = self.path / "groundtruth.txt"
        self._gt_pose: list[NDArray[np.float64] | None] = [None] * len(self._entries)
        self.frames_without_ground_truth: list[int] = []
        if self.groundtruth_file.is_file():
            gt = read_pose_file(read_tum, self.groundtruth_file)
            gt_keep = check_increasing_stamps(gt.stamps_ns.tolist(), [f"row {r + 1}" for r in range(len(gt))],
                                              str(self.groundtruth_file), lenient=lenient)
            gt_stamps, gt_poses = gt.stamps_ns[gt_keep], gt.poses[gt_keep]
            match = associate_nearest(frame_stamps, gt_stamps, self.gt_tolerance_ns)
            for k, m in enumerate(match):
                if m >= 0:
                    self._gt_pose[k] = gt_poses[m]
                else:
                    self.frames_without_ground_truth.append(self._entries[k][0])
            if self.frames_without_ground_truth:
                first = self.frames_without_ground_truth[0]
                logger.warning(
                    "%s: %d of %d frames have no ground-truth pose within %.1f ms (first: frame %d at stamp_ns %d)",
                    self.groundtruth_file, len(self.frames_without_ground_truth), len(self._entries),
                    self.gt_tolerance_ns / 1e6, first, listed[first][0],
                )
        elif self.poses_from_ground_truth:
            raise SourceError(f"{self.groundtruth_file}: ground truth not found (poses_from_ground_truth=True, build --poses-from-source)")
        else:
            self.frames_without_ground_truth = [e[0] for e in self._entries]

    def _associate_colour(self, frame_stamps: NDArray[np.int64]) -> None:
        """The colour image (``rgb.txt``) nearest each frame's stamp within ``gt_tolerance_ns``."""
        rgb_list = self.path / "rgb.txt"
        rgb = read_file_list(rgb_list)
        rgb_stamps = np.array([s for s, _, _ in rgb], dtype=np.int64)
        order = np.argsort(rgb_stamps, kind="stable")
        match = associate_nearest(frame_stamps, rgb_stamps[order], self.gt_tolerance_ns)
        self._rgb = [None if m < 0 else self.path / rgb[order[m]][1] for m in match]

    def _resolve_intrinsics(self, value: Any) -> PinholeIntrinsics:
        if isinstance(value, str) and value.lower() in (*TUM_INTRINSICS, "generic"):
            return TUM_INTRINSICS.get(value.lower(), TUM_GENERIC_INTRINSICS)
        if value is not None:
            return intrinsics_from_option(value, str(self.path))
        setup = tum_setup(self.path.resolve().name)
        if setup is not None:
            logger.info("%s: using the TUM %s calibration %s", self.path, setup, TUM_INTRINSICS[setup])
            return TUM_INTRINSICS[setup]
        logger.warning(
            "%s: cannot tell the TUM setup (freiburg1/2/3) from the folder name; using the generic intrinsics "
            "525/525/319.5/239.5 (pass intrinsics= to choose)", self.path,
        )
        return TUM_GENERIC_INTRINSICS

    def _count(self) -> int:
        return len(self._entries)

    def _frame_id(self, index: int) -> int:
        return self._entries[index][0]

    def _stamp_ns(self, index: int) -> int:
        return self._entries[index][1]

    def _depth_entry(self, index: int) -> tuple[int, int, Path]:
        frame_id, stamp_ns, file = self._entries[index]
        return frame_id, stamp_ns, file

    def _pose_estimate(self, index: int) -> PoseEstimate:
        if not self.poses_from_ground_truth:
            return pose_or_none(None, PoseSource.NONE)
        T = self._gt_pose[index]
        if T is None:
            frame_id, stamp_ns, _ = self._entries[index]
            raise SourceError(
                f"{self.groundtruth_file}: no ground-truth pose within {self.gt_tolerance_ns / 1e6:g} ms of "
                f"frame {frame_id} (stamp_ns {stamp_ns})"
            )
        return pose_or_none(T, PoseSource.GROUND_TRUTH)

    def _color(self, index: int) -> NDArray[np.uint8] | None:
        if not self.color:
            return None
        rgb = self._rgb[index]
        if rgb is None:
            frame_id, stamp_ns, _ = self._entries[index]
            raise SourceError(
                f"{self.path / 'rgb.txt'}: no colour image within {self.gt_tolerance_ns / 1e6:g} ms of frame "
                f"{frame_id} (stamp_ns {stamp_ns})"
            )
        return read_color_image(rgb, self._entries[index][0])

    def ground_truth(self) -> Trajectory | None:
        """Associated ground truth ``T_world_camera`` of the selected frames that have a match, at the
        frames' stamps (``frame_ids`` set); ``None`` without ``groundtruth.txt``."""
        if not self.groundtruth_file.is_file():
            return None
        idx = [i for i in self._indices() if self._gt_pose[i] is not None]
        return Trajectory(
            np.array([self._entries[i][1] for i in idx], dtype=np.int64),
            np.array([self._gt_pose[i] for i in idx], dtype=np.float64).reshape(-1, 4, 4),
            np.array([self._entries[i][0] for i in idx], dtype=np.int64),
        )

    def describe(self) -> dict[str, Any]:
        return {**super().describe(), "ground_truth": self.groundtruth_file.is_file(),
                "frames_without_ground_truth": len(self.frames_without_ground_truth), "estimate": None}


def _detect(path: Path) -> bool:
    try:
        return path.is_dir() and (path / "depth.txt").is_file()
    except OSError:
        return False


register_source("tum", _detect, opener_for(TumRgbd),
                "TUM RGB-D sequence (depth.txt, depth/*.png at 5000 units/m, groundtruth.txt)")
