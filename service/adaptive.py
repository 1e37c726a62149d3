"""How much model a scene needs: the serving policy.

Two modes (`HAPTICLINK_SERVING_POLICY`):

* ``always-full`` — every camera frame is embedded and the session's visual input is the newest
  frame's embedding; every window is estimated by the full (served) model.
* ``adaptive`` — a frame is embedded only when the scene changed (`drivers/scene_change.py`: its
  thumbnail differs from the scene's first frame by more than `frame_change`), and then the next
  `pool_frames − 1` frames of that scene too; the scene's embeddings are pooled
  (`models/visual/pooling.py`'s `pool_views`, the mean) into the session's visual input, so several views of one
  surface count, and then the camera costs nothing until the scene changes. With a cheap model
  (`HAPTICLINK_CHEAP_MODEL_PATH`) every window is first estimated by it; the full model runs on the
  windows where the cheap estimate is not good enough (`needs_full`): its calibrated per-window
  interval is wider than `full_model_width` on some attribute (or it has no calibration), the window
  is flagged out of distribution, or the estimate lies within `full_model_margin` of a library decision
  boundary (the two nearest library models' distances differ by less than that: the choice could flip).

`ServingPolicy` decides; `SceneViews` is one session's camera state under it (which frames to embed, the
pooled visual input), used alike by the service's sessions and by `benchmarks/adaptive.py`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from drivers.scene_change import scene_changed
from models.visual.pooling import ViewPool

PolicyMode = Literal["always-full", "adaptive"]
POLICY_MODES: tuple[str, ...] = ("always-full", "adaptive")


@dataclass(frozen=True)
class ServingPolicy:
    """mode: see the module docstring; pool_frames: embeddings pooled per scene (≥ 1); full_model_width:
    largest per-window interval width (bipolar) the cheap estimate may have; full_model_margin: least
    distance margin (bipolar) between the two nearest library models for the cheap estimate to stand."""

    mode: PolicyMode = "adaptive"
    pool_frames: int = 1
    full_model_width: float = 40.0
    full_model_margin: float = 5.0

    def __post_init__(self) -> None:
        if self.mode not in POLICY_MODES:
            raise ValueError(f"serving policy must be one of {POLICY_MODES}, got {self.mode!r}")
        if not isinstance(self.pool_frames, int) or self.pool_frames < 1:
            raise ValueError(f"pool_frames must be an integer ≥ 1, got {self.pool_frames!r}")
        if not (self.full_model_width >= 0 and self.full_model_margin >= 0):
            raise ValueError(
                f"full_model_width and full_model_margin must be ≥ 0, got {self.full_model_width}, "
                f"{self.full_model_margin}"
            )

    @classmethod
    def from_settings(cls, settings) -> ServingPolicy:
        return cls(settings.serving_policy, settings.pool_frames, settings.full_model_width, settings.full_model_margin)

    @property
    def adaptive(self) -> bool:
        return self.mode == "adaptive"

    def embed_frame(self, scene_changed: bool, embedded_in_scene: int) -> bool:
        """Should this frame be embedded? scene_changed: the scene-change test's answer against the scene's first
        frame; embedded_in_scene: frames of the current scene embedded so far."""
        if not self.adaptive:
            return True
        return scene_changed or embedded_in_scene < self.pool_frames

    @property
    def views_pooled(self) -> int:
        """Embeddings of one scene pooled into the session's visual input (always-full: the newest frame's only)."""
        return self.pool_frames if self.adaptive else 1

    def needs_full(self, width: np.ndarray | None, margin: np.ndarray, flagged: np.ndarray | None) -> np.ndarray:
        """(n,) bool: windows the full model must estimate after the cheap one.

        width: (n, A) the cheap estimates' interval widths (None: the cheap model has no calibration, so its
        estimate is never trusted alone); margin: (n,) distance of the second-nearest library model minus the
        nearest (texture_library.nearest.decision_margin); flagged: (n,) out of distribution (None: no detector)."""
        margin = np.asarray(margin, float)
        if not self.adaptive or width is None:
            return np.ones(margin.shape, dtype=bool)
        need = (np.asarray(width).max(axis=1) > self.full_model_width) | (margin < self.full_model_margin)
        if flagged is not None:
            need |= np.asarray(flagged, bool)
        return need


class SceneViews:
    """One session's camera scene under a policy: which frames to embed, and the pooled visual input.

    offer(thumbnail) → (embed it?, does it start a new scene?) for each decoded frame, in arrival order;
    add(embedding (D,), new_scene) → the session's visual input (D,) float32 once it is embedded;
    forget() after a failed embedding, so the next frame is tried whatever it shows."""

    def __init__(self, policy: ServingPolicy, change_threshold: float) -> None:
        if not 0 <= change_threshold <= 2:
            raise ValueError(f"change_threshold must lie in [0, 2], got {change_threshold!r}")
        self.policy = policy
        self.threshold = change_threshold
        self._scene: np.ndarray | None = None  # thumbnail of the scene's first frame
        self._taken = 0  # frames of the current scene taken for embedding
        self._views = ViewPool(policy.views_pooled)

    def offer(self, thumb: np.ndarray) -> tuple[bool, bool]:
        take, changed = self._decide(thumb)
        if changed:
            self._scene, self._taken = thumb, 0
        if take:
            self._taken += 1
        return take, changed

    def wants(self, thumb: np.ndarray) -> bool:
        """Would offer() take a frame with this thumbnail? (Takes nothing: a robot's scene check.)"""
        return self._decide(thumb)[0]

    def _decide(self, thumb: np.ndarray) -> tuple[bool, bool]:
        """(take it?, does it start a new scene?) for a frame with this thumbnail, as the scene stands."""
        changed = scene_changed(self._scene, thumb, self.threshold)
        return self.policy.embed_frame(changed, 0 if changed else self._taken), changed

    def add(self, embedding: np.ndarray, new_scene: bool) -> np.ndarray:
        if new_scene:
            self._views.reset()
        self._views.add(embedding)
        return self._views.value()

    @property
    def views(self) -> int:
        """Embeddings in the current visual input."""
        return len(self._views)

    def forget(self) -> None:
        self._scene = None
