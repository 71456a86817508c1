"""Double-wall diagnostics: detector throughput against an MME implementation on the same map, and a whole
``diagnose`` of a few-hundred-frame store.

* ``double_wall_detector``: :func:`driftmap.diagnostics.double_wall.detect_double_walls` (three voxel sizes)
  on the samples of 200 real 7-Scenes frames (3000 per frame, 600k points, a 4 cm step injected at frame
  500) vs Mean Map Entropy computed the usual fast way on the same points (Open3D hybrid neighbourhoods,
  r = 0.1 m, at most 64 neighbours, C++ covariances, then ``0.5 ln det(2 pi e C)``), and vs the time budget
  of 2 million points per second (issue 27's target: within it; a fleet's diagnose time is dominated by it).
* ``diagnose_store``: the whole ``diagnose`` of that store (sampling with own-frame normals, detector,
  attribution, MME/MPV) vs a one-minute budget (target: well under, <= 0.25x).
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import open3d as o3d
from _harness import check, time_per_item

from driftmap.datasets import shared_datasets_dir
from driftmap.diagnostics import perturb
from driftmap.diagnostics.double_wall import DiagnosticCloud, detect_double_walls, map_entropy
from driftmap.diagnostics.report import diagnose_store
from driftmap.map.view import MapView
from driftmap.sources.sevenscenes import SevenScenes
from driftmap.store.frame_store import FrameStore

REPEATS, QUICK_REPEATS = 7, 2
MME_RADIUS_M, MME_MAX_NN = 0.1, 64


def mme_open3d(points: np.ndarray) -> tuple[float, float]:
    """MME and MPV over every point with Open3D's hybrid neighbourhoods (the anchor). Open3D gives points with
    fewer than 3 neighbours an identity covariance; they are skipped (as ``map_entropy(min_neighbors=3)`` does)."""
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pcd.estimate_covariances(o3d.geometry.KDTreeSearchParamHybrid(MME_RADIUS_M, MME_MAX_NN))
    cov = np.asarray(pcd.covariances)
    cov = cov[np.abs(np.trace(cov, axis1=1, axis2=2) - 3.0) > 1e-9]
    lam = np.linalg.eigvalsh(cov)
    det = np.prod(np.maximum(lam, 0.0), axis=1) * (2 * np.pi * np.e) ** 3
    good = det > 0
    return float(np.mean(0.5 * np.log(det[good]))), float(np.mean(np.maximum(lam[:, 0], 0.0)))


def run(quick: bool = False) -> list[dict]:
    repeats = QUICK_REPEATS if quick else REPEATS
    folder = shared_datasets_dir() / "7scenes-redkitchen"
    results = []
    with tempfile.TemporaryDirectory(prefix="driftmap-bench-") as tmp:
        path = Path(tmp) / "kitchen"
        source = SevenScenes(folder, pixel_stride=4, poses_from_ground_truth=True, frames="0:1000:5")
        with FrameStore.create(path) as store:
            for frame in source:
                store.append(frame)
        store = FrameStore.open(path)
        n_map = MapView.from_store(store, 0).n_points
        cloud = DiagnosticCloud.from_store(store)
        base = store.poses(0)
        k = int(np.searchsorted(cloud.frame_ids, 500))
        normals = cloud.place(base).normals_world
        step = 0.04 * np.array([-0.011, 0.891, 0.454]) / np.linalg.norm([-0.011, 0.891, 0.454])  # the floor's normal
        placed = cloud.place(perturb.translation_step(base, k, step))
        points = placed.points_world
        n = len(points)
        check(len(normals) == n, "one own-frame normal per sample")

        # correctness: the detector finds the injected step; our MME/MPV equal Open3D's on a shared subset
        result = detect_double_walls(placed)
        scores = perturb.evaluate_step(cloud, base, k, step, result)
        affected = sum(s.n_affected for s in scores)
        rate = sum(s.n_detected for s in scores) / max(affected, 1)
        check(affected > 50 and rate >= 0.9, f"detector found {rate:.2f} of {affected} voxels affected by a 4 cm step")
        sub = points[np.random.default_rng(0).choice(n, 60_000, replace=False)]
        ours_e = map_entropy(sub, radius_m=MME_RADIUS_M, min_neighbors=3, max_neighbors=MME_MAX_NN, max_query_points=None)
        ref_mme, ref_mpv = mme_open3d(sub)
        check(abs(ours_e.mme - ref_mme) < 2e-3 and abs(ours_e.mpv_m2 - ref_mpv) < 1e-3 * ref_mpv,
              f"MME/MPV: ours {ours_e.mme:.4f}/{ours_e.mpv_m2:.3e}, Open3D {ref_mme:.4f}/{ref_mpv:.3e}")

        timings = time_per_item({"driftmap": lambda _: detect_double_walls(placed),
                                 "mme_open3d": lambda _: mme_open3d(points)}, [None], repeats=repeats)
        budget = {"median_s": n / 2e6, "min_s": n / 2e6, "max_s": n / 2e6, "repeats": 0, "items": 1,
                  "page_faults_per_item": 0.0, "samples_s": []}
        ours = timings.pop("driftmap")
        results.append({
            "name": "double_wall_detector",
            "description": f"double-wall detector (voxels 0.1/0.2/0.4 m) on {n / 1e3:.0f}k samples of 200 real 7-Scenes frames "
                           f"({ours['items'] and n / ours['median_s'] / 1e6:.2f} M points/s) vs MME on the same points "
                           f"(Open3D hybrid r={MME_RADIUS_M} m, <= {MME_MAX_NN} nn) and vs the 2 M points/s budget",
            "unit": "map",
            "ours": ours,
            "anchors": {"mme_open3d": timings["mme_open3d"], "budget_2M_points_per_s": budget},
            "target_ratio": 1.0,
            "check": f"a 4 cm step is found in {rate:.0%} of {affected} affected voxels; our MME/MPV equal Open3D's "
                     f"({ours_e.mme:.3f} vs {ref_mme:.3f})",
            "details": {"n_points": n, "points_per_s": n / ours["median_s"], "n_map_points": n_map,
                        "mme_points_per_s": n / timings["mme_open3d"]["median_s"]},
        })

        def diagnose(_):
            return diagnose_store(store, 0)

        timings = time_per_item({"driftmap": diagnose}, [None], repeats=max(1, repeats // 3), warmup=0)
        ours = timings["driftmap"]
        minute = {"median_s": 60.0, "min_s": 60.0, "max_s": 60.0, "repeats": 0, "items": 1, "page_faults_per_item": 0.0,
                  "samples_s": []}
        diag = diagnose_store(store, 0)
        check(diag.double_walls.voxels_evaluated > 1000, "diagnose evaluated the map")
        results.append({
            "name": "diagnose_store",
            "description": f"whole diagnose of a 200-frame 7-Scenes store ({n_map / 1e6:.1f}M map points; sampling with "
                           f"own-frame normals, detector, attribution, MME/MPV) vs a one-minute budget",
            "unit": "store",
            "ours": ours,
            "anchors": {"one_minute": minute},
            "target_ratio": 0.25,
            "check": f"{diag.double_walls.voxels_evaluated} surface voxels evaluated",
            "details": {"seconds": diag.seconds, "n_map_points": n_map, "map_points_per_s": n_map / ours["median_s"]},
        })
        store.close()
    return results
