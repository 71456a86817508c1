"""Action decisions (issue 25): 1,000 mixed queries answered by ``driftmap.decisions.decide`` on a real 7-Scenes store,
against a brute-force KD-tree baseline in the same run. Issue target: all 1,000 in <= 1 s on this machine.

The map (built once, untimed, in a temporary folder): ``7scenes-redkitchen`` frames ``0:1000:10`` (100 frames) with the
data set's poses (``build(..., poses_from_source=True, loop_closure=False)``: the default 2-pixel stride, ~6.8M points),
and its volumetric layers (``VolumeLayers.from_store``, default settings: 2 cm voxels, 2.29 m max range), also built
once and untimed and handed to ``decide(store, queries, layers=layers)``, as a navigation stack keeping them in memory
would.

The queries (seed 0; every region starts at a map point, so all lie inside the map's bounds), shuffled into one set:

* 300 ``clearance``: 1-3 points (5-20 cm apart) at a camera centre (1/4) or 2-50 cm from a map point (towards the
  sensor that saw it, or in a random direction), radius 5-30 cm;
* 200 ``collision``: a path of 1-2 segments of 20-70 cm (mostly horizontal) starting 10-60 cm from a map point, a box
  (8-35 cm sides) or vertical cylinder (radius 5-20 cm, height 10-50 cm) swept along it;
* 150 ``grasp``: a ROI of 4-12 cm sides centred on a map point;
* 150 ``foothold``: a patch of radius 5-15 cm centred on a map point, max slope 10-30 deg (the 7-Scenes world frame is
  not gravity-aligned, so most patches are ``too_steep``: the cost does not depend on it);
* 200 ``explore``: a box of 20-100 cm sides around a point near the map, max unknown fraction 0.1-0.6.

Ours: ``decide(store, queries, layers=layers)`` on all 1,000 (one item; the unit is the whole set). Anchor
(``kdtree_brute_force``): the same queries answered from a scipy ``cKDTree`` over the map's full-resolution points --
the points the layers trust as hits, i.e. within the max range of their sensor, as ``decide``'s grasp/foothold use --
with no volumetric layers (so no unknown space, no frames, no uncertainty):

* clearance: nearest-neighbour distance minus the radius (``blocked`` below 0, else ``free``);
* collision: the footprint placed every half voxel along the path (as ours); at the placements whose nearest point is
  within the footprint's bounding radius plus the tolerance, the points in that ball tested against the box /
  cylinder; the smallest signed distance (exact below the tolerance; a sweep stops at a contact deeper than it);
* grasp / foothold: the points in the ROI (a ball query, then the box / cylinder test) and one PCA plane normal
  (foothold: slope, flatness and the decision; grasp: ``too_few_points`` or not, and the normal);
* explore: not answered (a point cloud has no free / unknown space; a ray cast per region would be a volumetric map of
  its own): the anchor's time covers the 800 other queries, which favours the anchor.

Both get an untimed warm-up: ``decide``'s shared structures (surface KD-tree, unknown-voxel table, provenance index,
cell index of the points, the map's 1 cm voxel normals: cached on the layers, as for a stack) and one query of each
kind; the anchor's KD-tree is built untimed.

``python benchmarks/bench_decide.py --records OUT.json`` writes the records of the 1,000 decisions without their
latencies, ``--compare A.json B.json`` lists the fields in which two such files differ (floats compared exactly): a
speed-up must leave them identical.

Checks (on the results of the last timed pass; the run fails when one does not hold):

* clearance: ours measures to the *cube* of the nearest observed-surface voxel (occupied, at least 2 hits: no point
  measured in it is nearer), the anchor to raw points. Where the anchor's nearest point lies in such a voxel, ours is
  at most the anchor's margin (that point's cube is at most as far) and at least it less one voxel diagonal
  (``CLEARANCE_BAND``: the nearest cube holds measured points at most that much farther); this holds on
  >= ``MIN_AGREEMENT`` of those queries, and so do the ``blocked`` decisions whose anchor margin is farther than the
  band from 0; and on every query ours is never nearer to an obstacle than the nearest map point by more than the
  band (a surface ours would invent). (Before clearance went to the cubes, the check was "within one voxel of the
  anchor", which the cubes' up to 3.5 cm nearer margins no longer meet: 82.7 % on this run.) The other queries have
  their nearest raw point in a voxel the layers carved free (other frames' rays passed through it: 20 % of the hit
  voxels of this map, e.g. a cluster of 16 points one frame saw) or that holds a single point: there ours is farther
  by up to 23 cm, by design; the counts are in the details;
* collision: contact or not (ours: margin < 0, i.e. a surface point inside the footprint anywhere on the path,
  whatever the unknown space decided) agrees with the anchor on >= ``MIN_AGREEMENT`` of the sweeps, where the anchor's
  deepest point within the tolerance of the footprint's boundary counts as agreeing when both margins are within the
  tolerance of each other (measured: 99 %; both others have the anchor's deepest point in a voxel ours does not keep
  as surface);
* grasp / foothold: the number of points in every ROI / patch is the same (exactly: the same points and the same
  range cut), and so is every ``too_few_points`` decision. The normals are not compared as a check (ours fits one per
  1 cm voxel over its 64 nearest within 3 cm and takes the dominant one and the spread; the anchor one plane): their median angle and
  the foothold decisions' agreement are in the details.

``decide(..., threads=2)`` and one thread are timed in the same passes; the headline (``ours``) is two threads, the
machine's two cores as ``decide --threads 2`` answers (since stop 54; one thread before), one thread is in
``details.one_thread`` with the speed-up in ``details.threads``; the two-thread records must equal one thread's, bit
for bit, or the run fails.

Per-query latency (``Decision.latency_s``, per kind) and ``decide``'s own split (prepare / decide) are in the details,
and (not in a quick run) the top functions of a cProfile of ``decide`` on 10 queries of each kind. The run's target
ratio is 1 s over the anchor's time, so that PASS means the issue's absolute target (1,000 queries <= 1 s) is met; the
machine is shared, so the load averages before and after timing are kept too.
"""

from __future__ import annotations

import cProfile
import itertools
import os
import statistics
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
from _harness import check, time_per_item, top_functions
from scipy.spatial import cKDTree

from driftmap.datasets import shared_datasets_dir
from driftmap.decisions import DecideConfig, QuerySet, decide, parse_queries
from driftmap.decisions.decide import prepare
from driftmap.pipeline.build import build
from driftmap.store.frame_store import FrameStore
from driftmap.volume import VolumeLayers
from driftmap.volume.queries import surface_tree

SCENE = "7scenes-redkitchen"
FRAMES = "0:1000:10"
SEED = 0
N_KIND = {"clearance": 300, "collision": 200, "grasp": 150, "foothold": 150, "explore": 200}
TARGET_S = 1.0
"""the issue's target: all 1,000 queries in this many seconds"""
MIN_AGREEMENT = 0.95
CLEARANCE_BAND = float(np.sqrt(3.0))
"""clearance: ours (to an observed-surface voxel's cube) may be nearer than the nearest raw point by this many voxels"""
REPEATS, QUICK_REPEATS = 5, 1
BUDGET_S = 900.0
"""no further repetition is started when it would take the timed passes beyond this (a pass of ``decide`` took 9-19
minutes on the shared 2-core machine when this benchmark was written: one repetition is then all there is)"""
PROFILE_PER_KIND = 10
THREADS = 2
"""``decide(..., threads=THREADS)``: the headline (the queries answered by both cores of the machine, as
``decide --threads 2``); one thread is timed in the same passes (``details.one_thread``)"""


# ------------------------------------------------------------------------------------------------------ the map
def range_limited_points(layers: VolumeLayers) -> tuple[np.ndarray, np.ndarray]:
    """The map's full-resolution points (float64) within the volume's max range of their sensor, and their frames:
    the points ``decide`` reads for grasp and foothold (``DecisionContext.points_in_box``), the layers' hits."""
    view = layers.view
    pts = view.points_world.astype(np.float64)
    fids = np.asarray(view.point_frame_ids(), dtype=np.int64)
    max_range = layers.config.max_range_m
    if max_range is None:
        return pts, fids
    uniq, inv = np.unique(fids, return_inverse=True)
    origins = np.stack([view.pose(int(f))[:3, 3] for f in uniq])
    keep = np.linalg.norm(pts - origins[inv], axis=1) <= float(max_range)
    return pts[keep], fids[keep]


def _unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def make_queries(layers: VolumeLayers, pts: np.ndarray, fids: np.ndarray, rng: np.random.Generator) -> QuerySet:
    """The 1,000 mixed queries (module docstring), shuffled."""
    view = layers.view
    origin = {int(f): view.pose(int(f))[:3, 3] for f in np.unique(fids)}
    centres = np.stack(list(origin.values()))

    def surface_point() -> tuple[np.ndarray, np.ndarray]:
        i = int(rng.integers(len(pts)))
        return pts[i], origin[int(fids[i])]

    def near_point(lo_m: float, hi_m: float) -> np.ndarray:
        """a map point moved towards the sensor that saw it (into observed free space), or in a random direction"""
        p, o = surface_point()
        d = (o - p) / np.linalg.norm(o - p)
        if rng.random() < 0.5:
            d = _unit(rng)
        return p + d * rng.uniform(lo_m, hi_m)

    out = []
    for k in range(N_KIND["clearance"]):
        a = centres[rng.integers(len(centres))] if rng.random() < 0.25 else near_point(0.02, 0.5)
        points = a + np.arange(int(rng.integers(1, 4)))[:, None] * (_unit(rng) * rng.uniform(0.05, 0.2))
        out.append({"id": f"clearance-{k:03d}", "kind": "clearance", "points_m": points.round(4).tolist(),
                    "radius_m": round(float(rng.uniform(0.05, 0.3)), 3)})
    for k in range(N_KIND["collision"]):
        path = [near_point(0.1, 0.6)]
        for _ in range(int(rng.integers(1, 3))):
            d = _unit(rng) * np.array([1.0, 1.0, 0.3])
            path.append(path[-1] + d / np.linalg.norm(d) * rng.uniform(0.2, 0.7))
        if rng.random() < 0.5:
            fp = {"box_m": rng.uniform(0.08, 0.35, 3).round(3).tolist()}
        else:
            fp = {"cylinder_m": [round(float(rng.uniform(0.05, 0.2)), 3), round(float(rng.uniform(0.1, 0.5)), 3)]}
        out.append({"id": f"collision-{k:03d}", "kind": "collision", "path_m": np.round(path, 4).tolist(),
                    "footprint": fp})
    for k in range(N_KIND["grasp"]):
        p, _ = surface_point()
        h = rng.uniform(0.02, 0.06, 3)
        out.append({"id": f"grasp-{k:03d}", "kind": "grasp", "roi_min_m": (p - h).round(4).tolist(),
                    "roi_max_m": (p + h).round(4).tolist()})
    for k in range(N_KIND["foothold"]):
        p, _ = surface_point()
        out.append({"id": f"foothold-{k:03d}", "kind": "foothold", "center_m": p.round(4).tolist(),
                    "radius_m": round(float(rng.uniform(0.05, 0.15)), 3),
                    "max_slope_deg": round(float(rng.uniform(10, 30)), 1)})
    for k in range(N_KIND["explore"]):
        c = near_point(0.0, 0.3)
        h = rng.uniform(0.1, 0.5, 3)
        out.append({"id": f"explore-{k:03d}", "kind": "explore", "min_m": (c - h).round(4).tolist(),
                    "max_m": (c + h).round(4).tolist(), "max_unknown_fraction": round(float(rng.uniform(0.1, 0.6)), 2)})
    return parse_queries({"queries": [out[i] for i in rng.permutation(len(out))]})


# ------------------------------------------------------------------------------------------------------ the anchor
def _path_samples(path: np.ndarray, step_m: float) -> np.ndarray:
    """Points every ``step_m`` (at most) along a polyline, its vertices included."""
    pts = [path[:1]]
    for a, b in itertools.pairwise(path):
        seg = float(np.linalg.norm(b - a))
        if seg > 0:
            n = max(1, int(np.ceil(seg / step_m)))
            pts.append(a + (b - a) * (np.arange(1, n + 1) / n)[:, None])
    return np.concatenate(pts)


def _footprint_signed(q, offsets: np.ndarray) -> np.ndarray:
    """Signed distance of points (relative to the footprint's centre) to a box / vertical cylinder: negative inside."""
    if q.footprint == "box":
        d = np.abs(offsets) - 0.5 * np.asarray(q.size_m)
    else:
        r, h = q.size_m
        d = np.stack([np.hypot(offsets[:, 0], offsets[:, 1]) - r, np.abs(offsets[:, 2]) - 0.5 * h], axis=1)
    outside = np.sqrt(np.sum(np.maximum(d, 0.0) ** 2, axis=1))
    return np.where(np.all(d <= 0, axis=1), d.max(axis=1), outside)


def _pca_normal(p: np.ndarray) -> np.ndarray:
    c = p - p.mean(axis=0)
    return np.linalg.eigh(c.T @ c)[1][:, 0]


class BruteForce:
    """The baseline: every query answered from one KD-tree over the map's points (module docstring)."""

    def __init__(self, pts: np.ndarray, tolerance_m: float, sweep_step_m: float, cfg: DecideConfig):
        self.pts, self.tol, self.step, self.cfg = pts, tolerance_m, sweep_step_m, cfg
        self.tree = cKDTree(pts)

    def answer(self, qs: QuerySet) -> dict[str, dict]:
        out = {}
        for q in qs:
            t = time.perf_counter()
            result = getattr(self, q.kind)(q)
            result["latency_s"] = time.perf_counter() - t
            out[q.id] = result
        return out

    def clearance(self, q) -> dict:
        d, i = self.tree.query(q.points_m)
        k = int(np.argmin(d))
        margin = float(d[k]) - q.radius_m
        return {"decision": "blocked" if margin < 0 else "free", "margin": margin, "nearest_m": self.pts[i[k]]}

    def collision(self, q) -> dict:
        samples = _path_samples(q.path_m, self.step)
        reach = float(np.linalg.norm(q.half_extent_m)) + self.tol
        d_nn, _ = self.tree.query(samples)
        best, deepest = np.inf, None
        for i in np.flatnonzero(d_nn <= reach):
            idx = self.tree.query_ball_point(samples[i], reach)
            if idx:
                signed = _footprint_signed(q, self.pts[idx] - samples[i])
                j = int(np.argmin(signed))
                if signed[j] < best:
                    best, deepest = float(signed[j]), self.pts[idx[j]]
                if best < -self.tol:  # a contact deeper than the tolerance: the answer cannot change
                    break
        return {"decision": "blocked" if best < 0 else "free", "margin": best, "deepest_m": deepest}

    def _region(self, centre: np.ndarray, radius: float) -> np.ndarray:
        return self.pts[self.tree.query_ball_point(centre, radius * (1 + 1e-9) + 1e-9)]

    def grasp(self, q) -> dict:
        lo, hi = q.roi_min_m, q.roi_max_m
        p = self._region(0.5 * (lo + hi), float(np.linalg.norm(0.5 * (hi - lo))))
        p = p[np.all((p >= lo) & (p <= hi), axis=1)]
        if len(p) < (q.min_points or self.cfg.grasp_min_points):
            return {"decision": "too_few_points", "n_points": len(p)}
        return {"decision": "enough_points", "n_points": len(p), "normal": _pca_normal(p)}

    def foothold(self, q) -> dict:
        r, c = q.radius_m, q.center_m
        p = self._region(c, r * np.sqrt(2.0))
        p = p[(np.linalg.norm(p[:, :2] - c[:2], axis=1) <= r) & (np.abs(p[:, 2] - c[2]) <= r)]
        if len(p) < (q.min_points or self.cfg.foothold_min_points):
            return {"decision": "too_few_points", "n_points": len(p)}
        e = _pca_normal(p)
        e = -e if e[2] < 0 else e
        along = p @ e
        flatness = float(np.sqrt(np.mean((along - np.median(along)) ** 2)))
        slope = float(np.degrees(np.arccos(np.clip(abs(e[2]), 0.0, 1.0))))
        max_flat = q.max_flatness_m if q.max_flatness_m is not None else self.cfg.foothold_max_flatness_m
        decision = "uneven" if flatness > max_flat else "too_steep" if slope > q.max_slope_deg else "stable"
        return {"decision": decision, "n_points": len(p), "normal": e, "slope_deg": slope, "flatness_m": flatness}

    def explore(self, q) -> dict:
        return {"decision": None}  # not answered: a point cloud has no unknown space


# ------------------------------------------------------------------------------------------------------ timing
def _timed(impls: dict, item, *, max_repeats: int, budget_s: float) -> dict[str, dict]:
    """``time_per_item`` on one item, a repetition at a time (the implementations taking turns, the first one
    rotating), until ``max_repeats`` or until one more repetition would take the passes beyond ``budget_s``."""
    names, samples, faults = list(impls), defaultdict(list), defaultdict(float)
    t0 = time.perf_counter()
    for rep in range(max_repeats):
        order = names[rep % len(names):] + names[:rep % len(names)]
        got = time_per_item({n: impls[n] for n in order}, [item], repeats=1, warmup=0)
        for n in names:
            samples[n] += got[n]["samples_s"]
            faults[n] += got[n]["page_faults_per_item"]
        elapsed = time.perf_counter() - t0
        if elapsed * (rep + 2) / (rep + 1) > budget_s:
            break
    return {n: {"median_s": statistics.median(s), "min_s": min(s), "max_s": max(s), "repeats": len(s), "items": 1,
                "page_faults_per_item": faults[n] / len(s), "samples_s": s} for n, s in samples.items()}


def _latency_stats(values: list[float]) -> dict:
    v = np.asarray(values)
    return {"n": len(v), "mean_ms": 1e3 * float(v.mean()), "median_ms": 1e3 * float(np.median(v)),
            "p90_ms": 1e3 * float(np.percentile(v, 90)), "max_ms": 1e3 * float(v.max()), "sum_s": float(v.sum())}


def _profile_top(store: FrameStore, qs: QuerySet, layers: VolumeLayers, n: int = 12) -> dict:
    picked = []
    for kind in N_KIND:
        picked += [q for q in qs if q.kind == kind][:PROFILE_PER_KIND]
    profile = cProfile.Profile()
    t0 = time.perf_counter()
    profile.enable()
    decide(store, QuerySet(picked), layers=layers)
    profile.disable()
    total = time.perf_counter() - t0
    return {"queries": len(picked), "seconds": total, "top_by_tottime": top_functions(profile, n)}


# ------------------------------------------------------------------------------------------------------ the check
def _compare(decisions, theirs: dict[str, dict], tol: float, surface_voxel, band: float) -> dict:
    """Agreement of ours with the anchor; ``surface_voxel(points)``: which points lie in a voxel the layers keep as
    observed surface (occupied, at least ``surface_min_hits`` points); ``band``: how much nearer than the anchor's
    nearest point ours may measure (to a voxel's cube: a voxel diagonal)."""
    by_kind = defaultdict(list)
    for d in decisions:
        by_kind[d.kind].append((d, theirs[d.id]))

    # clearance: where the anchor's nearest point is on ours' observed surface, ours (to the voxels' cubes) between
    # the anchor's margin and it less the band; everywhere: ours never nearer than a raw point by more than the band
    rows = by_kind["clearance"]
    eps = 1e-9
    delta = np.array([d.margin - a["margin"] for d, a in rows])
    on_surface = surface_voxel(np.array([a["nearest_m"] for _, a in rows]))
    within = (delta <= eps) & (delta >= -band - eps)
    firm = on_surface & np.array([abs(a["margin"]) > band for _, a in rows])
    blocked_same = np.array([(d.decision == "blocked") == (a["margin"] < 0) for d, a in rows])
    worst = sorted(((float(x), d.id) for x, (d, _) in zip(delta, rows)), key=lambda t: -abs(t[0]))[:5]
    # collision: contact or not, the tolerance band judged by the margins
    coll_ok, coll_strict, coll_band = [], [], 0
    for d, a in by_kind["collision"]:
        ours_contact, m = d.margin is not None and d.margin < 0, a["margin"]
        if m < -tol:
            ok = ours_contact
        elif m >= tol:
            ok = not ours_contact
        else:
            coll_band += 1
            ok = d.margin is not None and abs(d.margin - m) <= tol
        coll_ok.append(ok)
        coll_strict.append(ours_contact == (m < 0))
    coll_fail = [d.id for (d, _), ok in zip(by_kind["collision"], coll_ok) if not ok]
    fail_points = [a["deepest_m"] for (_, a), ok in zip(by_kind["collision"], coll_ok)
                   if not ok and a["deepest_m"] is not None]
    coll_fail_off_surface = int((~surface_voxel(np.array(fail_points))).sum()) if fail_points else 0

    # grasp / foothold: the same points in every region; normals and foothold decisions for information
    count_diff, few_diff, angles, foot_same = [], [], [], []
    for kind in ("grasp", "foothold"):
        for d, a in by_kind[kind]:
            if d.details.get("n_points") != a["n_points"]:
                count_diff.append((d.id, d.details.get("n_points"), a["n_points"]))
            if (d.decision == "too_few_points") != (a["decision"] == "too_few_points"):
                few_diff.append(d.id)
            if "normal" in a and d.details.get("normal") is not None:
                cos = abs(float(np.dot(np.asarray(d.details["normal"], dtype=np.float64), a["normal"])))
                angles.append(float(np.degrees(np.arccos(min(1.0, cos)))))
            if kind == "foothold" and a["decision"] != "too_few_points":
                foot_same.append(d.decision == a["decision"])
    return {
        "clearance_on_surface": int(on_surface.sum()),
        "clearance_margin_agreement_on_surface": float(np.mean(within[on_surface])) if on_surface.any() else 1.0,
        "clearance_never_nearer": float(np.mean(delta >= -band - eps)),
        "clearance_band_m": band,
        "clearance_margin_agreement_all": float(np.mean(within)),
        "clearance_disagreeing_off_surface": int(np.sum(~within & ~on_surface)),
        "clearance_blocked_agreement_on_surface_outside_band": (float(np.mean(blocked_same[firm])) if firm.any()
                                                                else 1.0),
        "clearance_blocked_agreement_all": float(np.mean(blocked_same)),
        "clearance_margin_delta_m": {"median": float(np.median(delta)), "p05": float(np.percentile(delta, 5)),
                                     "p95": float(np.percentile(delta, 95)), "worst": worst},
        "collision_contact_agreement": float(np.mean(coll_ok)),
        "collision_contact_agreement_strict": float(np.mean(coll_strict)),
        "collision_in_tolerance_band": coll_band,
        "collision_disagreeing": coll_fail[:20],
        "collision_disagreeing_off_surface": coll_fail_off_surface,
        "grasp_foothold_count_mismatches": count_diff[:20],
        "grasp_foothold_too_few_points_mismatches": few_diff[:20],
        "normal_angle_deg_ours_vs_pca": ({"median": float(np.median(angles)), "p90": float(np.percentile(angles, 90)),
                                          "n": len(angles)} if angles else None),
        "foothold_decision_agreement_info": float(np.mean(foot_same)) if foot_same else None,
    }


# ------------------------------------------------------------------------------------------------------ run
def run(quick: bool = False) -> list[dict]:
    folder = shared_datasets_dir() / SCENE
    with tempfile.TemporaryDirectory(prefix="driftmap-bench-decide-") as tmp:
        path = Path(tmp) / "kitchen"
        t0 = time.perf_counter()
        build(folder, path, poses_from_source=True, loop_closure=False, frames=FRAMES)
        build_s = time.perf_counter() - t0
        store = FrameStore.open(path)
        n_frames = len(store)
        t0 = time.perf_counter()
        layers = VolumeLayers.from_store(store, store.head)
        layers_s = time.perf_counter() - t0
        pts, fids = range_limited_points(layers)
        qs = make_queries(layers, pts, fids, np.random.default_rng(SEED))
        cfg = DecideConfig()
        voxel = float(layers.grid.voxel_size_m)
        tol = voxel
        t0 = time.perf_counter()
        anchor = BruteForce(pts, tol, cfg.sweep_step_m or 0.5 * voxel, cfg)
        tree_s = time.perf_counter() - t0

        # warm-up (untimed): the shared structures decide caches on the layers, and one query of each kind
        t0 = time.perf_counter()
        prepare(layers)
        prepare_s = time.perf_counter() - t0
        warm = QuerySet([next(q for q in qs if q.kind == kind) for kind in N_KIND])
        decide(store, warm, layers=layers)
        anchor.answer(warm)

        last: dict[str, object] = {}

        def ours(item: QuerySet) -> None:
            last["ours"] = decide(store, item, layers=layers)

        def brute(item: QuerySet) -> None:
            last["anchor"] = anchor.answer(item)

        def ours_threads(item: QuerySet) -> None:
            last["ours_threads"] = decide(store, item, layers=layers, threads=THREADS)

        load_before = os.getloadavg()
        timings = _timed({"driftmap": ours, "kdtree_brute_force": brute, "driftmap_threads": ours_threads}, qs,
                         max_repeats=QUICK_REPEATS if quick else REPEATS, budget_s=BUDGET_S)
        load_after = os.getloadavg()
        decisions, theirs = last["ours"].decisions, last["anchor"]

        surface_keys = {tuple(k) for k in layers.grid.lattice_index(np.asarray(surface_tree(layers).data)).tolist()}

        def surface_voxel(points: np.ndarray) -> np.ndarray:
            return np.array([tuple(k) in surface_keys for k in layers.grid.lattice_index(points).tolist()], dtype=bool)

        band = CLEARANCE_BAND * voxel
        agreement = _compare(decisions, theirs, tol, surface_voxel, band)
        check(agreement["clearance_margin_agreement_on_surface"] >= MIN_AGREEMENT,
              f"clearance: where the KD-tree's nearest point lies on the observed surface, margins between its and "
              f"{band * 100:.1f} cm less on only {agreement['clearance_margin_agreement_on_surface']:.1%} of the "
              f"queries (< {MIN_AGREEMENT:.0%}); worst {agreement['clearance_margin_delta_m']['worst']}")
        check(agreement["clearance_blocked_agreement_on_surface_outside_band"] >= MIN_AGREEMENT,
              f"clearance: blocked decisions agree with the KD-tree's on only "
              f"{agreement['clearance_blocked_agreement_on_surface_outside_band']:.1%} (< {MIN_AGREEMENT:.0%})")
        check(agreement["clearance_never_nearer"] == 1.0,
              f"clearance: ours finds an obstacle nearer than any map point by more than {band * 100:.1f} cm on "
              f"{1 - agreement['clearance_never_nearer']:.1%} of the queries: {agreement['clearance_margin_delta_m']}")
        check(agreement["collision_contact_agreement"] >= MIN_AGREEMENT,
              f"collision: contact agrees with the KD-tree sweep on only "
              f"{agreement['collision_contact_agreement']:.1%} (< {MIN_AGREEMENT:.0%}): "
              f"{agreement['collision_disagreeing']}")
        check(not agreement["grasp_foothold_count_mismatches"],
              f"grasp/foothold: other point counts than the KD-tree's: {agreement['grasp_foothold_count_mismatches']}")
        check(not agreement["grasp_foothold_too_few_points_mismatches"],
              f"grasp/foothold: too_few_points differs: {agreement['grasp_foothold_too_few_points_mismatches']}")

        lat_ours, lat_theirs, counts = defaultdict(list), defaultdict(list), defaultdict(int)
        for d in decisions:
            lat_ours[d.kind].append(d.latency_s)
            counts[f"{d.kind}:{d.decision}"] += 1
            if d.kind != "explore":
                lat_theirs[d.kind].append(theirs[d.id]["latency_s"])
        check(records(last["ours_threads"]) == records(last["ours"]),
              f"decide with {THREADS} threads: other records than with 1 (they must be the same, bit for bit)")
        profile = None if quick else _profile_top(store, qs, layers)
        ours_t = timings.pop("driftmap")
        threads_t = timings.pop("driftmap_threads")
        anchor_s = timings["kdtree_brute_force"]["median_s"]
        n_points = int(layers.view.n_points)
        n_steps = sum(len(_path_samples(q.path_m, anchor.step)) for q in qs if q.kind == "collision")
        details = {
            "headline": f"decide(..., threads={THREADS}): the machine's {THREADS} cores, as `decide --threads "
                        f"{THREADS}` answers (since stop 54; one thread below, in 'one_thread')",
            "target_s": TARGET_S,
            "target_met": threads_t["median_s"] <= TARGET_S,
            "total_s": threads_t["median_s"],
            "per_query_ms": 1e3 * threads_t["median_s"] / len(qs),
            "anchor_total_s": anchor_s,
            "anchor_per_query_ms": 1e3 * anchor_s / len(qs),
            "anchor_answers": "800 (explore not answered by the anchor: no unknown space in a point cloud)",
            "ratio_vs_anchor": threads_t["median_s"] / anchor_s,
            "threads": {"threads": THREADS, "total_s": threads_t["median_s"],
                        "target_met": threads_t["median_s"] <= TARGET_S,
                        "speed_up_vs_1_thread": ours_t["median_s"] / threads_t["median_s"], "timing": threads_t,
                        "records": "the same as with 1 thread, bit for bit (checked)"},
            "one_thread": {"total_s": ours_t["median_s"], "target_met": ours_t["median_s"] <= TARGET_S,
                           "ratio_vs_anchor": ours_t["median_s"] / anchor_s, "timing": ours_t},
            "times_over_target": threads_t["median_s"] / TARGET_S,
            "latency_per_kind_ours": {k: _latency_stats(v) for k, v in lat_ours.items()},
            "latency_per_kind_anchor": {k: _latency_stats(v) for k, v in lat_theirs.items()},
            "decide_seconds_split": last["ours"].seconds,
            "decisions": dict(sorted(counts.items())),
            "agreement": agreement,
            "tolerance_m": tol,
            "min_agreement": MIN_AGREEMENT,
            "n_queries": len(qs),
            "queries_per_kind": N_KIND,
            "collision_placements_total": n_steps,
            "map": {"scene": SCENE, "frames": FRAMES, "n_frames": n_frames, "n_points": n_points,
                    "n_points_in_range": len(pts), "voxel_m": voxel, "max_range_m": layers.config.max_range_m,
                    "grid_min_m": layers.grid.min_m.tolist(), "grid_max_m": layers.grid.max_m.tolist()},
            "untimed_setup_s": {"build": build_s, "layers": layers_s, "anchor_kdtree": tree_s, "prepare": prepare_s},
            "machine": {"cpu_count": os.cpu_count(), "load_avg_before": load_before, "load_avg_after": load_after},
            "profile": profile,
        }
        store.close()
    return [{
        "name": "decide",
        "description": f"driftmap.decisions.decide (threads={THREADS}; one thread in the details) on {len(qs):,} mixed queries (clearance 300, collision 200, grasp "
                       f"150, foothold 150, explore 200; seed {SEED}) with the layers built once, on a 7-Scenes "
                       f"redkitchen store ({n_frames} frames {FRAMES}, data set's poses, {n_points / 1e6:.1f}M "
                       f"points); issue target: all {len(qs):,} in <= {TARGET_S:g} s (the target ratio is "
                       f"{TARGET_S:g} s / the anchor's time); anchor: scipy cKDTree brute force over the "
                       f"{len(pts) / 1e6:.1f}M in-range points (explore not answered by it)",
        "unit": f"{len(qs):,} queries",
        "ours": threads_t,
        "anchors": timings,
        "target_ratio": TARGET_S / anchor_s,
        "check": f"clearance: margins between the KD-tree's and {band * 100:.1f} cm less (a voxel diagonal: ours "
                 f"measures to the voxels' cubes) on "
                 f"{agreement['clearance_margin_agreement_on_surface']:.1%} of the {agreement['clearance_on_surface']} "
                 f"queries whose nearest map point lies in an observed-surface voxel (blocked agrees on "
                 f"{agreement['clearance_blocked_agreement_on_surface_outside_band']:.1%} of them outside the band; "
                 f"{agreement['clearance_margin_agreement_all']:.1%} of all {N_KIND['clearance']}: the others' "
                 f"nearest point is one the layers carved or saw once), never nearer than the map's points by more; "
                 f"collision contact on {agreement['collision_contact_agreement']:.1%} (>= {MIN_AGREEMENT:.0%} "
                 "each); grasp/foothold point counts and too_few_points identical; explore not compared",
        "details": details,
    }]


# ------------------------------------------------------------------------------------------------------ records
def records(decisions) -> list[dict]:
    """The JSON records of a decision set without their latencies: what must not change when only the speed does."""
    out = []
    for d in decisions.decisions:
        j = d.to_json()
        j.pop("latency_s")
        out.append(j)
    return out


def write_records(path: Path) -> None:
    """Answer the benchmark's 1,000 queries once on its store and write their records (:func:`records`) as JSON."""
    import json

    with tempfile.TemporaryDirectory(prefix="driftmap-bench-decide-") as tmp:
        store_path = Path(tmp) / "kitchen"
        build(shared_datasets_dir() / SCENE, store_path, poses_from_source=True, loop_closure=False, frames=FRAMES)
        store = FrameStore.open(store_path)
        layers = VolumeLayers.from_store(store, store.head)
        pts, fids = range_limited_points(layers)
        qs = make_queries(layers, pts, fids, np.random.default_rng(SEED))
        path.write_text(json.dumps(records(decide(store, qs, layers=layers))))
        store.close()


def differences(a: list[dict], b: list[dict], tolerance: float = 0.0) -> list[tuple]:
    """Every field (path, a's value, b's value) in which two record lists differ; floats compared exactly, or to
    within ``tolerance`` (absolute, or relative to the larger magnitude, whichever is looser)."""
    out: list[tuple] = []

    def walk(x, y, where: str) -> None:
        if (tolerance and isinstance(x, float) and isinstance(y, float)
                and abs(x - y) <= tolerance * max(1.0, abs(x), abs(y))):
            return
        if isinstance(x, dict) and isinstance(y, dict) and x.keys() == y.keys():
            for k in x:
                walk(x[k], y[k], f"{where}.{k}")
        elif isinstance(x, list) and isinstance(y, list) and len(x) == len(y):
            for i, (u, v) in enumerate(zip(x, y)):
                walk(u, v, f"{where}[{i}]")
        elif x != y or type(x) is not type(y):
            out.append((where, x, y))

    if len(a) != len(b):
        return [("<records>", len(a), len(b))]
    for r, s in zip(a, b):
        walk(r, s, str(r.get("id")))
    return out


if __name__ == "__main__":
    import argparse
    import json
    import sys

    parser = argparse.ArgumentParser(description="the decide benchmark's records (latency aside), to check that a "
                                                 "speed-up changes no decision (timing: run.py --only decide)")
    parser.add_argument("--records", type=Path, help="answer the 1,000 queries and write their records here")
    parser.add_argument("--compare", type=Path, nargs=2, metavar=("A", "B"), help="compare two records files")
    parser.add_argument("--tolerance", type=float, default=0.0,
                        help="--compare: floats within this (absolute, or relative above 1) count as equal (the "
                             "frame spread's compiled pass rounds differently from numpy: 1e-12 m)")
    args = parser.parse_args()
    if args.records:
        write_records(args.records)
    if args.compare:
        diff = differences(*(json.loads(p.read_text()) for p in args.compare), tolerance=args.tolerance)
        for row in diff[:20]:
            print(*row)
        print(f"{len(diff)} differing fields")
        sys.exit(1 if diff else 0)
