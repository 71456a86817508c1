"""Per-point fields a reader takes from a file -- coordinates, normals and per-point times -- checked against the
data before they are used. One owner of these rules, shared by the cloud-folder (PCD / PLY), KITTI ``.bin`` and ROS
PointCloud2 readers.

**Coordinates.** A point farther than :data:`MAX_POINT_RANGE_M` from the sensor (the origin of the cloud's frame)
is no measurement: the readers drop and count it as they drop points with a NaN / inf coordinate
(:func:`far_points`), with one warning per cloud naming the file / message and the count; a cloud more than
:data:`MAX_ABSURD_FRACTION` of whose points are that far is refused (:class:`SourceError`): its bytes are not read
as they were meant (a wrong byte order, a wrong layout) or it is not a sensor's scan. A coordinate of 1e30 m would
otherwise pass every reader and fail every later command (a voxel grid too large to index). A cloud within the
range is returned as read, bit for bit. Depth back-projection cannot produce such points (depth is bounded by the
depth range kept, the intrinsics by :func:`driftmap.sources.depth_folder.intrinsics_problem`).

**Units.** Points are read in metres. A cloud whose median range (of its finite points off the origin) is beyond
:data:`MAX_MEDIAN_RANGE_M` is no LiDAR scan in metres: it is refused (:class:`SourceError` naming the file and the
median), suggesting millimetres (the usual mistake: the median would then be a thousandth of it) or points that are
not in the sensor's frame. The warning about far points says it may be a units problem when a large share
(:data:`LARGE_FAR_FRACTION`) of the cloud is dropped.

**No return.** A point exactly at the sensor origin ``(0, 0, 0)`` (range 0) is what LiDAR drivers and converters
write where a beam had no return (organised clouds, zero-filled scans): it is no measurement, and is dropped with
one warning per cloud naming the file and the count (:func:`measured_points`, the KITTI and PCD / PLY readers). A cloud left without any point
(every point NaN / inf, at the origin or too far) is refused, naming the file and the counts: the readers never
store an empty frame (lenient sources skip it, as any frame that cannot be read).

**Normals.** A normal field is kept only when *every* normal of the cloud is finite and unit length within
:data:`NORMAL_UNIT_TOLERANCE`. Otherwise the cloud's normals are dropped, all of them, with one warning naming the
file / message and the counts (zero, NaN / inf, not unit length): a field that is partly wrong is not trusted
(BALM's PCD files carry ``normal_x/y/z`` fields that are all zero; PCL writes NaN where it could not estimate
one). Without normals the consumers estimate their own from the points (the diagnostics do).

**Per-point times** (:data:`POINT_TIME_FIELDS`) become ``PointAttributes.time_offset_ns``, int64 ns relative to
the frame stamp. The unit is decided from the data (:func:`point_time_offsets_ns`): integer fields are
nanoseconds (Livox ``offset_time``, Ouster ``t``), relative to the scan or absolute when they are close to the
frame stamp; float fields are seconds relative to the scan (Velodyne / Ouster ROS ``time``, may be negative) or
absolute epoch seconds / nanoseconds when they are close to the frame stamp (Hesai ``timestamp``). The result
is then checked: a field with a non-finite value, or whose offsets span more than :data:`MAX_SCAN_SPAN_NS` or
lie more than that from the frame stamp, is not used (``None``, one warning naming the file / frame / field).
"""

from __future__ import annotations

import enum
import logging

import numpy as np
from numpy.typing import NDArray

from driftmap.errors import SourceError

logger = logging.getLogger(__name__)

NORMAL_UNIT_TOLERANCE = 1e-2
"""A normal is unit length when ``abs(|n| - 1) <= NORMAL_UNIT_TOLERANCE`` (float32 normals written by any tool
are within 1e-6; a field of unnormalised vectors is off by far more)."""
ZERO_NORMAL_M = 1e-6
"""A normal shorter than this counts as zero (no normal), not as merely not unit length."""

#: Per-point time fields, in the order they are looked for.
POINT_TIME_FIELDS = ("t", "offset_time", "time", "timestamp", "time_stamp")

MAX_SCAN_SPAN_NS = 1_000_000_000
"""Per-point times of one scan span at most this (1 s: a 10 Hz spinning LiDAR spans 0.1 s, a 1 Hz scan 1 s)
and lie within it of the frame stamp; anything else is not a time field of this scan (or not in its unit)."""

MAX_POINT_RANGE_M = 10_000.0
"""No sensor driftmap reads measures farther than this (10 km; long-range LiDARs reach 1-2 km): a point farther
from the sensor is a reader's or a writer's error, dropped and counted as invalid (:func:`far_points`)."""
MAX_ABSURD_FRACTION = 0.5
"""A cloud with more than this fraction of its points beyond :data:`MAX_POINT_RANGE_M` is refused as a whole."""
_BOX_M = MAX_POINT_RANGE_M / 3**0.5
"""Points with every coordinate within this are within :data:`MAX_POINT_RANGE_M` (the check's fast path)."""
MAX_MEDIAN_RANGE_M = 1_000.0
"""No LiDAR scan in metres has its median point farther than this from the sensor (a KITTI scan's is about 10 m,
an outdoor long-range scan's well under 100 m): a cloud whose median range is beyond it is refused
(:func:`check_units`), most likely millimetres read as metres."""
MILLIMETRE_MEDIAN_RANGE_M = 1e6
"""Up to this median range (1 km once divided by 1000) the units message suggests millimetres; beyond it the data
is refused by the far-point check as not read as it was meant (:func:`far_points`)."""
LARGE_FAR_FRACTION = 0.1
"""When more than this fraction of a cloud's finite points are dropped as too far, the warning says it may be a
units problem."""
_UNITS_SAMPLE = 4096
"""About how many points of a cloud the units check looks at (evenly spaced)."""


def median_range_m(points: NDArray) -> float | None:
    """The median distance from the sensor of (a sample of about :data:`_UNITS_SAMPLE` of) the finite points of a
    cloud (N, 3) that are not at the origin; ``None`` when there is none."""
    xyz = np.asarray(points)
    if len(xyz) == 0:
        return None
    sample = xyz[:: max(1, len(xyz) // _UNITS_SAMPLE)]
    with np.errstate(over="ignore", invalid="ignore"):
        coords = sample.astype(np.float64)
        coords = coords[np.isfinite(coords).all(axis=1)]
        ranges = np.sqrt(np.einsum("ij,ij->i", coords, coords))
    ranges = ranges[np.isfinite(ranges) & (ranges > 0)]
    return float(np.median(ranges)) if ranges.size else None


def check_units(points: NDArray, what: str) -> None:
    """:class:`SourceError` naming ``what`` when the cloud's median range (:func:`median_range_m`) is beyond
    :data:`MAX_MEDIAN_RANGE_M` (and within :data:`MILLIMETRE_MEDIAN_RANGE_M`, beyond which :func:`far_points` refuses
    the cloud as not read as it was meant): the coordinates are most likely millimetres."""
    median = median_range_m(points)
    if median is None or not MAX_MEDIAN_RANGE_M < median <= MILLIMETRE_MEDIAN_RANGE_M:
        return
    raise SourceError(f"{what}: the median point lies {median:.4g} m from the sensor, which no LiDAR scan in metres "
                      f"does (at most {MAX_MEDIAN_RANGE_M:g} m): the coordinates look like millimetres or centimetres "
                      f"(the median would be {median / 1000:.3g} m in millimetres, {median / 100:.3g} m in centimetres; "
                      f"hostile trial 28 W12), or the points are not in the sensor's frame; LiDAR points are "
                      f"read in metres, in the sensor's frame: convert the file's coordinates to metres; the cloud is "
                      f"refused")


def far_points(points: NDArray, what: str, *, hint: str = "") -> NDArray[np.bool_] | None:
    """Which points of a cloud (N, 3), in its sensor's frame, lie farther than :data:`MAX_POINT_RANGE_M` from the
    sensor; ``None`` when none does (the cloud is used as it is, bit for bit). NaN / inf coordinates are not this
    check's (each reader drops and counts them itself) and are never in the mask.

    The points found are to be dropped and counted (``"beyond_max"``, as
    :class:`driftmap.preprocess.depth.InvalidReason`) by the caller; one warning names ``what`` (the file or
    message, and the frame) and the count. When more than :data:`MAX_ABSURD_FRACTION` of the finite points are that
    far, :class:`SourceError` names ``what``, the count and ``hint`` (what may be wrong, e.g. a PointCloud2's
    ``is_bigendian``): the cloud is refused. A cloud whose median range is not a LiDAR's in metres is refused first
    (:func:`check_units`)."""
    xyz = np.asarray(points)
    if len(xyz) == 0:
        return None
    check_units(xyz, what)
    with np.errstate(invalid="ignore"):
        inside = np.abs(xyz) <= _BOX_M  # False for NaN: those rows are looked at below
    if bool(np.all(inside)):
        return None
    rows = np.flatnonzero(~inside.all(axis=1))
    with np.errstate(over="ignore", invalid="ignore"):  # (signalling NaNs of byte-swapped data, squares of 1e300)
        coords = xyz[rows].astype(np.float64)
        finite_rows = np.isfinite(coords).all(axis=1)
        ranges = np.sqrt(np.einsum("ij,ij->i", coords, coords))
    beyond = finite_rows & (ranges > MAX_POINT_RANGE_M)
    n_far = int(np.count_nonzero(beyond))
    if not n_far:
        return None
    n_finite = len(xyz) - int(np.count_nonzero(~finite_rows))
    largest = float(np.max(ranges[beyond]))
    if n_far > MAX_ABSURD_FRACTION * n_finite:
        raise SourceError(f"{what}: {n_far} of the {n_finite} finite points lie farther than {MAX_POINT_RANGE_M:g} m "
                          f"from the sensor (up to {largest:.3g} m): no sensor measures that far, so the data is not "
                          f"read as it was meant{hint}; the cloud is refused")
    far = np.zeros(len(xyz), dtype=bool)
    far[rows[beyond]] = True
    units = ("" if n_far <= LARGE_FAR_FRACTION * n_finite else
             f"; that is {n_far / n_finite:.0%} of the cloud: it may be a units problem (LiDAR points are read in "
             f"metres; are the coordinates in millimetres?)")
    logger.warning("%s: dropping %d of %d points farther than %g m from the sensor (up to %.3g m): no sensor "
                   "measures that far%s%s", what, n_far, len(xyz), MAX_POINT_RANGE_M, largest, hint, units)
    return far


def measured_points(points: NDArray, what: str, *, hint: str = "") -> NDArray[np.bool_] | None:
    """The coordinate check every LiDAR point reader (KITTI ``.bin``, PCD / PLY clouds) applies to a cloud (N, 3) in
    its sensor's frame: which points are measurements, or ``None`` when every point is (the cloud is used as it is,
    bit for bit).

    Dropped (the caller applies the mask): points with a NaN / inf coordinate (the readers warn about those
    themselves), points farther than :data:`MAX_POINT_RANGE_M` (:func:`far_points`, which also refuses a cloud most of
    whose points are that far, or whose median range says it is not in metres, :func:`check_units`), and points
    exactly at the sensor origin (range 0: no return), with one warning naming ``what`` and their count. A cloud with
    no point left raises :class:`SourceError` naming ``what`` and the counts."""
    xyz = np.asarray(points)
    n = len(xyz)
    if n == 0:
        raise SourceError(f"{what}: the cloud has no points")
    finite = np.isfinite(xyz).all(axis=1)
    far = far_points(xyz, what, hint=hint)
    at_origin = finite & ~xyz.any(axis=1)  # exactly (0, 0, 0); -0.0 is 0 too
    n_origin = int(np.count_nonzero(at_origin))
    keep = finite & ~at_origin
    if far is not None:
        keep &= ~far
    n_keep = int(np.count_nonzero(keep))
    if n_keep == 0:
        n_far = 0 if far is None else int(np.count_nonzero(far))
        n_bad = n - int(np.count_nonzero(finite))
        parts = [f"{count} {why}" for count, why in ((n_bad, "with a NaN or infinite coordinate"),
                                                    (n_origin, "at the sensor origin (0, 0, 0: no return)"),
                                                    (n_far, f"farther than {MAX_POINT_RANGE_M:g} m")) if count]
        raise SourceError(f"{what}: no valid point: of its {n} points, {', '.join(parts)}; a frame without a "
                          f"measurement is not stored (--lenient skips it, lenient=True in the library)")
    if n_origin:
        logger.warning("%s: dropping %d of %d points exactly at the sensor origin (0, 0, 0): range 0 is no return, "
                       "not a measurement", what, n_origin, n)
    return None if n_keep == n else keep


class PointTimeReference(enum.Enum):
    """How float per-point time fields (``time``, ``timestamp``) relate to the frame stamp."""

    AUTO = "auto"
    """Absolute when the values are closer to the frame stamp than to zero, else relative."""
    RELATIVE = "relative"
    ABSOLUTE = "absolute"


def normal_problems(normals: NDArray) -> dict[str, int]:
    """Counts of the normals that are ``non_finite`` (a NaN / inf component), ``zero`` (shorter than
    :data:`ZERO_NORMAL_M`) and ``non_unit`` (finite, not zero, length off 1 by more than the tolerance)."""
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    finite = np.all(np.isfinite(n), axis=1)
    length = np.linalg.norm(np.where(finite[:, None], n, 0.0), axis=1)
    zero = finite & (length < ZERO_NORMAL_M)
    non_unit = finite & ~zero & (np.abs(length - 1.0) > NORMAL_UNIT_TOLERANCE)
    return {"non_finite": int(np.count_nonzero(~finite)), "zero": int(np.count_nonzero(zero)),
            "non_unit": int(np.count_nonzero(non_unit))}


def checked_normals(normals: NDArray | None, what: str, warned: set[str] | None = None) -> NDArray[np.float32] | None:
    """``normals`` (float32, as given) when every one is finite and unit length; otherwise ``None`` and one
    warning naming ``what`` (the file or message, and the frame) and the counts. See the module docs.

    ``warned``: a source's own set of what it has warned about; when it holds ``"normals"`` already, later frames
    are logged at DEBUG (a log of 4,000 scans with zero normal fields warns once, not 4,000 times)."""
    if normals is None:
        return None
    normals = np.asarray(normals)
    counts = normal_problems(normals)
    bad = sum(counts.values())
    if not bad:
        return normals.astype(np.float32, copy=False)
    n = len(normals)
    again = warned is not None and "normals" in warned
    logger.log(logging.DEBUG if again else logging.WARNING,
               "%s: normals not used (%d of %d are unusable: %d zero, %d NaN/inf, %d not unit length within %g); "
               "a normal field is used only when every normal is a unit vector%s", what, bad, n, counts["zero"],
               counts["non_finite"], counts["non_unit"], NORMAL_UNIT_TOLERANCE,
               "" if warned is None or again else " (the source's later frames alike are logged at debug level)")
    if warned is not None:
        warned.add("normals")
    return None


def checked_intensity(intensity: NDArray | None, what: str) -> NDArray[np.float32] | None:
    """``intensity`` (float32) when every value is finite; otherwise ``None`` and a warning naming ``what`` (the
    file and frame): a field with NaN / inf values is not a measurement to keep (the points stay)."""
    if intensity is None:
        return None
    values = np.asarray(intensity, dtype=np.float32)
    bad = int(np.count_nonzero(~np.isfinite(values)))
    if bad:
        logger.warning("%s: intensity not used (%d of %d values are NaN or infinite)", what, bad, len(values))
        return None
    return values


def _offsets_ns(values: NDArray, stamp_ns: int, reference: PointTimeReference, field: str,
                what: str) -> tuple[NDArray[np.float64] | NDArray[np.int64], str]:
    """Per-point times -> ns relative to the frame stamp (not yet checked), and how they were read."""
    sample = values[:: max(1, values.size // 1024)]
    if values.dtype.kind in "iu":  # integer: nanoseconds
        v = values.astype(np.int64)
        median = float(np.median(sample.astype(np.float64)))
        absolute = reference is PointTimeReference.ABSOLUTE or (
            reference is PointTimeReference.AUTO and stamp_ns > 0 and abs(median - stamp_ns) < stamp_ns / 2
        )
        return (v - stamp_ns, "absolute ns") if absolute else (v, "ns from the scan")
    if values.dtype.kind != "f":
        raise SourceError(f"{what}: per-point time field {field!r} has unsupported type {values.dtype}")
    v = values.astype(np.float64)
    finite = sample[np.isfinite(sample)].astype(np.float64)
    median = float(np.median(finite)) if finite.size else 0.0
    stamp_s = stamp_ns / 1e9
    if reference is PointTimeReference.RELATIVE:
        unit = "relative_s"
    elif reference is PointTimeReference.ABSOLUTE:
        unit = "absolute_ns" if median > 1e14 else "absolute_s"
    elif stamp_ns > 0 and abs(median - stamp_ns) < stamp_ns / 2:
        unit = "absolute_ns"  # float nanoseconds (e.g. livox_ros_driver2 ``timestamp``)
    elif stamp_s > 0 and abs(median - stamp_s) < stamp_s / 2:
        unit = "absolute_s"
    else:
        unit = "relative_s"
    if unit == "relative_s":
        return np.rint(v * 1e9), "s from the scan"
    if unit == "absolute_ns":
        return np.rint(v - float(stamp_ns)), "absolute ns"
    whole_s = stamp_ns // 1_000_000_000
    return np.rint((v - whole_s) * 1e9) - float(stamp_ns - whole_s * 1_000_000_000), "absolute s"


def point_time_offsets_ns(values: NDArray, stamp_ns: int, field: str, what: str,
                          reference: PointTimeReference = PointTimeReference.AUTO) -> NDArray[np.int64] | None:
    """Per-point times of a scan stamped ``stamp_ns`` -> int64 ns relative to the stamp, or ``None`` (with one
    warning naming ``what``, the field and why) when they are not plausible for one scan: a non-finite value,
    a span over :data:`MAX_SCAN_SPAN_NS`, or an offset farther than that from the stamp (e.g. absolute epoch
    times in a folder whose stamps are only assumed). See the module docs for the units."""
    values = np.asarray(values).reshape(-1)
    if values.size == 0:
        return np.empty(0, dtype=np.int64)
    if values.dtype.kind == "f" and not np.all(np.isfinite(values)):
        bad = int(np.count_nonzero(~np.isfinite(values)))
        logger.warning("%s: per-point time field %r not used: %d of %d values are NaN/inf", what, field, bad,
                       values.size)
        return None
    with np.errstate(invalid="ignore", over="ignore"):
        offsets, read_as = _offsets_ns(values, stamp_ns, reference, field, what)
    lo, hi = float(np.min(offsets)), float(np.max(offsets))
    limit = float(MAX_SCAN_SPAN_NS)
    if hi - lo > limit or max(abs(lo), abs(hi)) > limit:
        why = (f"its values span {(hi - lo) / 1e9:.6g} s" if hi - lo > limit else
               f"its values lie {lo / 1e9:+.6g} .. {hi / 1e9:+.6g} s from the frame stamp {stamp_ns} ns")
        logger.warning("%s: per-point time field %r not used: read as %s, %s, more than one scan (%g s) can; "
                       "is the frame stamp right, and the field in that unit?", what, field, read_as, why,
                       MAX_SCAN_SPAN_NS / 1e9)
        return None
    return np.asarray(offsets).astype(np.int64)
