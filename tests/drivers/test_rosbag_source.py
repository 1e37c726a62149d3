"""RosbagSource: a simulated stroke written as a ROS 2 bag (.db3 and MCAP) with rosbags comes back as the same
blocks and the same window features as the simulated source gives directly; every bad bag is refused before a
block is sent, naming its topic or message."""

from __future__ import annotations

import asyncio
import sqlite3
from pathlib import Path

import numpy as np
import pytest

from drivers.blocks import Frame, SampleBlock
from drivers.camera import png_bytes
from drivers.rosbag_mapping import IMU as IMU_TYPE
from drivers.rosbag_mapping import WRENCH as WRENCH_TYPE
from drivers.rosbag_mapping import TopicMap, load_topic_map, topic_map_from_dict
from drivers.rosbag_source import BagError, RosbagSource, scan_bag
from drivers.rosbag_writer import DEFAULT_START_NS, TOPICS, storage_file, stroke_messages, write_bag
from drivers.simulated import SimulatedSource
from models.tactile.config import TactileConfig
from models.tactile.features import window_features
from models.tactile.preprocess import TactilePreprocessor
from texture_library.procedural import make_world
from texture_library.recording import make_channel

SECONDS = 3.0
#: both storages: sqlite3 is read by rosbags, MCAP through its index (drivers.rosbag_mcap)
STORAGES = ("sqlite3", "mcap")
START_S = DEFAULT_START_NS * 1e-9
#: the bag's samples are float64 in CDR, the wire's float32: what survives is float32 rounding (relative 6e-8) and
#: the interpolation weight of a nanosecond-rounded stamp
SAMPLE_RTOL = 1e-6
#: features of the bag's stream against the simulated one's: accel is the same 1 kHz signal; force and speed reach
#: the service at 500 Hz and 100 Hz and are resampled to 1 kHz there, which moves their statistics a little
FEATURE_RTOL, FEATURE_ATOL = 0.02, 0.02


@pytest.fixture(scope="module")
def stroke():
    """SECONDS of a simulated robot stroking a procedural texture: (blocks and frames it sends, its image)."""
    texture = make_world(1, seed=11)[0]
    image = png_bytes(texture.image)
    source = SimulatedSource(texture.model, image, seed=3, realtime=False, duration_s=SECONDS)
    items = asyncio.run(_take(source))
    return items, image


@pytest.fixture(scope="module", params=["sqlite3", "mcap"])
def bag(request, stroke, tmp_path_factory) -> Path:
    items, image = stroke
    blocks = [i for i in items if isinstance(i, SampleBlock)]
    accel, force, speed = (_concat(blocks, k) for k in ("accel", "force", "speed"))
    root = tmp_path_factory.mktemp(f"bag-{request.param}")
    return write_bag(root / "stroke", stroke_messages(accel, force, speed, 1000.0, image), request.param)


async def _take(source) -> list:
    return [item async for item in source]


def _concat(blocks: list[SampleBlock], kind: str) -> np.ndarray:
    return np.concatenate([b.channels[kind].data for b in blocks if kind in b.channels])


def _features(blocks: list[SampleBlock]) -> np.ndarray:
    """The served tactile features of every window of a stream (the service's streaming preprocessor)."""
    config = TactileConfig()
    pre = TactilePreprocessor(config, max_buffer_s=None)
    for b in blocks:
        pre.push(**{k: make_channel(k, c.data, c.rate_hz, c.units) for k, c in b.channels.items()})
    pre.flush()
    batch = pre.take()
    return window_features(batch.accel, batch.speed, batch.force, config)


def test_the_bag_streams_the_simulated_stroke_back(bag, stroke):
    items, image = stroke
    sim = [i for i in items if isinstance(i, SampleBlock)]
    got = asyncio.run(_take(RosbagSource(bag, realtime=False)))
    blocks = [i for i in got if isinstance(i, SampleBlock)]
    frames = [i for i in got if isinstance(i, Frame)]
    assert [b.seq for b in blocks] == list(range(len(blocks)))
    assert blocks[0].t0 == pytest.approx(START_S), "stream time is the robot's clock: header.stamp in seconds"
    assert {(k, c.rate_hz, c.units) for b in blocks for k, c in b.channels.items()} == {
        ("accel", 1000.0, "m/s^2"),
        ("force", 500.0, "N"),
        ("speed", 100.0, "mm/s"),
    }
    accel, force, speed = (_concat(sim, k) for k in ("accel", "force", "speed"))
    n = int(SECONDS * 1000)
    np.testing.assert_allclose(_concat(blocks, "accel"), accel[:n], rtol=SAMPLE_RTOL, atol=1e-5)
    np.testing.assert_allclose(_concat(blocks, "force"), force[:n:2], rtol=SAMPLE_RTOL, atol=1e-5)
    np.testing.assert_allclose(_concat(blocks, "speed"), speed[:n:10], rtol=SAMPLE_RTOL, atol=1e-4)
    # 5 Hz of the same picture, each at its stamp, in time order among the blocks
    assert [f.t - START_S for f in frames] == pytest.approx([0.2 * k for k in range(int(SECONDS * 5))], abs=1e-6)
    assert all(f.image == image and f.content_type == "image/png" for f in frames)
    order = [i.t if isinstance(i, Frame) else i.t0 for i in got]
    assert order == sorted(order)


def test_its_windows_give_the_simulated_strokes_features(bag, stroke):
    items, _ = stroke
    sim = _features([i for i in items if isinstance(i, SampleBlock)])
    got = _features([i for i in asyncio.run(_take(RosbagSource(bag, realtime=False))) if isinstance(i, SampleBlock)])
    assert got.shape == sim.shape and got.shape[0] >= 4
    np.testing.assert_allclose(got, sim, rtol=FEATURE_RTOL, atol=FEATURE_ATOL)


def test_the_default_topic_map_is_the_shipped_yaml():
    assert load_topic_map() == TopicMap()
    with pytest.raises(ValueError, match=r"force.normal must be one of x, y, z"):
        topic_map_from_dict({"force": {"normal": "w"}})
    with pytest.raises(ValueError, match=r"accel.units must be one of"):
        topic_map_from_dict({"accel": {"units": "ft/s^2"}})
    with pytest.raises(ValueError, match=r"speed: unknown key\(s\) \['axis'\]"):
        topic_map_from_dict({"speed": {"axis": "x"}})


def test_a_named_frame_normal_axis_and_units_are_applied(stroke, tmp_path):
    """The wrench pressing along -y of its frame, the IMU publishing g, the twist mm/s: the map says so, and the
    channels come out as the simulated ones."""
    items, _ = stroke
    sim = [i for i in items if isinstance(i, SampleBlock)]
    accel, force, speed = (_concat(sim, k)[:1000] for k in ("accel", "force", "speed"))
    frame_force = np.column_stack([force[:, 0], -force[:, 2], force[:, 1]])  # normal along -y; tangential x, z

    def messages():
        for topic, stamp, msg in stroke_messages(accel / 9.80665, frame_force, speed, 1000.0):
            if topic == TOPICS["speed"]:
                msg.twist.linear.x *= 1000.0  # a driver publishing mm/s
            yield topic, stamp, msg

    bag = write_bag(tmp_path / "bag", messages())
    topic_map = topic_map_from_dict(
        {
            "accel": {"units": "g"},
            "force": {"frame": "tool0_ft", "normal": "-y"},
            "speed": {"units": "mm/s"},
        }
    )
    scan = scan_bag(bag, topic_map)
    np.testing.assert_allclose(scan.channels["accel"].values, accel, rtol=1e-6)
    np.testing.assert_allclose(
        scan.channels["force"].values, np.column_stack([force[:, 0], force[:, 1], force[:, 2]])[::2]
    )
    np.testing.assert_allclose(scan.channels["speed"].values[:, 0], speed[::10], rtol=1e-6)


# ---- a hole, a stopped topic, reordering --------------------------------------------------------------
def _stamped(stroke, drop=lambda topic, stamp: False, shift=lambda topic, stamp: stamp, seconds: float = 2.0):
    items, _ = stroke
    sim = [i for i in items if isinstance(i, SampleBlock)]
    n = int(seconds * 1000)
    accel, force, speed = (_concat(sim, k)[:n] for k in ("accel", "force", "speed"))
    for topic, stamp, msg in stroke_messages(accel, force, speed, 1000.0):
        if drop(topic, stamp):
            continue
        new = shift(topic, stamp)
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(new, 1_000_000_000)
        yield topic, stamp, msg


def test_a_hole_starts_a_new_segment_and_a_stopped_topic_leaves_its_channel_out(stroke, tmp_path):
    """All topics silent for 0.3 s at 0.8 s; the twist stops at 1.5 s: blocks resume at 1.1 s, and after 1.5 s they
    go on without speed (the service estimates no window there, as for a replayed recording's short channel)."""

    def drop(topic, stamp):
        t = (stamp - DEFAULT_START_NS) * 1e-9
        return 0.8 <= t < 1.1 or (topic == TOPICS["speed"] and t >= 1.5)

    bag = write_bag(tmp_path / "bag", _stamped(stroke, drop))
    blocks = [i for i in asyncio.run(_take(RosbagSource(bag, realtime=False))) if isinstance(i, SampleBlock)]
    t0 = np.array([b.t0 - START_S for b in blocks])
    assert not np.any((t0 > 0.8 - 1e-6) & (t0 < 1.1 - 1e-6)), "nothing is invented inside the hole"
    assert np.isclose(t0, 1.1).any(), "the stream resumes where the data does"
    assert all(("speed" in b.channels) == (b.t0 - START_S < 1.5 - 1e-6) for b in blocks)
    assert _concat(blocks, "accel").shape[0] == 2000 - 300


def test_stamps_a_little_out_of_order_are_put_back_in_order(stroke, tmp_path):
    swap = {DEFAULT_START_NS + 100_000_000: 1_000_000, DEFAULT_START_NS + 101_000_000: -1_000_000}

    def shift(topic, stamp):  # two IMU messages swapped: the transport delivered them out of order
        return stamp + swap.get(stamp, 0) if topic == TOPICS["accel"] else stamp

    scan = scan_bag(write_bag(tmp_path / "bag", _stamped(stroke, shift=shift)))
    assert np.all(np.diff(scan.channels["accel"].stamps_ns) == 1_000_000)


# ---- bad bags: each refused before a block is sent, naming its topic or message --------------------------
def _refused(path, match: str, topic_map: TopicMap | None = None) -> None:
    with pytest.raises(BagError, match=match):
        RosbagSource(path, topic_map, realtime=False)


def test_a_truncated_bag(stroke, tmp_path):
    for storage in ("sqlite3", "mcap"):
        bag = write_bag(tmp_path / storage, _stamped(stroke), storage)
        f = storage_file(bag)
        data = f.read_bytes()
        f.write_bytes(data[: len(data) * 2 // 3])
        _refused(bag, "truncated or damaged|cannot open the bag")


@pytest.mark.parametrize("storage", STORAGES)
def test_a_bag_without_the_mapped_topics(stroke, tmp_path, storage):
    bag = write_bag(tmp_path / "bag", ((t, s, m) for t, s, m in _stamped(stroke) if t != TOPICS["accel"]), storage)
    _refused(bag, r"no sensor_msgs/msg/Imu topic to read acceleration from .*/wrist/wrench")
    _refused(
        bag,
        r"force topic /ft is not in the bag; its topics: /tool/twist",
        topic_map_from_dict({"force": {"topic": "/ft"}}),
    )


@pytest.mark.parametrize("storage", STORAGES)
def test_an_unknown_message_type(stroke, tmp_path, storage):
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    Temperature = ts.types["sensor_msgs/msg/Temperature"]

    def messages():
        for topic, stamp, msg in _stamped(stroke):
            if topic == TOPICS["accel"]:
                yield "/tool/accel", stamp, Temperature(header=msg.header, temperature=21.0, variance=0.0)
            yield topic, stamp, msg

    bag = write_bag(tmp_path / "bag", messages(), storage)
    _refused(
        bag,
        r"topic /tool/accel carries sensor_msgs/msg/Temperature, a message type accel cannot read",
        topic_map_from_dict({"accel": {"topic": "/tool/accel"}}),
    )


@pytest.mark.parametrize("storage", STORAGES)
def test_a_wrench_in_another_frame(stroke, tmp_path, storage):
    bag = write_bag(tmp_path / "bag", _stamped(stroke), storage)
    _refused(
        bag,
        r"topic /wrist/wrench message 0: the wrench is in frame 'tool0_ft', the topic map says 'base_link'",
        topic_map_from_dict({"force": {"frame": "base_link"}}),
    )


@pytest.mark.parametrize("storage", STORAGES)
def test_accelerations_in_the_wrong_units(stroke, tmp_path, storage):
    items, _ = stroke
    sim = [i for i in items if isinstance(i, SampleBlock)]
    accel, force, speed = (_concat(sim, k)[:2000] for k in ("accel", "force", "speed"))
    in_g = write_bag(tmp_path / "g", stroke_messages(accel / 9.80665, force, speed, 1000.0), storage)
    _refused(in_g, r"topic /tool/imu .*gravity reads 1.00 m/s² with units 'm/s\^2'; these accelerations look like g")
    _refused(
        write_bag(tmp_path / "ms2", stroke_messages(accel, force, speed, 1000.0), storage),
        r"gravity reads 96.\d m/s² with units 'g'; these accelerations look like m/s²",
        topic_map_from_dict({"accel": {"units": "g"}}),
    )


@pytest.mark.parametrize("storage", STORAGES)
def test_timestamps_going_backwards(stroke, tmp_path, storage):
    def shift(topic, stamp):  # the wrench sensor's clock steps back 0.5 s at 1 s
        back = topic == TOPICS["force"] and stamp >= DEFAULT_START_NS + 1_000_000_000
        return stamp - 500_000_000 if back else stamp

    bag = write_bag(tmp_path / "bag", _stamped(stroke, shift=shift), storage)
    _refused(bag, r"topic /wrist/wrench .*header.stamp goes back 0.498 s at message 500")


def test_a_zero_byte_file_and_a_db3_that_is_not_sqlite(tmp_path):
    for name in ("empty.db3", "empty.mcap"):
        (tmp_path / name).write_bytes(b"")
        _refused(tmp_path / name, r"empty.* empty file \(0 bytes\), not a ROS 2 bag")
    (tmp_path / "notes.db3").write_text("these are my notes, not a bag\n" * 10)
    _refused(tmp_path / "notes.db3", r"notes.db3: not an SQLite database")
    with pytest.raises(sqlite3.DatabaseError):  # what sqlite itself would have said, without the bag's name
        sqlite3.connect(tmp_path / "notes.db3").execute("select * from topics")
    (tmp_path / "x.mcap").write_bytes(b"PK\x03\x04" + bytes(100))
    _refused(tmp_path / "x.mcap", r"x.mcap: not an MCAP file")
    _refused(tmp_path / "missing.db3", r"no such bag")


# ---- hapticlink dataset build --source rosbag ---------------------------------------------------------
def test_a_folder_of_bags_builds_a_dataset_whole_or_not_at_all(stroke, tmp_path):
    from models.offline.datasets.build import build
    from texture_library.recording import load_recording

    items, image = stroke
    sim = [i for i in items if isinstance(i, SampleBlock)]
    accel, force, speed = (_concat(sim, k) for k in ("accel", "force", "speed"))
    src = tmp_path / "src"
    (src / "recordings" / "wood").mkdir(parents=True)
    (src / "textures.csv").write_text("texture,name,group\nwood,Wood,natural\n")
    (src / "ratings.csv").write_text("texture,rater,attribute,rating\nwood,r1,rough_smooth,20\n")
    write_bag(src / "recordings" / "wood" / "run1", stroke_messages(accel, force, speed, 1000.0, image), "mcap")
    out = build("rosbag", tmp_path / "ds", path=src)
    rec = load_recording(out / "textures" / "wood" / "recording_000.npz")
    np.testing.assert_allclose(rec.accel.data, accel[: int(SECONDS * 1000)], rtol=SAMPLE_RTOL, atol=1e-5)
    assert (rec.force.rate_hz, rec.speed.rate_hz) == (500.0, 100.0)
    assert (out / "textures" / "wood" / "image_000.png").read_bytes() == image, "the bag's first camera image"
    # a second texture whose bag is not sqlite: refused, naming it, and no dataset folder is left behind
    (src / "recordings" / "cork").mkdir()
    (src / "recordings" / "cork" / "run1.db3").write_text("not a bag")
    (src / "textures.csv").write_text("texture,name,group\nwood,Wood,natural\ncork,Cork,natural\n")
    with pytest.raises(BagError, match=r"cork/run1.db3: not an SQLite database"):
        build("rosbag", tmp_path / "ds2", path=src)
    assert not (tmp_path / "ds2").exists() and not (tmp_path / "ds2.partial").exists()


# ---- the batch codec agrees with rosbags ---------------------------------------------------------------
def test_the_batch_codec_reads_and_writes_what_rosbags_does(stroke):
    from rosbags.typesys import Stores, get_typestore

    from drivers.rosbag_cdr import decode_batch
    from drivers.rosbag_writer import stroke_raw_messages

    ts = get_typestore(Stores.ROS2_HUMBLE)
    items, _ = stroke
    sim = [i for i in items if isinstance(i, SampleBlock)]
    accel, force, speed = (_concat(sim, k)[:500].astype(np.float64) for k in ("accel", "force", "speed"))
    slow = [(t, s, bytes(ts.serialize_cdr(m, m.__msgtype__))) for t, s, m in stroke_messages(accel, force, speed, 1e3)]
    fast = [(t, s, m.data) for t, s, m in stroke_raw_messages(accel, force, speed, 1e3)]
    assert fast == slow, "encode_batch writes rosbags' own bytes"
    for topic, msgtype in ((TOPICS["accel"], IMU_TYPE), (TOPICS["force"], WRENCH_TYPE)):
        raws = [r for t, _, r in slow if t == topic]
        batch = decode_batch(raws, msgtype)
        assert batch is not None
        for k, raw in enumerate(raws):
            msg = ts.deserialize_cdr(raw, msgtype)
            vec = msg.linear_acceleration if msgtype == IMU_TYPE else msg.wrench.force
            assert batch.vectors[k].tolist() == [vec.x, vec.y, vec.z]
            assert batch.stamps_ns[k] == msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
    wrenches = [r for t, _, r in slow if t == TOPICS["force"]]
    other = ts.serialize_cdr(ts.deserialize_cdr(wrenches[0], WRENCH_TYPE), WRENCH_TYPE)
    assert decode_batch(wrenches[:3] + [bytes(other)], WRENCH_TYPE) is not None, "same length, same frame: one batch"
    msg = ts.deserialize_cdr(wrenches[0], WRENCH_TYPE)
    msg.header.frame_id = "tool0_fx"  # same length, another frame: rosbags reads that batch, message by message
    assert decode_batch(wrenches[:3] + [bytes(ts.serialize_cdr(msg, WRENCH_TYPE))], WRENCH_TYPE) is None
    msg.header.frame_id = "ft"
    assert decode_batch(wrenches[:3] + [bytes(ts.serialize_cdr(msg, WRENCH_TYPE))], WRENCH_TYPE) is None
    big_endian = b"\x00\x00" + wrenches[0][2:]
    assert decode_batch([big_endian], WRENCH_TYPE) is None


@pytest.mark.parametrize("storage", STORAGES)
def test_speeds_in_the_wrong_units(stroke, tmp_path, storage):
    bag = write_bag(tmp_path / "bag", _stamped(stroke), storage)  # twist in m/s, as REP 103 says
    _refused(
        bag,
        r"topic /tool/twist .*median scanning speed 0.\d+ mm/s .*look like m/s",
        topic_map_from_dict({"speed": {"units": "mm/s"}}),
    )


@pytest.mark.parametrize("storage", STORAGES)
def test_odometry_for_speed_and_raw_images_for_frames(stroke, tmp_path, storage):
    """nav_msgs/Odometry's twist.twist.linear feeds speed; a sensor_msgs/Image in bgr8 becomes a PNG frame in RGB."""
    from PIL import Image as PILImage

    from drivers.rosbag_writer import _typestore

    ts = _typestore()
    items, _ = stroke
    sim = [i for i in items if isinstance(i, SampleBlock)]
    speed = _concat(sim, "speed")[:2000]
    rgb = np.random.default_rng(0).integers(0, 255, (8, 12, 3), dtype=np.uint8)
    Odometry, Image = ts.types["nav_msgs/msg/Odometry"], ts.types["sensor_msgs/msg/Image"]

    def messages():
        for topic, stamp, msg in _stamped(stroke):
            if topic == TOPICS["speed"]:
                odom = Odometry(
                    header=msg.header,
                    child_frame_id="tool0",
                    pose=ts.types["geometry_msgs/msg/PoseWithCovariance"](
                        pose=ts.types["geometry_msgs/msg/Pose"](
                            position=ts.types["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
                            orientation=ts.types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
                        ),
                        covariance=np.zeros(36),
                    ),
                    twist=ts.types["geometry_msgs/msg/TwistWithCovariance"](twist=msg.twist, covariance=np.zeros(36)),
                )
                yield "/odom", stamp, odom
                if (stamp - DEFAULT_START_NS) % 500_000_000 == 0:
                    bgr = rgb[:, :, ::-1].copy()
                    yield (
                        "/camera/raw",
                        stamp,
                        Image(
                            header=msg.header,
                            height=8,
                            width=12,
                            encoding="bgr8",
                            is_bigendian=0,
                            step=36,
                            data=bgr.ravel(),
                        ),
                    )
            else:
                yield topic, stamp, msg

    bag = write_bag(tmp_path / "bag", messages(), storage)
    got = asyncio.run(_take(RosbagSource(bag, realtime=False)))
    blocks = [i for i in got if isinstance(i, SampleBlock)]
    frames = [i for i in got if isinstance(i, Frame)]
    np.testing.assert_allclose(_concat(blocks, "speed"), speed[::10], rtol=1e-6)
    assert len(frames) == 4 and all(f.content_type == "image/png" for f in frames)
    import io

    np.testing.assert_array_equal(np.asarray(PILImage.open(io.BytesIO(frames[0].image))), rgb)


# ---- MCAP through its index ------------------------------------------------------------------------------
def _rewritten(src: Path, dst: Path, **writer_options) -> Path:
    """The MCAP bag `src` written again by the mcap package's Writer (its options: compression, chunk size,
    indexes) into the file `dst` (a bag given as its .mcap file alone)."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    with storage_file(src).open("rb") as fh, dst.open("wb") as sink:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert summary is not None
        writer = Writer(sink, **writer_options)
        writer.start(profile="ros2", library="test")
        schema_ids = {
            sid: writer.register_schema(name=s.name, encoding=s.encoding, data=s.data)
            for sid, s in summary.schemas.items()
        }
        channel_ids = {
            cid: writer.register_channel(
                topic=c.topic,
                message_encoding=c.message_encoding,
                schema_id=schema_ids[c.schema_id],
                metadata=c.metadata,
            )
            for cid, c in summary.channels.items()
        }
        for _, channel, message in reader.iter_messages(log_time_order=False):
            writer.add_message(
                channel_ids[channel.id], message.log_time, message.data, message.publish_time, message.sequence
            )
        writer.finish()
    return dst


def _rosbags_messages(bag: Path) -> dict[str, list[bytes]]:
    from rosbags.rosbag2 import Reader

    out: dict[str, list[bytes]] = {}
    with Reader(bag) as reader:
        for conn, _, raw in reader.messages():
            out.setdefault(conn.topic, []).append(bytes(raw))
    return out


@pytest.mark.parametrize("variant", ["rosbags", "zstd", "lz4", "no message index"])
def test_an_mcap_bag_read_through_its_index_gives_what_rosbags_reads(stroke, tmp_path, variant):
    """Every topic's messages, byte for byte and in rosbags' order, come out of an MCAP's index: as rosbags writes it
    (1 MiB chunks, uncompressed) and as the mcap package does (64 kB chunks, zstd or lz4, with CRCs); a chunk without
    message indexes is walked (rosbags itself reads nothing of it). The scan is the .db3's of the same messages,
    to the bit."""
    from mcap.writer import CompressionType, IndexType

    from drivers.rosbag_mcap import open_indexed

    items, image = stroke
    sim = [i for i in items if isinstance(i, SampleBlock)]
    accel, force, speed = (_concat(sim, k) for k in ("accel", "force", "speed"))
    messages = list(stroke_messages(accel, force, speed, 1000.0, image))
    db3 = write_bag(tmp_path / "db3", iter(messages), "sqlite3")
    bag = original = write_bag(tmp_path / "mcap", iter(messages), "mcap")
    if variant != "rosbags":
        options = {
            "zstd": {"compression": CompressionType.ZSTD},
            "lz4": {"compression": CompressionType.LZ4},
            "no message index": {"index_types": IndexType.CHUNK},
        }[variant]
        bag = _rewritten(bag, tmp_path / f"{variant.replace(' ', '-')}.mcap", chunk_size=64 * 1024, **options)
    indexed = open_indexed(storage_file(bag) if bag.is_dir() else bag)
    assert indexed is not None and len(indexed.chunks) > 2
    got: dict[str, list[bytes]] = {}
    for piece in indexed.read(set(TOPICS.values())):
        got.setdefault(piece.topic, []).extend(piece.messages())
    assert got == _rosbags_messages(original)
    camera = [r for p in indexed.read([TOPICS["frames"]], whole_chunks=False) for r in p.messages()]
    assert camera == got[TOPICS["frames"]]
    want, scan = scan_bag(db3), scan_bag(bag)
    for ch, samples in want.channels.items():
        np.testing.assert_array_equal(scan.channels[ch].stamps_ns, samples.stamps_ns)
        np.testing.assert_array_equal(scan.channels[ch].values, samples.values)
    assert want.frames is not None and scan.frames is not None
    np.testing.assert_array_equal(scan.frames.stamps_ns, want.frames.stamps_ns)
    frames = [i for i in asyncio.run(_take(RosbagSource(bag, realtime=False))) if isinstance(i, Frame)]
    assert len(frames) == int(SECONDS * 5) and all(f.image == image for f in frames)


def test_an_mcap_whose_chunk_disagrees_with_its_index(stroke, tmp_path):
    """The index points at a byte that holds no message of the topic (the file was damaged after it was written):
    refused, naming the topic, before a block is sent."""
    bag = write_bag(tmp_path / "bag", _stamped(stroke), "mcap")
    f = storage_file(bag)
    data = bytearray(f.read_bytes())
    first_imu = _rosbags_messages(bag)[TOPICS["accel"]][0]
    at = data.find(first_imu) - 31  # its Message record's opcode
    assert data[at] == 0x05
    data[at] = 0x09
    f.write_bytes(bytes(data))
    _refused(bag, r"truncated or damaged .*topic /tool/imu\): an indexed offset holds no message of the channel")


def test_a_bag_compressed_message_by_message_streams_as_the_plain_one(bag, tmp_path):
    """rosbag2's per-message compression (each message zstd'd alone): read by rosbags in both passes, the same
    blocks and frames as the plain bag's."""
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, Reader, StoragePlugin, Writer

    plugin = {".db3": StoragePlugin.SQLITE3, ".mcap": StoragePlugin.MCAP}[storage_file(bag).suffix]
    packed_writer = Writer(tmp_path / "packed", version=9, storage_plugin=plugin)
    packed_writer.set_compression(CompressionMode.MESSAGE, CompressionFormat.ZSTD)
    with Reader(bag) as reader, packed_writer as writer:
        conns = {
            c.id: writer.add_connection(c.topic, c.msgtype, msgdef=c.msgdef.data, rihs01=c.digest)
            for c in reader.connections
        }
        for conn, stamp, raw in reader.messages():
            writer.write(conns[conn.id], stamp, raw)
    plain = asyncio.run(_take(RosbagSource(bag, realtime=False)))
    got = asyncio.run(_take(RosbagSource(tmp_path / "packed", realtime=False)))
    assert len(got) == len(plain)
    for a, b in zip(got, plain):
        assert type(a) is type(b)
        if isinstance(a, Frame):
            assert (a.t, a.image) == (b.t, b.image)
        else:
            assert a.t0 == b.t0 and a.channels.keys() == b.channels.keys()
            for k in a.channels:
                np.testing.assert_array_equal(a.channels[k].data, b.channels[k].data)


@pytest.mark.parametrize("storage", STORAGES)
def test_tool_poses_differentiated_give_the_scanning_speed(stroke, tmp_path, storage):
    """geometry_msgs/PoseStamped at 100 Hz, the tool moving along x as x(t) = v0 t + A sin(2π f t) m, silent for
    0.3 s at 0.8 s: the speed channel is |v0 + 2π f A cos(2π f t)| in mm/s (central differences, exact to
    (2π f / 100 Hz)² / 6 ≈ 1e-4 relative), and the hole's displacement is no speed."""
    from drivers.rosbag_writer import _typestore

    ts = _typestore()
    PoseStamped, Pose = ts.types["geometry_msgs/msg/PoseStamped"], ts.types["geometry_msgs/msg/Pose"]
    Point, Quaternion = ts.types["geometry_msgs/msg/Point"], ts.types["geometry_msgs/msg/Quaternion"]
    v0, amp, freq = 0.08, 0.01, 0.5  # m/s, m, Hz: 80 mm/s ± 31 mm/s

    def messages():
        for topic, stamp, msg in _stamped(stroke):
            if topic != TOPICS["speed"]:
                yield topic, stamp, msg
                continue
            t = (stamp - DEFAULT_START_NS) * 1e-9
            if 0.8 <= t < 1.1:
                continue
            x = v0 * t + amp * np.sin(2 * np.pi * freq * t)
            pose = Pose(position=Point(x=x, y=0.25, z=0.1), orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0))
            yield "/tool/pose", stamp, PoseStamped(header=msg.header, pose=pose)

    scan = scan_bag(write_bag(tmp_path / "bag", messages(), storage))
    speed = scan.channels["speed"]
    assert speed.msgtype == "geometry_msgs/msg/PoseStamped" and speed.rate_hz == 100.0
    t = (speed.stamps_ns - DEFAULT_START_NS) * 1e-9
    want = np.abs(v0 + 2 * np.pi * freq * amp * np.cos(2 * np.pi * freq * t)) * 1000.0
    inner = np.ones(t.shape[0], dtype=bool)
    inner[[0, -1]] = False
    inner[np.flatnonzero(np.diff(t) > 0.05)] = False  # the samples on each side of the hole: one-sided differences
    inner[np.flatnonzero(np.diff(t) > 0.05) + 1] = False
    np.testing.assert_allclose(speed.values[inner, 0], want[inner], rtol=2e-4)
    np.testing.assert_allclose(speed.values[~inner, 0], want[~inner], rtol=0.01)
    blocks = [
        i
        for i in asyncio.run(_take(RosbagSource(write_bag(tmp_path / "b2", messages(), storage), realtime=False)))
        if isinstance(i, SampleBlock)
    ]
    assert _concat(blocks, "speed").max() < (v0 + 2 * np.pi * freq * amp) * 1000.0 * 1.01
