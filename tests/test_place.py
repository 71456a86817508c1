"""LiDAR place recognition (Scan Context) on real KITTI 00 scans: invariant to the sensor's yaw, which it
recovers, and growing with the distance between two scans' places."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from driftmap.errors import ConfigError
from driftmap.registration.place import scan_context, scan_context_distance, yaw_guess
from driftmap.sources.kitti import KittiOdometry


@pytest.fixture(scope="module")
def kitti(kitti_dir: Path) -> tuple[list[np.ndarray], np.ndarray]:
    source = KittiOdometry(kitti_dir)
    scans = [frame.points_sensor for frame in source]
    gt = source.ground_truth()
    assert gt is not None and len(scans) == 16
    return scans, gt.poses


@pytest.mark.parametrize("yaw_deg", [37.0, -100.0, 180.0])
def test_a_turned_sensor_gives_the_same_context_and_its_yaw(kitti: tuple[list[np.ndarray], np.ndarray], yaw_deg: float) -> None:
    scans, _ = kitti
    R = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
    a = scan_context(scans[4])
    b = scan_context(scans[4] @ R)  # the same place, the sensor turned by +yaw_deg (points in its frame: R^T p)
    distance, yaw = scan_context_distance(a, b)
    assert distance < 0.1  # measured 0.00-0.08: points move between bins by up to one sector width
    sector_deg = 360.0 / a.n_sectors
    assert abs(math.remainder(math.degrees(yaw) - yaw_deg, 360.0)) <= sector_deg
    # the guess turns b's points back onto a's: yaw_guess(yaw) is T_a_b
    back = (scans[4] @ R) @ yaw_guess(yaw)[:3, :3].T
    np.testing.assert_allclose(np.linalg.norm(back - scans[4], axis=1).max() / np.linalg.norm(scans[4], axis=1).max(),
                               0.0, atol=2 * math.sin(math.radians(sector_deg) / 2))
    np.testing.assert_allclose(a.ring_key, b.ring_key, atol=0.1)  # the ring key ignores the yaw


def test_the_distance_grows_with_the_distance_between_places(kitti: tuple[list[np.ndarray], np.ndarray]) -> None:
    scans, poses = kitti
    first = scan_context(scans[0])
    apart_m = np.linalg.norm(poses[:, :3, 3] - poses[0, :3, 3], axis=1)
    d = np.array([scan_context_distance(first, scan_context(s))[0] for s in scans])
    assert d[0] == 0.0 and apart_m[-1] > 10.0
    # measured 0.09 at 0.9 m, 0.24 at 4 m, 0.30 at 8 m, 0.40 at 12.9 m: rank correlation with the distance
    rho = np.corrcoef(np.argsort(np.argsort(apart_m)), np.argsort(np.argsort(d)))[0, 1]
    assert rho > 0.95, (apart_m.round(1), d.round(3))
    assert d[1] < 0.15 and d[-1] > 0.3


def test_too_few_points_match_nothing() -> None:
    empty = scan_context(np.zeros((5, 3)))
    assert empty.is_empty and not empty.ring_key.any()
    full = scan_context(np.random.default_rng(0).uniform(-20, 20, (2000, 3)))
    assert scan_context_distance(empty, full) == (1.0, 0.0)
    with pytest.raises(ConfigError, match="shapes"):
        scan_context_distance(full, scan_context(np.zeros((5, 3)), n_sectors=30))
    with pytest.raises(ConfigError, match="positive"):
        scan_context(np.zeros((5, 3)), max_radius_m=0.0)
