"""Hostile trial 25: its findings, each through the path the user took (docs/bad-input.md, trial 25).

B1 (g2o information matrices that are not positive definite, read by GTSAM as other matrices) is tested in
``tests/test_posegraph.py``. B2: a LiDAR scan whose points are all one point was tracked "ok" and stored 1.4 m /
16 deg off: one distinct point fits any surface."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from cli_run import run_cli

from driftmap.store.frame_store import FrameStore


def _ok(out):  # noqa: ANN001, ANN202 - a CompletedProcess
    assert out.returncode == 0, (out.stdout[-2000:], out.stderr[-2000:])
    return out


def _xyz_pcd(path: Path, points: np.ndarray) -> None:
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    assert o3d.io.write_point_cloud(str(path), cloud)


def test_t25_b2_a_scan_of_one_repeated_point_is_flagged_and_its_pose_predicted(balm_dir: Path, tmp_path: Path) -> None:
    """BALM scans 30-37 as a PCD folder, scan 4 replaced by 87,170 copies of one point: the scan is flagged (lost:
    too few points after the voxel grid, pose predicted), its pose lies between its neighbours' instead of 1.4 m below
    them, and the other scans are tracked."""
    import open3d as o3d

    folder = tmp_path / "scans"
    folder.mkdir()
    for k in range(8):
        pts = np.asarray(o3d.io.read_point_cloud(str(balm_dir / f"full{30 + k}.pcd")).points)
        if k == 4:
            pts = np.tile([3.0, 1.0, 0.5], (87_170, 1))
        _xyz_pcd(folder / f"{k:06d}.pcd", pts)
    store = tmp_path / "s"
    out = _ok(run_cli("build", folder, "--out", store, "--period-s", "0.5", "--threads", "1", "--no-loop-closure"))
    assert "frame 4" in out.stderr and "pose predicted" in out.stderr, out.stderr[-3000:]
    tracking = json.loads((store / "build_summary.json").read_text())["tracking"]
    assert [f["frame_id"] for f in tracking["flagged"]] == [4], tracking["flagged"]
    assert tracking["by_status"] == {"first": 1, "ok": 6, "lost": 1}, tracking["by_status"]
    assert "87170 measured" in tracking["flagged"][0]["reason"], tracking["flagged"][0]
    with FrameStore.open(store) as s:
        poses = s.poses()
    t = poses[:, :3, 3]
    assert np.linalg.norm(t[4] - 0.5 * (t[3] + t[5])) < 0.15, t[3:6]
