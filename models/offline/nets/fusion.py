"""Visuo-tactile Net: HV-Net (visual) and HT-Net (tactile) embeddings fused into 4 ratings.

Head (paper): concat (128 + 128) → FC 128 → FC 128 → max-pool 2 over the feature axis
(128 → 64) → FC 32 → FC 4 (linear). A single-modality model has no second branch at all
(not a zero embedding), so its concat is just its one embedding.

Every network in ``models.offline.nets`` shares the forward contract

    forward(tactile: (B, F_t) float32, visual: (B, D) float32)
        -> {"ratings": (B, 4), "reconstruction": (B, D) or None}

on standardized inputs and targets, and carries a ``modality`` attribute
("both" | "tactile" | "visual") naming the inputs it actually reads.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import torch
import torch.nn.functional as F
from torch import nn

from models.offline.nets.htnet import PAPER_FILTERS, HTNet
from models.offline.nets.hvnet import HVNet

Modality = Literal["both", "tactile", "visual"]
TactileBranch = Literal["htnet", "mlp"]
MODALITIES: tuple[str, ...] = ("both", "tactile", "visual")
N_RATINGS = 4


def check_modality(modality: str) -> None:
    """ValueError unless ``modality`` is one of MODALITIES."""
    if modality not in MODALITIES:
        raise ValueError(f"modality must be one of {MODALITIES}, got {modality!r}")


def check_tactile_layout(tactile_dim: int, n_frames: int, n_coeffs: int, n_stats: int) -> None:
    """ValueError unless tactile_dim = n_frames·n_coeffs + n_stats (the MFCC window layout)."""
    if tactile_dim != n_frames * n_coeffs + n_stats:
        raise ValueError(
            f"tactile_dim {tactile_dim} does not match the MFCC layout n_frames·n_coeffs + n_stats = "
            f"{n_frames}·{n_coeffs} + {n_stats} = {n_frames * n_coeffs + n_stats}; "
            "use a layout-free tactile branch (tactile_branch='mlp') for other feature sets"
        )


class MLPBranch(nn.Module):
    """Fully connected branch for a feature vector of any length (no layout assumed).

    Args: in_dim, hidden sizes, out_dim; ReLU after every layer (the output is an embedding).
    forward(x: (B, in_dim) float32) → (B, out_dim).
    """

    def __init__(self, in_dim: int, hidden: Sequence[int], out_dim: int) -> None:
        super().__init__()
        sizes = (in_dim, *hidden, out_dim)
        if any(n < 1 for n in sizes):
            raise ValueError(f"MLPBranch sizes must be positive, got {sizes}")
        self.layers = nn.ModuleList(nn.Linear(sizes[n], sizes[n + 1]) for n in range(len(sizes) - 1))
        self.in_dim, self.out_dim = in_dim, out_dim

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.dim() != 2 or x.shape[1] != self.in_dim:
            raise ValueError(f"MLPBranch expects (batch, {self.in_dim}), got {tuple(x.shape)}")
        for layer in self.layers:
            x = F.relu(layer(x))
        return x


def pairwise_max_pool(x: torch.Tensor) -> torch.Tensor:
    """Max-pool 2 over the feature axis: x: (B, 2n) → (B, n), max of features (2j, 2j+1)."""
    if x.shape[1] % 2:
        raise ValueError(f"pairwise_max_pool needs an even feature count, got {x.shape[1]}")
    return torch.maximum(x[:, 0::2], x[:, 1::2])


class FusionHead(nn.Module):
    """concat → FC a → FC b → max-pool 2 → FC c → FC 4 (linear); ReLU after the hidden FCs.

    Args: in_dim (sum of the branch embeddings), sizes (a, b, c) with b even.
    forward(z: (B, in_dim)) → (B, 4).
    """

    def __init__(self, in_dim: int, sizes: Sequence[int] = (128, 128, 32)) -> None:
        super().__init__()
        sizes = tuple(sizes)
        if len(sizes) != 3 or any(n < 1 for n in sizes) or sizes[1] % 2:
            raise ValueError(f"FusionHead sizes must be 3 positive ints with an even second, got {sizes}")
        a, b, c = sizes
        self.fc1 = nn.Linear(in_dim, a)
        self.fc2 = nn.Linear(a, b)
        self.fc3 = nn.Linear(b // 2, c)
        self.out = nn.Linear(c, N_RATINGS)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        z = F.relu(self.fc2(F.relu(self.fc1(z))))
        z = F.relu(self.fc3(pairwise_max_pool(z)))
        return self.out(z)


class VisuoTactileNet(nn.Module):
    """The paper's Visuo-tactile Net, with size knobs for compact variants.

    Args:
        visual_dim: D, length of the visual vector (1536 or 2304).
        tactile_dim: length of the tactile vector (526 for MFCC windows).
        modality: "both", "tactile" (no visual branch) or "visual" (no tactile branch).
        width: multiplier on HV-Net's conv filters.
        visual_widths, visual_kernels, visual_fc: HV-Net stages and head (embedding = visual_fc[-1]).
        tactile_branch: "htnet" (ConvLSTM over the MFCC layout; needs tactile_dim =
            n_frames·n_coeffs + n_stats) or "mlp" (any tactile_dim, e.g. DWT/DFT features).
        tactile_filters, tactile_pool_after, tactile_kernel, tactile_frame_pool: HT-Net stack (see `HTNet`).
        tactile_hidden: hidden sizes of the MLP branch.
        tactile_out: tactile embedding size.
        n_frames, n_coeffs, n_stats: the MFCC window layout.
        head: fusion head sizes (FC a, FC b, FC c after pooling b → b/2).

    forward(tactile: (B, tactile_dim), visual: (B, visual_dim)) →
        {"ratings": (B, 4), "reconstruction": (B, visual_dim) or None (no visual branch)}.
    """

    modality: str = "both"

    def __init__(
        self,
        visual_dim: int,
        tactile_dim: int,
        *,
        modality: Modality = "both",
        width: float = 1.0,
        visual_widths: Sequence[int] = (256, 256, 128, 64, 32),
        visual_kernels: Sequence[int] = (4, 4, 3, 3, 3),
        visual_fc: Sequence[int] = (512, 128),
        tactile_branch: TactileBranch = "htnet",
        tactile_filters: Sequence[int] = PAPER_FILTERS,
        tactile_pool_after: Sequence[int] | None = None,
        tactile_kernel: int = 3,
        tactile_frame_pool: int = 1,
        tactile_hidden: Sequence[int] = (128,),
        tactile_out: int = 128,
        n_frames: int = 40,
        n_coeffs: int = 13,
        n_stats: int = 6,
        head: Sequence[int] = (128, 128, 32),
    ) -> None:
        super().__init__()
        check_modality(modality)
        if visual_dim < 1 or tactile_dim < 1:
            raise ValueError(f"visual_dim and tactile_dim must be ≥ 1, got {visual_dim}, {tactile_dim}")
        if tactile_branch not in ("htnet", "mlp"):
            raise ValueError(f"tactile_branch must be 'htnet' or 'mlp', got {tactile_branch!r}")
        self.modality = modality
        self.visual_dim, self.tactile_dim = visual_dim, tactile_dim
        self.visual: HVNet | None = None
        self.tactile: nn.Module | None = None
        fused = 0
        if modality in ("both", "visual"):
            self.visual = HVNet(visual_dim, visual_widths, visual_kernels, visual_fc, width=width)
            fused += self.visual.out_dim
        if modality in ("both", "tactile"):
            if tactile_branch == "htnet":
                check_tactile_layout(tactile_dim, n_frames, n_coeffs, n_stats)
                self.tactile = HTNet(
                    n_frames,
                    n_coeffs,
                    n_stats,
                    tactile_filters,
                    tactile_pool_after,
                    tactile_kernel,
                    tactile_out,
                    frame_pool=tactile_frame_pool,
                )
            else:
                self.tactile = MLPBranch(tactile_dim, tactile_hidden, tactile_out)
            fused += tactile_out
        self.head = FusionHead(fused, head)

    def forward(
        self, tactile: torch.Tensor, visual: torch.Tensor, visual_index: torch.Tensor | None = None
    ) -> dict[str, torch.Tensor | None]:
        """tactile: (B, tactile_dim), visual: (B, visual_dim) float32, standardized →
        {"ratings": (B, 4) standardized, "reconstruction": (B, visual_dim) or None}.

        visual_index: (B,) rows of `visual` (then (U, visual_dim), U ≤ B) paired with each window —
        windows sharing an image view share one HV-Net pass; the reconstruction is then (U, visual_dim).
        """
        parts = []
        reconstruction = None
        if self.visual is not None:
            embedding, reconstruction = self.visual(visual)
            parts.append(embedding if visual_index is None else embedding[visual_index])
        if self.tactile is not None:
            parts.append(self.tactile(tactile))
        z = parts[0] if len(parts) == 1 else torch.cat(parts, dim=1)
        return {"ratings": self.head(z), "reconstruction": reconstruction}
