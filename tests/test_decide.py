"""Decisions (issue 25): clearance, collision, grasp, foothold and exploration queries answered on a store's revision,
checked against the synthetic room's truth (datasets/synthetic-loop-queries.json, made by
``python -m driftmap.decisions.synthetic_queries``), compared between the drifting odometry and its loop closure,
and through ``driftmap decide`` (the JSON contract, --compare, bad input)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from driftmap.decisions import DecisionSet, QueryError, compare, decide, decide_revisions, load_queries, parse_queries
from driftmap.decisions.compare import output_json
from driftmap.diagnostics.diagnosis import diagnose_store
from driftmap.pipeline.build import build
from driftmap.store.frame_store import FrameStore

ROOT = Path(__file__).resolve().parents[1]
LOG = ROOT / "datasets" / "synthetic-loop"
QUERY_FILE = ROOT / "datasets" / "synthetic-loop-queries.json"

CONTRACT_REPRESENTATION = {"store": str, "revision": int, "settings_hash": str, "driftmap_version": str}
CONTRACT_DECISION = {"id": str, "kind": str, "decision": str, "margin": (float, type(None)),
                     "uncertainty": (float, type(None)), "failure_label": (str, type(None)), "frames": list,
                     "stamp_ns_newest": (int, type(None)), "latency_s": float}
CONTRACT_FLIP = {"id": str, "before": str, "after": str, "margin_delta": (float, type(None))}
DECISIONS_OF = {"clearance": {"free", "blocked", "unknown"}, "collision": {"free", "blocked", "unknown"},
                "grasp": {"graspable", "unstable_normal", "too_few_points"},
                "foothold": {"stable", "too_steep", "uneven", "too_few_points"}, "explore": {"go_look", "known"}}


def _truth(decisions: DecisionSet) -> dict[str, dict]:
    return {q["id"]: q["truth"] for q in decisions.queries.raw}


def _agreement(decisions: DecisionSet) -> tuple[float, list[str]]:
    truth = _truth(decisions)
    wrong = [d.id for d in decisions.decisions if d.decision != truth[d.id]["decision"]]
    return 1.0 - len(wrong) / len(decisions.decisions), wrong


# ------------------------------------------------------------------------------------------------ fixtures
@pytest.fixture(scope="module")
def queries():
    return load_queries(QUERY_FILE)


@pytest.fixture(scope="module")
def gt_store(tmp_path_factory: pytest.TempPathFactory) -> FrameStore:
    """The embedded log placed with its ground-truth poses (the room's frame)."""
    out = tmp_path_factory.mktemp("decide") / "gt"
    build(LOG, out, poses_file=LOG / "groundtruth.txt", loop_closure=False)
    return FrameStore.open(out)


@pytest.fixture(scope="module")
def gt_decisions(gt_store: FrameStore, queries) -> DecisionSet:
    return decide(gt_store, queries)


@pytest.fixture(scope="module")
def odo_store(tmp_path_factory: pytest.TempPathFactory) -> FrameStore:
    """The log's drifting odometry (revision 0: 1 %/m scale, 0.6 deg/m yaw, a 3 cm step at frame 30) and its loop
    closure (revision 1), both in the room's frame."""
    out = tmp_path_factory.mktemp("decide") / "odo"
    result = build(LOG, out, poses_file=LOG / "odometry.txt")
    assert result.loop_revision == 1
    return FrameStore.open(out)


@pytest.fixture(scope="module")
def odo_diagnosis(odo_store: FrameStore):
    return diagnose_store(odo_store, 0)


@pytest.fixture(scope="module")
def odo_decisions(odo_store: FrameStore, queries, odo_diagnosis) -> tuple[DecisionSet, DecisionSet]:
    (before, after), _ = decide_revisions(odo_store, queries, [0, 1], double_walls=[odo_diagnosis, None])
    return before, after


def _cli(*args: object) -> subprocess.CompletedProcess:
    env = {**os.environ, "COLUMNS": "200"}
    return subprocess.run([sys.executable, "-m", "driftmap.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=600, env=env, check=False)


# ------------------------------------------------------------------------------------------------ the query set
def test_the_generated_query_set_covers_the_acceptance_cases(queries) -> None:
    """>= 200 queries of all five kinds: clearance along and beside the path, collision sweeps past the table and
    chair legs, grasps on the 2 cm board, footholds on the floor, exploration behind furniture; every truth is a
    decision of its kind, and each category has more than one outcome where the room allows it."""
    assert len(queries) >= 200
    cats = Counter(q["truth"]["category"] for q in queries.raw)
    for needed in ("clearance_path", "clearance_beside", "collision_obstacle", "grasp_board", "foothold_floor",
                   "explore_furniture"):
        assert cats[needed] >= 12, cats
    for q, raw in zip(queries, queries.raw):
        assert raw["truth"]["decision"] in DECISIONS_OF[q.kind], raw
    outcomes = Counter((raw["truth"]["category"], raw["truth"]["decision"]) for raw in queries.raw)
    for cat in ("clearance_beside", "collision_obstacle", "grasp_board", "foothold_floor", "explore_furniture"):
        assert sum(1 for (c, _) in outcomes if c == cat) >= 2, (cat, outcomes)


# ------------------------------------------------------------------------------------------------ truth
def test_the_committed_truth_is_what_the_generator_computes(queries, gt_store: FrameStore) -> None:
    """Two queries of every category: the truth in the file is the truth the code computes from the room (so the
    file cannot drift from :mod:`driftmap.decisions.synthetic_truth`), at the layers' own max range."""
    from driftmap.decisions.synthetic_queries import Generator, depth_camera_max_range_m
    from driftmap.decisions.synthetic_truth import SceneTruth
    from driftmap.volume import VolumeConfig
    from driftmap.volume.defaults import resolve_config

    max_range = depth_camera_max_range_m()
    assert resolve_config(gt_store, VolumeConfig()).max_range_m == pytest.approx(max_range)
    gen = Generator(SceneTruth.from_log(LOG, max_range))
    picked: dict[str, int] = {}
    for raw in queries.raw:
        cat = raw["truth"]["category"]
        if picked.get(cat, 0) < 2:
            picked[cat] = picked.get(cat, 0) + 1
            again = gen.truth_of({k: v for k, v in raw.items() if k != "truth"})
            assert again is not None and again["decision"] == raw["truth"]["decision"], raw["id"]
    assert len(picked) == len(Counter(q["truth"]["category"] for q in queries.raw))


def test_decisions_on_the_ground_truth_store_agree_with_the_truth(gt_decisions: DecisionSet) -> None:
    """>= 99 % agree (measured 331 of 333: two sweeps past a chair leg whose truth meets a thin unseen sliver of the
    leg's shadow before the contact, where the map's rays saw part of those voxels); and the map never calls free
    what is physically blocked, seen or not."""
    agreement, wrong = _agreement(gt_decisions)
    assert agreement >= 0.99, wrong
    truth = _truth(gt_decisions)
    for d in gt_decisions.decisions:
        t = truth[d.id]
        if d.kind == "clearance" and t.get("physically_blocked"):
            assert d.decision != "free", d.id
        if d.kind == "collision" and t.get("physical_contact_m") is not None:
            assert d.decision != "free", d.id
    assert {d.kind for d in gt_decisions.decisions} == set(DECISIONS_OF)
    for d in gt_decisions.decisions:
        assert d.decision in DECISIONS_OF[d.kind]


def test_grasp_normals_on_the_board_face_the_robot(gt_decisions: DecisionSet) -> None:
    """Graspable ROIs on the 2 cm board's face: the normal within 10 deg of +y (the face the camera saw), the
    approach against it, the contact point on the face (y = -2.0) within 1.5 cm."""
    truth = _truth(gt_decisions)
    found = 0
    for d in gt_decisions.decisions:
        if d.id.startswith("grasp-board") and d.decision == "graspable" and truth[d.id]["decision"] == "graspable":
            n = np.asarray(d.details["normal"])
            assert np.degrees(np.arccos(n @ [0, 1, 0])) < 10.0
            assert np.allclose(d.details["approach"], -n)
            assert abs(d.details["contact_point_m"][1] + 2.0) < 0.015
            found += 1
    assert found >= 5


def test_each_decision_records_its_evidence(gt_decisions: DecisionSet, gt_store: FrameStore) -> None:
    """Frames that observed the evidence, the newest one's stamp, the pose revision of each, the latency; on the
    ground-truth store the uncertainty (how far apart the frames put the surface) is millimetres."""
    stamps = dict(zip(gt_store.frame_ids.tolist(), gt_store.ledger.stamps_ns.tolist()))
    with_frames = 0
    for d in gt_decisions.decisions:
        assert d.latency_s > 0
        if d.frames:
            with_frames += 1
            assert d.stamp_ns_newest == max(stamps[f] for f in d.frames)
            assert d.details["frame_pose_revisions"] == [0] * len(d.frames)
        else:
            assert d.stamp_ns_newest is None
    assert with_frames > 0.6 * len(gt_decisions)
    unc = np.array([d.uncertainty for d in gt_decisions.decisions if d.uncertainty is not None])
    assert len(unc) > 0.5 * len(gt_decisions) and np.median(unc) < 0.005  # measured 1.5 mm


# ------------------------------------------------------------------------------------------------ drift
def test_drift_flips_decisions_and_the_loop_closure_restores_them(odo_decisions, odo_store: FrameStore) -> None:
    """Revision 0 (drifting odometry, up to 8 cm off): 95.8 % agree with the truth; the loop-closure revision:
    >= 99 % (measured 99.4 %: the same two sweeps as on the ground-truth store). The comparison lists the flipped
    decisions; every flip takes a wrong decision to the truth, and every flip's evidence moved with its frames
    (8-14 cm)."""
    before, after = odo_decisions
    agree0, wrong0 = _agreement(before)
    agree1, wrong1 = _agreement(after)
    assert agree1 >= 0.99, wrong1
    assert agree0 < agree1
    comparison = compare(before, after)
    truth = _truth(after)
    assert len(comparison.flipped) >= 5
    for f in comparison.flipped:
        assert f.id in wrong0 and truth[f.id]["decision"] == f.after, f
        assert f.why["frames_moved"] and f.why["max_evidence_shift_m"] >= 0.03, f
    assert len(set(wrong0) - set(comparison.flipped_ids())) <= len(wrong1)
    moved = {int(f) for f, T0, T1 in zip(odo_store.frame_ids, odo_store.poses(0), odo_store.poses(1))
             if not np.array_equal(T0, T1)}
    assert moved
    for d in after.decisions:  # the frames the loop closure moved carry its revision
        for f, r in zip(d.frames, d.details["frame_pose_revisions"]):
            assert r == 1 if f in moved else r in (0, 1)


def test_double_walls_in_reach_bound_the_uncertainty(odo_decisions, odo_diagnosis) -> None:
    """With the diagnosis of revision 0, a decision with a double wall in reach has an uncertainty of at least its
    separation and, when it otherwise passes, the label double_wall_nearby. Of the flips, those at the table lie at
    its double walls (where the loop's start and end overlap); the ones at the chair and the board lie where the
    drift moved surfaces seen on one visit only, which diagnose cannot flag (reported, not asserted)."""
    before, after = odo_decisions
    regions = odo_diagnosis.double_walls.regions
    assert regions
    near = [d for d in before.decisions if d.details["double_walls_in_reach"]]
    assert near
    for d in near:
        sep = max(w["separation_m"] for w in d.details["double_walls_in_reach"])
        assert d.uncertainty is not None and d.uncertainty >= sep - 1e-12
        assert d.failure_label is not None
    assert any(d.failure_label == "double_wall_nearby" for d in near)
    assert not any(d.details["double_walls_in_reach"] for d in after.decisions)  # no diagnosis given for it
    unc0 = np.array([d.uncertainty for d in before.decisions if d.uncertainty is not None])
    unc1 = np.array([d.uncertainty for d in after.decisions if d.uncertainty is not None])
    assert np.percentile(unc0, 90) > 3 * np.percentile(unc1, 90)  # measured 5.3 cm vs 0.6 cm


def test_the_loop_closures_marginals_bound_the_uncertainty(odo_decisions, odo_store: FrameStore) -> None:
    """Revision 1 comes from the pose graph: its GTSAM marginals, kept with the revision, propagate to the evidence
    of the decisions (measured: 251 of 333, median 1.4 mm, 90th percentile 1.9 mm); revision 0 (a pose file) has
    none."""
    before, after = odo_decisions
    assert not any(d.details["uncertainty_parts"]["pose_marginal_m"] for d in before.decisions)
    assert len(odo_store.ledger.covariances(1)) == len(odo_store)
    marginals = [(d, d.details["uncertainty_parts"]["pose_marginal_m"]) for d in after.decisions]
    with_marginal = [(d, m) for d, m in marginals if m is not None]
    assert len(with_marginal) >= 0.6 * len(after.decisions)
    values = np.array([m for _, m in with_marginal])
    assert 1e-4 < np.median(values) < 0.02  # the loop closes to millimetres (ATE 1.6 cm at most)
    assert all(d.uncertainty >= m for d, m in with_marginal)
    # every decision resting on a point measured by frames has one (explore judges a region, not a point)
    assert all(m is not None for d, m in marginals if d.kind != "explore" and d.evidence_m is not None and d.frames)


# ------------------------------------------------------------------------------------------------ contract
def _check_types(obj: dict, spec: dict, what: str) -> None:
    for key, typ in spec.items():
        assert key in obj, f"{what}: {key} missing"
        assert isinstance(obj[key], typ) and not isinstance(obj[key], bool), f"{what}: {key} = {obj[key]!r}"


def test_the_json_follows_the_contract(odo_decisions) -> None:
    before, after = odo_decisions
    data = json.loads(json.dumps(output_json(after, compare(before, after))))
    _check_types(data["representation"], CONTRACT_REPRESENTATION, "representation")
    assert data["representation"]["revision"] == 1 and len(data["representation"]["settings_hash"]) == 16
    assert data["representation"]["settings_hash"] == before.representation.settings_hash
    for d in data["decisions"]:
        _check_types(d, CONTRACT_DECISION, d.get("id", "?"))
        assert all(isinstance(f, int) for f in d["frames"])
        assert d["decision"] in DECISIONS_OF[d["kind"]]
    assert [d["id"] for d in data["decisions"]] == [q.id for q in after.queries]
    for f in data["flipped"]:
        _check_types(f, CONTRACT_FLIP, f["id"])
    assert set(data["compared"]) == {"a", "b"}
    assert data["compared"]["a"]["revision"] == 0 and data["compared"]["b"]["revision"] == 1


def test_yaml_and_json_query_files_read_alike(tmp_path: Path) -> None:
    pytest.importorskip("yaml")
    import yaml

    data = json.loads(QUERY_FILE.read_text())
    (tmp_path / "q.yaml").write_text(yaml.safe_dump({"queries": data["queries"][:40]}))
    (tmp_path / "q.json").write_text(json.dumps({"queries": data["queries"][:40]}))
    a, b = load_queries(tmp_path / "q.yaml"), load_queries(tmp_path / "q.json")
    assert [q.id for q in a] == [q.id for q in b]
    for qa, qb in zip(a, b):
        for lo_a, lo_b in zip(qa.extent_m(), qb.extent_m()):
            assert np.array_equal(lo_a, lo_b)


@pytest.mark.parametrize(("query", "qid", "field"), [
    ({"id": "x", "kind": "teleport"}, "x", "kind"),
    ({"id": "p", "kind": "collision", "path_m": [[0, 0, 1]], "footprint": {"box_m": [0.1, 0.1, 0.1]}}, "p", "path_m"),
    ({"id": "p0", "kind": "collision", "path_m": [[0, 0, 1], [0, 0, 1]], "footprint": {"box_m": [0.1, 0.1, 0.1]}}, "p0", "path_m"),
    ({"id": "r", "kind": "clearance", "points_m": [[0, 0, 1]], "radius_m": -0.1}, "r", "radius_m"),
    ({"id": "n", "kind": "clearance", "points_m": [[0, float("nan"), 1]], "radius_m": 0.1}, "n", "points_m[0]"),
    ({"id": "b", "kind": "clearance", "points_m": [[0, 0, 1]], "radius_m": True}, "b", "radius_m"),
    ({"id": "g", "kind": "grasp", "roi_min_m": [0, 0, 1], "roi_max_m": [0.1, -0.1, 1.1]}, "g", "roi_max_m"),
    ({"id": "f", "kind": "foothold", "center_m": [0, 0, 0], "radius_m": 0.1, "max_slope_deg": 120}, "f", "max_slope_deg"),
    ({"id": "e", "kind": "explore", "min_m": [0, 0, 0], "max_m": [1, 1, 1], "max_unknown_fraction": 1.5}, "e", "max_unknown_fraction"),
    ({"id": "c", "kind": "collision", "path_m": [[0, 0, 1], [1, 0, 1]], "footprint": {"sphere_m": 0.1}}, "c", "footprint"),
    ({"id": "t", "kind": "clearance", "points_m": [[0, 0, 1]], "radius": 0.1}, "t", "radius"),
])
def test_bad_queries_name_the_query_and_the_field(query: dict, qid: str, field: str) -> None:
    with pytest.raises(QueryError) as err:
        parse_queries({"queries": [query]})
    assert err.value.query_id == qid and err.value.field == field
    assert repr(qid) in str(err.value)
    with pytest.raises(QueryError, match="used twice"):
        parse_queries({"queries": [{"id": "d", "kind": "explore", "min_m": [0, 0, 0], "max_m": [1, 1, 1],
                                    "max_unknown_fraction": 0.5}] * 2})


# ------------------------------------------------------------------------------------------------ CLI
BAD_CLI = {
    "unknown_kind": ({"id": "ok", "kind": "clearance", "points_m": [[1.5, 0, 1]], "radius_m": 0.1},
                     {"id": "q-teleport", "kind": "teleport", "points_m": [[0, 0, 0]]}),
    "one_point_path": ({"id": "p-one", "kind": "collision", "path_m": [[1.5, 0, 0.5]], "footprint": {"box_m": [0.1, 0.1, 0.1]}},),
    "negative_radius": ({"id": "r-neg", "kind": "clearance", "points_m": [[1.5, 0, 1]], "radius_m": -0.2},),
    "roi_outside_the_map": ({"id": "ok", "kind": "clearance", "points_m": [[1.5, 0, 1]], "radius_m": 0.1},
                            {"id": "g-far", "kind": "grasp", "roi_min_m": [40, 40, 0], "roi_max_m": [40.1, 40.1, 0.1]}),
}


def _store_files(path: Path) -> dict[str, tuple[int, int]]:
    return {str(p.relative_to(path)): (p.stat().st_size, p.stat().st_mtime_ns) for p in sorted(path.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("case", list(BAD_CLI))
def test_bad_input_through_the_cli(case: str, gt_store: FrameStore, tmp_path: Path) -> None:
    """Exit 1, one line naming the query, nothing written and nothing in the store changed."""
    q = tmp_path / "q.json"
    q.write_text(json.dumps({"queries": list(BAD_CLI[case])}))
    before = _store_files(gt_store.path)
    out = _cli("decide", gt_store.path, "--queries", q, "--json", tmp_path / "out.json", "--report", tmp_path / "rep")
    assert out.returncode == 1, (out.stdout, out.stderr)
    lines = [line for line in out.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:"), out.stderr
    bad_id = BAD_CLI[case][-1]["id"]
    assert repr(bad_id) in lines[0], lines[0]
    assert not (tmp_path / "out.json").exists() and not (tmp_path / "rep").exists()
    assert _store_files(gt_store.path) == before


def test_cli_compare_lists_the_flips_and_writes_the_contract(odo_store: FrameStore, odo_decisions,
                                                             tmp_path: Path) -> None:
    """``decide --compare 0,1`` on a subset of the queries (the flips and every 25th): the same flips as the
    library, the contract's keys, a report figure; an existing --json is refused without --overwrite."""
    before, after = odo_decisions
    flips = set(compare(before, after).flipped_ids())
    data = json.loads(QUERY_FILE.read_text())
    subset = [q for k, q in enumerate(data["queries"]) if q["id"] in flips or k % 25 == 0]
    qfile = tmp_path / "subset.json"
    qfile.write_text(json.dumps({"queries": subset}))
    out_json, report = tmp_path / "out.json", tmp_path / "report"
    out = _cli("decide", odo_store.path, "--queries", qfile, "--json", out_json, "--compare", "0,1", "--report", report)
    assert out.returncode == 0, out.stderr[-3000:]
    result = json.loads(out_json.read_text())
    _check_types(result["representation"], CONTRACT_REPRESENTATION, "representation")
    assert result["representation"]["revision"] == 1
    assert [d["id"] for d in result["decisions"]] == [q["id"] for q in subset]
    for d in result["decisions"]:
        _check_types(d, CONTRACT_DECISION, d["id"])
    assert {f["id"] for f in result["flipped"]} == flips
    for f in result["flipped"]:
        _check_types(f, CONTRACT_FLIP, f["id"])
    assert result["compared"]["a"]["revision"] == 0 and result["compared"]["b"]["revision"] == 1
    assert (report / "decisions.png").stat().st_size > 10_000
    again = _cli("decide", odo_store.path, "--queries", qfile, "--json", out_json, "--compare", "0,1")
    assert again.returncode == 1 and "--overwrite" in again.stderr
    assert json.loads(out_json.read_text()) == result


def test_queries_off_the_map_are_refused_by_the_library(gt_store: FrameStore) -> None:
    with pytest.raises(QueryError) as err:
        decide(gt_store, {"queries": [{"id": "far", "kind": "explore", "min_m": [50, 50, 0], "max_m": [51, 51, 1],
                                        "max_unknown_fraction": 0.5}]})
    assert err.value.query_id == "far"


# ------------------------------------------------------------------------------------------------ hostile input
def _one_error_line(out: subprocess.CompletedProcess) -> str:
    assert out.returncode != 0, (out.stdout, out.stderr)
    lines = [line for line in out.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and "Traceback" not in out.stderr, out.stderr
    return lines[0]


def test_decide_never_writes_into_the_source_the_store_was_built_from(gt_store: FrameStore, tmp_path: Path) -> None:
    """--json / --report inside (or equal to) the recorded source folder or the --poses file are refused, even with
    --overwrite, and the source file is left as it was."""
    q = tmp_path / "q.json"
    q.write_text(json.dumps({"queries": [BAD_CLI["negative_radius"][0] | {"radius_m": 0.1}]}))
    victim = LOG / "synthetic.json"
    before = victim.read_bytes()
    for args, flag in ((["--json", victim, "--overwrite"], "--json"),
                       (["--json", tmp_path / "o.json", "--report", LOG, "--overwrite"], "--report"),
                       (["--json", LOG / "groundtruth.txt", "--overwrite"], "--json")):
        line = _one_error_line(_cli("decide", gt_store.path, "--queries", q, *args))
        assert line.startswith(f"error: {flag} ") and "would replace" in line and "write it elsewhere" in line, line
    assert victim.read_bytes() == before
    assert not (tmp_path / "o.json").exists()


def test_a_diagnosis_with_double_walls_through_the_cli(odo_store: FrameStore, odo_decisions, odo_diagnosis,
                                                      tmp_path: Path) -> None:
    """``decide --diagnosis DG.json`` with double walls in reach (walls converted once, no AttributeError); the
    query file starts with a UTF-8 byte-order mark, which is accepted."""
    before, _ = odo_decisions
    near = [d.id for d in before.decisions if d.details["double_walls_in_reach"]][:2]
    assert near
    data = json.loads(QUERY_FILE.read_text())
    q = tmp_path / "q.json"
    q.write_text(json.dumps({"queries": [x for x in data["queries"] if x["id"] in near]}), encoding="utf-8-sig")
    assert q.read_bytes().startswith(b"\xef\xbb\xbf")
    dg = tmp_path / "dg.json"
    dg.write_text(json.dumps(odo_diagnosis.to_json()))
    out_json = tmp_path / "out.json"
    out = _cli("decide", odo_store.path, "--queries", q, "--json", out_json, "--revision", 0, "--diagnosis", dg)
    assert out.returncode == 0, out.stderr[-3000:]
    result = json.loads(out_json.read_text())
    assert [d["id"] for d in result["decisions"]] == [x for x in near]
    assert all(d["details"]["double_walls_in_reach"] for d in result["decisions"])


@pytest.mark.parametrize(("content", "field"), [
    ({"revision": 0, "double_wall": {"regions": [{}]}}, "center_m"),
    ({"revision": "zero"}, "revision"),
    (["x"], "not a diagnosis"),
    ({"revision": 0, "double_wall": {"regions": [{"center_m": [0, 0, 1], "separation_m": "wide"}]}}, "separation_m"),
])
def test_a_lying_diagnosis_is_one_line_naming_the_file(content, field: str, gt_store: FrameStore,
                                                       tmp_path: Path) -> None:
    q = tmp_path / "q.json"
    q.write_text(json.dumps({"queries": [{"id": "ok", "kind": "clearance", "points_m": [[1.5, 0, 1]], "radius_m": 0.1}]}))
    dg = tmp_path / "dg.json"
    dg.write_text(json.dumps(content))
    line = _one_error_line(_cli("decide", gt_store.path, "--queries", q, "--json", tmp_path / "o.json",
                                "--diagnosis", dg))
    assert str(dg) in line and field in line, line
    assert not (tmp_path / "o.json").exists()


def test_double_walls_already_converted_pass_through() -> None:
    from driftmap.decisions.walls import DoubleWall, double_walls_of

    wall = DoubleWall(np.zeros(3), np.array([0.0, 0.0, 1.0]), 0.05, (1, 2))
    assert double_walls_of(double_walls_of([wall])) == [wall]


@pytest.mark.parametrize(("query", "field"), [
    ({"id": "far", "kind": "collision", "path_m": [[0, 0, 0.3], [1e6, 0, 0.3]], "footprint": {"box_m": [0.1, 0.1, 0.1]}}, "path_m"),
    ({"id": "huge", "kind": "clearance", "points_m": [[1.5, 0, 1]], "radius_m": 1e20}, "radius_m"),
    ({"id": "wide", "kind": "collision", "path_m": [[0, 0, 0.3], [1, 0, 0.3]], "footprint": {"cylinder_m": [1e9, 1]}}, "footprint.cylinder_m"),
])
def test_runaway_sizes_are_refused_through_the_cli(query: dict, field: str, gt_store: FrameStore,
                                                   tmp_path: Path) -> None:
    """A path far off the map (100 M sweep samples) and a radius of 1e20 m: a QueryError naming query and field."""
    q = tmp_path / "q.json"
    q.write_text(json.dumps({"queries": [query]}))
    line = _one_error_line(_cli("decide", gt_store.path, "--queries", q, "--json", tmp_path / "o.json"))
    assert repr(query["id"]) in line and field in line, line


def test_a_sweep_needing_too_many_placements_is_refused() -> None:
    from driftmap.decisions import space

    q = parse_queries({"queries": [{"id": "long", "kind": "collision", "path_m": [[0, 0, 0], [20_000, 0, 0]],
                                    "footprint": {"box_m": [0.1, 0.1, 0.1]}}]}).queries[0]
    assert space.n_path_samples(q.path_m, 0.01) == 2_000_001
    with pytest.raises(QueryError) as err:
        space.check_path_samples(q, 0.01)
    assert err.value.query_id == "long" and err.value.field == "path_m"
    space.check_path_samples(q, 1.0)


def test_against_a_store_of_another_log_is_refused(gt_store: FrameStore, tmp_path: Path) -> None:
    """The same frame ids with other stamps: not the same log (the first differing frame named), nothing written."""
    log = tmp_path / "log"
    log.mkdir()
    for name in ("depth", "groundtruth.txt", "odometry.txt"):
        (log / name).symlink_to(LOG / name)
    data = json.loads((LOG / "synthetic.json").read_text())
    for f in data["frames"]:
        f["stamp_ns"] += 1000
    (log / "synthetic.json").write_text(json.dumps(data))
    build(log, tmp_path / "other", frames="0:3", poses_from_source=True, loop_closure=False)
    q = tmp_path / "q.json"
    q.write_text(json.dumps({"queries": [{"id": "ok", "kind": "clearance", "points_m": [[1.5, 0, 1]], "radius_m": 0.1}]}))
    line = _one_error_line(_cli("decide", gt_store.path, "--queries", q, "--json", tmp_path / "o.json",
                                "--against", tmp_path / "other"))
    assert "not of the same log" in line and "frame 0 " in line, line
    assert not (tmp_path / "o.json").exists()


def test_cli_messages_of_inputs(gt_store: FrameStore, tmp_path: Path) -> None:
    """--diagnosis equal to --queries, a missing --against-revision, a non-UTF-8 query file, a YAML id: yes."""
    q = tmp_path / "q.json"
    q.write_text(json.dumps({"queries": [{"id": "ok", "kind": "clearance", "points_m": [[1.5, 0, 1]], "radius_m": 0.1}]}))
    line = _one_error_line(_cli("decide", gt_store.path, "--queries", q, "--json", tmp_path / "o.json",
                                "--diagnosis", q))
    assert "the diagnosis and the queries are different files" in line and "own path" not in line, line
    line = _one_error_line(_cli("decide", gt_store.path, "--queries", q, "--json", tmp_path / "o.json",
                                "--against", gt_store.path, "--against-revision", 3))
    assert "--against-revision 3" in line and "--against store" in line, line
    latin = tmp_path / "latin.json"
    latin.write_bytes('{"queries": [{"id": "caf\u00e9"}]}'.encode("latin-1"))
    line = _one_error_line(_cli("decide", gt_store.path, "--queries", latin, "--json", tmp_path / "o.json"))
    assert str(latin) in line and "UTF-8" in line, line
    if pytest.importorskip("yaml"):
        for value in ("yes", "2024-01-02"):
            y = tmp_path / "q.yaml"
            y.write_text(f"queries:\n- id: {value}\n  kind: clearance\n  points_m: [[1.5, 0, 1]]\n  radius_m: 0.1\n")
            line = _one_error_line(_cli("decide", gt_store.path, "--queries", y, "--json", tmp_path / "o.json"))
            assert f'id: "{value}"' in line and "quote" in line, line
    assert not (tmp_path / "o.json").exists()


def test_a_decide_table_in_the_config_sets_the_thresholds_through_the_cli(gt_decisions: DecisionSet, queries,
                                                                          gt_store: FrameStore, tmp_path: Path) -> None:
    """``decide --config`` with a ``[decide]`` table: a graspable board grasp needs more points than its ROI holds
    and becomes too_few_points, under another settings hash; a bad threshold is one error line naming the key."""
    graspable = next(d for d in gt_decisions.decisions if d.kind == "grasp" and d.decision == "graspable")
    q = next(q for q in queries.queries if q.id == graspable.id)
    (tmp_path / "q.json").write_text(json.dumps({"queries": [
        {"id": q.id, "kind": "grasp", "roi_min_m": q.roi_min_m.tolist(), "roi_max_m": q.roi_max_m.tolist()}]}))
    (tmp_path / "strict.toml").write_text("[decide]\ngrasp_min_points = 1000000\n")
    runs = {}
    for name, extra in (("default", []), ("strict", ["--config", tmp_path / "strict.toml"])):
        out = _cli("decide", gt_store.path, "--queries", tmp_path / "q.json", "--json", tmp_path / f"{name}.json", *extra)
        assert out.returncode == 0, out.stderr[-2000:]
        runs[name] = json.loads((tmp_path / f"{name}.json").read_text())
    (default,), (strict,) = runs["default"]["decisions"], runs["strict"]["decisions"]
    assert default["decision"] == "graspable" and strict["decision"] == "too_few_points"
    assert runs["default"]["representation"]["settings_hash"] != runs["strict"]["representation"]["settings_hash"]
    (tmp_path / "bad.toml").write_text("[decide]\ngrasp_min_points = 1\n")
    line = _one_error_line(_cli("decide", gt_store.path, "--queries", tmp_path / "q.json", "--json",
                                tmp_path / "bad.json", "--config", tmp_path / "bad.toml"))
    assert "decide.grasp_min_points" in line and "bad.toml" in line, line
    assert not (tmp_path / "bad.json").exists()


def _without_latency(records: list[dict]) -> list[dict]:
    return [{k: v for k, v in d.items() if k != "latency_s"} for d in records]


def test_threads_answer_the_same_decisions_bit_for_bit(gt_decisions: DecisionSet, queries, gt_store: FrameStore,
                                                       tmp_path: Path) -> None:
    """``decide --threads 2`` through the CLI, on the whole query set (the shared voxel normals, frame spreads and
    provenance all read by two threads at once), writes the same records as the library's one thread, every float
    bit for bit (the JSON floats compared exactly), in the query file's order; a thread count the machine does
    not take is one error line naming --threads."""
    out_json = tmp_path / "threads.json"
    out = _cli("decide", gt_store.path, "--queries", QUERY_FILE, "--json", out_json, "--threads", 2)
    assert out.returncode == 0, out.stderr[-3000:]
    threaded = json.loads(out_json.read_text())["decisions"]
    single = json.loads(json.dumps(gt_decisions.to_json()))["decisions"]
    assert [d["id"] for d in threaded] == [q.id for q in queries]
    assert _without_latency(threaded) == _without_latency(single)
    line = _one_error_line(_cli("decide", gt_store.path, "--queries", QUERY_FILE, "--json", tmp_path / "o.json",
                                "--threads", 100_000))
    assert "--threads: 100000 threads is more than this machine takes" in line, line
    zero = _cli("decide", gt_store.path, "--queries", QUERY_FILE, "--json", tmp_path / "o.json", "--threads", 0)
    assert zero.returncode == 2 and "Invalid value for '--threads'" in zero.stderr, zero.stderr
    assert not (tmp_path / "o.json").exists()


def test_threads_of_the_library_are_checked(gt_store: FrameStore, queries) -> None:
    from driftmap.errors import ConfigError

    for bad in (0, -1, 2.5, True, 100_000):
        with pytest.raises(ConfigError, match="threads"):
            decide(gt_store, queries, threads=bad)


def test_threads_run_in_a_pool_and_a_failing_query_is_raised(monkeypatch: pytest.MonkeyPatch) -> None:
    """With 2 threads the queries run in the pool's threads, the decisions come back in the queries' order, and a
    query that raises is raised to the caller, naming it (the others' results are not returned half)."""
    import importlib
    import threading

    decide_module = importlib.import_module("driftmap.decisions.decide")  # the package exports the function
    ran_in: dict[str, str] = {}

    def fake(ctx, q):  # noqa: ANN001, ANN202
        ran_in[q.id] = threading.current_thread().name
        if q.id == "bad":
            raise QueryError(f"query {q.id!r}: cannot answer", query_id=q.id)
        return {"decision": "free", "margin": 1.0, "uncertainty": None, "failure_label": None, "frames": [],
                "stamp_ns_newest": None}

    class Context:
        prepared = 0

        def prepare_shared(self) -> None:
            Context.prepared += 1

    monkeypatch.setitem(decide_module.DECIDERS, "clearance", fake)
    qs = parse_queries({"queries": [{"id": f"q{k}", "kind": "clearance", "points_m": [[0, 0, k]], "radius_m": 0.1}
                                    for k in range(40)]})
    ticks: list[int] = []
    out = decide_module._answer_all(Context(), qs, 2, lambda stage, done, total: ticks.append(done))
    assert [d.id for d in out] == [q.id for q in qs] and ticks == list(range(1, 41))
    assert Context.prepared == 1 and all(name.startswith("driftmap-decide") for name in ran_in.values())
    bad = parse_queries({"queries": [*qs.raw[:5], {"id": "bad", "kind": "clearance", "points_m": [[0, 0, 0]],
                                                    "radius_m": 0.1}, *qs.raw[5:10]]})
    with pytest.raises(QueryError, match="bad"):
        decide_module._answer_all(Context(), bad, 2, lambda stage, done, total: None)
