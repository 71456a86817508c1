"""Point-cloud pre-processing on sensor-frame points: voxel downsampling with a full-resolution region of
interest, statistical / radius outlier removal, and normals with a per-point stability measure.

The neighbour searches, voxel grids and outlier filters are Open3D's; this module only wires them to
driftmap's types and reports how many points each step removed.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from driftmap.errors import ConfigError, GeometryError
from driftmap.frame import Frame, PointAttributes

logger = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class BoxROI:
    """Axis-aligned box ``min_m <= p <= max_m`` in the world frame (``in_world=True``) or the sensor frame."""

    min_m: tuple[float, float, float]
    max_m: tuple[float, float, float]
    in_world: bool = True

    def contains(self, points: NDArray[np.floating]) -> NDArray[np.bool_]:
        lo = np.asarray(self.min_m, dtype=np.float64)
        hi = np.asarray(self.max_m, dtype=np.float64)
        if np.any(hi < lo):
            raise ConfigError(f"BoxROI: max_m {self.max_m} is below min_m {self.min_m}")
        return np.all((points >= lo) & (points <= hi), axis=1)


@dataclass(frozen=True, slots=True)
class SphereROI:
    """Ball of ``radius_m`` around ``center_m`` in the world frame (``in_world=True``) or the sensor frame."""

    center_m: tuple[float, float, float]
    radius_m: float
    in_world: bool = True

    def contains(self, points: NDArray[np.floating]) -> NDArray[np.bool_]:
        if self.radius_m <= 0:
            raise ConfigError(f"SphereROI: radius_m must be positive, got {self.radius_m}")
        d2 = np.sum((points - np.asarray(self.center_m, dtype=np.float64)) ** 2, axis=1)
        return d2 <= self.radius_m**2


RegionOfInterest = BoxROI | SphereROI


@dataclass(frozen=True, slots=True)
class StepReport:
    """What one processing step did: points in, points out."""

    step: str
    n_in: int
    n_out: int

    @property
    def n_removed(self) -> int:
        return self.n_in - self.n_out


def roi_mask(frame: Frame, roi: RegionOfInterest) -> NDArray[np.bool_]:
    """Which of a frame's sensor-frame points lie inside ``roi`` (evaluated in the ROI's frame)."""
    pts = frame.points_world() if roi.in_world else frame.points_sensor
    return roi.contains(np.asarray(pts, dtype=np.float64))


def _to_tensor_cloud(points: NDArray[np.float32], attributes: PointAttributes) -> o3d.t.geometry.PointCloud:
    pcd = o3d.t.geometry.PointCloud(o3d.core.Tensor(np.ascontiguousarray(points)))
    if attributes.intensity is not None:
        pcd.point["intensity"] = o3d.core.Tensor(attributes.intensity.reshape(-1, 1).astype(np.float32))
    if attributes.color_rgb is not None:
        pcd.point["colors"] = o3d.core.Tensor(attributes.color_rgb.astype(np.float32) / 255.0)
    if attributes.normal_sensor is not None:
        pcd.point["normals"] = o3d.core.Tensor(np.ascontiguousarray(attributes.normal_sensor))
    return pcd


def _from_tensor_cloud(pcd: o3d.t.geometry.PointCloud, template: PointAttributes) -> tuple[NDArray[np.float32], PointAttributes]:
    points = pcd.point.positions.numpy().astype(np.float32, copy=False)
    attrs: dict[str, NDArray] = {}
    if template.intensity is not None:
        attrs["intensity"] = pcd.point["intensity"].numpy().reshape(-1)
    if template.color_rgb is not None:
        attrs["color_rgb"] = np.clip(np.rint(pcd.point["colors"].numpy() * 255.0), 0, 255).astype(np.uint8)
    if template.normal_sensor is not None:
        n = pcd.point["normals"].numpy()
        attrs["normal_sensor"] = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return points, PointAttributes(**attrs)


def voxel_downsample(
    frame: Frame, voxel_size_m: float, roi: RegionOfInterest | None = None
) -> tuple[Frame, StepReport]:
    """Voxel-grid downsampling (Open3D: one averaged point per occupied voxel, attributes averaged).

    Points inside ``roi`` are kept at full resolution; only the rest is downsampled. Per-point time
    offsets cannot be averaged meaningfully: they are kept only when no point had to be averaged.
    """
    if not voxel_size_m > 0:
        raise ConfigError(f"voxel_size_m must be positive, got {voxel_size_m}")
    n_in = frame.n_points
    if n_in == 0:
        return frame, StepReport("voxel_downsample", 0, 0)
    keep = roi_mask(frame, roi) if roi is not None else np.zeros(n_in, dtype=bool)
    rest = ~keep
    rest_attrs = frame.attributes.subset(rest)
    if rest.any():
        pcd = _to_tensor_cloud(frame.points_sensor[rest], rest_attrs).voxel_down_sample(voxel_size_m)
        down_points, down_attrs = _from_tensor_cloud(pcd, rest_attrs)
    else:  # everything is inside the ROI: nothing to downsample
        down_points, down_attrs = frame.points_sensor[rest], rest_attrs
    if roi is None:
        points, attrs = down_points, down_attrs
    else:
        kept_attrs = frame.attributes.subset(keep)
        points = np.concatenate([frame.points_sensor[keep], down_points])
        merged = {}
        for name in PointAttributes._SPEC:
            a, b = getattr(kept_attrs, name), getattr(down_attrs, name)
            if a is not None and b is not None:
                merged[name] = np.concatenate([a, b])
        attrs = PointAttributes(**merged)
    report = StepReport("voxel_downsample", n_in, len(points))
    logger.debug("frame %d: voxel %.3f m kept %d of %d points (%d inside ROI at full resolution)",
                 frame.frame_id, voxel_size_m, len(points), n_in, int(keep.sum()))
    return frame.with_points(points, attrs), report


def _legacy_cloud(points: NDArray[np.float32]) -> o3d.geometry.PointCloud:
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))


def remove_statistical_outliers(frame: Frame, nb_neighbors: int = 20, std_ratio: float = 2.0) -> tuple[Frame, StepReport]:
    """Open3D statistical outlier removal; returns the filtered frame and how many points went."""
    if frame.n_points == 0:
        return frame, StepReport("statistical_outliers", 0, 0)
    _, index = _legacy_cloud(frame.points_sensor).remove_statistical_outlier(nb_neighbors=nb_neighbors, std_ratio=std_ratio)
    return _subset(frame, np.asarray(index, dtype=np.int64), "statistical_outliers")


def remove_radius_outliers(frame: Frame, nb_points: int = 5, radius_m: float = 0.05) -> tuple[Frame, StepReport]:
    """Open3D radius outlier removal (fewer than ``nb_points`` neighbours within ``radius_m`` -> removed)."""
    if frame.n_points == 0:
        return frame, StepReport("radius_outliers", 0, 0)
    _, index = _legacy_cloud(frame.points_sensor).remove_radius_outlier(nb_points=nb_points, radius=radius_m)
    return _subset(frame, np.asarray(index, dtype=np.int64), "radius_outliers")


def _subset(frame: Frame, index: NDArray[np.int64], step: str) -> tuple[Frame, StepReport]:
    out = frame.with_points(frame.points_sensor[index], frame.attributes.subset(index))
    report = StepReport(step, frame.n_points, out.n_points)
    logger.debug("frame %d: %s removed %d of %d points", frame.frame_id, step, report.n_removed, report.n_in)
    return out, report


@dataclass(frozen=True, slots=True)
class NormalsResult:
    """Per-point normals with their stability.

    ``normals``: unit vectors oriented towards the viewpoint (NaN where too few neighbours).
    ``curvature``: surface variation ``l0 / (l0 + l1 + l2)`` of the neighbourhood covariance (0 on a plane,
    1/3 for isotropic scatter). ``confidence``: ``1 - l0 / l1`` in [0, 1]; near 0 the normal direction is
    ill-defined (edges, thin structures, sparse areas). ``n_neighbors`` (with ``radius_m``): the points within the
    radius, the point itself included, counted up to ``min_neighbors`` (all that decides a NaN normal; counting every
    neighbour of a dense map cost most of a query).
    """

    normals: NDArray[np.float32]
    curvature: NDArray[np.float32]
    confidence: NDArray[np.float32]
    n_neighbors: NDArray[np.int32] | None = None


def estimate_normals(
    points: NDArray[np.floating],
    *,
    k: int = 20,
    radius_m: float | None = None,
    viewpoint: NDArray[np.floating] | None = None,
    min_neighbors: int = 5,
    at: NDArray[np.integer] | None = None,
) -> NormalsResult:
    """Normals from the covariance of the ``k`` nearest neighbours (Open3D), oriented towards ``viewpoint``.

    The normal is the eigenvector of the smallest eigenvalue; with ``radius_m`` the search is a hybrid
    (at most ``k`` neighbours within ``radius_m``) and points with fewer than ``min_neighbors`` get a NaN
    normal and zero confidence. ``viewpoint`` defaults to the origin (the sensor, for sensor-frame points).

    ``at`` (indices into ``points``): only the normals of those points, their neighbours searched among all of
    ``points`` (the result has one row per index). The same search and covariance as Open3D's (the ``k`` nearest
    within the radius, the point itself included; fewer than 3: an identity covariance), from one SciPy
    ``cKDTree`` query, for a region whose border points only lend their neighbourhood.
    """
    if not 3 <= k <= 1000:
        raise ConfigError(f"normals: k must be in 3..1000, got {k}")
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise GeometryError(f"normals: expected (N, 3) points, got {pts.shape}")
    n = len(pts)
    if n == 0:
        empty = np.zeros((0,), np.float32)
        return NormalsResult(np.zeros((0, 3), np.float32), empty, empty)
    counts = None
    if at is not None:
        at = np.asarray(at, dtype=np.int64).ravel()
        if len(at) == 0:
            empty = np.zeros((0,), np.float32)
            return NormalsResult(np.zeros((0, 3), np.float32), empty, empty,
                                 None if radius_m is None else np.zeros(0, np.int32))
        cov, counts = _knn_covariances(pts, at, k, radius_m)
        pts = pts[at]
    else:
        pcd = _legacy_cloud(pts)
        param = (o3d.geometry.KDTreeSearchParamKNN(k) if radius_m is None
                 else o3d.geometry.KDTreeSearchParamHybrid(radius_m, k))
        pcd.estimate_covariances(param)
        cov = np.asarray(pcd.covariances)
    eigval, eigvec = np.linalg.eigh(cov)  # ascending eigenvalues, batched
    normals = eigvec[:, :, 0]
    l0, l1, l2 = eigval[:, 0].clip(min=0), eigval[:, 1].clip(min=0), eigval[:, 2].clip(min=0)
    total = l0 + l1 + l2
    with np.errstate(invalid="ignore", divide="ignore"):
        curvature = np.where(total > 0, l0 / total, 0.0)
        confidence = np.where(l1 > 0, 1.0 - l0 / l1, 0.0)
    vp = np.zeros(3) if viewpoint is None else np.asarray(viewpoint, dtype=np.float64)
    flip = np.einsum("ij,ij->i", normals, vp - pts) < 0
    normals[flip] *= -1.0
    if radius_m is not None:
        k_min = max(int(min_neighbors), 1)
        if counts is not None and k_min <= k:  # the neighbours within the radius, found up to k >= min_neighbors
            counts = np.minimum(counts, k_min).astype(np.int32)
        else:
            src = np.asarray(points, dtype=np.float64)
            dist, _ = cKDTree(src).query(pts, k=k_min, distance_upper_bound=np.nextafter(radius_m, np.inf))
            within = np.asarray(dist).reshape(len(pts), k_min) <= radius_m  # as query_ball_point: distance <= radius
            counts = within.sum(axis=1).astype(np.int32)
        sparse = counts < min_neighbors
        normals[sparse] = np.nan
        confidence[sparse] = 0.0
    return NormalsResult(normals.astype(np.float32), curvature.astype(np.float32), confidence.astype(np.float32),
                         counts if radius_m is not None else None)


def _knn_covariances(pts: NDArray[np.float64], at: NDArray[np.int64], k: int, radius_m: float | None
                     ) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Open3D's neighbourhood covariances (``estimate_covariances``: the ``k`` nearest, within ``radius_m`` when
    given, the point itself included; population covariance; identity below 3 neighbours) of ``pts[at]`` among
    ``pts``, and how many neighbours each had (at most ``k``)."""
    kk = min(int(k), len(pts))
    bound = np.inf if radius_m is None else np.nextafter(radius_m, np.inf)
    dist, idx = cKDTree(pts).query(pts[at], k=kk, distance_upper_bound=bound)
    dist, idx = dist.reshape(len(at), kk), idx.reshape(len(at), kk)
    valid = np.isfinite(dist) if radius_m is None else dist <= radius_m
    n = valid.sum(axis=1)
    # offsets from the query point (a missing neighbour: the point itself, adding nothing to the sums)
    nb = pts[np.where(valid, idx, at[:, None])] - pts[at][:, None, :]
    x, y, z = nb[..., 0], nb[..., 1], nb[..., 2]
    inv = 1.0 / np.maximum(n, 1)
    mx, my, mz = x.sum(axis=1) * inv, y.sum(axis=1) * inv, z.sum(axis=1) * inv
    cov = np.empty((len(at), 3, 3))
    cov[:, 0, 0] = (x * x).sum(axis=1) * inv - mx * mx
    cov[:, 1, 1] = (y * y).sum(axis=1) * inv - my * my
    cov[:, 2, 2] = (z * z).sum(axis=1) * inv - mz * mz
    cov[:, 0, 1] = cov[:, 1, 0] = (x * y).sum(axis=1) * inv - mx * my
    cov[:, 0, 2] = cov[:, 2, 0] = (x * z).sum(axis=1) * inv - mx * mz
    cov[:, 1, 2] = cov[:, 2, 1] = (y * z).sum(axis=1) * inv - my * mz
    cov[n < 3] = np.eye(3)
    return cov, n


def frame_with_normals(frame: Frame, *, k: int = 20, radius_m: float | None = None) -> tuple[Frame, NormalsResult]:
    """Attach sensor-frame normals (oriented towards the sensor origin) to a frame."""
    result = estimate_normals(frame.points_sensor, k=k, radius_m=radius_m)
    attrs = PointAttributes(
        intensity=frame.attributes.intensity,
        color_rgb=frame.attributes.color_rgb,
        normal_sensor=result.normals,
        time_offset_ns=frame.attributes.time_offset_ns,
    )
    return frame.with_points(frame.points_sensor, attrs), result



def process_frame(
    frame: Frame,
    *,
    voxel_size_m: float | None = None,
    roi: RegionOfInterest | None = None,
    statistical_outlier_neighbors: int | None = None,
    statistical_outlier_std_ratio: float = 2.0,
    radius_outlier_min_points: int | None = None,
    radius_outlier_radius_m: float = 0.05,
    normals_k: int | None = None,
) -> tuple[Frame, list[StepReport]]:
    """The per-frame chain: voxel downsampling (ROI kept at full resolution), outlier removal, normals.

    Each step runs only when configured; the reports say how many points each one removed.
    Keyword names match :class:`driftmap.config.PreprocessConfig` (``process_frame(f, **cfg.model_dump())``
    works after dropping unknown keys).
    """
    reports: list[StepReport] = []
    if voxel_size_m is not None:
        frame, report = voxel_downsample(frame, voxel_size_m, roi)
        reports.append(report)
    if statistical_outlier_neighbors is not None:
        frame, report = remove_statistical_outliers(frame, statistical_outlier_neighbors, statistical_outlier_std_ratio)
        reports.append(report)
    if radius_outlier_min_points is not None:
        frame, report = remove_radius_outliers(frame, radius_outlier_min_points, radius_outlier_radius_m)
        reports.append(report)
    if normals_k is not None:
        frame, _ = frame_with_normals(frame, k=normals_k)
        reports.append(StepReport("normals", frame.n_points, frame.n_points))
    return frame, reports
