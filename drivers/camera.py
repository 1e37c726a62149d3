"""Camera frames: image files, a watched directory, or an OpenCV camera (when cv2 is installed).

Frames carry encoded bytes (PNG or JPEG, what the service accepts) and their content type.
Other image formats Pillow reads (BMP, TIFF, WebP, …) are re-encoded as PNG.
"""

from __future__ import annotations

import asyncio
import io
import logging
import os
import threading
import time
from collections.abc import AsyncIterator, Callable, Sequence
from pathlib import Path

import numpy as np

from drivers.blocks import DEFAULT_MAX_BODY_BYTES, Frame, FrameTooLarge, check_frame_pixels, frame_bomb
from drivers.source import Item, ThreadedSource, check_positive, paced

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = frozenset({".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".gif"})


def sniff_content_type(data: bytes) -> str | None:
    """'image/png' or 'image/jpeg' from the magic bytes, else None."""
    if data.startswith(b"\x89PNG\r\n\x1a\n"):
        return "image/png"
    if data.startswith(b"\xff\xd8\xff"):
        return "image/jpeg"
    return None


def png_bytes(image: np.ndarray) -> bytes:
    """Encode a uint8 image, (h, w) grey or (h, w, 3) RGB, as PNG."""
    from PIL import Image

    arr = np.asarray(image)
    if arr.dtype != np.uint8 or arr.ndim not in (2, 3) or (arr.ndim == 3 and arr.shape[2] not in (3, 4)):
        raise ValueError(f"image must be uint8 (h, w), (h, w, 3) or (h, w, 4), got {arr.dtype} {arr.shape}")
    buf = io.BytesIO()
    Image.fromarray(arr).save(buf, format="PNG")
    return buf.getvalue()


def frame_gray(data: bytes) -> np.ndarray:
    """Encoded image → (H, W) float32 grey in [0, 1] (8-bit luma); ValueError when Pillow cannot read it."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(io.BytesIO(data)) as img:
            return np.asarray(img.convert("L"), dtype=np.float32) / np.float32(255.0)
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError, Image.DecompressionBombError) as exc:
        raise ValueError(f"not a readable image ({exc})") from None


def encode_image(data: bytes, label: str = "image") -> tuple[bytes, str]:
    """(bytes, content type) ready to send: complete PNG/JPEG as is, other formats as PNG.

    ValueError when the data is not a complete image Pillow can read (truncated, not an image), or one the service
    would refuse: over MAX_FRAME_PIXELS (judged from its header, before decoding) or, encoded, over
    DEFAULT_MAX_BODY_BYTES.
    """
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(io.BytesIO(data)) as img:
            check_frame_pixels(*img.size, label)  # from the header: nothing decoded yet
            img.load()  # decodes fully: a half-written file fails here
            fmt = img.format
            if fmt in ("PNG", "JPEG") and sniff_content_type(data):
                out, ctype = data, f"image/{fmt.lower()}"
            else:
                buf = io.BytesIO()
                img.save(buf, format="PNG")
                out, ctype = buf.getvalue(), "image/png"
    except FrameTooLarge:
        raise
    except Image.DecompressionBombError as exc:
        raise frame_bomb(exc, label) from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        raise ValueError(f"{label}: not a complete image ({exc})") from None
    if len(out) > DEFAULT_MAX_BODY_BYTES:
        raise ValueError(
            f"{label}: {len(out) / 2**20:.1f} MiB encoded; the service takes at most "
            f"{DEFAULT_MAX_BODY_BYTES / 2**20:g} MiB a request by default (save it as JPEG, or smaller)"
        )
    return out, ctype


def frame_from_file(path: str | Path, t: float = 0.0) -> Frame:
    """A Frame holding the file's image (re-encoded as PNG unless PNG/JPEG); ValueError if unreadable."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"image not found: {path}")
    data, ctype = encode_image(path.read_bytes(), str(path))
    return Frame(t=t, image=data, content_type=ctype, meta={"path": str(path)})


def _warn_skip_once(source: str, warned: set[str], key: str, what: str, why: str) -> bool:
    """Say once per key why `what` is not sent (a source skips what the service would refuse); True the first time."""
    if key in warned:
        return False
    warned.add(key)
    log.warning("%s: skipping %s: %s", source, what, why)
    return True


class ImageFilesSource:
    """Frames from a list of image files, one every interval_s seconds (stream time i·interval_s).

    Files are checked to exist when constructed and read (off the event loop) when their turn comes.
    loop=True cycles through them forever.
    """

    def __init__(
        self, paths: Sequence[str | Path], interval_s: float = 1.0, realtime: bool = True, loop: bool = False
    ) -> None:
        self.paths = [Path(p) for p in paths]
        if not self.paths:
            raise ValueError("ImageFilesSource needs at least one image path")
        missing = [str(p) for p in self.paths if not p.is_file()]
        if missing:
            raise ValueError(f"image file(s) not found: {missing}")
        check_positive("interval_s", interval_s)
        self.interval_s = interval_s
        self.realtime = realtime
        self.loop = loop
        self.name = f"images:{len(self.paths)}"
        self._closed = False

    async def _frames(self) -> AsyncIterator[Frame]:
        i = 0
        while not self._closed:
            for path in self.paths:
                yield await asyncio.to_thread(frame_from_file, path, i * self.interval_s)
                i += 1
            if not self.loop:
                return

    def __aiter__(self) -> AsyncIterator[Item]:
        return paced(self._frames(), self.realtime).__aiter__()

    async def aclose(self) -> None:
        self._closed = True


class WatchedDirectorySource:
    """A Frame for each image file that appears in a directory (a camera app saving snapshots).

    Polls every poll_s seconds; new or changed files are taken oldest first (mtime, then name).
    A file is sent once its size has stayed the same for one poll and it decodes completely;
    partial files are retried while they change, non-image names and files that never decode
    are skipped with one warning each. Frame.t: file mtime − the source's start time (s);
    meta carries the file name. include_existing=False ignores files present at start.
    """

    def __init__(self, directory: str | Path, poll_s: float = 0.5, include_existing: bool = True) -> None:
        self.directory = Path(directory)
        if not self.directory.is_dir():
            raise ValueError(f"not a directory: {self.directory}")
        check_positive("poll_s", poll_s)
        self.poll_s = poll_s
        self.include_existing = include_existing
        self.name = f"camera-dir:{self.directory}"
        self._closed = asyncio.Event()
        self._done: dict[str, tuple[float, int]] = {}  # name → (mtime, size) sent or given up on
        self._warned: set[str] = set()
        self._gone = False  # the directory has disappeared (said once)
        self.skipped = 0

    def _scan(self) -> dict[str, tuple[float, int]]:
        """name → (mtime, size) of the directory's regular files (blocking: run in a thread)."""
        out = {}
        with os.scandir(self.directory) as it:
            for entry in it:
                try:
                    if entry.is_file():
                        st = entry.stat()
                        out[entry.name] = (st.st_mtime, st.st_size)
                except FileNotFoundError:
                    continue  # removed while we looked
        return out

    def _warn_once(self, name: str, why: str) -> None:
        if _warn_skip_once(self.name, self._warned, name, name, why):
            self.skipped += 1

    def _read(self, name: str, t: float) -> Frame | str:
        """The file as a Frame, or why it cannot be sent (yet: a partial file)."""
        try:
            data, ctype = encode_image((self.directory / name).read_bytes(), name)
        except (ValueError, OSError) as exc:
            return str(exc).removeprefix(f"{name}: ")
        return Frame(t=t, image=data, content_type=ctype, meta={"path": name})

    async def _look(self) -> dict[str, tuple[float, int]]:
        """`_scan` off the event loop; a directory that is gone (moved, unmounted) reads as empty until it is back,
        said once each way."""
        try:
            seen = await asyncio.to_thread(self._scan)
        except (FileNotFoundError, NotADirectoryError) as exc:
            if not self._gone:
                self._gone = True
                log.warning("%s: the directory is gone (%s); watching for it to come back", self.name, exc)
            return {}
        if self._gone:
            self._gone = False
            log.warning("%s: the directory is back", self.name)
        return seen

    async def _frames(self) -> AsyncIterator[Frame]:
        start = time.time()
        seen = await self._look()
        if not self.include_existing:
            self._done.update(seen)
            seen = {}
        previous: dict[str, tuple[float, int]] = {}
        while not self._closed.is_set():
            for name, stamp in sorted(seen.items(), key=lambda kv: (kv[1][0], kv[0])):
                if self._done.get(name) == stamp or name.startswith("."):
                    continue
                if Path(name).suffix.lower() not in IMAGE_SUFFIXES:
                    self._warn_once(name, "not an image file name")
                    self._done[name] = stamp
                    continue
                if previous.get(name) != stamp:
                    continue  # new or still changing: look again next poll
                frame = await asyncio.to_thread(self._read, name, stamp[0] - start)
                self._done[name] = stamp  # a changed file (new mtime/size) is tried again
                if isinstance(frame, str):
                    self._warn_once(name, frame)
                    continue
                yield frame
            previous = seen
            try:
                await asyncio.wait_for(self._closed.wait(), self.poll_s)
            except TimeoutError:
                pass
            seen = await self._look()

    def __aiter__(self) -> AsyncIterator[Item]:
        return self._frames().__aiter__()

    async def aclose(self) -> None:
        self._closed.set()


class OpenCVCameraSource(ThreadedSource):
    """JPEG frames from an OpenCV camera (cv2.VideoCapture(index)), one every interval_s seconds.

    Needs OpenCV (`pip install opencv-python-headless`); ImportError says so otherwise.
    Frame.t: seconds since the first capture. A frame the service would refuse (encode_image) is skipped and
    counted in `skipped`, with one warning for each kind of refusal: a camera's every frame would be the same.
    """

    def __init__(self, index: int = 0, interval_s: float = 1.0, jpeg_quality: int = 90) -> None:
        try:
            import cv2  # noqa: F401 - checked here so the error comes at construction
        except ImportError:
            raise ImportError(
                "OpenCVCameraSource needs OpenCV: pip install opencv-python-headless (or use camera-dir / image files)"
            ) from None
        super().__init__(queue_size=4)
        check_positive("interval_s", interval_s)
        if not 1 <= jpeg_quality <= 100:
            raise ValueError(f"jpeg_quality must lie in [1, 100], got {jpeg_quality}")
        self.index = index
        self.interval_s = interval_s
        self.jpeg_quality = jpeg_quality
        self.name = f"opencv:{index}"
        self.skipped = 0
        self._warned: set[str] = set()

    def _frame(self, jpeg: bytes, t: float) -> Frame | None:
        """The encoded capture as a Frame, or None (counted, said once) when the service would refuse it."""
        try:
            data, ctype = encode_image(jpeg, "frame")
        except ValueError as exc:
            self.skipped += 1
            # keyed by the kind of refusal: too many pixels (the camera's mode), too many bytes (the scene)
            why = str(exc).removeprefix("frame: ")
            _warn_skip_once(self.name, self._warned, type(exc).__name__, "frames like this", why)
            return None
        return Frame(t=t, image=data, content_type=ctype, meta={"camera": self.index})

    def _produce(self, stop: threading.Event, emit: Callable[[Item], None]) -> None:
        import cv2

        cap = cv2.VideoCapture(self.index)
        try:
            if not cap.isOpened():
                raise OSError(f"OpenCV could not open camera {self.index}")
            t0 = time.monotonic()
            while not stop.is_set():
                ok, image = cap.read()
                if not ok:
                    raise OSError(f"camera {self.index} stopped delivering frames")
                ok, jpeg = cv2.imencode(".jpg", image, [int(cv2.IMWRITE_JPEG_QUALITY), self.jpeg_quality])
                frame = self._frame(jpeg.tobytes(), time.monotonic() - t0) if ok else None
                if frame is not None:
                    emit(frame)
                stop.wait(self.interval_s)
        finally:
            cap.release()
