"""A ROS 2 bag (sqlite3 `.db3` or MCAP, a bag folder or its storage file) as a sensor source.

Two passes over the bag, each streamed (the bag is never loaded whole): a .db3 (or a bag split over several files)
message by message with rosbags' reader; an MCAP file a chunk at a time through its message index
(drivers.rosbag_mcap), each topic's messages cut out of the chunk together, and in the second pass only the
camera's messages read:

1. `scan_bag` decodes the mapped numeric topics (Imu → accel, WrenchStamped → force, TwistStamped or Odometry →
   speed) into float arrays in canonical units stamped by header.stamp, and the camera topic's stamps, and judges
   them all: a bag that is truncated, lacks a mapped topic, carries an unknown message type, a wrench in another
   frame, accelerations in the wrong units or stamps that go back is refused here, with its topic and message
   named, before a single block is sent. What it keeps is the decoded samples (about 20 kB per second of bag at
   1 kHz IMU, 500 Hz wrench, 100 Hz twist), never the images.
2. `RosbagSource` resamples each channel onto a uniform grid at its own rate (the median interval of its stamps),
   cuts the stream into blocks (drivers.source.blocks_from_arrays) and reads the camera topic again, one image at a
   time, sending each frame in time order among the blocks.

Stream time is the robot's clock: header.stamp in seconds, so what the service estimates lines up with the bag.
A hole longer than max_gap_s in a topic's stamps ends its run: the stream goes on in a new segment (t0 where the
data resumes), without that channel while it is silent, as a replayed recording goes on without a channel that
ends early; the service estimates no window that lacks one.
"""

from __future__ import annotations

import io
import logging
import math
import sqlite3
from collections.abc import AsyncIterator, Generator, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from drivers.blocks import DEFAULT_MAX_BODY_BYTES, Frame, SampleBlock, check_frame_pixels, frame_bomb
from drivers.camera import encode_image, png_bytes, sniff_content_type
from drivers.rosbag_cdr import LAYOUT, decode_rows
from drivers.rosbag_mapping import (
    CHANNEL_TYPES,
    COMPRESSED_IMAGE,
    IMAGE,
    IMU,
    ODOMETRY,
    POSE,
    TWIST,
    WRENCH,
    TopicMap,
    load_topic_map,
)
from drivers.rosbag_mcap import IndexedMcap, open_indexed
from drivers.source import Item, blocks_from_arrays, check_positive, default_block_s, paced
from texture_library.channels import CANONICAL_UNITS, UNIT_SCALE, check_rate
from texture_library.recording import Channel, Recording

log = logging.getLogger(__name__)

SQLITE_MAGIC = b"SQLite format 3\x00"
MCAP_MAGIC = b"\x89MCAP0\r\n"
STANDARD_GRAVITY = 9.80665
#: an interval shorter than this between channel starts and ends carries no window: left out
MIN_SPAN_S = 0.05
#: a measured rate within this fraction of a whole number of Hz is taken as that number (1000.2 Hz → 1000 Hz)
RATE_SNAP = 0.01
#: a scanning speed whose median (while moving) lies outside these bounds, mm/s, is in other units than declared
SPEED_RANGE_MM_S = (1.0, 5000.0)
#: the gravity an IMU reports (REP 145), m/s², after the declared units are applied: a magnitude in LOOKS_LIKE_G
#: was published in g, one beyond GRAVITY_TOO_LARGE in m/s² declared as g
LOOKS_LIKE_G = (0.5, 2.0)
GRAVITY_TOO_LARGE = 5.0 * STANDARD_GRAVITY
#: a gravity magnitude below this is "removed by the driver": nothing to judge the units by
GRAVITY_PRESENT = 0.3
#: messages of one topic decoded together (drivers.rosbag_cdr): 4096 IMU messages are 1.3 MB
BATCH = 4096


class BagError(ValueError):
    """A bag refused: the message names the bag, and the topic or message at fault."""


# ---- opening --------------------------------------------------------------------------------------
def _storage_files(path: Path) -> list[Path]:
    if path.is_dir():
        return sorted(p for p in path.iterdir() if p.suffix in (".db3", ".mcap"))
    return [path]


def _check_storage_file(path: Path) -> None:
    """Refuse, by their first bytes, files rosbags would misread or crash on."""
    size = path.stat().st_size
    if size == 0:
        raise BagError(f"{path}: empty file (0 bytes), not a ROS 2 bag")
    with path.open("rb") as fh:
        head = fh.read(16)
    if path.suffix == ".db3" and head != SQLITE_MAGIC:
        raise BagError(f"{path}: not an SQLite database (a .db3 bag is one; its first bytes are {head[:8]!r})")
    if path.suffix == ".mcap" and not head.startswith(MCAP_MAGIC):
        raise BagError(f"{path}: not an MCAP file (its first bytes are {head[:8]!r})")
    if path.suffix not in (".db3", ".mcap"):
        raise BagError(f"{path}: not a ROS 2 bag (expected a bag folder, a .db3 or an .mcap file)")


def open_bag(path: str | Path) -> Any:
    """rosbags' Reader on the bag, opened; BagError says why a bag cannot be read."""
    from rosbags.rosbag2 import Reader
    from rosbags.rosbag2.errors import ReaderError

    path = Path(path)
    if not path.exists():
        raise BagError(f"{path}: no such bag (a bag folder, a .db3 or an .mcap file)")
    for f in _storage_files(path):
        _check_storage_file(f)
    try:
        reader = Reader(path)
        reader.open()
    except (ReaderError, sqlite3.DatabaseError, OSError, KeyError, ValueError) as exc:
        raise BagError(f"{path}: cannot open the bag ({type(exc).__name__}: {exc})") from None
    except Exception as exc:  # noqa: BLE001 - mcap's own errors have no common base; name them, never crash
        raise BagError(f"{path}: cannot open the bag ({type(exc).__name__}: {exc})") from None
    return reader


# ---- decoded topics -------------------------------------------------------------------------------
@dataclass
class TopicSamples:
    """One channel's topic, decoded: stamps_ns (n,) int64 header.stamp, increasing; values (n, k) float64 in the
    channel's canonical units (images: (n, 0)); rate_hz: the grid's rate, from the median stamp interval."""

    channel: str
    topic: str
    msgtype: str
    stamps_ns: np.ndarray
    values: np.ndarray
    rate_hz: float = 0.0
    dropped_repeats: int = 0


@dataclass
class BagScan:
    """What scan_bag found: the bag, its decoded channels (accel, force, speed) and the camera topic's stamps."""

    path: Path
    topic_map: TopicMap
    channels: dict[str, TopicSamples]
    frames: TopicSamples | None
    topics: dict[str, str] = field(default_factory=dict)  # every topic of the bag → its message type
    per_message_compression: bool = False  # rosbag2's compression mode "message": each message compressed alone

    @property
    def start_ns(self) -> int:
        return min(int(c.stamps_ns[0]) for c in self.channels.values())

    @property
    def end_ns(self) -> int:
        return max(int(c.stamps_ns[-1]) for c in self.channels.values())

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) * 1e-9


def _bag_topics(reader: Any) -> dict[str, str]:
    return {c.topic: c.msgtype for c in reader.connections}


def _pick_topic(channel: str, wanted: str | None, topics: dict[str, str], path: Path) -> str | None:
    """The topic `channel` reads: the one named (BagError when the bag lacks it or it carries another type), or the
    bag's one topic of a type it knows (None when there is none; BagError when there are several)."""
    types = CHANNEL_TYPES[channel]
    listing = ", ".join(f"{t} ({m})" for t, m in sorted(topics.items())) or "none"
    if wanted is not None:
        if wanted not in topics:
            raise BagError(f"{path}: {channel} topic {wanted} is not in the bag; its topics: {listing}")
        if topics[wanted] not in types:
            raise BagError(
                f"{path}: topic {wanted} carries {topics[wanted]}, a message type {channel} cannot read "
                f"(it reads {' or '.join(types)})"
            )
        return wanted
    found = sorted(t for t, m in topics.items() if m in types)
    if len(found) > 1:
        raise BagError(
            f"{path}: {len(found)} topics could feed {channel} ({', '.join(found)}); name one in the topic map "
            f"({channel}.topic)"
        )
    return found[0] if found else None


def _deserializer() -> Any:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE).deserialize_cdr


def _stamp_ns(msg: Any) -> int:
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


def _vector(v: Any) -> tuple[float, float, float]:
    return (v.x, v.y, v.z)


class _Decoder:
    """Decodes one mapped topic's messages as they stream past and judges each."""

    def __init__(self, channel: str, topic: str, msgtype: str, topic_map: TopicMap, path: Path) -> None:
        self.channel, self.topic, self.msgtype, self.map, self.path = channel, topic, msgtype, topic_map, path
        self.stamps: list[int] = []
        self.rows: list[tuple[float, ...]] = []
        self.frames: set[str] = set()
        self.batches: list[tuple[np.ndarray, np.ndarray]] = []  # (stamps, vectors) decoded a batch at a time
        self.pending: list[bytes] = []
        self.first_pending = 0  # message index of pending[0]
        self.count = 0  # the topic's messages read so far
        self._deserialize = _deserializer()

    def add_raw(self, raw: bytes) -> None:
        """The topic's next raw message: batched for decode_rows where the type allows."""
        index = self.count
        self.count += 1
        if self.msgtype not in LAYOUT:
            self._add_one(index, raw)
            return
        if not self.pending:
            self.first_pending = index
        self.pending.append(raw)
        if len(self.pending) >= BATCH:
            self._flush()

    def add_rows(self, rows: np.ndarray | list[bytes]) -> None:
        """The topic's next messages, as drivers.rosbag_mcap cuts them out of a chunk: (m, L) uint8, one message of
        one length per row, or a list of bytes."""
        if isinstance(rows, list) or self.msgtype not in LAYOUT:
            for raw in rows if isinstance(rows, list) else (row.tobytes() for row in rows):
                self.add_raw(raw)
            return
        if self.pending:
            self._flush()
        first = self.count
        self.count += rows.shape[0]
        self._decode(first, rows)

    def _flush(self) -> None:
        raws, first = self.pending, self.first_pending
        self.pending = []
        size = len(raws[0])
        if any(len(r) != size for r in raws):
            for k, raw in enumerate(raws):  # rosbags reads them, and names the message at fault
                self._add_one(first + k, raw)
            return
        self._decode(first, np.frombuffer(b"".join(raws), dtype=np.uint8).reshape(len(raws), size))

    def _decode(self, first: int, rows: np.ndarray) -> None:
        """Messages first, first + 1, … of the topic, one per row of rows (n, L) uint8: decoded together, or by
        rosbags one at a time where they are not uniform or their wrench frame is not the one wanted."""
        batch = decode_rows(rows, self.msgtype)
        if batch is None or (self.msgtype == WRENCH and self.map.force_frame not in (None, batch.frame_id)):
            for k in range(rows.shape[0]):  # rosbags reads it, and names the message at fault
                self._add_one(first + k, rows[k].tobytes())
            return
        if self.msgtype == WRENCH:
            self.frames.add(batch.frame_id)
        self._keep_rows()
        self.batches.append((batch.stamps_ns, batch.vectors))

    def _keep_rows(self) -> None:
        """Rows decoded one by one so far, as a batch (keeps the topic's messages in their order)."""
        if self.stamps:
            self.batches.append((np.asarray(self.stamps, dtype=np.int64), np.asarray(self.rows, dtype=np.float64)))
            self.stamps, self.rows = [], []

    def _add_one(self, index: int, raw: bytes) -> None:
        from rosbags.serde import SerdeError

        try:
            msg = self._deserialize(raw, self.msgtype)
        except (SerdeError, ValueError, IndexError, KeyError, UnicodeDecodeError, AssertionError) as exc:
            where = f"{self.path}: topic {self.topic} message {index}"
            raise BagError(f"{where}: not a valid {self.msgtype} ({exc})") from None
        self.add(index, msg)

    def add(self, index: int, msg: Any) -> None:
        self.stamps.append(_stamp_ns(msg))
        t = self.msgtype
        if t == IMU:
            self.rows.append(_vector(msg.linear_acceleration))
        elif t == WRENCH:
            frame = msg.header.frame_id
            want = self.map.force_frame
            if want is not None and frame != want:
                raise BagError(
                    f"{self.path}: topic {self.topic} message {index}: the wrench is in frame {frame!r}, the topic "
                    f"map says {want!r} (force.frame); its normal axis would be another"
                )
            self.frames.add(frame)
            self.rows.append(_vector(msg.wrench.force))
        elif t in (TWIST, ODOMETRY):
            lin = msg.twist.linear if t == TWIST else msg.twist.twist.linear
            self.rows.append(_vector(lin))
        elif t == POSE:
            self.rows.append(_vector(msg.pose.position))
        elif t == COMPRESSED_IMAGE:
            fmt = str(msg.format).lower()
            if "jpeg" not in fmt and "jpg" not in fmt and "png" not in fmt:
                raise BagError(
                    f"{self.path}: topic {self.topic} message {index}: CompressedImage format {msg.format!r} is "
                    "neither jpeg nor png"
                )
        elif t == IMAGE:
            _image_array(msg, self.topic)  # judges the encoding and size now, not mid-stream

    def finish(self) -> TopicSamples:
        where = f"{self.path}: topic {self.topic} ({self.msgtype})"
        if self.pending:
            self._flush()
        if self.channel == "frames":
            self.rows = [() for _ in self.stamps]
        self._keep_rows()
        if not self.batches:
            raise BagError(f"{where}: no messages")
        if len(self.frames) > 1:
            raise BagError(
                f"{where}: the wrench comes in frames {sorted(self.frames)}; name the one whose normal axis the "
                "topic map gives (force.frame)"
            )
        stamps = np.concatenate([b[0] for b in self.batches])
        values = np.concatenate([b[1].reshape(b[0].shape[0], -1) for b in self.batches])
        stamps, values, repeats = _ordered(stamps, values, self.map.reorder_s, where)
        out = TopicSamples(self.channel, self.topic, self.msgtype, stamps, values, dropped_repeats=repeats)
        if self.channel == "frames":
            return out
        if stamps.shape[0] < 2:
            raise BagError(f"{where}: {stamps.shape[0]} message(s); a channel needs at least 2 to have a rate")
        if self.msgtype == POSE:
            values = _velocity(stamps, values, self.map.max_gap_s)
        out.values = self._canonical(values, where)
        out.rate_hz = _grid_rate(stamps, where)
        return out

    def _canonical(self, values: np.ndarray, where: str) -> np.ndarray:
        m = self.map
        if self.channel == "accel":
            accel = values * UNIT_SCALE["accel"][m.accel_units]
            _check_gravity(accel, m.accel_units, where)
            return accel
        if self.channel == "force":
            n = values[:, m.normal_axis] * m.normal_sign
            tangential = [values[:, a] for a in range(3) if a != m.normal_axis]
            return np.column_stack([*tangential, n]) * UNIT_SCALE["force"][m.force_units]
        speed = np.linalg.norm(values[:, list(m.speed_axes)], axis=1) * UNIT_SCALE["speed"][m.speed_units]
        _check_speed(speed, m.speed_units, where)
        return speed[:, None]


def _ordered(stamps: np.ndarray, values: np.ndarray, reorder_s: float, where: str):
    """Stamps put in order (a step back of at most reorder_s is transport reordering), repeated stamps dropped;
    BagError for a step further back: the topic's clock went back, and its samples have no one timeline."""
    step = np.diff(stamps)
    back = np.flatnonzero(step < 0)
    if back.size:
        worst = int(back[np.argmin(step[back])])
        if -step[worst] > reorder_s * 1e9:
            raise BagError(
                f"{where}: header.stamp goes back {-step[worst] * 1e-9:.3f} s at message {worst + 1} "
                f"({stamps[worst] * 1e-9:.6f} s → {stamps[worst + 1] * 1e-9:.6f} s); more than the "
                f"{reorder_s:g} s of reordering the topic map allows (reorder_s)"
            )
        order = np.argsort(stamps, kind="stable")
        stamps, values = stamps[order], values[order]
    keep = np.concatenate([[True], np.diff(stamps) > 0])
    repeats = int(keep.size - np.count_nonzero(keep))
    if repeats:
        log.warning("%s: %d message(s) repeat the stamp of the one before; dropped", where, repeats)
    return stamps[keep], values[keep], repeats


def _velocity(stamps_ns: np.ndarray, positions: np.ndarray, max_gap_s: float) -> np.ndarray:
    """The velocity of a tool's positions (n, 3) at stamps_ns (n,) increasing: (n, 3), position units per second;
    central differences inside each run of stamps without a hole longer than max_gap_s, one-sided at its ends (a
    hole's displacement is no velocity), zero in a run of one position."""
    t = (stamps_ns - stamps_ns[0]).astype(np.float64) * 1e-9
    out = np.zeros_like(positions)
    edges = [0, *(np.flatnonzero(np.diff(stamps_ns) > max_gap_s * 1e9) + 1).tolist(), stamps_ns.shape[0]]
    for a, b in zip(edges[:-1], edges[1:]):
        if b - a >= 2:
            out[a:b] = np.gradient(positions[a:b], t[a:b], axis=0, edge_order=1)
    return out


def _grid_rate(stamps: np.ndarray, where: str) -> float:
    """The rate of a topic's grid, Hz: 1 / median stamp interval, snapped to a whole number of Hz when that close."""
    rate = 1e9 / float(np.median(np.diff(stamps)))
    whole = round(rate)
    if whole and abs(rate - whole) <= RATE_SNAP * whole:
        rate = float(whole)
    try:
        return check_rate(rate, where)
    except ValueError as exc:
        raise BagError(str(exc)) from None


def _check_gravity(accel: np.ndarray, units: str, where: str) -> None:
    """Order-of-magnitude check of the declared units by gravity, which an IMU's linear_acceleration carries
    (REP 145): the median over 1000-sample stretches of the norm of their mean. Removed gravity: nothing to judge."""
    n = accel.shape[0]
    chunk = min(1000, n)
    means = accel[: n - n % chunk].reshape(-1, chunk, 3).mean(axis=1)
    g = float(np.median(np.linalg.norm(means, axis=1)))
    if LOOKS_LIKE_G[0] <= g <= LOOKS_LIKE_G[1]:
        raise BagError(
            f"{where}: gravity reads {g:.2f} m/s² with units {units!r}; these accelerations look like g "
            "(set accel.units: g in the topic map)"
        )
    if g > GRAVITY_TOO_LARGE:
        raise BagError(
            f"{where}: gravity reads {g:.1f} m/s² with units {units!r}; these accelerations look like m/s² "
            "(set accel.units: m/s^2 in the topic map)"
        )
    if g < GRAVITY_PRESENT:
        log.info("%s: gravity removed by the driver; accel units %r taken as declared", where, units)


def _check_speed(speed_mm_s: np.ndarray, units: str, where: str) -> None:
    moving = speed_mm_s[speed_mm_s > 1e-6]
    if moving.size == 0:
        return
    median = float(np.median(moving))
    if median < SPEED_RANGE_MM_S[0]:
        raise BagError(
            f"{where}: median scanning speed {median:.3g} mm/s with units {units!r}; a stroke is 10–500 mm/s, these "
            "speeds look like m/s (set speed.units: m/s in the topic map)"
        )
    if median > SPEED_RANGE_MM_S[1]:
        raise BagError(
            f"{where}: median scanning speed {median:.3g} mm/s with units {units!r}; a stroke is 10–500 mm/s, these "
            "speeds look like mm/s (set speed.units: mm/s in the topic map)"
        )


def _image_array(msg: Any, topic: str) -> np.ndarray:
    """A sensor_msgs/Image as a uint8 (h, w) or (h, w, 3) RGB array; BagError for an encoding it cannot take."""
    enc = str(msg.encoding).lower()
    channels = {"mono8": 1, "8uc1": 1, "rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "8uc3": 3}.get(enc)
    if channels is None:
        raise BagError(f"topic {topic}: Image encoding {msg.encoding!r}; readable: mono8, rgb8, bgr8, rgba8, bgra8")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.asarray(msg.data, dtype=np.uint8)
    if step < w * channels or data.size < h * step:
        raise BagError(f"topic {topic}: Image of {w}×{h} {enc} holds {data.size} bytes, step {step}")
    arr = data[: h * step].reshape(h, step)[:, : w * channels].reshape(h, w, channels)
    if enc.startswith("bgr"):
        arr = arr[:, :, [2, 1, 0]]
    return arr[:, :, 0] if channels == 1 else arr[:, :, :3]


def indexed_mcap(path: Path, reader: Any) -> IndexedMcap | None:
    """The bag's MCAP file read through its index (drivers.rosbag_mcap), or None where rosbags reads the bag: a .db3,
    a bag split over several files, messages compressed one by one, an MCAP without message indexes."""
    files = _storage_files(path)
    if len(files) != 1 or files[0].suffix != ".mcap" or reader.compression_mode == "message":
        return None
    return open_indexed(files[0])


def scan_bag(path: str | Path, topic_map: TopicMap | None = None) -> BagScan:
    """Read and judge the bag's mapped topics (pass 1, see the module's docstring); BagError names what is wrong."""
    path = Path(path)
    topic_map = topic_map or load_topic_map()
    reader = open_bag(path)
    try:
        topics = _bag_topics(reader)
        per_message = reader.compression_mode == "message"
        chosen = {ch: _pick_topic(ch, topic_map.topic(ch), topics, path) for ch in CHANNEL_TYPES}
        if chosen["accel"] is None:
            listing = ", ".join(f"{t} ({m})" for t, m in sorted(topics.items())) or "no topics"
            raise BagError(f"{path}: no {IMU} topic to read acceleration from (accel.topic); the bag holds {listing}")
        decoders = {t: _Decoder(ch, t, topics[t], topic_map, path) for ch, t in chosen.items() if t is not None}
        try:
            indexed = indexed_mcap(path, reader)
            if indexed is not None:
                for piece in indexed.read(decoders):
                    decoders[piece.topic].add_rows(piece.rows)
            else:
                wanted = [c for c in reader.connections if c.topic in decoders]
                for conn, _, raw in reader.messages(connections=wanted):
                    decoders[conn.topic].add_raw(raw)
        except BagError:
            raise
        except Exception as exc:  # noqa: BLE001 - sqlite, mcap, zstd: a truncated bag surfaces in any of them
            where = ", ".join(f"{t} after {d.count} message(s)" for t, d in decoders.items())
            raise BagError(
                f"{path}: the bag is truncated or damaged ({type(exc).__name__}: {exc}); read {where}"
            ) from None
    finally:
        reader.close()
    decoded = {d.channel: d.finish() for d in decoders.values()}
    frames = decoded.pop("frames", None)
    return BagScan(path, topic_map, decoded, frames, topics, per_message)


# ---- resampling onto the stream contract ----------------------------------------------------------
@dataclass(frozen=True)
class Span:
    """A stretch of the stream in which the same channels run without a hole: [start_ns, stop_ns)."""

    start_ns: int
    stop_ns: int
    channels: tuple[str, ...]


def _runs(samples: TopicSamples, max_gap_s: float) -> list[tuple[int, int, int, int]]:
    """(first index, last index + 1, start ns, stop ns) of each run of a channel's stamps without a hole longer
    than max_gap_s; a run lasts one sample period past its last stamp."""
    s = samples.stamps_ns
    breaks = np.flatnonzero(np.diff(s) > max_gap_s * 1e9) + 1
    edges = [0, *breaks.tolist(), s.shape[0]]
    period = int(round(1e9 / samples.rate_hz))
    return [(a, b, int(s[a]), int(s[b - 1]) + period) for a, b in zip(edges[:-1], edges[1:])]


def spans(scan: BagScan) -> list[Span]:
    """The stream's spans: every run start and end of every channel cuts it; spans shorter than MIN_SPAN_S (the few
    milliseconds between one topic's first message and another's) are left out."""
    runs = {ch: _runs(s, scan.topic_map.max_gap_s) for ch, s in scan.channels.items()}
    cuts = sorted({t for rs in runs.values() for _, _, a, b in rs for t in (a, b)})
    out: list[Span] = []
    for a, b in zip(cuts[:-1], cuts[1:]):
        active = tuple(ch for ch, rs in runs.items() if any(ra <= a and b <= rb for _, _, ra, rb in rs))
        if not active or (b - a) < MIN_SPAN_S * 1e9:
            continue
        if out and out[-1].channels == active and out[-1].stop_ns == a:
            out[-1] = Span(out[-1].start_ns, b, active)
        else:
            out.append(Span(a, b, active))
    return out


def resample(samples: TopicSamples, start_ns: int, stop_ns: int) -> np.ndarray:
    """The channel on its uniform grid start + i / rate_hz within [start, stop): (n, k) float64, linear
    interpolation between header stamps (exact where a stamp lies on the grid)."""
    n = int(math.floor((stop_ns - start_ns) * 1e-9 * samples.rate_hz + 1e-6))
    grid = np.arange(n, dtype=np.float64) / samples.rate_hz
    t = (samples.stamps_ns - start_ns).astype(np.float64) * 1e-9
    lo = max(0, int(np.searchsorted(samples.stamps_ns, start_ns)) - 1)
    hi = min(t.shape[0], int(np.searchsorted(samples.stamps_ns, stop_ns)) + 1)
    cols = [np.interp(grid, t[lo:hi], samples.values[lo:hi, k]) for k in range(samples.values.shape[1])]
    return np.column_stack(cols)


def bag_blocks(scan: BagScan, block_s: float | None = None, seq0: int = 0) -> Iterator[SampleBlock]:
    """The scanned bag as consecutive blocks, span after span, in canonical units; t0 on the robot's clock (s)."""
    seq = seq0
    rates = [c.rate_hz for c in scan.channels.values()]
    block = block_s if block_s is not None else default_block_s(rates)
    for span in spans(scan):
        arrays = {}
        for ch in span.channels:
            data = resample(scan.channels[ch], span.start_ns, span.stop_ns)
            if data.shape[0]:
                arrays[ch] = (
                    data[:, 0] if data.shape[1] == 1 else data,
                    scan.channels[ch].rate_hz,
                    CANONICAL_UNITS[ch],
                )
        if not arrays:
            continue
        for b in blocks_from_arrays(arrays, block, t0=span.start_ns * 1e-9, seq0=seq):
            yield b
            seq = b.seq + 1


def _compressed_frame(data: bytes, label: str) -> tuple[bytes, str]:
    """A CompressedImage's bytes ready to send: PNG or JPEG as they are, judged by their header alone (the robot
    client decodes each frame for its scene-change check and the service to embed it, so a full decode here would
    be a third, and costs more than the rest of the bag's reading); other formats re-encoded by encode_image."""
    from PIL import Image, UnidentifiedImageError

    ctype = sniff_content_type(data)
    if ctype is None:
        return encode_image(data, label)
    try:
        with Image.open(io.BytesIO(data)) as img:
            check_frame_pixels(*img.size, label)
    except Image.DecompressionBombError as exc:
        raise frame_bomb(exc, label) from None
    except (UnidentifiedImageError, OSError, SyntaxError) as exc:
        raise ValueError(f"{label}: not a readable image ({exc})") from None
    if len(data) > DEFAULT_MAX_BODY_BYTES:
        raise ValueError(
            f"{label}: {len(data) / 2**20:.1f} MiB; the service takes {DEFAULT_MAX_BODY_BYTES} bytes at most"
        )
    return data, ctype


def bag_frames(scan: BagScan) -> Generator[Frame, None, None]:
    """The camera topic's images, read again one at a time, as Frames at their header.stamp (s); an image that
    will not encode is skipped with a warning (a glitch in the camera never ends the stream)."""
    if scan.frames is None:
        return
    deserialize = _deserializer()
    topic, msgtype = scan.frames.topic, scan.frames.msgtype
    raws = _topic_messages(scan, topic)
    try:
        for index, raw in enumerate(raws):
            msg = deserialize(raw, msgtype)
            label = f"{scan.path}: topic {topic} message {index}"
            try:
                if msgtype == COMPRESSED_IMAGE:
                    data, ctype = _compressed_frame(bytes(msg.data), label)
                else:
                    data, ctype = png_bytes(_image_array(msg, topic)), "image/png"
            except ValueError as exc:
                log.warning("%s: image skipped: %s", label, exc)
                continue
            yield Frame(_stamp_ns(msg) * 1e-9, data, ctype, {"topic": topic})
    finally:
        raws.close()


def _topic_messages(scan: BagScan, topic: str) -> Generator[bytes, None, None]:
    """One topic's raw messages, in the bag's order, read again for the stream: an MCAP's through its index, a
    single .db3's by one query (rosbags' reader would first count every topic's messages again), any other bag's
    with rosbags' reader."""
    files = _storage_files(scan.path)
    if len(files) == 1 and files[0].suffix == ".db3" and not scan.per_message_compression:
        db = sqlite3.connect(files[0].resolve().as_uri() + "?mode=ro", uri=True)
        try:
            query = (
                "SELECT messages.data FROM messages JOIN topics ON messages.topic_id = topics.id "
                "WHERE topics.name = ? ORDER BY messages.timestamp"
            )
            for (raw,) in db.execute(query, (topic,)):
                yield raw
        finally:
            db.close()
        return
    reader = open_bag(scan.path)
    try:
        indexed = indexed_mcap(scan.path, reader)
        if indexed is not None:  # the topic's messages alone, not the whole bag again
            for piece in indexed.read([topic], whole_chunks=False):
                yield from piece.messages()
        else:
            for _, _, raw in reader.messages(connections=[c for c in reader.connections if c.topic == topic]):
                yield raw
    finally:
        reader.close()


def _merged(blocks: Iterator[SampleBlock], frames: Iterator[Frame], start_s: float, stop_s: float) -> Iterator[Item]:
    """Blocks and frames in time order: a frame goes out before the first block that starts after it. Frames
    outside the stream's span are left out."""
    pending = next(frames, None)
    for block in blocks:
        while pending is not None and pending.t <= block.t0:
            if pending.t >= start_s - 1.0:
                yield pending
            pending = next(frames, None)
        yield block
    while pending is not None and pending.t <= stop_s:
        yield pending
        pending = next(frames, None)


class RosbagSource:
    """A ROS 2 bag streamed as a robot would have streamed it (see the module's docstring).

    path: a bag folder, .db3 or .mcap; topic_map: which topics feed which channels (None: the defaults,
    drivers/rosbag_topics.yaml). The bag is judged whole when the source is made (BagError, a ValueError, naming
    the topic or message at fault), so a bad bag sends nothing. realtime paces it at `speed` × its own pace.
    """

    def __init__(
        self,
        path: str | Path,
        topic_map: TopicMap | None = None,
        block_s: float | None = None,
        realtime: bool = True,
        speed: float = 1.0,
        with_frames: bool = True,
        name: str | None = None,
    ) -> None:
        if block_s is not None:
            check_positive("block_s", block_s)
        check_positive("speed", speed, "finite factor")
        self.scan = scan_bag(path, topic_map)
        if not spans(self.scan):
            raise BagError(f"{path}: no stretch of {MIN_SPAN_S:g} s or more in which the mapped topics run")
        for ch in ("force", "speed"):
            if ch not in self.scan.channels:
                log.warning("%s: no %s topic; the stream carries no %s", path, ch, ch)
        self.block_s = block_s
        self.realtime = realtime
        self.speed = speed
        self.with_frames = with_frames
        self.name = name or f"rosbag:{Path(path).name}"
        self._closed = False

    def _items(self) -> Iterator[Item]:
        start, stop = self.scan.start_ns * 1e-9, self.scan.end_ns * 1e-9
        frames = bag_frames(self.scan) if self.with_frames else iter(())
        for item in _merged(bag_blocks(self.scan, self.block_s), frames, start, stop):
            if self._closed:
                return
            yield item

    def __aiter__(self) -> AsyncIterator[Item]:
        return paced(self._items(), self.realtime, self.speed).__aiter__()

    async def aclose(self) -> None:
        self._closed = True


# ---- a bag as dataset recordings --------------------------------------------------------------------
def bag_recordings(scan: BagScan, min_s: float = 1.0) -> list[Recording]:
    """The scanned bag's stretches in which accel, force and speed all run, each at least min_s long, as Recordings
    (each channel on its own uniform grid, canonical units); BagError when it has none."""
    out = []
    for span in spans(scan):
        if set(span.channels) != {"accel", "force", "speed"} or (span.stop_ns - span.start_ns) * 1e-9 < min_s:
            continue
        chans = {}
        for ch in span.channels:
            data = resample(scan.channels[ch], span.start_ns, span.stop_ns)
            chans[ch] = Channel(data[:, 0] if data.shape[1] == 1 else data, scan.channels[ch].rate_hz)
        out.append(Recording(**chans))
    if not out:
        raise BagError(f"{scan.path}: no stretch of {min_s:g} s or more in which accel, force and speed all run")
    return out


def bag_first_image(scan: BagScan) -> Frame | None:
    """The first image of the scanned bag's camera topic that encodes (None: no camera topic, or none encodes)."""
    frames = bag_frames(scan)
    try:
        return next(frames, None)
    finally:
        frames.close()
