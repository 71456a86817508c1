"""The eighth hostile-input trial's weak findings about ``perturb`` and ``synth`` (docs/bad-input.md), through the
command line: W7 a rotation step of 1e9 deg accepted; W8 synth messages naming a frame count the user never gave, a
2-frame log written silently from ``--speed-m-per-s 1e9`` / ``--period-s 100``, a yaw drift of 1e9 deg/m accepted."""

from __future__ import annotations

from pathlib import Path

import pytest
from cli_run import one_error, run_cli

from driftmap.diagnostics.perturb import PosePerturbation
from driftmap.errors import ConfigError
from driftmap.sources.synthetic import SyntheticLogConfig


@pytest.fixture()
def poses(tmp_path: Path) -> Path:
    path = tmp_path / "p.tum"
    path.write_text("0 0 0 0 0 0 0 1\n1 1 0 0 0 0 0 1\n2 2 0 0 0 0 0 1\n")
    return path


def test_t8_w7_perturb_bounds_the_rotation_step_naming_the_value_given(poses: Path, tmp_path: Path) -> None:
    """--step-deg 1e9,0,0 was accepted while --drift-deg-per-m is bounded to +-360: the rotation vector is at most
    360 deg long (a component of 1e300 does not overflow the length), the refusal names the text given."""
    out = tmp_path / "out.tum"
    for given, length in (("1e9,0,0", "1e+09 deg"), ("1e300,1e300,0", "1.41421e+300 deg"), ("300,300,0", "424.264 deg")):
        line = one_error(run_cli("perturb", poses, out, "--step-frame", 1, "--step-deg", given))
        assert line.startswith("error: --step-deg: a rotation step must be within 360 deg"), line
        assert f"got '{given}' ({length}" in line, line
        assert not out.exists()
    ok = run_cli("perturb", poses, out, "--step-frame", 1, "--step-deg", "0,0,90")
    assert ok.returncode == 0 and out.exists(), ok.stderr
    with pytest.raises(ConfigError, match=r"PosePerturbation.step_deg: the rotation step must be within 360 deg"):
        PosePerturbation(step_index=1, step_deg=(1e9, 0.0, 0.0))

    # the drift bounds report the value given, not a rounded one (a fix of the trial)
    for flag, value in (("--drift-percent-per-m", "100.0001"), ("--drift-deg-per-m", "360.0000001")):
        out2 = run_cli("perturb", poses, tmp_path / "d.tum", flag, value)
        assert out2.returncode == 2 and f"got {value}" in " ".join(out2.stderr.split()), out2.stderr
        assert not (tmp_path / "d.tum").exists()


@pytest.mark.parametrize(("args", "named", "total"), [
    (("--stationary-start", 19990), "--stationary-start 19990", "20,050 frames"),
    (("--stops", 1000, "--stop-frames", 100), "--stops 1000 x --stop-frames 100", "100,060 frames"),
    (("--turns", 100, "--turn-frames", 300, "--turn-deg-per-frame", 45),
     "--turns 100 x --turn-frames 300 x 2 (each turns back)", "60,060 frames"),
])
def test_t8_w8_synth_a_derived_count_over_the_limit_names_where_it_came_from(args: tuple, named: str, total: str,
                                                                             tmp_path: Path) -> None:
    """Stationary, stop and turn scans beyond the derived-count limit said 'n_frames: 60 frames leave no moving scan'
    (a 60 the user never gave): the count derived, what it is made of and the 20,000-frame limit are named."""
    line = one_error(run_cli("synth", tmp_path / "log", *args))
    assert " 60 frames" not in line and "leave no moving scan" not in line and "n_frames" not in line, line
    assert f"need {total}" in line and named in line and "59 moving scans" in line, line
    assert "more than the 20,000 a derived frame count may reach" in line and "--frames N" in line, line
    assert "fewer stationary, stop or turn scans" in line, line
    assert not (tmp_path / "log").exists()


def test_t8_w8_synth_refuses_a_derived_count_too_small_for_the_odometry(tmp_path: Path) -> None:
    """--speed-m-per-s 1e9 or --period-s 100 wrote a 2-frame log without a word: a derived count must leave at least
    20 moving scans; the refusal names the count, the path per scan and the option that set it."""
    for args, named in ((("--speed-m-per-s", "1e9"), "--speed-m-per-s 1e+09"), (("--period-s", 100), "--period-s 100"),
                        (("--scene", "street", "--speed-m-per-s", "1e9"), "--speed-m-per-s 1e+09"),
                        (("--speed-m-per-s", "1e9", "--stationary-start", 50), "--stationary-start 50")):
        line = one_error(run_cli("synth", tmp_path / "log", *args))
        assert "derive only" in line and named in line and "1 + 1 moving scan" in line, line
        assert "at least 20 moving scans" in line and "--period-s" in line, line
        assert not (tmp_path / "log").exists()
    assert "only 2 frames" in one_error(run_cli("synth", tmp_path / "log", "--period-s", 100))


def test_t8_w8_synth_a_room_log_under_40_frames_warns_about_the_depth_odometry(tmp_path: Path) -> None:
    """The room at 2 Hz (25 frames, as docs/synthetic-log.md's recipe) is written, with a warning that its depth
    camera turns too far between frames for the odometry (docs/fleet.md: below about 40 frames)."""
    out = run_cli("synth", tmp_path / "log", "--period-s", 0.5)
    assert out.returncode == 0, out.stderr
    err = " ".join(out.stderr.split())
    assert "warning: 25 frames" in err and "--period-s 0.5" in err and "below about 40 frames" in err, err
    assert "--lidar" in err and "25 frames, 0.5 s apart" in out.stdout


def test_t8_w8_synth_bounds_the_yaw_drift(tmp_path: Path) -> None:
    """--yaw-drift-deg-per-m 1e9 was accepted: within +-360 deg/m, as perturb --drift-deg-per-m."""
    out = run_cli("synth", tmp_path / "log", "--yaw-drift-deg-per-m", "1e9")
    err = " ".join(out.stderr.split())
    assert out.returncode == 2 and "--yaw-drift-deg-per-m" in err and "-360 .. 360 deg per m" in err, err
    assert not (tmp_path / "log").exists()
    with pytest.raises(ConfigError, match=r"yaw_drift_deg_per_m: must be finite and \[-360, 360\]"):
        SyntheticLogConfig(yaw_drift_deg_per_m=-1e9)
