"""Ground truth for a diagnosis: how far poses are from it (ATE, RPE, KITTI segment errors); reading a ground-truth
file for a store's frames is :func:`driftmap.pipeline.pose_files.read_ground_truth`. Only a diagnosis with ``--gt`` uses this; every other measure of
:mod:`driftmap.diagnostics` works without ground truth."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from driftmap import geometry
from driftmap.diagnostics.trajectory_metrics import project_rotations, relative_pose_errors, trajectory_errors
from driftmap.errors import ConfigError

logger = logging.getLogger(__name__)

MIN_GT_FRAMES = 3
"""ATE (a rigid alignment) and RPE need at least this many frames with a ground-truth pose."""

#: formats of ``diagnose --gt`` (``--gt-format``)
GT_FORMATS = ("tum", "kitti", "redwood", "4x4", "euroc")


@dataclass(frozen=True)
class SegmentErrors:
    """KITTI-style errors: per segment length, mean translational error (%) and rotational error (deg/m)."""

    lengths_m: NDArray[np.float64]
    translation_percent: NDArray[np.float64]
    rotation_deg_per_m: NDArray[np.float64]
    n_segments: NDArray[np.int64]

    @property
    def mean_translation_percent(self) -> float | None:
        ok = self.n_segments > 0
        return float(np.mean(self.translation_percent[ok])) if ok.any() else None

    @property
    def mean_rotation_deg_per_m(self) -> float | None:
        ok = self.n_segments > 0
        return float(np.mean(self.rotation_deg_per_m[ok])) if ok.any() else None


def segment_errors(estimate: NDArray[np.float64], ground_truth: NDArray[np.float64], *,
                   lengths_m: tuple[float, ...] = (100, 200, 300, 400, 500, 600, 700, 800), step_frames: int = 10) -> SegmentErrors:
    """KITTI odometry metric (Geiger et al. 2012): for segments of each length along the ground-truth path,
    starting every ``step_frames`` frames, the relative-pose error at the segment's end divided by its length."""
    est = np.asarray(estimate, dtype=np.float64)
    gt = np.asarray(ground_truth, dtype=np.float64)
    if est.shape != gt.shape or est.ndim != 3 or est.shape[1:] != (4, 4):
        raise ConfigError(f"segment_errors: need matching (N, 4, 4) arrays, got {est.shape} and {gt.shape}")
    est, gt = project_rotations(est), project_rotations(gt)  # as trajectory_errors: files store a few digits
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1))])
    L = np.asarray(lengths_m, dtype=np.float64)
    starts = np.arange(0, len(gt), step_frames)
    first = np.repeat(starts, len(L))
    li = np.tile(np.arange(len(L)), len(starts))
    last = np.searchsorted(s, s[first] + L[li])  # the first frame at least `length` along the path
    ok = last < len(gt)
    first, li, last = first[ok], li[ok], last[ok]
    E = relative_pose_errors(est, gt, first, last)
    t_err = np.bincount(li, np.linalg.norm(E[:, :3, 3], axis=1) / L[li], minlength=len(L))
    r_err = np.bincount(li, np.degrees(geometry.relative_rotation_angle_rad(np.eye(3), E)) / L[li], minlength=len(L))
    count = np.bincount(li, minlength=len(L)).astype(np.int64)
    with np.errstate(invalid="ignore", divide="ignore"):
        return SegmentErrors(L, 100.0 * t_err / np.maximum(count, 1), r_err / np.maximum(count, 1), count)


RPE_UNRELATED_STEP_FRACTION = 0.5
"""An RPE over consecutive frames above this share of the median ground-truth step (and above
:data:`RPE_UNRELATED_FLOOR_M`), or above :data:`RPE_UNRELATED_DEG`, is warned about: no odometry is that far off on
every step (ours: about 1 %); the ground truth is likely another log's."""
RPE_UNRELATED_FLOOR_M = 0.05
RPE_UNRELATED_DEG = 5.0


def ground_truth_errors(estimate: NDArray[np.float64], ground_truth: NDArray[np.float64], *,
                        segment_lengths_m: tuple[float, ...] | None = None) -> dict:
    """ATE (rigid Umeyama), RPE over consecutive frames and KITTI segment errors as a JSON-ready dict.

    Segment lengths default to 1/8 .. 8/8 of the ground-truth path (KITTI's 100..800 m on a long drive)."""
    errs = trajectory_errors(estimate, ground_truth)
    gt = np.asarray(ground_truth, dtype=np.float64)
    steps = np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1)  # ground-truth frame-to-frame travel (m)
    total = float(np.sum(steps)) if len(gt) > 1 else 0.0
    lengths = segment_lengths_m or tuple(total * k / 8.0 for k in range(1, 8)) if total > 0 else ()
    seg = segment_errors(estimate, ground_truth, lengths_m=lengths, step_frames=1) if lengths else None
    est_path = float(np.sum(np.linalg.norm(np.diff(np.asarray(estimate)[:, :3, 3], axis=0), axis=1))) if len(gt) > 1 else 0.0
    lengths_apart = max(total, est_path) > 3.0 * max(min(total, est_path), 0.1) and max(total, est_path) > 1.0
    if lengths_apart or errs.ate_rmse_m > max(0.5 * max(total, est_path), 1.0):
        logger.warning("ATE %.2f m over a path of %.2f m estimated and %.2f m in the ground truth: is the ground truth "
                       "for these frames (the same sequence, frame numbering and sensor frame)?",
                       errs.ate_rmse_m, est_path, total)
    step_m = float(np.median(steps)) if len(gt) > 1 else 0.0
    if errs.rpe_trans_rmse_m > max(RPE_UNRELATED_STEP_FRACTION * step_m, RPE_UNRELATED_FLOOR_M) or (
            errs.rpe_rot_rmse_deg > RPE_UNRELATED_DEG):  # hostile trial 27 W5: another log's file, 24 cm / 13.7 deg
        logger.warning("RPE %.3g m / %.3g deg from one frame to the next, against a median ground-truth step of %.3g m: "
                       "the ground truth's frame-to-frame motion does not fit the estimate's (another log's ground "
                       "truth with the same stamps? an estimate that jumps?); the ATE then compares unrelated "
                       "trajectories", errs.rpe_trans_rmse_m, errs.rpe_rot_rmse_deg, step_m)
    return {
        "ate_rmse_m": errs.ate_rmse_m,
        "ate_max_m": errs.ate_max_m,
        "rpe_trans_rmse_m": errs.rpe_trans_rmse_m,
        "rpe_rot_rmse_deg": errs.rpe_rot_rmse_deg,
        "n_poses": errs.n_poses,
        "segment_translation_percent": None if seg is None else seg.mean_translation_percent,
        "segment_rotation_deg_per_m": None if seg is None else seg.mean_rotation_deg_per_m,
        "segment_lengths_m": [float(v) for v in lengths],
    }
