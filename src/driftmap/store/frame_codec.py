"""How a frame is stored: its point payload (``x y z`` float32 then the attributes, interleaved), its metadata
record (``driftmap.FrameInfo``, JSON) and the checks on both: every value of a frame before it is written, and
every stored record a scan relies on."""

from __future__ import annotations

from typing import Any

import numpy as np
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from numpy.typing import NDArray

from driftmap.errors import FrameRejectedError
from driftmap.frame import (
    Frame,
    FrameQuality,
    PinholeIntrinsics,
    PointAttributes,
    PoseEstimate,
    PoseSource,
    Provenance,
    SensorKind,
    TrackingHealth,
)

WORLD_FRAME = "world"
UINT64_MAX = 2**64 - 1
INT64_MAX = 2**63 - 1

_NUMERIC = PackedElementField.NumericType
#: point attribute -> (component field names, numeric type, numpy dtype of one component)
_ATTRIBUTE_FIELDS: dict[str, tuple[tuple[str, ...], int, Any]] = {
    "intensity": (("intensity",), _NUMERIC.FLOAT32, np.float32),
    "color_rgb": (("red", "green", "blue", "alpha"), _NUMERIC.UINT8, np.uint8),
    "normal_sensor": (("normal_x", "normal_y", "normal_z"), _NUMERIC.FLOAT32, np.float32),
    "time_offset_ns": (("time_offset_ns",), _NUMERIC.FLOAT64, np.float64),
}


def point_layout(attributes: PointAttributes) -> tuple[int, list[dict[str, Any]]]:
    """Interleaved layout: ``x y z`` float32, then each present attribute; returns (stride, fields)."""
    fields = [{"name": n, "offset": 4 * i, "type": int(_NUMERIC.FLOAT32)} for i, n in enumerate("xyz")]
    offset = 12
    for attr in attributes.names():
        names, numeric, dtype = _ATTRIBUTE_FIELDS[attr]
        size = np.dtype(dtype).itemsize
        for name in names:
            fields.append({"name": name, "offset": offset, "type": int(numeric)})
            offset += size
    return offset, fields


def pack_points(points: NDArray[np.float32], attributes: PointAttributes) -> tuple[bytes, int, list[dict[str, Any]]]:
    """Interleave points and attributes into one little-endian payload."""
    stride, fields = point_layout(attributes)
    n = len(points)
    if stride == 12:
        return np.ascontiguousarray(points, dtype="<f4").tobytes(), stride, fields
    buf = np.zeros((n, stride), dtype=np.uint8)
    buf[:, :12] = np.ascontiguousarray(points, dtype="<f4").view(np.uint8).reshape(n, 12)
    offset = 12
    for attr in attributes.names():
        names, _, dtype = _ATTRIBUTE_FIELDS[attr]
        value = getattr(attributes, attr)
        if attr == "color_rgb":
            value = np.concatenate([value, np.full((n, 1), 255, np.uint8)], axis=1)
        comp = np.ascontiguousarray(value, dtype=np.dtype(dtype).newbyteorder("<")).reshape(n, len(names))
        width = comp.itemsize * len(names)
        buf[:, offset : offset + width] = comp.view(np.uint8).reshape(n, width)
        offset += width
    return buf.tobytes(), stride, fields


def unpack_attributes(payload: NDArray[np.uint8], n: int, stride: int, fields: list[dict[str, Any]]) -> PointAttributes:
    """Copy the attribute columns out of an interleaved payload (``payload`` is ``n * stride`` bytes)."""
    rows = payload.reshape(n, stride) if n else payload.reshape(0, stride)
    by_name = {f["name"]: f for f in fields}
    values: dict[str, NDArray] = {}
    for attr, (names, numeric, dtype) in _ATTRIBUTE_FIELDS.items():
        if names[0] not in by_name:
            continue
        start = by_name[names[0]]["offset"]
        width = np.dtype(dtype).itemsize * len(names)
        comp = np.ascontiguousarray(rows[:, start : start + width]).view(np.dtype(dtype).newbyteorder("<"))
        comp = comp.reshape(n, len(names)).astype(dtype)
        if attr == "color_rgb":
            values[attr] = comp[:, :3]
        elif attr == "time_offset_ns":
            values[attr] = comp[:, 0].astype(np.int64)
        elif len(names) == 1:
            values[attr] = comp[:, 0]
        else:
            values[attr] = comp
    return PointAttributes(**values)


def _matrix(T: NDArray[np.float64] | None) -> list[float] | None:
    return None if T is None else [float(v) for v in np.asarray(T, dtype=np.float64).ravel()]


def frame_info(frame: Frame, stride: int, fields: list[dict[str, Any]], payload_crc32: int) -> dict[str, Any]:
    """JSON-ready metadata of a frame (everything except the point payload)."""
    q = frame.quality
    return {
        "frame_id": frame.frame_id,
        "stamp_ns": frame.stamp_ns,
        "sensor_name": frame.sensor_name,
        "sensor_kind": frame.sensor_kind.value,
        "sensor_frame": frame.sensor_frame,
        "base_frame": frame.base_frame,
        "T_base_sensor": _matrix(frame.T_base_sensor),
        "pose": {
            "T_world_sensor": _matrix(frame.pose.T_world_sensor),
            "revision": frame.pose.revision,
            "source": frame.pose.source.value,
            "covariance_6x6": _matrix(frame.pose.covariance_6x6),
            "world_frame": frame.pose.world_frame,
        },
        "intrinsics": None if frame.intrinsics is None else frame.intrinsics.to_dict(),
        "depth_scale": frame.depth_scale,
        "quality": None
        if q is None
        else {"n_measurements": q.n_measurements, "n_valid": q.n_valid, "invalid_counts": dict(q.invalid_counts), "flags": list(q.flags)},
        "provenance": None if frame.provenance is None else {"source_uri": frame.provenance.source_uri, "index": frame.provenance.index},
        "points": {"n_points": frame.n_points, "point_stride": stride, "fields": fields, "crc32": payload_crc32},
        "tracking": None if frame.tracking is None else frame.tracking.to_dict(),
    }


def frame_from_info(info: dict[str, Any], points: NDArray[np.float32], attributes: PointAttributes) -> Frame:
    """Rebuild a :class:`Frame` from its stored metadata and points."""
    pose = info["pose"]
    cov = pose.get("covariance_6x6")
    q = info.get("quality")
    prov = info.get("provenance")
    intr = info.get("intrinsics")
    return Frame(
        frame_id=info["frame_id"],
        stamp_ns=info["stamp_ns"],
        sensor_name=info["sensor_name"],
        sensor_kind=SensorKind(info["sensor_kind"]),
        points_sensor=points,
        pose=PoseEstimate(
            np.asarray(pose["T_world_sensor"]).reshape(4, 4),
            revision=pose["revision"],
            source=PoseSource(pose["source"]),
            covariance_6x6=None if cov is None else np.asarray(cov).reshape(6, 6),
            world_frame=pose.get("world_frame", WORLD_FRAME),
        ),
        T_base_sensor=np.asarray(info["T_base_sensor"]).reshape(4, 4),
        attributes=attributes,
        intrinsics=None if intr is None else PinholeIntrinsics(**intr),
        depth_scale=info.get("depth_scale"),
        quality=None if q is None else FrameQuality(q["n_measurements"], q["n_valid"], q["invalid_counts"], tuple(q["flags"])),
        provenance=None if prov is None else Provenance(prov["source_uri"], prov["index"]),
        sensor_frame=info["sensor_frame"],
        base_frame=info["base_frame"],
        tracking=None if info.get("tracking") is None else TrackingHealth.from_dict(info["tracking"]),
    )


def cloud_frame_name(sensor_frame: str, frame_id: int) -> str:
    """The coordinate-frame name a stored frame's cloud uses in Foxglove: one per frame."""
    return f"{sensor_frame}@{frame_id:06d}"


def check_log_time(value: object, what: str, *, frame_id: int | None = None, field_name: str = "stamp_ns") -> int:
    """``value`` as an MCAP log time: an integer number of nanoseconds in ``0 .. 2**63 - 1`` (MCAP log times are
    unsigned 64-bit; the ledger keeps them as signed 64-bit). Anything else is a
    :class:`~driftmap.errors.FrameRejectedError` naming ``what`` (nothing has been written)."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise FrameRejectedError(f"{what}: {field_name} must be an integer number of nanoseconds, got {value!r}",
                                 frame_id=frame_id, field=field_name)
    out = int(value)
    if not 0 <= out <= INT64_MAX:
        why = ("negative: MCAP log times are unsigned (a data set whose times start before 0 needs its stamps "
               "shifted)") if out < 0 else "beyond 2**63 - 1 ns"
        raise FrameRejectedError(f"{what}: {field_name} = {out} ns is {why}", frame_id=frame_id, field=field_name)
    return out


def _finite_matrix(T: object, what: str, frame_id: int | None, field_name: str) -> None:
    arr = np.asarray(T, dtype=np.float64) if T is not None else None
    if arr is None or arr.shape != (4, 4) or not np.all(np.isfinite(arr)):
        raise FrameRejectedError(f"{what}: {field_name} must be a finite 4x4 matrix", frame_id=frame_id, field=field_name)


def check_frame_for_store(frame: Frame, what: str) -> None:
    """Every value of ``frame`` the store writes, checked before anything is written (a
    :class:`~driftmap.errors.FrameRejectedError` naming the frame and the field):

    - ``frame_id``: an integer that fits int64; ``stamp_ns``: see :func:`check_log_time` (stamps need not increase);
    - ``pose.T_world_sensor``, ``T_base_sensor`` and the covariance: finite (``Frame`` also checks that the poses
      are rigid);
    - ``points_sensor``: float32 (N, 3) without an infinite coordinate. NaN coordinates are accepted: they mark
      points without a measurement, which the map leaves out (docs/store.md);
    - attributes: the dtypes and lengths ``Frame`` guarantees.
    """
    if not isinstance(frame, Frame):
        raise FrameRejectedError(f"{what}: expected a Frame, got {type(frame).__name__}", frame_id=None, field="frame")
    fid = frame.frame_id
    if isinstance(fid, bool) or not isinstance(fid, (int, np.integer)) or not -(2**63) <= int(fid) <= INT64_MAX:
        raise FrameRejectedError(f"{what}: frame_id must be a 64-bit integer, got {fid!r}", frame_id=None, field="frame_id")
    fid = int(fid)
    where = f"{what}: frame {fid}"
    check_log_time(frame.stamp_ns, where, frame_id=fid)
    if not isinstance(frame.pose, PoseEstimate):
        raise FrameRejectedError(f"{where}: pose must be a PoseEstimate", frame_id=fid, field="pose")
    _finite_matrix(frame.pose.T_world_sensor, where, fid, "pose.T_world_sensor")
    _finite_matrix(frame.T_base_sensor, where, fid, "T_base_sensor")
    cov = frame.pose.covariance_6x6
    if cov is not None and not (np.shape(cov) == (6, 6) and np.all(np.isfinite(cov))):
        raise FrameRejectedError(f"{where}: pose.covariance_6x6 must be a finite 6x6 matrix", frame_id=fid,
                                 field="pose.covariance_6x6")
    pts = frame.points_sensor
    if not isinstance(pts, np.ndarray) or pts.dtype != np.float32 or pts.ndim != 2 or pts.shape[1] != 3:
        raise FrameRejectedError(f"{where}: points_sensor must be a float32 (N, 3) array", frame_id=fid,
                                 field="points_sensor")
    if pts.size and np.isinf(pts).any():
        row = int(np.flatnonzero(np.isinf(pts).any(axis=1))[0])
        raise FrameRejectedError(
            f"{where}: points_sensor[{row}] = {pts[row].tolist()} has an infinite coordinate ({int(np.isinf(pts).any(axis=1).sum())} "
            f"such points); drop them before storing (NaN marks a point without a measurement, inf is refused)",
            frame_id=fid, field="points_sensor")
    for name in frame.attributes.names():
        value = getattr(frame.attributes, name)
        if not isinstance(value, np.ndarray) or len(value) != len(pts):
            raise FrameRejectedError(f"{where}: attributes.{name} must hold one value per point", frame_id=fid,
                                     field=f"attributes.{name}")


# ---- checks of stored metadata (a scan runs them on every record it reads) ------------------------------------

_FIELD_SIZES = {_NUMERIC.FLOAT32: 4, _NUMERIC.FLOAT64: 8, _NUMERIC.UINT8: 1}
_SENSOR_KINDS = frozenset(k.value for k in SensorKind)
_POSE_SOURCES = frozenset(p.value for p in PoseSource)


def is_int(value: object) -> bool:
    """An ``int`` that is not a bool (a JSON integer)."""
    return isinstance(value, int) and not isinstance(value, bool)


def _numbers(value: object, n: int) -> bool:
    """A list of ``n`` finite JSON numbers."""
    return (isinstance(value, list) and len(value) == n
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) for v in value))


def check_frame_info(info: object) -> str | None:
    """What is wrong with a stored frame's metadata as far as the store relies on it when opening (ids, stamp,
    revision-0 pose, point layout), or None. Cheap: run for every frame of every scanned segment. (The remaining
    fields are checked when a frame is read, :meth:`driftmap.store.frame_store.FrameStore.frame`, and by recovery.)"""
    if not isinstance(info, dict):
        return f"frame metadata is a JSON {type(info).__name__}, not an object"
    fid = info.get("frame_id")
    if not is_int(fid) or not -(2**63) <= fid <= INT64_MAX:
        return f"frame_id {fid!r} is not a 64-bit integer"
    stamp = info.get("stamp_ns")
    if not is_int(stamp) or not 0 <= stamp <= INT64_MAX:
        return f"frame {fid}: stamp_ns {stamp!r} is not a non-negative 64-bit integer"
    for key in ("sensor_name", "sensor_frame", "base_frame"):
        if not isinstance(info.get(key), str):
            return f"frame {fid}: {key} is not a string"
    if info.get("sensor_kind") not in _SENSOR_KINDS:
        return f"frame {fid}: unknown sensor_kind {info.get('sensor_kind')!r}"
    if not _numbers(info.get("T_base_sensor"), 16):
        return f"frame {fid}: T_base_sensor is not 16 finite numbers"
    pose = info.get("pose")
    if not isinstance(pose, dict) or not _numbers(pose.get("T_world_sensor"), 16):
        return f"frame {fid}: pose.T_world_sensor is not 16 finite numbers"
    if pose.get("source") not in _POSE_SOURCES or not is_int(pose.get("revision")) or pose["revision"] < 0:
        return f"frame {fid}: pose.source / pose.revision malformed"
    if not isinstance(pose.get("world_frame", WORLD_FRAME), str):
        return f"frame {fid}: pose.world_frame is not a string"
    cov = pose.get("covariance_6x6")
    if cov is not None and not _numbers(cov, 36):
        return f"frame {fid}: pose.covariance_6x6 is not 36 finite numbers"
    points = info.get("points")
    if not isinstance(points, dict):
        return f"frame {fid}: no point layout"
    n, stride, fields = points.get("n_points"), points.get("point_stride"), points.get("fields")
    if not is_int(n) or n < 0 or not is_int(stride) or not 12 <= stride <= 1 << 16 or not isinstance(fields, list):
        return f"frame {fid}: point layout malformed (n_points {n!r}, point_stride {stride!r})"
    names: list[str] = []
    for f in fields:
        if (not isinstance(f, dict) or not isinstance(f.get("name"), str) or not is_int(f.get("offset"))
                or f.get("type") not in _FIELD_SIZES or not 0 <= f["offset"] <= stride - _FIELD_SIZES[f["type"]]):
            return f"frame {fid}: point field {f!r} malformed"
        names.append(f["name"])
    if fields[:3] != [{"name": c, "offset": 4 * i, "type": int(_NUMERIC.FLOAT32)} for i, c in enumerate("xyz")]:
        return f"frame {fid}: the first point fields are not x y z float32"
    if len(set(names)) != len(names):
        return f"frame {fid}: point field names repeat"
    for attr, (comp, numeric, _) in _ATTRIBUTE_FIELDS.items():
        present = [c in names for c in comp]
        if any(present) and not all(present):
            return f"frame {fid}: attribute {attr} is missing some of its fields {comp}"
        if all(present):
            by_name = {f["name"]: f for f in fields}
            first = by_name[comp[0]]["offset"]
            size = _FIELD_SIZES[numeric]
            if any(by_name[c]["type"] != int(numeric) or by_name[c]["offset"] != first + k * size for k, c in enumerate(comp)):
                return f"frame {fid}: attribute {attr} has an unexpected layout"
    if not is_int(points.get("crc32")):
        return f"frame {fid}: points.crc32 is not an integer"
    return None
