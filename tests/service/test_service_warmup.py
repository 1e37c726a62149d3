"""No cold start: /ready waits for the warm-up, which runs the whole serving path, the backbone on a full frame."""

from __future__ import annotations

import dataclasses
import gc
import threading

import httpx

import service.state
from service.runtime import load_runtime
from service.settings import Settings
from service.warmup import WARM_UP_FRAME_PX, warm_up


class _CountingBackbone:
    def __init__(self, backbone) -> None:
        self._backbone, self.patches = backbone, []

    def __getattr__(self, name):
        return getattr(self._backbone, name)

    def embed(self, patches):
        self.patches.append(patches.shape)
        return self._backbone.embed(patches)


def test_warm_up_runs_every_model_and_the_backbone_on_a_whole_frame(kit, visual_model, library_dir):
    settings = Settings(
        model_path=visual_model.model,
        tactile_model_path=visual_model.tactile,
        library_dir=library_dir,
        backbone_path=visual_model.backbone,
    )
    runtime = load_runtime(settings)
    spy = _CountingBackbone(runtime.backbone)
    runtime = dataclasses.replace(runtime, backbone=spy)
    calls = {"main": 0, "tactile": 0}
    for name, predictor in (("main", runtime.predictor), ("tactile", runtime.tactile)):
        original = predictor.predict

        def counted(*args, _name=name, _original=original):
            calls[_name] += 1
            return _original(*args)

        predictor.predict = counted  # type: ignore[method-assign]
    assert warm_up(runtime, settings) > 0
    # a frame's whole patch grid (grid² patches), not one patch
    assert sum(shape[0] for shape in spy.patches) == runtime.visual_config.n_patches, spy.patches
    assert all(shape[1:] == (runtime.visual_config.patch_size,) * 2 for shape in spy.patches)
    assert WARM_UP_FRAME_PX > runtime.visual_config.patch_size
    assert calls["main"] >= 2 and calls["tactile"] >= 2, calls  # each model alone and in a batch


def test_ready_waits_for_the_warm_up_and_the_heap_is_frozen(kit, base_settings, monkeypatch):
    release, entered = threading.Event(), threading.Event()
    real = service.state.warm_up

    def slow_warm_up(runtime, settings):
        entered.set()
        release.wait(30)
        return real(runtime, settings)

    monkeypatch.setattr(service.state, "warm_up", slow_warm_up)
    settings = base_settings.model_copy(update={"instance_id": "warm"})
    with kit.running(settings, wait_ready=False) as srv, httpx.Client(base_url=srv.url, timeout=10) as client:
        assert entered.wait(30)
        r = client.get("/ready")
        assert r.status_code == 503 and "warming up" in r.json()["detail"]
        assert client.post("/sessions", json={}, headers=kit.FLEET).status_code == 503
        release.set()
        kit.wait_for(lambda: client.get("/ready").status_code == 200)
        assert gc.get_freeze_count() > 0
