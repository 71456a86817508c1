"""Fuzzing the frame store's reader (issue 22): a small valid store is damaged at random -- segments truncated
at random offsets, bits flipped anywhere in them, the manifest's text or values changed, revision and frame
records that are well-formed MCAP (valid CRCs) but hold nonsense -- and then opened, read and recovered.

Whatever the damage, each of ``FrameStore.open``, reading every frame, building the map and ``FrameStore.recover``
ends either in a typed :class:`~driftmap.errors.DriftmapError` or in a store whose frames are bit-identical to the
originals: never another exception, never a crash. Nothing read from a file sizes an allocation before it is
checked against the bytes present (a length field pointing past the end is damage, not a request for memory).
With chunk CRCs checked (the default), a store that still opens after one corruption holds *every* original frame
and revision: damage is never read silently.
"""

from __future__ import annotations

import copy
import itertools
import json
import os
import shutil
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from unittest import mock

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_store import assert_frames_identical

from driftmap import Frame, PointAttributes, PoseEstimate, PoseSource
from driftmap.errors import DriftmapError
from driftmap.map.view import MapView
from driftmap.store import segment as segment_module
from driftmap.store.frame_store import FrameStore

#: 25 examples per test keep the file well under a minute; DRIFTMAP_FUZZ_EXAMPLES=1000 for a longer hunt
SETTINGS = settings(max_examples=int(os.environ.get("DRIFTMAP_FUZZ_EXAMPLES", "25")), deadline=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


def _frame(i: int, *, attributes: bool = False) -> Frame:
    rng = np.random.default_rng(i)
    n = 40
    attrs = PointAttributes()
    if attributes:
        normals = rng.normal(size=(n, 3)).astype(np.float32)
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        attrs = PointAttributes(intensity=rng.random(n).astype(np.float32),
                                color_rgb=rng.integers(0, 255, (n, 3), dtype=np.uint8), normal_sensor=normals,
                                time_offset_ns=rng.integers(0, 10**8, n).astype(np.int64))
    T = np.eye(4)
    T[:3, 3] = (0.3 * i, 0.05 * i * i, 0.01)
    return Frame(frame_id=i, stamp_ns=10**9 + 10**8 * i, sensor_name="lidar", sensor_kind="lidar",
                 points_sensor=rng.normal(size=(n, 3)).astype(np.float32), attributes=attrs,
                 pose=PoseEstimate(T, source=PoseSource.ODOMETRY), sensor_frame="velodyne")


def _moved(T: np.ndarray, dx: float) -> np.ndarray:
    out = T.copy()
    out[0, 3] += dx
    return out


@dataclass
class Template:
    path: Path
    frames: dict[int, Frame] = field(repr=False)
    poses: dict[int, np.ndarray] = field(repr=False)  # revision -> (N, 4, 4) in frame id order
    segment_of: dict[int, str] = field(repr=False)  # frame id -> segment file name


def _write_template(path: Path) -> Template:
    """Two writer sessions (two segments), five frames (one with every attribute), three revisions."""
    frames = {i: _frame(i, attributes=i == 1) for i in range(5)}
    with FrameStore.create(path) as store:
        for i in (0, 1, 2):
            store.append(frames[i])
        store.add_revision({0: _moved(frames[0].T_world_sensor, 0.02), 2: _moved(frames[2].T_world_sensor, -0.01)},
                           source="loop_closure")
    with FrameStore.open(path, "a") as store:
        for i in (3, 4):
            store.append(frames[i])
        store.add_revision({4: _moved(frames[4].T_world_sensor, 0.05)}, source="external_file")
        store.rollback(1)
        poses = {r.revision_id: store.poses(r.revision_id).copy() for r in store.revisions}
        segment_of = {int(f): store.frame_ref(int(f)).segment.name for f in store.frame_ids}
    return Template(path, frames, poses, segment_of)


@pytest.fixture(scope="module")
def template(tmp_path_factory: pytest.TempPathFactory) -> Template:
    return _write_template(tmp_path_factory.mktemp("fuzz") / "template")


_counter = itertools.count()


@contextmanager
def damaged_copy(template: Template):
    base = Path(tempfile.mkdtemp(prefix=f"fuzz{next(_counter)}-"))
    try:
        path = base / "store"
        shutil.copytree(template.path, path)
        yield path
    finally:
        shutil.rmtree(base, ignore_errors=True)


def _segments(path: Path) -> list[Path]:
    return sorted(path.glob("segment-*.mcap"))


# ------------------------------------------------------------------------------------------------ checks


def _read_everything(path: Path, template: Template, *, verify: bool = True) -> FrameStore | None:
    """Open, read every frame and build the map of every revision. Returns the (closed) store, or None when a typed
    error stopped it; any other exception fails the test. With ``verify``, every frame read is the original."""
    try:
        with FrameStore.open(path, verify=verify) as store:
            for fid in store.frame_ids:
                frame = store.frame(int(fid))
                if verify:
                    assert_frames_identical(frame, template.frames[int(fid)])
            for rev in store.revisions:
                store.poses(rev.revision_id)
            view = MapView.from_store(store, store.head)
            view.points_world.sum()
            return store
    except DriftmapError:
        return None


def _assert_complete(store: FrameStore, template: Template) -> None:
    """The store holds every original frame and revision, bit for bit."""
    assert [int(i) for i in store.frame_ids] == sorted(template.frames)
    assert sorted(r.revision_id for r in store.revisions) == sorted(template.poses)
    assert not store.loss
    for rid, poses in template.poses.items():
        assert store.poses(rid).tobytes() == poses.tobytes()


def _assert_true_to_the_originals(path: Path, template: Template, must_keep: set[int]) -> None:
    """A recovered store: opens, every frame it holds is the original, the frames of undamaged segments are all
    there, and every revision that lost nothing (nor an ancestor) has the original poses of the frames left."""
    with FrameStore.open(path) as store:
        ids = [int(i) for i in store.frame_ids]
        assert must_keep <= set(ids), (must_keep, ids)
        for fid in ids:
            assert_frames_identical(store.frame(fid), template.frames[fid])
        order = np.searchsorted(sorted(template.frames), ids)
        assert store.poses(0).tobytes() == template.poses[0][order].tobytes()
        for rev in store.revisions:
            chain, r = [], rev.revision_id
            while r is not None:
                chain.append(r)
                r = store.ledger.revision(r).parent_id
            if rev.revision_id in template.poses and not set(chain) & set(store.loss.revision_ids):
                assert store.poses(rev.revision_id).tobytes() == template.poses[rev.revision_id][order].tobytes()
        MapView.from_store(store, store.head)


def _recover_and_check(path: Path, template: Template, must_keep: set[int]) -> None:
    try:
        FrameStore.recover(path)
    except DriftmapError:
        return
    _assert_true_to_the_originals(path, template, must_keep)
    assert FrameStore.recover(path) == []  # idempotent: a second run has nothing to do


# --------------------------------------------------------------------------------------------- segment bytes


@SETTINGS
@given(data=st.data())
def test_a_segment_truncated_anywhere(template: Template, data: st.DataObject) -> None:
    with damaged_copy(template) as path:
        seg = data.draw(st.sampled_from(_segments(path)), label="segment")
        size = seg.stat().st_size
        cut = data.draw(st.integers(0, size - 1), label="cut at")
        os.truncate(seg, cut)
        store = _read_everything(path, template)
        assert store is None  # a closed segment cut short is never read as if nothing happened
        _read_everything(path, template, verify=False)  # no other exception, whatever it holds
        untouched = {f for f, name in template.segment_of.items() if name != seg.name}
        _recover_and_check(path, template, untouched)


@SETTINGS
@given(data=st.data())
def test_bits_flipped_anywhere_in_the_segments(template: Template, data: st.DataObject) -> None:
    with damaged_copy(template) as path:
        segs = _segments(path)
        flips = data.draw(st.lists(st.tuples(st.sampled_from(segs), st.floats(0, 1, exclude_max=True),
                                             st.integers(0, 7)), min_size=1, max_size=4), label="flips")
        touched = set()
        for seg, where, bit in flips:
            raw = bytearray(seg.read_bytes())
            offset = int(where * len(raw))
            raw[offset] ^= 1 << bit
            seg.write_bytes(bytes(raw))
            touched.add(seg.name)
        store = _read_everything(path, template)
        if store is not None:  # a flip that changed nothing anyone reads (the header's library string, ...)
            _assert_complete(store, template)
        _read_everything(path, template, verify=False)
        untouched = {f for f, name in template.segment_of.items() if name not in touched}
        _recover_and_check(path, template, untouched)


@SETTINGS
@given(data=st.data())
def test_a_huge_length_field_is_damage_not_an_allocation(template: Template, data: st.DataObject) -> None:
    """Overwrite 8 bytes with a huge little-endian length: a record header's length, a string length, a chunk's
    uncompressed size... Checked against the bytes present, never allocated."""
    with damaged_copy(template) as path:
        seg = data.draw(st.sampled_from(_segments(path)), label="segment")
        raw = bytearray(seg.read_bytes())
        offset = data.draw(st.integers(0, len(raw) - 8), label="offset")
        value = data.draw(st.sampled_from([2**63 - 1, 2**64 - 1, 2**40, 2**32 - 1, len(raw) + 1]), label="value")
        raw[offset:offset + 8] = value.to_bytes(8, "little")
        seg.write_bytes(bytes(raw))
        store = _read_everything(path, template)
        if store is not None:
            _assert_complete(store, template)
        _read_everything(path, template, verify=False)
        untouched = {f for f, name in template.segment_of.items() if name != seg.name}
        _recover_and_check(path, template, untouched)


# ------------------------------------------------------------------------------------------------- manifest

_json_values = st.recursive(st.none() | st.booleans() | st.integers(-2**70, 2**70) | st.floats(allow_nan=False)
                            | st.text(max_size=20),
                            lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=8), inner, max_size=3),
                            max_leaves=6)


def _paths(value: Any, prefix: tuple = ()) -> list[tuple]:
    """Every key path into a JSON value (the root excluded)."""
    out = []
    items = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list) else []
    for key, child in items:
        out.append((*prefix, key))
        out += _paths(child, (*prefix, key))
    return out


def _mutate(doc: Any, data: st.DataObject, label: str) -> Any:
    """``doc`` with one value replaced, one key or list item removed, or one list item duplicated."""
    doc = copy.deepcopy(doc)
    path = data.draw(st.sampled_from(_paths(doc)), label=f"{label} path")
    parent = doc
    for key in path[:-1]:
        parent = parent[key]
    key = path[-1]
    action = data.draw(st.sampled_from(["replace", "remove", "duplicate"]), label=f"{label} action")
    if action == "replace":
        parent[key] = data.draw(_json_values, label=f"{label} value")
    elif action == "remove":
        del parent[key]
    elif isinstance(parent, list):
        parent.insert(key, copy.deepcopy(parent[key]))
    else:
        parent[key] = [parent[key], parent[key]]
    return doc


@SETTINGS
@given(data=st.data())
def test_a_manifest_with_a_changed_value(template: Template, data: st.DataObject) -> None:
    with damaged_copy(template) as path:
        manifest = json.loads((path / "store.json").read_text())
        (path / "store.json").write_text(json.dumps(_mutate(manifest, data, "manifest")))
        store = _read_everything(path, template)
        if store is not None:  # the change was harmless (a creation time, a version string): nothing may be missing
            _assert_complete(store, template)
        _recover_and_check(path, template, set(template.frames))  # the segments are intact: every frame survives


@SETTINGS
@given(data=st.data())
def test_a_manifest_with_damaged_text(template: Template, data: st.DataObject) -> None:
    with damaged_copy(template) as path:
        raw = bytearray((path / "store.json").read_bytes())
        kind = data.draw(st.sampled_from(["truncate", "flip", "garbage"]), label="damage")
        if kind == "truncate":
            raw = raw[: data.draw(st.integers(0, len(raw) - 1), label="keep")]
        elif kind == "flip":
            offset = data.draw(st.integers(0, len(raw) - 1), label="offset")
            raw[offset] ^= 1 << data.draw(st.integers(0, 7), label="bit")
        else:
            raw = bytearray(data.draw(st.binary(max_size=64), label="garbage"))
        (path / "store.json").write_bytes(bytes(raw))
        store = _read_everything(path, template)
        if store is not None:
            _assert_complete(store, template)
        _recover_and_check(path, template, set(template.frames))


# ------------------------------------------------------------------- records with valid CRCs but nonsense inside


@SETTINGS
@given(data=st.data())
def test_a_revision_record_holding_nonsense(template: Template, data: st.DataObject) -> None:
    """A well-formed chunk (valid CRC) whose revision JSON is not a revision: opening is a typed error or reads
    it (when the change still makes a valid revision); the frames are never touched, and recovery keeps them all."""
    with damaged_copy(template) as path:
        with FrameStore.open(path, "a") as store:
            good = store.ledger.plan_rollback(0, note="fuzzed").to_json()
            bad = _mutate(good, data, "revision")
            writer = store._writable()
            try:
                writer.append_revision(bad, 10**18)
            except DriftmapError:  # not storable as MCAP / JSON: refused before writing, nothing to read back
                return
        store = _read_everything(path, template)
        if store is not None:
            assert [int(i) for i in store.frame_ids] == sorted(template.frames)
        _recover_and_check(path, template, set(template.frames))


@SETTINGS
@given(data=st.data())
def test_a_frame_record_holding_nonsense(template: Template, data: st.DataObject) -> None:
    """A well-formed chunk (valid CRC) whose frame metadata was changed before it was written: the other frames
    read back bit for bit; the changed one is read, or refused with a typed error; after ``recover`` every frame the
    store holds reads back without an error."""
    real = segment_module.frame_info

    def fuzzed(*args: Any, **kwargs: Any) -> dict[str, Any]:
        return _mutate(real(*args, **kwargs), data, "frame info")

    with damaged_copy(template) as path:
        with FrameStore.open(path, "a") as store:
            extra = _frame(7, attributes=data.draw(st.booleans(), label="attributes"))
            with mock.patch.object(segment_module, "frame_info", fuzzed):
                try:
                    store._writable().append_frame(extra)
                except DriftmapError:
                    return
        try:
            with FrameStore.open(path) as store:
                for fid in store.frame_ids:
                    try:
                        frame = store.frame(int(fid))
                    except DriftmapError:
                        continue
                    if int(fid) in template.frames:
                        assert_frames_identical(frame, template.frames[int(fid)])
                MapView.from_store(store, store.head)
        except DriftmapError:
            pass
        try:
            FrameStore.recover(path)
        except DriftmapError:
            return
        with FrameStore.open(path) as store:
            assert set(template.frames) <= {int(i) for i in store.frame_ids}
            for fid in store.frame_ids:
                frame = store.frame(int(fid))  # no error left after recovery
                if int(fid) in template.frames:
                    assert_frames_identical(frame, template.frames[int(fid)])
            MapView.from_store(store, store.head)
        assert FrameStore.recover(path) == []


def test_the_template_itself_is_healthy(template: Template) -> None:
    """The invariants above hold on the undamaged store (so a failure above is about the damage)."""
    with damaged_copy(template) as path:
        store = _read_everything(path, template)
        assert store is not None
        _assert_complete(store, template)
        assert FrameStore.recover(path) == []
