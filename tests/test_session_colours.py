"""Colour by session (issue 26): ``driftmap view --color session``, ``driftmap export --mcap --color session`` and
``driftmap info`` on a merged store of two sessions of the synthetic room, and on a store of one session; run through
the command line as a user does (docs/viewer.md, docs/export.md)."""

from __future__ import annotations

import re
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from cli_run import one_error, run_cli
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from PIL import Image
from scipy.spatial.transform import Rotation

from driftmap import geometry
from driftmap.export.foxglove import TOPIC_MAP, TOPIC_POINTS, export_foxglove_mcap
from driftmap.pipeline.build import build
from driftmap.pipeline.build_config import BuildConfig
from driftmap.pipeline.merge import SESSION_ID_STRIDE, merge_stores
from driftmap.render import SESSION_PALETTE_RGB
from driftmap.sources.synthetic import SyntheticLogConfig, generate_synthetic_log
from driftmap.store.frame_store import FrameStore
from driftmap.trajectory import read_trajectory

pytestmark = pytest.mark.slow

#: the room log at half resolution, 60 frames round the circle 2.2 times: frames 0-29 and 30-59 each see the room
ROOM = dict(n_frames=60, loop_turns=2.2, seed=5, width=160, height=120, fx=131.25, fy=131.25, cx=79.5, cy=59.5)
#: session B is stored in its own world frame, 3.6 m / 70 deg yaw away (nothing shared but the place)
T_MOVED = geometry.make_transform(Rotation.from_euler("zyx", [70, 5, -3], degrees=True), [3.0, -2.0, 0.4])
BLUE, ORANGE, GREEN = (np.asarray(SESSION_PALETTE_RGB[k], np.float64) for k in (0, 1, 2))


@pytest.fixture(scope="module")
def stores(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A (frames 0-29, the log's odometry), B (frames 30-59 moved by :data:`T_MOVED`) and their merge AB (~25 s)."""
    root = tmp_path_factory.mktemp("session_colours")
    log = generate_synthetic_log(root / "log", SyntheticLogConfig(**ROOM))
    odometry = read_trajectory(log / "odometry.txt", "tum")
    moved = root / "b_moved.txt"
    with moved.open("w") as f:
        for stamp, P in zip(odometry.stamps_ns[30:60], odometry.poses[30:60], strict=True):
            t, q = geometry.to_tum(T_MOVED @ P)
            f.write(f"{stamp / 1e9:.9f} {' '.join(f'{v:.9f}' for v in t)} {' '.join(f'{v:.9f}' for v in q)}\n")
    build(log, root / "A", poses_from_source=True, frames="0:30", loop_closure=False)
    build(log, root / "B", poses_file=moved, frames="30:60", loop_closure=False)
    result = merge_stores([root / "A", root / "B"], root / "AB", config=BuildConfig(odometry_edge_window=1))
    assert result.not_connected == [] and result.revision_id == 1
    return {"root": root, "A": root / "A", "B": root / "B", "AB": root / "AB"}


def _flat(text: str) -> str:
    """CLI output with table bars and runs of white space collapsed."""
    return " ".join(text.replace("\u2502", " ").split())


def _pixels_of(image: np.ndarray, rgb: np.ndarray, tol: float = 6.0) -> int:
    """Pixels drawn in colour ``rgb``: ``s * rgb`` for a shading ``s`` in [0.3, 1] (the renderer darkens depth
    edges by at most 0.35), within ``tol`` of it."""
    p = image.reshape(-1, 3).astype(np.float64)
    s = p @ rgb / (rgb @ rgb)
    return int(np.count_nonzero((s >= 0.3) & (s <= 1.02) & (np.linalg.norm(p - s[:, None] * rgb, axis=1) <= tol)))


def _view(store: Path, out: Path, *extra: object) -> Any:
    return run_cli("view", store, "--color", "session", "--headless", "--backend", "software", "--out", out, *extra)


def read_mcap(path: Path) -> tuple[dict[str, list[tuple[Any, Any]]], dict[str, dict[str, str]]]:
    """topic -> [(channel, decoded message)] and the metadata records, with the generic mcap reader only."""
    by_topic: dict[str, list] = defaultdict(list)
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for _, channel, _, decoded in reader.iter_decoded_messages(log_time_order=False):
            by_topic[channel.topic].append((channel, decoded))
        metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
    return by_topic, metadata


def cloud_columns(msg: Any) -> dict[str, np.ndarray]:
    """Every float32 and uint8 field of a foxglove.PointCloud as a column."""
    data = np.frombuffer(msg.data, dtype=np.uint8).reshape(-1, msg.point_stride)
    cols = {}
    for f in msg.fields:
        if f.type == 7:  # FLOAT32
            cols[f.name] = np.ascontiguousarray(data[:, f.offset : f.offset + 4]).view("<f4")[:, 0]
        elif f.type == 1:  # UINT8
            cols[f.name] = data[:, f.offset].copy()
    return cols


def test_view_color_session_draws_each_session_in_its_own_colour(stores: dict, tmp_path: Path) -> None:
    """Headless PNG views of the merged store: the top view holds many pixels of session 0's blue and session 1's
    orange (the two sessions see the same room, so both are everywhere) and none of a third palette colour; the
    command lists each session with its colour, frames and source store."""
    out = _view(stores["AB"], tmp_path / "view")
    assert out.returncode == 0, out.stderr[-2000:]
    text = _flat(out.stdout)
    assert "colour session" in text and "2 sessions:" in text
    assert re.search(rf"session 0 #1f77b4 \(blue\) 30 frames, [\d,]+ points shown from {re.escape(str(stores['A'].resolve()))}", text), text
    assert re.search(rf"session 1 #ff7f0e \(orange\) 30 frames, [\d,]+ points shown from {re.escape(str(stores['B'].resolve()))}", text), text
    top = np.asarray(Image.open(tmp_path / "view" / "top_rev1_session.png").convert("RGB"))
    drawn = int(np.count_nonzero(np.any(np.abs(top.astype(int) - (20, 20, 24)) > 8, axis=2)))
    blue, orange, green = (_pixels_of(top, c) for c in (BLUE, ORANGE, GREEN))
    assert drawn > 20_000, drawn
    # measured: 47 % blue and 53 % orange of the drawn pixels
    assert blue > 0.2 * drawn and orange > 0.2 * drawn, (blue, orange, drawn)
    assert blue + orange > 0.9 * drawn and green == 0, (blue, orange, green, drawn)
    assert (tmp_path / "view" / "overview_rev1_session.png").stat().st_size > 0


def test_view_colours_every_point_by_its_frames_session(stores: dict) -> None:
    """The library behind ``view``: every shown point of session 0's frames is blue, of session 1's orange; the
    legend counts the frames and the points."""
    from driftmap.viewer import colored_map

    with FrameStore.open(stores["AB"]) as store:
        cmap = colored_map(store, color="session")
    ses = cmap.frame_ids // SESSION_ID_STRIDE
    assert set(np.unique(ses)) == {0, 1}
    assert np.all(cmap.colors[ses == 0] == SESSION_PALETTE_RGB[0])
    assert np.all(cmap.colors[ses == 1] == SESSION_PALETTE_RGB[1])
    assert [(s.session, s.n_frames, s.n_points_shown) for s in cmap.sessions] == [
        (0, 30, int(np.sum(ses == 0))), (1, 30, int(np.sum(ses == 1)))]
    assert cmap.sessions[0].source_store == str(stores["A"].resolve()) and cmap.sessions[1].source_store == str(stores["B"].resolve())


def test_view_color_session_on_a_store_of_one_session_is_one_colour_and_says_so(stores: dict, tmp_path: Path) -> None:
    """A store that no merge made is one session: drawn in session 0's colour only, and the command says so."""
    out = _view(stores["A"], tmp_path / "one")
    assert out.returncode == 0, out.stderr[-2000:]
    text = _flat(out.stdout)
    assert "one session (not a merged store: driftmap merge makes one), one colour: session 0 #1f77b4 (blue), 30 frames" in text
    top = np.asarray(Image.open(tmp_path / "one" / "top_rev0_session.png").convert("RGB"))
    drawn = int(np.count_nonzero(np.any(np.abs(top.astype(int) - (20, 20, 24)) > 8, axis=2)))
    blue, orange = _pixels_of(top, BLUE), _pixels_of(top, ORANGE)
    assert drawn > 20_000 and blue > 0.9 * drawn and orange == 0, (blue, orange, drawn)


def test_export_mcap_color_session_carries_each_sessions_colour_on_its_frames(stores: dict, tmp_path: Path) -> None:
    """``export --mcap --color session``: every ``/points`` cloud is its frame's session's colour, ``/map`` has a
    ``session`` field and that session's colour per voxel (both sessions present), the metadata names the colours."""
    path = tmp_path / "sessions.mcap"
    out = run_cli("export", stores["AB"], "--mcap", path, "--color", "session", "--no-volume")
    assert out.returncode == 0, out.stderr[-2000:]
    text = _flat(out.stdout)
    assert "session 0 #1f77b4 (blue) 30 frames" in text and "session 1 #ff7f0e (orange) 30 frames" in text
    by_topic, metadata = read_mcap(path)
    frames_seen = {0: 0, 1: 0}
    for _, msg in by_topic[TOPIC_POINTS]:
        fid = int(msg.frame_id.rsplit("@", 1)[1])
        session = fid // SESSION_ID_STRIDE
        cols = cloud_columns(msg)
        rgba = np.stack([cols[c] for c in ("red", "green", "blue", "alpha")], axis=1)
        assert len(rgba) > 0 and np.all(rgba == (*SESSION_PALETTE_RGB[session], 255)), (fid, rgba[:3])
        frames_seen[session] += 1
    assert frames_seen == {0: 30, 1: 30}
    (_, map_msg), = by_topic[TOPIC_MAP]
    cols = cloud_columns(map_msg)
    assert [f.name for f in map_msg.fields] == ["x", "y", "z", "n_frames", "frame_id", "session", "red", "green", "blue",
                                                "alpha"]
    session = cols["session"].astype(int)
    assert set(np.unique(session)) == {0, 1} and np.sum(session == 1) > 0.1 * len(session)
    # frame_id is float32 (1e9 + k rounds to a multiple of 64): its session is still the right one
    assert np.array_equal(session, (cols["frame_id"] >= SESSION_ID_STRIDE - 64).astype(int))
    palette = np.asarray(SESSION_PALETTE_RGB, np.uint8)
    assert np.array_equal(np.stack([cols["red"], cols["green"], cols["blue"]], axis=1), palette[session])
    assert np.all(cols["alpha"] == 255)
    meta = metadata["driftmap.foxglove_export"]
    assert meta["color"] == "session"
    assert meta["sessions"] == "0=#1f77b4 (blue), 30 frames; 1=#ff7f0e (orange), 30 frames"


def test_export_mcap_without_color_session_is_unchanged(stores: dict, tmp_path: Path) -> None:
    """Without the option the export is what it always was: ``color="frame"`` writes the same bytes as leaving it
    out, ``/map`` has the five float fields and ``/points`` no colour (the room has none), no session metadata."""
    with FrameStore.open(stores["AB"]) as store:
        # per-frame downsampling off: Open3D's voxel downsampling does not keep the point order from run to run
        export_foxglove_mcap(store, tmp_path / "default.mcap", frame_voxel_size_m=None, map_voxel_size_m=0.05)
        export_foxglove_mcap(store, tmp_path / "frame.mcap", frame_voxel_size_m=None, map_voxel_size_m=0.05,
                             color="frame")
    assert (tmp_path / "default.mcap").read_bytes() == (tmp_path / "frame.mcap").read_bytes()
    by_topic, metadata = read_mcap(tmp_path / "default.mcap")
    (_, map_msg), = by_topic[TOPIC_MAP]
    assert [f.name for f in map_msg.fields] == ["x", "y", "z", "n_frames", "frame_id"]
    assert all([f.name for f in msg.fields] == ["x", "y", "z"] for _, msg in by_topic[TOPIC_POINTS])
    assert "color" not in metadata["driftmap.foxglove_export"] and "sessions" not in metadata["driftmap.foxglove_export"]


def test_export_mcap_color_session_of_one_session_is_one_colour(stores: dict, tmp_path: Path) -> None:
    path = tmp_path / "one.mcap"
    out = run_cli("export", stores["A"], "--mcap", path, "--color", "session", "--no-volume")
    assert out.returncode == 0, out.stderr[-2000:]
    assert "one session (not a merged store: driftmap merge makes one), one colour: session 0 #1f77b4 (blue)" in _flat(out.stdout)
    by_topic, metadata = read_mcap(path)
    cols = cloud_columns(by_topic[TOPIC_MAP][0][1])
    assert np.all(cols["session"] == 0) and np.all(cols["red"] == SESSION_PALETTE_RGB[0][0])
    assert metadata["driftmap.foxglove_export"]["sessions"] == "0=#1f77b4 (blue), 30 frames"


def test_info_lists_each_session_with_its_frames_source_and_stamps(stores: dict) -> None:
    out = run_cli("info", stores["AB"])
    assert out.returncode == 0, out.stderr[-2000:]
    text = _flat(out.stdout)
    for k, name in ((0, "A"), (1, "B")):
        with FrameStore.open(stores[name]) as src:
            stamps = src.ledger.stamps_ns
            n = len(src)
        span = f"stamps {stamps.min() / 1e9:.3f} .. {stamps.max() / 1e9:.3f} s ({(stamps.max() - stamps.min()) / 1e9:.2f} s)"
        assert f"session {k} {n} frames from {stores[name].resolve()} (revision 0); {span}" in text, text
    assert "session 2" not in text
    assert "session 0" not in _flat(run_cli("info", stores["A"]).stdout)  # a store no merge made has no session rows


def test_bad_color_values_are_refused_with_the_choices(stores: dict, tmp_path: Path) -> None:
    err = one_error(run_cli("view", stores["AB"], "--color", "sessions", "--headless", "--out", tmp_path / "v"))
    assert "--color" in err and "frame, revision, double-wall, state, session" in err, err
    err = one_error(run_cli("export", stores["AB"], "--mcap", tmp_path / "x.mcap", "--color", "rainbow"))
    assert "--color" in err and "frame, session" in err, err
    err = one_error(run_cli("export", stores["AB"], "--map", tmp_path / "x.ply", "--color", "session"))
    assert "--color" in err and "--mcap" in err, err
    assert not (tmp_path / "v").exists() and not (tmp_path / "x.mcap").exists() and not (tmp_path / "x.ply").exists()


def test_export_session_arguments_are_checked_before_anything_is_written(stores: dict, tmp_path: Path) -> None:
    """``sessions=`` without ``color="session"``, an unknown colour, a frame in no session, in two or unknown to the
    store: a ``ConfigError`` naming it, and no file."""
    from driftmap.errors import ConfigError

    path = tmp_path / "bad.mcap"
    with FrameStore.open(stores["AB"]) as store:
        ids = [int(f) for f in store.frame_ids]
        a, b = ids[:30], ids[30:]
        cases = [(dict(sessions={0: a, 1: b}), "color='session'"), (dict(color="rainbow"), "frame, session"),
                 (dict(color="session", sessions={0: a, 1: b[:-1]}), f"frame {b[-1]} of .* is in no session"),
                 (dict(color="session", sessions={0: a, 1: b + [a[0]]}), f"frame {a[0]} is in two sessions"),
                 (dict(color="session", sessions={0: a, 1: b + [5 * SESSION_ID_STRIDE]}),
                  f"names frame {5 * SESSION_ID_STRIDE}, which .* does not hold")]
        for kwargs, message in cases:
            with pytest.raises(ConfigError, match=message):
                export_foxglove_mcap(store, path, include_frames=False, map_voxel_size_m=0.1, **kwargs)
    assert not path.exists() and list(tmp_path.iterdir()) == []
