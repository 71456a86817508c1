"""Pose-file readers reject malformed input with a SourceError naming the file, the 1-based line and the
field (non-finite values, KITTI rotation blocks that are not rotations, stamps going back in time, text
that is not UTF-8); writers and readers round-trip exactly; every shared trajectory file still reads."""

from __future__ import annotations

import logging
import re
from decimal import Decimal
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from driftmap.errors import SourceError
from driftmap.geometry import RIGID_TOLERANCE
from driftmap.trajectory import (
    Trajectory,
    detect_trajectory_format,
    has_stamps,
    read_euroc,
    read_kitti,
    read_matrix4x4,
    read_redwood_log,
    read_trajectory,
    read_tum,
    write_kitti,
    write_tum,
)

TUM_HEADER = "# timestamp tx ty tz qx qy qz qw\n"
TUM_ROW = "1305031102.175304 1.3405 0.6266 1.6575 0.6574 0.6126 -0.2949 -0.3248\n"
KITTI_ROW = "1 0 0 0 0 1 0 0 0 0 1 0\n"
EUROC_HEADER = "#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []\n"
EUROC_ROW = "1403715524907143168,0.515356,1.996773,0.971104,0.161996,0.789985,-0.205376,0.554528\n"


def _raises_naming(read: Callable[[Path], Trajectory], path: Path, line: int, *fields: str) -> str:
    """``read(path)`` raises SourceError; its one-line message names the file, ``line`` and every field."""
    with pytest.raises(SourceError) as info:
        read(path)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(f"{path}:{line}:") or message.startswith(f"{path}:{line} "), message
    for field in fields:
        assert field in message, message
    return message


# ---- 1. NaN / inf ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("read", [read_tum, read_trajectory])
@pytest.mark.parametrize(
    ("column", "value", "field"),
    [(2, "nan", "translation"), (4, "inf", "translation"), (5, "NaN", "quaternion"), (8, "-inf", "quaternion")],
)
def test_tum_non_finite_value_names_line_and_field(tmp_path: Path, read: Callable, column: int, value: str,
                                                   field: str) -> None:
    row = TUM_ROW.split()
    row[0] = "1305031102.275304"
    row[column - 1] = value
    path = tmp_path / "poses.tum"
    path.write_text(TUM_HEADER + TUM_ROW + " ".join(row) + "\n")
    message = _raises_naming(read, path, 3, field, "not finite", f"column {column}")
    assert value.lower().lstrip("-") in message.lower()


def test_tum_stamp_overflowing_to_inf_is_named(tmp_path: Path) -> None:
    path = tmp_path / "poses.tum"
    path.write_text(TUM_ROW + "1e400" + TUM_ROW[TUM_ROW.index(" "):])
    _raises_naming(read_tum, path, 2, "stamp", "'1e400'")


@pytest.mark.parametrize("read", [read_kitti, read_trajectory])
@pytest.mark.parametrize(
    ("column", "field"), [(1, "rotation"), (7, "rotation"), (4, "translation"), (12, "translation")]
)
def test_kitti_non_finite_value_names_line_and_field(tmp_path: Path, read: Callable, column: int, field: str) -> None:
    row = KITTI_ROW.split()
    row[column - 1] = "nan"
    path = tmp_path / "poses.txt"
    path.write_text(KITTI_ROW * 2 + "\n" + " ".join(row) + "\n")  # a blank line 3: the bad row is line 4
    _raises_naming(read, path, 4, field, "not finite", f"column {column}", "nan")


@pytest.mark.parametrize("read", [read_euroc, read_trajectory])
def test_euroc_non_finite_value_names_line_and_field(tmp_path: Path, read: Callable) -> None:
    row = EUROC_ROW.strip().split(",")
    row[0] = str(int(row[0]) + 5_000_000)
    row[6] = "inf"  # q_RS_y
    path = tmp_path / "data.csv"
    path.write_text(EUROC_HEADER + EUROC_ROW + ",".join(row) + "\n")
    _raises_naming(read, path, 3, "quaternion", "not finite", "column 7", "inf")


# ---- 2. KITTI rotation blocks that are not rotations -------------------------------------------------------------


@pytest.mark.parametrize("read", [read_kitti, read_trajectory])
@pytest.mark.parametrize(
    ("rotation_row", "what"),
    [
        ("2 0 0 0 0 1 0 0 0 0 1 0", "not orthonormal"),  # R[0,0] = 2
        ("1 0 0 0 0 1 0 0 0 1 0 0", "not orthonormal"),  # two equal rows: singular
        ("-1 0 0 0 0 1 0 0 0 0 1 0", "determinant"),  # orthonormal but a reflection
        (f"{1 + 5 * RIGID_TOLERANCE} 0 0 0 0 1 0 0 0 0 1 0", "not orthonormal"),  # just outside the tolerance
    ],
    ids=["scaled", "singular", "reflection", "just-outside-tolerance"],
)
def test_kitti_rotation_that_is_not_a_rotation_is_named(tmp_path: Path, read: Callable, rotation_row: str,
                                                        what: str) -> None:
    path = tmp_path / "poses.txt"
    path.write_text(KITTI_ROW * 2 + rotation_row + "\n" + KITTI_ROW)
    _raises_naming(read, path, 3, "rotation block", what, "frame 2")


def test_kitti_rotation_within_tolerance_is_kept_as_written(tmp_path: Path) -> None:
    R = Rotation.from_rotvec([0.1, -0.4, 0.7]).as_matrix()
    R_written = np.round(R, 4)  # what a file with 4 decimals holds: not exactly orthonormal
    assert 1e-6 < np.max(np.abs(R_written.T @ R_written - np.eye(3))) < RIGID_TOLERANCE
    rows = np.hstack([R_written, [[1.5], [-2.0], [0.25]]])
    path = tmp_path / "poses.txt"
    path.write_text(KITTI_ROW + " ".join(f"{v:.4f}" for v in rows.ravel()) + "\n")
    traj = read_kitti(path)
    np.testing.assert_array_equal(traj.poses[1][:3, :], rows)  # validated, not projected onto SO(3)


# ---- 3. stamps out of order / repeated ----------------------------------------------------------------------------


@pytest.mark.parametrize("read", [read_tum, read_trajectory])
def test_tum_stamp_going_back_in_time_names_both_lines(tmp_path: Path, read: Callable) -> None:
    rest = TUM_ROW[TUM_ROW.index(" "):]
    path = tmp_path / "poses.tum"
    path.write_text(TUM_HEADER + "1305031102.1" + rest + "1305031102.3" + rest + "1305031102.2" + rest)
    _raises_naming(read, path, 4, "stamp goes back in time", "1305031102.2", "1305031102.3", "line 3")


def test_euroc_stamp_going_back_in_time_names_both_lines(tmp_path: Path) -> None:
    stamp, rest = EUROC_ROW.split(",", 1)
    earlier = str(int(stamp) - 1)
    path = tmp_path / "data.csv"
    path.write_text(EUROC_HEADER + EUROC_ROW + f"{earlier},{rest}")
    _raises_naming(read_euroc, path, 3, "stamp goes back in time", earlier, stamp, "line 2")


@pytest.mark.parametrize("read", [read_tum, read_trajectory])
def test_tum_repeated_stamp_is_kept_and_logged_with_both_lines(tmp_path: Path, read: Callable,
                                                               caplog: pytest.LogCaptureFixture) -> None:
    """A stamp written twice is not rejected (the official TUM fr2_desk ground truth has one), but logged."""
    rest = TUM_ROW[TUM_ROW.index(" "):]
    moved = rest.replace("1.3405", "1.3415")
    path = tmp_path / "poses.tum"
    path.write_text(TUM_HEADER + "10.0" + rest + "10.5" + rest + "10.5" + moved + "11.0" + rest)
    with caplog.at_level(logging.WARNING, logger="driftmap.trajectory"):
        traj = read(path)
    assert traj.stamps_ns.tolist() == [10_000_000_000, 10_500_000_000, 10_500_000_000, 11_000_000_000]
    assert traj.poses[2][0, 3] - traj.poses[1][0, 3] == pytest.approx(0.001)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1
    assert warnings[0].startswith(f"{path}:4: duplicate stamp") and "line 3" in warnings[0]


# ---- 4. text that is not UTF-8 -------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("read", "good_lines"),
    [
        (read_tum, TUM_HEADER + TUM_ROW),
        (read_kitti, KITTI_ROW * 2),
        (read_euroc, EUROC_HEADER + EUROC_ROW),
        (read_redwood_log, "0 0 1\n1 0 0 0\n"),
        (read_trajectory, TUM_HEADER + TUM_ROW),
    ],
    ids=["tum", "kitti", "euroc", "redwood", "detected"],
)
def test_bytes_that_are_not_utf8_are_named_with_their_line(tmp_path: Path, read: Callable, good_lines: str) -> None:
    path = tmp_path / "poses.txt"
    path.write_bytes(good_lines.encode() + b"1 2 \xff\xfe 3\n")
    _raises_naming(read, path, 3, "not UTF-8", "0xff")


@pytest.mark.parametrize("read", [read_tum, read_trajectory])
def test_utf16_file_is_named_as_such(tmp_path: Path, read: Callable) -> None:
    path = tmp_path / "poses.tum"
    path.write_bytes(b"\xff\xfe" + (TUM_HEADER + TUM_ROW).encode("utf-16-le"))
    _raises_naming(read, path, 1, "not UTF-8", "UTF-16")


def test_utf8_byte_order_mark_is_accepted(tmp_path: Path) -> None:
    path = tmp_path / "poses.tum"
    path.write_bytes(b"\xef\xbb\xbf" + (TUM_ROW + TUM_ROW.replace("1102.175304", "1102.275304")).encode())
    plain = tmp_path / "plain.tum"
    plain.write_bytes(path.read_bytes()[3:])
    for read in (read_tum, read_trajectory):
        traj = read(path)
        np.testing.assert_array_equal(traj.stamps_ns, read_tum(plain).stamps_ns)
        np.testing.assert_array_equal(traj.poses, read_tum(plain).poses)


# ---- 4x4 blocks (one matrix per frame, BALM's alidarPose.csv) --------------------------------------------------------

BLOCK = "1 0 0 0.5\n0 1 0 0\n0 0 1 0\n0 0 0 {s}\n"


@pytest.mark.parametrize("read", [read_matrix4x4, read_trajectory])
@pytest.mark.parametrize(
    ("text", "line", "fields"),
    [
        (BLOCK.format(s=1) + "1 0 0 0\n0 1 0 0\n", 5, ("not a multiple of 4", "only 2 row(s)")),
        (BLOCK.format(s=1) + "1 0 0 0\n\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", 6, ("blank line inside a 4x4 block", "line 5")),
        (BLOCK.format(s=1) + "1 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", 5, ("expected 4 numbers", "3 fields")),
        (BLOCK.format(s=1) + "1,0,,0\n0,1,0,0\n0,0,1,0\n0,0,0,1\n", 5, ("expected 4 numbers", "empty field")),
        (BLOCK.format(s=1) + "1 0 0 0\n0 1 0 nan\n0 0 1 0\n0 0 0 1\n", 6, ("not finite", "column 4")),
        (BLOCK.format(s=1) + "1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0.5 0 1\n", 8, ("must start with 0 0 0", "block 1")),
        (BLOCK.format(s=1) + "2 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", 5, ("rotation block", "not orthonormal", "block 1")),
        (BLOCK.format(s="10.5") + BLOCK.format(s="10.25"), 8, ("stamp goes back in time", "10.25", "line 4")),
    ],
    ids=["partial-block", "blank-inside", "three-numbers", "empty-field", "nan", "last-row", "not-rigid", "backwards"],
)
def test_matrix4x4_bad_input_names_line_and_field(tmp_path: Path, read: Callable, text: str, line: int,
                                                 fields: tuple[str, ...]) -> None:
    path = tmp_path / "poses.txt"
    path.write_text(text)
    _raises_naming(read, path, line, *fields)


@pytest.mark.parametrize("separator", [" ", ","])
def test_matrix4x4_write_read_round_trip_with_and_without_stamps(tmp_path: Path, separator: str) -> None:
    rng = np.random.default_rng(9)
    poses = _random_rigid(rng, 50, 20.0)
    stamps_s = [f"{1630577758 + k // 2}.{(k % 2) * 5}{rng.integers(0, 10**8):08d}" for k in range(len(poses))]

    def write(path: Path, last: list[str]) -> None:
        blocks = []
        for T, s in zip(poses, last, strict=True):
            rows = [[repr(float(v)) for v in T[i]] for i in range(3)] + [["0", "0", "0", s]]
            end = "," if separator == "," else ""  # BALM ends each row with a comma
            blocks.append("".join(separator.join(r) + end + "\n" for r in rows))
        path.write_text("\n".join(blocks))  # blank lines between blocks

    write(tmp_path / "stamped.txt", stamps_s)
    traj = read_trajectory(tmp_path / "stamped.txt")
    assert detect_trajectory_format(tmp_path / "stamped.txt") == "4x4" and has_stamps(traj, "4x4")
    assert traj.frame_ids is None
    assert traj.stamps_ns.tolist() == [_stamp_ns(s) for s in stamps_s]  # exact, not through a float
    np.testing.assert_array_equal(traj.poses, poses)  # as written: repr round-trips, the last row is 0 0 0 1
    write(tmp_path / "plain.txt", ["1"] * len(poses))
    plain = read_trajectory(tmp_path / "plain.txt")
    assert not has_stamps(plain, "4x4")
    assert plain.frame_ids.tolist() == plain.stamps_ns.tolist() == list(range(len(poses)))  # block k = frame k
    np.testing.assert_array_equal(plain.poses, poses)


def test_a_4x4_file_read_as_tum_says_what_it_looks_like(tmp_path: Path) -> None:
    path = tmp_path / "poses.csv"
    path.write_text(BLOCK.format(s="1630577758.569490").replace(" ", ","))
    _raises_naming(read_tum, path, 1, "expected 8 columns", "a file of 4x4 matrices?", "--gt-format 4x4")


# ---- round trips ------------------------------------------------------------------------------------------------


def _random_rigid(rng: np.random.Generator, n: int, scale_m: float) -> np.ndarray:
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.random(n, random_state=rng).as_matrix()
    poses[:, :3, 3] = rng.uniform(-scale_m, scale_m, (n, 3))
    return poses


@pytest.mark.parametrize("scale_m", [1.0, 5000.0])
def test_tum_write_read_round_trip(tmp_path: Path, scale_m: float) -> None:
    rng = np.random.default_rng(7)
    poses = _random_rigid(rng, 300, scale_m)
    stamps = 1_311_868_163_000_000_000 + np.cumsum(rng.integers(1, 50_000_000, len(poses)))
    write_tum(tmp_path / "rt.tum", Trajectory(stamps.astype(np.int64), poses))
    back = read_tum(tmp_path / "rt.tum")
    np.testing.assert_array_equal(back.stamps_ns, stamps)
    np.testing.assert_allclose(back.poses, poses, rtol=0, atol=1e-9)


@pytest.mark.parametrize("scale_m", [1.0, 5000.0])
def test_kitti_write_read_round_trip(tmp_path: Path, scale_m: float) -> None:
    rng = np.random.default_rng(8)
    poses = _random_rigid(rng, 300, scale_m)
    ids = np.arange(len(poses), dtype=np.int64)
    write_kitti(tmp_path / "rt.txt", Trajectory(ids, poses, ids))
    back = read_kitti(tmp_path / "rt.txt")
    np.testing.assert_array_equal(back.frame_ids, ids)
    np.testing.assert_allclose(back.poses, poses, rtol=0, atol=1e-9)


# ---- the shared real files still read ------------------------------------------------------------------------------

SHARED_POSE_FILES = {
    "trajectories/KITTI_00_gt.txt": "kitti",
    "trajectories/KITTI_00_ORB.txt": "kitti",
    "trajectories/fr2_desk_groundtruth.txt": "tum",
    "trajectories/fr2_desk_ORB.txt": "tum",
    "trajectories/freiburg1_xyz-groundtruth.txt": "tum",
    "trajectories/freiburg1_xyz-rgbdslam_drift.txt": "tum",
    "trajectories/V102_groundtruth.csv": "euroc",
    "kitti-00-frames0-15/poses.txt": "kitti",
    "icl-nuim-livingroom1-5frames/trajectory.log": "redwood",
    "icl-nuim-livingroom1-5frames/odometry.log": "redwood",
    "balm-lidar-0-79/alidarPose.csv": "4x4",
}


def _stamp_ns(text: str) -> int:
    return int(Decimal(text) * 10**9)


def _data_lines(path: Path) -> int:
    return sum(1 for line in path.read_text().splitlines() if line.strip() and not line.lstrip().startswith("#"))


@pytest.mark.parametrize("name", sorted(SHARED_POSE_FILES))
def test_every_shared_trajectory_file_still_reads(datasets_dir: Path, name: str) -> None:
    path = datasets_dir / name
    traj = read_trajectory(path)
    expected_rows = _data_lines(path) // {"redwood": 5, "4x4": 4}.get(SHARED_POSE_FILES[name], 1)
    assert detect_trajectory_format(path) == SHARED_POSE_FILES[name]
    assert len(traj) == expected_rows  # every data row became a pose
    assert np.all(np.isfinite(traj.poses))
    R = traj.poses[:, :3, :3]
    assert np.max(np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3))) < RIGID_TOLERANCE
    assert np.all(np.diff(traj.stamps_ns) >= 0)
    if SHARED_POSE_FILES[name] == "kitti":  # rows are kept exactly as written
        np.testing.assert_array_equal(traj.poses[:, :3, :].reshape(-1, 12), np.loadtxt(path, ndmin=2))


def test_shared_trajectory_folder_is_fully_covered(datasets_dir: Path) -> None:
    """A pose file added to the shared folder must be added to the list above (the times file is not one)."""
    listed = {Path(name).name for name in SHARED_POSE_FILES if name.startswith("trajectories/")}
    present = {p.name for p in (datasets_dir / "trajectories").iterdir()} - {"KITTI_00_gt_times.txt"}
    assert present == listed


def test_fr2_desk_repeated_stamp_is_reported_not_rejected(datasets_dir: Path,
                                                          caplog: pytest.LogCaptureFixture) -> None:
    path = datasets_dir / "trajectories" / "fr2_desk_groundtruth.txt"
    with caplog.at_level(logging.WARNING, logger="driftmap.trajectory"):
        traj = read_tum(path)
    repeated = np.flatnonzero(np.diff(traj.stamps_ns) == 0)
    assert repeated.size >= 1
    warnings = [r.getMessage() for r in caplog.records if "duplicate stamp" in r.getMessage()]
    assert len(warnings) == 1
    found = re.fullmatch(rf"{re.escape(str(path))}:(\d+): duplicate stamp: (\S+) is also on line (\d+);.*", warnings[0])
    assert found is not None, warnings[0]
    # the two lines it names really carry the same stamp, and it is the first repeated stamp of the trajectory
    lines = path.read_text().splitlines()
    line, stamp, other = int(found[1]), found[2], int(found[3])
    assert lines[line - 1].split()[0] == lines[other - 1].split()[0] == stamp
    assert traj.stamps_ns[repeated[0]] == traj.stamps_ns[repeated[0] + 1] == _stamp_ns(stamp)
