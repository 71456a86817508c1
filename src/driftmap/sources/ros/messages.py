"""Sensor messages as arrays: ``sensor_msgs/PointCloud2`` (any field layout; points, attributes and rejection
counts), depth ``sensor_msgs/Image`` and ``sensor_msgs/CameraInfo`` (pinhole intrinsics), every size a message
states checked against its bytes before anything is built (:class:`SourceError` naming the message)."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from driftmap.errors import GeometryError, SourceError
from driftmap.frame import PinholeIntrinsics, PointAttributes
from driftmap.preprocess.depth import InvalidReason
from driftmap.sources.depth_folder import checked_intrinsics
from driftmap.sources.point_fields import (
    POINT_TIME_FIELDS,
    PointTimeReference,
    checked_normals,
    far_points,
    point_time_offsets_ns,
)
from driftmap.sources.ros.msgtypes import DEPTH_ENCODINGS, POINTFIELD_TYPES, first_field

logger = logging.getLogger(__name__)


def raw_bytes(data: Any) -> Any:
    """A ``uint8[]`` field (bytes from mcap_ros2, a numpy array from rosbags) as a buffer numpy can wrap."""
    if isinstance(data, np.ndarray):
        return np.ascontiguousarray(data, dtype=np.uint8)
    return data


def pointcloud2_array(msg: Any, what: str = "PointCloud2") -> NDArray[np.void]:
    """All fields of a ``sensor_msgs/PointCloud2`` as a structured array of ``height * width`` points
    (row-major, row padding removed, fields in the message's byte order; nothing is filtered).

    Every size the message states (``width``, ``height``, ``point_step``, ``row_step``, the fields' offsets and
    counts) is checked against the bytes of ``data`` before anything is built: :class:`SourceError` naming
    ``what`` and the field otherwise."""
    data = raw_bytes(msg.data)
    width, height, point_step, row_step = checked_cloud_layout(msg, len(data), what)
    dtype = cloud_dtype(msg, point_step, what)
    n = width * height
    if n == 0:
        return np.empty(0, dtype=dtype)
    if row_step == width * point_step:
        return np.frombuffer(data, dtype=dtype, count=n)
    rows = np.ndarray((height, width), dtype=dtype, buffer=data, strides=(row_step, point_step))
    return rows.reshape(-1)


def checked_cloud_layout(msg: Any, n_bytes: int, what: str) -> tuple[int, int, int, int]:
    """``(width, height, point_step, row_step)`` of a PointCloud2, checked against its ``n_bytes`` of data."""
    point_step = int(msg.point_step)
    width, height = int(msg.width), int(msg.height)
    row_step = int(msg.row_step)
    if point_step <= 0:
        raise SourceError(f"{what}: point_step is {point_step}")
    if width * height == 0:
        if n_bytes:
            raise SourceError(f"{what}: {width}x{height} points, but data has {n_bytes} bytes: width / height do not "
                              f"describe the data")
        if point_step >= 2**31:
            raise SourceError(f"{what}: point_step is {point_step}")
        return width, height, point_step, row_step
    if row_step < width * point_step:
        raise SourceError(f"{what}: row_step {row_step} < width {width} * point_step {point_step}")
    needed = row_step * (height - 1) + width * point_step
    if n_bytes < needed:
        raise SourceError(
            f"{what}: data has {n_bytes} bytes, {width}x{height} points with point_step {point_step} and row_step "
            f"{row_step} need {needed}"
        )
    if n_bytes > row_step * height:
        raise SourceError(
            f"{what}: data has {n_bytes} bytes, more than the height {height} * row_step {row_step} = "
            f"{row_step * height} of {width}x{height} points: width / height / row_step do not describe the data"
        )
    return width, height, point_step, row_step


def cloud_dtype(msg: Any, point_step: int, what: str) -> np.dtype:
    """The structured dtype of one point (``point_step`` bytes), every field checked to fit in it."""
    endian = ">" if msg.is_bigendian else "<"
    names, formats, offsets = [], [], []
    for f in msg.fields:
        name = str(f.name)
        if not name or name in names:
            if name:
                logger.debug("%s: duplicate field %r ignored", what, name)
            continue
        code = POINTFIELD_TYPES.get(int(f.datatype))
        if code is None:
            raise SourceError(f"{what}: field {name!r} has unknown PointField datatype {f.datatype}")
        count = max(int(f.count), 1)
        item_bytes = np.dtype(code).itemsize * count
        if int(f.offset) < 0 or int(f.offset) + item_bytes > point_step:  # checked before a dtype of that size is made
            raise SourceError(
                f"{what}: field {name!r} (offset {f.offset}, {item_bytes} bytes) does not fit in "
                f"point_step {point_step}"
            )
        names.append(name)
        formats.append(np.dtype(endian + code) if count == 1 else np.dtype((endian + code, (count,))))
        offsets.append(int(f.offset))
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step})


#: PointCloud2 fields read as one value per point
SCALAR_FIELDS = frozenset(("x", "y", "z", "intensity", "rgb", "rgba", "r", "g", "b", "normal_x", "normal_y",
                            "normal_z", "ring", *POINT_TIME_FIELDS))


@dataclass(frozen=True)
class CloudPoints:
    """The usable content of one PointCloud2: finite points, their attributes and the rejection counts."""

    points: NDArray[np.float32]
    attributes: PointAttributes
    n_measurements: int
    invalid_counts: dict[str, int]
    ring: NDArray[np.uint16] | None
    """``ring`` field of the kept points, if present (:class:`PointAttributes` has no slot for it)."""
    time_field: str | None


def pointcloud2_points(
    msg: Any, stamp_ns: int, *, what: str = "PointCloud2", point_time: PointTimeReference = PointTimeReference.AUTO,
    warned: set[str] | None = None,
) -> CloudPoints:
    """Points (float32, sensor frame) and attributes of a PointCloud2, its fields read in the byte order
    ``is_bigendian`` states (big-endian data is byte-swapped); points with a NaN or inf coordinate, or farther than
    :data:`~driftmap.sources.point_fields.MAX_POINT_RANGE_M` from the sensor, are dropped and counted (whatever
    ``is_dense`` claims; :func:`~driftmap.sources.point_fields.far_points`: a cloud most of whose points are that far
    is refused, naming the message). ``warned``: the reading source's set of warnings given once
    (:func:`driftmap.sources.point_fields.checked_normals`)."""
    arr = pointcloud2_array(msg, what)
    names = arr.dtype.names or ()
    missing = [c for c in ("x", "y", "z") if c not in names]
    if missing:
        raise SourceError(
            f"{what}: PointCloud2 has no {'/'.join(missing)} field (fields present: {', '.join(names) or 'none'})"
        )
    n = len(arr)
    for c in names:  # the fields read below hold one value per point
        if c in SCALAR_FIELDS and arr.dtype[c].shape:
            raise SourceError(f"{what}: field {c!r} has count {arr.dtype[c].shape[0]}; expected 1 value per point")
    for c in "xyz":
        if arr.dtype[c].kind != "f" and arr.dtype[c].kind not in "iu":
            raise SourceError(f"{what}: field {c!r} has unsupported type {arr.dtype[c]}")
    xyz = np.empty((n, 3), dtype=np.float32)
    xyz[:, 0] = arr["x"]
    xyz[:, 1] = arr["y"]
    xyz[:, 2] = arr["z"]
    finite = np.isfinite(xyz).all(axis=1)
    n_valid = int(np.count_nonzero(finite))
    counts: dict[str, int] = {}
    keep: NDArray[np.bool_] | None = None
    if n_valid < n:
        n_nan = int(np.count_nonzero(np.isnan(xyz).any(axis=1)))
        counts = {InvalidReason.NAN.value: n_nan, InvalidReason.INF.value: n - n_valid - n_nan}
        keep = finite
    hint = (" (the message says is_bigendian: true; is its data little-endian?)" if msg.is_bigendian else
            " (is the data big-endian while is_bigendian says false, or the fields' offsets or types wrong?)")
    far = far_points(xyz, what, hint=hint)
    if far is not None:
        counts[InvalidReason.BEYOND_MAX.value] = int(np.count_nonzero(far))
        keep = finite & ~far
    at_origin = finite & ~xyz.any(axis=1)  # exactly (0, 0, 0): no return (organized clouds fill their gaps so)
    if at_origin.any():
        counts[InvalidReason.ZERO.value] = int(np.count_nonzero(at_origin))
        keep = (finite if keep is None else keep) & ~at_origin
    if keep is not None:
        xyz = xyz[keep]

    def kept(values: NDArray) -> NDArray:
        return values if keep is None else values[keep]

    intensity = kept(arr["intensity"]).astype(np.float32) if "intensity" in names else None
    color = None
    if "rgb" in names or "rgba" in names:
        packed = kept(arr["rgb" if "rgb" in names else "rgba"])
        packed = (
            np.ascontiguousarray(packed).view(np.uint32) if packed.dtype.itemsize == 4 else packed.astype(np.uint32)
        )
        color = np.stack([(packed >> 16) & 255, (packed >> 8) & 255, packed & 255], axis=1).astype(np.uint8)
    elif all(c in names for c in ("r", "g", "b")):
        color = np.stack([kept(arr[c]) for c in ("r", "g", "b")], axis=1).astype(np.uint8)
    normals = None
    if all(c in names for c in ("normal_x", "normal_y", "normal_z")):
        normals = checked_normals(np.stack([kept(arr[c]) for c in ("normal_x", "normal_y", "normal_z")], axis=1), what,
                                  warned)
    time_field = next((f for f in POINT_TIME_FIELDS if f in names), None)
    offsets = None
    if time_field is not None:
        offsets = point_time_offsets_ns(kept(arr[time_field]), stamp_ns, time_field, what, point_time)
    ring = kept(arr["ring"]).astype(np.uint16) if "ring" in names else None
    attributes = PointAttributes(intensity=intensity, color_rgb=color, normal_sensor=normals, time_offset_ns=offsets)
    return CloudPoints(xyz, attributes, n, counts, ring, time_field)


@dataclass(frozen=True)
class RawMeasurement:
    """One decoded sensor message before back-projection or pose lookup (:meth:`RosLogSource.iter_raw`)."""

    message_index: int
    stamp_ns: int
    log_time_ns: int
    sensor_frame: str
    depth: NDArray | None
    """(height, width) uint16 or float32 depth image (native byte order), for Image topics."""
    depth_scale: float | None
    cloud: NDArray[np.void] | None
    """Structured array of every PointCloud2 field, for PointCloud2 topics."""
    cloud_msg: Any
    intrinsics: PinholeIntrinsics | None
    flags: tuple[str, ...]
    size_bytes: int


def depth_image_array(msg: Any, what: str = "Image") -> tuple[NDArray, float | None]:
    """A depth ``sensor_msgs/Image`` as a (height, width) array in native byte order, and its depth scale
    (1000 for ``16UC1``/``mono16`` millimetres, ``None`` for ``32FC1`` metres). Row padding is allowed."""
    encoding = str(msg.encoding)
    if encoding not in DEPTH_ENCODINGS:
        raise SourceError(
            f"{what}: image encoding {encoding!r} is not a depth encoding (expected {', '.join(DEPTH_ENCODINGS)})"
        )
    dtype, scale = DEPTH_ENCODINGS[encoding]
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    item = np.dtype(dtype).itemsize
    if width <= 0 or height <= 0:
        raise SourceError(f"{what}: image is {width}x{height}")
    if step < width * item:
        raise SourceError(f"{what}: step {step} < width {width} * {item} bytes")
    data = raw_bytes(msg.data)
    needed = step * (height - 1) + width * item
    if len(data) < needed:
        raise SourceError(
            f"{what}: data has {len(data)} bytes, a {width}x{height} {encoding} image with step {step} needs {needed}"
        )
    if len(data) > step * height:
        raise SourceError(
            f"{what}: data has {len(data)} bytes, more than the height {height} * step {step} = {step * height} of a "
            f"{width}x{height} {encoding} image: width / height / step do not describe the data"
        )
    wire = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")
    image = np.ndarray((height, width), dtype=wire, buffer=data, strides=(step, item))
    if not wire.isnative or step != width * item:
        image = np.ascontiguousarray(image, dtype=np.dtype(dtype))
    return image, scale


def camera_info_intrinsics(
    msg: Any, *, what: str = "CameraInfo", ignore_distortion: bool = False
) -> tuple[PinholeIntrinsics, tuple[str, ...]]:
    """``PinholeIntrinsics`` of a ``sensor_msgs/CameraInfo`` and the quality flags to attach.

    Non-zero distortion coefficients raise :class:`SourceError` (depth back-projection here is pinhole)
    unless ``ignore_distortion``, which flags every frame instead. Binning other than 1 and skew are refused.
    """
    K = np.asarray(first_field(msg, "k", "K"), dtype=np.float64).reshape(-1)
    D = np.asarray(first_field(msg, "d", "D"), dtype=np.float64).reshape(-1)
    if K.size != 9:
        raise SourceError(f"{what}: K has {K.size} entries, expected 9")
    fx, skew, cx, _, fy, cy = K[0], K[1], K[2], K[3], K[4], K[5]
    if fx <= 0 or fy <= 0:
        raise SourceError(f"{what}: camera is not calibrated (K = {K.tolist()})")
    if abs(skew) > 1e-9 * abs(fx):
        raise SourceError(f"{what}: K has skew {skew} (pinhole intrinsics without skew are supported)")
    for name in ("binning_x", "binning_y"):
        value = int(getattr(msg, name, 0) or 0)
        if value > 1:
            raise SourceError(f"{what}: {name}={value} is not supported")
    flags: tuple[str, ...] = ()
    if D.size and np.any(D != 0):
        model = getattr(msg, "distortion_model", "")
        if not ignore_distortion:
            raise SourceError(
                f"{what}: distortion {model!r} D={D.tolist()} is not zero; depth is back-projected with a pinhole "
                f"model (pass ignore_distortion=True to accept and flag the frames)"
            )
        flags = (f"distortion_ignored: {model} D={D.tolist()}",)
    try:
        intrinsics = PinholeIntrinsics(fx=fx, fy=fy, cx=cx, cy=cy, width=int(msg.width), height=int(msg.height))
    except GeometryError as exc:
        raise SourceError(f"{what}: {exc}") from exc
    return checked_intrinsics(intrinsics, what), flags
