"""ReplaySource over a small dataset on disk; SimulatedSource over a procedural texture."""

from __future__ import annotations

import asyncio
import dataclasses
import io
import json
import logging

import numpy as np
import pytest
from PIL import Image

from drivers.blocks import Frame, SampleBlock, TapBlock
from drivers.camera import png_bytes
from drivers.replay import ReplaySource
from drivers.simulated import SimulatedSource
from texture_library.library import Library, add_entry
from texture_library.procedural import make_world
from texture_library.recording import Recording, make_channel, save_recording


def blocks_of(items) -> list[SampleBlock]:
    return [i for i in items if isinstance(i, SampleBlock)]


@pytest.fixture
def dataset(tmp_path):
    """DIR/textures/t1 with one multi-rate recording (accel 2 kHz in g, force 500 Hz, position 250 Hz) and an image."""
    rng = np.random.default_rng(0)
    rec = Recording(
        accel=make_channel("accel", rng.standard_normal((2000, 3)), 2000.0, "g"),
        force=make_channel("force", rng.uniform(1, 2, 500), 500.0),
        position=make_channel("position", np.cumsum(rng.uniform(0, 0.4, (250, 2)), axis=0), 250.0),
    )
    folder = tmp_path / "textures" / "t1"
    folder.mkdir(parents=True)
    save_recording(folder / "recording_000.npz", rec)
    image = png_bytes(rng.integers(0, 255, (24, 24), dtype=np.uint8))
    (folder / "image_000.png").write_bytes(image)
    meta = {"images": ["image_000.png", str(tmp_path / "elsewhere" / "gone.png")], "recordings": ["recording_000.npz"]}
    (folder / "meta.json").write_text(json.dumps(meta))
    return tmp_path, rec, image


def test_replay_sends_the_image_then_the_recording_in_canonical_units(kit, dataset, caplog):
    root, rec, image = dataset
    with caplog.at_level(logging.WARNING, logger="drivers.replay"):
        source = ReplaySource.from_dataset(root, "t1", realtime=False, block_s=0.05)
    assert "gone.png" in caplog.text, "a missing image is skipped with a warning"
    items = asyncio.run(kit.take(source))
    assert isinstance(items[0], Frame) and items[0].image == image and items[0].content_type == "image/png"
    blocks = blocks_of(items)
    assert len(blocks) == 20 and [b.seq for b in blocks] == list(range(20))
    for kind, ch in rec.channels().items():
        np.testing.assert_array_equal(kit.concat(blocks, kind), ch.data.astype(np.float32))
    assert blocks[0].channels["accel"].units == "m/s^2", "the recording holds canonical units (g converted on load)"
    assert [b.channels["position"].data.shape for b in blocks[:2]] == [(13, 2), (12, 2)], (
        "12.5 samples per block at 250 Hz: remainders carried"
    )


def test_replay_loops_with_running_time(kit, dataset):
    root, _, _ = dataset
    source = ReplaySource.from_dataset(root, "t1", realtime=False, block_s=0.1, loop=True, with_images=False)
    blocks = blocks_of(asyncio.run(kit.take(source, 25)))
    t0 = [b.t0 for b in blocks]
    assert t0 == pytest.approx([0.1 * k for k in range(25)]), "pass 2 starts where pass 1 ended"
    first, second = kit.concat(blocks[:10], "accel"), kit.concat(blocks[10:20], "accel")
    np.testing.assert_array_equal(first, second)


def test_replay_names_bad_arguments(dataset):
    root, rec, _ = dataset
    with pytest.raises(ValueError, match="no texture 'nope'"):
        ReplaySource.from_dataset(root, "nope")
    with pytest.raises(ValueError, match="not a valid name"):
        ReplaySource.from_dataset(root, "../t1")
    with pytest.raises(ValueError, match="1 recording"):
        ReplaySource.from_dataset(root, "t1", recording=3)
    with pytest.raises(ValueError, match="block_s"):
        ReplaySource(rec, block_s=-1)
    # a meta.json a hand edit broke: a TypeError deep inside, or a string of images read letter by letter
    meta_path = root / "textures" / "t1" / "meta.json"
    for meta, why in [
        ({"recordings": [7]}, r"recordings\[0\] must be a file name, got 7"),
        ({"recordings": ["recording_000.npz"], "images": "image_000.png"}, "images must be a list of file names"),
        ({"recordings": ["recording_000.npz"], "images": [None]}, "images must be a list of file names"),
    ]:
        meta_path.write_text(json.dumps(meta))
        with pytest.raises(ValueError, match=why):
            ReplaySource.from_dataset(root, "t1")


def test_replay_says_when_its_channels_cover_different_spans(caplog):
    rng = np.random.default_rng(0)
    rec = Recording(
        accel=make_channel("accel", rng.standard_normal((10_000, 3)), 1000.0),
        force=make_channel("force", rng.uniform(1, 2, 100), 1000.0),
        speed=make_channel("speed", rng.uniform(20, 80, 10_000), 1000.0),
    )
    with caplog.at_level(logging.WARNING, logger="drivers.replay"):
        ReplaySource(rec, realtime=False, name="short-force")
    assert "short-force: its channels cover different spans (accel 10.00 s, force 0.10 s" in caplog.text
    assert "only the first 0.10 s has every channel" in caplog.text


@pytest.fixture(scope="module")
def texture():
    return make_world(1, seed=11)[0]


def test_simulated_robot_strokes_the_texture_continuously(kit, texture):
    image = png_bytes(texture.image)
    source = SimulatedSource(
        texture.model, image, seed=3, realtime=False, chunk_s=1.0, duration_s=3.0, frame_every_s=1.0
    )
    items = asyncio.run(kit.take(source))
    frames = [i for i in items if isinstance(i, Frame)]
    assert [f.t for f in frames] == [0.0, 1.0, 2.0] and isinstance(items[0], Frame) and frames[0].image == image
    blocks = blocks_of(items)
    assert [b.seq for b in blocks] == list(range(len(blocks)))
    # contiguous across chunks: each block starts where the previous one ended
    ends = [b.t0 + b.channels["speed"].duration_s for b in blocks]
    assert [b.t0 for b in blocks[1:]] == pytest.approx(ends[:-1])
    accel, force, speed = kit.concat(blocks, "accel"), kit.concat(blocks, "force"), kit.concat(blocks, "speed")
    assert accel.shape == (3000, 3) and force.shape == (3000, 3) and speed.shape == (3000,)
    assert {(k, c.units, c.rate_hz) for b in blocks for k, c in b.channels.items()} == {
        ("accel", "m/s^2", 1000.0),
        ("force", "N", 1000.0),
        ("speed", "mm/s", 1000.0),
    }
    assert 20.0 - 1e-3 <= speed.min() and speed.max() <= 0.95 * texture.model.max_speed + 1e-3
    assert 0.2 <= force[:, 2].min() + 0.05 and force[:, 2].max() <= 0.95 * texture.model.max_force + 0.05
    # one fixed sensor mounting for the whole run: gravity stays one vector of 1 g across chunks
    per_second = [np.linalg.norm(accel[k * 1000 : (k + 1) * 1000].mean(axis=0)) for k in range(3)]
    assert per_second == pytest.approx([9.81] * 3, abs=0.3)
    drift = np.linalg.norm(accel[:1000].mean(axis=0) - accel[2000:].mean(axis=0))
    assert drift < 1.5, "a re-drawn mounting would turn gravity by ~10 m/s² between chunks"


def test_simulated_source_is_reproducible_from_its_seed(kit, texture):
    def run(seed):
        src = SimulatedSource(texture.model, seed=seed, realtime=False, chunk_s=0.5, duration_s=1.2)
        return kit.concat(blocks_of(asyncio.run(kit.take(src))), "accel")

    a, b, c = run(5), run(5), run(6)
    np.testing.assert_array_equal(a, b)
    assert a.shape == c.shape and not np.array_equal(a, c)


def test_simulated_from_library_with_an_image_file(kit, texture, tmp_path):
    lib_dir = tmp_path / "lib"
    entry = add_entry(
        lib_dir,
        "t-11",
        texture.model,
        name="t 11",
        group=texture.group,
        ratings=texture.truth,
        ratings_source="ground-truth",
        provenance="procedural",
        licence="CC0",
        image_path="images/t-11.png",
    )
    Library(lib_dir, "test", [entry]).save()
    (lib_dir / "images").mkdir()
    (lib_dir / "images" / "t-11.png").write_bytes(png_bytes(texture.image))
    own = asyncio.run(kit.take(SimulatedSource.from_library(lib_dir, "t-11", realtime=False, duration_s=0.1)))
    assert own[0].content_type == "image/png" and own[0].image == png_bytes(texture.image), "the entry's own image"
    jpeg = io.BytesIO()
    Image.fromarray(texture.image).save(jpeg, format="JPEG")
    (tmp_path / "t11.jpg").write_bytes(jpeg.getvalue())
    source = SimulatedSource.from_library(
        lib_dir, "t-11", image_path=tmp_path / "t11.jpg", realtime=False, duration_s=0.1
    )
    items = asyncio.run(kit.take(source))
    assert items[0].content_type == "image/jpeg" and items[0].image == jpeg.getvalue()
    assert sum(b.channels["accel"].data.shape[0] for b in blocks_of(items)) == 100
    assert source.name == "simulated:t-11"
    with pytest.raises(ValueError, match="no entry 'nope'"):
        SimulatedSource.from_library(lib_dir, "nope")
    with pytest.raises(ValueError, match="PNG or JPEG"):
        SimulatedSource(texture.model, b"GIF89a...")


def test_simulated_robot_taps_before_stroking(kit, texture):
    """taps=True: one tap block first — the texture's tap transients as recorded, at 1 kHz — then the stroke
    (seq 1 on); a model without tap transients cannot tap."""
    source = SimulatedSource(texture.model, seed=3, realtime=False, duration_s=0.5, taps=True)
    items = asyncio.run(kit.take(source))
    tap, blocks = items[0], blocks_of(items)
    assert isinstance(tap, TapBlock) and (tap.t0, tap.seq, tap.accel.rate_hz, tap.accel.units) == (
        0.0,
        0,
        1000.0,
        "m/s^2",
    )
    np.testing.assert_array_equal(tap.speeds, texture.model.taps.speeds)
    np.testing.assert_allclose(tap.accel.data, texture.model.taps.accel, rtol=1e-6, atol=1e-6)
    assert [b.seq for b in blocks] == list(range(1, len(blocks) + 1)) and blocks[0].t0 == 0.0
    assert not any(isinstance(i, TapBlock) for i in items[1:])
    with pytest.raises(ValueError, match="no tap transients"):
        SimulatedSource(dataclasses.replace(texture.model, taps=None), taps=True)
