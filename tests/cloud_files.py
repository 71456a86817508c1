"""Small binary PCD / PLY writers for the reader tests: every field written with the dtype given, independently
of Open3D's writers (so the tests check what Open3D's reader makes of a file that another tool wrote); and ROS logs
(MCAP, ROS 1 bag, rosbag2 folder) with PointCloud2, TF and odometry, written with mcap_ros2 / rosbags."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

#: numpy dtype -> (PCD TYPE, PLY property type)
_TYPES = {
    np.dtype("float32"): ("F", "float"), np.dtype("float64"): ("F", "double"),
    np.dtype("uint32"): ("U", "uint"), np.dtype("int32"): ("I", "int"),
    np.dtype("uint16"): ("U", "ushort"), np.dtype("uint8"): ("U", "uchar"),
    np.dtype("uint64"): ("U", None), np.dtype("int64"): ("I", None),
}


def _table(columns: dict[str, np.ndarray]) -> np.ndarray:
    n = len(next(iter(columns.values())))
    table = np.zeros(n, dtype=np.dtype([(name, values.dtype.newbyteorder("<")) for name, values in columns.items()]))
    for name, values in columns.items():
        table[name] = values
    return table


def _ascii_rows(columns: dict[str, np.ndarray]) -> bytes:
    """One line per point, every value written so that it reads back exactly (``repr`` of floats)."""
    values = [v.tolist() for v in columns.values()]
    return "".join(" ".join(repr(float(x)) if isinstance(x, float) else str(x) for x in row) + "\n"
                   for row in zip(*values)).encode()


def write_pcd(path: Path, columns: dict[str, np.ndarray], *, data: str = "binary") -> Path:
    """A PCD with one field per column (name -> (N,) array, its dtype kept), ``DATA binary`` or ``ascii``."""
    table = _table(columns)
    types = [_TYPES[np.dtype(v.dtype)][0] for v in columns.values()]
    sizes = [np.dtype(v.dtype).itemsize for v in columns.values()]
    n = len(table)
    header = (f"# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS {' '.join(columns)}\n"
              f"SIZE {' '.join(map(str, sizes))}\nTYPE {' '.join(types)}\nCOUNT {' '.join('1' for _ in columns)}\n"
              f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {data}\n")
    path.write_bytes(header.encode() + (table.tobytes() if data == "binary" else _ascii_rows(columns)))
    return path


def write_ply(path: Path, columns: dict[str, np.ndarray], *, ascii: bool = False) -> Path:
    """A ``binary_little_endian`` (or ``ascii``) PLY with one vertex property per column."""
    table = _table(columns)
    props = "".join(f"property {_TYPES[np.dtype(v.dtype)][1]} {name}\n" for name, v in columns.items())
    encoding = "ascii" if ascii else "binary_little_endian"
    header = f"ply\nformat {encoding} 1.0\nelement vertex {len(table)}\n{props}end_header\n"
    path.write_bytes(header.encode() + (_ascii_rows(columns) if ascii else table.tobytes()))
    return path


def replace_once(path: Path, old: bytes, new: bytes) -> Path:
    """Replace the one occurrence of ``old`` in a file (a header field, say) with ``new``."""
    data = path.read_bytes()
    assert data.count(old) == 1, (path, old)
    path.write_bytes(data.replace(old, new))
    return path


def xyz_columns(rng: np.random.Generator, n: int) -> dict[str, np.ndarray]:
    xyz = rng.normal(scale=5.0, size=(n, 3)).astype(np.float32)
    return {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}


# ---- ROS logs with point clouds (MCAP, ROS 1 bag, rosbag2 folder), written without driftmap's reader -------------

ROS_LOG_KINDS = ("mcap", "rosbag1", "rosbag2")
ROS_CLOUD_TOPIC = "/points"
ROS_ODOM_TOPIC = "/odom"


def _quat_xyzw(T: np.ndarray) -> list[float]:
    from scipy.spatial.transform import Rotation

    return [float(v) for v in Rotation.from_matrix(T[:3, :3]).as_quat()]


def pointcloud2_fields(xyz: np.ndarray, intensity: np.ndarray) -> dict:
    """The layout fields of a PointCloud2 of float32 ``x y z intensity`` (16 bytes a point), data as bytes."""
    table = np.zeros(len(xyz), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4")])
    table["x"], table["y"], table["z"], table["intensity"] = xyz[:, 0], xyz[:, 1], xyz[:, 2], intensity
    fields = [{"name": n, "offset": 4 * k, "datatype": 7, "count": 1} for k, n in enumerate(("x", "y", "z", "intensity"))]
    return {"height": 1, "width": len(xyz), "fields": fields, "is_bigendian": False, "point_step": 16,
            "row_step": 16 * len(xyz), "data": table.tobytes(), "is_dense": True}


def ros_log_messages(scans: list, T_odom_base: list, T_base_lidar: np.ndarray) -> list[tuple[str, str, dict, int]]:
    """(topic, ROS 2 type, message dict, log time) of :func:`write_ros_log`'s log."""
    def header(stamp: int, frame: str) -> dict:
        return {"stamp": {"sec": stamp // 10**9, "nanosec": stamp % 10**9}, "frame_id": frame}

    def tf(stamp: int, parent: str, child: str, T: np.ndarray) -> dict:
        q = _quat_xyzw(T)
        return {"transforms": [{"header": header(stamp, parent), "child_frame_id": child, "transform": {
            "translation": dict(zip("xyz", map(float, T[:3, 3]))), "rotation": dict(zip("xyzw", q))}}]}

    first = scans[0][0]
    out = [("/tf_static", "tf2_msgs/msg/TFMessage", tf(first, "base_link", "lidar", T_base_lidar), first)]
    for (stamp, xyz, intensity), T in zip(scans, T_odom_base, strict=True):
        q = _quat_xyzw(T)
        odom = {"header": header(stamp, "odom"), "child_frame_id": "base_link",
                "pose": {"pose": {"position": dict(zip("xyz", map(float, T[:3, 3]))), "orientation": dict(zip("xyzw", q))},
                         "covariance": [0.0] * 36},
                "twist": {"twist": {"linear": {"x": 0.0, "y": 0.0, "z": 0.0}, "angular": {"x": 0.0, "y": 0.0, "z": 0.0}},
                          "covariance": [0.0] * 36}}
        out.append(("/tf", "tf2_msgs/msg/TFMessage", tf(stamp, "odom", "base_link", T), stamp))
        out.append((ROS_ODOM_TOPIC, "nav_msgs/msg/Odometry", odom, stamp))
        out.append((ROS_CLOUD_TOPIC, "sensor_msgs/msg/PointCloud2",
                    {"header": header(stamp, "lidar"), **pointcloud2_fields(xyz, intensity)}, stamp + 1000))
    return out


def _rosbags_object(ts: Any, typename: str, value: Any) -> Any:
    """A message dict as an object of a rosbags typestore (nested messages, byte and number arrays converted)."""
    if not isinstance(value, dict):
        return value
    cls = ts.types[typename]
    kwargs = {}
    for name, (kind, arg) in _field_specs(ts, typename):
        v = value.get(name, 0 if name == "seq" else None)
        if kind == "msg":
            kwargs[name] = _rosbags_object(ts, arg, v)
        elif kind == "msglist":
            kwargs[name] = [_rosbags_object(ts, arg, x) for x in v]
        elif kind == "bytes":
            kwargs[name] = np.frombuffer(v, dtype=np.uint8)
        elif kind == "array":
            kwargs[name] = np.asarray(v, dtype=np.float64)
        else:
            kwargs[name] = v
    return cls(**kwargs)


def _field_specs(ts: Any, typename: str) -> list[tuple[str, tuple[str, str | None]]]:
    """(field name, (kind, message type)) of a rosbags type: kind msg / msglist / bytes / array / value."""
    from rosbags.typesys.base import Nodetype

    specs = []
    for name, desc in ts.fielddefs[typename][1]:
        node, arg = desc
        if node == Nodetype.NAME:
            specs.append((name, ("msg", arg)))
        elif node in (Nodetype.SEQUENCE, Nodetype.ARRAY):
            inner_node, inner = arg[0]
            if inner_node == Nodetype.NAME:
                specs.append((name, ("msglist", inner)))
            elif inner[0] == "uint8":
                specs.append((name, ("bytes", None)))
            else:
                specs.append((name, ("array", None)))
        else:
            specs.append((name, ("value", None)))
    return specs


def write_ros_log(path: Path, kind: str, scans: list, T_odom_base: list, T_base_lidar: np.ndarray, *,
                  short_last_cloud: bool = False) -> Path:
    """A ROS log of ``kind`` (``mcap``, ``rosbag1``, ``rosbag2``) with ``/tf_static`` (base_link -> lidar), per scan
    ``/tf`` and ``/odom`` (odom -> base_link) and a PointCloud2 on ``/points`` (frame ``lidar``, logged 1 us after
    its stamp). ``scans``: ``[(stamp_ns, (N, 3) float32 xyz, (N,) float32 intensity)]``. ``short_last_cloud``: the
    last cloud's width says one point more than its data holds (a frame a reader must refuse or skip)."""
    messages = ros_log_messages(scans, T_odom_base, T_base_lidar)
    if short_last_cloud:
        topic, typename, msg, log_time = messages[-1]
        messages[-1] = (topic, typename, {**msg, "width": msg["width"] + 1, "row_step": msg["row_step"] + 16}, log_time)
    return write_ros_messages(path, kind, messages)


def write_ros_messages(path: Path, kind: str, messages: list[tuple[str, str, dict, int]]) -> Path:
    """Write (topic, ROS 2 type, message dict, log time) as an MCAP (mcap_ros2), a ROS 1 bag or a rosbag2 folder
    (rosbags), uncompressed."""
    if kind == "mcap":
        from mcap.writer import CompressionType
        from mcap_ros2.writer import Writer

        from driftmap.export.ros_messages import ros2_msgdef

        with open(path, "wb") as f:
            writer = Writer(f, compression=CompressionType.NONE)
            schemas: dict = {}
            for topic, typename, msg, log_time in messages:
                if typename not in schemas:
                    schemas[typename] = writer.register_msgdef(typename, ros2_msgdef(typename))
                writer.write_message(topic, schemas[typename], msg, log_time=log_time, publish_time=log_time)
            writer.finish()
        return path
    from rosbags.typesys import Stores, get_typestore

    ros1 = kind == "rosbag1"
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if ros1:  # rosbags' ROS 1 store has no tf2_msgs; ROS 1 tf2_msgs/TFMessage has this definition
        from rosbags.rosbag1 import Writer as Bag1Writer
        from rosbags.typesys import get_types_from_msg

        ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
        writer, serialize = Bag1Writer(path), ts.serialize_ros1
    else:
        from rosbags.rosbag2 import Writer as Bag2Writer

        writer, serialize = Bag2Writer(path, version=9), ts.serialize_cdr
    with writer:
        connections: dict = {}
        for topic, typename, msg, log_time in messages:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, typename, typestore=ts)
            writer.write(connections[topic], log_time, serialize(_rosbags_object(ts, typename, msg), typename))
    return path
