"""The eighth hostile-input trial's weak findings about ``driftmap decide`` (each worked but misled), through the path
the user took: W2 YAML merge keys refused cryptically; W5 a 400-digit id or unknown_is echoed in full (and a YAML
hint for a JSON file); W6 any JSON object taken as a diagnosis without double walls; W13 a ``[decide]`` threshold
written as text accepted."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from cli_run import one_error, run_cli

CLEARANCE = {"kind": "clearance", "points_m": [[0.0, 0.0, 1.0]], "radius_m": 0.2}


def _has_yaml() -> bool:
    try:
        import yaml  # noqa: F401
    except ImportError:
        return False
    return True


def _decide(room10: dict[str, Path], queries: Path, out: Path, *extra: object):
    return run_cli("decide", room10["gt"], "--queries", queries, "--json", out, *extra)


def test_t8_w2_yaml_merge_keys_are_defaults_and_a_duplicated_key_is_still_refused(room10: dict[str, Path],
                                                                                 tmp_path: Path) -> None:
    """``<<: *base``, ``<<: {...}`` and ``<<: [...]`` were refused with "could not determine a constructor for the
    tag 'tag:yaml.org,2002:merge'". They are standard YAML: the merged keys are defaults, an explicit key overrides
    them. A key written twice in one mapping (explicit, or inside a merged mapping) is still refused."""
    pytest.importorskip("yaml")
    (tmp_path / "q.yaml").write_text(
        "queries:\n"
        "  - &base {id: a, kind: clearance, points_m: [[0, 0, 1]], radius_m: 0.2}\n"
        "  - <<: *base\n"
        "    id: b\n"
        "    radius_m: 0.05\n"
        "  - <<: {kind: clearance, points_m: [[0, 0, 1]], radius_m: 0.1, unknown_is: free}\n"
        "    id: c\n"
        "  - <<: [{radius_m: 0.15}, *base]\n"
        "    id: d\n")
    out = _decide(room10, tmp_path / "q.yaml", tmp_path / "d.json")
    assert out.returncode == 0, out.stderr[-2000:]
    d = {x["id"]: x for x in json.loads((tmp_path / "d.json").read_text())["decisions"]}
    assert list(d) == ["a", "b", "c", "d"]
    radius = {qid: x["details"]["clearance_m"] - x["margin"] for qid, x in d.items()}
    assert radius == pytest.approx({"a": 0.2, "b": 0.05, "c": 0.1, "d": 0.15}, abs=1e-9), radius
    assert d["c"]["details"]["unknown_is"] == "free" and d["a"]["details"]["unknown_is"] == "occupied"
    for name, text in (
            ("twice.yaml", "queries:\n  - <<: {kind: clearance, points_m: [[0, 0, 1]], radius_m: 0.2}\n"
                           "    id: a\n    radius_m: 0.3\n    radius_m: 0.4\n"),
            ("inner.yaml", "queries:\n  - <<: {kind: clearance, points_m: [[0, 0, 1]], radius_m: 0.2, radius_m: 0.3}\n"
                           "    id: a\n")):
        (tmp_path / name).write_text(text)
        line = one_error(_decide(room10, tmp_path / name, tmp_path / "o.json"))
        assert name in line and "'radius_m' appears twice" in line and "constructor" not in line, line
    (tmp_path / "bad.yaml").write_text("queries:\n  - <<: 5\n    id: a\n")
    line = one_error(_decide(room10, tmp_path / "bad.yaml", tmp_path / "o.json"))
    assert "bad.yaml: not valid YAML" in line and "mapping or list of mappings for merging" in line, line
    assert "line 2" in line, line
    assert not (tmp_path / "o.json").exists()


def test_t8_w5_long_ids_and_policies_are_shortened_and_the_yaml_hint_is_for_yaml(room10: dict[str, Path],
                                                                                tmp_path: Path) -> None:
    """A 400-digit id or unknown_is was echoed in full, and the id's message told a JSON file's author to quote it
    in YAML. Long values are shortened (an integer by its digit count, a text by its start and length); the YAML
    hint is for YAML files, a JSON file is told to give a JSON string."""
    big = "7" * 400
    cases = [("id.json", '{"queries": [{"id": ' + big + ', "kind": "clearance"}]}',
              ["'id' must be a non-empty string, got an integer of 400 digits", "JSON string"]),
             ("id7.json", '{"queries": [{"id": 7, "kind": "clearance"}]}', ['give it as a JSON string ("id": "7")']),
             ("policy.json", json.dumps({"queries": [{**CLEARANCE, "id": "c"}]})[:-3] + ', "unknown_is": ' + big + "}]}",
              ["unknown_is must be one of occupied, free, got an integer of 400 digits"]),
             ("text.json", json.dumps({"queries": [{**CLEARANCE, "id": "c", "unknown_is": "x" * 400}]}),
              ["unknown_is must be one of occupied, free, got 'xxx", "(str of 400 characters)"])]
    if _has_yaml():
        cases += [("id.yaml", f"queries:\n  - id: {big}\n    kind: clearance\n",
                   ["got an integer of 400 digits", "in YAML quote it so it stays text"]),
                  ("id7.yaml", "queries:\n  - id: 7\n    kind: clearance\n", ['in YAML quote it (id: "7")'])]
    for name, text, expected in cases:
        (tmp_path / name).write_text(text)
        line = one_error(_decide(room10, tmp_path / name, tmp_path / "o.json"))
        assert all(e in line for e in expected), (name, line)
        assert big not in line and "x" * 100 not in line and len(line) < 400, (name, line)
        if name.endswith(".json"):
            assert "YAML" not in line, line
    assert not (tmp_path / "o.json").exists()


def test_t8_w6_a_json_object_that_is_no_diagnosis_is_refused(room10: dict[str, Path], tmp_path: Path) -> None:
    """``--diagnosis`` took any object ({}, the log's synthetic.json, the store's build_summary.json) as a diagnosis
    without double walls. Like a list, an object without 'revision' and 'double_wall' (or with values of the wrong
    type) is refused naming the file and what is missing; a diagnosis of the store still decides."""
    (tmp_path / "q.json").write_text(json.dumps({"queries": [{**CLEARANCE, "id": "c"}]}))
    (tmp_path / "empty.json").write_text("{}")
    (tmp_path / "types.json").write_text(json.dumps({"revision": True, "double_wall": []}))
    (tmp_path / "noregions.json").write_text(json.dumps({"revision": 0, "double_wall": {"voxels_evaluated": 3}}))
    (tmp_path / "norevision.json").write_text(json.dumps({"double_wall": {"regions": []}}))
    cases = [(tmp_path / "empty.json", ["it has no 'revision' and no 'double_wall'"]),
             (room10["log"] / "synthetic.json", ["it has no 'revision' and no 'double_wall'"]),
             (room10["gt"] / "build_summary.json", ["it has no 'revision' and no 'double_wall'"]),
             (tmp_path / "types.json", ["its 'revision' is true, not a revision id",
                                        "its 'double_wall' is [], not an object with 'regions'"]),
             (tmp_path / "noregions.json", ["its 'double_wall' has no 'regions' list"]),
             (tmp_path / "norevision.json", ["it has no 'revision'"])]
    for path, expected in cases:
        line = one_error(_decide(room10, tmp_path / "q.json", tmp_path / "o.json", "--diagnosis", path))
        assert f"{path}: not a diagnosis (diagnose --json writes an object with 'revision' and 'double_wall'" in line, line
        assert all(e in line for e in expected), (path, line)
    assert not (tmp_path / "o.json").exists()
    (tmp_path / "list.json").write_text("[1]")  # the message a list had already
    line = one_error(_decide(room10, tmp_path / "q.json", tmp_path / "o.json", "--diagnosis", tmp_path / "list.json"))
    assert "list.json: not a diagnosis (diagnose --json writes an object with 'revision' and 'double_wall', got a list)" \
        in line, line
    (tmp_path / "dg.json").write_text(json.dumps({"revision": 0, "double_wall": {"regions": []}}))
    out = _decide(room10, tmp_path / "q.json", tmp_path / "o.json", "--diagnosis", tmp_path / "dg.json")
    assert out.returncode == 0, out.stderr[-2000:]


def test_t8_w13_decide_thresholds_written_as_text_or_bools_are_refused(room10: dict[str, Path],
                                                                      tmp_path: Path) -> None:
    """``[decide] sweep_step_m = "0.1"`` was read as 0.1 m while a query file refuses "1". A ``[decide]`` threshold
    that is not a number (text, true / false), or a range_limited_points that is not true / false, is one error line
    naming the file and the key; the environment (always text) and numbers still set them."""
    (tmp_path / "q.json").write_text(json.dumps({"queries": [{**CLEARANCE, "id": "c"}]}))
    cases = [("step.toml", '[decide]\nsweep_step_m = "0.1"\n',
              "decide.sweep_step_m: expected a number, got '0.1' (text, in quotes: write the number without quotes)"),
             ("points.toml", '[decide]\ngrasp_min_points = "30"\n', "decide.grasp_min_points: expected a number, got '30'"),
             ("bool.toml", "[decide]\ndouble_wall_reach_m = true\n", "decide.double_wall_reach_m: expected a number, got true"),
             ("flag.toml", '[decide]\nrange_limited_points = "false"\n',
              "decide.range_limited_points: expected true or false, got 'false'"),
             ("step.json", json.dumps({"decide": {"normal_radius_m": "0.03"}}),
              "decide.normal_radius_m: expected a number, got '0.03'")]
    for name, text, expected in cases:
        (tmp_path / name).write_text(text)
        line = one_error(_decide(room10, tmp_path / "q.json", tmp_path / "o.json", "--config", tmp_path / name))
        assert f"{tmp_path / name}: {expected}" in line, line
    assert not (tmp_path / "o.json").exists()
    (tmp_path / "ok.toml").write_text("[decide]\nsweep_step_m = 0.1\ngrasp_min_points = 30\nrange_limited_points = false\n")
    out = _decide(room10, tmp_path / "q.json", tmp_path / "o.json", "--config", tmp_path / "ok.toml")
    assert out.returncode == 0, out.stderr[-2000:]
    out = run_cli("decide", room10["gt"], "--queries", tmp_path / "q.json", "--json", tmp_path / "e.json",
                  env={"DRIFTMAP_DECIDE__SWEEP_STEP_M": "0.1"})
    assert out.returncode == 0, out.stderr[-2000:]
