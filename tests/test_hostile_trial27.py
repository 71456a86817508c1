"""Hostile trial 27: its findings, each through the path the user took (docs/bad-input.md, trial 27)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from cli_run import one_error, run_cli


def test_t27_b1_a_diagnose_voxel_size_given_twice_is_refused(room10: dict[str, Path], tmp_path: Path) -> None:
    """``[diagnose.double_wall] voxel_sizes_m = [0.1, 0.1]`` was counted twice (6 / 4048 surface voxels doubled instead
    of 3 / 2024, and a mixed list moved the fraction and the smearing score): refused naming the setting and the
    size, nothing written."""
    cfg = tmp_path / "dup.toml"
    cfg.write_text("[diagnose.double_wall]\nvoxel_sizes_m = [0.4, 0.1, 0.1]\n")
    err = one_error(run_cli("diagnose", room10["gt"], "--json", tmp_path / "d.json", "--config", cfg))
    assert "voxel_sizes_m" in err and "each voxel size once: 0.1 m given more than once" in err, err
    assert not (tmp_path / "d.json").exists()


@pytest.mark.parametrize("fx", ["5850", "585e3"])
def test_t27_b2_a_focal_length_for_a_pencil_thin_field_of_view_is_warned_about(sevenscenes_dir: Path, tmp_path: Path,
                                                                              fx: str) -> None:
    """``--intrinsics 5850,...`` (10x the 7-Scenes focal length: a 6 deg field of view) and ``585e3`` (0.06 deg) built
    "tracking ok" without a word (only a field of view over 150 deg was warned about): a horizontal field of view
    under 20 deg is warned about, naming fx; the right focal length is not."""
    log = tmp_path / "d7"
    log.mkdir()
    for i in range(2):
        for kind in ("depth.png", "pose.txt"):
            shutil.copy(sevenscenes_dir / f"frame-{i:06d}.{kind}", log)
    shutil.copy(sevenscenes_dir / "camera-intrinsics.txt", log)
    out = run_cli("build", log, "--out", tmp_path / "s", "--intrinsics", f"{fx},{fx},320,240", "--poses-from-source",
                  "--no-loop-closure")
    err = " ".join(out.stderr.split())
    fov = 2 * np.degrees(np.arctan(320 / float(fx)))
    assert f"fx={float(fx):g} px gives a {fov:.2g} deg horizontal field of view" in err, err[-2000:]
    assert "is fx in other units, or for another image size?" in err
    out = run_cli("build", log, "--out", tmp_path / "ok", "--poses-from-source", "--no-loop-closure")
    assert out.returncode == 0 and "field of view" not in out.stderr


def test_t27_b3_footholds_and_a_grasp_on_a_kitti_road_measure_it_as_a_plane_fit_does(kitti_dir: Path,
                                                                                     tmp_path: Path) -> None:
    """KITTI 00 frames 0-4 with their ground truth: footholds of 0.3 m on the road ahead of frame 2 read 31-66 deg
    steep and 7-13 cm uneven, and a 1 m grasp ROI on it a normal spread of 166 deg (the depth camera's 3 cm normal
    neighbourhoods hold a few points of one scan ring). On a LiDAR map the normal lengths scale with the layers'
    voxel: every patch's slope is within 3 deg of a plane fitted to its points, its flatness within 1 cm of the fit's
    RMS, and the grasp's spread under 10 deg."""
    from driftmap.decisions import decide
    from driftmap.map.view import MapView
    from driftmap.pipeline.build import build
    from driftmap.store.frame_store import FrameStore

    build(kitti_dir, tmp_path / "k", frames="0:5", poses_from_source=True, loop_closure=False)
    with FrameStore.open(tmp_path / "k") as store:
        ground = store.poses()[2][:3, 3] - np.array([0.0, 0.0, 1.73])  # the Velodyne sits 1.73 m above the road
        pts = MapView.from_store(store, store.head).points_world.astype(np.float64)
        offsets = [(4, 0), (6, 0), (8, 0), (-4, 0), (5, 1), (5, -1)]
        queries = [{"id": f"road{k}", "kind": "foothold", "center_m": (ground + [dx, dy, 0.0]).tolist(),
                    "radius_m": 0.3, "max_slope_deg": 15} for k, (dx, dy) in enumerate(offsets)]
        queries.append({"id": "grasp", "kind": "grasp", "roi_min_m": (ground + [4.5, -0.5, -0.2]).tolist(),
                        "roi_max_m": (ground + [5.5, 0.5, 0.2]).tolist()})
        decisions = decide(store, {"queries": queries}).decisions
    for d, q in zip(decisions[:-1], queries[:-1]):
        c = np.array(q["center_m"])
        patch = pts[(np.linalg.norm(pts[:, :2] - c[:2], axis=1) <= 0.3) & (np.abs(pts[:, 2] - c[2]) <= 0.3)]
        assert len(patch) >= 50 and d.details["n_points"] == len(patch), (d.id, len(patch))
        centred = patch - patch.mean(axis=0)
        w, v = np.linalg.eigh(centred.T @ centred)
        slope = np.degrees(np.arccos(abs(v[2, 0])))
        assert abs(d.details["slope_deg"] - slope) < 3.0, (d.id, d.details["slope_deg"], slope)
        assert abs(d.details["flatness_m"] - np.sqrt(w[0] / len(patch))) < 0.01, (d.id, d.details["flatness_m"])
        assert d.decision != "too_steep", d.id
    assert decisions[-1].decision == "graspable" and decisions[-1].details["normal_spread_deg"] < 10.0


def test_t27_w3_w4_the_layers_api_refuses_what_it_would_misread(room10: dict[str, Path]) -> None:
    """``decide(config=..., layers=...)`` ignored a config the layers were not built with; ``states_flat(-1)`` read the
    last voxel, ``mesh(nan)`` gave an empty mesh, ``equals(None)`` raised AttributeError and a 1e300 coordinate leaked
    a numpy warning from ``states`` (``observers`` refused it): each is a ConfigError naming the argument."""
    import warnings

    from driftmap.config import VolumeConfig
    from driftmap.decisions import decide
    from driftmap.errors import ConfigError
    from driftmap.store.frame_store import FrameStore
    from driftmap.volume import VolumeLayers

    with FrameStore.open(room10["gt"]) as store:
        layers = VolumeLayers.from_store(store, store.head)
        q = {"queries": [{"id": "c", "kind": "clearance", "points_m": [[0.0, 0.0, 1.0]], "radius_m": 0.1}]}
        with pytest.raises(ConfigError, match=r"config sets voxel_size_m 0.1 \(the layers: 0.02\)"):
            decide(store, q, config=VolumeConfig(voxel_size_m=0.1), layers=layers)
        same = decide(store, q, config=VolumeConfig(voxel_size_m=layers.config.voxel_size_m), layers=layers)
        assert same.decisions[0].decision == decide(store, q, layers=layers).decisions[0].decision
        n = layers.grid.n_voxels
        for bad in ([-1], [n]):
            with pytest.raises(ConfigError, match=rf"states_flat: flat voxel indices must be integers in 0 .. {n - 1}"):
                layers.states_flat(np.array(bad))
            with pytest.raises(ConfigError, match="tsdf_flat"):
                layers.tsdf_flat(np.array(bad))
        assert layers.states_flat(np.array([0, n - 1])).shape == (2,)
        for bad in (float("nan"), -1.0):
            with pytest.raises(ConfigError, match="weight_threshold must be a finite number >= 0"):
                layers.mesh(bad)
        with pytest.raises(ConfigError, match="equals: compares VolumeLayers with VolumeLayers, got NoneType"):
            layers.equals(None)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            for call in (layers.states, layers.observers):
                with pytest.raises(ConfigError, match=r"within \+-1e\+09 m of the world origin"):
                    call(np.array([[1e300, 0.0, 0.0]]))


def test_t27_w6_the_ate_row_says_how_many_frames_it_covers(room10: dict[str, Path], tmp_path: Path) -> None:
    """``diagnose --gt`` with ground truth for 3 of the 10 frames printed "ATE / RPE 0.00 cm / 0.00 cm" as if for the
    whole map (only a log line said the others were left out): the row says over how many of the frames."""
    rows = [line for line in (room10["log"] / "groundtruth.txt").read_text().splitlines() if not line.startswith("#")]
    (tmp_path / "gt3.txt").write_text("\n".join(rows[:3]) + "\n")
    out = run_cli("diagnose", room10["gt"], "--json", tmp_path / "d.json", "--gt", tmp_path / "gt3.txt")
    assert out.returncode == 0, out.stderr[-2000:]
    text = " ".join(out.stdout.replace("\u2502", " ").split())
    assert "(over 3 of the 10 frames: the others have no ground truth)" in text, text[-3000:]
    out = run_cli("diagnose", room10["gt"], "--json", tmp_path / "e.json", "--gt", room10["log"] / "groundtruth.txt")
    assert out.returncode == 0 and "ATE / RPE" in out.stdout and "the others have no ground truth" not in out.stdout
