"""Trajectory error against ground truth: ATE after rigid (or Sim(3)) Umeyama alignment, RPE, and
KITTI-style segment errors. Standard definitions (Sturm et al. 2012; Geiger et al. 2012)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from driftmap import geometry
from driftmap.errors import ConfigError


def umeyama(source_m: NDArray[np.float64], target_m: NDArray[np.float64], *, with_scale: bool = False) -> tuple[NDArray[np.float64], float]:
    """Least-squares ``(T, s)`` with ``target ~ s R source + t`` (Umeyama 1991); ``T`` holds R and t."""
    src = np.asarray(source_m, dtype=np.float64)
    dst = np.asarray(target_m, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ConfigError(f"umeyama: need two (N>=3, 3) arrays of equal shape, got {src.shape} and {dst.shape}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    scale = float(np.trace(np.diag(D) @ S) / xs.var(0).sum()) if with_scale else 1.0
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = mu_d - scale * R @ mu_s
    return T, scale


def project_rotations(poses: NDArray[np.float64]) -> NDArray[np.float64]:
    """The nearest rotation (SVD) in every pose's rotation block; poses already orthonormal are unchanged."""
    U, _, Vt = np.linalg.svd(poses[:, :3, :3])
    R = U @ Vt
    flip = np.linalg.det(R) < 0
    if np.any(flip):
        U[flip, :, 2] *= -1.0
        R = U @ Vt
    out = poses.copy()
    out[:, :3, :3] = R
    return out


@dataclass(frozen=True)
class TrajectoryErrors:
    ate_rmse_m: float
    ate_max_m: float
    rpe_trans_rmse_m: float
    rpe_rot_rmse_deg: float
    n_poses: int
    alignment: NDArray[np.float64]
    scale: float


def relative_pose_errors(estimate: NDArray[np.float64], ground_truth: NDArray[np.float64], first: NDArray[np.integer],
                         last: NDArray[np.integer] | int) -> NDArray[np.float64]:
    """(K, 4, 4) errors ``inv(inv(gt[i]) @ gt[j]) @ (inv(est[i]) @ est[j])`` of the relative motions from frames
    ``first`` to ``last`` (``last`` an index array, or an int offset added to ``first``)."""
    i = np.asarray(first, dtype=np.int64)
    j = i + last if isinstance(last, (int, np.integer)) else np.asarray(last, dtype=np.int64)
    rel_gt = geometry.invert(ground_truth[i]) @ ground_truth[j]
    rel_est = geometry.invert(estimate[i]) @ estimate[j]
    return geometry.invert(rel_gt) @ rel_est


def trajectory_errors(estimate: NDArray[np.float64], ground_truth: NDArray[np.float64], *, delta: int = 1,
                      with_scale: bool = False) -> TrajectoryErrors:
    """ATE (positions after Umeyama alignment of the estimate onto the ground truth) and RPE over ``delta``
    frames, for (N, 4, 4) pose arrays that correspond row by row."""
    est = np.asarray(estimate, dtype=np.float64)
    gt = np.asarray(ground_truth, dtype=np.float64)
    if est.shape != gt.shape or est.ndim != 3 or est.shape[1:] != (4, 4):
        raise ConfigError(f"trajectory_errors: need matching (N, 4, 4) arrays, got {est.shape} and {gt.shape}")
    # pose files store rotations to a few digits (KITTI: 6 significant): project them onto SO(3) so that the
    # rigid inverse is exact and a perfect estimate gives zero rotation error
    est, gt = project_rotations(est), project_rotations(gt)
    T, s = umeyama(est[:, :3, 3], gt[:, :3, 3], with_scale=with_scale)
    aligned = s * est[:, :3, 3] @ T[:3, :3].T + T[:3, 3]
    err = np.linalg.norm(aligned - gt[:, :3, 3], axis=1)
    E = relative_pose_errors(est, gt, np.arange(max(len(est) - delta, 0)), delta)
    trans = np.linalg.norm(E[:, :3, 3], axis=1)
    rot = np.degrees(geometry.relative_rotation_angle_rad(np.eye(3), E))
    return TrajectoryErrors(
        ate_rmse_m=float(np.sqrt(np.mean(err**2))),
        ate_max_m=float(err.max()),
        rpe_trans_rmse_m=float(np.sqrt(np.mean(np.square(trans)))) if trans.size else 0.0,
        rpe_rot_rmse_deg=float(np.sqrt(np.mean(np.square(rot)))) if rot.size else 0.0,
        n_poses=len(est),
        alignment=T,
        scale=s,
    )
