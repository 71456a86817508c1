"""The embedded default data: a deterministic synthetic drifting-robot log.

A robot drives a loop (a little more than one full circle) through a furnished room. Open3D's
``RaycastingScene`` renders what a Kinect-like depth camera sees (axial noise
``sigma_z = 0.0012 + 0.0019 (z - 0.4)^2`` m after Nguyen et al. 2012, millimetre quantisation, random
dropouts, no reading on a glass patch) and, optionally, a 16-beam spinning LiDAR. The room has walls,
floor, ceiling, a table, a chair with thin legs, a 2 cm board and a 5 cm door recess.

Two pose streams are written: the ground truth and a drifting odometry (known yaw drift in deg/m, scale
drift in %, and one known translation step at a known frame). Everything is seeded, so the same config
gives the same log.

On-disk layout (a folder)::

    synthetic.json        metadata: config, intrinsics, depth_scale, T_base_sensor, frames (id, stamp, file)
    depth/NNNNNN.png      uint16 depth, depth_scale units per metre (0 = no reading)
    groundtruth.txt       TUM, T_world_sensor of the depth camera (ground truth)
    odometry.txt          TUM, T_world_sensor of the depth camera from the drifting odometry
    lidar/NNNNNN.bin      optional, KITTI layout float32 x y z intensity in the LiDAR frame
    lidar/NNNNNN.time.bin with lidar_point_times: int64 ns per point after the frame's stamp (the scan's start)

A LiDAR may spin (beams x azimuths) or draw a rosette (:mod:`driftmap.sources.synthetic_lidar`); the robot may
stand, stop and turn in place on its way (:mod:`driftmap.sources.synthetic_motion`). The scene's boxes are in
:mod:`driftmap.sources.synthetic_scene` (:func:`build_scene` makes the ray-casting scene of a config), the sensors'
rendering in :mod:`driftmap.sources.synthetic_render`; this module re-exports their names.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from PIL import Image
from scipy.spatial.transform import Rotation

from driftmap import geometry
from driftmap.errors import ConfigError, DriftmapError, SourceError, parse_enum
from driftmap.frame import Frame, PinholeIntrinsics, PointAttributes, PoseEstimate, PoseSource, Provenance, SensorKind
from driftmap.preprocess.depth import InvalidFractionMonitor, depth_frame
from driftmap.sources.base import FrameSource, register_source, same_file_or_copy
from driftmap.sources.depth_folder import frame_errors_named, intrinsics_named, read_depth_png
from driftmap.sources.point_fields import far_points
from driftmap.sources.stamps import MAX_STAMP_NS, check_increasing_stamps, check_stamp_ns, read_pose_file
from driftmap.sources.synthetic_lidar import LidarPattern, cast_lidar, lidar_rays  # noqa: F401 (re-exported)
from driftmap.sources.synthetic_motion import (  # re-exported: STREET_CORNER_RADIUS_M, STREET_PERIMETER_M, street_path
    STREET_CORNER_RADIUS_M,  # noqa: F401
    STREET_HALF_SIZE_M,  # noqa: F401
    STREET_PERIMETER_M,  # noqa: F401
    MotionSchedule,  # noqa: F401
    ScanMotion,
    base_poses_at,
    frame_base_poses,
    frames_for_speed,
    motion_schedule,
    moving_scans,
    non_moving_scans,
    path_length_m,
    street_path,  # noqa: F401
)
from driftmap.sources.synthetic_render import (  # re-exported: T_base_camera, render_depth, render_lidar, ...
    T_base_camera,
    T_base_lidar,
    render_depth,
    render_lidar,  # noqa: F401
    render_scan,
)
from driftmap.sources.synthetic_scene import (  # re-exported: the scene's boxes and sizes
    BOARD_THICKNESS_M,  # noqa: F401
    DOOR_RECESS_M,  # noqa: F401
    ROOM_MAX_M,  # noqa: F401
    ROOM_MIN_M,  # noqa: F401
    STREET_FACADE_OFFSET_M,  # noqa: F401
    WALL_THICKNESS_M,  # noqa: F401
    SceneBox,  # noqa: F401
    boxes_of,
    build_scene,
    scene_boxes,  # noqa: F401
    street_boxes,  # noqa: F401
)
from driftmap.trajectory import Trajectory, read_tum, write_tum

logger = logging.getLogger(__name__)

FORMAT_NAME = "driftmap-synthetic"
FORMAT_VERSION = 1
METADATA_FILE = "synthetic.json"
LIDAR_TIME_CONVENTION = {
    "file": "lidar/NNNNNN.time.bin: one little-endian int64 per point of lidar/NNNNNN.bin, in its order",
    "unit": "ns",
    "relative_to": "the frame's stamp_ns, the scan's start: the point at offset t was measured from "
                   "T_world_lidar(stamp_ns + t); offsets lie in [0, frame_period_ns)",
}
"""What a log with per-point LiDAR times records about them (``synthetic.json``'s ``lidar_time``)."""


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
        if not self.lidar and (self.lidar_point_times or self.lidar_pattern != LidarPattern.SPINNING):
            raise ConfigError("lidar: lidar_pattern='rosette' and lidar_point_times need lidar=True")
        if self.speed_m_per_s is not None:
            if not self.speed_m_per_s > 0.0:
                raise ConfigError(f"speed_m_per_s: must be > 0, got {self.speed_m_per_s}")
            object.__setattr__(self, "n_frames", frames_for_speed(self, self.speed_m_per_s))
            check_frame_count(self, f" (the frames speed_m_per_s={self.speed_m_per_s:g} needs at a period of "
                                    f"{self.frame_period_ns / 1e9:g} s)")
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
    for name in ("cx", "cy", "camera_height_m", "camera_pitch_down_deg", "yaw_drift_deg_per_m", "scale_drift_percent",
                 "lidar_rosette_k", "turn_in_place_deg_per_frame"):
        _number(config, name)
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


def ground_truth_base_poses(config: SyntheticLogConfig) -> NDArray[np.float64]:
    """``T_world_base`` at the frame stamps along a counter-clockwise circle (the room) or the street loop, heading
    along the tangent (plus any in-place turn); the stationary start, stops and turns of the config included
    (:mod:`driftmap.sources.synthetic_motion`)."""
    return frame_base_poses(config)


def ground_truth_base_poses_at(config: SyntheticLogConfig, stamps_ns: NDArray[np.int64]) -> NDArray[np.float64]:
    """Ground-truth ``T_world_base`` at any ``stamps_ns`` of the log (from its first stamp to one period after the
    last): the continuous trajectory the per-point LiDAR times were rendered with. The LiDAR point at offset ``t``
    of the scan stamped ``stamp_ns`` was measured from ``ground_truth_base_poses_at(config, stamp_ns + t) @
    T_base_lidar(config)``."""
    return base_poses_at(config, stamps_ns)


def drifting_base_poses(config: SyntheticLogConfig, gt: NDArray[np.float64], rng: np.random.Generator) -> NDArray[np.float64]:
    """Integrate the ground-truth increments with yaw drift, scale drift, noise and one translation step."""
    odom = np.empty_like(gt)
    odom[0] = gt[0]
    for k in range(1, len(gt)):
        delta = geometry.invert(gt[k - 1]) @ gt[k]
        dist = float(np.linalg.norm(delta[:3, 3]))
        t = delta[:3, 3] * (1.0 + config.scale_drift_percent / 100.0) + rng.normal(0.0, config.odometry_noise_m, 3) * [1, 1, 0]
        if k == config.step_frame:
            t = t + np.asarray(config.step_m)
        yaw_err = math.radians(config.yaw_drift_deg_per_m * dist + rng.normal(0.0, config.odometry_noise_deg))
        R = Rotation.from_euler("z", yaw_err).as_matrix() @ delta[:3, :3]
        odom[k] = odom[k - 1] @ geometry.make_transform(R, t)
    return odom


def _clear_earlier_log(out: Path, overwrite: bool) -> None:
    """Check that ``out`` may be written (a new or empty folder; with ``overwrite`` an earlier synthetic log) and
    remove the files of an earlier synthetic log; refuse anything else before touching it."""
    if not out.exists():
        return
    if not out.is_dir():
        raise SourceError(f"{out}: is a file, not a folder for a synthetic log")
    if not any(out.iterdir()):
        return
    try:
        earlier = json.loads((out / METADATA_FILE).read_text()).get("format") == FORMAT_NAME
    except (OSError, ValueError, AttributeError):
        earlier = False
    if not earlier:
        raise SourceError(f"{out}: is not empty and holds no synthetic log ({METADATA_FILE}); give a new or empty folder")
    if not overwrite:
        raise ConfigError(f"{out}: a synthetic log exists: pass overwrite=True / --overwrite to replace it (or give "
                          f"a new or empty folder)")
    stale = [*out.glob("depth/[0-9]*.png"), *out.glob("lidar/[0-9]*.bin")]
    for f in stale:
        f.unlink()
    logger.info("%s: replacing an earlier synthetic log (%d frame files removed)", out, len(stale))


def generate_synthetic_log(out_dir: str | Path, config: SyntheticLogConfig | None = None, *,
                           overwrite: bool = False) -> Path:
    """Write a synthetic log to ``out_dir``, a new or empty folder. An existing synthetic log there is refused with
    :class:`ConfigError` unless ``overwrite`` (``driftmap synth --overwrite``), which replaces it (its frame files
    that the new log does not have are removed, so no stale frame stays behind). Any other non-empty folder is
    refused with :class:`SourceError`, with or without ``overwrite`` (nothing of it is touched)."""
    config = config or SyntheticLogConfig()
    out = Path(out_dir)
    _clear_earlier_log(out, overwrite)
    (out / "depth").mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(config.seed)
    scene, glass_ids = build_scene(config)
    T_bc = T_base_camera(config)
    schedule = motion_schedule(config)
    gt_base = frame_base_poses(config, schedule)
    odom_base = drifting_base_poses(config, gt_base, rng)
    stamps = config.start_stamp_ns + config.frame_period_ns * np.arange(config.n_frames, dtype=np.int64)
    frames_meta = []
    if config.lidar:
        (out / "lidar").mkdir(exist_ok=True)
    for k in range(config.n_frames):
        depth = render_depth(scene, glass_ids, gt_base[k] @ T_bc, config, rng)
        name = f"depth/{k:06d}.png"
        Image.fromarray(depth).save(out / name, optimize=True)
        entry = {"frame_id": k, "stamp_ns": int(stamps[k]), "depth": name}
        if config.lidar:
            scan, offsets_ns = render_scan(scene, config, schedule, gt_base[k] @ T_base_lidar(config), k,
                                           int(stamps[k]), rng)
            entry["lidar"] = f"lidar/{k:06d}.bin"
            scan.tofile(out / entry["lidar"])
            if offsets_ns is not None:
                entry["lidar_time"] = f"lidar/{k:06d}.time.bin"
                offsets_ns.astype("<i8").tofile(out / entry["lidar_time"])
        frames_meta.append(entry)
    write_tum(out / "groundtruth.txt", Trajectory(stamps, gt_base @ T_bc))
    write_tum(out / "odometry.txt", Trajectory(stamps, odom_base @ T_bc))
    meta = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "config": asdict(config),
        "intrinsics": PinholeIntrinsics(config.fx, config.fy, config.cx, config.cy, config.width, config.height).to_dict(),
        "depth_scale": config.depth_scale,
        "sensor_name": "depth_camera",
        "sensor_frame": "camera_depth_optical_frame",
        "base_frame": "base_link",
        "T_base_sensor": T_bc.tolist(),
        "T_base_lidar": T_base_lidar(config).tolist(),
        "ground_truth": "groundtruth.txt",
        "odometry": "odometry.txt",
        "scene": [asdict(b) for b in boxes_of(config)],
        "frames": frames_meta,
    }
    if config.lidar and config.lidar_point_times:
        meta["lidar_time"] = LIDAR_TIME_CONVENTION
    if schedule.kinds.count(ScanMotion.MOVE) != len(schedule.kinds):  # only logs that stand or turn somewhere
        meta["scan_motion"] = [m.value for m in schedule.kinds[: config.n_frames]]
    (out / METADATA_FILE).write_text(json.dumps(meta, indent=1))
    logger.info("wrote synthetic log with %d frames to %s", config.n_frames, out)
    return out


class SyntheticLog(FrameSource):
    """Reader for a synthetic log folder: frames carry the drifting odometry as their pose estimate.

    Ground truth is available separately through :meth:`ground_truth` and is never used as the estimate.
    ``sensor="lidar"`` yields the LiDAR scans instead (logs generated with ``lidar=True``).
    """

    format_name = "synthetic"

    def __init__(self, path: str | Path, *, min_depth_m: float = 0.3, max_depth_m: float = 8.0, sensor: str = "depth",
                 pixel_stride: int = 1, frames: str | slice | None = None, lenient: bool = False):
        super().__init__(str(path), frames=frames, lenient=lenient)
        self.pixel_stride = int(pixel_stride)
        self.path = Path(path)
        self.min_depth_m = min_depth_m
        self.max_depth_m = max_depth_m
        if sensor not in ("depth", "lidar"):
            raise SourceError(f"{self.path}: sensor must be 'depth' or 'lidar', got {sensor!r}")
        self.sensor = sensor
        meta_file = self.path / METADATA_FILE
        try:
            self.meta = json.loads(meta_file.read_text())
        except FileNotFoundError as exc:
            raise SourceError(f"{meta_file}: not a driftmap synthetic log (metadata file missing)") from exc
        except (OSError, ValueError) as exc:  # JSON that does not parse, text that is not UTF-8
            raise SourceError(f"{meta_file}: corrupt metadata ({exc})") from exc
        if not isinstance(self.meta, dict) or self.meta.get("format") != FORMAT_NAME:
            found = self.meta.get("format") if isinstance(self.meta, dict) else type(self.meta).__name__
            raise SourceError(f"{meta_file}: format is {found!r}, expected {FORMAT_NAME!r}")
        try:
            self._read_metadata(meta_file)
        except (KeyError, TypeError, ValueError, OverflowError, DriftmapError) as exc:
            if isinstance(exc, SourceError):
                raise
            raise SourceError(f"{meta_file}: corrupt metadata ({type(exc).__name__}: {exc})") from exc
        self._monitor = InvalidFractionMonitor()

    def _read_metadata(self, meta_file: Path) -> None:
        """The fields of ``synthetic.json`` this source uses, checked: the frames' ids and stamps (every stamp a
        frame's, :func:`driftmap.sources.stamps.check_stamp_ns`, strictly increasing), intrinsics, extrinsics."""
        frames = self.meta["frames"]
        if not isinstance(frames, list) or not all(isinstance(e, dict) for e in frames):
            raise SourceError(f"{meta_file}: field frames must be a list of frame entries")
        for k, entry in enumerate(frames):
            where = f"{meta_file} (frames[{k}].stamp_ns)"
            if not isinstance(entry.get("stamp_ns"), int) or not isinstance(entry.get("frame_id"), int):
                raise SourceError(f"{where}: frame_id and stamp_ns must be integers, got {entry.get('frame_id')!r}, "
                                  f"{entry.get('stamp_ns')!r}")
            check_stamp_ns(entry["stamp_ns"], where)
        check_increasing_stamps([e["stamp_ns"] for e in frames], [e["frame_id"] for e in frames], str(meta_file),
                                lenient=False)
        self.intrinsics = intrinsics_named(f"{meta_file} (intrinsics)", **self.meta["intrinsics"])
        self.depth_scale = float(self.meta["depth_scale"])
        self.T_base_sensor = geometry.as_rigid(np.asarray(self.meta["T_base_sensor"], dtype=np.float64),
                                               f"{meta_file} (T_base_sensor)")
        self.config = SyntheticLogConfig(**{**self.meta["config"], **{k: tuple(v) for k, v in self.meta["config"].items()
                                                                      if isinstance(v, list)}})
        self._odometry = read_pose_file(read_tum, self.path / str(self.meta["odometry"]))
        if len(self._odometry) != len(self.meta["frames"]):
            raise SourceError(
                f"{self.path / self.meta['odometry']}: {len(self._odometry)} poses for {len(self.meta['frames'])} frames"
            )

    def _count(self) -> int:
        return len(self.meta["frames"])

    def _frame_id(self, index: int) -> int:
        return int(self.meta["frames"][index]["frame_id"])

    def _stamp_ns(self, index: int) -> int:
        return int(self.meta["frames"][index]["stamp_ns"])

    def _load(self, index: int) -> Frame:
        return self.lidar_frame(index) if self.sensor == "lidar" else self.depth_frame(index, self._monitor)

    def read_depth(self, index: int) -> NDArray[np.uint16]:
        entry = self.meta["frames"][index]
        return read_depth_png(self.path / str(entry.get("depth")), entry["frame_id"])

    def depth_frame(self, index: int, monitor: InvalidFractionMonitor | None = None) -> Frame:
        """The depth frame at underlying ``index`` (validated and back-projected)."""
        entry = self.meta["frames"][index]
        pose = PoseEstimate(self._odometry.poses[index], revision=0, source=PoseSource.ODOMETRY)
        depth = self.read_depth(index)
        with frame_errors_named(self.path / str(entry["depth"]), int(entry["frame_id"])):
            return self._depth_frame(index, depth, pose, monitor)

    def _depth_frame(self, index: int, depth: NDArray[np.uint16], pose: PoseEstimate,
                     monitor: InvalidFractionMonitor | None) -> Frame:
        entry = self.meta["frames"][index]
        return depth_frame(
            depth,
            self.intrinsics,
            frame_id=int(entry["frame_id"]),
            stamp_ns=int(entry["stamp_ns"]),
            pose=pose,
            sensor_name=self.meta["sensor_name"],
            sensor_frame=self.meta["sensor_frame"],
            T_base_sensor=self.T_base_sensor,
            depth_scale=self.depth_scale,
            min_depth_m=self.min_depth_m,
            max_depth_m=self.max_depth_m,
            provenance=Provenance(str((self.path / entry["depth"]).resolve()), index),
            monitor=monitor,
            pixel_stride=self.pixel_stride,
        )

    def lidar_frame(self, index: int) -> Frame:
        """The LiDAR scan of frame ``index`` (only in logs generated with ``lidar=True``)."""
        entry = self.meta["frames"][index]
        if "lidar" not in entry:
            raise SourceError(f"{self.path}: this log has no LiDAR scans (generate with lidar=True)")
        file = self.path / str(entry["lidar"])
        try:
            raw = np.fromfile(file, dtype="<f4")
        except OSError as exc:
            raise SourceError(f"{file}: cannot read the LiDAR scan of frame {entry['frame_id']} ({exc})") from exc
        if raw.size % 4:
            raise SourceError(f"{file}: size {raw.nbytes} bytes is not a multiple of 16 (x, y, z, intensity float32)")
        scan = raw.reshape(-1, 4)
        attributes = PointAttributes()
        if "lidar_time" in entry:  # logs generated with lidar_point_times
            time_file = self.path / entry["lidar_time"]
            try:
                offsets_ns = np.fromfile(time_file, dtype="<i8").astype(np.int64)
            except OSError as exc:
                raise SourceError(f"{time_file}: cannot read the point times of frame {entry['frame_id']} "
                                  f"({exc})") from exc
            if len(offsets_ns) != len(scan):
                raise SourceError(f"{time_file}: {len(offsets_ns)} point times for the {len(scan)} points of {file}")
            attributes = PointAttributes(time_offset_ns=offsets_ns)
        far = far_points(scan[:, :3], f"{file} (frame {entry['frame_id']})")  # as every point reader
        if far is not None:
            scan = scan[~far]
            if attributes.time_offset_ns is not None:
                attributes = PointAttributes(time_offset_ns=attributes.time_offset_ns[~far])
        T_base_lidar = np.asarray(self.meta["T_base_lidar"], dtype=np.float64)
        T_world_lidar = self._odometry.poses[index] @ self._T_camera_lidar()
        return Frame(
            frame_id=int(entry["frame_id"]),
            stamp_ns=int(entry["stamp_ns"]),
            sensor_name="lidar",
            sensor_kind=SensorKind.LIDAR,
            points_sensor=scan[:, :3],
            pose=PoseEstimate(T_world_lidar, revision=0, source=PoseSource.ODOMETRY),
            T_base_sensor=T_base_lidar,
            sensor_frame="lidar",
            attributes=attributes,
            provenance=Provenance(str(file.resolve()), index),
        )

    def _T_camera_lidar(self) -> NDArray[np.float64]:
        """Where the LiDAR sits in the depth camera's frame: the log's pose files hold the camera's poses, and
        ``T_world_camera @ T_camera_lidar`` is the LiDAR's."""
        return geometry.invert(self.T_base_sensor) @ np.asarray(self.meta["T_base_lidar"], dtype=np.float64)

    def _of_selected_sensor(self, trajectory: Trajectory) -> Trajectory:
        """A depth-camera trajectory of the log as ``T_world_sensor`` of this source's sensor, selected frames only."""
        idx = np.asarray(self._indices(), dtype=np.int64)
        ids = np.array([int(f["frame_id"]) for f in self.meta["frames"]], dtype=np.int64)[idx]
        poses = trajectory.poses[idx]
        if self.sensor == "lidar":  # the files hold the depth camera's poses; the LiDAR sits elsewhere on the base
            poses = poses @ self._T_camera_lidar()
        return Trajectory(trajectory.stamps_ns[idx], poses, ids)

    def pose_file_in_sensor_frame(self, poses_file: Path, trajectory: Trajectory) -> Trajectory:
        """The log's own ``groundtruth.txt`` / ``odometry.txt`` (or byte-identical copies) hold the depth camera's
        poses: for the LiDAR they are converted (``T_world_cam @ inv(T_base_cam) @ T_base_lidar``), with an info
        line. Any other file is taken as it is."""
        if self.sensor != "lidar":
            return trajectory
        own = [self.path / self.meta[key] for key in ("ground_truth", "odometry")]
        if not any(same_file_or_copy(poses_file, f) for f in own):
            return trajectory
        logger.info("%s is the synthetic log's depth-camera pose file: rows converted to the LiDAR frame "
                    "(T_base_lidar of %s)", poses_file, self.path / METADATA_FILE)
        return Trajectory(trajectory.stamps_ns, trajectory.poses @ self._T_camera_lidar(), trajectory.frame_ids)

    def odometry(self) -> Trajectory:
        """The drifting odometry as ``T_world_sensor`` of the selected frames (the frames' own pose estimates)."""
        return self._of_selected_sensor(self._odometry)

    def ground_truth(self) -> Trajectory:
        """Ground-truth ``T_world_sensor`` of the selected frames, for the sensor this source yields (the depth
        camera, or with ``sensor="lidar"`` the LiDAR); for evaluation only."""
        return self._of_selected_sensor(read_pose_file(read_tum, self.path / str(self.meta["ground_truth"])))


def _detect(path: Path) -> bool:
    return (path / METADATA_FILE).is_file()


register_source("synthetic", _detect, SyntheticLog, "driftmap's synthetic drifting-robot log (synthetic.json + depth/)",
                converts_pose_files=True)
