"""Which ROS log container a path is (MCAP file, ROS 1 bag, rosbag2 folder) and the reader that opens it."""

from __future__ import annotations

from pathlib import Path

from driftmap.errors import SourceError
from driftmap.sources.ros.backend import Backend, TopicInfo
from driftmap.sources.ros.mcap_backend import McapBackend
from driftmap.sources.ros.msgtypes import FORMAT_MCAP, FORMAT_ROSBAG1, FORMAT_ROSBAG2, MCAP_MAGIC, ROSBAG1_MAGIC
from driftmap.sources.ros.rosbags_backend import RosbagsBackend, rosbag2_dir


_NAMES = {FORMAT_MCAP: "an MCAP file", FORMAT_ROSBAG1: "a ROS 1 bag", FORMAT_ROSBAG2: "a rosbag2 folder"}


def read_magic(path: Path, n: int) -> bytes:
    try:
        with open(path, "rb") as f:
            return f.read(n)
    except OSError:
        return b""


def detect_mcap(path: Path) -> bool:
    return path.is_file() and read_magic(path, len(MCAP_MAGIC)) == MCAP_MAGIC


def detect_rosbag1(path: Path) -> bool:
    return path.is_file() and read_magic(path, len(ROSBAG1_MAGIC)) == ROSBAG1_MAGIC


def detect_rosbag2(path: Path) -> bool:
    return rosbag2_dir(path) is not None


def detect_format(path: str | Path) -> str | None:
    """``"mcap"``, ``"rosbag1"``, ``"rosbag2"`` or ``None``."""
    path = Path(path)
    for name, detect in (
        (FORMAT_ROSBAG2, detect_rosbag2),
        (FORMAT_MCAP, detect_mcap),
        (FORMAT_ROSBAG1, detect_rosbag1),
    ):
        if detect(path):
            return name
    return None


def open_backend(path: str | Path, format: str | None = None, *, lenient: bool = False) -> Backend:
    """The message reader for a log (``format`` as registered: ``mcap``, ``rosbag1``, ``rosbag2``)."""
    path = Path(path)
    if not path.exists():
        raise SourceError(f"{path}: no such file or folder")
    found = detect_format(path)
    if format is not None and found is not None and format != found:  # the bytes decide, not the flag
        raise SourceError(f"{path}: is {_NAMES[found]} (by its first bytes or layout), not {_NAMES.get(format, repr(format))}"
                          f"; leave the format out or give format={found!r}")
    fmt = format or found
    if fmt == FORMAT_MCAP:
        return McapBackend(path, lenient=lenient)
    if fmt in (FORMAT_ROSBAG1, FORMAT_ROSBAG2):
        return RosbagsBackend(path, fmt)
    raise SourceError(
        f"{path}: not a ROS log (expected an MCAP file, a ROS 1 .bag or a rosbag2 folder; format={format!r})"
    )


def list_topics(path: str | Path, format: str | None = None) -> dict[str, TopicInfo]:
    """Topics of a log with their message types and counts."""
    backend = open_backend(path, format)
    try:
        return backend.topics()
    finally:
        backend.close()
