#!/usr/bin/env python
"""Accuracy evaluation of ``build`` on the shared real data (prints numbers; see docs/build.md).

1. 7-Scenes redkitchen, all 1000 frames: ATE of the odometry (revision 0) and after loop closure, whether
   the 216-260 <-> 928-966 revisit was found and accepted.
2. The same graph with a deliberately wrong loop injected: is it rejected, how does ATE change.
3. KITTI 00 frames 0-15: relative translation error of build vs plain KISS-ICP on the same frames.
4. g2o pose graphs through driftmap.posegraph vs plain GTSAM LM.

Usage: .venv/bin/python scripts/evaluate_build.py [--frames 0:1000] [--skip-kitti] [--skip-g2o]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from driftmap import geometry
from driftmap.datasets import shared_datasets_dir
from driftmap.diagnostics.trajectory_metrics import trajectory_errors
from driftmap.pipeline.build import build
from driftmap.posegraph import optimize_g2o
from driftmap.sources.kitti import KittiOdometry
from driftmap.sources.sevenscenes import SevenScenes
from driftmap.store.frame_store import FrameStore


def sevenscenes(frames: str, tmp: Path) -> None:
    folder = shared_datasets_dir() / "7scenes-redkitchen"
    gt = SevenScenes(folder, frames=frames).ground_truth().poses
    t0 = time.perf_counter()
    result = build(folder, tmp / "kitchen", frames=frames)
    seconds = time.perf_counter() - t0
    with FrameStore.open(tmp / "kitchen") as store:
        odo = trajectory_errors(store.poses(0), gt)
        lc = trajectory_errors(store.poses(), gt)
    loop = [x for x in result.loops if x["accepted"] and 200 <= x["a"] <= 280 and 900 <= x["b"] <= 990]
    print(f"7-Scenes {frames}: {result.n_frames} frames in {seconds:.1f} s ({result.n_frames / seconds:.1f} frames/s)")
    print(f"  ATE odometry (KISS-ICP) {odo.ate_rmse_m * 100:.2f} cm -> after loop closure {lc.ate_rmse_m * 100:.2f} cm "
          f"(target <= 3 cm); RPE {odo.rpe_trans_rmse_m * 100:.2f} -> {lc.rpe_trans_rmse_m * 100:.2f} cm")
    print(f"  loops tried {result.loops_tried}, accepted {result.loops_accepted}, rejected by graph {result.loops_rejected_by_graph}; "
          f"216-260 <-> 928-966 found: {bool(loop)} ({len(loop)} pairs)")
    print(f"  stages: " + ", ".join(f"{k} {v:.1f}s" for k, v in result.seconds_per_stage.items()))
    wrong = np.eye(4)
    wrong[:3, 3] = (0.8, -0.4, 0.3)
    from driftmap.registration.loops import select_keyframes
    from driftmap.pipeline.build import BuildConfig

    with FrameStore.open(tmp / "kitchen") as store:
        rows = select_keyframes(store.poses(0), BuildConfig().loop_closure)
        ids = [int(store.frame_ids[r]) for r in rows]
    a, b = ids[len(ids) // 4], ids[3 * len(ids) // 4]
    result_w = build(folder, tmp / "kitchen_wrong", frames=frames, inject_wrong_loop=(a, b, wrong))
    with FrameStore.open(tmp / "kitchen_wrong") as store:
        lc_w = trajectory_errors(store.poses(), gt)
    inj = [x for x in result_w.loops if x["kind"] == "injected"][0]
    print(f"  wrong loop {a}<->{b} injected: kept by graph {inj.get('kept_by_graph')}, weight {inj.get('graph_weight')}; "
          f"ATE {lc_w.ate_rmse_m * 100:.2f} cm vs {lc.ate_rmse_m * 100:.2f} cm without it "
          f"({(lc_w.ate_rmse_m / lc.ate_rmse_m - 1) * 100:+.1f} %, allowed +10 %)")


def kitti(tmp: Path) -> None:
    folder = shared_datasets_dir() / "kitti-00-frames0-15"
    src = KittiOdometry(folder)
    gt = src.ground_truth().poses
    result = build(folder, tmp / "kitti")
    with FrameStore.open(tmp / "kitti") as store:
        ours = store.poses()
    from kiss_icp.config import KISSConfig
    from kiss_icp.kiss_icp import KissICP

    cfg = KISSConfig()
    cfg.data.max_range, cfg.data.min_range, cfg.data.deskew = 100.0, 0.5, False
    cfg.mapping.voxel_size = 1.0
    kiss = KissICP(cfg)
    plain = []
    for f in src:
        kiss.register_frame(f.points_sensor.astype(np.float64), np.zeros(f.n_points))
        plain.append(kiss.last_pose.copy())
    plain = np.array(plain)

    def rte(poses: np.ndarray) -> float:
        errs = []
        for i in range(len(poses) - 1):
            e = geometry.invert(geometry.invert(gt[i]) @ gt[i + 1]) @ (geometry.invert(poses[i]) @ poses[i + 1])
            errs.append(np.linalg.norm(e[:3, 3]))
        length = np.sum(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1))
        return float(np.sum(errs) / length * 100)

    print(f"KITTI 00 frames 0-15: relative translation error build {rte(ours):.3f} % vs plain KISS-ICP {rte(plain):.3f} % "
          f"(loops accepted {result.loops_accepted})")


def g2o() -> None:
    folder = shared_datasets_dir() / "pose-graphs"
    for name in ("parking-garage.g2o", "sphere_bignoise_vertex3.g2o", "cubicle.g2o"):
        t0 = time.perf_counter()
        res = optimize_g2o(folder / name)
        print(f"{name}: error {res.initial_error:.4g} -> {res.final_error:.4g} (converged {res.converged}, "
              f"{time.perf_counter() - t0:.1f} s)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", default="0:1000")
    parser.add_argument("--skip-kitti", action="store_true")
    parser.add_argument("--skip-g2o", action="store_true")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="driftmap-eval-") as tmp:
        sevenscenes(args.frames, Path(tmp))
        if not args.skip_kitti:
            kitti(Path(tmp))
    if not args.skip_g2o:
        g2o()


if __name__ == "__main__":
    main()
