"""MCAP files with ROS 2 messages: the ``mcap`` reader and the ``mcap_ros2`` decoder, the MCAP index for counts,
random access and starting mid-file, and a linear scan for files without a usable summary (truncated or damaged:
what precedes the damage is readable in lenient mode)."""

from __future__ import annotations

import contextlib
import heapq
import logging
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from driftmap.errors import SourceError
from driftmap.sources.ros.backend import Backend, RawMessage, TopicInfo
from driftmap.sources.ros.msgtypes import FORMAT_MCAP, MCAP_MAGIC, normalize_type

logger = logging.getLogger(__name__)


DAMAGED_INSIDE_HINT = ("the damage is inside the file (a chunk that does not decompress or parse), which --lenient does "
                       "not skip (it reads past a truncated end only); the mcap CLI's `mcap recover FILE -o FIXED.mcap` "
                       "salvages the intact chunks")

class McapBackend(Backend):
    """``mcap`` reader + ``mcap_ros2`` decoder; an in-memory catalogue for files without a usable summary."""

    format_name = FORMAT_MCAP

    def __init__(self, path: Path, *, lenient: bool):
        from mcap.reader import SeekingReader
        from mcap_ros2.decoder import DecoderFactory

        self.path = path
        self.lenient = lenient
        try:
            self._file = open(path, "rb")
        except OSError as exc:
            raise SourceError(f"{path}: cannot open MCAP file ({exc})") from exc
        self._size = path.stat().st_size
        try:
            self._reader = SeekingReader(self._file, validate_crcs=True)  # a flipped bit is an error, not data
        except Exception as exc:  # McapError, or whatever a damaged magic / header makes the parser raise
            self._file.close()
            raise SourceError(f"{path}: not an MCAP file ({type(exc).__name__}: {exc})") from exc
        self._factory = DecoderFactory()
        self._decoders: dict[int, Any] = {}
        self._summary = None
        self._memory: dict[str, list[tuple[int, int, Any, Any, Any]]] | None = None
        self._mem_channels: dict[int, Any] = {}
        self._mem_schemas: dict[int, Any] = {}
        self._mem_metadata: dict[str, dict[str, str]] = {}
        self.damage: str | None = None
        """Why the file could not be read to its end (lenient mode only)."""
        footer_problem = None
        try:
            self._summary = self._reader.get_summary()
        except Exception as exc:  # no footer / summary: a truncated file, or one written without a summary
            footer_problem = exc
        if self._summary is None:
            try:
                self._scan(footer_problem)
            except BaseException:
                self._file.close()
                raise

    # -- linear scan (no summary, or a damaged/truncated file)
    def _scan(self, footer_problem: Exception | None) -> None:
        from mcap.records import Channel, Message, Metadata, Schema
        from mcap.stream_reader import StreamReader

        memory: dict[str, list[tuple[int, int, Any, Any, Any]]] = {}
        self._file.seek(0)
        reader = StreamReader(self._file, skip_magic=False, validate_crcs=True)
        readable_to = len(MCAP_MAGIC)
        seq = 0
        try:
            for record in reader.records:
                if isinstance(record, Schema):
                    self._mem_schemas[record.id] = record
                elif isinstance(record, Channel):
                    self._mem_channels[record.id] = record
                elif isinstance(record, Message):
                    channel = self._mem_channels.get(record.channel_id)
                    if channel is None:
                        raise SourceError(f"{self.path}: message on unknown channel id {record.channel_id}")
                    schema = self._mem_schemas.get(channel.schema_id)
                    memory.setdefault(channel.topic, []).append((record.log_time, seq, channel, schema, record))
                    seq += 1
                elif isinstance(record, Metadata):
                    self._mem_metadata[record.name] = dict(record.metadata)
                readable_to = self._file.tell()
        except SourceError:
            raise
        except Exception as exc:  # any record that does not parse (short read, bad compression, ...) is damage
            n = sum(len(v) for v in memory.values())
            message = (
                f"{self.path}: truncated or damaged MCAP: nothing readable after byte offset {readable_to} of "
                f"{self._size} ({type(exc).__name__}: {exc}); {n} messages before it are readable"
            )
            if not self.lenient:
                raise SourceError(message + " (open with lenient=True, CLI --lenient, to read them)") from exc
            logger.warning("%s; reading those (lenient)", message)
            self.damage = message
        else:
            if footer_problem is not None:  # pragma: no cover - summary unreadable but records fine
                logger.warning("%s: summary unreadable (%s); read the file linearly", self.path, footer_problem)
            logger.info("%s: no MCAP summary; scanned the file linearly (%d messages)", self.path, seq)
        for entries in memory.values():
            entries.sort(key=lambda e: (e[0], e[1]))
        self._memory = memory

    # -- topics
    def topics(self) -> dict[str, TopicInfo]:
        if self._memory is not None:
            channels = list(self._mem_channels.values())
            schemas = self._mem_schemas
            counts: dict[int, int] = {}
            for entries in self._memory.values():
                for e in entries:
                    counts[e[2].id] = counts.get(e[2].id, 0) + 1
            has_counts = True
        else:
            assert self._summary is not None
            channels = list(self._summary.channels.values())
            schemas = self._summary.schemas
            stats = self._summary.statistics
            has_counts = stats is not None
            counts = dict(stats.channel_message_counts) if stats is not None else {}
        out: dict[str, TopicInfo] = {}
        for ch in channels:
            schema = schemas.get(ch.schema_id)
            count: int | None = counts.get(ch.id, 0) if has_counts else None
            prev = out.get(ch.topic)
            if prev is not None:
                count = None if count is None or prev.count is None else count + prev.count
            out[ch.topic] = TopicInfo(
                ch.topic,
                normalize_type(schema.name) if schema is not None else "",
                count,
                ch.message_encoding,
                schema.encoding if schema is not None else "",
            )
        return out

    # -- reading
    def stream(
        self, topics: Sequence[str], start_ns: int | None = None, end_ns: int | None = None
    ) -> Iterator[RawMessage]:
        if self._memory is not None:
            lists = [self._memory.get(t, []) for t in topics]
            for log_time, _, channel, schema, message in heapq.merge(*lists, key=lambda e: (e[0], e[1])):
                if (start_ns is not None and log_time < start_ns) or (end_ns is not None and log_time >= end_ns):
                    continue
                yield RawMessage(channel.topic, log_time, (schema, channel, message), len(message.data))
            return
        try:
            for schema, channel, message in self._reader.iter_messages(
                topics=list(topics), starting_at=start_ns, ending_before=end_ns
            ):
                yield RawMessage(channel.topic, message.log_time, (schema, channel, message), len(message.data))
        except SourceError:
            raise
        except Exception as exc:  # a chunk that does not parse or decompress
            raise SourceError(
                f"{self.path}: damaged MCAP data while reading {', '.join(topics)} ({type(exc).__name__}: {exc}); "
                f"{DAMAGED_INSIDE_HINT}"
            ) from exc

    def decoder(self, topic: str, channel: Any, schema: Any) -> Any:
        """The ROS 2 decoder of a channel; :class:`SourceError` naming topic and schema if there is none."""
        decoder = self._decoders.get(channel.id)
        if decoder is not None:
            return decoder
        schema_name = schema.name if schema is not None else "<no schema>"
        schema_encoding = schema.encoding if schema is not None else ""
        try:
            decoder = self._factory.decoder_for(channel.message_encoding, schema)
        except Exception as exc:  # the ros2msg schema text does not parse
            raise SourceError(
                f"{self.path}: topic {topic}: cannot parse schema {schema_name!r} ({schema_encoding}): {exc}"
            ) from exc
        if decoder is None:
            raise SourceError(
                f"{self.path}: topic {topic}: unknown message encoding {channel.message_encoding!r} with schema "
                f"{schema_name!r} (schema encoding {schema_encoding!r}); driftmap reads ROS 2 messages "
                f"(message encoding 'cdr', schema encoding 'ros2msg')"
            )
        self._decoders[channel.id] = decoder
        return decoder

    def check_decodable(self, topic: str) -> None:
        if self._memory is not None:
            entries = self._memory.get(topic)
            if entries:
                self.decoder(topic, entries[0][2], entries[0][3])
            return
        assert self._summary is not None
        for channel in self._summary.channels.values():
            if channel.topic == topic:
                self.decoder(topic, channel, self._summary.schemas.get(channel.schema_id))

    def decode(self, raw: RawMessage) -> Any:
        schema, channel, message = raw.handle
        decoder = self.decoder(raw.topic, channel, schema)
        try:
            return decoder(message.data)
        except Exception as exc:
            raise SourceError(
                f"{self.path}: topic {raw.topic}: cannot decode message logged at {raw.log_time_ns} ns as "
                f"{schema.name if schema else '?'} ({type(exc).__name__}: {exc})"
            ) from exc

    @contextlib.contextmanager
    def _records(self, what: str) -> Iterator[None]:
        """Records read directly (chunks, message indexes): whatever a damaged one makes the parser raise is a
        :class:`SourceError` naming the file."""
        try:
            yield
        except SourceError:
            raise
        except Exception as exc:  # the mcap parser raises many types for a damaged record
            raise SourceError(
                f"{self.path}: damaged MCAP data while reading {what} ({type(exc).__name__}: {exc}); "
                f"{DAMAGED_INSIDE_HINT}"
            ) from exc

    def log_times(self, topic: str) -> NDArray[np.int64]:
        """From the message-index records next to every chunk (no chunk is decompressed)."""
        with self._records(f"the message index of {topic}"):
            return self._log_times(topic)

    def _log_times(self, topic: str) -> NDArray[np.int64]:
        from mcap.records import MessageIndex
        from mcap.stream_reader import StreamReader

        if self._memory is not None:
            return np.array([e[0] for e in self._memory.get(topic, [])], dtype=np.int64)
        summary = self._summary
        assert summary is not None
        channel_ids = [cid for cid, ch in summary.channels.items() if ch.topic == topic]
        if not summary.chunk_indexes or any(not ci.message_index_offsets for ci in summary.chunk_indexes):
            return super().log_times(topic)  # no message indexes: read the chunks once
        entries: list[tuple[int, int, int]] = []
        for ci in summary.chunk_indexes:
            for cid in channel_ids:
                offset = ci.message_index_offsets.get(cid)
                if offset is None:
                    continue
                self._file.seek(offset)
                record = next(iter(StreamReader(self._file, skip_magic=True, validate_crcs=True).records))
                if not isinstance(record, MessageIndex):
                    raise SourceError(
                        f"{self.path}: expected a message index at byte offset {offset}, found {type(record).__name__}"
                    )
                entries.extend((t, ci.chunk_start_offset, o) for t, o in record.records)
        entries.sort()
        return np.array([e[0] for e in entries], dtype=np.int64)

    def first_messages(self, topics: Sequence[str]) -> dict[str, RawMessage]:
        """One pass over the earliest chunks: every chunk is read at most once, however many topics."""
        with self._records(f"the first messages of {', '.join(topics)}"):
            return self._first_messages(topics)

    def _first_messages(self, topics: Sequence[str]) -> dict[str, RawMessage]:
        from mcap.records import Chunk, Message
        from mcap.stream_reader import StreamReader, breakup_chunk

        summary = self._summary
        if (
            self._memory is not None
            or summary is None
            or not summary.chunk_indexes
            or any(not ci.message_index_offsets for ci in summary.chunk_indexes)
        ):
            return super().first_messages(topics)
        wanted = {cid: ch for cid, ch in summary.channels.items() if ch.topic in set(topics)}
        out: dict[str, RawMessage] = {}
        for ci in sorted(summary.chunk_indexes, key=lambda c: (c.message_start_time, c.chunk_start_offset)):
            if not any(cid in ci.message_index_offsets and wanted[cid].topic not in out for cid in wanted):
                continue
            self._file.seek(ci.chunk_start_offset)
            chunk = next(iter(StreamReader(self._file, skip_magic=True, emit_chunks=True).records))
            if not isinstance(chunk, Chunk):
                raise SourceError(f"{self.path}: expected a chunk at byte offset {ci.chunk_start_offset}")
            for record in breakup_chunk(chunk):
                if isinstance(record, Message) and record.channel_id in wanted:
                    channel = wanted[record.channel_id]
                    if channel.topic not in out:
                        out[channel.topic] = RawMessage(
                            channel.topic,
                            record.log_time,
                            (summary.schemas.get(channel.schema_id), channel, record),
                            len(record.data),
                        )
            if len(out) == len({ch.topic for ch in wanted.values()}):
                break
        return out

    def fetch(self, topic: str, k: int, log_times: NDArray[np.int64]) -> RawMessage:
        if self._memory is not None:
            log_time, _, channel, schema, message = self._memory[topic][k]
            return RawMessage(topic, log_time, (schema, channel, message), len(message.data))
        return super().fetch(topic, k, log_times)

    def metadata(self) -> dict[str, dict[str, str]]:
        if self._memory is not None:
            return dict(self._mem_metadata)
        out = {}
        try:
            for record in self._reader.iter_metadata():
                out[record.name] = dict(record.metadata)
        except Exception as exc:  # metadata is optional; a damaged record must not stop reading
            logger.warning("%s: cannot read MCAP metadata (%s)", self.path, exc)
        return out

    def close(self) -> None:
        self._file.close()
