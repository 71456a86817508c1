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
stand, stop and turn in place on its way (:mod:`driftmap.sources.synthetic_motion`).
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from PIL import Image
from scipy.spatial.transform import Rotation

from driftmap import geometry
from driftmap.errors import ConfigError, DriftmapError, SourceError, parse_enum
from driftmap.frame import Frame, PinholeIntrinsics, PointAttributes, PoseEstimate, PoseSource, Provenance, SensorKind
from driftmap.preprocess.depth import InvalidFractionMonitor, depth_frame
from driftmap.sources.base import FrameSource, register_source, same_file_or_copy
from driftmap.sources.redwood import frame_errors_named, intrinsics_named, read_depth_png
from driftmap.sources.stamps import check_increasing_stamps, check_stamp_ns, read_pose_file
from driftmap.sources.synthetic_lidar import LidarPattern, cast_lidar, lidar_rays
from driftmap.sources.synthetic_motion import (  # re-exported: STREET_CORNER_RADIUS_M, STREET_PERIMETER_M, street_path
    STREET_CORNER_RADIUS_M,  # noqa: F401
    STREET_HALF_SIZE_M,
    STREET_PERIMETER_M,  # noqa: F401
    MotionSchedule,
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
        object.__setattr__(self, "lidar_pattern", parse_enum(LidarPattern, self.lidar_pattern, "lidar_pattern"))
        object.__setattr__(self, "turn_in_place_at", tuple(float(f) for f in self.turn_in_place_at))
        for name in ("stationary_start_frames", "stops", "stop_frames", "turn_in_place_frames", "turns_in_place"):
            if getattr(self, name) < 0:
                raise ConfigError(f"{name}: must be >= 0, got {getattr(self, name)}")
        if self.frame_period_ns <= 0:
            raise ConfigError(f"frame_period_ns: must be > 0, got {self.frame_period_ns}")
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


@dataclass(frozen=True)
class SceneBox:
    name: str
    min_m: tuple[float, float, float]
    max_m: tuple[float, float, float]
    glass: bool = False


ROOM_MIN_M = (-3.0, -2.5, 0.0)
ROOM_MAX_M = (3.0, 2.5, 2.6)
WALL_THICKNESS_M = 0.1
DOOR_RECESS_M = 0.05
BOARD_THICKNESS_M = 0.02


def scene_boxes() -> list[SceneBox]:
    """The room as axis-aligned boxes (world frame, z up, floor at z = 0)."""
    (x0, y0, z0), (x1, y1, z1) = ROOM_MIN_M, ROOM_MAX_M
    w = WALL_THICKNESS_M
    door_y, door_h = (-0.45, 0.45), 2.0
    boxes = [
        SceneBox("floor", (x0 - w, y0 - w, z0 - w), (x1 + w, y1 + w, z0)),
        SceneBox("ceiling", (x0 - w, y0 - w, z1), (x1 + w, y1 + w, z1 + w)),
        SceneBox("wall_-x", (x0 - w, y0 - w, z0), (x0, y1 + w, z1)),
        SceneBox("wall_-y", (x0 - w, y0 - w, z0), (x1 + w, y0, z1)),
        SceneBox("wall_+y", (x0 - w, y1, z0), (x1 + w, y1 + w, z1)),
        # +x wall with a door opening; the door panel sits DOOR_RECESS_M behind the wall face
        SceneBox("wall_+x_left", (x1, y0 - w, z0), (x1 + w, door_y[0], z1)),
        SceneBox("wall_+x_right", (x1, door_y[1], z0), (x1 + w, y1 + w, z1)),
        SceneBox("wall_+x_top", (x1, door_y[0], door_h), (x1 + w, door_y[1], z1)),
        SceneBox("door_panel", (x1 + DOOR_RECESS_M, door_y[0], z0), (x1 + DOOR_RECESS_M + 0.04, door_y[1], door_h)),
        # a glass pane just in front of the -x wall: the depth camera gets no reading there
        SceneBox("glass", (x0, -1.0, 0.8), (x0 + 0.01, 0.0, 1.8), glass=True),
        # table near the +y wall
        SceneBox("table_top", (-0.6, 1.4, 0.72), (0.6, 2.2, 0.76)),
        *[
            SceneBox(f"table_leg_{i}", (lx, ly, 0.0), (lx + 0.05, ly + 0.05, 0.72))
            for i, (lx, ly) in enumerate([(-0.6, 1.4), (0.55, 1.4), (-0.6, 2.15), (0.55, 2.15)])
        ],
        # chair near the -y wall: thin legs (2.4 cm) and a seat
        SceneBox("chair_seat", (0.8, -2.0, 0.45), (1.25, -1.55, 0.48)),
        *[
            SceneBox(f"chair_leg_{i}", (lx, ly, 0.0), (lx + 0.024, ly + 0.024, 0.45))
            for i, (lx, ly) in enumerate([(0.8, -2.0), (1.226, -2.0), (0.8, -1.574), (1.226, -1.574)])
        ],
        # a 2 cm board standing half a metre in front of the -y wall
        SceneBox("thin_board", (-1.8, -2.0 - BOARD_THICKNESS_M, 0.0), (-0.8, -2.0, 1.2)),
        # furniture along the walls: every view sees structure in all directions, so registration is
        # well-posed (a bare wall plus floor leaves the slide along the wall unobservable)
        SceneBox("shelf_-x", (x0, 1.0, 0.0), (x0 + 0.4, 2.0, 1.8)),
        SceneBox("crate_-x", (x0, -2.3, 0.0), (x0 + 0.3, -1.6, 0.9)),
        SceneBox("cabinet_+x", (x1 - 0.45, 1.2, 0.0), (x1, 2.2, 0.9)),
        SceneBox("locker_+x", (x1 - 0.4, -2.4, 0.0), (x1, -1.6, 2.0)),
        SceneBox("wall_shelf_-y", (1.8, y0, 1.2), (2.6, y0 + 0.3, 1.6)),
        SceneBox("pillar_-y", (-2.2, y0, 0.0), (-1.95, y0 + 0.25, z1)),
        SceneBox("sideboard_+y", (1.0, y1 - 0.4, 0.0), (2.2, y1, 0.85)),
        SceneBox("pillar_+y", (x0 + 0.05, y1 - 0.3, 0.0), (x0 + 0.3, y1, z1)),
        SceneBox("lamp", (-0.3, -0.3, z1 - 0.3), (0.3, 0.3, z1)),
    ]
    return boxes


STREET_FACADE_OFFSET_M = 7.0
"""Building facades stand this far from the road's centreline (+- 1 m per building)."""


def street_boxes(seed: int) -> list[SceneBox]:
    """The city block of ``scene="street"`` (world frame, z up, ground at z = 0): buildings of random width, depth
    and height inside and outside the road loop, with gaps between them, poles on both sides and parked cars,
    all drawn from ``seed`` (so the same seed gives the same town)."""
    rng = np.random.default_rng([seed, 20261123])
    a, b = STREET_HALF_SIZE_M
    d = STREET_FACADE_OFFSET_M
    boxes = [SceneBox("ground", (-a - 60, -b - 60, -0.2), (a + 60, b + 60, 0.0))]

    def along(side: str, t0: float, t1: float, off0: float, off1: float, z1: float) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """A box spanning ``t0..t1`` along a side of the loop and ``off0..off1`` outwards from its centreline."""
        lo, hi = min(off0, off1), max(off0, off1)
        if side == "-y":
            return (t0, -b - hi, 0.0), (t1, -b - lo, z1)
        if side == "+y":
            return (t0, b + lo, 0.0), (t1, b + hi, z1)
        if side == "-x":
            return (-a - hi, t0, 0.0), (-a - lo, t1, z1)
        return (a + lo, t0, 0.0), (a + hi, t1, z1)

    for side, half in (("-y", a), ("+y", a), ("-x", b), ("+x", b)):
        # outside the loop: a row of buildings past the corners; inside: a row up to the block's inner corners
        for where, t_lo, t_hi, sign in (("out", -half - 15.0, half + 15.0, 1.0), ("in", -half + d, half - d, -1.0)):
            t = t_lo + rng.uniform(0.0, 4.0)
            n = 0
            while t < t_hi - 3.0:
                width = min(rng.uniform(6.0, 16.0), t_hi - t)
                facade = d + rng.uniform(-1.0, 1.0)
                depth = rng.uniform(8.0, 12.0)
                lo, hi = along(side, t, t + width, sign * facade, sign * (facade + depth), rng.uniform(5.0, 18.0))
                boxes.append(SceneBox(f"building_{side}_{where}_{n}", lo, hi))
                t += width + rng.uniform(1.5, 5.0)
                n += 1
        # poles on both sides of the road, parked cars on the outer side
        for sign in (1.0, -1.0):
            t = -half + rng.uniform(2.0, 8.0)
            n = 0
            while t < half - 2.0:
                lo, hi = along(side, t, t + 0.3, sign * 4.5, sign * 4.8, rng.uniform(3.5, 6.0))
                boxes.append(SceneBox(f"pole_{side}_{'out' if sign > 0 else 'in'}_{n}", lo, hi))
                if sign > 0 and rng.random() < 0.5:
                    lo, hi = along(side, t + 2.0, t + 6.3, 2.6, 4.4, rng.uniform(1.4, 1.8))
                    boxes.append(SceneBox(f"car_{side}_{n}", lo, hi))
                t += rng.uniform(8.0, 15.0)
                n += 1
    return boxes


def boxes_of(config: SyntheticLogConfig) -> list[SceneBox]:
    """The scene of a log: :func:`scene_boxes` (``room``) or :func:`street_boxes` (``street``)."""
    if config.scene == "room":
        return scene_boxes()
    if config.scene == "street":
        return street_boxes(config.seed)
    raise SourceError(f"synthetic log: scene must be 'room' or 'street', got {config.scene!r}")


def _build_scene(config: SyntheticLogConfig) -> tuple[o3d.t.geometry.RaycastingScene, set[int]]:
    scene = o3d.t.geometry.RaycastingScene()
    glass_ids: set[int] = set()
    for box in boxes_of(config):
        size = np.subtract(box.max_m, box.min_m)
        mesh = o3d.geometry.TriangleMesh.create_box(*size)
        mesh.translate(box.min_m)
        gid = scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
        if box.glass:
            glass_ids.add(int(gid))
    return scene, glass_ids


def T_base_camera(config: SyntheticLogConfig) -> NDArray[np.float64]:
    """Depth camera (optical frame: x right, y down, z forward) on the robot base (x forward, z up)."""
    R_base_optical = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    R_pitch = Rotation.from_euler("y", config.camera_pitch_down_deg, degrees=True).as_matrix()
    return geometry.make_transform(R_pitch @ R_base_optical, (0.1, 0.0, config.camera_height_m))


def T_base_lidar(config: SyntheticLogConfig) -> NDArray[np.float64]:
    """LiDAR frame (x forward, z up) on the robot base: 1.3 m up in the room, 1.73 m (KITTI's) on the street."""
    return geometry.make_transform(None, (0.0, 0.0, 1.73 if config.scene == "street" else 1.3))


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


def _camera_rays(config: SyntheticLogConfig) -> NDArray[np.float64]:
    u, v = np.meshgrid(np.arange(config.width, dtype=np.float64), np.arange(config.height, dtype=np.float64))
    return np.stack([(u - config.cx) / config.fx, (v - config.cy) / config.fy, np.ones_like(u)], axis=-1).reshape(-1, 3)


def render_depth(
    scene: o3d.t.geometry.RaycastingScene,
    glass_ids: set[int],
    T_world_camera: NDArray[np.float64],
    config: SyntheticLogConfig,
    rng: np.random.Generator,
) -> NDArray[np.uint16]:
    """One noisy uint16 depth image (``config.depth_scale`` units per metre, 0 = no reading)."""
    rays_cam = _camera_rays(config)
    dirs = rays_cam @ T_world_camera[:3, :3].T  # z-component 1 in the camera => t_hit is the depth z
    origins = np.broadcast_to(T_world_camera[:3, 3], dirs.shape)
    ans = scene.cast_rays(o3d.core.Tensor(np.hstack([origins, dirs]).astype(np.float32)))
    z = ans["t_hit"].numpy().astype(np.float64)
    gid = ans["geometry_ids"].numpy()
    sigma = 0.0012 + 0.0019 * (z - 0.4) ** 2
    noisy = z + rng.normal(0.0, 1.0, z.shape) * np.where(np.isfinite(sigma), sigma, 0.0)
    invalid = ~np.isfinite(z) | (z > config.max_range_m) | (rng.random(z.shape) < config.dropout_fraction)
    for g in glass_ids:
        invalid |= gid == g
    codes = np.where(invalid, 0.0, np.rint(noisy * config.depth_scale))
    return np.clip(codes, 0, 65534).astype(np.uint16).reshape(config.height, config.width)


def render_lidar(
    scene: o3d.t.geometry.RaycastingScene,
    T_world_lidar: NDArray[np.float64],
    config: SyntheticLogConfig,
    rng: np.random.Generator,
    *,
    scan_index: int = 0,
) -> NDArray[np.float32]:
    """One LiDAR scan in the LiDAR frame: (N, 4) float32 x, y, z, intensity, of ``config.lidar_pattern`` (the
    rosette's part of the pattern depends on ``scan_index``), seen from one pose ``T_world_lidar`` (4, 4) or from
    one pose per ray of :func:`~driftmap.sources.synthetic_lidar.lidar_rays` (N, 4, 4)."""
    dirs_l, _ = lidar_rays(config, scan_index)
    return cast_lidar(scene, T_world_lidar, dirs_l, config, rng)[0]


def _render_scan(scene: o3d.t.geometry.RaycastingScene, config: SyntheticLogConfig, schedule: MotionSchedule,
                 T_world_lidar: NDArray[np.float64], k: int, stamp_ns: int,
                 rng: np.random.Generator) -> tuple[NDArray[np.float32], NDArray[np.int64] | None]:
    """Scan ``k``: its points and, with ``lidar_point_times``, their times after ``stamp_ns`` (each ray cast from
    the ground-truth pose at its capture time)."""
    dirs_l, offsets_ns = lidar_rays(config, k)
    if not config.lidar_point_times:
        return cast_lidar(scene, T_world_lidar, dirs_l, config, rng)[0], None
    poses = base_poses_at(config, np.int64(stamp_ns) + offsets_ns, schedule) @ T_base_lidar(config)
    scan, ok = cast_lidar(scene, poses, dirs_l, config, rng)
    return scan, offsets_ns[ok]


def _clear_earlier_log(out: Path) -> None:
    """Remove the frame files of an earlier synthetic log in ``out``; refuse a folder that holds anything else."""
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
    stale = [*out.glob("depth/[0-9]*.png"), *out.glob("lidar/[0-9]*.bin")]
    for f in stale:
        f.unlink()
    logger.info("%s: replacing an earlier synthetic log (%d frame files removed)", out, len(stale))


def generate_synthetic_log(out_dir: str | Path, config: SyntheticLogConfig | None = None) -> Path:
    """Write a synthetic log to ``out_dir``: a new or empty folder, or an earlier synthetic log, which is replaced
    (its frame files that the new log does not have are removed, so no stale frame stays behind). Any other
    non-empty folder is refused with :class:`SourceError` (nothing of it is touched)."""
    config = config or SyntheticLogConfig()
    out = Path(out_dir)
    _clear_earlier_log(out)
    (out / "depth").mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(config.seed)
    scene, glass_ids = _build_scene(config)
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
            scan, offsets_ns = _render_scan(scene, config, schedule, gt_base[k] @ T_base_lidar(config), k,
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
