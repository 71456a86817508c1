"""SE(3) log/exp/interpolation and the pose ledger: hand-computed correction propagation, single-sided
propagation, rollback and branching resolved bit for bit, diffs, rejected calls that change nothing, JSON
round trips, trajectory matching, and propagation of known corrections over real 7-Scenes poses."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from driftmap import geometry
from driftmap.errors import StoreError, TransformError
from driftmap.frame import PoseSource
from driftmap.geometry import interpolate_se3, se3_exp, se3_log
from driftmap.store.ledger import (
    PoseLedger,
    PoseMatchMode,
    Revision,
    match_trajectory,
)
from driftmap.trajectory import Trajectory

S = 1_000_000_000  # ns per second
MS = 1_000_000  # ns per millisecond
SQRT2 = math.sqrt(2.0)


def Tr(x: float, y: float, z: float) -> np.ndarray:
    return geometry.make_transform(translation_m=[x, y, z])


def Rz(deg: float) -> np.ndarray:
    return geometry.make_transform(Rotation.from_euler("z", deg, degrees=True))


def Rx(deg: float) -> np.ndarray:
    return geometry.make_transform(Rotation.from_euler("x", deg, degrees=True))


def random_rigid(rng: np.random.Generator, angle_scale: float = 1.0, translation_m: float = 5.0) -> np.ndarray:
    return geometry.make_transform(
        Rotation.from_rotvec(rng.normal(size=3) * angle_scale), rng.uniform(-translation_m, translation_m, size=3)
    )


def bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float64).view(np.uint64)


def line_ledger(n: int = 5, stamps_s: list[float] | None = None) -> PoseLedger:
    """Frames 0..n-1 at (i, 0, 0) m with identity rotation, stamps i s (or the given ones)."""
    ledger = PoseLedger(created_ns=0)
    stamps_s = list(range(n)) if stamps_s is None else stamps_s
    for i, t in enumerate(stamps_s):
        ledger.add_frame(i, round(t * S), Tr(i, 0, 0))
    return ledger


def random_ledger(n: int, seed: int = 0) -> PoseLedger:
    rng = np.random.default_rng(seed)
    ledger = PoseLedger(created_ns=0)
    for i in rng.permutation(n):  # frames arrive in any order
        ledger.add_frame(int(i), int(i) * 50 * MS, random_rigid(rng))
    return ledger


def snapshot(ledger: PoseLedger) -> tuple:
    return (
        ledger.frame_ids.copy(),
        ledger.stamps_ns.copy(),
        ledger.n_frames,
        ledger.head,
        len(ledger.revisions),
        [bits(ledger.poses(r)).copy() for r in range(ledger.head + 1)],
    )


def assert_same_snapshot(a: tuple, b: tuple) -> None:
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    assert a[2:5] == b[2:5]
    assert len(a[5]) == len(b[5])
    for x, y in zip(a[5], b[5], strict=True):
        np.testing.assert_array_equal(x, y)


# ==============================================================================================================
# geometry: se3_log / se3_exp / interpolate_se3
# ==============================================================================================================

ANGLES_RAD = [0.0, 1e-12, 1e-8, 1e-5, 9.99e-4, 1.001e-3, 0.3, 1.0, 2.5, math.pi - 1e-6, math.pi - 1e-10]


@pytest.mark.parametrize("angle", ANGLES_RAD)
def test_exp_of_log_is_identity_map(angle: float) -> None:
    rng = np.random.default_rng(int(angle * 1e6) % 1000)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    T = geometry.make_transform(Rotation.from_rotvec(axis * angle), rng.uniform(-3, 3, size=3))
    xi = se3_log(T)
    assert xi.shape == (6,)
    assert np.linalg.norm(xi[3:]) == pytest.approx(angle, abs=1e-12)
    np.testing.assert_allclose(se3_exp(xi), T, rtol=0, atol=2e-15)


def test_exp_known_values() -> None:
    # pure translation: exp([rho, 0]) is exactly a translation by rho; exp(0) is exactly the identity
    np.testing.assert_array_equal(se3_exp([1.5, -2.0, 0.25, 0, 0, 0]), Tr(1.5, -2.0, 0.25))
    np.testing.assert_array_equal(se3_exp(np.zeros(6)), np.eye(4))
    # screw along z: rotation about z by theta while advancing v along z -> translation exactly (0, 0, v)
    T = se3_exp([0, 0, 0.7, 0, 0, 1.2])
    np.testing.assert_allclose(T[:3, :3], Rz(math.degrees(1.2))[:3, :3], atol=1e-15)
    np.testing.assert_allclose(T[:3, 3], [0, 0, 0.7], atol=1e-15)
    # rotation of 90 deg about z with rho = (pi/2, 0, 0): a quarter turn about the point (0, 1, 0)
    # (rho = V^-1 t; for a turn about c, t = c - R c = (1, 1, 0), and V^-1 (1, 1, 0) = (pi/2, 0, 0))
    T = se3_exp([math.pi / 2, 0, 0, 0, 0, math.pi / 2])
    np.testing.assert_allclose(T[:3, 3], [1, 1, 0], atol=1e-15)


def test_log_and_exp_are_vectorised() -> None:
    rng = np.random.default_rng(1)
    Ts = np.stack([random_rigid(rng) for _ in range(20)])
    xis = se3_log(Ts)
    assert xis.shape == (20, 6)
    for T, xi in zip(Ts, xis, strict=True):
        np.testing.assert_allclose(xi, se3_log(T), atol=1e-15)
    np.testing.assert_allclose(se3_exp(xis), Ts, atol=5e-15)
    np.testing.assert_allclose(se3_log(se3_exp(xis)), xis, atol=1e-13)


def test_interpolation_endpoints() -> None:
    rng = np.random.default_rng(2)
    T_a, T_b = random_rigid(rng), random_rigid(rng, angle_scale=0.5)
    np.testing.assert_array_equal(interpolate_se3(T_a, T_b, 0.0), T_a)
    np.testing.assert_allclose(interpolate_se3(T_a, T_b, 1.0), T_b, atol=1e-14)


def test_interpolation_midpoint_of_a_yaw_is_half_the_angle() -> None:
    mid = interpolate_se3(np.eye(4), Rz(90.0), 0.5)
    np.testing.assert_allclose(mid, Rz(45.0), atol=1e-15)
    # also relative to a non-trivial start: T_a @ Rz(30) at alpha 1/3 of T_a @ Rz(90)
    T_a = Tr(1, 2, 3) @ Rx(20)
    np.testing.assert_allclose(interpolate_se3(T_a, T_a @ Rz(90.0), 1 / 3), T_a @ Rz(30.0), atol=1e-14)


def test_interpolation_follows_constant_velocity_screw_motion() -> None:
    xi = np.array([0.4, -0.1, 0.3, 0.2, -0.5, 0.9])  # a twist per second
    T0 = Tr(0.5, 1.0, -2.0) @ Rx(35)

    def T_at(t_s: float) -> np.ndarray:
        return T0 @ se3_exp(t_s * xi)

    t_a, t_b = 0.3, 1.7
    alphas = np.linspace(0.0, 1.0, 11)
    batch = interpolate_se3(T_at(t_a), T_at(t_b), alphas)
    assert batch.shape == (11, 4, 4)
    for alpha, T in zip(alphas, batch, strict=True):
        np.testing.assert_allclose(T, T_at(t_a + alpha * (t_b - t_a)), atol=1e-13)


def test_se3_rejects_bad_shapes() -> None:
    with pytest.raises(geometry.GeometryError):
        se3_exp(np.zeros(5))
    with pytest.raises(geometry.GeometryError):
        se3_log(np.eye(3))


# ==============================================================================================================
# frames and revision 0
# ==============================================================================================================


def test_frames_arrive_in_any_order_and_stay_sorted() -> None:
    ledger = PoseLedger(PoseSource.GROUND_TRUTH, created_ns=123)
    for fid in (7, 2, 9, 0, 5):
        ledger.add_frame(fid, fid * 10 * MS, Tr(fid, 0, 0))
    assert ledger.frame_ids.dtype == np.int64
    np.testing.assert_array_equal(ledger.frame_ids, [0, 2, 5, 7, 9])
    np.testing.assert_array_equal(ledger.stamps_ns, [0, 20 * MS, 50 * MS, 70 * MS, 90 * MS])
    assert ledger.n_frames == 5
    assert 5 in ledger and np.int64(9) in ledger and 3 not in ledger and "5" not in ledger
    np.testing.assert_array_equal(ledger.poses(0)[:, 0, 3], [0, 2, 5, 7, 9])
    assert ledger.head == 0
    rev0 = ledger.revision(0)
    assert rev0.revision_id == 0 and rev0.parent_id is None and rev0.source is PoseSource.GROUND_TRUTH
    assert rev0.created_ns == 123 and rev0.restores is None
    np.testing.assert_array_equal(rev0.changed_frame_ids, [0, 2, 5, 7, 9])
    np.testing.assert_array_equal(rev0.set_directly[7], Tr(7, 0, 0))
    assert ledger.revisions == [rev0]
    # a frame added later shows up in revision 0 and the array views
    ledger.add_frame(3, 30 * MS, Tr(3, 0, 0))
    np.testing.assert_array_equal(ledger.frame_ids, [0, 2, 3, 5, 7, 9])
    np.testing.assert_array_equal(ledger.poses(0)[:, 0, 3], [0, 2, 3, 5, 7, 9])
    assert 3 in ledger.revision(0).set_directly


def test_revision0_poses_are_validated_and_projected() -> None:
    ledger = PoseLedger()
    nearly = Rz(10.0)
    nearly[0, 0] += 2e-4  # within the rigid tolerance: projected onto SO(3)
    ledger.add_frame(0, 0, nearly)
    R = ledger.poses(0)[0, :3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-15)
    assert not ledger.poses(0).flags.writeable


def test_rejected_add_frame_changes_nothing() -> None:
    ledger = line_ledger()
    ledger.commit(ledger.plan_correction({4: Tr(0, 1, 0) @ Tr(4, 0, 0)}, source=PoseSource.LOOP_CLOSURE))
    before = snapshot(ledger)
    with pytest.raises(StoreError, match=r"frame 3 is already"):
        ledger.add_frame(3, 99, np.eye(4))
    scaled = np.eye(4)
    scaled[:3, :3] *= 2.0
    with pytest.raises(TransformError, match="frame 8"):
        ledger.add_frame(8, 99, scaled)
    with pytest.raises(TransformError):
        ledger.add_frame(8, 99, np.eye(3))
    with pytest.raises(StoreError, match="stamp_ns"):
        ledger.add_frame(8, 1.5, np.eye(4))
    with pytest.raises(StoreError, match="frame_id"):
        ledger.add_frame(True, 0, np.eye(4))
    assert 8 not in ledger
    assert_same_snapshot(before, snapshot(ledger))
    ledger.add_frame(8, 99, np.eye(4))  # the id is still free
    assert 8 in ledger


# ==============================================================================================================
# correction propagation: hand-computed cases
# ==============================================================================================================


def corrected(ledger: PoseLedger, keys: dict[int, np.ndarray], **kwargs) -> np.ndarray:
    """Commit a correction ``frame -> D_k`` (applied in the world frame, N_k = D_k @ O_k); return the new poses."""
    head = ledger.poses(ledger.head)
    poses = {k: D @ head[int(np.searchsorted(ledger.frame_ids, k))] for k, D in keys.items()}
    rev = ledger.commit(ledger.plan_correction(poses, source=PoseSource.LOOP_CLOSURE, **kwargs))
    return ledger.poses(rev.revision_id)


def test_translation_correction_interpolates_linearly() -> None:
    # D_0 = translate (0, 0.4, 0), D_4 = translate (0.8, 0, 0.2); frame k sits at (k, 0, 0) with stamp k s,
    # so it moves by (1 - k/4) * D_0 + (k/4) * D_4 and keeps its (identity) rotation
    P = corrected(line_ledger(), {0: Tr(0, 0.4, 0), 4: Tr(0.8, 0, 0.2)})
    expected_positions = [
        [0.0, 0.4, 0.0],
        [1.2, 0.3, 0.05],
        [2.4, 0.2, 0.1],
        [3.6, 0.1, 0.15],
        [4.8, 0.0, 0.2],
    ]
    np.testing.assert_allclose(P[:, :3, 3], expected_positions, atol=1e-15)
    np.testing.assert_allclose(P[:, :3, :3], np.broadcast_to(np.eye(3), (5, 3, 3)), atol=1e-15)


def test_yaw_correction_of_90_deg_gives_45_deg_at_the_midpoint() -> None:
    # D_0 = I, D_4 = Rz(90) about the world origin: frame k gets Rz(22.5 k) @ O_k
    P = corrected(line_ledger(), {0: np.eye(4), 4: Rz(90.0)})
    np.testing.assert_allclose(P[2], Rz(45.0) @ Tr(2, 0, 0), atol=1e-15)
    np.testing.assert_allclose(P[2, :3, 3], [SQRT2, SQRT2, 0.0], atol=1e-15)
    np.testing.assert_allclose(P[4, :3, 3], [0.0, 4.0, 0.0], atol=1e-15)
    for k in range(5):
        yaw = math.radians(22.5 * k)
        np.testing.assert_allclose(P[k, :3, 3], [k * math.cos(yaw), k * math.sin(yaw), 0.0], atol=1e-15)
        np.testing.assert_allclose(P[k, :3, :3], Rz(22.5 * k)[:3, :3], atol=1e-15)


def test_rotation_about_a_point_interpolates_about_that_point() -> None:
    # D_4 = [Rz(90) | (1, 0, 0)] turns the plane by 90 deg about c = (0.5, 0.5) (solve (I - R) c = t).
    # Halfway, the correction is a 45 deg turn about c: frame 2 at (2, 0) goes to
    # c + Rz(45) (p - c) = (0.5, 0.5) + Rz(45) (1.5, -0.5) = (0.5 + sqrt2, 0.5 + sqrt2 / 2).
    D4 = Tr(1, 0, 0) @ Rz(90.0)
    P = corrected(line_ledger(), {0: np.eye(4), 4: D4})
    np.testing.assert_allclose(P[2, :3, 3], [0.5 + SQRT2, 0.5 + SQRT2 / 2, 0.0], atol=1e-15)
    np.testing.assert_allclose(P[2, :3, :3], Rz(45.0)[:3, :3], atol=1e-15)
    np.testing.assert_allclose(P[4], D4 @ Tr(4, 0, 0), atol=1e-15)


def test_interpolation_weight_comes_from_stamps_not_indices() -> None:
    # stamps 0, 1, 4 s: the middle frame is a quarter of the way -> a quarter of the 0.8 m correction
    P = corrected(line_ledger(3, stamps_s=[0, 1, 4]), {0: np.eye(4), 2: Tr(0.8, 0, 0)})
    np.testing.assert_allclose(P[1, :3, 3], [1.2, 0.0, 0.0], atol=1e-15)


def test_frames_sharing_a_keyframe_stamp_take_its_correction() -> None:
    # frames (id: stamp s) 0:0, 1:1, 2:1, 3:1, 4:2; keyframes 0, 2, 4. Frames 1 and 3 share keyframe 2's stamp.
    ledger = line_ledger(5, stamps_s=[0, 1, 1, 1, 2])
    P = corrected(ledger, {0: Tr(1, 0, 0), 2: Tr(0, 1, 0), 4: Tr(0, 0, 1)})
    np.testing.assert_array_equal(P[1, :3, 3], [1, 1, 0])
    np.testing.assert_array_equal(P[3, :3, 3], [3, 1, 0])
    # two keyframes on one stamp: frames are ordered by (stamp, id); between them (t_a == t_b) D_a applies
    ledger = line_ledger(5, stamps_s=[0, 1, 1, 1, 2])
    P = corrected(ledger, {1: Tr(1, 0, 0), 3: Tr(0, 1, 0)})
    np.testing.assert_array_equal(P[:, :3, 3], [[1, 0, 0], [2, 0, 0], [3, 0, 0], [3, 1, 0], [4, 1, 0]])


def test_single_sided_propagation_keeps_the_pose_relative_to_the_keyframe() -> None:
    rng = np.random.default_rng(3)
    ledger = random_ledger(10, seed=3)
    O = ledger.poses(0)
    N = {3: random_rigid(rng), 6: random_rigid(rng)}
    rev = ledger.commit(ledger.plan_correction(N, source=PoseSource.LOOP_CLOSURE))
    P = ledger.poses(rev.revision_id)
    inv = geometry.invert
    for f, k in [(0, 3), (1, 3), (2, 3), (7, 6), (8, 6), (9, 6)]:
        np.testing.assert_allclose(inv(N[k]) @ P[f], inv(O[k]) @ O[f], atol=1e-12)
    for k in (3, 6):
        np.testing.assert_array_equal(P[k], geometry.as_rigid(N[k]))
    # a lone keyframe moves the whole ledger rigidly with it
    ledger2 = random_ledger(10, seed=3)
    P2 = corrected(ledger2, {5: Tr(1, 2, 3) @ Rx(40)})
    for f in range(10):
        np.testing.assert_allclose(P2[f], Tr(1, 2, 3) @ Rx(40) @ O[f], atol=1e-12)


def reference_propagation(ledger: PoseLedger, parent: int, new: dict[int, np.ndarray]) -> np.ndarray:
    """Per-frame Python loop of the documented rule, to check the vectorised implementation against."""
    ids, stamps, O = ledger.frame_ids.tolist(), ledger.stamps_ns.tolist(), ledger.poses(parent)
    index = {f: i for i, f in enumerate(ids)}
    D = {k: geometry.as_rigid(N) @ geometry.invert(O[index[k]]) for k, N in new.items()}
    keys = sorted(new, key=lambda k: (stamps[index[k]], k))
    out = O.copy()
    for f in ids:
        i = index[f]
        if f in new:
            out[i] = geometry.as_rigid(new[f])
            continue
        before = [k for k in keys if (stamps[index[k]], k) < (stamps[i], f)]
        after = [k for k in keys if (stamps[index[k]], k) > (stamps[i], f)]
        if not after:
            Df = D[before[-1]]
        elif not before:
            Df = D[after[0]]
        else:
            a, b = before[-1], after[0]
            t_a, t_b = stamps[index[a]], stamps[index[b]]
            Df = D[a] if t_a == t_b else interpolate_se3(D[a], D[b], (stamps[i] - t_a) / (t_b - t_a))
        out[i] = Df @ O[i]
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_vectorised_propagation_matches_a_per_frame_reference(seed: int) -> None:
    rng = np.random.default_rng(seed)
    ledger = PoseLedger(created_ns=0)
    n = 300
    stamps = rng.integers(0, 120, size=n) * 25 * MS  # many shared stamps
    for fid in rng.permutation(n):
        ledger.add_frame(int(fid) * 3, int(stamps[fid]), random_rigid(rng))
    ledger.commit(ledger.plan_correction({0: random_rigid(rng)}, source=PoseSource.LOOP_CLOSURE))
    keys = rng.choice(ledger.frame_ids, size=25, replace=False)
    new = {int(k): se3_exp(rng.normal(size=6) * 0.3) @ ledger.pose(1, int(k)) for k in keys}
    expected = reference_propagation(ledger, 1, new)
    rev = ledger.plan_correction(new, source=PoseSource.LOOP_CLOSURE)
    assert sorted(rev.set_directly) == sorted(new)
    assert len(rev.propagated) == n - 25
    ledger.commit(rev)
    np.testing.assert_allclose(ledger.poses(2), expected, rtol=0, atol=1e-12)


def test_propagate_false_changes_only_the_given_frames() -> None:
    ledger = line_ledger()
    rev = ledger.commit(ledger.plan_correction({2: Tr(2, 1, 0)}, source=PoseSource.EXTERNAL_FILE, propagate=False))
    assert dict(rev.propagated) == {}
    np.testing.assert_array_equal(rev.changed_frame_ids, [2])
    np.testing.assert_array_equal(ledger.changed_frames(0, 1), [2])
    np.testing.assert_array_equal(ledger.poses(1)[[0, 1, 3, 4]], ledger.poses(0)[[0, 1, 3, 4]])


# ==============================================================================================================
# plan / commit, rejected calls
# ==============================================================================================================


def test_plan_does_not_add_and_commit_appends() -> None:
    ledger = line_ledger()
    rev = ledger.plan_correction({4: Tr(4, 1, 0)}, source="loop_closure", note="loop 1", created_ns=42)
    assert ledger.head == 0 and len(ledger.revisions) == 1
    assert (rev.revision_id, rev.parent_id, rev.source, rev.note, rev.created_ns) == (
        1, 0, PoseSource.LOOP_CLOSURE, "loop 1", 42,
    )
    np.testing.assert_array_equal(rev.changed_frame_ids, [0, 1, 2, 3, 4])
    assert sorted(rev.set_directly) == [4] and sorted(rev.propagated) == [0, 1, 2, 3]
    assert ledger.commit(rev) is rev
    assert ledger.head == 1 and ledger.revisions[1] is rev and ledger.revision(1) is rev


def test_rejected_corrections_change_nothing() -> None:
    ledger = line_ledger()
    ledger.commit(ledger.plan_correction({4: Tr(4, 1, 0)}, source=PoseSource.LOOP_CLOSURE))
    before = snapshot(ledger)
    with pytest.raises(StoreError, match=r"2 frame\(s\) not in the pose ledger: \[42, 99\]"):
        ledger.plan_correction({99: np.eye(4), 1: np.eye(4), 42: np.eye(4)}, source=PoseSource.LOOP_CLOSURE)
    with pytest.raises(StoreError, match="parent revision 5 does not exist"):
        ledger.plan_correction({1: np.eye(4)}, source=PoseSource.LOOP_CLOSURE, parent=5)
    sheared = np.eye(4)
    sheared[0, 1] = 0.3
    with pytest.raises(TransformError, match="frame 1"):
        ledger.plan_correction({0: np.eye(4), 1: sheared}, source=PoseSource.LOOP_CLOSURE)
    with pytest.raises(StoreError, match="non-empty"):
        ledger.plan_correction({}, source=PoseSource.LOOP_CLOSURE)
    with pytest.raises(StoreError, match="pose source"):
        ledger.plan_correction({1: np.eye(4)}, source="gps")
    with pytest.raises(StoreError, match="rollback target revision 7"):
        ledger.plan_rollback(7)
    with pytest.raises(StoreError):
        ledger.revision(2)
    with pytest.raises(StoreError):
        ledger.poses(-1)
    with pytest.raises(StoreError, match="frame 17"):
        ledger.pose(1, 17)
    assert_same_snapshot(before, snapshot(ledger))


def test_commit_rechecks_the_plan() -> None:
    ledger = line_ledger()
    first = ledger.plan_correction({1: Tr(1, 1, 0)}, source=PoseSource.LOOP_CLOSURE)
    stale = ledger.plan_correction({2: Tr(2, 1, 0)}, source=PoseSource.LOOP_CLOSURE)
    ledger.commit(first)
    before = snapshot(ledger)
    with pytest.raises(StoreError, match="next revision id is 2"):
        ledger.commit(stale)
    foreign = Revision(2, 1, PoseSource.EXTERNAL_FILE, 0, set_directly={77: np.eye(4)})
    with pytest.raises(StoreError, match=r"frames \[77\] are not in the pose ledger"):
        ledger.commit(foreign)
    with pytest.raises(StoreError, match="expects a Revision"):
        ledger.commit({"revision_id": 2})  # type: ignore[arg-type]
    assert_same_snapshot(before, snapshot(ledger))


def test_revision_is_immutable_and_validated() -> None:
    rev = Revision(1, 0, PoseSource.LOG, 5, set_directly={3: Tr(1, 2, 3)}, propagated={4: np.eye(4)})
    with pytest.raises(dataclasses.FrozenInstanceError):
        rev.note = "x"  # type: ignore[misc]
    with pytest.raises(TypeError):
        rev.set_directly[5] = np.eye(4)  # type: ignore[index]
    with pytest.raises(ValueError):
        rev.set_directly[3][0, 3] = 9.0
    np.testing.assert_array_equal(rev.changed_frame_ids, [3, 4])
    with pytest.raises(StoreError, match="both set directly and propagated"):
        Revision(1, 0, PoseSource.LOG, 0, set_directly={3: np.eye(4)}, propagated={3: np.eye(4)})
    with pytest.raises(StoreError, match="parent_id must be an earlier revision"):
        Revision(2, 2, PoseSource.LOG, 0)
    with pytest.raises(TransformError, match="frame 3"):
        Revision(1, 0, PoseSource.LOG, 0, set_directly={3: 2 * np.eye(4)})


# ==============================================================================================================
# rollback, ancestry, diff
# ==============================================================================================================


def build_history(ledger: PoseLedger, rng: np.random.Generator, n_revisions: int) -> None:
    ids = ledger.frame_ids
    for r in range(n_revisions):
        keys = rng.choice(ids, size=3, replace=False)
        head = ledger.head
        poses = {int(k): se3_exp(rng.normal(size=6) * 0.2) @ ledger.pose(head, int(k)) for k in keys}
        ledger.commit(ledger.plan_correction(poses, source=PoseSource.LOOP_CLOSURE, propagate=r % 3 != 2))


def test_chain_of_corrections_and_rollback_is_bit_identical() -> None:
    rng = np.random.default_rng(4)
    ledger = random_ledger(40, seed=4)
    build_history(ledger, rng, 12)  # more revisions than the pose cache holds
    assert ledger.head == 12
    head_bits = bits(ledger.poses(12)).copy()
    for target in (3, 0, 7):
        rev = ledger.plan_rollback(target, note=f"back to {target}", created_ns=1)
        differs = np.any(bits(ledger.poses(ledger.head)) != bits(ledger.poses(target)), axis=(1, 2))
        assert (rev.parent_id, rev.source, rev.restores) == (ledger.head, PoseSource.ROLLBACK, target)
        np.testing.assert_array_equal(sorted(rev.set_directly), ledger.frame_ids[differs])
        assert dict(rev.propagated) == {}
        ledger.commit(rev)
        np.testing.assert_array_equal(bits(ledger.poses(rev.revision_id)), bits(ledger.poses(target)))
        assert ledger.diff(target, rev.revision_id).max_translation_m == 0.0
        assert ledger.changed_frames(target, rev.revision_id, eps_m=0.0, eps_rad=0.0).size == 0
    np.testing.assert_array_equal(bits(ledger.poses(12)), head_bits)  # history is untouched
    # rolling back to where you are is an empty revision
    assert ledger.plan_rollback(ledger.head).changed_frame_ids.size == 0


def test_rollback_restores_a_one_ulp_difference() -> None:
    ledger = line_ledger()
    nudged = Tr(2, 0, 0)
    nudged[0, 3] = np.nextafter(2.0, 3.0)  # one unit in the last place
    ledger.commit(ledger.plan_correction({2: nudged}, source=PoseSource.EXTERNAL_FILE, propagate=False))
    assert ledger.changed_frames(0, 1).size == 0  # far below any epsilon ...
    rev = ledger.plan_rollback(0)
    assert sorted(rev.set_directly) == [2]  # ... but still a difference a rollback must undo
    ledger.commit(rev)
    np.testing.assert_array_equal(bits(ledger.poses(2)), bits(ledger.poses(0)))


def test_correction_based_on_an_older_parent_branches() -> None:
    ledger = line_ledger()
    A, B = Tr(2, 5, 0), Tr(3, 7, 0)
    ledger.commit(ledger.plan_correction({2: A}, source=PoseSource.LOOP_CLOSURE, propagate=False))  # 1
    ledger.commit(ledger.plan_correction({3: B}, source=PoseSource.LOOP_CLOSURE, propagate=False))  # 2 on 1
    # 3 branches from 1: revision 2's change of frame 3 is not on its ancestry
    D = Tr(0, 0, 1)
    rev3 = ledger.commit(ledger.plan_correction({4: D @ Tr(4, 0, 0)}, source=PoseSource.LOOP_CLOSURE, parent=1))
    assert rev3.parent_id == 1
    P3 = ledger.poses(3)
    # propagation used revision 1's poses: frame 3 is its revision-0 pose moved by D, frame 2 is A moved by D
    np.testing.assert_allclose(P3[3], D @ Tr(3, 0, 0), atol=1e-15)
    np.testing.assert_allclose(P3[2], D @ A, atol=1e-15)
    np.testing.assert_array_equal(ledger.poses(2)[3], B)
    # without propagation the branch keeps revision 1's frame 2 and the revision-0 frame 3
    rev4 = ledger.commit(
        ledger.plan_correction({4: Tr(9, 9, 9)}, source=PoseSource.LOOP_CLOSURE, parent=1, propagate=False)
    )
    P4 = ledger.poses(rev4.revision_id)
    np.testing.assert_array_equal(P4[2], A)
    np.testing.assert_array_equal(P4[3], Tr(3, 0, 0))
    np.testing.assert_array_equal(P4[4], Tr(9, 9, 9))
    # pose(r, f) agrees with poses(r) everywhere
    for r in range(ledger.head + 1):
        for i, f in enumerate(ledger.frame_ids.tolist()):
            np.testing.assert_array_equal(ledger.pose(r, f), ledger.poses(r)[i])


def test_frames_added_after_a_revision_keep_their_revision0_pose() -> None:
    ledger = line_ledger()
    ledger.commit(ledger.plan_correction({0: Tr(0, 1, 0)}, source=PoseSource.LOOP_CLOSURE))
    assert ledger.poses(1).shape == (5, 4, 4)
    ledger.add_frame(10, 10 * S, Tr(10, 0, 0))
    P = ledger.poses(1)
    assert P.shape == (6, 4, 4)
    np.testing.assert_array_equal(P[-1], Tr(10, 0, 0))
    np.testing.assert_array_equal(ledger.pose(1, 10), Tr(10, 0, 0))


def test_a_revision_places_the_frames_it_was_made_over_not_those_stored_later() -> None:
    """Hostile trial 17 B1: frames stored after revision 1 (an append, a resume) are not among its members once a later
    revision exists; the head alone shows them (at revision-0 poses) until one does; a rollback to revision 1 leaves
    them out again, and a correction's propagation never moves a frame its parent does not place."""
    ledger = line_ledger()
    ledger.commit(ledger.plan_correction({0: Tr(0, 1, 0), 4: Tr(4, 1, 0)}, source=PoseSource.LOOP_CLOSURE))
    np.testing.assert_array_equal(ledger.members(1), [0, 1, 2, 3, 4])
    for f in (10, 11):
        ledger.add_frame(f, f * S, Tr(f, 0, 0))
    np.testing.assert_array_equal(ledger.members(1), [0, 1, 2, 3, 4, 10, 11])  # the head shows frames stored since
    np.testing.assert_array_equal(ledger.members(1, later=False), [0, 1, 2, 3, 4])
    np.testing.assert_array_equal(ledger.members(0), [0, 1, 2, 3, 4, 10, 11])
    ledger.commit(ledger.plan_correction({10: Tr(10, 1, 0), 11: Tr(11, 1, 0)}, source=PoseSource.LOOP_CLOSURE,
                                         propagate=False))
    np.testing.assert_array_equal(ledger.members(1), [0, 1, 2, 3, 4])  # no longer the head: its own frames only
    np.testing.assert_array_equal(ledger.members(2), [0, 1, 2, 3, 4, 10, 11])
    d = ledger.diff(1, 2)
    np.testing.assert_array_equal(d.frame_ids, [0, 1, 2, 3, 4])  # over the frames both place
    assert d.n_changed == 0
    rollback = ledger.commit(ledger.plan_rollback(1))
    np.testing.assert_array_equal(rollback.frames, [0, 1, 2, 3, 4])
    assert rollback.n_changed == 0  # the poses of revision 1's frames are those of revision 2: only the frames change
    np.testing.assert_array_equal(ledger.members(3), [0, 1, 2, 3, 4])
    # a correction on the rollback: its propagation stays on the rollback's frames; a frame it sets joins them
    rev = ledger.commit(ledger.plan_correction({0: Tr(0, 2, 0)}, source=PoseSource.EXTERNAL_FILE))
    np.testing.assert_array_equal(rev.frames, [0, 1, 2, 3, 4])
    assert 10 not in rev.propagated and 11 not in rev.propagated
    rev = ledger.commit(ledger.plan_correction({11: Tr(11, 3, 0)}, source=PoseSource.EXTERNAL_FILE, propagate=False))
    np.testing.assert_array_equal(rev.frames, [0, 1, 2, 3, 4, 11])
    # a rollback to the head drops what was stored after it (an interrupted append, abandoned)
    ledger.add_frame(20, 20 * S, Tr(20, 0, 0))
    assert 20 in ledger.members(ledger.head)
    ledger.commit(ledger.plan_rollback(ledger.head))
    assert 20 not in ledger.members(ledger.head)


def test_revisions_without_recorded_frames_take_the_frames_stored_before_them() -> None:
    """Revisions written before membership was recorded: a correction places the frames the ledger held when it was
    committed (store order), a rollback its target's; the JSON round trip keeps ``frames`` (ranges) or its absence."""
    ledger = line_ledger()
    ledger.commit(Revision(1, 0, PoseSource.LOOP_CLOSURE, 1, set_directly={0: Tr(0, 1, 0)}))
    ledger.add_frame(7, 7 * S, Tr(7, 0, 0))
    ledger.commit(Revision(2, 1, PoseSource.LOOP_CLOSURE, 2, set_directly={7: Tr(7, 1, 0)}))
    ledger.commit(Revision(3, 2, PoseSource.ROLLBACK, 3, set_directly={}, restores=1))
    np.testing.assert_array_equal(ledger.members(1), [0, 1, 2, 3, 4])
    np.testing.assert_array_equal(ledger.members(2), [0, 1, 2, 3, 4, 7])
    np.testing.assert_array_equal(ledger.members(3), [0, 1, 2, 3, 4])
    legacy = ledger.revision(2).to_json()
    assert "frames" not in legacy and Revision.from_json(legacy).frames is None
    made = ledger.plan_correction({0: Tr(0, 5, 0)}, source=PoseSource.LOOP_CLOSURE, propagate=False)
    data = made.to_json()
    assert data["frames"] == [[0, 4]]
    assert Revision.from_json(data) == made
    with pytest.raises(StoreError, match="changes frames \\[9\\] that are not among its frames"):
        Revision(5, 4, PoseSource.LOG, 5, set_directly={9: Tr(9, 0, 0)}, frames=[0, 1])
    with pytest.raises(StoreError, match="frames must be a list of"):
        Revision.from_json(data | {"frames": [[4, 0]]})
    bad = Revision(5, 4, PoseSource.LOG, 5, set_directly={0: Tr(0, 0, 1)}, frames=[0, 99])
    with pytest.raises(StoreError, match="its frames \\[99\\] are not in the pose ledger"):
        ledger.commit(dataclasses.replace(bad, revision_id=ledger.head + 1, parent_id=ledger.head))


def test_diff_numbers() -> None:
    ledger = line_ledger()
    # frame 2 turns 30 deg about its own x axis and moves by (3, 4, 0): 5 m
    moved = Tr(3, 4, 0) @ Tr(2, 0, 0) @ Rx(30.0)
    # frame 3 turns by only 1e-8 rad (arccos of the trace would lose this)
    tiny = Tr(3, 0, 0) @ geometry.make_transform(Rotation.from_rotvec([0, 0, 1e-8]))
    ledger.commit(ledger.plan_correction({2: moved, 3: tiny}, source=PoseSource.LOOP_CLOSURE, propagate=False))
    d = ledger.diff(0, 1)
    np.testing.assert_array_equal(d.frame_ids, [0, 1, 2, 3, 4])
    np.testing.assert_allclose(d.translation_m, [0, 0, 5, 0, 0], atol=1e-15)
    np.testing.assert_allclose(d.rotation_deg, [0, 0, 30, math.degrees(1e-8), 0], rtol=1e-7, atol=1e-13)
    assert d.max_translation_m == pytest.approx(5.0, abs=1e-15)
    assert d.max_rotation_deg == pytest.approx(30.0, abs=1e-12)
    np.testing.assert_array_equal(ledger.changed_frames(0, 1), [2, 3])
    np.testing.assert_array_equal(ledger.changed_frames(0, 1, eps_rad=1e-6), [2])
    np.testing.assert_array_equal(ledger.changed_frames(1, 0, eps_m=4.9, eps_rad=math.radians(31)), [2])
    np.testing.assert_array_equal(ledger.changed_frames(1, 0, eps_m=5.1, eps_rad=math.radians(31)), [])


# ==============================================================================================================
# JSON
# ==============================================================================================================


def test_revision_json_round_trip_is_bit_identical() -> None:
    rng = np.random.default_rng(5)
    ledger = random_ledger(30, seed=5)
    build_history(ledger, rng, 5)
    ledger.commit(ledger.plan_rollback(2, note="undo ünïcode loop"))
    for rev in ledger.revisions:
        text = json.dumps(rev.to_json())
        back = Revision.from_json(json.loads(text))
        assert back == rev
        assert (back.revision_id, back.parent_id, back.source, back.created_ns, back.note, back.restores) == (
            rev.revision_id, rev.parent_id, rev.source, rev.created_ns, rev.note, rev.restores,
        )
        assert sorted(back.set_directly) == sorted(rev.set_directly)
        assert sorted(back.propagated) == sorted(rev.propagated)
        for mine, theirs in ((rev.set_directly, back.set_directly), (rev.propagated, back.propagated)):
            for fid, T in mine.items():
                np.testing.assert_array_equal(bits(theirs[fid]), bits(T))
        assert json.dumps(back.to_json()) == text
    json_matrix = ledger.revision(1).to_json()["set_directly"]["T_world_sensor"][0]
    assert len(json_matrix) == 16 and all(type(x) is float for x in json_matrix)


def test_replaying_json_revisions_rebuilds_identical_poses() -> None:
    """What the store does on load: frames first, then every persisted revision committed in order."""
    rng = np.random.default_rng(6)
    ledger = random_ledger(25, seed=6)
    build_history(ledger, rng, 6)
    ledger.commit(ledger.plan_rollback(1))
    saved = [json.dumps(r.to_json()) for r in ledger.revisions[1:]]
    replay = PoseLedger(created_ns=0)
    for i, fid in enumerate(ledger.frame_ids.tolist()):
        replay.add_frame(fid, int(ledger.stamps_ns[i]), ledger.poses(0)[i])
    for text in saved:
        replay.commit(Revision.from_json(json.loads(text)))
    assert replay.head == ledger.head
    for r in range(ledger.head + 1):
        np.testing.assert_array_equal(bits(replay.poses(r)), bits(ledger.poses(r)))


def test_damaged_json_is_a_store_error() -> None:
    good = Revision(1, 0, PoseSource.LOG, 5, set_directly={3: Tr(1, 2, 3)}).to_json()
    Revision.from_json(good)

    def damaged(**changes) -> dict:
        data = json.loads(json.dumps(good))
        data.update(changes)
        return data

    cases = [
        damaged(schema_version=99),
        {k: v for k, v in good.items() if k != "source"},
        damaged(source="gps"),
        damaged(revision_id="1"),
        damaged(set_directly={"frame_ids": [3], "T_world_sensor": [[1.0] * 15]}),
        damaged(set_directly={"frame_ids": [3, 4], "T_world_sensor": [[1.0] * 16]}),
        damaged(set_directly={"frame_ids": [3], "T_world_sensor": [[2.0] * 16]}),
        damaged(set_directly={"frame_ids": [3.0], "T_world_sensor": good["set_directly"]["T_world_sensor"]}),
        damaged(propagated=[]),
    ]
    for data in cases:
        with pytest.raises(StoreError):
            Revision.from_json(data)


# ==============================================================================================================
# trajectory matching
# ==============================================================================================================


def a_trajectory(stamps_ns: list[int], seed: int = 7) -> Trajectory:
    rng = np.random.default_rng(seed)
    poses = np.stack([random_rigid(rng) for _ in stamps_ns])
    return Trajectory(np.asarray(stamps_ns, dtype=np.int64), poses)


def test_match_by_index_with_a_slice_of_frames() -> None:
    traj = a_trajectory([i * 100 * MS for i in range(30)])
    ids = np.arange(10, 20)
    m = match_trajectory(traj, ids, ids * 100 * MS, match="index")
    assert sorted(m.poses) == list(range(10, 20))
    for fid, T in m.poses.items():
        np.testing.assert_array_equal(T, traj.poses[fid])
    assert m.rows == {i: i for i in range(10, 20)}
    assert m.unmatched_rows == list(range(10)) + list(range(20, 30))
    assert len(m.unmatched_rows) == 20
    assert m.unmatched_frames == []
    # frames beyond the end of the file have no row; stamps are not needed by index
    m = match_trajectory(traj, np.arange(25, 35), None, match=PoseMatchMode.INDEX)
    assert sorted(m.poses) == list(range(25, 30))
    assert m.unmatched_frames == list(range(30, 35))
    assert m.unmatched_rows == list(range(25))


def test_matched_poses_feed_a_correction() -> None:
    traj = a_trajectory([i * 100 * MS for i in range(30)])
    ledger = PoseLedger(created_ns=0)
    for fid in range(10, 20):
        ledger.add_frame(fid, fid * 100 * MS, np.eye(4))
    m = match_trajectory(traj, ledger.frame_ids, ledger.stamps_ns, match="index")
    rev = ledger.commit(ledger.plan_correction(m.poses, source=PoseSource.EXTERNAL_FILE, propagate=False))
    np.testing.assert_allclose(ledger.poses(rev.revision_id), traj.poses[10:20], atol=1e-15)


def test_match_by_stamp_with_tolerance_and_contested_rows() -> None:
    # rows are not in stamp order
    row_stamps_ms = [500, 0, 300, 100, 400, 200]
    traj = a_trajectory([s * MS for s in row_stamps_ms])
    frames_ms = {
        1: 0,  # row 1, exact
        2: 103,  # row 3, 3 ms off
        3: 198,  # row 5, 2 ms off: closer than frame 4, keeps the row
        4: 205,  # row 5, 5 ms off: loses it -> unmatched
        5: 350,  # 50 ms from rows 2 and 4 -> unmatched
        6: 509,  # row 0, 9 ms off
        7: 611,  # nothing within 10 ms
        8: 396,  # row 4, 4 ms off: tie with frame 9, the lower id keeps the row
        9: 404,
    }
    ids = np.array(list(frames_ms), dtype=np.int64)
    stamps = np.array(list(frames_ms.values()), dtype=np.int64) * MS
    m = match_trajectory(traj, ids, stamps, match="stamp")
    assert m.rows == {1: 1, 2: 3, 3: 5, 6: 0, 8: 4}
    for fid, row in m.rows.items():
        np.testing.assert_array_equal(m.poses[fid], traj.poses[row])
    assert m.unmatched_frames == [4, 5, 7, 9]
    assert m.unmatched_rows == [2]
    assert m.n_matched == 5
    # halfway between two rows: the earlier stamp wins
    m = match_trajectory(traj, [1], [250 * MS], match="stamp", max_dt_ns=50 * MS)
    assert m.rows == {1: 5}
    # the tolerance is inclusive
    assert 6 in match_trajectory(traj, ids, stamps, match=PoseMatchMode.STAMP, max_dt_ns=9 * MS).rows
    narrow = match_trajectory(traj, ids, stamps, match=PoseMatchMode.STAMP, max_dt_ns=8 * MS)
    assert 6 not in narrow.rows and 6 in narrow.unmatched_frames and 0 in narrow.unmatched_rows


def test_match_rejects_bad_arguments() -> None:
    traj = a_trajectory([0, MS])
    with pytest.raises(StoreError, match="unknown pose match mode"):
        match_trajectory(traj, [0], [0], match="nearest")
    with pytest.raises(StoreError, match="needs the frames' stamps_ns"):
        match_trajectory(traj, [0], None, match="stamp")
    with pytest.raises(StoreError, match="1 frame ids but 2 stamps"):
        match_trajectory(traj, [0], [0, 1], match="stamp")
    with pytest.raises(StoreError, match="duplicates"):
        match_trajectory(traj, [0, 0], [0, 1], match="index")


# ==============================================================================================================
# real data: 7-Scenes redkitchen ground-truth poses as revision 0
# ==============================================================================================================

FRAME_PERIOD_NS = 33_333_333  # 7-Scenes is recorded at 30 Hz; the files carry no stamps


def sevenscenes_ledger(sevenscenes_dir: Path, n: int = 100) -> PoseLedger:
    ledger = PoseLedger(PoseSource.GROUND_TRUTH, created_ns=0)
    for i in range(n):
        ledger.add_frame(i, i * FRAME_PERIOD_NS, np.loadtxt(sevenscenes_dir / f"frame-{i:06d}.pose.txt"))
    return ledger


def test_constant_correction_of_keyframes_applies_to_every_frame(sevenscenes_dir: Path) -> None:
    ledger = sevenscenes_ledger(sevenscenes_dir)
    O = ledger.poses(0)
    C = geometry.make_transform(Rotation.from_rotvec([0.01, -0.03, 0.02]), [0.05, -0.02, 0.01])
    keyframes = list(range(0, 100, 10))
    rev = ledger.commit(
        ledger.plan_correction({k: C @ O[k] for k in keyframes}, source=PoseSource.LOOP_CLOSURE, note="offset")
    )
    assert sorted(rev.set_directly) == keyframes
    assert sorted(rev.propagated) == sorted(set(range(100)) - set(keyframes))
    P = ledger.poses(rev.revision_id)
    for f in range(100):  # interpolated frames and the single-sided tail 91..99 alike
        np.testing.assert_allclose(P[f], C @ O[f], rtol=0, atol=1e-12)
    d = ledger.diff(0, rev.revision_id)
    assert d.max_rotation_deg == pytest.approx(math.degrees(np.linalg.norm([0.01, -0.03, 0.02])), abs=1e-9)


def test_screw_correction_of_keyframes_is_interpolated_exactly(sevenscenes_dir: Path) -> None:
    # a correction growing at constant velocity in time, C(s) = exp(s xi): the keyframes get C(s_k) and
    # every other frame must come out with C(s_f), since screw interpolation is exact for such motion
    ledger = sevenscenes_ledger(sevenscenes_dir)
    O = ledger.poses(0)
    xi = np.array([0.3, -0.1, 0.05, 0.02, 0.15, -0.25])
    s = ledger.stamps_ns / ledger.stamps_ns[-1]
    keyframes = list(range(0, 100, 10)) + [99]
    rev = ledger.commit(
        ledger.plan_correction({k: se3_exp(s[k] * xi) @ O[k] for k in keyframes}, source=PoseSource.LOOP_CLOSURE)
    )
    P = ledger.poses(rev.revision_id)
    for f in range(100):
        np.testing.assert_allclose(P[f], se3_exp(s[f] * xi) @ O[f], rtol=0, atol=1e-12)
    # rolling back restores the ground truth bit for bit
    back = ledger.commit(ledger.plan_rollback(0))
    assert sorted(back.set_directly) == list(range(1, 100))  # frame 0 had C(0) = I: never changed
    np.testing.assert_array_equal(bits(ledger.poses(back.revision_id)), bits(O))


def test_frames_added_between_corrections_get_their_own_pose_in_every_cached_revision() -> None:
    # a live stack appends frames between corrections (ids out of order too): the cached revisions grow with the
    # new frames' revision-0 poses and must equal a ledger replayed from scratch in one go
    rng = np.random.default_rng(11)
    live = PoseLedger()
    added: list[tuple[int, int, np.ndarray]] = []
    plans: list[tuple[int, dict[int, np.ndarray], int | None]] = []  # (frames known, poses, parent)
    ids = rng.permutation(60) * 3
    for k, fid in enumerate(ids):
        T = random_rigid(rng)
        live.add_frame(int(fid), int(fid) * MS, T)
        added.append((int(fid), int(fid) * MS, T))
        if k % 7 == 6:  # a correction of some known frames, sometimes on an older parent (a branch)
            known = [a[0] for a in added]
            keys = rng.choice(known, size=min(3, len(known)), replace=False)
            poses = {int(f): random_rigid(rng) for f in keys}
            parent = int(rng.integers(0, live.head + 1)) if k % 3 == 0 else None
            live.commit(live.plan_correction(poses, source=PoseSource.LOOP_CLOSURE, parent=parent))
            plans.append((len(added), poses, parent))
        for r in range(live.head + 1):  # touch every revision, so the cache holds entries built before later frames
            live.poses(r)
    replay = PoseLedger()
    done = 0
    for n_known, poses, parent in plans:
        for fid, stamp, T in added[done:n_known]:
            replay.add_frame(fid, stamp, T)
        done = n_known
        replay.commit(replay.plan_correction(poses, source=PoseSource.LOOP_CLOSURE, parent=parent))
    for fid, stamp, T in added[done:]:
        replay.add_frame(fid, stamp, T)
    assert live.head == replay.head == len(plans) >= 8
    assert np.array_equal(live.frame_ids, replay.frame_ids)
    for r in range(live.head + 1):
        assert np.array_equal(live.poses(r), replay.poses(r)), f"revision {r}"
        for fid in live.frame_ids[::9]:
            assert np.array_equal(live.pose(r, int(fid)), live.poses(r)[np.searchsorted(live.frame_ids, fid)])


def test_rotation_angles_are_precise_for_tiny_and_large_angles() -> None:
    # arccos of the trace loses everything below ~1e-6 deg (it returned 0.0 for 1e-7 deg); atan2 keeps it
    for deg in (1e-9, 1e-7, 1e-3, 1.0, 90.0, 179.0):
        axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
        T = geometry.make_transform(Rotation.from_rotvec(np.radians(deg) * axis))
        A = random_rigid(np.random.default_rng(int(deg * 1e9) % 1000))
        assert geometry.rotation_angle_deg(A, A @ T) == pytest.approx(deg, rel=1e-6)
    stack = np.stack([Rz(d) for d in (0.0, 1e-6, 45.0)])
    np.testing.assert_allclose(np.degrees(geometry.relative_rotation_angle_rad(np.eye(3), stack)), [0.0, 1e-6, 45.0],
                               rtol=1e-9, atol=0)
