"""The settings of ``driftmap build`` (:class:`BuildConfig`, the ``[build]`` table of a config file) and what a build
returns (:class:`BuildResult`, written to ``build_summary.json``)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import ConfigDict, Field

from driftmap.config import SettingsModel, Threads
from driftmap.errors import ConfigError
from driftmap.posegraph import Optimizer, RobustKernel
from driftmap.registration.loops import (
    LoopClosureConfig,
)
from driftmap.registration.odometry import OdometryConfig
from driftmap.store.frame_store import FrameStore

#: (stage, done, total) -- total None when unknown
ProgressCallback = Callable[[str, int, int | None], None]


DEFAULT_POSES_MAX_DT_NS = 20_000_000
"""A ``--poses`` TUM row matches a frame within this (20 ms, as TUM's ``associate.py``)."""


class BuildConfig(SettingsModel):
    """Everything ``build`` decides; saved next to the store as ``build_config.json``."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    pixel_stride: int | None = Field(None, ge=1, description="depth images: keep every n-th pixel (None: 2 for images >= 640 px wide, else 1)")
    odometry: OdometryConfig | None = Field(None, description="odometry settings (None: defaults for the sensor kind, LiDAR lengths scaled to the scene)")
    loop_closure: LoopClosureConfig = Field(default_factory=LoopClosureConfig)
    loop_kernel: RobustKernel = Field(RobustKernel.CAUCHY, description="robust kernel on loop edges")
    optimizer: Optimizer = Field(Optimizer.LM, description="pose-graph optimiser")
    odometry_edge_max_disagreement_m: float = Field(0.1, gt=0.0, description="GICP may refine an odometry edge by at most this (m)")
    fallback_sigma_translation: float = Field(0.02, gt=0.0, description="odometry edge sigma when registration fails: fraction of the motion + 1 cm")
    fallback_sigma_rotation_deg: float = Field(1.0, gt=0.0, description="odometry edge rotation sigma when registration fails (deg)")
    resume_seed_frames: int = Field(10, ge=1, description="not used (kept so that configs setting it still load): --resume re-tracks every stored frame with the odometry, which continues exactly as an uninterrupted build (it used to re-seed the odometry from this many stored frames)")
    odometry_edge_window: int = Field(3, ge=1, description="pose graph: each keyframe is linked to the next this many keyframes")
    odometry_edges: Literal["auto", "trajectory", "registration"] = Field(
        "auto", description="odometry edge measurement: the revision-0 relative pose (trajectory), the keyframe GICP (registration), "
                            "or auto (trajectory for frame-to-map odometry that keeps its whole map, else registration)")
    depth_scale_error: float = Field(1.0, gt=0.0, description="diagnostics experiment: scale every frame's ranges by this factor before odometry and storing (1 = none)")
    focal_length_error: float = Field(1.0, gt=0.0, description="diagnostics experiment: depth cameras as if back-projected with this times the true focal length (1 = none)")
    num_threads: Threads | None = Field(None, description="registration threads of the odometry and the loop closure (overrides odometry.num_threads and loop_closure.num_threads); 1: the same input gives the same poses, every revision, to the bit")
    information_calibration_iterations: int = Field(10, ge=0, description="pose graph: at most this many variance-component re-weighting rounds (they stop once no group's scale changes by more than 5 %)")

    @classmethod
    def load(cls, path: str | Path | None = None) -> BuildConfig:
        """The build settings: defaults, then a config file (JSON or TOML: its ``build`` table, next to which only
        the general tables -- ``depth``, ``map``, ``volume``: :class:`driftmap.config.DriftmapConfig` -- may stand;
        or, without any of these tables, the whole file), then the ``DRIFTMAP_BUILD__*`` environment (as
        ``driftmap config --show`` lists: defaults < file < environment < flags). Problems are
        :class:`ConfigError`, one line each, naming the file or the environment variable and the key."""
        from pydantic import ValidationError

        from driftmap.config import (
            BUILD_TABLE,
            check_written_types,
            env_table,
            has_setting,
            merge_settings,
            split_config_file,
            validation_problems,
        )

        data, prefix = ({}, (BUILD_TABLE,)) if path is None else split_config_file(path)[1:]
        if path is not None:
            check_written_types(data, cls, path, "".join(f"{p}." for p in prefix))
        env = env_table(BUILD_TABLE)
        try:
            return cls(**merge_settings(data, env))
        except ValidationError as exc:
            def origin(loc: tuple[str, ...]) -> str:
                return "environment" if has_setting(env, loc) else str(path)
            problems = validation_problems(exc, origin, prefix=prefix, env_names=True)
            if not prefix:  # a bare build file: its keys have no table, the environment's are DRIFTMAP_BUILD__...
                problems = "\n".join(
                    line.replace("environment DRIFTMAP_", f"environment DRIFTMAP_{BUILD_TABLE.upper()}__", 1)
                    for line in problems.splitlines())
            raise ConfigError(problems) from exc


@dataclass
class BuildResult:
    store: str
    n_frames: int
    n_frames_new: int
    mean_invalid_fraction: float | None
    pose_source: str
    odometry_fps: float | None
    n_keyframes: int = 0
    loops_tried: int = 0
    loops_accepted: int = 0
    loops_rejected_by_graph: int = 0
    graph_error_before: float | None = None
    graph_error_after: float | None = None
    loop_revision: int | None = None
    max_correction_m: float | None = None
    max_correction_deg: float | None = None
    seconds_per_stage: dict[str, float] = field(default_factory=dict)
    loops: list[dict[str, Any]] = field(default_factory=list)
    odometry_edges: int = 0
    information_scale: dict[str, float] = field(default_factory=dict)
    source: dict[str, Any] | None = None
    """What the store was built from (resolved path, format, the path as given); see ``build_source.json``."""
    odometry_config: dict[str, Any] | None = None
    """The odometry settings this run used (``[build.odometry]``, or the defaults for the sensor and scene)."""
    scene_reach: dict[str, Any] | None = None
    """How far the LiDAR scene reaches (:class:`driftmap.preprocess.scene.SceneReach`: the median over frames spread
    across the log of their 99th range percentile, which scaled the odometry's default lengths); None when the
    lengths were not chosen from the scene (depth cameras, a config, a resumed build that recorded them)."""
    tracking: dict[str, Any] = field(default_factory=lambda: tracking_summary(None))
    """How the odometry's registrations went (:func:`tracking_summary`): counts per status, the flagged and the
    recovered frames with their reasons, fitness and degeneracy, and one record per frame."""
    given_poses_check: dict[str, Any] | None = None
    """Frames built with given poses (``--poses`` / ``--poses-from-source``): do those poses move the way the frames
    do (:class:`driftmap.pipeline.given_poses.GivenPosesCheck`: ``consistent``, the registered frame pairs)? None
    with the odometry's poses, or when no frame was added."""
    loop_closure_config: dict[str, Any] | None = None
    """The loop-closure settings this run used: ``[build.loop_closure]``'s explicit ones over the defaults for the
    sensor (LiDAR: :meth:`LoopClosureConfig.for_lidar`); None without loop closure."""

    @property
    def frames_per_second(self) -> float:
        total = sum(self.seconds_per_stage.values())
        return self.n_frames_new / total if total > 0 else float("nan")

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["frames_per_second"] = self.frames_per_second
        return d


def tracking_summary(store: FrameStore | None) -> dict[str, Any]:
    """The tracking-health records of a store's frames (:class:`driftmap.frame.TrackingHealth`, kept with each frame
    its odometry registered): ``frames`` (with a record), ``by_status`` counts, ``flagged`` (lost / reinitialised),
    ``recovered`` and ``degenerate`` (bridged along a direction the scan left free) frames with their reasons, the median fitness, the smallest degeneracy and ``per_frame``."""
    per_frame = []
    for fid in (store.frame_ids if store is not None else []):
        record = store.frame_info(int(fid)).get("tracking")
        if record is not None:
            per_frame.append({"frame_id": int(fid), **record})
    by_status: dict[str, int] = {}
    for r in per_frame:
        by_status[r["status"]] = by_status.get(r["status"], 0) + 1
    fitness = [r["fitness"] for r in per_frame if r["fitness"] is not None]
    degeneracy = [r["degeneracy"] for r in per_frame if r["degeneracy"] is not None]

    def brief(r: dict[str, Any]) -> dict[str, Any]:
        return {k: r[k] for k in ("frame_id", "status", "hypothesis", "fitness", "reason")}
    return {
        "frames": len(per_frame), "by_status": by_status,
        "flagged": [brief(r) for r in per_frame if r["status"] in ("lost", "reinitialised")],
        "recovered": [brief(r) for r in per_frame if r["status"] == "recovered"],
        "degenerate": [brief(r) for r in per_frame if r["status"] == "degenerate"],
        "median_fitness": float(np.median(fitness)) if fitness else None,
        "min_degeneracy": float(np.min(degeneracy)) if degeneracy else None,
        "per_frame": per_frame,
    }
