"""How large a sensor's scene is, measured over many frames, and the length scales derived from it.

KISS-ICP ties every length to the sensor's reach (voxel = max range / 100), and the diagnostics' voxel sizes and
visit gaps depend on it too. A single frame is a poor witness: a LiDAR log may start facing a wall, or standing
still in a corner for its first 23 scans (the real Livox log in ../shared/datasets/balm-lidar-0-79). The reach is
therefore the **median over frames spread across the log** of each scan's 99th range percentile
(:func:`scene_reach`), and the scales derived from it vary continuously with it:

* :func:`lidar_odometry_scale`: ``min(1, max(0.05, reach / 25 m))`` times the outdoor (100 m sensor) KISS-ICP
  lengths; a scene reaching 25 m or more keeps them;
* :func:`diagnostics_scale`: ``min(5, max(1, reach / 5 m))`` times the indoor (depth camera) diagnostic lengths;
  a scene within 5 m keeps them, one reaching 25 m or more gets the outdoor ones (five times larger, ten for the
  travel between visits).
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from driftmap.frame import Frame, SensorKind

logger = logging.getLogger(__name__)

LIDAR_OUTDOOR_P99_RANGE_M = 25.0
"""Scans reaching this far (99th range percentile) keep the outdoor LiDAR odometry defaults; shorter ones scale them."""
LIDAR_MIN_SCENE_SCALE = 0.05
"""The smallest scale applied to the LiDAR odometry defaults (5 cm voxels)."""
INDOOR_REACH_M = 5.0
"""Scenes reaching this far or less are diagnosed with the indoor lengths; each metre more scales them up."""
OUTDOOR_DIAGNOSTICS_SCALE = LIDAR_OUTDOOR_P99_RANGE_M / INDOOR_REACH_M
"""The outdoor diagnostic lengths are this many times the indoor ones (reached at ``LIDAR_OUTDOOR_P99_RANGE_M``)."""
SAMPLE_FRAMES = 15
"""Frames :func:`sample_positions` picks across a log to measure its reach."""


def scan_reach_m(frame: Frame) -> float | None:
    """How far a scan reaches: the 99th percentile of its points' ranges (``None`` without a finite point)."""
    if frame.n_points == 0:
        return None
    ranges = np.linalg.norm(np.asarray(frame.points_sensor, dtype=np.float64), axis=1)
    ranges = ranges[np.isfinite(ranges) & (ranges > 0)]
    return float(np.percentile(ranges, 99)) if len(ranges) else None


@dataclass(frozen=True)
class SceneReach:
    """The reach of a scene: the median of ``per_frame_m`` (each frame's 99th range percentile)."""

    reach_m: float
    frame_ids: tuple[int, ...]
    per_frame_m: tuple[float, ...]

    @property
    def n_frames(self) -> int:
        return len(self.frame_ids)

    def describe(self) -> str:
        lo, hi = min(self.per_frame_m), max(self.per_frame_m)
        return (f"{self.reach_m:.1f} m (median of {self.n_frames} frames' 99th range percentiles, {lo:.1f}..{hi:.1f} m; "
                f"frames {', '.join(map(str, self.frame_ids[:6]))}{' ...' if self.n_frames > 6 else ''})")

    def to_json(self) -> dict[str, object]:
        return {"reach_m": self.reach_m, "frame_ids": list(self.frame_ids), "per_frame_m": list(self.per_frame_m)}


def scene_reach(frames: Iterable[Frame]) -> SceneReach | None:
    """:class:`SceneReach` of ``frames`` (LiDAR or not), or None when none has a point."""
    ids, reaches = [], []
    for frame in frames:
        reach = scan_reach_m(frame)
        if reach is not None:
            ids.append(frame.frame_id)
            reaches.append(reach)
    if not reaches:
        return None
    return SceneReach(float(np.median(reaches)), tuple(ids), tuple(reaches))


def sample_positions(n: int, k: int = SAMPLE_FRAMES) -> list[int]:
    """Up to ``k`` positions spread evenly over ``0 .. n-1`` (both ends included)."""
    if n <= 0:
        return []
    return sorted({int(round(x)) for x in np.linspace(0, n - 1, min(n, k))})


def lidar_odometry_scale(reach_m: float) -> float:
    """``min(1, max(0.05, reach / 25 m))``: the factor on the outdoor LiDAR odometry lengths."""
    return min(1.0, max(LIDAR_MIN_SCENE_SCALE, reach_m / LIDAR_OUTDOOR_P99_RANGE_M))


def diagnostics_scale(reach_m: float) -> float:
    """``min(5, max(1, reach / 5 m))``: the factor on the indoor diagnostic lengths."""
    return min(OUTDOOR_DIAGNOSTICS_SCALE, max(1.0, reach_m / INDOOR_REACH_M))


def lidar_frames(frames: Iterable[Frame]) -> list[Frame]:
    return [f for f in frames if f.sensor_kind is SensorKind.LIDAR]
