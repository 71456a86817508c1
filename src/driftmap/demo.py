"""The demo: the whole driftmap story on the embedded synthetic log.

1. **build** a store from the log with its drifting odometry (revision 0, every frame in its sensor frame);
2. **diagnose revision 0**: the double walls at the loop, how far apart, which frames disagree;
3. **close the loop**: verified loop closures, a GTSAM pose graph, revision 1, and the stored frames
   re-transformed (not rebuilt);
4. **diagnose revision 1** (and the ground-truth placement as a reference): the double walls are gone,
   the smearing score drops;
5. **export**: PLY maps, TUM trajectories, an MCAP that opens in Foxglove;
6. **volume**: the volumetric layers (free / occupied / unknown space, :mod:`driftmap.volume`) of revision 0,
   updated to the loop closure's revision with :meth:`~driftmap.volume.VolumeLayers.apply` (not rebuilt), drawn
   from above before and after, and the TSDF mesh of the corrected revision;
7. **report**: PNG figures and a Markdown + HTML page in the results folder.

The CLI (``driftmap demo``) shows progress and prints the summary; this module only computes and writes.
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from driftmap.config import DriftmapConfig
from driftmap.datasets import embedded_dir
from driftmap.demo_report import (  # re-exported: the demo's results and its reports
    DemoResult,
    DiagnosisSummary,
    VolumeSummary,
    region_lines,  # noqa: F401
    summary_rows,  # noqa: F401
    volume_rows,  # noqa: F401
    write_html_report,
    write_markdown_report,
)
from driftmap.diagnostics.double_wall import DiagnosticCloud
from driftmap.diagnostics.figures import (
    StateTopView,
    plot_state_top_view,
    sensor_band_m,
    sensor_up,
    state_top_view,
    union_extent,
)
from driftmap.diagnostics.report import DiagnoseConfig, Diagnosis, diagnose_cloud, diagnose_store, write_report
from driftmap.diagnostics.trajectory_metrics import trajectory_errors
from driftmap.diagnostics.walls import WallSpread, wall_spread
from driftmap.errors import ConfigError, EmptyExportError
from driftmap.export.foxglove import export_foxglove_mcap
from driftmap.map.fusion import FusedCloud
from driftmap.map.view import MapView
from driftmap.pipeline.build import BuildConfig, BuildResult, build
from driftmap.registration.loops import LoopClosureConfig
from driftmap.report import top_view
from driftmap.sources.synthetic import ROOM_MAX_M, ROOM_MIN_M, SyntheticLog, generate_synthetic_log
from driftmap.store.frame_store import FrameStore
from driftmap.store.guards import is_store_folder
from driftmap.volume import VolumeConfig, VolumeLayers, VolumeStats
from driftmap.volume.export import write_mesh
from driftmap.volume.grid import GridSpec

logger = logging.getLogger(__name__)

EMBEDDED_LOG_NAME = "synthetic-loop"

#: The +y wall is seen at the start of the loop and again at its end: where drift shows as a double wall.
LOOP_WALL = {"normal": (0.0, 1.0, 0.0), "offset_m": ROOM_MAX_M[1], "tangent": (1.0, 0.0, 0.0), "z_range_m": (0.9, 2.4),
             "tangent_range_m": (ROOM_MIN_M[0] + 0.4, ROOM_MAX_M[0] - 0.4)}

#: The synthetic log is short (60 frames at 5 Hz): loops may be 20 frames apart, keyframes every 20 cm.
DEMO_MAP_VOXEL_M = 0.01
"""Voxel size of the demo's map exports unless ``map.export_voxel_size_m`` is set (m)."""
DEMO_VOLUME_VOXEL_M = 0.04
"""Voxel of the demo's volumetric layers unless ``volume.voxel_size_m`` is set (m): twice a depth camera's default
2 cm, to keep the demo fast (the cost is in carving the rays, about 60 ms a frame here: building revision 0 takes
~10 s and the update to the loop closure, which takes out and puts back every moved frame, ~15 s); the loop wall's
double wall (~5 cm apart) still shows as a thicker wall from above."""
LOOP_WALL_STRIP_M = 0.25
"""The loop wall's thickness from above is measured within this distance of its true plane (m)."""
DEMO_BUILD_CONFIG = BuildConfig(loop_closure=LoopClosureConfig(min_gap_frames=20, keyframe_distance_m=0.2, keyframe_angle_deg=15))

#: (stage, done, total) -- the same shape as the build's progress callback
DemoProgress = Callable[[str, int, int | None], None]


def embedded_log_path(generate_if_missing: bool = True) -> Path:
    """The repository's synthetic log; regenerated (deterministically) if it is not there."""
    path = embedded_dir() / EMBEDDED_LOG_NAME
    if not (path / "synthetic.json").exists():
        if not generate_if_missing:
            raise FileNotFoundError(path)
        logger.info("embedded log missing at %s; generating it", path)
        generate_synthetic_log(path)
    return path


def _loop_wall_spread(points_world: np.ndarray) -> WallSpread:
    return wall_spread(points_world, **LOOP_WALL)


class _Stages:
    """Times the demo's stages and forwards progress."""

    def __init__(self, progress: DemoProgress | None):
        self.tick: DemoProgress = progress or (lambda stage, done, total: None)
        self.seconds: dict[str, float] = {}

    def run(self, name: str, fn: Callable[[], Any]) -> Any:
        self.tick(name, 0, 1)
        value = self.timed(name, fn)
        self.tick(name, 1, 1)
        return value

    def timed(self, name: str, fn: Callable[[], Any]) -> Any:
        """Time ``fn`` without reporting it as a stage (a build reports its own stages)."""
        t = time.perf_counter()
        value = fn()
        self.seconds[name] = round(time.perf_counter() - t, 3)
        return value


@dataclass
class _DemoRun:
    """What the steps of one demo run share: where it writes, the log, the stage timer, and the files written so
    far (the very dict that becomes :attr:`DemoResult.files`: the reports add themselves to it)."""

    out: Path
    log: SyntheticLog
    store_dir: Path
    map_voxel_m: float
    mesh_weight_threshold: float
    build_kwargs: dict[str, Any]
    stages: _Stages
    files: dict[str, str]

    def run_build(self, stage: str, **kwargs: Any) -> BuildResult:
        """Run the build on the log into the demo's store, timed as ``stage``."""
        return self.stages.timed(stage, lambda: build(self.log.path, self.store_dir, **kwargs, **self.build_kwargs))


@dataclass
class _Revision0:
    """The drifting map (revision 0), diagnosed, and what the later steps reuse (samples, ground truth)."""

    built: BuildResult
    ground_truth: tuple[np.ndarray, np.ndarray]  # (frame ids, T_world_sensor) of the stored frames
    diagnose_config: DiagnoseConfig
    cloud: DiagnosticCloud
    diagnosis: Diagnosis
    points: np.ndarray
    point_frames: np.ndarray
    spread: WallSpread
    ate_m: float | None
    flagged: list[int]

    @property
    def gt_poses(self) -> np.ndarray:
        return self.ground_truth[1]


@dataclass
class _Corrected:
    """The loop closure's revision (if any), diagnosed, and the ground-truth placement as the reference."""

    closed: BuildResult
    diagnosis: Diagnosis | None
    points: np.ndarray | None
    frames_moved: int
    ate_m: float | None
    diagnosis_gt: Diagnosis
    gt_points: np.ndarray
    spread: WallSpread | None
    gt_spread: WallSpread


def run_demo(
    out_dir: str | Path,
    *,
    log_path: str | Path | None = None,
    max_frames: int | None = None,
    config: DriftmapConfig | None = None,
    progress: DemoProgress | None = None,
) -> DemoResult:
    """Run the demo into ``out_dir``; ``progress(stage, done, total)`` reports each stage."""
    t0 = time.perf_counter()
    config = config or DriftmapConfig()
    run = _prepare(out_dir, log_path, max_frames, config, progress)
    built = _build(run)
    before = _diagnose_before(run, built)
    closed = _close_the_loop(run)
    after = _diagnose_after(run, before, closed)
    volume = _volume(run, demo_volume_config(config), closed.loop_revision)
    # 7. figures, diagnosis JSON and the report
    run.files.update(run.stages.run("figures", lambda: _figures(run.out, before, after)))
    diag_files = _export_diagnoses_and_config(run, config, before.diagnosis, after.diagnosis)
    result = _demo_result(run, before, after, diag_files, seconds=time.perf_counter() - t0)
    result = replace(result, volume=volume)
    return _write_report(run, result, t0)


def _prepare(out_dir: str | Path, log_path: str | Path | None, max_frames: int | None, config: DriftmapConfig,
             progress: DemoProgress | None) -> _DemoRun:
    """The results folder (its store emptied), the log, and the build settings both builds share."""
    stages = _Stages(progress)
    out = Path(out_dir)
    _check_results_folder(out)
    log = SyntheticLog(Path(log_path) if log_path else embedded_log_path())  # a bad --log leaves no folder behind
    out.mkdir(parents=True, exist_ok=True)
    # the map exports: map.export_voxel_size_m when set, else the demo's own 1 cm
    map_voxel_m = config.map.export_voxel_size_m if config.map.export_voxel_size_m is not None else DEMO_MAP_VOXEL_M
    n = len(log) if max_frames is None else min(max_frames, len(log))
    _remove_earlier_results(out)
    store_dir = out / "store"
    if store_dir.exists():  # an earlier demo's store (checked above): the demo rebuilds it
        shutil.rmtree(store_dir)
    build_kwargs = dict(poses_from_source=True, frames=f"0:{n}", config=DEMO_BUILD_CONFIG, progress=stages.tick,
                        depth=config.depth)
    return _DemoRun(out, log, store_dir, map_voxel_m, config.map.mesh_weight_threshold, build_kwargs, stages,
                    {"store": str(store_dir)})


def _check_results_folder(out: Path) -> None:
    """The demo writes into a new or empty folder, or over an earlier demo's results (its ``summary.json`` and, if
    there, its ``store/`` frame store); anything else -- a frame store, a file, a folder of other files -- is refused
    with :class:`ConfigError` before anything is touched (the demo replaces its own store, never someone else's)."""
    if not out.exists():
        return
    if not out.is_dir():
        raise ConfigError(f"{out}: is a file, not a results folder (--out); give a new or empty folder")
    if is_store_folder(out):
        raise ConfigError(f"{out}: is a frame store, not a results folder (--out): the demo writes its own store into "
                          f"OUT/store; give a new or empty folder")
    if not any(out.iterdir()):
        return
    try:
        earlier = "store" in json.loads((out / "summary.json").read_text()).get("files", {})
    except (OSError, ValueError, RecursionError, AttributeError):
        earlier = False
    if not earlier:
        raise ConfigError(f"{out}: is not empty and holds no earlier demo result (summary.json); give a new or empty "
                          f"folder (--out)")
    store_dir = out / "store"
    if store_dir.exists() and not is_store_folder(store_dir):
        raise ConfigError(f"{store_dir}: is not a frame store the demo wrote; move it away or give a new folder (--out)")


def _remove_earlier_results(out: Path) -> None:
    """The files an earlier demo's ``summary.json`` lists in ``out`` (its store aside): a run that writes fewer of them
    (no loop-closure revision) leaves none of the other log's maps or figures beside its own (trial 24 W5). Only a
    listed file directly in ``out`` or ``out/figures`` is removed, matched by name."""
    try:
        files = json.loads((out / "summary.json").read_text()).get("files", {})
    except (OSError, ValueError, RecursionError, AttributeError):
        return
    if not isinstance(files, dict):
        return
    for key, value in files.items():
        if key == "store" or not isinstance(value, str):
            continue
        listed = Path(value)
        target = out / "figures" / listed.name if listed.parent.name == "figures" else out / listed.name
        if target.is_symlink() or target.is_file():  # a link is removed, never what it points to
            logger.info("demo: removing the earlier run's %s", target)
            target.unlink()


def _build(run: _DemoRun) -> BuildResult:
    """1. The drifting odometry of the log becomes revision 0 of a new store."""
    return run.run_build("build (revision 0)", loop_closure=False)


def _diagnose_before(run: _DemoRun, built: BuildResult) -> _Revision0:
    """2. Sample the stored frames (the loop closure's revision is diagnosed on the same samples) and diagnose
    revision 0: the double walls of the drifting map; export its map and trajectory."""
    gt_all = run.log.ground_truth().poses
    with FrameStore.open(run.store_dir) as store:
        gt_poses = gt_all[store.frame_ids]  # the log's frame ids are its row numbers
        gt = (store.frame_ids.copy(), gt_poses)
        dcfg = DiagnoseConfig.for_store(store)
        cloud = run.stages.run("sample frames for diagnosis", lambda: DiagnosticCloud.from_store(store, dcfg.sampling))
        diag0 = run.stages.run("diagnose revision 0",
                               lambda: diagnose_store(store, 0, config=dcfg, cloud=cloud, ground_truth=gt))
        view = MapView.from_store(store, 0)
        odom_points = view.points_world.copy()
        point_frames = view.point_frame_ids()
        odom_spread = _loop_wall_spread(odom_points)
        run.files["map_odometry_ply"] = str(view.export(run.out / "map_odometry.ply", voxel_size_m=run.map_voxel_m))
        run.files["trajectory_odometry_tum"] = str(store.export_trajectory(run.out / "trajectory_odometry.tum", revision=0))
        ate_odometry = trajectory_errors(store.poses(0), gt_poses).ate_rmse_m if len(store) >= 3 else None
        flagged = [int(f) for f in store.frame_ids if (store.frame_info(int(f)).get("quality") or {}).get("flags")]
        del view  # its sensor pages belong to this (read-only) opening of the store
    return _Revision0(built, gt, dcfg, cloud, diag0, odom_points, point_frames, odom_spread, ate_odometry, flagged)


def _close_the_loop(run: _DemoRun) -> BuildResult:
    """3. Loop closure: the pose graph's revision re-transforms the stored frames (the build resumes the store)."""
    return run.run_build("loop closure + pose graph + re-transform", resume=True)


def _diagnose_after(run: _DemoRun, before: _Revision0, closed: BuildResult) -> _Corrected:
    """4. Move the map to the loop closure's revision and diagnose it with revision 0's samples; diagnose the
    ground-truth placement as the reference. Exports the corrected map, trajectory and MCAP, and the
    ground-truth map."""
    rev = closed.loop_revision
    with FrameStore.open(run.store_dir) as store:
        view = MapView.from_store(store, 0)
        diag1, corrected_points, frames_moved = None, None, 0
        if rev is not None:
            diag1, corrected_points, frames_moved = _apply_and_diagnose(run, store, view, rev, before)
        run.files["trajectory_corrected_tum"] = str(store.export_trajectory(run.out / "trajectory_corrected.tum"))
        ate_corrected = (trajectory_errors(store.poses(), before.gt_poses).ate_rmse_m
                         if rev is not None and len(store) >= 3 else None)
        diag_gt, gt_points = _ground_truth_reference(run, store, view, before)
        if rev is not None:
            run.files.update(_export_mcap(store, run.out, rev, diag1))
    return _Corrected(closed, diag1, corrected_points, frames_moved, ate_corrected, diag_gt, gt_points,
                      None if corrected_points is None else _loop_wall_spread(corrected_points),
                      _loop_wall_spread(gt_points))


def _apply_and_diagnose(run: _DemoRun, store: FrameStore, view: MapView, rev: int,
                        before: _Revision0) -> tuple[Diagnosis, np.ndarray, int]:
    """Move ``view`` to revision ``rev``, diagnose it on revision 0's samples and export its map:
    ``(diagnosis, points, frames moved)``."""
    changes = run.stages.run("re-transform the stored frames", lambda: view.apply(rev))
    frames_moved = len(changes.changes)
    corrected_points = view.points_world.copy()
    diag1 = run.stages.run(f"diagnose revision {rev}", lambda: diagnose_store(
        store, rev, config=before.diagnose_config, cloud=before.cloud, ground_truth=before.ground_truth))
    run.files["map_corrected_ply"] = str(view.export(run.out / "map_corrected.ply", voxel_size_m=run.map_voxel_m))
    return diag1, corrected_points, frames_moved


def _ground_truth_reference(run: _DemoRun, store: FrameStore, view: MapView,
                            before: _Revision0) -> tuple[Diagnosis, np.ndarray]:
    """The samples diagnosed at their ground-truth poses, and the map placed there and exported:
    ``(diagnosis, points)``."""
    gt_poses = before.gt_poses
    rows_in_cloud = np.searchsorted(store.frame_ids, before.cloud.frame_ids)
    diag_gt = run.stages.run("diagnose the ground-truth placement (reference)", lambda: diagnose_cloud(
        before.cloud, gt_poses[rows_in_cloud], revision=-1, config=before.diagnose_config))
    # the ground-truth map, for the wall spread and the top view (a scratch view, not a revision)
    view.apply(-1, poses=gt_poses[np.searchsorted(store.frame_ids, view.frame_ids)])
    gt_points = view.points_world.copy()
    run.files["map_ground_truth_ply"] = str(view.export(run.out / "map_ground_truth.ply", voxel_size_m=run.map_voxel_m))
    return diag_gt, gt_points


def demo_volume_config(config: DriftmapConfig) -> VolumeConfig:
    """The ``[volume]`` settings with the demo's voxel (:data:`DEMO_VOLUME_VOXEL_M`) unless one is set."""
    volume = config.volume
    if volume.voxel_size_m is None:
        volume = volume.model_copy(update={"voxel_size_m": DEMO_VOLUME_VOXEL_M})
    return volume


@dataclass(frozen=True)
class _VolumeState:
    """One revision of the layers as the top view needs it (copied: the update changes the layers in place)."""

    revision: int
    states: np.ndarray
    grid: GridSpec
    stats: VolumeStats
    sensor_origins_m: np.ndarray

    @classmethod
    def of(cls, layers: VolumeLayers, store: FrameStore) -> _VolumeState:
        return cls(layers.revision, layers.state_grid(), layers.grid, layers.stats(),
                   store.poses(layers.revision)[:, :3, 3].copy())


def _volume(run: _DemoRun, config: VolumeConfig, rev: int | None) -> VolumeSummary:
    """6. The volumetric layers of revision 0, updated to the loop closure's revision ``rev`` with
    :meth:`VolumeLayers.apply` (not rebuilt); their top views before and after, and the TSDF mesh of the last
    revision."""
    with FrameStore.open(run.store_dir) as store:
        layers = run.stages.run("volume: build revision 0", lambda: VolumeLayers.from_store(store, 0, config))
        build_s = run.stages.seconds["volume: build revision 0"]
        states = [_VolumeState.of(layers, store)]
        change = None
        if rev is not None:
            change = run.stages.run(f"volume: update to revision {rev}", lambda: layers.apply(rev, store))
            states.append(_VolumeState.of(layers, store))
        up = sensor_up(store.poses(0), layers.sensor_kind)
        n_triangles = run.stages.run("volume: TSDF mesh", lambda: _write_volume_mesh(run, layers))
    views, extent = run.stages.run("volume: top views", lambda: _volume_top_views(run, states, up))
    b, a = states[0], states[-1]
    summary = VolumeSummary(
        voxel_size_m=b.grid.voxel_size_m, revision_before=b.revision, occupied_before=b.stats.occupied,
        free_before=b.stats.free, unknown_before=b.stats.unknown, n_voxels=a.stats.n_voxels,
        unknown_fraction=a.stats.unknown / a.stats.n_voxels, build_s=build_s,
        top_view_band_m=(round(views[0].band_m[0], 6), round(views[0].band_m[1], 6)),
        top_view_extent_m=extent, loop_wall_thickness_before_m=loop_wall_thickness_m(views[0]),
        mesh_triangles=n_triangles)
    if change is None:
        return summary
    return replace(summary, revision_after=a.revision, occupied_after=a.stats.occupied, free_after=a.stats.free,
                   unknown_after=a.stats.unknown, update_s=round(change.seconds, 3), update_rebuilt=change.rebuilt,
                   frames_reintegrated=len(change.frame_ids), state_changed=change.n_state_changed,
                   loop_wall_thickness_after_m=loop_wall_thickness_m(views[1]))


def _write_volume_mesh(run: _DemoRun, layers: VolumeLayers) -> int | None:
    """The TSDF mesh of the layers' revision as PLY; None (logged) when there is no surface to mesh."""
    try:
        mesh = write_mesh(layers, run.out / f"volume_mesh_rev{layers.revision}.ply",
                          weight_threshold=run.mesh_weight_threshold)
    except EmptyExportError as exc:
        logger.warning("demo: no TSDF mesh: %s", exc)
        return None
    run.files["volume_mesh_ply"] = str(mesh.path)
    return mesh.n_triangles


def _volume_top_views(run: _DemoRun, states: list[_VolumeState],
                      up: np.ndarray) -> tuple[list[StateTopView], tuple[float, float, float, float]]:
    """The top views of every revision in ``states`` over one extent and height band (pixel-aligned PNGs):
    ``(views, extent)``."""
    band = sensor_band_m(states[0].sensor_origins_m, up)
    extent = union_extent(*(state_top_view(s.states, s.grid, band, up).extent_m for s in states))
    labels = ["revision 0 (drifting odometry)", "revision {rev} (loop closure, layers updated, not rebuilt)"]
    views = []
    for key, label, s in zip(("before", "after"), labels, states):
        title = (f"{label.format(rev=s.revision)}: free / occupied / unknown from above, z {band[0]:.1f} .. "
                 f"{band[1]:.1f} m, voxel {100 * s.grid.voxel_size_m:g} cm")
        figure = plot_state_top_view(run.out / f"volume_top_view_rev{s.revision}.png", s.states, s.grid, band_m=band,
                                     up=up, sensor_origins_m=s.sensor_origins_m, extent_m=extent, title=title)
        run.files[f"volume_top_view_{key}_png"] = str(figure.path)
        views.append(figure.view)
    return views, extent


def loop_wall_thickness_m(view: StateTopView) -> float | None:
    """The loop wall (:data:`LOOP_WALL`) from above: per cell along it, the extent across it of its occupied cells
    within :data:`LOOP_WALL_STRIP_M` of its true plane; their median (metres). None: not seen, or not a z-up view."""
    normal_axis = int(np.argmax(np.abs(LOOP_WALL["normal"])))
    tangent_axis = int(np.argmax(np.abs(LOOP_WALL["tangent"])))
    if set(view.axes) != {normal_axis, tangent_axis}:
        return None
    t_i, n_i = view.axes.index(tangent_axis), view.axes.index(normal_axis)
    cells = view.cells if t_i == 0 else view.cells.T  # [along the wall, across it]
    vs = view.voxel_size_m
    along = view.min_m[t_i] + (np.arange(cells.shape[0]) + 0.5) * vs
    across = view.min_m[n_i] + (np.arange(cells.shape[1]) + 0.5) * vs
    lo, hi = LOOP_WALL["tangent_range_m"]
    occupied = cells[np.ix_((along >= lo) & (along <= hi), np.abs(across - LOOP_WALL["offset_m"]) <= LOOP_WALL_STRIP_M)] == 1
    seen = occupied.any(axis=1)
    if not seen.any():
        return None
    first = np.argmax(occupied, axis=1)
    last = occupied.shape[1] - 1 - np.argmax(occupied[:, ::-1], axis=1)
    return float(np.median((last - first + 1)[seen]) * vs)


def _figures(out: Path, before: _Revision0, after: _Corrected) -> dict[str, str]:
    """The top view of the three placements and the diagnosis figures of both revisions."""
    written: dict[str, str] = {}
    panels = [(f"revision 0 (drifting odometry): loop wall spread {before.spread.max_m * 100:.1f} cm",
               FusedCloud(before.points, before.point_frames))]
    if after.points is not None:
        panels.append((f"revision {after.closed.loop_revision} (loop closure): {after.spread.max_m * 100:.1f} cm",
                       FusedCloud(after.points, before.point_frames)))
    panels.append((f"ground truth: {after.gt_spread.max_m * 100:.1f} cm", FusedCloud(after.gt_points, before.point_frames)))
    written["top_view_png"] = str(top_view(
        out / "top_view.png", panels, z_range_m=(0.9, 2.4),
        title="the same room fused with the drifting odometry, after loop closure, and with ground truth"))
    figs = out / "figures"
    diag0, diag1 = before.diagnosis, after.diagnosis
    for name, path in write_report(figs, diag0).items():
        written[f"{name}_rev0_png"] = str(path)
    if diag1 is not None:
        compare = {"revision 0 (odometry)": diag0, f"revision {diag1.revision} (loop closure)": diag1,
                   "ground truth (reference)": after.diagnosis_gt}
        for name, path in write_report(figs, diag1, compare=compare).items():
            written[f"{name}_rev{diag1.revision}_png" if name != "score_comparison" else "smearing_before_after_png"] = str(path)
    return written


def _export_diagnoses_and_config(run: _DemoRun, config: DriftmapConfig, diag0: Diagnosis,
                                 diag1: Diagnosis | None) -> dict[str, Path]:
    """The diagnosis JSON of each revision, the configuration and the demo's build configuration."""
    diag_files = {}
    for label, d in (("rev0", diag0), ("rev1", diag1)):
        if d is not None:
            path = run.out / f"diagnosis_{label}.json"
            path.write_text(json.dumps(d.to_json(), indent=1) + "\n")
            diag_files[label] = path
            run.files[f"diagnosis_{label}_json"] = str(path)
    run.files["config_json"] = str(config.write(run.out / "config.json"))
    (run.out / "build_config.json").write_text(DEMO_BUILD_CONFIG.model_dump_json(indent=2) + "\n")
    run.files["build_config_json"] = str(run.out / "build_config.json")
    return diag_files


def _demo_result(run: _DemoRun, before: _Revision0, after: _Corrected, diag_files: dict[str, Path], *,
                 seconds: float) -> DemoResult:
    built, closed, diag1 = before.built, after.closed, after.diagnosis
    return DemoResult(
        out_dir=run.out.resolve(),
        n_frames=len(before.gt_poses),
        n_points=len(before.points),
        mean_invalid_fraction=float(built.mean_invalid_fraction or 0.0),
        flagged_frames=before.flagged,
        wall_spread_odometry_m=before.spread.median_m,
        wall_spread_ground_truth_m=after.gt_spread.median_m,
        wall_spread_odometry_max_m=before.spread.max_m,
        wall_spread_ground_truth_max_m=after.gt_spread.max_m,
        files=run.files,
        seconds=seconds,
        loops_accepted=closed.loops_accepted,
        wall_spread_corrected_m=None if after.spread is None else after.spread.median_m,
        wall_spread_corrected_max_m=None if after.spread is None else after.spread.max_m,
        ate_odometry_m=before.ate_m,
        ate_corrected_m=after.ate_m,
        loop_revision=closed.loop_revision,
        loops_tried=closed.loops_tried,
        max_correction_m=closed.max_correction_m,
        frames_retransformed=after.frames_moved,
        diagnosis_before=DiagnosisSummary.of("revision 0 (odometry)", before.diagnosis, diag_files.get("rev0"), revision=0),
        diagnosis_after=None if diag1 is None else DiagnosisSummary.of(
            f"revision {diag1.revision} (loop closure)", diag1, diag_files.get("rev1"), revision=diag1.revision),
        diagnosis_ground_truth=DiagnosisSummary.of("ground truth (reference)", after.diagnosis_gt, None, revision=None),
        seconds_per_stage={**{f"build: {k}": round(v, 3) for k, v in built.seconds_per_stage.items()},
                           **{f"loop closure: {k}": round(v, 3) for k, v in closed.seconds_per_stage.items()},
                           **run.stages.seconds},
    )


def _write_report(run: _DemoRun, result: DemoResult, t0: float) -> DemoResult:
    """The Markdown and HTML reports, then ``summary.json`` with the total time (since ``t0``)."""
    run.files["report_md"] = str(write_markdown_report(run.out / "report.md", result))
    run.files["report_html"] = str(write_html_report(run.out / "report.html", result))
    run.files["summary_json"] = str(run.out / "summary.json")
    result = replace(result, seconds=time.perf_counter() - t0)
    (run.out / "summary.json").write_text(json.dumps(result.to_json(), indent=2) + "\n")
    return result


def _export_mcap(store: FrameStore, out: Path, revision: int, diagnosis: Diagnosis | None) -> dict[str, str]:
    """The corrected map, trajectory and double-wall markers as an MCAP that opens in Foxglove."""
    path = out / "map_corrected.mcap"
    export_foxglove_mcap(store, path, revision=revision, overwrite=True,
                         double_walls=None if diagnosis is None else diagnosis.double_walls)
    return {"foxglove_mcap": str(path)}
