#!/usr/bin/env python
"""Accuracy evaluation of ``build`` on the shared real data (prints numbers; see docs/build.md).

1. 7-Scenes redkitchen, all 1000 frames: ATE of the odometry (revision 0, frame-to-map GICP) and after loop
   closure, whether the 216-260 <-> 928-966 revisit was found and accepted; the same with KISS-ICP odometry
   (a drifting odometry, to show what the loop closure corrects).
2. The same graph with a deliberately wrong loop injected: is it rejected, how does ATE change.
3. KITTI 00 frames 0-15: relative translation error of build vs plain KISS-ICP on the same frames (without
   deskewing, and with KISS-ICP's azimuth-derived per-point times).
4. g2o pose graphs through driftmap.posegraph vs plain GTSAM LM.

Usage: .venv/bin/python scripts/evaluate_build.py [--frames 0:1000] [--skip-kiss] [--skip-kitti] [--skip-g2o]
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
from driftmap.pipeline.build import BuildConfig, build
from driftmap.registration.odometry import OdometryConfig, OdometryMethod
from driftmap.posegraph import optimize_g2o
from driftmap.sources.kitti import KittiOdometry
from driftmap.sources.sevenscenes import SevenScenes
from driftmap.store.frame_store import FrameStore


def _sevenscenes_build(folder: Path, frames: str, out: Path, gt: np.ndarray, label: str, config: BuildConfig | None = None) -> float:
    t0 = time.perf_counter()
    result = build(folder, out, frames=frames, config=config)
    seconds = time.perf_counter() - t0
    with FrameStore.open(out) as store:
        odo = trajectory_errors(store.poses(0), gt)
        lc = trajectory_errors(store.poses(), gt)
    loop = [x for x in result.loops if x["accepted"] and 200 <= x["a"] <= 280 and 900 <= x["b"] <= 990]
    print(f"7-Scenes {frames}, {label}: {result.n_frames} frames in {seconds:.1f} s ({result.n_frames / seconds:.1f} frames/s)")
    print(f"  ATE odometry {odo.ate_rmse_m * 100:.2f} cm -> after loop closure {lc.ate_rmse_m * 100:.2f} cm "
          f"(target <= 3 cm); RPE {odo.rpe_trans_rmse_m * 100:.2f} -> {lc.rpe_trans_rmse_m * 100:.2f} cm")
    print(f"  loops tried {result.loops_tried}, accepted {result.loops_accepted}, rejected by graph {result.loops_rejected_by_graph}; "
          f"216-260 <-> 928-966 found: {bool(loop)} ({len(loop)} pairs); information scale {result.information_scale}")
    print("  stages: " + ", ".join(f"{k} {v:.1f}s" for k, v in result.seconds_per_stage.items()))
    return lc.ate_rmse_m


def sevenscenes(frames: str, tmp: Path, kiss: bool = True) -> None:
    folder = shared_datasets_dir() / "7scenes-redkitchen"
    gt = SevenScenes(folder, frames=frames).ground_truth().poses
    ate_lc = _sevenscenes_build(folder, frames, tmp / "kitchen", gt, "default (frame-to-map GICP odometry)")
    if kiss:
        _sevenscenes_build(folder, frames, tmp / "kitchen_kiss", gt, "KISS-ICP odometry",
                           BuildConfig(odometry=OdometryConfig(method=OdometryMethod.KISS)))
    wrong = np.eye(4)
    wrong[:3, 3] = (0.8, -0.4, 0.3)
    from driftmap.registration.loops import select_keyframes

    with FrameStore.open(tmp / "kitchen") as store:
        rows = select_keyframes(store.poses(0), BuildConfig().loop_closure)
        ids = [int(store.frame_ids[r]) for r in rows]
    a, b = ids[len(ids) // 4], ids[3 * len(ids) // 4]
    result_w = build(folder, tmp / "kitchen_wrong", frames=frames, inject_wrong_loop=(a, b, wrong))
    with FrameStore.open(tmp / "kitchen_wrong") as store:
        lc_w = trajectory_errors(store.poses(), gt)
    inj = [x for x in result_w.loops if x["kind"] == "injected"][0]
    print(f"  wrong loop {a}<->{b} injected: kept by graph {inj.get('kept_by_graph')}, weight {inj.get('graph_weight')}; "
          f"ATE {lc_w.ate_rmse_m * 100:.2f} cm vs {ate_lc * 100:.2f} cm without it "
          f"({(lc_w.ate_rmse_m / ate_lc - 1) * 100:+.1f} %, allowed +10 %)")


def kitti(tmp: Path) -> None:
    folder = shared_datasets_dir() / "kitti-00-frames0-15"
    src = KittiOdometry(folder)
    gt = src.ground_truth().poses
    result = build(folder, tmp / "kitti")
    with FrameStore.open(tmp / "kitti") as store:
        ours = store.poses()
    from kiss_icp.config import KISSConfig
    from kiss_icp.kiss_icp import KissICP

    def plain_kiss(deskew: bool) -> np.ndarray:
        cfg = KISSConfig()
        cfg.data.max_range, cfg.data.min_range, cfg.data.deskew = 100.0, 0.5, deskew
        cfg.mapping.voxel_size = 1.0
        kiss = KissICP(cfg)
        poses = []
        for f in src:
            pts = f.points_sensor.astype(np.float64)
            # KISS-ICP's own KITTI loader: per-point time from the azimuth, 0..1 over the sweep
            t = 0.5 * (-np.arctan2(pts[:, 1], pts[:, 0]) / np.pi + 1.0) if deskew else np.zeros(len(pts))
            kiss.register_frame(pts, t)
            poses.append(kiss.last_pose.copy())
        return np.array(poses)

    plain, plain_deskewed = plain_kiss(False), plain_kiss(True)

    def rte(poses: np.ndarray) -> float:
        errs = []
        for i in range(len(poses) - 1):
            e = geometry.invert(geometry.invert(gt[i]) @ gt[i + 1]) @ (geometry.invert(poses[i]) @ poses[i + 1])
            errs.append(np.linalg.norm(e[:3, 3]))
        length = np.sum(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1))
        return float(np.sum(errs) / length * 100)

    print(f"KITTI 00 frames 0-15: relative translation error build {rte(ours):.3f} % vs plain KISS-ICP {rte(plain):.3f} % "
          f"(deskewed with azimuth times: {rte(plain_deskewed):.3f} %; loops accepted {result.loops_accepted})")


def g2o() -> None:
    folder = shared_datasets_dir() / "pose-graphs"
    for name in ("parking-garage.g2o", "sphere_bignoise_vertex3.g2o", "cubicle.g2o"):
        t0 = time.perf_counter()
        # cubicle.g2o holds information matrices that are not positive definite: read as gtsam.readG2o does
        res = optimize_g2o(folder / name, non_pd_information="gtsam" if name == "cubicle.g2o" else "refuse")
        print(f"{name}: error {res.initial_error:.4g} -> {res.final_error:.4g} (converged {res.converged}, "
              f"{time.perf_counter() - t0:.1f} s)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", default="0:1000")
    parser.add_argument("--skip-kiss", action="store_true", help="skip the 7-Scenes build with KISS-ICP odometry")
    parser.add_argument("--skip-kitti", action="store_true")
    parser.add_argument("--skip-g2o", action="store_true")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="driftmap-eval-") as tmp:
        sevenscenes(args.frames, Path(tmp), kiss=not args.skip_kiss)
        if not args.skip_kitti:
            kitti(Path(tmp))
    if not args.skip_g2o:
        g2o()


if __name__ == "__main__":
    main()
