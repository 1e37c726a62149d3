"""models.offline.calibrate: held-out predictions see one frame, whatever number of views the model pools."""

import importlib.util
from dataclasses import replace
from pathlib import Path

import numpy as np

from models.offline.calibrate import predict
from models.offline.evaluation.estimator_registry import EstimatorSpec

_spec = importlib.util.spec_from_file_location("eval_conftest", Path(__file__).parent / "evaluation" / "conftest.py")
_eval = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_eval)


def test_a_view_pooling_model_predicts_from_one_frame_as_if_every_view_were_that_frame():
    data = _eval.make_linear_world(n_textures=16, n_windows=5)  # 3 stored views per texture
    train = data.take(np.arange(1, 16))
    est = EstimatorSpec("ridge-pooled").build().fit(train, 0)
    assert est.pooled_views(data.visual.shape[1]) == 3
    frame = data.visual[0, 1]
    got = predict(est, train, data.tactile[0], frame)
    tiled = replace(data.take(np.array([0])).with_targets(None), visual=np.tile(frame[None, None], (1, 3, 1)))
    np.testing.assert_allclose(got.texture, np.clip(est.predict(tiled)[0], -100, 100), rtol=1e-6)
    assert got.windows.shape == (5, 4)
    one_view = predict(EstimatorSpec("ridge-both").build().fit(train, 0), train, data.tactile[0], frame)
    assert one_view.windows.shape == (5, 4)  # a one-view model reads the same frame
