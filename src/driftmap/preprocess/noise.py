"""Sensor noise along a surface normal: how far a single measured point scatters around its surface (the
double-wall detector's and the attribution's noise floor, the volumetric layers' range for a depth camera)."""

from __future__ import annotations

import enum

import numpy as np
from numpy.typing import NDArray
from pydantic import ConfigDict, Field

from driftmap.config import SettingsModel
from driftmap.frame import SensorKind


class NoiseModelKind(enum.Enum):
    """How the sensor noise grows with distance."""

    QUADRATIC_DEPTH = "quadratic_depth"
    """Structured-light depth camera: ``sigma_z = a + b (z - z0)^2`` along the ray, z = depth (Nguyen et al. 2012)."""
    CONSTANT_RANGE = "constant_range"
    """LiDAR / ToF: a constant range sigma along the ray."""


class NoiseModel(SettingsModel):
    """Per-point measurement noise along the viewing ray, projected onto the surface normal."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    kind: NoiseModelKind = NoiseModelKind.QUADRATIC_DEPTH
    a_m: float = Field(0.0012, ge=0.0, description="quadratic model: constant term (m)")
    b_per_m: float = Field(0.0019, ge=0.0, description="quadratic model: coefficient of (z - z0)^2 (1/m)")
    z0_m: float = Field(0.4, description="quadratic model: depth of least noise (m)")
    range_sigma_m: float = Field(0.02, gt=0.0, description="constant model: range sigma (m)")
    min_incidence_cos: float = Field(0.3, gt=0.0, le=1.0,
                                     description="floor of |cos(ray, normal)| in the projection (grazing views are not noise-free)")

    @classmethod
    def for_sensor(cls, kind: SensorKind) -> NoiseModel:
        """Kinect-v1 quadratic model for depth cameras, 2 cm range sigma for LiDAR."""
        if kind is SensorKind.LIDAR:
            return cls(kind=NoiseModelKind.CONSTANT_RANGE)
        return cls()

    def sigma_ray_m(self, points_sensor: NDArray[np.floating]) -> NDArray[np.float64]:
        """Noise sigma along the viewing ray of sensor-frame points (optical/z axis forward for depth cameras)."""
        p = np.asarray(points_sensor, dtype=np.float64)
        if self.kind is NoiseModelKind.CONSTANT_RANGE:
            return np.full(len(p), self.range_sigma_m)
        return self.a_m + self.b_per_m * (p[:, 2] - self.z0_m) ** 2

    def sigma_normal_m(self, points_sensor: NDArray[np.floating], normals_sensor: NDArray[np.floating]) -> NDArray[np.float64]:
        """Noise sigma along each point's normal: ``sigma_ray * max(|ray . normal|, min_incidence_cos)``."""
        p = np.asarray(points_sensor, dtype=np.float64)
        ray = p / np.maximum(np.linalg.norm(p, axis=1, keepdims=True), 1e-9)
        cos = np.abs(np.einsum("ij,ij->i", ray, np.asarray(normals_sensor, dtype=np.float64)))
        return self.sigma_ray_m(p) * np.maximum(np.nan_to_num(cos, nan=1.0), self.min_incidence_cos)

    def depth_for_sigma_m(self, sigma_m: float) -> float:
        """The depth (m) beyond which the quadratic model's ray sigma exceeds ``sigma_m`` (infinity for a constant
        model within it, 0 when even the best depth is noisier)."""
        if self.kind is NoiseModelKind.CONSTANT_RANGE:
            return float("inf") if self.range_sigma_m <= sigma_m else 0.0
        if sigma_m < self.a_m or self.b_per_m == 0:
            return 0.0 if sigma_m < self.a_m else float("inf")
        return float(self.z0_m + np.sqrt((sigma_m - self.a_m) / self.b_per_m))
