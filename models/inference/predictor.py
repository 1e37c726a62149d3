"""Run an exported perceptual model with onnxruntime (serving path: numpy + onnxruntime, no torch)."""

from __future__ import annotations

from pathlib import Path
from typing import get_args

import numpy as np
import onnxruntime as ort

from models.inference import jsonarrays
from models.inference.modelfile import INPUT_TACTILE, INPUT_VISUAL, ModelCard
from models.tactile.config import TactileConfig
from models.visual.config import BackboneChoice, VisualConfig

# The most a model's outputs on its card's probe inputs may differ from the stored ones, bipolar points (−100…100):
# fp32 kernels differ across CPUs by rounding (≈ 1e-4 here); a broken graph or a lossy kernel by far more.
PROBE_TOLERANCE = 0.01


class Predictor:
    """ratings = predictor.predict(tactile (N, F) float32, visual (N, D) float32 | None) → (N, 4) bipolar.

    expected_tactile_hash: refuse a model trained on other tactile features than the pipeline computes.
    visual_config: the image configuration the model was trained on, its backbone included (from its card; the
    default for a card from before the card carried it), so the service computes the vector the model reads.
    probe_tolerance: the load-time check: a model whose outputs on its card's probe inputs differ from the stored
    ones by more (bipolar points) on this CPU is refused (`probe_error`: the difference; None without a probe).
    """

    def __init__(
        self,
        path: str | Path,
        *,
        threads: int = 1,
        expected_tactile_hash: str | None = None,
        probe_tolerance: float = PROBE_TOLERANCE,
    ):
        self.path = Path(path)
        if not self.path.is_file():
            raise ValueError(f"model file not found: {self.path}")
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
        try:
            self.session = ort.InferenceSession(str(self.path), opts, providers=["CPUExecutionProvider"])
        except Exception as exc:  # noqa: BLE001
            raise ValueError(f"{self.path}: not a loadable ONNX model ({exc})") from None
        self.card = ModelCard.from_metadata(self.session.get_modelmeta().custom_metadata_map, str(self.path))
        self.tactile_config = TactileConfig(**self.card.tactile_config)
        if self.tactile_config.hash() != self.card.tactile_hash:
            raise ValueError(
                f"{self.path}: tactile config hash {self.card.tactile_hash} does not match its config "
                f"({self.tactile_config.hash()}); the feature code changed since export"
            )
        if expected_tactile_hash is not None and expected_tactile_hash != self.card.tactile_hash:
            raise ValueError(
                f"{self.path}: model expects tactile features {self.card.tactile_hash}, "
                f"the pipeline computes {expected_tactile_hash}; re-export the model or change the feature settings"
            )
        visual = self.card.visual or {}
        # the backbone the card names (a selection field, outside the hash): int8 and fp32 features differ
        backbone = {"backbone": visual["backbone"]} if visual.get("backbone") in get_args(BackboneChoice) else {}
        self.visual_config = VisualConfig(**visual.get("visual_config", {}), **backbone)
        if self.card.visual and self.visual_config.hash() != self.card.visual.get("visual_hash"):
            # a card from before the configuration was recorded names only the hash; the default is what it had
            raise ValueError(
                f"{self.path}: visual config hash {self.card.visual.get('visual_hash')} does not match its config "
                f"({self.visual_config.hash()}); re-export the model"
            )
        self.inputs = {i.name: i for i in self.session.get_inputs()}
        self.n_tactile = self._width(INPUT_TACTILE)
        self.n_visual = self._width(INPUT_VISUAL)
        if self.n_tactile is not None and self.n_tactile != self.tactile_config.n_features:
            raise ValueError(
                f"{self.path}: tactile input has {self.n_tactile} features, "
                f"its config says {self.tactile_config.n_features}"
            )
        self.probe_error: float | None = None
        if self.card.probe is not None:
            self.probe_error = self._self_check(self.card.probe, probe_tolerance)

    def _self_check(self, probe: dict, tolerance: float) -> float:
        """Run the card's probe inputs; ValueError when the outputs differ from the stored ones past `tolerance`."""
        what = f"{self.path}: card probe"
        if not isinstance(probe, dict) or "ratings" not in probe:
            raise ValueError(f"{what} is not a probe (no ratings)")
        inputs = {
            name: None if probe.get(name) is None else jsonarrays.decode(probe[name], f"{what} {name}")
            for name in (INPUT_TACTILE, INPUT_VISUAL)
        }
        expected = jsonarrays.decode(probe["ratings"], f"{what} ratings")
        try:
            got = self.predict(inputs[INPUT_TACTILE], inputs[INPUT_VISUAL])
        except ValueError as exc:
            raise ValueError(f"{what} does not fit the model: {exc}") from None
        if got.shape != expected.shape:
            raise ValueError(f"{what}: the model gives {got.shape} outputs, the card stores {expected.shape}")
        error = float(np.max(np.abs(got.astype(np.float64) - expected), initial=0.0))
        if not error <= tolerance:  # NaN fails too
            raise ValueError(
                f"{self.path}: on this CPU the model's outputs on the probe inputs its card stores differ from the "
                f"outputs recorded at export by up to {error:.4g} bipolar points (tolerance {tolerance:g}); "
                "refusing it: its numerics do not hold here (export it again on this host to compare)"
            )
        return error

    def _width(self, name: str) -> int | None:
        if name not in self.inputs:
            return None
        return int(self.inputs[name].shape[1])

    @property
    def needs_visual(self) -> bool:
        return self.n_visual is not None

    @property
    def needs_tactile(self) -> bool:
        return self.n_tactile is not None

    def predict(self, tactile: np.ndarray | None, visual: np.ndarray | None = None) -> np.ndarray:
        feeds = {}
        n = None
        for name, arr, width in ((INPUT_TACTILE, tactile, self.n_tactile), (INPUT_VISUAL, visual, self.n_visual)):
            if width is None:
                continue
            if arr is None:
                raise ValueError(f"model {self.card.model} needs a {name} input")
            arr = np.asarray(arr, np.float32)
            if arr.ndim == 1:
                arr = arr[None, :]
            if arr.ndim != 2 or arr.shape[1] != width:
                raise ValueError(f"{name} must be (N, {width}), got {arr.shape}")
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"{name} contains NaN or Inf")
            if n is not None and arr.shape[0] != n:
                raise ValueError(f"tactile and visual batch sizes differ: {n} vs {arr.shape[0]}")
            n = arr.shape[0]
            feeds[name] = arr
        return self.session.run(None, feeds)[0]

    def warm_up(self) -> None:
        """One inference so the first real window does not pay for lazy initialisation."""
        tactile = None if self.n_tactile is None else np.zeros((1, self.n_tactile), np.float32)
        visual = None if self.n_visual is None else np.zeros((1, self.n_visual), np.float32)
        self.predict(tactile, visual)
