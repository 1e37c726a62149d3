"""`hapticlink train` and `hapticlink predict`: fit on every rated texture, export ONNX, predict textures."""

from __future__ import annotations

import csv
import json
import warnings
from pathlib import Path

import numpy as np

from models.inference.modelfile import ModelCard
from models.inference.predictor import Predictor
from models.offline.evaluation.data import TextureData, load_texture_data
from models.offline.evaluation.estimator_registry import build_estimator
from models.tactile.config import TactileConfig
from models.visual.config import VisualConfig
from models.visual.embedding import VisualPart
from models.visual.pooling import POOLING, pool_views
from texture_library.attributes import ATTRIBUTES

VIEW_SEED = 0  # the augmented views' seed (featurize.visual_table's default)


MIN_CALIBRATION_TEXTURES = 8  # K-fold calibration with a detector per fold needs a few textures per side


def train_and_export(
    dataset: str | Path,
    model: str,
    out: str | Path,
    *,
    seed: int = 0,
    tactile_config: TactileConfig | None = None,
    visual_config: VisualConfig | None = None,
    visual_part: VisualPart = "both",
    metrics: str | Path | None = None,
    options: dict | None = None,
    calibration_folds: int = 10,
    interval_scale: str = "none",
    exclude: tuple[str, ...] = (),
) -> Path:
    """Train `model` on all rated textures of `dataset` and write an ONNX file with its card.

    metrics: a results.json from `hapticlink evaluate` whose LOOCV numbers go into the card.
    calibration_folds: K of the cross-validation that calibrates the card's prediction intervals
    and goes with its out-of-distribution detector (models.offline.calibrate.cv_uncertainty; K more fits);
    0 leaves both out. interval_scale: "none" or "distance" (see models.inference.intervals).
    visual_config: how images become features (default VisualConfig()); the card records it for the service.
    `selected` runs its selection rule (inner CV) on all rated textures here, as each LOOCV fold did on its own.
    exclude: rated textures left out of everything (training, calibration, detector), e.g. the textures a
    benchmark then streams as unseen.
    """
    from models.offline.datasets.format import Dataset

    ds = Dataset(dataset)
    if not ds.has_recordings:
        # every exported model card carries the tactile pipeline the service checks; an image-only card does not
        # exist yet. Offline predictions: python -m models.offline.evaluation.image_benchmark withheld
        raise ValueError(
            f"dataset {ds.name!r} is image-only (no recordings): exporting a model trained on it is not supported; "
            "use `python -m models.offline.evaluation.image_benchmark withheld` for its predictions"
        )
    est = build_estimator(model, **(options or {}))
    if not hasattr(est, "export"):
        raise ValueError(f"model {model!r} has no ONNX export; export a network, ridge, a *-pooled model or selected")
    needs_visual = est.modality in ("visual", "both")
    data = load_texture_data(
        dataset,
        tactile_config=tactile_config,
        visual=needs_visual,
        visual_part=visual_part,
        visual_config=visual_config,
    )
    if exclude:
        unknown = sorted(set(exclude) - set(data.textures))
        if unknown:
            raise ValueError(f"cannot exclude {unknown}: not rated textures of {dataset}")
        data = data.take([i for i, t in enumerate(data.textures) if t not in set(exclude)])
    est.fit(data, seed)
    loocv = {}
    if metrics is not None:
        res = json.loads(Path(metrics).read_text())
        if res["model"] != model:
            raise ValueError(f"{metrics} holds the LOOCV of {res['model']!r}, not of {model!r}")
        loocv = {"mae": res["mae"], "rmse": res["rmse"], "seeds": res["seeds"], "model": res["model"]}
    visual = None
    if est.modality in ("visual", "both"):  # what the fitted model reads (a selection may drop a modality)
        visual = {k: data.meta[k] for k in ("backbone", "backbone_dim", "visual_hash", "visual_config", "visual_part")}
        visual.update(
            views=est.pooled_views(data.visual.shape[1]),
            pooling=POOLING,
            view_seed=VIEW_SEED,
            views_stored=int(data.visual.shape[1]),
        )
    intervals = ood = None
    if calibration_folds and len(data) < MIN_CALIBRATION_TEXTURES:
        warnings.warn(
            f"{len(data)} rated textures are too few to calibrate intervals (need ≥ {MIN_CALIBRATION_TEXTURES}); "
            "the model card carries no intervals and no OOD detector",
            stacklevel=2,
        )
    elif calibration_folds:
        from models.offline.calibrate import cv_uncertainty, photo_statistics
        from models.offline.evaluation.estimator_registry import EstimatorSpec

        frames = photo_statistics(dataset, data.textures) if needs_visual else None
        cals, detector = cv_uncertainty(
            data,
            EstimatorSpec(model, options or {}),
            seed,
            folds=min(calibration_folds, len(data)),
            scale_kind=interval_scale,
            frames=frames,
        )
        intervals = {target: cal.to_dict() for target, cal in cals.items()}
        ood = detector.to_dict()
    card = ModelCard(
        model=model,
        modality=est.modality,
        tactile_config=data.meta["tactile_config"],
        tactile_hash=data.meta["tactile_hash"],
        visual=visual,
        dataset=str(data.meta.get("dataset")),
        metrics=loocv,
        n_params=est.n_params(),
        trained_on=data.textures,
        seed=seed,
        intervals=intervals,
        ood=ood,
        fit_info=est.fit_info(),
    )
    path = Path(est.export(out, card.to_metadata()))
    attach_probe(path, data)
    return path


PROBE_TEXTURES = 4


def attach_probe(path: Path, data: TextureData) -> None:
    """Store the load-time check in the card of the model exported at `path`: the first window (and view-0 image
    features) of PROBE_TEXTURES textures spread over `data`, and the file's outputs on them on this host."""
    from models.inference import jsonarrays
    from models.inference.modelfile import read_metadata, write_metadata

    predictor = Predictor(path)
    picks = np.unique(np.linspace(0, len(data) - 1, min(PROBE_TEXTURES, len(data))).round().astype(int))
    tactile = np.stack([data.tactile[i][0] for i in picks]) if predictor.needs_tactile else None
    visual = None
    if predictor.needs_visual:
        if data.visual is None or data.visual.shape[2] != predictor.n_visual:
            raise ValueError(
                f"{path}: the model reads {predictor.n_visual} visual features, the data holds "
                f"{None if data.visual is None else data.visual.shape[2]}"
            )
        visual = data.visual[picks, 0]
    ratings = predictor.predict(tactile, visual)
    probe = {
        "tactile": None if tactile is None else jsonarrays.encode(tactile),
        "visual": None if visual is None else jsonarrays.encode(visual),
        "ratings": jsonarrays.encode(ratings),
    }
    meta = read_metadata(path)
    meta["probe"] = json.dumps(probe, sort_keys=True)
    write_metadata(path, meta)


def predict_dataset(
    model_path: str | Path, dataset: str | Path, *, rated: str | None = None
) -> tuple[list[str], np.ndarray]:
    """Per-texture predictions (T, 4) bipolar: each texture's windows predicted and averaged."""
    predictor = Predictor(model_path)
    card = predictor.card
    part = card.visual["visual_part"] if card.visual else "both"
    data: TextureData = load_texture_data(
        dataset,
        tactile_config=predictor.tactile_config,
        visual=predictor.needs_visual,
        visual_part=part,
        visual_config=predictor.visual_config,
        rated=rated,
    )
    if predictor.needs_visual:
        if data.meta["backbone"] != card.visual["backbone"] or data.meta["visual_hash"] != card.visual["visual_hash"]:
            raise ValueError(
                f"model wants visual features from {card.visual['backbone']} ({card.visual['visual_hash']}), "
                f"this machine computes {data.meta['backbone']} ({data.meta['visual_hash']})"
            )
    views = int(card.visual.get("views", 1)) if card.visual else 1
    if predictor.needs_visual and data.visual.shape[1] < views:
        raise ValueError(f"model pools {views} image views per texture; the dataset stores {data.visual.shape[1]}")
    preds = []
    for i, windows in enumerate(data.tactile):
        # the texture's first `views` views pooled as in training: one visual vector for all its windows
        visual = (
            np.repeat(pool_views(data.visual[i, :views])[None], len(windows), axis=0)
            if predictor.needs_visual
            else None
        )
        preds.append(predictor.predict(windows if predictor.needs_tactile else None, visual).mean(axis=0))
    return data.textures, np.array(preds)


def write_predictions(path: str | Path, textures: list[str], preds: np.ndarray) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["texture", *ATTRIBUTES])
        for t, p in zip(textures, preds):
            w.writerow([t, *(f"{v:.2f}" for v in p)])
    return path
