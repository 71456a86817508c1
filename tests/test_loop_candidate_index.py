"""Loop candidates from a KD-tree over the keyframe positions (issue 27: costs that grow no faster than the log)
equal the all-pairs search they replace, and the flagged-stretch test over sorted rows equals a scan of them."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from driftmap.registration.loops import (
    Keyframe,
    LoopClosureConfig,
    _gap_positions,
    _older,
    _viewing_angle_deg,
    proximity_candidates,
    untrusted_between,
)


def _all_pairs(keyframes: list[Keyframe], config: LoopClosureConfig) -> list[tuple[int, int]]:
    """The former all-pairs search: per keyframe, every older one's distance."""
    pos = np.array([k.T_world_sensor[:3, 3] for k in keyframes])
    at = _gap_positions(keyframes, config)
    pairs = []
    for j in range(len(keyframes)):
        older = _older(at, j, config)
        if older.size == 0:
            continue
        d = np.linalg.norm(pos[older] - pos[j], axis=1)
        ok = [i for i in older[d < config.proximity_radius_m]
              if _viewing_angle_deg(keyframes[i].T_world_sensor, keyframes[j].T_world_sensor)
              < config.proximity_max_angle_deg]
        ok.sort(key=lambda i: np.linalg.norm(pos[i] - pos[j]))
        pairs += [(int(i), j) for i in ok[: config.max_candidates_per_keyframe]]
    return pairs


def _keyframes(seed: int, n: int) -> list[Keyframe]:
    """A wandering path that comes back on itself (loops), with headings that turn, 2 Hz keyframes; some positions
    repeat exactly (a robot standing still) so that ties in distance occur."""
    rng = np.random.default_rng(seed)
    steps = rng.normal(0.0, 0.4, (n, 3)) * [1, 1, 0.05]
    pos = np.cumsum(steps, axis=0) % 6.0  # folded into a 6 m box: many revisits
    pos[rng.random(n) < 0.1] = pos[0]
    yaw = np.cumsum(rng.normal(0.0, 0.5, n))
    out = []
    for k in range(n):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("xyz", [np.pi / 2, 0.0, yaw[k]]).as_matrix()  # camera z looks sideways
        T[:3, 3] = pos[k]
        out.append(Keyframe(k * 5, k, T, np.zeros((0, 3)), np.zeros(8), None, k * 500_000_000))  # type: ignore[arg-type]
    return out


@pytest.mark.parametrize("seed", range(6))
def test_proximity_candidates_equal_the_all_pairs_search(seed: int) -> None:
    keyframes = _keyframes(seed, 300)
    for config in (LoopClosureConfig(), LoopClosureConfig(proximity_radius_m=0.5, max_candidates_per_keyframe=3),
                   LoopClosureConfig(min_gap_frames=40, proximity_max_angle_deg=90.0)):
        got = proximity_candidates(keyframes, config)
        assert got == _all_pairs(keyframes, config)
        assert got, "the path revisits places: there must be candidates to compare"


def test_untrusted_between_equals_a_scan_of_the_flagged_rows() -> None:
    keyframes = _keyframes(1, 200)
    rng = np.random.default_rng(5)
    flagged = {int(r): int(r) * 5 for r in rng.choice(200, 25, replace=False)}
    config = LoopClosureConfig()
    rows = np.array(sorted(flagged), dtype=np.int64)
    for _ in range(200):
        i, j = sorted(rng.choice(200, 2, replace=False))
        lo = keyframes[i].index - config.submap_radius_frames
        hi = keyframes[j].index + config.submap_radius_frames
        want = [fid for row, fid in sorted(flagged.items()) if lo <= row <= hi]
        assert untrusted_between(keyframes[i], keyframes[j], flagged, config) == want
        assert untrusted_between(keyframes[i], keyframes[j], flagged, config, rows) == want
