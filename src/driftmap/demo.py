"""The demo on the embedded synthetic log: validate, back-project, fuse with the drifting odometry and
with the ground truth; build a store with the odometry as revision 0, close the loop (pose graph, revision
1, frames re-transformed); export the maps, the corrected trajectory and a top view where the doubled
walls of the drifting map show and disappear after the correction.

The CLI (``driftmap demo``) prints the summary; this module only computes and writes files.
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from driftmap.config import DriftmapConfig
from driftmap.diagnostics.trajectory_metrics import trajectory_errors
from driftmap.pipeline.build import BuildConfig, build
from driftmap.registration.loops import LoopClosureConfig
from driftmap.store.frame_store import FrameStore
from driftmap.datasets import embedded_dir
from driftmap.diagnostics.walls import WallSpread, wall_spread
from driftmap.frame import Frame
from driftmap.map.fusion import FusedCloud, fuse, write_cloud
from driftmap.preprocess.depth import InvalidFractionMonitor
from driftmap.report import top_view
from driftmap.sources.synthetic import ROOM_MAX_M, ROOM_MIN_M, SyntheticLog, generate_synthetic_log

logger = logging.getLogger(__name__)

EMBEDDED_LOG_NAME = "synthetic-loop"

#: The +y wall is seen at the start of the loop and again at its end: where drift shows as a double wall.
LOOP_WALL = {"normal": (0.0, 1.0, 0.0), "offset_m": ROOM_MAX_M[1], "tangent": (1.0, 0.0, 0.0), "z_range_m": (0.9, 2.4),
             "tangent_range_m": (ROOM_MIN_M[0] + 0.4, ROOM_MAX_M[0] - 0.4)}


#: The synthetic log is short (60 frames at 5 Hz): loops may be 20 frames apart, keyframes every 20 cm.
DEMO_BUILD_CONFIG = BuildConfig(loop_closure=LoopClosureConfig(min_gap_frames=20, keyframe_distance_m=0.2, keyframe_angle_deg=15))


def embedded_log_path(generate_if_missing: bool = True) -> Path:
    """The repository's synthetic log; regenerated (deterministically) if it is not there."""
    path = embedded_dir() / EMBEDDED_LOG_NAME
    if not (path / "synthetic.json").exists():
        if not generate_if_missing:
            raise FileNotFoundError(path)
        logger.info("embedded log missing at %s; generating it", path)
        generate_synthetic_log(path)
    return path


@dataclass(frozen=True)
class DemoResult:
    out_dir: Path
    n_frames: int
    n_points: int
    mean_invalid_fraction: float
    flagged_frames: list[int]
    wall_spread_odometry_m: float
    wall_spread_ground_truth_m: float
    wall_spread_odometry_max_m: float
    wall_spread_ground_truth_max_m: float
    files: dict[str, str]
    seconds: float
    loops_accepted: int = 0
    wall_spread_corrected_m: float | None = None
    wall_spread_corrected_max_m: float | None = None
    ate_odometry_m: float | None = None
    ate_corrected_m: float | None = None

    def to_json(self) -> dict:
        d = asdict(self)
        d["out_dir"] = str(self.out_dir)
        return d


def _loop_wall_spread(cloud: FusedCloud) -> WallSpread:
    return wall_spread(cloud.points_world, **LOOP_WALL)


def run_demo(
    out_dir: str | Path,
    *,
    log_path: str | Path | None = None,
    max_frames: int | None = None,
    config: DriftmapConfig | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> DemoResult:
    """Run the demo; ``progress(done, total)`` is called after each frame."""
    t0 = time.perf_counter()
    config = config or DriftmapConfig()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    log = SyntheticLog(Path(log_path) if log_path else embedded_log_path(),
                       min_depth_m=config.depth.min_depth_m, max_depth_m=config.depth.max_depth_m)
    n = len(log) if max_frames is None else min(max_frames, len(log))
    monitor = InvalidFractionMonitor()
    frames: list[Frame] = []
    for i in range(n):
        frames.append(log.depth_frame(i, monitor))
        if progress:
            progress(i + 1, n)
    gt = log.ground_truth()
    gt_poses = {f.frame_id: gt.poses[i] for i, f in enumerate(frames)}
    odom_map = fuse(frames)
    gt_map = fuse(frames, gt_poses)
    voxel = config.map.export_voxel_size_m
    files = {
        "map_odometry_ply": str(write_cloud(out / "map_odometry.ply", odom_map.voxel_downsample(voxel).points_world)),
        "map_ground_truth_ply": str(write_cloud(out / "map_ground_truth.ply", gt_map.voxel_downsample(voxel).points_world)),
    }
    odom_spread, gt_spread = _loop_wall_spread(odom_map), _loop_wall_spread(gt_map)
    # loop closure: the drifting odometry is stored as revision 0, the pose graph adds revision 1 and the
    # stored frames are re-transformed (not rebuilt)
    store_dir = out / "store"
    if store_dir.exists():
        shutil.rmtree(store_dir)
    built = build(log.path, store_dir, poses_from_source=True, frames=f"0:{n}", config=DEMO_BUILD_CONFIG)
    corrected_map = odom_map
    corrected_spread = None
    ate_odometry = ate_corrected = None
    with FrameStore.open(store_dir) as store:
        gt_rows = gt.poses[: len(store)]
        ate_odometry = trajectory_errors(store.poses(0), gt_rows).ate_rmse_m if len(store) >= 3 else None
        if built.loop_revision is not None:
            view = store.map(built.loop_revision)
            corrected_map = FusedCloud(view.points_world.copy(), view.point_frame_ids())
            corrected_spread = _loop_wall_spread(corrected_map)
            files["map_corrected_ply"] = str(view.export(out / "map_corrected.ply", voxel_size_m=voxel))
            ate_corrected = trajectory_errors(store.poses(), gt_rows).ate_rmse_m
        files["trajectory_corrected_tum"] = str(store.export_trajectory(out / "trajectory_corrected.tum"))
    files["store"] = str(store_dir)
    panels = [(f"drifting odometry: loop wall spread {odom_spread.max_m * 100:.1f} cm", odom_map)]
    if corrected_spread is not None:
        panels.append((f"after loop closure: {corrected_spread.max_m * 100:.1f} cm", corrected_map))
    panels.append((f"ground truth: {gt_spread.max_m * 100:.1f} cm", gt_map))
    files["top_view_png"] = str(
        top_view(
            out / "top_view.png",
            panels,
            z_range_m=(0.9, 2.4),
            title="driftmap demo: the same room fused with drifting odometry, after loop closure, and with ground truth",
        )
    )
    files["config_json"] = str(config.write(out / "config.json"))
    result = DemoResult(
        out_dir=out.resolve(),
        n_frames=n,
        n_points=len(odom_map),
        mean_invalid_fraction=float(np.mean([f.quality.invalid_fraction for f in frames])),
        flagged_frames=[f.frame_id for f in frames if f.quality.flagged],
        wall_spread_odometry_m=odom_spread.median_m,
        wall_spread_ground_truth_m=gt_spread.median_m,
        wall_spread_odometry_max_m=odom_spread.max_m,
        wall_spread_ground_truth_max_m=gt_spread.max_m,
        files=files,
        seconds=time.perf_counter() - t0,
        loops_accepted=built.loops_accepted,
        wall_spread_corrected_m=None if corrected_spread is None else corrected_spread.median_m,
        wall_spread_corrected_max_m=None if corrected_spread is None else corrected_spread.max_m,
        ate_odometry_m=ate_odometry,
        ate_corrected_m=ate_corrected,
    )
    (out / "summary.json").write_text(json.dumps(result.to_json(), indent=2) + "\n")
    files["summary_json"] = str(out / "summary.json")
    return result
