"""The int8 EfficientNet-Lite0: built offline from the fp32 file, loadable, named apart, close to fp32."""

from pathlib import Path

import numpy as np
import onnx
import pytest

from models.offline.backbones.onnx_export import export_backbone_onnx
from models.offline.backbones.quantize import INT8_SUFFIX, int8_fingerprint, quantize_backbone_onnx, synthetic_patches
from models.visual.cache import cache_key
from models.visual.config import VisualConfig
from models.visual.onnx_backbone import OnnxBackbone

CONFIG = VisualConfig(grid=2, glcm=False)
# Measured with this test's small calibration set (4 synthetic photos of 448²): the frame-mean cosine to fp32 on
# the 6 held-out synthetic photos below was ≥ 0.954 (median 0.979); the full recipe (24 photos of 1024²) gives
# ≥ 0.911 (median 0.975) on 12 held-out ones (docs/models.md). The bound leaves room for other CPUs' kernels.
MIN_FRAME_COSINE = 0.90


def _cosine(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return (a * b).sum(-1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))


@pytest.fixture(scope="module")
def fp32_onnx(tmp_path_factory, efficientnet_backbone) -> Path:
    return export_backbone_onnx(
        efficientnet_backbone, tmp_path_factory.mktemp("fp32") / "lite0.onnx", config_hash=CONFIG.hash()
    )


@pytest.fixture(scope="module")
def calibration() -> np.ndarray:
    return synthetic_patches(4, 448, seed=0)


@pytest.fixture(scope="module")
def int8_onnx(tmp_path_factory, fp32_onnx, calibration) -> Path:
    return quantize_backbone_onnx(fp32_onnx, tmp_path_factory.mktemp("int8") / "lite0_int8.onnx", calibration)


def test_int8_loads_with_its_own_name_and_fingerprint(fp32_onnx, int8_onnx):
    fp32 = OnnxBackbone(fp32_onnx, intra_op_threads=1)
    int8 = OnnxBackbone(int8_onnx, intra_op_threads=1, expected_config_hash=CONFIG.hash())
    assert int8.name == "efficientnet_lite0" + INT8_SUFFIX and int8.dim == fp32.dim == 1280
    assert int8.fingerprint == int8_fingerprint(fp32.fingerprint) != fp32.fingerprint
    assert int8.input_size == 224
    ops = {n.op_type for n in onnx.load(str(int8_onnx)).graph.node}
    assert {"QuantizeLinear", "DequantizeLinear"} <= ops  # QDQ: the convolutions run in int8
    # Features are cached under the backbone's name and fingerprint: int8 and fp32 never share an entry.
    img = np.zeros((224, 224), np.float32)
    assert cache_key(img, {}, CONFIG.hash(), fp32.name, fp32.fingerprint) != cache_key(
        img, {}, CONFIG.hash(), int8.name, int8.fingerprint
    )


def test_int8_embeddings_match_fp32_on_held_out_synthetic_photos(fp32_onnx, int8_onnx):
    fp32 = OnnxBackbone(fp32_onnx, intra_op_threads=1)
    int8 = OnnxBackbone(int8_onnx, intra_op_threads=1)
    patches = synthetic_patches(6, 448, seed=1)  # other photos than the calibration's
    a, b = fp32.embed(patches), int8.embed(patches)
    assert b.shape == a.shape == (24, 1280) and b.dtype == np.float32
    assert np.isfinite(b).all()
    frames = _cosine(a.reshape(6, 4, -1).mean(1), b.reshape(6, 4, -1).mean(1))
    assert frames.min() >= MIN_FRAME_COSINE, frames
    assert int8.embed(patches[:1]).shape == (1, 1280)  # the batch axis stays dynamic


def test_quantization_is_deterministic(tmp_path, fp32_onnx, int8_onnx, calibration):
    again = quantize_backbone_onnx(fp32_onnx, tmp_path / "again.onnx", calibration)
    assert again.read_bytes() == int8_onnx.read_bytes()


def test_refuses_to_quantize_twice_or_a_foreign_file(tmp_path, int8_onnx, calibration):
    with pytest.raises(ValueError, match="already quantized"):
        quantize_backbone_onnx(int8_onnx, tmp_path / "twice.onnx", calibration)
    bare = onnx.load(str(int8_onnx))
    del bare.metadata_props[:]
    onnx.save(bare, str(tmp_path / "bare.onnx"))
    with pytest.raises(ValueError, match="not a hapticlink visual backbone"):
        quantize_backbone_onnx(tmp_path / "bare.onnx", tmp_path / "out.onnx", calibration)


def test_int8_is_a_backbone_choice_that_keeps_the_configuration_hash():
    int8 = VisualConfig(grid=2, glcm=False, backbone="efficientnet_lite0_int8")
    assert int8.hash() == CONFIG.hash()  # the choice is no computation: name and fingerprint tell them apart


def test_int8_has_no_torch_form():
    from models.offline.backbones.cnn import resolve_backbone

    with pytest.raises(ValueError, match="no torch form"):
        resolve_backbone(VisualConfig(backbone="efficientnet_lite0_int8"))


def test_synthetic_patches_are_seeded_and_in_range():
    a, b = synthetic_patches(2, 256, seed=3), synthetic_patches(2, 256, seed=3)
    assert a.shape == (8, 224, 224) and a.dtype == np.float32
    assert np.array_equal(a, b) and 0.0 <= a.min() and a.max() <= 1.0
