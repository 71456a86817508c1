"""The Foxglove MCAP export of one pose revision: read back with the generic ``mcap`` reader and the protobuf
decoder only (no driftmap code on the reading side), the file holds exactly the revision's poses, its fused
map, every frame's downsampled points, the double walls, and metadata; bad inputs raise typed errors."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from driftmap import ConfigError, StoreError, __version__
from driftmap.demo import embedded_log_path
from driftmap.diagnostics.double_wall import DoubleWallRegion, DoubleWallResult
from driftmap.errors import ExportError
from driftmap.export.foxglove import export_foxglove_mcap
from driftmap.map.view import MapView
from driftmap.pipeline.build import build
from driftmap.preprocess.cloud import voxel_downsample
from driftmap.store.frame_store import FrameStore

MAP_VOXEL_M = 0.02
FRAME_VOXEL_M = 0.05
N_FRAMES = 20


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> FrameStore:
    """20 frames of the embedded synthetic log with its drifting odometry (revision 0), the ground truth
    imported as revision 1 (the correction), and revision 2 (another correction) on top."""
    log = embedded_log_path()
    out = tmp_path_factory.mktemp("fx") / "store"
    build(log, out, poses_from_source=True, frames=f"0:{N_FRAMES}", loop_closure=False)
    with FrameStore.open(out, "a") as s:
        s.import_poses(log / "groundtruth.txt", format="tum")
        shift = np.eye(4)
        shift[:3, 3] = [0.3, -0.2, 0.1]
        s.add_revision({int(f): shift @ T for f, T in zip(s.frame_ids, s.poses(1))}, source="external_file")
    s = FrameStore.open(out)
    yield s
    s.close()


def read_back(path: Path) -> tuple[Any, dict[str, list[tuple[Any, Any, Any]]], dict[str, dict[str, str]]]:
    """(summary, topic -> [(channel, message record, decoded)], metadata name -> dict), generic reader only."""
    by_topic: dict[str, list] = defaultdict(list)
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        for _, channel, message, decoded in reader.iter_decoded_messages(log_time_order=False):
            by_topic[channel.topic].append((channel, message, decoded))
        metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
    return summary, by_topic, metadata


def decode_cloud(msg: Any) -> dict[str, np.ndarray]:
    """Every float32 field of a foxglove.PointCloud as a column (the export writes float32 and uint8 only)."""
    data = np.frombuffer(msg.data, dtype=np.uint8).reshape(-1, msg.point_stride)
    cols = {}
    for f in msg.fields:
        if f.type == 7:  # FLOAT32
            cols[f.name] = np.ascontiguousarray(data[:, f.offset : f.offset + 4]).view("<f4")[:, 0]
    return cols


def xyz(msg: Any) -> np.ndarray:
    c = decode_cloud(msg)
    return np.stack([c["x"], c["y"], c["z"]], axis=1)


def matrix(translation: Any, rotation: Any) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat([rotation.x, rotation.y, rotation.z, rotation.w]).as_matrix()
    T[:3, 3] = [translation.x, translation.y, translation.z]
    return T


def sort_rows(a: np.ndarray) -> np.ndarray:
    return a[np.lexsort(a.T[::-1])]


@pytest.fixture(scope="module")
def exported(store: FrameStore, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Any]:
    path = tmp_path_factory.mktemp("fx_out") / "rev1.mcap"
    stages: list[tuple[str, int, int | None]] = []
    summary = export_foxglove_mcap(store, path, revision=1, map_voxel_size_m=MAP_VOXEL_M, frame_voxel_size_m=FRAME_VOXEL_M,
                                   progress=lambda *a: stages.append(a))
    assert stages[-1] == ("frames", N_FRAMES, N_FRAMES)
    return path, summary


def test_file_is_an_indexed_mcap_of_foxglove_schemas_with_one_message_per_frame(exported, store: FrameStore) -> None:
    path, summary = exported
    raw = path.read_bytes()
    assert raw[:8] == raw[-8:] == b"\x89MCAP0\r\n"
    mcap_summary, by_topic, _ = read_back(path)
    assert mcap_summary is not None and mcap_summary.chunk_indexes and mcap_summary.statistics is not None
    assert {s.name for s in mcap_summary.schemas.values()} == {"foxglove.PointCloud", "foxglove.PosesInFrame", "foxglove.FrameTransform"}
    assert all(s.encoding == "protobuf" for s in mcap_summary.schemas.values())
    counts = {topic: len(v) for topic, v in by_topic.items()}
    assert counts == {"/map": 1, "/trajectory": 1, "/tf": len(store), "/points": len(store)} == summary.message_counts
    assert mcap_summary.statistics.message_count == sum(counts.values())
    assert summary.n_frames == len(store) == N_FRAMES and summary.revision == 1 and summary.bytes == len(raw)


def test_tf_and_trajectory_are_the_poses_of_the_exported_revision(exported, store: FrameStore) -> None:
    path, _ = exported
    _, by_topic, _ = read_back(path)
    ids = [int(f) for f in store.frame_ids]
    stamps = {int(f): int(s) for f, s in zip(store.frame_ids, store.ledger.stamps_ns)}
    expected = {f: T for f, T in zip(ids, store.poses(1))}
    seen = {}
    for _, message, tf in by_topic["/tf"]:
        assert tf.parent_frame_id == "world"
        fid = int(tf.child_frame_id.rsplit("@", 1)[1])
        assert tf.child_frame_id == f"{store.frame_info(fid)['sensor_frame']}@{fid:06d}"
        assert tf.timestamp.ToNanoseconds() == message.log_time == stamps[fid]
        seen[fid] = matrix(tf.translation, tf.rotation)
    assert sorted(seen) == ids
    for fid in ids:
        assert np.max(np.abs(seen[fid] - expected[fid])) <= 1e-6
    # the correction really changed the poses, and revision 2 was not exported by mistake
    assert max(np.max(np.abs(seen[f] - T)) for f, T in zip(ids, store.poses(0))) > 1e-3
    assert min(np.max(np.abs(seen[f] - T)) for f, T in zip(ids, store.poses(2))) > 0.1
    # log times never go backwards (frames play in time order)
    log_times = [m.log_time for _, m, _ in by_topic["/tf"]]
    assert log_times == sorted(log_times)
    ((_, _, traj),) = by_topic["/trajectory"]
    assert traj.frame_id == "world" and len(traj.poses) == len(ids)
    order = np.argsort([stamps[f] for f in ids], kind="stable")
    for k, pose in zip(order, traj.poses):
        assert np.max(np.abs(matrix(pose.position, pose.orientation) - expected[ids[k]])) <= 1e-6


def test_map_is_the_fused_map_of_the_revision_and_lies_on_the_frames(exported, store: FrameStore) -> None:
    path, summary = exported
    _, by_topic, _ = read_back(path)
    ((_, message, cloud),) = by_topic["/map"]
    assert cloud.frame_id == "world"
    assert message.log_time == cloud.timestamp.ToNanoseconds() == int(store.ledger.stamps_ns.min())
    cols = decode_cloud(cloud)
    points = np.stack([cols["x"], cols["y"], cols["z"]], axis=1)
    fused = MapView.from_store(store, 1).fused(MAP_VOXEL_M)
    assert points.tobytes() == fused.points_world.astype("<f4").tobytes()
    assert np.array_equal(cols["n_frames"], fused.n_frames_per_point().astype(np.float32))
    first = np.array([fused.frames_of(i).min() for i in range(len(fused.points_world))], dtype=np.float32)
    assert np.array_equal(cols["frame_id"], first)
    assert summary.n_map_points == len(points) and cols["n_frames"].max() > 1
    # independent of MapView: every voxel centroid lies within one voxel diagonal of a raw point placed
    # with the decoded /tf pose of the exported revision
    tf = {int(t.child_frame_id.rsplit("@", 1)[1]): matrix(t.translation, t.rotation) for _, _, t in by_topic["/tf"]}
    raw_world = np.concatenate([store.frame(f).points_sensor.astype(np.float64) @ T[:3, :3].T + T[:3, 3] for f, T in tf.items()])
    d, _ = cKDTree(raw_world).query(points.astype(np.float64), distance_upper_bound=1.0)
    assert np.max(d) <= MAP_VOXEL_M * np.sqrt(3) + 1e-6


def test_points_are_the_downsampled_sensor_points_and_land_on_the_map(exported, store: FrameStore) -> None:
    path, summary = exported
    _, by_topic, _ = read_back(path)
    tf = {t.child_frame_id: (m.log_time, matrix(t.translation, t.rotation)) for _, m, t in by_topic["/tf"]}
    ((_, _, map_cloud),) = by_topic["/map"]
    map_tree = cKDTree(xyz(map_cloud).astype(np.float64))
    n_total = 0
    for _, message, cloud in by_topic["/points"]:
        fid = int(cloud.frame_id.rsplit("@", 1)[1])
        log_time, T = tf[cloud.frame_id]  # every cloud has its own coordinate frame on /tf, at its stamp
        assert message.log_time == cloud.timestamp.ToNanoseconds() == log_time
        assert [f.name for f in cloud.fields] == ["x", "y", "z"] and cloud.point_stride == 12
        pts = xyz(cloud)
        expected, _ = voxel_downsample(store.frame(fid), FRAME_VOXEL_M)
        assert len(pts) == expected.n_points < store.frame(fid).n_points
        np.testing.assert_allclose(sort_rows(pts), sort_rows(expected.points_sensor), atol=1e-6, rtol=0)
        # placed with its /tf transform, the frame lands on the corrected map
        d, _ = map_tree.query(pts.astype(np.float64) @ T[:3, :3].T + T[:3, 3])
        assert np.median(d) < FRAME_VOXEL_M
        n_total += len(pts)
    assert n_total == summary.n_frame_points


def test_metadata_names_the_version_store_and_revision(exported, store: FrameStore) -> None:
    path, _ = exported
    _, _, metadata = read_back(path)
    meta = metadata["driftmap.foxglove_export"]
    assert meta["driftmap_version"] == __version__
    assert Path(meta["store_path"]) == Path(store.path).resolve()
    assert meta["revision"] == "1" and meta["revision_source"] == store.ledger.revision(1).source.value
    assert meta["head_revision"] == "2" and meta["n_frames"] == str(N_FRAMES)
    assert "synthetic-loop" in meta["source"]
    assert float(meta["map_voxel_size_m"]) == MAP_VOXEL_M and float(meta["frame_voxel_size_m"]) == FRAME_VOXEL_M


def region(center: list[float], normal: list[float], separation_m: float, frames_a: list[int], frames_b: list[int]) -> DoubleWallRegion:
    return DoubleWallRegion(
        center_m=np.array(center), normal=np.array(normal), separation_m=separation_m, separation_sigma_m=0.002,
        offset_b_minus_a_m=-separation_m, frames_a=np.array(frames_a), frames_b=np.array(frames_b),
        stamp_ns_a=(frames_a[0] * 10, frames_a[-1] * 10), stamp_ns_b=(frames_b[0] * 10, frames_b[-1] * 10),
        n_voxels=3, voxel_sizes_m=(0.1, 0.2), n_points=500)


@pytest.mark.parametrize("as_result", [False, True])
def test_double_walls_scene_and_frames_left_out(store: FrameStore, tmp_path: Path, as_result: bool) -> None:
    regions = [region([1.0, 2.0, 0.5], [0.0, 1.0, 0.0], 0.04, [0, 1, 2], [17, 18, 19]),
               region([-1.0, 0.0, 1.0], [0.6, 0.0, -0.8], 0.012, [3, 5], [12, 14, 16])]
    walls = DoubleWallResult(scales=[], regions=regions, frame_ids=store.frame_ids, stamps_ns=store.ledger.stamps_ns) if as_result else regions
    path = tmp_path / "walls.mcap"
    summary = export_foxglove_mcap(store, path, map_voxel_size_m=0.1, include_frames=False, double_walls=walls)
    assert summary.revision == store.head == 2 and summary.n_double_walls == 2 and summary.n_frame_points == 0
    mcap_summary, by_topic, _ = read_back(path)
    assert "/points" not in by_topic and len(by_topic["/tf"]) == len(store)
    assert "foxglove.SceneUpdate" in {s.name for s in mcap_summary.schemas.values()}
    ((_, _, scene),) = by_topic["/double_walls"]
    assert [e.id for e in scene.entities] == ["double_wall_0000", "double_wall_0001"]
    for entity, reg in zip(scene.entities, regions):
        assert entity.frame_id == "world"
        (cube,), (arrow,) = entity.cubes, entity.arrows
        np.testing.assert_allclose([cube.pose.position.x, cube.pose.position.y, cube.pose.position.z], reg.center_m, atol=1e-12)
        T = matrix(cube.pose.position, cube.pose.orientation)
        normal = reg.normal / np.linalg.norm(reg.normal)
        assert abs(abs(T[:3, 2] @ normal) - 1) < 1e-9  # the cube's thin side is along the wall normal
        assert cube.size.z == pytest.approx(reg.separation_m)
        # the arrow points from layer A to layer B: offset_b_minus_a_m < 0 here, so against the normal
        assert matrix(arrow.pose.position, arrow.pose.orientation)[:3, 0] @ normal == pytest.approx(-1.0)
        meta = {kv.key: kv.value for kv in entity.metadata}
        assert float(meta["separation_m"]) == pytest.approx(reg.separation_m)
        assert meta["frames_a"].startswith(f"{reg.frames_a.min()}..{reg.frames_a.max()}")
        assert meta["frames_b"].startswith(f"{reg.frames_b.min()}..{reg.frames_b.max()}")
    # the wider separation is drawn redder (less green)
    assert scene.entities[0].cubes[0].color.g < scene.entities[1].cubes[0].color.g


def test_bad_inputs_raise_typed_errors_and_never_leave_a_partial_file(store: FrameStore, tmp_path: Path) -> None:
    path = tmp_path / "out.mcap"
    with pytest.raises(StoreError, match="revision 7 does not exist"):
        export_foxglove_mcap(store, path, revision=7)
    with pytest.raises(ConfigError, match="map_voxel_size_m"):
        export_foxglove_mcap(store, path, map_voxel_size_m=0.0)
    with pytest.raises(ConfigError, match="frame_voxel_size_m"):
        export_foxglove_mcap(store, path, frame_voxel_size_m=-1.0)
    assert not path.exists() and not list(tmp_path.iterdir())
    path.write_bytes(b"not an mcap")
    with pytest.raises(ExportError, match="already exists"):
        export_foxglove_mcap(store, path, revision=0, map_voxel_size_m=0.1, include_frames=False)
    assert path.read_bytes() == b"not an mcap"
    with pytest.raises(ExportError, match="directory"):
        export_foxglove_mcap(store, tmp_path, map_voxel_size_m=0.1)
    summary = export_foxglove_mcap(store, path, revision=0, map_voxel_size_m=0.1, include_frames=False, overwrite=True)
    _, by_topic, metadata = read_back(path)
    assert summary.revision == 0 and metadata["driftmap.foxglove_export"]["revision"] == "0"
    T0 = {int(f): T for f, T in zip(store.frame_ids, store.poses(0))}
    for _, _, tf in by_topic["/tf"]:
        assert np.max(np.abs(matrix(tf.translation, tf.rotation) - T0[int(tf.child_frame_id.rsplit("@", 1)[1])])) <= 1e-6
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.mcap"]  # no temporary file left behind


def test_cli_export_mcap_writes_the_requested_revision_and_refuses_to_overwrite(store: FrameStore, tmp_path: Path) -> None:
    import os
    import subprocess
    import sys

    out = tmp_path / "cli.mcap"
    cmd = [sys.executable, "-m", "driftmap.cli", "export", str(store.path), "--revision", "1", "--mcap", str(out)]
    env = {**os.environ, "COLUMNS": "200"}
    first = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env)
    assert first.returncode == 0, first.stderr
    assert "foxglove mcap (revision 1" in first.stdout
    _, messages, _ = read_back(out)
    tf = {m.child_frame_id: matrix(m.translation, m.rotation) for _, _, m in messages["/tf"]}
    assert len(tf) == len(store)
    assert max(np.abs(T - store.poses(1)[k]).max() for k, T in enumerate(tf[name] for name in sorted(tf, key=lambda n: int(n.rsplit("@", 1)[1])))) < 1e-6
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env)
    assert again.returncode == 1 and "already exists" in again.stderr and "Traceback" not in again.stderr
    assert subprocess.run(cmd + ["--overwrite"], capture_output=True, text=True, timeout=300, env=env).returncode == 0
