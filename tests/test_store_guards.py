"""No silent wrong answer at the store boundary (issue 22):

- every value of a frame is checked before anything is written; a refused frame leaves the store as it was, and
  it still closes and reopens with the frames before it bit for bit (case 2);
- an output path inside any store folder is refused, by the CLI and by the library writers themselves (case 4);
- reading a store needs no lock file and no write access (case 9);
- an OS error (a full disk) is a StoreIOError naming the file with the way to continue, and the frames before it
  survive (case 10);
- an export checks its input first and is written atomically: no partial file, ever (case 12).

The tests marked "real mount" run the store on a tmpfs in a private mount namespace (``unshare -m``, root): a disk
that really fills up and a file system that really is read-only. Where that is not possible they are skipped; the
monkeypatched tests next to them run everywhere.
"""

from __future__ import annotations

import builtins
import copy
import errno
import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from test_store import assert_frames_identical

from driftmap import Frame, PointAttributes, PoseEstimate, PoseSource
from driftmap.diagnostics.perturb import PosePerturbation, perturb_pose_file
from driftmap.errors import (
    DriftmapError,
    EmptyExportError,
    EmptyStoreError,
    ExportError,
    FrameRejectedError,
    OutputInsideStoreError,
    OutputWriteError,
    StoreError,
    StoreIOError,
)
from driftmap.export.foxglove import export_foxglove_mcap
from driftmap.map.view import MapView
from driftmap.store import refuse_inside_store
from driftmap.store import segment as segment_module
from driftmap.store.frame_store import FrameStore
from driftmap.trajectory import Trajectory, read_tum, write_tum

# ---------------------------------------------------------------------------------------------------- helpers


def make_frame(i: int, *, n: int = 300, stamp_ns: int | None = None, seed: int | None = None) -> Frame:
    """A small LiDAR-like frame with intensities and a covariance, deterministic in ``i`` (and ``seed``)."""
    rng = np.random.default_rng(1000 + i if seed is None else seed)
    T = np.eye(4)
    T[:3, 3] = (0.5 * i, 0.1 * i, 0.0)
    return Frame(frame_id=i, stamp_ns=100_000_000 * (i + 1) if stamp_ns is None else stamp_ns, sensor_name="lidar",
                 sensor_kind="lidar", points_sensor=rng.normal(size=(n, 3)).astype(np.float32),
                 attributes=PointAttributes(intensity=rng.random(n).astype(np.float32)),
                 pose=PoseEstimate(T, source=PoseSource.ODOMETRY, covariance_6x6=np.diag(rng.random(6) + 0.1)),
                 sensor_frame="velodyne")


def hacked(frame: Frame, name: str, value: object, *, in_pose: bool = False) -> Frame:
    """A copy of ``frame`` with one field set past ``Frame``'s own validation (what a buggy source or a frame
    changed in place after construction would hand the store)."""
    out = copy.copy(frame)
    if in_pose:
        pose = copy.copy(frame.pose)
        object.__setattr__(pose, name, value)
        object.__setattr__(out, "pose", pose)
    else:
        object.__setattr__(out, name, value)
    return out


def manifest(path: Path) -> dict:
    return json.loads((path / "store.json").read_text())


def files_of(path: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(path.iterdir()) if p.is_file() and p.name != "writer.lock"}


def assert_store_holds(path: Path, frames: list[Frame]) -> None:
    """The store opens without recovery, every segment is closed, and it holds exactly ``frames``, bit for bit."""
    with FrameStore.open(path) as store:
        assert [int(i) for i in store.frame_ids] == sorted(f.frame_id for f in frames)
        for f in frames:
            assert_frames_identical(store.frame(f.frame_id), f)
        assert store.recovery_events == []
    assert all(s["state"] == "closed" for s in manifest(path)["segments"])


def cli(*args: object, cwd: Path | None = None) -> subprocess.CompletedProcess:
    env = {**os.environ, "COLUMNS": "250"}
    return subprocess.run([sys.executable, "-m", "driftmap.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=300, env=env, cwd=cwd, check=False)


def one_line_error(out: subprocess.CompletedProcess) -> str:
    assert out.returncode == 1, (out.returncode, out.stdout, out.stderr)
    assert "Traceback" not in out.stderr, out.stderr
    lines = [line for line in out.stderr.strip().splitlines() if line.strip()]
    assert lines and lines[-1].startswith("error:"), out.stderr
    return " ".join(out.stderr.split())  # rich may wrap a long message


@pytest.fixture()
def store3(tmp_path: Path) -> tuple[Path, list[Frame]]:
    """A closed store of three frames."""
    frames = [make_frame(i) for i in range(3)]
    with FrameStore.create(tmp_path / "store") as store:
        for f in frames:
            store.append(f)
    return tmp_path / "store", frames


# ---------------------------------------------------------------------------------------- case 2: bad values


def _bad_frames() -> list[tuple[str, Frame, str]]:
    good = make_frame(3)
    nan_pose = good.pose.T_world_sensor.copy()
    nan_pose[0, 3] = np.nan
    scaled = good.pose.T_world_sensor.copy()
    scaled[:3, :3] *= 1.5
    inf_points = good.points_sensor.copy()
    inf_points[7, 1] = np.inf
    inf_base = np.eye(4)
    inf_base[2, 3] = -np.inf
    return [
        ("negative stamp", make_frame(3, stamp_ns=-5), "stamp_ns"),
        ("stamp past int64", hacked(good, "stamp_ns", 2**63), "stamp_ns"),
        ("float stamp", hacked(good, "stamp_ns", 1.5e9), "stamp_ns"),
        ("NaN in the pose", hacked(good, "T_world_sensor", nan_pose, in_pose=True), "pose.T_world_sensor"),
        ("non-rigid pose", hacked(good, "T_world_sensor", scaled, in_pose=True), "pose"),
        ("infinite point", good.with_points(inf_points, good.attributes), "points_sensor"),
        ("infinite T_base_sensor", hacked(good, "T_base_sensor", inf_base), "T_base_sensor"),
    ]


@pytest.mark.parametrize("case", range(len(_bad_frames())), ids=[c[0] for c in _bad_frames()])
def test_a_refused_frame_writes_nothing_and_the_store_goes_on(tmp_path: Path, case: int) -> None:
    what, bad, field = _bad_frames()[case]
    frames = [make_frame(i) for i in range(3)]
    path = tmp_path / "store"
    with FrameStore.create(path) as store:
        for f in frames:
            store.append(f)
        before = files_of(path)
        with pytest.raises(FrameRejectedError) as err:
            store.append(bad)
        assert err.value.frame_id == 3 and err.value.field == field, what
        assert "frame 3" in str(err.value) and field.split(".")[0] in str(err.value)
        assert files_of(path) == before  # not a byte written
        later = make_frame(4)
        store.append(later)  # the session goes on
    assert_store_holds(path, [*frames, later])


def test_a_negative_stamp_names_the_value_and_a_refused_first_frame_leaves_no_segment(tmp_path: Path) -> None:
    path = tmp_path / "store"
    with FrameStore.create(path) as store, \
            pytest.raises(FrameRejectedError, match=r"frame 0: stamp_ns = -500000000 ns is negative.*unsigned"):
        store.append(make_frame(0, stamp_ns=-500_000_000))
    assert not list(path.glob("segment-*")) and manifest(path)["segments"] == []
    with FrameStore.open(path, "a") as store:  # reopens, and takes frames
        store.append(make_frame(0))
    assert_store_holds(path, [make_frame(0)])


def test_nan_points_are_stored_as_given(tmp_path: Path) -> None:
    """The documented policy: NaN marks a point without a measurement; it is stored bit for bit (the map leaves it
    out), only infinite coordinates are refused."""
    f = make_frame(0)
    pts = f.points_sensor.copy()
    pts[[3, 10], :] = np.nan
    pts[11, 2] = np.float32(-np.nan)
    f = f.with_points(pts, f.attributes)
    with FrameStore.create(tmp_path / "s") as store:
        store.append(f)
    assert_store_holds(tmp_path / "s", [f])
    with FrameStore.open(tmp_path / "s") as store:
        world = MapView.from_store(store, 0).points_world
        assert len(world) == len(pts) and np.isnan(world).any(axis=1).sum() == 3


def test_a_kitti_folder_whose_times_start_before_zero_leaves_no_broken_store(kitti_dir: Path, tmp_path: Path) -> None:
    """times.txt starting at -0.5 s: the build stops with a typed error naming the frame's stamp (the store refuses
    negative stamps before writing; a source may refuse them earlier), and leaves no store with an unclosed
    segment behind."""
    from driftmap.pipeline.build import build

    folder = tmp_path / "kitti"
    folder.mkdir()
    (folder / "velodyne").symlink_to(kitti_dir / "velodyne")
    for name in ("calib.txt", "poses.txt"):
        shutil.copy(kitti_dir / name, folder / name)
    times = np.loadtxt(kitti_dir / "times.txt") - 0.5
    (folder / "times.txt").write_text("".join(f"{t:.6e}\n" for t in times))
    out = tmp_path / "out"
    with pytest.raises(DriftmapError) as err:
        build(folder, out, poses_from_source=True, frames="0:3", loop_closure=False)
    message = str(err.value)
    assert "stamp" in message or "times" in message, message
    assert "-500000000" in message or "-0.5" in message or "negative" in message, message
    if out.exists() and (out / "store.json").exists():  # kept: then it opens, and nothing is left open
        assert all(s["state"] == "closed" for s in manifest(out)["segments"])
        with FrameStore.open(out) as store:
            assert store.recovery_events == []


# --------------------------------------------------------------------------------- case 4: outputs in a store


def test_outputs_inside_any_store_folder_are_refused(store3: tuple[Path, list[Frame]], tmp_path: Path) -> None:
    path, _ = store3
    other = tmp_path / "other"  # another store: not the one being exported, refused all the same
    FrameStore.create(other).close()
    (tmp_path / "link").symlink_to(path)
    (tmp_path / "seg-link.mcap").symlink_to(path / "segment-000000.mcap")
    inside = [
        path / "segment-000000.mcap",
        path / "store.json",
        path / "new.mcap",
        path / "sub" / "deeper" / "map.ply",
        tmp_path / "elsewhere" / ".." / "store" / "segment-000000.mcap",
        path / "sub" / ".." / "store.json",
        tmp_path / "link" / "out.mcap",
        tmp_path / "seg-link.mcap",
        other / "out.mcap",
        path,
    ]
    for target in inside:
        with pytest.raises(OutputInsideStoreError) as err:
            refuse_inside_store(target, "--mcap")
        assert err.value.flag == "--mcap" and err.value.path == target
        assert str(err.value).startswith(f"--mcap {target}") and "write it outside the store folder" in str(err.value)
        assert Path(err.value.store) in (path.resolve(), other.resolve())
    # outside: fine, and so is a folder that merely holds some other store.json, or a store's sibling
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "store.json").write_text('{"name": "shopping"}')
    (tmp_path / "store2").mkdir()
    for target in (tmp_path / "out.mcap", tmp_path / "notes" / "x.ply", tmp_path / "store2" / "x.tum", None):
        refuse_inside_store(target, "--mcap")
    # build --out: a store may be continued, but not made inside another one
    refuse_inside_store(path, "--out", output_is_store=True)
    with pytest.raises(OutputInsideStoreError, match="--out"):
        refuse_inside_store(path / "nested", "--out", output_is_store=True)


def test_a_store_with_a_damaged_or_missing_manifest_is_still_protected(store3: tuple[Path, list[Frame]]) -> None:
    path, _ = store3
    (path / "store.json").write_text("{ damaged")
    with pytest.raises(OutputInsideStoreError):
        refuse_inside_store(path / "out.tum", "--trajectory")
    (path / "store.json").unlink()
    with pytest.raises(OutputInsideStoreError):
        refuse_inside_store(path / "out.tum", "--trajectory")


def test_library_writers_refuse_to_write_into_a_store(store3: tuple[Path, list[Frame]]) -> None:
    """The store protects itself even when the caller forgot to check: every export writer refuses a path inside a
    store folder, overwrite or not, and the store keeps every frame."""
    path, frames = store3
    before = files_of(path)
    with FrameStore.open(path) as store:
        with pytest.raises(OutputInsideStoreError):
            export_foxglove_mcap(store, path / "segment-000000.mcap", overwrite=True)
        with pytest.raises(OutputInsideStoreError):
            store.export_trajectory(path / "store.json")
        with pytest.raises(OutputInsideStoreError):
            MapView.from_store(store, 0).write(path / "segment-000000.ply")
        traj = Trajectory(store.ledger.stamps_ns.copy(), store.poses(0), store.frame_ids.copy())
    write_tum(tmp := path.parent / "t.tum", traj)  # the pose-file writers sit below the store: their callers check
    with pytest.raises(OutputInsideStoreError):
        perturb_pose_file(tmp, path / "t.tum", PosePerturbation(drift_percent_per_m=1.0))
    with pytest.raises(OutputInsideStoreError):
        perturb_pose_file(tmp, path / "t.txt", PosePerturbation(drift_percent_per_m=1.0))
    assert files_of(path) == before
    assert FrameStore.recover(path) == []
    assert_store_holds(path, frames)


def test_cli_export_into_the_store_keeps_every_frame(store3: tuple[Path, list[Frame]]) -> None:
    """The reported damage: `export STORE --mcap STORE/segment-000000.mcap --overwrite` replaced the only segment
    (recover then kept 0 of the frames), `--trajectory STORE/store.json --overwrite` the manifest. Now both exit 1
    with one line naming the flag, and the store is untouched. (The library writers already refuse these paths;
    naming the flag needs the CLI's output check to call ``driftmap.store.refuse_inside_store(path, flag)``.)"""
    path, frames = store3
    before = files_of(path)
    for flag, target in (("--mcap", path / "segment-000000.mcap"), ("--trajectory", path / "store.json"),
                         ("--map", path / "map.ply")):
        message = one_line_error(cli("export", path, flag, target, "--overwrite"))
        assert flag in message and str(target) in message and "inside the frame store" in message, message
    assert files_of(path) == before
    assert FrameStore.recover(path) == []
    assert_store_holds(path, frames)


def test_cli_diagnose_and_view_outputs_inside_a_store_are_refused(store3: tuple[Path, list[Frame]]) -> None:
    """diagnose --json / --report and view --out (the PNG folder) name the flag too (before any work). Needs the CLI
    wiring: ``check_output`` calling ``refuse_inside_store``, and ``view`` checking ``--out`` with it."""
    path, _ = store3
    before = files_of(path)
    for args, flag in ((("diagnose", path, "--json", path / "d.json"), "--json"),
                       (("view", path, "--out", path / "views", "--backend", "software"), "--out")):
        message = one_line_error(cli(*args))
        assert flag in message and "inside the frame store" in message, message
    assert files_of(path) == before and not (path / "views").exists()


# ------------------------------------------------------------------------------------------ case 9: read-only


@pytest.fixture()
def read_only_store(monkeypatch: pytest.MonkeyPatch, store3: tuple[Path, list[Frame]]):
    """``store3`` on a simulated read-only file system: every attempt to open a file inside it for writing (or to
    create, replace, rename, link, truncate or delete anything in it) fails with EROFS, as on a read-only mount.
    (Tests run as root, so chmod alone would not stop a write.) Proves that no reading code path writes."""
    path, frames = store3
    root = str(path.resolve())
    attempts: list[str] = []

    def inside(target: object) -> bool:
        try:
            return os.path.realpath(os.fspath(target)).startswith(root)  # type: ignore[arg-type]
        except TypeError:  # a file descriptor
            return False

    def refuse(what: str, target: object) -> None:
        attempts.append(f"{what} {target}")
        raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(target))

    real_open, real_os_open = builtins.open, os.open

    def fake_open(file, mode="r", *args, **kwargs):
        if inside(file) and any(c in mode for c in "wax+"):
            refuse(f"open({mode!r})", file)
        return real_open(file, mode, *args, **kwargs)

    def fake_os_open(file, flags, *args, **kwargs):
        writes = os.O_WRONLY | os.O_RDWR | os.O_CREAT | os.O_TRUNC | os.O_APPEND
        if inside(file) and flags & writes:
            refuse("os.open(write)", file)
        return real_os_open(file, flags, *args, **kwargs)

    def guard(name: str, n_paths: int = 1):
        real = getattr(os, name)

        def fake(*args, **kwargs):
            for target in args[:n_paths]:
                if inside(target):
                    refuse(f"os.{name}", target)
            return real(*args, **kwargs)
        return fake

    monkeypatch.setattr(builtins, "open", fake_open)
    monkeypatch.setattr(os, "open", fake_os_open)
    for name, n in (("replace", 2), ("rename", 2), ("link", 2), ("unlink", 1), ("truncate", 1), ("mkdir", 1),
                    ("rmdir", 1), ("symlink", 2)):
        monkeypatch.setattr(os, name, guard(name, n))
    return path, frames, attempts


def test_reading_needs_no_write_access(read_only_store, tmp_path: Path) -> None:
    path, frames, attempts = read_only_store
    assert (path / "writer.lock").exists()  # every written store has one: reading must not need to open it for writing
    with FrameStore.open(path) as store:
        for f in frames:
            assert_frames_identical(store.frame(f.frame_id), f)
        view = MapView.from_store(store, 0)
        assert len(view.points_world) == sum(f.n_points for f in frames)
        store.export_trajectory(tmp_path / "out.tum")  # outputs outside the store are fine
        view.write(tmp_path / "map.ply")
        export_foxglove_mcap(store, tmp_path / "out.mcap")
    assert attempts == []
    assert len(read_tum(tmp_path / "out.tum")) == 3


def test_appending_to_a_read_only_store_names_the_lock_and_says_reading_works(read_only_store) -> None:
    path, _, attempts = read_only_store
    with pytest.raises(StoreIOError) as err:
        FrameStore.open(path, "a")
    message = str(err.value)
    assert str(path / "writer.lock") in message and "read-only file system" in message and "reading does not" in message
    assert err.value.errno == errno.EROFS and isinstance(err.value, OSError)
    with pytest.raises(StoreIOError, match="writer.lock"):
        FrameStore.recover(path)
    assert attempts  # the refusals came from the simulated file system


def test_a_lock_file_that_cannot_be_opened_does_not_stop_a_reader(store3: tuple[Path, list[Frame]]) -> None:
    path, frames = store3
    (path / "writer.lock").unlink()
    (path / "writer.lock").mkdir()  # cannot be opened as a file at all
    assert_store_holds(path, frames)


# --------------------------------------------------------------------------------------- case 10: disk full


class FullDisk:
    """A segment file that accepts ``budget`` more bytes and then fails with ENOSPC, after writing the part of the
    failing write that fits (a short write, as a real full disk does)."""

    def __init__(self, path: Path, budget: int):
        self.fh = open(path, "xb")  # noqa: SIM115
        self.budget = budget

    def write(self, data: bytes) -> int:
        data = bytes(data)
        if len(data) > self.budget:
            self.fh.write(data[: self.budget])
            self.fh.flush()
            self.budget = 0
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        self.budget -= len(data)
        return self.fh.write(data)

    def __getattr__(self, name: str):
        return getattr(self.fh, name)


def fill_disk_after(monkeypatch: pytest.MonkeyPatch, budgets: list[int]) -> None:
    """Segment files opened from now on get the next budget of ``budgets`` (then unlimited)."""
    real = segment_module.open_new_segment_file

    def opener(path: Path):
        if not budgets:
            return real(path)
        return FullDisk(path, budgets.pop(0))

    monkeypatch.setattr(segment_module, "open_new_segment_file", opener)


def _segment_bytes_for(frames: list[Frame], tmp_path: Path) -> int:
    """The size of a segment holding ``frames`` before its summary (where the next append starts)."""
    with FrameStore.create(tmp_path / "probe") as store:
        for f in frames:
            store.append(f)
        size = store._writer.good_size
    shutil.rmtree(tmp_path / "probe")
    return size


@pytest.mark.parametrize("finish_with", ["reopen for appending", "recover"])
def test_disk_full_mid_append_names_the_file_and_keeps_the_frames_before(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, finish_with: str) -> None:
    frames = [make_frame(i, n=2000) for i in range(5)]
    budget = _segment_bytes_for(frames[:3], tmp_path) + 5000  # frame 3 breaks off after 5000 of its ~36000 bytes
    fill_disk_after(monkeypatch, [budget])
    path = tmp_path / "store"
    seg = path / "segment-000000.mcap"
    with FrameStore.create(path) as store:
        for f in frames[:3]:
            store.append(f)
        with pytest.raises(StoreIOError) as err:
            store.append(frames[3])
        message = str(err.value)
        assert message.startswith(f"{seg}: appending frame 3 failed: no space left on the device [ENOSPC]"), message
        assert "--resume" in message and f"driftmap recover {path}" in message
        assert err.value.errno == errno.ENOSPC and Path(err.value.path) == seg and isinstance(err.value, OSError)
        with pytest.raises(StoreError, match="earlier write"):  # this session takes no more appends
            store.append(frames[4])
    # closed without an error; the unfinished record was cut off: the segment ends with frame 2's chunk
    assert manifest(path)["segments"] == [{"name": seg.name, "state": "open", "bytes": None}]
    assert seg.stat().st_size == budget - 5000  # exactly the three complete frames
    with FrameStore.open(path) as store:  # a reader sees the three frames, bit for bit
        assert [int(i) for i in store.frame_ids] == [0, 1, 2]
        for f in frames[:3]:
            assert_frames_identical(store.frame(f.frame_id), f)
    monkeypatch.undo()  # space is free again
    if finish_with == "recover":
        events = FrameStore.recover(path)
        assert [e.frames_kept for e in events] == [3]
    with FrameStore.open(path, "a") as store:  # the build goes on (--resume)
        for f in frames[3:]:
            store.append(f)
    assert_store_holds(path, frames)


def test_disk_full_when_closing_the_segment(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    frames = [make_frame(i) for i in range(3)]
    budget = _segment_bytes_for(frames, tmp_path) + 10  # every frame fits, the summary does not
    fill_disk_after(monkeypatch, [budget])
    path = tmp_path / "store"
    store = FrameStore.create(path)
    for f in frames:
        store.append(f)
    with pytest.raises(StoreIOError, match=r"segment-000000.mcap: finishing the segment.*no space left.*--resume"):
        store.close()
    monkeypatch.undo()
    with FrameStore.open(path, "a") as again:  # the lock was released; the open segment is rewritten closed
        assert [e.action for e in again.recovery_events] == ["rewritten as a closed segment"]
    assert_store_holds(path, frames)


def test_disk_full_when_starting_a_segment_or_writing_the_manifest(store3: tuple[Path, list[Frame]],
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    from driftmap.store import manifest as frame_store  # the manifest is written there

    path, frames = store3

    def full(path_: Path, data: dict) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(frame_store, "atomic_write_json", full)
    with FrameStore.open(path, "a") as store, \
            pytest.raises(StoreIOError, match=r"store.json: starting segment segment-000001.mcap \(appending frame 3\) "
                                              r"failed: no space left"):
        store.append(make_frame(3))
    monkeypatch.undo()
    assert not (path / "segment-000001.mcap").exists()
    fill_disk_after(monkeypatch, [0])  # the new segment file cannot take a byte
    with FrameStore.open(path, "a") as store, \
            pytest.raises(StoreIOError, match=r"segment-000001.mcap: starting the segment"):
        store.append(make_frame(3))
    monkeypatch.undo()
    with FrameStore.open(path, "a") as store:  # the empty, open segment is rewritten; appending goes on
        store.append(make_frame(3))
    assert_store_holds(path, [*frames, make_frame(3)])


def test_disk_full_when_storing_a_revision(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The ledger write: the revision is neither on disk nor in memory, the frames are intact."""
    frames = [make_frame(i) for i in range(3)]
    fill_disk_after(monkeypatch, [_segment_bytes_for(frames, tmp_path) + 100])
    path = tmp_path / "store"
    with FrameStore.create(path) as store:
        for f in frames:
            store.append(f)
        with pytest.raises(StoreIOError, match=r"segment-000000.mcap: storing pose revision 1 failed: no space left.*"
                                               r"driftmap recover .* and make the correction again"):
            store.add_revision({0: np.eye(4)}, source="loop_closure")
        assert store.head == 0
    monkeypatch.undo()
    with FrameStore.open(path) as store:
        assert store.head == 0
    assert [e.frames_kept for e in FrameStore.recover(path)] == [3]
    assert_store_holds(path, frames)
    with FrameStore.open(path, "a") as store:  # the correction can be made again
        assert store.add_revision({0: np.eye(4)}, source="loop_closure").revision_id == 1


def test_io_errors_when_opening_name_the_file_and_are_not_called_damage(store3: tuple[Path, list[Frame]],
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    path, _ = store3
    real_read_bytes = Path.read_bytes

    def eio(self: Path) -> bytes:
        if self.name == "store.json":
            raise OSError(errno.EIO, os.strerror(errno.EIO), str(self))
        return real_read_bytes(self)

    monkeypatch.setattr(Path, "read_bytes", eio)
    with pytest.raises(StoreIOError, match=r"store.json: reading the manifest failed: Input/output error \[EIO\]") as err:
        FrameStore.open(path)
    assert "recover" not in str(err.value)  # an unreadable device is not a damaged manifest
    monkeypatch.undo()

    real_scan = segment_module.scan_segment

    def eio_scan(file: Path, **kwargs: object):
        raise OSError(errno.EIO, os.strerror(errno.EIO))

    from driftmap.store import opening as frame_store  # opening scans the segments there

    monkeypatch.setattr(frame_store, "scan_segment", eio_scan)
    with pytest.raises(StoreIOError, match=r"segment-000000.mcap: reading the segment failed: Input/output error"):
        FrameStore.open(path)
    monkeypatch.setattr(frame_store, "scan_segment", real_scan)


def test_disk_full_during_recovery_is_resumed_by_the_next_recovery(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    frames = [make_frame(i) for i in range(4)]
    path = tmp_path / "store"
    with FrameStore.create(path) as store:
        for f in frames:
            store.append(f)
        cut = store._refs[3].payload_offset + 50
    os.truncate(path / "segment-000000.mcap", cut)  # frame 3 damaged
    fill_disk_after(monkeypatch, [3000])
    with pytest.raises(StoreIOError) as err:
        FrameStore.recover(path)
    assert "segment-000000.mcap.recovering" in str(err.value) and "no space left" in str(err.value)
    assert f"run `driftmap recover {path}` again" in str(err.value)
    monkeypatch.undo()
    events = FrameStore.recover(path)
    # frame 3, cut short, is declared lost (the manifest recorded that the segment held it)
    assert events[0].frames_kept == 3 and events[-1].loss is not None and events[-1].loss.frame_ids == (3,), events
    assert_store_holds(path, frames[:3])


def test_recover_drops_a_frame_whose_points_disagree_with_their_recorded_crc(store3: tuple[Path, list[Frame]],
                                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """A chunk with a valid CRC whose frame metadata records another payload CRC32 (a writer bug, or metadata
    that describes other points): recovery does not give such a frame a fresh CRC and keep it; it drops it and
    says so, and keeps every other frame bit for bit."""
    path, frames = store3
    real = segment_module.frame_info

    def wrong_crc(*args: object, **kwargs: object) -> dict:
        info = real(*args, **kwargs)
        info["points"]["crc32"] ^= 1
        return info

    with FrameStore.open(path, "a") as store:
        monkeypatch.setattr(segment_module, "frame_info", wrong_crc)
        store.append(make_frame(3))
        monkeypatch.undo()
    events = FrameStore.recover(path)
    assert len(events) == 2 and "frame 3: the point payload's CRC32 is not the one its metadata recorded" in events[0].detail
    assert events[0].frames_kept == 0
    assert events[1].loss is not None and events[1].loss.frame_ids == (3,)  # declared lost, not silently dropped
    assert_store_holds(path, frames)


# ------------------------------------------------------------------------------- case 12: empty and atomic exports


def test_exports_of_an_empty_store_are_typed_errors_and_write_nothing(tmp_path: Path) -> None:
    path = tmp_path / "empty"
    FrameStore.create(path).close()
    out = tmp_path / "out"
    with FrameStore.open(path) as store:
        with pytest.raises(EmptyStoreError, match=rf"store {path} has no frames in revision 0"):
            store.export_trajectory(out / "t.tum")
        with pytest.raises(EmptyStoreError, match=rf"store {path} has no frames in revision 0"):
            MapView.from_store(store, 0).write(out / "m.ply")
        with pytest.raises(EmptyStoreError, match=rf"store {path} has no frames in revision 0") as err:
            export_foxglove_mcap(store, out / "x.mcap")
        assert isinstance(err.value, ExportError)  # as before
    assert not out.exists() or list(out.iterdir()) == []


def test_a_map_without_a_finite_point_is_not_exported(tmp_path: Path) -> None:
    f = make_frame(0)
    f = f.with_points(np.full_like(f.points_sensor, np.nan), f.attributes)
    with FrameStore.create(tmp_path / "s") as store:
        store.append(f)
        with pytest.raises(EmptyExportError, match="no point to write"):
            MapView.from_store(store, 0).write(tmp_path / "m.ply")
    assert not (tmp_path / "m.ply").exists()
    with pytest.raises(EmptyExportError):
        write_tum(tmp_path / "t.tum", Trajectory(np.zeros(0, np.int64), np.zeros((0, 4, 4))))
    assert list(tmp_path.glob("*.tum")) == [] and list(tmp_path.glob(".*")) == []


def _leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith(".") or "tmp" in p.name)


def test_failed_exports_leave_no_partial_file_and_keep_the_old_one(store3: tuple[Path, list[Frame]], tmp_path: Path,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    import open3d as o3d

    from driftmap.export import foxglove as foxglove_export

    path, _ = store3
    out = tmp_path / "out"
    out.mkdir()
    old = {name: f"old {name}\n".encode() for name in ("map.ply", "traj.tum", "traj.txt", "x.mcap")}
    for name, data in old.items():
        (out / name).write_bytes(data)

    def broken_ply(file: str, pcd, **kwargs) -> bool:
        Path(file).write_bytes(b"ply\nformat binary_little_endian 1.0\nhalf")  # a partial file, then failure
        return False

    real_write_text = Path.write_text

    def disk_full(self: Path, data: str, *args, **kwargs) -> int:
        real_write_text(self, data[: len(data) // 2])
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    def broken_frames(*args, **kwargs):
        raise RuntimeError("simulated failure in the middle of the frames")

    with FrameStore.open(path) as store:
        monkeypatch.setattr(o3d.io, "write_point_cloud", broken_ply)
        with pytest.raises(DriftmapError, match="Open3D could not write"):
            MapView.from_store(store, 0).write(out / "map.ply", voxel_size_m=0.05, provenance=True)
        monkeypatch.setattr(Path, "write_text", disk_full)
        for name, fmt in (("traj.tum", "tum"), ("traj.txt", "kitti")):
            with pytest.raises(OutputWriteError) as err:
                store.export_trajectory(out / name, format=fmt)
            assert str(err.value).startswith(f"{out / name}: could not be written") and "no space left" in str(err.value)
            assert err.value.errno == errno.ENOSPC
        monkeypatch.setattr(foxglove_export, "frame_cloud_points", broken_frames)
        with pytest.raises(RuntimeError, match="simulated"):
            export_foxglove_mcap(store, out / "x.mcap", overwrite=True)
        monkeypatch.undo()
        assert {p.name: p.read_bytes() for p in out.iterdir()} == old  # every old file intact, nothing else
        assert _leftovers(out) == []
        # and when nothing fails, the same calls replace them
        MapView.from_store(store, 0).write(out / "map.ply", voxel_size_m=0.05, provenance=True)
        store.export_trajectory(out / "traj.tum")
        export_foxglove_mcap(store, out / "x.mcap", overwrite=True)
        assert read_tum(out / "traj.tum").poses.tobytes() == store.poses(0).tobytes()
    assert sorted(p.name for p in out.iterdir()) == ["map.ply", "map.ply.provenance.npz", "traj.tum", "traj.txt", "x.mcap"]
    assert (out / "map.ply").read_bytes()[:3] == b"ply"


def test_cli_export_of_an_empty_store_is_one_line_and_leaves_no_file(tmp_path: Path) -> None:
    path = tmp_path / "empty"
    FrameStore.create(path).close()
    for flag, name in (("--trajectory", "t.tum"), ("--map", "m.ply"), ("--mcap", "x.mcap")):
        out = cli("export", path, flag, tmp_path / name)
        message = one_line_error(out)
        assert "has no frames in revision 0" in message, message
        assert "Write PLY failed" not in out.stderr + out.stdout and "[Open3D" not in out.stderr + out.stdout
        assert not (tmp_path / name).exists()
    assert _leftovers(tmp_path) == []


# ------------------------------------------------------------------------ real mounts (tmpfs in a private namespace)


def _private_mounts() -> bool:
    if sys.platform != "linux" or shutil.which("unshare") is None or shutil.which("mount") is None:
        return False
    probe = "d=$(mktemp -d) && mount -t tmpfs -o size=1m tmpfs \"$d\" && umount \"$d\" && rmdir \"$d\""
    try:
        return subprocess.run(["unshare", "-m", "sh", "-c", probe], capture_output=True, timeout=30,
                              check=False).returncode == 0
    except (OSError, subprocess.SubprocessError):
        return False


@pytest.fixture(scope="session")
def private_mounts() -> None:
    if not _private_mounts():
        pytest.skip("needs root and unshare -m (private tmpfs mounts)")

_REAL_MOUNT_PRELUDE = textwrap.dedent(
    """
    import errno, json, os, subprocess, sys
    from pathlib import Path
    sys.path.insert(0, sys.argv[2])
    from test_store_guards import make_frame
    from test_store import assert_frames_identical
    from driftmap.errors import StoreIOError
    from driftmap.store.frame_store import FrameStore
    mnt = Path(sys.argv[1])
    result = {}
    """
)


def _run_in_private_tmpfs(tmp_path: Path, size: str, body: str) -> dict:
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    script = tmp_path / "script.py"
    script.write_text(_REAL_MOUNT_PRELUDE + textwrap.dedent(body) + "\nprint(json.dumps(result))\n")
    shell = f'mount -t tmpfs -o size={size} tmpfs "$1" && exec "$2" "$3" "$1" "$4"'
    proc = subprocess.run(["unshare", "-m", "sh", "-c", shell, "sh", str(mnt), sys.executable, str(script),
                           str(Path(__file__).parent)], capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_real_read_only_mount_can_be_read_by_the_library_and_the_cli(tmp_path: Path, private_mounts: None) -> None:
    result = _run_in_private_tmpfs(tmp_path, "16m", f"""
        frames = [make_frame(i) for i in range(3)]
        store = mnt / "store"
        with FrameStore.create(store) as s:
            for f in frames:
                s.append(f)
        subprocess.run(["mount", "-o", "remount,ro", str(mnt)], check=True)
        try:
            (store / "probe").write_text("x")
            result["writable"] = True
        except OSError as exc:
            result["writable"] = exc.errno
        with FrameStore.open(store) as s:
            for f in frames:
                assert_frames_identical(s.frame(f.frame_id), f)
            result["frames"] = len(s)
        try:
            FrameStore.open(store, "a")
        except StoreIOError as exc:
            result["append_error"] = str(exc)
        cli = [sys.executable, "-m", "driftmap.cli"]
        info = subprocess.run(cli + ["info", str(store)], capture_output=True, text=True)
        export = subprocess.run(cli + ["export", str(store), "--trajectory", "{tmp_path / 'out.tum'}"],
                                capture_output=True, text=True)
        result["info"] = [info.returncode, info.stderr]
        result["export"] = [export.returncode, export.stderr]
    """)
    assert result["writable"] == errno.EROFS  # the mount really was read-only
    assert result["frames"] == 3
    assert "writer.lock" in result["append_error"] and "read-only file system" in result["append_error"]
    assert result["info"][0] == 0, result["info"][1]
    assert result["export"][0] == 0, result["export"][1]
    assert len(read_tum(tmp_path / "out.tum")) == 3


def test_real_full_disk_names_the_segment_and_the_store_recovers_once_space_is_free(tmp_path: Path,
                                                                                   private_mounts: None) -> None:
    result = _run_in_private_tmpfs(tmp_path, "2m", """
        filler = mnt / "filler"
        filler.write_bytes(b"x" * 1_200_000)
        store = mnt / "store"
        frames = [make_frame(i, n=8000) for i in range(40)]  # ~130 kB each: the disk fills after a few
        stored = 0
        s = FrameStore.create(store)
        try:
            for f in frames:
                s.append(f)
                stored += 1
        except StoreIOError as exc:
            result["error"], result["errno"] = str(exc), exc.errno
        finally:
            s.close()
        result["stored"] = stored
        with FrameStore.open(store) as r:
            result["readable"] = [int(i) for i in r.frame_ids]
            for f in frames[:stored]:
                assert_frames_identical(r.frame(f.frame_id), f)
        filler.unlink()  # space is free again
        with FrameStore.open(store, "a") as w:
            result["events"] = [e.action for e in w.recovery_events]
        with FrameStore.open(store) as r:
            for f in frames[:stored]:
                assert_frames_identical(r.frame(f.frame_id), f)
            result["after"] = len(r)
    """)
    assert 0 < result["stored"] < 40 and result["errno"] == errno.ENOSPC
    assert "segment-000000.mcap: appending frame" in result["error"] and "no space left" in result["error"]
    assert "--resume" in result["error"] and "driftmap recover" in result["error"]
    assert result["readable"] == list(range(result["stored"])) and result["after"] == result["stored"]
    assert result["events"] == ["rewritten as a closed segment"]
