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
"""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import onnxruntime as ort

from models.visual.patches import check_patch_batch

INPUT_NAME = "patches"
OUTPUT_NAME = "features"
META_PREFIX = "hapticlink.visual."
META_KEYS = ("backbone", "dim", "weights_fingerprint", "config_hash", "input_size")
DEFAULT_BATCH_SIZE = 16


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
    """

    def __init__(
        self,
        path: str | Path,
        *,
        intra_op_threads: int | None = None,
        batch_size: int = DEFAULT_BATCH_SIZE,
        expected_config_hash: str | None = None,
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

        # each run's RunOptions while it is in flight, so that stop() can raise their terminate flags
        self._lock = threading.Lock()
        self._runs: set[ort.RunOptions] = set()
        self._stopped = False

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
