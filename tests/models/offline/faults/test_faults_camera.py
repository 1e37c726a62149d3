"""Known-answer tests of the camera faults."""

import numpy as np
import pytest

from models.offline.faults import camera


def grating(period_px: float, size: int = 256) -> np.ndarray:
    cols = np.arange(size)
    row = 0.5 + 0.4 * np.sin(2 * np.pi * cols / period_px)
    return np.tile(row, (size, 1)).astype(np.float32)


def period_of(img: np.ndarray) -> float:
    row = img[img.shape[0] // 2] - img[img.shape[0] // 2].mean()
    spec = np.abs(np.fft.rfft(row * np.hanning(len(row))))
    return 1.0 / np.fft.rfftfreq(len(row))[1 + np.argmax(spec[1:])]


def test_blur_keeps_the_mean_and_spreads_a_point_by_sigma():
    img = np.zeros((101, 101), np.float32)
    img[50, 50] = 1.0
    out = camera.blur(img, 3.0)
    assert out.sum() == pytest.approx(1.0, rel=1e-4)
    rows = np.arange(101)
    var = np.sum(out.sum(axis=1) * (rows - 50) ** 2)
    assert np.sqrt(var) == pytest.approx(3.0, rel=0.02)
    np.testing.assert_array_equal(camera.blur(img, 0.0), img)


def test_exposure_scales_and_saturates():
    img = np.linspace(0, 1, 10000, dtype=np.float32).reshape(100, 100)
    np.testing.assert_allclose(camera.exposure(img, 0.25), 0.25 * img, atol=1e-7)
    over = camera.exposure(img, 4.0)
    assert np.mean(over == 1.0) == pytest.approx(0.75, abs=0.001)  # every pixel above 1/4 saturates


def test_image_noise_has_the_asked_std():
    img = np.full((200, 200), 0.5, np.float32)
    out = camera.sensor_noise(img, 0.05, np.random.default_rng(0))
    assert float(np.std(out - img)) == pytest.approx(0.05, rel=0.03)


def test_jpeg_error_grows_as_quality_falls():
    rng = np.random.default_rng(0)
    img = np.clip(grating(9.0) + 0.05 * rng.standard_normal((256, 256)), 0, 1).astype(np.float32)
    errors = [float(np.mean(np.abs(camera.jpeg(img, q) - img))) for q in (95, 50, 10, 2)]
    assert errors == sorted(errors) and errors[0] < 0.01 < errors[-1]
    assert camera.jpeg(img, 50).shape == img.shape


def test_quarter_turn_is_exact_and_small_turns_keep_the_texture_statistics():
    img = grating(10.0)
    np.testing.assert_array_equal(camera.rotate(img, 90.0), np.rot90(img))
    turned = camera.rotate(img, 30.0)
    assert turned.shape == img.shape and abs(float(turned.mean()) - float(img.mean())) < 0.01


@pytest.mark.parametrize("factor", [2.0, 0.5])
def test_distance_rescales_the_texture_period(factor):
    img = grating(16.0)
    out = camera.distance(img, factor)
    assert out.shape == img.shape
    assert period_of(out) == pytest.approx(16.0 * factor, rel=0.06)
    np.testing.assert_allclose(camera.distance(img, 1.0), img)


@pytest.mark.parametrize("fraction", [0.25, 0.5])
def test_occlusion_covers_exactly_that_fraction(fraction):
    img = np.full((100, 200), 0.6, np.float32)
    out = camera.occlude(img, fraction)
    assert np.mean(out != img) == fraction


@pytest.mark.parametrize(
    "call",
    [
        lambda img: camera.blur(img, -1.0),
        lambda img: camera.exposure(img, 0.0),
        lambda img: camera.sensor_noise(img, 2.0, np.random.default_rng()),
        lambda img: camera.jpeg(img, 0),
        lambda img: camera.jpeg(img, 50.5),
        lambda img: camera.rotate(img, float("inf")),
        lambda img: camera.distance(img, 0.01),
        lambda img: camera.occlude(img, 1.0),
        lambda img: camera.blur(img * 3, 1.0),
        lambda img: camera.blur(img[None], 1.0),
    ],
)
def test_bad_strengths_and_images_are_refused(call):
    with pytest.raises(ValueError):
        call(np.full((32, 32), 0.5, np.float32))
