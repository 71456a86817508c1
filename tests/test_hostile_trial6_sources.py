"""The sixth hostile-input trial, the source cases: ``--pose-from-tf`` naming no pose (B3: parent == child, a world
frame that is the sensor's own frame or below the moving frame), TF errors that named no file (W9), quaternions of
norm 2 normalised silently (W10b), a Redwood ``trajectory.log`` naming one frame twice (B6) and two intrinsics JSONs of
different values in a Redwood folder (W18). Every case goes through the CLI: one error line naming the file / flag /
frame, exit 1 or 2, no traceback."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap_ros2.writer import Writer as Ros2McapWriter

from driftmap.export.ros_messages import ros2_msgdef
from driftmap.sources.base import open_source

T0_NS = 1_700_000_000 * 10**9


def _cli(*args: object) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "driftmap.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=600, env={**os.environ, "COLUMNS": "200"})


def _error(out: subprocess.CompletedProcess) -> str:
    """The one-line error of a refused command (exit 1 or 2, no traceback), whitespace joined."""
    assert out.returncode in (1, 2), (out.returncode, out.stdout[-1500:], out.stderr[-1500:])
    assert "Traceback" not in out.stderr and "Traceback" not in out.stdout
    lines = [line for line in out.stderr.splitlines() if line.startswith("error:")]
    assert len(lines) == 1, out.stderr[-2000:]
    return " ".join(out.stderr.split())


# ---- a small ROS log (as /tmp/hostile6/mkmcap.py and mkbag1.py): a lidar in a room, odom -> base_link -> lidar


def _room(n: int = 600) -> np.ndarray:
    rng = np.random.default_rng(1)
    u, v = rng.uniform(-4, 4, n), rng.uniform(0, 2.5, n)
    wall = rng.integers(5, size=n)
    pts = np.stack([u, v * 1.6 - 2, np.zeros(n)], axis=1)
    pts[wall == 0] = np.stack([np.full(n, 4.0), u, v], axis=1)[wall == 0]
    pts[wall == 1] = np.stack([np.full(n, -4.0), u, v], axis=1)[wall == 1]
    pts[wall == 2] = np.stack([u, np.full(n, 4.0), v], axis=1)[wall == 2]
    pts[wall == 3] = np.stack([u, np.full(n, -4.0), v], axis=1)[wall == 3]
    return pts.astype(np.float32)


def _header(stamp_ns: int, frame_id: str) -> dict[str, Any]:
    return {"stamp": {"sec": stamp_ns // 10**9, "nanosec": stamp_ns % 10**9}, "frame_id": frame_id}


def _tf(stamp_ns: int, parent: str, child: str, xyz: tuple[float, float, float], qw: float = 1.0) -> dict[str, Any]:
    return {"header": _header(stamp_ns, parent), "child_frame_id": child,
            "transform": {"translation": dict(zip("xyz", xyz, strict=True)),
                          "rotation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": qw}}}


def write_ros_mcap(path: Path, mode: str = "ok", n: int = 6) -> Path:
    """``/points`` (frame ``lidar``), ``/tf`` (odom -> base_link -> lidar) and ``/odom`` per frame. ``mode``:
    ``twoparents`` (``map -> base_link`` too), ``badquat`` (message 3's odom -> base_link and /odom quaternion w=2)."""
    world = _room()
    schemas: dict[str, Any] = {}
    with open(path, "wb") as f:
        writer = Ros2McapWriter(f)

        def write(topic: str, typename: str, msg: dict[str, Any], t: int) -> None:
            if typename not in schemas:
                schemas[typename] = writer.register_msgdef(typename, ros2_msgdef(typename))
            writer.write_message(topic, schemas[typename], msg, log_time=t, publish_time=t)

        for i in range(n):
            t, x = T0_NS + i * 100_000_000, 0.1 * i
            qw = 2.0 if mode == "badquat" and i == 3 else 1.0
            tfs = [_tf(t, "odom", "base_link", (x, 0.0, 0.0), qw), _tf(t, "base_link", "lidar", (0.0, 0.0, 0.5))]
            if mode == "twoparents":
                tfs.append(_tf(t, "map", "base_link", (5.0, 0.0, 0.0)))
            write("/tf", "tf2_msgs/msg/TFMessage", {"transforms": tfs}, t)
            write("/odom", "nav_msgs/msg/Odometry", {
                "header": _header(t, "odom"), "child_frame_id": "base_link",
                "pose": {"pose": {"position": {"x": x, "y": 0.0, "z": 0.0},
                                  "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": qw}}}}, t)
            pts = world - np.array([x, 0, 0.5], np.float32)
            fields = [{"name": c, "offset": 4 * k, "datatype": 7, "count": 1} for k, c in enumerate("xyz")]
            write("/points", "sensor_msgs/msg/PointCloud2", {
                "header": _header(t, "lidar"), "height": 1, "width": len(pts), "fields": fields, "is_bigendian": False,
                "point_step": 12, "row_step": 12 * len(pts), "data": pts.tobytes(), "is_dense": True}, t)
        writer.finish()
    return path


def write_rosbag2(path: Path, mode: str = "ok", n: int = 6) -> Path:
    """A rosbag2 folder: ``/points`` and ``/tf`` odom -> lidar; ``framechange``: message 3's frame_id is ``lidar2``."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    types = ts.types
    H, T, PF = types["std_msgs/msg/Header"], types["builtin_interfaces/msg/Time"], types["sensor_msgs/msg/PointField"]
    TS, TR = types["geometry_msgs/msg/TransformStamped"], types["geometry_msgs/msg/Transform"]
    V, Q = types["geometry_msgs/msg/Vector3"], types["geometry_msgs/msg/Quaternion"]
    world = _room()
    with Writer(path, version=8) as w:
        c = w.add_connection("/points", "sensor_msgs/msg/PointCloud2", typestore=ts)
        ct = w.add_connection("/tf", "tf2_msgs/msg/TFMessage", typestore=ts)
        for i in range(n):
            t = T0_NS + i * 100_000_000
            sec, ns = divmod(t, 10**9)
            frame = "lidar2" if mode == "framechange" and i == 3 else "lidar"
            pts = world - np.array([0.1 * i, 0, 0.5], np.float32)
            msg = types["sensor_msgs/msg/PointCloud2"](
                header=H(stamp=T(sec=sec, nanosec=ns), frame_id=frame), height=1, width=len(pts),
                fields=[PF(name=n_, offset=4 * k, datatype=7, count=1) for k, n_ in enumerate("xyz")],
                is_bigendian=False, point_step=12, row_step=12 * len(pts),
                data=np.frombuffer(pts.tobytes(), np.uint8), is_dense=True)
            w.write(c, t, ts.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2"))
            tf = types["tf2_msgs/msg/TFMessage"](transforms=[TS(
                header=H(stamp=T(sec=sec, nanosec=ns), frame_id="odom"), child_frame_id="lidar",
                transform=TR(translation=V(x=0.1 * i, y=0.0, z=0.5), rotation=Q(x=0.0, y=0.0, z=0.0, w=1.0)))])
            w.write(ct, t, ts.serialize_cdr(tf, "tf2_msgs/msg/TFMessage"))
    return path


@pytest.fixture(scope="module")
def ros(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("trial6_ros")
    return {
        "ok": write_ros_mcap(root / "ok.mcap"),
        "twoparents": write_ros_mcap(root / "twoparents.mcap", "twoparents"),
        "badquat": write_ros_mcap(root / "badquat.mcap", "badquat"),
        "b2_ok": write_rosbag2(root / "b2_ok"),
        "b2_framechange": write_rosbag2(root / "b2_framechange", "framechange"),
    }


def test_t6_b3_pose_from_tf_parent_equal_to_child_is_one_error_naming_the_flag(ros: dict, tmp_path: Path) -> None:
    out = _error(_cli("build", ros["ok"], "--out", tmp_path / "s", "--pose-from-tf", "lidar,lidar",
                      "--poses-from-source", "--no-loop-closure"))
    assert "ok.mcap" in out and "--pose-from-tf lidar,lidar" in out and "both 'lidar'" in out, out
    assert not (tmp_path / "s").exists()
    out = _error(_cli("convert", ros["b2_ok"], tmp_path / "c.mcap", "--pose-from-tf", "lidar,lidar"))
    assert "b2_ok" in out and "--pose-from-tf lidar,lidar" in out and "makes no pose" in out, out
    assert not (tmp_path / "c.mcap").exists()


def test_t6_b3_pose_from_tf_world_frame_that_moves_with_the_sensor_is_refused(ros: dict, tmp_path: Path) -> None:
    # the world frame is the sensor's own frame: every pose would be the identity
    out = _error(_cli("build", ros["ok"], "--out", tmp_path / "s1", "--pose-from-tf", "lidar,odom",
                      "--poses-from-source", "--no-loop-closure"))
    assert "ok.mcap" in out and "--pose-from-tf lidar,odom" in out and "frame of the sensor topic /points" in out, out
    # PARENT,CHILD swapped: the world frame lies below the child frame, the "pose" is a constant extrinsic
    out = _error(_cli("build", ros["ok"], "--out", tmp_path / "s2", "--pose-from-tf", "base_link,odom",
                      "--poses-from-source", "--no-loop-closure"))
    assert "--pose-from-tf base_link,odom" in out and "lies below the child frame 'odom'" in out, out
    assert "did you mean --pose-from-tf odom,base_link" in out, out
    # the right order still gives the moving poses
    frames = list(open_source(ros["ok"], pose_from_tf=("odom", "base_link")))
    assert [round(float(f.T_world_sensor[0, 3]), 6) for f in frames] == [round(0.1 * i, 6) for i in range(6)]


def test_t6_w9_tf_errors_name_the_log_topic_and_message(ros: dict, tmp_path: Path) -> None:
    out = _error(_cli("build", ros["twoparents"], "--out", tmp_path / "s1", "--pose-from-tf", "odom,lidar",
                      "--poses-from-source", "--no-loop-closure"))
    assert "twoparents.mcap: /tf message logged at" in out and f"(stamp {T0_NS} ns)" in out, out
    assert "frame 'base_link' has two parents, 'odom'" in out and "and 'map'" in out, out
    out = _error(_cli("build", ros["b2_framechange"], "--out", tmp_path / "s2", "--pose-from-tf", "odom,lidar",
                      "--poses-from-source", "--no-loop-closure"))
    assert "b2_framechange: /points message 3" in out and f"stamp {T0_NS + 300_000_000} ns" in out, out
    assert "frame_id 'lidar2' (changed from 'lidar')" in out and "'lidar2' is not in the TF tree" in out, out


def test_t6_w10b_quaternion_of_norm_2_in_tf_or_odometry_is_refused(ros: dict, tmp_path: Path) -> None:
    stamp = f"stamp {T0_NS + 300_000_000} ns"
    out = _error(_cli("build", ros["badquat"], "--out", tmp_path / "s1", "--pose-from-tf", "odom,lidar",
                      "--poses-from-source", "--no-loop-closure"))
    assert "badquat.mcap: /tf odom -> base_link" in out and stamp in out and "norm 2.0000, expected 1" in out, out
    out = _error(_cli("build", ros["badquat"], "--out", tmp_path / "s2", "--pose-from-odometry", "/odom",
                      "--poses-from-source", "--no-loop-closure"))
    assert "badquat.mcap: /odom" in out and stamp in out and "norm 2.0000, expected 1" in out, out


# ---- Redwood (ICL-NUIM in Redwood layout)


def _redwood_copy(icl_dir: Path, dest: Path) -> Path:
    shutil.copytree(icl_dir, dest)
    return dest


def test_t6_b6_redwood_log_naming_one_frame_twice_is_refused(icl_dir: Path, tmp_path: Path) -> None:
    folder = _redwood_copy(icl_dir, tmp_path / "rw_dupid")
    log = folder / "trajectory.log"
    lines = log.read_text().splitlines(keepends=True)
    assert lines[5].split() == ["1", "1", "2"]
    lines[5] = "0 0 1\n"  # block 2 names frame 0 again
    log.write_text("".join(lines))
    out = _error(_cli("build", folder, "--out", tmp_path / "s", "--poses-from-source", "--no-loop-closure",
                      "--lenient"))
    assert "trajectory.log:6: frame id 0 is named by two pose blocks, at lines 1 and 6" in out, out
    assert not (tmp_path / "s").exists()


def test_t6_w18_two_redwood_intrinsics_jsons_that_disagree_are_refused(icl_dir: Path, tmp_path: Path) -> None:
    folder = _redwood_copy(icl_dir, tmp_path / "rw_twojson")
    original = (folder / "camera_primesense.json").read_text()
    (folder / "intrinsic.json").write_text(original.replace("525.0", "600.0"))
    assert "600.0" in (folder / "intrinsic.json").read_text()
    out = _error(_cli("build", folder, "--out", tmp_path / "s", "--poses-from-source", "--no-loop-closure"))
    assert "two intrinsics JSONs with different values" in out, out
    assert "camera_primesense.json (fx=525" in out and "intrinsic.json (fx=600" in out and "--intrinsics" in out, out
    # --intrinsics chooses; a second JSON with the same values is no conflict
    assert open_source(folder, intrinsics=str(folder / "intrinsic.json")).intrinsics.fx == 600.0
    (folder / "intrinsic.json").write_text(original)
    assert open_source(folder).intrinsics.fx == 525.0
