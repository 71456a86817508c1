"""Hostile trial 24: its broken findings, each through the path the user took (docs/bad-input.md, trial 24).

B1: a clearance query within the documented limits (100,000 points, radius 2 m) allocated 30 GiB and died with a
raw traceback (one row per point per voxel column); B2: ``export --voxel-size-m 1e-100`` wrote a 1-point map and
exited 0 (the voxel coordinates' cast to int64 wrapped); B3: ``decide --diagnosis`` took another store's diagnosis
when the two logs shared every frame id and stamp."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from cli_run import one_error, run_cli

from driftmap.decisions import space
from driftmap.decisions.query_file import ClearanceQuery
from driftmap.store.frame_store import FrameStore


def _ok(out):  # noqa: ANN001, ANN202 - a CompletedProcess
    assert out.returncode == 0, (out.stdout[-2000:], out.stderr[-2000:])
    return out


def _clearance_file(path: Path, n: int, radius_m: float, seed: int = 1) -> Path:
    rng = np.random.default_rng(seed)
    pts = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-1, 1, n), rng.uniform(0.5, 1.5, n)])
    path.write_text(json.dumps({"queries": [{"id": "wide", "kind": "clearance", "points_m": pts.round(4).tolist(),
                                             "radius_m": radius_m}]}))
    return path


def test_t24_b1_a_clearance_query_beyond_the_work_bound_is_one_error_line(room10: dict, tmp_path: Path) -> None:
    q = _clearance_file(tmp_path / "q.json", 100_000, 2.0)
    line = one_error(run_cli("decide", room10["gt"], "--queries", q, "--json", tmp_path / "o.json"))
    assert "'wide'" in line and "voxel columns" in line and "radius_m" in line, line
    assert not (tmp_path / "o.json").exists()


def test_t24_b1_the_balls_counted_in_chunks_give_the_same_count(room10: dict, monkeypatch) -> None:  # noqa: ANN001
    """The unknown voxels of many balls, counted in chunks of a few columns, equal the count of one pass (and a
    query just under the bound passes the check)."""
    from driftmap.volume.layers import VolumeLayers

    store = FrameStore.open(room10["gt"])
    try:
        layers = VolumeLayers.from_store(store, store.head)
    finally:
        store.close()
    rng = np.random.default_rng(5)
    pts = np.column_stack([rng.uniform(-2, 2, 40), rng.uniform(-2, 2, 40), rng.uniform(0.2, 2.0, 40)])
    whole = space.unknown_in_balls(layers, pts, 0.3)
    assert whole > 0
    monkeypatch.setattr(space, "BALL_COLUMN_CHUNK", 1000)  # ~900 columns per ball: one or two balls per chunk
    assert space.unknown_in_balls(layers, pts, 0.3) == whole
    monkeypatch.setattr(space, "BALL_COLUMN_CHUNK", 1)  # smaller than one ball: one ball per chunk
    assert space.unknown_in_balls(layers, pts, 0.3) == whole
    vs = float(layers.grid.voxel_size_m)
    q = ClearanceQuery(id="edge", kind="clearance", points_m=pts, radius_m=0.3)
    n = space.n_ball_columns(pts, 0.3, vs)
    monkeypatch.setattr(space, "MAX_BALL_COLUMNS", n)
    space.check_ball_columns(q, vs)  # at the bound: taken
    monkeypatch.setattr(space, "MAX_BALL_COLUMNS", n - 1)
    with pytest.raises(space.QueryError, match="'edge'"):
        space.check_ball_columns(q, vs)


@pytest.mark.parametrize("flag", ["--map", "--mcap"])
@pytest.mark.parametrize("size", ["1e-25", "1e-100", "1e-300"])
def test_t24_b2_a_voxel_size_too_small_to_index_is_refused(room10: dict, tmp_path: Path, flag: str,
                                                           size: str) -> None:
    out_file = tmp_path / ("m.ply" if flag == "--map" else "m.mcap")
    line = one_error(run_cli("export", room10["gt"], flag, out_file, "--voxel-size-m", size))
    assert "voxel_size_m" in line and "too small" in line, line
    assert not out_file.exists()


def test_t24_b2_voxel_coords_never_wrap() -> None:
    from driftmap.errors import ConfigError
    from driftmap.voxels import voxel_coord_columns, voxel_coords

    pts = np.array([[1.0, -2.0, 0.5], [0.25, 0.0, -0.75]], np.float32)
    assert voxel_coords(pts, 0.5).tolist() == [[2, -4, 1], [0, 0, -2]]
    for size in (1e-25, 1e-60, 1e-300):  # float32 coordinates beyond 2^62, or a size that is 0 in float32
        with pytest.raises(ConfigError, match="too small"):
            voxel_coords(pts, size)
        with pytest.raises(ConfigError, match="too small"):
            voxel_coord_columns(list(pts.T), size)


@pytest.fixture(scope="module")
def other_room(tmp_path_factory: pytest.TempPathFactory, room10: dict) -> dict[str, Path]:
    """Another log (seed 4) of the same length as room10's: the same frame ids and stamps, another map; its
    diagnosis, and room10's own."""
    root = tmp_path_factory.mktemp("trial24")
    log = root / "log"
    _ok(run_cli("synth", log, "--seed", 4, "--frames", 10))
    store = root / "B"
    _ok(run_cli("build", log, "--out", store, "--poses", log / "groundtruth.txt", "--no-loop-closure"))
    _ok(run_cli("diagnose", store, "--json", root / "diag_B.json"))
    _ok(run_cli("diagnose", room10["gt"], "--json", root / "diag_A.json"))
    return {"B": store, "diag_B": root / "diag_B.json", "diag_A": root / "diag_A.json"}


def test_t24_b3_decide_refuses_another_stores_diagnosis(room10: dict, other_room: dict, tmp_path: Path) -> None:
    a, b = FrameStore.open(room10["gt"]), FrameStore.open(other_room["B"])
    try:  # the trial's premise: frame ids and stamps alike, so the frames check alone cannot tell them apart
        assert np.array_equal(a.ledger.frame_ids, b.ledger.frame_ids)
        assert np.array_equal(a.ledger.stamps_ns, b.ledger.stamps_ns)
        uuid_a, uuid_b = a.uuid, b.uuid
    finally:
        a.close()
        b.close()
    assert json.loads(other_room["diag_B"].read_text())["store_uuid"] == uuid_b != uuid_a
    q = tmp_path / "q.json"
    q.write_text(json.dumps({"queries": [{"id": "c", "kind": "clearance", "points_m": [[0.0, 0.0, 1.0]],
                                          "radius_m": 0.1}]}))
    line = one_error(run_cli("decide", room10["gt"], "--queries", q, "--json", tmp_path / "o.json", "--diagnosis",
                             other_room["diag_B"]))
    assert "another store" in line and uuid_b in line and str(other_room["diag_B"]) in line, line
    assert not (tmp_path / "o.json").exists()
    _ok(run_cli("decide", room10["gt"], "--queries", q, "--json", tmp_path / "o.json", "--diagnosis",
                other_room["diag_A"]))  # its own diagnosis: taken
    old = json.loads(other_room["diag_A"].read_text())
    del old["store_uuid"]  # a diagnosis written before the store id was: its frames checked, with a warning
    (tmp_path / "old.json").write_text(json.dumps(old))
    out = _ok(run_cli("decide", room10["gt"], "--queries", q, "--json", tmp_path / "o2.json", "--diagnosis",
                      tmp_path / "old.json"))
    assert "names no store" in " ".join(out.stderr.split())


def test_t24_w6_against_the_store_itself_at_the_same_revision_is_refused(room10: dict, tmp_path: Path) -> None:
    q = tmp_path / "q.json"
    q.write_text(json.dumps({"queries": [{"id": "c", "kind": "clearance", "points_m": [[0.0, 0.0, 1.0]],
                                          "radius_m": 0.1}]}))
    line = one_error(run_cli("decide", room10["gt"], "--queries", q, "--json", tmp_path / "o.json", "--against",
                             room10["gt"]))
    assert "with itself" in line and "--against-revision" in line, line
    assert not (tmp_path / "o.json").exists()
