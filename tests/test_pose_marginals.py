"""Pose uncertainty from the pose graph (issue 25): GTSAM's marginal covariances of the optimised keyframes, kept
with the loop-closure revision in the store, looked up per frame through the revision's ancestry, and propagated to
a decision's evidence point."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

from driftmap.decisions.evidence import DecisionContext
from driftmap.errors import StoreError
from driftmap.frame import Frame, PoseEstimate, SensorKind
from driftmap.posegraph import PoseGraph
from driftmap.store.frame_store import FrameStore
from driftmap.store.revision import Revision


def _T(x: float = 0.0, y: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:2, 3] = x, y
    return T


def test_marginals_of_a_chain_grow_as_a_random_walk() -> None:
    """Translation-only odometry of sigma 1 cm per step (rotation held stiff): node k is sqrt(k) cm uncertain on
    every axis, on top of the prior's 0.1 mm."""
    graph = PoseGraph()
    for k in range(6):
        graph.add_node(k, _T(k))
    graph.add_prior(0, _T(0), np.diag([1e8] * 6))
    for k in range(5):
        graph.add_odometry(k, k + 1, _T(1), np.diag([1e4] * 3 + [1e14] * 3))
    cov = graph.marginal_covariances({k: _T(k) for k in range(6)})
    for k in range(6):
        expected = 1e-8 + k * 1e-4
        np.testing.assert_allclose(np.diag(cov[k])[:3], expected, rtol=1e-3)
        assert np.all(np.diag(cov[k])[3:] < 1.1e-8)  # [translation, rotation] order: the rotation is the prior's
        np.testing.assert_allclose(cov[k], cov[k].T, atol=1e-15)


def test_a_revision_keeps_its_covariances_bit_for_bit() -> None:
    cov = np.diag([1e-4, 2e-4, 3e-4, 1e-6, 2e-6, 3e-6])
    cov[0, 1] = cov[1, 0] = 1e-5 / 3
    rev = Revision(1, 0, "loop_closure", 5, set_directly={3: _T(1), 4: _T(2)}, covariances={3: cov})
    data = json.loads(json.dumps(rev.to_json()))
    back = Revision.from_json(data)
    assert back == rev and back.covariances[3].tobytes() == rev.covariances[3].tobytes()
    plain = Revision(1, 0, "loop_closure", 5, set_directly={3: _T(1)})
    assert "covariances" not in plain.to_json() and Revision.from_json(plain.to_json()).covariances == {}
    assert back != Revision(1, 0, "loop_closure", 5, set_directly={3: _T(1), 4: _T(2)})
    with pytest.raises(StoreError, match="a covariance for frame 9, whose pose the revision does not set"):
        Revision(1, 0, "loop_closure", 5, set_directly={3: _T(1)}, covariances={9: cov})
    bad = cov.copy()
    bad[0, 0] = np.nan
    with pytest.raises(StoreError, match="covariance of frame 3 is not a finite symmetric 6x6"):
        Revision(1, 0, "loop_closure", 5, set_directly={3: _T(1)}, covariances={3: bad})
    data["covariances"]["covariance_6x6"][0] = data["covariances"]["covariance_6x6"][0][:35]
    with pytest.raises(StoreError, match="one list of 36 numbers per frame id"):
        Revision.from_json(data)


def _frame(fid: int) -> Frame:
    return Frame(frame_id=fid, stamp_ns=fid * 100_000_000, sensor_name="lidar", sensor_kind=SensorKind.LIDAR,
                 points_sensor=np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], np.float32),
                 pose=PoseEstimate(_T(fid)))


def test_the_store_keeps_them_and_frames_find_theirs_through_the_ancestry(tmp_path) -> None:
    with FrameStore.create(tmp_path / "s") as store:
        for fid in range(6):
            store.append(_frame(fid))
        c1, c4 = np.eye(6) * 1e-4, np.eye(6) * 4e-4
        store.add_revision({1: _T(1.1), 4: _T(4.1)}, source="loop_closure", covariances={1: c1, 4: c4})
        store.add_revision({4: _T(4.2)}, source="external_file", propagate=False)  # no covariance: frame 4 loses it
    store = FrameStore.open(tmp_path / "s")
    assert store.ledger.covariances(0) == {}
    rev1 = store.ledger.covariances(1)
    assert sorted(rev1) == [0, 1, 2, 3, 4, 5]  # propagated frames take the nearest keyframe's
    for fid, expected in ((0, c1), (1, c1), (2, c1), (3, c4), (4, c4), (5, c4)):
        np.testing.assert_array_equal(rev1[fid], expected)
    rev2 = store.ledger.covariances(2)
    assert sorted(rev2) == [0, 1, 2, 3, 5]  # frame 4's pose now comes from a revision without one


def test_the_covariance_is_propagated_to_the_evidence_point() -> None:
    """1 cm translation sigma alone gives 1 cm at any point; 0.01 rad of rotation about z seen 2 m along x gives
    2 cm; the median over the contributing frames; frames without a covariance do not count."""
    pose = np.eye(4)
    pose[:3, :3] = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # turned 90 deg about z
    covs = {1: np.diag([1e-4] * 3 + [0.0] * 3), 2: np.diag([0.0] * 5 + [1e-4]), 3: np.diag([4e-4] * 3 + [0.0] * 3)}
    fake = SimpleNamespace(covariances=lambda: covs, view=SimpleNamespace(pose=lambda f: pose))
    point = pose[:3, :3] @ np.array([2.0, 0.0, 0.0])  # 2 m along the sensor's x
    marginal = DecisionContext.pose_marginal_m
    assert marginal(fake, point, [1]) == pytest.approx(0.01)
    assert marginal(fake, point, [2]) == pytest.approx(0.02)
    assert marginal(fake, point, [1, 2, 3, 7]) == pytest.approx(0.02)  # median of 1, 2, 2 cm; frame 7 has none
    assert marginal(fake, pose[:3, :3] @ np.array([0.0, 0.0, 2.0]), [2]) == pytest.approx(0.0, abs=1e-12)  # on the axis
    assert marginal(fake, None, [1]) is None and marginal(fake, point, [7]) is None


def test_dense_marginals_equal_gtsams_per_node_marginals() -> None:
    """The dense inversion (the default up to DENSE_MARGINALS_MAX_DIM unknowns) gives GTSAM's marginals: a square
    with a Huber-weighted true loop and a Cauchy-weighted wrong one (robust weights are part of the linearisation),
    optimised; and a graph that cannot be factored fails both ways with a PoseGraphError."""
    from driftmap import geometry
    from driftmap.errors import PoseGraphError
    from driftmap.posegraph import RobustKernel

    rng = np.random.default_rng(3)
    graph = PoseGraph()
    truth = [geometry.make_transform(None, (float(np.cos(a)), float(np.sin(a)), 0.1 * a))
             for a in np.linspace(0, 4 * np.pi, 40)]
    info = np.diag([1e4] * 3 + [1e5] * 3)
    for k, T in enumerate(truth):
        graph.add_node(k, T @ geometry.se3_exp(rng.normal(0, 0.01, 6)))
        if k:
            graph.add_odometry(k - 1, k, geometry.invert(truth[k - 1]) @ T, info)
    for a, b in ((0, 20), (5, 25), (10, 30), (15, 35)):
        graph.add_loop(a, b, geometry.invert(truth[a]) @ truth[b], info, robust=RobustKernel.HUBER)
    graph.add_loop(3, 33, geometry.make_transform(None, (1.0, 0.0, 0.0)), info, robust=RobustKernel.CAUCHY)
    poses = graph.optimize().poses
    dense, per_node = graph.marginal_covariances(poses, dense=True), graph.marginal_covariances(poses, dense=False)
    assert dense.keys() == per_node.keys() == set(range(40))
    for k in dense:
        np.testing.assert_allclose(dense[k], per_node[k], rtol=1e-9, atol=1e-18)
    assert graph.marginal_covariances(poses).keys() == dense.keys()  # the default for 240 unknowns: dense
    split = PoseGraph()  # two nodes, no edge: the second is free
    split.add_node(0, np.eye(4))
    split.add_node(1, np.eye(4))
    for dense_path in (True, False):
        with pytest.raises(PoseGraphError, match=r"node\(s\) \[1\] have no edge and no prior"):
            split.marginal_covariances({0: np.eye(4), 1: np.eye(4)}, dense=dense_path)
