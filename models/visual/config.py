"""Visual feature configuration: patching, GLCM and backbone choice, as one hashable value.

Imports no torch: the service builds this object too.
"""

from __future__ import annotations

import hashlib
import json
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

BackboneChoice = Literal["auto", "resnet50", "efficientnet_lite0", "efficientnet_lite0_int8"]
BackboneLayer = Literal["head", "last_block"]

# Fields that say how to *pick* the backbone on this machine, not what is computed:
# "auto" resolves differently per machine and the weights path is local. The
# resolved backbone travels beside the hash as name, dim and weights fingerprint,
# so a model trained on one machine still matches a service on another.
_SELECTION_FIELDS = frozenset({"backbone", "resnet50_weights"})
# Descriptor settings: serialised (and hashed) only when some descriptor is on, so the default
# configuration keeps its hash, its caches and its exported models.
_DESCRIPTOR_FIELDS = (
    "descriptors",
    "descriptor_size",
    "lbp_radii",
    "spectrum_bands",
    "grid_scales",
    "scattering_size",
    "scattering_j",
    "scattering_l",
)
DESCRIPTOR_NAMES = ("lbp", "spectrum", "colour", "grids", "scattering")  # = models.visual.descriptors.DESCRIPTORS


class VisualConfig(BaseModel):
    """How an image becomes a visual feature vector.

    patch_size       side of each square patch, pixels (the backbones' 224 input)
    grid             patches per side; grid × grid overlapping patches cover the image
    glcm             compute the grey-level co-occurrence matrix (False: the vector has no GLCM columns, and a
                     frame costs the backbone alone)
    glcm_levels      grey levels of the co-occurrence matrix (levels² features)
    glcm_distances   pixel offsets of the co-occurrence pairs
    glcm_angles_deg  directions of the pairs, degrees (0 = to the right)
    backbone         "auto": ResNet-50 if its ImageNet weights are found, else EfficientNet-Lite0;
                     "efficientnet_lite0_int8": EfficientNet-Lite0 quantized to int8 (ONNX only,
                     models.offline.backbones.quantize)
    resnet50_weights path of a torchvision ResNet-50 checkpoint (else torch's hub cache is searched)
    backbone_layer   where the backbone is read: "head" (its last feature map averaged over space: 1280 columns
                     for EfficientNet-Lite0, 2048 for ResNet-50) or "last_block" (EfficientNet-Lite0 only: the
                     last block's 320 channels, mean ⊕ standard deviation over space, 640 columns)
    resize           None: use the image as it comes; N: first scale it (antialiased, aspect kept) so its
                     shorter side is N pixels (≥ patch_size), then cut patches and compute the GLCM — a
                     cheaper frame: fewer pixels, and patches that see more of the surface each
    descriptors      classic texture descriptors appended after the GLCM (models.visual.descriptors), any of
                     lbp, spectrum, colour, grids, scattering; kept in that order whatever order they are given
    descriptor_size  the descriptors read the frame's centre square scaled to this many pixels a side
    lbp_radii        LBP circle radii, pixels (8 neighbours each)
    spectrum_bands   octave bands of the radial power spectrum
    grid_scales      cells per side of each patch grid
    scattering_size  scattering reads the centre square scaled to this many pixels a side
    scattering_j     scattering scales (J) and orientations (L)
    scattering_l
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    patch_size: int = Field(224, ge=32)
    grid: int = Field(7, ge=1)
    glcm: bool = True
    glcm_levels: int = Field(16, ge=2, le=256)
    glcm_distances: tuple[int, ...] = (1,)
    glcm_angles_deg: tuple[float, ...] = (0.0, 45.0, 90.0, 135.0)
    backbone: BackboneChoice = "auto"
    resnet50_weights: str | None = None
    backbone_layer: BackboneLayer = "head"
    resize: int | None = Field(None, ge=32)
    descriptors: tuple[str, ...] = ()
    descriptor_size: int = Field(512, ge=64)
    lbp_radii: tuple[int, ...] = (1, 2, 4)
    spectrum_bands: int = Field(6, ge=1, le=8)
    grid_scales: tuple[int, ...] = (2, 4, 8, 16)
    scattering_size: int = Field(128, ge=32)
    scattering_j: int = Field(3, ge=1, le=5)
    scattering_l: int = Field(8, ge=1, le=16)

    @field_validator("descriptors")
    @classmethod
    def _known_descriptors(cls, value: tuple[str, ...]) -> tuple[str, ...]:
        unknown = [d for d in value if d not in DESCRIPTOR_NAMES]
        if unknown:
            raise ValueError(f"unknown descriptor(s) {unknown}; expected any of {list(DESCRIPTOR_NAMES)}")
        return tuple(d for d in DESCRIPTOR_NAMES if d in value)  # one canonical order, no repeats

    @field_validator("lbp_radii", "grid_scales")
    @classmethod
    def _positive_ints(cls, value: tuple[int, ...]) -> tuple[int, ...]:
        if not value or any(v < 1 for v in value):
            raise ValueError(f"must be a non-empty tuple of positive ints, got {value}")
        return value

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
        """Length of the flattened GLCM feature (levels², 0 with the GLCM off)."""
        return self.glcm_levels * self.glcm_levels if self.glcm else 0

    @property
    def descriptor_dims(self) -> dict[str, int]:
        """Columns of each descriptor that is on, in column order."""
        dims = {
            "lbp": len(self.lbp_radii) * 10,
            "spectrum": self.spectrum_bands + 2,
            "colour": 13,
            "grids": 3 * len(self.grid_scales),
            "scattering": 1 + self.scattering_j + self.scattering_l * self.scattering_j * (self.scattering_j - 1) // 2,
        }
        return {d: dims[d] for d in self.descriptors}

    @property
    def descriptor_dim(self) -> int:
        """Total descriptor columns (0 when none is on)."""
        return sum(self.descriptor_dims.values())

    @property
    def needs_colour(self) -> bool:
        """Whether a frame must be given in colour (the colour statistics read it)."""
        return "colour" in self.descriptors

    def without_descriptors(self) -> VisualConfig:
        """The same backbone and GLCM computation with no descriptors (its hash is the one from before them)."""
        return self.model_copy(update={"descriptors": ()})

    def canonical_json(self) -> str:
        """Sorted, whitespace-free JSON of the fields that define the computation (patching, GLCM, descriptors)."""
        data = self.model_dump(mode="json", exclude=set(_SELECTION_FIELDS))
        if data["resize"] is None:
            # Added after models were exported: absent, it leaves every existing hash (and cache entry) as it was.
            del data["resize"]
        if self.glcm:
            del data["glcm"]  # likewise: the GLCM was always on before it could be turned off
        if self.backbone_layer == "head":
            del data["backbone_layer"]  # likewise: the head was the only layer read before
        if not self.descriptors:
            for key in _DESCRIPTOR_FIELDS:
                del data[key]
        return json.dumps(data, sort_keys=True, separators=(",", ":"))

    def computation(self) -> dict:
        """The fields `canonical_json` holds, as a dict: `VisualConfig(**computation())` computes the same vector
        (a model card carries it, so the service builds the configuration its model was trained on)."""
        return json.loads(self.canonical_json())

    def hash(self) -> str:
        """First 16 hex digits of the sha256 of `canonical_json()`."""
        return hashlib.sha256(self.canonical_json().encode("utf-8")).hexdigest()[:16]
