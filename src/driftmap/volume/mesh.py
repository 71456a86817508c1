"""The TSDF's triangle mesh, extracted by Open3D's marching cubes.

driftmap's TSDF (:mod:`driftmap.volume.kernels`) is Open3D's, summed in integers so that frames can be taken out;
its values are loaded into an Open3D ``VoxelBlockGrid`` (the blocks that hold an observation) and the library
extracts the mesh, as it would from a grid it had integrated itself.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
import open3d.core as o3c

from driftmap.config import MapConfig
from driftmap.kernels.volume import TSDF_QUANTUM
from driftmap.volume.grid import BLOCK_RESOLUTION
from driftmap.volume.protocol import Layers

DEFAULT_WEIGHT_THRESHOLD = float(MapConfig.model_fields["mesh_weight_threshold"].default)
"""Marching cubes uses samples observed at least this many times (Open3D's default for ``extract_triangle_mesh``;
``map.mesh_weight_threshold``)."""


def to_voxel_block_grid(layers: Layers) -> o3d.t.geometry.VoxelBlockGrid:
    """An Open3D ``VoxelBlockGrid`` (``tsdf``, ``weight``; 8^3 blocks) holding the layers' TSDF: the blocks with an
    observation, each sample's TSDF and its observation count as weight."""
    g = layers.grid
    R = BLOCK_RESOLUTION
    count = layers.arrays.tsdf_count.reshape(g.shape)
    nb = tuple(s // R for s in g.shape)
    # (bx, by, bz, x, y, z) view of the grid: which blocks hold an observation
    blocked = count.reshape(nb[0], R, nb[1], R, nb[2], R)
    active = np.argwhere(blocked.max(axis=(1, 3, 5)) > 0)
    vbg = o3d.t.geometry.VoxelBlockGrid(attr_names=("tsdf", "weight"), attr_dtypes=(o3c.float32, o3c.float32),
                                        attr_channels=((1), (1)), voxel_size=g.voxel_size_m, block_resolution=R,
                                        block_count=max(len(active), 1), device=o3c.Device("CPU:0"))
    if len(active) == 0:
        return vbg
    keys = active + np.asarray(g.origin_index, dtype=np.int64) // R
    buf, _ = vbg.hashmap().activate(o3c.Tensor(keys.astype(np.int32)))
    tsdf_sum = layers.arrays.tsdf_sum.reshape(nb[0], R, nb[1], R, nb[2], R)
    counts = blocked
    bx, by, bz = active.T
    # per block (x, y, z) -> Open3D's (z, y, x) layout inside a block
    block_counts = counts[bx, :, by, :, bz, :].astype(np.float32)           # (M, R, R, R) as (x, y, z)
    block_sums = tsdf_sum[bx, :, by, :, bz, :]
    with np.errstate(invalid="ignore", divide="ignore"):
        block_tsdf = np.where(block_counts > 0, block_sums / TSDF_QUANTUM / np.maximum(block_counts, 1), 0.0).astype(np.float32)
    tsdf_attr = vbg.attribute("tsdf").numpy()
    weight_attr = vbg.attribute("weight").numpy()
    slots = buf.numpy().astype(np.int64)
    tsdf_attr[slots] = np.transpose(block_tsdf, (0, 3, 2, 1))[..., None]
    weight_attr[slots] = np.transpose(block_counts, (0, 3, 2, 1))[..., None]
    vbg.attribute("tsdf")[:] = o3c.Tensor(tsdf_attr)
    vbg.attribute("weight")[:] = o3c.Tensor(weight_attr)
    return vbg


def triangle_mesh(layers: Layers, weight_threshold: float = DEFAULT_WEIGHT_THRESHOLD) -> o3d.geometry.TriangleMesh:
    """The TSDF's zero surface as a triangle mesh (world frame, metres); empty when nothing was observed."""
    vbg = to_voxel_block_grid(layers)
    if vbg.hashmap().size() == 0 or not np.any(layers.arrays.tsdf_count >= weight_threshold):
        return o3d.geometry.TriangleMesh()
    try:
        return vbg.extract_triangle_mesh(weight_threshold=weight_threshold).to_legacy()
    except RuntimeError as exc:  # Open3D fails to colour a mesh without a triangle instead of returning it empty
        if "shape {0}" not in str(exc) and "No block is touched" not in str(exc):  # else: nothing to mesh
            raise
        return o3d.geometry.TriangleMesh()
