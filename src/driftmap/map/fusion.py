"""Fuse frames into one world-frame cloud with per-point provenance (which frame each point came from).

This is the simple batch fusion used by the demo and the tests; the incremental, revision-aware map view
lives with the store.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from driftmap import geometry
from driftmap.errors import ConfigError, DriftmapError, EmptyExportError, OutputWriteError, SourceError
from driftmap.frame import Frame
from driftmap.sources.cloud_headers import check_cloud_file
from driftmap.store.guards import atomic_output
from driftmap.voxels import first_point_per_voxel

logger = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class FusedCloud:
    """World-frame points and, per point, the ``frame_id`` that observed it."""

    points_world: NDArray[np.float32]
    frame_ids: NDArray[np.int64]

    def __len__(self) -> int:
        return int(self.points_world.shape[0])

    def voxel_downsample(self, voxel_size_m: float) -> FusedCloud:
        """One point per occupied voxel (the first one seen, so provenance stays a real frame id)."""
        if not voxel_size_m > 0:
            raise ConfigError(f"voxel_size_m must be positive, got {voxel_size_m}")
        if len(self) == 0:
            return self
        first = first_point_per_voxel(self.points_world, voxel_size_m)
        return FusedCloud(self.points_world[first], self.frame_ids[first])


def fuse(frames: Iterable[Frame], poses: Mapping[int, NDArray[np.float64]] | None = None) -> FusedCloud:
    """Transform every frame to the world with its own pose, or with ``poses[frame_id]`` when given."""
    chunks: list[NDArray[np.float32]] = []
    ids: list[NDArray[np.int64]] = []
    for frame in frames:
        T = frame.T_world_sensor if poses is None else poses[frame.frame_id]
        chunks.append(geometry.transform_points(T, frame.points_sensor))
        ids.append(np.full(frame.n_points, frame.frame_id, dtype=np.int64))
    if not chunks:
        return FusedCloud(np.zeros((0, 3), np.float32), np.zeros(0, np.int64))
    return FusedCloud(np.concatenate(chunks), np.concatenate(ids))


def write_cloud(path: str | Path, points_world: NDArray[np.floating], colors_rgb01: NDArray[np.floating] | None = None) -> Path:
    """Write a PLY or PCD file with Open3D (binary, readable by CloudCompare).

    Checked first: the suffix, at least one point (Open3D cannot write an empty cloud:
    :class:`~driftmap.errors.EmptyExportError`), and a path outside every store folder
    (:func:`driftmap.store.refuse_inside_store`). The file is written under a temporary name in the same folder and
    renamed into place when complete (:func:`driftmap.store.atomic_output`): a failed write leaves no partial file and
    an existing file survives a failed overwrite."""
    path = Path(path)
    if path.suffix.lower() not in (".ply", ".pcd"):
        raise ConfigError(f"{path}: map export supports .ply and .pcd")
    points = np.asarray(points_world, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ConfigError(f"{path}: points must be an (N, 3) array, got shape {points.shape}")
    if len(points) == 0:
        raise EmptyExportError(f"{path}: no points to write; nothing written")
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    if colors_rgb01 is not None:
        pcd.colors = o3d.utility.Vector3dVector(np.asarray(colors_rgb01, dtype=np.float64))
    with atomic_output(path, "map export path") as tmp:
        if not o3d.io.write_point_cloud(str(tmp), pcd, write_ascii=False, compressed=False):
            raise DriftmapError(f"{path}: Open3D could not write the point cloud")
        # Open3D reports success when its writes fail on a full disk (and reads a truncated file back at full
        # length): the written header is checked against the bytes on disk before the file is renamed into place,
        # so a truncated map never appears under the requested name
        try:
            written = check_cloud_file(tmp).n_points
        except SourceError as exc:
            written, why = -1, str(exc)
        else:
            why = f"{written} of {len(pcd.points)} points"
        if written != len(pcd.points):
            raise OutputWriteError(f"{path}: the map was not written completely ({why}; a full disk?); nothing was "
                                   f"written under that name", path=path, errno=None)
    logger.info("wrote %d points to %s", len(pcd.points), path)
    return path
