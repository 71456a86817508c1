"""ROS log sources: TF buffer and odometry on the real bags (ROS 1, rosbag2 sqlite3, MCAP) checked against a
direct read of the messages; MCAP round trips of the synthetic log and of real 7-Scenes frames; real
7-Scenes depth images as sensor_msgs/Image against driftmap.backproject; PointCloud2 field layouts; the
rosbags paths (ROS 1, rosbag2 sqlite3 and mcap storage); every bad-input case."""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from mcap_ros2.writer import Writer as Ros2McapWriter
from PIL import Image
from scipy.spatial.transform import Rotation

from driftmap import (
    PinholeIntrinsics,
    PointAttributes,
    PoseEstimate,
    PoseSource,
    Provenance,
    SourceError,
    backproject,
    depth_frame,
    geometry,
)
from driftmap.errors import ExportError
from driftmap.export.depth_log import write_depth_image_mcap
from driftmap.export.mcap import convert, export_mcap
from driftmap.export.ros_messages import ros2_msgdef
from driftmap.frame import Frame, SensorKind
from driftmap.sources.base import open_source
from driftmap.sources.ros import (
    PointTimeReference,
    RosLogSource,
    StampSource,
    detect_format,
    list_topics,
    parse_provenance_uri,
    read_pose_topic,
    read_tf,
)
from driftmap.sources.tf import TfBuffer, TfError

IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")
SEVENSCENES_K = PinholeIntrinsics(fx=585.0, fy=585.0, cx=320.0, cy=240.0, width=640, height=480)
BASE_STAMP_NS = 1_700_000_000_000_000_000


# ---------------------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------------------


@pytest.fixture(scope="session")
def bags_dir(datasets_dir: Path) -> Path:
    path = datasets_dir / "bags"
    if not path.exists():
        message = f"shared bags not found at {path}"
        if IN_CI:
            pytest.fail(message + "; in CI the data must be present", pytrace=False)
        pytest.skip(message)
    return path


def T_of(t: Any, q: Any) -> np.ndarray:
    """4x4 from message translation/position and quaternion (written here independently of driftmap)."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
    T[:3, 3] = [t.x, t.y, t.z]
    return T


def ns(stamp: Any) -> int:
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def raw_tf_samples(path: Path) -> dict[tuple[str, str, str], list[tuple[int, np.ndarray]]]:
    """(topic, parent, child) -> [(stamp, T)] read directly with the mcap reader or rosbags."""
    out: dict[tuple[str, str, str], list[tuple[int, np.ndarray]]] = {}

    def add(topic: str, msg: Any) -> None:
        for tr in msg.transforms:
            key = (topic, tr.header.frame_id.lstrip("/"), tr.child_frame_id.lstrip("/"))
            out.setdefault(key, []).append((ns(tr.header.stamp), T_of(tr.transform.translation, tr.transform.rotation)))

    if path.suffix == ".mcap":
        with open(path, "rb") as f:
            for _, channel, _, msg in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages(
                topics=["/tf", "/tf_static"]
            ):
                add(channel.topic, msg)
    else:
        from rosbags.highlevel import AnyReader

        with AnyReader([path]) as reader:
            conns = [c for c in reader.connections if c.topic in ("/tf", "/tf_static")]
            for conn, _, raw in reader.messages(connections=conns):
                add(conn.topic, reader.deserialize(raw, conn.msgtype))
    return out


def header(stamp_ns: int, frame_id: str) -> dict[str, Any]:
    return {"stamp": {"sec": stamp_ns // 1_000_000_000, "nanosec": stamp_ns % 1_000_000_000}, "frame_id": frame_id}


def write_mcap(path: Path, messages: list[tuple[str, str, dict[str, Any], int]]) -> Path:
    """Write (topic, ROS 2 type, message dict, log time) with mcap_ros2 (no driftmap code involved)."""
    with open(path, "wb") as f:
        writer = Ros2McapWriter(f)
        schemas: dict[str, Any] = {}
        for topic, typename, msg, log_time in messages:
            if typename not in schemas:
                schemas[typename] = writer.register_msgdef(typename, ros2_msgdef(typename))
            writer.write_message(topic, schemas[typename], msg, log_time=log_time, publish_time=log_time)
        writer.finish()
    return path


def tf_msg(stamp_ns: int, parent: str, child: str, T: np.ndarray) -> dict[str, Any]:
    q = Rotation.from_matrix(T[:3, :3]).as_quat()
    return {
        "transforms": [
            {
                "header": header(stamp_ns, parent),
                "child_frame_id": child,
                "transform": {
                    "translation": dict(zip("xyz", map(float, T[:3, 3]), strict=True)),
                    "rotation": dict(zip("xyzw", map(float, q), strict=True)),
                },
            }
        ]
    }


_DATATYPE = {"i1": 1, "u1": 2, "i2": 3, "u2": 4, "i4": 5, "u4": 6, "f4": 7, "f8": 8}


def cloud_msg(
    stamp_ns: int,
    frame_id: str,
    columns: dict[str, np.ndarray],
    *,
    big_endian: bool = False,
    point_step: int | None = None,
    height: int = 1,
    row_pad: int = 0,
    is_dense: bool = False,
) -> dict[str, Any]:
    """A PointCloud2 dict with the given columns (name -> (N,) array) at packed offsets (+ padding)."""
    endian = ">" if big_endian else "<"
    names = list(columns)
    offsets, offset = [], 0
    for name in names:
        offsets.append(offset)
        offset += columns[name].dtype.itemsize
    step = point_step or offset
    dtype = np.dtype(
        {
            "names": names,
            "formats": [endian + columns[n].dtype.str[1:] for n in names],
            "offsets": offsets,
            "itemsize": step,
        }
    )
    n = len(next(iter(columns.values())))
    width = n // height
    arr = np.zeros(n, dtype=dtype)
    for name in names:
        arr[name] = columns[name]
    rows = arr.tobytes()
    row_bytes = width * step
    data = b"".join(rows[r * row_bytes : (r + 1) * row_bytes] + b"\xee" * row_pad for r in range(height))
    fields = [
        {"name": name, "offset": off, "datatype": _DATATYPE[columns[name].dtype.str[1:]], "count": 1}
        for name, off in zip(names, offsets, strict=True)
    ]
    return {
        "header": header(stamp_ns, frame_id),
        "height": height,
        "width": width,
        "fields": fields,
        "is_bigendian": big_endian,
        "point_step": step,
        "row_step": row_bytes + row_pad,
        "data": data,
        "is_dense": is_dense,
    }


def load_7scenes(sevenscenes_dir: Path, ids: list[int]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    depths = [np.array(Image.open(sevenscenes_dir / f"frame-{i:06d}.depth.png")) for i in ids]
    poses = [np.loadtxt(sevenscenes_dir / f"frame-{i:06d}.pose.txt") for i in ids]
    return depths, poses


def assert_same_frames(a: list[Frame], b: list[Frame], *, pose_tol: float = 1e-12, ids: bool = True) -> None:
    assert len(a) == len(b)
    for fa, fb in zip(a, b, strict=True):
        if ids:
            assert fa.frame_id == fb.frame_id
        assert fa.stamp_ns == fb.stamp_ns
        assert fa.points_sensor.dtype == fb.points_sensor.dtype == np.float32
        assert fa.points_sensor.tobytes() == fb.points_sensor.tobytes(), f"frame {fa.frame_id}: points differ"
        assert fa.intrinsics == fb.intrinsics
        assert fa.sensor_kind == fb.sensor_kind
        assert np.abs(fa.T_world_sensor - fb.T_world_sensor).max() <= pose_tol
        assert np.abs(fa.T_base_sensor - fb.T_base_sensor).max() <= pose_tol
        for name in ("intensity", "color_rgb", "normal_sensor", "time_offset_ns"):
            va, vb = getattr(fa.attributes, name), getattr(fb.attributes, name)
            assert (va is None) == (vb is None), name
            if va is not None:
                assert np.array_equal(va, vb), name


# ---------------------------------------------------------------------------------------------------------
# TF and odometry on the real bags
# ---------------------------------------------------------------------------------------------------------

TF_FILES = ["tf_example.bag", "tf_example", "nav2_turtlebot.mcap"]


@pytest.mark.parametrize("name", TF_FILES)
def test_tf_buffer_matches_direct_read(bags_dir: Path, name: str) -> None:
    path = bags_dir / name
    buffer = read_tf(path)
    raw = raw_tf_samples(path)
    assert {(p, c) for (_, p, c) in raw} == {(p, c) for p, c, _ in buffer.edges()}
    for (topic, parent, child), samples in raw.items():
        if topic == "/tf_static":
            assert np.allclose(buffer.static_transform(parent, child), samples[-1][1], atol=1e-12)
            continue
        series = buffer.series(parent, child)
        assert len(series) == len({s for s, _ in samples})
        for stamp, T in samples[:: max(1, len(samples) // 50)]:
            assert np.abs(buffer.lookup(parent, child, stamp) - T).max() < 1e-12
            assert np.abs(buffer.lookup(child, parent, stamp) - geometry.invert(T)).max() < 1e-12


def test_tf_example_ros1_and_rosbag2_agree_and_chain(bags_dir: Path) -> None:
    ros1, ros2 = read_tf(bags_dir / "tf_example.bag"), read_tf(bags_dir / "tf_example")
    assert ros1.edges() == ros2.edges() == [("base_footprint", "base_link", True), ("odom", "base_footprint", False)]
    s1, s2 = ros1.series("odom", "base_footprint"), ros2.series("odom", "base_footprint")
    assert np.array_equal(s1.stamps_ns, s2.stamps_ns) and np.array_equal(s1.T_parent_child, s2.T_parent_child)
    raw = raw_tf_samples(bags_dir / "tf_example.bag")
    T_bf_bl = raw[("/tf_static", "base_footprint", "base_link")][0][1]
    samples = raw[("/tf", "odom", "base_footprint")]
    for stamp, T_odom_bf in samples[::40]:  # odom -> base_footprint (dynamic) -> base_link (static)
        assert np.abs(ros2.lookup("odom", "base_link", stamp) - T_odom_bf @ T_bf_bl).max() < 1e-12
    # between two samples: SE(3) interpolation of the neighbours, translation in between
    (s0, T0), (s1_, T1) = samples[100], samples[101]
    mid = (s0 + s1_) // 2
    got = ros1.lookup("odom", "base_footprint", mid)
    alpha = (mid - s0) / (s1_ - s0)
    assert np.abs(got - geometry.interpolate_se3(T0, T1, alpha)).max() < 1e-12
    lo, hi = np.minimum(T0[:3, 3], T1[:3, 3]), np.maximum(T0[:3, 3], T1[:3, 3])
    assert np.all(got[:3, 3] >= lo - 1e-12) and np.all(got[:3, 3] <= hi + 1e-12)
    # latest common time
    assert np.abs(ros1.lookup("odom", "base_link") - samples[-1][1] @ T_bf_bl).max() < 1e-12


def test_nav2_map_odom_base_chain(bags_dir: Path) -> None:
    path = bags_dir / "nav2_turtlebot.mcap"
    buffer = read_tf(path)
    raw = raw_tf_samples(path)
    map_odom = raw[("/tf", "map", "odom")]
    odom_base = sorted(raw[("/tf", "odom", "base_link")], key=lambda s: s[0])
    stamps = np.array([s for s, _ in odom_base])
    lo, hi = buffer.time_range_ns("map", "base_link")
    assert (lo, hi) == (max(map_odom[0][0], odom_base[0][0]), min(map_odom[-1][0], odom_base[-1][0]))
    checked = 0
    for stamp, T_map_odom in map_odom[::30]:
        if not lo <= stamp <= hi:
            continue
        i = int(np.searchsorted(stamps, stamp, side="right")) - 1
        (sa, Ta), (sb, Tb) = odom_base[i], odom_base[i + 1]
        T_odom_base = Ta if sa == stamp else geometry.interpolate_se3(Ta, Tb, (stamp - sa) / (sb - sa))
        assert np.abs(buffer.lookup("map", "base_link", stamp) - T_map_odom @ T_odom_base).max() < 1e-12
        checked += 1
    assert checked >= 20
    # a camera on the robot: static chain base_link -> shell_link -> oakd_camera_bracket -> ... -> optical frame
    assert buffer.is_static("base_link", "oakd_rgb_camera_optical_frame")
    T = buffer.lookup("map", "oakd_rgb_camera_optical_frame", lo + 10**9)
    assert np.allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12)
    with pytest.raises(TfError, match=r"map <- base_link.*no data at.*cover"):
        buffer.lookup("map", "base_link", hi + 10**9)


def test_tf_errors_name_frames() -> None:
    buffer = TfBuffer()
    buffer.add_static("base_link", "camera", geometry.make_transform(None, (0.1, 0, 1.0)))
    buffer.add("odom", "base_link", 100, np.eye(4))
    buffer.add("odom", "base_link", 200, geometry.make_transform(None, (1.0, 0, 0)))
    buffer.add_static("robot2/base", "robot2/lidar", np.eye(4))
    assert np.allclose(buffer.lookup("odom", "camera", 150)[:3, 3], (0.6, 0, 1.0))
    with pytest.raises(TfError, match=r"'camera'.*'robot2/lidar'|'robot2/lidar'.*'camera'"):
        buffer.lookup("camera", "robot2/lidar", 150)
    with pytest.raises(TfError, match=r"frame 'nowhere' is not in the TF tree"):
        buffer.lookup("odom", "nowhere", 150)
    with pytest.raises(TfError, match=r"odom <- camera.*odom -> base_link.*no data at 250 ns.*100 ns.*200 ns"):
        buffer.lookup("odom", "camera", 250)
    with pytest.raises(TfError, match="two parents"):
        buffer.add_static("map", "base_link", np.eye(4))


def test_tf_samples_added_after_a_lookup_join_the_earlier_ones_and_batched_lookups_agree(bags_dir: Path) -> None:
    # a live stack interleaves add() and lookup(): the samples given before a lookup must stay
    buffer = TfBuffer()
    buffer.add("odom", "base_link", 0, np.eye(4))
    buffer.add("odom", "base_link", 10, geometry.make_transform(None, (10.0, 0, 0)))
    assert np.allclose(buffer.lookup("odom", "base_link", 5)[:3, 3], (5.0, 0, 0))
    buffer.add("odom", "base_link", 20, geometry.make_transform(None, (20.0, 0, 0)))
    assert buffer.time_range_ns("odom", "base_link") == (0, 20)
    assert np.allclose(buffer.lookup("odom", "base_link", 5)[:3, 3], (5.0, 0, 0))
    assert np.allclose(buffer.lookup("odom", "base_link", 15)[:3, 3], (15.0, 0, 0))
    assert len(buffer.series("odom", "base_link")) == 3
    # lookup_many (one batch per edge) equals one lookup per stamp on a real chain: dynamic map->odom->base_link,
    # static base_link -> camera optical frame, both directions, exact stamps and stamps between samples
    real = read_tf(bags_dir / "nav2_turtlebot.mcap")
    lo, hi = real.time_range_ns("map", "base_link")
    stamps = np.linspace(lo, hi, 97).astype(np.int64)
    for target, source in (("map", "oakd_rgb_camera_optical_frame"), ("oakd_rgb_camera_optical_frame", "map")):
        many = real.lookup_many(target, source, stamps)
        one = np.stack([real.lookup(target, source, int(s)) for s in stamps])
        assert many.shape == (97, 4, 4) and np.abs(many - one).max() < 1e-12
    with pytest.raises(TfError, match=r"map <- base_link.*no data at"):
        real.lookup_many("map", "base_link", [lo, hi + 10**9])


def test_nav2_odometry_matches_messages_and_tf(bags_dir: Path) -> None:
    path = bags_dir / "nav2_turtlebot.mcap"
    series = read_pose_topic(path, "/odom")
    assert (series.parent_frame, series.child_frame) == ("odom", "base_link")
    with open(path, "rb") as f:
        raw = [
            (ns(m.header.stamp), T_of(m.pose.pose.position, m.pose.pose.orientation))
            for *_, m in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages(topics=["/odom"])
        ]
    assert len(series) == len(raw) == 2639
    assert np.array_equal(series.stamps_ns, [s for s, _ in raw])
    assert np.abs(series.T_parent_child - np.stack([T for _, T in raw])).max() < 1e-12
    tf = read_tf(path)
    for stamp, T in raw[::97]:  # the diff-drive publishes the same pose on /odom and /tf
        assert np.abs(tf.lookup("odom", "base_link", stamp) - T).max() < 1e-12
    amcl = read_pose_topic(path, "/amcl_pose")
    assert amcl.parent_frame == "map" and len(amcl) == 135


def test_ros1_pose_stamped(bags_dir: Path) -> None:
    from rosbags.highlevel import AnyReader

    path = bags_dir / "ROS_example.bag"
    series = read_pose_topic(path, "groundtruth")
    with AnyReader([path]) as reader:
        conns = [c for c in reader.connections if c.topic == "groundtruth"]
        raw = [reader.deserialize(r, c.msgtype) for c, _, r in reader.messages(connections=conns)]
    assert len(series) == len({ns(m.header.stamp) for m in raw}) == 12765
    first = min(raw, key=lambda m: ns(m.header.stamp))
    assert series.stamps_ns[0] == ns(first.header.stamp)
    assert np.abs(series.T_parent_child[0] - T_of(first.pose.position, first.pose.orientation)).max() < 1e-12
    assert detect_format(path) == "rosbag1"
    with pytest.raises(SourceError, match=r"no PointCloud2 or depth Image topic.*groundtruth"):
        open_source(path)


def test_formats_detected(bags_dir: Path) -> None:
    assert detect_format(bags_dir / "nav2_turtlebot.mcap") == "mcap"
    assert detect_format(bags_dir / "tf_example") == "rosbag2"
    assert detect_format(bags_dir / "tf_example" / "tf_example.db3") == "rosbag2"
    assert detect_format(bags_dir / "tf_example.bag") == "rosbag1"
    topics = list_topics(bags_dir / "nav2_turtlebot.mcap")
    assert topics["/tf"].count == 5422 and topics["/odom"].msgtype == "nav_msgs/msg/Odometry"
    with pytest.raises(SourceError, match=r"nav2_turtlebot.mcap: no PointCloud2 or depth Image topic.*/odom"):
        open_source(bags_dir / "nav2_turtlebot.mcap")


# ---------------------------------------------------------------------------------------------------------
# round trips through MCAP
# ---------------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def synthetic_export(tmp_path_factory: pytest.TempPathFactory) -> tuple[Any, list[Frame], Path, dict]:
    from driftmap.demo import embedded_log_path
    from driftmap.sources.synthetic import SyntheticLog

    log = SyntheticLog(embedded_log_path())
    frames = list(log)
    out = tmp_path_factory.mktemp("ros") / "synthetic.mcap"
    summary = export_mcap(log, out, ground_truth=log.ground_truth())
    return log, frames, out, summary


def test_synthetic_log_round_trip(synthetic_export: tuple[Any, list[Frame], Path, dict]) -> None:
    log, frames, out, summary = synthetic_export
    assert summary["frames"] == len(frames) == 60 and summary["poses_written"] == 60
    assert all(f.pose.source is PoseSource.ODOMETRY for f in frames)
    source = open_source(out)
    assert source.format_name == "mcap" and len(source) == 60
    back = list(source)
    assert_same_frames(frames, back)
    assert [f.pose.source for f in back] == [PoseSource.ODOMETRY] * 60  # recorded in the export metadata
    assert {f.sensor_name for f in back} == {frames[0].sensor_name}
    assert back[0].depth_scale == frames[0].depth_scale and back[0].base_frame == frames[0].base_frame
    path, topic, stamp = parse_provenance_uri(back[3].provenance.source_uri)
    assert (Path(path), topic, stamp, back[3].provenance.index) == (
        out.resolve(),
        "/depth_camera/points",
        StampSource.HEADER,
        3,
    )
    gt = source.ground_truth()
    ref = log.ground_truth()
    assert np.array_equal(gt.frame_ids, ref.frame_ids) and np.abs(gt.poses - ref.poses).max() < 1e-12
    # random access and slicing agree with iteration
    assert_same_frames([back[17]], [source.frame(17)])
    sliced = open_source(out, frames="10:40:10")
    assert sliced.frame_ids() == [10, 20, 30]
    assert_same_frames([back[10], back[20], back[30]], list(sliced))


def test_synthetic_round_trip_without_metadata(synthetic_export: tuple[Any, list[Frame], Path, dict]) -> None:
    _, frames, out, _ = synthetic_export
    plain = RosLogSource(
        out,
        use_export_metadata=False,
        pose_from_tf=("world", "base_link"),
        start_ns=frames[5].stamp_ns,
        end_ns=frames[9].stamp_ns,
    )
    back = list(plain)
    assert [f.frame_id for f in back] == [5, 6, 7, 8]  # message indices on the topic
    assert all(f.pose.source is PoseSource.LOG and f.pose.world_frame == "world" for f in back)
    assert_same_frames(frames[5:9], back)
    assert back[0].sensor_name == "depth_camera/points"
    # the same frames read without any pose input: no estimate
    bare = RosLogSource(out, use_export_metadata=False, frames="0:2")
    assert [f.pose.source for f in bare] == [PoseSource.NONE] * 2
    assert np.array_equal(bare.frame(0).T_world_sensor, np.eye(4))
    # log-time stamps select with the MCAP index only
    by_log = RosLogSource(out, stamp=StampSource.LOG, start_ns=frames[58].stamp_ns)
    assert len(by_log) == 2 and by_log.frame_ids() == [58, 59]


def test_sevenscenes_frames_round_trip(sevenscenes_dir: Path, tmp_path: Path) -> None:
    ids = [0, 250, 640, 999]
    depths, poses = load_7scenes(sevenscenes_dir, ids)
    T_base_cam = geometry.make_transform(Rotation.from_euler("y", 10, degrees=True), (0.05, 0.0, 1.2))
    frames = [
        depth_frame(
            d,
            SEVENSCENES_K,
            frame_id=i,
            stamp_ns=BASE_STAMP_NS + i * 33_333_333,
            pose=PoseEstimate(P, source=PoseSource.GROUND_TRUTH),
            T_base_sensor=T_base_cam,
            provenance=Provenance(str(sevenscenes_dir / f"frame-{i:06d}.depth.png"), i),
        )
        for i, d, P in zip(ids, depths, poses, strict=True)
    ]
    out = tmp_path / "sevenscenes.mcap"
    export_mcap(frames, out)
    back = list(open_source(out))
    assert_same_frames(frames, back)
    assert [f.frame_id for f in back] == ids and back[0].intrinsics == SEVENSCENES_K
    assert all(f.pose.source is PoseSource.GROUND_TRUTH for f in back)
    # a reader that only knows ROS conventions sees standard messages
    with open(out, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        topics = {
            c.topic: reader.get_summary().schemas[c.schema_id].name for c in reader.get_summary().channels.values()
        }
        infos = [m for *_, m in reader.iter_decoded_messages(topics=["/depth_camera/camera_info"])]
    assert topics == {
        "/tf_static": "tf2_msgs/msg/TFMessage",
        "/tf": "tf2_msgs/msg/TFMessage",
        "/depth_camera/points": "sensor_msgs/msg/PointCloud2",
        "/depth_camera/camera_info": "sensor_msgs/msg/CameraInfo",
    }
    assert list(infos[0].k) == [585.0, 0.0, 320.0, 0.0, 585.0, 240.0, 0.0, 0.0, 1.0]


def unit_normals(rng: np.random.Generator, n: int) -> np.ndarray:
    v = rng.normal(size=(n, 3))
    return (v / np.linalg.norm(v, axis=1, keepdims=True)).astype(np.float32)


def test_attributes_and_pose_none_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    n = 500

    def frame(k: int, offsets: np.ndarray, source: PoseSource) -> Frame:
        return Frame(
            frame_id=100 + k,
            stamp_ns=BASE_STAMP_NS + k * 100_000_000,
            sensor_name="lidar",
            sensor_kind=SensorKind.LIDAR,
            points_sensor=rng.normal(size=(n, 3)).astype(np.float32),
            pose=PoseEstimate(
                geometry.make_transform(Rotation.random(random_state=k), rng.normal(size=3)),
                source=source,
                world_frame="map",
            ),
            T_base_sensor=geometry.make_transform(None, (0, 0, 1.5)),
            attributes=PointAttributes(
                intensity=rng.random(n, dtype=np.float32),
                color_rgb=rng.integers(0, 256, (n, 3), dtype=np.uint8),
                normal_sensor=unit_normals(rng, n),  # normals that are not unit vectors are not read back
                time_offset_ns=offsets,
            ),
            sensor_frame="velodyne",
            base_frame="base_link",
        )

    frames = [
        frame(0, rng.integers(0, 100_000_000, n), PoseSource.LOOP_CLOSURE),
        frame(1, rng.integers(-50_000_000, 50_000_000, n), PoseSource.NONE),  # negative offsets -> "time" float64
        frame(2, rng.integers(0, 100_000_000, n), PoseSource.ODOMETRY),
    ]
    out = tmp_path / "lidar.mcap"
    export_mcap(frames, out)
    back = list(open_source(out))
    assert [f.pose.source for f in back] == [PoseSource.LOOP_CLOSURE, PoseSource.NONE, PoseSource.ODOMETRY]
    assert np.array_equal(back[1].T_world_sensor, np.eye(4))
    assert_same_frames([frames[0], frames[2]], [back[0], back[2]])
    assert_same_frames([frames[1].with_pose(PoseEstimate(np.eye(4), source=PoseSource.NONE))], [back[1]])
    assert back[0].sensor_kind is SensorKind.LIDAR and back[0].intrinsics is None
    with pytest.raises(ExportError, match="T_base_sensor differs"):
        moved = frames[2].__class__(
            **{
                **{f: getattr(frames[2], f) for f in frames[2].__dataclass_fields__},
                "T_base_sensor": np.eye(4),
                "stamp_ns": frames[2].stamp_ns + 1,
            }
        )
        export_mcap([frames[0], moved], tmp_path / "bad.mcap")
    assert not (tmp_path / "bad.mcap").exists() and not (tmp_path / "bad.mcap.partial").exists()


def test_convert_synthetic(tmp_path: Path) -> None:
    from driftmap.demo import embedded_log_path

    summary = convert(embedded_log_path(), tmp_path / "out.mcap", frames="0:6")
    assert summary["frames"] == 6 and summary["ground_truth_poses"] == 6 and summary["source_format"] == "synthetic"
    back = open_source(tmp_path / "out.mcap")
    assert back.frame_ids() == [0, 1, 2, 3, 4, 5] and len(back.ground_truth()) == 6


# ---------------------------------------------------------------------------------------------------------
# depth images
# ---------------------------------------------------------------------------------------------------------


def test_depth_image_mcap_matches_backproject(sevenscenes_dir: Path, tmp_path: Path) -> None:
    ids = [0, 33, 250, 640]
    depths, poses = load_7scenes(sevenscenes_dir, ids)
    stamps = [BASE_STAMP_NS + i * 33_333_333 for i in ids]
    T_base_cam = geometry.make_transform(Rotation.from_euler("xyz", (-90, 0, -90), degrees=True), (0.1, 0.0, 0.9))
    out = write_depth_image_mcap(
        tmp_path / "depth.mcap",
        depths,
        stamps,
        SEVENSCENES_K,
        T_base_sensor=T_base_cam,
        T_world_sensor=poses,
        world_frame="odom",
    )["out"]
    source = RosLogSource(out, pose_from_tf=("odom", "base_link"))
    assert source.msgtype == "sensor_msgs/msg/Image" and source.camera_info_topic == "/camera/depth/camera_info"
    frames = list(source)
    for frame, depth, pose, stamp in zip(frames, depths, poses, stamps, strict=True):
        ref = backproject(depth, SEVENSCENES_K)
        assert frame.points_sensor.tobytes() == ref.points.tobytes()
        assert dict(frame.quality.invalid_counts) == ref.invalid_counts
        assert frame.intrinsics == SEVENSCENES_K and frame.depth_scale == 1000.0 and frame.stamp_ns == stamp
        assert frame.sensor_kind is SensorKind.DEPTH_CAMERA and frame.pose.source is PoseSource.LOG
        assert np.abs(frame.T_world_sensor - geometry.as_rigid(pose)).max() < 1e-12
        assert np.abs(frame.T_base_sensor - T_base_cam).max() < 1e-12
        assert frame.sensor_frame == "camera_depth_optical_frame" and frame.base_frame == "base_link"
    raws = list(source.iter_raw())
    assert all(np.array_equal(r.depth, d) for r, d in zip(raws, depths, strict=True))
    assert_same_frames([frames[2]], [source.frame(2)])
    # extrinsics without poses (only /tf_static is needed)
    extr = RosLogSource(out, base_frame="base_link")
    assert (
        extr.frame(0).pose.source is PoseSource.NONE and np.abs(extr.frame(0).T_base_sensor - T_base_cam).max() < 1e-12
    )
    with pytest.raises(SourceError, match=r"no TF path from 'turret' to 'camera_depth_optical_frame'"):
        RosLogSource(out, base_frame="turret")
    # pixel_stride as in every depth source: the subsampled image with the subsampled intrinsics
    strided = open_source(out, pixel_stride=2).frame(1)
    ref = backproject(depths[1][::2, ::2], SEVENSCENES_K.subsampled(2))
    assert strided.points_sensor.tobytes() == ref.points.tobytes()
    assert strided.intrinsics == SEVENSCENES_K.subsampled(2)
    with pytest.raises(SourceError, match=r"unknown option\(s\) depth_sclae for format 'mcap'; accepted: .*topic"):
        open_source(out, depth_sclae=1000)


@pytest.mark.parametrize("variant", ["32FC1", "big_endian", "row_padding"])
def test_depth_image_encodings(sevenscenes_dir: Path, tmp_path: Path, variant: str) -> None:
    (depth,), _ = load_7scenes(sevenscenes_dir, [250])
    K = SEVENSCENES_K
    if variant == "32FC1":
        image = depth.astype(np.float32) / np.float32(1000.0)
        data, encoding, step, big = image.astype("<f4").tobytes(), "32FC1", 640 * 4, False
        ref = backproject(image, K).points
    elif variant == "big_endian":
        data, encoding, step, big = depth.astype(">u2").tobytes(), "16UC1", 640 * 2, True
        ref = backproject(depth, K).points
    else:
        padded = np.zeros((480, 656), dtype="<u2")
        padded[:, :640] = depth
        padded[:, 640:] = 4321
        data, encoding, step, big = padded.tobytes(), "16UC1", 656 * 2, False
        ref = backproject(depth, K).points
    info = {
        "header": header(BASE_STAMP_NS, "cam"),
        "height": 480,
        "width": 640,
        "distortion_model": "plumb_bob",
        "d": [0.0] * 5,
        "k": [585.0, 0, 320.0, 0, 585.0, 240.0, 0, 0, 1],
        "r": [1.0, 0, 0, 0, 1, 0, 0, 0, 1],
        "p": [585.0, 0, 320.0, 0, 0, 585.0, 240.0, 0, 0, 0, 1, 0],
    }
    image_msg = {
        "header": header(BASE_STAMP_NS, "cam"),
        "height": 480,
        "width": 640,
        "encoding": encoding,
        "is_bigendian": big,
        "step": step,
        "data": data,
    }
    path = write_mcap(
        tmp_path / "d.mcap",
        [
            ("/cam/depth/camera_info", "sensor_msgs/msg/CameraInfo", info, 1),
            ("/cam/depth/image", "sensor_msgs/msg/Image", image_msg, 2),
        ],
    )
    (frame,) = list(open_source(path))
    assert frame.points_sensor.tobytes() == ref.tobytes()


# ---------------------------------------------------------------------------------------------------------
# PointCloud2 layouts
# ---------------------------------------------------------------------------------------------------------

N_PTS = 120


def _layout(variant: str, stamp_ns: int) -> tuple[dict[str, Any], np.ndarray, np.ndarray | None, dict[str, int]]:
    """(message, expected float32 points, expected time offsets, expected invalid counts)."""
    rng = np.random.default_rng(len(variant))
    xyz = rng.normal(scale=10.0, size=(N_PTS, 3))
    offsets = np.sort(rng.integers(0, 100_000_000, N_PTS))
    cols: dict[str, np.ndarray] = {}
    kwargs: dict[str, Any] = {}
    expected_offsets: np.ndarray | None = None
    if variant == "float64_xyz":
        cols = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}
    else:
        cols = {"x": xyz[:, 0].astype(np.float32), "y": xyz[:, 1].astype(np.float32), "z": xyz[:, 2].astype(np.float32)}
    if variant == "big_endian_extras":
        cols |= {"intensity": rng.random(N_PTS).astype(np.float32), "ring": (np.arange(N_PTS) % 16).astype(np.uint16)}
        kwargs = {"big_endian": True}
    elif variant == "organized_padded":
        cols |= {"intensity": rng.integers(0, 4000, N_PTS).astype(np.uint16)}
        kwargs = {"height": 4, "point_step": 32, "row_pad": 12}
    elif variant == "ouster_t":
        cols |= {"t": offsets.astype(np.uint32), "ring": (np.arange(N_PTS) % 64).astype(np.uint16)}
        expected_offsets = offsets
    elif variant == "livox_offset_time":
        cols |= {"offset_time": offsets.astype(np.uint32)}
        expected_offsets = offsets
    elif variant == "velodyne_time_f32":
        cols |= {"time": (offsets / 1e9).astype(np.float32)}
        expected_offsets = offsets
    elif variant == "hesai_timestamp_f64_absolute":
        cols |= {"timestamp": (stamp_ns + offsets) / 1e9}
        expected_offsets = offsets
    elif variant == "nan_points":
        xyz[::10, 1] = np.nan
        xyz[5, 2] = np.inf
        cols = {"x": xyz[:, 0].astype(np.float32), "y": xyz[:, 1].astype(np.float32), "z": xyz[:, 2].astype(np.float32)}
    msg = cloud_msg(stamp_ns, "lidar_link", cols, **kwargs)
    points = xyz.astype(np.float32)
    finite = np.isfinite(points).all(axis=1)
    counts = {} if finite.all() else {"nan": int(np.isnan(points).any(axis=1).sum()), "inf": 1}
    if expected_offsets is not None:
        expected_offsets = expected_offsets[finite]
    return msg, points[finite], expected_offsets, counts


LAYOUTS = [
    "float64_xyz",
    "big_endian_extras",
    "organized_padded",
    "ouster_t",
    "livox_offset_time",
    "velodyne_time_f32",
    "hesai_timestamp_f64_absolute",
    "nan_points",
]


@pytest.mark.parametrize("variant", LAYOUTS)
def test_pointcloud2_layouts(tmp_path: Path, variant: str) -> None:
    stamps = [BASE_STAMP_NS, BASE_STAMP_NS + 100_000_000]
    layouts = [_layout(variant, s) for s in stamps]
    path = write_mcap(
        tmp_path / "c.mcap",
        [
            ("/lidar/points", "sensor_msgs/msg/PointCloud2", m, s + 5)
            for (m, *_), s in zip(layouts, stamps, strict=True)
        ],
    )
    frames = list(open_source(path))
    assert [f.stamp_ns for f in frames] == stamps
    for frame, (msg, points, offsets, counts) in zip(frames, layouts, strict=True):
        assert frame.points_sensor.tobytes() == points.tobytes()
        assert frame.sensor_kind is SensorKind.LIDAR and frame.sensor_frame == "lidar_link"
        assert frame.quality.n_measurements == N_PTS and dict(frame.quality.invalid_counts) == counts
        if offsets is None:
            assert frame.attributes.time_offset_ns is None
        else:
            tol = 0 if variant in ("ouster_t", "livox_offset_time") else 10 if variant.endswith("f32") else 500
            assert np.abs(frame.attributes.time_offset_ns - offsets).max() <= tol
        if "intensity" in {f["name"] for f in msg["fields"]}:
            assert frame.attributes.intensity is not None and frame.attributes.intensity.dtype == np.float32
    if variant == "big_endian_extras":
        from driftmap.sources.ros import pointcloud2_points

        with open(path, "rb") as f:
            (*_, msg), *_ = make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages()
        assert np.array_equal(pointcloud2_points(msg, stamps[0]).ring, np.arange(N_PTS) % 16)


def test_point_time_reference_override(tmp_path: Path) -> None:
    offsets = np.arange(N_PTS) * 1000
    cols = {c: np.ones(N_PTS, dtype=np.float32) for c in "xyz"} | {"time": offsets / 1e9}  # not at the origin: no return
    stamp = 50_000_000  # a stamp close to zero (sim time) makes AUTO ambiguous: force RELATIVE
    path = write_mcap(tmp_path / "t.mcap", [("/p", "sensor_msgs/msg/PointCloud2", cloud_msg(stamp, "l", cols), stamp)])
    (frame,) = list(RosLogSource(path, point_time=PointTimeReference.RELATIVE))
    assert np.array_equal(frame.attributes.time_offset_ns, offsets)


@pytest.mark.parametrize("variant", ["unit", "zero", "nan", "not_unit"])
def test_pointcloud2_normals_are_used_only_when_all_are_unit_vectors(
    tmp_path: Path, variant: str, caplog: pytest.LogCaptureFixture
) -> None:
    rng = np.random.default_rng(11)
    normals = unit_normals(rng, N_PTS)
    if variant == "zero":
        normals[:] = 0.0  # BALM-style: the fields are there, every value 0
    elif variant == "nan":
        normals[7] = np.nan
    elif variant == "not_unit":
        normals[3:9] *= 1.5
    cols = {c: rng.normal(size=N_PTS).astype(np.float32) for c in "xyz"}
    cols |= {f"normal_{c}": normals[:, k].copy() for k, c in enumerate("xyz")}
    path = write_mcap(tmp_path / "n.mcap", [("/p", "sensor_msgs/msg/PointCloud2", cloud_msg(BASE_STAMP_NS, "l", cols), BASE_STAMP_NS)])
    with caplog.at_level(logging.WARNING, logger="driftmap.sources.point_fields"):
        (frame,) = list(RosLogSource(path))
    if variant == "unit":
        assert frame.attributes.normal_sensor.tobytes() == normals.tobytes()
        assert not caplog.records
        return
    assert frame.attributes.normal_sensor is None
    (record,) = caplog.records
    expected = {"zero": f"{N_PTS} zero, 0 NaN/inf, 0 not unit", "nan": "0 zero, 1 NaN/inf, 0 not unit",
                "not_unit": "0 zero, 0 NaN/inf, 6 not unit"}[variant]
    assert "n.mcap: /p message 0: normals not used" in record.getMessage() and expected in record.getMessage()


@pytest.mark.parametrize("variant", ["span_5s", "nan", "far_from_stamp"])
def test_pointcloud2_implausible_time_field_is_not_used(
    tmp_path: Path, variant: str, caplog: pytest.LogCaptureFixture
) -> None:
    times = np.linspace(0.0, 0.1, N_PTS)  # a plausible Velodyne ``time`` (s from the scan start) ...
    if variant == "span_5s":
        times = np.linspace(0.0, 5.0, N_PTS)  # ... is not when it spans 5 s
    elif variant == "nan":
        times[4] = np.nan
    else:
        times = times + 3600.0  # relative seconds an hour away from the stamp
    cols = {c: np.ones(N_PTS, dtype=np.float32) for c in "xyz"} | {"time": times.astype(np.float64)}
    path = write_mcap(tmp_path / "t.mcap", [("/p", "sensor_msgs/msg/PointCloud2", cloud_msg(BASE_STAMP_NS, "l", cols), BASE_STAMP_NS)])
    with caplog.at_level(logging.WARNING, logger="driftmap.sources.point_fields"):
        (frame,) = list(RosLogSource(path))
    assert frame.attributes.time_offset_ns is None
    (record,) = caplog.records
    assert "t.mcap: /p message 0: per-point time field 'time' not used" in record.getMessage()


def _rosbags_cloud(typestore: Any, msg: dict[str, Any], ros1: bool) -> Any:
    T = typestore.types
    hdr = msg["header"]
    kwargs = {"seq": 0} if ros1 else {}
    return T["sensor_msgs/msg/PointCloud2"](
        header=T["std_msgs/msg/Header"](
            **kwargs, stamp=T["builtin_interfaces/msg/Time"](**hdr["stamp"]), frame_id=hdr["frame_id"]
        ),
        height=msg["height"],
        width=msg["width"],
        fields=[T["sensor_msgs/msg/PointField"](**f) for f in msg["fields"]],
        is_bigendian=msg["is_bigendian"],
        point_step=msg["point_step"],
        row_step=msg["row_step"],
        data=np.frombuffer(msg["data"], dtype=np.uint8),
        is_dense=msg["is_dense"],
    )


@pytest.mark.parametrize("kind", ["rosbag1", "rosbag2_sqlite3", "rosbag2_mcap"])
def test_rosbags_pointcloud2_and_tf(tmp_path: Path, kind: str) -> None:
    from rosbags.typesys import Stores, get_typestore

    stamps = [BASE_STAMP_NS + k * 100_000_000 for k in range(3)]
    layouts = [_layout("organized_padded", s) for s in stamps]
    T_odom_base = [geometry.make_transform(Rotation.from_euler("z", 10 * k, degrees=True), (k, 0, 0)) for k in range(3)]
    T_base_lidar = geometry.make_transform(None, (0.2, 0.0, 1.1))
    ros1 = kind == "rosbag1"
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if ros1:  # rosbags' ROS 1 store has no tf2_msgs; ROS 1 tf2_msgs/TFMessage has this definition
        from rosbags.typesys import get_types_from_msg

        ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
    T = ts.types

    def tf(stamp: int, parent: str, child: str, M: np.ndarray) -> Any:
        q = Rotation.from_matrix(M[:3, :3]).as_quat()
        kwargs = {"seq": 0} if ros1 else {}
        return T["tf2_msgs/msg/TFMessage"](
            transforms=[
                T["geometry_msgs/msg/TransformStamped"](
                    header=T["std_msgs/msg/Header"](
                        **kwargs,
                        stamp=T["builtin_interfaces/msg/Time"](sec=stamp // 10**9, nanosec=stamp % 10**9),
                        frame_id=parent,
                    ),
                    child_frame_id=child,
                    transform=T["geometry_msgs/msg/Transform"](
                        translation=T["geometry_msgs/msg/Vector3"](*M[:3, 3]),
                        rotation=T["geometry_msgs/msg/Quaternion"](*q),
                    ),
                )
            ]
        )

    if ros1:
        from rosbags.rosbag1 import Writer

        path = tmp_path / "log.bag"
        writer, serialize = Writer(path), ts.serialize_ros1
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        path = tmp_path / "log"
        plugin = StoragePlugin.MCAP if kind == "rosbag2_mcap" else StoragePlugin.SQLITE3
        writer, serialize = Writer(path, version=9, storage_plugin=plugin), ts.serialize_cdr
    with writer:
        c_static = writer.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=ts)
        c_tf = writer.add_connection("/tf", "tf2_msgs/msg/TFMessage", typestore=ts)
        c_pts = writer.add_connection("/velodyne_points", "sensor_msgs/msg/PointCloud2", typestore=ts)
        writer.write(
            c_static,
            stamps[0],
            serialize(tf(stamps[0], "base_link", "lidar_link", T_base_lidar), "tf2_msgs/msg/TFMessage"),
        )
        for s, (msg, *_), M in zip(stamps, layouts, T_odom_base, strict=True):
            writer.write(c_tf, s, serialize(tf(s, "odom", "base_link", M), "tf2_msgs/msg/TFMessage"))
            writer.write(c_pts, s + 1000, serialize(_rosbags_cloud(ts, msg, ros1), "sensor_msgs/msg/PointCloud2"))
    expected_format = "rosbag1" if ros1 else "rosbag2"
    source = open_source(path, pose_from_tf=("odom", "base_link"))
    assert source.format_name == expected_format and len(source) == 3
    frames = list(source)
    for frame, (_, points, *_), M in zip(frames, layouts, T_odom_base, strict=True):
        assert frame.points_sensor.tobytes() == points.tobytes()
        assert np.abs(frame.T_world_sensor - M @ T_base_lidar).max() < 1e-12
        assert np.abs(frame.T_base_sensor - T_base_lidar).max() < 1e-12
    assert [f.stamp_ns for f in frames] == stamps
    assert list(RosLogSource(path, stamp=StampSource.LOG))[1].stamp_ns == stamps[1] + 1000
    if kind == "rosbag2_mcap":  # the storage file alone goes through the mcap reader: same frames
        (inner,) = path.glob("*.mcap")
        assert_same_frames(frames, list(open_source(inner, pose_from_tf=("odom", "base_link"))))


# ---------------------------------------------------------------------------------------------------------
# bad input
# ---------------------------------------------------------------------------------------------------------


def test_truncated_mcap(synthetic_export: tuple[Any, list[Frame], Path, dict], tmp_path: Path) -> None:
    _, frames, out, _ = synthetic_export
    data = out.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(SourceError, match=r"cut.mcap: truncated or damaged MCAP.*byte offset \d+ of \d+.*lenient=True"):
        RosLogSource(cut)
    lenient = RosLogSource(cut, lenient=True, pose_from_tf=("world", "base_link"))
    back = list(lenient)
    assert 5 < len(back) < 60 and "truncated" in lenient.describe()["damage"]
    assert_same_frames(frames[: len(back)], back)


def test_unknown_encoding_and_schema(tmp_path: Path) -> None:
    from mcap.writer import Writer

    path = tmp_path / "json.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema("sensor_msgs/msg/PointCloud2", "jsonschema", b"{}")
        cid = w.register_channel("/points", "json", sid)
        w.add_message(cid, 1, b"{}", 1)
        sid2 = w.register_schema("foxglove.PointCloud", "protobuf", b"")
        cid2 = w.register_channel("/fox", "protobuf", sid2)
        w.add_message(cid2, 1, b"", 1)
        w.finish()
    with pytest.raises(
        SourceError, match=r"topic /points: unknown message encoding 'json' with schema 'sensor_msgs/msg/PointCloud2'"
    ):
        open_source(path)
    with pytest.raises(SourceError, match=r"topic /fox has schema 'foxglove.PointCloud'"):
        open_source(path, topic="/fox")
    broken = tmp_path / "broken.mcap"
    with open(broken, "wb") as f:
        w = Ros2McapWriter(f)
        schema = w.register_msgdef("sensor_msgs/msg/PointCloud2", "this is not a msg definition ][")
        w._writer.add_message(w._writer.register_channel("/points", "cdr", schema.id), 1, b"\x00\x01\x00\x00", 1)
        w.finish()
    with pytest.raises(SourceError, match=r"topic /points: cannot parse schema 'sensor_msgs/msg/PointCloud2'"):
        open_source(broken)


def test_pointcloud2_without_xyz_and_short_data(tmp_path: Path) -> None:
    cols = {"a": np.zeros(4, np.float32), "b": np.zeros(4, np.float32), "intensity": np.zeros(4, np.float32)}
    path = write_mcap(tmp_path / "noxyz.mcap", [("/p", "sensor_msgs/msg/PointCloud2", cloud_msg(1, "l", cols), 1)])
    with pytest.raises(
        SourceError, match=r"/p message 0: PointCloud2 has no x/y/z field \(fields present: a, b, intensity\)"
    ):
        list(open_source(path))
    short = cloud_msg(1, "l", {c: np.zeros(4, np.float32) for c in "xyz"})
    short["data"] = short["data"][:-5]
    path = write_mcap(tmp_path / "short.mcap", [("/p", "sensor_msgs/msg/PointCloud2", short, 1)])
    with pytest.raises(SourceError, match=r"data has 43 bytes.*need 48"):
        list(open_source(path))


@pytest.mark.parametrize(
    ("stamps", "kind", "pair"), [([1, 3, 2, 4], "non-monotonic", (2, 1)), ([1, 2, 2, 3], "duplicate", (2, 1))]
)
def test_non_monotonic_stamps(tmp_path: Path, stamps: list[int], kind: str, pair: tuple[int, int]) -> None:
    pts = {c: np.zeros(3, np.float32) for c in "xyz"}
    path = write_mcap(
        tmp_path / "s.mcap",
        [("/p", "sensor_msgs/msg/PointCloud2", cloud_msg(s * 10**9, "l", pts), 10 + k) for k, s in enumerate(stamps)],
    )
    with pytest.raises(
        SourceError, match=rf"topic /p: {kind} header stamps: message {pair[0]} has .* message {pair[1]} before it"
    ):
        list(open_source(path))
    lenient = open_source(path, lenient=True)
    assert [f.frame_id for f in lenient] == [0, 1, 3] and [i for i, _ in lenient.skipped] == [2]
    assert len(list(open_source(path, stamp=StampSource.LOG))) == 4  # log times increase


def test_depth_image_without_camera_info(sevenscenes_dir: Path, tmp_path: Path) -> None:
    (depth,), _ = load_7scenes(sevenscenes_dir, [0])
    image = {
        "header": header(5, "camera_depth_optical_frame"),
        "height": 480,
        "width": 640,
        "encoding": "16UC1",
        "is_bigendian": 0,
        "step": 1280,
        "data": depth.astype("<u2").tobytes(),
    }
    info_other = {
        "header": header(5, "camera_color_optical_frame"),
        "height": 480,
        "width": 640,
        "k": [585.0, 0, 320.0, 0, 585.0, 240.0, 0, 0, 1],
    }
    path = write_mcap(
        tmp_path / "noinfo.mcap",
        [
            ("/camera/depth/image_raw", "sensor_msgs/msg/Image", image, 5),
            ("/camera/color/camera_info", "sensor_msgs/msg/CameraInfo", info_other, 5),
        ],
    )
    with pytest.raises(
        SourceError,
        match=r"depth image topic /camera/depth/image_raw \(frame_id 'camera_depth_optical_frame'\) "
        r"has no sensor_msgs/msg/CameraInfo on the same frame_id",
    ):
        open_source(path)
    rgb = {**image, "encoding": "rgb8", "step": 1920, "data": bytes(640 * 480 * 3)}
    path = write_mcap(tmp_path / "rgb.mcap", [("/camera/color/image", "sensor_msgs/msg/Image", rgb, 5)])
    with pytest.raises(SourceError, match="'rgb8' image, not a depth image"):
        open_source(path, topic="/camera/color/image")


def test_pose_outside_tf_range_and_topic_choice(tmp_path: Path) -> None:
    pts = {c: np.ones(3, np.float32) for c in "xyz"}
    msgs = [("/tf", "tf2_msgs/msg/TFMessage", tf_msg(s * 10**9, "odom", "lidar", np.eye(4)), s * 10**9) for s in (2, 3)]
    msgs += [
        ("/a/points", "sensor_msgs/msg/PointCloud2", cloud_msg(s * 10**9, "lidar", pts), s * 10**9 + 1)
        for s in (1, 2, 3, 4)
    ]
    msgs += [
        ("/b/points", "sensor_msgs/msg/PointCloud2", cloud_msg(s * 10**9, "lidar", pts), s * 10**9 + 2) for s in (1, 2)
    ]
    path = write_mcap(tmp_path / "range.mcap", sorted(msgs, key=lambda m: m[3]))
    with pytest.raises(SourceError, match=r"several sensor topics, choose one with topic=: /a/points, /b/points"):
        open_source(path)
    with pytest.raises(TfError, match=r"lookup odom <- lidar at 1000000000 ns.*odom -> lidar.*no data"):
        list(open_source(path, topic="/a/points", pose_from_tf=("odom", "lidar")))
    lenient = open_source(path, topic="/a/points", pose_from_tf=("odom", "lidar"), lenient=True)
    assert [f.frame_id for f in lenient] == [1, 2] and [i for i, _ in lenient.skipped] == [0, 3]
    with pytest.raises(SourceError, match=r"no TF path from 'map' to 'odom'"):
        open_source(path, topic="/a/points", pose_from_tf=("map", "odom"))
    with pytest.raises(SourceError, match=r"no topic '/c/points'"):
        open_source(path, topic="/c/points")


def _odom_msg(stamp_ns: int, T: np.ndarray) -> dict[str, Any]:
    q = Rotation.from_matrix(T[:3, :3]).as_quat()
    return {
        "header": header(stamp_ns, "odom"),
        "child_frame_id": "base_link",
        "pose": {
            "pose": {
                "position": dict(zip("xyz", map(float, T[:3, 3]), strict=True)),
                "orientation": dict(zip("xyzw", map(float, q), strict=True)),
            }
        },
    }


def test_pose_from_odometry_interpolates(tmp_path: Path) -> None:
    pts = {c: np.ones(3, np.float32) for c in "xyz"}
    T_base_lidar = geometry.make_transform(Rotation.from_euler("y", 5, degrees=True), (0.3, 0.0, 1.2))
    odom = [geometry.make_transform(Rotation.from_euler("z", 20 * k, degrees=True), (k, 0.5 * k, 0)) for k in range(4)]
    delay_ns = 7_000_000  # the recorder logs every message 7 ms after its stamp
    msgs = [("/tf_static", "tf2_msgs/msg/TFMessage", tf_msg(0, "base_link", "lidar", T_base_lidar), 1)]
    msgs += [
        ("/odom", "nav_msgs/msg/Odometry", _odom_msg(k * 10**9, T), k * 10**9 + delay_ns) for k, T in enumerate(odom)
    ]
    cloud_stamps = [500_000_000, 1_000_000_000, 2_250_000_000]
    msgs += [
        ("/lidar/points", "sensor_msgs/msg/PointCloud2", cloud_msg(s, "lidar", pts), s + delay_ns) for s in cloud_stamps
    ]
    path = write_mcap(tmp_path / "odom.mcap", sorted(msgs, key=lambda m: m[3]))
    for stamp in (StampSource.HEADER, StampSource.LOG):  # both clocks shift alike: the same poses
        frames = list(open_source(path, pose_from_odometry="/odom", stamp=stamp))
        assert [f.pose.source for f in frames] == [PoseSource.ODOMETRY] * 3 and frames[0].pose.world_frame == "odom"
        assert frames[0].base_frame == "base_link" and np.abs(frames[0].T_base_sensor - T_base_lidar).max() < 1e-12
        for frame, s in zip(frames, cloud_stamps, strict=True):
            k, alpha = divmod(s, 10**9)
            expected = geometry.interpolate_se3(odom[k], odom[k + 1], alpha / 1e9) @ T_base_lidar
            assert np.abs(frame.T_world_sensor - expected).max() < 1e-12
            assert frame.stamp_ns == (s if stamp is StampSource.HEADER else s + delay_ns)
    with pytest.raises(
        SourceError, match=r"pose_from_odometry topic /lidar/points has type sensor_msgs/msg/PointCloud2"
    ):
        open_source(path, pose_from_odometry="/lidar/points")
