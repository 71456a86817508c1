"""A diagnosis that knows when it cannot judge: coverage, validity, stored normals that are not normals, the scene
scale of its lengths and diagnose --config."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from driftmap.cli import app
from driftmap.diagnostics.double_wall import DiagnosticCloud, DoubleWallConfig, RejectReason
from driftmap.diagnostics.report import DiagnoseConfig, diagnose_store
from driftmap.errors import ConfigError
from driftmap.frame import Frame, PointAttributes, PoseEstimate, SensorKind
from driftmap.store.frame_store import FrameStore


def _room_scan(rng: np.random.Generator, n: int, T_world_sensor: np.ndarray, half_m: float = 3.0) -> np.ndarray:
    """Sensor-frame points on the walls, floor and ceiling of a box room (range noise 5 mm)."""
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = T_world_sensor[:3, 3]
    dw = d @ T_world_sensor[:3, :3].T
    with np.errstate(divide="ignore"):
        t = np.min(np.where(dw != 0, (np.sign(dw) * half_m - o) / dw, np.inf), axis=1)
    p_world = o + dw * (t + rng.normal(0, 0.005, n))[:, None]
    return ((p_world - o) @ T_world_sensor[:3, :3]).astype(np.float32)


def _store(path: Path, n_frames: int, n_points: int, *, normals: str | None = None, loop: bool = True) -> FrameStore:
    rng = np.random.default_rng(4)
    with FrameStore.create(path) as store:
        for k in range(n_frames):
            a = (2 * np.pi * 1.1 * k / n_frames) if loop else 0.0
            T = np.eye(4)
            T[:3, 3] = (1.2 * np.cos(a), 1.2 * np.sin(a), 0.0) if loop else (-2.0 + 4.0 * k / n_frames, 0.0, 0.0)
            pts = _room_scan(rng, n_points, T)
            attrs = PointAttributes()
            if normals == "zero":
                attrs = PointAttributes(normal_sensor=np.zeros_like(pts))
            store.append(Frame(frame_id=k, stamp_ns=k * 100_000_000, sensor_name="lidar", sensor_kind=SensorKind.LIDAR,
                               points_sensor=pts, pose=PoseEstimate(T), attributes=attrs))
    return FrameStore.open(path)


@pytest.fixture(scope="module")
def room_store(tmp_path_factory: pytest.TempPathFactory) -> FrameStore:
    return _store(tmp_path_factory.mktemp("cov") / "room", 40, 20000)


def test_a_good_map_is_judged_with_its_coverage(room_store: FrameStore) -> None:
    d = diagnose_store(room_store)
    cov = d.coverage
    assert cov is not None and cov.valid and cov.reasons == []
    # a box room: every wall is a surface seen by many frames; what is not evaluated is the finest voxels' share of
    # the 800k samples over 216 m2 of wall (measured: 73 % evaluated)
    assert cov.fraction_evaluated > 0.6
    why = cov.not_evaluated_fractions()
    assert max(why, key=why.get) == "too_sparse"
    assert abs(sum(cov.not_evaluated_fractions().values()) + cov.fraction_evaluated - 1.0) < 1e-9
    data = d.to_json()
    assert data["valid"] is True and data["coverage"]["measures"]["smearing_score"]["valid"]
    for s in data["coverage"]["per_scale"]:  # every occupied voxel is in exactly one state
        assert s["voxels_evaluated"] + sum(s["not_evaluated"].values()) == s["voxels_occupied"]
        assert s["points_evaluated"] + sum(s["points_not_evaluated"].values()) == s["points"]
    assert data["fraction_inconsistent"] <= 0.02  # the exact poses: neither doubled nor smeared surfaces


def test_zero_normals_in_the_frames_are_not_taken_as_normals(tmp_path: Path, room_store: FrameStore,
                                                             caplog: pytest.LogCaptureFixture) -> None:
    """The real Livox PCDs carry all-zero normal fields: once kept, the detector evaluated 0 of 0 voxels."""
    store = _store(tmp_path / "zero", 40, 20000, normals="zero")
    with caplog.at_level(logging.WARNING, logger="driftmap.diagnostics.double_wall"):
        cloud = DiagnosticCloud.from_store(store, DiagnoseConfig.for_store(store).sampling)
    warned = [r for r in caplog.records if "not unit vectors" in r.getMessage()]
    assert len(warned) == 1 and "40 of 40 frames" in warned[0].getMessage()  # one warning, not one per frame
    assert cloud.stored_normals_refused is not None and cloud.stored_normals_refused.all()
    assert np.allclose(np.linalg.norm(cloud.normals_sensor, axis=1), 1.0, atol=1e-4)
    d = diagnose_store(store, cloud=cloud)
    good = diagnose_store(room_store)
    assert d.double_walls.voxels_evaluated == good.double_walls.voxels_evaluated > 0
    assert d.coverage.frames_with_refused_normals == 40 and d.coverage.valid


def test_a_map_too_sparse_to_judge_says_so_instead_of_a_small_number(tmp_path: Path) -> None:
    store = _store(tmp_path / "sparse", 12, 15)  # 15 points per scan, fewer than a normal's 20 neighbours
    out = tmp_path / "d.json"
    result = CliRunner().invoke(app, ["diagnose", str(store.path), "--json", str(out)])
    assert result.exit_code == 0, result.output
    data = json.loads(out.read_text())
    assert data["valid"] is False and data["reasons"]
    assert data["double_wall"]["voxels_evaluated"] == 0 and data["double_wall"]["fraction_flagged"] == 0.0  # kept keys
    assert not data["coverage"]["measures"]["fraction_flagged"]["valid"]
    assert data["coverage"]["not_evaluated"]["no_normals"] > 0.9
    samples = data["coverage"]["samples"]
    assert samples["no_normal"] == samples["drawn"] == 12 * 15 and samples["kept"] == 0
    assert "cannot judge" in result.output


def test_a_single_pass_cannot_show_drift_in_its_smearing_score(tmp_path: Path) -> None:
    store = _store(tmp_path / "pass", 25, 6000, loop=False)
    cfg = DiagnoseConfig.for_store(store).model_copy(
        update={"double_wall": DoubleWallConfig(visit_gap_m=50.0)})  # nothing is ever a second visit
    d = diagnose_store(store, config=cfg)
    m = d.coverage.measures
    assert not m["smearing_score"]["valid"] and "two visits" in m["smearing_score"]["reasons"][0]
    assert m["fraction_flagged"]["valid"] and not d.coverage.valid


def test_rejected_samples_are_kept_for_the_coverage_at_the_density_of_the_usable_ones(room_store: FrameStore) -> None:
    cloud = DiagnosticCloud.from_store(room_store)
    counts = cloud.sample_counts
    assert counts is not None and counts.shape == (40, 3) and np.all(counts[:, 0] > 0)
    rejected = np.diff(cloud.rejected_offsets)
    kept = np.diff(cloud.offsets)
    with_normal = counts[:, 0] - counts[:, 1] - counts[:, 2]
    expected = (counts[:, 1] + counts[:, 2]) * kept / with_normal
    assert np.all(np.abs(rejected - expected) <= 1.0)
    assert set(np.unique(cloud.rejected_reason)) <= {int(RejectReason.NO_NORMAL), int(RejectReason.NOT_PLANAR)}
    placed = cloud.place(room_store.poses(0))
    assert placed.rejected_world.shape == (len(cloud.rejected_points_sensor), 3)


def test_diagnose_lengths_follow_the_scene_continuously() -> None:
    indoor, outdoor = DiagnoseConfig(), DiagnoseConfig.for_sensor(SensorKind.LIDAR)
    room = DiagnoseConfig.for_scene(SensorKind.LIDAR, 4.0)
    assert room.double_wall == indoor.double_wall and room.attribution == indoor.attribution
    far = DiagnoseConfig.for_scene(SensorKind.LIDAR, 40.0)
    assert far == outdoor
    voxels = [DiagnoseConfig.for_scene(SensorKind.LIDAR, r).double_wall.voxel_sizes_m[0] for r in np.linspace(3, 30, 55)]
    gaps = [DiagnoseConfig.for_scene(SensorKind.LIDAR, r).double_wall.visit_gap_m for r in np.linspace(3, 30, 55)]
    assert np.all(np.diff(voxels) >= 0) and np.all(np.diff(gaps) >= 0)
    assert np.max(np.diff(voxels)) < 0.02 and voxels[0] == 0.1 and voxels[-1] == pytest.approx(0.5)
    mid = DiagnoseConfig.for_scene(SensorKind.LIDAR, 15.0)  # three times the indoor lengths
    assert mid.double_wall.voxel_sizes_m == pytest.approx((0.3, 0.6, 1.2))
    assert mid.attribution.max_residual_m == pytest.approx(0.3)
    assert 1.0 < mid.double_wall.visit_gap_m < 10.0
    assert DiagnoseConfig.for_scene(SensorKind.DEPTH_CAMERA, 40.0) == indoor


def test_diagnose_config_file_sets_its_own_lengths(tmp_path: Path, room_store: FrameStore) -> None:
    cfg_file = tmp_path / "d.toml"
    cfg_file.write_text("[build]\nnum_threads = 1\n\n[diagnose.double_wall]\nvoxel_sizes_m = [0.3]\nvisit_gap_m = 2.0\n\n"
                        "[diagnose.coverage]\nmin_groups_evaluated = 5\n")
    out = tmp_path / "d.json"
    result = CliRunner().invoke(app, ["diagnose", str(room_store.path), "--json", str(out), "--config", str(cfg_file)])
    assert result.exit_code == 0, result.output
    data = json.loads(out.read_text())
    assert data["config"]["double_wall"]["voxel_sizes_m"] == [0.3] and data["config"]["double_wall"]["visit_gap_m"] == 2.0
    assert [s["voxel_size_m"] for s in data["double_wall"]["per_scale"]] == [0.3]
    # the scene's other defaults stay
    assert data["config"]["double_wall"]["min_points"] == DoubleWallConfig().min_points
    assert data["config"]["coverage"]["min_groups_evaluated"] == 5
    bad = tmp_path / "bad.toml"
    bad.write_text("[diagnose.double_wall]\nvoxel_size = 0.3\n")
    result = CliRunner().invoke(app, ["diagnose", str(room_store.path), "--json", str(tmp_path / "e.json"), "--config", str(bad)])
    assert isinstance(result.exception, ConfigError)  # the CLI's main() prints it as one line, exit code 1
    assert "diagnose.double_wall.voxel_size: unknown setting" in str(result.exception) and str(bad) in str(result.exception)
    with pytest.raises(ConfigError, match="cannot read config"):
        DiagnoseConfig.load(tmp_path / "missing.toml", DiagnoseConfig())
