"""The frame store: bit-identical round trips, crash safety, damage detection and recovery, rejection of
bad appends, and a store Foxglove can read."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from driftmap import Frame, PinholeIntrinsics, PointAttributes, PoseEstimate, PoseSource, StoreError
from driftmap.errors import ConfigError
from driftmap.preprocess.depth import depth_frame
from driftmap.sources.synthetic import SyntheticLog
from driftmap.demo import embedded_log_path
from driftmap.store.frame_store import FrameStore, StoreCorruptError

K_7SCENES = PinholeIntrinsics(fx=585, fy=585, cx=320, cy=240, width=640, height=480)


def sevenscenes_frame(folder: Path, index: int, *, stride_px: int = 1) -> Frame:
    depth = np.asarray(Image.open(folder / f"frame-{index:06d}.depth.png"))
    T = np.loadtxt(folder / f"frame-{index:06d}.pose.txt")
    frame = depth_frame(depth, K_7SCENES, frame_id=index, stamp_ns=index * 33_333_333, depth_scale=1000.0,
                        min_depth_m=0.2, max_depth_m=4.0, sensor_name="kinect", sensor_frame="kinect_depth_optical",
                        pose=PoseEstimate(T, source=PoseSource.GROUND_TRUTH))
    if stride_px > 1:
        frame = frame.with_points(frame.points_sensor[::stride_px])
    return frame


def assert_frames_identical(a: Frame, b: Frame) -> None:
    assert a.frame_id == b.frame_id and a.stamp_ns == b.stamp_ns
    assert a.sensor_name == b.sensor_name and a.sensor_kind == b.sensor_kind
    assert a.sensor_frame == b.sensor_frame and a.base_frame == b.base_frame
    assert a.points_sensor.tobytes() == b.points_sensor.tobytes()
    assert a.T_base_sensor.tobytes() == b.T_base_sensor.tobytes()
    assert a.pose.T_world_sensor.tobytes() == b.pose.T_world_sensor.tobytes()
    assert a.pose.revision == b.pose.revision and a.pose.source == b.pose.source
    assert (a.pose.covariance_6x6 is None) == (b.pose.covariance_6x6 is None)
    if a.pose.covariance_6x6 is not None:
        assert a.pose.covariance_6x6.tobytes() == b.pose.covariance_6x6.tobytes()
    assert a.intrinsics == b.intrinsics and a.depth_scale == b.depth_scale
    # every FrameQuality field, none allowed to differ: the store writes invalid_counts as a JSON object and flags
    # as a list, and FrameQuality turns them back into a read-only mapping and a tuple, so they compare equal
    assert (a.quality is None) == (b.quality is None)
    if a.quality is not None:
        for f in dataclasses.fields(a.quality):
            x, y = getattr(a.quality, f.name), getattr(b.quality, f.name)
            assert type(x) is type(y) and x == y, f"quality.{f.name}: {x!r} != {y!r}"
    assert a.provenance == b.provenance
    for name in ("intensity", "color_rgb", "normal_sensor", "time_offset_ns"):
        x, y = getattr(a.attributes, name), getattr(b.attributes, name)
        assert (x is None) == (y is None), name
        if x is not None:
            assert x.dtype == y.dtype and x.tobytes() == y.tobytes(), name


@pytest.fixture(scope="module")
def synthetic_frames() -> list[Frame]:
    log = SyntheticLog(embedded_log_path(generate_if_missing=False))
    return [log.frame(i) for i in range(12)]


def with_attributes(frame: Frame, seed: int) -> Frame:
    rng = np.random.default_rng(seed)
    n = frame.n_points
    normals = rng.normal(size=(n, 3)).astype(np.float32)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    attrs = PointAttributes(
        intensity=rng.random(n, dtype=np.float32),
        color_rgb=rng.integers(0, 256, (n, 3), dtype=np.uint8),
        normal_sensor=normals,
        time_offset_ns=rng.integers(-50_000_000, 50_000_000, n),
    )
    cov = np.diag(rng.random(6) + 0.1)
    pose = PoseEstimate(frame.T_world_sensor, revision=0, source=PoseSource.ODOMETRY, covariance_6x6=cov)
    return frame.with_points(frame.points_sensor, attrs).with_pose(pose)


def test_round_trip_is_bit_identical(tmp_path: Path, synthetic_frames: list[Frame], sevenscenes_dir: Path) -> None:
    frames = [with_attributes(synthetic_frames[0], 1), *synthetic_frames[1:4], sevenscenes_frame(sevenscenes_dir, 640)]
    with FrameStore.create(tmp_path / "s") as store:
        for f in frames:
            store.append(f)
        assert_frames_identical(store.frame(frames[0].frame_id), frames[0])  # readable while writing
    with FrameStore.open(tmp_path / "s") as store:
        assert [int(i) for i in store.frame_ids] == sorted(f.frame_id for f in frames)
        for f in frames:
            assert_frames_identical(store.frame(f.frame_id), f)
        assert store.recovery_events == []


def test_reopen_and_append_creates_a_new_segment(tmp_path: Path, synthetic_frames: list[Frame]) -> None:
    with FrameStore.create(tmp_path / "s") as store:
        for f in synthetic_frames[:3]:
            store.append(f)
    with FrameStore.open(tmp_path / "s", "a") as store:
        for f in synthetic_frames[3:6]:
            store.append(f)
    manifest = json.loads((tmp_path / "s" / "store.json").read_text())
    assert [s["state"] for s in manifest["segments"]] == ["closed", "closed"]
    with FrameStore.open(tmp_path / "s") as store:
        assert len(store) == 6
        for f in synthetic_frames[:6]:
            assert_frames_identical(store.frame(f.frame_id), f)


def test_bad_appends_are_rejected_and_change_nothing(tmp_path: Path, synthetic_frames: list[Frame]) -> None:
    path = tmp_path / "s"
    with FrameStore.create(path) as store:
        for f in synthetic_frames[:4]:
            store.append(f)
        rev = store.add_revision({0: synthetic_frames[0].T_world_sensor @ np.diag([1.0, 1, 1, 1])}, source="loop_closure")
        assert rev.revision_id == 1
        size_before = store.size_bytes()
        with pytest.raises(StoreError, match="frame 2 is already stored"):
            store.append(synthetic_frames[2])
        with pytest.raises(StoreError, match="999"):
            store.add_revision({999: np.eye(4)}, source="external_file")
        with pytest.raises(StoreError, match="(?i)parent"):
            store.add_revision({1: np.eye(4)}, source="external_file", parent=7)
        # misspelt choices are typed errors naming the accepted values, not bare ValueErrors
        with pytest.raises(ConfigError, match=r"add_revision source: 'bogus' is not one of \[.*'loop_closure'"):
            store.add_revision({1: np.eye(4)}, source="bogus")
        poses = tmp_path / "poses.txt"
        store.export_trajectory(poses)
        with pytest.raises(ConfigError, match=r"poses.txt: format: 'xyz' is not one of \['tum', 'kitti', 'redwood', '4x4', 'euroc'\]"):
            store.import_poses(poses, format="xyz")
        with pytest.raises(ConfigError, match=r"poses.txt: match: 'nearest' is not one of"):
            store.import_poses(poses, match="nearest")
        with pytest.raises(ConfigError, match=r"poses.txt: source: 'gps' is not one of"):
            store.import_poses(poses, source="gps")
        with pytest.raises(ConfigError, match=r"out.txt: format: 'xyz' is not one of"):
            store.export_trajectory(tmp_path / "out.txt", format="xyz")
        with pytest.raises(ConfigError, match=r"out.txt: trajectories are exported as tum or kitti, not 4x4"):
            store.export_trajectory(tmp_path / "out.txt", format="4x4")  # read, not written
        assert not (tmp_path / "out.txt").exists()
        assert store.size_bytes() == size_before
        assert len(store.revisions) == 2 and len(store) == 4
    with FrameStore.open(path) as store:
        assert len(store.revisions) == 2 and len(store) == 4


def test_a_second_writer_is_refused(tmp_path: Path, synthetic_frames: list[Frame]) -> None:
    with FrameStore.create(tmp_path / "s") as store:
        store.append(synthetic_frames[0])
        with pytest.raises(StoreError, match="another process"):
            FrameStore.open(tmp_path / "s", "a")
        # a reader may open while the writer appends, and sees the committed frames
        with FrameStore.open(tmp_path / "s") as reader:
            assert [int(i) for i in reader.frame_ids] == [0]
            assert_frames_identical(reader.frame(0), synthetic_frames[0])


WRITER_SCRIPT = textwrap.dedent(
    """
    import sys, numpy as np
    from driftmap import Frame, PoseEstimate, SensorKind
    from driftmap.store.frame_store import FrameStore
    path, n = sys.argv[1], int(sys.argv[2])
    store = FrameStore.create(path)
    rng = np.random.default_rng(0)
    for i in range(n):
        pts = rng.normal(size=(400_000, 3)).astype(np.float32)
        T = np.eye(4); T[0, 3] = i
        print(f"begin {i}", flush=True)
        store.append(Frame(frame_id=i, stamp_ns=i * 1000, sensor_name="lidar", sensor_kind=SensorKind.LIDAR,
                           points_sensor=pts, pose=PoseEstimate(T)))
        if i == 2:
            store.add_revision({0: np.eye(4)}, source="loop_closure")
    """
)


def _expected_points(i: int) -> np.ndarray:
    rng = np.random.default_rng(0)
    for _ in range(i):
        rng.normal(size=(400_000, 3))
    return rng.normal(size=(400_000, 3)).astype(np.float32)


def test_sigkill_mid_append_loses_at_most_the_frame_in_flight(tmp_path: Path) -> None:
    path = tmp_path / "s"
    proc = subprocess.Popen([sys.executable, "-c", WRITER_SCRIPT, str(path), "1000"], stdout=subprocess.PIPE, text=True)
    started = -1
    while started < 6:
        line = proc.stdout.readline()
        assert line, "writer died early"
        started = int(line.split()[1])
    time.sleep(0.004)  # let it get into the middle of writing frame 6 or 7
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    with FrameStore.open(path) as store:  # a reader after the crash: everything committed, the tail dropped
        ids = [int(i) for i in store.frame_ids]
        assert ids == list(range(len(ids))) and len(ids) >= 6
        assert len(store.revisions) == 2
        for i in (0, len(ids) - 1):
            assert store.frame(i).points_sensor.tobytes() == _expected_points(i).tobytes()
    with FrameStore.open(path, "a") as store:  # a writer recovers the segment and appends again
        assert [int(i) for i in store.frame_ids] == ids
        store.append(Frame(frame_id=5000, stamp_ns=10**12, sensor_name="lidar", sensor_kind="lidar",
                           points_sensor=np.ones((10, 3), np.float32), pose=PoseEstimate(np.eye(4))))
    with FrameStore.open(path) as store:
        assert len(store) == len(ids) + 1 and len(store.revisions) == 2
        assert store.frame(ids[-1]).points_sensor.tobytes() == _expected_points(ids[-1]).tobytes()
        manifest = json.loads((path / "store.json").read_text())
        assert all(s["state"] == "closed" for s in manifest["segments"])


def _crashed_store(path: Path, frames: list[Frame], cut_into_last: int) -> int:
    """A store whose writer 'died' while writing its last frame: the manifest says open, the file ends
    ``cut_into_last`` bytes into the last frame's chunk. Returns the size of the intact part."""
    with FrameStore.create(path) as store:
        for f in frames[:-1]:
            store.append(f)
        intact = store.size_bytes()
        store.append(frames[-1])
        seg = path / "segment-000000.mcap"
        writer = store._writer
        store._writer = None  # simulate the crash: no summary, manifest left "open"
        writer.abandon()
    os.truncate(seg, intact + cut_into_last)
    manifest = json.loads((path / "store.json").read_text())
    manifest["segments"][0].update(state="open", bytes=None)
    (path / "store.json").write_text(json.dumps(manifest))
    return intact


@pytest.mark.parametrize("cut", [5, 200, 60_000])
def test_crash_tail_is_dropped_and_reported(tmp_path: Path, synthetic_frames: list[Frame], cut: int) -> None:
    path = tmp_path / "s"
    intact = _crashed_store(path, synthetic_frames[:5], cut)
    with FrameStore.open(path) as store:
        assert [int(i) for i in store.frame_ids] == [0, 1, 2, 3]
        assert len(store.recovery_events) == 1 and store.recovery_events[0].dropped_bytes == cut
    with FrameStore.open(path, "a") as store:
        store.append(synthetic_frames[4])  # the frame that was in flight can be appended again
    assert (path / "segment-000000.dropped-tail.bin").stat().st_size == cut
    with FrameStore.open(path) as store:
        for f in synthetic_frames[:5]:
            assert_frames_identical(store.frame(f.frame_id), f)
    assert intact > 0


def test_truncated_closed_segment_is_a_typed_error_and_recoverable(tmp_path: Path, synthetic_frames: list[Frame]) -> None:
    path = tmp_path / "s"
    with FrameStore.create(path) as store:
        for f in synthetic_frames[:6]:
            store.append(f)
        cut_at = store._refs[4].payload_offset + 1000  # in the middle of frame 4's points
    seg = path / "segment-000000.mcap"
    os.truncate(seg, cut_at)
    with pytest.raises(StoreCorruptError) as err:
        FrameStore.open(path)
    assert err.value.path == seg and err.value.offset is not None and str(seg) in str(err.value)
    assert "driftmap recover" in str(err.value)
    events = FrameStore.recover(path)
    assert len(events) == 2 and events[0].frames_kept == 4
    # the manifest recorded the frames the closed segment held: the ones cut off its end are declared lost
    assert events[1].loss is not None and events[1].loss.frame_ids == (4, 5), events
    assert (path / "segment-000000.mcap.damaged").exists()
    with FrameStore.open(path) as store:
        assert [int(i) for i in store.frame_ids] == [0, 1, 2, 3]
        assert store.loss.frame_ids == (4, 5)
        for f in synthetic_frames[:4]:
            assert_frames_identical(store.frame(f.frame_id), f)
    assert FrameStore.recover(path) == []  # healthy now


def _six_frames_cut_in_frame_4(path: Path, frames: list[Frame]) -> Path:
    """A store of frames 0..5 in one closed segment, truncated in the middle of frame 4's points."""
    with FrameStore.create(path) as store:
        for f in frames[:6]:
            store.append(f)
        cut_at = store._refs[4].payload_offset + 1000
    os.truncate(path / "segment-000000.mcap", cut_at)
    return path


def test_a_recovery_stopped_before_it_declared_a_loss_is_refused_until_run_again(
        tmp_path: Path, synthetic_frames: list[Frame], monkeypatch: pytest.MonkeyPatch) -> None:
    """A recovery that rewrote a truncated segment but stopped before its ``data_lost`` record (disk full) leaves a
    closed, intact segment that no longer holds frames its manifest entry records: opening refuses it (naming
    `driftmap recover`), and the next recovery declares them."""
    from driftmap.store import recovery

    path = _six_frames_cut_in_frame_4(tmp_path / "s", synthetic_frames)

    def full(self: object, *args: object) -> None:
        raise OSError(28, "No space left on device", str(path / "segment-000001.mcap"))

    monkeypatch.setattr(recovery._Recovery, "write_loss", full)
    with pytest.raises(StoreError, match="(?i)no space left"):
        FrameStore.recover(path)
    monkeypatch.undo()
    with pytest.raises(StoreCorruptError, match=r"records frames \[4, 5\] in it.*driftmap recover"):
        FrameStore.open(path)
    events = FrameStore.recover(path)
    assert [e.loss.frame_ids for e in events if e.loss] == [(4, 5)], events
    # hostile trial 19 W4: the reason names the segment whose record shows the cut (and the damaged copy kept), not
    # "stored revisions name frames ... that no segment holds"
    (because,) = [e.detail for e in events if e.loss]
    assert because.startswith("segment-000000.mcap: its manifest entry records frames [4, 5]"), because
    assert "segment-000000.mcap.damaged" in because, because
    with FrameStore.open(path) as store:
        assert store.loss.frame_ids == (4, 5) and [int(i) for i in store.frame_ids] == [0, 1, 2, 3]
    assert FrameStore.recover(path) == []


def _store_with_a_lost_tail_revision(path: Path, frames: list[Frame]) -> int:
    """Frames 0..5 (segment 0), revision 1 (segment 1); the segment-1 record cut off and recovered: revision 1 is
    declared lost. Returns the head (the stand-in's id)."""
    with FrameStore.create(path) as store:
        for f in frames[:6]:
            store.append(f)
    with FrameStore.open(path, "a") as store:
        store.add_revision({0: _moved(store.poses(0)[0], 0.02)}, source="loop_closure")
    seg = path / "segment-000001.mcap"
    os.truncate(seg, seg.read_bytes().find(b'"revision_id"'))  # in the revision record
    FrameStore.recover(path)
    with FrameStore.open(path) as store:
        assert store.loss.revision_ids == (1,)
        return int(store.head)


def test_a_damaged_loss_record_is_declared_again_and_no_revision_id_is_reused(
        tmp_path: Path, synthetic_frames: list[Frame]) -> None:
    """Hostile trial 19 B1: damaging (or deleting) the segment that holds recover's data_lost record erased the loss,
    and the next revision took the lost one's id. The record's manifest entry accounts for the loss it declares, so
    the next recovery declares it again."""
    for how in ("flip", "delete"):
        path = tmp_path / how
        assert _store_with_a_lost_tail_revision(path, synthetic_frames) == 1
        loss_segment = sorted(path.glob("segment-*.mcap"))[-1]
        if how == "delete":
            loss_segment.unlink()
        else:
            data = bytearray(loss_segment.read_bytes())
            data[data.find(b"data_lost") + 30] ^= 1
            loss_segment.write_bytes(bytes(data))
        with pytest.raises(StoreCorruptError, match="recover"):
            FrameStore.open(path)
        FrameStore.recover(path)
        with FrameStore.open(path, "a") as store:
            assert store.loss.revision_ids == (1,) and store.head == 1
            rev = store.rollback(0)
            assert rev.revision_id == 2  # not 1 again


def test_a_frame_lost_stored_again_and_lost_again_is_a_new_loss(tmp_path: Path, synthetic_frames: list[Frame]) -> None:
    """Hostile trial 19 B5: frames declared lost, stored again (a resume stores lost ids again) and lost again were not
    reported: the first declaration covered their ids. A declaration covers only the copies stored before it."""
    path = _six_frames_cut_in_frame_4(tmp_path / "s", synthetic_frames)
    FrameStore.recover(path)
    with FrameStore.open(path, "a") as store:
        assert store.loss.frame_ids == (4, 5)
        for f in synthetic_frames[4:8]:  # 4 and 5 again, 6 and 7 new
            store.append(f)
        again = store._refs[5]
    os.truncate(again.segment, again.payload_offset + 1000)  # frames 5, 6, 7 of the new segment
    events = FrameStore.recover(path)
    assert [e.loss.frame_ids for e in events if e.loss] == [(5, 6, 7)], events
    with FrameStore.open(path) as store:
        assert [int(i) for i in store.frame_ids] == [0, 1, 2, 3, 4] and store.loss.frame_ids == (5, 6, 7)


def test_manifest_records_that_lie_are_refused_or_not_used(tmp_path: Path, synthetic_frames: list[Frame]) -> None:
    """Hostile trial 19 B2-B4, W5: a record naming a revision far past the store's last (1e9: a billion stand-ins), a
    revision another segment holds, millions of frames, or negative frame ids. Opening refuses them (a typed error
    naming recover); recovery does not declare anything lost on their word, and rewrites them."""
    base = tmp_path / "base"
    with FrameStore.create(base) as store:
        for f in synthetic_frames[:6]:
            store.append(f)
    with FrameStore.open(base, "a") as store:
        store.add_revision({0: _moved(store.poses(0)[0], 0.02)}, source="loop_closure")
    lies = {"far_revision": (0, "revisions", [1, 1_000_000_000]), "other_segments_revision": (0, "revisions", [1]),
            "millions_of_frames": (0, "frames", [[0, 22_000_000]]), "negative_frames": (0, "frames", [[-1000, 5]])}
    for name, (index, key, value) in lies.items():
        path = tmp_path / name
        shutil.copytree(base, path)
        manifest = json.loads((path / "store.json").read_text())
        manifest["segments"][index][key] = value
        (path / "store.json").write_text(json.dumps(manifest))
        if name == "other_segments_revision":  # held by segment 1: nothing is missing, nothing to refuse
            FrameStore.open(path).close()
        else:
            with pytest.raises(StoreCorruptError, match="recover"):
                FrameStore.open(path)
        FrameStore.recover(path)
        with FrameStore.open(path) as store:
            assert not store.loss and store.head == 1 and len(store) == 6, name


def test_recover_rebuilds_an_unreadable_or_missing_manifest_from_the_segments(tmp_path: Path, synthetic_frames: list[Frame]) -> None:
    """store.json garbled (or deleted): opening is a typed error; `recover` rebuilds it from the segments, which
    name their store, and every frame and revision comes back. Segments of two stores are refused."""
    path = tmp_path / "s"
    with FrameStore.create(path) as store:
        for f in synthetic_frames[:4]:
            store.append(f)
    with FrameStore.open(path, "a") as store:  # a second writer session: a second segment
        for f in synthetic_frames[4:7]:
            store.append(f)
        moved = store.poses(0)[-1].copy()
        moved[:3, 3] += [0.05, 0.0, 0.0]
        store.add_revision({6: moved}, source=PoseSource.EXTERNAL_FILE, propagate=False, note="moved frame 6")
        uuid = store._manifest["store_uuid"]
        poses = {rev: store.poses(rev) for rev in (0, 1)}
    manifest = path / "store.json"
    manifest.write_text('{"format": "driftmap-store", "vers')  # a torn write by some other tool
    with pytest.raises(StoreCorruptError, match="manifest"):
        FrameStore.open(path)
    events = FrameStore.recover(path)
    assert [e.segment for e in events] == ["store.json"] and "2 segments" in events[0].action
    assert (path / "store.json.damaged").read_text().startswith('{"format"')
    with FrameStore.open(path) as store:
        assert store._manifest["store_uuid"] == uuid and "rebuilt_because" in store._manifest
        assert [int(i) for i in store.frame_ids] == list(range(7)) and store.head == 1
        for rev, expected in poses.items():
            np.testing.assert_array_equal(store.poses(rev), expected)
        for f in synthetic_frames[:7]:
            assert_frames_identical(store.frame(f.frame_id), f)
    assert FrameStore.recover(path) == []  # healthy now
    good = manifest.read_text()
    for shape in ('["segments"]', good.replace('"segments"', '"segment_list"'), good.replace('"name"', '"nom"', 1)):
        manifest.write_text(shape)  # valid JSON of the wrong shape: the same typed error, and recover rebuilds it
        with pytest.raises(StoreCorruptError, match="unreadable manifest"):
            FrameStore.open(path)
        assert "rebuilt" in FrameStore.recover(path)[0].action
        with FrameStore.open(path) as store:
            assert len(store) == 7 and store.head == 1
    with pytest.raises(StoreError, match="is a file, not a store directory"):
        FrameStore.create(manifest)
    manifest.unlink()
    with pytest.raises(StoreError, match="missing"):
        FrameStore.open(path)
    assert "rebuilt" in FrameStore.recover(path)[0].action
    with FrameStore.open(path) as store:
        assert len(store) == 7 and store.head == 1
    with FrameStore.create(tmp_path / "other") as other:  # a segment of another store dropped in by mistake
        other.append(synthetic_frames[7])
    os.replace(tmp_path / "other" / "segment-000000.mcap", path / "segment-000002.mcap")
    manifest.write_text("garbage")
    with pytest.raises(StoreError, match="exactly one store"):
        FrameStore.recover(path)


def test_corrupted_bytes_are_detected_and_only_the_damaged_frame_is_lost(tmp_path: Path, synthetic_frames: list[Frame]) -> None:
    path = tmp_path / "s"
    with FrameStore.create(path) as store:
        for f in synthetic_frames[:6]:
            store.append(f)
        damaged_at = store._refs[2].payload_offset + 4096
    seg = path / "segment-000000.mcap"
    with open(seg, "r+b") as fh:
        fh.seek(damaged_at)
        byte = fh.read(1)
        fh.seek(damaged_at)
        fh.write(bytes([byte[0] ^ 0xFF]))
    with pytest.raises(StoreCorruptError, match="CRC") as err:
        FrameStore.open(path)
    assert err.value.path == seg and err.value.offset is not None and err.value.offset <= damaged_at
    events = FrameStore.recover(path)
    assert events[0].frames_kept == 5
    with FrameStore.open(path) as store:
        assert [int(i) for i in store.frame_ids] == [0, 1, 3, 4, 5]
        assert_frames_identical(store.frame(5), synthetic_frames[5])


def test_store_opens_in_a_generic_mcap_reader(tmp_path: Path, synthetic_frames: list[Frame]) -> None:
    """The store's segments are standard MCAP with Foxglove schemas (what Foxglove reads)."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    with FrameStore.create(tmp_path / "s") as store:
        for f in synthetic_frames[:2]:
            store.append(f)
    with open(tmp_path / "s" / "segment-000000.mcap", "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        schemas = {s.name for s in summary.schemas.values()}
        assert {"foxglove.PointCloud", "foxglove.FrameTransform"} <= schemas
        clouds = [(m.log_time, d) for s, c, m, d in reader.iter_decoded_messages(topics=["/driftmap/depth_camera/points"])]
    assert len(clouds) == 2
    stamp, cloud = clouds[1]
    assert stamp == synthetic_frames[1].stamp_ns
    pts = np.frombuffer(cloud.data, dtype="<f4").reshape(-1, 3)
    np.testing.assert_array_equal(pts, synthetic_frames[1].points_sensor)
    assert [f.name for f in cloud.fields] == ["x", "y", "z"]


# ------------------------------------------------------------------------------------------ losses and recovery


def _snapshot(path: Path) -> dict[str, bytes]:
    """Every file of a store with its bytes (to show that a second recovery changes nothing)."""
    return {f.name: f.read_bytes() for f in sorted(path.iterdir()) if f.name != "writer.lock"}


def _moved(T: np.ndarray, dx_m: float) -> np.ndarray:
    out = np.array(T, dtype=np.float64, copy=True)
    out[0, 3] += dx_m
    return out


def _flip_byte(file: Path, offset: int) -> None:
    with open(file, "r+b") as fh:
        fh.seek(offset)
        byte = fh.read(1)
        fh.seek(offset)
        fh.write(bytes([byte[0] ^ 0xFF]))


def _rows(store: FrameStore, revision: int, ids: list[int]) -> bytes:
    """The poses of ``ids`` in ``revision``, as bytes (compared bit for bit)."""
    return store.poses(revision)[np.searchsorted(store.frame_ids, ids)].tobytes()


def test_recover_keeps_a_later_revision_that_names_frames_of_a_truncated_segment(tmp_path: Path, sevenscenes_dir: Path) -> None:
    """The audit's case on real 7-Scenes frames: a correction stored in a later segment names frames that a
    truncation of the first segment took with it. Recovery must leave a store that opens, with every revision,
    each keeping the poses of the frames that remain (bit for bit), and must say what was lost."""
    frames = [sevenscenes_frame(sevenscenes_dir, i, stride_px=8) for i in range(0, 100, 10)]
    path = tmp_path / "s"
    with FrameStore.create(path) as store:
        for f in frames:
            store.append(f)
        cut_at = store._refs[60].payload_offset + 1000  # in the middle of frame 60's points
    with FrameStore.open(path, "a") as store:  # a later writer session (segment 1) corrects the poses
        store.add_revision({0: _moved(store.poses(0)[0], 0.02), 90: _moved(store.poses(0)[-1], 0.05)},
                           source=PoseSource.LOOP_CLOSURE, note="loop")  # propagated to every frame
        store.add_revision({80: _moved(store.poses(1)[8], 0.01), 90: _moved(store.poses(1)[9], 0.01)},
                           source=PoseSource.EXTERNAL_FILE, propagate=False, note="only frames that will be lost")
        store.add_revision({10: _moved(store.poses(2)[1], 0.03)}, source=PoseSource.EXTERNAL_FILE, propagate=False)
        before = {rev: store.poses(rev).copy() for rev in range(4)}
    os.truncate(path / "segment-000000.mcap", cut_at)
    kept, lost = [0, 10, 20, 30, 40, 50], [60, 70, 80, 90]
    with pytest.raises(StoreCorruptError, match="driftmap recover"):
        FrameStore.open(path)

    events = FrameStore.recover(path)
    assert [e.segment for e in events] == ["segment-000000.mcap", "segment-000002.mcap"]
    assert events[0].frames_kept == len(kept) and events[0].dropped_bytes > 0
    loss = events[1].loss
    assert loss is not None and list(loss.frame_ids) == lost and loss.revision_ids == ()
    assert loss.trimmed == {1: tuple(lost), 2: (80, 90)}
    assert (events[1].frames_kept, events[1].revisions_kept) == (len(kept), 4)
    assert "frames [60, 70, 80, 90] are lost" in str(events[1]) and "revision 2 lost the poses of [80, 90]" in str(events[1])

    with FrameStore.open(path) as store:
        assert [int(i) for i in store.frame_ids] == kept and store.head == 3
        assert list(store.loss.frame_ids) == lost and store.loss.trimmed == loss.trimmed
        for rev in range(4):  # the kept frames are the first six of the ten
            assert store.poses(rev).tobytes() == before[rev][: len(kept)].tobytes(), rev
        assert store.revisions[1].n_changed == len(kept) and store.revisions[1].source is PoseSource.LOOP_CLOSURE
        assert store.revisions[2].n_changed == 0 and store.revisions[2].parent_id == 1  # kept: it is history
        assert "lost frame" in store.revisions[2].note
        assert_frames_identical(store.frame(50), frames[5])

    snapshot = _snapshot(path)
    assert FrameStore.recover(path) == []  # idempotent: nothing to do, nothing written, and the store opens
    assert _snapshot(path) == snapshot
    with FrameStore.open(path) as store:
        assert len(store) == len(kept) and store.head == 3


def test_recover_after_a_segment_file_was_deleted(tmp_path: Path, synthetic_frames: list[Frame]) -> None:
    """A deleted segment: opening names it and asks for `driftmap recover`; so does a store whose manifest was
    tidied by hand, with a revision naming the frames that went with it (not a message about "commit").
    Recovery keeps the revisions, says what was lost, and the store accepts new segments (and the lost frames)."""
    path = tmp_path / "s"
    for session in (synthetic_frames[:4], synthetic_frames[4:8]):
        with (FrameStore.create(path) if not path.exists() else FrameStore.open(path, "a")) as store:
            for f in session:
                store.append(f)
    with FrameStore.open(path, "a") as store:  # session 3 (segment 2): two corrections
        store.add_revision({0: _moved(store.poses(0)[0], 0.02), 7: _moved(store.poses(0)[7], 0.04)}, source="loop_closure")
        store.add_revision({2: _moved(store.poses(1)[2], 0.01)}, source="external_file", propagate=False)
        before = {rev: store.poses(rev).copy() for rev in range(3)}
    (path / "segment-000001.mcap").unlink()
    with pytest.raises(StoreCorruptError, match=r"segment-000001.mcap: segment listed in the manifest is missing.*driftmap recover"):
        FrameStore.open(path)

    tidied = tmp_path / "tidied"  # the same damage after someone removed the segment from store.json by hand
    shutil.copytree(path, tidied)
    manifest = json.loads((tidied / "store.json").read_text())
    manifest["segments"] = [s for s in manifest["segments"] if s["name"] != "segment-000001.mcap"]
    (tidied / "store.json").write_text(json.dumps(manifest))
    with pytest.raises(StoreCorruptError, match=r"revision 1 holds poses of frames \[4, 5, 6, 7\].*driftmap recover") as err:
        FrameStore.open(tidied)
    assert "commit" not in str(err.value)

    for store_path in (path, tidied):
        events = FrameStore.recover(store_path)
        assert [e.action for e in events][:-1] == (["missing segment removed from the manifest"] if store_path == path else [])
        loss = events[-1].loss
        assert loss is not None and loss.frame_ids == (4, 5, 6, 7) and loss.trimmed == {1: (4, 5, 6, 7)}
        assert FrameStore.recover(store_path) == []
        with FrameStore.open(store_path) as store:
            assert [int(i) for i in store.frame_ids] == [0, 1, 2, 3] and store.head == 2
            for rev in range(3):
                assert store.poses(rev).tobytes() == before[rev][:4].tobytes()

    env = {**os.environ, "COLUMNS": "300"}  # the command line shows the loss whenever the store is opened
    info = subprocess.run([sys.executable, "-m", "driftmap.cli", "info", str(tidied)], capture_output=True, text=True, env=env)
    assert info.returncode == 0, info.stderr
    assert "recovered earlier: frames [4, 5, 6, 7] are lost" in info.stderr and "lost to damage" in info.stdout
    again = subprocess.run([sys.executable, "-m", "driftmap.cli", "recover", str(tidied)], capture_output=True, text=True, env=env)
    assert again.returncode == 0 and "nothing to do" in again.stdout

    with FrameStore.open(path, "a") as store:  # appending goes on in a new segment (no name of a lost one reused)
        store.append(synthetic_frames[5])  # a lost frame stored again is a new frame: no old revision moves it
        store.append(synthetic_frames[8])
    manifest = json.loads((path / "store.json").read_text())
    assert [s["name"] for s in manifest["segments"]] == ["segment-000000.mcap", "segment-000002.mcap",
                                                        "segment-000003.mcap", "segment-000004.mcap"]
    with FrameStore.open(path) as store:
        assert [int(i) for i in store.frame_ids] == [0, 1, 2, 3, 5, 8] and store.loss.frame_ids == (4, 6, 7)
        for rev in (1, 2):
            assert store.poses(rev)[4].tobytes() == synthetic_frames[5].T_world_sensor.tobytes()
        assert_frames_identical(store.frame(5), synthetic_frames[5])


def test_recover_after_bit_flips_in_a_frame_chunk_and_in_a_revision_chunk(tmp_path: Path, synthetic_frames: list[Frame]) -> None:
    """A flipped bit in a frame's chunk loses that frame; one in a revision's chunk loses that revision. The
    revisions after it keep their ids (a stand-in holds the lost one's place) and the report says which revision
    lost its parent."""
    path = tmp_path / "s"
    with FrameStore.create(path) as store:
        for f in synthetic_frames[:6]:
            store.append(f)
        damaged_at = store._refs[2].payload_offset + 4096
    with FrameStore.open(path, "a") as store:
        store.add_revision({0: _moved(store.poses(0)[0], 0.02), 5: _moved(store.poses(0)[5], 0.02)}, source="loop_closure")
        store.add_revision({0: _moved(store.poses(1)[0], 0.01)}, source="external_file", propagate=False, note="lost")
        store.add_revision({1: _moved(store.poses(2)[1], 0.03)}, source="external_file", propagate=False, note="child")
        before = {rev: store.poses(rev).copy() for rev in range(4)}
    _flip_byte(path / "segment-000000.mcap", damaged_at)
    seg1 = path / "segment-000001.mcap"
    data = seg1.read_bytes()
    _flip_byte(seg1, data.index(b'"revision_id":2,') + 200)  # in revision 2's matrices
    with pytest.raises(StoreCorruptError, match="CRC"):
        FrameStore.open(path)

    events = FrameStore.recover(path)
    assert [e.segment for e in events] == ["segment-000000.mcap", "segment-000001.mcap", "segment-000002.mcap"]
    assert events[0].frames_kept == 5 and events[0].dropped_bytes > synthetic_frames[2].n_points * 12
    assert events[1].revisions_kept == 2 and events[1].dropped_bytes > 0
    loss = events[2].loss
    assert loss is not None and loss.frame_ids == (2,) and loss.revision_ids == (2,)
    assert loss.trimmed == {1: (2,)} and loss.orphaned == {3: 2}
    assert "revision 3: its parent 2 is lost, the frames it does not set take revision 1's poses" in str(events[2])

    with FrameStore.open(path) as store:
        kept = [0, 1, 3, 4, 5]
        assert [int(i) for i in store.frame_ids] == kept and store.head == 3
        rows = [0, 1, 3, 4, 5]
        for rev in (0, 1):
            assert store.poses(rev).tobytes() == before[rev][rows].tobytes()
        stand_in = store.revisions[2]
        assert stand_in.source is PoseSource.NONE and stand_in.n_changed == 0 and stand_in.parent_id == 1
        assert store.poses(2).tobytes() == store.poses(1).tobytes()
        # revision 3 keeps its own pose; the frames it does not set take revision 1's poses (revision 2 is gone)
        assert _rows(store, 3, [1]) == before[3][1:2].tobytes()
        assert _rows(store, 3, [0, 3, 4, 5]) == before[1][[0, 3, 4, 5]].tobytes()
        assert store.loss.orphaned == {3: 2}
    snapshot = _snapshot(path)
    assert FrameStore.recover(path) == [] and _snapshot(path) == snapshot


def test_recover_report_counts_and_manifest_errors_name_the_fix(tmp_path: Path, synthetic_frames: list[Frame]) -> None:
    """A rebuilt store.json is reported with the frames and revisions the store kept (not 0 and 0), and a
    missing or unreadable store.json tells the user to run `driftmap recover PATH`."""
    path = tmp_path / "s"
    with FrameStore.create(path) as store:
        for f in synthetic_frames[:4]:
            store.append(f)
    with FrameStore.open(path, "a") as store:
        for f in synthetic_frames[4:7]:
            store.append(f)
        store.add_revision({6: _moved(store.poses(0)[6], 0.05)}, source="external_file", propagate=False)
    manifest = path / "store.json"
    manifest.write_text('{"format": "driftmap-store", "vers')
    with pytest.raises(StoreCorruptError, match=f"unreadable manifest.*run `driftmap recover {path}`"):
        FrameStore.open(path)
    events = FrameStore.recover(path)
    assert [e.segment for e in events] == ["store.json"]
    assert (events[0].frames_kept, events[0].revisions_kept) == (7, 2)
    assert "kept 7 frames and 2 revisions" in str(events[0])
    manifest.unlink()
    with pytest.raises(StoreCorruptError, match=f"store.json: missing.*run `driftmap recover {path}`"):
        FrameStore.open(path)
    seg1 = path / "segment-000001.mcap"  # and the revision's chunk cut off: the counts are those after recovery
    os.truncate(seg1, seg1.read_bytes().index(b'"revision_id":1,'))
    events = FrameStore.recover(path)
    assert events[0].segment == "store.json" and (events[0].frames_kept, events[0].revisions_kept) == (7, 1)
    assert "kept 7 frames and 1 revisions" in str(events[0])
    assert events[1].segment == "segment-000001.mcap" and (events[1].frames_kept, events[1].revisions_kept) == (3, 0)
    with FrameStore.open(path) as store:
        assert len(store) == 7 and store.head == 0
    with pytest.raises(StoreError, match="not a driftmap store") as err:  # an empty folder is no store to recover
        FrameStore.open(tmp_path)
    assert "driftmap recover" not in str(err.value)


def test_an_interrupted_recovery_is_finished_by_the_next_one(tmp_path: Path, synthetic_frames: list[Frame],
                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """Recovery is idempotent and resumable: killed while it records the loss (after the damaged segment was
    rewritten), the store is left in a state the next `recover` finishes, and a third run has nothing to do."""
    from driftmap.store.segment import SegmentWriter

    path = tmp_path / "s"
    with FrameStore.create(path) as store:
        for f in synthetic_frames[:6]:
            store.append(f)
        cut_at = store._refs[4].payload_offset + 100
    with FrameStore.open(path, "a") as store:
        store.add_revision({0: _moved(store.poses(0)[0], 0.02), 5: _moved(store.poses(0)[5], 0.01)}, source="loop_closure")
        before = store.poses(1).copy()
    os.truncate(path / "segment-000000.mcap", cut_at)

    def power_cut(self: SegmentWriter, payload: dict, log_time_ns: int) -> None:
        raise OSError("simulated power cut while recording the loss")

    monkeypatch.setattr(SegmentWriter, "append_event", power_cut)
    with pytest.raises(OSError, match="power cut"):
        FrameStore.recover(path)
    monkeypatch.undo()
    with pytest.raises(StoreCorruptError, match=r"records frames \[4, 5\] in it.*driftmap recover"):
        FrameStore.open(path)  # segment 0 is clean now, but the loss is not recorded yet: not silently read

    events = FrameStore.recover(path)
    assert [e.segment for e in events] == ["segment-000002.mcap", "segment-000003.mcap"]  # the torn one, the record
    assert events[-1].loss is not None and events[-1].loss.frame_ids == (4, 5) and events[-1].loss.trimmed == {1: (4, 5)}
    assert (path / "segment-000000.mcap.damaged").stat().st_size == cut_at  # the first run's copy was not overwritten
    snapshot = _snapshot(path)
    assert FrameStore.recover(path) == [] and _snapshot(path) == snapshot
    with FrameStore.open(path) as store:
        assert [int(i) for i in store.frame_ids] == [0, 1, 2, 3] and store.head == 1
        assert store.poses(1).tobytes() == before[:4].tobytes()


def test_an_index_match_of_a_stamped_file_whose_stamps_disagree_is_warned_about(tmp_path: Path, synthetic_frames: list[Frame],
                                                                                caplog: pytest.LogCaptureFixture) -> None:
    import logging

    from driftmap.trajectory import Trajectory, write_tum

    with FrameStore.create(tmp_path / "s") as store:
        for f in synthetic_frames[:6]:
            store.append(f)
        poses, stamps = store.poses(0), store.ledger.stamps_ns
        own = tmp_path / "own.tum"
        write_tum(own, Trajectory(stamps, poses))
        other = tmp_path / "other.tum"  # another recording: the same number of rows, stamps an hour later
        write_tum(other, Trajectory(stamps + 3600 * 10**9, poses))
        with caplog.at_level(logging.WARNING, logger="driftmap.store.frame_store"):
            store.import_poses(own, match="index")
            assert not [r for r in caplog.records if "stamps differ" in r.getMessage()]
            store.import_poses(other, match="index")
        warned = [r.getMessage() for r in caplog.records if "stamps differ" in r.getMessage()]
        assert len(warned) == 1 and "other.tum" in warned[0] and "3600.000 s" in warned[0]
        # a file of another place: the correction is kept (it is what the file says), with a warning
        far = tmp_path / "far.tum"
        moved = poses[::-1].copy()  # another path, 40 m away
        moved[:, :3, 3] += [40.0, 0.0, 0.0]
        write_tum(far, Trajectory(stamps, moved))
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="driftmap.store.frame_store"):
            store.import_poses(own)  # back to the frames' own poses: no warning
            assert not [r for r in caplog.records if "is the file for these frames" in r.getMessage()]
            rev, _ = store.import_poses(far)
        warned = [r.getMessage() for r in caplog.records if "is the file for these frames" in r.getMessage()]
        assert len(warned) == 1 and "far.tum" in warned[0] and f"--to {rev.parent_id}" in warned[0]
        # the same path moved 40 m as one rigid body: a re-anchoring (trial 12: it was asked "is the file for these
        # frames?" next to correct's "re-anchors the map"), said as such
        shifted = tmp_path / "shifted.tum"
        rigid = poses.copy()
        rigid[:, :3, 3] += [40.0, 0.0, 0.0]
        write_tum(shifted, Trajectory(stamps, rigid))
        store.import_poses(own)  # back from the reversed path (warned: not one rigid move)
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="driftmap.store.frame_store"):
            rev, _ = store.import_poses(shifted)
        messages = [r.getMessage() for r in caplog.records]
        assert not [m for m in messages if "is the file for these frames" in m], messages
        assert [m for m in messages if "shifted.tum" in m and f"revision {rev.revision_id} moves every frame by one "
                "rigid transform (up to 40.00 m): the map is re-anchored" in m], messages


def test_revisions_place_the_frames_stored_before_them_also_after_reopening_and_recovery(
        tmp_path: Path, synthetic_frames: list[Frame]) -> None:
    """Hostile trial 17 B1 at the store: a revision's frames come back from the segments as they were -- recorded
    (``frames``) for new revisions, and for revisions written before that, the frames stored before them in store
    order, within one segment too; recovery of a crashed segment keeps that order."""
    from driftmap.store.revision import Revision

    path = tmp_path / "s"
    with FrameStore.create(path) as store:
        for f in synthetic_frames[:3]:
            store.append(f)
        # as a driftmap before membership was recorded wrote it: no ``frames``
        store._persist(Revision(1, 0, PoseSource.LOOP_CLOSURE, 1, set_directly={0: _moved(store.poses(0)[0], 0.1)}))
        for f in synthetic_frames[3:5]:
            store.append(f)
        store._persist(Revision(2, 1, PoseSource.LOOP_CLOSURE, 2, set_directly={3: _moved(store.poses(0)[3], 0.1)}))
        store.add_revision({4: _moved(store.poses(0)[4], 0.2)}, source=PoseSource.EXTERNAL_FILE, propagate=False)
        store.rollback(1)
        for f in synthetic_frames[5:6]:
            store.append(f)
        expected = {r: store.members(r).tolist() for r in range(5)}
        store.abandon()  # the writer "crashes": its segment stays open
    assert expected == {0: [0, 1, 2, 3, 4, 5], 1: [0, 1, 2], 2: [0, 1, 2, 3, 4], 3: [0, 1, 2, 3, 4],
                        4: [0, 1, 2, 5]}  # the head shows frame 5, stored after it
    with FrameStore.open(path, "a") as store:  # recovers the open segment, rewriting its chunks in store order
        assert store.recovery_events
        assert {r: store.members(r).tolist() for r in range(5)} == expected
    with FrameStore.open(path) as store:
        assert {r: store.members(r).tolist() for r in range(5)} == expected


def _resumed_store(path: Path, frames: list[Frame]) -> Path:
    """Frames 0..5 in segment 0; frames 6..11 and revision 1 appended in segment 1 (as a resume writes them)."""
    with FrameStore.create(path) as store:
        for f in frames[:6]:
            store.append(f)
    with FrameStore.open(path, "a") as store:
        for f in frames[6:12]:
            store.append(f)
        store.add_revision({0: _moved(store.poses(0)[0], 0.02)}, source="loop_closure")
    return path


def test_a_segment_cut_to_a_fraction_of_its_size_declares_what_its_record_names(
        tmp_path: Path, synthetic_frames: list[Frame]) -> None:
    """Hostile trial 20 B1: the record was checked against the size of the rewritten segment, so a cut that kept less
    than a quarter of it (or emptied it) made the record look implausible: the frames and the revision went unreported
    and the next revision reused the lost id. It is checked against the size before the damage now."""
    for keep in ("fifth", "empty", "zeros"):
        path = _resumed_store(tmp_path / keep, synthetic_frames)
        seg = path / "segment-000001.mcap"
        size = seg.stat().st_size
        if keep == "fifth":
            os.truncate(seg, size // 5)
        elif keep == "empty":
            os.truncate(seg, 0)
        else:
            seg.write_bytes(bytes(size))
        events = FrameStore.recover(path)
        (loss,) = [e.loss for e in events if e.loss]
        with FrameStore.open(path) as store:
            kept = {int(i) for i in store.frame_ids}
            assert set(loss.frame_ids) == set(range(6, 12)) - kept and len(loss.frame_ids) >= 4, (keep, loss)
            assert loss.revision_ids == (1,) and store.loss.revision_ids == (1,), (keep, loss)
        with FrameStore.open(path, "a") as store:  # the lost id is not used again
            assert store.add_revision({0: _moved(store.poses(0)[0], 0.01)}, source="loop_closure").revision_id == 2


def test_a_damaged_record_of_an_intact_segment_is_corrected_and_declares_nothing(
        tmp_path: Path, synthetic_frames: list[Frame]) -> None:
    """Hostile trial 20 B2: one flipped digit in store.json's record of an intact segment (frames 6..11 -> 6..19,
    revisions [1] -> [1, 2]) made `recover` declare, for good, frames and a revision that never existed (a stand-in
    head). An intact segment holds what it held: the record is the damaged part, and recovery corrects it."""
    for field, value in (("frames", [[6, 19]]), ("revisions", [1, 2])):
        path = _resumed_store(tmp_path / field, synthetic_frames)
        manifest = json.loads((path / "store.json").read_text())
        manifest["segments"][1][field] = value
        (path / "store.json").write_text(json.dumps(manifest))
        with pytest.raises(StoreCorruptError, match="driftmap recover"):
            FrameStore.open(path)
        events = FrameStore.recover(path)
        assert not [e for e in events if e.loss], events
        with FrameStore.open(path) as store:
            assert not store.loss and len(store) == 12 and store.head == 1, field
        assert json.loads((path / "store.json").read_text())["segments"][1]["frames"] == [[6, 11]]


def test_a_recovery_stopped_before_its_declaration_by_older_code_is_still_declared(
        tmp_path: Path, synthetic_frames: list[Frame], monkeypatch: pytest.MonkeyPatch) -> None:
    """Hostile trial 21 B2: a recovery stopped after rewriting a segment and before declaring its loss leaves a
    healthy segment whose record names more. With `rewritten_from_bytes` in its entry the next recovery declares the
    loss; without it (older code left none, or the key was damaged) the segment read as never damaged and its record
    was "corrected": frames 4, 5 lost without a word. The damaged copy kept beside the segment is evidence too."""
    from driftmap.store import recovery

    path = _six_frames_cut_in_frame_4(tmp_path / "s", synthetic_frames)

    def full(self: object, *args: object) -> None:
        raise OSError(28, "No space left on device", str(path / "segment-000001.mcap"))

    monkeypatch.setattr(recovery._Recovery, "write_loss", full)
    with pytest.raises(StoreError):
        FrameStore.recover(path)
    monkeypatch.undo()
    manifest = json.loads((path / "store.json").read_text())
    assert manifest["segments"][0].pop("rewritten_from_bytes") > 0  # as older code left it
    (path / "store.json").write_text(json.dumps(manifest))
    assert (path / "segment-000000.mcap.damaged").exists()
    events = FrameStore.recover(path)
    assert [e.loss.frame_ids for e in events if e.loss] == [(4, 5)], events
    with FrameStore.open(path) as store:
        assert store.loss.frame_ids == (4, 5)
