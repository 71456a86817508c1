"""The failure modes of real LiDAR logs as synthetic regressions with ground truth (docs/synthetic-log.md): a
stationary start, stops, in-place turns of 45-50 deg per scan, 2 Hz scans -- on the room and on the street. The
default build of each must stay within 2x the ATE of the same log without the difficulty."""

from __future__ import annotations


import numpy as np
import pytest
from cli_run import run_cli

from driftmap.diagnostics.trajectory_metrics import trajectory_errors
from driftmap.pipeline.build import build
from driftmap.sources.synthetic import SyntheticLog, SyntheticLogConfig, generate_synthetic_log
from driftmap.store.frame_store import FrameStore

ROOM = dict(lidar=True, speed_m_per_s=SyntheticLogConfig().default_speed_m_per_s(), width=80, height=60, fx=65.625,
            fy=65.625, cx=39.5, cy=29.5)
STREET_SPEED = dict(speed_m_per_s=SyntheticLogConfig.street().default_speed_m_per_s())

MODES = {
    "room": lambda: SyntheticLogConfig(**ROOM),
    "room_stationary_start": lambda: SyntheticLogConfig(stationary_start_frames=23, **ROOM),
    "room_stops": lambda: SyntheticLogConfig(stops=3, stop_frames=10, **ROOM),
    "room_turns_45deg": lambda: SyntheticLogConfig(turns_in_place=2, turn_in_place_deg_per_frame=45.0,
                                                   turn_in_place_frames=8, **ROOM),
    "room_2hz": lambda: SyntheticLogConfig(frame_period_ns=500_000_000, **ROOM),
    "street": lambda: SyntheticLogConfig.street(**STREET_SPEED),
    "street_stationary_start": lambda: SyntheticLogConfig.street(stationary_start_frames=23, **STREET_SPEED),
    "street_stops": lambda: SyntheticLogConfig.street(stops=3, stop_frames=10, **STREET_SPEED),
    "street_turns_50deg": lambda: SyntheticLogConfig.street(turn_in_place_at=(0.25, 0.6), turn_in_place_deg_per_frame=50.0,
                                                            turn_in_place_frames=1, **STREET_SPEED),
    "street_2hz": lambda: SyntheticLogConfig.street(frame_period_ns=500_000_000, **STREET_SPEED),
    "room_rosette": lambda: SyntheticLogConfig(lidar_pattern="rosette", **ROOM),
    "street_rosette": lambda: SyntheticLogConfig.street(lidar_pattern="rosette", **STREET_SPEED),
    # the same 70 deg cone, every scan the same curve: the rosette's plain log (its field of view, not its pattern)
    "room_cone": lambda: SyntheticLogConfig(lidar_pattern="rosette", lidar_rosette_k=10.0, **ROOM),
    "street_cone": lambda: SyntheticLogConfig.street(lidar_pattern="rosette", lidar_rosette_k=10.0, **STREET_SPEED),
}


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory):
    """``name -> (final ATE m, revision-0 ATE m, build summary)`` of the default build of each log, built on demand."""
    root = tmp_path_factory.mktemp("modes")
    cache: dict[str, tuple[float, float, dict]] = {}

    def get(name: str) -> tuple[float, float, dict]:
        if name not in cache:
            log = generate_synthetic_log(root / name, MODES[name]())
            result = build(log, root / f"{name}.store", source_options={"sensor": "lidar"})
            gt = SyntheticLog(log, sensor="lidar").ground_truth()
            store = FrameStore.open(root / f"{name}.store")
            truth = gt.poses[np.searchsorted(gt.frame_ids, store.frame_ids)]
            cache[name] = (trajectory_errors(store.poses(), truth).ate_rmse_m,
                           trajectory_errors(store.poses(0), truth).ate_rmse_m, result.to_json())
            for f in (root / name / "lidar").glob("*"):  # the scans are not needed again (a street log is 124 MB)
                f.unlink()
        return cache[name]

    return get


# measured (final ATE, cm; the point-to-plane refinement on): room 0.23, stationary start 0.22, stops 0.21, turns
# 0.26, 2 Hz 0.23; street 0.50, stationary start 0.48, stops 0.48, turns 0.49, 2 Hz 0.33 (without the refinement:
# street 3.27, 3.60, 4.48, 5.89, 0.70; before this changes: street stationary start 11.8, turns 2352 (lost),
# 2 Hz 7.9 (no loop closed); room turns 1.2)
@pytest.mark.slow
@pytest.mark.parametrize("mode", ["room_stationary_start", "room_stops", "room_turns_45deg", "room_2hz",
                                  "street_stationary_start", "street_stops", "street_turns_50deg", "street_2hz"])
def test_lidar_failure_modes_stay_within_2x_of_the_plain_log(built, mode: str) -> None:
    plain = mode.split("_")[0]
    base, _, _ = built(plain)
    ate, _, summary = built(mode)
    assert ate <= 2.0 * base, f"{mode}: ATE {100 * ate:.2f} cm, plain {plain} {100 * base:.2f} cm"
    assert summary["tracking"]["flagged"] == []


@pytest.mark.slow
def test_in_place_turns_are_recovered_not_lost_and_2hz_closes_its_loop(built) -> None:
    _, _, turns = built("room_turns_45deg")
    recovered = turns["tracking"]["recovered"]
    assert recovered and all(r["status"] == "recovered" for r in recovered)
    _, ate0, street_2hz = built("street_2hz")
    ate, _, _ = built("street_2hz")
    # keyframe clouds of the scans within 0.3 s: single scans at 2 Hz, so keyframes fall into the 22 m revisit
    assert street_2hz["loop_closure_config"]["submap_radius_frames"] == 0 and street_2hz["loops_accepted"] > 0
    assert ate < ate0
    _, _, street = built("street")
    assert street["loop_closure_config"]["submap_radius_frames"] == 3  # 10 Hz: 7-scan keyframe clouds, as before


# measured (final ATE, cm): rosette room 1.8 / repetitive cone 45, street 6.31 / 4.34 (before the weak directions were
# bridged by the prediction: rosette room 40.1, 4 scans facing one wall slid 25 cm sideways each; before the
# point-to-plane refinement: rosette room 100, street 548 with 9 scans lost). Against the spinning LiDAR (0.23 /
# 0.50 cm) the cone's 70 deg field of view costs more than its pattern: facing a wall, sideways motion is barely
# constrained, and the frames where it is not at all are reported ``degenerate``.
@pytest.mark.slow
@pytest.mark.parametrize("scene", ["room", "street"])
def test_a_non_repetitive_rosette_tracks_within_2x_of_the_same_cone_repeating(built, scene: str) -> None:
    cone, _, _ = built(f"{scene}_cone")
    ate, ate0, summary = built(f"{scene}_rosette")
    assert ate <= 2.0 * cone, f"{scene} rosette: ATE {100 * ate:.2f} cm, repetitive cone {100 * cone:.2f} cm"
    assert summary["tracking"]["flagged"] == []
    assert summary["odometry_config"]["kiss_refine_plane"] is True
    if scene == "street":
        assert ate <= 0.10 and ate0 <= 0.15  # 6.3 / 8.5 cm (548 cm before the refinement)
    else:  # facing one wall, a few scans leave the sideways motion free: bridged by the prediction and reported
        assert ate <= 0.05 and ate0 <= 0.05  # 1.8 / 2.2 cm (40 / 38 cm without the bridge)
        degenerate = summary["tracking"]["degenerate"]
        assert 1 <= len(degenerate) <= 10 and summary["tracking"]["by_status"]["degenerate"] == len(degenerate)
        assert all("replaced by the prediction" in d["reason"] for d in degenerate)
        info = run_cli("info", summary["store"])  # the user sees them too
        assert info.returncode == 0, info.stderr
        row = next(line for line in info.stdout.splitlines() if "frames degenerate" in line)
        assert all(str(d["frame_id"]) in row for d in degenerate)
