"""Pose-graph layer: tangent ordering, g2o round trips, agreement with plain GTSAM on the classic benchmarks,
loop closure on a synthetic square, outlier loops, ISAM2 vs batch LM."""

from __future__ import annotations

import time
from pathlib import Path

import gtsam
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from driftmap import geometry
from driftmap.posegraph import (
    CHI2_6DOF_99,
    EdgeKind,
    Initialization,
    Optimizer,
    PoseGraph,
    PoseGraphError,
    RobustKernel,
    TangentOrder,
    information_from_gtsam,
    information_to_gtsam,
    optimize_g2o,
    reorder_6x6,
)
from driftmap.posegraph.solvers import lm_params, run_lm


def _random_spd(rng: np.random.Generator) -> np.ndarray:
    A = rng.normal(size=(6, 6))
    return A @ A.T + 6.0 * np.eye(6)


def _plain_gtsam_lm(path: Path, is3d: bool = True) -> tuple[float, float, int]:
    """The reference, no driftmap code involved: GTSAM's reader, a prior on key 0 as in GTSAM's own
    Pose3SLAMExample_g2o.py, and LM with default parameters. (Without the gauge prior GTSAM's LM takes another
    path: sphere_bignoise stops at 3.84e6 instead of 3.76e6.)"""
    graph, initial = gtsam.readG2o(str(path), is3d)
    if is3d:
        variances = np.array([1e-6, 1e-6, 1e-6, 1e-4, 1e-4, 1e-4])  # GTSAM order: rotation, translation
        graph.add(gtsam.PriorFactorPose3(0, initial.atPose3(0), gtsam.noiseModel.Diagonal.Variances(variances)))
    else:
        variances = np.array([1e-4, 1e-4, 1e-6])  # Pose2 order: x, y, theta
        graph.add(gtsam.PriorFactorPose2(0, initial.atPose2(0), gtsam.noiseModel.Diagonal.Variances(variances)))
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, gtsam.LevenbergMarquardtParams())
    result = optimizer.optimize()
    return float(graph.error(initial)), float(graph.error(result)), int(optimizer.iterations())


# ------------------------------------------------------------------------------------------------------------
# tangent ordering
# ------------------------------------------------------------------------------------------------------------


def test_reorder_swaps_translation_and_rotation_blocks() -> None:
    M = np.arange(36, dtype=float).reshape(6, 6)
    R = reorder_6x6(M, TangentOrder.TRANSLATION_ROTATION, TangentOrder.ROTATION_TRANSLATION)
    np.testing.assert_array_equal(R[:3, :3], M[3:, 3:])  # rotation-rotation block first in GTSAM order
    np.testing.assert_array_equal(R[3:, 3:], M[:3, :3])
    np.testing.assert_array_equal(R[:3, 3:], M[3:, :3])
    np.testing.assert_array_equal(R[3:, :3], M[:3, 3:])
    np.testing.assert_array_equal(information_from_gtsam(information_to_gtsam(M)), M)
    np.testing.assert_array_equal(reorder_6x6(M, TangentOrder.ROTATION_TRANSLATION, TangentOrder.ROTATION_TRANSLATION), M)
    # the same permutation serves covariance and information: inv(reorder(cov)) == reorder(inv(cov))
    cov = _random_spd(np.random.default_rng(0))
    np.testing.assert_allclose(np.linalg.inv(information_to_gtsam(cov)), information_to_gtsam(np.linalg.inv(cov)), atol=1e-12)
    with pytest.raises(PoseGraphError):
        reorder_6x6(np.eye(3), TangentOrder.TRANSLATION_ROTATION, TangentOrder.ROTATION_TRANSLATION)


def test_gtsam_pose3_residual_is_rotation_first() -> None:
    """The fact the conversion relies on: GTSAM's Pose3 between-residual is [rotation, translation], and its
    chart is the SE(3) log, i.e. our se3_log with the halves swapped."""
    factor = gtsam.BetweenFactorPose3(0, 1, gtsam.Pose3(), gtsam.noiseModel.Unit.Create(6))
    values = gtsam.Values()
    values.insert(0, gtsam.Pose3())
    values.insert(1, gtsam.Pose3(gtsam.Rot3(), gtsam.Point3(0.1, 0.0, 0.0)))
    np.testing.assert_allclose(factor.unwhitenedError(values), [0, 0, 0, 0.1, 0, 0], atol=1e-15)
    T = geometry.make_transform(Rotation.from_rotvec([0.3, -0.2, 0.5]), [1.0, 2.0, 3.0])
    xi = geometry.se3_log(T)
    np.testing.assert_allclose(gtsam.Pose3.Logmap(gtsam.Pose3(T)), np.r_[xi[3:], xi[:3]], atol=1e-12)


def _three_node_line(info: np.ndarray) -> PoseGraph:
    """Nodes 0, 1, 2 one metre apart on the x axis, identity rotations, odometry 0->1->2 measuring exactly that."""
    pg = PoseGraph()
    step = geometry.make_transform(translation_m=[1.0, 0.0, 0.0])
    for k in range(3):
        pg.add_node(k, geometry.make_transform(translation_m=[float(k), 0.0, 0.0]))
    pg.add_prior(0)
    pg.add_odometry(0, 1, step, info)
    pg.add_odometry(1, 2, step, info)
    return pg


def test_translation_only_confident_information_weights_translation_residuals() -> None:
    lam_t, lam_r = 1e4, 1e-2  # confident in translation (sigma 1 cm), not in rotation (sigma 10 rad)
    info = np.diag([lam_t] * 3 + [lam_r] * 3)  # driftmap order [translation, rotation]
    pg = _three_node_line(info)
    assert pg.error() == pytest.approx(0.0, abs=1e-12)
    # node 1 moved 0.1 m along x: pure translation residuals of +-0.1 m on both edges
    poses = dict(pg.nodes)
    poses[1] = geometry.make_transform(translation_m=[1.1, 0.0, 0.0])
    prior_error = 0.0  # node 0 untouched
    assert pg.error(poses) == pytest.approx(prior_error + 0.5 * 2 * lam_t * 0.1**2, rel=1e-9)  # 100, not 1e-4
    # node 2 rotated 0.1 rad about z in place: a pure rotation residual on edge 1->2 only
    poses = dict(pg.nodes)
    poses[2] = geometry.make_transform(Rotation.from_rotvec([0.0, 0.0, 0.1]), [2.0, 0.0, 0.0])
    assert pg.error(poses) == pytest.approx(0.5 * lam_r * 0.1**2, rel=1e-9)  # 5e-5, not 50


def test_optimum_takes_translation_and_rotation_from_the_confident_edges() -> None:
    """Two measurements of 0->1 disagree in both translation and rotation; each is confident in one half."""
    lam_hi, lam_lo = 1e6, 1e-2
    info_t = np.diag([lam_hi] * 3 + [lam_lo] * 3)
    info_r = np.diag([lam_lo] * 3 + [lam_hi] * 3)
    pg = _three_node_line(np.diag([1e2] * 3 + [1e2] * 3))
    yaw = 0.2
    pg.add_loop(0, 1, geometry.make_transform(Rotation.from_rotvec([0, 0, yaw]), [1.5, 0.3, 0.0]), info_r,
                robust=RobustKernel.NONE)
    pg.add_loop(0, 1, geometry.make_transform(None, [1.0, 0.0, 0.0]), info_t, robust=RobustKernel.NONE)
    result = pg.optimize()
    T1 = result.poses[1]
    np.testing.assert_allclose(T1[:3, 3], [1.0, 0.0, 0.0], atol=1e-3)
    assert Rotation.from_matrix(T1[:3, :3]).as_rotvec() == pytest.approx([0.0, 0.0, yaw], abs=1e-3)
    assert result.converged


# ------------------------------------------------------------------------------------------------------------
# g2o
# ------------------------------------------------------------------------------------------------------------


def test_g2o_information_is_read_in_file_order(datasets_dir: Path) -> None:
    """Parse the first EDGE_SE3:QUAT line by hand: g2o stores [translation, rotation], as driftmap does."""
    path = datasets_dir / "pose-graphs" / "parking-garage.g2o"
    line = next(ln for ln in path.read_text().splitlines() if ln.startswith("EDGE_SE3:QUAT"))
    tokens = line.split()
    key_from, key_to = int(tokens[1]), int(tokens[2])
    t_m, quat_xyzw = np.array(tokens[3:6], float), np.array(tokens[6:10], float)
    info_file = np.zeros((6, 6))
    info_file[np.triu_indices(6)] = np.array(tokens[10:31], float)
    info_file = info_file + np.triu(info_file, 1).T
    assert info_file[0, 0] == 1.0 and info_file[3, 3] == pytest.approx(4.00073)  # translation 1, rotation ~4
    pg = PoseGraph.from_g2o(path)
    edge = pg.edges[0]
    assert (edge.key_from, edge.key_to, edge.kind) == (key_from, key_to, EdgeKind.ODOMETRY)
    np.testing.assert_allclose(edge.information_6x6, info_file, rtol=1e-12)
    np.testing.assert_allclose(edge.T_from_to, geometry.from_tum(t_m, quat_xyzw / np.linalg.norm(quat_xyzw)), atol=1e-9)
    graph, _ = gtsam.readG2o(str(path), True)
    np.testing.assert_allclose(graph.at(0).noiseModel().information(), information_to_gtsam(info_file), rtol=1e-9)
    assert len(pg.nodes) == 1661 and len(pg.edges) == 6275


def test_g2o_round_trip_full_precision(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    pg = PoseGraph()
    for k in range(6):
        pg.add_node(k, geometry.make_transform(Rotation.random(random_state=k), rng.normal(0, 100, 3)))
    for k in range(5):
        pg.add_odometry(k, k + 1, geometry.make_transform(Rotation.random(random_state=10 + k), rng.normal(0, 3, 3)),
                        _random_spd(rng))
    pg.add_loop(5, 0, geometry.make_transform(Rotation.random(random_state=99), rng.normal(0, 3, 3)), _random_spd(rng))
    path = tmp_path / "g.g2o"
    pg.to_g2o(path)
    back = PoseGraph.from_g2o(path)
    assert back.nodes.keys() == pg.nodes.keys()
    for k in pg.nodes:
        np.testing.assert_allclose(back.nodes[k], pg.nodes[k], atol=1e-12)
    for a, b in zip(pg.edges, back.edges, strict=True):
        assert (a.key_from, a.key_to, a.kind) == (b.key_from, b.key_to, b.kind)
        np.testing.assert_allclose(b.T_from_to, a.T_from_to, atol=1e-13)
        np.testing.assert_allclose(b.information_6x6, a.information_6x6, rtol=1e-12)
    assert back.edges[-1].robust is RobustKernel.NONE  # kernels are not part of g2o; from_g2o default
    # GTSAM's own reader sees the same least-squares problem (no prior in the file, so compare without it)
    graph, values = gtsam.readG2o(str(path), True)
    plain = PoseGraph()
    for k, T in pg.nodes.items():
        plain.add_node(k, T)
    for e in pg.edges:
        plain.add_odometry(e.key_from, e.key_to, e.T_from_to, e.information_6x6)
    plain.add_prior(0)
    assert float(graph.error(values)) == pytest.approx(plain.error(), rel=1e-9)


def test_parking_garage_matches_plain_gtsam(datasets_dir: Path) -> None:
    path = datasets_dir / "pose-graphs" / "parking-garage.g2o"
    ref_initial, ref_final, _ = _plain_gtsam_lm(path)
    assert ref_initial == pytest.approx(8.4e3, rel=0.01)  # README: about 8.4e3 -> about 0.63
    assert ref_final == pytest.approx(0.63, rel=0.01)
    result = optimize_g2o(path)
    assert result.converged and result.method is Optimizer.LM
    assert result.initial_error == pytest.approx(ref_initial, rel=1e-9)  # the default prior adds nothing there
    assert result.final_error == pytest.approx(ref_final, rel=1e-3)
    assert len(result.poses) == 1661 and result.n_edges == 6275
    assert len(result.loop_residuals) == 4615 and not result.rejected_loops


@pytest.mark.slow
@pytest.mark.parametrize("name", ["sphere_bignoise_vertex3", "cubicle"])
def test_large_3d_benchmarks_converge_like_plain_gtsam(datasets_dir: Path, name: str) -> None:
    """Plain GTSAM LM from the file's (odometry) initial: sphere 1.66e8 -> 3.76e6 in 72 iterations (a local
    minimum, see docs/posegraph.md), cubicle 5.41e6 -> 1373 in 39."""
    path = datasets_dir / "pose-graphs" / f"{name}.g2o"
    ref_initial, ref_final, ref_iterations = _plain_gtsam_lm(path)
    if name == "cubicle":  # 5021 of its 16869 information matrices are not positive definite: refused by default
        with pytest.raises(PoseGraphError, match=r"cubicle.g2o:5753: EDGE_SE3:QUAT 1 -> 2: .*not positive definite.*"
                                                 r"5021 of 16869"):
            optimize_g2o(path)
    result = optimize_g2o(path, non_pd_information="gtsam" if name == "cubicle" else "refuse")
    assert result.converged
    assert result.final_error < 0.05 * result.initial_error
    assert result.initial_error == pytest.approx(ref_initial, rel=1e-9)
    assert result.final_error == pytest.approx(ref_final, rel=1e-3)
    assert abs(result.iterations - ref_iterations) <= 2


def test_2d_g2o_lifted_into_the_plane_matches_plain_gtsam_pose2(datasets_dir: Path) -> None:
    path = datasets_dir / "pose-graphs" / "M3500.g2o"
    ref_initial, ref_final, _ = _plain_gtsam_lm(path, is3d=False)
    result = optimize_g2o(path)
    assert result.initial_error == pytest.approx(ref_initial, rel=1e-9)
    assert result.final_error == pytest.approx(ref_final, rel=1e-6)  # about 1.32e6 -> 68.96
    assert result.converged
    z = np.array([T[2, 3] for T in result.poses.values()])
    tilt = np.array([T[2, 2] for T in result.poses.values()])
    assert np.abs(z).max() < 1e-9 and tilt.min() > 1.0 - 1e-12  # stayed in the plane


# ------------------------------------------------------------------------------------------------------------
# synthetic square: loop closure and a wrong loop
# ------------------------------------------------------------------------------------------------------------

SIGMA_T_M = 0.05
SIGMA_R_RAD = np.radians(0.5)
ODOMETRY_INFO = np.diag([1 / SIGMA_T_M**2] * 3 + [1 / SIGMA_R_RAD**2] * 3)


def _square_ground_truth(n_side: int = 10, step_m: float = 1.0) -> list[np.ndarray]:
    """A 10 m x 10 m square driven counter-clockwise, a pose every metre; the last pose is the first."""
    poses = [np.eye(4)]
    for _side in range(4):
        for i in range(n_side):
            step = geometry.make_transform(translation_m=[step_m, 0.0, 0.0])
            if i == n_side - 1:
                step = step @ geometry.make_transform(Rotation.from_euler("z", 90, degrees=True))
            poses.append(poses[-1] @ step)
    return poses


def _square_graph(
    seed: int, *, true_loop: bool = True, wrong_loop: tuple[int, int] | None = None, robust: RobustKernel = RobustKernel.HUBER
) -> tuple[PoseGraph, list[np.ndarray]]:
    rng = np.random.default_rng(seed)
    gt = _square_ground_truth()
    pg = PoseGraph()
    T_world_x = gt[0].copy()
    pg.add_node(0, T_world_x)
    for k in range(1, len(gt)):
        noise = geometry.se3_exp(np.r_[rng.normal(0, SIGMA_T_M, 3), rng.normal(0, SIGMA_R_RAD, 3)])
        T_meas = geometry.invert(gt[k - 1]) @ gt[k] @ noise
        T_world_x = T_world_x @ T_meas  # dead reckoning
        pg.add_node(k, T_world_x)
        pg.add_odometry(k - 1, k, T_meas, ODOMETRY_INFO)
    last = len(gt) - 1
    if true_loop:
        pg.add_loop(0, last, geometry.invert(gt[0]) @ gt[last], ODOMETRY_INFO, robust=robust)
    if wrong_loop is not None:
        a, b = wrong_loop
        off_2m = geometry.make_transform(translation_m=[2.0, 0.0, 0.0])
        pg.add_loop(a, b, geometry.invert(gt[a]) @ gt[b] @ off_2m, ODOMETRY_INFO, robust=robust)
    return pg, gt


def _ate_m(poses, gt: list[np.ndarray]) -> float:
    return float(np.sqrt(np.mean([np.sum((poses[k][:3, 3] - gt[k][:3, 3]) ** 2) for k in range(len(gt))])))


def test_true_loop_closure_reduces_end_point_error() -> None:
    pg, gt = _square_graph(seed=0)
    last = len(gt) - 1
    end_before_m = geometry.translation_distance_m(pg.nodes[last], gt[last])
    result = pg.optimize()
    end_after_m = geometry.translation_distance_m(result.poses[last], gt[last])
    assert end_before_m > 1.0  # about 1.2 m of drift around the square
    assert end_after_m < 0.05 and end_after_m < 0.05 * end_before_m
    assert _ate_m(result.poses, gt) < 0.5 * _ate_m(pg.nodes, gt)
    assert result.converged and result.final_error < result.initial_error
    (loop,) = result.loop_residuals
    assert (loop.key_from, loop.key_to, loop.accepted, loop.weight) == (0, last, True, 1.0)
    assert loop.chi2 < CHI2_6DOF_99 and loop.whitened_error == pytest.approx(np.sqrt(loop.chi2))
    np.testing.assert_allclose(result.poses[0], gt[0], atol=1e-6)  # the default prior holds node 0


@pytest.mark.parametrize(
    ("robust", "method"),
    [(RobustKernel.CAUCHY, Optimizer.LM), (RobustKernel.NONE, Optimizer.GNC), (RobustKernel.HUBER, Optimizer.GNC)],
)
@pytest.mark.parametrize("seed", range(5))
def test_wrong_loop_is_rejected(robust: RobustKernel, method: Optimizer, seed: int) -> None:
    """A loop 2 m off (about 10 sigma of the drift between its nodes) barely moves the trajectory.

    (Huber with LM does not pass this: its bounded but non-vanishing pull bends the weak odometry chain and
    the trajectory error grows 1.5-2.6x on these seeds; see docs/posegraph.md.)
    """
    clean, gt = _square_graph(seed, robust=robust)
    ate_clean_m = _ate_m(clean.optimize(method).poses, gt)
    pg, _ = _square_graph(seed, wrong_loop=(25, 15), robust=robust)
    result = pg.optimize(method)
    assert _ate_m(result.poses, gt) <= 1.10 * ate_clean_m
    true_loop, wrong = result.loop_residuals
    assert (wrong.key_from, wrong.key_to) == (25, 15)
    assert not wrong.accepted and wrong.chi2 > 10 * CHI2_6DOF_99 and wrong.weight < 0.05
    assert true_loop.accepted and true_loop.weight > 0.95
    assert result.rejected_loops == (wrong,)
    if method is Optimizer.GNC:
        assert result.converged and result.iterations is None
        weights = result.gnc_edge_weights
        assert weights is not None and len(weights) == len(pg.edges)
        assert all(w == 1.0 for w, e in zip(weights, pg.edges) if e.kind is EdgeKind.ODOMETRY)  # known inliers
        assert weights[wrong.edge_index] < 1e-3 and weights[true_loop.edge_index] > 0.999
    else:
        assert result.gnc_edge_weights is None


def test_isam2_matches_batch_lm() -> None:
    pg, gt = _square_graph(seed=1)
    pg.add_loop(10, 30, geometry.invert(gt[10]) @ gt[30], ODOMETRY_INFO)
    batch = pg.optimize(Optimizer.LM)
    seen = []
    incremental = pg.optimize(Optimizer.ISAM2, callback=seen.append)
    assert incremental.converged and batch.converged
    assert incremental.iterations == len(seen) > len(gt)  # one update per node, then relinearisation passes
    assert incremental.final_error == pytest.approx(batch.final_error, rel=1e-6)
    for k in pg.nodes:
        assert geometry.translation_distance_m(incremental.poses[k], batch.poses[k]) < 1e-4
        assert geometry.rotation_angle_deg(incremental.poses[k], batch.poses[k]) < 1e-3
    assert [r.accepted for r in incremental.loop_residuals] == [r.accepted for r in batch.loop_residuals]


# ------------------------------------------------------------------------------------------------------------
# API behaviour
# ------------------------------------------------------------------------------------------------------------


def test_callback_sees_every_lm_iteration_and_can_stop() -> None:
    pg, _ = _square_graph(seed=2)
    seen = []
    full = pg.optimize(callback=seen.append)
    assert [p.iteration for p in seen] == list(range(1, full.iterations + 1))
    assert all(p.error <= p.previous_error for p in seen) and seen[-1].error == pytest.approx(full.final_error)
    assert all(p.lm_lambda is not None for p in seen)
    stopped = pg.optimize(callback=lambda p: True)
    assert stopped.iterations == 1 and not stopped.converged and "callback" in stopped.warnings[0]


def test_chordal_initialization_reaches_the_same_optimum() -> None:
    pg, _ = _square_graph(seed=3)
    given = pg.optimize()
    chordal = pg.optimize(initialization=Initialization.CHORDAL)
    assert chordal.initialization is Initialization.CHORDAL
    assert chordal.initial_error < given.initial_error
    assert chordal.final_error == pytest.approx(given.final_error, rel=1e-6)
    with pytest.raises(PoseGraphError, match="ISAM2"):
        pg.optimize(Optimizer.ISAM2, initialization=Initialization.CHORDAL)


def test_default_prior_is_on_the_lowest_key_unless_one_is_given() -> None:
    pg = PoseGraph()
    pg.add_node(7, geometry.make_transform(translation_m=[1.0, 2.0, 3.0]))
    pg.add_node(3, np.eye(4))
    pg.add_odometry(3, 7, geometry.make_transform(translation_m=[1.0, 2.0, 3.0]), ODOMETRY_INFO)
    (prior,) = pg.effective_priors()
    assert prior.key == 3 and prior.information_6x6[0, 0] == pytest.approx(1e8)
    pg.add_prior(7)
    assert [p.key for p in pg.effective_priors()] == [7]
    result = pg.optimize()
    np.testing.assert_allclose(result.poses[7], pg.nodes[7], atol=1e-9)


def test_edge_loop_default_is_huber_and_validation_errors() -> None:
    pg = PoseGraph()
    pg.add_node(0, np.eye(4))
    pg.add_node(1, np.eye(4))
    loop = pg.add_loop(0, 1, np.eye(4), ODOMETRY_INFO)
    assert loop.robust is RobustKernel.HUBER and loop.robust_param == pytest.approx(np.sqrt(CHI2_6DOF_99))
    assert pg.add_odometry(0, 1, np.eye(4), ODOMETRY_INFO).robust is RobustKernel.NONE
    with pytest.raises(PoseGraphError, match="does not exist"):
        pg.add_odometry(0, 2, np.eye(4), ODOMETRY_INFO)
    with pytest.raises(PoseGraphError, match="already exists"):
        pg.add_node(1, np.eye(4))
    with pytest.raises(PoseGraphError, match="positive definite"):
        pg.add_loop(0, 1, np.eye(4), np.diag([1.0] * 5 + [0.0]))
    with pytest.raises(PoseGraphError, match="symmetric"):
        pg.add_loop(0, 1, np.eye(4), np.eye(6) + np.triu(np.ones((6, 6)), 1))
    with pytest.raises(PoseGraphError, match="robust_param"):
        pg.add_odometry(0, 1, np.eye(4), ODOMETRY_INFO, robust_param=2.0)
    with pytest.raises(PoseGraphError, match="rotation"):
        pg.add_odometry(0, 1, np.diag([1.0, 1.0, -1.0, 1.0]), ODOMETRY_INFO)
    with pytest.raises(PoseGraphError, match="no nodes"):
        PoseGraph().optimize()
    with pytest.raises(PoseGraphError, match="g2o"):
        PoseGraph.from_g2o(Path(__file__))


@pytest.mark.parametrize("offset_m, converged", [(0.01, True), (100.0, False)])
def test_lm_at_a_stationary_point_converges_within_the_noise_and_warns_beyond_it(offset_m: float,
                                                                                converged: bool) -> None:
    """Hostile trial 17 W10: LM started where it cannot decrease the error gives up at maximum lambda. Within the
    residuals' noise (two priors 2 cm apart at 10 cm sigma, started between them) that is the optimum, not a failure
    to report; far beyond it (200 m apart: the INTEL data set's case) it stays a warning and ``converged`` False."""
    graph = gtsam.NonlinearFactorGraph()
    noise = gtsam.noiseModel.Isotropic.Sigma(6, 0.1)
    for sign in (1.0, -1.0):
        graph.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(gtsam.Rot3(), np.array([sign * offset_m, 0.0, 0.0])), noise))
    initial = gtsam.Values()
    initial.insert(0, gtsam.Pose3())
    warnings: list[str] = []
    _, iterations, ok = run_lm(graph, initial, lm_params(100, 0.0, 0.0), float(graph.error(initial)),
                               time.perf_counter(), None, warnings)
    assert iterations == 0 and ok is converged
    assert bool(warnings) is not converged and all("maximum lambda" in w for w in warnings)


# ------------------------------------------------------------------------------------------------------------
# g2o lines checked before GTSAM reads them (hostile trial 25 B1, W1)
_V0 = "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1"
_V1 = "VERTEX_SE3:QUAT 1 1 0 0 0 0 0 1"
_INFO = "1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 1"  # identity, upper triangle


@pytest.mark.parametrize("lines, message", [
    # B1: [[1, 5], [5, 1]] in the translation block (eigenvalue -4): GTSAM's unchecked Cholesky made it [[1,5],[5,26]]
    ([_V0, _V1, "EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 1 5 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 1"],
     r"g2o:3: EDGE_SE3:QUAT 0 -> 1: the information matrix is not positive definite \(smallest eigenvalue -4"),
    ([_V0, _V1, "EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 " + " ".join(["0"] * 21)], r"g2o:3: .*not positive definite"),
    ([_V0, "VERTEX_SE3:QUAT -5 1 0 0 0 0 0 1"], r"g2o:2: id '-5' is not a whole number"),
    ([_V0, "VERTEX_SE3:QUAT 99999999999999999999 1 0 0 0 0 0 1"], r"g2o:2: id '99999999999999999999'"),
    ([_V0, "VERTEX_SE3:QUAT 1 1 0 0"], r"g2o:2: a VERTEX_SE3:QUAT line holds 1 id\(s\), 7 pose numbers; this one "
                                       r"holds 4 values"),
    ([_V0, _V1 + " 99"], r"g2o:2: .*this one holds 9 values"),
    ([_V0, "VERTEX_SE3:QUAT 1 1 0 0 0 0 0 5"], r"g2o:2: VERTEX_SE3:QUAT 1: quaternion has norm 5.0000"),
    ([_V0, _V1, f"EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1.22 {_INFO}"], r"g2o:3: .*quaternion has norm 1.2200"),
    ([_V0, "VERTEX_SE3:QUAT 1 nan 0 0 0 0 0 1"], r"g2o:2: VERTEX_SE3:QUAT 1: holds NaN or inf"),
    ([_V0, _V1, f"EDGE_SE3:QUAT 0 7 1 0 0 0 0 0 1 {_INFO}"], r"g2o:3: EDGE_SE3:QUAT 0 -> 7: no vertex 7 in the file"),
    ([_V0, _V1, f"EDGE_SE3:QUAT 1 1 1 0 0 0 0 0 1 {_INFO}"], r"g2o:3: .*must join two different vertices"),
    ([_V0, _V1, "FIX 4", f"EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 {_INFO}"], r"g2o:3: FIX 4: no vertex 4"),
    (["VERTEX_SE2 0 0 0 0", "VERTEX_SE2 1 1 0 0", "EDGE_SE2 0 1 1 0 0 -1 0 0 1 0 1"],
     r"g2o:3: EDGE_SE2 0 -> 1: the information matrix is not positive definite"),
])
def test_g2o_lines_are_checked_before_gtsam_reads_them(tmp_path: Path, lines: list[str], message: str) -> None:
    path = tmp_path / "bad.g2o"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(PoseGraphError, match=message):
        PoseGraph.from_g2o(path)


def test_g2o_fix_lines_hold_their_nodes_and_non_pd_information_can_be_read_as_gtsam_does(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """FIX 1 holds node 1 where the file puts it (the edge then moves node 0); non_pd_information='gtsam' reads
    [[1, 5], [5, 1]] as GTSAM does, [[1, 5], [5, 26]], with a warning."""
    path = tmp_path / "fix.g2o"
    path.write_text("\n".join([_V0, _V1, "FIX 1", f"EDGE_SE3:QUAT 0 1 2 0 0 0 0 0 1 {_INFO}"]) + "\n")
    pg = PoseGraph.from_g2o(path)
    assert [p.key for p in pg.effective_priors()] == [1]
    result = pg.optimize()
    assert result.poses[1][0, 3] == pytest.approx(1.0, abs=1e-6) and result.poses[0][0, 3] == pytest.approx(-1.0, abs=1e-6)
    path.write_text("\n".join([_V0, _V1, "EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 1 5 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 1"]))
    with caplog.at_level("WARNING"):
        pg = PoseGraph.from_g2o(path, non_pd_information="gtsam")
    assert np.allclose(pg.edges[0].information_6x6[:2, :2], [[1, 5], [5, 26]])
    assert "1 of 1 edges' information matrices are not positive definite" in caplog.text
    with pytest.raises(PoseGraphError, match="non_pd_information must be one of refuse, gtsam"):
        PoseGraph.from_g2o(path, non_pd_information="accept")
