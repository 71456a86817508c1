"""Hostile trial 16, B5: ``driftmap diagnose`` on a moving LiDAR with per-point times.

A ground-truth-posed map of the room LiDAR whose points carry their capture times read 16 double-wall regions,
11.5 mm smearing and 3 change points, where the same scene without the times read 0.39 mm and no region: the map
view deskews such frames with the revision's continuous trajectory, the diagnostics' samples were placed rigidly.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from driftmap import geometry
from driftmap.diagnostics.samples import DiagnosticCloud, SamplingConfig
from driftmap.preprocess.deskew import scan_motion
from driftmap.map.view import MapView
from driftmap.pipeline.build import build
from driftmap.sources.synthetic import SyntheticLogConfig, generate_synthetic_log
from driftmap.store.frame_store import FrameStore

from cli_run import run_cli

SMALL = dict(n_frames=20, seed=24, lidar=True, width=80, height=60, fx=65.625, fy=65.625, cx=39.5, cy=29.5)


@pytest.fixture(scope="module")
def stores(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """``P0``: the moving room LiDAR without per-point times, ``P1``: the same with them; both stored with the
    ground-truth poses and no loop closure."""
    root = tmp_path_factory.mktemp("b5")
    out = {}
    for name, times in (("P0", False), ("P1", True)):
        log = generate_synthetic_log(root / name, SyntheticLogConfig(**SMALL, lidar_point_times=times))
        build(log, root / f"st_{name}", poses_file=log / "groundtruth.txt", loop_closure=False,
              source_options={"sensor": "lidar"})
        out[name] = root / f"st_{name}"
    return out


def _diagnose(store: Path, out: Path) -> dict:
    res = run_cli("diagnose", store, "--json", out)
    assert res.returncode == 0, (res.stdout[-1500:], res.stderr[-1500:])
    return json.loads(out.read_text())


def test_cli_diagnosis_with_point_times_reads_like_without(stores, tmp_path: Path) -> None:
    without = _diagnose(stores["P0"], tmp_path / "p0.json")
    timed = _diagnose(stores["P1"], tmp_path / "p1.json")
    assert without["double_wall"]["regions"] == [] and without["change_points"] == []
    # before the fix (30 frames): 16 regions, 11.5 mm against 0.39 mm, 3 change points
    assert timed["double_wall"]["regions"] == []
    assert timed["change_points"] == []
    assert timed["smearing_score_m"] <= without["smearing_score_m"] + 0.001, (timed["smearing_score_m"],
                                                                             without["smearing_score_m"])


def _sample_rows_in_frame(frame_points: np.ndarray, samples: np.ndarray) -> np.ndarray:
    """Index into ``frame_points`` of every sample (samples are exact copies of some of the frame's points)."""
    keys = np.ascontiguousarray(frame_points, dtype=np.float32).view(np.dtype((np.void, 12))).ravel()
    wanted = np.ascontiguousarray(samples, dtype=np.float32).view(np.dtype((np.void, 12))).ravel()
    order = np.argsort(keys, kind="stable")
    pos = np.searchsorted(keys[order], wanted)
    idx = order[np.clip(pos, 0, len(order) - 1)]
    assert np.array_equal(keys[idx], wanted)
    return idx


def test_samples_of_timed_frames_are_placed_as_the_map_view_places_them(stores) -> None:
    store = FrameStore.open(stores["P1"])
    head = store.head
    cloud = DiagnosticCloud.from_store(store, SamplingConfig(points_per_frame=300))
    assert cloud.timed is not None and cloud.timed.all() and cloud.time_offset_ns is not None
    poses = store.poses(head)[np.searchsorted(store.frame_ids, cloud.frame_ids)]
    placed = cloud.place(poses)
    assert len(placed.scan_motions) == cloud.n_frames  # every frame deskewed (the last one extrapolating)
    view = MapView.from_store(store, head)
    assert view.deskew_problems == {}
    order = np.arange(cloud.n_frames)
    moved = 0.0
    for k in (0, cloud.n_frames // 2, cloud.n_frames - 1):
        fid = int(cloud.frame_ids[k])
        a, b = cloud.offsets[k], cloud.offsets[k + 1]
        frame = store.frame(fid)
        idx = _sample_rows_in_frame(frame.points_sensor, cloud.points_sensor[a:b])
        assert np.array_equal(cloud.time_offset_ns[a:b], frame.attributes.time_offset_ns[idx])
        expected = view.frame_points_world(fid)[idx]
        np.testing.assert_allclose(placed.points_world[a:b], expected, rtol=0, atol=2e-6 * (1 + np.abs(expected).max()))
        rigid = cloud.points_sensor[a:b].astype(np.float64) @ poses[k, :3, :3].T + poses[k, :3, 3]
        moved = max(moved, float(np.abs(placed.points_world[a:b] - rigid).max()))
        # normals turned with the same motion as their points
        motion, why = scan_motion(cloud.stamps_ns, poses, k, order, order, int(np.ptp(frame.attributes.time_offset_ns)))
        assert motion is not None, why
        D = geometry.se3_exp((cloud.time_offset_ns[a:b] / motion.dt_ns)[:, None] * motion.xi[None, :])
        n = np.einsum("nij,nj->ni", D[:, :3, :3], cloud.normals_sensor[a:b].astype(np.float64)) @ poses[k, :3, :3].T
        np.testing.assert_allclose(placed.normals_world[a:b], n, rtol=0, atol=1e-12)
    assert moved > 0.01  # the deskew matters here (the sensor moves decimetres during a scan)
    # the rejected samples (the coverage report) are deskewed too
    r = cloud.rejected_offsets
    assert r is not None and cloud.rejected_time_offset_ns is not None
    k = cloud.n_frames // 2
    if r[k + 1] > r[k]:
        fid = int(cloud.frame_ids[k])
        frame = store.frame(fid)
        idx = _sample_rows_in_frame(frame.points_sensor, cloud.rejected_points_sensor[r[k]:r[k + 1]])
        expected = view.frame_points_world(fid)[idx]
        np.testing.assert_allclose(placed.rejected_world[r[k]:r[k + 1]], expected, rtol=0,
                                   atol=2e-6 * (1 + np.abs(expected).max()))
    # a subset keeps every array consistent
    sub = cloud.subset([1, 2, 3])
    assert sub.time_offset_ns is not None and sub.timed is not None and len(sub.time_offset_ns) == sub.n_points
    # rows 1 and 2 keep their neighbours in time (rows 2 and 3), so their samples land where they did
    np.testing.assert_array_equal(sub.place(poses[1:4]).points_world[: sub.offsets[2]],
                                  placed.points_world[cloud.offsets[1]:cloud.offsets[3]])


def _rigid(cloud: DiagnosticCloud, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pts = np.empty((cloud.n_points, 3))
    nrm = np.empty((cloud.n_points, 3))
    for k in range(cloud.n_frames):
        a, b = cloud.offsets[k], cloud.offsets[k + 1]
        R, t = poses[k, :3, :3], poses[k, :3, 3]
        pts[a:b] = cloud.points_sensor[a:b].astype(np.float64) @ R.T + t
        nrm[a:b] = cloud.normals_sensor[a:b].astype(np.float64) @ R.T
    return pts, nrm


def test_frames_without_times_are_placed_rigidly_as_before(stores) -> None:
    store = FrameStore.open(stores["P0"])
    cloud = DiagnosticCloud.from_store(store, SamplingConfig(points_per_frame=300))
    assert cloud.timed is None and cloud.time_offset_ns is None
    poses = store.poses(store.head)[np.searchsorted(store.frame_ids, cloud.frame_ids)]
    placed = cloud.place(poses)
    pts, nrm = _rigid(cloud, poses)
    assert placed.scan_motions == {}
    assert np.array_equal(placed.points_world, pts) and np.array_equal(placed.normals_world, nrm)
    # a timed store with its times dropped is placed rigidly, bit for bit
    timed = DiagnosticCloud.from_store(FrameStore.open(stores["P1"]), SamplingConfig(points_per_frame=300))
    plain = dataclasses.replace(timed, timed=None, time_offset_ns=None, rejected_time_offset_ns=None, time_span_ns=None)
    placed = plain.place(poses)
    pts, nrm = _rigid(plain, poses)
    assert np.array_equal(placed.points_world, pts) and np.array_equal(placed.normals_world, nrm)
