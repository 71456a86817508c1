"""Redwood-style RGB-D folders (Redwood indoor scenes, ICL-NUIM in Redwood layout, Open3D test data).

Layout::

    depth/NNNNN.png          uint16 depth, millimetres (depth_scale 1000); 0 = no reading
    color/NNNNN.jpg          colour, registered to depth (optional; only read with color=True)
    rgbd.match               optional "depth/NNNNN.png color/NNNNN.jpg" pairs, in frame order
    camera_*.json            Open3D PinholeCameraIntrinsic JSON (width, height, column-major intrinsic_matrix)
    trajectory.log           ground truth T_world_camera (Redwood .log), frame id = first number of each block
    odometry.log             optional estimate T_world_camera -> frames carry it as PoseSource.ODOMETRY

``frame_id`` is the number in the depth file name. The format has no time stamps: ``stamp_ns`` is
``frame_id * 33_333_333`` (nominal 30 Hz). This module also holds the RGB-D helpers the 7-Scenes and TUM
sources share (16-bit PNG reading, Open3D intrinsics JSON, the Kinect-class range check of the depth scale).
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from PIL import Image

from driftmap.errors import DepthScaleError, SourceError
from driftmap.frame import Frame, PinholeIntrinsics, PoseSource, Provenance
from driftmap.preprocess.depth import COMMON_DEPTH_SCALES, UINT16_NO_READING, InvalidFractionMonitor, depth_frame
from driftmap.sources.base import FrameSource, register_source
from driftmap.sources.cloud_folder import frame_number, numbered_files, opener_for, pose_or_none
from driftmap.trajectory import Trajectory, read_redwood_log

logger = logging.getLogger(__name__)

NOMINAL_30HZ_PERIOD_NS = 33_333_333
"""Stamp step for data sets recorded at 30 Hz without time stamps (7-Scenes, Redwood, ICL-NUIM)."""

#: What a Kinect-class structured-light camera (Kinect v1, PrimeSense Carmine / Xtion) can measure, metres.
#: (Kinect v1: about 0.4 m in near mode, readings up to about 8-10 m far out.)
KINECT_RANGE_M = (0.3, 10.0)
#: A frame with more of its readings than this outside the sensor's range has the wrong depth scale.
MAX_OUT_OF_RANGE_FRACTION = 0.1

#: Open3D's ``PinholeCameraIntrinsicParameters.PrimeSenseDefault`` (also the TUM / ROS default).
PRIMESENSE_DEFAULT = PinholeIntrinsics(fx=525.0, fy=525.0, cx=319.5, cy=239.5, width=640, height=480)


# ---- RGB-D helpers shared with the 7-Scenes and TUM sources ----------------------------------------------------


def read_depth_png(file: Path, frame_id: int) -> NDArray[np.uint16]:
    """A single-channel 16-bit PNG as a (height, width) uint16 array; :class:`SourceError` names the file."""
    try:
        with Image.open(file) as image:
            mode = image.mode
            depth = np.asarray(image)
    except FileNotFoundError:
        raise SourceError(f"{file}: depth image of frame {frame_id} not found") from None
    except OSError as exc:
        raise SourceError(f"{file}: cannot read depth image of frame {frame_id} ({exc})") from exc
    if depth.dtype in (np.int32, np.uint32) and depth.ndim == 2 and depth.size:
        if 0 <= depth.min() and depth.max() <= 65535:
            depth = depth.astype(np.uint16)  # older Pillow opens 16-bit PNGs in mode "I"
    if depth.ndim != 2 or depth.dtype != np.uint16:
        raise SourceError(
            f"{file}: depth image of frame {frame_id} must be a single-channel 16-bit PNG, got mode {mode!r} "
            f"(dtype {depth.dtype}, shape {depth.shape})"
        )
    return depth


def read_color_image(file: Path, frame_id: int) -> NDArray[np.uint8]:
    """An 8-bit RGB image as (height, width, 3) uint8."""
    try:
        with Image.open(file) as image:
            return np.asarray(image.convert("RGB"))
    except FileNotFoundError:
        raise SourceError(f"{file}: colour image of frame {frame_id} not found") from None
    except OSError as exc:
        raise SourceError(f"{file}: cannot read colour image of frame {frame_id} ({exc})") from exc


def check_sensor_range(
    depth: NDArray[np.uint16],
    depth_scale: float,
    sensor_range_m: tuple[float, float] | None,
    *,
    what: str,
    max_outside_fraction: float = MAX_OUT_OF_RANGE_FRACTION,
) -> None:
    """Raise :class:`DepthScaleError` when more than ``max_outside_fraction`` of the readings (sampled on a
    4x4 grid) fall outside what the sensor can measure at this ``depth_scale``.

    Stricter than :func:`driftmap.preprocess.depth.check_depth_scale` (which only bounds the median to
    0.15..30 m): millimetre data read with TUM's 5000 puts a room at 0.2-0.8 m, which a Kinect-class camera
    cannot see, but whose median is still "plausible". ``sensor_range_m=None`` disables the check.
    """
    if sensor_range_m is None or depth.dtype != np.uint16:
        return
    sample = depth[::4, ::4].ravel()
    sample = sample[(sample != 0) & (sample != UINT16_NO_READING)].astype(np.float64)
    if sample.size == 0:
        return
    lo, hi = sensor_range_m

    def outside(scale: float) -> float:
        z = sample / scale
        return float(np.mean((z < lo) | (z > hi)))

    fraction = outside(depth_scale)
    if fraction <= max_outside_fraction:
        return
    # of the common scales that fit the sensor's range, the one that puts the median closest to 2 m
    median_code = float(np.median(sample))
    fitting = [s for s in COMMON_DEPTH_SCALES if s != depth_scale and outside(s) <= max_outside_fraction]
    suggested = min(fitting, key=lambda s: abs(math.log(median_code / s / 2.0))) if fitting else None
    hint = f"the data suggests depth_scale={suggested:g}" if suggested else "no common depth scale fits the data"
    raise DepthScaleError(
        f"{what}: at depth_scale={depth_scale:g} units/m, {fraction:.0%} of the readings fall outside the "
        f"{lo:g}..{hi:g} m this depth camera can measure (median {median_code / depth_scale:.3g} m); {hint} "
        f"(sensor_range_m=None disables this check)",
        depth_scale_used=depth_scale,
        depth_scale_suggested=suggested,
    )


def read_open3d_intrinsics(file: Path) -> PinholeIntrinsics:
    """An Open3D ``PinholeCameraIntrinsic`` JSON: ``width``, ``height`` and the **column-major** 3x3
    ``intrinsic_matrix`` ``[fx, 0, 0, 0, fy, 0, cx, cy, 1]``; a row-major matrix is rejected."""
    try:
        data = json.loads(file.read_text())
    except FileNotFoundError:
        raise SourceError(f"{file}: intrinsics file not found") from None
    except (OSError, json.JSONDecodeError) as exc:
        raise SourceError(f"{file}: cannot read intrinsics JSON ({exc})") from exc
    try:
        m = [float(v) for v in data["intrinsic_matrix"]]
        width, height = int(data["width"]), int(data["height"])
    except (KeyError, TypeError, ValueError) as exc:
        raise SourceError(f"{file}: expected 'width', 'height' and a 9-number 'intrinsic_matrix' ({exc!r})") from exc
    if len(m) != 9:
        raise SourceError(f"{file}: intrinsic_matrix has {len(m)} numbers, expected 9")
    K = np.array(m).reshape(3, 3).T  # stored column-major
    if K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1 or K[1, 0] != 0:
        raise SourceError(
            f"{file}: intrinsic_matrix {m} is not a column-major pinhole matrix [fx, 0, 0, 0, fy, 0, cx, cy, 1] "
            f"(row-major by mistake?)"
        )
    if K[0, 1] != 0:
        logger.warning("%s: skew %g in the intrinsic matrix is ignored", file, K[0, 1])
    return PinholeIntrinsics(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2], width=width, height=height)


def intrinsics_from_option(value: Any, what: str, *, width: int = 640, height: int = 480) -> PinholeIntrinsics:
    """``intrinsics=`` as :class:`PinholeIntrinsics`, a mapping (``fx fy cx cy [width height]``), a sequence
    ``(fx, fy, cx, cy[, width, height])`` or the path of an Open3D intrinsics JSON."""
    if isinstance(value, PinholeIntrinsics):
        return value
    if isinstance(value, (str, Path)):
        return read_open3d_intrinsics(Path(value))
    try:
        if isinstance(value, Mapping):
            return PinholeIntrinsics(**{"width": width, "height": height, **value})
        if isinstance(value, Sequence) and len(value) in (4, 6):
            values = list(value) + ([width, height] if len(value) == 4 else [])
            return PinholeIntrinsics(*values)
    except TypeError as exc:
        raise SourceError(f"{what}: bad intrinsics {value!r} ({exc})") from exc
    raise SourceError(
        f"{what}: intrinsics must be PinholeIntrinsics, a mapping, (fx, fy, cx, cy[, width, height]) or an Open3D "
        f"intrinsics JSON path; got {value!r}"
    )


# ---- the Redwood source -----------------------------------------------------------------------------------------


def _find_intrinsics_json(folder: Path) -> Path | None:
    preferred = [folder / n for n in ("camera_primesense.json", "camera_intrinsic.json", "intrinsic.json")]
    for candidate in preferred:
        if candidate.is_file():
            return candidate
    for candidate in sorted(folder.glob("*.json")):
        try:
            if "intrinsic_matrix" in json.loads(candidate.read_text()):
                return candidate
        except (OSError, ValueError):
            continue
    return None


class RedwoodRgbd(FrameSource):
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
        super().__init__(str(path), frames=frames, lenient=lenient)
        self.pixel_stride = int(pixel_stride)
        self.path = Path(path)
        if not self.path.is_dir():
            raise SourceError(f"{self.path}: no such folder")
        self.depth_scale = float(depth_scale)
        if depth_scale != 1000.0:
            logger.warning("%s: depth_scale=%g, but Redwood / ICL-NUIM depth PNGs are millimetres (1000)",
                           self.path, depth_scale)
        self.min_depth_m = min_depth_m
        self.max_depth_m = max_depth_m
        self.sensor_range_m = sensor_range_m
        self.color = color
        self.poses_from_ground_truth = poses_from_ground_truth
        self.intrinsics_file = _find_intrinsics_json(self.path)
        if intrinsics is not None:
            self.intrinsics = intrinsics_from_option(intrinsics, str(self.path))
        elif self.intrinsics_file is not None:
            self.intrinsics = read_open3d_intrinsics(self.intrinsics_file)
        else:
            logger.warning("%s: no intrinsics JSON; using the PrimeSense default 525/525/319.5/239.5", self.path)
            self.intrinsics = PRIMESENSE_DEFAULT

        # frames: rgbd.match (depth + colour pairs in frame order) or the numbered depth PNGs
        match_file = self.path / "rgbd.match"
        entries: list[tuple[int, Path, Path | None]] = []
        if match_file.is_file():
            for lineno, line in enumerate(match_file.read_text().splitlines(), start=1):
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
        else:
            color_dir = self.path / "color"
            colors = {}
            if color_dir.is_dir():
                colors = dict(numbered_files(color_dir, "Redwood colour", suffixes=(".jpg", ".png")))
            entries = [(n, f, colors.get(n)) for n, f in numbered_files(self.path / "depth", "Redwood depth",
                                                                            suffixes=(".png",))]
        ids = [e[0] for e in entries]
        for k in range(1, len(ids)):
            if ids[k] <= ids[k - 1]:
                what = str(match_file) if match_file.is_file() else str(self.path / "depth")
                raise SourceError(
                    f"{what}: frame {ids[k]} comes after frame {ids[k - 1]} (frame numbers must increase)"
                )
        self._entries = entries
        self._monitor = InvalidFractionMonitor()

        self.trajectory_file = self.path / trajectory
        self._gt: dict[int, NDArray[np.float64]] | None = None
        if self.trajectory_file.is_file():
            gt = read_redwood_log(self.trajectory_file)
            self._gt = dict(zip(gt.frame_ids.tolist(), gt.poses, strict=True))
            missing = [i for i in ids if i not in self._gt]
            if missing:
                logger.warning("%s: %d of %d frames have no ground-truth pose (first: frame %d)",
                               self.trajectory_file, len(missing), len(ids), missing[0])
        elif poses_from_ground_truth:
            raise SourceError(f"{self.trajectory_file}: ground truth not found (poses_from_ground_truth=True, build --poses-from-source)")
        self.odometry_file = self.path / odometry
        self._odometry: dict[int, NDArray[np.float64]] | None = None
        if self.odometry_file.is_file():
            odo = read_redwood_log(self.odometry_file)
            self._odometry = dict(zip(odo.frame_ids.tolist(), odo.poses, strict=True))

    def _count(self) -> int:
        return len(self._entries)

    def _frame_id(self, index: int) -> int:
        return self._entries[index][0]

    def _stamp_ns(self, index: int) -> int:
        return self._entries[index][0] * NOMINAL_30HZ_PERIOD_NS

    def read_depth(self, index: int) -> NDArray[np.uint16]:
        frame_id, file, _ = self._entries[index]
        return read_depth_png(file, frame_id)

    def _load(self, index: int) -> Frame:
        frame_id, depth_file, color_file = self._entries[index]
        if self.poses_from_ground_truth:
            if self._gt is None or frame_id not in self._gt:
                raise SourceError(f"{self.trajectory_file}: no ground-truth pose for frame {frame_id}")
            pose = pose_or_none(self._gt[frame_id], PoseSource.GROUND_TRUTH)
        elif self._odometry is not None:
            if frame_id not in self._odometry:
                raise SourceError(f"{self.odometry_file}: no odometry pose for frame {frame_id}")
            pose = pose_or_none(self._odometry[frame_id], PoseSource.ODOMETRY)
        else:
            pose = pose_or_none(None, PoseSource.NONE)
        depth = read_depth_png(depth_file, frame_id)
        what = f"frame {frame_id} ({depth_file})"
        check_sensor_range(depth, self.depth_scale, self.sensor_range_m, what=what)
        color = None
        if self.color:
            if color_file is None:
                raise SourceError(f"{self.path}: no colour image for frame {frame_id} (color=True)")
            color = read_color_image(color_file, frame_id)
        return depth_frame(
            depth,
            self.intrinsics,
            frame_id=frame_id,
            stamp_ns=frame_id * NOMINAL_30HZ_PERIOD_NS,
            pose=pose,
            sensor_name="depth_camera",
            sensor_frame="camera_depth_optical_frame",
            depth_scale=self.depth_scale,
            min_depth_m=self.min_depth_m,
            max_depth_m=self.max_depth_m,
            provenance=Provenance(str(depth_file.resolve()), frame_id),
            monitor=self._monitor,
            pixel_stride=self.pixel_stride,
            color_rgb=color,
        )

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
            "intrinsics": self.intrinsics.to_dict(),
            "depth_scale": self.depth_scale,
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
