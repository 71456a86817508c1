"""Change vs misalignment (issue 26; docs/merge.md): two sessions of the synthetic room, the second after the world
changed (the door closed, the chair moved: ``synth --door-open`` / ``--move-chair``), each built with its true
poses, merged, and diagnosed as a user does. The door and the chair's old and new places are reported ``changed``
(and nothing else); a 3 cm misalignment of the second session's poses is reported as double walls 3 cm apart, never
as a change."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from cli_run import one_error, run_cli

from driftmap.diagnostics.changes import ChangeConfig, session_changes
from driftmap.errors import ConfigError
from driftmap.pipeline.merge import SESSION_ID_STRIDE, store_sessions
from driftmap.sources.synthetic import SyntheticLogConfig, generate_synthetic_log
from driftmap.sources.synthetic_scene import CHAIR_MOVE_M, scene_boxes
from driftmap.store.frame_store import FrameStore

#: the room at half resolution, once round the circle (1.1 turns, 60 frames); B a day later with other noise
ROOM = dict(n_frames=60, seed=5, width=160, height=120, fx=131.25, fy=131.25, cx=79.5, cy=59.5)
DAY_NS = 86_400 * 10**9
MISALIGNMENT_M = np.array([0.03, 0.0, 0.0])
"""injected into session 1's merged poses (world x): the +-x walls are doubled 3 cm apart"""
FAR_MISALIGNMENT_M = np.array([0.15, 0.0, 0.0])
"""Trial 13: at a fixed 10 cm margin a 15 cm misalignment read as 19 change regions (whole walls added / removed)."""
FAST_MERGE = ("[build]\nodometry_edge_window = 1\n"
              "[build.loop_closure]\nkeyframe_distance_m = 0.4\nsession_descriptor_candidates = 1\n")
"""a keyframe every 40 cm (15 a session instead of 60), one descriptor candidate each: 30 loops tried, not 177"""


def _box(name: str, **scene: bool) -> tuple[np.ndarray, np.ndarray]:
    """min, max of the scene boxes whose names start with ``name``."""
    boxes = [b for b in scene_boxes(**scene) if b.name.startswith(name)]
    return np.min([b.min_m for b in boxes], axis=0), np.max([b.max_m for b in boxes], axis=0)


#: the true changes: (what, kind, session of the surface, box)
TRUTH = [
    ("door", "added", 1, _box("door_panel")),
    ("chair, new place", "added", 1, _box("chair_", chair_moved=True)),
    ("chair, old place", "removed", 0, _box("chair_")),
]


def _distance_to_box(p: np.ndarray, box: tuple[np.ndarray, np.ndarray]) -> float:
    lo, hi = box
    return float(np.linalg.norm(np.maximum(0.0, np.maximum(lo - p, p - hi))))


def _ok(out) -> None:  # noqa: ANN001
    assert out.returncode == 0, (out.stdout[-2000:], out.stderr[-2000:])


@pytest.fixture(scope="module")
def merged(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """Session A (door open, onto a corridor), session B (a day later: door closed, chair moved), each built with its
    true poses by ``driftmap build``, merged by ``driftmap merge`` (revision 1); revision 2 moves session 1 by
    :data:`MISALIGNMENT_M`. Both revisions diagnosed by ``driftmap diagnose --json``."""
    root = tmp_path_factory.mktemp("changes")
    logs = {"A": generate_synthetic_log(root / "logA", SyntheticLogConfig(**ROOM, door_open=True)),
            "B": generate_synthetic_log(root / "logB", SyntheticLogConfig(
                **{**ROOM, "seed": 6, "start_stamp_ns": SyntheticLogConfig().start_stamp_ns + DAY_NS}, chair_moved=True))}
    for name, log in logs.items():
        _ok(run_cli("build", log, "--out", root / name, "--poses", log / "groundtruth.txt", "--no-loop-closure"))
    (root / "fast.toml").write_text(FAST_MERGE)
    _ok(run_cli("merge", root / "A", root / "B", "--out", root / "AB", "--config", root / "fast.toml"))
    with FrameStore.open(root / "AB", "a") as store:
        assert store.head == 1
        P = store.poses(1)
        moved = {int(f): P[k].copy() for k, f in enumerate(store.frame_ids) if f >= SESSION_ID_STRIDE}
        for T in moved.values():
            T[:3, 3] += MISALIGNMENT_M
        store.add_revision(moved, source="external_file", propagate=False, note="session 1 moved by 3 cm")
        far = {f: T.copy() for f, T in moved.items()}
        for T in far.values():
            T[:3, 3] += FAR_MISALIGNMENT_M - MISALIGNMENT_M
        store.add_revision(far, source="external_file", parent=1, propagate=False, note="session 1 moved by 15 cm")
    out: dict = {"root": root, "store": root / "AB", "logs": logs}
    for rev in (1, 2, 3):
        path = root / f"diagnosis_rev{rev}.json"
        run = run_cli("diagnose", root / "AB", "--revision", rev, "--json", path)
        _ok(run)
        out[rev] = json.loads(path.read_text())
        out[f"stdout{rev}"] = run.stdout
    return out


def _match_truth(changes: dict) -> dict[str, dict]:
    """Each true change's region (its centre within 20 cm of the true object); every region must be one of them."""
    found: dict[str, dict] = {}
    for region in changes["regions"]:
        c = np.asarray(region["center_m"])
        near = [(what, kind, surf) for what, kind, surf, box in TRUTH if _distance_to_box(c, box) <= 0.2]
        assert near, f"a change reported where nothing changed: {region}"
        what, kind, surf = near[0]
        assert (region["kind"], region["session_surface"], region["sessions"]) == (kind, surf, [0, 1]), (what, region)
        found.setdefault(what, region)
    return found


def _changed_elsewhere(changes: dict) -> int:
    """Changed voxels not in a region at a true change (voxels in no region count as elsewhere)."""
    at_truth = sum(r["n_voxels"] for r in changes["regions"]
                   if any(_distance_to_box(np.asarray(r["center_m"]), box) <= 0.2 for *_, box in TRUTH))
    return changes["changed_voxels"] - at_truth


def test_moved_chair_and_closed_door_are_reported_changed(merged: dict) -> None:
    """Revision 1 (the merge): the door and the chair's two places are ``changed`` regions (added in session 1 /
    removed from session 0) with centres within 20 cm of the true objects; no other change (<= 1 % of the judged
    voxels, measured: none); no double wall at a changed place."""
    d = merged[1]
    changes = d["session_changes"]
    found = _match_truth(changes)
    assert set(found) == {what for what, *_ in TRUTH}, changes["regions"]
    for what, _, _, box in TRUTH:
        center = np.asarray(found[what]["center_m"])
        assert np.linalg.norm(center[:2] - 0.5 * (box[0][:2] + box[1][:2])) < 0.2, (what, center)
        assert found[what]["n_voxels"] >= 50
    assert changes["evaluated_voxels"] > 10_000
    assert _changed_elsewhere(changes) <= 0.01 * changes["evaluated_voxels"]
    # the stamps: the surface's frames are of its session, the free side's span is the other session's
    door = found["door"]
    assert all(f >= SESSION_ID_STRIDE for f in door["surface_frames"])
    start = SyntheticLogConfig().start_stamp_ns
    assert door["surface_stamp_ns"][0] >= start + DAY_NS and door["free_stamp_ns"][1] < start + DAY_NS
    for region in d["double_wall"]["regions"]:
        at_change = any(_distance_to_box(np.asarray(region["center_m"]), box) <= 0.1 for *_, box in TRUTH)
        assert not at_change or region["verdict"] == "changed", region
    assert "session changes" in merged["stdout1"] and "changed 1: added in session 1" in merged["stdout1"]


def test_misalignment_is_double_wall_not_change(merged: dict) -> None:
    """Revision 2 (session 1 moved 3 cm along x): double walls on the +-x walls, 3 cm apart, between the sessions
    (verdict ``double_wall``); the changes stay the true ones, nothing on the doubled walls."""
    d = merged[2]
    dw = d["double_wall"]
    walls = [r for r in dw["regions"] if abs(r["normal"][0]) > 0.9]
    assert len(walls) >= 3, dw["regions"]
    assert dw["median_separation_m"] == pytest.approx(0.03, abs=0.005)
    for r in walls:
        assert r["separation_m"] == pytest.approx(0.03, abs=0.008)
        assert r["verdict"] == "double_wall"
        assert {r["session_a"], r["session_b"]} == {0, 1}, r
    changes = d["session_changes"]
    found = _match_truth(changes)
    assert {"door", "chair, new place", "chair, old place"} <= set(found)
    assert _changed_elsewhere(changes) <= 0.01 * changes["evaluated_voxels"]
    assert d["session_changes"]["double_wall_regions_misaligned"] == len(dw["regions"])
    # the aligned merge has (almost) no double walls: the 3 cm ones are the injected misalignment
    assert merged[1]["double_wall"]["fraction_flagged"] < 0.2 * dw["fraction_flagged"]


def test_a_misalignment_within_the_detectors_range_is_no_change(merged: dict) -> None:
    """Revision 3 (session 1 moved 15 cm, within the detector's 20 cm): the changes are still only the true ones (the
    margin is the detector's range), and no double-wall region is called changed away from them."""
    d = merged[3]
    changes = d["session_changes"]
    assert changes["config"]["margin_m"] == pytest.approx(d["revisit_check"]["max_detectable_m"])
    found = _match_truth(changes)
    assert {"door", "chair, old place"} <= set(found), changes["regions"]
    assert _changed_elsewhere(changes) <= 0.01 * changes["evaluated_voxels"], changes["regions"]
    for region in d["double_wall"]["regions"]:
        at_change = any(_distance_to_box(np.asarray(region["center_m"]), box) <= 0.3 for *_, box in TRUTH)
        assert at_change or region["verdict"] == "double_wall", region


def test_without_the_margin_a_misalignment_reads_as_change(merged: dict) -> None:
    """The margin around each session's own surfaces is what keeps a misalignment out: with none, the 3 cm shift puts
    session 1's walls into session 0's free space and changes appear all over the +-x walls."""
    with FrameStore.open(merged["store"]) as store:
        sessions = store_sessions(store)
        assert sorted(sessions) == [0, 1] and len(sessions[1]) == 60
        bare = session_changes(store, sessions, 2, ChangeConfig(margin_m=0.0))
    elsewhere = _changed_elsewhere(bare.to_json())
    assert elsewhere > 0.01 * bare.evaluated_voxels
    assert elsewhere > 5 * max(_changed_elsewhere(merged[2]["session_changes"]), 1)


def test_single_store_has_no_session_changes(merged: dict, tmp_path: Path) -> None:
    """A store of one session: no ``session_changes`` key and no session fields on its regions (the JSON as before);
    ``session_changes`` itself refuses fewer than two sessions."""
    path = tmp_path / "a.json"
    _ok(run_cli("diagnose", merged["root"] / "A", "--json", path))
    d = json.loads(path.read_text())
    assert "session_changes" not in d
    assert all("verdict" not in r for r in d["double_wall"]["regions"])
    with FrameStore.open(merged["root"] / "A") as store, pytest.raises(ConfigError, match="two sessions"):
        session_changes(store, {0: [int(f) for f in store.frame_ids]})
    with pytest.raises(ConfigError, match="margin_m"):
        ChangeConfig(margin_m=-0.1)


def test_synth_door_open_and_move_chair(tmp_path: Path) -> None:
    """``synth --door-open`` leaves the door panel out and puts a corridor behind it; ``--move-chair`` moves the chair
    by :data:`CHAIR_MOVE_M`; without them ``synthetic.json`` has no such keys (the log as before); the street refuses
    them."""
    _ok(run_cli("synth", tmp_path / "open", "--frames", "2", "--door-open"))
    _ok(run_cli("synth", tmp_path / "moved", "--frames", "2", "--move-chair"))
    _ok(run_cli("synth", tmp_path / "plain", "--frames", "2"))
    meta = {k: json.loads((tmp_path / k / "synthetic.json").read_text()) for k in ("open", "moved", "plain")}
    names = {k: {b["name"] for b in m["scene"]} for k, m in meta.items()}
    assert "door_panel" not in names["open"] and "corridor_back" in names["open"] and "door_panel" in names["plain"]
    assert meta["open"]["config"]["door_open"] is True and "chair_moved" not in meta["open"]["config"]
    assert names["moved"] == names["plain"]
    seat = {k: next(b for b in m["scene"] if b["name"] == "chair_seat") for k, m in meta.items()}
    assert np.allclose(np.subtract(seat["moved"]["min_m"][:2], seat["plain"]["min_m"][:2]), CHAIR_MOVE_M)
    assert not {"door_open", "chair_moved"} & set(meta["plain"]["config"])
    err = one_error(run_cli("synth", tmp_path / "street", "--scene", "street", "--door-open"))
    assert "room" in err


def test_changes_that_cannot_be_judged_leave_the_diagnosis_standing(merged: dict) -> None:
    """A change test that cannot run (here a 9 m change voxel, larger than the room) is reported as skipped with the
    reason; the rest of the diagnosis is made as always."""
    from driftmap.diagnostics.diagnosis import diagnose_store
    from driftmap.diagnostics.diagnose_config import DiagnoseConfig

    with FrameStore.open(merged["store"]) as store:
        cfg = DiagnoseConfig.for_store(store)
        cfg = cfg.model_copy(update={"sampling": cfg.sampling.model_copy(update={"points_per_frame": 200})})
        result = diagnose_store(store, 2, config=cfg, sessions=store_sessions(store),
                                change_config=ChangeConfig(voxel_size_m=9.0))
    d = result.to_json()
    assert result.session_changes is None and "larger than the map" in d["session_changes"]["skipped"]
    assert d["session_changes"]["regions"] == [] and d["double_wall"]["voxels_evaluated"] > 0


def test_a_double_wall_inside_a_change_region_is_reported_changed(merged: dict) -> None:
    """Where a change region holds a double-wall region's centre, the change wins: the region's verdict is ``changed``
    with the change region's index, and the change region lists it; the other regions stay ``double_wall``."""
    import dataclasses

    from driftmap.diagnostics.changes import ChangeRegion, SessionChanges
    from driftmap.diagnostics.diagnose_config import DiagnoseConfig
    from driftmap.diagnostics.diagnosis import diagnose_store

    with FrameStore.open(merged["store"]) as store:
        cfg = DiagnoseConfig.for_store(store)
        cfg = cfg.model_copy(update={"sampling": cfg.sampling.model_copy(update={"points_per_frame": 300})})
        sessions = store_sessions(store)
        result = diagnose_store(store, 2, config=cfg)
    assert len(result.double_walls.regions) >= 2
    c = result.double_walls.regions[0].center_m
    region = ChangeRegion("added", 1, 0, c, c - 0.05, c + 0.05, 10, np.zeros(0, np.int64), (0, 0), (0, 0))
    changes = SessionChanges(2, [0, 1], [region], 1000, 10, 0.04, 3.0, ChangeConfig())
    d = dataclasses.replace(result, session_changes=changes, sessions=sessions).to_json()
    verdicts = [r["verdict"] for r in d["double_wall"]["regions"]]
    assert verdicts[0] == "changed" and d["double_wall"]["regions"][0]["change_region"] == 0
    assert d["session_changes"]["regions"][0]["double_wall_regions"] == [0]
    assert d["session_changes"]["double_wall_regions_changed"] == verdicts.count("changed") >= 1
    assert "double_wall" in verdicts[1:]


def _samples(box: tuple[np.ndarray, np.ndarray], step: float = 0.01) -> np.ndarray:
    lo, hi = box
    return np.mgrid[lo[0]:hi[0]:step, lo[1]:hi[1]:step, lo[2]:hi[2]:step].reshape(3, -1).T


def test_latest_state_layers_show_the_newest_world(merged: dict) -> None:
    """Latest-state layers (``driftmap.volume.sessions``): voxel by voxel the newest session that observed it decides,
    so the chair is only at its new place and the door is closed, while the layers of all frames hold both chairs.
    Measured (4 cm): old seat free 100 % (all frames: occupied 96 %), new seat occupied 99 % (all frames 95 %), the
    door panel occupied wherever session 1 saw it (99.7 %); farther than 20 cm from the changes 0.29 % of the
    observed voxels differ from the all-frames layers."""
    from driftmap.volume import VolumeConfig, VolumeLayers
    from driftmap.volume.layers import FREE, OCCUPIED, UNKNOWN
    from driftmap.volume.sessions import latest_state_layers, session_order

    cfg = VolumeConfig(voxel_size_m=0.04, keep_frame_voxels=False)
    with FrameStore.open(merged["store"]) as store:
        sessions = store_sessions(store)
        assert session_order(store, sessions) == [0, 1]  # B a day later
        latest = latest_state_layers(store, sessions, 1, cfg)
        everything = VolumeLayers.from_store(store, 1, cfg)
        # the other order (as if session 0 were the newer): the old world comes back
        older = latest_state_layers(store, sessions, 1, cfg, order=[1, 0])
        with pytest.raises(ConfigError, match="permutation"):
            latest_state_layers(store, sessions, 1, cfg, order=[0])
        with pytest.raises(ConfigError, match="read-only"):
            latest.layers.apply(2, store)
        assert latest.layers.store_uuid == store.uuid  # decide refuses them for another store by id
    L, s0, s1 = latest.layers, latest.session_layers[0], latest.session_layers[1]
    old_seat, new_seat = _samples(_box("chair_seat")), _samples(_box("chair_seat", chair_moved=True))
    door = _samples(_box("door_panel"))

    def share(layers: VolumeLayers, pts: np.ndarray, state: np.int8) -> float:
        return float(np.mean(layers.states(pts) == state))

    assert share(s0, old_seat, OCCUPIED) > 0.95 and share(s1, old_seat, FREE) > 0.95  # the change is real
    assert share(L, old_seat, FREE) > 0.95 and share(everything, old_seat, OCCUPIED) > 0.9
    assert share(L, new_seat, OCCUPIED) > 0.95 and share(everything, new_seat, OCCUPIED) > 0.9
    assert share(older.layers, old_seat, OCCUPIED) > 0.95 and share(older.layers, new_seat, FREE) > 0.95
    seen = s1.states(door) != UNKNOWN
    assert seen.mean() > 0.5 and share(s0, door[seen], FREE) > 0.8  # the doorway was open in session 0
    assert share(L, door[seen], OCCUPIED) > 0.99
    assert np.all(latest.deciding_session.ravel()[L.grid.flat(L.grid.grid_index(old_seat)[0])] == 1)
    # elsewhere the latest state is the all-frames map: the sessions agree on everything but the changes (measured:
    # 0.29 % of the observed voxels differ farther than 20 cm from a true change, single noisy voxels at surfaces)
    centers = L.grid.centers_m(np.arange(L.grid.n_voxels))
    states_all, states_latest = everything.states(centers), L.state_grid().ravel()
    near = np.zeros(len(centers), dtype=bool)
    for *_, (lo, hi) in TRUTH:
        near |= np.linalg.norm(np.maximum(0.0, np.maximum(lo - centers, centers - hi)), axis=1) <= 0.2
    differ = states_all != states_latest
    observed = int(np.sum(states_latest != UNKNOWN))
    assert np.sum(differ & ~near) <= 0.005 * observed
    assert np.sum(differ & near) > 100  # the changes are where they differ
    per = latest.voxels_per_session()
    assert per[1] > per[0] > 0 and sum(per.values()) == int(np.sum(states_latest != UNKNOWN))
    # queries work on them: the clearance at the old seat is the room's, at the new one zero
    assert L.clearance_m(_box("chair_seat", chair_moved=True)[0][None] + 0.02)[0] < 0.05


def test_export_latest_state_mesh_shows_the_chair_only_at_its_new_place(merged: dict) -> None:
    """``export --mesh --latest-state`` on the merged store: the TSDF mesh of the newest state (session 1: the chair
    moved, the door closed) has no surface left at the chair's old place, where the mesh of every session's rays keeps
    it; both have the chair at its new place. On a store of one session the flag is refused before anything is
    written."""
    import open3d as o3d

    root = merged["root"]
    meshes = {}
    for name, extra in (("all", ()), ("latest", ("--latest-state",))):
        path = root / f"mesh_{name}.ply"
        run = run_cli("export", merged["store"], "--revision", 1, "--mesh", path, "--overwrite", *extra)
        _ok(run)
        meshes[name] = np.asarray(o3d.io.read_triangle_mesh(str(path)).vertices)
    assert "latest state of 2 sessions" in " ".join(run.stdout.split()), run.stdout

    def near(vertices: np.ndarray, box: tuple[np.ndarray, np.ndarray]) -> int:
        lo, hi = box
        seat = (vertices >= lo - 0.02) & (vertices <= hi + 0.02)
        return int(np.count_nonzero(seat.all(axis=1) & (vertices[:, 2] > 0.3)))  # above the floor's own surface
    old = next(box for what, _, _, box in TRUTH if what == "chair, old place")
    new = next(box for what, _, _, box in TRUTH if what == "chair, new place")
    assert near(meshes["all"], old) > 50 and near(meshes["latest"], old) < 0.1 * near(meshes["all"], old), (
        near(meshes["all"], old), near(meshes["latest"], old))
    assert near(meshes["latest"], new) > 50, near(meshes["latest"], new)
    single = run_cli("export", root / "A", "--mesh", root / "mesh_single.ply", "--latest-state")
    assert "holds one session" in one_error(single) and not (root / "mesh_single.ply").exists()


def test_revisit_check_on_a_merged_store_knows_the_sessions(merged: dict) -> None:
    """Trial 13 (F5): on a merged store the revisit check said a frame was registered onto frame 1000000000 "46.7 m of
    travel earlier" -- another session, a day later, with no travel between them -- and took such pairs into the drift
    rate (correction per metre of a path that does not exist). Pairs across sessions are marked, have no travel
    (None), count for the consistency figure but not for the drift rate; a session's start is no jump."""
    for rev in (1, 3):
        check = merged[rev]["revisit_check"]
        across = [p for p in check["probes"] if p["cross_session"]]
        assert across, check["probes"]  # session 1 revisits session 0's room
        assert all(p["path_between_m"] is None for p in across), across
        within = [p for p in check["probes"] if not p["cross_session"] and p["target"] == "stretch"]
        assert all(p["path_between_m"] is not None and (p["frame_id"] >= SESSION_ID_STRIDE)
                   == (p["target_frame_id"] >= SESSION_ID_STRIDE) for p in within), within
        boundary = [j for j in check["jumps"] if (j["before_frame_id"] >= SESSION_ID_STRIDE)
                    != (j["frame_id"] >= SESSION_ID_STRIDE)]
        assert not boundary, check["jumps"]
    # 15 cm between the sessions (revision 3): the pairs across them measure it, the ones within a session do not
    far = [p["correction_m"] for p in merged[3]["revisit_check"]["probes"] if p["cross_session"] and p["counted"]]
    assert far and max(far) == pytest.approx(float(np.linalg.norm(FAR_MISALIGNMENT_M)), abs=0.03), far


def test_revisit_reason_names_sessions_not_travel_across_them() -> None:
    """The reason on a merged store names each frame's session and says "in another session" instead of a travel."""
    from driftmap.diagnostics.revisits import STRETCH, RevisitCheck, RevisitCheckConfig, RevisitProbe

    cfg = RevisitCheckConfig(max_detectable_m=0.2)
    probes = [RevisitProbe(SESSION_ID_STRIDE + k, 0.8, 0.9, 0.01, 0.3, 0.3 + 0.03 * k, 0.1, True, k, 0, float("nan"), STRETCH,
                           True) for k in range(4)]
    sessions = {**{k: 0 for k in range(4)}, **{SESSION_ID_STRIDE + k: 1 for k in range(4)}}
    check = RevisitCheck(cfg, probes, 4, (), sessions)
    reason = check.reason()
    assert reason.startswith("sessions 0 and 1 disagree by 33 cm / 0.1 deg (4 frame pairs across them, the largest "
                             f"frame {SESSION_ID_STRIDE + 3} (session 1) on frame 3 (session 0): 39 cm"), reason
    assert "travel" not in reason and check.drift_percent_per_m is None, reason  # no travel: no drift rate


def test_view_latest_state_shows_the_chair_only_at_its_new_place(merged: dict, tmp_path: Path) -> None:
    """``view --color state --latest-state`` (issue 26: latest-state layers in the viewer): the occupied voxels of the
    newest state hold no chair at its old place, where the layers of every session's rays still do; through the
    command line the picture is written and says so. Refused with another colour, and on a store of one session."""
    from driftmap.viewer import colored_map

    old = next(box for what, _, _, box in TRUTH if what == "chair, old place")
    new = next(box for what, _, _, box in TRUTH if what == "chair, new place")

    def seat(centres: np.ndarray, box: tuple[np.ndarray, np.ndarray]) -> int:
        lo, hi = box
        inside = ((centres >= lo - 0.02) & (centres <= hi + 0.02)).all(axis=1)
        return int(np.count_nonzero(inside & (centres[:, 2] > 0.3)))

    with FrameStore.open(merged["store"]) as store:
        every = colored_map(store, revision=1, color="state").points_world
        latest = colored_map(store, revision=1, color="state", latest_state=True).points_world
    assert seat(every, old) > 20 and seat(latest, old) < 0.1 * seat(every, old), (seat(every, old), seat(latest, old))
    assert seat(latest, new) > 20, seat(latest, new)
    run = run_cli("view", merged["store"], "--revision", 1, "--color", "state", "--latest-state", "--out",
                  tmp_path / "v", "--backend", "software")
    _ok(run)
    assert "revision 1, latest state, colour state" in " ".join(run.stdout.split()), run.stdout
    assert list((tmp_path / "v").glob("*state*.png")), list((tmp_path / "v").iterdir())
    wrong = run_cli("view", merged["store"], "--color", "frame", "--latest-state", "--out", tmp_path / "w")
    assert wrong.returncode == 2 and "applies to --color state" in " ".join(wrong.stderr.split()), wrong.stderr
    single = run_cli("view", merged["root"] / "A", "--color", "state", "--latest-state", "--out", tmp_path / "s",
                     "--backend", "software")
    assert "holds one session" in one_error(single), single.stderr


def test_one_session_off_the_others_is_judged_from_its_own_pairs() -> None:
    """Trial 14 (F1): a third session moved 40 cm read valid ("0.9 cm"): two of the twelve pairs measured it, and the
    disagreement was the third largest correction over all pairs. The pairs across each two sessions are judged on
    their own: two counted pairs that both put session 2 40 cm off make the map's disagreement 40 cm, and the reason
    names the sessions."""
    from driftmap.diagnostics.revisits import STRETCH, RevisitCheck, RevisitCheckConfig, RevisitProbe

    S = SESSION_ID_STRIDE
    cfg = RevisitCheckConfig(max_detectable_m=0.2)

    def pair(probe: int, target: int, m: float) -> RevisitProbe:
        cross = probe // S != target // S
        return RevisitProbe(probe, 0.8, 0.9, 0.01, 0.3, m, 0.05, True, target, target, float("nan") if cross else 3.0,
                            STRETCH, cross)

    probes = [pair(S + k, k, 0.01) for k in range(5)] + [pair(20 + k, k, 0.008) for k in range(5)]
    probes += [pair(2 * S + 3, 3, 0.405), pair(2 * S + 28, 1, 0.395)]
    sessions = {f: f // S for p in probes for f in (p.frame_id, p.target_frame_id)}
    check = RevisitCheck(cfg, probes, len(probes), (), sessions)
    assert check.group_disagreement(False) == pytest.approx(0.01)  # the third largest of all pairs hides it
    assert check.session_disagreements()[(0, 2)][0] == pytest.approx(0.395)
    assert check.disagreement_m == pytest.approx(0.395) and check.beyond_detector
    assert check.reason().startswith("sessions 0 and 2 disagree by 40 cm / 0.1 deg (2 frame pairs across them"), \
        check.reason()
    assert check.to_json()["sessions"][1] == {"session_a": 0, "session_b": 2, "disagreement_m": 0.395,
                                              "disagreement_deg": 0.05, "n_pairs": 2}
    one = RevisitCheck(cfg, probes[:-1], len(probes) - 1, (), sessions)  # one pair alone decides nothing
    assert (0, 2) not in one.session_disagreements() and not one.beyond_detector


def test_diagnostic_rows_of_sessions_that_share_stamps_run_session_by_session() -> None:
    """Trial 14 (F3): sessions recorded apart share stamps (every data set's log starts at 0); rows in stamp order
    interleaved them (0, 1e9, 1, 1e9 + 1, ...) and the revisit check's travel ran back and forth between sessions (a
    rigid 15 cm session offset read as 1.40 %/m of drift). With the sessions, the rows run session by session, each
    in time order, and the path is each session's own travel."""
    from driftmap.diagnostics.double_wall import DiagnosticCloud
    from driftmap.frame import Frame, PoseEstimate, SensorKind

    rng = np.random.default_rng(0)
    S = SESSION_ID_STRIDE

    def frame(fid: int, stamp_s: int, x: float) -> Frame:
        T = np.eye(4)
        T[0, 3] = x
        return Frame(frame_id=fid, stamp_ns=stamp_s * 10**9, sensor_name="lidar", sensor_kind=SensorKind.LIDAR,
                     points_sensor=rng.uniform(-5, 5, (500, 3)).astype(np.float32), pose=PoseEstimate(T))

    frames = [frame(k, k, 0.5 * k) for k in range(4)] + [frame(S + k, k, 10.0 + 0.5 * k) for k in range(4)]
    poses = np.stack([f.pose.T_world_sensor for f in frames])
    mixed = DiagnosticCloud.from_frames(frames)
    assert list(mixed.frame_ids) == [0, S, 1, S + 1, 2, S + 2, 3, S + 3]  # stamp order interleaves the sessions
    sessions = {0: [0, 1, 2, 3], 1: [S, S + 1, S + 2, S + 3]}
    cloud = DiagnosticCloud.from_frames(frames, sessions=sessions)
    assert list(cloud.frame_ids) == [0, 1, 2, 3, S, S + 1, S + 2, S + 3]
    path = cloud.place(poses[np.searchsorted([f.frame_id for f in frames], cloud.frame_ids)]).path_length_m
    assert np.allclose(np.diff(path)[[0, 1, 2, 4, 5, 6]], 0.5)  # each session's own steps; one jump between them


def test_diagnose_says_how_many_regions_it_does_not_list(merged: dict) -> None:
    """Trial 14 (W7): the table lists the first 5 double-wall and changed regions and dropped the rest without a word.
    It says how many more there are, and where they are (every region is in the JSON)."""
    seen_more = False
    for rev in (1, 2, 3):
        out = " ".join(merged[f"stdout{rev}"].split())
        for n, what in ((len(merged[rev]["double_wall"]["regions"]), "double-wall"),
                        (len(merged[rev]["session_changes"]["regions"]), "changed")):
            line = f"... and {n - 5} more {what} regions (all in the JSON"
            assert (line in out) == (n > 5), (rev, what, n, out[-3000:])
            seen_more |= n > 5
    assert seen_more, "no revision has more than 5 regions of a kind: the test checks only the absence"
