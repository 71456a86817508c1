"""What caused each double wall: a pose error splits the frames by time, a depth error by viewing range, with
frames interleaved in time (diagnostics/causes.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from driftmap.diagnostics import perturb
from driftmap.diagnostics.report import diagnose_store
from driftmap.frame import Frame, PoseEstimate, SensorKind
from driftmap.store.frame_store import FrameStore

HALF_M = 3.0


def _scan(rng: np.random.Generator, T: np.ndarray, n: int, range_scale: float) -> np.ndarray:
    """Points of a box room (walls at +-3 m, floor and ceiling) seen from ``T``, ranges scaled by ``range_scale``."""
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    dw = d @ T[:3, :3].T
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.min(np.where(dw != 0, (np.sign(dw) * HALF_M - T[:3, 3]) / dw, np.inf), axis=1)
    t = (t + rng.normal(0, 0.003, n)) * range_scale
    return (d * t[:, None]).astype(np.float32)


def _store(path: Path, origins: np.ndarray, *, range_scale: float = 1.0, poses: np.ndarray | None = None) -> FrameStore:
    rng = np.random.default_rng(11)
    true = np.tile(np.eye(4), (len(origins), 1, 1))
    true[:, :3, 3] = origins
    placed = true if poses is None else poses
    with FrameStore.create(path) as store:
        for k in range(len(origins)):
            store.append(Frame(frame_id=k, stamp_ns=k * 100_000_000, sensor_name="lidar", sensor_kind=SensorKind.LIDAR,
                               points_sensor=_scan(rng, true[k], 20000, range_scale), pose=PoseEstimate(placed[k])))
    return FrameStore.open(path)


def _circle(n: int, radius: np.ndarray | float) -> np.ndarray:
    a = np.linspace(0, 2 * np.pi * 1.1, n)
    return np.stack([radius * np.cos(a), radius * np.sin(a), np.zeros(n)], axis=1)


def test_a_pose_step_is_a_pose_error_between_the_frames_before_and_after(tmp_path: Path) -> None:
    origins = _circle(40, 1.2)
    true = np.tile(np.eye(4), (40, 1, 1))
    true[:, :3, 3] = origins
    stepped = perturb.translation_step(true, 20, (0.04, 0.0, 0.0))
    d = diagnose_store(_store(tmp_path / "s", origins, poses=stepped))
    causes = [c for c, r in zip(d.causes, d.double_walls.regions) if r.n_voxels >= 2]
    assert causes, "the 4 cm step must double the x walls"
    assert all(c.cause == "pose" for c in causes), [(c.cause, c.explanation) for c in causes]
    assert all(c.evidence["time_step_between_frames"] == [19, 20] for c in causes)
    assert all(c.evidence["r2_time_step"] > c.evidence["r2_range"] for c in causes)
    data = d.to_json()["double_wall"]
    assert data["causes"].get("pose", 0) >= len(causes) and data["regions"][0]["cause"] == "pose"


def test_a_depth_scale_error_seen_from_two_ranges_in_turn_is_a_depth_error_not_drift(tmp_path: Path) -> None:
    """Every other frame 1.5 m from the -x wall, the others 1.2 m from the +x wall; ranges 3 % long. The walls' layers are the
    near and the far views, their frames interleaved in time: no step in time explains them."""
    n = 40
    rng = np.random.default_rng(2)
    origins = np.where((np.arange(n) % 2 == 0)[:, None], [[-1.5, 0.0, 0.0]], [[1.8, 0.0, 0.0]])
    origins = origins + rng.uniform(-0.1, 0.1, (n, 3)) * [1, 1, 0]
    d = diagnose_store(_store(tmp_path / "s", origins, range_scale=1.03))
    big = [(c, r) for c, r in zip(d.causes, d.double_walls.regions) if r.n_voxels >= 2]
    assert big, "the near and far views must double the walls"
    kinds = [c.cause for c, _ in big]
    assert kinds.count("depth_range") >= 0.7 * len(kinds), [(c.cause, c.explanation) for c, _ in big]
    for c, _ in big:
        if c.cause == "depth_range":
            assert c.evidence["offset_per_m_range"] == pytest.approx(0.03, rel=0.5)  # 3 cm per m of range
            assert c.evidence["r2_range"] > c.evidence["r2_time_step"]
