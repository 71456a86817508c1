"""What the map view returns: how frames moved between revisions (:class:`ChangeSet`), query results, the fused
map with per-voxel provenance, and the argument checks its queries share."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from driftmap import geometry
from driftmap.errors import ConfigError


@dataclass(frozen=True, slots=True)
class FrameChange:
    """How one frame moved between two revisions, and the world-space region it touched."""

    frame_id: int
    stamp_ns: int
    translation_m: float
    rotation_deg: float
    box_before_m: NDArray[np.float32]
    """(2, 3): min and max corner of the frame's points before."""
    box_after_m: NDArray[np.float32]
    voxels_before: NDArray[np.int64] | None = None
    """Unique integer voxel keys ``floor(p / voxel_size_m)`` of the frame's points before (if asked)."""
    voxels_after: NDArray[np.int64] | None = None


@dataclass(frozen=True)
class ChangeSet:
    """The frames a revision change moved; a navigation stack refreshes only these regions."""

    from_revision: int
    to_revision: int
    changes: list[FrameChange]
    voxel_size_m: float | None = None

    @property
    def frame_ids(self) -> NDArray[np.int64]:
        return np.array([c.frame_id for c in self.changes], dtype=np.int64)

    @property
    def max_translation_m(self) -> float:
        return max((c.translation_m for c in self.changes), default=0.0)

    def boxes_m(self) -> NDArray[np.float32]:
        """(2K, 2, 3) every before and after box."""
        if not self.changes:
            return np.zeros((0, 2, 3), np.float32)
        return np.stack([b for c in self.changes for b in (c.box_before_m, c.box_after_m)])

    def voxels(self) -> NDArray[np.int64]:
        """Union of all before and after voxel keys (needs ``voxel_size_m`` at apply time)."""
        if self.voxel_size_m is None:
            raise ConfigError("voxel keys were not computed: pass voxel_size_m to apply()")
        keys = [k for c in self.changes for k in (c.voxels_before, c.voxels_after) if k is not None and len(k)]
        return np.unique(np.concatenate(keys), axis=0) if keys else np.zeros((0, 3), np.int64)


@dataclass(frozen=True, slots=True)
class QueryResult:
    points_world: NDArray[np.float32]
    frame_ids: NDArray[np.int64]


@dataclass(frozen=True, slots=True)
class Nearest:
    distance_m: float
    point_world: NDArray[np.float32]
    frame_id: int


@dataclass(frozen=True)
class FusedMap:
    """A voxel-deduplicated map with per-voxel provenance.

    ``points_world[i]`` is the centroid of voxel i (or a full-resolution ROI point); the frames that
    contributed to it are ``provenance_frame_ids[provenance_offsets[i]:provenance_offsets[i + 1]]``.
    """

    points_world: NDArray[np.float32]
    provenance_offsets: NDArray[np.int64]
    provenance_frame_ids: NDArray[np.int64]
    voxel_size_m: float | None
    n_roi_points: int

    def frames_of(self, index: int) -> NDArray[np.int64]:
        return self.provenance_frame_ids[self.provenance_offsets[index] : self.provenance_offsets[index + 1]]

    def n_frames_per_point(self) -> NDArray[np.int64]:
        return np.diff(self.provenance_offsets)


def displacements(T_a: NDArray[np.float64], T_b: NDArray[np.float64]) -> tuple[NDArray[np.float64], ...]:
    """Per pose pair of two (K, 4, 4) stacks: distance of the origins (m) and relative rotation angle (deg),
    computed as :meth:`PoseLedger.diff` does (one numpy pass, not a Python call per frame)."""
    translation_m = np.linalg.norm(T_a[:, :3, 3] - T_b[:, :3, 3], axis=1)
    return translation_m, np.degrees(geometry.relative_rotation_angle_rad(T_a, T_b))


def vec3_arg(method: str, name: str, value: Sequence[float]) -> NDArray[np.float64]:
    """A world position or corner as a fresh float64 (3,) array."""
    out = np.array(value, dtype=np.float64)
    if out.shape != (3,):
        raise ConfigError(f"{method}: {name} must be 3 numbers (x, y, z), got shape {out.shape}")
    if np.isnan(out).any():
        raise ConfigError(f"{method}: {name} has a NaN coordinate: {out.tolist()}")
    return out


def z_range_arg(method: str, z_range_m: tuple[float, float]) -> tuple[float, float]:
    """A height band ``(lo, hi)`` in metres (world z, inclusive)."""
    try:
        z_lo, z_hi = (float(v) for v in z_range_m)
    except (TypeError, ValueError):
        raise ConfigError(f"{method}: z_range_m must be two numbers (lo, hi), got {z_range_m!r}") from None
    if not z_lo <= z_hi:
        raise ConfigError(f"{method}: z_range_m must have lo <= hi, got {z_range_m!r}")
    return z_lo, z_hi
