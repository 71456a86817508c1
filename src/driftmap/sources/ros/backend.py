"""The message layer under a ROS log source: the topics of a log, undecoded messages, and what a reader of a log
container (:mod:`~driftmap.sources.ros.mcap_backend`, :mod:`~driftmap.sources.ros.rosbags_backend`) provides."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from driftmap.errors import SourceError


@dataclass(frozen=True)
class TopicInfo:
    """A topic of a log: name, message type (ROS 2 spelling), message count and encodings."""

    name: str
    msgtype: str
    count: int | None
    message_encoding: str
    schema_encoding: str


@dataclass(frozen=True, slots=True)
class RawMessage:
    """One undecoded message: topic, log time and a backend-specific handle."""

    topic: str
    log_time_ns: int
    handle: Any
    size_bytes: int


class Backend:
    """A reader of one log: its topics, its messages in log order (optionally a time range), decoding, random access
    by message index, and the log's metadata records."""

    path: Path
    format_name: str

    def topics(self) -> dict[str, TopicInfo]:
        raise NotImplementedError

    def stream(
        self, topics: Sequence[str], start_ns: int | None = None, end_ns: int | None = None
    ) -> Iterator[RawMessage]:
        raise NotImplementedError

    def decode(self, raw: RawMessage) -> Any:
        raise NotImplementedError

    def log_times(self, topic: str) -> NDArray[np.int64]:
        """Log times of every message of ``topic``, in reading order."""
        return np.fromiter((r.log_time_ns for r in self.stream([topic])), dtype=np.int64)

    def fetch(self, topic: str, k: int, log_times: NDArray[np.int64]) -> RawMessage:
        """The ``k``-th message of ``topic`` (``log_times`` from :meth:`log_times`)."""
        t = int(log_times[k])
        j = k - int(np.searchsorted(log_times, t, side="left"))
        for n, raw in enumerate(self.stream([topic], t, t + 1)):
            if n == j:
                return raw
        raise SourceError(f"{self.path}: topic {topic}: message {k} (log time {t} ns) not found where the index says")

    def check_decodable(self, topic: str) -> None:
        """Raise :class:`SourceError` naming topic and schema when messages of ``topic`` cannot be decoded."""

    def first_messages(self, topics: Sequence[str]) -> dict[str, RawMessage]:
        """An early message of each topic (the first one, or one from the first chunk holding the topic)."""
        out = {}
        for topic in topics:
            for raw in self.stream([topic]):
                out[topic] = raw
                break
        return out

    def metadata(self) -> dict[str, dict[str, str]]:
        return {}

    def close(self) -> None:
        pass
