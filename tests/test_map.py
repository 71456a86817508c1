"""The map view: exact incremental re-transforms after corrections and rollbacks, changed regions, queries,
fused export with provenance, and the store CLI round trip."""

from __future__ import annotations

import logging
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from driftmap import Frame, PointAttributes, PoseEstimate, SensorKind, geometry
from driftmap.errors import ConfigError, StoreError, TransformError
from driftmap.map import view as view_module
from driftmap.map.view import MapView
from driftmap.preprocess.cloud import BoxROI
from driftmap.store.frame_store import FrameStore
from driftmap.trajectory import Trajectory, read_kitti, read_tum, write_kitti, write_tum

from test_store import sevenscenes_frame

FRAME_IDS = list(range(0, 1000, 50))  # 20 real frames spread over the loop


@pytest.fixture(scope="module")
def kitchen_frames(sevenscenes_dir: Path) -> list[Frame]:
    return [sevenscenes_frame(sevenscenes_dir, i, stride_px=5) for i in FRAME_IDS]


@pytest.fixture()
def kitchen_store(tmp_path: Path, kitchen_frames: list[Frame]) -> FrameStore:
    store = FrameStore.create(tmp_path / "kitchen")
    for f in kitchen_frames:
        store.append(f)
    yield store
    store.close()


def perturbation(seed: int, n: int, scale: float) -> np.ndarray:
    rng = np.random.default_rng(seed)
    out = np.tile(np.eye(4), (n, 1, 1))
    out[:, :3, :3] = Rotation.from_rotvec(rng.normal(scale=scale, size=(n, 3))).as_matrix()
    out[:, :3, 3] = rng.normal(scale=scale, size=(n, 3))
    return out


def reference_map(frames: list[Frame], poses: np.ndarray) -> np.ndarray:
    """From scratch, in plain numpy float64: every frame transformed with its final pose."""
    return np.concatenate([geometry.transform_points(T, f.points_sensor) for f, T in zip(frames, poses)])


def test_map_is_exact_after_a_chain_of_corrections_and_a_rollback(kitchen_store: FrameStore, kitchen_frames: list[Frame]) -> None:
    store = kitchen_store
    view = MapView.from_store(store, store.head)
    np.testing.assert_allclose(view.points_world, reference_map(kitchen_frames, store.poses(0)), atol=1e-6, rtol=0)
    gt = store.poses(0)
    ids = [int(i) for i in store.frame_ids]
    # 1: every frame moved by its own small error; 2: keyframes only, propagated; 3: a subset, not propagated
    rev1 = store.add_revision({i: gt[k] @ P for k, (i, P) in enumerate(zip(ids, perturbation(1, len(ids), 0.02)))}, source="external_file")
    key = ids[::4]
    rev2 = store.add_revision({i: perturbation(2, 1, 0.05)[0] @ store.poses()[ids.index(i)] for i in key}, source="loop_closure")
    rev3 = store.add_revision({ids[3]: gt[3], ids[7]: gt[7]}, source="external_file", propagate=False)
    back = store.rollback(to=rev1.revision_id)
    rev5 = store.add_revision({ids[0]: gt[0] @ perturbation(5, 1, 0.01)[0]}, source="loop_closure")
    for rev in (rev1, rev2, rev3, back, rev5):
        view.apply(rev.revision_id)
        expected = reference_map(kitchen_frames, store.poses(rev.revision_id))
        assert np.max(np.abs(view.points_world - expected)) <= 1e-6
    # the rollback restored revision 1 bit for bit, and a view built from scratch equals the incremental one
    assert store.poses(back.revision_id).tobytes() == store.poses(rev1.revision_id).tobytes()
    fresh = MapView.from_store(store, rev5.revision_id)
    assert fresh.points_world.tobytes() == view.points_world.tobytes()


def test_changed_regions_contain_exactly_the_moved_points(kitchen_store: FrameStore) -> None:
    store = kitchen_store
    view = MapView.from_store(store, store.head)
    before = view.points_world.copy()
    owner = view.point_frame_ids()
    ids = [int(i) for i in store.frame_ids]
    moved_ids = ids[5:8]
    rev = store.add_revision({i: perturbation(9, 1, 0.03)[0] @ store.poses()[ids.index(i)] for i in moved_ids},
                             source="external_file", propagate=False)
    changes = view.apply(rev.revision_id, voxel_size_m=0.05)
    assert sorted(changes.frame_ids.tolist()) == moved_ids
    after = view.points_world
    moved_mask = np.isin(owner, moved_ids)
    assert np.array_equal(before[~moved_mask], after[~moved_mask]), "frames that did not move must not change"
    assert np.all(np.any(before[moved_mask] != after[moved_mask], axis=1).mean() > 0.99)
    for change in changes.changes:
        sel = owner == change.frame_id
        lo, hi = change.box_before_m
        assert np.all((before[sel] >= lo) & (before[sel] <= hi))
        assert np.allclose(before[sel].min(0), lo) and np.allclose(before[sel].max(0), hi)
        lo, hi = change.box_after_m
        assert np.all((after[sel] >= lo) & (after[sel] <= hi))
        keys_before = {tuple(k) for k in np.floor(before[sel] / 0.05).astype(np.int64)}
        keys_after = {tuple(k) for k in np.floor(after[sel] / 0.05).astype(np.int64)}
        assert {tuple(k) for k in change.voxels_before} == keys_before
        assert {tuple(k) for k in change.voxels_after} == keys_after
        assert change.translation_m > 0
    # since the previous revision, the same frames changed; their old region holds the old points
    since = view.changed_since(rev.parent_id)
    assert sorted(since.frame_ids.tolist()) == moved_ids
    for change in since.changes:
        sel = owner == change.frame_id
        lo, hi = change.box_before_m
        assert np.all((before[sel] >= lo - 1e-5) & (before[sel] <= hi + 1e-5))


def test_incremental_apply_touches_only_changed_frames(kitchen_store: FrameStore) -> None:
    store = kitchen_store
    view = MapView.from_store(store, store.head)
    rev = store.add_revision({int(store.frame_ids[0]): np.eye(4)}, source="external_file", propagate=False)
    changes = view.apply(rev.revision_id)
    assert changes.frame_ids.tolist() == [int(store.frame_ids[0])]
    assert view.apply(rev.revision_id).changes == []  # nothing left to do


def test_queries_agree_with_brute_force(kitchen_store: FrameStore) -> None:
    view = MapView.from_store(kitchen_store, kitchen_store.head)
    pts = view.points_world.astype(np.float64)
    owner = view.point_frame_ids()
    center = pts[12345]
    lo, hi = center - [0.3, 0.2, 0.1], center + [0.2, 0.3, 0.4]
    box = view.query_box(lo, hi)
    mask = np.all((pts >= lo) & (pts <= hi), axis=1)
    assert len(box.points_world) == mask.sum() > 0
    assert sorted(map(tuple, box.points_world.tolist())) == sorted(map(tuple, pts[mask].astype(np.float32).tolist()))
    assert np.array_equal(np.sort(box.frame_ids), np.sort(owner[mask]))
    ball = view.query_radius(center, 0.15)
    assert len(ball.points_world) == int(np.sum(np.linalg.norm(pts - center, axis=1) <= 0.15))
    tree = cKDTree(pts)
    for q in (center + [0.05, 0.0, 0.02], [10.0, 10.0, 10.0], pts[-1] + 0.3):
        d, i = tree.query(q)
        near = view.nearest(q)
        assert near.distance_m == pytest.approx(d, abs=1e-9)
        assert np.allclose(near.point_world, pts[i])


def test_fused_export_with_provenance_and_roi(kitchen_store: FrameStore, tmp_path: Path) -> None:
    view = MapView.from_store(kitchen_store, kitchen_store.head)
    pts = view.points_world
    owner = view.point_frame_ids()
    roi = BoxROI(min_m=tuple(pts[500] - 0.1), max_m=tuple(pts[500] + 0.1), in_world=True)
    fused = view.fused(0.05, roi)
    in_roi = roi.contains(pts.astype(np.float64))
    assert fused.n_roi_points == int(in_roi.sum()) > 0
    # ROI points are kept verbatim, the rest is one centroid per occupied voxel
    rest = pts[~in_roi]
    keys = np.floor(rest / 0.05).astype(np.int64)
    uniq = np.unique(keys, axis=0)
    assert len(fused.points_world) == len(uniq) + fused.n_roi_points
    np.testing.assert_array_equal(fused.points_world[-fused.n_roi_points:], pts[in_roi])
    # provenance of a voxel = the set of frames that had a point in it; centroid = mean of its points
    f_keys = np.floor(fused.points_world[: len(uniq)] / 0.05).astype(np.int64)
    rest_owner = owner[~in_roi]
    for i in np.random.default_rng(0).choice(len(uniq), 50, replace=False):
        sel = np.all(keys == f_keys[i], axis=1)
        assert sorted(fused.frames_of(i).tolist()) == sorted(set(rest_owner[sel].tolist()))
        np.testing.assert_allclose(fused.points_world[i], rest[sel].astype(np.float64).mean(0), atol=1e-6)
    assert fused.n_frames_per_point().max() > 1  # overlapping frames share voxels
    for suffix in (".ply", ".pcd"):
        out = view.export(tmp_path / f"map{suffix}", voxel_size_m=0.05, provenance=True)
        read = np.asarray(o3d.io.read_point_cloud(str(out)).points)
        np.testing.assert_allclose(read, view.fused(0.05).points_world, atol=1e-6)
        assert Path(str(out) + ".provenance.npz").exists()
    full = view.export(tmp_path / "full.ply")
    np.testing.assert_allclose(np.asarray(o3d.io.read_point_cloud(str(full)).points), pts, atol=1e-6)


def test_strided_sources_with_attributes_transform_exactly(tmp_path: Path, kitchen_frames: list[Frame]) -> None:
    f = kitchen_frames[0]
    rng = np.random.default_rng(3)
    g = f.with_points(f.points_sensor, PointAttributes(intensity=rng.random(f.n_points, dtype=np.float32),
                                                       time_offset_ns=rng.integers(0, 10**6, f.n_points)))
    with FrameStore.create(tmp_path / "s") as store:
        store.append(g)
        view = MapView.from_store(store, store.head)
        assert store.frame_ref(g.frame_id).point_stride > 12
        np.testing.assert_allclose(view.points_world, geometry.transform_points(g.T_world_sensor, g.points_sensor), atol=1e-6)


def _frame_boxes(view: MapView) -> np.ndarray:
    """Per frame the min and max of its world points that have no NaN coordinate, from the points themselves."""
    out = []
    for fid in view.frame_ids:
        p = view.frame_points_world(int(fid))
        p = p[~np.isnan(p).any(axis=1)]
        out.append(np.stack([p.min(axis=0), p.max(axis=0)]))
    return np.array(out)


def test_read_mapped_and_in_memory_sources_give_the_same_map(kitchen_store: FrameStore,
                                                              kitchen_frames: list[Frame]) -> None:
    # default: sensor points read from the segment file in pieces (frames span several pieces);
    # release_pages=False: memory-mapped; from_frames: the frames' own arrays
    store = kitchen_store
    assert store.frame_ref(int(store.frame_ids[0])).n_points * 12 > view_module.READ_PIECE_BYTES
    rev = store.add_revision({int(i): T @ P for i, T, P in zip(store.frame_ids, store.poses(0),
                                                                 perturbation(4, len(store.frame_ids), 0.05))},
                             source="external_file")
    read = MapView.from_store(store, 0)
    mapped = MapView.from_store(store, 0, release_pages=False)
    memory = MapView.from_frames(kitchen_frames)
    for revision in (0, rev.revision_id, 0):
        poses = store.poses(revision)
        for view in (read, mapped, memory):
            view.apply(revision, poses=poses)
        assert read.points_world.tobytes() == mapped.points_world.tobytes() == memory.points_world.tobytes()
        expected_boxes = _frame_boxes(read)
        for view in (read, mapped, memory):
            assert np.array_equal([view.frame_box_m(int(f)) for f in view.frame_ids], expected_boxes)
        assert np.max(np.abs(read.points_world - reference_map(kitchen_frames, poses))) <= 1e-6


def test_boxes_leave_out_points_with_nan_coordinates(tmp_path: Path, kitchen_frames: list[Frame]) -> None:
    f = kitchen_frames[2]
    pts = f.points_sensor.copy()
    bad = np.random.default_rng(8).choice(len(pts), 25, replace=False)
    pts[bad, np.arange(25) % 3] = np.nan
    pts[0] = [1e3, -1e3, 1e3]  # an outlier that must be in the box
    g = f.with_points(pts)
    with FrameStore.create(tmp_path / "nan") as store:
        store.append(g)
        for view in (MapView.from_store(store, store.head), MapView.from_store(store, 0, release_pages=False), MapView.from_frames([g])):
            world = view.points_world
            assert np.isnan(world[bad]).any(axis=1).all()
            good = np.delete(np.arange(len(pts)), bad)
            np.testing.assert_allclose(world[good], geometry.transform_points(g.T_world_sensor, pts[good]), atol=1e-6)
            assert np.array_equal(view.frame_box_m(g.frame_id), _frame_boxes(view)[0])
            assert np.all(np.isfinite(view.frame_box_m(g.frame_id)))


def test_a_segment_truncated_under_an_open_map_raises_and_the_map_recovers(tmp_path: Path,
                                                                          kitchen_frames: list[Frame]) -> None:
    frames = kitchen_frames[:4]
    with FrameStore.create(tmp_path / "t") as store:
        for f in frames:
            store.append(f)
        rev = store.add_revision({f.frame_id: f.T_world_sensor @ P for f, P in zip(frames, perturbation(6, 4, 0.05))},
                                 source="external_file")
    store = FrameStore.open(tmp_path / "t")
    view = MapView.from_store(store, 0)
    last = store.frame_ref(frames[-1].frame_id)
    segment = last.segment
    original = segment.read_bytes()
    with open(segment, "r+b") as fh:
        fh.truncate(last.payload_offset + 1000)
    with pytest.raises(StoreError, match=rf"{segment.name}.*frame {frames[-1].frame_id}"):
        view.apply(rev.revision_id)
    segment.write_bytes(original)
    view.apply(rev.revision_id)  # the frames left stale by the failed read are transformed again
    assert np.max(np.abs(view.points_world - reference_map(frames, store.poses(rev.revision_id)))) <= 1e-6
    store.close()


def test_a_failed_read_in_one_segment_leaves_no_frame_of_a_later_segment_silently_stale(tmp_path: Path,
                                                                                       kitchen_frames: list[Frame]) -> None:
    """Frames in two segment files; the first file fails mid-apply: the second file's frames were not
    re-transformed either, so the next apply must redo them too."""
    frames = kitchen_frames[:4]
    with FrameStore.create(tmp_path / "t") as store:
        for f in frames[:2]:
            store.append(f)
    with FrameStore.open(tmp_path / "t", "a") as store:  # appending after a reopen starts a second segment
        for f in frames[2:]:
            store.append(f)
        rev = store.add_revision({f.frame_id: f.T_world_sensor @ P for f, P in zip(frames, perturbation(7, 4, 0.05))},
                                 source="external_file")
    store = FrameStore.open(tmp_path / "t")
    first, last = store.frame_ref(frames[0].frame_id), store.frame_ref(frames[-1].frame_id)
    assert first.segment != last.segment
    view = MapView.from_store(store, 0)
    original = first.segment.read_bytes()
    with open(first.segment, "r+b") as fh:
        fh.truncate(first.payload_offset + 1000)
    with pytest.raises(StoreError, match=first.segment.name):
        view.apply(rev.revision_id)
    first.segment.write_bytes(original)
    view.apply(rev.revision_id)
    assert np.max(np.abs(view.points_world - reference_map(frames, store.poses(rev.revision_id)))) <= 1e-6
    store.close()


def test_nan_points_stay_out_of_fused_voxels_and_changed_voxel_keys(tmp_path: Path, kitchen_frames: list[Frame]) -> None:
    f = kitchen_frames[2]
    pts = f.points_sensor.copy()
    bad = np.random.default_rng(9).choice(len(pts), 25, replace=False)
    pts[bad, np.arange(25) % 3] = np.nan
    g = f.with_points(pts)
    clean = f.with_points(np.delete(f.points_sensor, bad, axis=0))
    with FrameStore.create(tmp_path / "nan") as store:
        store.append(g)
        store.append(Frame(frame_id=99, stamp_ns=g.stamp_ns + 1, sensor_name=g.sensor_name, sensor_kind=g.sensor_kind,
                           points_sensor=np.full((4, 3), np.nan, np.float32), pose=g.pose))  # nothing but NaN
        view, ref = MapView.from_store(store, store.head), MapView.from_frames([clean])
        fused, expected = view.fused(0.05), ref.fused(0.05)
        assert np.all(np.isfinite(fused.points_world))
        np.testing.assert_allclose(fused.points_world, expected.points_world, atol=1e-6)
        assert np.array_equal(fused.provenance_offsets, expected.provenance_offsets)
        assert len(view.fused(None).points_world) == len(clean.points_sensor)
        moved = np.array([g.T_world_sensor, g.T_world_sensor])
        moved[:, 0, 3] += 0.3
        changes = view.apply(1, poses=moved, voxel_size_m=0.1)
        ref_changes = ref.apply(1, poses=moved[:1], voxel_size_m=0.1)
        got = {c.frame_id: c for c in changes.changes}
        assert np.array_equal(got[g.frame_id].voxels_before, ref_changes.changes[0].voxels_before)
        assert np.array_equal(got[g.frame_id].voxels_after, ref_changes.changes[0].voxels_after)
        assert got[99].voxels_before.shape == (0, 3) and got[99].voxels_after.shape == (0, 3)


def test_map_from_frames_refuses_duplicates_missing_and_non_rigid_poses(kitchen_frames: list[Frame]) -> None:
    frames = kitchen_frames[:2]
    with pytest.raises(StoreError, match=rf"frame id\(s\) \[{frames[0].frame_id}\] given more than once"):
        MapView.from_frames([frames[0], frames[1], frames[0]])
    with pytest.raises(StoreError, match=rf"no pose for frame\(s\) \[{frames[1].frame_id}\]"):
        MapView.from_frames(frames, poses={frames[0].frame_id: np.eye(4)})
    with pytest.raises(TransformError, match=rf"from_frames: pose of frame {frames[1].frame_id} rotation block"):
        MapView.from_frames(frames, poses={frames[0].frame_id: np.eye(4), frames[1].frame_id: 2 * np.eye(4) + np.diag([0, 0, 0, -1])})
    view = MapView.from_frames(frames)
    scaled = np.array([np.eye(4), np.eye(4)])
    scaled[1, :3, :3] *= 1.01
    with pytest.raises(TransformError, match=rf"apply: pose of frame {frames[1].frame_id}"):
        view.apply(1, poses=scaled)
    with pytest.raises(ConfigError, match="voxel_size_m must be positive"):
        view.apply(1, poses=np.array([f.T_world_sensor for f in frames]), voxel_size_m=-1.0)


def test_map_from_frames_without_a_store(kitchen_frames: list[Frame]) -> None:
    view = MapView.from_frames(kitchen_frames[:3])
    np.testing.assert_allclose(view.points_world, reference_map(kitchen_frames[:3], [f.T_world_sensor for f in kitchen_frames[:3]]), atol=1e-6)
    new = np.array([f.T_world_sensor for f in kitchen_frames[:3]])
    new[1, 0, 3] += 0.5
    changes = view.apply(1, poses=new)
    assert changes.frame_ids.tolist() == [kitchen_frames[1].frame_id]


def _cli(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "COLUMNS": "200"}
    return subprocess.run([sys.executable, "-m", "driftmap.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=300, env=env)


def test_cli_round_trip_tum_correct_export(kitchen_store: FrameStore, tmp_path: Path) -> None:
    path = kitchen_store.path
    kitchen_store.close()
    out0 = tmp_path / "rev0.txt"
    assert _cli("export", path, "--trajectory", out0, "--format", "tum").returncode == 0
    traj = read_tum(out0)
    np.testing.assert_allclose(traj.poses, FrameStore.open(path).poses(0), atol=1e-8)
    # a corrected trajectory for every other frame (keyframes), written as a TUM file
    corrected = traj.poses @ perturbation(4, len(traj), 0.01)
    keep = np.arange(len(traj)) % 2 == 0
    write_tum(tmp_path / "fix.txt", Trajectory(traj.stamps_ns[keep], corrected[keep]))
    result = _cli("correct", path, "--poses", tmp_path / "fix.txt", "--format", "tum", "--match", "stamp")
    assert result.returncode == 0, result.stderr
    assert "revision 1" in result.stdout
    out1 = tmp_path / "rev1.txt"
    assert _cli("export", path, "--trajectory", out1).returncode == 0
    exported = read_tum(out1)
    np.testing.assert_allclose(exported.poses[keep], corrected[keep], atol=1e-8)  # set directly
    assert not np.allclose(exported.poses[~keep], traj.poses[~keep], atol=1e-6)  # propagated, not left behind
    table = _cli("revisions", path)
    assert table.returncode == 0 and "external_file" in table.stdout
    assert _cli("rollback", path, "--to", "0").returncode == 0
    assert _cli("export", path, "--trajectory", tmp_path / "rev2.txt").returncode == 0
    np.testing.assert_array_equal(read_tum(tmp_path / "rev2.txt").poses, traj.poses)
    ply = tmp_path / "map.ply"
    result = _cli("export", path, "--revision", "1", "--map", ply, "--voxel-size-m", "0.05")
    assert result.returncode == 0, result.stderr
    assert len(o3d.io.read_point_cloud(str(ply)).points) > 1000
    bad = _cli("correct", path, "--poses", tmp_path / "missing.txt")
    assert bad.returncode == 1 and bad.stderr.strip().splitlines()[-1].startswith("error:")


def test_kitti_import_by_index_with_a_sliced_store(tmp_path: Path, kitchen_frames: list[Frame]) -> None:
    """Row i of a KITTI file is the pose of frame_id i: a full-length file works for a sliced store."""
    with FrameStore.create(tmp_path / "s") as store:
        for f in kitchen_frames[:4]:  # frame ids 0, 50, 100, 150
            store.append(f)
        full = np.tile(np.eye(4), (200, 1, 1))
        full[:, 0, 3] = np.arange(200) * 0.01
        write_kitti(tmp_path / "poses.txt", Trajectory(np.arange(200), full))
        rev, matched = store.import_poses(tmp_path / "poses.txt", format="kitti")
        assert len(matched.unmatched_rows) == 196
        for fid in (0, 50, 100, 150):
            np.testing.assert_allclose(store.ledger.pose(rev.revision_id, fid), full[fid], atol=1e-12)
        store.export_trajectory(tmp_path / "out.txt", format="kitti")
    out = read_kitti(tmp_path / "out.txt")
    assert len(out) == 4  # one row per stored frame, in frame order
    np.testing.assert_allclose(out.poses, full[[0, 50, 100, 150]], atol=1e-9)


def test_kitti_export_of_a_sliced_store_is_not_read_back_onto_the_wrong_frames(tmp_path: Path, kitchen_frames: list[Frame],
                                                                                caplog: pytest.LogCaptureFixture) -> None:
    """The KITTI export (one row per stored frame, the contract) of a store whose ids are not 0..N-1 does not
    read back as row i = frame_id i: import refuses it by default instead of moving frames; the TUM export
    round-trips by stamp, and re-importing the head's own poses says that it changes nothing."""
    with FrameStore.create(tmp_path / "s") as store:
        for f in kitchen_frames[:6]:  # frame ids 0, 50, ..., 250
            store.append(f)
        store.export_trajectory(tmp_path / "own.kitti", format="kitti")
        with pytest.raises(StoreError, match="one per stored frame"):
            store.import_poses(tmp_path / "own.kitti", format="kitti")
        with pytest.raises(ConfigError, match="no stamps"):
            store.import_poses(tmp_path / "own.kitti", format="kitti", match="stamp")
        store.export_trajectory(tmp_path / "own.tum", format="tum")
        with caplog.at_level(logging.WARNING, logger="driftmap.store.frame_store"):
            same, _ = store.import_poses(tmp_path / "own.tum", format="tum")
        assert any("changes no pose" in r.getMessage() for r in caplog.records)
        d = store.diff(0, same.revision_id)
        assert d.max_translation_m < 1e-9 and d.max_rotation_deg < 1e-7
        # a real change imports silently
        moved = store.poses(0).copy()
        moved[3:, 0, 3] += 0.02
        write_tum(tmp_path / "moved.tum", Trajectory(store.ledger.stamps_ns, moved))
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="driftmap.store.frame_store"):
            rev, _ = store.import_poses(tmp_path / "moved.tum")
            assert not any("changes no pose" in r.getMessage() for r in caplog.records)
            assert store.rollback(0).revision_id == rev.revision_id + 1
        d = store.diff(same.revision_id, rev.revision_id)
        assert np.count_nonzero(d.translation_m > 1e-6) == 3
        np.testing.assert_array_equal(store.poses(), store.poses(0))


def test_cli_info(kitchen_store: FrameStore) -> None:
    path = kitchen_store.path
    kitchen_store.close()
    out = _cli("info", path)
    assert out.returncode == 0, out.stderr
    # the table rows, whatever box characters rich draws: "│ frames │ 20 │" (not "frames flagged")
    n = len(FRAME_IDS)
    assert re.findall(r"^\W*frames\W+(\d+)\W*$", out.stdout, re.M) == [str(n)], out.stdout
    assert re.search(rf"^\W*frame ids\W+{FRAME_IDS[0]} \.\. {FRAME_IDS[-1]}\W*$", out.stdout, re.M), out.stdout
    assert re.search(rf"^\W*sensors\W+kinect \(depth_camera\): {n}\W*$", out.stdout, re.M), out.stdout
    assert "invalid-pixel fraction" in out.stdout and "MiB" in out.stdout


# ------------------------------------------------------------------------------------------ compiled queries


def reference_box(view: MapView, lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """Brute force over every map point, in map order: the numpy expression the box query was written with."""
    pts, owner = view.points_world, view.point_frame_ids()
    mask = np.all((pts >= np.asarray(lo, np.float64)) & (pts <= np.asarray(hi, np.float64)), axis=1)
    return pts[mask], owner[mask]


def reference_ball(view: MapView, c, r: float, z_range=(-np.inf, np.inf)) -> tuple[np.ndarray, np.ndarray]:
    pts, owner = view.points_world, view.point_frame_ids()
    in_band = (pts[:, 2] >= z_range[0]) & (pts[:, 2] <= z_range[1])
    mask = (np.sum((pts - np.asarray(c, np.float64)) ** 2, axis=1) <= r**2) & in_band
    return pts[mask], owner[mask]


def assert_same_result(got, expected: tuple[np.ndarray, np.ndarray]) -> None:
    """Same points bit for bit, in the same order, with the same frame ids (and the documented dtypes)."""
    assert got.points_world.dtype == np.float32 and got.points_world.shape == expected[0].shape
    assert got.frame_ids.dtype == np.int64
    assert got.points_world.tobytes() == expected[0].tobytes()
    assert np.array_equal(got.frame_ids, expected[1])


def assert_nearest_is_brute_force(view: MapView, q, z_range=None) -> None:
    """Distance equal to the brute-force minimum; the point is one at that distance, in the returned frame, and
    the first such point of that frame."""
    pts, owner = view.points_world, view.point_frame_ids()
    d2 = np.sum((pts - np.asarray(q, np.float64)) ** 2, axis=1)
    if z_range is not None:
        d2[(pts[:, 2] < z_range[0]) | (pts[:, 2] > z_range[1])] = np.inf
    d2[np.isnan(d2)] = np.inf
    near = view.nearest(q, z_range_m=z_range)
    assert near.distance_m == float(np.sqrt(d2.min()))
    ties = np.flatnonzero((np.sqrt(d2) == near.distance_m) & (owner == near.frame_id))
    assert ties.size > 0
    assert pts[ties[0]].tobytes() == near.point_world.tobytes()
    if z_range is not None:
        assert z_range[0] <= near.point_world[2] <= z_range[1]


@pytest.fixture(params=["serial", "parallel"])
def query_mode(request, monkeypatch: pytest.MonkeyPatch) -> str:
    """Small pieces (frames span many), run on the calling thread or forced onto the parallel kernels."""
    monkeypatch.setattr(view_module, "QUERY_PIECE_POINTS", 997)
    monkeypatch.setattr(view_module, "QUERY_PARALLEL_POINTS", 0 if request.param == "parallel" else 1 << 62)
    return request.param


def test_compiled_queries_equal_numpy_on_real_frames(kitchen_store: FrameStore, query_mode: str) -> None:
    view = MapView.from_store(kitchen_store, kitchen_store.head)
    pts = view.points_world
    rng = np.random.default_rng(11)
    boxes = []
    for i in rng.choice(len(pts), 6, replace=False):
        half = rng.uniform(0.05, 1.0, 3)
        boxes.append((pts[i] - half, pts[i] + half))
    a, b = pts[rng.choice(len(pts), 2, replace=False)]
    boxes.append((np.minimum(a, b), np.maximum(a, b)))  # faces through map points: inclusive
    boxes.append((pts.min(0), pts.max(0)))  # everything
    boxes.append((pts.max(0) + 1.0, pts.max(0) + 2.0))  # nothing
    boxes.append((pts[5] + 0.1, pts[5] - 0.1))  # min above max: nothing
    n_found = []
    for lo, hi in boxes:
        got = view.query_box(lo, hi)
        assert_same_result(got, reference_box(view, lo, hi))
        n_found.append(len(got.points_world))
    assert n_found[-2:] == [0, 0] and n_found[-3] == view.n_points and min(n_found[:7]) > 0
    for i, r in zip(rng.choice(len(pts), 4, replace=False), (0.02, 0.3, 1.5, 0.0)):
        assert_same_result(view.query_radius(pts[i], r), reference_ball(view, pts[i], r))
    assert len(view.query_radius(pts[3], 0.0).points_world) >= 1  # the point itself, at distance 0
    assert_same_result(view.query_radius(pts.max(0) + 5.0, 1.0), reference_ball(view, pts.max(0) + 5.0, 1.0))
    for q in [pts[7], pts[100] + [0.05, -0.02, 0.1], pts.mean(0), pts.max(0) + 3.0, [50.0, -20.0, 3.0]]:
        assert_nearest_is_brute_force(view, q)


def _grid_frame(frame_id: int, points: np.ndarray, t: tuple[float, float, float]) -> Frame:
    T = np.eye(4)
    T[:3, 3] = t  # translations on the 1/4 grid: world = sensor + t exactly in float32
    return Frame(frame_id=frame_id, stamp_ns=frame_id * 1000, sensor_name="lidar", sensor_kind=SensorKind.LIDAR,
                 points_sensor=np.ascontiguousarray(points, dtype=np.float32), pose=PoseEstimate(T))


def random_grid_map(seed: int) -> MapView:
    """Frames of random points on a 1/4 m grid (so query faces pass exactly through points, and equal distances
    tie exactly), with an empty frame, NaN points (also negative NaN) and one frame of NaN points only."""
    rng = np.random.default_rng(seed)
    frames = []
    for k in range(12):
        n = [3000, 0, 1, 2500, 40, 5000][k % 6]
        pts = rng.integers(-8, 9, size=(n, 3)) / 4.0
        if k == 3:
            pts[::7, k % 3] = np.nan
            pts[1::11, 1] = np.copysign(np.nan, -1.0)
        frames.append(_grid_frame(10 * k + 1, pts, tuple(rng.integers(-8, 9, 3) / 4.0)))
    frames.append(_grid_frame(500, np.full((5, 3), np.nan), (0.0, 0.0, 0.0)))
    return MapView.from_frames(frames)


def test_compiled_queries_equal_numpy_on_random_grids(query_mode: str) -> None:
    rng = np.random.default_rng(5)
    for seed in range(3):
        view = random_grid_map(seed)
        pts = view.points_world
        assert np.isnan(pts).any() and view.n_points > 10_000
        n_on_faces = 0
        for _ in range(25):
            lo = rng.integers(-16, 17, 3) / 4.0
            hi = lo + rng.integers(0, 12, 3) / 4.0
            got = view.query_box(lo, hi)
            assert_same_result(got, reference_box(view, lo, hi))
            on_face = np.any((got.points_world == lo) | (got.points_world == hi), axis=1)
            n_on_faces += int(on_face.sum())  # grid points on the faces are inside
            # one float32 step inside the faces: the points on the faces are left out
            inner = (np.nextafter(lo.astype(np.float32), np.float32(np.inf)),
                     np.nextafter(hi.astype(np.float32), np.float32(-np.inf)))
            assert_same_result(view.query_box(*inner), reference_box(view, *inner))
            assert len(view.query_box(*inner).points_world) == len(got.points_world) - int(on_face.sum())
            c, r = rng.integers(-12, 13, 3) / 4.0, float(rng.integers(0, 9)) / 4.0
            ball = view.query_radius(c, r)
            assert_same_result(ball, reference_ball(view, c, r))
            # a map point exactly on the sphere is inside; with the radius one step smaller it is not
            p0 = pts[rng.integers(len(pts))].astype(np.float64)
            if np.isnan(p0).any():
                continue
            c0 = p0 + [0.0, 0.5, 0.0]
            on_sphere = view.query_radius(c0, 0.5)
            assert_same_result(on_sphere, reference_ball(view, c0, 0.5))
            assert np.any(np.all(on_sphere.points_world == p0, axis=1))
            smaller = view.query_radius(c0, float(np.nextafter(0.5, 0.0)))
            assert not np.any(np.all(smaller.points_world == p0, axis=1))
            assert_nearest_is_brute_force(view, c)
            assert_nearest_is_brute_force(view, c + 0.125)  # many points at exactly the same distance
        assert n_on_faces > 0
        nothing = (np.zeros((0, 3), np.float32), np.zeros(0, np.int64))
        assert_same_result(view.query_box([9, 9, 9], [10, 10, 10]), nothing)
        # a NaN query position is an upstream bug: answering "nothing there" would read as free space
        for query in (lambda: view.query_radius([np.nan, 0, 0], 1.0), lambda: view.nearest([0, np.nan, 0]),
                      lambda: view.query_box([0, 0, np.nan], [1, 1, 1])):
            with pytest.raises(ConfigError, match="NaN coordinate"):
                query()


def test_height_band_filters_nearest_and_the_queries(kitchen_store: FrameStore, query_mode: str) -> None:
    view = MapView.from_store(kitchen_store, kitchen_store.head)
    pts = view.points_world
    z_lo, z_hi = np.quantile(pts[:, 2], [0.55, 0.7])
    band = (float(z_lo), float(z_hi))
    below = pts[np.argmin(pts[:, 2])]  # the lowest map point: its own nearest point, but not in the band
    assert_nearest_is_brute_force(view, below, band)
    near = view.nearest(below, z_range_m=band)
    assert near.distance_m > 0 and view.nearest(below).distance_m == 0.0
    for q in (pts[42], pts.mean(0), pts.max(0) + 1.0):
        assert_nearest_is_brute_force(view, q, band)
        assert_same_result(view.query_radius(q, 0.8, z_range_m=band), reference_ball(view, q, 0.8, band))
    lo, hi = pts.min(0), pts.max(0)
    got = view.query_box(lo, hi, z_range_m=band)
    assert_same_result(got, reference_box(view, [lo[0], lo[1], band[0]], [hi[0], hi[1], band[1]]))
    assert 0 < len(got.points_world) < view.n_points
    assert np.all((got.points_world[:, 2] >= band[0]) & (got.points_world[:, 2] <= band[1]))
    with pytest.raises(StoreError, match="no points with z in"):
        view.nearest(pts[0], z_range_m=(float(hi[2]) + 1.0, float(hi[2]) + 2.0))
    with pytest.raises(ConfigError, match="z_range_m"):
        view.nearest(pts[0], z_range_m=(1.0, 0.0))
    with pytest.raises(ConfigError, match="center_m"):
        view.query_radius([0.0, 1.0], 0.5)
    with pytest.raises(ConfigError, match="radius_m"):
        view.query_radius(pts[0], -0.5)


def test_queries_on_an_empty_map() -> None:
    view = MapView.from_frames([])
    assert_same_result(view.query_box([-1, -1, -1], [1, 1, 1]), (np.zeros((0, 3), np.float32), np.zeros(0, np.int64)))
    assert_same_result(view.query_radius([0, 0, 0], 1.0), (np.zeros((0, 3), np.float32), np.zeros(0, np.int64)))
    with pytest.raises(StoreError, match="no points"):
        view.nearest([0.0, 0.0, 0.0])


def test_queries_follow_corrections_rollbacks_and_new_frames(tmp_path: Path, kitchen_frames: list[Frame],
                                                             query_mode: str) -> None:
    """The queries keep per-piece boxes of the map's points; after apply (frames moved a metre), refresh (new
    frames) and a rollback they still equal brute force over the map's current points."""

    def check_queries(view: MapView, around: np.ndarray) -> None:
        for lo, hi in ((around - 0.1, around + 0.1), (around - [1.0, 0.5, 0.3], around + [0.2, 0.6, 1.0])):
            assert_same_result(view.query_box(lo, hi), reference_box(view, lo, hi))
        assert_same_result(view.query_radius(around, 0.25), reference_ball(view, around, 0.25))
        for q in (around, around + [0.0, 0.3, -0.2]):
            assert_nearest_is_brute_force(view, q)
        assert len(view.query_box(around - 0.1, around + 0.1).points_world) > 0

    with FrameStore.create(tmp_path / "q") as store:
        for f in kitchen_frames[:12]:
            store.append(f)
        view = MapView.from_store(store, store.head)
        ids = [int(i) for i in store.frame_ids]
        check_queries(view, view.frame_points_world(ids[4])[100].astype(np.float64))
        shift = np.eye(4)
        shift[:3, 3] = [1.0, -0.5, 0.25]
        moved = ids[3:7]
        rev = store.add_revision({i: shift @ store.poses()[ids.index(i)] for i in moved}, source="external_file",
                                 propagate=False)
        view.apply(rev.revision_id)
        check_queries(view, view.frame_points_world(ids[4])[100].astype(np.float64))  # where the frame is now
        for f in kitchen_frames[12:]:
            store.append(f)
        assert view.refresh() == [f.frame_id for f in kitchen_frames[12:]]
        check_queries(view, view.frame_points_world(kitchen_frames[-1].frame_id)[50].astype(np.float64))
        back = store.rollback(to=0)
        view.apply(back.revision_id)
        check_queries(view, view.frame_points_world(ids[4])[100].astype(np.float64))


def test_queries_after_a_failed_read_see_the_points_the_map_holds(tmp_path: Path, kitchen_frames: list[Frame]) -> None:
    """A read error during apply leaves some frames stale (pose NaN): the queries re-measure those frames' pieces
    from the points the map holds, before and after the map recovers."""
    frames = kitchen_frames[:4]
    shift = np.eye(4)
    shift[:3, 3] = [0.8, 0.0, -0.4]
    with FrameStore.create(tmp_path / "t") as store:
        for f in frames:
            store.append(f)
        rev = store.add_revision({f.frame_id: shift @ f.T_world_sensor for f in frames}, source="external_file")
    store = FrameStore.open(tmp_path / "t")
    view = MapView.from_store(store, 0)
    around = view.frame_points_world(frames[1].frame_id)[10].astype(np.float64)
    assert_same_result(view.query_box(around - 0.2, around + 0.2), reference_box(view, around - 0.2, around + 0.2))
    last = store.frame_ref(frames[-1].frame_id)
    original = last.segment.read_bytes()
    with open(last.segment, "r+b") as fh:
        fh.truncate(last.payload_offset + 1000)
    with pytest.raises(StoreError):
        view.apply(rev.revision_id)
    moved = view.frame_points_world(frames[1].frame_id)[10].astype(np.float64)
    for q in (around, moved):
        assert_same_result(view.query_box(q - 0.2, q + 0.2), reference_box(view, q - 0.2, q + 0.2))
        assert_same_result(view.query_radius(q, 0.3), reference_ball(view, q, 0.3))
        assert_nearest_is_brute_force(view, q + 0.05)
    last.segment.write_bytes(original)
    view.apply(rev.revision_id)
    moved = view.frame_points_world(frames[1].frame_id)[10].astype(np.float64)
    assert_same_result(view.query_box(moved - 0.2, moved + 0.2), reference_box(view, moved - 0.2, moved + 0.2))
    assert len(view.query_box(moved - 0.2, moved + 0.2).points_world) > 0
    store.close()
