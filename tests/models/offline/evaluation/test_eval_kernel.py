"""Additive-kernel models: touch weighed per attribute, windows answered one by one, ONNX parity."""

from dataclasses import replace

import numpy as np
import onnxruntime as ort
import pytest

from models.offline.evaluation.data import TextureData
from models.offline.evaluation.estimator_registry import build_estimator
from models.offline.evaluation.kernel import (
    KernelRidgeEstimator,
    KernelSVREstimator,
    MeanOfEstimator,
    centred_loo_residuals,
    exact_loo_residuals,
)
from models.visual.pooling import pool_views


def split_world(n_textures: int = 36, n_windows: int = 5, seed: int = 0) -> TextureData:
    """Attributes 0–1 follow hidden factors seen only by the camera, 2–3 factors felt only by touch."""
    rng = np.random.default_rng(seed)
    f_vis, f_tac = rng.normal(size=(n_textures, 2)), rng.normal(size=(n_textures, 2))
    mix_v, mix_t = rng.normal(size=(2, 16)), rng.normal(size=(2, 10))
    visual = (f_vis @ mix_v)[:, None, :] + 0.1 * rng.normal(size=(n_textures, 4, 16))
    tactile = [
        (f_tac[i] @ mix_t + 0.3 * rng.normal(size=(n_windows, 10))).astype(np.float32) for i in range(n_textures)
    ]
    targets = np.clip(40 * np.concatenate([f_vis, f_tac], axis=1) + rng.normal(size=(n_textures, 4)), -100, 100)
    return TextureData(
        [f"t{i:02d}" for i in range(n_textures)],
        ["g"] * n_textures,
        tactile,
        visual.astype(np.float32),
        targets.astype(np.float32),
        {"dataset": "split-world"},
    )


@pytest.fixture(scope="module")
def world() -> TextureData:
    return split_world()


@pytest.mark.parametrize("kernel", ["linear", "rbf"])
def test_each_attribute_weighs_touch_for_itself(world, kernel):
    est = KernelRidgeEstimator("both", kernel).fit(world, 0)
    weights = [c["tactile_weight"] for c in est.chosen]
    assert weights[0] == weights[1] == 0.0, weights  # camera-only attributes drop touch
    assert weights[2] > 0 and weights[3] > 0, weights  # touch-only attributes keep it


def _brute_force_loo(kernel: np.ndarray, y: np.ndarray, alpha: float) -> np.ndarray:
    """Each texture left out and the model (mean intercept + kernel ridge) refitted on the others."""
    n = len(y)
    out = np.empty_like(y)
    for i in range(n):
        keep = np.arange(n) != i
        mean = y[keep].mean(axis=0)
        coef = np.linalg.solve(kernel[np.ix_(keep, keep)] + alpha * np.eye(n - 1), y[keep] - mean)
        out[i] = y[i] - (kernel[i, keep] @ coef + mean)
    return out


def _brute_force_free_intercept_ridge(z: np.ndarray, y: np.ndarray, alpha: float) -> np.ndarray:
    """Each texture left out and ridge with a free intercept refitted on the others (columns and targets centred
    on them)."""
    n = len(y)
    out = np.empty_like(y)
    for i in range(n):
        keep = np.arange(n) != i
        zm, ym = z[keep].mean(axis=0), y[keep].mean(axis=0)
        zk = z[keep] - zm
        beta = np.linalg.solve(zk.T @ zk + alpha * np.eye(z.shape[1]), zk.T @ (y[keep] - ym))
        out[i] = y[i] - ((z[i] - zm) @ beta + ym)
    return out


def _kernels(n: int = 30):
    """A centred kernel (linear on centred columns) and an uncentred one (RBF + a touch block of texture means of
    window z-scores, which are not centred), with two targets: one signal, one noise; and the centred columns."""
    rng = np.random.default_rng(0)
    z = rng.normal(size=(n, 20))
    z = (z - z.mean(axis=0)) / z.std(axis=0) / np.sqrt(20)
    touch = rng.normal(size=(n, 8)) / np.sqrt(8) + 0.3
    y = np.column_stack([40 * z[:, 0] * np.sqrt(20) + 20 * rng.normal(size=n), rng.normal(size=n)])
    sq = ((z[:, None] - z[None]) ** 2).sum(-1)
    rbf = np.exp(-sq / np.median(sq[~np.eye(n, dtype=bool)])) + touch @ touch.T
    return {"centred": z @ z.T, "uncentred": rbf}, y, z


@pytest.mark.parametrize("kind", ["centred", "uncentred"])
def test_exact_leave_one_out_is_the_refit_one(kind):
    kernels, y, _ = _kernels()
    lam, q = np.linalg.eigh(kernels[kind])
    lam = np.maximum(lam, 0.0)
    alphas = np.logspace(-3, 2, 6)
    for a, residuals in zip(alphas, exact_loo_residuals(lam, q, y, alphas)):
        np.testing.assert_allclose(residuals, _brute_force_loo(kernels[kind], y, a), rtol=1e-8, atol=1e-8)


def test_the_rules_criterion_is_exact_for_a_centred_kernel_and_leans_to_regularise_an_uncentred_one():
    kernels, y, z = _kernels()
    alphas = np.logspace(-3, 2, 6)
    lam, q = np.linalg.eigh(kernels["centred"])
    lam = np.maximum(lam, 0.0)
    # on centred columns it is ridge with a free intercept, left out and refitted
    for a, residuals in zip(alphas, centred_loo_residuals(lam, q, y, alphas)):
        np.testing.assert_allclose(residuals, _brute_force_free_intercept_ridge(z, y, a), rtol=1e-7, atol=1e-7)
    lam, q = np.linalg.eigh(kernels["uncentred"])
    lam = np.maximum(lam, 0.0)
    centred = np.abs(centred_loo_residuals(lam, q, y, alphas)).mean(axis=(1, 2))
    exact = np.abs(exact_loo_residuals(lam, q, y, alphas)).mean(axis=(1, 2))
    assert centred[0] > 2 * exact[0]  # on an RBF kernel weak regularisation looks far worse than it is
    assert np.argmin(centred) > np.argmin(exact)  # so the criterion picks a larger α


def test_leave_one_out_refuses_what_it_cannot_compute():
    for residuals in (centred_loo_residuals, exact_loo_residuals):
        with pytest.raises(ValueError, match="at least 2 textures"):
            residuals(np.ones(1), np.eye(1), np.zeros((1, 4)), np.array([1.0]))
        with pytest.raises(ValueError, match="alpha must be > 0"):
            residuals(np.ones(2), np.eye(2), np.zeros((2, 4)), np.array([1.0, 0.0]))
    with pytest.raises(ValueError, match="loo must be one of centred, exact"):
        KernelRidgeEstimator(loo="approximate")


def test_a_texture_is_predicted_as_the_mean_of_its_windows_predictions(world):
    est = KernelRidgeEstimator("both", "rbf").fit(world.take(range(30)), 0)
    test = world.take(range(30, 36))
    texture_level = est.predict(test)
    for i in range(len(test)):
        one = test.take([i])
        per_window = [est.predict(replace(one, tactile=[w[None]]))[0] for w in one.tactile[0]]
        np.testing.assert_allclose(np.mean(per_window, axis=0), texture_level[i], rtol=1e-9, atol=1e-9)


def test_views_pool_the_first_k_views_as_the_service_will(world):
    est = KernelRidgeEstimator("visual", "linear", views=2).fit(world.take(range(30)), 0)
    test = world.take(range(30, 36))
    same = replace(test, visual=np.concatenate([test.visual[:, :2], -test.visual[:, 2:]], axis=1))  # views ≥ 2 unused
    np.testing.assert_allclose(est.predict(test), est.predict(same))
    assert est.pooled_views(4) == 2 and KernelRidgeEstimator("visual").fit(world, 0).pooled_views(4) == 4
    with pytest.raises(ValueError, match=r"views must lie in 1…4"):
        KernelRidgeEstimator("visual", views=5).fit(world, 0)


def onnx_predict(path, data: TextureData, views: int) -> np.ndarray:
    """A texture's prediction as the service makes it: each window with the pooled views, then the mean."""
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    names = {i.name for i in sess.get_inputs()}
    out = []
    for i, windows in enumerate(data.tactile):
        feeds = {}
        if "tactile" in names:
            feeds["tactile"] = windows.astype(np.float32)
        if "visual" in names:
            feeds["visual"] = np.repeat(pool_views(data.visual[i, :views])[None], len(windows), axis=0)
        out.append(sess.run(None, feeds)[0].mean(axis=0))
    return np.array(out)


@pytest.mark.parametrize("name", ["ridge-pooled", "krr-pooled", "ksvr-pooled", "mean-pooled"])
def test_onnx_export_answers_as_the_fitted_model(world, name, tmp_path):
    est = build_estimator(name).fit(world.take(range(28)), 0)
    test = world.take(range(28, 36))
    path = est.export(tmp_path / "m.onnx", {"model": name})
    np.testing.assert_allclose(onnx_predict(path, test, est.views), np.clip(est.predict(test), -100, 100), atol=1e-3)


def test_onnx_bounds_a_window_far_outside_the_training_range_like_the_model(world, tmp_path):
    est = KernelRidgeEstimator("both", "rbf").fit(world.take(range(28)), 0)
    test = world.take([30])
    wild = replace(test, tactile=[test.tactile[0] * 1e4], visual=test.visual * 1e3)
    path = est.export(tmp_path / "m.onnx", {})
    got = onnx_predict(path, wild, est.views)
    np.testing.assert_allclose(got, np.clip(est.predict(wild), -100, 100), atol=1e-3)
    assert np.all(np.abs(got) <= 100)


def test_a_model_that_drops_touch_everywhere_exports_without_a_tactile_input(world, tmp_path):
    visual_only = replace(world, targets=world.targets[:, [0, 1, 0, 1]])
    est = KernelRidgeEstimator("both", "linear").fit(visual_only, 0)
    assert est.modality == "visual"
    sess = ort.InferenceSession(str(est.export(tmp_path / "m.onnx", {})), providers=["CPUExecutionProvider"])
    assert [i.name for i in sess.get_inputs()] == ["visual"]


def test_svr_and_mean_of_members(world):
    svr = KernelSVREstimator("both", "rbf").fit(world.take(range(30)), 0)
    assert all(c["C"] in (1.0, 10.0) and c["support"] > 0 for c in svr.chosen)
    members = {"a": lambda: KernelRidgeEstimator("both", "linear"), "b": lambda: KernelRidgeEstimator("both", "rbf")}
    mean = MeanOfEstimator(members).fit(world.take(range(30)), 0)
    test = world.take(range(30, 36))
    a, b = mean.members["a"].predict_windows(test), mean.members["b"].predict_windows(test)
    for got, wa, wb in zip(mean.predict_windows(test), a, b):
        np.testing.assert_allclose(got, (wa + wb) / 2)
    with pytest.raises(ValueError, match="at least 2 members"):
        MeanOfEstimator({"a": members["a"]})


def test_bad_arguments():
    with pytest.raises(ValueError, match="visual_kernel must be linear or rbf"):
        KernelRidgeEstimator("both", "poly")
    with pytest.raises(ValueError, match="tactile_weights must be non-negative"):
        KernelRidgeEstimator("both", tactile_weights=(-1.0,))
    with pytest.raises(ValueError, match="modality must be tactile, visual or both"):
        KernelRidgeEstimator("none")
    with pytest.raises(ValueError, match="does not take max_epochs"):
        build_estimator("krr-pooled", max_epochs=3)
