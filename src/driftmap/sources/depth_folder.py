"""Folders of 16-bit depth images from one pinhole camera: what the 7-Scenes, TUM and Redwood sources share.

* reading the images: :func:`read_depth_png` (single-channel 16-bit PNG, its stated size checked against the
  file's bytes before any pixel is decoded, :func:`png_size_problem`), :func:`read_color_image`;
* the camera: Open3D intrinsics JSON (:func:`read_open3d_intrinsics`), the ``intrinsics=`` option
  (:func:`intrinsics_from_option`), values no pinhole camera has refused (:func:`checked_intrinsics`);
* the depth scale: :func:`check_sensor_range` (readings a Kinect-class camera cannot measure at that scale);
* the frames: :class:`DepthFolderSource`, the base of those sources, turns entry ``index`` (a frame id, stamp and
  depth file, its pose, optionally its colour) into a back-projected :class:`~driftmap.Frame` whose errors name
  the file (:func:`frame_errors_named`).

Internal to :mod:`driftmap.sources` (the source modules re-export what they always exported).
"""

from __future__ import annotations

import contextlib
import dataclasses
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
from driftmap.frame import Frame, FrameQuality, PinholeIntrinsics, PoseEstimate, Provenance
from driftmap.preprocess.depth import COMMON_DEPTH_SCALES, UINT16_NO_READING, InvalidFractionMonitor, depth_frame
from driftmap.sources.base import FrameSource

logger = logging.getLogger(__name__)

NOMINAL_30HZ_PERIOD_NS = 33_333_333
"""Stamp step for data sets recorded at 30 Hz without time stamps (7-Scenes, Redwood, ICL-NUIM)."""

#: What a Kinect-class structured-light camera (Kinect v1, PrimeSense Carmine / Xtion) can measure, metres.
#: (Kinect v1: about 0.4 m in near mode, readings up to about 8-10 m far out.)
KINECT_RANGE_M = (0.3, 10.0)
#: A frame with more of its readings than this outside the sensor's range has the wrong depth scale.
MAX_OUT_OF_RANGE_FRACTION = 0.1
#: A frame with at least this fraction of its pixels invalid is warned about and flagged, whatever the frames
#: before it (:class:`~driftmap.preprocess.depth.InvalidFractionMonitor` flags only jumps above a history of
#: several frames: an image that is all zeros at the start of a sequence, or in a short one, passed without a word).
MOSTLY_INVALID_FRACTION = 0.95
#: How many such frames a source warns about one by one; later ones are logged at debug level.
MOSTLY_INVALID_WARNINGS = 10


# ---- images -----------------------------------------------------------------------------------------------------


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
        stated = png_stated_type(file)
        got = (f"the file is {stated} (Pillow opens it as mode {mode!r}, dtype {depth.dtype}, shape {depth.shape})"
               if stated else f"got mode {mode!r} (dtype {depth.dtype}, shape {depth.shape})")
        raise SourceError(f"{file}: depth image of frame {frame_id} must be a single-channel 16-bit PNG, {got}: save "
                          f"the depth as one 16-bit grey channel")
    return depth


_PNG_COLOUR_NAMES = {0: "grey", 2: "RGB", 3: "palette", 4: "grey + alpha", 6: "RGBA"}


def png_stated_type(file: Path) -> str | None:
    """What a PNG's IHDR says it holds ("16-bit RGB (3 channels)"), or None for a file that is no PNG (Pillow may
    open a 16-bit RGB PNG as 8-bit RGB: the header says what the file is; hostile trial 26 W5)."""
    with open(file, "rb") as f:
        head = f.read(len(PNG_SIGNATURE) + 8 + 13)
    if not head.startswith(PNG_SIGNATURE) or head[len(PNG_SIGNATURE) + 4:len(PNG_SIGNATURE) + 8] != b"IHDR":
        return None
    bit_depth, colour = head[len(PNG_SIGNATURE) + 16], head[len(PNG_SIGNATURE) + 17]
    channels = _PNG_CHANNELS.get(colour)
    if channels is None:
        return None
    return f"{bit_depth}-bit {_PNG_COLOUR_NAMES[colour]} ({channels} channel{'s' if channels > 1 else ''})"


def read_color_image(file: Path, frame_id: int) -> NDArray[np.uint8]:
    """An 8-bit RGB image as (height, width, 3) uint8."""
    image = _open_image_checked(file, frame_id, "colour image")
    try:
        with image:
            return np.asarray(image.convert("RGB"))
    except _IMAGE_ERRORS as exc:
        raise SourceError(f"{file}: cannot read colour image of frame {frame_id} ({type(exc).__name__}: {exc})") from exc


# ---- frames and the depth scale ---------------------------------------------------------------------------------


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


# ---- intrinsics -------------------------------------------------------------------------------------------------


def read_open3d_intrinsics(file: Path) -> PinholeIntrinsics:
    """An Open3D ``PinholeCameraIntrinsic`` JSON: ``width``, ``height`` and the **column-major** 3x3
    ``intrinsic_matrix`` ``[fx, 0, 0, 0, fy, 0, cx, cy, 1]``; a row-major matrix is rejected."""
    try:
        data = json.loads(file.read_text())
    except FileNotFoundError:
        raise SourceError(f"{file}: intrinsics file not found") from None
    except (OSError, ValueError, RecursionError) as exc:  # ValueError: JSON that does not parse, text that is not UTF-8
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
MAX_PLAUSIBLE_FOV_DEG = 150.0
"""A pinhole field of view wider than this (deg, horizontal) is warned about: a unit or image-size mistake."""
MAX_FOCAL_RATIO = 2.0
"""fx / fy beyond this (or below its inverse) is warned about (hostile trial 28 B3: fy 100x fx built "tracking ok")."""
MIN_PLAUSIBLE_FOV_DEG = 20.0
"""A pinhole field of view narrower than this (deg, horizontal) is warned about: a focal length in other units or for
another image size (hostile trial 27 B2: fx 10x and 1000x too large built "tracking ok" on pencil-thin clouds)."""


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


_WARNED: set[tuple[str, PinholeIntrinsics]] = set()
"""Intrinsics already checked (and warned about) per source, so that each warning is given once per process."""


def checked_intrinsics(intrinsics: PinholeIntrinsics, what: str | Path) -> PinholeIntrinsics:
    """``intrinsics``, or :class:`SourceError` naming ``what`` (where they come from) and :func:`intrinsics_problem`."""
    problem = intrinsics_problem(intrinsics)
    if problem is not None:
        raise SourceError(f"{what}: unusable camera intrinsics ({problem})")
    i = intrinsics
    if (str(what), i) in _WARNED:
        return intrinsics  # said once (a source opened twice, for its pixel stride: hostile trial 28 W10)
    _WARNED.add((str(what), i))
    for name, f, size, axis in (("fx", i.fx, i.width, "horizontal"), ("fy", i.fy, i.height, "vertical")):
        fov_deg = 2.0 * np.degrees(np.arctan(0.5 * size / f))  # (hostile trial 28 B3: fy was never looked at)
        if fov_deg > MAX_PLAUSIBLE_FOV_DEG:
            logger.warning("%s: %s=%g px gives a %.0f deg %s field of view over %d px (pinhole depth cameras see "
                           "55-120 deg): is %s in other units, or for another image size?", what, name, f, fov_deg,
                           axis, size, name)
        elif fov_deg < MIN_PLAUSIBLE_FOV_DEG:
            logger.warning("%s: %s=%g px gives a %.2g deg %s field of view over %d px (pinhole depth cameras see "
                           "55-120 deg): is %s in other units, or for another image size? Every point would lie in a "
                           "cone this narrow", what, name, f, fov_deg, axis, size, name)
    if not 1.0 / MAX_FOCAL_RATIO <= i.fx / i.fy <= MAX_FOCAL_RATIO:
        logger.warning("%s: fx=%g and fy=%g px differ %.3g-fold (a camera's pixels are near square): is one of them "
                       "in other units, or mistyped?", what, i.fx, i.fy, max(i.fx / i.fy, i.fy / i.fx))
    if not (0.0 < i.cx < i.width and 0.0 < i.cy < i.height):
        logger.warning("%s: the principal point cx=%g, cy=%g px lies on the edge of or outside the %dx%d image (a "
                       "camera's optical axis meets its image near the centre): are cx, cy in other units, for another image size, "
                       "or swapped with fx, fy?", what, i.cx, i.cy, i.width, i.height)
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


TUM_SETUP_NAMES = ("fr1", "fr2", "fr3")
"""The TUM RGB-D camera setups the TUM reader takes by name (``intrinsics="fr1"``); other depth sources refuse them
by name rather than look for a file called ``fr1``."""


def intrinsics_from_option(value: Any, what: str, *, width: int = 640, height: int = 480) -> PinholeIntrinsics:
    """``intrinsics=`` as :class:`PinholeIntrinsics`, a mapping (``fx fy cx cy [width height]``), a sequence
    ``(fx, fy, cx, cy[, width, height])`` or the path of an Open3D intrinsics JSON."""
    if isinstance(value, PinholeIntrinsics):
        return checked_intrinsics(value, f"{what}: intrinsics option")
    if isinstance(value, (str, Path)):
        if isinstance(value, str) and value.strip().lower() in TUM_SETUP_NAMES and not Path(value).exists():
            raise SourceError(f"{what}: intrinsics {value!r} names a TUM RGB-D camera setup, which only TUM "
                              f"sequences take; give this source 'fx,fy,cx,cy[,width,height]' or an Open3D "
                              f"intrinsics JSON")
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


# ---- the sources ------------------------------------------------------------------------------------------------


class DepthFolderSource(FrameSource):
    """Base of the sources that read a folder of 16-bit depth images taken by one pinhole camera (7-Scenes, TUM,
    Redwood): each frame is a depth file, back-projected with :attr:`intrinsics` at :attr:`depth_scale`, its
    readings checked against what the camera can measure (:func:`check_sensor_range`), errors naming the file.

    Subclasses call ``__init__`` first and :meth:`_set_depth_units` where their options are read, set
    :attr:`intrinsics`, and implement ``_count``, ``_frame_id``, ``_stamp_ns``, :meth:`_depth_entry` and
    :meth:`_pose_estimate` (and :meth:`_color` to colour the points)."""

    depth_sensor_name = "kinect_depth"
    """``Frame.sensor_name`` of the frames."""
    depth_sensor_frame = "camera_depth_optical_frame"
    """``Frame.sensor_frame`` of the frames."""
    intrinsics: PinholeIntrinsics

    def __init__(self, path: str | Path, *, pixel_stride: int, frames: str | slice | None, lenient: bool):
        super().__init__(str(path), frames=frames, lenient=lenient)
        self.pixel_stride = int(pixel_stride)
        self.path = Path(path)
        self._mostly_invalid = 0
        """How many frames :meth:`_flag_mostly_invalid` has flagged."""

    def _set_depth_units(self, depth_scale: float, min_depth_m: float, max_depth_m: float,
                         sensor_range_m: tuple[float, float] | None) -> None:
        """Depth units per metre, the depth range kept and the range the camera can measure (``None``: not
        checked)."""
        self.depth_scale = float(depth_scale)
        self.min_depth_m = min_depth_m
        self.max_depth_m = max_depth_m
        self.sensor_range_m = sensor_range_m
        self._monitor = InvalidFractionMonitor()

    # ---- to implement
    def _depth_entry(self, index: int) -> tuple[int, int, Path]:
        """``(frame_id, stamp_ns, depth file)`` of underlying ``index``."""
        raise NotImplementedError

    def _pose_estimate(self, index: int) -> PoseEstimate:
        """The pose frame ``index`` carries (:func:`~driftmap.sources.cloud_folder.pose_or_none`)."""
        raise NotImplementedError

    def _color(self, index: int) -> NDArray[np.uint8] | None:
        """The colour image registered to frame ``index``'s depth, if the points are to be coloured."""
        return None

    # ---- provided
    def read_depth(self, index: int) -> NDArray[np.uint16]:
        frame_id, _, file = self._depth_entry(index)
        return read_depth_png(file, frame_id)

    def _load(self, index: int) -> Frame:
        frame_id, stamp_ns, file = self._depth_entry(index)
        pose = self._pose_estimate(index)
        depth = read_depth_png(file, frame_id)
        check_sensor_range(depth, self.depth_scale, self.sensor_range_m, what=f"frame {frame_id} ({file})")
        color = self._color(index)
        with frame_errors_named(file, frame_id):
            frame = depth_frame(
                depth,
                self.intrinsics,
                frame_id=frame_id,
                stamp_ns=stamp_ns,
                pose=pose,
                sensor_name=self.depth_sensor_name,
                sensor_frame=self.depth_sensor_frame,
                depth_scale=self.depth_scale,
                min_depth_m=self.min_depth_m,
                max_depth_m=self.max_depth_m,
                provenance=Provenance(str(file.resolve()), frame_id),
                monitor=self._monitor,
                pixel_stride=self.pixel_stride,
                color_rgb=color,
                check_scale=self.sensor_range_m is not None,  # depth.check_scale = false turns off both checks
            )
        return self._flag_mostly_invalid(frame, file)

    def _flag_mostly_invalid(self, frame: Frame, file: Path) -> Frame:
        """``frame``, flagged (``mostly_invalid: ...``) with a warning naming ``file`` and its invalid-pixel fraction
        when at least :data:`MOSTLY_INVALID_FRACTION` of its pixels are invalid (an all-zero image: no point at
        all), unless the invalid-fraction monitor flagged it already (it warned then, naming the file)."""
        quality = frame.quality
        if quality is None or quality.invalid_fraction < MOSTLY_INVALID_FRACTION:
            return frame
        if any(f.startswith("invalid_fraction_jump") for f in quality.flags):
            return frame
        counts = ", ".join(f"{k} {v}" for k, v in sorted(quality.invalid_counts.items(), key=lambda kv: -kv[1]) if v)
        what = ("no valid pixel: the frame has no point" if quality.n_valid == 0 else
                f"only {quality.n_valid} valid pixels")
        reason = (f"mostly_invalid: {quality.invalid_fraction:.3f} of the {quality.n_measurements} pixels invalid "
                  f"({counts or 'none counted'}); {what}")
        self._mostly_invalid += 1
        again = self._mostly_invalid > MOSTLY_INVALID_WARNINGS
        logger.log(logging.DEBUG if again else logging.WARNING,
                   "%s (frame %d): invalid pixel fraction %.3f (%s); the frame is flagged%s", file, frame.frame_id,
                   quality.invalid_fraction, what,
                   f" (more such frames of {self.path} are logged at debug level)"
                   if self._mostly_invalid == MOSTLY_INVALID_WARNINGS else "")
        flagged = FrameQuality(quality.n_measurements, quality.n_valid, quality.invalid_counts,
                               (*quality.flags, reason))
        return dataclasses.replace(frame, quality=flagged)

    def describe(self) -> dict[str, Any]:
        return {**super().describe(), "intrinsics": self.intrinsics.to_dict(), "depth_scale": self.depth_scale}
