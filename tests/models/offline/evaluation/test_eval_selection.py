"""Nested-CV selection: the rule picks per attribute from inner folds only, and serves as one graph."""

import numpy as np
import onnxruntime as ort
import pytest

from models.offline.evaluation.estimator_registry import EstimatorSpec, build_estimator
from models.offline.evaluation.estimators import Estimator, MeanEstimator, RidgeEstimator
from models.offline.evaluation.kernel import KernelRidgeEstimator
from models.offline.evaluation.loocv import run_fold
from models.offline.evaluation.selection import SelectedEstimator
from models.visual.pooling import pool_views


class HalfGood(Estimator):
    """Ridge on the image for the attributes in `good`, a fixed wrong answer (+80) for the others."""

    modality = "visual"

    def __init__(self, good: tuple[int, ...]):
        self.good = good
        self.inner = RidgeEstimator("visual")

    def fit(self, data, seed):
        self.inner.fit(data, seed)
        return self

    def predict(self, data):
        out = np.full((len(data), 4), 80.0)
        out[:, list(self.good)] = self.inner.predict(data)[:, list(self.good)]
        return out

    def predict_windows(self, data):
        return [np.repeat(p[None], len(w), axis=0) for p, w in zip(self.predict(data), data.tactile)]


def test_each_attribute_gets_the_candidate_that_is_best_for_it_in_the_inner_folds(linear_world):
    sel = SelectedEstimator(
        {"first": lambda: HalfGood((0, 1)), "second": lambda: HalfGood((2, 3)), "mean": MeanEstimator},
        folds=3,
        repeats=1,
    ).fit(linear_world, 0)
    assert sel.chosen == ["first", "first", "second", "second"]
    assert set(sel.models) == {"first", "second"}  # the unpicked candidate is not refit
    ridge = RidgeEstimator("visual").fit(linear_world, 0).predict(linear_world)
    np.testing.assert_allclose(sel.predict(linear_world), np.clip(ridge, -100, 100), atol=1e-9)
    info = sel.fit_info()
    assert info["chosen"]["hard_soft"] == "second"
    assert info["inner_mae"]["mean"]["rough_smooth"] > info["inner_mae"]["first"]["rough_smooth"]


class Recorder(MeanEstimator):
    """Predict-the-mean that records the textures it is fit on and those it is asked about."""

    fitted: set = set()
    asked: list = []

    def fit(self, data, seed):
        Recorder.fitted.update(data.textures)
        return super().fit(data, seed)

    def predict_windows(self, data):
        assert data.targets is None, "ratings reached predict"
        Recorder.asked.append(list(data.textures))
        return [np.repeat(p[None], len(w), 0) for p, w in zip(super().predict(data), data.tactile)]


def test_the_held_out_texture_never_reaches_the_inner_selection(linear_world, monkeypatch):
    Recorder.fitted, Recorder.asked = set(), []
    monkeypatch.setattr(
        EstimatorSpec, "build", lambda self: SelectedEstimator({"a": Recorder, "b": Recorder}, folds=3, repeats=2)
    )
    held = linear_world.textures[5]
    run_fold(linear_world, EstimatorSpec("selected"), 5, 0)
    assert Recorder.fitted == set(linear_world.textures) - {held}  # inner folds and refit: training textures only
    assert Recorder.asked[-1] == [held]  # the outer prediction, asked last, of the picked model only
    assert all(held not in batch for batch in Recorder.asked[:-1])


def test_a_mean_candidate_is_scored_from_its_members_out_of_fold_predictions(linear_world):
    bases = {
        "ridge": lambda: KernelRidgeEstimator("both", "linear"),
        "krr": lambda: KernelRidgeEstimator("both", "rbf"),
    }
    sel = SelectedEstimator(bases, {"both": ("ridge", "krr")}, folds=3, repeats=1)
    errors = sel.inner_errors(linear_world, 0)
    assert errors.shape == (3, 4) and np.all(errors > 0)
    # the mean of two different models is scored on its own, not copied from a member
    assert not np.allclose(errors[2], errors[0]) and not np.allclose(errors[2], errors[1])


def test_the_selected_model_exports_as_one_graph_that_answers_like_it(linear_world, tmp_path):
    sel = build_estimator("selected", folds=3, repeats=1)
    sel.factories.pop("ksvr-pooled")  # keep the test quick: ridge, kernel ridge and a mean of them
    sel.means = {"mean-pooled": ("ridge-pooled", "krr-pooled")}
    train, test = linear_world.take(range(24)), linear_world.take(range(24, 30))
    sel.fit(train, 0)
    sess = ort.InferenceSession(str(sel.export(tmp_path / "sel.onnx", {})), providers=["CPUExecutionProvider"])
    names = {i.name for i in sess.get_inputs()}
    for i in range(len(test)):
        feeds = {"tactile": test.tactile[i]} if "tactile" in names else {}
        if "visual" in names:
            feeds["visual"] = np.repeat(pool_views(test.visual[i, : sel.views])[None], len(test.tactile[i]), 0)
        np.testing.assert_allclose(sess.run(None, feeds)[0].mean(axis=0), sel.predict(test.take([i]))[0], atol=1e-3)


def test_bad_arguments():
    with pytest.raises(ValueError, match="at least one base"):
        SelectedEstimator({})
    with pytest.raises(ValueError, match="needs ≥ 2 members among the bases"):
        SelectedEstimator({"a": MeanEstimator}, {"m": ("a", "zzz")})
    with pytest.raises(ValueError, match="inner folds must be ≥ 2"):
        SelectedEstimator({"a": MeanEstimator}, folds=1)
