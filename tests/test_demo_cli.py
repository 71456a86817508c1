"""The demo and the command line: what a newcomer runs first."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
from PIL import Image

from driftmap import __version__
from driftmap.demo import run_demo


def _cli(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "COLUMNS": "200"}
    return subprocess.run([sys.executable, "-m", "driftmap.cli", *args], capture_output=True, text=True, timeout=300, env=env)


def test_version() -> None:
    out = _cli("--version")
    assert out.returncode == 0
    assert __version__ in out.stdout


def test_demo_library_outputs(tmp_path: Path) -> None:
    result = run_demo(tmp_path / "demo")
    summary = json.loads((tmp_path / "demo" / "summary.json").read_text())
    assert summary["n_frames"] == result.n_frames == 60
    # the doubled loop wall of the drifting map is measured, and the ground-truth map is single-walled
    assert summary["wall_spread_odometry_m"] > 2.5 * summary["wall_spread_ground_truth_m"]
    # loop closure makes it single again and brings the trajectory closer to the truth
    assert summary["loops_accepted"] >= 3
    assert summary["wall_spread_corrected_m"] < 1.5 * summary["wall_spread_ground_truth_m"]
    assert summary["ate_corrected_m"] < 0.7 * summary["ate_odometry_m"]
    assert Path(result.files["map_corrected_ply"]).stat().st_size > 100_000
    assert len(Path(result.files["trajectory_corrected_tum"]).read_text().splitlines()) == 61
    png = np.asarray(Image.open(result.files["top_view_png"]).convert("L"))
    assert png.shape[0] > 300 and png.shape[1] > 600
    assert png.std() > 10, "the top view should not be a blank image"
    for key in ("map_odometry_ply", "map_ground_truth_ply"):
        assert Path(result.files[key]).stat().st_size > 100_000
    assert json.loads((tmp_path / "demo" / "config.json").read_text())["depth"]["max_depth_m"] > 0


def test_demo_cli_prints_summary_and_results_path(tmp_path: Path) -> None:
    out = _cli("demo", "--frames", "8", "--out", str(tmp_path / "d"))
    assert out.returncode == 0, out.stderr
    assert "loop wall spread" in out.stdout
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
