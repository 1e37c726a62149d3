"""A network as a LOOCV estimator: fit inside the fold, early stopping on training textures, export parity."""

import numpy as np
import pytest

from models.inference.modelfile import ModelCard
from models.offline.evaluation.estimator_registry import build_estimator

pytest.importorskip("torch")


def test_net_fits_predicts_and_exports_the_same_numbers(linear_world, tmp_path):
    train, test = linear_world.take(range(0, 24)), linear_world.take(range(24, 30))
    est = build_estimator("ann", max_epochs=15, patience=5, windows_per_texture=4).fit(train, seed=0)
    pred = est.predict(test.with_targets(None))
    assert pred.shape == (6, 4) and np.all(np.isfinite(pred))
    assert 0 <= est.fit_info()["best_epoch"] < 15
    card = ModelCard("ann", "both", {}, "", None, "linear-world", {}, est.n_params(), train.textures, 0)
    meta = {k: v for k, v in card.to_metadata().items() if k != "modality"}
    path = est.export(tmp_path / "ann.onnx", meta)
    import onnxruntime as ort

    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    windows = est.predict_windows(test)
    assert [w.shape for w in windows] == [(len(t), 4) for t in test.tactile]  # one answer per window
    for i in range(len(test)):
        feed = {"tactile": test.tactile[i], "visual": np.repeat(test.visual[i, :1], len(test.tactile[i]), axis=0)}
        np.testing.assert_allclose(sess.run(None, feed)[0], np.clip(windows[i], -100, 100), atol=1e-2)
    stored = sess.get_modelmeta().custom_metadata_map
    assert stored == {**meta, "inputs": "tactile,visual", "modality": "both"}  # the card, with what the graph reads


def test_net_needs_rated_textures(linear_world):
    with pytest.raises(ValueError, match="needs rated textures"):
        build_estimator("ann").fit(linear_world.with_targets(None), 0)


def test_ensemble_averages_its_members_and_exports_one_graph(linear_world, tmp_path):
    import onnxruntime as ort

    train, test = linear_world.take(range(0, 24)), linear_world.take(range(24, 27))
    ens = build_estimator("ann-ensemble", max_epochs=4, windows_per_texture=4).fit(train, seed=1)
    members = np.stack([m.predict(test) for m in ens.members])
    np.testing.assert_allclose(ens.predict(test), members.mean(axis=0), rtol=1e-6)
    assert not np.allclose(members[0], members[1])  # different seeds, different members
    path = ens.export(tmp_path / "ens.onnx", {})
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    feed = {"tactile": test.tactile[0], "visual": np.repeat(test.visual[0, :1], len(test.tactile[0]), axis=0)}
    expected = np.mean([np.clip(m.predict_windows(test.take([0]))[0], -100, 100) for m in ens.members], axis=0)
    np.testing.assert_allclose(sess.run(None, feed)[0], expected, atol=1e-2)
