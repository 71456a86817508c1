"""The demo on the embedded synthetic log: validate, back-project, fuse with the drifting odometry and
with the ground truth, export both maps and a top view where the doubled walls of the drifting map show.

The CLI (``driftmap demo``) prints the summary; this module only computes and writes files.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from driftmap.config import DriftmapConfig
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
    files["top_view_png"] = str(
        top_view(
            out / "top_view.png",
            [
                (f"drifting odometry: loop wall spread {odom_spread.max_m * 100:.1f} cm", odom_map),
                (f"ground truth: loop wall spread {gt_spread.max_m * 100:.1f} cm", gt_map),
            ],
            z_range_m=(0.9, 2.4),
            trajectories=[np.array([f.T_world_sensor[:3, 3] for f in frames]), gt.positions_m[:n]],
            title="driftmap demo: the same room fused with drifting odometry and with ground truth",
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
    )
    (out / "summary.json").write_text(json.dumps(result.to_json(), indent=2) + "\n")
    files["summary_json"] = str(out / "summary.json")
    return result
