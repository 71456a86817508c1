"""Hostile trial 26: its findings, each through the path the user took (docs/bad-input.md, trial 26)."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
from cli_run import one_error, run_cli

from driftmap.decisions import parse_queries
from driftmap.decisions.query_file import MAX_VALUES_PER_QUERY
from driftmap.errors import QueryError


def _ok(out):  # noqa: ANN001, ANN202 - a CompletedProcess
    assert out.returncode == 0, (out.stdout[-2000:], out.stderr[-2000:])
    return out


def _clearance_query(point: list[float]) -> str:
    return (f"  - id: c1\n    kind: clearance\n    points_m: [[{point[0]}, {point[1]}, {point[2]}]]\n"
            f"    radius_m: 0.1\n")


def test_t26_b1_a_yaml_alias_bomb_in_a_query_file_is_refused_at_once(room10: dict[str, Path], tmp_path: Path) -> None:
    """A 431-byte YAML query file whose ignored ``note`` names nested aliases (9^9 = 387M values) ran without end
    (1.1 GB and growing after 30 s): every value of a query is counted as it is read, the file refused past
    MAX_VALUES_PER_QUERY, naming the query; the same aliases within the bound are read."""
    levels = ["a: &a [" + ",".join(['"x"'] * 9) + "]"]
    for prev, name in zip("abcdefgh", "bcdefghi"):
        levels.append(f"{name}: &{name} [" + ",".join([f"*{prev}"] * 9) + "]")
    bomb = tmp_path / "q_bomb.yaml"
    bomb.write_text("\n".join(levels) + "\nqueries:\n" + _clearance_query([0.0, 0.0, 1.0]) + "    note: *i\n")
    assert bomb.stat().st_size < 1000
    t = time.monotonic()
    out = run_cli("decide", room10["gt"], "--queries", bomb, "--json", tmp_path / "d.json", timeout=120)
    err = one_error(out)
    assert time.monotonic() - t < 60
    assert "q_bomb.yaml" in err and "'c1'" in err and f"more than {MAX_VALUES_PER_QUERY:,} values" in err, err
    assert "aliases" in err and not (tmp_path / "d.json").exists()
    small = tmp_path / "q_small.yaml"  # 9^3 = 729 values through aliases: read, the note ignored
    small.write_text("\n".join(levels[:3]) + "\nqueries:\n" + _clearance_query([0.0, 0.0, 1.0]) + "    note: *c\n")
    _ok(run_cli("decide", room10["gt"], "--queries", small, "--json", tmp_path / "d.json"))
    assert json.loads((tmp_path / "d.json").read_text())["decisions"][0]["id"] == "c1"


def test_t26_b1_queries_made_in_code_are_bounded_alike() -> None:
    """parse_queries on Python data: a query sharing one list many times is refused (the library path)."""
    shared = [[0.0, 0.0, 1.0]] * 10
    huge = [shared] * (MAX_VALUES_PER_QUERY // 10)
    with pytest.raises(QueryError, match=r"query 'q' holds more than"):
        parse_queries({"queries": [{"id": "q", "kind": "clearance", "points_m": [[0.0, 0.0, 1.0]], "radius_m": 0.1,
                                    "note": huge}]})
    ok = parse_queries({"queries": [{"id": "q", "kind": "clearance", "points_m": np.zeros((3, 3)), "radius_m": 0.1}]})
    assert len(ok) == 1


@pytest.mark.parametrize("text, key", [
    ("[mapp]\nexport_voxel_size_m = 0.5\n", "mapp"),
    ("[volum]\nvoxel_size_m = 0.1\n", "volum"),
    ("voxel_size_m = 0.1\n", "voxel_size_m"),
])
def test_t26_b2_export_and_decide_refuse_a_misspelled_table_or_stray_key(room10: dict[str, Path], tmp_path: Path,
                                                                        text: str, key: str) -> None:
    """``export --config`` / ``decide --config`` took a file whose only table was misspelled (or bare keys) as a
    bare build config and ran on the defaults (exit 0): both now check the file as build does, naming the file and
    the key, and write nothing."""
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(text)
    out = run_cli("export", room10["gt"], "--map", tmp_path / "m.ply", "--config", cfg)
    err = one_error(out)
    assert "cfg.toml" in err and f"{key}: unknown setting" in err, err
    assert not (tmp_path / "m.ply").exists()
    queries = tmp_path / "q.yaml"
    queries.write_text("queries:\n" + _clearance_query([0.0, 0.0, 1.0]))
    err = one_error(run_cli("decide", room10["gt"], "--queries", queries, "--json", tmp_path / "d.json",
                            "--config", cfg))
    assert "cfg.toml" in err and f"{key}: unknown setting" in err, err
    assert not (tmp_path / "d.json").exists()


def test_t26_b2_a_build_only_config_applies_to_nothing_in_export(room10: dict[str, Path], tmp_path: Path) -> None:
    """A valid bare build config (no general table) given to export is refused as applying to nothing; the
    intended table is taken (0.5 m voxels)."""
    cfg = tmp_path / "build.toml"
    cfg.write_text("pixel_stride = 2\n")
    err = one_error(run_cli("export", room10["gt"], "--map", tmp_path / "m.ply", "--config", cfg))
    assert "build.toml" in err and "none of which applies to export" in err and "pixel_stride" in err, err
    good = tmp_path / "map.toml"
    good.write_text("[map]\nexport_voxel_size_m = 0.5\n")
    out = _ok(run_cli("export", room10["gt"], "--map", tmp_path / "m.ply", "--config", good))
    assert "voxel 0.5 m" in " ".join(out.stdout.split())
