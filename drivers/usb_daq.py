"""A USB DAQ speaking the HLD1 endpoint protocol (docs/drivers.md), read with pyusb in a thread.

- Vendor control IN request GET_CONFIG (bmRequestType 0xC0, bRequest 0x01) returns UTF-8 JSON:
  {"protocol": "HLD1", "rate_hz": 1000, "channels": [{"kind": "accel", "units": "g", "columns": 3,
  "scale": 0.0005}, …]} — channels in column order; value = int16 × scale, in the given units.
- Vendor control OUT request STREAM (bmRequestType 0x40, bRequest 0x02, wValue 1 start / 0 stop).
- Bulk IN endpoint 0x81: packets b"HLD1" | uint32 LE index of the packet's first sample (mod 2³²) |
  uint16 LE sample count n | n × columns int16 LE, interleaved in column order. A transfer may hold
  several packets back to back.
"""

from __future__ import annotations

import json
import logging
import math
import struct
import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from drivers.blocks import SampleBlock
from drivers.source import (
    Item,
    Layout,
    StreamAssembler,
    StreamStats,
    ThreadedSource,
    check_positive,
    device_rate,
    layout_channel,
)

log = logging.getLogger(__name__)

#: pid.codes test VID:PID, for development boards; a production DAQ gets its own PID.
DEFAULT_VID = 0x1209
DEFAULT_PID = 0x0001
INTERFACE = 0
ENDPOINT_IN = 0x81
REQ_TYPE_VENDOR_IN = 0xC0  # device-to-host | vendor | device
REQ_TYPE_VENDOR_OUT = 0x40  # host-to-device | vendor | device
REQ_GET_CONFIG = 0x01
REQ_STREAM = 0x02
CONFIG_MAX_BYTES = 1024
PACKET_MAGIC = b"HLD1"
PACKET_HEADER = struct.Struct("<4sIH")  # magic, first-sample index, sample count
READ_SIZE = 16384  # bytes per bulk read: several packets at most rates
READ_TIMEOUT_MS = 100  # so the reader thread sees a stop request within 0.1 s


class DeviceNotFoundError(LookupError):
    """No USB device with the requested VID:PID (unplugged, wrong ids, or no permission)."""


@dataclass(frozen=True)
class DaqConfig:
    """What the DAQ reports: rate (Hz), layout (kind, columns, units) in column order, int16 → units scale per
    channel."""

    rate_hz: float
    layout: Layout
    scales: tuple[float, ...]

    @property
    def columns(self) -> int:
        return sum(cols for _, cols, _ in self.layout)

    def column_scales(self) -> np.ndarray:
        """(columns,) factor for each int16 column."""
        return np.repeat(np.asarray(self.scales, float), [cols for _, cols, _ in self.layout])


def parse_config(raw: bytes) -> DaqConfig:
    """Decode the GET_CONFIG answer; ValueError names what is wrong."""
    try:
        doc = json.loads(bytes(raw).decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"USB DAQ config is not UTF-8 JSON ({exc})") from None
    if not isinstance(doc, dict) or doc.get("protocol") != "HLD1":
        raise ValueError(
            f"USB DAQ config: protocol must be 'HLD1', got {doc.get('protocol') if isinstance(doc, dict) else doc!r}"
        )
    rate = device_rate(doc.get("rate_hz"), "USB DAQ config")
    chans = doc.get("channels")
    if not isinstance(chans, list) or not chans:
        raise ValueError("USB DAQ config: channels must be a non-empty list")
    layout: list[tuple[str, int, str]] = []
    scales: list[float] = []
    for i, ch in enumerate(chans):
        if not isinstance(ch, dict):
            raise ValueError(f"USB DAQ config: channel {i} must be an object")
        kind, scale = ch.get("kind"), ch.get("scale")
        layout.append(layout_channel(layout, kind, ch.get("columns"), ch.get("units"), f"USB DAQ config: channel {i}"))
        if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not (math.isfinite(scale) and scale > 0):
            raise ValueError(f"USB DAQ config: {kind} scale must be a positive number, got {scale!r}")
        scales.append(float(scale))
    return DaqConfig(rate, tuple(layout), tuple(scales))


@dataclass
class DaqStats(StreamStats):
    """StreamStats plus what the packet protocol saw (written by the reader thread only)."""

    packets: int = 0
    bad_packets: int = 0  # wrong magic or truncated: the rest of that transfer is dropped
    timeouts: int = 0  # bulk reads that returned nothing within READ_TIMEOUT_MS


class PacketDecoder:
    """Bulk transfers → SampleBlocks (no I/O). Gap handling: drivers.source.StreamAssembler."""

    def __init__(self, config: DaqConfig, block_s: float | None = None) -> None:
        self.config = config
        self.stats = DaqStats()
        self._scales = config.column_scales()
        self._assembler = StreamAssembler(config.rate_hz, config.layout, block_s, stats=self.stats)

    def feed(self, transfer: bytes) -> list[SampleBlock]:
        """Decode one bulk transfer (one or more packets back to back); return finished blocks."""
        out: list[SampleBlock] = []
        buf = memoryview(bytes(transfer))
        offset = 0
        while offset < len(buf):
            if len(buf) - offset < PACKET_HEADER.size:
                self._bad(f"{len(buf) - offset} stray byte(s) after the last packet")
                break
            magic, first, n = PACKET_HEADER.unpack_from(buf, offset)
            size = PACKET_HEADER.size + 2 * n * self.config.columns
            if magic != PACKET_MAGIC:
                self._bad(f"bad magic {bytes(magic)!r}")
                break  # no way to find the next packet boundary in this transfer
            if n == 0 or len(buf) - offset < size:
                self._bad(f"packet of {n} samples is truncated or empty")
                break
            samples = np.frombuffer(buf, dtype="<i2", count=n * self.config.columns, offset=offset + PACKET_HEADER.size)
            rows = samples.reshape(n, self.config.columns) * self._scales
            self.stats.packets += 1
            out += self._assembler.add(first, rows)
            offset += size
        return out

    def _bad(self, why: str) -> None:
        self.stats.bad_packets += 1
        log.warning("USB DAQ: dropped a bad packet: %s", why)

    def settle(self) -> list[SampleBlock]:
        """A read timed out: StreamAssembler.settle."""
        return self._assembler.settle()

    def flush(self) -> list[SampleBlock]:
        return self._assembler.flush()


class UsbDaqSource(ThreadedSource):
    """Sample blocks from an HLD1 DAQ, read with pyusb in a background thread.

    vid, pid: USB ids; backend: a pyusb backend (None: libusb1/openusb/libusb0, whichever loads);
    block_s: seconds per block (None: from the device's rate, drivers.source.default_block_s). Opening happens
    when iteration starts; DeviceNotFoundError (from the iterator) when no such device is attached. Decoding
    counts live in `stats` once open.
    """

    def __init__(
        self,
        vid: int = DEFAULT_VID,
        pid: int = DEFAULT_PID,
        backend: object | None = None,
        block_s: float | None = None,
        queue_size: int = 256,
    ) -> None:
        super().__init__(queue_size)
        for label, value in (("vid", vid), ("pid", pid)):
            if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 0xFFFF:
                raise ValueError(f"{label} must be an integer in [0, 0xFFFF], got {value!r}")
        if block_s is not None:  # None: chosen from the device's rate (drivers.source.default_block_s)
            check_positive("block_s", block_s)
        self.vid, self.pid = vid, pid
        self.backend = backend
        self.block_s = block_s
        self.name = f"usb:{vid:04x}:{pid:04x}"
        self.config: DaqConfig | None = None
        self._decoder: PacketDecoder | None = None

    @property
    def stats(self) -> DaqStats:
        return self._decoder.stats if self._decoder is not None else DaqStats()

    def _open(self):
        import usb.core  # pyusb: imported here so the rest of drivers loads without it

        try:
            dev = usb.core.find(idVendor=self.vid, idProduct=self.pid, backend=self.backend)
        except usb.core.NoBackendError:
            raise DeviceNotFoundError(
                f"no USB backend available to look for {self.vid:04x}:{self.pid:04x} (install libusb-1.0)"
            ) from None
        if dev is None:
            raise DeviceNotFoundError(
                f"no USB device {self.vid:04x}:{self.pid:04x} found "
                "(is the DAQ plugged in? on Linux, does a udev rule give you access?)"
            )
        return dev

    def _produce(self, stop: threading.Event, emit: Callable[[Item], None]) -> None:
        import usb.core
        import usb.util

        dev = self._open()
        try:
            dev.set_configuration()
            self.config = parse_config(
                bytes(dev.ctrl_transfer(REQ_TYPE_VENDOR_IN, REQ_GET_CONFIG, 0, 0, CONFIG_MAX_BYTES))
            )
            self._decoder = PacketDecoder(self.config, self.block_s)
            usb.util.claim_interface(dev, INTERFACE)
            dev.ctrl_transfer(REQ_TYPE_VENDOR_OUT, REQ_STREAM, 1, 0)
            try:
                while not stop.is_set():
                    try:
                        data = dev.read(ENDPOINT_IN, READ_SIZE, READ_TIMEOUT_MS)
                    except usb.core.USBTimeoutError:
                        self._decoder.stats.timeouts += 1
                        for block in self._decoder.settle():
                            emit(block)
                        continue
                    for block in self._decoder.feed(bytes(data)):
                        emit(block)
                # stopped (finish() or close): the block being filled, and a packet held for judgement, still go
                for block in self._decoder.flush():
                    emit(block)
            finally:
                try:
                    dev.ctrl_transfer(REQ_TYPE_VENDOR_OUT, REQ_STREAM, 0, 0)
                except usb.core.USBError as exc:  # unplugged: nothing left to stop
                    log.debug("USB DAQ: stop request failed: %s", exc)
        finally:
            usb.util.dispose_resources(dev)
