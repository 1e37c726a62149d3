"""What an exported hapticlink model file says about itself (ONNX metadata_props).

Every key is a string; structured values are JSON. The service reads these to
refuse a model whose feature configuration differs from its own, to know
whether the model needs a visual input and from which backbone, and to show
where the model came from.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

from texture_library.attributes import ATTRIBUTES, RATING_MAX, RATING_MIN

FORMAT = "hapticlink-perceptual-model"
VERSION = 1
INPUT_TACTILE = "tactile"
INPUT_VISUAL = "visual"
OUTPUT = "ratings"


@dataclass(frozen=True)
class ModelCard:
    """model: registry name; modality: tactile | visual | both; tactile_config: TactileConfig.to_dict();
    visual: {"backbone", "backbone_dim", "visual_hash", "visual_config", "visual_part", "views", "pooling",
    "view_seed"} or None — visual_config: models.visual.config.VisualConfig.computation();
    views: how many image views the model's visual input pools (models.visual.pooling; 1: one photo/frame);
    metrics: LOOCV summary (0–100 scale); fit_info: what the fit chose (e.g. the selected candidate per attribute);
    intervals: {"window" | "ema" | "texture": models.inference.intervals.IntervalCalibration.to_dict()} or None;
    ood: models.inference.ood.OODDetector.to_dict() or None (both written by `hapticlink train`);
    probe: the load-time check (`Predictor` runs it): {"tactile", "visual": jsonarrays-encoded (n, F) / (n, D)
    inputs or None, "ratings": the (n, 4) outputs the exported file gave on the host that exported it} or None."""

    model: str
    modality: str
    tactile_config: dict
    tactile_hash: str
    visual: dict | None
    dataset: str
    metrics: dict
    n_params: int
    trained_on: list[str]
    seed: int
    intervals: dict | None = None
    ood: dict | None = None
    fit_info: dict = field(default_factory=dict)
    probe: dict | None = None

    def to_metadata(self) -> dict[str, str]:
        return {
            "hapticlink.format": FORMAT,
            "hapticlink.version": str(VERSION),
            "model": self.model,
            "modality": self.modality,
            "attributes": json.dumps(list(ATTRIBUTES)),
            "rating_scale": json.dumps([RATING_MIN, RATING_MAX]),
            "tactile_config": json.dumps(self.tactile_config, sort_keys=True),
            "tactile_hash": self.tactile_hash,
            "visual": json.dumps(self.visual),
            "dataset": self.dataset,
            "metrics": json.dumps(self.metrics),
            "n_params": str(self.n_params),
            "trained_on": json.dumps(self.trained_on),
            "seed": str(self.seed),
            **({} if self.intervals is None else {"intervals": json.dumps(self.intervals, sort_keys=True)}),
            **({} if self.ood is None else {"ood": json.dumps(self.ood, sort_keys=True)}),
            "fit_info": json.dumps(self.fit_info),
            **({} if self.probe is None else {"probe": json.dumps(self.probe, sort_keys=True)}),
        }

    @classmethod
    def from_metadata(cls, meta: dict[str, str], source: str = "model") -> ModelCard:
        if meta.get("hapticlink.format") != FORMAT:
            raise ValueError(f"{source}: not a hapticlink model (metadata format {meta.get('hapticlink.format')!r})")
        if meta.get("hapticlink.version") != str(VERSION):
            raise ValueError(
                f"{source}: unsupported model version {meta.get('hapticlink.version')!r} "
                f"(this hapticlink reads {VERSION})"
            )
        if json.loads(meta.get("attributes", "[]")) != list(ATTRIBUTES):
            raise ValueError(f"{source}: attributes {meta.get('attributes')} differ from {list(ATTRIBUTES)}")
        try:
            return cls(
                model=meta["model"],
                modality=meta["modality"],
                tactile_config=json.loads(meta["tactile_config"]),
                tactile_hash=meta["tactile_hash"],
                visual=json.loads(meta["visual"]),
                dataset=meta.get("dataset", ""),
                metrics=json.loads(meta.get("metrics", "{}")),
                n_params=int(meta.get("n_params", 0)),
                trained_on=json.loads(meta.get("trained_on", "[]")),
                seed=int(meta.get("seed", 0)),
                intervals=json.loads(meta["intervals"]) if "intervals" in meta else None,
                ood=json.loads(meta["ood"]) if "ood" in meta else None,
                fit_info=json.loads(meta.get("fit_info", "{}")),
                probe=json.loads(meta["probe"]) if "probe" in meta else None,
            )
        except (KeyError, json.JSONDecodeError) as exc:
            raise ValueError(f"{source}: incomplete model metadata ({exc})") from None


def read_metadata(path: str | Path) -> dict[str, str]:
    """An ONNX file's metadata_props, read with onnxruntime (no torch, no onnx package needed)."""
    import onnxruntime as ort

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"model file not found: {path}")
    options = ort.SessionOptions()
    options.log_severity_level = 3
    try:
        sess = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    except Exception as exc:  # noqa: BLE001 - onnxruntime raises several types for a bad file
        raise ValueError(f"{path}: not a loadable ONNX model ({exc})") from None
    return dict(sess.get_modelmeta().custom_metadata_map)


def write_metadata(path: str | Path, metadata: dict[str, str]) -> None:
    """Replace an ONNX file's metadata_props with `metadata` (string keys and values)."""
    import onnx

    model = onnx.load(str(path))
    del model.metadata_props[:]
    for k, v in metadata.items():
        entry = model.metadata_props.add()
        entry.key, entry.value = k, v
    onnx.save(model, str(path))


def read_card(path: str | Path) -> ModelCard:
    """The card of an exported hapticlink model."""
    return ModelCard.from_metadata(read_metadata(path), str(path))
