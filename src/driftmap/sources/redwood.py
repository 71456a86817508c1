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

import contextlib
import json
import logging
import math
import struct
import zlib
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from PIL import Image

from driftmap.errors import DepthError, DepthScaleError, GeometryError, SourceError
from driftmap.frame import Frame, PinholeIntrinsics, PoseSource, Provenance
from driftmap.preprocess.depth import COMMON_DEPTH_SCALES, UINT16_NO_READING, InvalidFractionMonitor, depth_frame
from driftmap.sources.base import FrameSource, register_source
from driftmap.sources.cloud_folder import frame_number, numbered_files, opener_for, pose_or_none
from driftmap.sources.stamps import nominal_stamp_ns, read_pose_file
from driftmap.trajectory import Trajectory, _read_lines, read_redwood_log

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


#: what Pillow raises for damaged images besides OSError (truncated headers, bad chunks, decompression bombs)
_IMAGE_ERRORS = (OSError, SyntaxError, ValueError, EOFError, struct.error, zlib.error, Image.DecompressionBombError)
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: PNG colour type -> samples per pixel
_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}
#: Adam7 passes: (x start, y start, x step, y step)
_ADAM7 = ((0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2), (0, 1, 1, 2))


def _png_raw_bytes(width: int, height: int, bit_depth: int, colour_type: int, interlace: int) -> int:
    """The bytes of filtered scanlines a PNG of this header decompresses to."""
    bits = _PNG_CHANNELS[colour_type] * bit_depth

    def rows(w: int, h: int) -> int:
        return 0 if w == 0 or h == 0 else h * (1 + (w * bits + 7) // 8)

    if not interlace:
        return rows(width, height)
    return sum(rows((width - x0 + dx - 1) // dx, (height - y0 + dy - 1) // dy) for x0, y0, dx, dy in _ADAM7)


def png_size_problem(file: Path) -> str | None:
    """What is wrong with the sizes of a PNG file, or ``None``: the image data must decompress to exactly the bytes
    its IHDR size implies (counted while streaming, so a header that claims a huge image allocates nothing).
    Files that are not PNG are left to Pillow."""
    data = file.read_bytes()
    if not data.startswith(PNG_SIGNATURE):
        return None
    pos, header, inflater, produced = len(PNG_SIGNATURE), None, zlib.decompressobj(), 0
    while pos + 8 <= len(data):
        length, kind = struct.unpack(">I4s", data[pos:pos + 8])
        body = data[pos + 8:pos + 8 + length]
        if len(body) < length:
            return f"chunk {kind.decode('latin-1')!r} says {length} bytes, the file holds {len(body)} (truncated)"
        pos += 12 + length
        if kind == b"IHDR":
            if length != 13:
                return f"IHDR chunk of {length} bytes (13 expected)"
            header = struct.unpack(">IIBBBBB", body)
            if header[3] not in _PNG_CHANNELS or header[2] not in (1, 2, 4, 8, 16):
                return f"IHDR: bit depth {header[2]}, colour type {header[3]}"
        elif kind == b"IDAT" and header is not None:
            expected = _png_raw_bytes(header[0], header[1], header[2], header[3], header[6])
            try:
                chunk = inflater.decompress(body, 1 << 20)
                while True:
                    produced += len(chunk)
                    if produced > expected or not inflater.unconsumed_tail:
                        break
                    chunk = inflater.decompress(inflater.unconsumed_tail, 1 << 20)
            except zlib.error as exc:
                return f"image data does not decompress ({exc})"
            if produced > expected:
                break
        elif kind == b"IEND":
            break
    if header is None:
        return "no IHDR chunk"
    expected = _png_raw_bytes(header[0], header[1], header[2], header[3], header[6])
    if produced != expected:
        return (f"the header says {header[0]}x{header[1]} pixels ({expected} bytes of image data), the file's image "
                f"data {'holds more than that' if produced > expected else f'holds {produced}'}: a damaged header "
                f"or a truncated file")
    return None


def _open_image_checked(file: Path, frame_id: int, what: str) -> Image.Image:
    """``Image.open`` of a frame's image whose stated size fits the bytes of the file (checked before any pixel
    is decoded: :func:`png_size_problem`); :class:`SourceError` naming the file otherwise."""
    try:
        problem = png_size_problem(file)
        if problem is not None:
            raise SourceError(f"{file}: {what} of frame {frame_id}: {problem}")
        return Image.open(file)
    except FileNotFoundError:
        raise SourceError(f"{file}: {what} of frame {frame_id} not found") from None
    except _IMAGE_ERRORS as exc:
        raise SourceError(f"{file}: cannot read {what} of frame {frame_id} ({type(exc).__name__}: {exc})") from exc


def read_depth_png(file: Path, frame_id: int) -> NDArray[np.uint16]:
    """A single-channel 16-bit PNG as a (height, width) uint16 array; :class:`SourceError` names the file (a
    missing or damaged file, a header whose image size the file cannot hold, another image type)."""
    image = _open_image_checked(file, frame_id, "depth image")
    try:
        with image:
            mode = image.mode
            depth = np.asarray(image)
    except _IMAGE_ERRORS as exc:
        raise SourceError(f"{file}: cannot read depth image of frame {frame_id} ({type(exc).__name__}: {exc})") from exc
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
    image = _open_image_checked(file, frame_id, "colour image")
    try:
        with image:
            return np.asarray(image.convert("RGB"))
    except _IMAGE_ERRORS as exc:
        raise SourceError(f"{file}: cannot read colour image of frame {frame_id} ({type(exc).__name__}: {exc})") from exc


@contextlib.contextmanager
def frame_errors_named(file: Path, frame_id: int) -> Iterator[None]:
    """Errors about a frame's content that do not name its file (a depth image of another size than the
    intrinsics, an unusable depth image) as :class:`SourceError` naming it, so lenient sources skip the frame.
    :class:`DepthScaleError` passes unchanged: a wrong scale is wrong for every frame."""
    try:
        yield
    except DepthScaleError:
        raise
    except (GeometryError, DepthError) as exc:
        raise SourceError(f"{file} (frame {frame_id}): {exc}") from exc


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
    except (OSError, ValueError) as exc:  # ValueError: JSON that does not parse, text that is not UTF-8
        raise SourceError(f"{file}: cannot read intrinsics JSON ({exc})") from exc
    try:
        m = [float(v) for v in data["intrinsic_matrix"]]
        width, height = int(data["width"]), int(data["height"])
    except (KeyError, TypeError, ValueError, OverflowError) as exc:
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
    return intrinsics_named(file, fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2], width=width, height=height)


#: focal lengths a pinhole depth camera can have, pixels (below 1 px the field of view of even a 2-pixel image
#: passes 90 degrees; beyond 1e6 px every point lands on the optical axis)
FOCAL_RANGE_PX = (1.0, 1e6)


def intrinsics_problem(intrinsics: PinholeIntrinsics) -> str | None:
    """What no pinhole camera has (a focal length outside :data:`FOCAL_RANGE_PX`, a principal point farther than one
    image size outside the image), or ``None``. Such values back-project depth to absurd or infinite coordinates."""
    lo, hi = FOCAL_RANGE_PX
    i = intrinsics
    if not (lo <= i.fx <= hi and lo <= i.fy <= hi):
        return f"focal lengths fx={i.fx:g}, fy={i.fy:g} px are outside {lo:g} .. {hi:g} px"
    if not (-i.width <= i.cx <= 2 * i.width and -i.height <= i.cy <= 2 * i.height):
        return (f"principal point cx={i.cx:g}, cy={i.cy:g} px lies far outside the {i.width}x{i.height} image")
    return None


def checked_intrinsics(intrinsics: PinholeIntrinsics, what: str | Path) -> PinholeIntrinsics:
    """``intrinsics``, or :class:`SourceError` naming ``what`` (where they come from) and :func:`intrinsics_problem`."""
    problem = intrinsics_problem(intrinsics)
    if problem is not None:
        raise SourceError(f"{what}: unusable camera intrinsics ({problem})")
    return intrinsics


def intrinsics_named(what: str | Path, **values: Any) -> PinholeIntrinsics:
    """``PinholeIntrinsics(**values)``, checked (:func:`checked_intrinsics`); values it refuses (a negative or NaN
    focal length, a zero width) or no camera has raise :class:`SourceError` naming ``what`` (the file they were
    read from)."""
    try:
        intrinsics = PinholeIntrinsics(**values)
    except (GeometryError, TypeError, ValueError, OverflowError) as exc:
        raise SourceError(f"{what}: unusable camera intrinsics ({exc})") from exc
    return checked_intrinsics(intrinsics, what)


def intrinsics_from_option(value: Any, what: str, *, width: int = 640, height: int = 480) -> PinholeIntrinsics:
    """``intrinsics=`` as :class:`PinholeIntrinsics`, a mapping (``fx fy cx cy [width height]``), a sequence
    ``(fx, fy, cx, cy[, width, height])`` or the path of an Open3D intrinsics JSON."""
    if isinstance(value, PinholeIntrinsics):
        return checked_intrinsics(value, f"{what}: intrinsics option")
    if isinstance(value, (str, Path)):
        return read_open3d_intrinsics(Path(value))
    try:
        if isinstance(value, Mapping):
            intrinsics = PinholeIntrinsics(**{"width": width, "height": height, **value})
            return checked_intrinsics(intrinsics, f"{what}: intrinsics option")
        if isinstance(value, Sequence) and len(value) in (4, 6):
            values = list(value) + ([width, height] if len(value) == 4 else [])
            return checked_intrinsics(PinholeIntrinsics(*values), f"{what}: intrinsics option")
    except (TypeError, ValueError, OverflowError, GeometryError) as exc:
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
            for lineno, line in enumerate(_read_lines(match_file, "Redwood rgbd.match"), start=1):
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
        self._entries = entries
        self._monitor = InvalidFractionMonitor()

        self.trajectory_file = self.path / trajectory
        self._gt: dict[int, NDArray[np.float64]] | None = None
        if self.trajectory_file.is_file():
            gt = read_pose_file(read_redwood_log, self.trajectory_file)
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
            odo = read_pose_file(read_redwood_log, self.odometry_file)
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
        with frame_errors_named(depth_file, frame_id):
            return self._depth_frame(depth, frame_id, depth_file, pose, color)

    def _depth_frame(self, depth: NDArray[np.uint16], frame_id: int, depth_file: Path, pose: Any,
                     color: NDArray[np.uint8] | None) -> Frame:
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
