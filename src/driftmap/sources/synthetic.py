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
from driftmap.errors import SourceError
from driftmap.frame import Frame, PinholeIntrinsics, PoseEstimate, PoseSource, Provenance, SensorKind
from driftmap.preprocess.depth import InvalidFractionMonitor, depth_frame
from driftmap.sources.base import FrameSource, register_source, same_file_or_copy
from driftmap.trajectory import Trajectory, read_tum, write_tum

logger = logging.getLogger(__name__)

FORMAT_NAME = "driftmap-synthetic"
FORMAT_VERSION = 1
METADATA_FILE = "synthetic.json"


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


STREET_HALF_SIZE_M = (35.0, 25.0)
"""Half the size of the street loop's rounded rectangle (x, y), centreline of the road."""
STREET_CORNER_RADIUS_M = 10.0
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


def street_path(s_m: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(xy, heading)`` at arc lengths ``s_m`` along the street loop: the rounded rectangle of
    :data:`STREET_HALF_SIZE_M` and :data:`STREET_CORNER_RADIUS_M`, counter-clockwise from the middle of its
    -y side (heading +x)."""
    a, b = STREET_HALF_SIZE_M
    r = STREET_CORNER_RADIUS_M
    # (length, start xy, start heading, curvature) of the nine pieces
    pieces = [(a - r, (0.0, -b), 0.0, 0.0), (math.pi * r / 2, (a - r, -b), 0.0, 1 / r),
              (2 * (b - r), (a, -b + r), math.pi / 2, 0.0), (math.pi * r / 2, (a, b - r), math.pi / 2, 1 / r),
              (2 * (a - r), (a - r, b), math.pi, 0.0), (math.pi * r / 2, (-a + r, b), math.pi, 1 / r),
              (2 * (b - r), (-a, b - r), 1.5 * math.pi, 0.0), (math.pi * r / 2, (-a, -b + r), 1.5 * math.pi, 1 / r),
              (a - r, (-a + r, -b), 0.0, 0.0)]
    perimeter = sum(p[0] for p in pieces)
    s = np.mod(np.asarray(s_m, dtype=np.float64), perimeter)
    xy = np.zeros((len(s), 2))
    heading = np.zeros(len(s))
    start = 0.0
    for length, (x0, y0), h0, kappa in pieces:
        on = (s >= start) & (s <= start + length)
        u = s[on] - start
        if kappa == 0.0:
            xy[on] = np.stack([x0 + u * math.cos(h0), y0 + u * math.sin(h0)], axis=1)
            heading[on] = h0
        else:  # a left turn of radius 1 / kappa
            h = h0 + u * kappa
            xy[on] = np.stack([x0 + (np.sin(h) - math.sin(h0)) / kappa, y0 - (np.cos(h) - math.cos(h0)) / kappa], axis=1)
            heading[on] = h
        start += length
    return xy, heading


STREET_PERIMETER_M = float(4 * (STREET_HALF_SIZE_M[0] - STREET_CORNER_RADIUS_M)
                           + 4 * (STREET_HALF_SIZE_M[1] - STREET_CORNER_RADIUS_M) + 2 * math.pi * STREET_CORNER_RADIUS_M)


def ground_truth_base_poses(config: SyntheticLogConfig) -> NDArray[np.float64]:
    """``T_world_base`` along a counter-clockwise circle (the room) or the street loop, heading along the
    tangent."""
    if config.scene == "street":
        xy, heading = street_path(np.linspace(0.0, STREET_PERIMETER_M * config.loop_turns, config.n_frames))
        poses = np.tile(np.eye(4), (config.n_frames, 1, 1))
        poses[:, :3, :3] = Rotation.from_euler("z", heading[:, None]).as_matrix()
        poses[:, :2, 3] = xy
        return poses
    angles = np.linspace(0.0, 2.0 * math.pi * config.loop_turns, config.n_frames)
    poses = np.tile(np.eye(4), (config.n_frames, 1, 1))
    for k, a in enumerate(angles):
        poses[k, :3, :3] = Rotation.from_euler("z", a + math.pi / 2).as_matrix()
        poses[k, :3, 3] = (config.circle_radius_m * math.cos(a), config.circle_radius_m * math.sin(a), 0.0)
    return poses


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
) -> NDArray[np.float32]:
    """One spinning-LiDAR scan in the LiDAR frame: (N, 4) float32 x, y, z, intensity."""
    elev = np.radians(np.linspace(*config.lidar_elevation_deg, config.lidar_beams))
    azim = np.linspace(0.0, 2 * math.pi, config.lidar_azimuth_steps, endpoint=False)
    ee, aa = np.meshgrid(elev, azim, indexing="ij")
    dirs_l = np.stack([np.cos(ee) * np.cos(aa), np.cos(ee) * np.sin(aa), np.sin(ee)], axis=-1).reshape(-1, 3)
    dirs_w = dirs_l @ T_world_lidar[:3, :3].T
    origins = np.broadcast_to(T_world_lidar[:3, 3], dirs_w.shape)
    ans = scene.cast_rays(o3d.core.Tensor(np.hstack([origins, dirs_w]).astype(np.float32)))
    r = ans["t_hit"].numpy().astype(np.float64)
    ok = np.isfinite(r) & (r < config.lidar_max_range_m)
    normals = ans["primitive_normals"].numpy()
    r_noisy = r + rng.normal(0.0, config.lidar_range_sigma_m, r.shape)
    pts = dirs_l[ok] * r_noisy[ok, None]
    intensity = np.abs(np.einsum("ij,ij->i", normals[ok], dirs_w[ok]))
    return np.hstack([pts, intensity[:, None]]).astype(np.float32)


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
    gt_base = ground_truth_base_poses(config)
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
            scan = render_lidar(scene, gt_base[k] @ T_base_lidar(config), config, rng)
            entry["lidar"] = f"lidar/{k:06d}.bin"
            scan.tofile(out / entry["lidar"])
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
        except json.JSONDecodeError as exc:
            raise SourceError(f"{meta_file}: corrupt metadata ({exc})") from exc
        if self.meta.get("format") != FORMAT_NAME:
            raise SourceError(f"{meta_file}: format is {self.meta.get('format')!r}, expected {FORMAT_NAME!r}")
        self.intrinsics = PinholeIntrinsics(**self.meta["intrinsics"])
        self.depth_scale = float(self.meta["depth_scale"])
        self.T_base_sensor = np.asarray(self.meta["T_base_sensor"], dtype=np.float64)
        self.config = SyntheticLogConfig(**{**self.meta["config"], **{k: tuple(v) for k, v in self.meta["config"].items()
                                                                      if isinstance(v, list)}})
        self._odometry = read_tum(self.path / self.meta["odometry"])
        if len(self._odometry) != len(self.meta["frames"]):
            raise SourceError(
                f"{self.path / self.meta['odometry']}: {len(self._odometry)} poses for {len(self.meta['frames'])} frames"
            )
        self._monitor = InvalidFractionMonitor()

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
        file = self.path / entry["depth"]
        try:
            return np.asarray(Image.open(file))
        except OSError as exc:
            raise SourceError(f"{file}: cannot read depth image of frame {entry['frame_id']} ({exc})") from exc

    def depth_frame(self, index: int, monitor: InvalidFractionMonitor | None = None) -> Frame:
        """The depth frame at underlying ``index`` (validated and back-projected)."""
        entry = self.meta["frames"][index]
        pose = PoseEstimate(self._odometry.poses[index], revision=0, source=PoseSource.ODOMETRY)
        return depth_frame(
            self.read_depth(index),
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
        file = self.path / entry["lidar"]
        raw = np.fromfile(file, dtype=np.float32)
        if raw.size % 4:
            raise SourceError(f"{file}: size {raw.nbytes} bytes is not a multiple of 16 (x, y, z, intensity float32)")
        scan = raw.reshape(-1, 4)
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
        return self._of_selected_sensor(read_tum(self.path / self.meta["ground_truth"]))


def _detect(path: Path) -> bool:
    return (path / METADATA_FILE).is_file()


register_source("synthetic", _detect, SyntheticLog, "driftmap's synthetic drifting-robot log (synthetic.json + depth/)",
                converts_pose_files=True)
