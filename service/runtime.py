"""What the service computes with: the model, its feature configuration, the library and the visual backbone.

Loaded once at start-up (blocking: run it in a thread) and checked against each other;
service/warmup.py then runs the whole serving path once. Everything here is numpy + onnxruntime; nothing imports torch.
"""

from __future__ import annotations

import io
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image

from drivers.blocks import check_frame_pixels, frame_bomb
from models.inference.ood import FrameCheck
from models.inference.predictor import Predictor
from models.tactile.config import TactileConfig
from models.visual.config import VisualConfig
from models.visual.embedding import part_columns, visual_features, visual_layout
from models.visual.image import load_image
from models.visual.onnx_backbone import OnnxBackbone, ProbeCheck
from service.adaptive import ServingPolicy
from service.render_models import RenderCatalog
from service.settings import Settings
from service.uncertainty import ServedModel
from texture_library.library import Library
from texture_library.nearest import PerceptualIndex
from texture_library.selection import SelectionRule, SpectralTable, sensor_noise_psd

log = logging.getLogger(__name__)

# drivers.blocks.MAX_FRAME_PIXELS: a larger declared size is refused before decoding, so a small compressed body cannot
# expand into gigabytes (Pillow itself only warns below 179 Mpx)


@dataclass(frozen=True)
class BackboneStatus:
    """The backbone the service embeds frames with, and why that one.

    configured: the name of the file configured (HAPTICLINK_BACKBONE_PATH); served: the name of the one that
    runs: the configured one, or the fp32 backbone it was quantized from where its check failed on this CPU;
    check: the configured backbone's load-time check (None: the file carries no probe, so it is unchecked);
    fallback_check: the served fallback's own check (None without a fallback or a probe)."""

    configured: str
    served: str
    check: ProbeCheck | None
    fallback_check: ProbeCheck | None = None

    @property
    def fallback(self) -> bool:
        return self.served != self.configured

    def to_dict(self) -> dict:
        """What /ready and a session's status say of it (service.schemas.BackboneOut)."""
        return {
            "served": self.served,
            "configured": self.configured,
            "fallback": self.fallback,
            "probe_cosine": None if self.check is None else round(self.check.cosine, 4),
            "bound": None if self.check is None else self.check.bound,
            "detail": self.describe(),
        }

    def describe(self) -> str:
        """One line for /ready and the log."""
        if self.check is None:
            return f"{self.configured}: unchecked (the file carries no probe; export it again)"
        if not self.fallback:
            return f"{self.configured}: {self.check.describe()}"
        return f"{self.configured} failed its check on this CPU ({self.check.describe()}); serving {self.served}"


@dataclass(frozen=True)
class Runtime:
    """The loaded models and library.

    main: the served model with its card's uncertainty (service.uncertainty.ServedModel);
    fallback: an optional tactile-only model that estimates windows while a session has no visual
    embedding yet (same feature configuration as the main model; None: such windows wait);
    cheap: an optional cheap model the adaptive policy asks first (service.adaptive);
    policy: how much model each window and frame gets (always-full | adaptive);
    interval_level: nominal coverage of the published intervals (and of those the adaptive policy reads);
    tactile_config: the model's TactileConfig with the serving hop (everything else as trained);
    backbone / visual_columns: set when the model reads visual features and a backbone is configured;
    backbone_status: which backbone embeds the frames and how its load-time check went (None: no backbone);
    problem: why the service cannot estimate (None when it can), shown by GET /ready;
    selection: the rule that picks the entry to render; spectra: the library's vibration spectra on a
    speed–force grid, precomputed at load for a rule that reads the window's vibration (else None).
    render_models: every library entry's rendering model as served (GET /library/{id}/model).
    untapped: for a model with the taps group, an optional tactile model trained on the same features without
    it, which estimates the windows of a surface that has not been tapped (None: such windows wait); it reads the
    first `untapped.predictor.n_tactile` feature columns (the taps group's columns come last).
    """

    main: ServedModel
    fallback: ServedModel | None
    cheap: ServedModel | None
    policy: ServingPolicy
    tactile_config: TactileConfig
    library: Library
    index: PerceptualIndex
    visual_config: VisualConfig
    backbone: OnnxBackbone | None
    visual_columns: np.ndarray | None
    problem: str | None
    load_s: float
    interval_level: float = 0.9
    selection: SelectionRule = SelectionRule()
    spectra: SpectralTable | None = None
    render_models: RenderCatalog = field(default_factory=lambda: RenderCatalog({}))
    untapped: ServedModel | None = None
    backbone_status: BackboneStatus | None = None

    @property
    def predictor(self) -> Predictor:
        return self.main.predictor

    @property
    def tactile(self) -> Predictor | None:
        """The tactile-only fallback model's predictor (None when none is configured)."""
        return None if self.fallback is None else self.fallback.predictor

    @property
    def model_name(self) -> str:
        return self.predictor.card.model

    @property
    def needs_visual(self) -> bool:
        return self.predictor.needs_visual

    @property
    def needs_taps(self) -> bool:
        """True when the model's features include the taps group (tap blocks feed it; others ignore them)."""
        return "taps" in self.tactile_config.extra_groups

    @property
    def can_estimate_without_frame(self) -> bool:
        """True when windows of a session without a visual embedding can be estimated (tactile-only)."""
        return not self.needs_visual or self.fallback is not None

    def full_model(self, visual: bool) -> ServedModel:
        """The full model for windows with (True) or without (False) a visual embedding."""
        if visual or not self.needs_visual:
            return self.main
        if self.fallback is None:
            raise ValueError(
                f"model {self.model_name} needs a camera frame first and no tactile-only model is configured"
            )
        return self.fallback

    def first_model(self, visual: bool) -> ServedModel:
        """The model a window asks first: the cheap one under the adaptive policy (where it can read what the
        window has), else the full one."""
        if self.policy.adaptive and self.cheap is not None and (visual or not self.cheap.predictor.needs_visual):
            return self.cheap
        return self.full_model(visual)

    def served_models(self) -> list[ServedModel]:
        return [m for m in (self.main, self.fallback, self.cheap) if m is not None]

    def visual_models(self) -> list[ServedModel]:
        return [m for m in self.served_models() if m.predictor.needs_visual]

    def embed_and_inspect(self, gray: np.ndarray) -> tuple[np.ndarray, dict[str, list[str]]]:
        """Visual pool: (H, W) grayscale → (its embedding (D,), each visual model's frame reasons by name)."""
        return self.embed_frame(gray), {m.name: m.frame_reasons(gray) for m in self.visual_models()}

    def frame_checks(self, reasons: dict[str, list[str]], visual: np.ndarray) -> dict[str, FrameCheck | None]:
        """A session's visual input (D,) and its newest frame's reasons → each visual model's FrameCheck by name."""
        return {m.name: m.frame_check(reasons.get(m.name, []), visual) for m in self.visual_models()}

    def decode_frame(self, image: bytes) -> np.ndarray:
        """Encoded image → (H, W) float32 grayscale in [0, 1]; ValueError if unreadable, smaller than a patch or
        larger than MAX_FRAME_PIXELS."""
        frame_pixels(image)
        try:
            return load_image(image, min_size=self.visual_config.patch_size)
        except ValueError:
            raise
        except Exception as exc:  # noqa: BLE001 - decoders of untrusted bytes raise all kinds of errors
            raise ValueError(f"not a readable image ({type(exc).__name__}: {exc})") from None

    def embed_frame(self, gray: np.ndarray) -> np.ndarray:
        """(H, W) grayscale → the model's visual input (D,) float32: backbone ⊕ GLCM, columns per the card.

        BackboneStopped after `stop()`."""
        if self.backbone is None or self.visual_columns is None:
            raise ValueError("no visual backbone is configured (HAPTICLINK_BACKBONE_PATH)")
        return visual_features(gray, self.visual_config, self.backbone)[self.visual_columns].astype(np.float32)

    def stop(self) -> None:
        """At shutdown: end an embedding in flight within milliseconds and refuse later ones (BackboneStopped).

        An embedding runs for up to seconds in a pool thread that the interpreter joins at exit; stopping the
        backbone lets the process exit as soon as the service has stopped. The tactile models' runs take
        milliseconds and are left to finish. Idempotent."""
        if self.backbone is not None:
            self.backbone.stop()


#: what Pillow names the formats of a frame (MPO: a camera's JPEG with more pictures after the first)
FRAME_FORMATS = frozenset({"PNG", "JPEG", "MPO"})


def frame_pixels(image: bytes) -> int:
    """An encoded frame's width × height, read from its header alone (nothing is decoded, ≈ 20 µs); 0 when the bytes
    are not an image Pillow recognises (decoding them says why); ValueError when it is not a PNG or JPEG (Pillow
    would decode GIF, BMP, TIFF, WebP … as well: frames are PNG or JPEG; the frames route has already refused one
    whose Content-Type names the other of the two) or larger than MAX_FRAME_PIXELS."""
    try:
        with Image.open(io.BytesIO(image)) as probe:
            width, height, kind = *probe.size, probe.format
    except Image.DecompressionBombError as exc:
        raise frame_bomb(exc) from None
    except Exception:  # noqa: BLE001 - not an image: decoding says why
        return 0
    if kind not in FRAME_FORMATS:
        raise ValueError(f"the image is {kind}; frames are PNG or JPEG")
    return check_frame_pixels(width, height)


def serving_config(model_config: TactileConfig, hop_s: float) -> TactileConfig:
    """The model's feature configuration with the serving hop; every other field stays as trained."""
    return TactileConfig(**{**model_config.to_dict(), "hop_s": hop_s})


def load_runtime(settings: Settings) -> Runtime:
    """Load and cross-check (service.warmup runs it once afterwards); ValueError names what is missing or
    inconsistent."""
    started = time.perf_counter()
    if settings.model_path is None:
        raise ValueError("no model configured: set HAPTICLINK_MODEL_PATH or pass --model")
    if settings.library_dir is None:
        raise ValueError("no texture library configured: set HAPTICLINK_LIBRARY_DIR or pass --library")
    predictor = Predictor(settings.model_path, threads=1)
    tactile_config = serving_config(predictor.tactile_config, settings.hop_s)
    tactile, untapped = _load_fallback(predictor, settings.tactile_model_path)
    cheap = None
    if settings.cheap_model_path is not None:
        cheap = Predictor(settings.cheap_model_path, threads=1, expected_tactile_hash=predictor.card.tactile_hash)
        if cheap.needs_visual and (not predictor.needs_visual or cheap.card.visual != predictor.card.visual):
            raise ValueError(
                f"{settings.cheap_model_path}: the cheap model ({cheap.card.model}) reads visual features "
                f"{cheap.card.visual}; the main model reads {predictor.card.visual}"
            )
    alpha = settings.smoothing_alpha
    library = Library.load(settings.library_dir)
    index = PerceptualIndex(library.ids, library.ratings, np.asarray(settings.nearest_weights))
    selection = SelectionRule(settings.selection_rule, settings.selection_weight)
    spectra = None
    if selection.needs_spectrum:
        spectra = SpectralTable(
            library.ids,
            [library.model(i) for i in library.ids],
            highpass_hz=tactile_config.accel_highpass_hz,
            noise_psd=sensor_noise_psd(settings.selection_sensor_noise, rate_hz=tactile_config.rate_hz),
        )
        if spectra.rate_hz != tactile_config.rate_hz:
            raise ValueError(
                f"selection rule {selection.name!r} compares windows at {tactile_config.rate_hz:g} Hz with library "
                f"models at {spectra.rate_hz:g} Hz; use the perceptual rule or a library at the model's rate"
            )
    visual_config = predictor.visual_config
    backbone, columns, problem, backbone_status = None, None, None, None
    if predictor.needs_visual:
        backbone, columns, problem = _load_backbone(
            predictor, visual_config, settings.backbone_path, settings.visual_threads
        )
    if backbone is not None:
        backbone, backbone_status, problem = _checked_backbone(
            backbone, settings.backbone_fallback_path, settings.visual_threads
        )
    return Runtime(
        ServedModel.load(predictor, alpha),
        None if tactile is None else ServedModel.load(tactile, alpha),
        None if cheap is None else ServedModel.load(cheap, alpha),
        ServingPolicy.from_settings(settings),
        tactile_config,
        library,
        index,
        visual_config,
        backbone,
        columns,
        problem,
        time.perf_counter() - started,
        settings.interval_level,
        selection,
        spectra,
        RenderCatalog.from_library(library),
        None if untapped is None else ServedModel.load(untapped, alpha),
        backbone_status,
    )


def untapped_config(config: TactileConfig) -> TactileConfig:
    """`config` without the taps group (the features a surface that has not been tapped still has)."""
    return TactileConfig(**{**config.to_dict(), "extra_groups": [g for g in config.extra_groups if g != "taps"]})


def _load_fallback(predictor: Predictor, path: Path | None) -> tuple[Predictor | None, Predictor | None]:
    """The tactile fallback model at `path` → (tactile-only fallback of a visual model, untapped fallback of a
    taps model): a model reading no images, trained on the main model's tactile features (windows without a frame)
    or on those without the taps group (windows of a surface not tapped). (None, None) when it serves neither."""
    needs_taps = "taps" in predictor.tactile_config.extra_groups
    if path is None or not (predictor.needs_visual or needs_taps):
        return None, None
    fallback = Predictor(path, threads=1)
    if fallback.needs_visual:
        raise ValueError(f"{path}: the tactile-only model ({fallback.card.model}) reads images")
    same = predictor.card.tactile_hash
    if fallback.card.tactile_hash == same:
        return (fallback if predictor.needs_visual else None), None
    if needs_taps and fallback.card.tactile_hash == untapped_config(predictor.tactile_config).hash():
        return None, fallback
    wanted = f"{same}" + (
        f" or, without the taps group, {untapped_config(predictor.tactile_config).hash()}" if needs_taps else ""
    )
    raise ValueError(
        f"{path}: model expects tactile features {fallback.card.tactile_hash}, the pipeline computes {wanted}; "
        "re-export the model or change the feature settings"
    )


def _load_backbone(
    predictor: Predictor, config: VisualConfig, path: Path | None, threads: int
) -> tuple[OnnxBackbone | None, np.ndarray | None, str | None]:
    """The backbone a visual model needs, checked against its card; (None, None, problem) without one."""
    card = predictor.card
    wanted = card.visual or {}
    if path is None:
        return (
            None,
            None,
            (
                f"model {card.model} needs visual features from {wanted.get('backbone', '?')}; "
                "set HAPTICLINK_BACKBONE_PATH (or --backbone) to its ONNX export"
            ),
        )
    backbone = OnnxBackbone(path, intra_op_threads=threads)  # checked here, so that the answer names both backbones
    if (
        wanted.get("backbone") != backbone.name
        or wanted.get("visual_hash") != backbone.config_hash
        or backbone.config_hash != config.hash()
    ):
        raise ValueError(
            f"model {card.model} was trained on {wanted.get('backbone')} features (visual config "
            f"{wanted.get('visual_hash')}); {path} is {backbone.name} (visual config {backbone.config_hash}): give it "
            "the backbone it was trained with (HAPTICLINK_BACKBONE_PATH, --backbone)"
        )
    columns, _ = part_columns(visual_layout(backbone.dim, config), wanted.get("visual_part", "both"))
    width = len(columns)
    if width != predictor.n_visual:
        raise ValueError(
            f"model {card.model} reads {predictor.n_visual} visual features; {backbone.name} gives {width}"
        )
    return backbone, columns, None


def _checked_backbone(
    backbone: OnnxBackbone, fallback_path: Path | None, threads: int
) -> tuple[OnnxBackbone | None, BackboneStatus, str | None]:
    """The backbone to serve after its load-time check → (backbone or None, status, problem or None).

    A backbone whose probe frames drift from fp32 past the bound (an int8 copy on a CPU without VNNI) is not
    served: the fp32 file it was quantized from is, found at `fallback_path` or else beside it under the name its
    metadata records; without one, the visual model is not ready and the problem says what to give it."""
    check = backbone.check
    if check is None:
        log.warning("visual backbone %s carries no probe: served unchecked (export it again)", backbone.name)
        return backbone, BackboneStatus(backbone.name, backbone.name, None), None
    if check.passed:
        log.info("visual backbone %s: %s", backbone.name, check.describe())
        return backbone, BackboneStatus(backbone.name, backbone.name, check), None
    backbone.stop()
    failed = f"visual backbone {backbone.name} failed its load-time check on this CPU ({check.describe()})"
    status = BackboneStatus(backbone.name, backbone.name, check)
    if backbone.source is None:
        return None, status, f"{failed}; it names no fp32 source to serve instead"
    path = fallback_path
    if path is None and backbone.source_file:
        path = backbone.path.parent / backbone.source_file
    if path is None or not path.is_file():
        return (
            None,
            status,
            f"{failed}; its fp32 source {backbone.source[0]} is not at {path}: set HAPTICLINK_BACKBONE_FALLBACK_PATH "
            "(or --backbone-fallback) to it",
        )
    fp32 = OnnxBackbone(path, intra_op_threads=threads)
    if (fp32.name, fp32.fingerprint) != backbone.source or fp32.config_hash != backbone.config_hash:
        fp32.stop()
        raise ValueError(
            f"{path} is {fp32.name} (fingerprint {fp32.fingerprint}, visual config {fp32.config_hash}); the fallback "
            f"of {backbone.name} must be the file it was quantized from: {backbone.source[0]} (fingerprint "
            f"{backbone.source[1]}, visual config {backbone.config_hash})"
        )
    status = BackboneStatus(backbone.name, fp32.name, check, fp32.check)
    if fp32.check is not None and not fp32.check.passed:
        fp32.stop()
        return None, status, f"{failed}, and so did its fp32 source {fp32.name} ({fp32.check.describe()})"
    # once per load, at WARNING: from here on every frame costs the fp32 backbone's time
    log.warning("%s: serving its fp32 source %s from %s instead", failed, fp32.name, path)
    return fp32, status, None
