"""The demo and the command line: what a newcomer runs first."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from driftmap import __version__


def _cli(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "COLUMNS": "200"}
    return subprocess.run([sys.executable, "-m", "driftmap.cli", *args], capture_output=True, text=True, timeout=300, env=env)


def test_version() -> None:
    out = _cli("--version")
    assert out.returncode == 0
    assert __version__ in out.stdout


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict, subprocess.CompletedProcess]:
    """The README's main command, once: `driftmap demo` on the whole embedded log (CI runs the demo)."""
    out_dir = tmp_path_factory.mktemp("demo") / "results"
    out = _cli("demo", "--out", str(out_dir))
    assert out.returncode == 0, out.stderr[-3000:]
    return out_dir, json.loads((out_dir / "summary.json").read_text()), out


def _image(path: str | Path) -> np.ndarray:
    img = np.asarray(Image.open(path).convert("RGB"))
    assert img.shape[0] > 250 and img.shape[1] > 400, f"{path}: {img.shape}"
    grey = img.mean(axis=2)
    assert grey.std() > 10, f"{path} looks blank"
    assert len(np.unique(img.reshape(-1, 3)[::7], axis=0)) > 50, f"{path} has too few colours to show data"
    return img


def test_demo_finds_the_double_walls_before_and_not_after(demo_run) -> None:
    _, summary, _ = demo_run
    assert summary["n_frames"] == 60
    before, after, ref = summary["diagnosis_before"], summary["diagnosis_after"], summary["diagnosis_ground_truth"]
    # revision 0 (drifting odometry): doubled surfaces at the loop, seen by early vs late frames
    assert before["revision"] == 0 and before["n_regions"] >= 1 and before["fraction_flagged"] > 0.01
    assert 0.01 < before["median_separation_m"] < 0.15
    assert any(r["frames_a"][0] < 15 and r["frames_b"][1] > 45 for r in before["regions"]), before["regions"]
    # after loop closure: gone, and the score falls to near the ground-truth placement's
    assert after["revision"] == summary["loop_revision"] >= 1
    assert after["n_regions"] == 0 and after["fraction_flagged"] < 0.002
    assert after["smearing_score_m"] < 0.25 * before["smearing_score_m"]
    assert after["smearing_score_m"] < 3.0 * ref["smearing_score_m"]
    assert summary["double_walls_before"] == before["n_regions"] and summary["double_walls_after"] == 0
    # the same numbers are in the full diagnosis JSON (the `driftmap diagnose` contract)
    for key, s in (("diagnosis_rev0_json", before), ("diagnosis_rev1_json", after)):
        full = json.loads(Path(summary["files"][key]).read_text())
        assert full["revision"] == s["revision"]
        assert full["double_wall"]["voxels_flagged"] == s["voxels_flagged"]
        assert abs(full["smearing_score_m"] - s["smearing_score_m"]) < 1e-9


def test_demo_correction_moves_old_frames_and_lowers_the_trajectory_error(demo_run) -> None:
    _, summary, _ = demo_run
    assert summary["loops_accepted"] >= 3
    assert summary["frames_retransformed"] >= 50
    assert summary["ate_corrected_m"] < 0.7 * summary["ate_odometry_m"]
    # the doubled loop wall of the drifting map is measured, and it is single with ground truth and after correction
    assert summary["wall_spread_odometry_m"] > 2.5 * summary["wall_spread_ground_truth_m"]
    assert summary["wall_spread_corrected_m"] < 1.5 * summary["wall_spread_ground_truth_m"]


def test_demo_exports(demo_run) -> None:
    out_dir, summary, _ = demo_run
    files = summary["files"]
    for key in ("map_odometry_ply", "map_corrected_ply", "map_ground_truth_ply"):
        assert Path(files[key]).stat().st_size > 100_000
    for key in ("trajectory_corrected_tum", "trajectory_odometry_tum"):
        assert len(Path(files[key]).read_text().splitlines()) == 61  # header + 60 frames
    from driftmap.config import DriftmapConfig

    saved = DriftmapConfig.model_validate(json.loads((out_dir / "config.json").read_text()))
    assert saved.depth.max_depth_m is None  # the synthetic log's own depth range (8 m)
    assert json.loads((out_dir / "build_config.json").read_text())["loop_closure"]["min_gap_frames"] == 20
    # the MCAP opens with a generic reader and carries Foxglove schemas
    from mcap.reader import make_reader

    with open(files["foxglove_mcap"], "rb") as f:
        summary_rec = make_reader(f).get_summary()
    schemas = {s.name for s in summary_rec.schemas.values()}
    assert {"foxglove.PointCloud", "foxglove.FrameTransform"} <= schemas
    topics = {c.topic for c in summary_rec.channels.values()}
    assert "/map" in topics


def test_demo_report_and_figures(demo_run) -> None:
    out_dir, summary, cli = demo_run
    files = summary["files"]
    for key in ("top_view_png", "double_walls_rev0_png", "double_walls_rev1_png", "frame_disagreement_rev0_png",
                "smearing_before_after_png"):
        _image(files[key])
    md = Path(files["report_md"]).read_text()
    html = Path(files["report_html"]).read_text()
    images = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", md)
    assert len(images) >= 5 and all((out_dir / p).exists() for p in images)
    assert all(f"src='{p}'" in html for p in images)
    assert "double-wall regions" in md and "smearing score" in html
    # the CLI printed the separations, the summary table and where the results are
    assert "apart at" in cli.stdout and "double-wall regions: revision 0 -> corrected" in cli.stdout
    assert str(out_dir.resolve()) in cli.stdout.replace("\n", "")


def test_demo_volume_layers_before_and_after_the_loop_closure(demo_run) -> None:
    """The volumetric layers of revision 0, updated (not rebuilt) to the loop closure's revision: the summary's
    counts add up, the TSDF mesh is written, and the two top views (one extent: pixel-aligned) differ where the loop
    wall was doubled far more than in the room's interior."""
    import open3d as o3d

    from driftmap.demo import DEMO_VOLUME_VOXEL_M, LOOP_WALL, LOOP_WALL_STRIP_M
    from driftmap.diagnostics.figures import STATE_TOP_VIEW_RGB, top_view_layout

    _, s, cli = demo_run
    files = s["files"]
    assert s["volume_voxel_size_m"] == DEMO_VOLUME_VOXEL_M
    assert s["volume_revision_before"] == 0 and s["volume_revision_after"] == s["loop_revision"]
    # every voxel of the grid is in one state; the grid never shrinks in an update
    assert s["volume_occupied_after"] + s["volume_free_after"] + s["volume_unknown_after"] == s["volume_n_voxels"]
    assert s["volume_occupied_before"] + s["volume_free_before"] + s["volume_unknown_before"] <= s["volume_n_voxels"]
    assert s["volume_unknown_fraction"] == pytest.approx(s["volume_unknown_after"] / s["volume_n_voxels"])
    assert 0.0 < s["volume_unknown_fraction"] < 1.0 and s["volume_occupied_after"] > 10_000
    # the update took out and put back the frames the correction moved (those the map view re-transformed)
    assert s["volume_update_rebuilt"] is False
    assert s["volume_frames_reintegrated"] == s["frames_retransformed"]
    assert s["volume_state_changed"] > 0
    assert s["volume_build_s"] == s["seconds_per_stage"]["volume: build revision 0"] > 0 and s["volume_update_s"] > 0
    # the doubled wall is thicker from above and holds more occupied voxels than the single one
    assert s["volume_occupied_before"] > s["volume_occupied_after"]
    assert s["volume_loop_wall_thickness_before_m"] >= s["volume_loop_wall_thickness_after_m"] + DEMO_VOLUME_VOXEL_M
    mesh = o3d.io.read_triangle_mesh(files["volume_mesh_ply"])
    assert len(mesh.triangles) == s["volume_mesh_triangles"] > 10_000
    assert Path(files["volume_mesh_ply"]).name == f"volume_mesh_rev{s['loop_revision']}.ply"
    # the two top views: the layout of their extent, every state's colour drawn
    layout = top_view_layout(s["volume_top_view_extent_m"])
    before, after = (np.asarray(Image.open(files[f"volume_top_view_{k}_png"]).convert("RGB")).astype(int)
                     for k in ("before", "after"))
    assert before.shape == after.shape == (layout.height_px, layout.width_px, 3)
    for image in (before, after):
        for rgb in STATE_TOP_VIEW_RGB.values():
            assert np.all(image == rgb, axis=2).sum() > 5_000
    differs = np.any(before != after, axis=2)

    def share_differing(x_m: tuple[float, float], y_m: tuple[float, float]) -> float:
        x, y = np.meshgrid(np.arange(*x_m, 0.01), np.arange(*y_m, 0.01))
        px = layout.pixels(np.c_[x.ravel(), y.ravel()]).astype(int)
        return float(differs[px[:, 1], px[:, 0]].mean())

    wall_y = LOOP_WALL["offset_m"]
    along = LOOP_WALL["tangent_range_m"]
    at_wall = share_differing(along, (wall_y - LOOP_WALL_STRIP_M, wall_y + LOOP_WALL_STRIP_M))
    interior = share_differing(along, (-2.0, 2.0))
    assert at_wall > 0.1 and at_wall > 4 * interior, (at_wall, interior)
    near_wall = [r["center_m"] for r in s["diagnosis_before"]["regions"] if abs(r["center_m"][1] - wall_y) < 0.3]
    assert near_wall
    for x, y, _ in near_wall:  # around every double wall the diagnosis found at the loop wall
        assert share_differing((x - 0.15, x + 0.15), (y - 0.15, y + 0.15)) > 2 * interior
    # the reports show both views, the CLI prints the rows
    md, html = Path(files["report_md"]).read_text(), Path(files["report_html"]).read_text()
    for key in ("volume_top_view_before_png", "volume_top_view_after_png"):
        name = Path(files[key]).name
        assert f"]({name})" in md and f"src='{name}'" in html
    assert "volume: loop wall thickness from above" in cli.stdout


def test_demo_without_a_loop_still_reports(tmp_path: Path) -> None:
    """8 frames never revisit anything: no loop closure, no corrected revision, and the demo says so."""
    out = _cli("demo", "--frames", "8", "--out", str(tmp_path / "d"))
    assert out.returncode == 0, out.stderr
    assert "loop wall spread" in out.stdout
    summary = json.loads((tmp_path / "d" / "summary.json").read_text())
    assert summary["n_frames"] == 8 and summary["loop_revision"] is None and summary["diagnosis_after"] is None
    # the reports tell what happened (trial 16 W5: they described a loop closure that never ran, and an invalid
    # diagnosis's figures as a verdict)
    md, html = Path(summary["files"]["report_md"]).read_text(), Path(summary["files"]["report_html"]).read_text()
    for text in (md, html, out.stdout):
        assert "corrected by loop closure" not in text and "single after the correction" not in text
    assert "loop closure made no correction" in md and "loop closure made no correction" in html
    assert "no correction:" in out.stdout
    before = summary["diagnosis_before"]
    assert before["valid"] in (True, False)
    if before["valid"] is False:  # 8 frames: the check cannot rule out what it does not see
        assert before["reasons"] and "cannot judge the map" in md and "cannot judge" in out.stdout
    # the volumetric layers of revision 0 only: one top view, no update
    assert Path(summary["files"]["volume_top_view_before_png"]).exists()
    assert "volume_top_view_after_png" not in summary["files"]
    assert summary["volume_revision_after"] is None and summary["volume_update_s"] is None
    assert summary["volume_occupied_before"] > 0
    assert str((tmp_path / "d").resolve()) in out.stdout.replace("\n", "")
    # the same folder again: the earlier demo's results (and its store) are replaced
    again = _cli("demo", "--frames", "6", "--out", str(tmp_path / "d"))
    assert again.returncode == 0, again.stderr
    assert json.loads((tmp_path / "d" / "summary.json").read_text())["n_frames"] == 6


def test_demo_never_replaces_what_it_did_not_write(tmp_path: Path) -> None:
    """--out on a frame store, on a folder of other files, or on a results folder whose store/ is not a store: refused
    with one line naming the folder, and nothing in it touched (the demo used to delete OUT/store whatever it was)."""
    from driftmap.demo import embedded_log_path
    from driftmap.store.frame_store import FrameStore

    store = tmp_path / "store"
    _cli("build", str(embedded_log_path()), "--out", str(store), "--frames", "0:3", "--no-loop-closure")
    assert FrameStore.open(store).frame_ids.tolist() == [0, 1, 2]
    other = tmp_path / "other"
    (other / "store").mkdir(parents=True)
    (other / "store" / "mine.txt").write_text("keep me")
    fake = tmp_path / "fake"
    (fake / "store").mkdir(parents=True)
    (fake / "store" / "mine.txt").write_text("keep me")
    (fake / "summary.json").write_text(json.dumps({"files": {"store": str(fake / "store")}}))
    for out_dir, words in ((store, "frame store"), (other, "holds no earlier demo result"),
                           (fake, "is not a frame store the demo wrote")):
        before = sorted(str(p) for p in out_dir.rglob("*"))
        out = _cli("demo", "--frames", "4", "--out", str(out_dir))
        assert out.returncode == 1 and "Traceback" not in out.stderr, out.stderr
        assert words in out.stderr.strip().splitlines()[-1], out.stderr
        assert sorted(str(p) for p in out_dir.rglob("*")) == before
    assert FrameStore.open(store).frame_ids.tolist() == [0, 1, 2]


def test_cli_error_is_one_line_without_traceback(tmp_path: Path) -> None:
    out = _cli("demo", "--log", str(tmp_path / "missing"), "--out", str(tmp_path / "d"))
    assert out.returncode == 1
    assert "Traceback" not in out.stderr
    lines = [line for line in out.stderr.strip().splitlines() if line.strip()]
    assert lines[-1].startswith("error:") and "synthetic.json" in out.stderr
    debug = _cli("--debug", "demo", "--log", str(tmp_path / "missing"), "--out", str(tmp_path / "d"))
    assert debug.returncode != 0 and "Traceback" in debug.stderr


def test_config_show_lists_settings_with_units() -> None:
    out = _cli("config", "--show")
    assert out.returncode == 0, out.stderr
    for name in ("depth.max_depth_m", "map.export_voxel_size_m", "build.loop_closure.proximity_radius_m"):
        assert name in out.stdout
    # the odometry defaults depend on the sensor kind: both are listed (not just "None")
    from driftmap.frame import SensorKind
    from driftmap.registration.odometry import OdometryConfig

    row = next(line for line in out.stdout.splitlines() if "build.odometry.max_range_m" in line)
    depth, lidar = (OdometryConfig.for_sensor(k).max_range_m for k in (SensorKind.DEPTH_CAMERA, SensorKind.LIDAR))
    assert f"depth: {depth}, lidar: {lidar}" in row


def test_one_config_file_holds_the_general_and_the_build_settings(tmp_path: Path) -> None:
    """`config --show` lists build.* keys; a file with a [build] table sets exactly those (what `build --config`
    reads), next to the general tables; a file without one is a bare build config, as before."""
    from driftmap.config import DriftmapConfig
    from driftmap.errors import ConfigError
    from driftmap.pipeline.build import BuildConfig

    both = tmp_path / "driftmap.toml"
    both.write_text('[map]\nexport_voxel_size_m = 0.03\n\n[build]\npixel_stride = 3\n\n[build.loop_closure]\n'
                    'proximity_radius_m = 1.5\n')
    assert BuildConfig.load(both).pixel_stride == 3
    assert BuildConfig.load(both).loop_closure.proximity_radius_m == 1.5
    assert DriftmapConfig.load(both).map.export_voxel_size_m == 0.03
    out = _cli("config", "--file", both)
    assert out.returncode == 0, out.stderr
    rows = {line.split("│")[1].strip(): line.split("│")[2].strip() for line in out.stdout.splitlines() if line.count("│") >= 3}
    assert rows["build.pixel_stride"] == "3" and rows["build.loop_closure.proximity_radius_m"] == "1.5"
    assert rows["map.export_voxel_size_m"] == "0.03"
    bare = tmp_path / "build.json"
    bare.write_text(json.dumps({"pixel_stride": 4}))
    assert BuildConfig.load(bare).pixel_stride == 4
    typo = tmp_path / "typo.toml"
    typo.write_text("[mapp]\nexport_voxel_size_m = 0.03\n\n[build]\npixel_stride = 3\n")
    with pytest.raises(ConfigError, match="mapp"):
        BuildConfig.load(typo)
    wrong = tmp_path / "wrong.toml"
    wrong.write_text("[build]\npixel_strid = 3\n")
    with pytest.raises(ConfigError, match="pixel_strid"):
        BuildConfig.load(wrong)


def test_config_errors_are_one_line_per_problem_naming_file_and_key(tmp_path: Path) -> None:
    """A bad value, a typo and a removed table: one `error:` line per problem, each naming where the value came
    from (the file or the environment variable) and the key, without pydantic's multi-line dump and links."""
    bad = tmp_path / "c1.toml"
    bad.write_text("[depth]\nmax_depth_m = -1.0\nmin_depth_mm = 0.3\n\n[build]\npixel_stride = 0\n")
    for args in (("config", "--file", str(bad)), ("build", ".", "--out", str(tmp_path / "s"), "--config", str(bad))):
        out = _cli(*args)
        assert out.returncode == 1 and "Traceback" not in out.stderr, out.stderr
        assert "pydantic" not in out.stderr and "http" not in out.stderr, out.stderr
        lines = [line.strip() for line in out.stderr.strip().splitlines()]
        expected = {f"{bad}: depth.max_depth_m: Input should be greater than 0 (got -1.0)",
                    f"{bad}: depth.min_depth_mm: unknown setting"}
        if args[0] == "build":  # build reads the [build] table too, and reports both at once
            expected.add(f"{bad}: build.pixel_stride: Input should be greater than or equal to 1 (got 0)")
        assert {line.removeprefix("error: ") for line in lines} == expected, out.stderr
        assert lines[0].startswith("error: ")
    assert not (tmp_path / "s").exists()
    env = {**os.environ, "COLUMNS": "200", "DRIFTMAP_DEPTH__MAX_DEPTH_M": "far"}
    out = subprocess.run([sys.executable, "-m", "driftmap.cli", "config"], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 1 and out.stderr.strip().startswith(
        "error: environment DRIFTMAP_DEPTH__MAX_DEPTH_M: depth.max_depth_m: Input should be a valid number"), out.stderr
    removed = tmp_path / "pre.toml"
    removed.write_text("[preprocess]\nvoxel_size_m = 0.05\n")
    out = _cli("config", "--file", str(removed))
    assert out.returncode == 1 and "preprocess" in out.stderr and "not part of 'driftmap build'" in " ".join(out.stderr.split())


def test_config_shows_only_settings_that_take_effect() -> None:
    """The depth settings default to the source's own values (None), not a made-up range; there is no preprocess
    table (build does no per-frame processing); the map export keeps every point by default."""
    from driftmap.config import DriftmapConfig

    out = _cli("config", "--show")
    assert out.returncode == 0, out.stderr
    rows = {line.split("│")[1].strip(): line.split("│")[2].strip() for line in out.stdout.splitlines() if line.count("│") >= 3}
    assert rows["depth.min_depth_m"] == rows["depth.max_depth_m"] == rows["depth.depth_scale"] == "None"
    assert rows["map.export_voxel_size_m"] == "None" and not any(k.startswith("preprocess.") for k in rows)
    # [volume] takes effect in `export --mesh/--octomap/--grid2d` and in the demo's volumetric layers; [decide] in
    # `decide --config` (tests/test_decide.py)
    assert set(DriftmapConfig.model_fields) == {"depth", "map", "volume", "decide"}
    assert rows["volume.voxel_size_m"] == "None" and rows["decide.grasp_min_points"] == "30"


def test_demo_applies_the_depth_settings(tmp_path: Path) -> None:
    """DRIFTMAP_DEPTH__* reach the demo's build: with max_depth_m = 2 every stored point is nearer than 2 m (the
    synthetic log's own range reaches 8 m), and config.json records it."""
    from driftmap.store.frame_store import FrameStore

    env = {**os.environ, "COLUMNS": "200", "DRIFTMAP_DEPTH__MAX_DEPTH_M": "2.0"}
    out = subprocess.run([sys.executable, "-m", "driftmap.cli", "demo", "--frames", "4", "--out", str(tmp_path / "d")],
                         capture_output=True, text=True, timeout=300, env=env)
    assert out.returncode == 0, out.stderr
    with FrameStore.open(tmp_path / "d" / "store") as store:
        depths = np.concatenate([store.frame(int(i)).points_sensor[:, 2] for i in store.frame_ids])
    assert depths.max() < 2.0 and len(depths) > 1000
    assert json.loads((tmp_path / "d" / "config.json").read_text())["depth"]["max_depth_m"] == 2.0
