"""An indexed MCAP bag's topics, read a chunk at a time with the chunk's message index: a topic's messages are cut
out of the chunk with numpy, with no Python work per message.

rosbags reads an MCAP bag one message record at a time in Python (a few µs each), and a bag of a tool's sensors
holds 1.6 k messages per second: that alone holds a read near 200× real time on a quiet core, and a bag source that
reads the bag twice (judge it, then stream it) under 100×. The MCAP summary (the `mcap` package reads it) lists each
chunk and, per channel, where the chunk's message index lies: the log time and offset of each of that channel's
messages in the chunk. So a chunk is read (and decompressed) once, and every message of a topic is a row gathered at
those offsets; a topic whose messages are all one length (Imu, WrenchStamped, TwistStamped at a fixed frame_id)
comes out as one (m, L) uint8 array per chunk, ready for drivers.rosbag_cdr.decode_rows.

Messages come out in rosbags' own order: chunks by start time, each chunk's messages of a topic by log time (ties in
record order). That is rosbags' order only when chunks do not overlap in time, so `open_indexed` takes a file only
then; any other file (or one without a summary) is left to rosbags (None). A chunk without a message index is
walked record by record instead. The index is checked against the chunk (each offset must hold a message record of
the topic's channel, inside the chunk), and the messages it lists against the summary's statistics; a mismatch is
an McapIndexError naming the chunk.
"""

from __future__ import annotations

import struct
from collections.abc import Collection, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np

CHUNK_OPCODE = 0x06
MESSAGE_OPCODE = 0x05
MESSAGE_INDEX_OPCODE = 0x07
#: a Message record's bytes before its data: opcode 1, record length 8, channel_id 2, sequence 4, log_time 8,
#: publish_time 8 (the record length counts the 22 after itself, then the data)
MESSAGE_HEAD = 31
MESSAGE_FIELDS = 22
#: a MessageIndex record's bytes before its entries: opcode 1, record length 8, channel_id 2, entries' length 4
INDEX_HEAD = 15
#: a Chunk record's fixed bytes before its compression name: opcode 1, length 8, start 8, end 8, size 8, crc 4,
#: the name's length 4; after the name, the records' length 8
CHUNK_HEAD = 41


class McapIndexError(ValueError):
    """The MCAP's index and its chunks disagree: the file is damaged."""


@dataclass(frozen=True)
class TopicRows:
    """One chunk's messages of one topic, in rosbags' order: rows (m, L) uint8 when all have one length (a view into
    the chunk), else a list of m bytes."""

    topic: str
    rows: np.ndarray | list[bytes]

    def __len__(self) -> int:
        return len(self.rows)

    def messages(self) -> list[bytes]:
        """Each message's bytes."""
        return self.rows if isinstance(self.rows, list) else [row.tobytes() for row in self.rows]


@dataclass(frozen=True)
class _Chunk:
    start_ns: int
    end_ns: int
    offset: int  # of the Chunk record, from the start of the file
    compression: str
    index_offsets: dict[int, int]  # channel id → offset of its MessageIndex record


class IndexedMcap:
    """An MCAP file whose chunks carry message indexes and follow one another in time (`open_indexed`).

    channels: channel id → topic; chunks in time order; counts: channel id → its messages, as the summary's
    statistics say (None: no statistics)."""

    def __init__(
        self,
        path: Path,
        channels: dict[int, str],
        chunks: list[_Chunk],
        counts: dict[int, int] | None,
    ) -> None:
        self.path, self.channels, self.chunks, self.counts = path, channels, chunks, counts

    def read(self, topics: Collection[str], whole_chunks: bool = True) -> Iterator[TopicRows]:
        """The messages of `topics`, chunk by chunk. whole_chunks=False reads an uncompressed chunk's messages of
        these topics alone (seeking to each: for a sparse topic, a camera's, it skips the rest of the bag); a
        compressed chunk is read whole either way."""
        wanted = {cid: t for cid, t in self.channels.items() if t in topics}
        seen = dict.fromkeys(wanted, 0)
        with self.path.open("rb") as fh:
            for chunk in self.chunks:
                data = None
                if chunk.index_offsets:
                    entries = {cid: _index_entries(fh, chunk, cid) for cid in wanted if cid in chunk.index_offsets}
                else:  # a writer that kept no message index: the chunk's records, walked
                    data = _chunk_records(fh, chunk)
                    entries = _walk(data, chunk, wanted)
                entries = {cid: e for cid, e in entries.items() if e.shape[0]}
                if not entries:
                    continue
                for cid, e in entries.items():
                    seen[cid] += e.shape[0]
                if whole_chunks or chunk.compression or data is not None:
                    data = _chunk_records(fh, chunk) if data is None else data
                    yield from _gather(data, chunk, entries, wanted)
                else:
                    yield from _seek_each(fh, chunk, entries, wanted)
        if self.counts is not None:
            for cid, n in seen.items():
                if cid in self.counts and self.counts[cid] != n:
                    raise McapIndexError(
                        f"{self.path}: the message indexes list {n} message(s) of topic {wanted[cid]}, the "
                        f"statistics {self.counts[cid]}"
                    )


def open_indexed(path: Path) -> IndexedMcap | None:
    """The MCAP file at `path` ready for indexed reading, or None where rosbags must read it: no summary, no chunks, or
    chunks that overlap in time. A chunk without its message index (some writers keep none) is walked record by
    record (rosbags reads no message of such a chunk)."""
    from mcap.reader import SeekingReader

    with path.open("rb") as fh:
        summary = SeekingReader(fh).get_summary()
    if summary is None or not summary.chunk_indexes:
        return None
    chunks = sorted(
        (
            _Chunk(
                ci.message_start_time,
                ci.message_end_time,
                ci.chunk_start_offset,
                ci.compression,
                dict(ci.message_index_offsets),
            )
            for ci in summary.chunk_indexes
        ),
        key=lambda c: (c.start_ns, c.offset),
    )
    for a, b in zip(chunks[:-1], chunks[1:]):
        # rosbags merges the chunks' messages by log time, ties in file order: one chunk after another only when
        # they do not overlap (a shared boundary stamp is in order when the later chunk lies later in the file)
        if b.start_ns < a.end_ns or (b.start_ns == a.end_ns and b.offset < a.offset):
            return None
    channels = {cid: c.topic for cid, c in summary.channels.items()}
    stats = summary.statistics
    counts = dict(stats.channel_message_counts) if stats is not None and stats.channel_message_counts else None
    return IndexedMcap(path, channels, chunks, counts)


def _read(fh: BinaryIO, offset: int, size: int, what: str) -> bytes:
    fh.seek(offset)
    data = fh.read(size)
    if len(data) != size:
        raise McapIndexError(f"{what} at byte {offset}: {len(data)} of {size} bytes (the file ends)")
    return data


def _index_entries(fh: BinaryIO, chunk: _Chunk, cid: int) -> np.ndarray:
    """The chunk's message index of channel `cid`: (m, 2) int64 (log time ns, offset in the chunk's records),
    in log-time order, ties in record order."""
    where = chunk.index_offsets[cid]
    head = _read(fh, where, INDEX_HEAD, "message index")
    opcode, _, channel, size = struct.unpack("<BQHI", head)
    if opcode != MESSAGE_INDEX_OPCODE or channel != cid or size % 16:
        raise McapIndexError(f"message index at byte {where}: not channel {cid}'s index (opcode {opcode:#x})")
    entries = np.frombuffer(_read(fh, where + INDEX_HEAD, size, "message index"), dtype="<u8").reshape(-1, 2)
    entries = entries.astype(np.int64)
    order = np.lexsort((entries[:, 1], entries[:, 0]))
    return entries[order]


def _walk(data: np.ndarray, chunk: _Chunk, wanted: dict[int, str]) -> dict[int, np.ndarray]:
    """What a message index would hold for the wanted channels of a chunk that has none, found by walking its
    records: channel id → (m, 2) int64 (log time ns, offset), by log time, ties in record order."""
    raw = data.tobytes()
    found: dict[int, list[tuple[int, int]]] = {}
    at = 0
    while at < len(raw):
        if at + 9 > len(raw):
            raise McapIndexError(f"chunk at byte {chunk.offset}: a record runs past the chunk's end")
        opcode, length = struct.unpack_from("<BQ", raw, at)
        if opcode == MESSAGE_OPCODE and at + MESSAGE_HEAD <= len(raw):
            cid, _, log_time = struct.unpack_from("<HIQ", raw, at + 9)
            if cid in wanted:
                found.setdefault(cid, []).append((log_time, at))
        at += 9 + length
    out = {}
    for cid, pairs in found.items():
        e = np.array(pairs, dtype=np.int64)
        out[cid] = e[np.lexsort((e[:, 1], e[:, 0]))]
    return out


def _chunk_records(fh: BinaryIO, chunk: _Chunk) -> np.ndarray:
    """The chunk's records, decompressed and checked against the chunk's CRC, as uint8."""
    from mcap.data_stream import ReadDataStream
    from mcap.records import Chunk
    from mcap.stream_reader import get_chunk_data_stream

    fh.seek(chunk.offset)
    if fh.read(1) != bytes([CHUNK_OPCODE]):
        raise McapIndexError(f"chunk at byte {chunk.offset}: the index points at another record")
    fh.seek(chunk.offset + 9)
    record = Chunk.read(ReadDataStream(fh))
    stream, size = get_chunk_data_stream(record, validate_crc=True)
    return np.frombuffer(stream.read(size), dtype=np.uint8)


def _by_topic(entries: dict[int, np.ndarray], wanted: dict[int, str]) -> dict[str, np.ndarray]:
    """The chunk's index entries per topic: (m, 3) int64 (log time ns, offset, channel id), by log time, then record
    order (a topic may have several channels)."""
    parts: dict[str, list[np.ndarray]] = {}
    for cid, e in entries.items():
        parts.setdefault(wanted[cid], []).append(np.column_stack([e, np.full(e.shape[0], cid, dtype=np.int64)]))
    out = {}
    for topic, ps in parts.items():
        e = np.concatenate(ps) if len(ps) > 1 else ps[0]
        out[topic] = e[np.lexsort((e[:, 1], e[:, 0]))] if len(ps) > 1 else e
    return out


def _rows(data: np.ndarray, starts: np.ndarray, size: int) -> np.ndarray:
    """data[s : s + size] for each s in starts, stacked: (len(starts), size) uint8, copied a row at a time (a view of
    every window of `data`, indexed on its first axis only)."""
    if size == 0:
        return np.zeros((starts.shape[0], 0), dtype=np.uint8)
    return np.lib.stride_tricks.sliding_window_view(data, size)[starts]


def _gather(data: np.ndarray, chunk: _Chunk, entries: dict[int, np.ndarray], wanted: dict[int, str]):
    """Each topic's messages of one chunk, cut out of its records at the indexed offsets (checked first)."""
    for topic, e in _by_topic(entries, wanted).items():
        at, cids = e[:, 1], e[:, 2]
        where = f"chunk at byte {chunk.offset} (topic {topic})"
        if at.min() < 0 or at.max() + MESSAGE_HEAD > data.shape[0]:
            raise McapIndexError(f"{where}: a message offset lies outside the chunk's {data.shape[0]} bytes")
        head = _rows(data, at, MESSAGE_HEAD)
        lengths = np.ascontiguousarray(head[:, 1:9]).view("<u8")[:, 0].astype(np.int64)
        channel = np.ascontiguousarray(head[:, 9:11]).view("<u2")[:, 0]
        if np.any(head[:, 0] != MESSAGE_OPCODE) or np.any(channel != cids):
            raise McapIndexError(f"{where}: an indexed offset holds no message of the channel")
        sizes = lengths - MESSAGE_FIELDS
        starts = at + MESSAGE_HEAD
        if np.any(sizes < 0) or np.any(starts + sizes > data.shape[0]):
            raise McapIndexError(f"{where}: a message runs past the chunk's end")
        if np.all(sizes == sizes[0]):
            yield TopicRows(topic, _rows(data, starts, int(sizes[0])))
        else:
            raw = data.tobytes()
            yield TopicRows(topic, [raw[a : a + n] for a, n in zip(starts.tolist(), sizes.tolist())])


def _seek_each(fh: BinaryIO, chunk: _Chunk, entries: dict[int, np.ndarray], wanted: dict[int, str]):
    """Each topic's messages of one uncompressed chunk, read one at a time where the index says they lie."""
    base = chunk.offset + CHUNK_HEAD + len(chunk.compression.encode()) + 8
    for topic, e in _by_topic(entries, wanted).items():
        out = []
        for at, cid in zip(e[:, 1].tolist(), e[:, 2].tolist()):
            head = _read(fh, base + at, MESSAGE_HEAD, f"message of topic {topic}")
            opcode, length, channel = struct.unpack_from("<BQH", head)
            if opcode != MESSAGE_OPCODE or channel != cid or length < MESSAGE_FIELDS:
                raise McapIndexError(
                    f"chunk at byte {chunk.offset} (topic {topic}): an indexed offset holds no message of the channel"
                )
            out.append(_read(fh, base + at + MESSAGE_HEAD, length - MESSAGE_FIELDS, f"message of topic {topic}"))
        yield TopicRows(topic, out)
