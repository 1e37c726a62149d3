"""Where the rendered vibration goes: a WAV file, a sound card (a voice-coil actuator behind an audio amplifier),
or the operator's device on a serial port. Each output takes blocks of acceleration (n,) m/s² and friction
force (n,) N at 1 kHz; `close()` finishes it.

Acceleration becomes a signal in [−1, 1] by `full_scale` (m/s² at full scale): what an amplifier and actuator
turn back into acceleration is their calibration, not ours. Samples beyond full scale are clipped and counted.
"""

from __future__ import annotations

import logging
import threading
import wave
from collections import deque
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

RATE_HZ = 1000
#: default acceleration at full scale, m/s² (HaTT's strongest textures peak near 30 m/s²)
FULL_SCALE = 40.0


def to_unit(accel: np.ndarray, full_scale: float) -> tuple[np.ndarray, int]:
    """(n,) m/s² → ((n,) in [−1, 1], how many samples were clipped)."""
    x = np.asarray(accel, float) / full_scale
    clipped = int(np.count_nonzero(np.abs(x) > 1.0))
    return np.clip(x, -1.0, 1.0), clipped


class WavOutput:
    """A mono 16-bit WAV at 1 kHz (the vibration as rendered, no resampling)."""

    def __init__(self, path: str | Path, full_scale: float = FULL_SCALE) -> None:
        if not full_scale > 0:
            raise ValueError(f"full_scale must be > 0 m/s², got {full_scale}")
        self.path, self.full_scale = Path(path), full_scale
        # the file first: wave.open(path) failing half-built leaves a writer whose __del__ prints a traceback
        self._file = self.path.open("wb")  # noqa: SIM115 - closed by close()
        self._wav = wave.open(self._file, "wb")  # noqa: SIM115 - closed by close()
        self._wav.setnchannels(1)
        self._wav.setsampwidth(2)
        self._wav.setframerate(RATE_HZ)
        self.samples = self.clipped = 0
        self.name = f"wav:{self.path}"

    def write(self, accel: np.ndarray, friction: np.ndarray) -> None:
        x, clipped = to_unit(accel, self.full_scale)
        self._wav.writeframes(np.rint(x * 32767).astype("<i2").tobytes())
        self.samples += x.size
        self.clipped += clipped

    def close(self) -> None:
        self._wav.close()  # writes the header's sizes; the file is ours to close
        self._file.close()


def load_sounddevice():
    """The sounddevice module; RuntimeError saying how to get it when it or PortAudio is missing."""
    try:
        import sounddevice  # optional: only sound output needs it
    except ImportError:
        raise RuntimeError(
            "sound output needs the sounddevice package: pip install 'hapticlink[operator]' (or sounddevice)"
        ) from None
    except OSError as exc:  # the package is there, the PortAudio library is not
        raise RuntimeError(
            f"sound output needs the PortAudio library ({exc}): e.g. apt-get install libportaudio2"
        ) from None
    return sounddevice


class SoundOutput:
    """The sound card (voice-coil actuators are driven through an audio amplifier): the 1 kHz vibration, upsampled
    to the card's rate by linear interpolation (images above 500 Hz stay below −30 dB for a voice coil's band),
    played from a buffer of at most `buffer_s` (older samples are dropped: the renderer runs ahead only when the
    card stalls). Underruns play silence and are counted."""

    def __init__(
        self, device: str | int | None = None, full_scale: float = FULL_SCALE, rate_hz: int = 48_000, buffer_s=0.1
    ) -> None:
        sd = load_sounddevice()
        if not sd.query_devices():
            raise RuntimeError("sound output: PortAudio finds no audio device on this machine")
        if rate_hz % RATE_HZ:
            raise ValueError(f"the sound card rate must be a multiple of {RATE_HZ} Hz, got {rate_hz}")
        self.full_scale, self.up = full_scale, rate_hz // RATE_HZ
        self._buffer: deque[float] = deque(maxlen=int(buffer_s * rate_hz))
        self._lock = threading.Lock()
        self._last = 0.0
        self.samples = self.clipped = self.underruns = 0
        self.name = f"sound:{device if device is not None else 'default'}"
        self._stream = sd.OutputStream(
            samplerate=rate_hz, channels=1, dtype="float32", device=device, callback=self._play
        )
        self._stream.start()

    def _play(self, out, frames, time_info, status) -> None:  # PortAudio's thread
        with self._lock:
            n = min(frames, len(self._buffer))
            out[:n, 0] = [self._buffer.popleft() for _ in range(n)]
        if n < frames:
            out[n:, 0] = 0.0
            self.underruns += 1

    def write(self, accel: np.ndarray, friction: np.ndarray) -> None:
        x, clipped = to_unit(accel, self.full_scale)
        if x.size == 0:
            return
        points = np.concatenate([[self._last], x])
        fine = np.interp(np.arange(1, x.size * self.up + 1) / self.up, np.arange(points.size), points)
        self._last = float(x[-1])
        with self._lock:
            self._buffer.extend(fine.tolist())
        self.samples += x.size
        self.clipped += clipped

    def close(self) -> None:
        self._stream.stop()
        self._stream.close()


class SerialOutput:
    """The operator's device on a serial port: one line per sample, `<counter>,<accel m/s²>,<friction N>\\n`,
    after a header `#HLO rate=1000 accel=m/s^2 friction=N` (the device renders the vibration on its actuator
    and the friction force on its motors, if it can)."""

    HEADER = b"#HLO rate=1000 accel=m/s^2 friction=N\n"

    def __init__(self, port: str, baudrate: int = 921_600) -> None:
        import serial  # pyserial, as drivers/serial_board.py

        self._serial = serial.Serial(port, baudrate, timeout=0.1, write_timeout=1.0)
        self._serial.write(self.HEADER)
        self.samples = 0
        self.name = f"serial:{port}"

    def write(self, accel: np.ndarray, friction: np.ndarray) -> None:
        counters = (self.samples + np.arange(accel.size)) % 65536
        lines = "".join(f"{c},{a:.5f},{f:.4f}\n" for c, a, f in zip(counters, accel, friction, strict=True))
        self._serial.write(lines.encode())
        self.samples += accel.size

    def close(self) -> None:
        self._serial.close()
