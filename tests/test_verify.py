"""The independent check of double-wall regions (``driftmap.diagnostics.verify``): on the synthetic log with an
injected step (exact ground truth) it must confirm and measure what was injected, and it must reject regions
whose claimed separation is not in the frames; on 7-Scenes redkitchen it must confirm the known ~4.5 cm jump of
the KinectFusion reference poses between frames 121 and 122, and rarely confirm a claim made at random."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from driftmap.cli import app
from driftmap.demo import embedded_log_path
from driftmap.diagnostics import perturb
from driftmap.diagnostics.double_wall import DiagnosticCloud, DoubleWallRegion, detect_double_walls
from driftmap.diagnostics.verify import RegionCheck, is_confirmed, verification_summary, verify_regions
from driftmap.errors import ConfigError, StoreError
from driftmap.sources.synthetic import SyntheticLog
from driftmap.store.frame_store import FrameStore

STEP_INDEX = 30
STEP_M = np.array([0.025, -0.02, 0.01])  # oblique: the floor and walls of both orientations see a different part
GT_JUMP_FRAME_ID = 125  # the KinectFusion poses jump between frames 121 and 122 (first stored frame after: 125)


def region(center: np.ndarray, normal: np.ndarray, offset_m: float, frames_a, frames_b, n_voxels: int = 1) -> DoubleWallRegion:
    return DoubleWallRegion(center_m=np.asarray(center, float), normal=np.asarray(normal, float), separation_m=abs(offset_m),
                            separation_sigma_m=0.002, offset_b_minus_a_m=offset_m, frames_a=np.asarray(frames_a, np.int64),
                            frames_b=np.asarray(frames_b, np.int64), stamp_ns_a=(0, 0), stamp_ns_b=(0, 0),
                            n_voxels=n_voxels, voxel_sizes_m=(0.1,), n_points=100)


# ---------------------------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def synthetic_store(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, int, int]:
    """The embedded synthetic log stored at full resolution; revision 1 = exact poses, revision 2 = a step."""
    path = tmp_path_factory.mktemp("verify") / "synthetic"
    log = SyntheticLog(embedded_log_path())
    gt = log.ground_truth().poses
    with FrameStore.create(path) as store:
        for frame in log:
            store.append(frame)
        ids = store.frame_ids.tolist()
        exact = store.add_revision(dict(zip(ids, gt)), source="external_file", propagate=False).revision_id
        stepped = store.add_revision(dict(zip(ids, perturb.translation_step(gt, STEP_INDEX, STEP_M))), source="external_file",
                                     parent=exact, propagate=False).revision_id
    return path, exact, stepped


@pytest.fixture(scope="module")
def synthetic_regions(synthetic_store) -> tuple[FrameStore, int, int, list[DoubleWallRegion], int]:
    path, exact, stepped = synthetic_store
    store = FrameStore.open(path)
    cloud = DiagnosticCloud.from_store(store)
    assert np.array_equal(cloud.frame_ids, store.frame_ids)
    clean = detect_double_walls(cloud.place(store.poses(exact)))
    assert clean.voxels_evaluated > 1000
    result = detect_double_walls(cloud.place(store.poses(stepped)))
    return store, exact, stepped, result.regions, len(clean.regions)


@pytest.fixture(scope="module")
def moved_patch(synthetic_regions, tmp_path_factory: pytest.TempPathFactory) -> tuple[FrameStore, DoubleWallRegion, np.ndarray]:
    """The synthetic log with exact poses, but from frame STEP_INDEX on a 0.35 m patch of one wall stands
    4 cm proud of it (a moved board): a real double layer in the map that no pose explains."""
    _, exact, _, step_regions, _ = synthetic_regions
    wall = max((r for r in step_regions if abs(r.normal[2]) < 0.3), key=lambda r: r.n_voxels)
    center, normal = np.asarray(wall.center_m), np.asarray(wall.normal) / np.linalg.norm(wall.normal)
    log = SyntheticLog(embedded_log_path())
    gt = log.ground_truth().poses

    def world(index: int, frame) -> np.ndarray:
        return frame.points_sensor.astype(np.float64) @ gt[index][:3, :3].T + gt[index][:3, 3]

    # the region centre is a mean of voxel centres: snap it onto the wall surface along the normal
    along = []
    for index, frame in enumerate(log):
        d = world(index, frame) - center
        near = (np.linalg.norm(d - np.outer(d @ normal, normal), axis=1) <= 0.35) & (np.abs(d @ normal) <= 0.3)
        along.append(d[near] @ normal)
    center = center + float(np.median(np.concatenate(along))) * normal
    path = tmp_path_factory.mktemp("verify") / "moved"
    with FrameStore.create(path) as store:
        for index, frame in enumerate(log):
            if index >= STEP_INDEX:
                T = gt[index]
                w = world(index, frame)
                d = w - center
                on_patch = (np.linalg.norm(d - np.outer(d @ normal, normal), axis=1) <= 0.35) & (np.abs(d @ normal) <= 0.05)
                w[on_patch] += 0.04 * normal
                frame = frame.with_points(((w - T[:3, 3]) @ T[:3, :3]).astype(np.float32))
            store.append(frame)
        ids = store.frame_ids.tolist()
        rev = store.add_revision(dict(zip(ids, gt)), source="external_file", propagate=False).revision_id
    store = FrameStore.open(path)
    cloud = DiagnosticCloud.from_store(store)
    regions = detect_double_walls(cloud.place(store.poses(rev))).regions
    return store, regions, normal


@pytest.fixture(scope="module")
def kitchen_regions(kitchen: FrameStore, kitchen_cloud: DiagnosticCloud) -> tuple[DiagnosticCloud, list[DoubleWallRegion]]:
    return kitchen_cloud, detect_double_walls(kitchen_cloud.place(kitchen.poses(0))).regions


# ---------------------------------------------------------------------------------------------- synthetic


def test_injected_step_regions_are_confirmed_and_measured(synthetic_regions) -> None:
    """Every region the detector finds after an oblique 3.3 cm step is confirmed, and the offset measured from
    the stored frames is the step along the region normal within max(5 mm, 15 %)."""
    store, _, stepped, regions, _ = synthetic_regions
    assert len(regions) >= 3 and sum(r.n_voxels for r in regions) >= 100
    checks = verify_regions(store, stepped, regions)
    assert len(checks) == len(regions)
    normals = set()
    for c, r in zip(checks, regions):
        expected = float(STEP_M @ r.normal)
        assert c.confirmed, (c, expected)
        assert c.note is None or c.note.startswith("pose or local: undecidable"), c.note
        assert abs(c.offset_b_minus_a_m - expected) <= max(0.005, 0.15 * abs(expected)), (c, expected)
        assert abs(c.offset_reverse_m - expected) <= max(0.005, 0.15 * abs(expected))
        if c.offset_icp_m is not None:
            assert abs(c.offset_icp_m - expected) <= max(0.005, 0.15 * abs(expected))
        assert c.n_points_a >= 100 and c.n_points_b >= 100 and c.n_correspondences >= 50
        assert 1 <= len(c.frames_a_used) <= 6 and 1 <= len(c.frames_b_used) <= 6
        assert set(c.frames_a_used) <= set(r.frames_a.tolist()) and set(c.frames_b_used) <= set(r.frames_b.tolist())
        normals.add(int(np.argmax(np.abs(r.normal))))
    assert normals == {0, 1, 2}  # walls of both orientations and the floor were checked


def test_injected_step_is_explained_by_the_poses(synthetic_regions) -> None:
    """A pose step moves everything the frames see: the surroundings of every confirmed region, aligned rigidly,
    explain its offset (``pose_explained``), and the summary counts no local region."""
    store, _, stepped, regions, _ = synthetic_regions
    checks = verify_regions(store, stepped, regions)
    decided = [(c, r) for c, r in zip(checks, regions) if c.pose_explained is not None]
    assert len(decided) >= 0.5 * len(regions), [c.note for c in checks]
    for c, r in decided:
        expected = float(STEP_M @ r.normal)
        assert c.pose_explained is True, (c, expected)
        assert abs(c.context_offset_m - expected) <= max(0.01, 0.35 * abs(expected)), (c, expected)
    for c in checks:
        assert c.pose_explained is not None or "surrounding points face the normal" in c.note
    summary = verification_summary(checks, regions, voxels_evaluated=10_000)
    assert summary["regions_local"] == 0 and summary["voxels_local"] == 0
    assert summary["fraction_pose"] == pytest.approx(sum(r.n_voxels for r, c in zip(regions, checks) if c.confirmed) / 10_000)
    (off,) = verify_regions(store, stepped, regions[:1], context=False)
    assert off.context_offset_m is None and off.pose_explained is None and off.confirmed


def test_moved_patch_is_confirmed_but_not_a_pose_error(moved_patch) -> None:
    """A patch that moved in the scene (exact poses) is flagged and confirmed at its 4 cm, but its surroundings
    agree: ``pose_explained`` is False, the context offset ~0, and the summary counts it as local."""
    store, regions, normal = moved_patch
    patch = [r for r in regions if abs(float(r.normal @ normal)) > 0.9]
    assert patch, [(r.separation_m, r.normal) for r in regions]
    checks = verify_regions(store, store.head, patch)
    for c, r in zip(checks, patch):
        assert c.confirmed, c
        assert abs(abs(c.offset_b_minus_a_m) - 0.04) <= 0.006, c
        assert c.pose_explained is False, c
        assert abs(c.context_offset_m) <= 0.005, c
        assert "not a pose error" in c.note
    summary = verification_summary(checks, patch, voxels_evaluated=10_000)
    assert summary["regions_local"] == len(patch) and summary["fraction_pose"] == 0.0


def test_surroundings_misaligned_by_another_amount_are_undecidable(moved_patch, monkeypatch: pytest.MonkeyPatch) -> None:
    """The pose/local call on the moved patch (measured ~4 cm) when the surroundings' rigid alignment says
    +4 cm (pose), +0.5 cm (they agree: local) or -5 cm (they are misaligned too, by another amount: neither,
    as on the real 7-Scenes loop wall, where the old rule said "local")."""
    from driftmap.diagnostics import verify

    store, regions, normal = moved_patch
    patch = [r for r in regions if abs(float(r.normal @ normal)) > 0.9][:1]
    assert patch
    measured = verify_regions(store, store.head, patch, context=False)[0].offset_b_minus_a_m
    assert measured is not None and abs(measured) > 0.03
    sign = float(np.sign(measured))
    for ctx, expected in ((measured, True), (0.005 * sign, False), (-0.05 * sign, None)):
        monkeypatch.setattr(verify, "_context_offset", lambda *a, _c=ctx, **k: (_c, None))
        (check,) = verify_regions(store, store.head, patch)
        assert check.context_offset_m == pytest.approx(ctx) and check.pose_explained is expected, check
        if expected is None:
            assert "undecidable" in check.note and "not a pose error" not in check.note


def test_exact_poses_flag_nothing_and_fabricated_regions_are_rejected(synthetic_regions) -> None:
    """With exact poses the detector flags nothing; the step's regions checked against the exact poses (claimed
    1-3 cm, really 0) and the same regions claiming 5 cm are not confirmed, and the measured offset is ~0."""
    store, exact, _, regions, n_clean = synthetic_regions
    assert n_clean == 0
    for claimed in (None, 0.05, -0.05):
        fabricated = regions if claimed is None else [dataclasses.replace(r, offset_b_minus_a_m=claimed, separation_m=abs(claimed))
                                                      for r in regions]
        checks = verify_regions(store, exact, fabricated)
        for c in checks:
            assert not c.confirmed, c
            assert abs(c.offset_b_minus_a_m) <= 0.002, c
            assert "measured" in c.note
    summary = verification_summary(checks, fabricated, voxels_evaluated=10_000)
    assert summary["regions_confirmed"] == 0 and summary["regions_checked"] == len(regions)
    assert summary["voxels_unconfirmed"] == sum(r.n_voxels for r in regions)


def test_unverifiable_and_invalid_regions(synthetic_regions) -> None:
    store, exact, _, regions, _ = synthetic_regions
    r0 = regions[0]
    empty = dataclasses.replace(r0, center_m=r0.center_m + np.array([0.0, 0.0, 50.0]))  # nothing within 0.3 m
    (c,) = verify_regions(store, exact, [empty])
    assert not c.confirmed and c.offset_b_minus_a_m is None and not c.verifiable
    assert c.n_points_a == 0 and c.n_points_b == 0 and "layer A" in c.note and "layer B" in c.note
    # a frame on both layers is used on neither: with every frame shared nothing is left
    shared = dataclasses.replace(r0, frames_b=np.union1d(r0.frames_a, r0.frames_b), frames_a=np.union1d(r0.frames_a, r0.frames_b))
    (c,) = verify_regions(store, exact, [shared])
    assert c.offset_b_minus_a_m is None and c.frames_a_used == () and c.frames_b_used == ()
    with pytest.raises(StoreError, match="frame 99999"):
        verify_regions(store, exact, [dataclasses.replace(r0, frames_b=np.array([99999]))])
    with pytest.raises(ConfigError):
        verify_regions(store, exact, regions[:1], radius_m=0.0)


def test_confirmation_rule_and_summary() -> None:
    assert is_confirmed(0.045, 0.05) and is_confirmed(-0.012, -0.01) and is_confirmed(0.0035, 0.008)
    assert not is_confirmed(-0.05, 0.05)  # wrong sign
    assert not is_confirmed(0.036, 0.05)  # 1.4 cm off; tolerance 1.25 cm
    assert not is_confirmed(0.002, 0.008)  # 6 mm off; tolerance 5 mm
    assert not is_confirmed(None, 0.05) and not is_confirmed(float("nan"), 0.05)
    regions = [region([0, 0, 0], [0, 0, 1], 0.03, [1], [2], n_voxels=n) for n in (4, 3, 5)]
    base = dict(reported_offset_m=0.03, offset_reverse_m=None, offset_icp_m=None, spread_m=None, n_points_a=0, n_points_b=0,
                n_correspondences=0, frames_a_used=(), frames_b_used=())
    checks = [RegionCheck(region_index=0, offset_b_minus_a_m=0.03, confirmed=True, **base),
              RegionCheck(region_index=1, offset_b_minus_a_m=0.0, confirmed=False, note="off", **base),
              RegionCheck(region_index=2, offset_b_minus_a_m=None, confirmed=False, note="too few", **base)]
    s = verification_summary(checks, regions, voxels_evaluated=200)
    assert s == {"regions_checked": 3, "regions_confirmed": 1, "regions_unverifiable": 1, "voxels_unconfirmed": 8,
                 "fraction_unconfirmed": 0.04, "regions_local": 0, "voxels_local": 0, "fraction_pose": 0.02}
    # a confirmed region whose surroundings do not share its offset is local: not in fraction_pose
    checks[0] = dataclasses.replace(checks[0], context_offset_m=0.001, pose_explained=False)
    s = verification_summary(checks, regions, voxels_evaluated=200)
    assert (s["regions_local"], s["voxels_local"], s["fraction_pose"], s["regions_confirmed"]) == (1, 4, 0.0, 1)
    with pytest.raises(ConfigError):
        verification_summary(checks[:2], regions, voxels_evaluated=200)


def test_cli_diagnose_verify_adds_keys_and_keeps_the_contract(synthetic_store, tmp_path: Path) -> None:
    path, _, stepped = synthetic_store
    out = tmp_path / "diag.json"
    result = CliRunner().invoke(app, ["diagnose", str(path), "--revision", str(stepped), "--json", str(out),
                                      "--points-per-frame", "3000", "--verify"])
    assert result.exit_code == 0, result.output
    data = json.loads(out.read_text())
    dw = data["double_wall"]
    assert {"voxels_evaluated", "voxels_flagged", "fraction_flagged", "median_separation_m", "regions", "per_scale"} <= dw.keys()
    assert dw["regions"], "the step must be flagged"
    for r in dw["regions"]:
        assert {"center_m", "normal", "separation_m", "separation_sigma_m", "frames_a", "frames_b", "stamp_ns_a", "stamp_ns_b",
                "offset_b_minus_a_m", "n_voxels", "voxel_sizes_m", "n_points"} <= r.keys()
        v = r["verification"]
        assert {"offset_b_minus_a_m", "confirmed", "n_points_a", "n_points_b", "note"} <= v.keys()
        assert isinstance(v["confirmed"], bool) and isinstance(v["n_points_a"], int)
    ver = dw["verified"]
    unconfirmed = sum(r["n_voxels"] for r in dw["regions"] if not r["verification"]["confirmed"])
    assert ver["regions_checked"] == len(dw["regions"])
    assert ver["regions_confirmed"] == sum(r["verification"]["confirmed"] for r in dw["regions"])
    assert ver["voxels_unconfirmed"] == unconfirmed
    assert ver["fraction_unconfirmed"] == pytest.approx(unconfirmed / dw["voxels_evaluated"])
    assert ver["regions_confirmed"] >= 0.8 * ver["regions_checked"]
    assert "regions confirmed (Open3D)" in result.output
    # without --verify the JSON has no verification keys
    plain = tmp_path / "plain.json"
    result = CliRunner().invoke(app, ["diagnose", str(path), "--revision", str(stepped), "--json", str(plain),
                                      "--points-per-frame", "3000"])
    assert result.exit_code == 0, result.output
    dw = json.loads(plain.read_text())["double_wall"]
    assert "verified" not in dw and all("verification" not in r for r in dw["regions"])


# ---------------------------------------------------------------------------------------------- 7-Scenes


def test_kitchen_reference_pose_jump_is_confirmed(kitchen: FrameStore, kitchen_regions) -> None:
    """The regions the detector flags across the 121/122 jump of the KinectFusion poses are real: the stored
    frames, placed with the data set's poses, are 3-7 cm apart there."""
    _, regions = kitchen_regions
    jump = [r for r in regions if (r.frames_a.max() <= 120 and r.frames_b.min() >= GT_JUMP_FRAME_ID)
            or (r.frames_b.max() <= 120 and r.frames_a.min() >= GT_JUMP_FRAME_ID)]
    assert jump, "the detector must flag the known jump"
    checks = verify_regions(kitchen, 0, jump)
    for c, r in zip(checks, jump):
        assert c.confirmed, c
        assert 0.03 <= abs(c.offset_b_minus_a_m) <= 0.07, c
        assert c.pose_explained is True, c  # a jump of the poses: the surroundings are off by as much
        assert np.sign(c.offset_b_minus_a_m) == np.sign(r.offset_b_minus_a_m)
        # the claim doubled or reversed is rejected on the same frames
        for wrong in (2.0 * r.offset_b_minus_a_m, -r.offset_b_minus_a_m):
            (w,) = verify_regions(kitchen, 0, [dataclasses.replace(r, offset_b_minus_a_m=wrong)])
            assert not w.confirmed


def test_kitchen_random_claims_are_rarely_confirmed(kitchen: FrameStore, kitchen_regions) -> None:
    """At random surface spots, with the frames that saw the spot split in time at their median, a claimed
    +-3 cm offset is confirmed at <= 10 % of the spots (measured: 0 of 60), and the typical measured offset is
    small (median |offset| <= 1 cm; measured 0.3 cm)."""
    cloud, _ = kitchen_regions
    placed = cloud.place(kitchen.poses(0))
    rng = np.random.default_rng(0)
    spots = []
    for k in rng.choice(len(placed.points_world), 300, replace=False):
        c, n = placed.points_world[k], placed.normals_world[k]
        near = (np.linalg.norm(placed.points_world - c, axis=1) < 0.1) & (np.abs(placed.normals_world @ n) > 0.9)
        frames = np.unique(placed.frame_ids[placed.frame_index[near]])
        if len(frames) >= 6:
            med = np.median(frames)
            spots.append(region(c, n, 0.03 if len(spots) % 2 else -0.03, frames[frames <= med], frames[frames > med]))
        if len(spots) == 30:
            break
    assert len(spots) == 30
    checks = verify_regions(kitchen, 0, spots)
    measured = np.array([c.offset_b_minus_a_m for c in checks if c.verifiable])
    assert len(measured) >= 25
    assert sum(c.confirmed for c in checks) <= 3
    assert np.median(np.abs(measured)) <= 0.01
