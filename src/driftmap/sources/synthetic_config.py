"""What determines a synthetic log: :class:`SyntheticLogConfig` (with the seed it fixes every byte of the depth) and
the bounds of its fields (:func:`check_config_fields`), so that no log needs more than a few GB of memory and its
stamps stay within the int64 ns a frame carries. :mod:`driftmap.sources.synthetic` re-exports every name."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from driftmap.errors import ConfigError, parse_enum
from driftmap.sources.stamps import MAX_STAMP_NS
from driftmap.sources.synthetic_lidar import LidarPattern
from driftmap.sources.synthetic_motion import frames_for_speed, moving_scans, non_moving_scans, path_length_m

__all__ = [
    "MAX_DEPTH_PIXELS",
    "MAX_FRAMES",
    "MAX_FRAME_PERIOD_NS",
    "MAX_IMAGE_SIDE",
    "MAX_LIDAR_RAYS",
    "MAX_SEED",
    "MAX_YAW_DRIFT_DEG_PER_M",
    "MIN_FRAME_PERIOD_NS",
    "SyntheticLogConfig",
    "check_config_fields",
    "check_frame_count",
]


@dataclass(frozen=True)
class SyntheticLogConfig:
    """Everything that determines a synthetic log (with the seed, it fixes every byte of the depth)."""

    seed: int = 7
    n_frames: int = 60
    loop_turns: float = 1.1
    """How many times the robot goes round the circle (> 1 means it revisits the start: a loop)."""
    circle_radius_m: float = 1.0
    frame_period_ns: int = 200_000_000
    start_stamp_ns: int = 1_700_000_000_000_000_000
    width: int = 320
    height: int = 240
    fx: float = 262.5
    fy: float = 262.5
    cx: float = 159.5
    cy: float = 119.5
    depth_scale: float = 1000.0
    max_range_m: float = 8.0
    dropout_fraction: float = 0.003
    camera_height_m: float = 1.0
    camera_pitch_down_deg: float = 15.0
    yaw_drift_deg_per_m: float = 0.6
    scale_drift_percent: float = 1.0
    step_frame: int = 30
    step_m: tuple[float, float, float] = (0.0, 0.03, 0.0)
    """Translation step (base frame of the robot, metres) added to the odometry increment at ``step_frame``."""
    odometry_noise_m: float = 0.001
    odometry_noise_deg: float = 0.05
    lidar: bool = False
    lidar_beams: int = 16
    lidar_azimuth_steps: int = 720
    lidar_range_sigma_m: float = 0.01
    lidar_elevation_deg: tuple[float, float] = (-15.0, 15.0)
    """Lowest and highest beam elevation (deg)."""
    lidar_max_range_m: float = 30.0
    scene: str = "room"
    """``room`` (the furnished room, a circle of ``circle_radius_m``) or ``street`` (a city block: see
    :meth:`street`)."""
    # --- motion (docs/synthetic-log.md, driftmap.sources.synthetic_motion); the defaults: driving all the time
    speed_m_per_s: float | None = None
    """Speed along the path while moving. None: the path is spread evenly over the moving scans of ``n_frames``
    (the default logs: 0.59 m/s in the room, 10 m/s on the street). Set: ``n_frames`` is derived, so that the
    robot drives the whole path at this speed, plus the stationary, stop and turn scans (a given ``n_frames`` is
    replaced): at 2 Hz a scan moves 5 times as far as at 10 Hz."""
    stationary_start_frames: int = 0
    """The first scans (this many) are captured standing at the start pose; motion starts at the stamp of frame
    ``stationary_start_frames`` (frames 0 to ``stationary_start_frames`` have the start pose)."""
    stops: int = 0
    """Stops on the way, at the fractions ``j / (stops + 1)`` of the moving path."""
    stop_frames: int = 0
    """Scans each stop lasts (standing)."""
    turn_in_place_deg_per_frame: float = 0.0
    """Yaw per scan of the in-place turns (deg, + counter-clockwise; |value| < 180), at a fixed position."""
    turn_in_place_frames: int = 0
    """Scans one in-place turn lasts at that rate. If they do not add up to whole turns (8 x 45 deg do), the robot
    turns back as many scans at the opposite rate, so it heads along the path again afterwards."""
    turns_in_place: int = 0
    """In-place turns at the fractions ``j / (turns_in_place + 1)`` of the moving path ..."""
    turn_in_place_at: tuple[float, ...] = ()
    """... or at these fractions (0 = where the path starts, 1 = its end) instead."""
    # --- LiDAR pattern and point times (driftmap.sources.synthetic_lidar)
    lidar_pattern: LidarPattern = LidarPattern.SPINNING
    """``spinning`` (beams x azimuth steps) or ``rosette`` (a non-repetitive Livox-like scanner)."""
    lidar_points_per_scan: int = 24_000
    """Rays per rosette scan (a Livox Avia measures 240k points/s: 24k per 0.1 s)."""
    lidar_fov_deg: float = 70.0
    """Full angle of the rosette's circular field of view, round the LiDAR's x axis."""
    lidar_rosette_k: float = 9.618034
    """``k`` of the rosette curve ``rho = (fov / 2) cos(k theta)``; not a whole number, so scans differ."""
    lidar_point_times: bool = False
    """Render each point from the pose at its capture time (the sensor moves during the scan) and store the times
    (``lidar/NNNNNN.time.bin``, int64 ns after the scan's stamp: the scan's start)."""
    # --- the world changed between sessions (room only; driftmap.sources.synthetic_scene.scene_boxes)
    door_open: bool = False
    """The +x wall's door stands open onto a corridor (the default room has it closed)."""
    chair_moved: bool = False
    """The chair stands before the -x wall instead of near the -y wall."""

    def __post_init__(self) -> None:
        """Every field checked before anything is computed from it (:func:`check_config_fields`): a value out of its
        range raises :class:`ConfigError` naming the field, never an ``OverflowError`` or a 20 GB allocation later."""
        object.__setattr__(self, "lidar_pattern", parse_enum(LidarPattern, self.lidar_pattern, "lidar_pattern"))
        check_config_fields(self)
        object.__setattr__(self, "turn_in_place_at", tuple(float(f) for f in self.turn_in_place_at))
        for name in ("stationary_start_frames", "stops", "stop_frames", "turn_in_place_frames", "turns_in_place"):
            if getattr(self, name) < 0:
                raise ConfigError(f"{name}: must be >= 0, got {getattr(self, name)}")
        if self.stops and self.stop_frames < 1:
            raise ConfigError(f"stop_frames: {self.stops} stops need stop_frames >= 1")
        turning = bool(self.turns_in_place or self.turn_in_place_at)
        if self.turns_in_place and self.turn_in_place_at:
            raise ConfigError("turn_in_place_at: give the turns' places or their number (turns_in_place), not both")
        if any(not 0.0 <= f <= 1.0 for f in self.turn_in_place_at):
            raise ConfigError(f"turn_in_place_at: fractions of the path must be in [0, 1], got {self.turn_in_place_at}")
        if turning and not 0.0 < abs(self.turn_in_place_deg_per_frame) < 180.0:
            raise ConfigError("turn_in_place_deg_per_frame: in-place turns need 0 < |deg per scan| < 180, got "
                              f"{self.turn_in_place_deg_per_frame}")
        if turning and self.turn_in_place_frames < 1:
            raise ConfigError("turn_in_place_frames: in-place turns need turn_in_place_frames >= 1")
        if self.lidar_points_per_scan < 1:
            raise ConfigError(f"lidar_points_per_scan: must be >= 1, got {self.lidar_points_per_scan}")
        if not 0.0 < self.lidar_fov_deg < 180.0:
            raise ConfigError(f"lidar_fov_deg: must be in (0, 180), got {self.lidar_fov_deg}")
        for name in ("door_open", "chair_moved"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"{name}: must be true or false, got {getattr(self, name)!r}")
            if getattr(self, name) and self.scene != "room":
                raise ConfigError(f"{name}: the room's door and chair; scene {self.scene!r} has none")
        if not self.lidar and (self.lidar_point_times or self.lidar_pattern != LidarPattern.SPINNING):
            raise ConfigError("lidar: lidar_pattern='rosette' and lidar_point_times need lidar=True")
        if self.speed_m_per_s is not None:
            if not self.speed_m_per_s > 0.0:
                raise ConfigError(f"speed_m_per_s: must be > 0, got {self.speed_m_per_s}")
            object.__setattr__(self, "n_frames", frames_for_speed(self, self.speed_m_per_s))
            check_frame_count(self, f" (derived: 1 + {moving_scans(self):,} moving scans to drive the "
                                    f"{path_length_m(self):.3g} m path at speed_m_per_s={self.speed_m_per_s:g}, "
                                    f"{self.frame_period_ns / 1e9:g} s apart, + {non_moving_scans(self):,} "
                                    f"stationary, stop and turn scans)")
        elif moving_scans(self) < 1:
            raise ConfigError(f"n_frames: {self.n_frames} frames leave no moving scan after the "
                              f"{non_moving_scans(self)} stationary, stop and turn scans (give more, or speed_m_per_s)")

    @classmethod
    def street(cls, **overrides: object) -> SyntheticLogConfig:
        """An outdoor log: a car-height 32-beam LiDAR drives 1.1 times round a city block (a rounded rectangle of
        70 x 50 m, ~1 m between scans at 10 Hz) between building facades, poles and parked cars; the odometry drifts
        by 1 % in scale and 0.02 deg/m in yaw (a few metres at the revisit). The depth camera renders 80 x 60."""
        base = dict(scene="street", n_frames=245, frame_period_ns=100_000_000, lidar=True, lidar_beams=32,
                    lidar_azimuth_steps=1024, lidar_elevation_deg=(-25.0, 3.0), lidar_max_range_m=80.0,
                    lidar_range_sigma_m=0.02, yaw_drift_deg_per_m=0.02, scale_drift_percent=1.0, step_frame=-1,
                    step_m=(0.0, 0.0, 0.0), odometry_noise_m=0.002, odometry_noise_deg=0.02,
                    width=80, height=60, fx=65.625, fy=65.625, cx=39.5, cy=29.5)
        base.update(overrides)
        return cls(**base)  # type: ignore[arg-type]

    def default_speed_m_per_s(self) -> float:
        """The speed of the scene's default log (0.59 m/s in the room, 10 m/s on the street): what ``driftmap
        synth`` keeps when the period or the stationary, stop and turn scans change and ``--frames`` is not given."""
        default = SyntheticLogConfig.street() if self.scene == "street" else SyntheticLogConfig()
        return path_length_m(default) / ((default.n_frames - 1) * default.frame_period_ns * 1e-9)


MIN_FRAME_PERIOD_NS = 1_000_000
MAX_FRAME_PERIOD_NS = 3_600_000_000_000
"""``frame_period_ns`` lies within 1 ms .. 1 h (sensors run at 1 kHz .. a frame an hour)."""
MAX_FRAMES = 1_000_000
"""At most this many frames (and stationary, stop and turn scans): a million depth images, ~10 GB on disk."""
MAX_IMAGE_SIDE = 8192
MAX_DEPTH_PIXELS = 4096 * 2048
"""Depth images of at most this many pixels (each side at most :data:`MAX_IMAGE_SIDE`): ray-casting one takes ~200
bytes a pixel, ~1.7 GB at this size."""
MAX_LIDAR_RAYS = 2_000_000
"""At most this many rays per LiDAR scan (``lidar_points_per_scan``, ``lidar_beams * lidar_azimuth_steps``):
casting one with per-point times takes ~1 kB a ray, ~2 GB at this size."""
MAX_YAW_DRIFT_DEG_PER_M = 360.0
"""``yaw_drift_deg_per_m`` lies within +- this (a full turn per metre; ``perturb --drift-deg-per-m`` alike)."""
MAX_SEED = 2**63 - 1
"""numpy's seeds are integers >= 0; this bound keeps them in the int64 a JSON reader gives back."""


def _integer(config: SyntheticLogConfig, name: str, lo: int, hi: int, why: str = "") -> int:
    value = getattr(config, name)
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ConfigError(f"{name}: must be an integer, got {value!r}")
    if not lo <= value <= hi:
        raise ConfigError(f"{name}: must be within {lo} .. {hi}{why}, got {value}")
    return int(value)


def _number(config: SyntheticLogConfig, name: str, lo: float = -math.inf, hi: float = math.inf, *,
            open_lo: bool = False, value: object = None, why: str = "") -> float:
    value = getattr(config, name) if value is None else value
    try:
        number = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError, OverflowError):
        raise ConfigError(f"{name}: must be a number, got {value!r}") from None
    inside = (lo < number if open_lo else lo <= number) and number <= hi
    if not math.isfinite(number) or not inside:
        bounds = f"{'(' if open_lo else '['}{lo:g}, {hi:g}]" if math.isfinite(hi) else (
            f"{'>' if open_lo else '>='} {lo:g}" if math.isfinite(lo) else "finite")
        raise ConfigError(f"{name}: must be {'finite and ' if bounds != 'finite' else ''}{bounds}{why}, got {value!r}")
    return number


def check_config_fields(config: SyntheticLogConfig) -> None:
    """Check every field of a :class:`SyntheticLogConfig` that can be wrong alone: :class:`ConfigError` naming the
    field and its range. Sizes are bounded so that no log needs more than a few GB of memory
    (:data:`MAX_DEPTH_PIXELS`, :data:`MAX_LIDAR_RAYS`, :data:`MAX_FRAMES`) and stamps stay within the int64 ns a frame
    carries (``frame_period_ns`` within :data:`MIN_FRAME_PERIOD_NS` .. :data:`MAX_FRAME_PERIOD_NS`, the last stamp
    at most :data:`~driftmap.sources.stamps.MAX_STAMP_NS`)."""
    _integer(config, "seed", 0, MAX_SEED, " (numpy's seeds are >= 0)")
    _integer(config, "frame_period_ns", MIN_FRAME_PERIOD_NS, MAX_FRAME_PERIOD_NS, " (1 ms .. 1 h)")
    _integer(config, "start_stamp_ns", 0, MAX_STAMP_NS)
    for name in ("stationary_start_frames", "stops", "stop_frames", "turn_in_place_frames", "turns_in_place"):
        _integer(config, name, 0, MAX_FRAMES)
    if len(config.turn_in_place_at) > MAX_FRAMES:
        raise ConfigError(f"turn_in_place_at: at most {MAX_FRAMES} turns, got {len(config.turn_in_place_at)}")
    if config.speed_m_per_s is None:
        check_frame_count(config)
    _integer(config, "step_frame", -MAX_FRAMES, MAX_FRAMES)
    width = _integer(config, "width", 1, MAX_IMAGE_SIDE)
    height = _integer(config, "height", 1, MAX_IMAGE_SIDE)
    if width * height > MAX_DEPTH_PIXELS:
        raise ConfigError(f"width, height: a {width}x{height} depth image has {width * height} pixels, more than the "
                          f"{MAX_DEPTH_PIXELS} a synthetic log renders (a few GB of memory)")
    for name in ("fx", "fy", "depth_scale", "max_range_m", "circle_radius_m", "loop_turns", "lidar_max_range_m",
                 "lidar_fov_deg"):
        _number(config, name, 0.0, open_lo=True)
    for name in ("cx", "cy", "camera_height_m", "camera_pitch_down_deg", "lidar_rosette_k",
                 "turn_in_place_deg_per_frame"):
        _number(config, name)
    _number(config, "yaw_drift_deg_per_m", -MAX_YAW_DRIFT_DEG_PER_M, MAX_YAW_DRIFT_DEG_PER_M,
            why=" (deg per m; a unit mistake? as perturb --drift-deg-per-m)")
    _number(config, "scale_drift_percent", -100.0, open_lo=True,
            why=" (at -100 % the odometry stands still, below it runs backwards)")
    for name in ("odometry_noise_m", "odometry_noise_deg", "lidar_range_sigma_m"):
        _number(config, name, 0.0)
    _number(config, "dropout_fraction", 0.0, 1.0)
    for name, size in (("step_m", 3), ("lidar_elevation_deg", 2)):
        values = getattr(config, name)
        if not isinstance(values, (tuple, list)) or len(values) != size:
            raise ConfigError(f"{name}: must be {size} numbers, got {values!r}")
        for v in values:
            _number(config, name, *((-90.0, 90.0) if name == "lidar_elevation_deg" else ()), value=v)
    if config.lidar_elevation_deg[0] > config.lidar_elevation_deg[1]:
        raise ConfigError(f"lidar_elevation_deg: (lowest, highest) beam elevation, got {config.lidar_elevation_deg}")
    for f in config.turn_in_place_at:
        _number(config, "turn_in_place_at", value=f)
    beams = _integer(config, "lidar_beams", 1, MAX_LIDAR_RAYS)
    steps = _integer(config, "lidar_azimuth_steps", 1, MAX_LIDAR_RAYS)
    if beams * steps > MAX_LIDAR_RAYS:
        raise ConfigError(f"lidar_beams, lidar_azimuth_steps: {beams} x {steps} = {beams * steps} rays a scan, more "
                          f"than the {MAX_LIDAR_RAYS} a synthetic LiDAR casts (a few GB of memory)")
    _integer(config, "lidar_points_per_scan", 1, MAX_LIDAR_RAYS)
    if config.speed_m_per_s is not None:
        _number(config, "speed_m_per_s", 0.0, open_lo=True)
    if config.scene not in ("room", "street"):
        raise ConfigError(f"scene: must be 'room' or 'street', got {config.scene!r}")


def check_frame_count(config: SyntheticLogConfig, why: str = "") -> None:
    """``n_frames`` within 2 .. :data:`MAX_FRAMES`, and the log's stamps (``start_stamp_ns + n_frames *
    frame_period_ns``, one period past the last frame) within the int64 ns a frame carries."""
    n = _integer(config, "n_frames", 2, MAX_FRAMES, why)
    end = config.start_stamp_ns + n * config.frame_period_ns
    if end > MAX_STAMP_NS:
        raise ConfigError(f"n_frames, frame_period_ns: {n} frames {config.frame_period_ns / 1e9:g} s apart from "
                          f"start_stamp_ns {config.start_stamp_ns} end at {end} ns{why}, beyond the largest stamp a "
                          f"frame can carry ({MAX_STAMP_NS} ns, the year 2262)")
