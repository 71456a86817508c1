"""No silent wrong answer at the readers' boundary (issue 22), through the path a user takes (``driftmap build`` /
``convert`` via the CLI, or the API where that is the entry point):

- sizes read from a header (PCD ``POINTS`` / ``WIDTH`` / ``HEIGHT``, PLY element counts, a depth PNG's size, a
  PointCloud2's layout) are checked against the bytes present before anything is allocated;
- stamps read from files are finite, ``>= 0`` and within the int64 ns a frame carries, else an error naming the
  file and the line;
- the ROS-log options (``--lenient``, ``--topic``, ``--pose-from-tf``, ``--pose-from-odometry``) are accepted for
  every ROS log format and still refused, with the documented message, for formats that do not take them;
- a folder of KITTI-layout ``.bin`` scans has one point layout (x, y, z, intensity or x, y, z) for every file;
- symlink loops, bad intrinsics, file names that are stamps and foreign formats are reported as what they are.
"""

from __future__ import annotations

import shutil
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from cloud_files import (
    ROS_LOG_KINDS,
    replace_once,
    ros_log_messages,
    write_pcd,
    write_ply,
    write_ros_log,
    write_ros_messages,
)
from PIL import Image
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from driftmap import geometry
from driftmap.cli import app
from driftmap.errors import ConfigError, SourceError
from driftmap.sources.base import open_source
from driftmap.store.frame_store import FrameStore

KITTI_EVERY = 4
"""KITTI frame 0, every 4th point: 31,167 points (the cloud of the issue)."""
LOG_STAMP0_NS = 1_700_000_000_000_000_000


def _ok(args: list[object]) -> str:
    result = CliRunner().invoke(app, [str(a) for a in args])
    assert result.exit_code == 0, (result.output, result.exception)
    return result.output


def _refused(args: list[object]) -> BaseException:
    result = CliRunner().invoke(app, [str(a) for a in args])
    assert result.exit_code != 0 and result.exception is not None, result.output
    return result.exception


def _kitti_scan(kitti_dir: Path, k: int, every: int = KITTI_EVERY) -> np.ndarray:
    return np.fromfile(kitti_dir / "velodyne" / f"{k:06d}.bin", dtype="<f4").reshape(-1, 4)[::every]


def _columns(scan: np.ndarray) -> dict[str, np.ndarray]:
    return {"x": scan[:, 0].copy(), "y": scan[:, 1].copy(), "z": scan[:, 2].copy(), "intensity": scan[:, 3].copy()}


# ---- 1. sizes in headers ---------------------------------------------------------------------------------------


def _cloud_file(folder: Path, kind: str, scan: np.ndarray) -> Path:
    """KITTI frame 0 (31,167 points) as ``scan_0`` in one of the cloud encodings."""
    folder.mkdir(parents=True, exist_ok=True)
    if kind == "pcd_binary_compressed":
        import open3d as o3d

        cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(scan[:, :3]))
        cloud.point["intensity"] = o3d.core.Tensor(scan[:, 3:4])
        path = folder / "scan_0.pcd"
        assert o3d.t.io.write_point_cloud(str(path), cloud, compressed=True)
        return path
    if kind.startswith("pcd"):
        return write_pcd(folder / "scan_0.pcd", _columns(scan), data=kind.removeprefix("pcd_"))
    return write_ply(folder / "scan_0.ply", _columns(scan), ascii=kind == "ply_ascii")


CLOUD_KINDS = ["pcd_ascii", "pcd_binary", "pcd_binary_compressed", "ply_ascii", "ply_binary"]


def _lie_about_count(file: Path, n: int, claimed: int) -> None:
    """Every count field of the header says ``claimed`` instead of ``n`` (consistent with itself, not the data)."""
    if file.suffix == ".pcd":
        replace_once(file, f"WIDTH {n}\n".encode(), f"WIDTH {claimed}\n".encode())
        replace_once(file, f"POINTS {n}\n".encode(), f"POINTS {claimed}\n".encode())
    else:
        replace_once(file, f"element vertex {n}\n".encode(), f"element vertex {claimed}\n".encode())


@pytest.mark.parametrize("claimed", [99_999_999, 10])
@pytest.mark.parametrize("kind", CLOUD_KINDS)
def test_a_cloud_header_that_lies_about_its_point_count_is_refused_by_build(kind: str, claimed: int, kitti_dir: Path,
                                                                           tmp_path: Path) -> None:
    """The issue's file: 31,167 points, a header saying 99,999,999 (Open3D then returns 99,999,999 points, zeros
    beyond the data, or crashes on binary_compressed); and a header saying fewer points than the data holds."""
    scan = _kitti_scan(kitti_dir, 0)
    assert len(scan) == 31_167
    folder = tmp_path / "clouds"
    file = _cloud_file(folder, kind, scan)
    assert len(open_source(folder).frame(0).points_sensor) == 31_167  # the honest file reads as written
    _lie_about_count(file, 31_167, claimed)
    exc = _refused(["build", folder, "--out", tmp_path / "store", "--no-loop-closure"])
    assert isinstance(exc, SourceError), exc
    field = "header field POINTS" if kind.startswith("pcd") else "header field element vertex"
    assert str(exc).startswith(str(file)) and field in str(exc), exc
    if (tmp_path / "store").exists():  # nothing of the lie was stored
        with FrameStore.open(tmp_path / "store") as store:
            assert store.frame_ids.size == 0


def test_a_pcd_whose_points_contradict_width_and_height_names_both(kitti_dir: Path, tmp_path: Path) -> None:
    folder = tmp_path / "clouds"
    file = _cloud_file(folder, "pcd_ascii", _kitti_scan(kitti_dir, 0))
    replace_once(file, b"POINTS 31167\n", b"POINTS 99999999\n")
    with pytest.raises(SourceError, match=r"scan_0\.pcd:10: header field POINTS is 99999999 but WIDTH \* HEIGHT"):
        list(open_source(folder))


def test_lenient_skips_a_cloud_whose_header_lies_and_says_why(kitti_dir: Path, tmp_path: Path) -> None:
    folder = tmp_path / "clouds"
    folder.mkdir()
    for k in range(3):
        write_pcd(folder / f"scan_{k}.pcd", _columns(_kitti_scan(kitti_dir, k)))
    n1 = len(_kitti_scan(kitti_dir, 1))
    _lie_about_count(folder / "scan_1.pcd", n1, 99_999_999)
    source = open_source(folder, lenient=True)
    frames = list(source)
    assert [f.frame_id for f in frames] == [0, 2]
    (index, reason), = source.skipped
    assert index == 1 and "scan_1.pcd" in reason and "POINTS" in reason


def _png_with_size(src: Path, dst: Path, width: int, height: int) -> Path:
    """``src`` (a PNG) with its IHDR width and height replaced (and the chunk's CRC fixed: a well-formed lie)."""
    data = bytearray(src.read_bytes())
    assert data[12:16] == b"IHDR"
    data[16:24] = struct.pack(">II", width, height)
    data[29:33] = struct.pack(">I", zlib.crc32(bytes(data[12:29])) & 0xFFFFFFFF)
    dst.write_bytes(bytes(data))
    return dst


def _sevenscenes_copy(sevenscenes_dir: Path, folder: Path, ids: range) -> Path:
    folder.mkdir(parents=True)
    for i in ids:
        for suffix in ("depth.png", "pose.txt"):
            shutil.copy(sevenscenes_dir / f"frame-{i:06d}.{suffix}", folder / f"frame-{i:06d}.{suffix}")
    return folder


def test_a_depth_png_whose_header_claims_more_pixels_than_its_bytes_hold_is_refused(sevenscenes_dir: Path,
                                                                                    tmp_path: Path) -> None:
    folder = _sevenscenes_copy(sevenscenes_dir, tmp_path / "seq", range(3))
    for width, height in ((2000, 2000), (60_000, 60_000), (640, 479)):
        bad = _png_with_size(sevenscenes_dir / "frame-000001.depth.png", folder / "frame-000001.depth.png", width,
                             height)
        exc = _refused(["build", folder, "--out", tmp_path / "store", "--no-loop-closure"])
        assert isinstance(exc, SourceError) and str(bad) in str(exc)
        assert f"the header says {width}x{height} pixels" in str(exc), exc
        shutil.rmtree(tmp_path / "store", ignore_errors=True)
    source = open_source(folder, lenient=True)  # lenient: the frame is skipped with the reason
    assert [f.frame_id for f in source] == [0, 2] and "640x479" in source.skipped[0][1]


def test_a_pointcloud2_whose_layout_does_not_describe_its_data_is_refused(tmp_path: Path) -> None:
    from driftmap.sources.ros import pointcloud2_array

    class Msg:  # a decoded PointCloud2 (the attributes every decoder gives)
        def __init__(self, width: int, data: bytes) -> None:
            self.height, self.width, self.point_step, self.row_step = 1, width, 12, 12 * width
            self.is_bigendian, self.data = False, data
            self.fields = [type("F", (), {"name": n, "offset": 4 * k, "datatype": 7, "count": 1})
                           for k, n in enumerate("xyz")]

    xyz = np.arange(30, dtype="<f4").tobytes()  # 10 points
    assert len(pointcloud2_array(Msg(10, xyz))) == 10
    with pytest.raises(SourceError, match=r"data has 120 bytes, 20x1 points .* need 240"):
        pointcloud2_array(Msg(20, xyz))
    with pytest.raises(SourceError, match=r"data has 120 bytes, more than the height 1 \* row_step 60"):
        pointcloud2_array(Msg(5, xyz))


# ---- 2. stamps read from files ---------------------------------------------------------------------------------


def _kitti_copy(kitti_dir: Path, folder: Path, n: int, *, scans: list[np.ndarray] | None = None) -> Path:
    (folder / "velodyne").mkdir(parents=True)
    for k in range(n):
        scan = _kitti_scan(kitti_dir, k, every=10) if scans is None else scans[k]
        scan.tofile(folder / "velodyne" / f"{k:06d}.bin")
    shutil.copy(kitti_dir / "calib.txt", folder / "calib.txt")
    return folder


def test_kitti_times_starting_before_zero_are_refused_naming_the_line(kitti_dir: Path, tmp_path: Path) -> None:
    """A times.txt starting at -0.5 s used to reach the store and fail there with a raw struct.error."""
    folder = _kitti_copy(kitti_dir, tmp_path / "seq", 3)
    (folder / "times.txt").write_text("-0.5\n-0.4\n-0.3\n")
    exc = _refused(["build", folder, "--out", tmp_path / "store", "--no-loop-closure"])
    assert isinstance(exc, SourceError)
    assert str(exc).startswith(f"{folder / 'times.txt'}:1: stamp '-0.5' s is negative")
    (folder / "times.txt").write_text("0.0\nnan\n0.2\n")
    with pytest.raises(SourceError, match=r"times\.txt:2: 'nan' is not a number of seconds"):
        open_source(folder)
    (folder / "times.txt").write_text("0.0\n0.1\n1e12\n")
    with pytest.raises(SourceError, match=r"times\.txt:3: stamp '1e12' s is beyond the largest stamp"):
        open_source(folder)
    (folder / "times.txt").write_text("0.0\n0.1\n0.1\n")  # strictly increasing (lenient: the later frame skipped)
    with pytest.raises(SourceError, match=r"times\.txt: duplicate stamp: frame 2 .* frame 1"):
        open_source(folder)
    assert open_source(folder, lenient=True).frame_ids() == [0, 1]


def test_tum_depth_list_stamps_are_checked(sevenscenes_dir: Path, tmp_path: Path) -> None:
    folder = tmp_path / "rgbd_dataset_freiburg1_x"
    (folder / "depth").mkdir(parents=True)
    lines = []
    for k, stamp in enumerate(("-0.033", "0.0", "0.033")):
        depth = np.asarray(Image.open(sevenscenes_dir / f"frame-{k:06d}.depth.png")).astype(np.uint32) * 5
        Image.fromarray(np.clip(depth, 0, 65535).astype(np.uint16)).save(folder / "depth" / f"{k}.png")
        lines.append(f"{stamp} depth/{k}.png")
    (folder / "depth.txt").write_text("# depth\n" + "\n".join(lines) + "\n")
    exc = _refused(["build", folder, "--out", tmp_path / "store"])
    assert isinstance(exc, SourceError) and str(exc).startswith(f"{folder / 'depth.txt'}:2: stamp '-0.033' s is negative")


def test_cloud_folder_stamps_from_a_pose_file_are_checked_naming_its_line(kitti_dir: Path, tmp_path: Path) -> None:
    folder = tmp_path / "clouds"
    folder.mkdir()
    for k in range(3):
        write_pcd(folder / f"scan_{k}.pcd", _columns(_kitti_scan(kitti_dir, k, every=10)))
    poses = tmp_path / "poses.tum"
    poses.write_text("# stamp x y z qx qy qz qw\n-1.0 0 0 0 0 0 0 1\n-0.9 0 0 0 0 0 0 1\n-0.8 0 0 0 0 0 0 1\n")
    with pytest.raises(SourceError, match=rf"{poses}:2: stamp -1000000000 ns is negative"):
        open_source(folder, poses=poses)  # (the API's pose file: its rows stamp the clouds)
    (folder / "times.txt").write_text("0.0\n-0.1\n0.2\n")
    exc = _refused(["build", folder, "--out", tmp_path / "store"])
    assert isinstance(exc, SourceError) and str(exc).startswith(f"{folder / 'times.txt'}:2: stamp '-0.1' s is negative")


def test_a_negative_ros_header_stamp_is_refused_naming_the_message(kitti_dir: Path, tmp_path: Path) -> None:
    """ROS 2's ``builtin_interfaces/Time.sec`` is an int32: a negative stamp is refused (lenient: skipped)."""
    scans = [(LOG_STAMP0_NS + k * 100_000_000, *_xyz_intensity(_kitti_scan(kitti_dir, k, 50))) for k in range(3)]
    messages = ros_log_messages(scans, [np.eye(4)] * 3, np.eye(4))
    first_cloud = next(k for k, m in enumerate(messages) if m[0] == "/points")
    topic, typename, msg, log_time = messages[first_cloud]
    messages[first_cloud] = (topic, typename, {**msg, "header": {**msg["header"], "stamp": {"sec": -1, "nanosec": 0}}},
                             log_time)
    log = write_ros_messages(tmp_path / "log.mcap", "mcap", messages)
    with pytest.raises(SourceError, match=r"log\.mcap: /points message 0: header\.stamp: stamp -1000000000 ns is negative"):
        list(open_source(log))
    source = open_source(log, lenient=True)
    assert [f.frame_id for f in source] == [1, 2] and "negative" in source.skipped[0][1]


def _xyz_intensity(scan: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.ascontiguousarray(scan[:, :3]), np.ascontiguousarray(scan[:, 3])


# ---- 6. ROS-log options from the command line ------------------------------------------------------------------


N_LOG_SCANS = 3


@pytest.fixture(scope="module")
def ros_logs(kitti_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[Path, list[np.ndarray]]]:
    """Three real KITTI scans (every 20th point) as PointCloud2 on /points in an MCAP, a ROS 1 bag and a rosbag2
    folder, with /tf, /tf_static and /odom, and a fourth cloud whose data is one point short (only --lenient reads
    past it). Values: (log, the expected T_world_sensor = T_odom_base @ T_base_lidar per scan)."""
    root = tmp_path_factory.mktemp("ros_logs")
    scans, T_odom_base = [], []
    for k in range(N_LOG_SCANS + 1):
        scan = _kitti_scan(kitti_dir, k, every=20)
        scans.append((LOG_STAMP0_NS + k * 100_000_000, scan[:, :3].copy(), scan[:, 3].copy()))
        T_odom_base.append(geometry.make_transform(Rotation.from_euler("z", 2.0 * k, degrees=True), (0.8 * k, 0.1 * k, 0)))
    T_base_lidar = geometry.make_transform(None, (0.3, 0.0, 1.7))
    logs = {}
    for kind in ROS_LOG_KINDS:
        path = root / {"mcap": "log.mcap", "rosbag1": "log.bag", "rosbag2": "log"}[kind]
        write_ros_log(path, kind, scans, T_odom_base, T_base_lidar, short_last_cloud=True)
        logs[kind] = (path, [T @ T_base_lidar for T in T_odom_base[:N_LOG_SCANS]])
    return logs


POSE_OPTIONS = {"tf": ["--pose-from-tf", "odom,base_link"], "odometry": ["--pose-from-odometry", "/odom"]}


@pytest.mark.parametrize("kind", ROS_LOG_KINDS)
def test_ros_log_options_are_accepted_by_build(kind: str, ros_logs: dict, tmp_path: Path) -> None:
    log, expected = ros_logs[kind]
    for name, pose_option in POSE_OPTIONS.items():
        out = tmp_path / f"store_{name}"
        _ok(["build", log, "--out", out, "--lenient", "--topic", "/points", *pose_option, "--poses-from-source",
             "--no-loop-closure"])
        with FrameStore.open(out) as store:
            assert store.frame_ids.tolist() == [0, 1, 2]  # the short fourth cloud skipped (--lenient)
            np.testing.assert_allclose(store.poses(0), np.array(expected), atol=1e-9)
    exc = _refused(["build", log, "--out", tmp_path / "strict", "--topic", "/points", "--no-loop-closure"])
    assert isinstance(exc, SourceError) and "/points message 3" in str(exc)


@pytest.mark.parametrize("kind", ROS_LOG_KINDS)
def test_ros_log_options_are_accepted_by_convert(kind: str, ros_logs: dict, tmp_path: Path) -> None:
    log, expected = ros_logs[kind]
    for name, pose_option in POSE_OPTIONS.items():
        out = tmp_path / f"{name}.mcap"
        _ok(["convert", log, out, "--lenient", "--topic", "/points", *pose_option])
        frames = list(open_source(out))
        assert [f.frame_id for f in frames] == [0, 1, 2]
        np.testing.assert_allclose([f.T_world_sensor for f in frames], expected, atol=1e-9)


def test_depth_settings_stay_refused_for_ros_logs(ros_logs: dict, tmp_path: Path) -> None:
    """Declaring the ROS openers' options does not make build pass depth-image settings to logs whose topic may be a
    PointCloud2 (docs/sources-datasets.md: refused rather than ignored)."""
    log, _ = ros_logs["mcap"]
    result = CliRunner().invoke(app, ["build", str(log), "--out", str(tmp_path / "s"), "--lenient"],
                                env={"DRIFTMAP_DEPTH__MIN_DEPTH_M": "0.5"})
    assert isinstance(result.exception, ConfigError), result.output
    assert str(result.exception).startswith(f"depth.min_depth_m: does not apply to {log} (format mcap")


@pytest.mark.parametrize("command", ["build", "convert"])
def test_ros_log_options_are_still_refused_for_a_kitti_folder(command: str, kitti_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / ("store" if command == "build" else "out.mcap")
    target = ["--out", out] if command == "build" else [out]
    for flag, value in (("--topic", "/points"), ("--pose-from-tf", "odom,base_link"), ("--pose-from-odometry", "/odom")):
        exc = _refused([command, kitti_dir, *target, flag, value])
        assert isinstance(exc, ConfigError)
        assert str(exc) == f"{flag}: does not apply to {kitti_dir} (format kitti, which takes --lenient, --point-layout)"
    assert not out.exists()


# ---- 8. one point layout for a KITTI-layout folder --------------------------------------------------------------


def test_a_folder_of_xyz_scans_whose_sizes_divide_by_16_is_read_as_xyz(kitti_dir: Path, tmp_path: Path) -> None:
    """x, y, z float32 scans whose sizes happen to be multiples of 16 (and so of 48): the data decides, for the
    whole folder; every scan's points are the bytes as x, y, z triples."""
    xyz = [_kitti_scan(kitti_dir, k, every=8)[:, :3] for k in range(3)]
    xyz = [np.ascontiguousarray(p[: len(p) // 4 * 4]) for p in xyz]
    assert all(p.nbytes % 48 == 0 for p in xyz)
    folder = _kitti_copy(kitti_dir, tmp_path / "seq", 3, scans=xyz)
    out = tmp_path / "store"
    _ok(["build", folder, "--out", out, "--no-loop-closure"])
    with FrameStore.open(out) as store:
        for k in range(3):
            frame = store.frame(k)
            assert frame.points_sensor.tobytes() == xyz[k].tobytes()
            assert frame.attributes.intensity is None


def test_one_xyz_sized_scan_makes_the_whole_folder_xyz(kitti_dir: Path, tmp_path: Path) -> None:
    """Before: the first file (size a multiple of 16) was read as x, y, z, intensity, the next one failed."""
    xyz = [np.ascontiguousarray(_kitti_scan(kitti_dir, k, every=8)[:, :3]) for k in range(3)]
    xyz[0] = xyz[0][: len(xyz[0]) // 4 * 4]  # 48-byte multiple: fits both layouts
    xyz[1] = xyz[1][: len(xyz[1]) // 4 * 4 + 1]  # 12-byte multiple only
    xyz[2] = xyz[2][: len(xyz[2]) // 4 * 4 + 2]
    folder = _kitti_copy(kitti_dir, tmp_path / "seq", 3, scans=xyz)
    source = open_source(folder)
    assert source.point_layout.value == "xyz" and source.describe()["point_layout"] == "xyz"
    assert [f.points_sensor.tobytes() for f in source] == [p.tobytes() for p in xyz]


def test_kitti_layout_that_cannot_be_told_asks_for_the_option(kitti_dir: Path, tmp_path: Path) -> None:
    rng = np.random.default_rng(7)
    noise = [rng.normal(scale=10.0, size=(48, 4)).astype("<f4") for _ in range(2)]  # no scan in either layout
    folder = _kitti_copy(kitti_dir, tmp_path / "seq", 2, scans=noise)
    with pytest.raises(SourceError, match=r"cannot tell whether the scans are .* point_layout='xyzi' or 'xyz'"):
        open_source(folder)
    source = open_source(folder, point_layout="xyzi")
    assert [f.points_sensor.tobytes() for f in source] == [np.ascontiguousarray(n[:, :3]).tobytes() for n in noise]
    with pytest.raises(SourceError, match=r"point_layout: 'xyzw' is not one of"):
        open_source(folder, point_layout="xyzw")


def test_point_layout_is_given_on_the_command_line_for_build_and_convert(kitti_dir: Path, tmp_path: Path) -> None:
    """The ambiguous-layout error asks for ``point_layout``; ``--point-layout`` gives it through the CLI (build and
    convert), a wrong value is a usage error, and formats without .bin scans refuse the flag."""
    rng = np.random.default_rng(7)
    noise = [rng.normal(scale=10.0, size=(48, 4)).astype("<f4") for _ in range(2)]
    folder = _kitti_copy(kitti_dir, tmp_path / "seq", 2, scans=noise)
    poses = tmp_path / "identity.txt"  # KITTI rows, taken as Velodyne poses
    poses.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 2)
    given = ["--poses", str(poses), "--no-loop-closure"]
    runner = CliRunner()
    out = runner.invoke(app, ["build", str(folder), "--out", str(tmp_path / "a"), *given])
    assert out.exit_code != 0 and "point_layout" in str(out.exception), out.output
    for cmd in (["build", str(folder), "--out", str(tmp_path / "s"), *given],
                ["convert", str(folder), str(tmp_path / "c.mcap")]):
        done = runner.invoke(app, [*cmd, "--point-layout", "xyzi"])
        assert done.exit_code == 0, (done.output, done.exception)
    with FrameStore.open(tmp_path / "s") as store:
        assert store.frame(0).points_sensor.tobytes() == np.ascontiguousarray(noise[0][:, :3]).tobytes()
    bad = runner.invoke(app, ["build", str(folder), "--out", str(tmp_path / "b"), "--point-layout", "xyzw"])
    assert bad.exit_code == 2 and "--point-layout" in bad.output
    refused = runner.invoke(app, ["convert", str(Path(__file__).resolve().parents[1] / "datasets" / "synthetic-loop"),
                                  str(tmp_path / "d.mcap"), "--point-layout", "xyz"])
    assert refused.exit_code != 0 and "--point-layout" in str(refused.exception)


def test_the_real_kitti_scans_stay_xyzi(kitti_dir: Path) -> None:
    source = open_source(kitti_dir, frames="0:2")
    assert source.point_layout.value == "xyzi"
    raw = np.fromfile(kitti_dir / "velodyne" / "000000.bin", dtype="<f4").reshape(-1, 4)
    frame = source.frame(0)
    assert frame.points_sensor.tobytes() == np.ascontiguousarray(raw[:, :3]).tobytes()
    assert frame.attributes.intensity.tobytes() == np.ascontiguousarray(raw[:, 3]).tobytes()


# ---- 13. what happened, said ------------------------------------------------------------------------------------


def test_a_symlink_loop_among_frame_files_is_named(sevenscenes_dir: Path, tmp_path: Path) -> None:
    folder = tmp_path / "seq"
    folder.mkdir()
    a, b = folder / "frame-000000.depth.png", folder / "frame-000001.depth.png"
    a.symlink_to(b.name)
    b.symlink_to(a.name)
    exc = _refused(["build", folder, "--out", tmp_path / "store"])
    assert isinstance(exc, SourceError) and "symlink loop" in str(exc) and str(a) in str(exc), exc
    # one loop beside real frames: named too (it used to be left out without a word); lenient leaves it out
    shutil.copy(sevenscenes_dir / "frame-000002.depth.png", folder / "frame-000002.depth.png")
    with pytest.raises(SourceError, match=r"frame-00000[01]\.depth\.png: symlink loop"):
        open_source(folder)
    assert open_source(folder, lenient=True).frame_ids() == [2]


def test_a_negative_focal_length_names_the_intrinsics_file(sevenscenes_dir: Path, tmp_path: Path) -> None:
    folder = _sevenscenes_copy(sevenscenes_dir, tmp_path / "seq", range(2))
    (folder / "camera-intrinsics.txt").write_text("-585 0 320\n0 585 240\n0 0 1\n")
    exc = _refused(["build", folder, "--out", tmp_path / "store"])
    assert isinstance(exc, SourceError)
    assert str(exc).startswith(f"{folder / 'camera-intrinsics.txt'}: unusable camera intrinsics") and "fx=-585" in str(exc)


def test_cloud_files_named_by_nanosecond_stamps_that_are_not_used_as_stamps_say_so(kitti_dir: Path,
                                                                                    tmp_path: Path) -> None:
    """Two scans named by ns stamps 20 s apart: too slow for the names to be taken as stamps (median step outside
    1 ms .. 10 s), and as frame numbers their 10 Hz stamps leave the int64 range: the error says why."""
    folder = tmp_path / "clouds"
    folder.mkdir()
    for k in range(2):
        write_pcd(folder / f"{1_630_577_758_569_490_000 + k * 20_000_000_000}.pcd",
                  _columns(_kitti_scan(kitti_dir, k, every=10)))
    exc = _refused(["build", folder, "--out", tmp_path / "store"])
    assert isinstance(exc, SourceError)
    message = str(exc)
    assert str(folder / "1630577758569490000.pcd") in message
    assert "reads as a Unix time in ns" in message and "median step is 20 s" in message
    # with the stamps given, the names are frame numbers that fit: read
    (folder / "times.txt").write_text("0.0\n0.1\n")
    assert open_source(folder).frame_ids() == [1_630_577_758_569_490_000, 1_630_577_778_569_490_000]


def test_one_cloud_named_by_a_stamp_among_numbered_ones_says_so(kitti_dir: Path, tmp_path: Path) -> None:
    folder = tmp_path / "clouds"
    folder.mkdir()
    for name in ("scan_1.pcd", "1630577758569490000.pcd"):
        write_pcd(folder / name, _columns(_kitti_scan(kitti_dir, 0, every=10)))
    source = open_source(folder)
    assert source.frame_ids() == [1, 1_630_577_758_569_490_000] and len(source.frame(0).points_sensor)
    with pytest.raises(SourceError) as info:
        source.frame(1)
    message = str(info.value)
    assert message.startswith(f"{folder / '1630577758569490000.pcd'}: frame number 1630577758569490000 times the period")
    assert "reads as a Unix time in ns" in message and "only 1 of the 2 file names are stamps" in message
    assert [f.frame_id for f in open_source(folder, lenient=True)] == [1]


def test_a_frame_number_too_large_for_a_frame_id_is_named(kitti_dir: Path, tmp_path: Path) -> None:
    folder = tmp_path / "clouds"
    folder.mkdir()
    write_pcd(folder / "scan_99999999999999999999999.pcd", _columns(_kitti_scan(kitti_dir, 0, every=10)))
    with pytest.raises(SourceError, match=r"scan_99999999999999999999999\.pcd: the number .* too large for a frame id"):
        open_source(folder)


@pytest.mark.parametrize(("name", "expected"), [("scans", "LAS / LAZ"), ("scan.vtk", "VTK"), ("drive.pcap", "Ouster"),
                                                ("scan.pcd", "one point-cloud file")])
def test_an_unknown_format_lists_the_known_ones_and_how_to_convert(name: str, expected: str, tmp_path: Path) -> None:
    path = tmp_path / name
    if name == "scans":
        path.mkdir()
        for k in range(2):
            (path / f"scan_{k}.las").write_bytes(b"LASF" + bytes(200))
    else:
        path.write_bytes(b"# .PCD v0.7\n" if name.endswith(".pcd") else bytes(64))
    exc = _refused(["build", path, "--out", tmp_path / "store"])
    assert isinstance(exc, SourceError) and str(exc).startswith(f"{path}: cannot tell the format")
    assert expected in str(exc)
    for known in ("7scenes", "tum", "kitti", "redwood", "cloud_folder", "mcap", "rosbag1", "rosbag2"):
        assert f"{known} (" in str(exc)


# ---- bugs the fuzzed readers (tests/test_fuzz_readers.py) found, one deterministic case each ---------------------


def test_fuzz_found_a_calib_txt_that_is_not_utf8(kitti_dir: Path, tmp_path: Path) -> None:
    folder = _kitti_copy(kitti_dir, tmp_path / "seq", 2)
    shutil.copy(kitti_dir / "poses.txt", folder / "poses.txt")
    (folder / "calib.txt").write_bytes((kitti_dir / "calib.txt").read_bytes() + b"\x80\n")
    with pytest.raises(SourceError, match=r"calib\.txt.*not UTF-8"):
        open_source(folder, poses_from_ground_truth=True)


def _cloud_log(tmp_path: Path, **layout: object) -> Path:
    """An MCAP of one PointCloud2 (10 points) whose layout fields are overridden by ``layout``."""
    xyz = np.arange(30, dtype=np.float32).reshape(10, 3)
    (topic, typename, msg, log_time), = [m for m in ros_log_messages([(LOG_STAMP0_NS, xyz, np.zeros(10, np.float32))],
                                                                     [np.eye(4)], np.eye(4)) if m[0] == "/points"]
    return write_ros_messages(tmp_path / "log.mcap", "mcap", [(topic, typename, {**msg, **layout}, log_time)])


@pytest.mark.parametrize(("layout", "message"), [
    ({"point_step": 2**32 - 1}, r"row_step 160 < width 10 \* point_step 4294967295"),  # was a ValueError
    ({"height": 0}, r"10x0 points, but data has 160 bytes"),  # was an empty frame
    ({"fields": [{"name": "x", "offset": 0, "datatype": 7, "count": 3}, {"name": "y", "offset": 4, "datatype": 7,
                                                                        "count": 1},
                 {"name": "z", "offset": 8, "datatype": 7, "count": 1}]}, r"field 'x' has count 3"),
])
def test_fuzz_found_pointcloud2_layouts(layout: dict, message: str, tmp_path: Path) -> None:
    with pytest.raises(SourceError, match=message):
        list(open_source(_cloud_log(tmp_path, **layout)))


def test_fuzz_found_a_camera_info_that_back_projects_to_infinity(sevenscenes_dir: Path, tmp_path: Path) -> None:
    """A CameraInfo with cx = 1e300 was accepted (it is finite) and gave frames whose points were -inf."""
    from driftmap.export.depth_log import write_depth_image_mcap
    from driftmap.frame import PinholeIntrinsics

    depth = np.asarray(Image.open(sevenscenes_dir / "frame-000000.depth.png"))
    for cx, ok in ((320.0, True), (1e300, False), (-700.0, False)):
        log = tmp_path / f"cam_{ok}_{cx:g}.mcap"
        write_depth_image_mcap(log, [depth], [LOG_STAMP0_NS], PinholeIntrinsics(585.0, 585.0, cx, 240.0, 640, 480))
        if ok:
            assert np.isfinite(open_source(log).frame(0).points_sensor).all()
            continue
        with pytest.raises(SourceError, match=r"unusable camera intrinsics \(principal point cx=.* lies far outside"):
            list(open_source(log))


def test_fuzz_found_a_schema_without_the_standard_fields(tmp_path: Path) -> None:
    """An MCAP whose TFMessage schema lacks child_frame_id decoded into messages without it: an AttributeError."""
    from mcap_ros2.writer import Writer

    from driftmap.export.ros_messages import ros2_msgdef

    xyz = np.arange(30, dtype=np.float32).reshape(10, 3)
    messages = ros_log_messages([(LOG_STAMP0_NS, xyz, np.zeros(10, np.float32))], [np.eye(4)], np.eye(4))
    path = tmp_path / "log.mcap"
    with open(path, "wb") as f:
        writer, schemas = Writer(f), {}
        for topic, typename, msg, log_time in messages:
            if typename not in schemas:
                text = ros2_msgdef(typename)
                if typename == "tf2_msgs/msg/TFMessage":
                    text = text.replace("string child_frame_id", "string child_frame_ie")
                    msg = {"transforms": [{**t, "child_frame_ie": t["child_frame_id"]} for t in msg["transforms"]]}
                schemas[typename] = writer.register_msgdef(typename, text)
            elif typename == "tf2_msgs/msg/TFMessage":
                msg = {"transforms": [{**t, "child_frame_ie": t["child_frame_id"]} for t in msg["transforms"]]}
            writer.write_message(topic, schemas[typename], msg, log_time=log_time, publish_time=log_time)
        writer.finish()
    with pytest.raises(SourceError, match=r"/tf(_static)? message logged at .* does not have the fields of its type"):
        open_source(path, pose_from_tf=("odom", "base_link"))


def test_fuzz_found_a_pcd_count_too_large_for_a_dtype(kitti_dir: Path, tmp_path: Path) -> None:
    folder = tmp_path / "clouds"
    file = _cloud_file(folder, "pcd_ascii", _kitti_scan(kitti_dir, 0, every=100))
    replace_once(file, b"COUNT 1 1 1 1\n", b"COUNT 1 1 1 2147483648\n")
    with pytest.raises(SourceError, match=r"scan_0\.pcd:6: header field COUNT says 2147483651 values per point"):
        open_source(folder).frame(0)


@pytest.mark.parametrize("line", [b"data ascii\n", b"DATA Ascii\n"])
def test_fuzz_found_pcd_keys_and_values_in_another_case(line: bytes, kitti_dir: Path, tmp_path: Path) -> None:
    """The PCD spec spells keys and DATA / TYPE values exactly; other spellings are not read as them."""
    folder = tmp_path / "clouds"
    file = _cloud_file(folder, "pcd_ascii", _kitti_scan(kitti_dir, 0, every=100))
    replace_once(file, b"DATA ascii\n", line)
    with pytest.raises(SourceError, match=r"scan_0\.pcd"):
        open_source(folder).frame(0)


def test_fuzz_found_a_pose_file_stamp_beyond_int64(kitti_dir: Path, tmp_path: Path) -> None:
    """A 4x4 pose file whose stamp (9630577759 s, year 2275) is past the int64 ns range: an OverflowError from the
    trajectory reader, now a SourceError naming the file (given with poses=) or a file left alone (found beside)."""
    folder = tmp_path / "clouds"
    folder.mkdir()
    for k in range(3):
        write_pcd(folder / f"scan_{k}.pcd", _columns(_kitti_scan(kitti_dir, k, every=100)))
    blocks = "".join(f"1,0,0,{k}\n0,1,0,0\n0,0,1,0\n0,0,0,{s},\n" for k, s in enumerate(("1.0", "1.5", "9630577759.0")))
    poses = tmp_path / "poses.csv"
    poses.write_text(blocks)
    with pytest.raises(SourceError, match=r"poses\.csv:\d+: stamp '9630577759\.0' is not a usable time"):
        open_source(folder, poses=poses)
    (folder / "alidarPose.csv").write_text(blocks)
    assert open_source(folder).describe()["stamps"] == "assumed 10 Hz"


# ---- the hostile-input trial: files a killed run leaves, absurd coordinates, stamps in another unit ---------------


def _stamp_named_clouds(kitti_dir: Path, folder: Path, n: int = 3) -> list[int]:
    """``n`` KITTI scans (every 10th point) as PCDs named by their stamps (s with a fraction, 10 Hz); the stamps."""
    folder.mkdir(parents=True)
    stamps = [1_630_577_758_000_000_000 + k * 100_000_000 for k in range(n)]
    for k, stamp in enumerate(stamps):
        write_pcd(folder / f"{stamp // 10**9}.{stamp % 10**9 // 1000:06d}.pcd", _columns(_kitti_scan(kitti_dir, k, 10)))
    return stamps


def test_hidden_and_temporary_files_among_clouds_are_not_frames(kitti_dir: Path, tmp_path: Path) -> None:
    """B13: the temp file of a killed export (``.map.pcd.297cc9cf.tmp.pcd``, a whole cloud) was read as a fourth
    frame and its name, no stamp, made the folder's stamps "assumed 10 Hz"; a macOS ``._`` file (not a PCD) made the
    folder unreadable. Neither is a frame now; describe() lists them."""
    folder = tmp_path / "clouds"
    stamps = _stamp_named_clouds(kitti_dir, folder)
    shutil.copy(next(folder.glob("*.pcd")), folder / ".map.pcd.297cc9cf.tmp.pcd")
    (folder / "._1630577758.000000.pcd").write_bytes(b"\x00\x05\x16\x07 AppleDouble")
    (folder / "scan.tmp.pcd").write_bytes(b"half a cloud")
    _ok(["convert", folder, tmp_path / "out.mcap"])
    converted = open_source(tmp_path / "out.mcap")
    assert converted.frame_ids() == [0, 1, 2] and [f.stamp_ns for f in converted] == stamps
    source = open_source(folder)
    assert source.describe()["stamps"] == "file names (s)"
    assert source.describe()["ignored_files"] == ["._1630577758.000000.pcd", ".map.pcd.297cc9cf.tmp.pcd", "scan.tmp.pcd"]
    _ok(["build", folder, "--out", tmp_path / "store", "--no-loop-closure"])
    with FrameStore.open(tmp_path / "store") as store:
        assert store.frame_ids.tolist() == [0, 1, 2]


def test_hidden_and_temporary_files_among_kitti_scans_are_not_frames(kitti_dir: Path, tmp_path: Path) -> None:
    folder = _kitti_copy(kitti_dir, tmp_path / "seq", 3)
    shutil.copy(folder / "velodyne" / "000001.bin", folder / "velodyne" / ".000007.bin.5e1f2a9c.tmp.bin")
    (folder / "velodyne" / "._000002.bin").write_bytes(b"\x00\x05\x16\x07")
    (folder / "times.txt").write_text("0.0\n0.1\n0.2\n")
    source = open_source(folder)
    assert source.frame_ids() == [0, 1, 2] and source.point_layout.value == "xyzi"
    assert source.describe()["ignored_files"] == [".000007.bin.5e1f2a9c.tmp.bin", "._000002.bin"]
    _ok(["convert", folder, tmp_path / "out.mcap"])
    assert open_source(tmp_path / "out.mcap").frame_ids() == [0, 1, 2]


ABSURD_M = 1e30


def _with_absurd_points(scan: np.ndarray, n_bad: int) -> np.ndarray:
    """``scan`` (N, 4) with its first ``n_bad`` points moved to 1e30 m."""
    bad = scan.copy()
    bad[:n_bad, :3] = ABSURD_M
    return bad


def _absurd_source(kind: str, folder: Path, scans: list[np.ndarray]) -> tuple[Path, Path]:
    """A folder of ``kind`` (a cloud encoding, or ``kitti_bin``) holding ``scans``; the folder and frame 1's file."""
    if kind == "kitti_bin":
        (folder / "velodyne").mkdir(parents=True)
        for k, scan in enumerate(scans):
            np.ascontiguousarray(scan, dtype="<f4").tofile(folder / "velodyne" / f"{k:06d}.bin")
        (folder / "times.txt").write_text("".join(f"{0.1 * k:.1f}\n" for k in range(len(scans))))
        return folder, folder / "velodyne" / "000001.bin"
    folder.mkdir(parents=True)
    for k, scan in enumerate(scans):
        if kind.startswith("pcd"):
            write_pcd(folder / f"scan_{k}.pcd", _columns(scan), data=kind.removeprefix("pcd_"))
        else:
            write_ply(folder / f"scan_{k}.ply", _columns(scan), ascii=kind == "ply_ascii")
    return folder, next(folder.glob("scan_1.*"))


@pytest.mark.parametrize("kind", ["pcd_binary", "pcd_ascii", "ply_binary", "kitti_bin"])
def test_points_beyond_any_sensor_range_are_dropped_and_counted(kind: str, kitti_dir: Path, tmp_path: Path,
                                                                 caplog: pytest.LogCaptureFixture) -> None:
    """B14: 10 points at 1e30 m in a real scan were read as points (a map of 1e30 m: every later command failed
    with "voxel grid too large"). They are dropped with one warning naming the file and the count; the others are
    read as written."""
    scans = [_kitti_scan(kitti_dir, k, 10) for k in range(3)]
    folder, bad_file = _absurd_source(kind, tmp_path / "data", [scans[0], _with_absurd_points(scans[1], 10), scans[2]])
    with caplog.at_level("WARNING"):
        frames = list(open_source(folder))
    assert [len(f.points_sensor) for f in frames] == [len(scans[0]), len(scans[1]) - 10, len(scans[2])]
    assert frames[1].points_sensor.tobytes() == np.ascontiguousarray(scans[1][10:, :3]).tobytes()
    if kind == "kitti_bin":
        assert frames[1].attributes.intensity.tobytes() == np.ascontiguousarray(scans[1][10:, 3]).tobytes()
    warned = [r.getMessage() for r in caplog.records if "farther than" in r.getMessage()]
    assert len(warned) == 1 and str(bad_file) in warned[0], warned
    assert f"dropping 10 of {len(scans[1])} points farther than 10000 m from the sensor (up to 1.73e+30 m)" in warned[0]
    _ok(["convert", folder, tmp_path / "out.mcap"])  # through the CLI: nothing absurd reaches the output
    converted = list(open_source(tmp_path / "out.mcap"))
    assert max(float(np.abs(f.points_sensor).max()) for f in converted) < 1000.0


def test_a_cloud_of_absurd_points_is_refused_naming_the_file(kitti_dir: Path, tmp_path: Path) -> None:
    """B14's file: a PCD of 10 points, all at 1e30 m, built without a word. Refused now (lenient: skipped)."""
    folder = tmp_path / "clouds"
    folder.mkdir()
    for k in range(3):
        write_pcd(folder / f"scan_{k}.pcd", _columns(_kitti_scan(kitti_dir, k, 10)))
    write_pcd(folder / "scan_1.pcd", _columns(_with_absurd_points(_kitti_scan(kitti_dir, 1, 10)[:10], 10)))
    exc = _refused(["build", folder, "--out", tmp_path / "store", "--no-loop-closure"])
    assert isinstance(exc, SourceError) and str(exc).startswith(f"{folder / 'scan_1.pcd'} (frame 1): 10 of the 10 "
                                                                f"finite points lie farther than 10000 m"), exc
    source = open_source(folder, lenient=True)
    assert [f.frame_id for f in source] == [0, 2] and "farther than 10000 m" in source.skipped[0][1]


def _cloud_messages(kitti_dir: Path) -> list[tuple[str, str, dict, int]]:
    scans = [(LOG_STAMP0_NS + k * 100_000_000, *_xyz_intensity(_kitti_scan(kitti_dir, k, 50))) for k in range(3)]
    return ros_log_messages(scans, [np.eye(4)] * 3, np.eye(4))


def _cloud_message_index(messages: list, k: int) -> int:
    return [i for i, m in enumerate(messages) if m[0] == "/points"][k]


def test_pointcloud2_is_bigendian_is_honoured_and_a_wrong_flag_is_refused(kitti_dir: Path, tmp_path: Path) -> None:
    """B14: a PointCloud2 whose is_bigendian is true over little-endian data gave coordinates up to 3.4e38 m without
    a word. Big-endian data is byte-swapped (read as the same cloud); the wrong flag is refused naming the message."""
    messages = _cloud_messages(kitti_dir)
    reference = [f.points_sensor for f in open_source(write_ros_messages(tmp_path / "le.mcap", "mcap", messages))]
    i = _cloud_message_index(messages, 1)
    topic, typename, msg, log_time = messages[i]
    little = np.frombuffer(msg["data"], dtype=[(n, "<f4") for n in ("x", "y", "z", "intensity")])
    big = {**msg, "is_bigendian": True, "data": little.astype([(n, ">f4") for n in ("x", "y", "z", "intensity")]).tobytes()}
    messages[i] = (topic, typename, big, log_time)
    frames = list(open_source(write_ros_messages(tmp_path / "be.mcap", "mcap", messages)))
    assert all(f.points_sensor.tobytes() == r.tobytes() for f, r in zip(frames, reference, strict=True))
    messages[i] = (topic, typename, {**msg, "is_bigendian": True}, log_time)  # the flag lies about the data
    log = write_ros_messages(tmp_path / "flag.mcap", "mcap", messages)
    exc = _refused(["convert", log, tmp_path / "out.mcap"])
    assert isinstance(exc, SourceError) and "/points message 1: " in str(exc), exc
    assert "farther than 10000 m" in str(exc) and "is_bigendian: true; is its data little-endian?" in str(exc)
    source = open_source(log, lenient=True)
    assert [f.frame_id for f in source] == [0, 2] and "is_bigendian" in source.skipped[0][1]


def test_pointcloud2_points_beyond_range_are_counted_as_invalid(kitti_dir: Path, tmp_path: Path) -> None:
    messages = _cloud_messages(kitti_dir)
    i = _cloud_message_index(messages, 0)
    topic, typename, msg, log_time = messages[i]
    table = np.frombuffer(msg["data"], dtype=[(n, "<f4") for n in ("x", "y", "z", "intensity")]).copy()
    table["x"][:5] = 3.4e38
    messages[i] = (topic, typename, {**msg, "data": table.tobytes()}, log_time)
    frame = open_source(write_ros_messages(tmp_path / "log.mcap", "mcap", messages)).frame(0)
    assert len(frame.points_sensor) == len(table) - 5 and dict(frame.quality.invalid_counts) == {"beyond_max": 5}
    assert not frame.quality.flags  # the points are not NaN / inf: is_dense is not contradicted


def test_the_real_scans_read_as_before_the_range_check(kitti_dir: Path, balm_dir: Path) -> None:
    """No real point is beyond the range: KITTI and the BALM Livox clouds read bit for bit as their files hold."""
    kitti = open_source(kitti_dir, frames="0:3")
    for k, frame in enumerate(kitti):
        raw = np.fromfile(kitti_dir / "velodyne" / f"{k:06d}.bin", dtype="<f4").reshape(-1, 4)
        assert frame.points_sensor.tobytes() == np.ascontiguousarray(raw[:, :3]).tobytes()
    balm = open_source(balm_dir, frames="0:80:20")
    import open3d as o3d

    for frame in balm:
        cloud = o3d.t.io.read_point_cloud(frame.provenance.source_uri).point["positions"].numpy()
        assert frame.points_sensor.tobytes() == cloud.astype(np.float32).tobytes()


def test_kitti_times_in_milliseconds_are_refused(kitti_dir: Path, tmp_path: Path) -> None:
    """B15: a times.txt in ms (steps of ~100 "seconds") was accepted; the same check as the cloud folder's."""
    folder = _kitti_copy(kitti_dir, tmp_path / "seq", 3)
    (folder / "times.txt").write_text("0.0\n103.73\n207.205\n")
    exc = _refused(["build", folder, "--out", tmp_path / "store", "--no-loop-closure"])
    assert isinstance(exc, SourceError), exc
    assert str(exc) == (f"{folder / 'times.txt'}: read as seconds, the stamps of its 3 rows do not fit a sensor: their "
                        f"median step is 103.603 s, outside 0.001 .. 10 s (is the file in seconds?)")
    (folder / "times.txt").write_text("0.0\n0.103730\n0.207205\n")
    assert open_source(folder).stamps_ns() == [0, 103_730_000, 207_205_000]


def test_tum_lists_in_milliseconds_are_refused(sevenscenes_dir: Path, tmp_path: Path) -> None:
    folder = tmp_path / "rgbd_dataset_freiburg1_x"
    (folder / "depth").mkdir(parents=True)
    for k in range(3):
        depth = np.asarray(Image.open(sevenscenes_dir / f"frame-{k:06d}.depth.png")).astype(np.uint32) * 5
        Image.fromarray(np.clip(depth, 0, 65535).astype(np.uint16)).save(folder / "depth" / f"{k}.png")
    (folder / "depth.txt").write_text("# depth\n" + "".join(f"{175 + 33 * k} depth/{k}.png\n" for k in range(3)))
    exc = _refused(["build", folder, "--out", tmp_path / "store"])
    assert isinstance(exc, SourceError) and str(exc).startswith(f"{folder / 'depth.txt'}: read as seconds, the stamps of "
                                                                f"its 3 entries do not fit a sensor"), exc
    assert "median step is 33 s" in str(exc) and str(exc).endswith("(is the file in seconds?)")
    (folder / "depth.txt").write_text("# depth\n" + "".join(f"{1305031102.175 + 0.033 * k:.3f} depth/{k}.png\n"
                                                            for k in range(3)))
    assert len(open_source(folder)) == 3


def test_a_pointcloud2_header_stamp_nanosec_beyond_a_second_is_refused(kitti_dir: Path, tmp_path: Path) -> None:
    """B16: nanosec 3,000,000,000 was carried into the seconds (a stamp 3 s later than the publisher's sec)."""
    messages = _cloud_messages(kitti_dir)
    i = _cloud_message_index(messages, 1)
    topic, typename, msg, log_time = messages[i]
    sec = msg["header"]["stamp"]["sec"]
    messages[i] = (topic, typename, {**msg, "header": {**msg["header"], "stamp": {"sec": sec, "nanosec": 3_000_000_000}}},
                   log_time)
    log = write_ros_messages(tmp_path / "log.mcap", "mcap", messages)
    exc = _refused(["convert", log, tmp_path / "out.mcap"])
    assert isinstance(exc, SourceError), exc
    assert str(exc).startswith(f"{log}: /points message 1: header.stamp.nanosec is 3000000000, not a fraction of a "
                               f"second (0 .. 999999999; header.stamp.sec is {sec})"), exc
    source = open_source(log, lenient=True)
    assert [f.frame_id for f in source] == [0, 2] and "header.stamp.nanosec" in source.skipped[0][1]


def test_a_depth_image_header_stamp_nanosec_beyond_a_second_is_refused(sevenscenes_dir: Path, tmp_path: Path) -> None:
    from driftmap.export.ros_messages import camera_info_msg, depth_image_msg
    from driftmap.frame import PinholeIntrinsics

    K = PinholeIntrinsics(585.0, 585.0, 320.0, 240.0, 640, 480)
    messages = []
    for k in range(2):
        stamp = LOG_STAMP0_NS + k * 33_333_333
        depth = np.asarray(Image.open(sevenscenes_dir / f"frame-{k:06d}.depth.png"))
        image = depth_image_msg(depth, stamp, "camera")
        if k == 1:
            image["header"] = {**image["header"], "stamp": {"sec": stamp // 10**9, "nanosec": 1_500_000_000}}
        messages += [("/camera/camera_info", "sensor_msgs/msg/CameraInfo", camera_info_msg(K, stamp, "camera"), stamp),
                     ("/camera/depth", "sensor_msgs/msg/Image", image, stamp + 1000)]
    log = write_ros_messages(tmp_path / "cam.mcap", "mcap", messages)
    with pytest.raises(SourceError, match=r"/camera/depth message 1: header\.stamp\.nanosec is 1500000000"):
        list(open_source(log))


def test_a_pcd_viewpoint_that_is_not_the_identity_is_warned_about_once(kitti_dir: Path, tmp_path: Path,
                                                                       caplog: pytest.LogCaptureFixture) -> None:
    """W9: VIEWPOINT was ignored without a word. It is still not applied (docs/sources-datasets.md): one warning per
    folder names the first file and the viewpoint."""
    folder = tmp_path / "clouds"
    folder.mkdir()
    scans = [_kitti_scan(kitti_dir, k, 10) for k in range(3)]
    for k, scan in enumerate(scans):
        file = write_pcd(folder / f"scan_{k}.pcd", _columns(scan))
        if k:
            replace_once(file, b"VIEWPOINT 0 0 0 1 0 0 0\n", b"VIEWPOINT 5 0 1.5 0.7071 0 0 0.7071\n")
    with caplog.at_level("WARNING"):
        frames = list(open_source(folder))
    assert all(f.points_sensor.tobytes() == np.ascontiguousarray(s[:, :3]).tobytes() for f, s in zip(frames, scans))
    warned = [r.getMessage() for r in caplog.records if "VIEWPOINT" in r.getMessage()]
    assert len(warned) == 1 and warned[0].startswith(f"{folder / 'scan_1.pcd'}: VIEWPOINT 5 0 1.5 0.7071 0 0 0.7071 is "
                                                     f"not the identity (0 0 0 1 0 0 0); it is not applied"), warned
    caplog.clear()
    with caplog.at_level("WARNING"):
        list(open_source(folder, frames="0:1"))  # the identity: nothing said
    assert not [r for r in caplog.records if "VIEWPOINT" in r.getMessage()]


# ---- the synthetic-log generator: every config field checked, an existing log not replaced silently -------------


@pytest.mark.parametrize(("args", "field"), [
    (["--period-s", "1e12"], "frame_period_ns"),  # was an OverflowError traceback
    (["--period-s", "4e9", "--frames", "3"], "frame_period_ns"),  # wrote wrapped, negative stamps
    (["--seed", "-1"], "seed"),  # was a ValueError traceback from numpy
    (["--points-per-scan", "2000000000", "--lidar-pattern", "rosette"], "lidar_points_per_scan"),  # 20+ GB
    (["--speed-m-per-s", "0.001", "--period-s", "0.001"], "n_frames"),  # 7 million frames
])
def test_synth_refuses_a_config_field_out_of_range_naming_it(args: list[str], field: str, tmp_path: Path) -> None:
    exc = _refused(["synth", tmp_path / "log", *args])
    assert isinstance(exc, ConfigError) and str(exc).startswith(f"{field}: must be "), exc
    assert not (tmp_path / "log").exists()


@pytest.mark.parametrize(("overrides", "message"), [
    ({"frame_period_ns": 0}, r"frame_period_ns: must be within 1000000 \.\. 3600000000000 \(1 ms \.\. 1 h\), got 0"),
    ({"start_stamp_ns": 2**63 - 1 - 10**14, "frame_period_ns": 3_600_000_000_000},
     r"n_frames, frame_period_ns: 60 frames 3600 s apart from start_stamp_ns 9223272036854775807 end at .* beyond"),
    ({"width": 100_000}, r"width: must be within 1 \.\. 8192, got 100000"),
    ({"width": 8192, "height": 8192}, r"width, height: a 8192x8192 depth image has 67108864 pixels, more than"),
    ({"lidar_beams": 4096, "lidar_azimuth_steps": 4096}, r"lidar_beams, lidar_azimuth_steps: 4096 x 4096 = 16777216"),
    ({"stops": 10**12, "stop_frames": 1}, r"stops: must be within 0 \.\. 1000000"),
    ({"fx": float("nan")}, r"fx: must be finite and > 0, got nan"),
    ({"dropout_fraction": 1.5}, r"dropout_fraction: must be finite and \[0, 1\], got 1\.5"),
    ({"lidar_elevation_deg": (-15.0, 120.0)}, r"lidar_elevation_deg: must be finite and \[-90, 90\], got 120\.0"),
    ({"scene": "forest"}, r"scene: must be 'room' or 'street', got 'forest'"),
    ({"seed": 1.5}, r"seed: must be an integer, got 1\.5"),
])
def test_synthetic_log_config_checks_every_field_up_front(overrides: dict, message: str) -> None:
    from driftmap.sources.synthetic import SyntheticLogConfig

    with pytest.raises(ConfigError, match=message):
        SyntheticLogConfig(**overrides)


def test_generate_synthetic_log_refuses_an_existing_log_without_overwrite(tmp_path: Path) -> None:
    """B5: ``driftmap synth OUT`` silently replaced the log in OUT (57 of its 60 depth images deleted). The library
    refuses it now unless overwrite=True; a folder that is no synthetic log is never replaced."""
    from driftmap.sources.synthetic import SyntheticLogConfig, generate_synthetic_log

    small = SyntheticLogConfig(n_frames=5, width=40, height=30, fx=32.8, fy=32.8, cx=19.5, cy=14.5)
    out = generate_synthetic_log(tmp_path / "log", small)
    before = {p.relative_to(out): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}
    with pytest.raises(ConfigError, match=r"log: a synthetic log exists: pass overwrite=True / --overwrite to replace it"):
        generate_synthetic_log(out, SyntheticLogConfig(n_frames=3, width=40, height=30, fx=32.8, fy=32.8, cx=19.5,
                                                       cy=14.5))
    assert {p.relative_to(out): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()} == before
    generate_synthetic_log(out, SyntheticLogConfig(n_frames=3, width=40, height=30, fx=32.8, fy=32.8, cx=19.5, cy=14.5),
                           overwrite=True)
    assert sorted(p.name for p in (out / "depth").iterdir()) == ["000000.png", "000001.png", "000002.png"]
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    for overwrite in (False, True):
        with pytest.raises(SourceError, match=r"other: is not empty and holds no synthetic log"):
            generate_synthetic_log(other, small, overwrite=overwrite)
    assert [p.name for p in other.iterdir()] == ["notes.txt"]
    empty = tmp_path / "empty"
    empty.mkdir()
    assert len(list((generate_synthetic_log(empty, small) / "depth").iterdir())) == 5


# ---- 14. a hostile-input trial: what the readers stored without a word ------------------------------------------


def _cli(args: list[object]) -> tuple[int, str]:
    """``python -m driftmap.cli ARGS`` as a user runs it: the exit code and what it printed (stdout + stderr, log lines
    not wrapped)."""
    import os
    import subprocess
    import sys

    env = {**os.environ, "COLUMNS": "4000"}
    done = subprocess.run([sys.executable, "-m", "driftmap.cli", *map(str, args)], check=False, capture_output=True,
                          text=True, env=env, timeout=600)
    return done.returncode, done.stdout + done.stderr


def _store_ids(path: Path) -> list[int]:
    with FrameStore.open(path) as store:
        return store.frame_ids.tolist()


@pytest.mark.parametrize("kind", ["kitti_bin", "pcd_binary", "ply_binary"])
def test_points_at_the_sensor_origin_are_dropped_and_an_all_zero_scan_is_refused(kind: str, kitti_dir: Path,
                                                                                 tmp_path: Path,
                                                                                 caplog: pytest.LogCaptureFixture) -> None:
    """B2: a KITTI .bin of zeros (every point at the sensor origin: no return) was stored as 124k identical points.
    Points at (0, 0, 0) are dropped with a logged count; a scan with no point left is refused naming the file
    (--lenient skips it), for KITTI .bin, PCD and PLY alike."""
    scans = [_kitti_scan(kitti_dir, k, 10) for k in range(3)]
    holes = scans[1].copy()
    holes[:100, :3] = 0.0  # organised-cloud style "no return" points
    zeros = np.zeros((3000, 4), dtype="<f4")
    folder, _ = _absurd_source(kind, tmp_path / "data", [scans[0], holes, zeros])
    zero_file = next(p for p in (folder / "velodyne" / "000002.bin", folder / "scan_2.pcd", folder / "scan_2.ply")
                     if p.exists())
    with caplog.at_level("WARNING"):
        frame = open_source(folder).frame(1)
    assert frame.points_sensor.tobytes() == np.ascontiguousarray(holes[100:, :3]).tobytes()
    assert any("dropping 100 of" in r.getMessage() and "sensor origin" in r.getMessage() for r in caplog.records)
    code, said = _cli(["build", folder, "--out", tmp_path / "store", "--no-loop-closure"])
    assert code != 0 and f"{zero_file} (frame 2): no valid point: of its 3000 points, 3000 at the sensor origin" in said, said
    assert "--lenient" in said
    code, said = _cli(["build", folder, "--out", tmp_path / "lenient", "--no-loop-closure", "--lenient"])
    assert code == 0, said
    assert _store_ids(tmp_path / "lenient") == [0, 1]
    with FrameStore.open(tmp_path / "lenient") as store:
        assert store.frame(1).n_points == len(holes) - 100


def _bin_copy(kitti_dir: Path, folder: Path, n: int) -> list[np.ndarray]:
    """``n`` real KITTI scans (every 10th point, cut to a multiple of 3 points: 48-byte sizes, which both layouts
    fit) as a sequence folder; the scans."""
    scans = [_kitti_scan(kitti_dir, k, 10) for k in range(n)]
    scans = [np.ascontiguousarray(s[: len(s) // 3 * 3]) for s in scans]
    _kitti_copy(kitti_dir, folder, n, scans=scans)
    (folder / "times.txt").write_text("".join(f"{0.1 * k:.1f}\n" for k in range(n)))
    return scans


def test_a_forced_point_layout_the_data_contradicts_is_refused_before_anything_is_stored(kitti_dir: Path,
                                                                                        tmp_path: Path) -> None:
    """B5: --point-layout xyz on x, y, z, intensity scans read the intensities as coordinates without a word. The data
    check of ``auto`` now applies to a forced layout: refused for the whole folder, naming it, the flag and the layout
    the data has; a layout the data agrees with, or cannot tell, is read as given."""
    folder = tmp_path / "seq"
    scans = _bin_copy(kitti_dir, folder, 3)
    assert all(s.nbytes % 48 == 0 for s in scans)
    code, said = _cli(["build", folder, "--out", tmp_path / "store", "--no-loop-closure", "--point-layout", "xyz"])
    assert code != 0, said
    assert (f"{folder / 'velodyne'}: --point-layout xyz (point_layout='xyz' in the library) reads the scans as float32 "
            f"x, y, z, but the data looks like xyzi") in said, said
    assert "give --point-layout xyzi" in said
    assert not (tmp_path / "store").exists() or _store_ids(tmp_path / "store") == []
    source = open_source(folder, point_layout="xyzi")  # what the data is: read as given
    assert source.frame(0).points_sensor.tobytes() == np.ascontiguousarray(scans[0][:, :3]).tobytes()
    assert "--point-layout xyzi" in source.point_layout_reason
    xyz = tmp_path / "xyz"  # and the other way round: x, y, z scans forced as x, y, z, intensity
    _kitti_copy(kitti_dir, xyz, 3, scans=[np.ascontiguousarray(s[: len(s) // 4 * 4, :3]) for s in scans])
    with pytest.raises(SourceError, match=r"--point-layout xyzi .* the data looks like xyz \(float32 x, y, z\)"):
        open_source(xyz, point_layout="xyzi")


def test_a_pcd_in_millimetres_is_refused_as_a_units_problem(kitti_dir: Path, tmp_path: Path,
                                                            caplog: pytest.LogCaptureFixture) -> None:
    """B6: a PCD whose coordinates are millimetres was stored 1000x too large, with only a warning about points
    farther than 10 km. Its median range (10 km for a KITTI scan) is no LiDAR scan in metres: refused, naming the
    file and millimetres. A cloud of which a large share is dropped as too far says it may be units."""
    folder = tmp_path / "mm"
    folder.mkdir()
    for k in range(3):
        scan = _kitti_scan(kitti_dir, k, 10)
        write_pcd(folder / f"scan_{k}.pcd", {**_columns(scan), "x": scan[:, 0] * 1000, "y": scan[:, 1] * 1000,
                                             "z": scan[:, 2] * 1000})
    code, said = _cli(["build", folder, "--out", tmp_path / "store", "--no-loop-closure"])
    assert code != 0, said
    assert f"{folder / 'scan_0.pcd'} (frame 0): the median point lies 1.008e+04 m from the sensor" in said, said
    assert "look like millimetres or centimetres (the median would be 10.1 m in millimetres" in said and "read in metres" in said
    scan = _kitti_scan(kitti_dir, 0, 10)
    part = scan.copy()
    part[: len(part) // 5, :3] *= 5000.0  # a fifth of the cloud beyond 10 km (the median stays in range)
    far = tmp_path / "part"
    far.mkdir()
    write_pcd(far / "scan_0.pcd", _columns(part))
    with caplog.at_level("WARNING"):
        frame = open_source(far).frame(0)
    assert 0 < len(frame.points_sensor) < len(part)
    warned = [r.getMessage() for r in caplog.records if "farther than 10000 m" in r.getMessage()]
    assert len(warned) == 1 and "may be a units problem" in warned[0] and "millimetres" in warned[0], warned


def test_a_pcd_whose_coordinates_are_all_nan_is_refused_not_stored_empty(kitti_dir: Path, tmp_path: Path) -> None:
    """W2: a PCD whose x, y, z are all NaN was stored as an empty frame (exit 0), while ``POINTS 0`` is an error.
    A frame without a valid point is refused naming the file; --lenient skips it."""
    folder = tmp_path / "clouds"
    folder.mkdir()
    for k in range(3):
        scan = _kitti_scan(kitti_dir, k, 10).copy()
        if k == 1:
            scan[:, :3] = np.nan
        write_pcd(folder / f"scan_{k}.pcd", _columns(scan))
    code, said = _cli(["build", folder, "--out", tmp_path / "store", "--no-loop-closure"])
    assert code != 0, said
    assert f"{folder / 'scan_1.pcd'} (frame 1): no valid point: of its" in said and "with a NaN or infinite" in said
    code, said = _cli(["build", folder, "--out", tmp_path / "lenient", "--no-loop-closure", "--lenient"])
    assert code == 0, said
    assert _store_ids(tmp_path / "lenient") == [0, 2]


def test_an_all_zero_depth_image_is_warned_about_and_flagged_with_poses_from_source(sevenscenes_dir: Path,
                                                                                    tmp_path: Path) -> None:
    """W3: a depth PNG of zeros built with --poses-from-source was stored without a word (the invalid-fraction
    monitor flags jumps over a history of frames, and none comes before frame 1). It is warned about, naming the
    file and its invalid fraction, and flagged in the store."""
    folder = _sevenscenes_copy(sevenscenes_dir, tmp_path / "seq", range(3))
    zero_file = folder / "frame-000001.depth.png"
    Image.fromarray(np.zeros((480, 640), dtype=np.uint16)).save(zero_file)
    code, said = _cli(["build", folder, "--out", tmp_path / "store", "--no-loop-closure", "--poses-from-source"])
    assert code == 0, said
    assert f"{zero_file} (frame 1): invalid pixel fraction 1.000 (no valid pixel: the frame has no point)" in said, said
    with FrameStore.open(tmp_path / "store") as store:
        assert store.frame_ids.tolist() == [0, 1, 2]
        flags = [store.frame(k).quality.flags for k in range(3)]
    assert not flags[0] and not flags[2]
    assert len(flags[1]) == 1 and flags[1][0].startswith("mostly_invalid: 1.000 of the"), flags


def test_a_folder_named_like_a_frame_file_is_called_a_folder(sevenscenes_dir: Path, kitti_dir: Path, tmp_path: Path,
                                                            caplog: pytest.LogCaptureFixture) -> None:
    """W4: a folder named ``frame-000001.depth.png`` was reported as a "missing" depth image; it is a folder, not a
    file, and the warnings say so (a KITTI scan name that is a folder alike, which was left out without a word)."""
    folder = _sevenscenes_copy(sevenscenes_dir, tmp_path / "seq", range(3))
    (folder / "frame-000001.depth.png").unlink()
    (folder / "frame-000001.depth.png").mkdir()
    with caplog.at_level("WARNING"):
        source = open_source(folder)
        assert [f.frame_id for f in source] == [0, 2]
    said = [r.getMessage() for r in caplog.records]
    assert f"{folder / 'frame-000001.depth.png'}: is a folder, not a file (7-Scenes depth)" in said[0], said
    gap = next(m for m in said if "have no depth image" in m)
    assert f"frame 1 ({folder / 'frame-000001.depth.png'} is a folder, not a file)" in gap and "missing" not in gap
    seq = _kitti_copy(kitti_dir, tmp_path / "kitti", 2)
    (seq / "velodyne" / "000002.bin").mkdir()
    caplog.clear()
    with caplog.at_level("WARNING"):
        assert open_source(seq).frame_ids() == [0, 1]
    assert any(f"{seq / 'velodyne' / '000002.bin'}: is a folder, not a file" in r.getMessage() for r in caplog.records)


def test_a_frame_store_given_as_a_source_is_named_a_store(kitti_dir: Path, tmp_path: Path) -> None:
    """W13: ``driftmap build STORE --out x`` called the store's segment "a log that does not start with its format's
    magic bytes: a damaged or foreign file". It is a driftmap frame store: used directly, or its frames written as a
    ROS 2 log with export_mcap (trial 25 W8: the advice was `export --mcap`, a Foxglove view no reader takes)."""
    store = tmp_path / "store"
    with FrameStore.create(store) as created:
        created.append(open_source(_kitti_copy(kitti_dir, tmp_path / "seq", 1)).frame(0))
    for args in (["build", store, "--out", tmp_path / "x"], ["convert", store, tmp_path / "x.mcap"]):
        code, said = _cli(args)
        assert code != 0, said
        assert f"{store}: is a driftmap frame store" in said and "driftmap.export.mcap.export_mcap(" in said, said
        assert "magic bytes" not in said
    (store / "store.json").write_text("{damaged")  # a store whose manifest is damaged: its segments tell
    with pytest.raises(SourceError, match="is a driftmap frame store"):
        open_source(store)


def test_reader_messages_name_the_command_line_flag_first(kitti_dir: Path, tmp_path: Path,
                                                          caplog: pytest.LogCaptureFixture) -> None:
    """W1: messages that reach the command line named only the library's arguments (``poses=``, ``format=``,
    ``period_ns``, "point_layout option"); they name the flag first now."""
    unknown = tmp_path / "unknown"
    unknown.mkdir()
    (unknown / "notes.txt").write_text("no frames here")
    code, said = _cli(["build", unknown, "--out", tmp_path / "s1"])
    assert code != 0 and "pass --format FORMAT to force one, format= in the library" in said, said
    clouds = tmp_path / "clouds"
    clouds.mkdir()
    for k in range(2):
        write_pcd(clouds / f"scan_{k}.pcd", _columns(_kitti_scan(kitti_dir, k, 10)))
    code, said = _cli(["build", clouds, "--out", tmp_path / "s2", "--poses-from-source"])
    assert code != 0 and "give their pose file with --poses FILE instead (poses= in the library)" in said, said
    with caplog.at_level("WARNING"):
        open_source(clouds)
    assert any("the scan period (--period-s SECONDS; period_ns= in the library)" in r.getMessage()
               for r in caplog.records)
    seq = tmp_path / "seq"
    _bin_copy(kitti_dir, seq, 2)
    assert open_source(seq, point_layout="xyzi").point_layout_reason == (
        "given with --point-layout xyzi (point_layout='xyzi' in the library)")


def test_an_all_zero_scan_does_not_hide_the_layout_of_the_folder(kitti_dir: Path, tmp_path: Path) -> None:
    """B2, the layout side: with every size a multiple of 48 bytes the data decides the layout, and a scan of zeros
    (the same in either layout) made the folder "cannot tell". It abstains now; the others decide, and the zero
    scan itself is refused when read (lenient: skipped)."""
    folder = tmp_path / "seq"
    scans = _bin_copy(kitti_dir, folder, 3)
    np.zeros((3000, 4), dtype="<f4").tofile(folder / "velodyne" / "000001.bin")
    source = open_source(folder)
    assert source.point_layout.value == "xyzi" and "000001.bin holds too few points" in source.point_layout_reason
    assert source.frame(2).points_sensor.tobytes() == np.ascontiguousarray(scans[2][:, :3]).tobytes()
    with pytest.raises(SourceError, match=r"000001\.bin \(frame 1\): no valid point: of its 3000 points, 3000 at the "
                                          r"sensor origin"):
        source.frame(1)
    assert [f.frame_id for f in open_source(folder, lenient=True)] == [0, 2]
