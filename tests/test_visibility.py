"""The free-space conflict between two clouds (driftmap.registration.visibility; docs/merge.md): points in front of,
on and behind the surface a viewer measured in their direction, whatever way the viewer looks, checked against a
brute-force reference on random clouds."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from driftmap.errors import ConfigError
from driftmap.registration.visibility import direction_cells, free_space_conflict


def _wall(distance_m: float, axis: int, sign: float, n: int = 40, half_m: float = 1.0) -> np.ndarray:
    """An ``n x n`` grid of points on the plane ``x[axis] = sign * distance_m``."""
    u, v = np.meshgrid(np.linspace(-half_m, half_m, n), np.linspace(-half_m, half_m, n))
    p = np.zeros((n * n, 3))
    p[:, axis] = sign * distance_m
    p[:, (axis + 1) % 3], p[:, (axis + 2) % 3] = u.ravel(), v.ravel()
    return p


@pytest.mark.parametrize(("axis", "sign"), [(2, 1.0), (0, 1.0), (0, -1.0), (1, -1.0), (2, -1.0)])
def test_a_wall_in_front_on_and_behind_the_viewers_wall_in_every_look_direction(axis: int, sign: float) -> None:
    """A depth camera looks along +z, a LiDAR all round: a wall at 3 m seen by the viewer; another cloud's wall at
    1.5 m lies in the viewer's free space (all conflicting), at 3.02 m on it (agreeing), at 5 m behind it (occluded);
    points off the viewer's rays are not counted."""
    viewer = _wall(3.0, axis, sign, n=120)
    front = free_space_conflict(viewer, _wall(1.5, axis, sign, half_m=0.4), margin_m=0.1)
    on = free_space_conflict(viewer, _wall(3.02, axis, sign), margin_m=0.1)
    behind = free_space_conflict(viewer, _wall(5.0, axis, sign, half_m=1.5), margin_m=0.1)
    assert front.conflicting == 1600 and front.agreeing == 0 and front.share == 1.0
    assert on.conflicting == 0 and on.agreeing >= 1500 and on.share == 0.0
    assert behind.conflicting == 0 and behind.agreeing == 0 and behind.occluded >= 1500 and behind.share == 0.0
    elsewhere = free_space_conflict(viewer, _wall(3.0, (axis + 1) % 3, sign), margin_m=0.1)
    assert elsewhere.conflicting + elsewhere.agreeing + elsewhere.occluded == 0


def test_the_margin_grows_with_range_and_the_nearest_point_bounds_a_cell() -> None:
    """A point 0.3 m in front of a wall at 10 m is within 5 % of the range (agreeing); at 2 m it conflicts. A cell
    holding a near and a far viewer point takes the near one: the far side's free space is never counted."""
    for distance, expected in ((10.0, 0), (2.0, 1)):
        viewer = np.array([[0.0, 0.0, distance]])
        other = np.array([[0.0, 0.0, distance - 0.3]])
        assert free_space_conflict(viewer, other, margin_m=0.1).conflicting == expected
    viewer = np.array([[0.0, 0.0, 1.0], [0.001, 0.0, 8.0]])
    assert free_space_conflict(viewer, np.array([[0.0, 0.0, 4.0]]), margin_m=0.1).occluded == 1


def test_degenerate_input() -> None:
    """Points at the sensor's origin have no direction; empty clouds judge nothing; bad settings are refused."""
    keys, r = direction_cells(np.zeros((3, 3)), 1.0)
    assert (keys == -1).all() and (r == 0).all()
    assert free_space_conflict(np.zeros((0, 3)), _wall(2.0, 2, 1.0), margin_m=0.1).share == 0.0
    assert free_space_conflict(_wall(2.0, 2, 1.0), np.zeros((0, 3)), margin_m=0.1).share == 0.0
    with pytest.raises(ConfigError, match="bin_deg"):
        free_space_conflict(_wall(2.0, 2, 1.0), _wall(2.0, 2, 1.0), margin_m=0.1, bin_deg=0.0)


def _reference(viewer: np.ndarray, other: np.ndarray, margin_m: float, bin_deg: float) -> tuple[int, int, int]:
    """The same count point by point: the cube face of the largest coordinate, the cell of the other two divided by
    it, the nearest viewer point per cell."""
    n = math.ceil(2.0 / math.tan(math.radians(bin_deg)))

    def cell(p: np.ndarray) -> tuple[int, int, int]:
        a = int(np.argmax(np.abs(p)))
        u, v = p[(a + 1) % 3] / abs(p[a]), p[(a + 2) % 3] / abs(p[a])
        return (2 * a + int(p[a] < 0), min(n - 1, int((u + 1) / 2 * n)), min(n - 1, int((v + 1) / 2 * n)))

    nearest: dict[tuple[int, int, int], float] = {}
    for p in viewer:
        c = cell(p)
        nearest[c] = min(nearest.get(c, math.inf), float(np.linalg.norm(p)))
    counts = [0, 0, 0]
    for p in other:
        c = cell(p)
        if c not in nearest:
            continue
        r, bound = float(np.linalg.norm(p)), nearest[c]
        m = max(margin_m, 0.05 * bound)
        counts[0 if r < bound - m else 2 if r > bound + m else 1] += 1
    return counts[0], counts[1], counts[2]


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), bin_deg=st.sampled_from([0.5, 1.0, 3.0, 10.0]))
def test_agrees_with_a_point_by_point_reference(seed: int, bin_deg: float) -> None:
    rng = np.random.default_rng(seed)
    viewer = rng.normal(size=(300, 3)) * rng.uniform(0.5, 5.0, size=(300, 1))
    other = np.concatenate([viewer[:100] * rng.uniform(0.5, 1.5, size=(100, 1)), rng.normal(size=(100, 3)) * 3.0])
    got = free_space_conflict(viewer, other, margin_m=0.05, bin_deg=bin_deg)
    assert (got.conflicting, got.agreeing, got.occluded) == _reference(viewer, other, 0.05, bin_deg)
