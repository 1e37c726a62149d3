"""The visual backbone as an ONNX file, run by onnxruntime on the serving side (`OnnxBackbone`).

The export (torch) lives in the offline wing: `models.offline.backbones.onnx_export`.

The graph takes the same input as `Backbone.embed` — "patches", (batch, 224, 224)
float32 grayscale in [0, 1] — and returns "features", (batch, dim) float32;
RGB replication and normalisation are inside it. metadata_props:
    hapticlink.visual.backbone             "resnet50" | "efficientnet_lite0" | "efficientnet_lite0_int8"
    hapticlink.visual.dim                  feature length
    hapticlink.visual.weights_fingerprint  16 hex digits of the weights
    hapticlink.visual.config_hash          VisualConfig.hash() it was exported for
    hapticlink.visual.input_size           patch side, pixels
    hapticlink.visual.probe                (optional) the self-check: JSON {"patches": uint8 (n, s, s) patches
                                           (pixel / 255 is the input), "per_frame": patches per frame,
                                           "reference": float32 (n / per_frame, dim) frame-mean embeddings of
                                           the fp32 backbone, "reference_from": what computed them}, arrays as
                                           base64 .npy (`encode_array`)
    hapticlink.visual.source_backbone      (optional, a quantized copy) the fp32 backbone it was made from:
    hapticlink.visual.source_fingerprint   its name and weights fingerprint (the fallback must be that file)
    hapticlink.visual.source_file          and its file name (the service looks for it beside the copy)

A backbone with a probe checks itself at load (`ProbeCheck`): the frame cosine of its embeddings of the probe
patches to the stored fp32 ones. onnxruntime's int8 kernels differ per CPU (u8s8 saturates without VNNI), so a
quantized file faithful on one host can drift on another; the check measures it on the host that serves.
"""

from __future__ import annotations

import base64
import io
import json
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnxruntime as ort

from models.visual.patches import check_patch_batch

INPUT_NAME = "patches"
OUTPUT_NAME = "features"
META_PREFIX = "hapticlink.visual."
META_KEYS = ("backbone", "dim", "weights_fingerprint", "config_hash", "input_size")
DEFAULT_BATCH_SIZE = 16
PROBE_KEY = META_PREFIX + "probe"
SOURCE_NAME_KEY = META_PREFIX + "source_backbone"
SOURCE_FINGERPRINT_KEY = META_PREFIX + "source_fingerprint"
SOURCE_FILE_KEY = META_PREFIX + "source_file"
# The least mean probe-frame cosine to the fp32 reference a backbone must reach to be served. The target for the
# served image features is 0.97 on held-out photos. The int8 copy (recipe 3: min-max ranges) gives probe means of
# 0.994 with VNNI (held-out worst frame 0.986) and 0.978 under qemu's Haswell (AVX2, where onnxruntime's u8s8 kernels
# saturate a little in its int8 blocks; held-out worst 0.964), so the bound sits between the two: a CPU without
# VNNI serves the fp32 source. Recipe 1, every convolution int8, gave 0.936 and 0.812; an fp32 file 1.000
# (benchmarks/backbone_int8.py --recipes; docs/models.md).
MIN_PROBE_COSINE = 0.985


def encode_array(array: np.ndarray) -> str:
    """An array as base64 of its .npy bytes (exact, dtype and shape included)."""
    buffer = io.BytesIO()
    np.save(buffer, np.ascontiguousarray(array), allow_pickle=False)
    return base64.b64encode(buffer.getvalue()).decode("ascii")


def decode_array(text: str, what: str) -> np.ndarray:
    """`encode_array`'s inverse; ValueError naming `what` on anything else."""
    try:
        return np.load(io.BytesIO(base64.b64decode(text, validate=True)), allow_pickle=False)
    except (ValueError, TypeError, OSError) as exc:
        raise ValueError(f"{what}: not a base64 .npy array ({exc})") from None


def probe_metadata(patches: np.ndarray, reference: np.ndarray, per_frame: int, reference_from: str) -> str:
    """The value of PROBE_KEY: probe patches (n, s, s) float in [0, 1] (stored as uint8: pixel / 255 is what runs)
    and the fp32 frame-mean embeddings (n / per_frame, dim) of exactly those inputs (`probe_inputs(...)`)."""
    if patches.ndim != 3 or patches.shape[0] % per_frame or reference.shape[0] != patches.shape[0] // per_frame:
        raise ValueError(
            f"probe patches {patches.shape} and reference {reference.shape} do not make frames of {per_frame}"
        )
    pixels = (probe_inputs(patches) * 255.0).round().astype(np.uint8)
    return json.dumps(
        {
            "patches": encode_array(pixels),
            "per_frame": per_frame,
            "reference": encode_array(np.asarray(reference, np.float32)),
            "reference_from": reference_from,
        }
    )


def probe_inputs(patches: np.ndarray) -> np.ndarray:
    """The float32 patches a probe stores for `patches` (rounded to 1/255): embed these for its reference."""
    return np.clip(np.rint(np.asarray(patches) * 255.0), 0, 255).astype(np.float32) / 255.0


def frame_cosines(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cosine between matching rows of a and b, (n, dim) each → (n,)."""
    return (a * b).sum(-1) / np.maximum(np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1), 1e-30)


@dataclass(frozen=True)
class ProbeCheck:
    """A backbone's check at load: the frame cosine of its probe embeddings to the stored fp32 ones.

    cosines: one per probe frame (frame mean of its patches' embeddings, as the served vector pools them);
    bound: the least mean of them that passes; reference_from: what computed the reference."""

    cosines: tuple[float, ...]
    bound: float
    reference_from: str

    @property
    def cosine(self) -> float:
        """The mean probe frame cosine (one frame's quantization error is no drift of the kernels; a mean over the
        frames separates the two, where single frames of either overlap)."""
        return float(np.mean(self.cosines))

    @property
    def passed(self) -> bool:
        return self.cosine >= self.bound

    def describe(self) -> str:
        verdict = "≥" if self.passed else "<"
        return (
            f"mean probe frame cosine to {self.reference_from} {self.cosine:.3f} {verdict} {self.bound:g} "
            f"(frames: {', '.join(f'{c:.3f}' for c in self.cosines)})"
        )


class BackboneStopped(RuntimeError):
    """`OnnxBackbone.stop()` was called: the run in flight was terminated, or the backbone refuses new ones."""


def backbone_metadata(name: str, dim: int, fingerprint: str, config_hash: str, input_size: int) -> dict[str, str]:
    """The metadata_props an exported backbone carries, keyed with META_PREFIX."""
    values = {
        "backbone": name,
        "dim": str(dim),
        "weights_fingerprint": fingerprint,
        "config_hash": config_hash,
        "input_size": str(input_size),
    }
    return {META_PREFIX + key: value for key, value in values.items()}


class OnnxBackbone:
    """An exported backbone run by onnxruntime on the CPU; same API as `backbone.Backbone`.

    path                  .onnx written by `export_backbone_onnx`
    intra_op_threads      onnxruntime intra-op threads (None: onnxruntime's default, all cores)
    batch_size            patches per run
    expected_config_hash  if given, refuse a file exported for another VisualConfig
    min_probe_cosine      the bound of the load-time check (`check`: None for a file without a probe); None:
                          no check (a tool that reads only the file's metadata, or checks it apart)
    """

    def __init__(
        self,
        path: str | Path,
        *,
        intra_op_threads: int | None = None,
        batch_size: int = DEFAULT_BATCH_SIZE,
        expected_config_hash: str | None = None,
        min_probe_cosine: float | None = MIN_PROBE_COSINE,
    ) -> None:
        if batch_size < 1:
            raise ValueError(f"batch_size must be ≥ 1, got {batch_size}")
        if intra_op_threads is not None and intra_op_threads < 1:
            raise ValueError(f"intra_op_threads must be ≥ 1 or None, got {intra_op_threads}")
        self.path = Path(path)
        if not self.path.is_file():
            raise ValueError(f"path {str(self.path)!r} is not a file")
        options = ort.SessionOptions()
        if intra_op_threads is not None:
            options.intra_op_num_threads = intra_op_threads
        try:
            self.session = ort.InferenceSession(str(self.path), options, providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime's load errors (Fail, InvalidProtobuf, …) subclass only Exception
            raise ValueError(f"path {str(self.path)!r} is not a loadable ONNX model: {exc}") from exc
        meta = self.session.get_modelmeta().custom_metadata_map
        missing = [META_PREFIX + k for k in META_KEYS if META_PREFIX + k not in meta]
        if missing:
            raise ValueError(f"path {str(self.path)!r} is not a hapticlink visual backbone: metadata lacks {missing}")
        self.name = meta[META_PREFIX + "backbone"]
        self.dim = int(meta[META_PREFIX + "dim"])
        self.fingerprint = meta[META_PREFIX + "weights_fingerprint"]
        self.config_hash = meta[META_PREFIX + "config_hash"]
        self.input_size = int(meta[META_PREFIX + "input_size"])
        self.batch_size = batch_size
        self.intra_op_threads = intra_op_threads
        if expected_config_hash is not None and expected_config_hash != self.config_hash:
            raise ValueError(
                f"path {str(self.path)!r} was exported for visual config {self.config_hash}, "
                f"expected {expected_config_hash}"
            )

        source = (meta.get(SOURCE_NAME_KEY), meta.get(SOURCE_FINGERPRINT_KEY))
        # the fp32 backbone a quantized copy was made from (name, fingerprint) and its file name, else None
        self.source: tuple[str, str] | None = (source[0], source[1]) if source[0] and source[1] else None
        self.source_file: str | None = meta.get(SOURCE_FILE_KEY) or None

        # each run's RunOptions while it is in flight, so that stop() can raise their terminate flags
        self._lock = threading.Lock()
        self._runs: set[ort.RunOptions] = set()
        self._stopped = False
        self.check: ProbeCheck | None = None
        if PROBE_KEY in meta and min_probe_cosine is not None:
            self.check = self._self_check(meta[PROBE_KEY], min_probe_cosine)

    def _self_check(self, text: str, bound: float) -> ProbeCheck:
        """Embed the stored probe patches on this CPU and compare each frame with the stored fp32 embedding."""
        what = f"{self.path}: probe"
        try:
            probe = json.loads(text)
            pixels = decode_array(probe["patches"], what + " patches")
            reference = decode_array(probe["reference"], what + " reference")
            per_frame = int(probe["per_frame"])
            reference_from = str(probe["reference_from"])
        except (json.JSONDecodeError, KeyError, TypeError) as exc:
            raise ValueError(f"{what} is not a backbone probe ({exc})") from None
        n = pixels.shape[0] if pixels.ndim == 3 else 0
        if (
            pixels.dtype != np.uint8
            or pixels.shape[1:] != (self.input_size, self.input_size)
            or per_frame < 1
            or n == 0
            or n % per_frame
            or reference.shape != (n // per_frame, self.dim)
        ):
            raise ValueError(
                f"{what} holds patches {pixels.shape} {pixels.dtype} and reference {reference.shape}; expected uint8 "
                f"(n, {self.input_size}, {self.input_size}) and (n / {per_frame}, {self.dim})"
            )
        frames = self.embed(pixels.astype(np.float32) / 255.0).reshape(n // per_frame, per_frame, self.dim).mean(1)
        # a NaN embedding is as far as it gets
        cosines = np.nan_to_num(frame_cosines(frames.astype(np.float64), reference.astype(np.float64)), nan=-1.0)
        return ProbeCheck(tuple(float(c) for c in cosines), bound, reference_from)

    def __repr__(self) -> str:
        return (
            f"OnnxBackbone(name={self.name!r}, dim={self.dim}, fingerprint={self.fingerprint!r}, "
            f"path={str(self.path)!r})"
        )

    def embed(self, patches: np.ndarray) -> np.ndarray:
        """(n, 224, 224) float in [0, 1] → (n, dim) float32, in batches of `batch_size`."""
        batch = check_patch_batch(patches, self.input_size)
        out = np.empty((batch.shape[0], self.dim), dtype=np.float32)
        for start in range(0, batch.shape[0], self.batch_size):
            chunk = batch[start : start + self.batch_size]
            out[start : start + chunk.shape[0]] = self._run(chunk)
        return out

    @property
    def stopped(self) -> bool:
        """True once `stop()` was called (every later run raises BackboneStopped)."""
        return self._stopped

    @property
    def runs_in_flight(self) -> int:
        """Runs under way now (each a batch of at most batch_size patches)."""
        with self._lock:
            return len(self._runs)

    def stop(self) -> None:
        """Terminate the runs in flight and refuse later ones (both raise BackboneStopped); idempotent.

        onnxruntime checks a run's terminate flag between graph nodes, so a thread inside `embed` returns within
        one node's time (milliseconds) instead of the whole embedding (up to seconds on a busy CPU): a process
        stopping does not have to wait for it."""
        with self._lock:
            self._stopped = True
            for options in self._runs:
                options.terminate = True

    def _run(self, chunk: np.ndarray) -> np.ndarray:
        """One batch (b, 224, 224) → (b, dim) through the session; BackboneStopped once stop() is called."""
        options = ort.RunOptions()
        with self._lock:
            if self._stopped:
                raise BackboneStopped(f"backbone {self.name} is stopped")
            self._runs.add(options)
        try:
            return self.session.run([OUTPUT_NAME], {INPUT_NAME: chunk}, options)[0]
        except Exception as exc:  # onnxruntime's terminated run raises a plain Fail
            if self._stopped:
                raise BackboneStopped(f"backbone {self.name} was stopped during a run") from exc
            raise
        finally:
            with self._lock:
                self._runs.discard(options)
