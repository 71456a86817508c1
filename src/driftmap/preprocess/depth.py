"""Depth-image validation and back-projection (``P_c = z K^-1 [u v 1]^T``).

* uint16 images are converted with ``depth_scale`` (units per metre: 1000 for millimetres, 5000 for TUM);
  float32/float64 images are already in metres and ``depth_scale`` is ignored.
* Every rejected pixel is counted under one :class:`InvalidReason`.
* Points come out float32, in the sensor (optical) frame, in row-major pixel order -- the order Open3D's
  ``PointCloud.create_from_depth_image`` uses -- so results can be compared point for point.
* A pixel is valid when ``min_depth_m <= z < max_depth_m``; the upper bound is exclusive, exactly like
  Open3D's ``depth_trunc``.

The hot path is vectorised: uint16 depth is converted through a 65536-entry lookup table (0 marks an
invalid code), and the per-pixel rays ``K^-1 [u v 1]`` are cached per intrinsics.
"""

from __future__ import annotations

import enum
import functools
import logging
import math
from collections import deque
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from driftmap.errors import DepthError, DepthScaleError
from driftmap.frame import (
    Frame,
    FrameQuality,
    PinholeIntrinsics,
    PointAttributes,
    PoseEstimate,
    Provenance,
    SensorKind,
    adopt_readonly,
)
from driftmap.kernels.points import backproject_uint16

logger = logging.getLogger(__name__)

#: uint16 "no reading" value used by Kinect-class sensors and 7-Scenes.
UINT16_NO_READING = 65535

DEFAULT_MIN_DEPTH_M = 0.1
DEFAULT_MAX_DEPTH_M = 10.0

#: Median depth (of the pixels that carry a reading) that a depth camera can plausibly see, in metres.
PLAUSIBLE_MEDIAN_DEPTH_M = (0.15, 30.0)
#: Scales tried when suggesting the right ``depth_scale`` for a uint16 image (units per metre).
COMMON_DEPTH_SCALES = (1000.0, 5000.0, 4000.0, 10000.0, 100.0, 1.0)


class InvalidReason(enum.Enum):
    """Why a depth pixel was rejected."""

    ZERO = "zero"
    NAN = "nan"
    INF = "inf"
    NO_READING_65535 = "no_reading_65535"
    NEGATIVE = "negative"
    BELOW_MIN = "below_min"
    BEYOND_MAX = "beyond_max"


@dataclass(frozen=True)
class BackprojectionResult:
    """Valid points of one depth image in the sensor frame plus per-reason rejection counts."""

    points: NDArray[np.float32]
    """(N, 3) float32, sensor (optical) frame: x right, y down, z forward; row-major pixel order."""
    valid_mask: NDArray[np.bool_]
    """Flat (height * width,) mask of the pixels that became points."""
    invalid_counts: dict[str, int]
    n_pixels: int
    depth_scale: float | None
    """The scale used for a uint16 image, ``None`` for float images (already metres)."""

    @functools.cached_property
    def pixel_index(self) -> NDArray[np.int64]:
        """Flat pixel index ``v * width + u`` of each point (to look up colour or other per-pixel data)."""
        return np.flatnonzero(self.valid_mask)

    @property
    def n_valid(self) -> int:
        return int(self.points.shape[0])

    @property
    def valid_fraction(self) -> float:
        return self.n_valid / self.n_pixels if self.n_pixels else 0.0

    @property
    def invalid_fraction(self) -> float:
        return 1.0 - self.valid_fraction

    def quality(self, flags: tuple[str, ...] = ()) -> FrameQuality:
        return FrameQuality(self.n_pixels, self.n_valid, self.invalid_counts, flags)


_RAY_ITEM = np.dtype((np.void, 12))


@functools.lru_cache(maxsize=16)
def _rays(intrinsics: PinholeIntrinsics) -> NDArray[np.void]:
    """Per-pixel rays ``K^-1 [u v 1] = ((u - cx) / fx, (v - cy) / fy, 1)``, row-major, read-only.

    Stored as one 12-byte item per pixel so the valid rays are gathered with a single 1-D compress.
    """
    u = np.arange(intrinsics.width, dtype=np.float64)
    v = np.arange(intrinsics.height, dtype=np.float64)
    rays = np.empty((intrinsics.height * intrinsics.width, 3), dtype=np.float32)
    rays[:, 0] = np.tile((u - intrinsics.cx) / intrinsics.fx, intrinsics.height)
    rays[:, 1] = np.repeat((v - intrinsics.cy) / intrinsics.fy, intrinsics.width)
    rays[:, 2] = 1.0
    items = rays.view(_RAY_ITEM).ravel()
    items.setflags(write=False)
    return items


@functools.lru_cache(maxsize=16)
def _uint16_lut(depth_scale: float, min_depth_m: float, max_depth_m: float) -> tuple[NDArray[np.float32], int, int]:
    """Lookup table code -> metres (0 where the code is invalid), and the first codes at/above min and max depth.

    Like Open3D, a code becomes the float32 ``code / depth_scale`` and that float32 value is compared with
    the (double) bounds, so the kept pixels are exactly Open3D's for the same ``depth_trunc``.
    """
    z = (np.arange(65536, dtype=np.float64) / depth_scale).astype(np.float32)
    z64 = z.astype(np.float64)
    valid = (z64 >= min_depth_m) & (z64 < max_depth_m)
    valid[0] = False
    valid[UINT16_NO_READING] = False
    lut = np.where(valid, z, np.float32(0.0)).astype(np.float32)
    lut.setflags(write=False)
    min_code = int(np.searchsorted(z64, min_depth_m, side="left"))
    max_code = int(np.searchsorted(z64, max_depth_m, side="left"))
    return lut, min_code, max_code


def _suggest_scale(median_code: float) -> float | None:
    """The common depth scale that puts a uint16 median reading closest to 2 m, if any is plausible."""
    lo, hi = PLAUSIBLE_MEDIAN_DEPTH_M
    plausible = [s for s in COMMON_DEPTH_SCALES if lo <= median_code / s <= hi]
    if not plausible:
        return None
    return min(plausible, key=lambda s: abs(math.log(median_code / s / 2.0)))


def check_depth_scale(depth: NDArray, depth_scale: float, *, what: str = "depth image") -> None:
    """Raise :class:`DepthScaleError` when the scale puts the scene at an implausible distance.

    Uses the median of the pixels that carry a reading (sampled on a 4x4 grid); ranges are not applied
    first, so a wrong scale cannot hide behind ``max_depth_m``.
    """
    sample = np.asarray(depth)[::4, ::4].ravel()
    if depth.dtype == np.uint16:
        sample = sample[(sample != 0) & (sample != UINT16_NO_READING)]
        if sample.size == 0:
            return
        median_code = float(np.median(sample))
        median_m = median_code / depth_scale
        lo, hi = PLAUSIBLE_MEDIAN_DEPTH_M
        if lo <= median_m <= hi:
            return
        suggested = _suggest_scale(median_code)
        hint = f"the data suggests depth_scale={suggested:g}" if suggested else "no common depth scale fits the data"
        raise DepthScaleError(
            f"{what}: depth_scale={depth_scale:g} units/m puts the median reading ({median_code:g} units) at "
            f"{median_m:.4g} m, outside the plausible {lo:g}..{hi:g} m for a depth camera; {hint}",
            depth_scale_used=depth_scale,
            depth_scale_suggested=suggested,
        )
    sample = sample[np.isfinite(sample) & (sample > 0)]
    if sample.size == 0:
        return
    median_m = float(np.median(sample))
    lo, hi = PLAUSIBLE_MEDIAN_DEPTH_M
    if lo <= median_m <= hi:
        return
    suggested = _suggest_scale(median_m)
    hint = (
        f"the values look like units of 1/{suggested:g} m: divide by {suggested:g} (or pass the raw uint16 "
        f"image with depth_scale={suggested:g})"
        if suggested
        else "no common unit fits the data"
    )
    raise DepthScaleError(
        f"{what}: float depth is read as metres, which puts the median reading at {median_m:.4g} m, outside "
        f"the plausible {lo:g}..{hi:g} m for a depth camera; {hint}",
        depth_scale_used=1.0,
        depth_scale_suggested=suggested,
    )


def backproject(
    depth: NDArray,
    intrinsics: PinholeIntrinsics,
    *,
    depth_scale: float = 1000.0,
    min_depth_m: float = DEFAULT_MIN_DEPTH_M,
    max_depth_m: float = DEFAULT_MAX_DEPTH_M,
    check_scale: bool = True,
    what: str = "depth image",
) -> BackprojectionResult:
    """Validate a depth image and back-project its valid pixels into the sensor frame.

    Args:
        depth: (height, width) uint16 (scaled by ``depth_scale``) or float32/float64 (metres).
        intrinsics: pinhole intrinsics; their size must match the image.
        depth_scale: units per metre for uint16 images (1000 for millimetres, 5000 for TUM); ignored
            for float images.
        min_depth_m, max_depth_m: valid range ``min_depth_m <= z < max_depth_m``.
        check_scale: raise :class:`DepthScaleError` when the scale puts the scene at an implausible
            distance (the classic millimetres-vs-metres mistake).
        what: how to name the image in error messages (e.g. the file and frame).

    Returns:
        :class:`BackprojectionResult` with ``.points`` (N, 3) float32 in row-major pixel order.
    """
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise DepthError(f"{what}: expected a single-channel (height, width) image, got shape {depth.shape}")
    intrinsics.check_image_shape(depth.shape, what)
    if not (min_depth_m >= 0 and max_depth_m > min_depth_m):
        raise DepthError(f"{what}: need 0 <= min_depth_m < max_depth_m, got {min_depth_m}, {max_depth_m}")
    if depth.dtype == np.uint16:
        return _backproject_uint16(depth, intrinsics, depth_scale, min_depth_m, max_depth_m, check_scale, what)
    if depth.dtype not in (np.float32, np.float64):
        raise DepthError(f"{what}: unsupported depth dtype {depth.dtype} (expected uint16, float32 or float64)")
    return _backproject_metres(depth, intrinsics, min_depth_m, max_depth_m, check_scale, what)


def _backproject_uint16(depth: NDArray, intrinsics: PinholeIntrinsics, depth_scale: float, min_depth_m: float,
                        max_depth_m: float, check_scale: bool, what: str) -> BackprojectionResult:
    """:func:`backproject` of a uint16 image in ``depth_scale`` units per metre: one compiled pass."""
    flat = depth.ravel()
    n_pixels = flat.size
    if not (math.isfinite(depth_scale) and depth_scale > 0):
        raise DepthScaleError(f"{what}: depth_scale must be positive, got {depth_scale}",
                              depth_scale_used=depth_scale, depth_scale_suggested=None)
    if check_scale:
        check_depth_scale(depth, depth_scale, what=what)
    rays = _rays(intrinsics)
    lut, min_code, max_code = _uint16_lut(float(depth_scale), float(min_depth_m), float(max_depth_m))
    # one compiled pass: validity, points in pixel order, counts per reason (same float32 products as
    # the float path, so the points are bit-identical)
    valid = np.empty(n_pixels, dtype=bool)
    scratch = np.empty((n_pixels, 3), dtype=np.float32)
    n_valid, n_zero, n_sentinel, n_below, n_beyond = backproject_uint16(
        flat, lut, rays.view(np.float32).reshape(-1, 3), min_code, max_code, valid, scratch)
    counts = {
        InvalidReason.ZERO.value: int(n_zero),
        InvalidReason.NO_READING_65535.value: int(n_sentinel),
        InvalidReason.BELOW_MIN.value: int(n_below),
        InvalidReason.BEYOND_MAX.value: int(n_beyond),
    }
    # shrink the buffer to the valid points in place (realloc: no copy of the points), so that the result
    # owns exactly its points and a Frame can take them without copying (frame.adopt_readonly)
    scratch.resize((int(n_valid), 3), refcheck=False)
    result = BackprojectionResult(scratch, valid, counts, n_pixels, float(depth_scale))
    logger.debug("%s: %d valid pixels, invalid fraction %.3f %s", what, result.n_valid, result.invalid_fraction, counts)
    return result


def _backproject_metres(depth: NDArray, intrinsics: PinholeIntrinsics, min_depth_m: float, max_depth_m: float,
                        check_scale: bool, what: str) -> BackprojectionResult:
    """:func:`backproject` of a float image in metres (classified in the image's own precision; only the kept depths
    become float32)."""
    flat = depth.ravel()
    n_pixels = flat.size
    if check_scale:
        check_depth_scale(depth, 1.0, what=what)
    rays = _rays(intrinsics)
    valid = (flat >= min_depth_m) & (flat < max_depth_m)
    if min_depth_m == 0:
        valid &= flat != 0
    finite = np.isfinite(flat)
    n_nan = int(np.count_nonzero(np.isnan(flat)))
    counts = {
        InvalidReason.ZERO.value: int(np.count_nonzero(flat == 0)),
        InvalidReason.NAN.value: n_nan,
        InvalidReason.INF.value: n_pixels - n_nan - int(np.count_nonzero(finite)),
        InvalidReason.NEGATIVE.value: int(np.count_nonzero(finite & (flat < 0))),
        InvalidReason.BELOW_MIN.value: int(np.count_nonzero((flat > 0) & (flat < min_depth_m))),
        InvalidReason.BEYOND_MAX.value: int(np.count_nonzero(finite & (flat >= max_depth_m))),
    }
    zv = flat[valid].astype(np.float32)
    # gather the valid rays (x, y, 1) in one compress, then scale by depth: (x z, y z, z)
    points = rays[valid].view(np.float32).reshape(-1, 3)
    np.multiply(points[:, 0], zv, out=points[:, 0])
    np.multiply(points[:, 1], zv, out=points[:, 1])
    points[:, 2] = zv
    result = BackprojectionResult(points, valid, counts, n_pixels, None)
    if sum(counts.values()) + result.n_valid != n_pixels:  # pragma: no cover - internal consistency guard
        raise DepthError(f"{what}: invalid-pixel accounting does not add up ({counts}, valid={result.n_valid})")
    logger.debug("%s: %d valid pixels, invalid fraction %.3f %s", what, result.n_valid, result.invalid_fraction, counts)
    return result


def depth_frame(
    depth: NDArray,
    intrinsics: PinholeIntrinsics,
    *,
    frame_id: int,
    stamp_ns: int,
    pose: PoseEstimate,
    sensor_name: str = "depth_camera",
    sensor_frame: str = "camera_depth_optical_frame",
    T_base_sensor: NDArray[np.float64] | None = None,
    depth_scale: float = 1000.0,
    min_depth_m: float = DEFAULT_MIN_DEPTH_M,
    max_depth_m: float = DEFAULT_MAX_DEPTH_M,
    provenance: Provenance | None = None,
    monitor: InvalidFractionMonitor | None = None,
    color_rgb: NDArray[np.uint8] | None = None,
    pixel_stride: int = 1,
    base_frame: str = "base_link",
    flags: tuple[str, ...] = (),
    check_scale: bool = True,
) -> Frame:
    """Validate and back-project one depth image into a :class:`Frame` (points in the sensor frame).

    ``monitor`` (one per sensor stream) flags frames whose invalid fraction jumps above recent history.
    ``color_rgb`` is an optional (height, width, 3) image registered to the depth image.
    ``pixel_stride`` > 1 keeps every ``pixel_stride``-th pixel in both directions (a cheap, exact
    pre-downsampling: the frame carries the matching subsampled intrinsics, and its quality counts refer
    to the sampled pixels). ``flags`` (e.g. a source's notes on the message) follow the monitor's flag in the
    frame's quality flags; ``base_frame`` names the frame ``T_base_sensor`` maps into. ``check_scale=False`` skips
    :func:`backproject`'s plausibility check of the depth scale (``depth.check_scale = false``).
    """
    if pixel_stride != 1:
        intrinsics.check_image_shape(np.shape(depth), f"frame {frame_id}")
        intrinsics = intrinsics.subsampled(pixel_stride)  # first: it names a bad stride (IntrinsicsError)
        depth = np.ascontiguousarray(np.asarray(depth)[::pixel_stride, ::pixel_stride])
        if color_rgb is not None:
            color_rgb = np.ascontiguousarray(np.asarray(color_rgb)[::pixel_stride, ::pixel_stride])
    what = f"frame {frame_id}" + (f" ({provenance.source_uri})" if provenance else "")
    result = backproject(depth, intrinsics, depth_scale=depth_scale, min_depth_m=min_depth_m,
                         max_depth_m=max_depth_m, check_scale=check_scale, what=what)
    if monitor is not None:
        reason = monitor.update(result.invalid_fraction, what)
        flags = ((reason,) if reason else ()) + tuple(flags)
    attributes = PointAttributes()
    if color_rgb is not None:
        color = np.asarray(color_rgb)
        if color.shape != (intrinsics.height, intrinsics.width, 3):
            raise DepthError(f"{what}: colour image shape {color.shape} does not match the depth image")
        attributes = PointAttributes(color_rgb=color.reshape(-1, 3)[result.pixel_index])
    return Frame(
        frame_id=frame_id,
        stamp_ns=stamp_ns,
        sensor_name=sensor_name,
        sensor_kind=SensorKind.DEPTH_CAMERA,
        points_sensor=adopt_readonly(result.points),  # made here, held by no one else: shared, not copied
        pose=pose,
        T_base_sensor=np.eye(4) if T_base_sensor is None else T_base_sensor,
        attributes=attributes,
        intrinsics=intrinsics,
        depth_scale=result.depth_scale,
        quality=result.quality(tuple(flags)),
        provenance=provenance,
        sensor_frame=sensor_frame,
        base_frame=base_frame,
    )


class InvalidFractionMonitor:
    """Flags frames whose invalid-pixel fraction jumps far above the recent history of the same sensor.

    A sudden jump usually means a material the sensor cannot see (glass, black or shiny surfaces) or a
    sensor fault. The threshold is ``median + max(min_jump, k * 1.4826 * MAD)`` over the last ``window``
    frames; nothing is flagged until ``min_history`` frames have been seen.
    """

    def __init__(self, window: int = 30, min_history: int = 5, min_jump: float = 0.15, k_mad: float = 5.0):
        self.window = window
        self.min_history = min_history
        self.min_jump = min_jump
        self.k_mad = k_mad
        self._history: deque[float] = deque(maxlen=window)

    def update(self, invalid_fraction: float, what: str = "frame") -> str | None:
        """Record a frame's invalid fraction; return a flag reason if it jumped, else ``None``."""
        reason = None
        if len(self._history) >= self.min_history:
            hist = np.fromiter(self._history, dtype=np.float64)
            median = float(np.median(hist))
            mad = float(np.median(np.abs(hist - median)))
            threshold = median + max(self.min_jump, self.k_mad * 1.4826 * mad)
            if invalid_fraction > threshold:
                reason = (
                    f"invalid_fraction_jump: {invalid_fraction:.3f} invalid vs recent median {median:.3f} "
                    f"(threshold {threshold:.3f})"
                )
                logger.warning("%s: %s", what, reason)
        logger.info("%s: invalid pixel fraction %.3f", what, invalid_fraction)
        self._history.append(invalid_fraction)
        return reason
