"""Map queries a navigation stack asks: box, radius and nearest point (clearance) on a map of real 7-Scenes frames.

The map: 63 depth frames spread over ``7scenes-redkitchen`` (every 16th of the first 1000), back-projected at full
resolution and thinned to every 4th pixel (~75k points per frame, as in ``examples/nav_costmap.py``), placed
with the ground-truth poses in a ``MapView``.

* ``query_box``: the region a costmap refresh queries after a correction: the world box of a moved frame
  (8 frames spread over the map; each box holds 29-75 % of the map's points). Anchors: the previous
  implementation (numpy, frame by frame, kept below as ``numpy_frame_loop_*``) and Open3D's
  ``PointCloud.crop(AxisAlignedBoundingBox)`` of one cloud holding the same points (float64, built untimed).
* ``query_box_small``: a 0.6 m box around a map point (what a planner asks about the space ahead).
* ``query_radius``: the points within 1 m of a map point; anchor: the previous numpy implementation.
* ``nearest``: the closest map point to positions inside the room (the frames' camera centres); anchor: the
  previous implementation (frames by box distance, numpy per frame, stop when the next box is farther).

Checks: our results equal the previous implementation's bit for bit (points, order, frame ids; nearest: distance,
point and frame), and Open3D's crop holds the same points (compared sorted: its order is its own).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import open3d as o3d
from _harness import check, time_per_item
from PIL import Image

from driftmap import PinholeIntrinsics, PoseEstimate
from driftmap.datasets import shared_datasets_dir
from driftmap.map.view import MapView, Nearest, QueryResult
from driftmap.preprocess.depth import depth_frame

FRAME_NUMBERS = range(0, 1000, 16)
PIXEL_STRIDE = 4
REPEATS, QUICK_REPEATS = 9, 3


# -------------------------------------------------- the previous implementation (anchor; not in the library)


def _numpy_candidates(view: MapView, lo: np.ndarray, hi: np.ndarray) -> list[int]:
    boxes = np.array([view.frame_box_m(int(f)).reshape(6) for f in view.frame_ids])
    counts = np.array([len(view.frame_points_world(int(f))) for f in view.frame_ids])
    overlap = np.all(boxes[:, :3] <= hi, axis=1) & np.all(boxes[:, 3:] >= lo, axis=1)
    return np.flatnonzero(overlap & (counts > 0)).tolist()


def _numpy_collect(view: MapView, rows: list[int], select) -> QueryResult:
    pts, ids = [], []
    for r in rows:
        p = view.frame_points_world(int(view.frame_ids[r]))
        m = select(p)
        if m.any():
            pts.append(p[m])
            ids.append(np.full(int(m.sum()), view.frame_ids[r], np.int64))
    if not pts:
        return QueryResult(np.zeros((0, 3), np.float32), np.zeros(0, np.int64))
    return QueryResult(np.concatenate(pts), np.concatenate(ids))


def numpy_frame_loop_box(view: MapView, min_m: Sequence[float], max_m: Sequence[float]) -> QueryResult:
    lo, hi = np.asarray(min_m, np.float64), np.asarray(max_m, np.float64)
    return _numpy_collect(view, _numpy_candidates(view, lo, hi), lambda p: np.all((p >= lo) & (p <= hi), axis=1))


def numpy_frame_loop_radius(view: MapView, center_m: Sequence[float], radius_m: float) -> QueryResult:
    c = np.asarray(center_m, np.float64)
    return _numpy_collect(view, _numpy_candidates(view, c - radius_m, c + radius_m),
                          lambda p: np.sum((p - c) ** 2, axis=1) <= radius_m**2)


def numpy_frame_loop_nearest(view: MapView, position_m: Sequence[float]) -> Nearest:
    q = np.asarray(position_m, np.float64)
    b = np.array([view.frame_box_m(int(f)).reshape(6) for f in view.frame_ids]).astype(np.float64)
    counts = np.array([len(view.frame_points_world(int(f))) for f in view.frame_ids])
    gap = np.maximum(0.0, np.maximum(b[:, :3] - q, q - b[:, 3:]))
    box_dist = np.where(counts > 0, np.linalg.norm(gap, axis=1), np.inf)
    best = (np.inf, -1, -1)
    for r in np.argsort(box_dist):
        if box_dist[r] >= best[0]:
            break
        p = view.frame_points_world(int(view.frame_ids[r]))
        d2 = np.sum((p - q) ** 2, axis=1)
        i = int(np.argmin(d2))
        if np.sqrt(d2[i]) < best[0]:
            best = (float(np.sqrt(d2[i])), int(r), i)
    r, i = best[1], best[2]
    return Nearest(best[0], view.frame_points_world(int(view.frame_ids[r]))[i].copy(), int(view.frame_ids[r]))


# -------------------------------------------------- the benchmark


def kitchen_map() -> MapView:
    folder = shared_datasets_dir() / "7scenes-redkitchen"
    intrinsics = PinholeIntrinsics(fx=585, fy=585, cx=320, cy=240, width=640, height=480)
    frames = []
    for i in FRAME_NUMBERS:
        depth = np.asarray(Image.open(folder / f"frame-{i:06d}.depth.png"))
        T = np.loadtxt(folder / f"frame-{i:06d}.pose.txt")
        frame = depth_frame(depth, intrinsics, frame_id=i, stamp_ns=i * 33_333_333, pose=PoseEstimate(T),
                            min_depth_m=0.2, max_depth_m=4.0)
        frames.append(frame.with_points(frame.points_sensor[::PIXEL_STRIDE]))
    return MapView.from_frames(frames)


def _same(a: QueryResult, b: QueryResult) -> bool:
    return a.points_world.tobytes() == b.points_world.tobytes() and np.array_equal(a.frame_ids, b.frame_ids)


def _sorted_rows(p: np.ndarray) -> np.ndarray:
    p = np.asarray(p, np.float64)
    return p[np.lexsort(p.T[::-1])]


def run(quick: bool = False) -> list[dict]:
    repeats = QUICK_REPEATS if quick else REPEATS
    view = kitchen_map()
    pts = view.points_world
    n_points = view.n_points
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts.astype(np.float64)))
    rng = np.random.default_rng(0)
    ids = view.frame_ids
    region_frames = ids[np.linspace(0, len(ids) - 1, 8).round().astype(int)]
    regions = [tuple(view.frame_box_m(int(f)).astype(np.float64)) for f in region_frames]
    small = [(p - 0.3, p + 0.3) for p in pts[rng.choice(n_points, 8, replace=False)].astype(np.float64)]
    centres = [tuple(p) for p in pts[rng.choice(n_points, 8, replace=False)].astype(np.float64)]
    positions = [view.pose(int(f))[:3, 3] for f in ids[np.linspace(0, len(ids) - 1, 8).round().astype(int)]]

    def open3d_crop(region):
        return np.asarray(cloud.crop(o3d.geometry.AxisAlignedBoundingBox(region[0], region[1])).points)

    results = []
    for name, items, what in (("query_box", regions, "the world box of a moved frame"),
                              ("query_box_small", small, "a 0.6 m box around a map point")):
        fractions = []
        for lo, hi in items:
            ours = view.query_box(lo, hi)
            check(_same(ours, numpy_frame_loop_box(view, lo, hi)), f"{name}: differs from the numpy frame loop")
            theirs = open3d_crop((lo, hi))
            same_set = np.array_equal(_sorted_rows(theirs), _sorted_rows(ours.points_world))
            check(len(theirs) == len(ours.points_world) and same_set,
                  f"{name}: Open3D's crop holds other points ({len(theirs)} vs {len(ours.points_world)})")
            fractions.append(len(ours.points_world) / n_points)
        timings = time_per_item({"driftmap": lambda r: view.query_box(*r),
                                 "numpy_frame_loop": lambda r: numpy_frame_loop_box(view, *r),
                                 "open3d_crop": open3d_crop}, items, repeats=repeats)
        ours = timings.pop("driftmap")
        results.append({
            "name": name,
            "description": f"MapView.query_box of {what} in a map of {len(ids)} real 7-Scenes frames "
                           f"({n_points / 1e6:.1f}M points); {min(fractions) * 100:.1f}-{max(fractions) * 100:.1f} "
                           "% of the points inside",
            "unit": "query",
            "ours": ours,
            "anchors": timings,
            "target_ratio": 0.2,
            "check": "same points, order and frame ids as the numpy frame loop (bit for bit); Open3D's crop holds the "
                     "same points",
            "details": {"n_points": n_points, "frames": len(ids), "fraction_inside": fractions,
                        "ratio_vs_numpy_frame_loop": ours["median_s"] / timings["numpy_frame_loop"]["median_s"],
                        "ratio_vs_open3d_crop": ours["median_s"] / timings["open3d_crop"]["median_s"]},
        })

    for c in centres:
        check(_same(view.query_radius(c, 1.0), numpy_frame_loop_radius(view, c, 1.0)), "query_radius: differs")
    timings = time_per_item({"driftmap": lambda c: view.query_radius(c, 1.0),
                             "numpy_frame_loop": lambda c: numpy_frame_loop_radius(view, c, 1.0)},
                            centres, repeats=repeats)
    ours = timings.pop("driftmap")
    results.append({
        "name": "query_radius",
        "description": "MapView.query_radius (1 m around a map point) on the same map",
        "unit": "query",
        "ours": ours,
        "anchors": timings,
        "target_ratio": 0.2,
        "check": "same points, order and frame ids as the numpy frame loop (bit for bit)",
        "details": {},
    })

    for q in positions:
        a, b = view.nearest(q), numpy_frame_loop_nearest(view, q)
        same = a.distance_m == b.distance_m and a.frame_id == b.frame_id
        check(same and a.point_world.tobytes() == b.point_world.tobytes(),
              f"nearest: {a} differs from the numpy frame loop's {b}")
    timings = time_per_item({"driftmap": view.nearest, "numpy_frame_loop": lambda q: numpy_frame_loop_nearest(view, q)},
                            positions, repeats=repeats)
    ours = timings.pop("driftmap")
    results.append({
        "name": "nearest",
        "description": "MapView.nearest (clearance) from camera centres inside the room, on the same map",
        "unit": "query",
        "ours": ours,
        "anchors": timings,
        "target_ratio": 0.2,
        "check": "same distance, point and frame as the numpy frame loop",
        "details": {},
    })
    return results
