"""The demo's assets, built once and cached: a synthetic world, models trained on it, the library, unseen probes.

Assets from another world version, model or feature set are rebuilt; `demo.run` runs on them.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

from demo.run import DemoAssets

#: reads touch and vision, fits in a second, best exportable model on the synthetic world with these features
#: (reports/synthetic)
DEMO_MODEL = "ridge-both"
TACTILE_MODEL = "ridge-tactile"  # estimates windows until the session's first frame is embedded
#: tactile feature groups of the demo's models: every physical cue (the robot taps each probe before stroking it)
DEMO_GROUPS = ("friction", "spatial", "taps")
#: the world the models learn from (the library holds the first 24 of them): error still falls with more
#: textures at 48
DEMO_TEXTURES = 96


def demo_features():
    """The demo model's TactileConfig: the paper's MFCC set + DEMO_GROUPS."""
    from models.tactile.config import TactileConfig

    return TactileConfig(extra_groups=DEMO_GROUPS)


def demo_visual():
    """The demo model's VisualConfig: the served one (a frame costs tens of milliseconds, not ~0.6 s)."""
    from models.offline.featurize import SERVED_VISUAL

    return SERVED_VISUAL


#: models made by an older version of this recipe are retrained — 2: the OOD detector reads the speed/force
#: statistics where they are (before the extra groups' columns), not the last six columns (the tap features);
#: 3: the card carries its visual configuration; 4: the int8 backbone keeps its first six convolutions fp32 (its
#: features moved), and the card carries probe inputs and outputs it is checked against at load
MODELS_VERSION = 4
#: stamp keys that define the world (a change rebuilds dataset, library and probes); the rest retrain the models
WORLD_KEYS = ("world_version", "n_textures", "library_textures", "n_probes", "seed")


def _stamp(n_textures: int, library_textures: int, n_probes: int, seed: int) -> dict:
    from texture_library.procedural import WORLD_VERSION

    return {
        "world_version": WORLD_VERSION,
        "models_version": MODELS_VERSION,
        "model": DEMO_MODEL,
        "tactile_model": TACTILE_MODEL,
        "tactile_hash": demo_features().hash(),
        "visual_hash": demo_visual().hash(),
        "backbone": demo_visual().backbone,  # a selection field, outside the hash: int8 and fp32 features differ
        "n_textures": n_textures,
        "library_textures": library_textures,
        "n_probes": n_probes,
        "seed": seed,
    }


def prepare_assets(
    root: Path, *, n_textures: int = DEMO_TEXTURES, n_probes: int = 4, seed: int = 0, library_textures: int = 24
) -> DemoAssets:
    """Build whatever is missing under root (needs the train extra the first time); assets made for
    another world version or size are rebuilt, models made for another model or feature set retrained."""
    import shutil

    from models.offline.datasets.build import build
    from models.offline.featurize import backbone_onnx, featurize_dataset
    from models.offline.train import train_and_export
    from texture_library.synthetic_library import build_synthetic_library

    root.mkdir(parents=True, exist_ok=True)
    assets = DemoAssets(
        root / "dataset", root / "model.onnx", root / "tactile.onnx", Path(), root / "library", root / "probes"
    )
    stamp_path, stamp = root / "assets.json", _stamp(n_textures, library_textures, n_probes, seed)
    old = json.loads(stamp_path.read_text()) if stamp_path.is_file() else None
    if old is None and assets.model.is_file() or old is not None and any(old.get(k) != stamp[k] for k in WORLD_KEYS):
        print("  · assets were made for another world: rebuilding them", flush=True)
        for path in (assets.dataset, assets.library, assets.probes):
            shutil.rmtree(path, ignore_errors=True)
    if old != stamp:
        assets.model.unlink(missing_ok=True)
        assets.tactile.unlink(missing_ok=True)
    features, visual = demo_features(), demo_visual()
    library_textures = min(library_textures, n_textures)
    groups = " + ".join(["MFCC", *DEMO_GROUPS])
    steps = [
        (
            not (assets.dataset / "dataset.json").is_file(),
            f"building a synthetic world of {n_textures} textures",
            lambda: build("synthetic", assets.dataset, n_textures=n_textures, seed=seed),
        ),
        (  # only the training reads them: a warm run (both models current) skips the step and its line
            not (assets.model.is_file() and assets.tactile.is_file()),
            "computing features",
            lambda: featurize_dataset(assets.dataset, tactile_config=features, visual_config=visual),
        ),
        (
            not assets.model.is_file(),
            f"training {DEMO_MODEL} on it ({groups}) and exporting ONNX",
            lambda: train_and_export(
                assets.dataset, DEMO_MODEL, assets.model, seed=seed, tactile_config=features, visual_config=visual
            ),
        ),
        (
            not assets.tactile.is_file(),
            f"training {TACTILE_MODEL} (the same features; windows before the first frame) and exporting ONNX",
            lambda: train_and_export(assets.dataset, TACTILE_MODEL, assets.tactile, seed=seed, tactile_config=features),
        ),
        (
            not (assets.library / "library.json").is_file(),
            "writing the texture library",
            lambda: build_synthetic_library(assets.library, n_textures=library_textures, seed=seed),
        ),
        (
            not (assets.probes / "library.json").is_file(),
            f"making {n_probes} unseen probe textures",
            lambda: build_synthetic_library(assets.probes, n_textures=n_probes, seed=seed + 1),
        ),
    ]
    for needed, what, step in steps:
        if needed:
            print(f"  · {what} …", flush=True)
            step()
    stamp_path.write_text(json.dumps(stamp))
    return dataclasses.replace(assets, backbone=backbone_onnx(visual))


def prepared(assets_dir: str | Path) -> DemoAssets:
    """prepare_assets with progress lines for the terminal."""
    print("hapticlink demo — preparing assets", flush=True)
    t0 = time.perf_counter()
    assets = prepare_assets(Path(assets_dir))
    print(f"  assets ready in {time.perf_counter() - t0:.0f} s: {assets.model}", flush=True)
    return assets
