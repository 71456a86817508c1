"""The settings of the decisions (thresholds with units) and the hash that names them with the volumetric settings.

A query may override its own thresholds (``min_points``, ``max_normal_spread_deg``, ``max_flatness_m``,
``unknown_is``); everything else is here. (A ``[decide]`` table of :class:`driftmap.config.DriftmapConfig` would
make these settable from a config file; until then the library takes a :class:`DecideConfig`.)
"""

from __future__ import annotations

import hashlib
import json

from pydantic import ConfigDict, Field

from driftmap.config import SettingsModel, VolumeConfig


class DecideConfig(SettingsModel):
    """Thresholds of the five query kinds and of the uncertainty."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    sweep_step_m: float | None = Field(None, gt=0.0, description="collision: the footprint is placed every this many metres along the path; None: half a voxel")
    grasp_min_points: int = Field(30, ge=3, description="grasp: fewer map points than this inside the ROI is too_few_points")
    grasp_max_normal_spread_deg: float = Field(20.0, ge=0.0, le=90.0, description="grasp: the normal is unstable when the 90th percentile of the angles between the points' normals and the dominant normal exceeds this (deg)")
    normal_radius_m: float = Field(0.03, gt=0.0, description="grasp and foothold: a point's normal is fitted to its neighbours within this radius (m)")
    normal_max_neighbors: int = Field(64, ge=5, le=1000, description="grasp and foothold: at most this many neighbours per normal")
    normal_margin_m: float = Field(0.03, ge=0.0, description="grasp and foothold: points up to this far outside the region lend their neighbourhood to the normals of the points inside")
    foothold_min_points: int = Field(30, ge=3, description="foothold: fewer map points than this in the patch is too_few_points")
    foothold_max_flatness_m: float = Field(0.02, gt=0.0, description="foothold: RMS distance of the patch's points from their plane above which the patch is uneven (m)")
    spread_radius_m: float = Field(0.05, gt=0.0, description="uncertainty: the map points within this radius of a decision's evidence point are grouped by frame (m)")
    spread_min_points: int = Field(5, ge=1, description="uncertainty: a frame takes part in the spread with at least this many points near the evidence")
    double_wall_reach_m: float = Field(0.3, ge=0.0, description="a double wall (diagnose) whose centre lies within this distance of a query's region is in reach (m)")
    range_limited_points: bool = Field(True, description="grasp, foothold, uncertainty: use only points within the volume's max range of their sensor (where the depth noise stays below 0.4 voxel)")


def settings_hash(volume: VolumeConfig, decide: DecideConfig) -> str:
    """16 hex digits of the SHA-256 of the resolved volumetric settings and the decision settings (canonical JSON):
    two decision sets with the same hash were made with the same settings."""
    payload = {"volume": volume.model_dump(mode="json"), "decide": decide.model_dump(mode="json")}
    text = json.dumps(payload, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]
