"""The :class:`Frame`: one sensor observation as a typed state estimate.

A frame keeps its points in the **sensor frame** together with everything needed to trust or replay it:
stamp, sensor, intrinsics and depth scale (for depth images), extrinsics ``T_base_sensor``, the pose
estimate that placed it in the world (``T_world_sensor``, its revision and source), per-frame quality and
provenance. Points are float32 (N, 3) and read-only; a frame is immutable (use :meth:`Frame.with_pose`).
"""

from __future__ import annotations

import dataclasses
import enum
import math
import weakref
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np
from numpy.typing import NDArray

from driftmap import geometry
from driftmap.errors import GeometryError, IntrinsicsError, parse_enum


class SensorKind(enum.Enum):
    """What produced a frame's points."""

    DEPTH_CAMERA = "depth_camera"
    LIDAR = "lidar"


class PoseSource(enum.Enum):
    """Where a pose estimate came from (also used for ledger revisions)."""

    NONE = "none"
    """No estimate yet (the source had none): odometry or ``--poses`` must provide one."""
    ODOMETRY = "odometry"
    LOG = "log"
    GROUND_TRUTH = "ground_truth"
    LOOP_CLOSURE = "loop_closure"
    EXTERNAL_FILE = "external_file"
    ROLLBACK = "rollback"
    SYNTHETIC = "synthetic"


@dataclass(frozen=True, slots=True)
class PinholeIntrinsics:
    """Pinhole camera intrinsics in pixels; ``width`` x ``height`` is the image size they belong to."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self) -> None:
        for name in ("fx", "fy", "cx", "cy"):
            value = getattr(self, name)
            if not isinstance(value, (int, float, np.floating, np.integer)) or not math.isfinite(float(value)):
                raise IntrinsicsError(f"PinholeIntrinsics.{name} must be a finite number, got {value!r}")
            object.__setattr__(self, name, float(value))
        if self.fx <= 0 or self.fy <= 0:
            raise IntrinsicsError(f"PinholeIntrinsics: focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or int(value) != value or int(value) <= 0:
                raise IntrinsicsError(f"PinholeIntrinsics.{name} must be a positive integer, got {value!r}")
            object.__setattr__(self, name, int(value))

    @property
    def K(self) -> NDArray[np.float64]:
        """The 3x3 camera matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def check_image_shape(self, shape: tuple[int, ...], what: str = "depth image") -> None:
        """Raise :class:`IntrinsicsError` unless ``shape`` is ``(height, width)``."""
        if len(shape) != 2 or shape[0] != self.height or shape[1] != self.width:
            raise IntrinsicsError(
                f"{what} has shape {tuple(shape)} (rows, cols) but the intrinsics are for "
                f"{self.width}x{self.height} (width x height)"
            )

    def scaled(self, factor: float) -> PinholeIntrinsics:
        """Intrinsics of the image resized by ``factor`` (pixel-centre convention)."""
        return PinholeIntrinsics(
            fx=self.fx * factor,
            fy=self.fy * factor,
            cx=(self.cx + 0.5) * factor - 0.5,
            cy=(self.cy + 0.5) * factor - 0.5,
            width=round(self.width * factor),
            height=round(self.height * factor),
        )

    def subsampled(self, stride: int) -> PinholeIntrinsics:
        """Intrinsics of the image ``image[::stride, ::stride]`` (pixel u' is the original pixel stride * u')."""
        if stride < 1 or int(stride) != stride:
            raise IntrinsicsError(f"pixel stride must be a positive integer, got {stride}")
        if stride == 1:
            return self
        if 2 * stride > min(self.width, self.height):
            raise IntrinsicsError(f"pixel stride {stride} leaves fewer than 2 rows or columns of a {self.width}x"
                                  f"{self.height} image (build.pixel_stride: keep it below half the image's shorter side)")
        return PinholeIntrinsics(
            fx=self.fx / stride,
            fy=self.fy / stride,
            cx=self.cx / stride,
            cy=self.cy / stride,
            width=-(-self.width // stride),
            height=-(-self.height // stride),
        )

    def to_dict(self) -> dict[str, float | int]:
        return dataclasses.asdict(self)


_INT64_MIN, _INT64_MAX = -(2**63), 2**63 - 1


def _int64(value: object, what: str, expected: str, *, allow_float: bool = True) -> int:
    """``value`` as a Python int that fits the store's int64 columns; :class:`GeometryError` naming ``what``."""
    ok = isinstance(value, (int, np.integer)) or (allow_float and isinstance(value, (float, np.floating)))
    if isinstance(value, bool) or not ok or int(value) != value:
        raise GeometryError(f"{what} must be {expected}, got {value!r}")
    out = int(value)
    if not _INT64_MIN <= out <= _INT64_MAX:
        raise GeometryError(f"{what} = {out} does not fit in a signed 64-bit integer")
    return out


@dataclass(frozen=True, slots=True)
class PoseEstimate:
    """A pose estimate ``T_world_sensor`` and where it came from."""

    T_world_sensor: NDArray[np.float64]
    revision: int = 0
    source: PoseSource = PoseSource.ODOMETRY
    covariance_6x6: NDArray[np.float64] | None = None
    world_frame: str = "world"

    def __post_init__(self) -> None:
        object.__setattr__(self, "T_world_sensor", geometry.as_rigid(self.T_world_sensor, "PoseEstimate.T_world_sensor"))
        revision = _int64(self.revision, "PoseEstimate.revision", "an integer")
        if revision < 0:
            raise GeometryError(f"PoseEstimate.revision must be >= 0, got {revision}")
        object.__setattr__(self, "revision", revision)
        if not isinstance(self.source, PoseSource):
            object.__setattr__(self, "source", parse_enum(PoseSource, self.source, "PoseEstimate.source", GeometryError))
        if self.covariance_6x6 is not None:
            cov = np.array(self.covariance_6x6, dtype=np.float64)
            if cov.shape != (6, 6) or not np.all(np.isfinite(cov)):
                raise GeometryError(f"PoseEstimate.covariance_6x6: expected a finite 6x6 matrix, got shape {cov.shape}")
            if not np.allclose(cov, cov.T, atol=1e-12 + 1e-9 * np.abs(cov).max()):
                raise GeometryError("PoseEstimate.covariance_6x6 is not symmetric")
            cov.setflags(write=False)
            object.__setattr__(self, "covariance_6x6", cov)


@dataclass(frozen=True, slots=True)
class FrameQuality:
    """Per-frame quality of the raw measurement.

    ``invalid_counts`` maps an invalid-pixel reason (see :class:`driftmap.preprocess.depth.InvalidReason`)
    to how many pixels were rejected for it. ``flags`` lists human-readable reasons a frame is suspicious.
    """

    n_measurements: int
    n_valid: int
    invalid_counts: Mapping[str, int] = field(default_factory=dict)
    flags: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "invalid_counts", MappingProxyType(dict(self.invalid_counts)))
        object.__setattr__(self, "flags", tuple(self.flags))

    @property
    def valid_fraction(self) -> float:
        return self.n_valid / self.n_measurements if self.n_measurements else 0.0

    @property
    def invalid_fraction(self) -> float:
        return 1.0 - self.valid_fraction if self.n_measurements else 0.0

    @property
    def flagged(self) -> bool:
        return bool(self.flags)


class TrackingStatus(enum.Enum):
    """How far a frame's odometry registration can be trusted (:class:`TrackingHealth`)."""

    FIRST = "first"
    """the first frame of a trajectory: nothing to register against"""
    OK = "ok"
    """registered from the motion model's prediction, and it fits the map"""
    RECOVERED = "recovered"
    """the prediction's registration did not fit; another initial guess did (a fast turn, a stop)"""
    LOST = "lost"
    """no initial guess gave a registration that fits the map: the pose is bridged (flagged, not trusted)"""
    REINITIALISED = "reinitialised"
    """tracking restarted after lost frames: a new local map starts at the bridged pose (flagged)"""
    DEGENERATE = "degenerate"
    """the registration fits, but the scan leaves a direction of motion unconstrained (one surface, a corridor seen
    by a narrow field of view): along it the pose is the motion model's prediction (bridged along that direction;
    reported, and the trajectory still trusted by loop closure: the prediction moves it by centimetres, not metres)"""


@dataclass(frozen=True, slots=True)
class TrackingHealth:
    """How well a frame's odometry registration went (stored with the frame, summarised by ``build``).

    ``fitness``: share of the registered points with a map point within ``fitness_radius_m``; ``rmse_m``: RMS
    distance of those points; ``degeneracy``: ``sqrt(lambda_min / lambda_max)`` of the translational block of the
    point-to-plane information of the registered points (1: constrained equally in every direction, near 0: a
    corridor or a single plane leaves one direction free); ``deviation_m`` / ``deviation_deg``: the registration
    against the motion model's prediction; ``hypothesis``: the initial guess that was kept (``constant_velocity``,
    ``zero_motion``, ``half_velocity``, ``yaw+30``, ...). ``reason`` says why a frame is not ``ok``."""

    status: TrackingStatus
    fitness: float | None = None
    rmse_m: float | None = None
    degeneracy: float | None = None
    deviation_m: float | None = None
    deviation_deg: float | None = None
    hypothesis: str = "constant_velocity"
    n_points: int = 0
    fitness_radius_m: float | None = None
    reason: str = ""

    def __post_init__(self) -> None:
        if not isinstance(self.status, TrackingStatus):
            object.__setattr__(self, "status", parse_enum(TrackingStatus, self.status, "TrackingHealth.status", GeometryError))
        for name in ("fitness", "rmse_m", "degeneracy", "deviation_m", "deviation_deg", "fitness_radius_m"):
            value = getattr(self, name)
            if value is not None:
                if not math.isfinite(float(value)):
                    raise GeometryError(f"TrackingHealth.{name} must be finite, got {value!r}")
                object.__setattr__(self, name, float(value))

    @property
    def flagged(self) -> bool:
        """The registration is not trustworthy (lost, or the restart after lost frames)."""
        return self.status in (TrackingStatus.LOST, TrackingStatus.REINITIALISED)

    def to_dict(self) -> dict[str, object]:
        return {"status": self.status.value, "fitness": self.fitness, "rmse_m": self.rmse_m,
                "degeneracy": self.degeneracy, "deviation_m": self.deviation_m, "deviation_deg": self.deviation_deg,
                "hypothesis": self.hypothesis, "n_points": self.n_points, "fitness_radius_m": self.fitness_radius_m,
                "reason": self.reason}

    @classmethod
    def from_dict(cls, d: Mapping[str, object]) -> TrackingHealth:
        return cls(**{k: d[k] for k in d if k in cls.__dataclass_fields__})  # type: ignore[arg-type]


@dataclass(frozen=True, slots=True)
class Provenance:
    """Where a frame came from: a URI (file, log + topic) and the index inside it."""

    source_uri: str
    index: int


#: Arrays this module made read-only itself (id -> array); only these are shared without a copy.
_OWNED: weakref.WeakValueDictionary[int, np.ndarray] = weakref.WeakValueDictionary()


def adopt_readonly(array: NDArray[Any]) -> NDArray[Any]:
    """Hand an array its maker holds the only reference to over to a :class:`Frame` without a copy: it is made
    read-only and registered as frozen by this module. Arrays that do not own their data (views) are returned
    as they are (the frame then copies them). The caller must not keep a writable reference."""
    if array.base is None and array.flags.owndata and array.flags.c_contiguous:
        array.setflags(write=False)
        _OWNED[id(array)] = array
    return array


def _readonly(array: Any, dtype: Any, shape_tail: tuple[int, ...], name: str, n: int | None) -> NDArray[Any]:
    arr = np.asarray(array)
    if _OWNED.get(id(arr)) is not arr or arr.dtype != dtype or arr.flags.writeable:
        # copy anything the caller could still write through (even a read-only view of a writable
        # base), so a frame can never change under us; arrays we froze ourselves are shared
        arr = np.array(arr, dtype=dtype, order="C", copy=True)
    if arr.ndim != 1 + len(shape_tail) or arr.shape[1:] != shape_tail or (n is not None and arr.shape[0] != n):
        expected = ("N" if n is None else str(n),) + tuple(str(s) for s in shape_tail)
        raise GeometryError(f"{name}: expected shape ({', '.join(expected)}), got {arr.shape}")
    arr.setflags(write=False)
    _OWNED[id(arr)] = arr
    return arr


@dataclass(frozen=True, slots=True)
class PointAttributes:
    """Optional per-point attributes, each aligned with the frame's points."""

    intensity: NDArray[np.float32] | None = None
    color_rgb: NDArray[np.uint8] | None = None
    normal_sensor: NDArray[np.float32] | None = None
    time_offset_ns: NDArray[np.int64] | None = None

    _SPEC = {
        "intensity": (np.float32, ()),
        "color_rgb": (np.uint8, (3,)),
        "normal_sensor": (np.float32, (3,)),
        "time_offset_ns": (np.int64, ()),
    }

    def validated(self, n: int) -> PointAttributes:
        values = {}
        for name, (dtype, tail) in self._SPEC.items():
            value = getattr(self, name)
            values[name] = None if value is None else _readonly(value, dtype, tail, f"PointAttributes.{name}", n)
        return PointAttributes(**values)

    def subset(self, index: NDArray[np.integer] | NDArray[np.bool_]) -> PointAttributes:
        """Attributes of the selected points (an index array or a boolean mask)."""
        return PointAttributes(
            **{name: None if getattr(self, name) is None else getattr(self, name)[index] for name in self._SPEC}
        )

    def names(self) -> list[str]:
        return [name for name in self._SPEC if getattr(self, name) is not None]


@dataclass(frozen=True, slots=True)
class Frame:
    """One observation: sensor-frame points plus the metadata needed to trust or replay it."""

    frame_id: int
    stamp_ns: int
    sensor_name: str
    sensor_kind: SensorKind
    points_sensor: NDArray[np.float32]
    pose: PoseEstimate
    T_base_sensor: NDArray[np.float64] = field(default_factory=geometry.identity)
    attributes: PointAttributes = field(default_factory=PointAttributes)
    intrinsics: PinholeIntrinsics | None = None
    depth_scale: float | None = None
    quality: FrameQuality | None = None
    provenance: Provenance | None = None
    sensor_frame: str = "sensor"
    base_frame: str = "base_link"
    tracking: TrackingHealth | None = None
    """How the odometry registration of this frame went (frames whose poses odometry produced)."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "frame_id", _int64(self.frame_id, "Frame.frame_id", "an integer"))
        object.__setattr__(self, "stamp_ns", _int64(self.stamp_ns, f"frame {self.frame_id}: stamp_ns",
                                                    "an integer number of nanoseconds", allow_float=False))
        if not isinstance(self.sensor_kind, SensorKind):
            object.__setattr__(self, "sensor_kind", parse_enum(SensorKind, self.sensor_kind, f"frame {self.frame_id}: sensor_kind", GeometryError))
        if not isinstance(self.pose, PoseEstimate):
            geometry.as_rigid(self.pose, f"frame {self.frame_id}: pose")  # a malformed matrix: TransformError
            raise GeometryError(
                f"frame {self.frame_id}: pose must be a PoseEstimate (T_world_sensor with its revision and source), "
                f"got {type(self.pose).__name__}"
            )
        pts = _readonly(self.points_sensor, np.float32, (3,), f"frame {self.frame_id}: points_sensor", None)
        object.__setattr__(self, "points_sensor", pts)
        object.__setattr__(self, "attributes", self.attributes.validated(len(pts)))
        object.__setattr__(self, "T_base_sensor", geometry.as_rigid(self.T_base_sensor, f"frame {self.frame_id}: T_base_sensor"))
        if self.depth_scale is not None and not (isinstance(self.depth_scale, (int, float, np.number))
                                                 and math.isfinite(self.depth_scale) and self.depth_scale > 0):
            raise GeometryError(f"frame {self.frame_id}: depth_scale must be a positive number, got {self.depth_scale!r}")

    @property
    def n_points(self) -> int:
        return int(self.points_sensor.shape[0])

    @property
    def T_world_sensor(self) -> NDArray[np.float64]:
        return self.pose.T_world_sensor

    def points_world(self, T_world_sensor: NDArray[np.float64] | None = None) -> NDArray[np.float32]:
        """Points in the world frame, with this frame's pose or an explicit ``T_world_sensor``."""
        T = self.pose.T_world_sensor if T_world_sensor is None else T_world_sensor
        return geometry.transform_points(T, self.points_sensor)

    def with_pose(self, pose: PoseEstimate) -> Frame:
        """A copy of this frame carrying another pose estimate (points are shared, not copied)."""
        return dataclasses.replace(self, pose=pose)

    def with_points(self, points_sensor: NDArray[np.float32], attributes: PointAttributes | None = None) -> Frame:
        """A copy with other sensor-frame points (e.g. after downsampling); attributes must match them."""
        return dataclasses.replace(self, points_sensor=points_sensor, attributes=attributes or PointAttributes())
