"""Training on every rated texture, ONNX export with its card, prediction of withheld textures."""

import csv
from dataclasses import replace

import numpy as np
import pytest

from models.inference.modelfile import read_card
from models.inference.predictor import Predictor
from models.offline.datasets.build import build
from models.offline.evaluation.data import load_texture_data
from models.offline.evaluation.estimator_registry import build_estimator
from models.offline.train import predict_dataset, train_and_export
from models.tactile.config import TactileConfig
from models.visual.config import VisualConfig
from service.cli import main as cli
from texture_library.attributes import ATTRIBUTES


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return build(
        "synthetic", tmp_path_factory.mktemp("ds") / "synthetic", n_textures=8, duration_s=3, withheld=2, image_size=256
    )


@pytest.fixture(scope="module")
def ridge_model(dataset, tmp_path_factory):
    return train_and_export(dataset, "ridge-tactile", tmp_path_factory.mktemp("m") / "ridge.onnx", seed=3)


def test_model_card_says_what_the_model_expects(ridge_model, dataset):
    card = read_card(ridge_model)
    assert card.model == "ridge-tactile" and card.modality == "tactile" and card.visual is None
    assert card.tactile_hash == TactileConfig().hash()
    assert TactileConfig(**card.tactile_config) == TactileConfig()
    assert len(card.trained_on) == 6  # the 2 withheld textures are not trained on
    assert card.seed == 3


def test_onnx_equals_the_fitted_estimator_window_by_window(ridge_model, dataset):
    data = load_texture_data(dataset, visual=False)
    est = build_estimator("ridge-tactile").fit(data, 3)
    predictor = Predictor(ridge_model)
    for i in range(len(data)):
        windows = data.tactile[i]
        # linear: the model at the texture's mean window is the texture-level prediction
        expected = np.clip(est.predict(data.take([i]))[0], -100, 100)
        np.testing.assert_allclose(predictor.predict(windows.mean(axis=0)), expected[None], atol=1e-2)
        assert predictor.predict(windows).shape == (len(windows), 4)


def test_a_window_far_outside_the_training_range_gives_the_same_bounded_answer_in_onnx(ridge_model, dataset):
    data = load_texture_data(dataset, visual=False)
    est = build_estimator("ridge-tactile").fit(data, 3)
    window = data.tactile[0].mean(axis=0).copy()
    window[::7] += 1e4 * (np.abs(window[::7]) + 1.0)  # channels far beyond anything trained on
    expected = np.clip(est.predict(replace(data.take([0]), tactile=[window[None]]))[0], -100, 100)
    got = Predictor(ridge_model).predict(window)
    np.testing.assert_allclose(got, expected[None], atol=1e-2)
    assert np.all(np.abs(got) <= 100)


def test_predict_writes_one_row_per_withheld_texture(ridge_model, dataset, tmp_path):
    out = tmp_path / "withheld.csv"
    assert (
        cli(
            [
                "predict",
                "--model",
                str(ridge_model),
                "--dataset",
                str(dataset),
                "--out",
                str(out),
                "--textures",
                "withheld",
            ]
        )
        == 0
    )
    rows = list(csv.DictReader(open(out)))
    assert [r["texture"] for r in rows] == ["synth_006", "synth_007"]
    assert list(rows[0]) == ["texture", *ATTRIBUTES]
    textures, preds = predict_dataset(ridge_model, dataset, rated="withheld")
    np.testing.assert_allclose([[float(r[a]) for a in ATTRIBUTES] for r in rows], preds, atol=0.01)
    assert np.all(np.abs(preds) <= 100)


def test_predictor_refuses_other_features(ridge_model):
    other = TactileConfig(hop_s=0.25).hash()
    with pytest.raises(ValueError, match="pipeline computes"):
        Predictor(ridge_model, expected_tactile_hash=other)
    predictor = Predictor(ridge_model)
    with pytest.raises(ValueError, match=r"tactile must be \(N, 526\)"):
        predictor.predict(np.zeros((2, 10), np.float32))
    with pytest.raises(ValueError, match="NaN or Inf"):
        predictor.predict(np.full((1, 526), np.nan, np.float32))


def test_models_without_export_say_so(dataset, tmp_path):
    with pytest.raises(ValueError, match="has no ONNX export"):
        train_and_export(dataset, "knn-tactile", tmp_path / "knn.onnx")


def test_not_a_model_file(tmp_path):
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"not onnx")
    with pytest.raises(ValueError, match="not a loadable ONNX model"):
        Predictor(bad)
    with pytest.raises(ValueError, match="not found"):
        Predictor(tmp_path / "missing.onnx")


@pytest.fixture()
def stand_in_images(monkeypatch):
    """The dataset's tactile features with stand-in image features (8 views × 24 per texture, seeded by the
    texture id): the selected model reads images, and real embeddings would cost minutes here."""
    import zlib

    import models.offline.train as train_module

    real = train_module.load_texture_data

    def load(root, *, visual=True, visual_part="both", rated="yes", **kw):
        data = real(root, visual=False, rated=rated, **kw)
        views = np.stack([np.random.default_rng(zlib.crc32(t.encode())).normal(size=(8, 24)) for t in data.textures])
        meta = {
            **data.meta,
            "backbone": "stand-in",
            "backbone_dim": 24,
            "visual_hash": VisualConfig(grid=2, glcm=False).hash(),
            "visual_config": VisualConfig(grid=2, glcm=False).computation(),
            "visual_part": visual_part,
        }
        return replace(data, visual=views.astype(np.float32), meta=meta)

    monkeypatch.setattr(train_module, "load_texture_data", load)
    return load


def test_train_selected_applies_the_rule_to_every_rated_texture_and_records_it(dataset, tmp_path, stand_in_images):
    from models.offline.evaluation.estimator_registry import build_estimator as build

    path = train_and_export(dataset, "selected", tmp_path / "selected.onnx", seed=1, options={"folds": 3, "repeats": 1})
    card = read_card(path)
    assert card.model == "selected" and len(card.trained_on) == 6
    assert card.visual["views"] == 8 and card.visual["pooling"] == "mean" and card.visual["views_stored"] == 8
    assert set(card.fit_info["chosen"]) == set(ATTRIBUTES)
    assert set(card.fit_info["chosen"].values()) <= {"ridge-pooled", "krr-pooled", "ksvr-pooled", "mean-pooled"}
    # the exported graph, fed each window with the texture's 8 views pooled, answers as the fitted rule does
    est = build("selected", folds=3, repeats=1).fit(stand_in_images(dataset), 1)
    assert [est.fit_info()["chosen"][a] for a in ATTRIBUTES] == [card.fit_info["chosen"][a] for a in ATTRIBUTES]
    textures, preds = predict_dataset(path, dataset, rated="withheld")
    expected = est.predict(stand_in_images(dataset, rated="withheld"))
    assert textures == ["synth_006", "synth_007"]
    np.testing.assert_allclose(preds, expected, atol=1e-2)


def test_the_card_carries_the_visual_configuration_and_a_forged_one_is_refused(dataset, tmp_path, stand_in_images):
    import json

    import onnx

    path = train_and_export(dataset, "selected", tmp_path / "selected.onnx", seed=1, options={"folds": 3, "repeats": 1})
    assert Predictor(path).visual_config == VisualConfig(grid=2, glcm=False)  # what the service will compute
    model = onnx.load(str(path))
    for prop in model.metadata_props:
        if prop.key == "visual":
            visual = json.loads(prop.value)
            visual["visual_config"]["grid"] = 3  # the configuration no longer matches the hash trained on
            prop.value = json.dumps(visual)
    onnx.save(model, str(tmp_path / "forged.onnx"))
    with pytest.raises(ValueError, match="visual config hash .* does not match its config"):
        Predictor(tmp_path / "forged.onnx")


def test_the_configuration_read_from_a_card_names_the_backbone_the_model_was_trained_on(
    dataset, tmp_path, stand_in_images
):
    """The backbone is outside the configuration's hash (int8 and fp32 share it), so the card's backbone name is
    what says which file computes the model's features: `hapticlink train` names that file from it."""
    import json

    import onnx

    path = train_and_export(dataset, "selected", tmp_path / "selected.onnx", seed=1, options={"folds": 3, "repeats": 1})
    model = onnx.load(str(path))
    for prop in model.metadata_props:
        if prop.key == "visual":
            visual = json.loads(prop.value)
            visual["backbone"] = "efficientnet_lite0_int8"
            prop.value = json.dumps(visual)
    onnx.save(model, str(tmp_path / "int8.onnx"))
    assert Predictor(tmp_path / "int8.onnx").visual_config == VisualConfig(
        grid=2, glcm=False, backbone="efficientnet_lite0_int8"
    )


def test_train_refuses_metrics_of_another_model(dataset, tmp_path):
    import json

    metrics = tmp_path / "results.json"
    metrics.write_text(json.dumps({"model": "ridge-both", "mae": {}, "rmse": {}, "seeds": [0]}))
    with pytest.raises(ValueError, match="holds the LOOCV of 'ridge-both', not of 'ridge-tactile'"):
        train_and_export(dataset, "ridge-tactile", tmp_path / "m.onnx", metrics=metrics)


def test_a_bad_visual_flag_is_named_by_its_flag(dataset, tmp_path, capsys):
    """`--visual-grid 0` printed pydantic's 'validation error for VisualConfig / grid …' with its web link."""
    status = cli(["evaluate", "--dataset", str(dataset), "--model", "ridge-visual", "--out", str(tmp_path),
                  "--visual-grid", "0"])  # fmt: skip
    err = capsys.readouterr().err
    assert status == 2 and "--visual-grid: Input should be greater than or equal to 1" in err
    assert "pydantic" not in err


@pytest.mark.parametrize(
    "model, views, words",
    [
        ("ridge-visual", "3", "--test-views: test views must divide the 8 stored views, got 3"),
        ("ridge-visual", "0", "--test-views: test views must divide the 8 stored views, got 0"),
        ("ridge-tactile", "2", "--test-views: model 'ridge-tactile' reads no images: it has no views to hold out"),
    ],
)
def test_a_bad_test_views_is_refused_before_any_feature_is_computed(dataset, tmp_path, capsys, monkeypatch, model,
                                                                    views, words):  # fmt: skip
    """`--test-views 3` was refused only after the features were computed (≈ 30 s on HaTT)."""

    def featurized(*args, **kwargs):
        raise AssertionError("features were computed before --test-views was checked")

    monkeypatch.setattr("models.offline.evaluation.data.load_texture_data", featurized)
    status = cli(["evaluate", "--dataset", str(dataset), "--model", model, "--out", str(tmp_path),
                  "--test-views", views])  # fmt: skip
    assert status == 2 and words in capsys.readouterr().err


def _with_probe(src, dst, change):
    """A copy of the model at `src` whose card's probe is `change(probe)`."""
    import json

    from models.inference.modelfile import read_metadata, write_metadata

    meta = read_metadata(src)
    meta["probe"] = json.dumps(change(json.loads(meta["probe"])))
    dst.write_bytes(src.read_bytes())
    write_metadata(dst, meta)
    return dst


def test_the_card_stores_probe_inputs_and_outputs_and_the_model_checks_them_at_load(ridge_model, dataset, tmp_path):
    from models.inference import jsonarrays

    card = read_card(ridge_model)
    assert card.probe is not None and card.probe["visual"] is None
    tactile = jsonarrays.decode(card.probe["tactile"])
    ratings = jsonarrays.decode(card.probe["ratings"])
    assert tactile.shape == (4, TactileConfig().n_features) and ratings.shape == (4, 4)
    predictor = Predictor(ridge_model)
    assert predictor.probe_error is not None and predictor.probe_error <= 1e-3
    np.testing.assert_allclose(predictor.predict(tactile), ratings, atol=1e-3)

    def shifted(probe):  # outputs recorded elsewhere that this CPU no longer reproduces
        r = jsonarrays.decode(probe["ratings"])
        r[2, 1] += 0.5
        return {**probe, "ratings": jsonarrays.encode(r)}

    drifted = _with_probe(ridge_model, tmp_path / "drifted.onnx", shifted)
    with pytest.raises(ValueError, match=r"differ from the outputs recorded at export by up to 0\.5.* refusing it"):
        Predictor(drifted)
    assert Predictor(drifted, probe_tolerance=1.0).probe_error == pytest.approx(0.5, abs=1e-3)
    wrong = _with_probe(
        ridge_model, tmp_path / "wrong.onnx", lambda p: {**p, "tactile": jsonarrays.encode(tactile[:, :3])}
    )
    with pytest.raises(ValueError, match="card probe does not fit the model"):
        Predictor(wrong)


def test_a_visual_card_probe_holds_both_inputs(dataset, tmp_path, stand_in_images):
    from models.inference import jsonarrays

    path = train_and_export(dataset, "ridge-both", tmp_path / "both.onnx", seed=1)
    probe = read_card(path).probe
    assert probe is not None and jsonarrays.decode(probe["visual"]).shape == (4, 24)
    assert Predictor(path).probe_error <= 1e-3
