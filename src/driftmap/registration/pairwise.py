"""Pairwise registration (small_gicp GICP) returning a result that carries its own quality and an
information matrix derived from the registration's Hessian -- never an identity.

Ordering: driftmap's 6x6 information matrices are in [translation(3), rotation(3)] order (the pose graph's
convention); small_gicp's Hessian is [rotation, translation] and is permuted here.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import small_gicp
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from driftmap import geometry
from driftmap.posegraph import TangentOrder, reorder_6x6

logger = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class RegistrationResult:
    """``T_target_source`` maps source points into the target frame."""

    T_target_source: NDArray[np.float64]
    converged: bool
    fitness: float
    """Fraction of source points with a target neighbour within ``inlier_distance_m`` after alignment."""
    rmse_m: float
    """RMS distance of those inliers to their nearest target point."""
    information_6x6: NDArray[np.float64]
    """[t, r] order; GICP Hessian scaled by the residual variance and de-correlated (see ``register``)."""
    iterations: int
    n_source: int

    def describe(self) -> str:
        t = np.linalg.norm(self.T_target_source[:3, 3])
        return (f"fitness {self.fitness:.2f}, rmse {self.rmse_m * 100:.1f} cm, converged {self.converged}, "
                f"|t| {t:.3f} m, iterations {self.iterations}")


def downsample(points: NDArray[np.floating], voxel_size_m: float) -> NDArray[np.float64]:
    """small_gicp's voxel-grid sampling (float64 output)."""
    pcd = small_gicp.voxelgrid_sampling(np.asarray(points, dtype=np.float64), voxel_size_m)
    return np.asarray(pcd.points())[:, :3]


def register(
    target_m: NDArray[np.floating],
    source_m: NDArray[np.floating],
    init_T_target_source: NDArray[np.float64],
    *,
    voxel_size_m: float = 0.04,
    max_correspondence_m: float = 0.15,
    inlier_distance_m: float | None = None,
    max_iterations: int = 30,
    correlation_factor: float = 10.0,
    num_threads: int = 2,
) -> RegistrationResult:
    """Align ``source`` to ``target`` with GICP, starting from ``init_T_target_source``.

    Information: the GICP Hessian ``H`` at the solution divided by the variance factor ``cost / dof`` (so
    it reflects the residuals actually observed) and by ``correlation_factor`` because neighbouring points'
    residuals are not independent (a plain Hessian makes edges absurdly confident).
    """
    target = np.asarray(target_m, dtype=np.float64)
    source = np.asarray(source_m, dtype=np.float64)
    result = small_gicp.align(
        target, source, np.asarray(init_T_target_source, dtype=np.float64), registration_type="GICP",
        downsampling_resolution=voxel_size_m, max_correspondence_distance=max_correspondence_m,
        num_threads=num_threads, max_iterations=max_iterations,
    )
    T = np.array(result.T_target_source)
    inlier_d = inlier_distance_m if inlier_distance_m is not None else 1.5 * voxel_size_m
    tgt = downsample(target, voxel_size_m)
    src = downsample(source, voxel_size_m)
    d, _ = cKDTree(tgt).query(src @ T[:3, :3].T + T[:3, 3], distance_upper_bound=inlier_d)
    inliers = np.isfinite(d)
    fitness = float(inliers.mean()) if len(src) else 0.0
    rmse = float(np.sqrt(np.mean(d[inliers] ** 2))) if inliers.any() else float("inf")
    H = reorder_6x6(np.array(result.H), TangentOrder.ROTATION_TRANSLATION, TangentOrder.TRANSLATION_ROTATION)
    H = 0.5 * (H + H.T)
    # variance-factor calibration: the Hessian assumes GICP's unit-less plane covariances; the residual
    # cost per degree of freedom at the solution says how large the real noise is relative to that
    dof = max(int(result.num_inliers) - 6, 1)
    variance_factor = max(float(result.error), 1e-12) / dof
    information = H / variance_factor / correlation_factor
    information = 0.5 * (information + information.T)
    return RegistrationResult(T, bool(result.converged), fitness, rmse, information, int(result.iterations), len(src))


def relative_pose(T_world_a: NDArray[np.float64], T_world_b: NDArray[np.float64]) -> NDArray[np.float64]:
    """``T_a_b = inv(T_world_a) @ T_world_b``."""
    return geometry.invert(T_world_a) @ T_world_b
