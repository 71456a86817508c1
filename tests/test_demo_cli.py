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
    assert json.loads((out_dir / "config.json").read_text())["depth"]["max_depth_m"] > 0
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


def test_demo_without_a_loop_still_reports(tmp_path: Path) -> None:
    """8 frames never revisit anything: no loop closure, no corrected revision, and the demo says so."""
    out = _cli("demo", "--frames", "8", "--out", str(tmp_path / "d"))
    assert out.returncode == 0, out.stderr
    assert "loop wall spread" in out.stdout
    summary = json.loads((tmp_path / "d" / "summary.json").read_text())
    assert summary["n_frames"] == 8 and summary["loop_revision"] is None and summary["diagnosis_after"] is None
    assert Path(summary["files"]["report_md"]).exists()
    assert str((tmp_path / "d").resolve()) in out.stdout.replace("\n", "")


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
