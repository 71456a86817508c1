"""A generated query set for the synthetic room with its truth (``datasets/synthetic-loop-queries.json``).

Queries are drawn with a seeded generator in the room's frame (the ground-truth frame of the synthetic log):
clearance along the robot's path and beside it and near furniture, collision sweeps past the table and chair legs
(and along the path), grasps on the 2 cm board (its face, its edges, behind it) and other furniture, footholds on the
floor (and on furniture tops, walls, at the foot of furniture), exploration behind furniture and elsewhere. Each
query's truth is :mod:`driftmap.decisions.synthetic_truth`'s; a draw whose truth is ambiguous at the map's
resolution (it changes within the tolerances of :class:`Tolerances`) is left out and drawn again. The truth of each
query travels in its ``truth`` key (``decision``, the category and the numbers behind it), which decide ignores.

``python -m driftmap.decisions.synthetic_queries OUT.json [LOG]`` writes the set.
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from driftmap.decisions.query_file import (
    ClearanceQuery,
    CollisionQuery,
    ExploreQuery,
    FootholdQuery,
    GraspQuery,
    parse_query,
)
from driftmap.decisions.settings import DecideConfig
from driftmap.decisions.space import sweep_step
from driftmap.decisions.synthetic_truth import (
    SceneTruth,
    clearance_truth,
    collision_truth,
    explore_truth,
    foothold_truth,
    grasp_truth,
)

GLASS_KEEP_OUT_M = 0.6
"""No clearance or collision query comes this close to the glass pane (a depth camera cannot see glass: the map can
only call it unknown, the truth calls it a solid)."""

SEEN_MARGIN_M = 0.3
"""Queries stay within this of the box of what the camera saw (the layers' grid pads that box by 0.5 m)."""

FURNITURE = ("table_top", "table_leg_0", "table_leg_1", "table_leg_2", "table_leg_3", "chair_seat", "chair_leg_0",
             "chair_leg_1", "chair_leg_2", "chair_leg_3", "thin_board", "crate_-x", "cabinet_+x", "locker_+x",
             "sideboard_+y", "shelf_-x", "pillar_-y", "pillar_+y")
LEGS = ("table_leg_0", "table_leg_1", "table_leg_2", "table_leg_3", "chair_leg_0", "chair_leg_1", "chair_leg_2",
        "chair_leg_3")


@dataclass(frozen=True)
class Tolerances:
    """How far a query must be from changing its truth to be kept (the map's resolution is 2 cm voxels)."""

    clearance_m: float = 0.04
    footprint_m: float = 0.03
    roi_m: float = 0.03
    patch_m: float = 0.03
    unknown_fraction: float = 0.1


QUOTAS = {"clearance_path": 25, "clearance_beside": 40, "clearance_view": 35, "clearance_obstacle": 30,
          "collision_obstacle": 40, "collision_path": 12, "collision_view": 25, "grasp_board": 30, "grasp_other": 12,
          "foothold_floor": 30, "foothold_other": 16, "explore_furniture": 22, "explore_other": 16}


class Generator:
    """Draws the queries of one category at a time and keeps those with an unambiguous truth."""

    def __init__(self, truth: SceneTruth, seed: int = 25, tolerances: Tolerances | None = None,
                 decide_config: DecideConfig | None = None):
        self.truth = truth
        self.rng = np.random.default_rng(seed)
        self.tol = tolerances or Tolerances()
        self.cfg = decide_config or DecideConfig()
        self.path = truth.poses[:, :3, 3]
        names = truth.names
        self.box = {n: (truth.box_min[k], truth.box_max[k]) for k, n in enumerate(names)}
        seen = np.argwhere(truth.seen)
        self.seen_lo = (seen.min(axis=0) + truth.origin_index) * truth.voxel_m
        self.seen_hi = (seen.max(axis=0) + truth.origin_index + 1) * truth.voxel_m

    # -------------------------------------------------------------------------------------------- helpers
    def _near_glass(self, lo: NDArray[np.float64], hi: NDArray[np.float64]) -> bool:
        g0, g1 = self.box["glass"]
        gap = np.maximum(0.0, np.maximum(g0 - hi, lo - g1))
        return float(np.linalg.norm(gap)) < GLASS_KEEP_OUT_M

    def _on_path(self, s: float) -> NDArray[np.float64]:
        """A point of the camera path at fractional frame index ``s``."""
        k = int(np.clip(np.floor(s), 0, len(self.path) - 2))
        t = s - k
        return (1 - t) * self.path[k] + t * self.path[k + 1]

    def _face_point(self, name: str) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """A random point on an exposed face of a box (not its bottom) and the face's normal."""
        lo, hi = self.box[name]
        for _ in range(100):
            axis, side = int(self.rng.integers(3)), int(self.rng.integers(2))
            if axis == 2 and side == 0:
                continue
            p = self.rng.uniform(lo, hi)
            p[axis] = hi[axis] if side else lo[axis]
            n = np.zeros(3)
            n[axis] = 1.0 if side else -1.0
            if self.truth.distance(p + 0.01 * n)[0] > 0:
                return p, n
        raise RuntimeError(f"no exposed face on {name}")

    def _u(self, a: float, b: float) -> float:
        return float(self.rng.uniform(a, b))

    # -------------------------------------------------------------------------------------------- draws
    def clearance_path(self, qid: str) -> dict:
        s0 = self._u(0, len(self.path) - 6)
        n = int(self.rng.choice([1, 3, 5]))
        pts = np.stack([self._on_path(s0 + 0.5 * k) for k in range(n)])
        z = float(self.rng.choice([-1.0, 0.3, 0.5, 0.75]))
        if z > 0:
            pts[:, 2] = z
        return {"id": qid, "kind": "clearance", "points_m": _r(pts), "radius_m": round(self._u(0.05, 0.35), 3)}

    def clearance_beside(self, qid: str) -> dict:
        a, rr = self._u(0, 2 * np.pi), self._u(1.15, 2.9)
        p = np.array([rr * np.cos(a), rr * np.sin(a), self._u(0.1, 1.7)])
        pts = [p] + [p + self.rng.uniform(-0.25, 0.25, 3) * [1, 1, 0.3] for _ in range(int(self.rng.choice([0, 0, 1, 2])))]
        return {"id": qid, "kind": "clearance", "points_m": _r(np.stack(pts)), "radius_m": round(self._u(0.05, 0.4), 3)}

    def _in_view(self, frame: int, dist_m: tuple[float, float]) -> NDArray[np.float64]:
        """A point in frame ``frame``'s view (the middle 70 % of its image) at a distance in ``dist_m``."""
        fx, fy, cx, cy = self.truth.intrinsics
        u, v = self._u(0.15, 0.85) * 2 * cx, self._u(0.15, 0.85) * 2 * cy
        T = self.truth.poses[frame]
        ray = T[:3, :3] @ np.array([(u - cx) / fx, (v - cy) / fy, 1.0])
        return T[:3, 3] + self._u(*dist_m) * ray / np.linalg.norm(ray)

    def clearance_view(self, qid: str) -> dict:
        p = self._in_view(int(self.rng.integers(len(self.path))), (0.4, 1.8))
        return {"id": qid, "kind": "clearance", "points_m": _r(p[None]), "radius_m": round(self._u(0.05, 0.3), 3)}

    def collision_view(self, qid: str) -> dict:
        f = int(self.rng.integers(len(self.path)))
        pts = np.stack([self._in_view(f, (0.5, 1.6)) for _ in range(2)])
        footprint, _ = self._footprint()
        return {"id": qid, "kind": "collision", "path_m": _r(pts), "footprint": footprint}

    def clearance_obstacle(self, qid: str) -> dict:
        p, n = self._face_point(str(self.rng.choice(FURNITURE)))
        d = self._u(0.03, 0.35)
        return {"id": qid, "kind": "clearance", "points_m": _r((p + d * n)[None]),
                "radius_m": round(d * self._u(0.4, 1.6), 3)}

    def _footprint(self) -> tuple[dict, float]:
        if self.rng.random() < 0.5:
            size = [round(self._u(0.08, 0.35), 3), round(self._u(0.08, 0.35), 3), round(self._u(0.15, 0.5), 3)]
            return {"box_m": size}, size[2]
        size = [round(self._u(0.04, 0.2), 3), round(self._u(0.15, 0.5), 3)]
        return {"cylinder_m": size}, size[1]

    def collision_obstacle(self, qid: str) -> dict:
        name = str(self.rng.choice(LEGS + ("thin_board", "crate_-x", "cabinet_+x", "sideboard_+y", "open")))
        if name == "open":
            a, rr = self._u(0, 2 * np.pi), self._u(1.3, 2.6)
            target = np.array([rr * np.cos(a), rr * np.sin(a), 0.0])
        else:
            lo, hi = self.box[name]
            target = 0.5 * (lo + hi) + np.append(self.rng.uniform(-0.4, 0.4, 2), 0.0)
        footprint, height = self._footprint()
        target[2] = 0.5 * height + self._u(0.03, 0.35)
        ang, length = self._u(0, 2 * np.pi), self._u(0.6, 2.0)
        d = np.array([np.cos(ang), np.sin(ang), 0.0])
        pts = [target - 0.5 * length * d, target + 0.5 * length * d]
        if self.rng.random() < 0.3:  # a kinked path
            kink = ang + self._u(-0.8, 0.8)
            pts.append(pts[-1] + self._u(0.3, 0.8) * np.array([np.cos(kink), np.sin(kink), 0.0]))
        return {"id": qid, "kind": "collision", "path_m": _r(np.stack(pts)), "footprint": footprint}

    def collision_path(self, qid: str) -> dict:
        s0 = self._u(0, len(self.path) - 8)
        pts = np.stack([self._on_path(s0 + k) for k in range(int(self.rng.integers(2, 6)))])
        footprint, _ = self._footprint()
        return {"id": qid, "kind": "collision", "path_m": _r(pts), "footprint": footprint}

    def grasp_board(self, qid: str) -> dict:
        lo, hi = self.box["thin_board"]
        where = self.rng.choice(["face", "face", "edge", "behind", "front"])
        c = np.array([self._u(lo[0] + 0.05, hi[0] - 0.05), hi[1], self._u(0.05, hi[2] - 0.05)])
        if where == "face":
            c[1] += self._u(-0.01, 0.01)
        elif where == "edge":
            k = int(self.rng.integers(3))
            c[0] = [lo[0], hi[0], c[0]][k] + self._u(-0.02, 0.02)
            c[2] = c[2] if k < 2 else self._u(0.0, 0.04)
        elif where == "behind":
            c[1] = self._u(-2.45, lo[1] - 0.08)
        else:
            c[1] = self._u(hi[1] + 0.1, hi[1] + 0.4)
        h = 0.5 * self._u(0.04, 0.1)
        return {"id": qid, "kind": "grasp", "roi_min_m": _r(c - h), "roi_max_m": _r(c + h)}

    def grasp_other(self, qid: str) -> dict:
        p, _ = self._face_point(str(self.rng.choice(FURNITURE)))
        h = 0.5 * self._u(0.04, 0.1)
        return {"id": qid, "kind": "grasp", "roi_min_m": _r(p - h), "roi_max_m": _r(p + h)}

    def foothold_floor(self, qid: str) -> dict:
        a, rr = self._u(0, 2 * np.pi), self._u(0.2, 2.9)
        return {"id": qid, "kind": "foothold", "center_m": _r(np.array([rr * np.cos(a), rr * np.sin(a), 0.0])),
                "radius_m": round(self._u(0.05, 0.2), 3), "max_slope_deg": round(self._u(5, 30), 1)}

    def foothold_other(self, qid: str) -> dict:
        where = self.rng.choice(["top", "wall", "foot"])
        if where == "top":
            lo, hi = self.box[str(self.rng.choice(["crate_-x", "cabinet_+x", "sideboard_+y", "table_top", "chair_seat"]))]
            c = np.array([self._u(lo[0], hi[0]), self._u(lo[1], hi[1]), hi[2]])
        elif where == "wall":
            c, _ = self._face_point(str(self.rng.choice(["locker_+x", "cabinet_+x", "sideboard_+y", "thin_board"])))
            c[2] = max(c[2], 0.3)
        else:
            c, _ = self._face_point(str(self.rng.choice(["crate_-x", "cabinet_+x", "sideboard_+y", "locker_+x"])))
            c[2] = 0.0
        return {"id": qid, "kind": "foothold", "center_m": _r(c), "radius_m": round(self._u(0.05, 0.15), 3),
                "max_slope_deg": round(self._u(5, 30), 1)}

    def explore_furniture(self, qid: str) -> dict:
        name = str(self.rng.choice(["behind_board", "under_table", "under_chair", "behind_crate", "behind_locker",
                                    "behind_cabinet"]))
        regions = {"behind_board": ([-1.8, -2.48, 0.02], [-0.8, -2.04, 1.15]),
                   "under_table": ([-0.55, 1.45, 0.02], [0.55, 2.15, 0.7]),
                   "under_chair": ([0.82, -1.98, 0.02], [1.22, -1.58, 0.43]),
                   "behind_crate": ([-2.7, -2.48, 0.92], [-2.0, -1.6, 1.4]),
                   "behind_locker": ([2.2, -2.48, 2.02], [2.58, -1.6, 2.5]),
                   "behind_cabinet": ([2.1, 1.2, 0.92], [2.58, 2.2, 1.3])}
        lo, hi = (np.asarray(v, dtype=np.float64) for v in regions[name])
        size = (hi - lo) * self.rng.uniform(0.4, 1.0, 3)
        a = lo + (hi - lo - size) * self.rng.uniform(0, 1, 3)
        return {"id": qid, "kind": "explore", "min_m": _r(a), "max_m": _r(a + size),
                "max_unknown_fraction": round(self._u(0.1, 0.9), 2)}

    def explore_other(self, qid: str) -> dict:
        size = self.rng.uniform(0.2, 0.9, 3)
        a = self.rng.uniform([-2.8, -2.3, 0.05], [2.8, 2.3, 2.0]) - 0.5 * size
        return {"id": qid, "kind": "explore", "min_m": _r(a), "max_m": _r(a + size),
                "max_unknown_fraction": round(self._u(0.1, 0.9), 2)}

    # -------------------------------------------------------------------------------------------- truth
    def truth_of(self, item: dict) -> dict | None:
        q = parse_query(item)
        lo, hi = q.extent_m()
        if np.any(lo < self.seen_lo - SEEN_MARGIN_M) or np.any(hi > self.seen_hi + SEEN_MARGIN_M):
            return None  # the map's bounds are those of what the camera saw (plus padding): keep queries near it
        if isinstance(q, ClearanceQuery):
            if self._near_glass(lo, hi) or np.any(self.truth.distance(q.points_m) < 0):
                return None
            return clearance_truth(self.truth, q, self.tol.clearance_m)
        if isinstance(q, CollisionQuery):
            if self._near_glass(lo, hi) or np.any(self.truth.distance(q.path_m[:1]) < 0):
                return None
            return collision_truth(self.truth, q, self.tol.footprint_m, sweep_step(q, self.cfg.sweep_step_m, self.truth.voxel_m))
        if isinstance(q, GraspQuery):
            return grasp_truth(self.truth, q, self.tol.roi_m)
        if isinstance(q, FootholdQuery):
            return foothold_truth(self.truth, q, self.tol.patch_m, self.cfg.foothold_max_flatness_m)
        if isinstance(q, ExploreQuery):
            return explore_truth(self.truth, q, self.tol.unknown_fraction)
        raise AssertionError(q)

    def category(self, name: str, n: int, max_tries: int = 40) -> tuple[list[dict], int]:
        """``n`` queries of a category with their truth, and how many draws were ambiguous."""
        draw: Callable[[str], dict] = getattr(self, name)
        out, dropped = [], 0
        for k in range(n * max_tries):
            if len(out) == n:
                break
            item = draw(f"{name.replace('_', '-')}-{len(out):03d}")
            truth = self.truth_of(item)
            if truth is None:
                dropped += 1
                continue
            item["truth"] = {"category": name, **{k: _plain(v) for k, v in truth.items()}}
            out.append(item)
        return out, dropped


def generate(truth: SceneTruth, seed: int = 25, quotas: dict[str, int] | None = None) -> dict:
    """The query file (a dict): every category of :data:`QUOTAS` with its truth, and how the set was made."""
    gen = Generator(truth, seed)
    queries, dropped = [], {}
    for name, n in (quotas or QUOTAS).items():
        got, d = gen.category(name, n)
        queries += got
        dropped[name] = d
    return {"queries": queries,
            "generator": {"module": "driftmap.decisions.synthetic_queries", "seed": seed, "max_range_m": truth.max_range_m, "voxel_m": truth.voxel_m,
                          "tolerances": vars(gen.tol), "ambiguous_draws_left_out": dropped,
                          "frame": "the synthetic room (ground truth world frame of the log)"}}


def depth_camera_max_range_m(voxel_m: float = 0.02) -> float:
    """The layers' default max range for a depth camera (:func:`driftmap.volume.defaults.resolve_config`)."""
    from driftmap.frame import SensorKind
    from driftmap.preprocess.noise import NoiseModel
    from driftmap.volume.defaults import DEPTH_MAX_RANGE_LIMITS_M, NOISE_PER_VOXEL

    depth = NoiseModel.for_sensor(SensorKind.DEPTH_CAMERA).depth_for_sigma_m(NOISE_PER_VOXEL * voxel_m)
    return float(np.clip(depth, *DEPTH_MAX_RANGE_LIMITS_M))


def _r(a: NDArray[np.float64]) -> list:
    return np.round(np.asarray(a, dtype=np.float64), 4).tolist()


def _plain(v: object) -> object:
    if isinstance(v, (np.floating, float)):
        return round(float(v), 5)
    return v


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if not args:
        print("usage: python -m driftmap.decisions.synthetic_queries OUT.json [LOG_DIR]", file=sys.stderr)
        return 2
    log = Path(args[1]) if len(args) > 1 else Path(__file__).resolve().parents[3] / "datasets" / "synthetic-loop"
    t = time.perf_counter()
    truth = SceneTruth.from_log(log, depth_camera_max_range_m())
    data = generate(truth)
    Path(args[0]).write_text(json.dumps(data, indent=1) + "\n")
    counts: dict[str, int] = {}
    for q in data["queries"]:
        counts[q["truth"]["decision"]] = counts.get(q["truth"]["decision"], 0) + 1
    print(f"{len(data['queries'])} queries ({counts}) in {time.perf_counter() - t:.1f} s: {args[0]}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
