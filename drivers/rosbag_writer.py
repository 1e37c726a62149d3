"""A stroke recorded as a ROS 2 bag, as a robot arm with a tool IMU, a wrist force/torque sensor and a camera would
record it: the worked example of docs/ros2.md, the bags the round-trip tests replay and the throughput benchmark's.

Standard message types only: sensor_msgs/msg/Imu (linear_acceleration, m/s², gravity included),
geometry_msgs/msg/WrenchStamped (force in the sensor frame, +z pressing into the surface),
geometry_msgs/msg/TwistStamped (the tool's linear velocity in the surface plane, m/s, along x) and
sensor_msgs/msg/CompressedImage (jpeg or png). Each topic samples the stroke at its own rate; stamps are
start_ns + i / rate.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from drivers.camera import sniff_content_type
from drivers.rosbag_mapping import COMPRESSED_IMAGE, IMU, TWIST, WRENCH

#: the topics the writer uses (the default topic map finds them by type)
TOPICS = {"accel": "/tool/imu", "force": "/wrist/wrench", "speed": "/tool/twist", "frames": "/camera/compressed"}
FT_FRAME = "tool0_ft"
#: 2023-11-14 22:13:20 UTC: stamps look like a real robot's clock
DEFAULT_START_NS = 1_700_000_000_000_000_000


@dataclass(frozen=True)
class BagRates:
    """Each topic's rate, Hz: IMU 1 kHz, wrench 500 Hz, twist 100 Hz, camera 5 Hz (a common arm's setup)."""

    imu_hz: float = 1000.0
    wrench_hz: float = 500.0
    twist_hz: float = 100.0
    camera_hz: float = 5.0


def _typestore() -> Any:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


def _header(ts: Any, stamp_ns: int, frame: str) -> Any:
    Time = ts.types["builtin_interfaces/msg/Time"]
    Header = ts.types["std_msgs/msg/Header"]
    return Header(stamp=Time(sec=int(stamp_ns // 1_000_000_000), nanosec=int(stamp_ns % 1_000_000_000)), frame_id=frame)


def _v3(ts: Any, xyz: np.ndarray) -> Any:
    return ts.types["geometry_msgs/msg/Vector3"](x=float(xyz[0]), y=float(xyz[1]), z=float(xyz[2]))


def stroke_messages(
    accel: np.ndarray,
    force: np.ndarray,
    speed: np.ndarray,
    rate_hz: float,
    image: bytes | None = None,
    rates: BagRates = BagRates(),
    start_ns: int = DEFAULT_START_NS,
    ft_frame: str = FT_FRAME,
) -> Iterator[tuple[str, int, Any]]:
    """(topic, stamp ns, message) of a stroke, in stamp order, each topic at its rate in `rates` taking the stroke's
    sample nearest its stamp. accel (n, 3) m/s²; force (n, 3) N (tangential x, y, normal); speed (n,) mm/s; all at
    rate_hz. image: PNG or JPEG bytes sent at rates.camera_hz."""
    ts = _typestore()
    Imu, Wrench, WrenchStamped = ts.types[IMU], ts.types["geometry_msgs/msg/Wrench"], ts.types[WRENCH]
    Twist, TwistStamped = ts.types["geometry_msgs/msg/Twist"], ts.types[TWIST]
    Quaternion, CompressedImage = ts.types["geometry_msgs/msg/Quaternion"], ts.types[COMPRESSED_IMAGE]
    n = speed.shape[0]
    duration_ns = int(round(n / rate_hz * 1e9))
    zero3, cov = np.zeros(3), np.zeros(9, dtype=np.float64)
    fmt = None
    if image is not None:
        ctype = sniff_content_type(image)
        if ctype is None:
            raise ValueError("image must be PNG or JPEG bytes")
        fmt = ctype.split("/")[1]

    def stamps(hz: float) -> np.ndarray:
        return start_ns + np.round(np.arange(int(duration_ns * 1e-9 * hz + 1e-9)) * (1e9 / hz)).astype(np.int64)

    def sample(stamp: int) -> int:
        return min(n - 1, int(round((stamp - start_ns) * 1e-9 * rate_hz)))

    def imu(stamp: int) -> Any:
        return Imu(
            header=_header(ts, stamp, "tool0_imu"),
            orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=cov,
            angular_velocity=_v3(ts, zero3),
            angular_velocity_covariance=cov,
            linear_acceleration=_v3(ts, accel[sample(stamp)]),
            linear_acceleration_covariance=cov,
        )

    def wrench(stamp: int) -> Any:
        f = force[sample(stamp)]
        return WrenchStamped(
            header=_header(ts, stamp, ft_frame), wrench=Wrench(force=_v3(ts, f), torque=_v3(ts, zero3))
        )

    def twist(stamp: int) -> Any:
        v = np.array([speed[sample(stamp)] * 1e-3, 0.0, 0.0])
        return TwistStamped(
            header=_header(ts, stamp, "surface"), twist=Twist(linear=_v3(ts, v), angular=_v3(ts, zero3))
        )

    def picture(stamp: int) -> Any:
        data = np.frombuffer(image or b"", dtype=np.uint8)
        return CompressedImage(header=_header(ts, stamp, "camera"), format=fmt, data=data)

    streams = [
        (TOPICS["accel"], stamps(rates.imu_hz), imu),
        (TOPICS["force"], stamps(rates.wrench_hz), wrench),
        (TOPICS["speed"], stamps(rates.twist_hz), twist),
    ]
    if image is not None:
        streams.append((TOPICS["frames"], stamps(rates.camera_hz), picture))
    merged = sorted((int(s), k, i) for k, (_, st, _) in enumerate(streams) for i, s in enumerate(st))
    for stamp, k, _ in merged:
        topic, _, make = streams[k]
        yield topic, stamp, make(stamp)


@dataclass(frozen=True)
class RawMessage:
    """A message already serialised (CDR), e.g. by drivers.rosbag_cdr.encode_batch."""

    msgtype: str
    data: bytes


def stroke_raw_messages(
    accel: np.ndarray,
    force: np.ndarray,
    speed: np.ndarray,
    rate_hz: float,
    rates: BagRates = BagRates(),
    start_ns: int = DEFAULT_START_NS,
) -> Iterator[tuple[str, int, RawMessage]]:
    """stroke_messages' IMU, wrench and twist messages (no camera), serialised a topic at a time with
    drivers.rosbag_cdr.encode_batch: the same bytes, fast enough to write a 10-minute bag for the benchmark."""
    from drivers.rosbag_cdr import encode_batch

    ts = _typestore()
    first = {}
    for topic, _, msg in stroke_messages(accel[:1], force[:1], speed[:1], 1.0, rates=BagRates(1, 1, 1, 1)):
        first[topic] = (msg.__msgtype__, bytes(ts.serialize_cdr(msg, msg.__msgtype__)))
    n = speed.shape[0]
    duration_s = n / rate_hz
    streams = []
    for topic, hz, values in (
        (TOPICS["accel"], rates.imu_hz, accel),
        (TOPICS["force"], rates.wrench_hz, force),
        (TOPICS["speed"], rates.twist_hz, np.column_stack([speed * 1e-3, np.zeros(n), np.zeros(n)])),
    ):
        stamps = start_ns + np.round(np.arange(int(duration_s * hz + 1e-9)) * (1e9 / hz)).astype(np.int64)
        index = np.minimum(n - 1, np.round((stamps - start_ns) * 1e-9 * rate_hz).astype(np.int64))
        msgtype, template = first[topic]
        streams.append((topic, msgtype, stamps, encode_batch(template, msgtype, stamps, values[index])))
    merged = sorted((int(st), k, i) for k, (_, _, sts, _) in enumerate(streams) for i, st in enumerate(sts))
    for stamp, k, i in merged:
        topic, msgtype, _, rows = streams[k]
        yield topic, stamp, RawMessage(msgtype, rows[i].tobytes())


def write_bag(path: str | Path, messages: Iterator[tuple[str, int, Any]], storage: str = "sqlite3") -> Path:
    """Write (topic, stamp ns, message or RawMessage) into a new ROS 2 bag folder at `path` (storage "sqlite3" or
    "mcap"); each message's log time is its stamp. Topics are registered as they first appear. → the bag folder."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    ts = _typestore()
    plugin = {"sqlite3": StoragePlugin.SQLITE3, "mcap": StoragePlugin.MCAP}.get(storage)
    if plugin is None:
        raise ValueError(f"storage must be 'sqlite3' or 'mcap', got {storage!r}")
    path = Path(path)
    with Writer(path, version=9, storage_plugin=plugin) as writer:
        conns: dict[str, Any] = {}
        for topic, stamp, msg in messages:
            raw = isinstance(msg, RawMessage)
            msgtype = msg.msgtype if raw else msg.__msgtype__
            conn = conns.get(topic)
            if conn is None:
                conn = conns[topic] = writer.add_connection(topic, msgtype, typestore=ts)
            writer.write(conn, stamp, msg.data if raw else bytes(ts.serialize_cdr(msg, msgtype)))
    return path


def storage_file(bag: Path) -> Path:
    """The one storage file (.db3 or .mcap) of a bag folder."""
    files = sorted(p for p in Path(bag).iterdir() if p.suffix in (".db3", ".mcap"))
    if len(files) != 1:
        raise ValueError(f"{bag}: expected one .db3 or .mcap file, found {[p.name for p in files]}")
    return files[0]
