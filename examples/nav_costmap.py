#!/usr/bin/env python3
"""Using driftmap from a navigation stack: volumetric layers and a 2-D costmap that follow pose corrections.

The loop a navigation stack runs, with driftmap's library API only (no ROS):

1. every frame is stored with the pose the robot had when the frame was taken (odometry, composed with the
   latest map->odom correction) and its rays are integrated into the store's ``VolumeLayers`` (occupied / free /
   unknown voxels); the planner's costmap is refreshed under the frame's box only;
2. every ``--correct-every`` frames a localiser sends corrected poses for the recent keyframes (here the synthetic
   log's ground truth stands in for a scan matcher or a pose graph); the correction becomes a new revision of the
   store's pose ledger, and ``layers.apply(revision, store)`` takes out the old contribution of exactly the frames
   that moved and puts in the new one. The ``VolumeChange`` it returns names those frames, the boxes of their rays
   before and after, and the voxels whose state flipped;
3. only the costmap cells under those boxes (grown by the inflation radius and two cells) are recomputed, from the
   layers' states (the voxel columns of the obstacle band: occupied / free / unknown) and their clearance;
4. after every correction the example checks that the layers equal layers rebuilt from scratch in that revision
   and that the costmap equals a costmap made from the rebuilt layers (through ``occupancy_grid2d``, the nav2
   ``map_server`` export); that unknown space is never reported free; and at the end it runs the queries a planner
   asks: the states along a candidate path, the clearance of robot positions and swept sphere and box checks
   reporting the first contact with the frames that observed it.

Run it (18-40 s for the 60 frames of the embedded log on a 2-core machine, depending on its load)::

    .venv/bin/python examples/nav_costmap.py --out /tmp/nav

It prints one line per correction and writes ``result.json`` (the checked outcomes), ``costmap.png`` (the costmap
before and after the correction that changed most costs: free, costs, lethal and unknown cells in distinct colours),
the final layers as a nav2 ``map_server`` map (``map.yaml`` + ``map.pgm``) and an OctoMap tree (``map.bt``), and the
store to ``--out``. The exit code is 0 only when every check holds. See docs/navigation-stack.md.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from driftmap.datasets import embedded_dir
from driftmap.frame import PoseEstimate, PoseSource
from driftmap.geometry import invert
from driftmap.sources.synthetic import SyntheticLog
from driftmap.store.frame_store import FrameStore
from driftmap.volume import FREE, OCCUPIED, UNKNOWN, VolumeChange, VolumeConfig, VolumeLayers
from driftmap.volume.export import GRID_FREE, GRID_OCCUPIED, occupancy_grid2d, write_grid2d, write_octomap

# Cost values as in ROS costmap_2d: 255 no information (unknown), 254 an obstacle in the cell, 253 the robot's centre
# here would make it touch one, then a cost decaying with the clearance, 0 free.
NO_INFORMATION = 255
LETHAL = 254
INSCRIBED = 253


@dataclass(frozen=True)
class CostmapSpec:
    """A fixed 2-D grid over the world's x-y plane (z is up in the synthetic log's world frame), one cell per voxel
    column of the layers (the cell size is the voxel size, the origin on the voxel lattice)."""

    origin_m: tuple[float, float] = (-4.0, -3.5)
    """World x, y of the grid's lower-left corner (the corner of cell row 0, column 0)."""
    size_m: tuple[float, float] = (8.0, 7.0)
    resolution_m: float = 0.05
    z_band_m: tuple[float, float] = (0.10, 1.80)
    """A cell is occupied when a voxel of its column with its centre in this band is occupied, else free when one is
    free, else unknown (the floor and the ceiling lamp are outside it)."""
    clearance_heights_m: tuple[float, float] = (0.6, 1.0)
    """Where a cell's clearance is measured: the smallest clearance of the cell centre at these heights (at least the
    inflation radius above the floor, or the floor would be the nearest obstacle everywhere)."""
    inscribed_radius_m: float = 0.20
    inflation_radius_m: float = 0.50
    cost_scaling_per_m: float = 5.0
    clearance_unknown_is: str = "free"
    """The costs ignore unknown space (unknown cells are NO_INFORMATION on their own, like costmap_2d without
    ``inflate_unknown``); "occupied" would also inflate around never-observed voxels."""

    def __post_init__(self) -> None:
        k = self.band_layers()
        lo, hi = min(self.clearance_heights_m), max(self.clearance_heights_m)
        eps = 1e-9  # metres: the comparison is about voxel faces, not float rounding
        if len(k) == 0 or k[0] * self.resolution_m > lo - self.inflation_radius_m + eps or \
                (k[-1] + 1) * self.resolution_m < hi + self.inflation_radius_m - eps:
            raise ValueError(f"the band {self.z_band_m} m must hold every voxel within the inflation radius of the "
                             f"clearance heights {self.clearance_heights_m} m (see reach_cells)")

    @property
    def reach_cells(self) -> int:
        """How far (in cells) an obstacle can raise a cell's cost: a surface within the inflation radius of a
        clearance probe lies in an occupied band column at most this many cells away (x and y)."""
        return int(np.ceil((self.inflation_radius_m + self.resolution_m) / self.resolution_m))

    @property
    def shape(self) -> tuple[int, int]:
        """(rows along y, columns along x)."""
        return round(self.size_m[1] / self.resolution_m), round(self.size_m[0] / self.resolution_m)

    @property
    def n_cells(self) -> int:
        return self.shape[0] * self.shape[1]

    @property
    def origin_index(self) -> tuple[int, int]:
        """The lattice voxel (x, y) of cell row 0, column 0."""
        ix, iy = (round(o / self.resolution_m) for o in self.origin_m)
        if not np.allclose([ix * self.resolution_m, iy * self.resolution_m], self.origin_m, rtol=0, atol=1e-9):
            raise ValueError(f"the costmap origin {self.origin_m} is not on the {self.resolution_m} m voxel lattice")
        return ix, iy

    def band_layers(self) -> NDArray[np.int64]:
        """The lattice z indices of the voxel layers whose centres lie in the band (as ``occupancy_grid2d`` picks them)."""
        vs, (z0, z1) = self.resolution_m, self.z_band_m
        k = np.arange(int(np.floor(z0 / vs)) - 1, int(np.floor(z1 / vs)) + 2, dtype=np.int64)
        z = (k + 0.5) * vs
        return k[(z >= z0) & (z <= z1)]

    def cell_centres_m(self, rows: NDArray[np.int64], cols: NDArray[np.int64]) -> NDArray[np.float64]:
        ix0, iy0 = self.origin_index
        return np.stack([(ix0 + cols + 0.5) * self.resolution_m, (iy0 + rows + 0.5) * self.resolution_m], axis=-1)

    def cells_of_boxes(self, boxes_m: NDArray[np.float64], grow_m: float) -> NDArray[np.bool_]:
        """The cells under world boxes ((K, 2, 3): min and max corners) grown by ``grow_m`` in x and y, as a mask."""
        mask = np.zeros(self.shape, bool)
        ix0, iy0 = self.origin_index
        for lo, hi in np.asarray(boxes_m, dtype=np.float64):
            if not np.all(np.isfinite([lo, hi])):
                continue
            c0, r0 = np.floor((lo[:2] - grow_m) / self.resolution_m).astype(np.int64) - (ix0, iy0)
            c1, r1 = np.floor((hi[:2] + grow_m) / self.resolution_m).astype(np.int64) - (ix0, iy0)
            r0, c0 = max(r0, 0), max(c0, 0)
            r1, c1 = min(r1, self.shape[0] - 1), min(c1, self.shape[1] - 1)
            if r0 <= r1 and c0 <= c1:
                mask[r0 : r1 + 1, c0 : c1 + 1] = True
        return mask


def cost_from(state: NDArray[np.int8], clearance_m: NDArray[np.float64], spec: CostmapSpec) -> NDArray[np.uint8]:
    """ROS costmap_2d costs: unknown columns NO_INFORMATION, occupied LETHAL, free cells by their clearance."""
    with np.errstate(invalid="ignore", over="ignore"):
        decayed = np.floor((INSCRIBED - 1) * np.exp(-spec.cost_scaling_per_m * (clearance_m - spec.inscribed_radius_m)))
        cost = np.where(clearance_m <= spec.inflation_radius_m, decayed, 0.0)
        cost = np.where(clearance_m <= spec.inscribed_radius_m, INSCRIBED, cost).astype(np.uint8)
    cost[state == OCCUPIED] = LETHAL
    cost[state == UNKNOWN] = NO_INFORMATION
    return cost


@dataclass(frozen=True)
class RefreshStats:
    """What one costmap refresh touched."""

    boxes: int
    cells_refreshed: int
    cells_cost_changed: int
    clearance_queries: int


class Costmap:
    """The planner's costmap, derived from volumetric layers: per cell the band column's state, the clearance (NaN
    where the column is not free, infinity where no obstacle is within ``reach_cells``) and the cost."""

    def __init__(self, spec: CostmapSpec):
        self.spec = spec
        self.state = np.full(spec.shape, UNKNOWN, np.int8)
        self.clearance_m = np.full(spec.shape, np.nan)
        self.cost = np.full(spec.shape, NO_INFORMATION, np.uint8)

    @classmethod
    def rebuild(cls, spec: CostmapSpec, layers: VolumeLayers) -> Costmap:
        """The reference, made from scratch: the column states of the nav2 map export (``occupancy_grid2d`` of the
        band, pasted onto the costmap's cells; cells beyond the layers' grid unknown), the clearance of every free
        cell, the costs of all cells."""
        costmap = cls(spec)
        grid = occupancy_grid2d(layers, spec.z_band_m)  # cells[ix, iy] over the layers' grid
        ix0, iy0 = spec.origin_index
        gx, gy = layers.grid.origin_index[0] - ix0, layers.grid.origin_index[1] - iy0  # grid cell 0 on the costmap
        rows, cols = spec.shape
        c0, c1 = max(gx, 0), min(gx + grid.shape[0], cols)
        r0, r1 = max(gy, 0), min(gy + grid.shape[1], rows)
        if c0 < c1 and r0 < r1:
            sub = grid.cells[c0 - gx : c1 - gx, r0 - gy : r1 - gy].T  # -> rows along y
            costmap.state[r0:r1, c0:c1] = np.where(sub == GRID_OCCUPIED, OCCUPIED, np.where(sub == GRID_FREE, FREE, UNKNOWN))
        costmap._derive(np.ones(spec.shape, bool), layers)
        return costmap

    def equals(self, other: Costmap) -> bool:
        return bool(np.array_equal(self.state, other.state) and np.array_equal(self.cost, other.cost)
                    and np.array_equal(self.clearance_m, other.clearance_m, equal_nan=True))

    def refresh(self, layers: VolumeLayers, change: VolumeChange) -> tuple[RefreshStats, NDArray[np.bool_]]:
        """After ``layers.apply`` (or new frames): recompute only the cells whose state or cost can have changed.

        A voxel's state, and the observed surface the clearance measures to, change only inside the change's boxes
        (the boxes of the moved frames' rays, before and after; a surface point is the mean of the points in its
        voxel, so within a voxel of them); a cost changes only where the clearance was or is within the inflation
        radius of such a change, and which cells are asked for their clearance depends on the occupied cells within
        ``reach_cells``. So the cells under the boxes grown by ``reach_cells`` + 1 cells are all that can change. A
        change that fell back to a rebuild (``change.rebuilt``) refreshes every cell."""
        s = self.spec
        if change.rebuilt:
            region = np.ones(s.shape, bool)
        else:
            region = s.cells_of_boxes(change.boxes_m, (s.reach_cells + 1) * s.resolution_m)
        before = self.cost[region]
        rows, cols = np.nonzero(region)
        self.state[rows, cols] = column_states(layers, s, rows, cols)
        queries = self._derive(region, layers)
        changed = int(np.count_nonzero(before != self.cost[region]))
        return RefreshStats(len(change.boxes_m), int(region.sum()), changed, queries), region

    def _derive(self, region: NDArray[np.bool_], layers: VolumeLayers) -> int:
        """Clearance and cost of the cells in ``region`` from their (already set) states.

        The clearance is asked only for free cells with an occupied cell within ``reach_cells``: with unknown space
        ignored, every surface within the inflation radius of a probe lies in such a column (the band holds the
        probes' reach, checked by the spec), so a farther cell's clearance exceeds the radius and its cost is 0; its
        clearance is recorded as infinity. This skips the cells in the open, whose nearest-surface queries cost most."""
        s = self.spec
        free = region & (self.state == FREE)
        if s.clearance_unknown_is == "free":
            w = s.reach_cells
            near = ndimage.maximum_filter((self.state == OCCUPIED).astype(np.uint8), size=2 * w + 1, mode="constant") > 0
        else:  # unknown voxels are obstacles too: every free cell is asked
            near = np.ones(s.shape, bool)
        rows, cols = np.nonzero(free & near)
        self.clearance_m[region] = np.nan
        self.clearance_m[free & ~near] = np.inf
        xy = s.cell_centres_m(rows, cols)
        probes = np.concatenate([np.column_stack([xy, np.full(len(xy), z)]) for z in s.clearance_heights_m])
        if len(probes):
            clearance = layers.clearance_m(probes, unknown_is=s.clearance_unknown_is)
            self.clearance_m[rows, cols] = clearance.reshape(len(s.clearance_heights_m), -1).min(axis=0)
        self.cost[region] = cost_from(self.state[region], self.clearance_m[region], s)
        return len(probes)


def column_states(layers: VolumeLayers, spec: CostmapSpec, rows: NDArray[np.int64],
                  cols: NDArray[np.int64]) -> NDArray[np.int8]:
    """The state of the band column of each cell, read from the layers' voxel states: occupied if a voxel is
    occupied, else free if one is free, else unknown (columns beyond the layers' grid: unknown)."""
    g = layers.grid
    ix0, iy0 = spec.origin_index
    k = spec.band_layers()
    idx = np.empty((len(rows), len(k), 3), np.int64)
    idx[..., 0] = (ix0 + cols - g.origin_index[0])[:, None]
    idx[..., 1] = (iy0 + rows - g.origin_index[1])[:, None]
    idx[..., 2] = (k - g.origin_index[2])[None, :]
    idx = idx.reshape(-1, 3)
    inside = np.all((idx >= 0) & (idx < np.asarray(g.shape)), axis=1)
    states = np.full(len(idx), UNKNOWN, np.int8)
    states[inside] = layers.states_flat(g.flat(idx[inside]))
    column = states.reshape(len(rows), len(k))
    return np.where(np.any(column == OCCUPIED, axis=1), OCCUPIED,
                    np.where(np.any(column == FREE, axis=1), FREE, UNKNOWN)).astype(np.int8)


def unknown_never_free(layers: VolumeLayers, costmap: Costmap) -> bool:
    """An independent check from the layers' full state grid: a cell is NO_INFORMATION exactly where no voxel of its
    band column was observed, LETHAL exactly where one is occupied, and only the rest carries a cost below LETHAL."""
    s, g = costmap.spec, layers.grid
    states = layers.state_grid()
    k = s.band_layers() - g.origin_index[2]
    band = states[:, :, k[(k >= 0) & (k < g.shape[2])]]
    observed = np.zeros(s.shape, bool)
    occupied = np.zeros(s.shape, bool)
    ix0, iy0 = s.origin_index
    rows, cols = np.indices(s.shape)
    gx, gy = ix0 + cols - g.origin_index[0], iy0 + rows - g.origin_index[1]
    on = (gx >= 0) & (gx < g.shape[0]) & (gy >= 0) & (gy < g.shape[1])
    observed[on] = np.any(band[gx[on], gy[on]] != UNKNOWN, axis=-1)
    occupied[on] = np.any(band[gx[on], gy[on]] == OCCUPIED, axis=-1)
    c = costmap.cost
    return bool(np.array_equal(c == NO_INFORMATION, ~observed) and np.array_equal(c == LETHAL, occupied))


# ------------------------------------------------------------------------------------------ new frames


def integrate_new_frames(layers: VolumeLayers, store: FrameStore) -> VolumeChange:
    """Integrate the frames stored since the layers last looked (``VolumeLayers.refresh``: the layers' map view takes
    them in, the grid grows to their rays; equal to a rebuild bit for bit) and return what changed."""
    return layers.refresh(store)


# ------------------------------------------------------------------------------------------ the loop


def localiser_poses(store: FrameStore, truth: dict[int, NDArray[np.float64]], window: list[int],
                    keyframe_every: int) -> dict[int, NDArray[np.float64]]:
    """The correction to store: the localiser's poses for the window's keyframes, and every older frame
    pinned at the pose it has now.

    With ``propagate`` (the default) the ledger interpolates the frames between keyframes, but it would
    also move every frame *before* the first keyframe rigidly with it; pinning the older frames (bit for
    bit) keeps them, and their voxels and costmap cells, untouched.
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
    region: NDArray[np.bool_]
    cost_before: NDArray[np.uint8]
    cost_after: NDArray[np.uint8]


def apply_correction(store: FrameStore, layers: VolumeLayers, costmap: Costmap, config: VolumeConfig,
                     poses: dict[int, NDArray[np.float64]], note: str) -> Correction:
    """Store a correction, update the layers, refresh the costmap under the change, check both against rebuilds."""
    s = costmap.spec
    adds_equal = costmap.equals(Costmap.rebuild(s, layers))  # the per-frame refreshes so far
    revision = store.add_revision(poses, source=PoseSource.GROUND_TRUTH, note=note)
    rev = revision.revision_id
    before_T = {int(f): layers.view.pose(int(f)) for f in layers.view.frame_ids}
    cost_before = costmap.cost.copy()
    t0 = time.perf_counter()
    change = layers.apply(rev, store)  # takes out and puts back only the frames whose pose changed
    t1 = time.perf_counter()
    stats, region = costmap.refresh(layers, change)  # only the cells the change can reach
    t2 = time.perf_counter()
    # the checks: layers rebuilt from scratch in this revision, and a costmap made from those
    rebuilt = VolumeLayers.from_store(store, rev, config)
    layers_equal = layers.equals(rebuilt)
    reference = Costmap.rebuild(s, rebuilt)
    t3 = time.perf_counter()
    moved = [int(f) for f in change.frame_ids]
    shifts = [np.linalg.norm(layers.view.pose(f)[:3, 3] - before_T[f][:3, 3]) for f in moved]
    turns = [np.degrees(np.arccos(np.clip((np.trace(before_T[f][:3, :3].T @ layers.view.pose(f)[:3, :3]) - 1) / 2, -1, 1)))
             for f in moved]
    record = {
        "revision": rev,
        "frames_total": len(layers.view.frame_ids),
        "frames_moved": len(moved),
        "max_translation_m": float(max(shifts, default=0.0)),
        "max_rotation_deg": float(max(turns, default=0.0)),
        "layers_rebuilt_fallback": bool(change.rebuilt),
        "change_boxes": len(change.boxes_m),
        "voxels_state_changed": change.n_state_changed,
        "voxels_total": layers.grid.n_voxels,
        "cells_refreshed": stats.cells_refreshed,
        "cells_total": s.n_cells,
        "cells_cost_changed": stats.cells_cost_changed,
        "clearance_queries": stats.clearance_queries,
        "layers_equal_to_rebuild": layers_equal,
        "costmap_equal_to_rebuild": costmap.equals(reference),
        "adds_equal_to_rebuild": adds_equal,
        "unknown_never_free": unknown_never_free(layers, costmap),
        "apply_ms": (t1 - t0) * 1e3,
        "refresh_ms": (t2 - t1) * 1e3,
        "rebuild_ms": (t3 - t2) * 1e3,
    }
    r = record
    ok = r["layers_equal_to_rebuild"] and r["costmap_equal_to_rebuild"]
    print(f"correction -> revision {r['revision']}: {r['frames_moved']} of {r['frames_total']} frames moved "
          f"(max {r['max_translation_m'] * 100:.1f} cm, {r['max_rotation_deg']:.2f} deg); "
          f"{r['voxels_state_changed']} voxels changed state; "
          f"{r['cells_refreshed']} of {r['cells_total']} cells refreshed "
          f"({100 * r['cells_refreshed'] / r['cells_total']:.0f} %), {r['cells_cost_changed']} costs changed; "
          f"equals rebuild: {'yes' if ok else 'NO'} "
          f"[apply {r['apply_ms']:.0f} ms, refresh {r['refresh_ms']:.0f} ms, rebuild {r['rebuild_ms']:.0f} ms]")
    return Correction(record, region, cost_before, costmap.cost.copy())


# ------------------------------------------------------------------------------------------ the planner's queries

PATH_LENGTH_M = 4.0
HEAD_RADIUS_M = 0.10
"""The robot's camera head as a sphere (the sphere sweep)."""
BODY_BOX_M = (0.4, 0.4, 1.0)
"""The robot's upper body as an axis-aligned box (x, y, z edges) around the path point (the box sweep)."""


def run_queries(layers: VolumeLayers, spec: CostmapSpec) -> dict:
    """What a planner asks the layers at the robot's latest pose: the states along a candidate path (straight ahead
    at the camera's height), the clearance of the robot's recent positions under both unknown-space policies, and
    swept sphere and box checks along the path, with the frames that observed the first contact."""
    ids = [int(f) for f in layers.view.frame_ids]
    T = layers.view.pose(ids[-1])
    heading = T[:2, 2] / np.linalg.norm(T[:2, 2])  # the camera's optical axis, on the x-y plane
    start = T[:3, 3].copy()
    path = np.array([start, start + PATH_LENGTH_M * np.array([heading[0], heading[1], 0.0])])

    samples, along = path_samples(path, 0.5 * layers.grid.voxel_size_m)  # where the sweeps look (half a voxel)
    states = layers.states(samples)
    not_free = np.flatnonzero(states != FREE)
    first = int(not_free[0]) if len(not_free) else None

    robots = np.array([[*layers.view.pose(f)[:2, 3], z] for f in ids[-5:] for z in spec.clearance_heights_m])
    clearance = layers.clearance_m(robots)  # the layers' policy: unknown_is = occupied (the default)
    clearance_free = layers.clearance_m(robots, unknown_is="free")

    point = layers.sweep(path, radius_m=0.0)
    sphere = layers.sweep(path, radius_m=HEAD_RADIUS_M)
    box = layers.sweep(path, box_m=BODY_BOX_M)
    contact = next((r for r in (sphere, point) if r.outcome == "contact"), None)
    observers = layers.observers(contact.voxel_center_m[None])[0] if contact is not None else np.zeros(0, np.int64)

    def sweep_record(r) -> dict:  # r: a SweepResult
        return {"outcome": r.outcome, "distance_m": r.distance_m,
                "voxel_center_m": None if r.voxel_center_m is None else r.voxel_center_m.tolist(),
                "frames": [int(f) for f in r.frames]}

    q = {
        "revision": layers.revision,
        "path_m": path.tolist(),
        "path_samples": len(samples),
        "path_states": {name: int(np.sum(states == v)) for name, v in (("free", FREE), ("occupied", OCCUPIED),
                                                                        ("unknown", UNKNOWN))},
        "path_first_not_free_m": None if first is None else float(along[first]),
        "path_first_not_free_state": None if first is None else int(states[first]),
        "robot_points_m": robots.tolist(),
        "clearance_m": clearance.tolist(),
        "clearance_unknown_free_m": clearance_free.tolist(),
        "sweep_point": sweep_record(point),
        "sweep_sphere": {"radius_m": HEAD_RADIUS_M, **sweep_record(sphere)},
        "sweep_box": {"box_m": list(BODY_BOX_M), **sweep_record(box)},
        "contact_observers": [int(f) for f in observers],
    }
    names = {-1: "unknown", 0: "free", 1: "occupied"}
    print(f"candidate path: {PATH_LENGTH_M:.1f} m straight ahead from the robot's camera at "
          f"({start[0]:.2f}, {start[1]:.2f}, {start[2]:.2f}) m, {len(samples)} samples: {q['path_states']['free']} "
          f"free, {q['path_states']['occupied']} occupied, {q['path_states']['unknown']} unknown; first not free "
          + ("nowhere" if first is None else f"at {along[first]:.3f} m ({names[int(states[first])]})"))
    for z in spec.clearance_heights_m:
        at = robots[:, 2] == z
        print(f"clearance of the last {len(ids[-5:])} robot positions at z {z} m: "
              f"{clearance[at].min():.2f}-{clearance[at].max():.2f} m (unknown_is=occupied), "
              f"{clearance_free[at].min():.2f}-{clearance_free[at].max():.2f} m (unknown_is=free)")
    for label, r in (("point", point), (f"sphere r {HEAD_RADIUS_M} m", sphere), (f"box {BODY_BOX_M} m", box)):
        where = "" if r.voxel_center_m is None else " at voxel ({:.3f}, {:.3f}, {:.3f})".format(*r.voxel_center_m)
        print(f"sweep {label}: {r.outcome}" + ("" if r.distance_m is None else f" after {r.distance_m:.3f} m")
              + where + (f", observed by {len(r.frames)} frames ({_ids(r.frames)})" if len(r.frames) else ""))
    return q


def path_samples(path: NDArray[np.float64], step_m: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Points every ``step_m`` along a straight path (a, b) and their distance along it, computed as
    ``VolumeLayers.sweep`` places its footprint, so the states here and a sweep's stop can be compared exactly."""
    a, b = path
    seg = float(np.linalg.norm(b - a))
    n = max(1, int(np.ceil(seg / step_m)))
    points = np.array([a] + [a + (b - a) * (j / n) for j in range(1, n + 1)])
    return points, np.array([0.0] + [seg * j / n for j in range(1, n + 1)])


def _ids(frames: NDArray[np.int64]) -> str:
    f = [int(x) for x in frames]
    return ", ".join(map(str, f)) if len(f) <= 8 else ", ".join(map(str, f[:6])) + f", ... {f[-1]}"


def query_checks(q: dict, layers: VolumeLayers, rebuilt: VolumeLayers) -> dict[str, bool]:
    """The planner's answers hold together: the point sweep stops where the path's states stop being free; a bigger
    footprint stops no later; a contact voxel is occupied and its frames are the ones whose rays ended in it
    (``observers``); an unknown stop is an unknown voxel and unknown space has zero clearance under
    unknown_is=occupied, which is never above unknown_is=free; the sphere sweep found a contact; the rebuilt layers
    give the same answers."""
    path = np.asarray(q["path_m"])
    point, sphere, box = q["sweep_point"], q["sweep_sphere"], q["sweep_box"]
    first = q["path_first_not_free_m"]
    expected = None if first is None else ("contact" if q["path_first_not_free_state"] == OCCUPIED else "unknown")
    point_matches_states = (point["outcome"] == "clear" and first is None) or (
        first is not None and point["distance_m"] == first and point["outcome"] == expected)
    no_later = point["distance_m"] is None or all(
        r["distance_m"] is not None and r["distance_m"] <= point["distance_m"] for r in (sphere, box))
    stops_ok = True
    for r in (point, sphere, box):
        if r["outcome"] == "clear":
            continue
        centre = np.asarray(r["voxel_center_m"])[None]
        state = layers.states(centre)[0]
        if r["outcome"] == "contact":
            stops_ok &= bool(state == OCCUPIED and len(r["frames"]) > 0
                             and np.array_equal(layers.observers(centre)[0], r["frames"]))
        else:
            stops_ok &= bool(state == UNKNOWN and len(r["frames"]) == 0)
    samples, _ = path_samples(path, 0.5 * layers.grid.voxel_size_m)
    unknown = samples[layers.states(samples) == UNKNOWN]
    unknown_zero = bool(len(unknown) == 0 or np.all(layers.clearance_m(unknown, unknown_is="occupied") == 0.0))
    conservative = bool(np.all(np.asarray(q["clearance_m"]) <= np.asarray(q["clearance_unknown_free_m"])))
    return {"point_sweep_matches_path_states": bool(point_matches_states),
            "footprints_stop_no_later": bool(no_later),
            "stops_are_occupied_with_their_observers_or_unknown": stops_ok,
            "unknown_has_zero_clearance": unknown_zero and conservative,
            "sphere_sweep_found_a_contact": sphere["outcome"] == "contact" and len(sphere["frames"]) > 0,
            "same_answers_on_rebuilt_layers": run_queries_quiet(rebuilt, q)}


def run_queries_quiet(rebuilt: VolumeLayers, q: dict) -> bool:
    """The same path, positions and sweeps on the rebuilt layers give the same numbers."""
    path, robots = np.asarray(q["path_m"]), np.asarray(q["robot_points_m"])
    same = np.array_equal(rebuilt.clearance_m(robots), q["clearance_m"])
    same &= np.array_equal(rebuilt.clearance_m(robots, unknown_is="free"), q["clearance_unknown_free_m"])
    for key, footprint in (("sweep_point", {"radius_m": 0.0}), ("sweep_sphere", {"radius_m": HEAD_RADIUS_M}),
                           ("sweep_box", {"box_m": BODY_BOX_M})):
        r = rebuilt.sweep(path, **footprint)
        same &= (r.outcome == q[key]["outcome"] and r.distance_m == q[key]["distance_m"]
                 and [int(f) for f in r.frames] == q[key]["frames"])
    return bool(same)


# ------------------------------------------------------------------------------------------ run


def _prepare_store_dir(path: Path) -> Path:
    if (path / "store.json").exists():
        shutil.rmtree(path)  # a store this example wrote before
    return path


@dataclass
class FrameTimes:
    append_ms: list[float] = field(default_factory=list)
    layers_ms: list[float] = field(default_factory=list)
    costmap_ms: list[float] = field(default_factory=list)
    cells: list[int] = field(default_factory=list)
    flips: list[int] = field(default_factory=list)


def run(args: argparse.Namespace) -> dict:
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="driftmap-nav-"))
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    spec = CostmapSpec(resolution_m=args.voxel_size_m)
    config = VolumeConfig(voxel_size_m=args.voxel_size_m)
    log = SyntheticLog(args.log, pixel_stride=args.pixel_stride)
    odometry = log.odometry().poses  # drifting T_odom_sensor, one per frame of the log
    gt = log.ground_truth()
    truth = dict(zip(gt.frame_ids.tolist(), gt.poses))  # stands in for the localiser's corrected poses
    n = min(args.frames, len(log))
    print(f"driftmap navigation example: {n} frames of {log.path} (every {args.pixel_stride}. pixel), layers of "
          f"{args.voxel_size_m * 100:.0f} cm voxels, costmap {spec.shape[1]} x {spec.shape[0]} cells, obstacle band "
          f"z {spec.z_band_m} m, clearance at z {spec.clearance_heights_m} m, inflation {spec.inflation_radius_m} m")

    corrections: list[Correction] = []
    times = FrameTimes()
    with FrameStore.create(_prepare_store_dir(out / "store")) as store:
        layers: VolumeLayers | None = None
        costmap = Costmap(spec)
        T_map_odom = np.eye(4)  # the latest correction: where the odometry frame sits in the map frame
        window: list[int] = []  # the frames since the last correction
        for i in range(n):
            # 1. a frame arrives with the pose the robot believes it has: store it, integrate its rays
            frame = log.depth_frame(i)
            pose = PoseEstimate(T_map_odom @ odometry[i], source=PoseSource.ODOMETRY)
            t0 = time.perf_counter()
            store.append(frame.with_pose(pose))
            t1 = time.perf_counter()
            if layers is None:
                layers = VolumeLayers.from_store(store, config=config)  # the first frame
                change = VolumeChange(0, 0, np.asarray([frame.frame_id]), np.zeros((0, 2, 3)), np.zeros(0, np.int64),
                                      np.zeros((0, 3)), rebuilt=True)  # built from scratch: every cell
            else:
                change = integrate_new_frames(layers, store)
            t2 = time.perf_counter()
            stats, _ = costmap.refresh(layers, change)  # only the cells under the new frame's box
            times.append_ms.append((t1 - t0) * 1e3)
            times.layers_ms.append((t2 - t1) * 1e3)
            times.costmap_ms.append((time.perf_counter() - t2) * 1e3)
            times.cells.append(stats.cells_refreshed)
            times.flips.append(change.n_state_changed)
            window.append(frame.frame_id)
            if len(window) < args.correct_every and i < n - 1:
                continue

            # 2.-4. the localiser corrects the window: new revision, layers.apply, costmap refresh, checks
            poses = localiser_poses(store, truth, window, args.keyframe_every)
            correction = apply_correction(store, layers, costmap, config, poses,
                                          note=f"localiser, frames {window[0]}-{window[-1]}")
            correction.record["window"] = [window[0], window[-1]]
            corrections.append(correction)
            # the localiser's estimate of map->odom places the frames that come next
            T_map_odom = truth[window[-1]] @ invert(odometry[window[-1]])
            window = []

        assert layers is not None
        print(f"per frame: store.append {np.mean(times.append_ms):.1f} ms, layers update {np.mean(times.layers_ms):.0f} ms "
              f"({np.mean(times.flips):.0f} voxels changed state), costmap refresh {np.mean(times.costmap_ms):.0f} ms "
              f"({np.mean(times.cells) / spec.n_cells * 100:.0f} % of the cells); layers "
              f"{layers.grid.describe()}, max range {layers.config.max_range_m:.2f} m")
        queries = run_queries(layers, spec)
        rebuilt = VolumeLayers.from_store(store, store.head, config)
        checks = query_checks(queries, layers, rebuilt)
        final_equal = layers.equals(rebuilt) and costmap.equals(Costmap.rebuild(spec, rebuilt))
        stats = layers.stats()
        head = store.head
        # the same layers for other tools: a nav2 map_server map of the band and an OctoMap tree
        grid2d = write_grid2d(layers, out / "map.yaml", spec.z_band_m)
        octomap = write_octomap(layers, out / "map.bt")
        print(f"exports: {grid2d.yaml_path.name} + {grid2d.pgm_path.name} (nav2 map_server, {grid2d.width} x "
              f"{grid2d.height} cells: {grid2d.n_occupied} occupied, {grid2d.n_free} free, {grid2d.n_unknown} unknown), "
              f"{octomap.path.name} (OctoMap, {octomap.n_occupied} occupied and {octomap.n_free} free voxels, "
              f"{octomap.bytes / 1e3:.0f} kB)")

    records = [c.record for c in corrections]
    counts = {name: int(np.sum(costmap.cost == v)) for name, v in (("lethal", LETHAL), ("inscribed", INSCRIBED),
                                                                    ("unknown", NO_INFORMATION), ("free", 0))}
    counts["cost"] = spec.n_cells - sum(counts.values())
    result = {
        "example": "nav_costmap",
        "frames": n,
        "revisions": head,
        "volume_config": layers.config.model_dump(mode="json"),
        "voxels": {"occupied": stats.occupied, "free": stats.free, "unknown": stats.unknown, "total": stats.n_voxels},
        "costmap_cells": counts,
        "corrections": records,
        "cells_total": spec.n_cells,
        "cells_refreshed": max((r["cells_refreshed"] for r in records), default=0),
        "layers_equal_to_rebuild": final_equal and all(r["layers_equal_to_rebuild"] for r in records),
        "costmap_equal_to_rebuild": final_equal and all(r["costmap_equal_to_rebuild"] for r in records),
        "adds_equal_to_rebuild": all(r["adds_equal_to_rebuild"] for r in records),
        "unknown_never_free": all(r["unknown_never_free"] for r in records) and unknown_never_free(layers, costmap),
        "per_frame_ms": {"store_append": float(np.mean(times.append_ms)), "layers_update": float(np.mean(times.layers_ms)),
                         "costmap_refresh": float(np.mean(times.costmap_ms))},
        "queries": queries,
        "query_checks": checks,
        "exports": {"grid2d_yaml": str(grid2d.yaml_path), "grid2d_pgm": str(grid2d.pgm_path),
                    "grid2d_cells": {"occupied": grid2d.n_occupied, "free": grid2d.n_free, "unknown": grid2d.n_unknown},
                    "octomap": str(octomap.path), "octomap_voxels": {"occupied": octomap.n_occupied,
                                                                     "free": octomap.n_free}},
        "store": str((out / "store").resolve()),
    }
    result["ok"] = bool(records) and all([result["layers_equal_to_rebuild"], result["costmap_equal_to_rebuild"],
                                          result["adds_equal_to_rebuild"], result["unknown_never_free"],
                                          *checks.values()])
    if args.png and corrections:
        largest = max(corrections, key=lambda c: c.record["cells_cost_changed"])
        result["png"] = str(write_png(out / "costmap.png", largest, spec))
    result["seconds"] = time.perf_counter() - t_start
    (out / "result.json").write_text(json.dumps(result, indent=1) + "\n")
    failed = [k for k, v in checks.items() if not v]
    print(f"costmap: {counts['free']} free, {counts['cost']} with a cost, {counts['inscribed']} inscribed, "
          f"{counts['lethal']} lethal, {counts['unknown']} unknown cells; voxels: {stats.occupied} occupied, "
          f"{stats.free} free, {stats.unknown} unknown")
    print(f"{'OK' if result['ok'] else 'FAILED'}: layers equal a rebuild: {result['layers_equal_to_rebuild']}, "
          f"costmap equals a rebuild: {result['costmap_equal_to_rebuild']}, unknown never free: "
          f"{result['unknown_never_free']}, query checks: {'all hold' if not failed else 'FAILED ' + ', '.join(failed)} "
          f"({result['seconds']:.0f} s); results in {out.resolve()}")
    return result


def costmap_rgb(cost: NDArray[np.uint8]) -> NDArray[np.float64]:
    """Colours: free white, costs yellow to red, inscribed dark red, lethal black, unknown grey-blue."""
    import matplotlib

    rgb = np.ones(cost.shape + (3,))
    graded = (cost > 0) & (cost < INSCRIBED)
    rgb[graded] = matplotlib.colormaps["YlOrRd"](0.15 + 0.7 * cost[graded] / (INSCRIBED - 1))[:, :3]
    rgb[cost == INSCRIBED] = (0.55, 0.0, 0.1)
    rgb[cost == LETHAL] = (0.0, 0.0, 0.0)
    rgb[cost == NO_INFORMATION] = (0.62, 0.68, 0.78)
    return rgb


def write_png(path: Path, correction: Correction, spec: CostmapSpec) -> Path:
    """The costmap before and after a correction and the cells whose cost changed; outlined: the refreshed cells."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    before, after = correction.cost_before, correction.cost_after
    changed = np.where(before != after, LETHAL, 0).astype(np.uint8)
    extent = (spec.origin_m[0], spec.origin_m[0] + spec.size_m[0], spec.origin_m[1], spec.origin_m[1] + spec.size_m[1])
    fig, axes = plt.subplots(1, 3, figsize=(15, 5.2), constrained_layout=True)
    panels = [(f"before revision {correction.record['revision']}", costmap_rgb(before)),
              ("after: only the outlined cells were recomputed", costmap_rgb(after)),
              (f"{np.count_nonzero(changed)} cells whose cost changed", costmap_rgb(changed))]
    for ax, (title, image) in zip(axes, panels):
        ax.imshow(image, origin="lower", extent=extent, interpolation="nearest")
        ax.contour(correction.region.astype(float), levels=[0.5], colors="tab:cyan", linewidths=1.2, origin="lower",
                   extent=extent)
        ax.set_title(title)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
    legend = [Patch(facecolor=costmap_rgb(np.array([v], np.uint8))[0], edgecolor="0.4", label=label) for v, label in
              ((0, "free (0)"), (120, "cost by clearance"), (INSCRIBED, "inscribed (253)"), (LETHAL, "lethal (254)"),
               (NO_INFORMATION, "unknown (255)"))]
    fig.legend(handles=legend, loc="lower center", ncol=5, bbox_to_anchor=(0.5, -0.01), frameon=False)
    fig.suptitle("driftmap: a costmap from volumetric layers, refreshed only where a pose correction changed them "
                 "(cyan: the cells recomputed)")
    fig.savefig(path, dpi=90, bbox_inches="tight")
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
    parser.add_argument("--voxel-size-m", type=float, default=0.05, help="voxel size of the layers = costmap cell size")
    parser.add_argument("--pixel-stride", type=int, default=2, help="use every Nth depth pixel (faster)")
    parser.add_argument("--no-png", dest="png", action="store_false", help="do not write costmap.png")
    args = parser.parse_args(argv)
    if args.frames < 2 or args.correct_every < 2 or args.keyframe_every < 1 or not args.voxel_size_m > 0:
        parser.error("--frames and --correct-every must be at least 2, --keyframe-every at least 1, "
                     "--voxel-size-m positive")
    try:
        CostmapSpec(resolution_m=args.voxel_size_m).origin_index  # noqa: B018 - the costmap must sit on the lattice
    except ValueError as exc:
        parser.error(f"--voxel-size-m {args.voxel_size_m}: {exc}")
    result = run(args)
    return 0 if result["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
