#!/usr/bin/env python3
"""Using driftmap from a navigation stack: a 2-D costmap that follows pose corrections.

The loop a navigation stack runs, with driftmap's library API only (no ROS):

1. every frame is stored with the pose the robot had when the frame was taken (odometry, composed with
   the latest map->odom correction) and added to a live ``MapView``; its obstacle points go straight
   into the costmap (only the cells they touch, and the inflation around them, are updated);
2. every ``--correct-every`` frames a localiser sends corrected poses for the recent keyframes (here the
   synthetic log's ground truth stands in for a scan matcher or a pose graph); the correction becomes a
   new revision of the store's pose ledger, and ``MapView.apply`` re-transforms only the frames that
   moved and returns a ``ChangeSet``: every moved frame's world box before and after;
3. only the costmap cells under those boxes are re-rasterised, from box queries of the corrected map,
   and the inflation is redone around them;
4. the example checks that this costmap equals a costmap rebuilt from scratch from a fresh map of the
   corrected store, and runs the clearance, radius and box queries a planner would use.

Run it (about 10-20 s for the 60 frames of the embedded log)::

    .venv/bin/python examples/nav_costmap.py --out /tmp/nav-costmap

It prints one line per correction and writes ``result.json`` (the checked outcomes), ``costmap.png``
(the costmap before and after the correction that changed most cells) and the store to ``--out``. The
exit code is 0 only when every refreshed costmap equals its rebuild. See docs/navigation-stack.md.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from driftmap.datasets import embedded_dir
from driftmap.frame import PoseEstimate, PoseSource
from driftmap.geometry import invert
from driftmap.map.view import ChangeSet, MapView
from driftmap.sources.synthetic import SyntheticLog
from driftmap.store.frame_store import FrameStore

# Cost values as in ROS costmap_2d: 254 an obstacle in the cell, 253 the robot's centre here would make
# it touch one, then a cost decaying with the distance to the nearest obstacle, 0 free.
LETHAL = 254
INSCRIBED = 253


@dataclass(frozen=True)
class CostmapSpec:
    """A fixed 2-D grid over the world's x-y plane (z is up in the synthetic log's world frame)."""

    origin_m: tuple[float, float] = (-4.0, -3.5)
    """World x, y of the grid's lower-left corner (the corner of cell row 0, column 0)."""
    size_m: tuple[float, float] = (8.0, 7.0)
    resolution_m: float = 0.05
    z_band_m: tuple[float, float] = (0.10, 1.80)
    """Map points with a height in this band are obstacles (the floor and the ceiling lamp are not)."""
    inscribed_radius_m: float = 0.20
    inflation_radius_m: float = 0.50
    cost_scaling_per_m: float = 5.0

    @property
    def shape(self) -> tuple[int, int]:
        """(rows along y, columns along x)."""
        return round(self.size_m[1] / self.resolution_m), round(self.size_m[0] / self.resolution_m)

    @property
    def n_cells(self) -> int:
        return self.shape[0] * self.shape[1]


def cost_from_distance(distance_m: NDArray[np.float64], spec: CostmapSpec) -> NDArray[np.uint8]:
    """Cost of a cell from its distance to the nearest obstacle cell (centre to centre)."""
    decayed = np.floor((INSCRIBED - 1) * np.exp(-spec.cost_scaling_per_m * (distance_m - spec.inscribed_radius_m)))
    cost = np.where(distance_m <= spec.inflation_radius_m, decayed, 0.0).astype(np.uint8)
    cost[distance_m <= spec.inscribed_radius_m] = INSCRIBED
    cost[distance_m == 0.0] = LETHAL
    return cost


@dataclass(frozen=True)
class RefreshStats:
    """What one costmap refresh touched."""

    changed_boxes: int
    regions: int
    cells_refreshed: int
    cells_reinflated: int
    points_queried: int


class Costmap:
    """Obstacle points per cell (``hits``) and the inflated cost (``cost``), both updated in place."""

    def __init__(self, spec: CostmapSpec):
        self.spec = spec
        self.hits = np.zeros(spec.shape, np.int32)
        self.cost = np.zeros(spec.shape, np.uint8)

    @classmethod
    def rebuild(cls, spec: CostmapSpec, points_world: NDArray[np.float32]) -> Costmap:
        """The reference: a costmap made from scratch from every map point, inflated over the whole grid."""
        costmap = cls(spec)
        costmap._count(*costmap.obstacle_cells(points_world))
        costmap._inflate(np.ones(spec.shape, bool))
        return costmap

    def equals(self, other: Costmap) -> bool:
        return bool(np.array_equal(self.hits, other.hits) and np.array_equal(self.cost, other.cost))

    # ---------------------------------------------------------------------------------------- geometry

    def cell_of(self, xy_m: NDArray[np.float64]) -> NDArray[np.int64]:
        """(row, column) of world x-y positions, possibly off the grid. Points and box corners go through
        this same float64 formula, so a point inside a box always lands in one of the box's cells."""
        s = self.spec
        xy = np.asarray(xy_m, dtype=np.float64)
        col = np.floor((xy[..., 0] - s.origin_m[0]) / s.resolution_m).astype(np.int64)
        row = np.floor((xy[..., 1] - s.origin_m[1]) / s.resolution_m).astype(np.int64)
        return np.stack([row, col], axis=-1)

    def on_grid(self, rc: NDArray[np.int64]) -> NDArray[np.bool_]:
        return np.all((rc >= 0) & (rc < self.spec.shape), axis=-1)

    def obstacle_cells(self, points_world: NDArray[np.float32]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """Row and column of every map point in the obstacle height band that falls on the grid."""
        p = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
        z0, z1 = self.spec.z_band_m
        rc = self.cell_of(p[(p[:, 2] >= z0) & (p[:, 2] <= z1), :2])
        rc = rc[self.on_grid(rc)]
        return rc[:, 0], rc[:, 1]

    def cells_of_boxes(self, boxes_m: NDArray[np.float32]) -> NDArray[np.bool_]:
        """The cells under world boxes ((K, 2, 3): min and max corners), as a mask."""
        mask = np.zeros(self.spec.shape, bool)
        z0, z1 = self.spec.z_band_m
        for lo, hi in np.asarray(boxes_m, dtype=np.float64):
            if not np.all(np.isfinite([lo, hi])) or hi[2] < z0 or lo[2] > z1:
                continue  # a frame without points, or a box that cannot hold an obstacle point
            (r0, c0), (r1, c1) = self.cell_of(lo[:2]), self.cell_of(hi[:2])
            r0, c0 = max(r0, 0), max(c0, 0)
            r1, c1 = min(r1, self.spec.shape[0] - 1), min(c1, self.spec.shape[1] - 1)
            if r0 <= r1 and c0 <= c1:
                mask[r0 : r1 + 1, c0 : c1 + 1] = True
        return mask

    def inflation_reach(self, cells: NDArray[np.bool_]) -> NDArray[np.bool_]:
        """The cells whose cost may depend on ``cells`` (within the inflation radius, as a square)."""
        r = math.ceil(self.spec.inflation_radius_m / self.spec.resolution_m)
        if cells.all():
            return cells
        return ndimage.binary_dilation(cells, structure=np.ones((2 * r + 1, 2 * r + 1), bool))

    # ---------------------------------------------------------------------------------------- updates

    def add_points(self, points_world: NDArray[np.float32]) -> int:
        """A new frame: count its obstacle points, re-inflate around the cells they touched."""
        rows, cols = self.obstacle_cells(points_world)
        touched = np.zeros(self.spec.shape, bool)
        touched[rows, cols] = True
        self._count(rows, cols)
        self._inflate(touched)
        return int(touched.sum())

    def refresh(self, view: MapView, changes: ChangeSet) -> RefreshStats:
        """After ``view.apply``: re-rasterise only the cells under the moved frames' boxes (before and
        after) from the corrected map, then redo the inflation around them."""
        s = self.spec
        region = self.cells_of_boxes(changes.boxes_m())
        labels, n_regions = ndimage.label(region)
        self.hits[region] = 0
        queried = 0
        for k, (rows_slice, cols_slice) in enumerate(ndimage.find_objects(labels), start=1):
            # one box query per connected region, padded by a cell; its points are kept by their cell
            lo = (s.origin_m[0] + (cols_slice.start - 1) * s.resolution_m,
                  s.origin_m[1] + (rows_slice.start - 1) * s.resolution_m, s.z_band_m[0])
            hi = (s.origin_m[0] + (cols_slice.stop + 1) * s.resolution_m,
                  s.origin_m[1] + (rows_slice.stop + 1) * s.resolution_m, s.z_band_m[1])
            found = view.query_box(lo, hi)
            queried += len(found.points_world)
            rows, cols = self.obstacle_cells(found.points_world)
            mine = labels[rows, cols] == k
            self._count(rows[mine], cols[mine])
        reinflated = self._inflate(region)
        return RefreshStats(len(changes.boxes_m()), n_regions, int(region.sum()), reinflated, queried)

    def _count(self, rows: NDArray[np.int64], cols: NDArray[np.int64]) -> None:
        """One more hit per (row, column) pair."""
        counts = np.bincount(rows * self.spec.shape[1] + cols, minlength=self.spec.n_cells)
        self.hits += counts.reshape(self.spec.shape).astype(np.int32)

    def _inflate(self, changed: NDArray[np.bool_]) -> int:
        """Recompute the cost of every cell within the inflation radius of ``changed`` cells.

        The distance transform runs on a window reaching one more inflation radius out, so every obstacle
        that can matter to a recomputed cell is in it: the result equals a whole-grid transform there.
        """
        s = self.spec
        r = math.ceil(s.inflation_radius_m / s.resolution_m)
        target = self.inflation_reach(changed)
        if not target.any():
            return 0
        rows, cols = np.nonzero(target)
        window = (slice(max(rows.min() - r, 0), rows.max() + r + 1), slice(max(cols.min() - r, 0), cols.max() + r + 1))
        obstacle = self.hits[window] > 0
        if obstacle.any():
            distance_m = ndimage.distance_transform_edt(~obstacle) * s.resolution_m
        else:
            distance_m = np.full(obstacle.shape, np.inf)
        inner = target[window]
        self.cost[window][inner] = cost_from_distance(distance_m, s)[inner]
        return int(target.sum())


# ------------------------------------------------------------------------------------------ the loop


def localiser_poses(store: FrameStore, truth: dict[int, NDArray[np.float64]], window: list[int],
                    keyframe_every: int) -> dict[int, NDArray[np.float64]]:
    """The correction to store: the localiser's poses for the window's keyframes, and every older frame
    pinned at the pose it has now.

    With ``propagate`` (the default) the ledger interpolates the frames between keyframes, but it would
    also move every frame *before* the first keyframe rigidly with it; pinning the older frames (bit for
    bit) keeps them, and their map points and costmap cells, untouched.
    """
    keyframes = sorted(set(window[::keyframe_every]) | {window[-1]})
    poses = {fid: truth[fid] for fid in keyframes}
    in_window = set(window)
    for fid, T_world_sensor in zip(store.frame_ids.tolist(), store.poses()):  # the head revision
        if fid not in in_window:
            poses[fid] = T_world_sensor
    return poses


@dataclass
class Correction:
    """One correction as the loop saw it: the numbers for result.json and the costmap before and after."""

    record: dict
    changes: ChangeSet
    cost_before: NDArray[np.uint8]
    cost_after: NDArray[np.uint8]


def apply_correction(store: FrameStore, view: MapView, costmap: Costmap, poses: dict[int, NDArray[np.float64]],
                     note: str) -> Correction:
    """Store a correction, move the map, refresh the costmap under the changed regions, check it."""
    adds_equal = costmap.equals(Costmap.rebuild(costmap.spec, view.points_world))
    revision = store.add_revision(poses, source=PoseSource.GROUND_TRUTH, note=note)
    before = costmap.cost.copy()
    t0 = time.perf_counter()
    changes = view.apply(revision.revision_id)  # re-transforms only the frames whose pose changed
    t1 = time.perf_counter()
    stats = costmap.refresh(view, changes)  # only the cells under the moved frames' boxes
    t2 = time.perf_counter()
    # the check: the same costmap as one rebuilt from scratch from a fresh map of the corrected store
    reference = Costmap.rebuild(costmap.spec, store.map(revision.revision_id).points_world)
    t3 = time.perf_counter()
    record = {
        "revision": revision.revision_id,
        "frames_total": len(view.frame_ids),
        "frames_moved": len(changes.changes),
        "max_translation_m": changes.max_translation_m,
        "max_rotation_deg": max((c.rotation_deg for c in changes.changes), default=0.0),
        "changed_boxes": stats.changed_boxes,
        "regions": stats.regions,
        "cells_refreshed": stats.cells_refreshed,
        "cells_reinflated": stats.cells_reinflated,
        "cells_total": costmap.spec.n_cells,
        "cells_cost_changed": int(np.count_nonzero(before != costmap.cost)),
        "points_queried": stats.points_queried,
        "points_total": view.n_points,
        "adds_equal_to_rebuild": adds_equal,
        "costmap_equal_to_rebuild": costmap.equals(reference),
        "apply_ms": (t1 - t0) * 1e3,
        "refresh_ms": (t2 - t1) * 1e3,
        "fresh_map_and_rebuild_ms": (t3 - t2) * 1e3,
    }
    r = record
    print(f"correction -> revision {r['revision']}: {r['frames_moved']} of {r['frames_total']} frames moved "
          f"(max {r['max_translation_m'] * 100:.1f} cm, {r['max_rotation_deg']:.2f} deg); "
          f"{r['cells_refreshed']} of {r['cells_total']} cells refreshed "
          f"({100 * r['cells_refreshed'] / r['cells_total']:.0f} %), {r['cells_cost_changed']} costs changed; "
          f"equals rebuild: {'yes' if r['costmap_equal_to_rebuild'] else 'NO'} "
          f"[apply {r['apply_ms']:.1f} ms, refresh {r['refresh_ms']:.0f} ms, "
          f"fresh map + rebuild {r['fresh_map_and_rebuild_ms']:.0f} ms]")
    return Correction(record, changes, before, costmap.cost.copy())


def run_queries(view: MapView, costmap: Costmap) -> dict:
    """What a planner asks the map, at the robot's latest pose."""
    z0, z1 = costmap.spec.z_band_m
    T_world_sensor = view.pose(int(view.frame_ids[-1]))
    position = T_world_sensor[:3, 3]
    heading = T_world_sensor[:2, 2] / np.linalg.norm(T_world_sensor[:2, 2])  # optical axis, on the x-y plane

    clearance = view.nearest(position, z_range_m=(z0, z1))  # the nearest obstacle (the floor does not count)
    near = view.query_radius(position, 1.0)
    near_obstacles = len(view.query_radius(position, 1.0, z_range_m=(z0, z1)).points_world)
    centre = position[:2] + 0.6 * heading
    box_min, box_max = (centre[0] - 0.3, centre[1] - 0.3, z0), (centre[0] + 0.3, centre[1] + 0.3, z1)
    ahead = view.query_box(box_min, box_max)
    rc = costmap.cell_of(position[:2])
    cost_here = int(costmap.cost[rc[0], rc[1]]) if costmap.on_grid(rc) else None

    print(f"robot (camera) at ({position[0]:.2f}, {position[1]:.2f}, {position[2]:.2f}) m: nearest map point "
          f"{clearance.distance_m:.2f} m away in the obstacle band (frame {clearance.frame_id}); {len(near.points_world)} points within "
          f"1 m ({near_obstacles} in the obstacle band, from {len(np.unique(near.frame_ids))} frames); "
          f"{len(ahead.points_world)} obstacle points in the 60 cm box 0.6 m ahead; cost under the robot: {cost_here}")
    return {
        "position_m": position.tolist(),
        "clearance_m": clearance.distance_m,
        "clearance_point_m": clearance.point_world.tolist(),
        "clearance_frame_id": clearance.frame_id,
        "radius_m": 1.0,
        "radius_points": len(near.points_world),
        "radius_obstacle_points": near_obstacles,
        "box_ahead_min_m": list(box_min),
        "box_ahead_max_m": list(box_max),
        "box_ahead_points": len(ahead.points_world),
        "cost_at_robot": cost_here,
    }


def _prepare_store_dir(path: Path) -> Path:
    if (path / "store.json").exists():
        shutil.rmtree(path)  # a store this example wrote before
    return path


def run(args: argparse.Namespace) -> dict:
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="driftmap-nav-"))
    out.mkdir(parents=True, exist_ok=True)
    spec = CostmapSpec(resolution_m=args.resolution_m)
    log = SyntheticLog(args.log, pixel_stride=args.pixel_stride)
    odometry = log.odometry().poses  # drifting T_odom_sensor, one per frame of the log
    gt = log.ground_truth()
    truth = dict(zip(gt.frame_ids.tolist(), gt.poses))  # stands in for the localiser's corrected poses
    n = min(args.frames, len(log))
    print(f"driftmap navigation example: {n} frames of {log.path}, costmap {spec.shape[1]} x {spec.shape[0]} cells "
          f"of {spec.resolution_m * 100:.0f} cm, obstacles at z {spec.z_band_m} m, "
          f"inflation {spec.inflation_radius_m} m")

    corrections: list[Correction] = []
    add_ms: list[tuple[float, float, float]] = []  # per frame: store.append, view.refresh, costmap update
    with FrameStore.create(_prepare_store_dir(out / "store")) as store:
        view = store.map()  # the live map: empty now, grows with view.refresh()
        costmap = Costmap(spec)
        T_map_odom = np.eye(4)  # the latest correction: where the odometry frame sits in the map frame
        window: list[int] = []  # the frames since the last correction
        for i in range(n):
            # 1. a frame arrives with the pose the robot believes it has: store it, add it to the map
            frame = log.depth_frame(i)
            pose = PoseEstimate(T_map_odom @ odometry[i], source=PoseSource.ODOMETRY)
            t0 = time.perf_counter()
            store.append(frame.with_pose(pose))
            t1 = time.perf_counter()
            new_ids = view.refresh()  # the frames stored since the last refresh, placed in the view's revision
            t2 = time.perf_counter()
            for frame_id in new_ids:
                costmap.add_points(view.frame_points_world(frame_id))
            add_ms.append(((t1 - t0) * 1e3, (t2 - t1) * 1e3, (time.perf_counter() - t2) * 1e3))
            window.append(frame.frame_id)
            if len(window) < args.correct_every and i < n - 1:
                continue

            # 2.-4. the localiser corrects the window: new revision, view.apply, costmap refresh, check
            poses = localiser_poses(store, truth, window, args.keyframe_every)
            note = f"localiser, frames {window[0]}-{window[-1]}"
            correction = apply_correction(store, view, costmap, poses, note=note)
            correction.record["window"] = [window[0], window[-1]]
            corrections.append(correction)
            # the localiser's estimate of map->odom places the frames that come next
            T_map_odom = truth[window[-1]] @ invert(odometry[window[-1]])
            window = []

        append_ms, refresh_ms, costmap_ms = np.mean(add_ms, axis=0)
        print(f"per frame: store.append {append_ms:.1f} ms, view.refresh {refresh_ms:.1f} ms, costmap update "
              f"{costmap_ms:.1f} ms ({view.n_points / n:.0f} points per frame)")
        queries = run_queries(view, costmap)
        final_equal = costmap.equals(Costmap.rebuild(spec, store.map().points_world))
        n_points, head = view.n_points, store.head

    records = [c.record for c in corrections]
    result = {
        "example": "nav_costmap",
        "frames": n,
        "points": n_points,
        "revisions": head,
        "corrections": records,
        "cells_total": spec.n_cells,
        "cells_refreshed": max((r["cells_refreshed"] for r in records), default=0),
        "costmap_equal_to_rebuild": final_equal and all(r["costmap_equal_to_rebuild"] for r in records),
        "adds_equal_to_rebuild": all(r["adds_equal_to_rebuild"] for r in records),
        "per_frame_ms": {"store_append": append_ms, "view_refresh": refresh_ms, "costmap_update": costmap_ms},
        "queries": queries,
        "store": str((out / "store").resolve()),
    }
    result["ok"] = bool(records) and result["costmap_equal_to_rebuild"] and result["adds_equal_to_rebuild"]
    if args.png and corrections:
        largest = max(corrections, key=lambda c: c.record["cells_cost_changed"])
        result["png"] = str(write_png(out / "costmap.png", largest, costmap))
    (out / "result.json").write_text(json.dumps(result, indent=1) + "\n")
    print(f"{'OK' if result['ok'] else 'FAILED'}: every refreshed costmap equals a rebuild from scratch: "
          f"{result['costmap_equal_to_rebuild']}; results in {out.resolve()}")
    return result


def write_png(path: Path, correction: Correction, costmap: Costmap) -> Path:
    """The costmap before and after a correction, and the cells whose cost changed; outlined: the cells
    re-rasterised (solid) and the cells re-inflated around them (dashed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    spec = costmap.spec
    before, after = correction.cost_before, correction.cost_after
    region = costmap.cells_of_boxes(correction.changes.boxes_m())
    reach = costmap.inflation_reach(region)
    changed = (before != after).astype(np.uint8) * LETHAL
    extent = (spec.origin_m[0], spec.origin_m[0] + spec.size_m[0], spec.origin_m[1], spec.origin_m[1] + spec.size_m[1])
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.8), constrained_layout=True)
    panels = [(f"before revision {correction.record['revision']}", before),
              ("after: only the outlined cells were recomputed", after),
              (f"{np.count_nonzero(changed)} cells whose cost changed", changed)]
    for ax, (title, image) in zip(axes, panels):
        ax.imshow(image, origin="lower", extent=extent, cmap="magma_r", vmin=0, vmax=LETHAL, interpolation="nearest")
        ax.contour(region.astype(float), levels=[0.5], colors="tab:cyan", linewidths=1.0, origin="lower", extent=extent)
        ax.contour(reach.astype(float), levels=[0.5], colors="tab:cyan", linewidths=0.8, linestyles="dashed",
                   origin="lower", extent=extent)
        ax.set_title(title)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
    fig.suptitle("driftmap: a 2-D costmap refreshed only where a pose correction moved frames "
                 "(solid: re-rasterised from box queries, dashed: re-inflated)")
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--out", help="output folder (default: a new temporary folder)")
    parser.add_argument("--frames", type=int, default=60, help="how many frames of the log to use")
    parser.add_argument("--log", default=str(embedded_dir() / "synthetic-loop"), help="synthetic log folder")
    parser.add_argument("--correct-every", type=int, default=8, help="a localiser correction after every N frames")
    parser.add_argument("--keyframe-every", type=int, default=4, help="the localiser corrects every Nth frame")
    parser.add_argument("--resolution-m", type=float, default=0.05, help="costmap cell size")
    parser.add_argument("--pixel-stride", type=int, default=1, help="use every Nth depth pixel (faster)")
    parser.add_argument("--no-png", dest="png", action="store_false", help="do not write costmap.png")
    args = parser.parse_args(argv)
    if args.frames < 2 or args.correct_every < 2 or args.keyframe_every < 1 or not args.resolution_m > 0:
        parser.error("--frames and --correct-every must be at least 2, --keyframe-every at least 1, "
                     "--resolution-m positive")
    result = run(args)
    return 0 if result["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
