"""Volumetric layers (issue 24) on real data: 7-Scenes redkitchen frames 0:1000:5 (200 Kinect v1 frames, the
2-pixel stride ``build`` stores) placed with the data set's poses. The TSDF mesh equals the one Open3D's own
VoxelBlockGrid builds from the same depth images, poses, intrinsics, voxel and truncation; occupied / free agree
with OctoMap's ``insertPointCloud`` on the same rays; and a pose correction applied to the layers equals a rebuild
of the corrected revision bit for bit, with a rollback giving the original layers back -- also when the memory budget
keeps only some frames' voxels and when a pose changes by less than the map view notices.

One store and one set of layers (revision 0) are built per module and shared (the correction test adds revisions and
builds its own layers); the quick cases use a 20-frame store of their own."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import open3d as o3d
import open3d.core as o3c
import pytest
from scipy.spatial import cKDTree

from driftmap.frame import PoseSource
from driftmap.pipeline.build import build
from driftmap.store.frame_store import FrameStore
from driftmap.volume import OCCUPIED, UNKNOWN, VolumeLayers
from driftmap.volume.grid import GridSpec
from driftmap.volume.layers import VoxelArrays
from driftmap.volume.observation import observe

FRAMES = "0:1000:5"
VALID_DEPTH_MM = (200, 4000)
"""The 7-Scenes source's valid depth range (0.2 .. 4 m; 0 and 65535 are no reading)."""
KINECT_FX, KINECT_CX, KINECT_CY = 585.0, 320.0, 240.0


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory, sevenscenes_dir: Path) -> FrameStore:
    """7-Scenes frames 0:1000:5 with the data set's poses as revision 0 (opened for appending: the correction test
    adds revisions; every other test reads revision 0)."""
    out = tmp_path_factory.mktemp("vol7") / "kitchen"
    build(sevenscenes_dir, out, poses_from_source=True, loop_closure=False, frames=FRAMES)
    s = FrameStore.open(out, "a")
    assert len(s) == 200
    yield s
    s.close()


@pytest.fixture(scope="module")
def layers(store: FrameStore) -> VolumeLayers:
    """The layers of revision 0 with the default settings (2 cm voxels, 8 cm truncation, 2.29 m range)."""
    return VolumeLayers.from_store(store, 0)


def _open3d_tsdf(sevenscenes_dir: Path, store: FrameStore, layers: VolumeLayers,
                 poses: np.ndarray) -> o3d.t.geometry.VoxelBlockGrid:
    """Open3D's VoxelBlockGrid integrating the frames' depth PNGs, read by Open3D and subsampled to the store's
    pixel stride, with the given poses, the store's intrinsics and the layers' voxel, truncation and max range."""
    cfg = layers.config
    vs, trunc, depth_max = float(cfg.voxel_size_m), float(cfg.truncation_m), float(cfg.max_range_m)
    K0 = store.frame(int(store.frame_ids[0])).intrinsics
    stride = 640 // K0.width
    assert (K0.fx, K0.cx, K0.cy) == (KINECT_FX / stride, KINECT_CX / stride, KINECT_CY / stride)
    K = o3c.Tensor(np.array([[K0.fx, 0.0, K0.cx], [0.0, K0.fy, K0.cy], [0.0, 0.0, 1.0]]))
    vbg = o3d.t.geometry.VoxelBlockGrid(attr_names=("tsdf", "weight"), attr_dtypes=(o3c.float32, o3c.float32),
                                        attr_channels=((1), (1)), voxel_size=vs, block_resolution=8,
                                        block_count=50_000, device=o3c.Device("CPU:0"))
    for fid, T in zip(store.frame_ids, poses):
        raw = np.asarray(o3d.io.read_image(str(sevenscenes_dir / f"frame-{int(fid):06d}.depth.png")))
        depth = np.ascontiguousarray(raw[::stride, ::stride])
        depth[(depth < VALID_DEPTH_MM[0]) | (depth > VALID_DEPTH_MM[1])] = 0
        image = o3d.t.geometry.Image(o3c.Tensor(depth))
        E = o3c.Tensor(np.linalg.inv(T))
        blocks = vbg.compute_unique_block_coordinates(image, K, E, 1000.0, depth_max, trunc / vs)
        vbg.integrate(blocks, image, K, E, 1000.0, depth_max, trunc / vs)
    return vbg


def _chamfer_m(a: o3d.geometry.TriangleMesh, b: o3d.geometry.TriangleMesh) -> float:
    """Symmetric Chamfer distance between the vertices of two meshes (mean of both directions' mean distances)."""
    pa, pb = np.asarray(a.vertices), np.asarray(b.vertices)
    return 0.5 * float(cKDTree(pb).query(pa)[0].mean() + cKDTree(pa).query(pb)[0].mean())


def test_tsdf_mesh_equals_open3d_s(sevenscenes_dir: Path, store: FrameStore, layers: VolumeLayers) -> None:
    """Open3D integrating the same 200 depth images with the store's poses (the pose files' matrices made exactly
    rigid, as the source reads them), intrinsics, voxel (2 cm), truncation (8 cm) and range (2.29 m): every
    sample's weight equals our count, the TSDF agrees to float32 rounding and the meshes are the same (Chamfer
    measured 1e-9 m; the acceptance bound is 1 mm). With the pose files' matrices as written (rotations off
    orthonormal by up to 1.5e-4) Open3D's mesh is still within 1 mm (measured 0.31 mm)."""
    cfg = layers.config
    assert (cfg.voxel_size_m, cfg.truncation_m) == (0.02, pytest.approx(0.08))
    assert cfg.max_range_m == pytest.approx(2.292, abs=1e-3)
    vs = cfg.voxel_size_m
    vbg = _open3d_tsdf(sevenscenes_dir, store, layers, store.poses(0))
    coords, idx = vbg.voxel_coordinates_and_flattened_indices()
    weight = vbg.attribute("weight").numpy().reshape(-1)[idx.numpy()]
    tsdf = vbg.attribute("tsdf").numpy().reshape(-1)[idx.numpy()]
    seen = weight > 0
    lattice = np.rint(coords.numpy()[seen] / vs).astype(np.int64) - np.asarray(layers.grid.origin_index)
    ours, count = layers.tsdf_flat(layers.grid.flat(lattice))
    assert int(seen.sum()) > 500_000  # measured 553,385 samples
    assert np.array_equal(count, weight[seen].astype(np.int32))
    assert int((layers.arrays.tsdf_count > 0).sum()) == int(seen.sum())
    assert np.max(np.abs(ours - tsdf[seen])) < 1e-5  # measured 8e-7

    mesh = layers.mesh()
    theirs = vbg.extract_triangle_mesh(weight_threshold=3.0).to_legacy()
    assert len(mesh.triangles) > 80_000  # measured 91,217
    assert abs(len(mesh.triangles) - len(theirs.triangles)) <= 1e-3 * len(theirs.triangles)
    assert _chamfer_m(mesh, theirs) <= 1e-3  # measured 1.3e-9 m

    files = np.array([np.loadtxt(sevenscenes_dir / f"frame-{int(f):06d}.pose.txt") for f in store.frame_ids])
    assert 0 < np.abs(files - store.poses(0)).max() < 1e-3
    as_written = _open3d_tsdf(sevenscenes_dir, store, layers, files).extract_triangle_mesh(weight_threshold=3.0)
    assert _chamfer_m(mesh, as_written.to_legacy()) <= 1e-3  # measured 3.1e-4 m


def test_occupancy_agrees_with_octomap_on_the_same_rays(store: FrameStore, layers: VolumeLayers) -> None:
    """OctoMap's ``insertPointCloud`` (pyoctomap) on the same rays -- every frame's points in the world frame from
    its camera centre, with the layers' max range (OctoMap cuts longer rays and carves them only) -- on every 5th
    frame of the store (40 frames: OctoMap takes 0.4 s a frame; all 200 measured 99.71 % agreement, with the same
    set of observed voxels). Both observe the same voxels, and their occupied / free decisions agree on >= 99 % of
    them (OctoMap clamps after every update, driftmap only when a voxel is read)."""
    pyoctomap = pytest.importorskip("pyoctomap")
    cfg = layers.config
    view = layers.view
    ids = [int(f) for f in store.frame_ids[::5]]
    obs = [observe(store.frame(f), view.pose(f), view.frame_points_world(f), cfg) for f in ids]
    lo = np.min([o.bounds_m[0] for o in obs], axis=0)
    hi = np.max([o.bounds_m[1] for o in obs], axis=0)
    grid = GridSpec.covering(lo, hi, cfg.voxel_size_m, padding_m=cfg.voxel_size_m)
    sub = VolumeLayers(cfg, grid, layers.sensor_kind, 0, VoxelArrays.zeros(grid.n_voxels))
    tree = pyoctomap.OcTree(cfg.voxel_size_m)
    assert (tree.getProbHit(), tree.getProbMiss()) == pytest.approx((cfg.prob_hit, cfg.prob_miss))
    assert (tree.getClampingThresMin(), tree.getClampingThresMax()) == pytest.approx((cfg.clamp_min, cfg.clamp_max))
    assert tree.getOccupancyThres() == pytest.approx(cfg.occupancy_threshold)
    n_cut = 0
    for fid, o in zip(ids, obs):
        assert len(o.ends_m) == store.frame(fid).n_points  # no point closer than min_range_m
        n_cut += int((~o.is_hit).sum())
        sub._integrate(o, +1)
        points = np.ascontiguousarray(view.frame_points_world(fid), dtype=np.float64)
        tree.insertPointCloud(points, o.origin_m, max_range=float(cfg.max_range_m), lazy_eval=True)
    tree.updateInnerOccupancy()
    assert n_cut > 100_000  # rays beyond the max range are part of the comparison (measured 1.04 M of 2.7 M)

    states = sub.state_grid().ravel()
    observed = np.flatnonzero(states != UNKNOWN)
    occupied = states[observed] == OCCUPIED
    assert len(observed) > 1_000_000 and occupied.sum() > 40_000  # measured 1.27 M and 57k
    both = agree = 0
    for is_occupied, centre in zip(occupied, grid.centers_m(observed)):
        node = tree.search(centre)
        if node is None:
            continue
        both += 1
        agree += tree.isNodeOccupied(node) == is_occupied
    assert both == len(observed)  # every voxel we observe, OctoMap observes
    assert tree.getNumLeafNodes() == len(observed)  # and no other (no leaf pruned at this clamping)
    assert agree / both >= 0.99  # measured 0.99977


# ------------------------------------------------------------------------------------------------ corrections
def _drift(poses: np.ndarray, start: int) -> np.ndarray:
    """Odometry-like drift from frame index ``start`` on: a rotation about the world z axis through that frame's
    camera centre growing to 1.5 deg, and a translation growing to (4, -3, 2) cm, at the last frame."""
    out = poses.copy()
    n = len(poses)
    for k in range(start, n):
        s = (k - start + 1) / (n - start)
        a = np.deg2rad(1.5) * s
        R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
        pivot = poses[start, :3, 3]
        out[k, :3, :3] = R @ poses[k, :3, :3]
        out[k, :3, 3] = R @ (poses[k, :3, 3] - pivot) + pivot + s * np.array([0.04, -0.03, 0.02])
    return out


def _snapshot(layers: VolumeLayers) -> VolumeLayers:
    """A copy of the layers' sums (for :meth:`VolumeLayers.equals`)."""
    a = layers.arrays
    copy = VoxelArrays(a.hits.copy(), a.misses.copy(), a.mark.copy(), a.tsdf_sum.copy(), a.tsdf_count.copy())
    return VolumeLayers(layers.config, layers.grid, layers.sensor_kind, layers.revision, copy)


def _states_on_union(layers: VolumeLayers, other: VolumeLayers) -> tuple[GridSpec, np.ndarray]:
    """The union of both layers' grids and ``layers``' voxel states on it (unknown outside its own grid), flat."""
    g = layers.grid
    lo = np.minimum(g.min_m, other.grid.min_m)
    hi = np.maximum(g.max_m, other.grid.max_m) - 0.5 * g.voxel_size_m
    common = GridSpec.covering(lo, hi, g.voxel_size_m)
    out = np.full(common.shape, UNKNOWN, dtype=np.int8)
    off = [a - b for a, b in zip(g.origin_index, common.origin_index)]
    out[tuple(slice(o, o + n) for o, n in zip(off, g.shape))] = layers.state_grid()
    return common, out.ravel()


def _hits(layers: VolumeLayers) -> str:
    keys, means, n = layers.hit_means()
    return hashlib.sha256(keys.tobytes() + means.tobytes() + n.tobytes()).hexdigest()


def test_a_correction_updates_the_layers_to_exactly_a_rebuild_and_back(store: FrameStore, layers: VolumeLayers) -> None:
    """Revision 1: the data set's poses with drift on the last 50 frames (growing to 1.5 deg and 5.4 cm); revision 2: the
    true poses imported again (the correction). Layers of revision 1 updated to revision 2 equal the layers built
    from scratch in revision 2 bit for bit (occupancy counts, TSDF sums and counts, hit points), which equal those
    of revision 0; the change names exactly the moved frames and the voxels whose state flipped; rolling back to
    revision 1 gives revision 1's layers again."""
    ids = [int(f) for f in store.frame_ids]
    true = store.poses(0)
    start = 150
    drifted = store.add_revision(dict(zip(ids, _drift(true, start))), source=PoseSource.EXTERNAL_FILE,
                                 propagate=False, note="drifted").revision_id
    corrected = store.add_revision(dict(zip(ids, true)), source=PoseSource.EXTERNAL_FILE, propagate=False,
                                   note="true poses").revision_id
    assert np.array_equal(store.poses(corrected), true)

    moving = VolumeLayers.from_store(store, drifted)
    original, original_hits = _snapshot(moving), _hits(moving)
    assert not moving.equals(layers)

    change = moving.apply(corrected, store)
    assert not change.rebuilt and change.revision_to == corrected
    assert sorted(change.frame_ids.tolist()) == ids[start:]
    rebuilt = VolumeLayers.from_store(store, corrected)
    assert moving.equals(rebuilt) and _hits(moving) == _hits(rebuilt)
    assert rebuilt.equals(layers) and _hits(rebuilt) == _hits(layers)
    assert change.n_state_changed > 1_000
    assert np.all(original.states(change.changed_centers_m) != rebuilt.states(change.changed_centers_m))
    # the reported voxels are exactly those whose state differs between the two revisions' layers
    common, before_states = _states_on_union(original, rebuilt)
    after_states = _states_on_union(rebuilt, original)[1]
    flips = np.flatnonzero(before_states != after_states)
    reported = common.flat(common.lattice_index(change.changed_centers_m) - np.asarray(common.origin_index))
    assert np.array_equal(np.sort(reported), flips)

    back = moving.apply(drifted, store)
    assert sorted(back.frame_ids.tolist()) == ids[start:]
    assert moving.equals(original) and _hits(moving) == original_hits
    assert back.n_state_changed == change.n_state_changed


@pytest.fixture(scope="module")
def small(tmp_path_factory: pytest.TempPathFactory, sevenscenes_dir: Path) -> FrameStore:
    """20 frames (0:1000:50) with the data set's poses, for the quick cases (tests add revisions to it)."""
    out = tmp_path_factory.mktemp("vol7") / "small"
    build(sevenscenes_dir, out, poses_from_source=True, loop_closure=False, frames="0:1000:50")
    s = FrameStore.open(out, "a")
    yield s
    s.close()


def test_the_memory_budget_bounds_the_kept_frame_voxels_and_the_update_stays_exact(small: FrameStore) -> None:
    """``keep_frame_voxels`` keeps each frame's missed voxels (about 1 MB a frame here) only while the grid and the
    kept voxels fit ``memory_budget_mb``; the frames beyond it are taken out by tracing their rays again, and an
    update mixing both ways still equals a rebuild bit for bit."""
    full = VolumeLayers.from_store(small, 0)
    assert len(full.frame_misses) == 20
    kept_mib = full.stats().cache_nbytes / 2**20
    budget = full.grid.nbytes / 2**20 + 0.5 * sum(m.nbytes for _, m in full.frame_misses.values()) / 2**20
    config = full.config.model_copy(update={"memory_budget_mb": budget})
    bounded = VolumeLayers.from_store(small, 0, config)
    assert bounded.equals(full)
    assert 5 <= len(bounded.frame_misses) <= 15  # the first frames kept, the rest not
    assert bounded.grid.nbytes + sum(m.nbytes for _, m in bounded.frame_misses.values()) <= budget * 2**20
    assert bounded.stats().cache_nbytes / 2**20 < kept_mib

    ids = [int(f) for f in small.frame_ids]
    drifted = small.add_revision(dict(zip(ids, _drift(small.poses(0), 5))), source=PoseSource.EXTERNAL_FILE,
                                 propagate=False).revision_id
    change = bounded.apply(drifted, small)
    assert sorted(change.frame_ids.tolist()) == ids[5:]  # kept and not kept frames among them
    assert bounded.equals(VolumeLayers.from_store(small, drifted, config))
    bounded.apply(0, small)
    assert bounded.equals(full)


def test_a_tiny_pose_change_still_equals_a_rebuild(small: FrameStore) -> None:
    """A rebuild places a frame at its exact pose, and a camera centre on a voxel boundary (0) moved by -1e-15 m lies
    in another voxel; the map view and the layers' update apply every pose change, however small, so the update still
    equals the rebuild (a loop closure on the synthetic log moves its first camera from 0 to -4e-20 m)."""
    from driftmap.map.view import MapView

    ids = [int(f) for f in small.frame_ids]
    on_boundary = small.poses(0).copy()
    on_boundary[:, :3, 3] -= on_boundary[0, :3, 3].copy()  # the first camera at exactly (0, 0, 0)
    rev_a = small.add_revision(dict(zip(ids, on_boundary)), source=PoseSource.EXTERNAL_FILE,
                               propagate=False).revision_id
    nudged = _drift(on_boundary, 15)
    nudged[0, :3, 3] = -1e-15
    assert 0 < np.abs(nudged[0] - on_boundary[0]).max() <= 1e-12
    rev_b = small.add_revision(dict(zip(ids, nudged)), source=PoseSource.EXTERNAL_FILE, propagate=False).revision_id
    assert ids[0] in MapView.from_store(small, rev_a).apply(rev_b).frame_ids  # the view moves frame 0 too

    layers = VolumeLayers.from_store(small, rev_a)
    before = _snapshot(layers)
    change = layers.apply(rev_b, small)
    assert not change.rebuilt and ids[0] in change.frame_ids.tolist()
    assert layers.equals(VolumeLayers.from_store(small, rev_b))
    layers.apply(rev_a, small)
    assert layers.equals(before)
