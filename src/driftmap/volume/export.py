"""Exports of the volumetric layers for other tools: the TSDF mesh, an OctoMap ``.bt`` and a 2-D occupancy map.

* :func:`write_mesh` -- the TSDF's triangle mesh (:meth:`VolumeLayers.mesh`, Open3D marching cubes) as PLY (binary),
  OBJ (text, no material file) or STL (binary, per-triangle normals), world frame, metres. Any mesh viewer
  (MeshLab, Blender, CloudCompare) opens it.
* :func:`write_octomap` -- an OctoMap binary tree (``.bt``, OctoMap 1.x ``OcTree`` binary format): the octree of the
  layers' voxel size with every observed voxel; a ``.bt`` keeps the maximum-likelihood state only (each node
  occupied or free, the log-odds are not stored), never-observed space stays absent (unknown). ``octovis``,
  ``octomap_server`` (``octomap_server_node map.bt``) and every OctoMap-based planner read it.
* :func:`write_grid2d` -- a 2-D occupancy map in the ROS ``map_server`` format (ROS 1 ``map_server`` and ROS 2
  ``nav2_map_server``): a YAML file naming a binary PGM next to it. A cell is the column of voxels above it whose
  centres lie in a height band: occupied if any of them is occupied, else free if any is free, else unknown.

:func:`occupancy_grid2d` gives that 2-D grid in memory (the Foxglove export draws it as a ``foxglove.Grid``).
Every writer checks its input first (a wrong suffix, an empty mesh, a band that selects nothing: nothing is
written), refuses a path inside a frame-store folder (:func:`driftmap.store.refuse_inside_store`) and writes
atomically (a temporary file in the same folder renamed into place with ``os.replace``: a failed export leaves no
partial file and an existing file survives a failed overwrite).
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from driftmap.errors import ConfigError, EmptyExportError
from driftmap.store.guards import atomic_output, refuse_inside_store

if TYPE_CHECKING:
    import open3d as o3d

    from driftmap.volume.layers import VolumeLayers

logger = logging.getLogger(__name__)

MESH_SUFFIXES = (".ply", ".obj", ".stl")
"""Mesh formats :func:`write_mesh` writes (Open3D picks the format by the suffix)."""
OCTOMAP_SUFFIX = ".bt"
GRID2D_SUFFIXES = (".yaml", ".yml")

# ---- the 2-D map's cell values and files
GRID_FREE, GRID_OCCUPIED, GRID_UNKNOWN = np.int8(0), np.int8(100), np.int8(-1)
"""Cell values of :class:`Grid2D` (those of a ROS ``nav_msgs/OccupancyGrid``: 0 free, 100 occupied, -1 unknown)."""
PGM_FREE, PGM_OCCUPIED, PGM_UNKNOWN = 254, 0, 205
"""PGM grey values of the three states, as ``map_saver`` writes them in trinary mode."""
OCCUPIED_THRESH = 0.65
"""``occupied_thresh`` of the YAML: ``map_server`` reads a pixel as occupied when ``(255 - value) / 255`` exceeds it
(``map_saver``'s value; 0 -> 1.0)."""
FREE_THRESH = 0.196
"""``free_thresh`` of the YAML: a pixel is free when ``(255 - value) / 255`` is below it (ROS ``map_saver``'s value:
254 -> 0.0039 is free, 205 -> 0.19608 is not, so it stays unknown in trinary mode)."""

OCTOMAP_KEY_HALF_RANGE = 32768
"""OctoMap keys are 16 bit: lattice voxels ``-32768 .. 32767`` per axis (about +-655 m at 2 cm)."""
_OCTOMAP_CHUNK = 200_000
"""Voxels handed to pyoctomap per call (the rows it iterates are views of one copy of the centres)."""


# ------------------------------------------------------------------------------------------------ summaries
@dataclass(frozen=True)
class MeshExportSummary:
    """What :func:`write_mesh` wrote."""

    path: Path
    n_vertices: int
    n_triangles: int
    bounds_min_m: tuple[float, float, float]
    bounds_max_m: tuple[float, float, float]
    bytes: int


@dataclass(frozen=True)
class OctomapExportSummary:
    """What :func:`write_octomap` wrote: the observed voxels by state and the tree after pruning."""

    path: Path
    resolution_m: float
    n_occupied: int
    n_free: int
    n_tree_nodes: int
    """nodes of the pruned maximum-likelihood tree (inner nodes included), as the file holds them"""
    n_leaf_nodes: int
    metric_min_m: tuple[float, float, float]
    metric_max_m: tuple[float, float, float]
    bytes: int


@dataclass(frozen=True)
class Grid2D:
    """A 2-D occupancy grid of the layers: ``cells[ix, iy]`` is :data:`GRID_OCCUPIED` / :data:`GRID_FREE` /
    :data:`GRID_UNKNOWN` for the column of voxels ``ix, iy`` of the layers' grid whose centres lie in ``band_m``.

    Cell ``(ix, iy)`` covers ``origin_xy_m + [ix, ix + 1) x [iy, iy + 1) * resolution_m`` (world frame)."""

    cells: NDArray[np.int8]
    resolution_m: float
    origin_xy_m: tuple[float, float]
    band_m: tuple[float, float]
    layer_z_m: NDArray[np.float64]
    """centres (z) of the voxel layers inside the band"""

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.cells.shape[0]), int(self.cells.shape[1])

    def counts(self) -> dict[str, int]:
        return {"occupied": int(np.sum(self.cells == GRID_OCCUPIED)), "free": int(np.sum(self.cells == GRID_FREE)),
                "unknown": int(np.sum(self.cells == GRID_UNKNOWN))}

    def pgm_image(self) -> NDArray[np.uint8]:
        """The map as the PGM holds it: ``(height = ny, width = nx)`` grey values, image row 0 at the largest y
        (``map_server`` puts the image's bottom-left pixel at ``origin``)."""
        grey = np.full(self.cells.shape, PGM_UNKNOWN, dtype=np.uint8)
        grey[self.cells == GRID_FREE] = PGM_FREE
        grey[self.cells == GRID_OCCUPIED] = PGM_OCCUPIED
        return np.ascontiguousarray(grey.T[::-1])


@dataclass(frozen=True)
class Grid2DExportSummary:
    """What :func:`write_grid2d` wrote."""

    yaml_path: Path
    pgm_path: Path
    width: int
    height: int
    resolution_m: float
    origin_xy_m: tuple[float, float]
    band_m: tuple[float, float]
    n_layers: int
    n_occupied: int
    n_free: int
    n_unknown: int


# ------------------------------------------------------------------------------------------------------ mesh
def prepare_mesh(layers: VolumeLayers, path: str | Path, *, weight_threshold: float | None = None,
                 flag: str = "--mesh") -> o3d.geometry.TriangleMesh:
    """Everything :func:`write_mesh` checks before it writes, and the mesh it would write: a caller writing several
    files checks them all first (``export`` writes nothing when one output would fail). Same errors."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise ConfigError(f"{flag} {path}: a mesh is written as {', '.join(MESH_SUFFIXES)} "
                          f"(got {suffix or 'no suffix'!r})")
    refuse_inside_store(path, flag)
    mesh = tsdf_mesh(layers, weight_threshold)
    if len(mesh.triangles) == 0:
        counts = layers.arrays.tsdf_count
        threshold = _weight_threshold(weight_threshold)
        raise EmptyExportError(f"{flag} {path}: the TSDF of revision {layers.revision} has no surface to mesh "
                               f"({int(np.count_nonzero(counts))} voxels with a TSDF sample, "
                               f"{int(np.count_nonzero(counts >= threshold))} of them observed at least {threshold:g} "
                               f"times; {layers.grid.describe()}); nothing written. A log of few frames: lower the "
                               f"weight threshold (export --mesh-weight-threshold, or map.mesh_weight_threshold in a "
                               f"config file or DRIFTMAP_MAP__MESH_WEIGHT_THRESHOLD; 1 meshes every observed voxel)")
    return mesh


def write_mesh(layers: VolumeLayers, path: str | Path, *, weight_threshold: float | None = None,
               flag: str = "--mesh", mesh: o3d.geometry.TriangleMesh | None = None) -> MeshExportSummary:
    """Write the TSDF's triangle mesh (:meth:`VolumeLayers.mesh`) to ``path``: ``.ply`` (binary PLY with vertex
    normals), ``.obj`` (Wavefront OBJ text with vertex normals, no material file) or ``.stl`` (binary STL: triangles
    with their normals, no shared vertices). World frame, metres.

    ``flag`` names the option in errors. Raises :class:`~driftmap.errors.ConfigError` for another suffix,
    :class:`~driftmap.errors.OutputInsideStoreError` for a path inside a store folder,
    :class:`~driftmap.errors.EmptyExportError` when the mesh has no triangle (nothing is written) and
    :class:`~driftmap.errors.OutputWriteError` naming ``path`` when the file cannot be written. ``mesh``: the one
    :func:`prepare_mesh` returned for ``layers`` and ``path`` (checked already; not computed again)."""
    import open3d as o3d

    path = Path(path)
    suffix = path.suffix.lower()
    if mesh is None:
        mesh = prepare_mesh(layers, path, weight_threshold=weight_threshold, flag=flag)
    n_tri, n_vert = len(mesh.triangles), len(mesh.vertices)
    if suffix == ".stl":
        mesh.compute_triangle_normals()  # Open3D's STL writer needs them
    with atomic_output(path, flag, guard=False) as tmp:
        if not o3d.io.write_triangle_mesh(str(tmp), mesh, write_ascii=False, compressed=False, print_progress=False):
            raise OSError(f"Open3D could not write a {suffix} mesh")
    lo, hi = mesh.get_min_bound(), mesh.get_max_bound()
    summary = MeshExportSummary(path, n_vert, n_tri, _triple(lo), _triple(hi), path.stat().st_size)
    logger.info("mesh: %s, %d vertices, %d triangles (revision %d)", path, n_vert, n_tri, layers.revision)
    return summary


def _weight_threshold(weight_threshold: float | None) -> float:
    from driftmap.volume.mesh import DEFAULT_WEIGHT_THRESHOLD

    return DEFAULT_WEIGHT_THRESHOLD if weight_threshold is None else float(weight_threshold)


def tsdf_mesh(layers: VolumeLayers, weight_threshold: float | None = None) -> o3d.geometry.TriangleMesh:
    """:meth:`VolumeLayers.mesh` at ``weight_threshold`` (default: Open3D's); empty when no triangle is found."""
    return layers.mesh(_weight_threshold(weight_threshold))


# --------------------------------------------------------------------------------------------------- octomap
@dataclass(frozen=True)
class PreparedOctomap:
    """The tree :func:`write_octomap` writes (maximum likelihood, inner nodes updated) and its voxel counts."""

    tree: object
    n_occupied: int
    n_free: int


def prepare_octomap(layers: VolumeLayers, path: str | Path, *, flag: str = "--octomap") -> PreparedOctomap:
    """Everything :func:`write_octomap` checks before it writes, and the tree it would write (same errors)."""
    import pyoctomap

    path = Path(path)
    if path.suffix.lower() != OCTOMAP_SUFFIX:
        raise ConfigError(f"{flag} {path}: an OctoMap is written as a binary tree {OCTOMAP_SUFFIX!r} "
                          f"(got {path.suffix or 'no suffix'!r})")
    refuse_inside_store(path, flag)
    grid, cfg = layers.grid, layers.config
    states = layers.state_grid().ravel()
    observed = np.flatnonzero(states >= 0)
    if len(observed) == 0:
        raise EmptyExportError(f"{flag} {path}: no voxel of revision {layers.revision} is observed "
                               f"({grid.describe()}); nothing written")
    origin = np.asarray(grid.origin_index, dtype=np.int64)
    chunks = [observed[a:a + _OCTOMAP_CHUNK] for a in range(0, len(observed), _OCTOMAP_CHUNK)]
    # the voxels in chunks: over all observed voxels at once, their lattice, centres and log-odds took ~100 bytes a
    # voxel beside the grid that memory_budget_mb checked (hostile trial 24 W4)
    lo_idx = np.min([(grid.unflat(c) + origin).min(axis=0) for c in chunks], axis=0)
    hi_idx = np.max([(grid.unflat(c) + origin).max(axis=0) for c in chunks], axis=0)
    if lo_idx.min() < -OCTOMAP_KEY_HALF_RANGE or hi_idx.max() >= OCTOMAP_KEY_HALF_RANGE:
        reach = OCTOMAP_KEY_HALF_RANGE * grid.voxel_size_m
        lo_m = (lo_idx * grid.voxel_size_m).round(2).tolist()
        hi_m = ((hi_idx + 1) * grid.voxel_size_m).round(2).tolist()
        raise ConfigError(f"{flag} {path}: the observed voxels span {lo_m} .. {hi_m} m, beyond OctoMap's 16-bit "
                          f"keys at {grid.voxel_size_m:g} m voxels (+-{reach:.0f} m around the origin): "
                          f"use larger voxels (volume.voxel_size_m)")
    tree = pyoctomap.OcTree(float(grid.voxel_size_m))
    tree.setProbHit(cfg.prob_hit)
    tree.setProbMiss(cfg.prob_miss)
    tree.setClampingThresMin(cfg.clamp_min)
    tree.setClampingThresMax(cfg.clamp_max)
    tree.setOccupancyThres(cfg.occupancy_threshold)

    threshold = float(tree.getOccupancyThresLog())
    n_occupied = 0
    for chunk in chunks:
        occupied = states[chunk] == 1
        n_occupied += int(occupied.sum())
        values = _octomap_log_odds(layers.log_odds_flat(chunk), occupied, threshold)
        centres = (grid.unflat(chunk) + origin + 0.5) * grid.voxel_size_m
        order = np.argsort(values, kind="stable")
        uniq, starts = np.unique(values[order], return_index=True)
        for value, a, b in zip(uniq.tolist(), starts.tolist(), [*starts[1:].tolist(), len(order)]):
            tree.updateNodes(centres[order[a:b]], float(value), True)  # lazy: inner nodes once, below
    tree.updateInnerOccupancy()
    tree.toMaxLikelihood()
    return PreparedOctomap(tree, n_occupied, len(observed) - n_occupied)


def write_octomap(layers: VolumeLayers, path: str | Path, *, flag: str = "--octomap",
                  prepared: PreparedOctomap | None = None) -> OctomapExportSummary:
    """Write the occupancy layers as an OctoMap binary tree (``.bt``) at ``path``.

    The tree (pyoctomap ``OcTree``) has the layers' voxel size as resolution and the config's sensor model
    (``prob_hit``, ``prob_miss``, ``clamp_min``, ``clamp_max``, ``occupancy_threshold``). Every observed voxel gets its
    clamped log-odds (:meth:`VolumeLayers.log_odds_flat`) through ``updateNode(coord, log_odds)`` on an empty node,
    so the node holds exactly that value (OctoMap's lattice is driftmap's: voxel ``i`` covers
    ``[i, i + 1) * resolution``); then, as OctoMap's own tools do before writing, ``updateInnerOccupancy``,
    ``toMaxLikelihood`` (every node set to the clamp of its state) and ``prune`` (done by ``writeBinary``). The file
    holds the maximum-likelihood state of every observed voxel (2 bits a node: occupied / free / has children);
    unobserved voxels are absent, which OctoMap reads as unknown. The sensor model is not stored in a ``.bt``.

    Raises :class:`~driftmap.errors.ConfigError` for a suffix other than ``.bt`` or a map beyond OctoMap's 16-bit keys,
    :class:`~driftmap.errors.OutputInsideStoreError`, :class:`~driftmap.errors.EmptyExportError` when no voxel is
    observed, :class:`~driftmap.errors.OutputWriteError` naming ``path`` when the file cannot be written.
    ``prepared``: what :func:`prepare_octomap` returned for ``layers`` and ``path`` (not built again)."""
    path = Path(path)
    if prepared is None:
        prepared = prepare_octomap(layers, path, flag=flag)
    tree = prepared.tree
    with atomic_output(path, flag, guard=False) as tmp:
        if not tree.writeBinary(str(tmp)):  # OctoMap's writeBinary: toMaxLikelihood, prune, write
            raise OSError("OctoMap could not write the binary tree")
    summary = OctomapExportSummary(
        path=path, resolution_m=float(tree.getResolution()), n_occupied=prepared.n_occupied,
        n_free=prepared.n_free, n_tree_nodes=int(tree.size()), n_leaf_nodes=int(tree.getNumLeafNodes()),
        metric_min_m=_triple(tree.getMetricMin()), metric_max_m=_triple(tree.getMetricMax()),
        bytes=path.stat().st_size)
    logger.info("octomap: %s, %d occupied and %d free voxels of %g m, %d nodes after pruning (revision %d)", path,
                summary.n_occupied, summary.n_free, summary.resolution_m, summary.n_tree_nodes, layers.revision)
    return summary


def _octomap_log_odds(log_odds: NDArray[np.float64], occupied: NDArray[np.bool_],
                      threshold_f32: float) -> NDArray[np.float32]:
    """The log-odds as OctoMap stores them (float32), nudged by one float step where the rounding would put a value
    on the other side of the tree's (float32) occupancy threshold than driftmap's double comparison does."""
    values = log_odds.astype(np.float32)
    thr = np.float32(threshold_f32)
    flipped = (values >= thr) != occupied
    if np.any(flipped):
        values[flipped & occupied] = thr
        values[flipped & ~occupied] = np.nextafter(thr, np.float32(-np.inf))
        logger.debug("octomap: %d log-odds within float rounding of the threshold nudged", int(flipped.sum()))
    return values


# -------------------------------------------------------------------------------------------------- 2-D map
def occupancy_grid2d(layers: VolumeLayers, band_m: Sequence[float], *, flag: str = "--band-m") -> Grid2D:
    """The 2-D occupancy grid of the voxel columns between ``band_m = (z_min, z_max)`` (metres, world z): the
    layers whose voxel centres lie in ``z_min .. z_max`` (both included); a cell is occupied if any voxel of its
    column there is occupied, else free if any is free, else unknown. The grid covers the layers' x-y extent.

    A band that is not two finite numbers, is inverted, selects no voxel layer or no observed voxel is a
    :class:`~driftmap.errors.ConfigError` naming ``flag``."""
    g = layers.grid
    try:
        z_min, z_max = (float(v) for v in band_m)
    except (TypeError, ValueError):
        raise ConfigError(f"{flag}: give two heights z_min z_max in metres, got {band_m!r}") from None
    if not (math.isfinite(z_min) and math.isfinite(z_max)):
        raise ConfigError(f"{flag}: the band must be finite, got {z_min:g} .. {z_max:g} m")
    if z_min > z_max:
        raise ConfigError(f"{flag}: the band {z_min:g} .. {z_max:g} m is inverted (z_min > z_max)")
    vs = g.voxel_size_m
    layer_z = (g.origin_index[2] + np.arange(g.shape[2]) + 0.5) * vs
    sel = np.flatnonzero((layer_z >= z_min) & (layer_z <= z_max))
    if len(sel) == 0:
        raise ConfigError(f"{flag}: the band {z_min:g} .. {z_max:g} m holds no voxel centre (the layers' voxel "
                          f"centres span z = {layer_z[0]:.3f} .. {layer_z[-1]:.3f} m, every {vs:g} m)")
    nx, ny, nz = g.shape
    flats = (np.arange(nx * ny, dtype=np.int64)[:, None] * nz + sel[None, :]).ravel()
    column = layers.states_flat(flats).reshape(nx, ny, len(sel))
    occupied = np.any(column == 1, axis=2)
    free = np.any(column == 0, axis=2)
    if not np.any(occupied | free):
        observed_z = _observed_z_range(layers)
        raise ConfigError(f"{flag}: no voxel in the band {z_min:g} .. {z_max:g} m is observed (observed voxels "
                          f"span z = {observed_z}): pick a band inside it")
    cells = np.where(occupied, GRID_OCCUPIED, np.where(free, GRID_FREE, GRID_UNKNOWN)).astype(np.int8)
    origin = (float(g.origin_index[0] * vs), float(g.origin_index[1] * vs))
    return Grid2D(cells, float(vs), origin, (z_min, z_max), layer_z[sel])


def _observed_z_range(layers: VolumeLayers) -> str:
    states = layers.state_grid()
    zs = np.flatnonzero(np.any(states >= 0, axis=(0, 1)))
    if len(zs) == 0:
        return "nothing (no voxel is observed)"
    vs, z0 = layers.grid.voxel_size_m, layers.grid.origin_index[2]
    return f"{(z0 + zs[0] + 0.5) * vs:.3f} .. {(z0 + zs[-1] + 0.5) * vs:.3f} m (voxel centres)"


def write_grid2d(layers: VolumeLayers, yaml_path: str | Path, band_m: Sequence[float], *, flag: str = "--grid2d",
                 band_flag: str = "--band-m", grid: Grid2D | None = None) -> Grid2DExportSummary:
    """Write the 2-D occupancy map of ``band_m`` (:func:`occupancy_grid2d`) in the ROS ``map_server`` format:
    ``yaml_path`` and a PGM of the same name next to it (``map.yaml`` -> ``map.pgm``).

    The PGM is binary (``P5``, 8 bit, width = x cells, height = y cells), grey 254 free, 0 occupied, 205 unknown,
    image row 0 the largest y. The YAML holds ``image`` (the PGM's file name, relative to the YAML), ``mode:
    trinary``, ``resolution`` (m per cell), ``origin: [x, y, yaw]`` (the world position of the image's bottom-left
    corner, yaw 0), ``negate: 0``, ``occupied_thresh: 0.65`` and ``free_thresh: 0.196``, with which ``map_server``
    (``p = (255 - value) / 255``) reads the three grey values back as occupied / free / unknown. The PGM is
    written before the YAML, so a YAML never names a missing image.

    Raises :class:`~driftmap.errors.ConfigError` for a suffix other than ``.yaml`` / ``.yml`` or a bad band (naming
    ``band_flag``), :class:`~driftmap.errors.OutputInsideStoreError` for a path inside a store folder and
    :class:`~driftmap.errors.OutputWriteError` naming the file that cannot be written."""
    yaml_path = Path(yaml_path)
    if yaml_path.suffix.lower() not in GRID2D_SUFFIXES:
        raise ConfigError(f"{flag} {yaml_path}: the 2-D map is named by its YAML file (.yaml or .yml), got "
                          f"{yaml_path.suffix or 'no suffix'!r}")
    pgm_path = yaml_path.with_suffix(".pgm")
    refuse_inside_store(yaml_path, flag)
    refuse_inside_store(pgm_path, flag)
    if grid is None:  # else: occupancy_grid2d(layers, band_m) computed (and checked) by the caller
        grid = occupancy_grid2d(layers, band_m, flag=band_flag)
    image = grid.pgm_image()
    height, width = image.shape
    with atomic_output(pgm_path, flag, guard=False) as tmp, open(tmp, "wb") as fh:
        fh.write(f"P5\n{width} {height}\n255\n".encode("ascii"))
        fh.write(image.tobytes())
    with atomic_output(yaml_path, flag, guard=False) as tmp:
        tmp.write_text(_map_yaml(pgm_path.name, grid), encoding="utf-8")
    counts = grid.counts()
    summary = Grid2DExportSummary(yaml_path, pgm_path, width, height, grid.resolution_m, grid.origin_xy_m, grid.band_m,
                                  len(grid.layer_z_m), counts["occupied"], counts["free"], counts["unknown"])
    logger.info("2-D map: %s + %s, %d x %d cells of %g m, band %g .. %g m (%d layers): %d occupied, %d free, "
                "%d unknown", yaml_path, pgm_path.name, width, height, grid.resolution_m, *grid.band_m,
                summary.n_layers, summary.n_occupied, summary.n_free, summary.n_unknown)
    return summary


def _map_yaml(image_name: str, grid: Grid2D) -> str:
    x0, y0 = grid.origin_xy_m
    return (
        f"# driftmap 2-D occupancy map (ROS map_server format): voxel columns with centres in z = "
        f"{grid.band_m[0]!r} .. {grid.band_m[1]!r} m\n"
        f"image: {json.dumps(image_name)}\n"
        f"mode: trinary\n"
        f"resolution: {grid.resolution_m!r}\n"
        f"origin: [{x0!r}, {y0!r}, 0.0]\n"
        f"negate: 0\n"
        f"occupied_thresh: {OCCUPIED_THRESH!r}\n"
        f"free_thresh: {FREE_THRESH!r}\n"
    )


def _triple(v: NDArray[np.floating] | Sequence[float]) -> tuple[float, float, float]:
    a = np.asarray(v, dtype=np.float64)
    return float(a[0]), float(a[1]), float(a[2])


__all__ = [
    "FREE_THRESH",
    "GRID_FREE",
    "GRID_OCCUPIED",
    "GRID_UNKNOWN",
    "MESH_SUFFIXES",
    "OCCUPIED_THRESH",
    "PGM_FREE",
    "PGM_OCCUPIED",
    "PGM_UNKNOWN",
    "Grid2D",
    "Grid2DExportSummary",
    "MeshExportSummary",
    "OctomapExportSummary",
    "PreparedOctomap",
    "occupancy_grid2d",
    "prepare_mesh",
    "prepare_octomap",
    "tsdf_mesh",
    "write_grid2d",
    "write_mesh",
    "write_octomap",
]
