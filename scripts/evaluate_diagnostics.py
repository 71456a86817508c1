#!/usr/bin/env python
"""The perturbation protocol for the double-wall and drift diagnostics on real data (see docs/diagnostics.md).

Perturb exactly one geometric assumption of a real 7-Scenes map (redkitchen, the data set's KinectFusion
poses as the reference), diagnose, and record what changed:

1. the reference map itself: share of surface voxels flagged (sampling seeds 0..2), regions, change points;
   the exact-ground-truth synthetic log as a clean control;
2. translation steps of 1/2/4/8 cm at frames after the first loop segment, along the three dominant surface
   normals: detection rate of the affected voxels, false flags, separation error, located step frame;
3. rotation steps of 0.25/0.5/1 deg: located step frame;
4. linear drift 0.25/0.5/1/2 %/m and 0.05/0.1/0.2 deg/m over seeds (random directions / axes): smearing
   score rank correlation, drift-rate estimate;
5. depth-scale and focal-length errors applied to the frames before storing them (build time);
6. with ``--build``: ``driftmap build`` (loop closure on three odometries: the default frame-to-map GICP,
   KISS-ICP, and a frame-to-map GICP with a 30-frame window that drifts into a loop double wall) on frames
   ``--build-frames`` (default 0:1000:4), revision 0 and the loop-closed revision, against the reference-posed
   map of the same frames.

Usage: .venv/bin/python scripts/evaluate_diagnostics.py [--frames 0:1000:5] [--quick] [--build [--build-frames F]] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.stats import spearmanr

from driftmap.datasets import shared_datasets_dir
from driftmap.demo import embedded_log_path
from driftmap.diagnostics import perturb
from driftmap.diagnostics.attribution import attribute
from driftmap.diagnostics.double_wall import DiagnosticCloud, SamplingConfig, detect_double_walls
from driftmap.diagnostics.report import diagnose_store
from driftmap.sources.sevenscenes import SevenScenes
from driftmap.sources.synthetic import SyntheticLog
from driftmap.store.frame_store import FrameStore

KITCHEN = shared_datasets_dir() / "7scenes-redkitchen"


def dominant_normals(cloud: DiagnosticCloud, poses: np.ndarray, n: int = 3) -> list[np.ndarray]:
    return perturb.dominant_normals(cloud.place(poses).normals_world, n)


def build_store(path: Path, frames: str, transform=None) -> FrameStore:
    source = SevenScenes(KITCHEN, pixel_stride=4, poses_from_ground_truth=True, frames=frames)
    with FrameStore.create(path) as store:
        for frame in source:
            store.append(transform(frame) if transform else frame)
    return FrameStore.open(path)


def fmt_pct(x: float) -> str:
    return f"{100 * x:.1f} %" if np.isfinite(x) else "-"


def reference_map(store: FrameStore, cloud: DiagnosticCloud, report: dict) -> None:
    print("\n== 1. the reference-posed map (7-Scenes KinectFusion poses) ==")
    base = store.poses(0)
    fractions = []
    for seed in (0, 1, 2):
        c = cloud if seed == 0 else DiagnosticCloud.from_store(store, SamplingConfig(seed=seed))
        r = detect_double_walls(c.place(base))
        fractions.append(r.fraction_flagged)
        if seed == 0:
            first = r
    print(f"  flagged: {', '.join(fmt_pct(f) for f in fractions)} of {first.voxels_evaluated} surface voxels (seeds 0, 1, 2; "
          f"target <= 1 %); smearing {1000 * first.smearing_score_m:.2f} mm "
          f"({', '.join(f'{k:g} m: {1000 * v:.2f}' for k, v in first.score_per_scale_m.items())}; frame to frame "
          f"{1000 * first.frame_smearing_score_m:.2f} mm)")
    for k, region in enumerate(first.regions[:5]):
        print(f"  region {k + 1}: {100 * region.separation_m:.1f} +- {100 * region.separation_sigma_m:.1f} cm, frames "
              f"{region.frames_a.min()}-{region.frames_a.max()} vs {region.frames_b.min()}-{region.frames_b.max()}, {region.n_voxels} voxels")
    a = attribute(cloud.place(base))
    print(f"  change points: {[(c.frame_id, round(100 * c.jump_m, 1)) for c in a.change_points]} (frame, cm); "
          f"revisited {100 * a.revisit_fraction:.0f} %; drift estimate {a.drift.percent_per_m:.2f} %/m {a.drift.deg_per_m:.3f} deg/m "
          f"(per-frame noise floor {100 * a.drift.noise_floor_m:.2f} cm, {a.drift.noise_floor_deg:.2f} deg)")
    report["reference"] = {"fraction_flagged_seeds": fractions, "voxels_evaluated": first.voxels_evaluated,
                           "smearing_score_m": first.smearing_score_m, "smearing_score_frames_m": first.frame_smearing_score_m,
                           "change_points": [(c.frame_id, c.jump_m) for c in a.change_points],
                           "drift_rate": {"percent_per_m": a.drift.percent_per_m, "deg_per_m": a.drift.deg_per_m,
                                          "noise_floor_m": a.drift.noise_floor_m, "noise_floor_deg": a.drift.noise_floor_deg}}


def synthetic_control(report: dict) -> None:
    print("\n== 1b. control: the synthetic log (exact ground truth; 2 cm board, 5 cm door recess, glass) ==")
    log = SyntheticLog(embedded_log_path())
    cloud = DiagnosticCloud.from_frames(list(log))
    gt, odo = log.ground_truth().poses, log.odometry().poses
    rg, ro = detect_double_walls(cloud.place(gt)), detect_double_walls(cloud.place(odo))
    print(f"  ground truth: {fmt_pct(rg.fraction_flagged)} flagged, smearing {1000 * rg.smearing_score_m:.2f} mm "
          f"(frame to frame {1000 * rg.frame_smearing_score_m:.2f}); drifting odometry: {fmt_pct(ro.fraction_flagged)} flagged, "
          f"smearing {1000 * ro.smearing_score_m:.2f} mm (frame to frame {1000 * ro.frame_smearing_score_m:.2f}), largest region "
          f"{100 * ro.regions[0].separation_m:.1f} cm (frames {ro.regions[0].frames_a.min()}-{ro.regions[0].frames_a.max()} vs "
          f"{ro.regions[0].frames_b.min()}-{ro.regions[0].frames_b.max()})")
    report["synthetic"] = {"gt_fraction_flagged": rg.fraction_flagged, "gt_smearing_m": rg.smearing_score_m,
                           "odometry_fraction_flagged": ro.fraction_flagged, "odometry_smearing_m": ro.smearing_score_m}


def steps(store: FrameStore, cloud: DiagnosticCloud, report: dict, quick: bool, step_frames: tuple[int, ...] | None = None) -> None:
    print("\n== 2. translation steps (affected = normal within 25 deg, both sides seen, consistent before) ==")
    base = store.poses(0)
    ids = cloud.frame_ids
    base_result = detect_double_walls(cloud.place(base))
    base_cps = {c.frame_id for c in attribute(cloud.place(base)).change_points}
    step_frames = step_frames or ((500,) if quick else (400, 500, 600, 700))
    mags = (0.02, 0.04) if quick else (0.01, 0.02, 0.04, 0.08)
    dirs = dominant_normals(cloud, base)
    rows = []
    for mag in mags:
        agg = {"affected": 0, "detected": 0, "affected_all": 0, "detected_all": 0, "false": 0, "evaluated": 0,
               "err": [], "ok": [], "located": 0, "located_top": 0, "runs": 0}
        for frame in step_frames:
            k = int(np.searchsorted(ids, frame))
            for d in dirs:
                step = mag * d
                placed = cloud.place(perturb.translation_step(base, k, step))
                result = detect_double_walls(placed)
                for s in perturb.evaluate_step(cloud, base, k, step, result):
                    agg["affected"] += s.n_affected
                    agg["detected"] += s.n_detected
                    agg["err"] += list(s.separation_error_m)
                    agg["ok"] += list(s.within_tolerance())
                for s, s0 in zip(perturb.evaluate_step(cloud, base, k, step, result, max_baseline_m=np.inf,
                                                       max_baseline_smear_m=None), base_result.scales):
                    agg["affected_all"] += s.n_affected
                    agg["detected_all"] += s.n_detected
                    agg["evaluated"] += s.n_evaluated
                agg["false"] += sum(int((sc.flagged & ~s.affected).sum()) for sc, s in
                                    zip(result.scales, perturb.evaluate_step(cloud, base, k, step, result, max_baseline_m=np.inf,
                                                                             max_baseline_smear_m=None)))
                cps = attribute(placed).change_points
                near = [c for c in cps if abs(int(np.searchsorted(ids, c.frame_id)) - k) <= 2]
                new = [c for c in cps if c.frame_id not in base_cps]
                agg["located"] += bool(near)
                agg["located_top"] += bool(new) and abs(int(np.searchsorted(ids, max(new, key=lambda c: c.z_score).frame_id)) - k) <= 2
                agg["runs"] += 1
        err = np.abs(np.array(agg["err"])) if agg["err"] else np.zeros(1)
        rows.append({"step_m": mag, "detection_rate": agg["detected"] / max(agg["affected"], 1), "n_affected": agg["affected"],
                     "detection_rate_all_affected": agg["detected_all"] / max(agg["affected_all"], 1),
                     "n_affected_all": agg["affected_all"], "false_flag_rate": agg["false"] / max(agg["evaluated"], 1),
                     "separation_error_median_m": float(np.median(err)), "separation_error_p90_m": float(np.percentile(err, 90)),
                     "within_tolerance": float(np.mean(agg["ok"])) if agg["ok"] else float("nan"),
                     "step_located": agg["located"] / agg["runs"], "step_located_as_top_new": agg["located_top"] / agg["runs"]})
    print(f"  step frames {list(step_frames)}, directions {[np.round(d, 2).tolist() for d in dirs]}")
    print(f"  {'step':>6} {'detected':>16} {'(all affected)':>16} {'false flags':>12} {'sep. error med/p90':>20} "
          f"{'<=max(5mm,15%)':>15} {'step frame +-2':>15} {'(top new cp)':>13}")
    for r in rows:
        print(f"  {100 * r['step_m']:4.0f}cm {fmt_pct(r['detection_rate']):>9} of {r['n_affected']:<4} "
              f"{fmt_pct(r['detection_rate_all_affected']):>9} of {r['n_affected_all']:<5} {fmt_pct(r['false_flag_rate']):>11} "
              f"{1000 * r['separation_error_median_m']:8.1f}/{1000 * r['separation_error_p90_m']:.1f} mm "
              f"{fmt_pct(r['within_tolerance']):>14} {fmt_pct(r['step_located']):>15} {fmt_pct(r['step_located_as_top_new']):>13}")
    print("  targets: >= 60 % detected at 2 cm, >= 90 % at 4 cm; separation error <= max(5 mm, 15 %); step within +-2 frames")
    report["translation_steps"] = rows


def rotation_steps(store: FrameStore, cloud: DiagnosticCloud, report: dict) -> None:
    print("\n== 3. rotation steps at frame 500 (random axes) ==")
    base = store.poses(0)
    ids = cloud.frame_ids
    k = int(np.searchsorted(ids, 500))
    out = []
    for deg in (0.25, 0.5, 1.0):
        located, flagged = 0, []
        for seed in range(3):
            axis = np.random.default_rng(seed).normal(size=3)
            rot = deg * axis / np.linalg.norm(axis)
            placed = cloud.place(perturb.rotation_step(base, k, rot))
            flagged.append(detect_double_walls(placed).fraction_flagged)
            cps = attribute(placed).change_points
            located += any(abs(int(np.searchsorted(ids, c.frame_id)) - k) <= 2 for c in cps)
        out.append({"step_deg": deg, "step_located": located / 3, "fraction_flagged": float(np.mean(flagged))})
        print(f"  {deg:.2f} deg: step frame found within +-2 frames in {located}/3 runs; {fmt_pct(np.mean(flagged))} voxels flagged")
    report["rotation_steps"] = out


def drifts(store: FrameStore, cloud: DiagnosticCloud, report: dict, quick: bool) -> None:
    print("\n== 4. linear drift (random directions / axes; score must rise with the drift) ==")
    base = store.poses(0)
    seeds = range(3 if quick else 5)
    for kind, mags in (("percent_per_m", (0.25, 0.5, 1.0, 2.0)), ("deg_per_m", (0.05, 0.1, 0.2))):
        x, y, yr, yf, monotone, monotone_r, monotone_f, estimates = [], [], [], [], 0, 0, 0, {m: [] for m in mags}
        for seed in seeds:
            v = np.random.default_rng(seed).normal(size=3)
            v /= np.linalg.norm(v)
            scores, revisit, frame = [], [], []
            for m in mags:
                poses = (perturb.linear_drift(base, percent_per_m=m, direction=v) if kind == "percent_per_m"
                         else perturb.linear_drift(base, deg_per_m=m, axis=v))
                placed = cloud.place(poses)
                result = detect_double_walls(placed)
                scores.append(result.smearing_score_m)
                revisit.append(result.revisit_score_m(1.0))
                frame.append(result.frame_smearing_score_m)
                a = attribute(placed)
                estimates[m].append(a.drift.percent_per_m if kind == "percent_per_m" else a.drift.deg_per_m)
            monotone += bool(np.all(np.diff(scores) > 0))
            monotone_r += bool(np.all(np.diff(revisit) > 0))
            monotone_f += bool(np.all(np.diff(frame) > 0))
            x += list(mags)
            y += scores
            yr += revisit
            yf += frame
        rho, rho_r, rho_f = spearmanr(x, y).statistic, spearmanr(x, yr).statistic, spearmanr(x, yf).statistic
        n = len(list(seeds))
        print(f"  {kind}: smearing score Spearman {rho:.3f} over {n} seeds (target >= 0.95), strictly increasing in "
              f"{monotone}/{n} seeds, {1000 * min(y):.2f}..{1000 * max(y):.2f} mm; frame-to-frame score Spearman {rho_f:.3f}, "
              f"increasing in {monotone_f}/{n}, {1000 * min(yf):.2f}..{1000 * max(yf):.2f} mm; its revisit-only form "
              f"Spearman {rho_r:.3f}, increasing in {monotone_r}/{n}")
        print("    drift-rate estimate (median over seeds): " + ", ".join(
            f"{m:g} -> {np.median([e for e in estimates[m] if e is not None]):.3f}" for m in mags))
        report[f"drift_{kind}"] = {"spearman": rho, "monotone_seeds": monotone, "spearman_revisit": rho_r,
                                   "monotone_seeds_revisit": monotone_r, "spearman_frames": rho_f,
                                   "monotone_seeds_frames": monotone_f, "seeds": n,
                                   "estimates": {str(m): estimates[m] for m in mags}}


def sensor_errors(tmp: Path, frames: str, report: dict) -> None:
    print("\n== 5. sensor errors at build time (every frame's points changed before storing) ==")
    out = []
    for name, transform in (("none", None),
                            ("depth scale 1.01", lambda f: perturb.with_depth_scale_error(f, 1.01)),
                            ("depth scale 1.03", lambda f: perturb.with_depth_scale_error(f, 1.03)),
                            ("focal 1.01", lambda f: perturb.with_focal_error(f, 1.01)),
                            ("focal 1.03", lambda f: perturb.with_focal_error(f, 1.03))):
        store = build_store(tmp / f"sensor-{name.replace(' ', '-')}", frames, transform)
        d = diagnose_store(store, 0)
        out.append({"perturbation": name, "smearing_score_m": d.smearing_score_m,
                    "smearing_score_frames_m": d.double_walls.frame_smearing_score_m,
                    "fraction_flagged": d.double_walls.fraction_flagged})
        print(f"  {name:18s} smearing {1000 * d.smearing_score_m:.2f} mm (frame to frame "
              f"{1000 * d.double_walls.frame_smearing_score_m:.2f}), flagged {fmt_pct(d.double_walls.fraction_flagged)}")
        store.close()
    report["sensor_errors"] = out


#: the odometries compared in section 6: the default frame-to-map GICP, KISS-ICP, and the windowed frame-to-map
#: GICP that drifts into a loop double wall (tests/test_diagnose_loop_7scenes.py)
BUILD_ODOMETRIES = {
    "gicp_map (default)": None,
    "kiss": {"method": "kiss"},
    "gicp_map, 30-frame window": {"method": "gicp_map", "gicp_map_horizon_frames": 30},
}


def build_comparison(tmp: Path, report: dict, frames: str) -> None:
    from driftmap.diagnostics.trajectory_metrics import trajectory_errors
    from driftmap.pipeline.build import BuildConfig, build

    print(f"\n== 6. driftmap build (odometry + loop closure) vs the reference poses, frames {frames} ==")
    build(KITCHEN, tmp / "reference", frames=frames, poses_from_source=True, loop_closure=False)
    ref = FrameStore.open(tmp / "reference")
    d_ref = diagnose_store(ref, 0)
    print(f"  {'reference poses':34s} smearing {1000 * d_ref.smearing_score_m:.2f} mm (frame to frame "
          f"{1000 * d_ref.double_walls.frame_smearing_score_m:.2f}), flagged {fmt_pct(d_ref.double_walls.fraction_flagged)}")
    report["build"] = {"frames": frames, "reference": {"smearing_score_m": d_ref.smearing_score_m,
                                                       "smearing_score_frames_m": d_ref.double_walls.frame_smearing_score_m,
                                                       "fraction_flagged": d_ref.double_walls.fraction_flagged}}
    for label, odometry in BUILD_ODOMETRIES.items():
        out = tmp / f"built-{len(report['build'])}"
        config = BuildConfig.model_validate({"odometry": odometry} if odometry else {})
        build(KITCHEN, out, frames=frames, config=config)
        built = FrameStore.open(out)
        cloud = DiagnosticCloud.from_store(built)  # the same samples for both revisions
        entry = {}
        for rev in sorted({0, built.head}):
            d = diagnose_store(built, rev, cloud=cloud)
            ate = trajectory_errors(built.poses(rev), ref.poses(0)).ate_rmse_m
            big = [r for r in d.double_walls.regions if r.separation_m >= 0.03]
            largest = ""
            if big:
                r = max(big, key=lambda r: r.separation_m)
                largest = (f" (largest {100 * r.separation_m:.1f} cm, frames {r.frames_a.min()}-{r.frames_a.max()} vs "
                           f"{r.frames_b.min()}-{r.frames_b.max()})")
            name = f"{label}, rev {rev}"
            print(f"  {name:34s} smearing {1000 * d.smearing_score_m:.2f} mm ({d.smearing_score_m / d_ref.smearing_score_m:.2f}x "
                  f"the reference; frame to frame {1000 * d.double_walls.frame_smearing_score_m:.2f} mm, "
                  f"{d.double_walls.frame_smearing_score_m / d_ref.double_walls.frame_smearing_score_m:.2f}x), "
                  f"flagged {fmt_pct(d.double_walls.fraction_flagged)}, ATE {100 * ate:.2f} cm, "
                  f"regions >= 3 cm: {len(big)}{largest}")
            entry[f"rev{rev}"] = {"smearing_score_m": d.smearing_score_m,
                                  "smearing_score_frames_m": d.double_walls.frame_smearing_score_m, "fraction_flagged": d.double_walls.fraction_flagged,
                                  "ate_rmse_m": ate, "regions_3cm": len(big)}
        report["build"][label] = entry
        built.close()
    ref.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", default="0:1000:5", help="7-Scenes frames (START:STOP:STEP)")
    parser.add_argument("--quick", action="store_true", help="fewer step frames, magnitudes and seeds")
    parser.add_argument("--build", action="store_true", help="also run driftmap build (three odometries + loop closure), a few minutes")
    parser.add_argument("--build-frames", default="0:1000:4", help="frames of the --build comparison")
    parser.add_argument("--json", type=Path, help="write the numbers here")
    parser.add_argument("--step-frames", help="frame ids of the injected steps, comma-separated (default 400,500,600,700)")
    args = parser.parse_args()
    report: dict = {"frames": args.frames}
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="driftmap-eval-") as tmp_name:
        tmp = Path(tmp_name)
        store = build_store(tmp / "kitchen", args.frames)
        cloud = DiagnosticCloud.from_store(store)
        print(f"7-Scenes redkitchen {args.frames}: {len(store)} frames, {cloud.n_points} samples")
        reference_map(store, cloud, report)
        synthetic_control(report)
        steps(store, cloud, report, args.quick,
              tuple(int(v) for v in args.step_frames.split(",")) if args.step_frames else None)
        rotation_steps(store, cloud, report)
        drifts(store, cloud, report, args.quick)
        sensor_errors(tmp, args.frames, report)
        if args.build:
            build_comparison(tmp, report, args.build_frames)
        store.close()
    print(f"\n{time.perf_counter() - t0:.0f} s")
    if args.json:
        args.json.write_text(json.dumps(report, indent=1, default=float) + "\n")


if __name__ == "__main__":
    main()
