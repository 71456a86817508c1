"""Volumetric layers (issue 24): TSDF and occupancy integration against Open3D and OctoMap, the cost of a correction
against a rebuild, and the memory per observed voxel.

Frames: 7-Scenes ``redkitchen`` frames 0, 5, 10, 15, 20 (the first frames of a store built with a 5-frame step),
ground-truth poses, 2 cm voxels. Every timed pass integrates the five frames, in order, into an empty map (a fresh
grid / VoxelBlockGrid / OcTree made untimed before the pass); times are per frame, medians over the passes, the
implementations taking turns.

* ``tsdf_integration``: one 640x480 depth frame (the PNG in metres, 0 and 65535 invalid), 8 cm truncation, 4 m depth
  max. Ours: the layers' block selection (:func:`driftmap.volume.layers.tsdf_blocks`: Open3D's
  ``compute_unique_block_coordinates``, including wrapping the numpy image) then ``kernels.tsdf_projective`` into a
  dense int64 / int32 grid covering the blocks of the five frames. Anchor: Open3D ``VoxelBlockGrid``
  ``compute_unique_block_coordinates`` + ``integrate`` on the same image (already an Open3D image) and pose.
  Target <= 1.0x. Check: after a pass every sample's weight equals our count and the TSDF agrees to 1e-5.
* ``occupancy_full_res`` / ``occupancy_stride2``: the frame's rays (its back-projected points, 0.2..4 m depth, in the
  world frame; origin the camera centre) at full resolution and at the 2-pixel stride ``build`` stores, cut at the
  layers' max range for a Kinect at 2 cm (2.29 m). Ours: the cut (as :func:`~driftmap.volume.observation.observe`)
  and ``kernels.occupancy_update``. Anchors: pyoctomap ``OcTree.insertPointCloud(points, origin, max_range)``
  (OctoMap cuts the rays itself) with its defaults, and with ``lazy_eval=True`` followed by one
  ``updateInnerOccupancy()`` per frame. Target <= 0.5x. Details: pyoctomap's Python-side cost of handing over the
  points (measured by inserting the same number of points at the origin) and OctoMap's ``discretize=True`` mode (one
  ray per end voxel: not the same rays, so not an anchor). Check: occupied / free agree on >= 99 % of sampled
  voxels both observe.
* ``correction_synthetic`` / ``correction_7scenes``: a store (the synthetic log with its ground truth; 7-Scenes
  frames 0:1000:5 with the data set's poses) gets a revision moving its last 10 % of frames by 3 cm;
  ``VolumeLayers.apply(new, store)`` on layers of the old revision vs ``VolumeLayers.from_store(store, new)``.
  Target <= 0.15x. Check: the updated layers equal the rebuild bit for bit. Details: the time split of the update
  and of the rebuild (stage timers wrapped around the layers' functions for one untimed run) and the top functions of
  a cProfile of that update.
* ``volume_memory_synthetic`` / ``volume_memory_7scenes``: ``VolumeLayers.stats()``: the layers' grid bytes against
  the observed voxels times 24 B (the same per-voxel fields stored for the observed voxels only); the ratio is
  bytes per observed voxel / 24. No target. Details: the per-frame records the layers keep besides the grid (hit
  keys, the missed voxels ``keep_frame_voxels`` keeps, hit-point sums: they grow with the frames, not the grid) and
  the total per observed voxel; what 8^3 blocks allocated only where a voxel was observed would take per observed
  voxel.

The machine's load moves the correction timings (single runs of 2-30 s): the details keep the ratio of every
repetition and of the instrumented run.
"""

from __future__ import annotations

import contextlib
import cProfile
import functools
import gc
import statistics
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d
import open3d.core as o3c
import pyoctomap
from _harness import _minor_page_faults, check, top_functions

import driftmap.volume.defaults as volume_defaults
import driftmap.volume.layers as layers_mod
from driftmap.datasets import embedded_dir, shared_datasets_dir
from driftmap.frame import PoseSource, SensorKind
from driftmap.kernels import volume as kernels
from driftmap.map.view import MapView
from driftmap.pipeline.build import build
from driftmap.preprocess.noise import NoiseModel
from driftmap.sources.redwood import read_depth_png
from driftmap.sources.sevenscenes import SevenScenes, read_pose_txt
from driftmap.store.frame_store import FrameStore
from driftmap.volume import VolumeConfig, VolumeLayers
from driftmap.volume.defaults import DEPTH_MAX_RANGE_LIMITS_M, NOISE_PER_VOXEL
from driftmap.volume.grid import BLOCK_RESOLUTION, BYTES_PER_VOXEL, GridSpec
from driftmap.volume.layers import tsdf_blocks
from driftmap.volume.observation import Observation

SCENE = "7scenes-redkitchen"
FRAMES = (0, 5, 10, 15, 20)
FX = FY = 585.0
CX, CY = 320.0, 240.0
VOXEL_M, TRUNCATION_M, DEPTH_MAX_M = 0.02, 0.08, 4.0
MOVED_FRACTION, SHIFT_M = 0.10, 0.03
TSDF_REPEATS, OCC_REPEATS, SYN_REPEATS, SEVEN_REPEATS = 15, 3, 3, 2


# ------------------------------------------------------------------------------------------------------ timing
def time_passes(impls: dict[str, dict[str, Callable]], items: Sequence, *, repeats: int) -> dict[str, dict]:
    """:func:`_harness.time_per_item` with an untimed ``setup()`` before and ``teardown()`` after every pass (a
    fresh, empty map per pass). ``impls``: name -> ``{"fn": fn(item), "setup": ..., "teardown": ...}``. The
    implementations take turns (the order rotates every repetition); the collector is off while timing."""
    names = list(impls)
    samples: dict[str, list[float]] = {n: [] for n in names}
    faults = dict.fromkeys(names, 0)
    gc_was_enabled = gc.isenabled()
    try:
        for rep in range(repeats):
            shift = rep % len(names)
            for name in names[shift:] + names[:shift]:
                impl = impls[name]
                if impl.get("setup"):
                    impl["setup"]()
                gc.collect()
                gc.disable()
                fn = impl["fn"]
                f0 = _minor_page_faults()
                t0 = time.perf_counter()
                for item in items:
                    fn(item)
                elapsed = time.perf_counter() - t0
                faults[name] += _minor_page_faults() - f0
                if gc_was_enabled:
                    gc.enable()
                if impl.get("teardown"):
                    impl["teardown"]()
                samples[name].append(elapsed / len(items))
    finally:
        if gc_was_enabled:
            gc.enable()
    return {n: {"median_s": statistics.median(s), "min_s": min(s), "max_s": max(s), "repeats": repeats,
                "items": len(items), "page_faults_per_item": faults[n] / (repeats * len(items)), "samples_s": s}
            for n, s in samples.items()}


@contextlib.contextmanager
def stage_timer(patches: Sequence[tuple[Any, str, Callable[..., str]]]) -> Iterator[dict[str, float]]:
    """Wrap functions (``(owner, attribute, label(*args))``) with timers for the ``with`` block; yields the seconds
    per label (nested stages are counted in their own label and in their caller's)."""
    acc: dict[str, float] = defaultdict(float)
    saved = []

    def wrap(fn: Callable, label: Callable[..., str]) -> Callable:
        @functools.wraps(fn)
        def timed(*args: Any, **kwargs: Any) -> Any:
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                acc[label(*args, **kwargs)] += time.perf_counter() - t0
        return timed

    try:
        for owner, attr, label in patches:
            raw = owner.__dict__[attr] if isinstance(owner, type) else getattr(owner, attr)
            saved.append((owner, attr, raw))
            if isinstance(raw, classmethod):
                new = classmethod(wrap(raw.__func__, lambda cls, *a, _l=label, **k: _l(*a, **k)))
            elif isinstance(raw, property):
                new = property(wrap(raw.fget, label))
            else:
                new = wrap(raw, label)
            setattr(owner, attr, new)
        yield acc
    finally:
        for owner, attr, raw in reversed(saved):
            setattr(owner, attr, raw)


def _const(name: str) -> Callable[..., str]:
    return lambda *args, **kwargs: name


# ------------------------------------------------------------------------------------------------- input data
def _folder() -> Path:
    return shared_datasets_dir() / SCENE


def _depth_images() -> list[tuple[np.ndarray, np.ndarray]]:
    """(depth in metres float32, 0 where invalid; T_world_camera) of the benchmark frames."""
    out = []
    for n in FRAMES:
        raw = read_depth_png(_folder() / f"frame-{n:06d}.depth.png", n)
        depth = raw.astype(np.float32) / np.float32(1000.0)
        depth[raw == 65535] = 0.0
        out.append((np.ascontiguousarray(depth), read_pose_txt(_folder() / f"frame-{n:06d}.pose.txt", n)))
    return out


def _layers_max_range_m() -> float:
    """The layers' default max range for a depth camera at 2 cm voxels (as ``volume.defaults.resolve_config``)."""
    noise = NoiseModel.for_sensor(SensorKind.DEPTH_CAMERA).depth_for_sigma_m(NOISE_PER_VOXEL * VOXEL_M)
    return float(np.clip(noise, *DEPTH_MAX_RANGE_LIMITS_M))


# --------------------------------------------------------------------------------------------- 1. TSDF
def bench_tsdf(quick: bool) -> dict:
    images = _depth_images()
    K = o3c.Tensor(np.array([[FX, 0.0, CX], [0.0, FY, CY], [0.0, 0.0, 1.0]]))
    trunc_vox = TRUNCATION_M / VOXEL_M
    obs = [Observation(n, T[:3, 3].copy(), np.zeros((0, 3)), np.zeros(0, bool), T, d, (FX, FY, CX, CY))
           for n, (d, T) in zip(FRAMES, images)]
    o3d_items = [(o3d.t.geometry.Image(o3c.Tensor(d)), o3c.Tensor(np.linalg.inv(T))) for d, T in images]
    blocks = np.concatenate([tsdf_blocks(o, VOXEL_M, TRUNCATION_M, DEPTH_MAX_M) for o in obs])
    grid = GridSpec.covering(blocks.min(axis=0) * BLOCK_RESOLUTION * VOXEL_M,
                             ((blocks.max(axis=0) + 1) * BLOCK_RESOLUTION - 0.5) * VOXEL_M, VOXEL_M)
    origin_index, shape = np.asarray(grid.origin_index, np.int64), np.asarray(grid.shape, np.int64)
    n_blocks = len(np.unique(blocks, axis=0))
    state: dict[str, Any] = {}

    def ours_setup() -> None:  # a fresh grid: np.zeros, pages faulted in as the blocks are first written
        state["sum"], state["count"] = np.zeros(grid.n_voxels, np.int64), np.zeros(grid.n_voxels, np.int32)

    def ours(k: int) -> None:
        o = obs[k]
        b = tsdf_blocks(o, VOXEL_M, TRUNCATION_M, DEPTH_MAX_M)
        kernels.tsdf_projective(o.depth_m, FX, FY, CX, CY, np.linalg.inv(o.T_world_sensor), b, BLOCK_RESOLUTION,
                                origin_index, shape, VOXEL_M, TRUNCATION_M, DEPTH_MAX_M, state["sum"],
                                state["count"], 1)

    def o3d_setup() -> None:
        state["vbg"] = o3d.t.geometry.VoxelBlockGrid(
            attr_names=("tsdf", "weight"), attr_dtypes=(o3c.float32, o3c.float32), attr_channels=((1), (1)),
            voxel_size=VOXEL_M, block_resolution=BLOCK_RESOLUTION, block_count=2 * n_blocks, device=o3c.Device("CPU:0"))

    def o3d_integrate(k: int) -> None:
        image, E = o3d_items[k]
        vbg = state["vbg"]
        b = vbg.compute_unique_block_coordinates(image, K, E, 1.0, DEPTH_MAX_M, trunc_vox)
        vbg.integrate(b, image, K, E, 1.0, DEPTH_MAX_M, trunc_vox)

    items = list(range(len(FRAMES)))
    # correctness (and warm-up): one pass each into empty maps, then every sample compared
    ours_setup(), o3d_setup()
    for k in items:
        ours(k), o3d_integrate(k)
    vbg = state["vbg"]
    coords, idx = vbg.voxel_coordinates_and_flattened_indices()
    w = vbg.attribute("weight").numpy().reshape(-1)[idx.numpy()]
    t = vbg.attribute("tsdf").numpy().reshape(-1)[idx.numpy()]
    seen = w > 0
    lattice = np.rint(coords.numpy()[seen] / VOXEL_M).astype(np.int64) - origin_index
    flats = grid.flat(lattice)
    count = state["count"][flats]
    ours_tsdf = state["sum"][flats] / kernels.TSDF_QUANTUM / np.maximum(count, 1)
    check(np.array_equal(count, w[seen].astype(np.int32)), "TSDF: a sample's count differs from Open3D's weight")
    check(int((state["count"] > 0).sum()) == int(seen.sum()), "TSDF: we updated samples Open3D did not")
    max_diff = float(np.max(np.abs(ours_tsdf - t[seen])))
    check(max_diff < 1e-5, f"TSDF differs from Open3D's by {max_diff}")
    del state["vbg"]

    timings = time_passes({"ours": {"fn": ours, "setup": ours_setup},
                           "open3d_voxel_block_grid": {"fn": o3d_integrate, "setup": o3d_setup}},
                          items, repeats=5 if quick else TSDF_REPEATS)
    state.clear()
    blocks_s = _median_time(lambda: [tsdf_blocks(o, VOXEL_M, TRUNCATION_M, DEPTH_MAX_M) for o in obs], 5) / len(obs)
    return {
        "name": "tsdf_integration",
        "description": f"TSDF of one 640x480 7-Scenes depth frame ({len(FRAMES)} frames, each pass into an empty map), "
                       f"2 cm voxels, 8 cm truncation, 4 m depth max: Open3D's blocks + kernels.tsdf_projective into a "
                       f"dense int64/int32 grid vs Open3D VoxelBlockGrid blocks + integrate, time per frame",
        "unit": "frame",
        "ours": timings["ours"],
        "anchors": {"open3d_voxel_block_grid": timings["open3d_voxel_block_grid"]},
        "target_ratio": 1.0,
        "check": f"{int(seen.sum()):,} samples: counts equal Open3D's weights, TSDF within {max_diff:.1e}",
        "details": {"grid": grid.describe(), "blocks_union": n_blocks, "samples_observed": int(seen.sum()),
                    "block_selection_s_per_frame (in both)": blocks_s},
    }


def _median_time(fn: Callable[[], object], repeats: int) -> float:
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return statistics.median(out)


# ---------------------------------------------------------------------------------------- 2. occupancy
def bench_occupancy(quick: bool, stride: int) -> dict:
    frames = list(SevenScenes(_folder(), frames=f"{FRAMES[0]}:{FRAMES[-1] + 1}:{FRAMES[1] - FRAMES[0]}",
                              poses_from_ground_truth=True, pixel_stride=stride))
    check([f.frame_id for f in frames] == list(FRAMES), f"frames {[f.frame_id for f in frames]}")
    max_range = _layers_max_range_m()
    cfg = VolumeConfig()
    rays = []
    for f in frames:
        T = f.pose.T_world_sensor
        pts = np.ascontiguousarray(f.points_sensor.astype(np.float64) @ T[:3, :3].T + T[:3, 3])
        rays.append((pts, T[:3, 3].copy()))
    n_rays = [len(p) for p, _ in rays]
    lo = np.min([np.minimum(p.min(axis=0), o) for p, o in rays], axis=0)
    hi = np.max([np.maximum(p.max(axis=0), o) for p, o in rays], axis=0)
    grid = GridSpec.covering(lo, hi, VOXEL_M, padding_m=2 * VOXEL_M)
    origin_index, shape = np.asarray(grid.origin_index, np.int64), np.asarray(grid.shape, np.int64)
    state: dict[str, Any] = {"token": 0}

    def ours_setup() -> None:
        state["hits"], state["misses"], state["mark"] = (np.zeros(grid.n_voxels, np.int32) for _ in range(3))

    def ours(k: int) -> None:
        pts, origin = rays[k]
        d = pts - origin
        r = np.sqrt(np.einsum("ij,ij->i", d, d))
        far = r > max_range
        ends = pts
        if far.any():
            ends = pts.copy()
            ends[far] = origin + d[far] * (max_range / r[far])[:, None]
        state["token"] += 1
        kernels.occupancy_update(origin / VOXEL_M, ends / VOXEL_M, ~far, origin_index, shape, state["hits"],
                                 state["misses"], state["mark"], state["token"], 1, np.empty(len(ends), np.int64),
                                 np.empty(0, np.int64))

    def tree_setup() -> None:
        state.pop("tree", None)
        state["tree"] = pyoctomap.OcTree(VOXEL_M)

    def octomap(k: int) -> None:
        pts, origin = rays[k]
        state["tree"].insertPointCloud(pts, origin, max_range=max_range)

    def octomap_lazy(k: int) -> None:
        pts, origin = rays[k]
        tree = state["tree"]
        tree.insertPointCloud(pts, origin, max_range=max_range, lazy_eval=True)
        tree.updateInnerOccupancy()

    items = list(range(len(frames)))
    # correctness (and warm-up): one pass each into empty maps; occupied / free compared on sampled voxels
    ours_setup(), tree_setup()
    for k in items:
        ours(k), octomap(k)
    h, m = state["hits"], state["misses"]
    seen = (h + m) > 0
    L = np.clip(h * cfg.log_odds_hit + m * cfg.log_odds_miss, cfg.log_odds_min, cfg.log_odds_max)
    occupied = seen & (L >= cfg.log_odds_threshold)
    rng = np.random.default_rng(1)
    observed = np.flatnonzero(seen)
    sample = np.concatenate([np.flatnonzero(occupied), rng.choice(observed, min(50_000, len(observed)), replace=False)])
    tree = state["tree"]
    both = agree = 0
    for flat, centre in zip(sample, grid.centers_m(sample)):
        node = tree.search(centre)
        if node is None:
            continue
        both += 1
        agree += tree.isNodeOccupied(node) == bool(occupied[flat])
    check(both > 0.9 * len(sample), f"OctoMap knows only {both} of {len(sample)} voxels we observed")
    check(agree / both >= 0.99, f"occupied / free agree on only {agree / both:.4f} of the voxels both observe")
    octomap_bytes_per_leaf = tree.memoryUsage() / max(tree.getNumLeafNodes(), 1)
    n_occupied, n_observed = int(occupied.sum()), int(seen.sum())
    state.pop("tree")

    timings = time_passes({"ours": {"fn": ours, "setup": ours_setup},
                           "octomap_insertPointCloud": {"fn": octomap, "setup": tree_setup},
                           "octomap_lazy_eval+updateInner": {"fn": octomap_lazy, "setup": tree_setup}},
                          items, repeats=1 if quick else OCC_REPEATS)
    # pyoctomap's Python-side cost of handing the points over (a Python loop building OctoMap's Pointcloud):
    # the same number of points all at the origin (no ray to trace, one voxel)
    at_origin = [(np.tile(o, (len(p), 1)), o) for p, o in rays]
    tree_setup()
    wrapper_s = statistics.median(
        _median_time(lambda p=p, o=o: state["tree"].insertPointCloud(p, o, max_range=max_range), 3)
        for p, o in at_origin)
    tree_setup()
    t0 = time.perf_counter()
    for pts, origin in rays:
        state["tree"].insertPointCloud(pts, origin, max_range=max_range, discretize=True)
    discretize_s = (time.perf_counter() - t0) / len(rays)
    state.clear()
    ours_s = timings["ours"]["median_s"]
    fastest = min(v["median_s"] for k, v in timings.items() if k != "ours")
    name = "occupancy_full_res" if stride == 1 else f"occupancy_stride{stride}"
    resolution = "full resolution" if stride == 1 else f"{stride}-pixel stride"
    return {
        "name": name,
        "description": f"occupancy of one 7-Scenes frame's rays ({resolution}, mean {np.mean(n_rays):,.0f} rays, "
                       f"cut at {max_range:.2f} m, {len(FRAMES)} frames per pass into an empty map), 2 cm: "
                       f"kernels.occupancy_update (with the cut) vs pyoctomap OcTree.insertPointCloud, time per frame",
        "unit": "frame",
        "ours": timings["ours"],
        "anchors": {k: v for k, v in timings.items() if k != "ours"},
        "target_ratio": 0.5,
        "check": f"occupied / free agree with OctoMap on {agree / both:.4f} of {both:,} sampled voxels both observe",
        "details": {"grid": grid.describe(), "max_range_m": max_range, "mean_rays": float(np.mean(n_rays)),
                    "observed_voxels": n_observed, "occupied_voxels": n_occupied,
                    "pyoctomap_wrapper_s_per_frame": wrapper_s,
                    "ratio_vs_fastest_anchor_minus_wrapper": ours_s / max(fastest - wrapper_s, 1e-12),
                    "octomap_discretize_s_per_frame (rays to end-voxel centres; not the same rays)": discretize_s,
                    "ratio_vs_octomap_discretize": ours_s / discretize_s,
                    "octomap_bytes_per_leaf": octomap_bytes_per_leaf},
    }


# ------------------------------------------------------------------------------------ 3. correction cost
APPLY_STAGES = [
    (VolumeLayers, "_observe", _const("observe (old + new rays)")),
    (MapView, "apply", _const("map view apply")),
    (VolumeLayers, "_grow_to", _const("grow grid")),
    (VolumeLayers, "states_flat", _const("state diff")),
    (layers_mod, "_region", _const("state diff")),
    (VolumeLayers, "_integrate", lambda self, obs, sign: "de-integrate" if sign < 0 else "integrate"),
    (Observation, "bounds_m", _const("ray bounds (Observation.bounds_m)")),
]
REBUILD_STAGES = [
    (MapView, "from_store", _const("map view")),
    (VolumeLayers, "_observe", _const("observe")),
    (VolumeLayers, "_integrate", _const("integrate")),
    (Observation, "bounds_m", _const("ray bounds (Observation.bounds_m)")),
    (volume_defaults, "resolve_config", _const("resolve config")),
    (layers_mod.VoxelArrays, "zeros", _const("allocate grid")),
]
KERNEL_STAGES = [  # inside (de-)integrate
    (kernels, "occupancy_update", _const("  occupancy kernel")),
    (layers_mod, "tsdf_blocks", _const("  tsdf blocks (Open3D)")),
    (kernels, "tsdf_projective", _const("  tsdf kernel")),
    (layers_mod, "_hit_sums", _const("  hit sums")),
]


def _split(total_s: float, stages: dict[str, float]) -> dict[str, Any]:
    """Seconds per stage (they add up to ``total``), and within (de-)integration per kernel."""
    top = {k: v for k, v in stages.items() if not k.startswith("  ")}
    out: dict[str, Any] = {"total": round(total_s, 4)}
    out |= {k: round(v, 4) for k, v in sorted(top.items(), key=lambda kv: -kv[1])}
    out["other"] = round(total_s - sum(top.values()), 4)
    out["within (de-)integrate"] = {k.strip(): round(v, 4) for k, v in sorted(stages.items(), key=lambda kv: -kv[1])
                                    if k.startswith("  ")}
    return out


def bench_correction(quick: bool, label: str, make_store: Callable[[Path], None], repeats: int) -> list[dict]:
    with tempfile.TemporaryDirectory(prefix="driftmap-bench-volume-") as tmp:
        path = Path(tmp) / label
        t0 = time.perf_counter()
        make_store(path)
        build_s = time.perf_counter() - t0
        with FrameStore.open(path, "a") as store:
            old = store.head
            ids = store.frame_ids
            poses = store.poses(old).copy()
            n_moved = max(1, round(MOVED_FRACTION * len(ids)))
            poses[len(ids) - n_moved:, 0, 3] += SHIFT_M
            new = store.add_revision({int(f): poses[k] for k, f in enumerate(ids)},
                                     source=PoseSource.EXTERNAL_FILE).revision_id
            t0 = time.perf_counter()
            layers = VolumeLayers.from_store(store, old)
            first_build_s = time.perf_counter() - t0
            stats = layers.stats()
            bricks = _bricks_in_use(layers)

            # one instrumented update and rebuild: the time split, a profile, and the check
            profile = cProfile.Profile()
            with stage_timer(APPLY_STAGES + KERNEL_STAGES) as apply_stages:
                t0 = time.perf_counter()
                profile.enable()
                change = layers.apply(new, store)
                profile.disable()
                apply_s = time.perf_counter() - t0
            with stage_timer(REBUILD_STAGES + KERNEL_STAGES) as rebuild_stages:
                t0 = time.perf_counter()
                rebuilt = VolumeLayers.from_store(store, new)
                rebuild_s = time.perf_counter() - t0
            check(not change.rebuilt, f"{label}: the update fell back to a rebuild")
            check(layers.equals(rebuilt), f"{label}: the updated layers differ from the rebuild")
            n_changed = len(change.frame_ids)
            del rebuilt
            layers.apply(old, store)

            def ours(rev: int) -> None:
                layers.apply(rev, store)

            def rebuild(rev: int) -> None:
                VolumeLayers.from_store(store, rev)

            timings = time_passes({"ours": {"fn": ours, "teardown": lambda: layers.apply(old, store)},
                                   "rebuild_from_store": {"fn": rebuild}}, [new], repeats=repeats)
        split = {"update": _split(apply_s, apply_stages), "rebuild": _split(rebuild_s, rebuild_stages)}
        print(f"  correction_{label}: update {apply_s:.2f} s, rebuild {rebuild_s:.2f} s (instrumented run)")
        for what, s in split.items():
            inner = s["within (de-)integrate"]
            print(f"    {what} (s): " + ", ".join(f"{k} {v:.3f}" for k, v in s.items() if not isinstance(v, dict))
                  + "; within (de-)integrate: " + ", ".join(f"{k} {v:.3f}" for k, v in inner.items()))
    memory = {
        "name": f"volume_memory_{label}",
        "description": f"VolumeLayers.stats() of the {label} store ({stats.n_voxels:,} grid voxels, {stats.observed:,} "
                       f"observed, {stats.occupied:,} occupied): the layers' bytes vs observed voxels x "
                       f"{BYTES_PER_VOXEL} B; ratio = bytes per observed voxel / {BYTES_PER_VOXEL}; no target",
        "unit": "store",
        "ours": {"median_bytes": stats.nbytes},
        "anchors": {f"observed_voxels_x_{BYTES_PER_VOXEL}B": {"median_bytes": stats.observed * BYTES_PER_VOXEL}},
        "target_ratio": float("inf"),
        "check": f"{stats.bytes_per_observed_voxel:.1f} bytes per observed voxel (grid), "
                 f"{stats.total_nbytes / max(stats.observed, 1):.1f} with the per-frame records",
        "details": {"bytes_per_observed_voxel": stats.bytes_per_observed_voxel,
                    "per_frame_records_bytes (hit keys, kept miss voxels, hit sums; not in the ratio)":
                        stats.cache_nbytes,
                    "per_frame_records_bytes_per_frame": stats.cache_nbytes / max(len(ids), 1),
                    "total_bytes_per_observed_voxel (grid + per-frame records)":
                        stats.total_nbytes / max(stats.observed, 1),
                    f"bricks_{BLOCK_RESOLUTION}^3_holding_an_observed_or_tsdf_voxel": bricks,
                    f"bytes_per_observed_voxel_if_only_those_bricks_were_allocated ({BYTES_PER_VOXEL} B/voxel)":
                        bricks * BLOCK_RESOLUTION**3 * BYTES_PER_VOXEL / max(stats.observed, 1),
                    "occupied": stats.occupied,
                    "free": stats.free, "unknown": stats.unknown, "n_voxels": stats.n_voxels, "nbytes": stats.nbytes},
    }
    correction = {
        "name": f"correction_{label}",
        "description": f"{label} store ({len(ids)} frames): a revision moving the last {n_moved} frames by 3 cm; "
                       f"VolumeLayers.apply on layers of the old revision vs VolumeLayers.from_store of the new one",
        "unit": "correction",
        "ours": timings["ours"],
        "anchors": {"rebuild_from_store": timings["rebuild_from_store"]},
        "target_ratio": 0.15,
        "check": f"updated layers equal the rebuild bit for bit ({n_changed} frames re-integrated, "
                 f"{change.n_state_changed:,} voxels changed state)",
        "details": {"frames": len(ids), "frames_moved": n_moved, "frames_reintegrated": n_changed,
                    "integration_work_ratio (2 x re-integrated / frames)": 2 * n_changed / len(ids),
                    "ratio_per_repetition": [a / b for a, b in zip(timings["ours"]["samples_s"],
                                                                     timings["rebuild_from_store"]["samples_s"])],
                    "ratio_instrumented_run": apply_s / rebuild_s,
                    "store_build_s": build_s, "first_layers_build_s": first_build_s,
                    "time_split_s": split, "update_profile_top_tottime": top_functions(profile)},
    }
    return [correction, memory]


def _bricks_in_use(layers: VolumeLayers) -> int:
    """How many 8^3 blocks of the grid hold a voxel observed by the occupancy or the TSDF (what a sparse, block-wise
    allocation as Open3D's VoxelBlockGrid would allocate)."""
    a, B = layers.arrays, BLOCK_RESOLUTION
    used = ((a.hits + a.misses) > 0) | (a.tsdf_count > 0)
    nx, ny, nz = layers.grid.shape
    return int(used.reshape(nx // B, B, ny // B, B, nz // B, B).any(axis=(1, 3, 5)).sum())


def _synthetic_store(path: Path) -> None:
    log = embedded_dir() / "synthetic-loop"
    build(log, path, poses_file=log / "groundtruth.txt", loop_closure=False)


def _sevenscenes_store(path: Path) -> None:
    build(_folder(), path, poses_from_source=True, loop_closure=False, frames="0:1000:5")


def run(quick: bool = False) -> list[dict]:
    results = [bench_tsdf(quick), bench_occupancy(quick, 1), bench_occupancy(quick, 2)]
    corrections = bench_correction(quick, "synthetic", _synthetic_store, 1 if quick else SYN_REPEATS)
    corrections += bench_correction(quick, "7scenes", _sevenscenes_store, 1 if quick else SEVEN_REPEATS)
    return results + [c for c in corrections if c["name"].startswith("correction")] + \
        [c for c in corrections if c["name"].startswith("volume_memory")]
