"""Hostile trial 17's findings, each through the path the user took (docs/bad-input.md, trial 17)."""

from __future__ import annotations

import json
from pathlib import Path

from cli_run import run_cli


def _ok(out) -> None:  # noqa: ANN001 - a CompletedProcess
    assert out.returncode == 0, out.stderr


def test_t17_b3_diagnose_checks_ground_truth_against_the_frames(tmp_path: Path) -> None:
    """B3: `diagnose --gt` with the store's own poses written quaternion-first (w x y z) reported ATE 0.00 cm, RPE
    34 cm / 19 deg, without a word, while `correct` warned on the same file. The ground truth is now checked against
    the frames as a pose file is, and a file that moves them as they do not move is named; the right file is not."""
    log = tmp_path / "L"
    _ok(run_cli("synth", log, "--lidar", "--frames", 20, "--seed", 7))
    store = tmp_path / "st"
    _ok(run_cli("build", log, "--sensor", "lidar", "--poses", log / "groundtruth.txt", "--no-loop-closure",
                "--out", store))
    _ok(run_cli("export", store, "--trajectory", tmp_path / "own.txt"))
    rows = [line.split() for line in (tmp_path / "own.txt").read_text().splitlines()
            if line.strip() and not line.startswith("#")]
    (tmp_path / "wxyz.txt").write_text("".join(" ".join([r[0], *r[1:4], r[7], *r[4:7]]) + "\n" for r in rows))
    wrong = run_cli("diagnose", store, "--json", tmp_path / "w.json", "--gt", tmp_path / "wxyz.txt")
    _ok(wrong)
    said = " ".join(wrong.stderr.split())
    assert "do not move the way the frames do" in said and "(--gt)" in said and "quaternion order" in said, said
    right = run_cli("diagnose", store, "--json", tmp_path / "r.json", "--gt", tmp_path / "own.txt")
    _ok(right)
    assert "do not move the way the frames do" not in right.stderr, right.stderr
    assert json.loads((tmp_path / "r.json").read_text())["trajectory"]["ate_rmse_m"] < 1e-6
