"""Visual feature configuration: patching, GLCM and backbone choice, as one hashable value.

Imports no torch: the service builds this object too.
"""

from __future__ import annotations

import hashlib
import json
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

BackboneChoice = Literal["auto", "resnet50", "efficientnet_lite0"]

# Fields that say how to *pick* the backbone on this machine, not what is computed:
# "auto" resolves differently per machine and the weights path is local. The
# resolved backbone travels beside the hash as name, dim and weights fingerprint,
# so a model trained on one machine still matches a service on another.
_SELECTION_FIELDS = frozenset({"backbone", "resnet50_weights"})


class VisualConfig(BaseModel):
    """How an image becomes a visual feature vector.

    patch_size       side of each square patch, pixels (the backbones' 224 input)
    grid             patches per side; grid × grid overlapping patches cover the image
    glcm_levels      grey levels of the co-occurrence matrix (levels² features)
    glcm_distances   pixel offsets of the co-occurrence pairs
    glcm_angles_deg  directions of the pairs, degrees (0 = to the right)
    backbone         "auto": ResNet-50 if its ImageNet weights are found, else EfficientNet-Lite0
    resnet50_weights path of a torchvision ResNet-50 checkpoint (else torch's hub cache is searched)
    resize           None: use the image as it comes; N: first scale it (antialiased, aspect kept) so its
                     shorter side is N pixels (≥ patch_size), then cut patches and compute the GLCM — a
                     cheaper frame: fewer pixels, and patches that see more of the surface each
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    patch_size: int = Field(224, ge=32)
    grid: int = Field(7, ge=1)
    glcm_levels: int = Field(16, ge=2, le=256)
    glcm_distances: tuple[int, ...] = (1,)
    glcm_angles_deg: tuple[float, ...] = (0.0, 45.0, 90.0, 135.0)
    backbone: BackboneChoice = "auto"
    resnet50_weights: str | None = None
    resize: int | None = Field(None, ge=32)

    @field_validator("glcm_distances")
    @classmethod
    def _distances_positive(cls, value: tuple[int, ...]) -> tuple[int, ...]:
        if not value or any(d < 1 for d in value):
            raise ValueError(f"glcm_distances must be a non-empty tuple of positive ints, got {value}")
        return value

    @field_validator("glcm_angles_deg")
    @classmethod
    def _angles_nonempty(cls, value: tuple[float, ...]) -> tuple[float, ...]:
        if not value:
            raise ValueError("glcm_angles_deg must not be empty")
        return value

    @model_validator(mode="after")
    def _resize_holds_a_patch(self) -> VisualConfig:
        if self.resize is not None and self.resize < self.patch_size:
            raise ValueError(
                f"resize ({self.resize} px) must be ≥ patch_size ({self.patch_size} px): one patch must fit"
            )
        return self

    @property
    def n_patches(self) -> int:
        """Number of patches per image (grid²)."""
        return self.grid * self.grid

    @property
    def glcm_dim(self) -> int:
        """Length of the flattened GLCM feature (levels²)."""
        return self.glcm_levels * self.glcm_levels

    def canonical_json(self) -> str:
        """Sorted, whitespace-free JSON of the fields that define the computation (patching and GLCM)."""
        data = self.model_dump(mode="json", exclude=set(_SELECTION_FIELDS))
        if data["resize"] is None:
            # Added after models were exported: absent, it leaves every existing hash (and cache entry) as it was.
            del data["resize"]
        return json.dumps(data, sort_keys=True, separators=(",", ":"))

    def hash(self) -> str:
        """First 16 hex digits of the sha256 of `canonical_json()`."""
        return hashlib.sha256(self.canonical_json().encode("utf-8")).hexdigest()[:16]
