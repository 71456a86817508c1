"""Validation + back-projection of real 7-Scenes depth frames: ``driftmap.backproject`` vs Open3D.

The frames are decoded into memory first, so PNG decoding is not timed. All three implementations use the
same valid range: driftmap keeps ``MIN_DEPTH_M <= z < MAX_DEPTH_M`` and always drops uint16 code 0 (no
reading) and 65535; Open3D drops ``z <= 0`` and ``z >= depth_trunc`` / ``depth_max``.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
from _harness import check, time_per_item
from PIL import Image

from driftmap import PinholeIntrinsics, backproject
from driftmap.datasets import ENV_VAR, shared_datasets_dir

SCENE = "7scenes-redkitchen"
INTRINSICS = PinholeIntrinsics(fx=585.0, fy=585.0, cx=320.0, cy=240.0, width=640, height=480)
N_FRAMES = 20
DEPTH_SCALE = 1000.0  # uint16 millimetres
MIN_DEPTH_M = 0.0  # code 0 is invalid in driftmap anyway, which matches Open3D's z > 0
MAX_DEPTH_M = 3.5  # below the scene's farthest readings (~4 m), so the upper bound is exercised
TOLERANCE_M = 1e-6
TARGET_RATIO = 0.5  # ours / faster Open3D path
REPEATS, QUICK_REPEATS = 30, 5


def load_depth_frames(n: int) -> tuple[list[str], list[np.ndarray]]:
    """``n`` depth images spread evenly over the sequence, decoded to uint16 arrays."""
    folder = shared_datasets_dir() / SCENE
    paths = sorted(folder.glob("frame-*.depth.png"))
    if not paths:
        raise FileNotFoundError(f"no frame-*.depth.png in {folder} (set {ENV_VAR} to the shared data-set folder)")
    picks = np.linspace(0, len(paths) - 1, min(n, len(paths))).round().astype(int)
    names, depths = [], []
    for i in picks:
        with Image.open(paths[i]) as im:
            depth = np.array(im).astype(np.uint16, copy=False)
        check(depth.shape == (INTRINSICS.height, INTRINSICS.width), f"{paths[i].name}: unexpected shape {depth.shape}")
        names.append(paths[i].name)
        depths.append(np.ascontiguousarray(depth))
    return names, depths


def run(quick: bool = False) -> list[dict]:
    names, depths = load_depth_frames(N_FRAMES)
    i = INTRINSICS
    legacy_intrinsics = o3d.camera.PinholeCameraIntrinsic(i.width, i.height, i.fx, i.fy, i.cx, i.cy)
    k_tensor = o3d.core.Tensor(i.K)

    def ours(depth):
        return backproject(depth, i, depth_scale=DEPTH_SCALE, min_depth_m=MIN_DEPTH_M, max_depth_m=MAX_DEPTH_M)

    def open3d_legacy(depth):
        return o3d.geometry.PointCloud.create_from_depth_image(
            o3d.geometry.Image(depth), legacy_intrinsics, depth_scale=DEPTH_SCALE, depth_trunc=MAX_DEPTH_M
        )

    def open3d_tensor(depth):
        return o3d.t.geometry.PointCloud.create_from_depth_image(
            o3d.t.geometry.Image(o3d.core.Tensor(depth)), k_tensor, depth_scale=DEPTH_SCALE, depth_max=MAX_DEPTH_M
        )

    # Correctness (untimed): point for point equal to Open3D legacy on every frame. The tensor path's point
    # order is not deterministic (parallel), so it is only checked for the same count and centroid.
    max_diff, n_points, n_beyond = 0.0, [], 0
    for name, depth in zip(names, depths):
        result = ours(depth)
        pts = result.points
        legacy = np.asarray(open3d_legacy(depth).points)
        check(pts.shape == legacy.shape, f"{name}: driftmap gives {len(pts)} points, Open3D legacy {len(legacy)}")
        diff = float(np.max(np.abs(pts - legacy))) if len(pts) else 0.0
        check(diff <= TOLERANCE_M, f"{name}: max |driftmap - Open3D legacy| = {diff:.3g} m > {TOLERANCE_M:g} m")
        tensor = open3d_tensor(depth).point.positions.numpy()
        check(len(tensor) == len(pts), f"{name}: driftmap gives {len(pts)} points, Open3D tensor {len(tensor)}")
        centroid_diff = float(np.max(np.abs(pts.mean(0, dtype=np.float64) - tensor.mean(0, dtype=np.float64))))
        check(centroid_diff <= TOLERANCE_M, f"{name}: centroid differs from Open3D tensor by {centroid_diff:.2g} m")
        max_diff = max(max_diff, diff)
        n_points.append(len(pts))
        n_beyond += result.invalid_counts["beyond_max"]

    timings = time_per_item(
        {"driftmap": ours, "open3d_legacy": open3d_legacy, "open3d_tensor": open3d_tensor},
        depths,
        repeats=QUICK_REPEATS if quick else REPEATS,
    )
    return [
        {
            "name": "backproject",
            "description": f"validate + back-project one 640x480 uint16 depth frame ({SCENE}, {len(depths)} frames)",
            "unit": "frame",
            "ours": timings.pop("driftmap"),
            "anchors": timings,
            "target_ratio": TARGET_RATIO,
            "check": (
                f"{len(depths)} frames: same points as Open3D legacy, in order (max |diff| {max_diff:.2g} m "
                f"<= {TOLERANCE_M:g}); Open3D tensor: same count and centroid"
            ),
            "details": {
                "frames": names,
                "depth_scale": DEPTH_SCALE,
                "min_depth_m": MIN_DEPTH_M,
                "max_depth_m": MAX_DEPTH_M,
                "points_per_frame_mean": float(np.mean(n_points)),
                "beyond_max_pixels_total": n_beyond,
                "max_abs_diff_vs_legacy_m": max_diff,
            },
        }
    ]
