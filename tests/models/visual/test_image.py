import io

import numpy as np
import pytest
from PIL import Image

from models.visual.image import array_to_gray, load_image


def _png_bytes(image: Image.Image) -> bytes:
    buffer = io.BytesIO()
    image.save(buffer, format="PNG")
    return buffer.getvalue()


def test_8bit_png_path_loads_exactly(tmp_path):
    pixels = np.random.default_rng(0).integers(0, 256, size=(230, 240), dtype=np.uint8)
    path = tmp_path / "tex.png"
    Image.fromarray(pixels, mode="L").save(path)
    gray = load_image(path)
    assert gray.shape == (230, 240) and gray.dtype == np.float32
    np.testing.assert_array_equal(gray, pixels.astype(np.float32) / 255.0)
    # str paths and bytes give the same array
    np.testing.assert_array_equal(load_image(str(path)), gray)
    np.testing.assert_array_equal(load_image(path.read_bytes()), gray)


def test_16bit_png_keeps_precision():
    pixels = np.random.default_rng(1).integers(0, 65536, size=(224, 224), dtype=np.uint16)
    gray = load_image(_png_bytes(Image.fromarray(pixels)))
    np.testing.assert_allclose(gray, pixels / 65535.0, atol=1e-7)


def test_rgb_png_and_rgb_array_agree_up_to_8bit_rounding():
    rgb = np.random.default_rng(2).integers(0, 256, size=(224, 250, 3), dtype=np.uint8)
    from_png = load_image(_png_bytes(Image.fromarray(rgb, mode="RGB")))
    from_array = load_image(rgb)
    assert from_png.shape == (224, 250)
    assert np.max(np.abs(from_png - from_array)) <= 1.0 / 255.0 + 1e-6


def test_array_conversions():
    base = np.random.default_rng(3).random((224, 224)).astype(np.float32)
    np.testing.assert_array_equal(array_to_gray(base), base)
    rgba = np.dstack([base, base, base, np.zeros_like(base)])
    np.testing.assert_allclose(array_to_gray(rgba), base, atol=1e-6)  # alpha ignored
    u16 = (base * 65535).astype(np.uint16)
    np.testing.assert_allclose(array_to_gray(u16), u16 / 65535.0, atol=1e-7)


def test_pil_image_input():
    image = Image.new("L", (300, 224), color=51)
    gray = load_image(image)
    assert gray.shape == (224, 300)
    np.testing.assert_allclose(gray, 0.2, atol=1e-7)


def test_not_an_image_raises(tmp_path):
    with pytest.raises(ValueError, match="source 20 bytes is not a readable image: cannot identify image file$"):
        load_image(b"definitely not a png")
    text = tmp_path / "notes.png"
    text.write_text("hello")
    with pytest.raises(ValueError, match="not a readable image"):
        load_image(text)
    with pytest.raises(ValueError, match="is not a file"):
        load_image(tmp_path / "missing.png")
    with pytest.raises(ValueError, match="must be a path"):
        load_image(12345)


def test_too_small_raises():
    with pytest.raises(ValueError, match=r"100×80 pixels; need at least 224×224"):
        load_image(np.zeros((80, 100), dtype=np.uint8))
    assert load_image(np.zeros((80, 100), dtype=np.uint8), min_size=64).shape == (80, 100)


@pytest.mark.parametrize(
    ("array", "message"),
    [
        (np.full((224, 224), 1.5, dtype=np.float32), r"\[0, 1\]"),
        (np.full((224, 224), np.nan, dtype=np.float32), "non-finite"),
        (np.zeros((224, 224), dtype=np.int32), "dtype"),
        (np.zeros((2, 224, 224, 3), dtype=np.uint8), "shape"),
        (np.zeros((224, 224, 2), dtype=np.uint8), "shape"),
    ],
)
def test_bad_arrays_raise(array, message):
    with pytest.raises(ValueError, match=message):
        load_image(array)


def test_resize_shorter_keeps_aspect_range_and_constants():
    from models.visual.image import resize_shorter

    rng = np.random.default_rng(0)
    img = rng.random((300, 600)).astype(np.float32)
    out = resize_shorter(img, 150)
    assert out.shape == (150, 300) and out.dtype == np.float32
    assert 0.0 <= out.min() and out.max() <= 1.0
    # antialiased: halving with Pillow's bilinear filter averages 4 taps per axis, weights
    # (1, 3, 3, 1)/8, so white noise keeps a std fraction of Σw² = 0.3125 (per axis, squared: 2-D)
    assert out.std() / img.std() == pytest.approx(0.3125, abs=0.01)
    np.testing.assert_allclose(resize_shorter(np.full((400, 300), 0.25, np.float32), 224), 0.25, atol=1e-6)
    assert resize_shorter(img, 300) is not None and resize_shorter(img, 300).shape == img.shape
    assert resize_shorter(img, 450).shape == (450, 900)  # small frames scale up to the same scale


def test_resize_shorter_rejects_bad_arguments():
    from models.visual.image import resize_shorter

    with pytest.raises(ValueError, match="size"):
        resize_shorter(np.zeros((10, 10), np.float32), 0)
    with pytest.raises(ValueError, match="2-D"):
        resize_shorter(np.zeros((10, 10, 3), np.float32), 5)
