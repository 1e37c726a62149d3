"""The fixed-layout messages a tool streams at kHz rates (sensor_msgs/Imu, geometry_msgs/WrenchStamped,
geometry_msgs/TwistStamped, geometry_msgs/PoseStamped), decoded and encoded thousands at a time with numpy.

rosbags decodes one message per Python call (tens of µs each): at 1.6 k messages per bag-second that alone holds a
bag read near 20× real time. These messages are a header (stamp, frame_id) and float64 fields at offsets fixed once
the frame_id's length is known, so a batch of messages of one length and one frame_id is one (n, L) byte array,
and its stamps and vectors are column views of it. Anything else — other lengths or frames within a batch, another
byte order — is left to rosbags (`decode_batch` and `decode_rows` return None), so the result is always rosbags'
own reading (tests/drivers/test_rosbag_source.py holds both to the same answer).

Layout (XCDR1, little endian): 4 bytes of encapsulation (00 01 00 00), then the body, aligned from its own start:
stamp.sec int32 @0, stamp.nanosec uint32 @4, frame_id length (with its NUL) uint32 @8, its bytes @12, then the
float64 fields from the next multiple of 8.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivers.rosbag_mapping import IMU, POSE, TWIST, WRENCH

CDR_LE = np.frombuffer(b"\x00\x01\x00\x00", dtype=np.uint8)
#: per type: (byte offset of the vector the channel reads, from the first float64 field; bytes of float64 fields)
LAYOUT: dict[str, tuple[int, int]] = {
    IMU: (200, 296),  # orientation 4, its covariance 9, angular_velocity 3, its covariance 9 → linear_acceleration
    WRENCH: (0, 48),  # wrench.force, then wrench.torque
    TWIST: (0, 48),  # twist.linear, then twist.angular
    POSE: (0, 56),  # pose.position, then pose.orientation
}


@dataclass(frozen=True)
class DecodedBatch:
    """stamps_ns (n,) int64; vectors (n, 3) float64; frame_id of every message in the batch."""

    stamps_ns: np.ndarray
    vectors: np.ndarray
    frame_id: str


def _fields_offset(frame_len: int) -> int:
    """Byte offset in the raw message of the first float64 field, for a frame_id of frame_len bytes with its NUL."""
    return 4 + ((12 + frame_len + 7) // 8) * 8


def decode_batch(raws: list[bytes], msgtype: str) -> DecodedBatch | None:
    """Stamps and the channel's vector of a batch of raw CDR messages of `msgtype` (a LAYOUT key), or None when the
    batch is not uniform (lengths, frame_ids, byte order) and rosbags must read it message by message."""
    if not raws or msgtype not in LAYOUT:
        return None
    size = len(raws[0])
    if any(len(r) != size for r in raws):
        return None
    return decode_rows(np.frombuffer(b"".join(raws), dtype=np.uint8).reshape(len(raws), size), msgtype)


def decode_rows(buf: np.ndarray, msgtype: str) -> DecodedBatch | None:
    """decode_batch of messages of one length already stacked: buf (n, L) uint8, one raw CDR message per row."""
    if msgtype not in LAYOUT or buf.ndim != 2 or buf.shape[0] == 0:
        return None
    n, size = buf.shape
    if size < 16:
        return None
    if not np.array_equal(buf[:, :4], np.broadcast_to(CDR_LE, (n, 4))):
        return None
    lengths = np.ascontiguousarray(buf[:, 12:16]).view("<u4")[:, 0]
    frame_len = int(lengths[0])
    if frame_len < 1 or np.any(lengths != frame_len) or 16 + frame_len > size:
        return None
    offset, fields = LAYOUT[msgtype]
    start = _fields_offset(frame_len)
    if start + fields != size:
        return None
    names = buf[:, 16 : 16 + frame_len]
    if not np.array_equal(names, np.broadcast_to(names[0], names.shape)) or names[0, -1] != 0:
        return None
    try:
        frame_id = bytes(names[0, :-1]).decode()
    except UnicodeDecodeError:
        return None
    sec = np.ascontiguousarray(buf[:, 4:8]).view("<i4")[:, 0].astype(np.int64)
    nsec = np.ascontiguousarray(buf[:, 8:12]).view("<u4")[:, 0].astype(np.int64)
    vectors = np.ascontiguousarray(buf[:, start + offset : start + offset + 24]).view("<f8").astype(np.float64)
    return DecodedBatch(sec * 1_000_000_000 + nsec, vectors, frame_id)


def encode_batch(template: bytes, msgtype: str, stamps_ns: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """Messages like `template` (one raw CDR message of `msgtype`, as rosbags serialises it) with their stamps and
    the channel's vector replaced: (n, len(template)) uint8, one message per row. stamps_ns (n,) int; vectors (n, 3)."""
    if msgtype not in LAYOUT:
        raise ValueError(f"encode_batch: {msgtype} has no fixed layout; one of {list(LAYOUT)}")
    n = int(np.asarray(stamps_ns).shape[0])
    vectors = np.asarray(vectors, dtype="<f8")
    if vectors.shape != (n, 3):
        raise ValueError(f"encode_batch: vectors must have shape ({n}, 3), got {vectors.shape}")
    frame_len = int(np.frombuffer(template[12:16], dtype="<u4")[0])
    offset, fields = LAYOUT[msgtype]
    start = _fields_offset(frame_len)
    if start + fields != len(template):
        raise ValueError(f"encode_batch: the template is not a {msgtype} message ({len(template)} bytes)")
    out = np.tile(np.frombuffer(template, dtype=np.uint8), (n, 1))
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    out[:, 4:8] = (stamps // 1_000_000_000).astype("<i4").view(np.uint8).reshape(n, 4)
    out[:, 8:12] = (stamps % 1_000_000_000).astype("<u4").view(np.uint8).reshape(n, 4)
    out[:, start + offset : start + offset + 24] = vectors.view(np.uint8).reshape(n, 24)
    return out
