"""Pairwise GICP (``driftmap.registration.pairwise``): the thin wrapper of small_gicp."""

from __future__ import annotations

import numpy as np
import pytest

from driftmap.registration.pairwise import MIN_ALIGN_POINTS, PreparedCloud, register_prepared


def test_a_cloud_too_small_to_register_fits_nothing_and_prints_nothing(capfd: pytest.CaptureFixture[str]) -> None:
    """Hostile trial 17: small_gicp printed "target point cloud is too small" on the console (10 or fewer points);
    such a fit constrains nothing. The wrapper returns an unconverged result at the start pose, quietly."""
    rng = np.random.default_rng(0)
    big = PreparedCloud(rng.uniform(-1, 1, (3000, 3)), 1)
    tiny = PreparedCloud(rng.uniform(-1, 1, (MIN_ALIGN_POINTS - 1, 3)), 1)
    start = np.eye(4)
    start[:3, 3] = [0.01, 0.0, 0.0]
    for target, source in ((big, tiny), (tiny, big)):
        result = register_prepared(target, source, start, voxel_size_m=0.01)
        assert not result.converged and result.fitness == 0.0
        np.testing.assert_array_equal(result.T_target_source, start)
        assert not np.any(result.information_6x6)
    out, err = capfd.readouterr()
    assert "too small" not in out + err
    # a cloud registered onto itself from a small offset comes back (the guard leaves real fits alone)
    faces = []
    for k in range(3):
        for side in (-1.0, 1.0):
            face = rng.uniform(-1, 1, (3000, 3))
            face[:, k] = side
            faces.append(face)
    cube = PreparedCloud(np.concatenate(faces), 1)
    result = register_prepared(cube, cube, start, voxel_size_m=0.05, max_correspondence_m=0.2)
    assert result.converged and result.fitness > 0.99
    assert np.linalg.norm(result.T_target_source[:3, 3]) < 1e-3
