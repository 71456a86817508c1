"""Issue 22: every number is checked where it enters -- on the command line (one callback for every number option,
one check of thread counts), in config files (no inf / nan in any settings model) and in the library's
perturbation harness -- and a refused number leaves nothing behind (no store, no output file)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from driftmap.config import check_threads, max_threads
from driftmap.errors import ConfigError

LOG = Path(__file__).resolve().parents[1] / "datasets" / "synthetic-loop"


def _cli(*args: object) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "driftmap.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=300, env={**os.environ, "COLUMNS": "200"})


def _error_line(out: subprocess.CompletedProcess, rc: int) -> str:
    assert out.returncode == rc, (out.returncode, out.stdout, out.stderr)
    assert "Traceback" not in out.stderr and "Segmentation" not in out.stderr, out.stderr
    return " ".join(out.stderr.split())


def test_absurd_thread_counts_are_refused_before_a_store_is_made(tmp_path: Path) -> None:
    """Case 3: `build --threads 100000` segfaulted (rc 139) and left an empty store."""
    out = tmp_path / "s"
    line = _error_line(_cli("build", LOG, "--out", out, "--threads", "100000", "--frames", "0:3"), 1)
    assert "--threads" in line and "100000" in line and f"at most {max_threads()}" in line, line
    assert not out.exists()
    assert check_threads(max_threads()) == max_threads()
    for bad in (0, -1, max_threads() + 1, 2.5, True):
        with pytest.raises(ConfigError, match="thread"):
            check_threads(bad)  # type: ignore[arg-type]


def test_a_config_file_cannot_ask_for_absurd_threads_or_infinite_lengths(tmp_path: Path) -> None:
    from driftmap.pipeline.build import BuildConfig

    for table, why in (("[build]\nnum_threads = 100000\n", "more than this machine"),
                       ("[build.odometry]\nvoxel_size_m = inf\n", "finite"),
                       ("[build.loop_closure]\nmax_rmse_m = nan\n", "finite")):
        cfg = tmp_path / "c.toml"
        cfg.write_text(table)
        with pytest.raises(ConfigError, match=why):
            BuildConfig.load(cfg)
        line = _error_line(_cli("build", LOG, "--out", tmp_path / "s", "--config", cfg, "--frames", "0:3"), 1)
        assert "c.toml" in line or why in line, line
        assert not (tmp_path / "s").exists()


@pytest.mark.parametrize("args", [
    ("perturb", LOG / "groundtruth.txt", "{tmp}/p.txt", "--drift-percent-per-m", "nan"),
    ("perturb", LOG / "groundtruth.txt", "{tmp}/p.txt", "--drift-deg-per-m", "inf"),
    ("build", LOG, "--out", "{tmp}/s", "--max-dt-ms", "nan", "--frames", "0:3"),
    ("build", LOG, "--out", "{tmp}/s", "--depth-scale", "inf", "--frames", "0:3"),
    ("synth", "{tmp}/log", "--period-s", "inf"),
    ("synth", "{tmp}/log", "--period-s", "nan"),
    ("correct", "{tmp}/st", "--max-dt-ms", "nan", "--poses", LOG / "groundtruth.txt"),
])
def test_every_number_option_refuses_nan_and_inf(args: tuple, tmp_path: Path) -> None:
    """Case 5: `perturb --drift-percent-per-m nan` was a LinAlgError traceback; click reads 'nan' and 'inf' as floats,
    so every number option goes through one finite-number check (a usage error naming the flag, exit 2)."""
    out = _cli(*(str(a).format(tmp=tmp_path) for a in args))
    line = _error_line(out, 2)
    flag = next(a for a in args if str(a).startswith("--") and a not in ("--out", "--frames"))
    # trial 17: a range option said "greater than or equal to 0" of nan (click's min= ran before the finite check)
    assert flag in line and "finite" in line, line
    assert not any(tmp_path.iterdir())


def test_perturbation_vectors_and_directions_are_checked_in_the_library() -> None:
    from driftmap.diagnostics.perturb import PosePerturbation, parse_vector

    with pytest.raises(ConfigError, match="finite"):
        parse_vector("nan,0,0", "--step-m")
    with pytest.raises(ConfigError, match="finite"):
        PosePerturbation(drift_percent_per_m=float("inf"))
    with pytest.raises(ConfigError, match="non-zero direction"):
        PosePerturbation(drift_percent_per_m=1.0, drift_direction=(0.0, 0.0, 0.0))
    assert PosePerturbation(drift_deg_per_m=0.1).drift_axis == (0.0, 0.0, 1.0)


def test_export_refuses_an_infinite_voxel_and_a_blank_frame_selection(tmp_path: Path) -> None:
    """Case 11: `export --voxel-size-m inf` wrote a 1-point map; `--frames " "` meant every frame."""
    line = _error_line(_cli("build", LOG, "--out", tmp_path / "s", "--frames", " "), 1)
    assert "--frames" in line and "empty" in line, line
    assert not (tmp_path / "s").exists()
    assert _cli("build", LOG, "--out", tmp_path / "s", "--frames", "0:3", "--no-loop-closure",
                "--poses-from-source").returncode == 0
    line = _error_line(_cli("export", tmp_path / "s", "--map", tmp_path / "m.ply", "--voxel-size-m", "inf"), 2)
    assert "--voxel-size-m" in line and "finite" in line, line
    assert not (tmp_path / "m.ply").exists()
