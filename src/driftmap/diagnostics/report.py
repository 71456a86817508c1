"""Diagnose a stored map (double walls, smearing score, MME/MPV, per-frame attribution, optional ground-truth
errors), turn the result into the JSON contract of ``driftmap diagnose`` and into PNG figures a person
looks at.

The JSON keys ``revision``, ``smearing_score_m``, ``double_wall``, ``frames``, ``change_points``,
``revisit_fraction``, ``mme``, ``mpv`` and (with ground truth) ``trajectory`` are a contract other tools
depend on; more keys may be added, none removed or renamed.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from numpy.typing import NDArray  # noqa: E402
from pydantic import BaseModel, ConfigDict, Field  # noqa: E402

from driftmap.diagnostics.attribution import Attribution, AttributionConfig, attribute, ground_truth_errors  # noqa: E402
from driftmap.diagnostics.causes import RegionCause, explain_regions  # noqa: E402
from driftmap.diagnostics.coverage import Coverage, CoverageConfig, assess  # noqa: E402
from driftmap.diagnostics.double_wall import (  # noqa: E402
    DiagnosticCloud,
    DoubleWallConfig,
    DoubleWallResult,
    MapEntropy,
    NoiseModel,
    PlacedCloud,
    SamplingConfig,
    detect_double_walls,
    map_entropy,
)
from driftmap.diagnostics.verify import RegionCheck, verification_summary  # noqa: E402
from driftmap.errors import ConfigError, StoreError  # noqa: E402
from driftmap.frame import SensorKind  # noqa: E402
from driftmap.preprocess.scene import (  # noqa: E402
    OUTDOOR_DIAGNOSTICS_SCALE,
    diagnostics_scale,
    lidar_frames,
    sample_positions,
    scene_reach,
)
from driftmap.trajectory import Trajectory, has_stamps, read_trajectory  # noqa: E402

if TYPE_CHECKING:
    from driftmap.store.frame_store import FrameStore

logger = logging.getLogger(__name__)


class EntropyConfig(BaseModel):
    """Neighbourhood rules of MME / MPV (values only compare within one rule set and one data set)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    radius_m: float = Field(0.1, gt=0.0, description="neighbours within this radius (m)")
    min_neighbors: int = Field(10, ge=4, description="points with fewer neighbours are skipped")
    max_neighbors: int = Field(64, ge=4, description="at most this many nearest neighbours")
    max_query_points: int = Field(50_000, ge=100, description="random query points (neighbours come from every sample)")


class DiagnoseConfig(BaseModel):
    """Everything ``diagnose`` uses; :meth:`for_sensor` gives indoor RGB-D or outdoor LiDAR defaults."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    sampling: SamplingConfig = Field(default_factory=SamplingConfig)
    double_wall: DoubleWallConfig = Field(default_factory=DoubleWallConfig)
    attribution: AttributionConfig = Field(default_factory=AttributionConfig)
    entropy: EntropyConfig = Field(default_factory=EntropyConfig)
    coverage: CoverageConfig = Field(default_factory=CoverageConfig)

    @classmethod
    def for_sensor(cls, kind: SensorKind) -> DiagnoseConfig:
        if kind is SensorKind.LIDAR:
            return cls(
                sampling=SamplingConfig(points_budget=1_000_000, min_points_per_frame=2000, normals_oversample=4.0, normals_k=20),
                double_wall=DoubleWallConfig(voxel_sizes_m=(0.5, 1.0, 2.0), min_separation_m=0.05, visit_gap_m=10.0),
                attribution=AttributionConfig(voxel_size_m=1.0, huber_m=0.1, max_residual_m=0.5, min_jump_m=0.05,
                                              revisit_min_path_m=10.0),
                entropy=EntropyConfig(radius_m=0.5),
            )
        return cls()

    @classmethod
    def for_scene(cls, kind: SensorKind, reach_m: float | None) -> DiagnoseConfig:
        """Defaults for a sensor whose scene reaches ``reach_m`` (:mod:`driftmap.preprocess.scene`).

        Depth cameras: the indoor lengths. LiDAR: its sampling, with every diagnostic length (voxel sizes, the
        smallest separation, attribution cells and thresholds, entropy radius) the indoor one times
        ``f = min(5, max(1, reach / 5 m))`` and the travel lengths (visit gap, revisit path) times ``f ** 1.43``
        (1 at f = 1, 10 at f = 5): a room reaching 5 m or less is diagnosed as a depth camera's, a scene reaching
        25 m or more with the outdoor lengths (2 m voxels, 10 m of travel between visits), and everything in
        between continuously."""
        if kind is not SensorKind.LIDAR:
            return cls()
        lidar = cls.for_sensor(kind)
        f = diagnostics_scale(reach_m) if reach_m is not None else OUTDOOR_DIAGNOSTICS_SCALE
        if f >= OUTDOOR_DIAGNOSTICS_SCALE:
            return lidar
        g = f ** (math.log(10.0) / math.log(OUTDOOR_DIAGNOSTICS_SCALE))
        dw, at, en = DoubleWallConfig(), AttributionConfig(), EntropyConfig()
        return lidar.model_copy(update={
            "double_wall": dw.model_copy(update={"voxel_sizes_m": tuple(f * v for v in dw.voxel_sizes_m),
                                                 "min_separation_m": f * dw.min_separation_m,
                                                 "visit_gap_m": g * dw.visit_gap_m}),
            "attribution": at.model_copy(update={"voxel_size_m": f * at.voxel_size_m, "huber_m": f * at.huber_m,
                                                 "max_residual_m": f * at.max_residual_m,
                                                 "min_jump_m": f * at.min_jump_m,
                                                 "revisit_min_path_m": g * at.revisit_min_path_m}),
            "entropy": en.model_copy(update={"radius_m": f * en.radius_m}),
        })

    @classmethod
    def for_store(cls, store: FrameStore) -> DiagnoseConfig:
        """:meth:`for_scene` of the store's sensor and of the reach of 15 of its frames spread over the log (the
        median of their 99th range percentiles)."""
        if len(store) == 0:
            raise StoreError(f"{store.path}: the store has no frames")
        ids = store.frame_ids
        first = store.frame(int(ids[0]))
        if first.sensor_kind is not SensorKind.LIDAR:
            return cls.for_sensor(first.sensor_kind)
        reach = scene_reach(lidar_frames(store.frame(int(ids[k])) for k in sample_positions(len(ids))))
        cfg = cls.for_scene(first.sensor_kind, None if reach is None else reach.reach_m)
        if reach is not None:
            logger.info("%s: the LiDAR scene reaches %s: diagnosing with %.2g x the indoor lengths (voxels %s m, "
                        "visit gap %.3g m)", store.path, reach.describe(), diagnostics_scale(reach.reach_m),
                        ", ".join(f"{v:.3g}" for v in cfg.double_wall.voxel_sizes_m), cfg.double_wall.visit_gap_m)
        return cfg

    @classmethod
    def load(cls, path: str | Path, defaults: DiagnoseConfig) -> DiagnoseConfig:
        """A diagnose config file (JSON or TOML): its ``[diagnose]`` table (or the whole file without one), each
        field set there over ``defaults`` (the scene's, :meth:`for_store`); nested tables (``[diagnose.double_wall]``
        ...) are merged field by field. Problems are :class:`ConfigError`, one line each, naming the file and key."""
        from pydantic import ValidationError

        from driftmap.config import BUILD_TABLE, DIAGNOSE_TABLE, GENERAL_TABLES, read_config_file, validation_problems

        data = read_config_file(path)
        prefix: tuple[str, ...] = ()
        if DIAGNOSE_TABLE in data:
            data, prefix = data[DIAGNOSE_TABLE], (DIAGNOSE_TABLE,)
        elif {BUILD_TABLE, *GENERAL_TABLES} & set(data):  # a build config without a [diagnose] table: defaults
            return defaults
        if not isinstance(data, dict):
            raise ConfigError(f"{path}: [diagnose] must be a table of settings")
        merged = defaults.model_dump(mode="json")
        for key, value in data.items():
            if isinstance(value, dict) and isinstance(merged.get(key), dict):
                merged[key] = {**merged[key], **value}
            else:
                merged[key] = value
        try:
            return cls.model_validate(merged)
        except ValidationError as exc:
            raise ConfigError(validation_problems(exc, str(path), prefix=prefix)) from exc


@dataclass(frozen=True)
class Diagnosis:
    """Everything ``diagnose`` found for one revision (``placed`` is kept for the figures)."""

    revision: int
    double_walls: DoubleWallResult
    attribution: Attribution
    entropy: MapEntropy
    trajectory: dict | None
    config: DiagnoseConfig
    placed: PlacedCloud
    seconds: dict[str, float] = field(default_factory=dict)
    verification: list[RegionCheck] | None = None
    """Per region (same order), the independent check of :func:`driftmap.diagnostics.verify.verify_regions`."""
    coverage: Coverage | None = None
    """How much of the map was judged, why the rest not, and which headline figures are a verdict."""
    causes: list[RegionCause] | None = None
    """Per double-wall region (same order), what caused it (:mod:`driftmap.diagnostics.causes`)."""

    @property
    def smearing_score_m(self) -> float:
        return self.double_walls.smearing_score_m

    def to_json(self) -> dict:
        dw, at = self.double_walls, self.attribution
        out = {
            "revision": int(self.revision),
            "smearing_score_m": _num(dw.smearing_score_m),
            "smearing_score_per_scale_m": {f"{k:g}": _num(v) for k, v in dw.score_per_scale_m.items()},
            "smearing_score_revisit_m": _num(dw.revisit_score_m(at.config.revisit_min_path_m)),
            "smearing_score_frames_m": _num(dw.frame_smearing_score_m),
            "double_wall": dw.to_json(),
            "frames": at.frames_json(),
            "change_points": [c.to_json() for c in at.change_points],
            "revisit_fraction": float(at.revisit_fraction),
            "revisit_note": at.revisit_note,
            "drift_rate": {"percent_per_m": at.drift.percent_per_m, "deg_per_m": at.drift.deg_per_m,
                           "n_frames": at.drift.n_frames, "path_span_m": at.drift.path_span_m,
                           "noise_floor_m": at.drift.noise_floor_m, "noise_floor_deg": at.drift.noise_floor_deg},
            "mme": _num(self.entropy.mme),
            "mpv": _num(self.entropy.mpv_m2),
            "entropy": {"mme_unit": "nats", "mpv_unit": "m^2",
                        "mpv_definition": "mean smallest eigenvalue of the neighbourhood covariance",
                        "radius_m": self.entropy.radius_m, "min_neighbors": self.entropy.min_neighbors,
                        "max_neighbors": self.entropy.max_neighbors, "n_points_used": self.entropy.n_points_used,
                        "n_points_queried": self.entropy.n_points_queried},
            "valid": None if self.coverage is None else self.coverage.valid,
            "reasons": [] if self.coverage is None else self.coverage.reasons,
            "fraction_inconsistent": None if self.coverage is None else self.coverage.fraction_inconsistent,
            "coverage": None if self.coverage is None else self.coverage.to_json(),
            "n_frames": int(len(at.frame_ids)),
            "n_points_sampled": int(self.placed.samples.n_points),
            "config": self.config.model_dump(mode="json"),
            "seconds": {k: round(v, 3) for k, v in self.seconds.items()},
        }
        if self.causes is not None:
            for region_json, cause in zip(out["double_wall"]["regions"], self.causes):
                region_json["cause"] = cause.cause
                region_json["cause_explanation"] = cause.explanation
                region_json["cause_evidence"] = cause.evidence
            counts: dict[str, int] = {}
            for cause in self.causes:
                counts[cause.cause] = counts.get(cause.cause, 0) + 1
            out["double_wall"]["causes"] = counts
        if self.trajectory is not None:
            out["trajectory"] = self.trajectory
        if self.verification is not None:
            for region_json, check in zip(out["double_wall"]["regions"], self.verification):
                region_json["verification"] = check.to_json()
            out["double_wall"]["verified"] = verification_summary(self.verification, dw.regions, dw.voxels_evaluated)
        return out


MIN_GT_FRAMES = 3
"""ATE (a rigid alignment) and RPE need at least this many frames with a ground-truth pose."""


def _num(v: float | None) -> float | None:
    return float(v) if v is not None and math.isfinite(v) else None


# ---------------------------------------------------------------------------------------------- diagnose


def diagnose_cloud(cloud: DiagnosticCloud, poses: NDArray[np.float64], *, revision: int = 0,
                   config: DiagnoseConfig | None = None, ground_truth: NDArray[np.float64] | None = None,
                   ground_truth_rows: NDArray[np.int64] | None = None) -> Diagnosis:
    """Diagnose samples placed with ``poses`` (rows in the cloud's frame order).

    ``ground_truth``: (K, 4, 4) poses of the frame rows ``ground_truth_rows`` (default: all rows) for ATE/RPE.
    """
    cfg = config or DiagnoseConfig()
    seconds: dict[str, float] = {}
    t = time.perf_counter()
    placed = cloud.place(poses)
    seconds["place"] = time.perf_counter() - t
    t = time.perf_counter()
    walls = detect_double_walls(placed, cfg.double_wall)
    seconds["double_walls"] = time.perf_counter() - t
    t = time.perf_counter()
    attribution = attribute(placed, cfg.attribution)
    seconds["attribution"] = time.perf_counter() - t
    t = time.perf_counter()
    e = cfg.entropy
    entropy = map_entropy(placed.points_world, radius_m=e.radius_m, min_neighbors=e.min_neighbors,
                          max_neighbors=e.max_neighbors, max_query_points=e.max_query_points)
    seconds["mme_mpv"] = time.perf_counter() - t
    t = time.perf_counter()
    coverage = assess(placed, walls, attribution.drift.n_frames, cfg.coverage)
    causes = explain_regions(placed, walls)
    seconds["coverage"] = time.perf_counter() - t
    trajectory = None
    if ground_truth is not None:
        rows = np.arange(cloud.n_frames) if ground_truth_rows is None else np.asarray(ground_truth_rows, dtype=np.int64)
        gt = np.asarray(ground_truth, dtype=np.float64).reshape(-1, 4, 4)
        if len(rows) != len(gt):
            raise ConfigError(f"ground truth: {len(gt)} poses for {len(rows)} frame rows")
        if len(rows) < MIN_GT_FRAMES:
            raise ConfigError(f"ground truth matched only {len(rows)} frames; ATE needs at least {MIN_GT_FRAMES}")
        trajectory = ground_truth_errors(placed.poses[rows], gt)
        trajectory["n_frames_matched"] = int(len(rows))
    return Diagnosis(revision, walls, attribution, entropy, trajectory, cfg, placed, seconds, coverage=coverage,
                     causes=causes)


#: formats of ``diagnose --gt`` (``--gt-format``)
GT_FORMATS = ("tum", "kitti", "redwood", "4x4")


def read_ground_truth(store: FrameStore, path: str | Path, format: str = "tum", *,
                      max_dt_ns: int = 10_000_000, kitti_frame: str = "auto",
                      calib_file: str | Path | None = None) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Ground-truth poses for the store's frames: TUM rows (and 4x4 blocks with stamps) matched by stamp, KITTI
    rows (and 4x4 blocks without stamps) row i = ``frame_id`` i, Redwood ``.log`` blocks by the frame id they name.

    Returns the matched frame ids and their poses; the file must hold ``T_world_sensor`` of the same sensor
    frame, except that on a store of KITTI Velodyne scans a KITTI data set's own cam0 ``poses.txt`` is
    converted to the Velodyne frame (``kitti_frame`` ``auto`` | ``velodyne`` | ``cam0`` and ``calib_file`` as
    in :func:`driftmap.sources.kitti.kitti_rows_as_velodyne`).
    """
    from driftmap.store.ledger import PoseMatchMode, match_pose_rows, stamp_ranges_text

    fmt = format.lower()
    if fmt not in GT_FORMATS:
        raise ConfigError(f"--gt-format must be one of {', '.join(GT_FORMATS)}, got {format!r}")
    if fmt != "kitti" and (kitti_frame != "auto" or calib_file is not None):
        raise ConfigError(f"{path}: --kitti-frame / --calib apply to KITTI ground truth only (--gt-format kitti)")
    traj: Trajectory = read_trajectory(path, fmt)
    traj = store.pose_rows_in_sensor_frame(path, traj, fmt, kitti_frame=kitti_frame, calib_file=calib_file)
    mode = PoseMatchMode.STAMP if has_stamps(traj, fmt) else PoseMatchMode.INDEX
    matched = match_pose_rows(traj, fmt, store.ledger.frame_ids, store.ledger.stamps_ns, match=mode, max_dt_ns=max_dt_ns)
    if not matched.poses:
        why = f" ({stamp_ranges_text(traj, store.ledger.stamps_ns)})" if mode is PoseMatchMode.STAMP else ""
        raise StoreError(f"{path}: no ground-truth row matched a stored frame (by {mode.value}){why}")
    if len(matched.poses) < MIN_GT_FRAMES:  # found before the costly diagnosis, not after it
        raise StoreError(f"{path}: ground truth matched only {len(matched.poses)} of the {len(store.ledger.frame_ids)} "
                         f"stored frames (by {mode.value}); ATE/RPE need at least {MIN_GT_FRAMES}")
    if matched.unmatched_frames:
        logger.warning("%s: %d stored frames have no ground-truth pose; they are left out of ATE/RPE", path,
                       len(matched.unmatched_frames))
    ids = np.array(sorted(matched.poses), dtype=np.int64)
    return ids, np.array([matched.poses[int(i)] for i in ids])


def diagnose_store(store: FrameStore, revision: int | None = None, *, config: DiagnoseConfig | None = None,
                   cloud: DiagnosticCloud | None = None, ground_truth: tuple[NDArray[np.int64], NDArray[np.float64]] | None = None,
                   noise: NoiseModel | None = None) -> Diagnosis:
    """Diagnose a store's map in ``revision`` (default: head). ``cloud`` reuses samples across revisions;
    ``ground_truth`` is ``(frame_ids, poses)`` as from :func:`read_ground_truth`."""
    rev = store.head if revision is None else int(revision)
    store.ledger.revision(rev)  # raises for an unknown revision
    if len(store) == 0:
        raise StoreError(f"{store.path}: the store has no frames")
    if config is None:
        config = DiagnoseConfig.for_store(store)
    t = time.perf_counter()
    if cloud is None:
        cloud = DiagnosticCloud.from_store(store, config.sampling, noise)
    sampling_s = time.perf_counter() - t
    all_ids = store.frame_ids
    poses = store.poses(rev)[np.searchsorted(all_ids, cloud.frame_ids)]
    gt_rows = gt_poses = None
    if ground_truth is not None:
        gt_ids, gt_all = ground_truth
        row_of = {int(f): k for k, f in enumerate(cloud.frame_ids)}
        pairs = [(row_of[int(f)], k) for k, f in enumerate(gt_ids) if int(f) in row_of]
        gt_rows = np.array([p[0] for p in pairs], dtype=np.int64)
        gt_poses = np.asarray(gt_all)[[p[1] for p in pairs]]
        order = np.argsort(gt_rows)
        gt_rows, gt_poses = gt_rows[order], gt_poses[order]
    diagnosis = diagnose_cloud(cloud, poses, revision=rev, config=config, ground_truth=gt_poses, ground_truth_rows=gt_rows)
    diagnosis.seconds["sampling"] = sampling_s
    return diagnosis


# ---------------------------------------------------------------------------------------------- figures


def _up_axis(placed: PlacedCloud) -> NDArray[np.float64]:
    """World 'up' from how the sensors were held: minus the mean camera y axis (image down) for depth cameras,
    the mean sensor z axis for LiDAR."""
    kinds = placed.samples.sensor_kinds
    lidar = sum(k is SensorKind.LIDAR for k in kinds) > len(kinds) / 2
    R = placed.poses[:, :3, :3]
    up = R[:, :, 2].mean(axis=0) if lidar else -R[:, :, 1].mean(axis=0)
    norm = np.linalg.norm(up)
    return up / norm if norm > 1e-6 else np.array([0.0, 0.0, 1.0])


def _plane_axes(up: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    helper = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = helper - up * (helper @ up)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(up, e1)


def plot_double_walls(path: str | Path, diagnosis: Diagnosis, *, max_points: int = 150_000, title: str | None = None) -> Path:
    """Top view of the map (grey) with every flagged surface group coloured by its separation (cm)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    placed, walls = diagnosis.placed, diagnosis.double_walls
    up = _up_axis(placed)
    e1, e2 = _plane_axes(up)
    P = placed.points_world
    if len(P) > max_points:
        P = P[np.random.default_rng(0).choice(len(P), max_points, replace=False)]
    fig, ax = plt.subplots(figsize=(8.0, 7.0))
    ax.scatter(P @ e1, P @ e2, s=0.2, c="0.75", linewidths=0, rasterized=True)
    centers, seps, sizes = [], [], []
    for s in walls.scales:
        sel = s.flagged
        centers.append(s.centers_m[sel])
        seps.append(np.abs(s.separation_m[sel]) * 100)
        sizes.append(np.full(int(sel.sum()), s.voxel_size_m))
    if centers and sum(len(c) for c in centers):
        C, S, Z = np.concatenate(centers), np.concatenate(seps), np.concatenate(sizes)
        order = np.argsort(-Z)  # large voxels first, small ones on top
        sc = ax.scatter(C[order] @ e1, C[order] @ e2, c=S[order], s=8 + 120 * Z[order] / Z.max(), cmap="inferno_r",
                        vmin=0, vmax=max(float(np.percentile(S, 95)), 1.0), edgecolors="k", linewidths=0.3)
        fig.colorbar(sc, ax=ax, label="double-wall separation (cm)", shrink=0.8)
        for k, region in enumerate(walls.regions[:8]):
            ax.annotate(f"{k + 1}", (region.center_m @ e1, region.center_m @ e2), fontsize=8, color="navy",
                        xytext=(4, 4), textcoords="offset points")
    traj = placed.origins_world
    ax.plot(traj @ e1, traj @ e2, "-", color="tab:blue", lw=0.8, alpha=0.7, label="sensor path")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_aspect("equal")
    ax.set_xlabel("m")
    ax.set_ylabel("m")
    ax.grid(alpha=0.3)
    ax.set_title(title or (f"revision {diagnosis.revision}: {walls.voxels_flagged} of {walls.voxels_evaluated} surface "
                           f"voxels doubled ({100 * walls.fraction_flagged:.1f} %), smearing "
                           f"{1000 * walls.smearing_score_m:.1f} mm"), fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def plot_frame_disagreement(path: str | Path, diagnosis: Diagnosis, *, title: str | None = None) -> Path:
    """Per-frame disagreement with the map and jump against the frames before, over time, with change points."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    at = diagnosis.attribution
    cfg = at.config
    x = at.frame_ids
    est = at.disagreement.estimated(cfg.min_correspondences)
    obs = at.disagreement.observable(cfg.min_correspondences)
    fig, axes = plt.subplots(2, 1, figsize=(10.0, 6.0), sharex=True)
    step = at.split.step_norm_m
    step_label = f"step: {cfg.split_window} frames from here vs the {cfg.split_window} before"
    for ax, d, j, unit, scale, label in (
            (axes[0], at.disagreement.translation_norm_m, step, "mm", 1000.0, step_label),
            (axes[1], at.disagreement.rotation_norm_deg, at.jumps.rotation_norm_deg, "deg", 1.0, f"jump vs the {cfg.window} frames before")):
        ax.plot(x[est], d[est] * scale, ".-", ms=3, lw=0.8, color="tab:blue", label="disagreement with the map")
        ax.plot(x[est & ~obs], d[est & ~obs] * scale, "x", ms=4, color="0.5", label="(a direction unobservable)")
        ax.plot(x, j * scale, "-", lw=0.8, color="tab:orange", label=label)
        for cp in at.change_points:
            ax.axvline(cp.frame_id, color="crimson", lw=1.0, alpha=0.8)
        ax.set_ylabel(unit)
        ax.grid(alpha=0.3)
    if at.change_points:
        axes[0].plot([], [], color="crimson", label="change point")
    axes[0].legend(loc="upper right", fontsize=8)
    axes[1].legend(loc="upper right", fontsize=8)
    axes[1].set_xlabel("frame id")
    drift = at.drift
    rate = ("no revisit: drift invisible" if drift.percent_per_m is None
            else f"drift ~{drift.percent_per_m:.2f} %/m, {drift.deg_per_m:.3f} deg/m")
    axes[0].set_title(title or f"revision {diagnosis.revision}: per-frame disagreement; {len(at.change_points)} change "
                               f"points; {rate}; revisited {100 * at.revisit_fraction:.0f} %", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def plot_score_comparison(path: str | Path, diagnoses: dict[str, Diagnosis], *, title: str | None = None) -> Path:
    """Smearing score per voxel scale and overall, and the share of doubled voxels, for several revisions
    (e.g. before / after a correction)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    labels = list(diagnoses)
    scales = sorted({s for d in diagnoses.values() for s in d.double_walls.score_per_scale_m})
    groups = [f"{s:g} m" for s in scales] + ["overall"]
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(11.0, 4.2), gridspec_kw={"width_ratios": [3, 1]})
    width = 0.8 / max(len(labels), 1)
    for k, label in enumerate(labels):
        d = diagnoses[label].double_walls
        vals = [d.score_per_scale_m.get(s, float("nan")) * 1000 for s in scales] + [d.smearing_score_m * 1000]
        ax.bar(np.arange(len(groups)) + k * width, vals, width, label=label)
        bar = ax2.bar(k, 100 * d.fraction_flagged, 0.6, label=label, color=f"C{k}")
        ax2.bar_label(bar, fmt="%.2f %%", fontsize=8)
    ax.set_xticks(np.arange(len(groups)) + width * (len(labels) - 1) / 2, groups)
    ax.set_ylabel("smearing score (mm)")
    ax.legend(fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    ax2.set_xticks(range(len(labels)), [label.replace(" (", "\n(") for label in labels], fontsize=7)
    ax2.set_ylabel("surface voxels doubled (%)")
    ax2.grid(axis="y", alpha=0.3)
    fig.suptitle(title or "smearing before / after", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def write_report(out_dir: str | Path, diagnosis: Diagnosis, *, compare: dict[str, Diagnosis] | None = None) -> dict[str, Path]:
    """The PNG figures of a diagnosis (and, with ``compare``, the before/after score figure)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = {
        "double_walls": plot_double_walls(out / f"double_walls_rev{diagnosis.revision}.png", diagnosis),
        "frame_disagreement": plot_frame_disagreement(out / f"frame_disagreement_rev{diagnosis.revision}.png", diagnosis),
    }
    if compare:
        files["score_comparison"] = plot_score_comparison(out / "smearing_before_after.png", compare)
    return files
