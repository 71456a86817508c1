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
rendering in :mod:`driftmap.sources.synthetic_render`, the config and the bounds of its fields in
:mod:`driftmap.sources.synthetic_config`; this module re-exports their names.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from PIL import Image
from scipy.spatial.transform import Rotation

from driftmap import geometry
from driftmap.errors import ConfigError, DriftmapError, SourceError
from driftmap.frame import Frame, PinholeIntrinsics, PointAttributes, PoseEstimate, PoseSource, Provenance, SensorKind
from driftmap.preprocess.depth import InvalidFractionMonitor, depth_frame
from driftmap.sources.base import FrameSource, register_source, same_file_or_copy
from driftmap.sources.depth_folder import frame_errors_named, intrinsics_named, read_depth_png
from driftmap.sources.point_fields import far_points
from driftmap.sources.stamps import check_increasing_stamps, check_stamp_ns, read_pose_file
from driftmap.sources.synthetic_config import (  # re-exported: the config and the bounds of its fields
    MAX_DEPTH_PIXELS,  # noqa: F401
    MAX_FRAME_PERIOD_NS,  # noqa: F401
    MAX_FRAMES,  # noqa: F401
    MAX_IMAGE_SIDE,  # noqa: F401
    MAX_LIDAR_RAYS,  # noqa: F401
    MAX_SEED,  # noqa: F401
    MAX_YAW_DRIFT_DEG_PER_M,  # noqa: F401
    MIN_FRAME_PERIOD_NS,  # noqa: F401
    SyntheticLogConfig,
    check_config_fields,  # noqa: F401
    check_frame_count,  # noqa: F401
)
from driftmap.sources.synthetic_lidar import LidarPattern, cast_lidar, lidar_rays  # noqa: F401 (re-exported)
from driftmap.sources.synthetic_motion import (  # re-exported: STREET_CORNER_RADIUS_M, STREET_PERIMETER_M, street_path
    STREET_CORNER_RADIUS_M,  # noqa: F401
    STREET_HALF_SIZE_M,  # noqa: F401
    STREET_PERIMETER_M,  # noqa: F401
    MotionSchedule,  # noqa: F401
    ScanMotion,
    base_poses_at,
    frame_base_poses,
    frames_for_speed,  # noqa: F401
    motion_schedule,
    moving_scans,  # noqa: F401
    non_moving_scans,  # noqa: F401
    path_length_m,  # noqa: F401
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
    except (OSError, ValueError, RecursionError, AttributeError):
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
        "config": _config_json(config),
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


WORLD_CHANGE_FIELDS = ("door_open", "chair_moved")
"""Config fields written to ``synthetic.json`` only when set: a log without them is byte for byte as before."""


def _config_json(config: SyntheticLogConfig) -> dict:
    out = asdict(config)
    for name in WORLD_CHANGE_FIELDS:
        if not out[name]:
            del out[name]
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
        except (OSError, ValueError, RecursionError) as exc:  # JSON that does not parse, text that is not UTF-8
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
        return replace(trajectory, poses=trajectory.poses @ self._T_camera_lidar())

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
