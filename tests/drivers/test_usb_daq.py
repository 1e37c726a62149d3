"""UsbDaqSource through pyusb's backend interface, with a simulated DAQ behind usb.backend.IBackend."""

from __future__ import annotations

import array
import asyncio
import json
import struct
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest
import usb.backend
import usb.core

from drivers.usb_daq import DeviceNotFoundError, UsbDaqSource, parse_config

VID, PID = 0x1209, 0x0001
CONFIG = {
    "protocol": "HLD1",
    "rate_hz": 1000,
    "channels": [
        {"kind": "accel", "units": "g", "columns": 3, "scale": 0.0005},
        {"kind": "force", "units": "N", "columns": 3, "scale": 0.001},
        {"kind": "position", "units": "mm", "columns": 1, "scale": 0.01},
    ],
}
SCALES = np.array([0.0005] * 3 + [0.001] * 3 + [0.01])


def raw_samples(first: int, n: int) -> np.ndarray:
    """(n, 7) int16 the simulated DAQ measures from sample index `first` on."""
    idx = np.arange(first, first + n)[:, None]
    return ((idx * np.array([3, -5, 7, 11, 13, -17, 19]) + np.array([0, 100, 2000, -300, 40, 5, -6])) % 30000).astype(
        np.int16
    )


def packet(first: int, n: int, magic: bytes = b"HLD1") -> bytes:
    return struct.pack("<4sIH", magic, first % 2**32, n) + raw_samples(first, n).astype("<i2").tobytes()


class SimulatedDaq(usb.backend.IBackend):
    """One HLD1 DAQ (or none): descriptors, vendor requests, and a bulk IN endpoint fed from a script."""

    def __init__(self, transfers: list[bytes], vid: int = VID, pid: int = PID, config: bytes | None = None) -> None:
        super().__init__()
        self.transfers = list(transfers)
        self.vid, self.pid = vid, pid
        self.config = config if config is not None else json.dumps(CONFIG).encode()
        self.streaming: list[int] = []  # wValue of each STREAM request
        self.claimed: set[int] = set()
        self.open_handles = 0
        self.drained = threading.Event()

    # -- descriptors --
    def enumerate_devices(self):
        return ["daq0"] if self.vid is not None else []

    def get_device_descriptor(self, dev):
        return SimpleNamespace(
            bLength=18,
            bDescriptorType=1,
            bcdUSB=0x0200,
            bDeviceClass=0xFF,
            bDeviceSubClass=0,
            bDeviceProtocol=0,
            bMaxPacketSize0=64,
            idVendor=self.vid,
            idProduct=self.pid,
            bcdDevice=0x0100,
            iManufacturer=0,
            iProduct=0,
            iSerialNumber=0,
            bNumConfigurations=1,
            address=5,
            bus=1,
            port_number=2,
            port_numbers=(2,),
            speed=3,
        )

    def get_configuration_descriptor(self, dev, config):
        if config != 0:
            raise IndexError(config)
        return SimpleNamespace(
            bLength=9,
            bDescriptorType=2,
            wTotalLength=32,
            bNumInterfaces=1,
            bConfigurationValue=1,
            iConfiguration=0,
            bmAttributes=0x80,
            bMaxPower=50,
            extra_descriptors=[],
        )

    def get_interface_descriptor(self, dev, intf, alt, config):
        if intf != 0 or alt != 0:
            raise IndexError((intf, alt))
        return SimpleNamespace(
            bLength=9,
            bDescriptorType=4,
            bInterfaceNumber=0,
            bAlternateSetting=0,
            bNumEndpoints=1,
            bInterfaceClass=0xFF,
            bInterfaceSubClass=0,
            bInterfaceProtocol=0,
            iInterface=0,
            extra_descriptors=[],
        )

    def get_endpoint_descriptor(self, dev, ep, intf, alt, config):
        if ep != 0:
            raise IndexError(ep)
        return SimpleNamespace(
            bLength=7,
            bDescriptorType=5,
            bEndpointAddress=0x81,
            bmAttributes=0x02,
            wMaxPacketSize=512,
            bInterval=0,
            bRefresh=0,
            bSynchAddress=0,
            extra_descriptors=[],
        )

    # -- handles and interfaces --
    def open_device(self, dev):
        self.open_handles += 1
        return "handle"

    def close_device(self, dev_handle):
        self.open_handles -= 1

    def set_configuration(self, dev_handle, config_value):
        assert config_value == 1

    def get_configuration(self, dev_handle):
        return 1

    def claim_interface(self, dev_handle, intf):
        self.claimed.add(intf)

    def release_interface(self, dev_handle, intf):
        self.claimed.discard(intf)

    # -- transfers --
    def ctrl_transfer(self, dev_handle, bmRequestType, bRequest, wValue, wIndex, data, timeout):
        if (bmRequestType, bRequest) == (0xC0, 0x01):  # GET_CONFIG
            n = min(len(data), len(self.config))
            data[:n] = array.array("B", self.config[:n])
            return n
        if (bmRequestType, bRequest) == (0x40, 0x02):  # STREAM start/stop
            self.streaming.append(wValue)
            return 0
        raise usb.core.USBError("stall", errno=32)

    def bulk_read(self, dev_handle, ep, intf, buff, timeout):
        assert ep == 0x81 and intf == 0
        if not self.streaming or self.streaming[-1] != 1:
            raise usb.core.USBError("not streaming")
        if not self.transfers:
            self.drained.set()
            time.sleep(timeout / 1000 / 10)  # an idle device: the read times out
            raise usb.core.USBTimeoutError("Operation timed out", error_code=-7, errno=110)
        chunk = self.transfers.pop(0)
        n = min(len(buff), len(chunk))
        buff[:n] = array.array("B", chunk[:n])
        return n


def test_decoded_values_gaps_and_bad_packets(kit):
    transfers = [
        packet(0, 25),
        packet(25, 25) + packet(50, 10),  # two packets in one transfer
        packet(60, 25, magic=b"XXXX"),  # corrupt: dropped, shows up as a gap
        packet(85, 35),
    ]
    backend = SimulatedDaq(transfers)
    source = UsbDaqSource(VID, PID, backend=backend, block_s=0.02)
    blocks = asyncio.run(asyncio.wait_for(kit.take(source, samples=95), 10))

    present = [i for i in range(120) if not 60 <= i < 85]
    truth = raw_samples(0, 120)[present] * SCALES
    accel = np.concatenate([b.channels["accel"].data for b in blocks])
    force = np.concatenate([b.channels["force"].data for b in blocks])
    position = np.concatenate([b.channels["position"].data for b in blocks])
    np.testing.assert_array_equal(accel, truth[:, 0:3].astype(np.float32))
    np.testing.assert_array_equal(force, truth[:, 3:6].astype(np.float32))
    np.testing.assert_array_equal(position, truth[:, 6].astype(np.float32))
    assert {(k, c.units) for b in blocks for k, c in b.channels.items()} == {
        ("accel", "g"),
        ("force", "N"),
        ("position", "mm"),
    }
    assert [round(b.t0 * 1000) for b in blocks] == [0, 20, 40, 85, 100], (
        "blocks on the 20-sample grid; after the gap, at the true time"
    )
    s = source.stats
    assert (s.packets, s.bad_packets, s.gaps, s.missing_samples) == (4, 1, 1, 25)
    assert backend.streaming == [1, 0], "streaming started, and stopped on close"
    assert backend.claimed == set() and backend.open_handles == 0, "interface released, device closed"
    assert source.config.rate_hz == 1000.0


def test_sample_index_wraps_without_a_gap(kit):
    first = 2**32 - 30
    backend = SimulatedDaq([packet(first, 30), packet(2**32, 30)])  # the second starts at index 0 (mod 2³²)
    source = UsbDaqSource(VID, PID, backend=backend, block_s=0.02)
    blocks = asyncio.run(asyncio.wait_for(kit.take(source, samples=60), 10))
    assert source.stats.gaps == 0 and sum(b.channels["accel"].data.shape[0] for b in blocks) == 60


def test_a_missing_device_is_a_clear_error():
    source = UsbDaqSource(0x1209, 0x0002, backend=SimulatedDaq([]))  # only 1209:0001 is attached

    async def main():
        return [b async for b in source]

    with pytest.raises(DeviceNotFoundError, match="no USB device 1209:0002 found"):
        asyncio.run(main())


def test_config_errors_are_named():
    with pytest.raises(ValueError, match="not UTF-8 JSON"):
        parse_config(b"\xff")
    with pytest.raises(ValueError, match="protocol must be 'HLD1'"):
        parse_config(json.dumps({**CONFIG, "protocol": "X"}).encode())
    bad = json.loads(json.dumps(CONFIG))
    bad["channels"][1]["columns"] = 2
    with pytest.raises(ValueError, match=r"force has \[1, 3\] column"):
        parse_config(json.dumps(bad).encode())
    bad["channels"][1]["columns"] = 3
    bad["channels"][2]["scale"] = 0
    with pytest.raises(ValueError, match="position scale must be a positive number"):
        parse_config(json.dumps(bad).encode())
    with pytest.raises(ValueError, match="vid must be"):
        UsbDaqSource(0x10000, 1)


def test_a_robot_stopped_mid_block_delivers_what_the_daq_already_sent(kit, fake_service):
    """70 samples in 20-sample blocks: 3 blocks and 10 samples the DAQ had sent, dropped at the stop."""
    source = UsbDaqSource(VID, PID, backend=SimulatedDaq([packet(0, 35), packet(35, 35)]), block_s=0.02)
    # the robot stops at 1 s; the DAQ is drained long before
    stats = kit.stream_source(fake_service.app, source, 1.0, backoff=(0.01, 0.05), seed=7)
    accepted = fake_service.only_session().accepted
    assert stats.acked == stats.read == 4 and stats.unsent == 0
    np.testing.assert_array_equal(
        kit.concat(accepted, "accel"), (raw_samples(0, 70) * SCALES)[:, 0:3].astype(np.float32)
    )
