"""Image files, a watched directory, and the OpenCV camera (its error without cv2; its frames through a stand-in)."""

from __future__ import annotations

import asyncio
import importlib.util
import io
import logging
import sys
import types

import numpy as np
import pytest
from PIL import Image

from drivers.camera import ImageFilesSource, OpenCVCameraSource, WatchedDirectorySource, encode_image, png_bytes


def image_bytes(fmt: str, seed: int = 0) -> bytes:
    rng = np.random.default_rng(seed)
    buf = io.BytesIO()
    Image.fromarray(rng.integers(0, 255, (32, 40, 3), dtype=np.uint8)).save(buf, format=fmt)
    return buf.getvalue()


def test_image_files_become_frames_with_their_content_type(tmp_path):
    png, jpeg, bmp = image_bytes("PNG"), image_bytes("JPEG"), image_bytes("BMP")
    for name, data in (("a.png", png), ("b.jpg", jpeg), ("c.bmp", bmp)):
        (tmp_path / name).write_bytes(data)
    source = ImageFilesSource(
        [tmp_path / "a.png", tmp_path / "b.jpg", tmp_path / "c.bmp"], interval_s=0.5, realtime=False
    )

    async def main():
        return [f async for f in source]

    frames = asyncio.run(main())
    assert [(f.t, f.content_type) for f in frames] == [(0.0, "image/png"), (0.5, "image/jpeg"), (1.0, "image/png")]
    assert frames[0].image == png and frames[1].image == jpeg
    assert np.array_equal(
        np.asarray(Image.open(io.BytesIO(frames[2].image))), np.asarray(Image.open(io.BytesIO(bmp)))
    ), "BMP re-encoded losslessly"
    with pytest.raises(ValueError, match="not found"):
        ImageFilesSource([tmp_path / "missing.png"])
    with pytest.raises(ValueError, match="interval_s"):
        ImageFilesSource([tmp_path / "a.png"], interval_s=0)


def pumped(source) -> tuple[asyncio.Queue, asyncio.Task]:
    """(a queue, the task that moves the source's frames into it); call inside the running loop."""
    frames: asyncio.Queue = asyncio.Queue()

    async def pump() -> None:
        async for frame in source:
            await frames.put(frame)

    return frames, asyncio.create_task(pump())


async def closed(source, task: asyncio.Task) -> None:
    """Close the source; its pump then ends (a hang guard of 10 s)."""
    await source.aclose()
    await asyncio.wait_for(task, 10)


def append(path, data: bytes) -> None:
    with open(path, "ab") as f:
        f.write(data)


def test_watched_directory_sends_new_images_and_skips_partial_and_other_files(tmp_path, caplog):
    first, later, jpeg = image_bytes("PNG", 1), image_bytes("PNG", 2), image_bytes("JPEG", 3)
    (tmp_path / "000.png").write_bytes(first)
    source = WatchedDirectorySource(tmp_path, poll_s=0.02)

    async def main():
        frames, task = pumped(source)
        got = [await asyncio.wait_for(frames.get(), 10)]  # the file that was there at start
        # a camera app writing a file: half of it first (must not be sent), then the rest
        (tmp_path / "001.png").write_bytes(later[: len(later) // 2])
        while source.skipped < 1:
            await asyncio.sleep(0.01)
        (tmp_path / "notes.txt").write_text("not an image")
        await asyncio.to_thread(append, tmp_path / "001.png", later[len(later) // 2 :])
        got.append(await asyncio.wait_for(frames.get(), 10))
        (tmp_path / "002.jpg").write_bytes(jpeg)
        got.append(await asyncio.wait_for(frames.get(), 10))
        await closed(source, task)
        return got

    with caplog.at_level(logging.WARNING, logger="drivers.camera"):
        frames = asyncio.run(main())
    assert [(f.meta["path"], f.content_type) for f in frames] == [
        ("000.png", "image/png"),
        ("001.png", "image/png"),
        ("002.jpg", "image/jpeg"),
    ]
    assert frames[0].image == first and frames[1].image == later and frames[2].image == jpeg
    assert "skipping 001.png: not a complete image" in caplog.text and "notes.txt" in caplog.text


def huge_png(width: int, height: int) -> bytes:
    """A PNG of width × height black pixels: a few kB on disk, any size decoded."""
    buf = io.BytesIO()
    Image.new("1", (width, height)).save(buf, format="PNG")
    return buf.getvalue()


def test_frames_the_service_would_refuse_are_refused_here_naming_why():
    with pytest.raises(ValueError, match="5000×4000 pixels; the service decodes at most 16777216"):
        encode_image(huge_png(5000, 4000), "big.png")
    # past Pillow's own bomb guard: the same refusal, naming the service's limit, not Pillow's
    with pytest.raises(ValueError, match=r"^bomb.png: 400000000 pixels; the service decodes at most 16777216"):
        encode_image(huge_png(20000, 20000), "bomb.png")
    noise = np.random.default_rng(0).integers(0, 255, (2048, 2048, 3), dtype=np.uint8)
    buf = io.BytesIO()
    Image.fromarray(noise).save(buf, format="BMP")  # 12 MiB once PNG: over the service's default body limit
    with pytest.raises(ValueError, match=r"noise.bmp: 1\d\.\d MiB encoded; the service takes at most 8 MiB"):
        encode_image(buf.getvalue(), "noise.bmp")


def test_watched_directory_survives_a_bomb_and_its_own_disappearance(tmp_path, caplog):
    watched = tmp_path / "snapshots"
    watched.mkdir()
    (watched / "000.png").write_bytes(huge_png(20000, 20000))
    source = WatchedDirectorySource(watched, poll_s=0.02)

    async def main():
        frames, task = pumped(source)
        while source.skipped < 1:  # the bomb: skipped, not raised
            await asyncio.sleep(0.01)
        (watched / "001.png").write_bytes(image_bytes("PNG", 1))
        got = [await asyncio.wait_for(frames.get(), 10)]
        watched.rename(tmp_path / "moved")  # the camera app moves its folder away ...
        await asyncio.sleep(0.2)
        watched.mkdir()  # ... and makes a new one
        (watched / "002.png").write_bytes(image_bytes("PNG", 2))
        got.append(await asyncio.wait_for(frames.get(), 10))
        await closed(source, task)
        return got

    with caplog.at_level(logging.WARNING, logger="drivers.camera"):
        frames = asyncio.run(main())
    assert [f.meta["path"] for f in frames] == ["001.png", "002.png"]
    assert "skipping 000.png: 400000000 pixels; the service decodes at most 16777216" in caplog.text
    assert caplog.text.count("the directory is gone") == 1 and caplog.text.count("the directory is back") == 1


def test_watched_directory_can_ignore_what_is_already_there(tmp_path):
    (tmp_path / "old.png").write_bytes(image_bytes("PNG"))
    source = WatchedDirectorySource(tmp_path, poll_s=0.02, include_existing=False)

    async def main():
        it = aiter(source)
        nxt = asyncio.ensure_future(anext(it))
        await asyncio.sleep(0.1)
        (tmp_path / "new.png").write_bytes(image_bytes("PNG", 5))
        frame = await asyncio.wait_for(nxt, 10)
        await source.aclose()
        return frame

    frame = asyncio.run(main())
    assert frame.meta["path"] == "new.png"
    with pytest.raises(ValueError, match="not a directory"):
        WatchedDirectorySource(tmp_path / "nope")


@pytest.mark.skipif(importlib.util.find_spec("cv2") is not None, reason="OpenCV is installed here")
def test_opencv_camera_without_cv2_says_what_to_install():
    with pytest.raises(ImportError, match="opencv-python-headless"):
        OpenCVCameraSource(0)


def fake_cv2(captures: list[bytes]) -> types.ModuleType:
    """A stand-in for cv2 whose camera delivers `captures` (each already "encoded": imencode hands it back), then
    stops."""
    cv2 = types.ModuleType("cv2")
    cv2.IMWRITE_JPEG_QUALITY = 1  # type: ignore[attr-defined]

    class VideoCapture:
        def __init__(self, index: int) -> None:
            self.left = list(captures)

        def isOpened(self) -> bool:  # noqa: N802 - OpenCV's name
            return True

        def read(self) -> tuple[bool, np.ndarray | None]:
            if not self.left:
                return False, None
            return True, np.frombuffer(self.left.pop(0), np.uint8)

        def release(self) -> None:
            pass

    cv2.VideoCapture = VideoCapture  # type: ignore[attr-defined]
    cv2.imencode = lambda ext, image, params: (True, image)  # type: ignore[attr-defined]
    return cv2


def _until_the_camera_stops(source: OpenCVCameraSource, caplog) -> list:
    """The frames a (fake) camera gave before it stopped delivering, its warnings in caplog."""
    frames = []

    async def main():
        async for frame in source:
            frames.append(frame)

    with caplog.at_level(logging.WARNING, logger="drivers.camera"), pytest.raises(OSError, match="stopped"):
        asyncio.run(main())
    return frames


def test_opencv_camera_skips_frames_the_service_would_refuse_with_one_warning(monkeypatch, caplog):
    """It sent cv2's JPEG unchecked: a camera over 4096×4096 had every frame refused by the service instead."""
    buf = io.BytesIO()
    Image.new("L", (5000, 4000)).save(buf, format="JPEG")
    small, huge = image_bytes("JPEG"), buf.getvalue()
    monkeypatch.setitem(sys.modules, "cv2", fake_cv2([small, huge, huge, small]))
    source = OpenCVCameraSource(0, interval_s=0.001)
    frames = _until_the_camera_stops(source, caplog)
    assert [f.image for f in frames] == [small, small] and source.skipped == 2
    assert caplog.text.count("skipping") == 1
    assert "opencv:0: skipping frames like this: 5000×4000 pixels; the service decodes at most" in caplog.text


def test_opencv_camera_skips_a_frame_over_the_body_limit(monkeypatch, caplog):
    small = image_bytes("JPEG")
    larger = small + b"\0" * 64  # a reader ignores what follows a JPEG's end marker
    monkeypatch.setattr("drivers.camera.DEFAULT_MAX_BODY_BYTES", len(small))
    monkeypatch.setitem(sys.modules, "cv2", fake_cv2([larger, small]))
    source = OpenCVCameraSource(0, interval_s=0.001)
    frames = _until_the_camera_stops(source, caplog)
    assert [f.image for f in frames] == [small] and source.skipped == 1
    assert "opencv:0: skipping frames like this: 0.0 MiB encoded; the service takes at most" in caplog.text


def test_encoding_helpers():
    img = np.arange(64, dtype=np.uint8).reshape(8, 8)
    data, ctype = encode_image(png_bytes(img))
    assert ctype == "image/png" and np.array_equal(np.asarray(Image.open(io.BytesIO(data))), img)
    with pytest.raises(ValueError, match="not a complete image"):
        encode_image(png_bytes(img)[:40])
    with pytest.raises(ValueError, match="uint8"):
        png_bytes(img.astype(float))
