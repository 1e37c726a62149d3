"""Replay a dataset recording as if a robot were stroking the texture now."""

from __future__ import annotations

import json
import logging
import re
from collections.abc import AsyncIterator, Iterator, Sequence
from pathlib import Path

from drivers.blocks import Frame
from drivers.camera import frame_from_file
from drivers.source import Item, blocks_from_arrays, check_positive, default_block_s, paced
from texture_library.channels import CANONICAL_UNITS
from texture_library.recording import Recording, load_recording

log = logging.getLogger(__name__)

_TEXTURE_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


class ReplaySource:
    """A recording's channels in blocks of block_s seconds, in canonical units, paced in real time.

    frames: image frames emitted first (t = 0). loop=True plays the recording again and again,
    cropped to the span all channels cover, with stream time running on (pass k starts at
    k·duration), so the service sees one continuous stroke. speed > 1 plays faster.
    """

    def __init__(
        self,
        recording: Recording,
        block_s: float | None = None,
        realtime: bool = True,
        speed: float = 1.0,
        loop: bool = False,
        frames: Sequence[Frame] = (),
        name: str = "replay",
    ) -> None:
        if block_s is None:
            block_s = default_block_s(c.rate_hz for c in recording.channels().values())
        check_positive("block_s", block_s)
        check_positive("speed", speed, "finite factor")
        if loop and recording.duration_s < block_s:
            raise ValueError(f"recording of {recording.duration_s:.3f} s is shorter than one block; cannot loop it")
        spans = {k: c.duration_s for k, c in recording.channels().items()}
        if max(spans.values()) - min(spans.values()) > block_s:
            # beyond the shortest channel the blocks go without it: the service estimates no window there
            log.warning(
                "%s: its channels cover different spans (%s); only the first %.2f s has every channel",
                name,
                ", ".join(f"{k} {v:.2f} s" for k, v in spans.items()),
                min(spans.values()),
            )
        self.recording = recording
        self.block_s = block_s
        self.realtime = realtime
        self.speed = speed
        self.loop = loop
        self.frames = [f if f.t == 0.0 else Frame(0.0, f.image, f.content_type, f.meta) for f in frames]
        self.name = name
        self._closed = False

    def _items(self) -> Iterator[Item]:
        yield from self.frames
        rec = self.recording.crop(0.0, self.recording.duration_s) if self.loop else self.recording
        seq, t0 = 0, 0.0
        while not self._closed:
            channels = {k: (c.data, c.rate_hz, CANONICAL_UNITS[k]) for k, c in rec.channels().items()}
            for block in blocks_from_arrays(channels, self.block_s, t0=t0, seq0=seq):
                if self._closed:
                    return
                yield block
                seq = block.seq + 1
            if not self.loop:
                return
            t0 += rec.duration_s

    def __aiter__(self) -> AsyncIterator[Item]:
        return paced(self._items(), self.realtime, self.speed).__aiter__()

    async def aclose(self) -> None:
        self._closed = True

    @classmethod
    def from_dataset(
        cls, dataset_dir: str | Path, texture_id: str, recording: int = 0, with_images: bool = True, **kwargs
    ) -> ReplaySource:
        """Replay recording number `recording` of a texture in a hapticlink dataset (docs/dataset-format.md).

        Reads DIR/textures/<id>/meta.json ("recordings": file names inside the texture's folder;
        "images": names inside it or absolute paths); its images become the first frames
        (missing ones are skipped with a warning). kwargs go to ReplaySource.
        """
        root = Path(dataset_dir)
        if not _TEXTURE_ID.match(texture_id):
            raise ValueError(f"texture id {texture_id!r} is not a valid name (letters, digits, _ . -)")
        folder = root / "textures" / texture_id
        meta_path = folder / "meta.json"
        if not meta_path.is_file():
            raise ValueError(f"{root}: no texture {texture_id!r} (missing {meta_path})")
        try:
            meta = json.loads(meta_path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise ValueError(f"{meta_path}: invalid JSON ({exc})") from None
        recs = meta.get("recordings") if isinstance(meta, dict) else None
        if not isinstance(recs, list) or not recs:
            raise ValueError(f"{meta_path}: no recordings listed")
        if not (isinstance(recording, int) and 0 <= recording < len(recs)):
            raise ValueError(
                f"texture {texture_id!r} has {len(recs)} recording(s); index {recording!r} is out of range"
            )
        name = recs[recording]
        if not isinstance(name, str) or not name:
            raise ValueError(f"{meta_path}: recordings[{recording}] must be a file name, got {name!r}")
        images = meta.get("images", [])
        if not isinstance(images, list) or not all(isinstance(i, str) and i for i in images):
            raise ValueError(f"{meta_path}: images must be a list of file names, got {images!r}")
        rec = load_recording(folder / name)
        frames: list[Frame] = []
        for image in images if with_images else []:
            path = Path(image) if Path(image).is_absolute() else folder / image
            try:
                frames.append(frame_from_file(path))
            except ValueError as exc:
                log.warning("replay %s: image skipped: %s", texture_id, exc)
        kwargs.setdefault("name", f"replay:{texture_id}:{recs[recording]}")
        return cls(rec, frames=frames, **kwargs)
