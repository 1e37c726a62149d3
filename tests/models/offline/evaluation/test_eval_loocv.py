from dataclasses import replace

import numpy as np
import pytest

from models.offline.evaluation.estimator_registry import EstimatorSpec, build_estimator
from models.offline.evaluation.estimators import MeanEstimator
from models.offline.evaluation.loocv import loocv, loocv_seeds, run_fold
from models.offline.evaluation.metrics import error_table


def mae(run, data):
    return error_table(run.predictions, data.targets)["mae"]["mean"]


@pytest.mark.parametrize("name", ["ridge-both", "ridge-tactile", "ridge-visual", "knn-both", "svr-visual"])
def test_models_learn_the_linear_world_far_better_than_the_mean(linear_world, name):
    mean = mae(loocv(linear_world, EstimatorSpec("mean"), backend="serial", progress=False), linear_world)
    model = mae(loocv(linear_world, EstimatorSpec(name), backend="serial", progress=False), linear_world)
    assert model < 0.5 * mean, (name, model, mean)


def test_no_leakage_shuffled_labels_stay_at_predict_the_mean_level(linear_world):
    mean = mae(loocv(linear_world, EstimatorSpec("mean"), backend="serial", progress=False), linear_world)
    real = mae(loocv(linear_world, EstimatorSpec("ridge-both"), backend="serial", progress=False), linear_world)
    shuffled = [
        mae(
            loocv(linear_world, EstimatorSpec("shuffled-ridge-both"), seed=s, backend="serial", progress=False),
            linear_world,
        )
        for s in range(3)
    ]
    assert real < 0.3 * mean
    assert np.mean(shuffled) > 0.8 * mean, (shuffled, mean)


class PeekingEstimator(MeanEstimator):
    """Tries to read the held-out ratings at predict time."""

    def predict(self, data):
        assert data.targets is None, "the held-out texture's ratings reached predict"
        return super().predict(data)


def test_held_out_ratings_never_reach_predict(linear_world, monkeypatch):
    monkeypatch.setattr(EstimatorSpec, "build", lambda self: PeekingEstimator())
    pred, _, _, _ = run_fold(linear_world, EstimatorSpec("mean"), 3, 0)
    others = np.delete(linear_world.targets, 3, axis=0).mean(axis=0)
    np.testing.assert_allclose(pred, others, rtol=1e-6)


class TruthRecorder(MeanEstimator):
    """Records the per-texture truth rows that fit and predict are handed."""

    seen: dict = {}

    def fit(self, data, seed):
        TruthRecorder.seen["fit"] = (list(data.textures), data.meta.get("true_ratings"))
        return super().fit(data, seed)

    def predict(self, data):
        TruthRecorder.seen["predict"] = data.meta.get("true_ratings")
        return super().predict(data)


def test_the_held_out_textures_true_ratings_reach_neither_fit_nor_predict(linear_world, monkeypatch):
    truth = np.arange(4.0 * len(linear_world)).reshape(-1, 4)  # as the synthetic world carries its truth
    world = replace(linear_world, meta={**linear_world.meta, "true_ratings": truth})
    monkeypatch.setattr(EstimatorSpec, "build", lambda self: TruthRecorder())
    run_fold(world, EstimatorSpec("mean"), 3, 0)
    textures, fit_truth = TruthRecorder.seen["fit"]
    assert world.textures[3] not in textures
    np.testing.assert_array_equal(fit_truth, np.delete(truth, 3, axis=0))  # the training textures' rows only
    assert TruthRecorder.seen["predict"] is None


def test_process_backend_equals_serial(linear_world):
    a = loocv(linear_world, EstimatorSpec("ridge-both"), backend="serial", progress=False)
    b = loocv(linear_world, EstimatorSpec("ridge-both"), backend="process", workers=2, progress=False)
    np.testing.assert_allclose(a.predictions, b.predictions, rtol=1e-6)


def test_bad_arguments(linear_world):
    with pytest.raises(ValueError, match="unknown model"):
        build_estimator("no-such-model")
    with pytest.raises(ValueError, match="'ridge-both' does not take max_epochs"):
        build_estimator("ridge-both", max_epochs=3)
    with pytest.raises(ValueError, match="backend must be one of"):
        loocv(linear_world, EstimatorSpec("mean"), backend="threads")
    with pytest.raises(ValueError, match="at least 3 rated textures"):
        loocv(linear_world.take([0, 1]), EstimatorSpec("mean"))


def test_seeds_run_as_one_batch_equal_runs_one_seed_at_a_time(linear_world):
    spec = EstimatorSpec("shuffled-ridge-both")  # its training labels depend on the seed
    runs = loocv_seeds(linear_world, spec, (0, 1), backend="process", workers=2, progress=False)
    assert [r.seed for r in runs] == [0, 1]
    for run in runs:
        alone = loocv(linear_world, spec, seed=run.seed, backend="serial", progress=False)
        np.testing.assert_allclose(run.predictions, alone.predictions, rtol=1e-6)
    assert not np.allclose(runs[0].predictions, runs[1].predictions)


@pytest.fixture(scope="module")
def local_ray():
    ray = pytest.importorskip("ray", reason="Ray is not installed (pip install ray)")
    from models.offline.evaluation.loocv import ray_init

    if ray.is_initialized():
        ray.shutdown()
    try:
        ray_init(None, num_cpus=2)
    except ValueError as exc:
        pytest.skip(f"a local Ray instance cannot start here: {exc}")
    yield ray
    ray.shutdown()


def test_ray_backend_gives_the_serial_answer(linear_world, local_ray, monkeypatch):
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    spec = EstimatorSpec("shuffled-ridge-both")
    small = linear_world.take(range(12))
    runs = loocv_seeds(small, spec, (0, 1), backend="ray", workers=2, progress=False)
    for run in runs:
        alone = loocv(small, spec, seed=run.seed, backend="serial", progress=False)
        np.testing.assert_allclose(run.predictions, alone.predictions, rtol=1e-6)
        assert len(run.fold_seconds) == len(small)


def test_a_held_out_texture_can_be_shown_through_fewer_views(linear_world):
    from models.offline.evaluation.loocv import seen_through

    two = seen_through(linear_world.take([0, 1]), 1)
    np.testing.assert_array_equal(two.visual[:, 2], linear_world.visual[:2, 0])  # view 0 fills every slot
    spec = EstimatorSpec("krr-pooled")
    full = loocv(linear_world, spec, backend="serial", progress=False)
    one = loocv(linear_world, spec, backend="serial", progress=False, test_views=1)
    same = loocv(linear_world, spec, backend="serial", progress=False, test_views=3)
    np.testing.assert_allclose(same.predictions, full.predictions)  # all 3 stored views: no change
    assert not np.allclose(one.predictions, full.predictions)
    with pytest.raises(ValueError, match="must divide the 3 stored views"):
        loocv(linear_world, spec, backend="serial", progress=False, test_views=2)


def test_ridge_leaves_a_textures_augmented_copies_out_together():
    """Augmented copies of a texture share its name (tradeoffs' augmentation study): left out one by one beside their
    near-twins, a weak α looked best (the grid's smallest, 0.0018); left out by texture, α is the plain data's
    scaled by the copies (m copies weigh the data m times), within a grid step."""
    from models.offline.evaluation.data import TextureData
    from models.offline.evaluation.estimators import RidgeEstimator

    from .conftest import make_linear_world

    world, m = make_linear_world(n_textures=30, noise=30.0, seed=3), 4
    rng = np.random.default_rng(0)
    copies = TextureData(
        [t for t in world.textures for _ in range(m)],
        [g for g in world.groups for _ in range(m)],
        [x for x in world.tactile for _ in range(m)],
        np.repeat(world.visual, m, axis=0) + 0.05 * rng.normal(size=(len(world) * m, *world.visual.shape[1:])),
        np.repeat(world.targets, m, axis=0),
        dict(world.meta),
    )
    plain = RidgeEstimator("visual").fit(world, 0).alpha
    together = RidgeEstimator("visual").fit(copies, 0).alpha
    assert m * plain / 2 <= together <= m * plain * 2, (plain, together)


def _families(world):
    """world with its first 12 textures in four families of three (f0_1, f0_2, f0_3, f1_1, …), the rest alone."""
    names = [f"f{i // 3}_{i % 3 + 1}" if i < 12 else name for i, name in enumerate(world.textures)]
    return replace(world, textures=names)


class FitRecorder(MeanEstimator):
    """Records the textures of every fit, in order."""

    fits: list = []

    def fit(self, data, seed):
        FitRecorder.fits.append(set(data.textures))
        return super().fit(data, seed)


def test_leaving_families_out_keeps_every_sibling_out_of_the_fold_that_predicts_a_texture(linear_world, monkeypatch):
    world = _families(linear_world)
    FitRecorder.fits = []
    monkeypatch.setattr(EstimatorSpec, "build", lambda self: FitRecorder())
    run = loocv(world, EstimatorSpec("mean"), backend="serial", progress=False, leave_out="family")
    assert len(FitRecorder.fits) == len(world)
    for i, (name, fitted) in enumerate(zip(world.textures, FitRecorder.fits, strict=True)):
        family = {t for t in world.textures if t.split("_")[0] == name.split("_")[0]} if i < 12 else {name}
        assert fitted == set(world.textures) - family, name
        # known answer: predict-the-mean predicts the mean of exactly the textures outside the family
        keep = [j for j, t in enumerate(world.textures) if t not in family]
        np.testing.assert_allclose(run.predictions[i], world.targets[keep].mean(axis=0), rtol=1e-6)


def test_leaving_families_out_changes_only_the_textures_with_siblings(linear_world):
    world = _families(linear_world)
    by_texture = loocv(world, EstimatorSpec("ridge-both"), backend="serial", progress=False)
    by_family = loocv(world, EstimatorSpec("ridge-both"), backend="serial", progress=False, leave_out="family")
    np.testing.assert_allclose(by_family.predictions[12:], by_texture.predictions[12:], rtol=1e-6)
    assert not np.allclose(by_family.predictions[:12], by_texture.predictions[:12])


def test_leaving_families_out_refuses_folds_left_with_too_few_textures(linear_world):
    world = replace(linear_world.take([0, 1, 2, 3]), textures=["a_1", "a_2", "a_3", "b"])
    with pytest.raises(
        ValueError, match=r"leaving family .a. \(3 of the 4 textures\) out leaves fewer than 2 to train on"
    ):
        loocv(world, EstimatorSpec("mean"), backend="serial", progress=False, leave_out="family")


def test_test_views_must_divide_the_stored_views_of_data_with_images():
    from models.offline.evaluation.loocv import check_test_views

    for views in (1, 2, 4, 8):
        check_test_views(views, 8)
    for views in (0, -2, 3, 16):
        with pytest.raises(ValueError, match=f"^test views must divide the 8 stored views, got {views}$"):
            check_test_views(views, 8)
    with pytest.raises(ValueError, match="^test views need visual features, but the data has none$"):
        check_test_views(1, None)
