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


def test_t26_w2_a_map_exported_again_without_voxels_leaves_no_stale_provenance(room10: dict[str, Path],
                                                                               tmp_path: Path) -> None:
    """``export --map X --voxel-size-m 0.5`` then ``export --map X --overwrite`` left the first export's
    ``X.provenance.npz`` beside the new full map: it is refused without --overwrite and removed with it."""
    out_map = tmp_path / "pv.ply"
    _ok(run_cli("export", room10["gt"], "--map", out_map, "--voxel-size-m", "0.5"))
    side = tmp_path / "pv.ply.provenance.npz"
    assert side.is_file()
    out_map.unlink()
    err = one_error(run_cli("export", room10["gt"], "--map", out_map))
    assert "pv.ply.provenance.npz" in err and "earlier voxelised export" in err, err
    assert not out_map.exists()
    out = _ok(run_cli("export", room10["gt"], "--map", out_map, "--overwrite"))
    assert out_map.is_file() and not side.exists() and "removed" in out.stdout


def test_t26_w3_w4_a_truncation_of_many_voxels_and_a_one_underscore_variable_are_named(room10: dict[str, Path],
                                                                                        tmp_path: Path) -> None:
    """``[volume] truncation_m = 100`` failed with an error blaming the voxel size for a 200 m grid; and
    ``DRIFTMAP_MAP_EXPORT_VOXEL_SIZE_M`` (one underscore between table and key) was ignored: both are refused, the
    setting named, the variable with the name it was meant to have."""
    cfg = tmp_path / "v.toml"
    cfg.write_text("[volume]\ntruncation_m = 100\n")
    err = one_error(run_cli("export", room10["gt"], "--mesh", tmp_path / "m.ply", "--config", cfg))
    assert "volume.truncation_m (100 m) must be at most 100 voxels" in err, err
    out = run_cli("export", room10["gt"], "--map", tmp_path / "e.ply", env={"DRIFTMAP_MAP_EXPORT_VOXEL_SIZE_M": "0.5"})
    err = one_error(out)
    assert "DRIFTMAP_MAP_EXPORT_VOXEL_SIZE_M" in err and "DRIFTMAP_MAP__EXPORT_VOXEL_SIZE_M?" in err, err
    assert not (tmp_path / "e.ply").exists()


def _png(path: Path, arr: np.ndarray, bit_depth: int, colour_type: int) -> None:
    import struct
    import zlib

    raw = b"".join(b"\x00" + row.tobytes() for row in arr)

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    h, w = arr.shape[:2]
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, bit_depth, colour_type, 0, 0, 0))
                     + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))


def test_t26_w5_a_16_bit_rgb_depth_png_is_named_as_the_file_states_it(sevenscenes_dir: Path, tmp_path: Path) -> None:
    """A 16-bit RGB PNG given as a depth image was reported as "dtype uint8" (Pillow reduces it to 8 bits), so the
    user would be told to save it as 16-bit: the error names the file's own bit depth and colour type."""
    import shutil

    from PIL import Image

    folder = tmp_path / "d7"
    folder.mkdir()
    shutil.copy(sevenscenes_dir / "camera-intrinsics.txt", folder)
    for i in range(3):
        for kind in ("pose.txt", "depth.png", "color.jpg"):
            shutil.copy(sevenscenes_dir / f"frame-{i:06d}.{kind}", folder)
    depth = np.asarray(Image.open(folder / "frame-000000.depth.png")).astype(">u2")
    _png(folder / "frame-000000.depth.png", np.stack([depth] * 3, axis=-1), 16, 2)
    err = one_error(run_cli("build", folder, "--out", tmp_path / "s", "--poses-from-source", "--no-loop-closure"))
    assert "frame-000000.depth.png" in err and "16-bit RGB (3 channels)" in err, err
    assert "one 16-bit grey channel" in err


def test_t26_w6_rows_exactly_between_two_frames_are_named_as_a_guess(room10: dict[str, Path], tmp_path: Path) -> None:
    """``correct --max-dt-ms`` wider than half the frames' spacing, rows stamped exactly between two frames: each
    went to the earlier frame without a word; the match is now warned about as a guess, naming the first such row."""
    import shutil

    from driftmap.store.frame_store import FrameStore

    store = tmp_path / "gt"
    shutil.copytree(room10["gt"], store)
    with FrameStore.open(store) as s:
        stamps = np.asarray(s.ledger.stamps_ns, dtype=np.int64)
        poses = np.asarray(s.poses(s.head))
    mid = (stamps[:-1] + stamps[1:]) // 2
    assert np.all((stamps[:-1] + stamps[1:]) % 2 == 0), "the test needs midpoints on whole nanoseconds"
    lines = []
    for t, T in zip(mid, poses[:-1]):
        from scipy.spatial.transform import Rotation

        q = Rotation.from_matrix(T[:3, :3]).as_quat()
        lines.append(f"{t // 10**9}.{t % 10**9:09d} " + " ".join(repr(float(v)) for v in (*T[:3, 3], *q)))
    (tmp_path / "mid.txt").write_text("\n".join(lines) + "\n")
    half_ms = float(np.median(np.diff(stamps))) / 2e6
    out = _ok(run_cli("correct", store, "--poses", tmp_path / "mid.txt", "--max-dt-ms", f"{half_ms + 1:.3f}"))
    text = " ".join((out.stdout + out.stderr).split())
    assert "lie exactly as far from two frames" in text and "which frame each belongs to is a guess" in text, text[-2000:]
