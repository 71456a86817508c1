"""Fuzzed readers (issue 22): every reader, fed small valid files mutated by hypothesis -- truncation, bytes
appended, bit flips, header fields that lie about counts and sizes, NaN / inf in the data, absurd sizes -- ends in
one of three ways only:

- frames whose arrays are what the bytes hold (checked against an independent reading of the bytes here:
  a reference PCD / PLY / LZF parser, the raw float32 of a KITTI scan, an independent PNG decode);
- a typed driftmap error (:class:`driftmap.errors.DriftmapError`);
- in lenient mode, frames skipped with a recorded reason.

Never another exception, never a crash, and never an allocation far beyond the input: every example runs with the
process's address space capped at its current size plus :data:`HEADROOM_BYTES` (a reader that trusts a header
claiming 100 million points fails with a MemoryError, which fails the test), and the points read never exceed the
bytes of the input divided by the smallest size a point can have.

Examples are bounded (``max_examples`` per reader) so that the file runs in well under a minute.
"""

from __future__ import annotations

import contextlib
import os
import re
import resource
import struct
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from cloud_files import ROS_CLOUD_TOPIC, ros_log_messages, write_pcd, write_ply, write_ros_messages
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from PIL import Image

from driftmap.errors import DriftmapError
from driftmap.frame import Frame
from driftmap.sources.base import open_source

HEADROOM_BYTES = 768 * 1024 * 1024
"""Address space an example may add to the process (the inputs are a few kB; the issue's lie asked for 1.2 GB)."""

FUZZ_EXAMPLES = int(os.environ.get("DRIFTMAP_FUZZ_EXAMPLES", "25"))
"""Examples per reader: 25, the same ones every run (derandomised: a CI failure reproduces), keep the file well under
a minute; ``DRIFTMAP_FUZZ_EXAMPLES=500`` hunts longer with fresh random examples (``--hypothesis-seed`` repeats one)."""
FUZZ = settings(max_examples=FUZZ_EXAMPLES, deadline=None, derandomize="DRIFTMAP_FUZZ_EXAMPLES" not in os.environ,
                database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                       HealthCheck.function_scoped_fixture])


# ---------------------------------------------------------------------------------------------------------------
# harness
# ---------------------------------------------------------------------------------------------------------------


def _vm_size_bytes() -> int:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmSize:"):
                return int(line.split()[1]) * 1024
    return 0


@contextlib.contextmanager
def bounded_memory() -> Iterator[None]:
    """The process may not grow its address space by more than :data:`HEADROOM_BYTES` inside the block."""
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    limit = _vm_size_bytes() + HEADROOM_BYTES
    if hard != resource.RLIM_INFINITY:
        limit = min(limit, hard)
    resource.setrlimit(resource.RLIMIT_AS, (limit, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


def read_frames(open_: Callable[..., Any]) -> tuple[list[Frame] | None, DriftmapError | None, Any]:
    """Open and iterate a source (strict); ``(frames, None, source)`` or ``(None, the typed error, None)``. Any other
    exception propagates (and fails the test)."""
    with bounded_memory():
        try:
            source = open_()
            frames = list(source)
        except DriftmapError as exc:
            event(f"refused: {type(exc).__name__}")
            return None, exc, None
    event(f"read: {min(len(frames), 3)} frame(s)")
    return frames, None, source


def read_lenient(open_: Callable[..., Any]) -> tuple[list[Frame], list[tuple[int, str]]] | None:
    """Lenient: the frames read and the skipped ones with their reasons (``None`` when the source cannot open)."""
    with bounded_memory():
        try:
            source = open_(lenient=True)
            frames = list(source)
        except DriftmapError:
            return None
    assert all(isinstance(reason, str) and reason for _, reason in source.skipped)
    return frames, source.skipped


def finite_rows(xyz: np.ndarray) -> np.ndarray:
    xyz = np.asarray(xyz, dtype=np.float32).reshape(-1, 3)
    return xyz[np.isfinite(xyz).all(axis=1)]


SENSOR_RANGE_M = 10_000.0
"""Points farther from the sensor are no measurement: every point reader drops them (a flipped exponent bit gives
1e30 m), as it drops NaN / inf (:data:`driftmap.sources.point_fields.MAX_POINT_RANGE_M`)."""


def measured_rows(xyz: np.ndarray) -> np.ndarray:
    """The rows a reader keeps: finite, and within :data:`SENSOR_RANGE_M` of the sensor."""
    rows = finite_rows(xyz)
    return rows[np.linalg.norm(rows.astype(np.float64), axis=1) <= SENSOR_RANGE_M]


def same_points(frame: Frame, expected_xyz: np.ndarray) -> None:
    expected = measured_rows(expected_xyz)
    assert frame.points_sensor.shape == expected.shape, (frame.points_sensor.shape, expected.shape)
    assert frame.points_sensor.tobytes() == expected.tobytes()


# ---- mutations ------------------------------------------------------------------------------------------------

LIES = (-1, 0, 1, 2, 3, 7, 99_999_999, 2**31, 2**32 + 1, 2**63, 10**30)


@st.composite
def mutated(draw: st.DrawFn, data: bytes, header_end: int, lie_fields: tuple[bytes, ...]) -> tuple[bytes, str]:
    """``data`` with one to three mutations, and what they were (for failure reports)."""
    out = bytearray(data)
    done = []
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(["truncate", "append", "flip", "lie", "nan", "overwrite"]))
        if kind == "truncate" and out:
            cut = draw(st.integers(0, len(out) - 1))
            del out[cut:]
            done.append(f"truncate@{cut}")
        elif kind == "append":
            extra = draw(st.binary(min_size=1, max_size=64))
            out += extra
            done.append(f"append{len(extra)}")
        elif kind == "flip" and out:
            pos = draw(st.integers(0, len(out) - 1))
            out[pos] ^= 1 << draw(st.integers(0, 7))
            done.append(f"flip@{pos}")
        elif kind == "lie" and lie_fields:
            out, what = _lie(draw, out, lie_fields)
            done.append(what)
        elif kind == "nan" and len(out) > header_end + 4:
            pos = draw(st.integers(header_end, len(out) - 4))
            value = draw(st.sampled_from([b"\x00\x00\xc0\x7f", b"\x00\x00\x80\x7f", b"\x00\x00\x80\xff", b"nan ", b"inf "]))
            out[pos:pos + 4] = value
            done.append(f"nan@{pos}")
        elif kind == "overwrite" and out:
            pos = draw(st.integers(0, len(out) - 1))
            chunk = draw(st.binary(min_size=1, max_size=16))
            out[pos:pos + len(chunk)] = chunk
            done.append(f"overwrite@{pos}")
    return bytes(out), ",".join(done)


def _lie(draw: st.DrawFn, out: bytearray, fields: tuple[bytes, ...]) -> tuple[bytearray, str]:
    """Replace the value(s) after one header keyword with a lie (a number or a word)."""
    key = draw(st.sampled_from(fields))
    match = re.search(re.escape(key) + rb"[ \t]+([^\n]*)\n", out)
    if match is None:
        return out, "lie-miss"
    values = match.group(1).split()
    k = draw(st.integers(0, max(len(values) - 1, 0)))
    new = draw(st.one_of(st.sampled_from(LIES).map(lambda v: str(v).encode()),
                         st.sampled_from([b"x", b"F", b"U", b"I", b"ascii", b"binary", b"binary_compressed", b"float",
                                          b"uint", b"list", b"", b"nan"])))
    values = values or [b""]
    values[min(k, len(values) - 1)] = new
    start, end = match.span(1)
    out[start:end] = b" ".join(values)
    return out, f"lie:{key.decode()}={new.decode(errors='replace')}"


def _scratch() -> contextlib.AbstractContextManager[str]:
    return tempfile.TemporaryDirectory(prefix="fuzz-")


# ---------------------------------------------------------------------------------------------------------------
# PCD / PLY: reference parsers written here, independently of the reader
# ---------------------------------------------------------------------------------------------------------------


def lzf_decompress(data: bytes, out_len: int) -> bytes | None:
    """LZF (liblzf) decompression; ``None`` for data that is not LZF of ``out_len`` bytes."""
    out = bytearray()
    i = 0
    while i < len(data):
        ctrl = data[i]
        i += 1
        if ctrl < 32:
            run = data[i:i + ctrl + 1]
            if len(run) != ctrl + 1:
                return None
            out += run
            i += ctrl + 1
        else:
            length = ctrl >> 5
            if length == 7:
                if i >= len(data):
                    return None
                length += data[i]
                i += 1
            if i >= len(data):
                return None
            ref = len(out) - ((ctrl & 0x1F) << 8) - data[i] - 1
            i += 1
            if ref < 0:
                return None
            for _ in range(length + 2):
                out.append(out[ref])
                ref += 1
        if len(out) > out_len:
            return None
    return bytes(out) if len(out) == out_len else None


_KIND = {b"F": "f", b"I": "i", b"U": "u"}


def reference_pcd_xyz(data: bytes) -> np.ndarray | None:
    """The x, y, z a PCD's bytes hold (every point, NaN included), or ``None`` when the header does not describe
    the data (then no reader may return points)."""
    end = data.find(b"\nDATA ")
    if end < 0:
        return None
    line_end = data.find(b"\n", end + 1)
    if line_end < 0:
        return None
    header = {}
    for line in data[:line_end].split(b"\n"):
        words = line.split()
        if words and not words[0].startswith(b"#"):
            header[words[0]] = words[1:]
    try:
        names = header[b"FIELDS"]
        sizes = [int(v) for v in header[b"SIZE"]]
        types = header[b"TYPE"]
        counts = [int(v) for v in header.get(b"COUNT", [b"1"] * len(names))]
        n = int(header[b"WIDTH"][0]) * int(header[b"HEIGHT"][0])
        if int(header.get(b"POINTS", [str(n).encode()])[0]) != n or n <= 0:
            return None
        dtype = np.dtype({"names": [v.decode("latin-1") for v in names],
                          "formats": [np.dtype((f"<{_KIND[t]}{s}", (c,)) if c > 1 else f"<{_KIND[t]}{s}")
                                      for t, s, c in zip(types, sizes, counts, strict=True)]})
        mode = header[b"DATA"][0]
    except (KeyError, ValueError, TypeError, IndexError):
        return None
    if not all(a in dtype.names for a in ("x", "y", "z")) or len(set(names)) != len(names):
        return None
    body = data[line_end + 1:]
    if mode == b"binary":
        if len(body) < n * dtype.itemsize:
            return None
        table = np.frombuffer(body, dtype=dtype, count=n)
    elif mode == b"binary_compressed":
        if len(body) < 8:
            return None
        csize, usize = struct.unpack("<II", body[:8])
        raw = lzf_decompress(body[8:8 + csize], usize) if usize == n * dtype.itemsize else None
        if raw is None:
            return None
        table = np.zeros(n, dtype=dtype)
        pos = 0
        for name in dtype.names:  # binary_compressed: one field after the other
            size = dtype[name].itemsize * n
            table[name] = np.frombuffer(raw[pos:pos + size], dtype=dtype[name]).reshape(table[name].shape)
            pos += size
    elif mode == b"ascii":
        rows = [r.split() for r in body.split(b"\n") if r.strip()]
        width = sum(counts)
        if len(rows) < n or any(len(r) < width for r in rows[:n]):
            return None
        columns = {}
        for axis in ("x", "y", "z"):
            col = sum(counts[: [v.decode("latin-1") for v in names].index(axis)])
            try:
                columns[axis] = np.array([float(r[col]) for r in rows[:n]], dtype=dtype[axis])
            except (ValueError, OverflowError):
                return None
        return np.stack([columns[a].astype(np.float32) for a in "xyz"], axis=1)
    else:
        return None
    return np.stack([table[a].astype(np.float32) for a in "xyz"], axis=1)


_PLY_CODES = {b"float": "f4", b"float32": "f4", b"double": "f8", b"float64": "f8", b"uchar": "u1", b"uint8": "u1",
              b"char": "i1", b"int8": "i1", b"ushort": "u2", b"uint16": "u2", b"short": "i2", b"int16": "i2",
              b"int": "i4", b"int32": "i4", b"uint": "u4", b"uint32": "u4"}


def reference_ply_xyz(data: bytes) -> np.ndarray | None:
    """The vertex x, y, z a vertex-only PLY's bytes hold, or ``None`` when the header does not describe them."""
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        return None
    fmt, elements = None, []
    for line in data[:end].split(b"\n")[1:]:
        words = line.split()
        if words[:1] == [b"format"] and len(words) >= 2:
            fmt = words[1]
        elif words[:1] == [b"element"] and len(words) == 3:
            try:
                elements.append([words[1], int(words[2]), []])
            except ValueError:
                return None
        elif words[:1] == [b"property"] and elements:
            if len(words) != 3 or words[1] not in _PLY_CODES:
                return None
            elements[-1][2].append((words[2].decode("latin-1"), _PLY_CODES[words[1]]))
    vertex = [k for k, e in enumerate(elements) if e[0] == b"vertex"]
    if len(vertex) != 1 or elements[vertex[0]][1] <= 0 or any(e[1] < 0 or not e[2] for e in elements):
        return None
    _, n, props = elements[vertex[0]]
    names = [p for p, _ in props]
    if not all(a in names for a in "xyz") or len(set(names)) != len(names):
        return None
    body = data[end + len(b"end_header\n"):]
    endian = ">" if fmt == b"binary_big_endian" else "<"
    if fmt in (b"binary_little_endian", b"binary_big_endian"):
        skip = sum(e[1] * np.dtype([(q, endian + c) for q, c in e[2]]).itemsize for e in elements[: vertex[0]])
        dtype = np.dtype([(p, endian + c) for p, c in props])
        if len(body) < skip + n * dtype.itemsize:
            return None
        table = np.frombuffer(body, dtype=dtype, count=n, offset=skip)
        return np.stack([table[a].astype(np.float32) for a in "xyz"], axis=1)
    if fmt == b"ascii":
        skip = sum(e[1] for e in elements[: vertex[0]])
        rows = [r.split() for r in body.split(b"\n") if r.strip()][skip:]
        if len(rows) < n or any(len(r) < len(props) for r in rows[:n]):
            return None
        try:
            return np.stack([np.array([float(r[names.index(a)]) for r in rows[:n]], dtype=dict(props)[a])
                             .astype(np.float32) for a in "xyz"], axis=1)
        except (ValueError, OverflowError):
            return None
    return None


def _base_clouds() -> dict[str, bytes]:
    """Small valid clouds in every encoding the folder reader takes."""
    rng = np.random.default_rng(22)
    n = 24
    xyz = rng.normal(scale=4.0, size=(n, 3)).astype(np.float32)
    cols = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "intensity": rng.random(n).astype(np.float32)}
    cols64 = {"x": xyz[:, 0].astype(np.float64), "y": xyz[:, 1].astype(np.float64), "z": xyz[:, 2].astype(np.float64),
              "t": rng.integers(0, 50_000_000, n).astype(np.uint32)}
    out = {}
    with _scratch() as tmp:
        root = Path(tmp)
        out["pcd_binary"] = write_pcd(root / "a.pcd", cols).read_bytes()
        out["pcd_binary_f8"] = write_pcd(root / "b.pcd", cols64).read_bytes()
        out["pcd_ascii"] = write_pcd(root / "c.pcd", cols, data="ascii").read_bytes()
        out["ply_binary"] = write_ply(root / "d.ply", cols).read_bytes()
        out["ply_ascii"] = write_ply(root / "e.ply", cols, ascii=True).read_bytes()
        head, _, body = out["ply_binary"].partition(b"element vertex")  # a camera element before the vertices
        out["ply_binary_2_elements"] = (head + b"element camera 2\nproperty double focal\nelement vertex" +
                                        body.replace(b"end_header\n", b"end_header\n" + struct.pack("<2d", 1.5, 2.5), 1))
        import open3d as o3d

        cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(xyz))
        cloud.point["intensity"] = o3d.core.Tensor(cols["intensity"].reshape(-1, 1))
        assert o3d.t.io.write_point_cloud(str(root / "f.pcd"), cloud, compressed=True)
        out["pcd_binary_compressed"] = (root / "f.pcd").read_bytes()
    return out


BASE_CLOUDS = _base_clouds()
PCD_FIELDS = (b"FIELDS", b"SIZE", b"TYPE", b"COUNT", b"WIDTH", b"HEIGHT", b"POINTS", b"DATA")
PLY_FIELDS = (b"element vertex", b"format", b"property float", b"property double")


@FUZZ
@given(data=st.data())
def test_fuzzed_pcd_and_ply_files(data: st.DataObject) -> None:
    kind = data.draw(st.sampled_from(sorted(BASE_CLOUDS)))
    base = BASE_CLOUDS[kind]
    header_end = base.find(b"DATA") + base[base.find(b"DATA"):].find(b"\n") + 1 if kind.startswith("pcd") else \
        base.find(b"end_header\n") + len(b"end_header\n")
    blob, how = data.draw(mutated(base, header_end, PCD_FIELDS if kind.startswith("pcd") else PLY_FIELDS))
    suffix = ".pcd" if kind.startswith("pcd") else ".ply"
    with _scratch() as tmp:
        folder = Path(tmp) / "clouds"
        folder.mkdir()
        (folder / f"scan_0{suffix}").write_bytes(blob)
        frames, error, _ = read_frames(lambda **kw: open_source(folder, format="cloud_folder", **kw))
        lenient = read_lenient(lambda **kw: open_source(folder, format="cloud_folder", **kw))
    if frames is None:
        assert error is not None and str(error)
        assert lenient is None or (not lenient[0] and len(lenient[1]) == 1), (how, lenient)
        return
    (frame,) = frames
    reference = (reference_pcd_xyz if suffix == ".pcd" else reference_ply_xyz)(blob)
    assert reference is not None, f"{kind} {how}: read, but its header does not describe its bytes"
    same_points(frame, reference)
    assert len(frame.points_sensor) <= len(blob) / 3  # no point from nothing: at least 3 bytes per point
    assert lenient is not None and len(lenient[0]) == 1 and lenient[0][0].points_sensor.tobytes() == \
        frame.points_sensor.tobytes()


# ---------------------------------------------------------------------------------------------------------------
# KITTI: .bin scans and times.txt
# ---------------------------------------------------------------------------------------------------------------


class Blobs(list):
    """Test inputs (a list) whose repr in failure reports is short."""

    def __repr__(self) -> str:
        return f"<{len(self)} inputs>"


@pytest.fixture(scope="module")
def kitti_small(kitti_dir: Path) -> Blobs:
    """Three real KITTI scans, every 250th point (about 500 points, 8 kB each)."""
    return Blobs(np.fromfile(kitti_dir / "velodyne" / f"{k:06d}.bin", dtype="<f4").reshape(-1, 4)[::250].tobytes()
                 for k in range(3))


_SECONDS = re.compile(r"[+]?(\d+(\.\d*)?|\.\d+)")


def _reference_stamp_ns(line: str) -> int | None:
    """Seconds written as a plain decimal -> ns (first 9 decimals); ``None`` for other spellings."""
    text = line.strip()
    if not _SECONDS.fullmatch(text):
        return None
    whole, _, frac = text.lstrip("+").partition(".")
    return int(whole or "0") * 10**9 + int((frac + "0" * 9)[:9])


TIMES = "0.0\n0.103730\n0.207205\n"


@FUZZ
@given(data=st.data())
def test_fuzzed_kitti_scans_and_times(data: st.DataObject, kitti_small: list[bytes]) -> None:
    target = data.draw(st.sampled_from(["scan", "scan", "times"]))
    scans = list(kitti_small)
    times = TIMES.encode()
    if target == "scan":
        k = data.draw(st.integers(0, 2))
        scans[k], how = data.draw(mutated(scans[k], 0, ()))
    else:
        times, how = data.draw(st.one_of(
            mutated(times, 0, ()),
            st.lists(st.sampled_from(["-0.5", "nan", "inf", "-inf", "1e12", "1e400", "1_0", "0x10", " ", "0.1", "0.3",
                                      "5", "1e-3", "-0", "+0.2", "9223372036.854775807", "9223372036.854775808"]),
                     min_size=0, max_size=5).map(lambda ls: ("\n".join(ls) + "\n").encode())).map(
            lambda v: v if isinstance(v, tuple) else (v, "lines")))
    with _scratch() as tmp:
        folder = Path(tmp) / "seq"
        (folder / "velodyne").mkdir(parents=True)
        for k, scan in enumerate(scans):
            (folder / "velodyne" / f"{k:06d}.bin").write_bytes(scan)
        (folder / "times.txt").write_bytes(times)
        frames, error, source = read_frames(lambda **kw: open_source(folder, **kw))
        read_lenient(lambda **kw: open_source(folder, **kw))
    if frames is None:
        assert error is not None and str(error)
        return
    lines = [x for x in times.decode("utf-8").split("\n") if x.strip()]
    columns = source.point_layout.columns
    assert [f.frame_id for f in frames] == [0, 1, 2]
    for frame, scan, k in zip(frames, scans, range(3), strict=True):
        raw = np.frombuffer(scan, dtype="<f4").reshape(-1, columns)
        same_points(frame, raw[:, :3])
        assert len(frame.points_sensor) <= len(scan) / 12
        expected = _reference_stamp_ns(lines[k])
        assert frame.stamp_ns >= 0 and (expected is None or frame.stamp_ns == expected), (how, lines[k], frame.stamp_ns)
    assert all(b.stamp_ns > a.stamp_ns for a, b in zip(frames, frames[1:]))


# ---------------------------------------------------------------------------------------------------------------
# depth PNG folders: 7-Scenes, TUM and Redwood layouts, with their pose files
# ---------------------------------------------------------------------------------------------------------------

SMALL_W, SMALL_H = 80, 60
SMALL_K = (73.125, 73.125, 39.875, 29.875, SMALL_W, SMALL_H)  # 7-Scenes' 585 / 320 / 240 at 1/8


@pytest.fixture(scope="module")
def small_depths(sevenscenes_dir: Path) -> list[np.ndarray]:
    """Two real 7-Scenes depth images at 1/8 (80x60, millimetres)."""
    return Blobs(np.asarray(Image.open(sevenscenes_dir / f"frame-{k:06d}.depth.png"))[::8, ::8].copy() for k in range(2))


def _png_bytes(depth: np.ndarray) -> bytes:
    with _scratch() as tmp:
        path = Path(tmp) / "d.png"
        Image.fromarray(depth).save(path)
        return path.read_bytes()


def _depth_folder(layout: str, root: Path, pngs: list[bytes], texts: dict[str, bytes]) -> tuple[Path, dict, list[Path]]:
    """A folder of ``layout`` with the two images; ``texts`` (name -> bytes) are its text files. Returns the folder,
    the options to open it with and the image paths."""
    if layout == "7scenes":
        paths = [root / f"frame-{k:06d}.depth.png" for k in range(2)]
        options = {"intrinsics": SMALL_K, "poses_from_ground_truth": True}
    elif layout == "tum":
        root = root / "rgbd_dataset_freiburg1_fuzz"
        paths = [root / "depth" / f"{k}.png" for k in range(2)]
        options = {"intrinsics": SMALL_K, "depth_scale": 1000.0, "poses_from_ground_truth": True}
    else:
        paths = [root / "depth" / f"{k:05d}.png" for k in range(2)]
        options = {"intrinsics": SMALL_K, "poses_from_ground_truth": True}
    for path, png in zip(paths, pngs, strict=True):
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(png)
    for name, text in texts.items():
        (root / name).write_bytes(text)
    return root, options, paths


def _text_files(layout: str) -> dict[str, bytes]:
    eye = "1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n"
    if layout == "7scenes":
        return {**{f"frame-{k:06d}.pose.txt": eye.encode() for k in range(2)},
                INTRINSICS_TXT: b"73.125 0 39.875\n0 73.125 29.875\n0 0 1\n"}
    if layout == "tum":
        return {"depth.txt": b"# depth\n0.0 depth/0.png\n0.033 depth/1.png\n",
                "groundtruth.txt": b"# tx ty tz qx qy qz qw\n0.0 0 0 0 0 0 0 1\n0.033 0.01 0 0 0 0 0 1\n"}
    return {"trajectory.log": ("0 0 1\n" + eye + "1 1 2\n" + eye).encode(),
            "rgbd.match": b"depth/00000.png color/00000.jpg\ndepth/00001.png color/00001.jpg\n",
            "camera_intrinsic.json": (b'{"width": 80, "height": 60, "intrinsic_matrix": '
                                      b'[73.125, 0, 0, 0, 73.125, 0, 39.875, 29.875, 1]}')}


INTRINSICS_TXT = "camera-intrinsics.txt"
"""(7-Scenes reads it as a 640x480 camera: read only when it is the file mutated, every frame then refused)"""


@FUZZ
@given(data=st.data())
def test_fuzzed_depth_png_folders(data: st.DataObject, small_depths: list[np.ndarray]) -> None:
    layout = data.draw(st.sampled_from(["7scenes", "tum", "redwood"]))
    pngs = [_png_bytes(d) for d in small_depths]
    texts = _text_files(layout)
    target = data.draw(st.sampled_from(["png", "png", "text"]))
    name = None
    if target == "png":
        k = data.draw(st.integers(0, 1))
        pngs[k], how = data.draw(mutated(pngs[k], 33, ()))
    else:
        name = data.draw(st.sampled_from(sorted(texts)))
        texts[name], how = data.draw(mutated(texts[name], 0, ()))
    with _scratch() as tmp:
        folder, options, paths = _depth_folder(layout, Path(tmp), pngs, texts)
        if layout == "redwood" or (target == "text" and name == INTRINSICS_TXT):
            options = {k: v for k, v in options.items() if k != "intrinsics"}  # the folder's own file is read
        frames, error, _ = read_frames(lambda **kw: open_source(folder, format=layout, **{**options, **kw}))
        read_lenient(lambda **kw: open_source(folder, format=layout, **{**options, **kw}))
        if frames is None:
            assert error is not None and str(error)
            return
        for frame in frames:
            image = _independent_decode(paths[[p.resolve() for p in paths].index(Path(frame.provenance.source_uri))])
            assert image is not None, f"{layout} {how}: a frame from an image that does not decode"
            readings = int(np.count_nonzero((image != 0) & (image != 65535)))
            assert image.shape == (SMALL_H, SMALL_W) and len(frame.points_sensor) <= readings
            assert np.isfinite(frame.points_sensor).all() and np.isfinite(frame.T_world_sensor).all()


def _independent_decode(path: Path) -> np.ndarray | None:
    """The 16-bit image Pillow decodes from ``path`` with every check on (``None`` when it cannot)."""
    try:
        with Image.open(path) as image:
            image.load()
            return np.asarray(image).astype(np.uint16) if image.mode in ("I;16", "I") else None
    except Exception:  # noqa: BLE001 - any failure means: not an image
        return None


# ---------------------------------------------------------------------------------------------------------------
# driftmap's synthetic log: synthetic.json, its odometry file, depth PNGs
# ---------------------------------------------------------------------------------------------------------------


def _synthetic_base() -> dict[str, bytes]:
    """The first two frames of the embedded demo log (relative path -> bytes)."""
    import json

    from driftmap.demo import embedded_log_path

    root = embedded_log_path()
    meta = json.loads((root / "synthetic.json").read_text())
    meta["frames"] = meta["frames"][:2]
    files = {"synthetic.json": json.dumps(meta, indent=1).encode()}
    for name in (meta["odometry"], meta["ground_truth"]):
        lines = (root / name).read_bytes().split(b"\n")
        data = [x for x in lines if x.strip() and not x.startswith(b"#")][:2]
        files[name] = b"\n".join([x for x in lines if x.startswith(b"#")] + data) + b"\n"
    for entry in meta["frames"]:
        files[entry["depth"]] = (root / entry["depth"]).read_bytes()
    return files


@FUZZ
@given(data=st.data())
def test_fuzzed_synthetic_logs(data: st.DataObject) -> None:
    files = dict(SYNTHETIC_BASE)
    name = data.draw(st.sampled_from(sorted(files)))
    files[name], how = data.draw(mutated(files[name], 33 if name.endswith(".png") else 0,
                                         (b'"stamp_ns":', b'"frame_id":', b'"depth_scale":', b'"fx":', b'"width":')))
    with _scratch() as tmp:
        root = Path(tmp)
        for rel, blob in files.items():
            (root / rel).parent.mkdir(parents=True, exist_ok=True)
            (root / rel).write_bytes(blob)
        frames, error, _ = read_frames(lambda **kw: open_source(root, format="synthetic", **kw))
        read_lenient(lambda **kw: open_source(root, format="synthetic", **kw))
        if frames is None:
            assert error is not None and str(error)
            return
        for frame in frames:
            image = _independent_decode(Path(frame.provenance.source_uri))
            assert image is not None, f"{name} {how}: a frame from an image that does not decode"
            assert len(frame.points_sensor) <= int(np.count_nonzero(image)) and np.isfinite(frame.points_sensor).all()
    assert all(f.stamp_ns >= 0 for f in frames) and all(b.stamp_ns > a.stamp_ns for a, b in zip(frames, frames[1:]))


SYNTHETIC_BASE = _synthetic_base()


# ---------------------------------------------------------------------------------------------------------------
# pose files that sources read (KITTI poses.txt + calib.txt, cloud-folder poses=, BALM-like 4x4 csv)
# ---------------------------------------------------------------------------------------------------------------

KITTI_POSES = b"1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0.5 0 1 0 0 0 0 1 0\n1 0 0 1.0 0 1 0 0 0 0 1 0\n"
CALIB = b"P0: 1 0 0 0 0 1 0 0 0 0 1 0\nTr: 0 -1 0 0 0 0 -1 0 1 0 0 0\n"
BLOCKS = b"".join(f"1,0,0,{k}\n0,1,0,0\n0,0,1,0\n0,0,0,{1630577758 + k * 0.5},\n".encode() for k in range(3))


@FUZZ
@given(data=st.data())
def test_fuzzed_pose_files_read_by_sources(data: st.DataObject, kitti_small: list[bytes]) -> None:
    which = data.draw(st.sampled_from(["kitti_poses", "kitti_calib", "cloud_4x4_beside", "cloud_poses_tum"]))
    base = {"kitti_poses": KITTI_POSES, "kitti_calib": CALIB, "cloud_4x4_beside": BLOCKS,
            "cloud_poses_tum": b"0.0 0 0 0 0 0 0 1\n0.1 0.1 0 0 0 0 0 1\n0.2 0.2 0 0 0 0 0 1\n"}[which]
    text, how = data.draw(mutated(base, 0, ()))
    with _scratch() as tmp:
        root = Path(tmp)
        if which.startswith("kitti"):
            (root / "velodyne").mkdir()
            for k, scan in enumerate(kitti_small):
                (root / "velodyne" / f"{k:06d}.bin").write_bytes(scan)
            (root / "times.txt").write_text(TIMES)
            (root / "poses.txt").write_bytes(text if which == "kitti_poses" else KITTI_POSES)
            (root / "calib.txt").write_bytes(text if which == "kitti_calib" else CALIB)

            def open_(**kw: Any) -> Any:
                return open_source(root, poses_from_ground_truth=True, **kw)
        else:
            for k, scan in enumerate(kitti_small):
                xyz = np.frombuffer(scan, dtype="<f4").reshape(-1, 4)
                write_pcd(root / f"scan_{k}.pcd", {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]})
            poses = root / ("alidarPose.csv" if which == "cloud_4x4_beside" else "poses.txt")
            poses.write_bytes(text)
            extra = {} if which == "cloud_4x4_beside" else {"poses": poses}

            def open_(**kw: Any) -> Any:
                return open_source(root, format="cloud_folder", **extra, **kw)
        frames, error, _ = read_frames(open_)
        read_lenient(open_)
    if frames is None:
        assert error is not None and str(error)
        return
    for frame in frames:
        assert frame.stamp_ns >= 0 and np.isfinite(frame.T_world_sensor).all()
        R = frame.T_world_sensor[:3, :3]
        assert np.abs(R @ R.T - np.eye(3)).max() < 1e-6, how
    assert all(b.stamp_ns > a.stamp_ns for a, b in zip(frames, frames[1:]))


# ---------------------------------------------------------------------------------------------------------------
# ROS logs: MCAP (message fields and bytes), ROS 1 bags and rosbag2 folders (bytes)
# ---------------------------------------------------------------------------------------------------------------

LOG_STAMP0_NS = 1_700_000_000_000_000_000


def _log_messages() -> list[tuple[str, str, dict, int]]:
    rng = np.random.default_rng(5)
    scans = [(LOG_STAMP0_NS + k * 100_000_000, rng.normal(scale=5.0, size=(16, 3)).astype(np.float32),
              rng.random(16).astype(np.float32)) for k in range(3)]
    T = [np.eye(4) for _ in range(3)]
    for k in range(3):
        T[k][0, 3] = 0.5 * k
    return ros_log_messages(scans, T, np.eye(4))


def _log_bytes(kind: str, messages: list) -> dict[str, bytes]:
    """The files of a log (name -> bytes): one file for MCAP / ROS 1, the folder's files for rosbag2."""
    with _scratch() as tmp:
        path = Path(tmp) / {"mcap": "log.mcap", "rosbag1": "log.bag", "rosbag2": "log"}[kind]
        write_ros_messages(path, kind, messages)
        if path.is_dir():
            return {f.name: f.read_bytes() for f in sorted(path.iterdir())}
        return {path.name: path.read_bytes()}


BASE_LOGS = {kind: _log_bytes(kind, _log_messages()) for kind in ("mcap", "rosbag1", "rosbag2")}


def _check_log(path: Path, total_bytes: int, how: str) -> None:
    options = {"pose_from_odometry": "/odom"}
    frames, error, _ = read_frames(lambda **kw: open_source(path, **options, **kw))
    lenient = read_lenient(lambda **kw: open_source(path, **options, **kw))
    if frames is None:
        assert error is not None and str(error)
        return
    assert sum(len(f.points_sensor) for f in frames) * 12 <= total_bytes, how
    for frame in frames:
        assert frame.stamp_ns >= 0 and np.isfinite(frame.points_sensor).all() and np.isfinite(frame.T_world_sensor).all()
    assert all(b.stamp_ns > a.stamp_ns for a, b in zip(frames, frames[1:])), how
    assert lenient is not None and [f.frame_id for f in lenient[0]] == [f.frame_id for f in frames]


@FUZZ
@given(data=st.data())
def test_fuzzed_ros_log_bytes(data: st.DataObject) -> None:
    kind = data.draw(st.sampled_from(["mcap", "rosbag1", "rosbag2"]))
    files = dict(BASE_LOGS[kind])
    name = data.draw(st.sampled_from(sorted(files)))
    files[name], how = data.draw(mutated(files[name], 0, (b"message_count:", b"topic_metadata:", b"serialization_format:")
                                         if name.endswith(".yaml") else ()))
    with _scratch() as tmp:
        if kind == "rosbag2":
            path = Path(tmp) / "log"
            path.mkdir()
            for n, blob in files.items():
                (path / n).write_bytes(blob)
        else:
            path = Path(tmp) / name
            path.write_bytes(files[name])
        _check_log(path, sum(len(b) for b in files.values()), f"{kind} {name} {how}")


_CLOUD_LIES = {"width": LIES, "height": LIES, "point_step": LIES, "row_step": LIES,
               "is_bigendian": (True,), "is_dense": (True, False)}


@FUZZ
@given(data=st.data())
def test_fuzzed_pointcloud2_fields(data: st.DataObject) -> None:
    """PointCloud2 messages whose layout fields lie (width, height, point_step, row_step, the fields' offsets,
    datatypes and counts) and data of another length, in an MCAP: frames are what the data holds, or refused."""
    messages = _log_messages()
    clouds = [k for k, m in enumerate(messages) if m[0] == ROS_CLOUD_TOPIC]
    k = data.draw(st.sampled_from(clouds))
    topic, typename, msg, log_time = messages[k]
    msg = {**msg, "fields": [dict(f) for f in msg["fields"]]}
    for _ in range(data.draw(st.integers(1, 3))):
        what = data.draw(st.sampled_from(["layout", "field", "data"]))
        if what == "layout":
            key = data.draw(st.sampled_from(sorted(_CLOUD_LIES)))
            value = data.draw(st.sampled_from(_CLOUD_LIES[key]))
            if isinstance(value, int) and not isinstance(value, bool) and not 0 <= value < 2**32:
                value = value % 2**32  # the wire type is uint32
            msg[key] = value
        elif what == "field":
            f = data.draw(st.sampled_from(msg["fields"]))
            key = data.draw(st.sampled_from(["offset", "datatype", "count"]))
            f[key] = data.draw(st.sampled_from((0, 1, 3, 4, 8, 9, 12, 16, 255, 2**31)))
            if key == "datatype":
                f[key] %= 256
        else:
            data_bytes = msg["data"]
            cut = data.draw(st.integers(0, len(data_bytes) + 32))
            msg["data"] = data_bytes[:cut] + bytes(max(0, cut - len(data_bytes)))
    messages[k] = (topic, typename, msg, log_time)
    with _scratch() as tmp:
        path = write_ros_messages(Path(tmp) / "log.mcap", "mcap", messages)
        frames, error, _ = read_frames(lambda **kw: open_source(path, **kw))
        read_lenient(lambda **kw: open_source(path, **kw))
    if frames is None:
        assert error is not None and str(error)
        return
    index = clouds.index(k)
    expected = _reference_cloud_xyz(msg)
    assert expected is not None, f"{msg['width']}x{msg['height']} step {msg['point_step']}: read, but inconsistent"
    same_points(frames[index], expected)


def _depth_image_messages(depth: np.ndarray) -> list[tuple[str, str, dict, int]]:
    """Two 16UC1 depth images (millimetres) with their CameraInfo, as message dicts."""
    h, w = depth.shape
    fx, fy, cx, cy = SMALL_K[:4]
    out = []
    for k in range(2):
        stamp = LOG_STAMP0_NS + k * 33_333_333
        header = {"stamp": {"sec": stamp // 10**9, "nanosec": stamp % 10**9}, "frame_id": "camera"}
        info = {"header": header, "height": h, "width": w, "distortion_model": "plumb_bob", "d": [0.0] * 5,
                "k": [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0], "r": [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0],
                "p": [fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0], "binning_x": 0, "binning_y": 0,
                "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False}}
        image = {"header": header, "height": h, "width": w, "encoding": "16UC1", "is_bigendian": 0, "step": 2 * w,
                 "data": depth.astype("<u2").tobytes()}
        out.append(("/camera/camera_info", "sensor_msgs/msg/CameraInfo", info, stamp))
        out.append(("/camera/depth", "sensor_msgs/msg/Image", image, stamp + 1000))
    return out


_IMAGE_LIES = {"width": LIES, "height": LIES, "step": LIES, "encoding": ("16UC1", "32FC1", "mono16", "rgb8", ""),
               "is_bigendian": (0, 1)}


@FUZZ
@given(data=st.data())
def test_fuzzed_depth_image_fields(data: st.DataObject, small_depths: list[np.ndarray]) -> None:
    """Depth Images (and their CameraInfo) whose sizes, step, encoding or data length lie, in an MCAP: frames hold
    at most the image's pixels, or are refused."""
    messages = _depth_image_messages(small_depths[0])
    k = data.draw(st.sampled_from(range(len(messages))))
    topic, typename, msg, log_time = messages[k]
    msg = dict(msg)
    for _ in range(data.draw(st.integers(1, 3))):
        if typename.endswith("Image") and data.draw(st.booleans()):
            key = data.draw(st.sampled_from(sorted(_IMAGE_LIES)))
            value = data.draw(st.sampled_from(_IMAGE_LIES[key]))
            msg[key] = value % 2**32 if isinstance(value, int) and key != "is_bigendian" else value
        elif typename.endswith("Image"):
            cut = data.draw(st.integers(0, len(msg["data"]) + 64))
            msg["data"] = msg["data"][:cut] + bytes(max(0, cut - len(msg["data"])))
        else:
            key = data.draw(st.sampled_from(["width", "height", "k", "d", "binning_x"]))
            if key in ("k", "d"):
                values = list(msg[key])
                values[data.draw(st.integers(0, len(values) - 1))] = data.draw(
                    st.sampled_from([0.0, -1.0, float("nan"), float("inf"), 1e300]))
                msg[key] = values
            else:
                msg[key] = data.draw(st.sampled_from(LIES)) % 2**32
    messages[k] = (topic, typename, msg, log_time)
    with _scratch() as tmp:
        path = write_ros_messages(Path(tmp) / "log.mcap", "mcap", messages)
        frames, error, _ = read_frames(lambda **kw: open_source(path, **kw))
        read_lenient(lambda **kw: open_source(path, **kw))
    if frames is None:
        assert error is not None and str(error)
        return
    images = [m[2] for m in messages if m[0] == "/camera/depth"]
    for frame, image in zip(frames, images, strict=True):
        pixels = int(image["width"]) * int(image["height"])
        item = 4 if image["encoding"] == "32FC1" else 2
        assert len(frame.points_sensor) <= min(pixels, len(image["data"]) // item)
        assert np.isfinite(frame.points_sensor).all() and frame.intrinsics is not None
        assert (frame.intrinsics.width, frame.intrinsics.height) == (image["width"], image["height"])


_POINTFIELD = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


def _reference_cloud_xyz(msg: dict) -> np.ndarray | None:
    """x, y, z of a PointCloud2 dict read from its bytes here, or ``None`` when its layout does not fit its data."""
    width, height, step, row_step = msg["width"], msg["height"], msg["point_step"], msg["row_step"]
    data = msg["data"]
    if width * height == 0:  # an empty cloud: empty data
        return np.empty((0, 3), dtype=np.float32) if not data and 0 < step < 2**31 else None
    if step <= 0 or row_step < width * step or len(data) > row_step * height:
        return None
    if len(data) < row_step * (height - 1) + width * step:
        return None
    endian = ">" if msg["is_bigendian"] else "<"
    columns = []
    for axis in "xyz":
        f = next((f for f in msg["fields"] if f["name"] == axis), None)
        if f is None or f["datatype"] not in _POINTFIELD or max(f["count"], 1) != 1:
            return None
        code = np.dtype(endian + _POINTFIELD[f["datatype"]])
        if f["offset"] + code.itemsize > step:
            return None
        buf = np.frombuffer(data, dtype=np.uint8)
        rows = [np.ndarray((width,), dtype=code, buffer=buf, offset=r * row_step + f["offset"], strides=(step,))
                for r in range(height)]
        columns.append(np.concatenate(rows).astype(np.float32))
    return np.stack(columns, axis=1)


# ---------------------------------------------------------------------------------------------------------------
# the harness itself catches what it must
# ---------------------------------------------------------------------------------------------------------------


def test_the_oracle_range_is_the_readers() -> None:
    from driftmap.sources.point_fields import MAX_POINT_RANGE_M

    assert SENSOR_RANGE_M == MAX_POINT_RANGE_M


def test_the_memory_bound_catches_an_allocation_far_beyond_the_input() -> None:
    with pytest.raises(MemoryError), bounded_memory():
        np.ones(HEADROOM_BYTES // 8 + (64 << 20), dtype=np.float64)
    np.ones(1 << 20)  # and is lifted afterwards


def test_the_references_read_the_base_files_as_written() -> None:
    for kind, blob in BASE_CLOUDS.items():
        ref = (reference_pcd_xyz if kind.startswith("pcd") else reference_ply_xyz)(blob)
        assert ref is not None and ref.shape == (24, 3), kind
        assert ref.tobytes() == finite_rows(ref).tobytes()  # (no NaN in the base files)
        with _scratch() as tmp:
            folder = Path(tmp)
            (folder / f"scan_0.{kind[:3]}").write_bytes(blob)
            same_points(open_source(folder, format="cloud_folder").frame(0), ref)
