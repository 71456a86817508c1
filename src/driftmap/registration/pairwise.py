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

from driftmap import geometry
from driftmap.errors import ConfigError
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


class PreparedCloud:
    """A cloud with its small_gicp preprocessing (downsampling, covariances, KD-tree) cached per voxel
    size, so a keyframe registered against many others is prepared once. ``num_threads`` serves the
    preprocessing and, by default, the registrations of this cloud (1: repeatable to the bit)."""

    def __init__(self, points_m: NDArray[np.floating], num_threads: int = 2):
        if num_threads < 1:
            raise ConfigError(f"num_threads must be >= 1, got {num_threads}")
        self.points_m = np.asarray(points_m, dtype=np.float64)
        self.num_threads = int(num_threads)
        self._levels: dict[float, tuple[small_gicp.PointCloud, small_gicp.KdTree]] = {}

    def level(self, voxel_size_m: float) -> tuple[small_gicp.PointCloud, small_gicp.KdTree]:
        if voxel_size_m not in self._levels:
            self._levels[voxel_size_m] = small_gicp.preprocess_points(
                self.points_m, downsampling_resolution=voxel_size_m, num_neighbors=10, num_threads=self.num_threads)
        return self._levels[voxel_size_m]


MIN_ALIGN_POINTS = 11
"""Clouds with fewer points (after downsampling) are not registered: small_gicp prints "point cloud is too small" on
stderr at 10 or fewer (hostile trial 17) and such a fit constrains nothing; the result does not converge."""


def register_prepared(
    target: PreparedCloud,
    source: PreparedCloud,
    init_T_target_source: NDArray[np.float64],
    *,
    voxel_size_m: float = 0.04,
    max_correspondence_m: float = 0.15,
    inlier_distance_m: float | None = None,
    max_iterations: int = 30,
    correlation_factor: float = 10.0,
    num_threads: int | None = None,
) -> RegistrationResult:
    """GICP of prepared clouds; see :func:`register`. ``num_threads``: the fewer of the two clouds' by default."""
    if num_threads is None:
        num_threads = min(target.num_threads, source.num_threads)
    tgt, tree = target.level(voxel_size_m)
    src, _ = source.level(voxel_size_m)
    if min(tgt.size(), src.size()) < MIN_ALIGN_POINTS:  # small_gicp would print a warning and fit nothing
        return RegistrationResult(np.asarray(init_T_target_source, dtype=np.float64).copy(), False, 0.0, float("inf"),
                                  np.zeros((6, 6)), 0, int(src.size()))
    result = small_gicp.align(tgt, src, tree, np.asarray(init_T_target_source, dtype=np.float64), registration_type="GICP",
                              max_correspondence_distance=max_correspondence_m, num_threads=num_threads,
                              max_iterations=max_iterations)
    T = np.array(result.T_target_source)
    inlier_d = inlier_distance_m if inlier_distance_m is not None else 1.5 * voxel_size_m
    d = nearest_distances(target, source, T, voxel_size_m)
    inliers = d <= inlier_d
    fitness = float(inliers.mean()) if len(d) else 0.0
    rmse = float(np.sqrt(np.mean(d[inliers] ** 2))) if inliers.any() else float("inf")
    H = reorder_6x6(np.array(result.H), TangentOrder.ROTATION_TRANSLATION, TangentOrder.TRANSLATION_ROTATION)
    H = 0.5 * (H + H.T)
    # variance-factor calibration: the Hessian assumes GICP's unit-less plane covariances; the residual
    # cost per degree of freedom at the solution says how large the real noise is relative to that
    dof = max(int(result.num_inliers) - 6, 1)
    variance_factor = max(float(result.error), 1e-12) / dof
    information = H / variance_factor / correlation_factor
    information = 0.5 * (information + information.T)
    return RegistrationResult(T, bool(result.converged), fitness, rmse, information, int(result.iterations), len(d))


def nearest_distances(target: PreparedCloud, source: PreparedCloud, T_target_source: NDArray[np.float64],
                      voxel_size_m: float) -> NDArray[np.float64]:
    """Distance from each point of ``source`` (downsampled at ``voxel_size_m``), moved by ``T_target_source``, to its
    nearest neighbour in ``target`` at the same level (m): the residuals behind a registration's fitness."""
    _, tree = target.level(voxel_size_m)
    src, _ = source.level(voxel_size_m)
    src_pts = np.asarray(src.points())[:, :3]
    if len(src_pts) == 0:
        return np.zeros(0)
    T = np.asarray(T_target_source, dtype=np.float64)
    _, d2 = tree.batch_nearest_neighbor_search(src_pts @ T[:3, :3].T + T[:3, 3])
    return np.sqrt(np.asarray(d2))


def register(
    target_m: NDArray[np.floating],
    source_m: NDArray[np.floating],
    init_T_target_source: NDArray[np.float64],
    **options: float | int | None,
) -> RegistrationResult:
    """Align ``source`` to ``target`` with GICP, starting from ``init_T_target_source``.

    Information: the GICP Hessian ``H`` at the solution divided by the variance factor ``cost / dof`` (so
    it reflects the residuals actually observed) and by ``correlation_factor`` because neighbouring points'
    residuals are not independent (a plain Hessian makes edges absurdly confident). Options as
    :func:`register_prepared` (``voxel_size_m``, ``max_correspondence_m``, ``inlier_distance_m``,
    ``max_iterations``, ``correlation_factor``, ``num_threads``).
    """
    threads = int(options.get("num_threads") or 2)
    return register_prepared(PreparedCloud(target_m, threads), PreparedCloud(source_m, threads), init_T_target_source, **options)


def relative_pose(T_world_a: NDArray[np.float64], T_world_b: NDArray[np.float64]) -> NDArray[np.float64]:
    """``T_a_b = inv(T_world_a) @ T_world_b``."""
    return geometry.invert(T_world_a) @ T_world_b
