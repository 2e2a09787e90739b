"""Frame patches: P consecutive frames per token (ViT's patches over time), for EMDM's generator and
discriminator and MotionDiffuse's denoiser.

A sequence of N frames is zero-padded to a multiple of P and reshaped to ceil(N / P) tokens of P C
values. A token is valid when its first frame is; padded frames are zeroed on the way in, and patch
boundaries sit at multiples of P from frame 0, so the valid frames' values do not depend on how much
padding follows them.
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch.nn import functional as F


def to_patches(x: Tensor, valid: Tensor, patch: int) -> tuple[Tensor, Tensor]:
    """Frames (B, N, C) with padded frames zeroed -> patches (B, ceil(N / P), P C) and their validity
    (B, ceil(N / P)) (a patch is valid when its first frame is)."""
    b, n, c = x.shape
    x = torch.where(valid[..., None], x, 0.0)
    extra = -n % patch
    if extra:
        x = F.pad(x, (0, 0, 0, extra))
    return x.reshape(b, (n + extra) // patch, patch * c), valid[:, ::patch]


def from_patches(x: Tensor, num_frames: int, patch: int) -> Tensor:
    """Patches (B, M, P C) -> frames (B, num_frames, C) (the inverse of :func:`to_patches`' layout)."""
    b, m, pc = x.shape
    return x.reshape(b, m * patch, pc // patch)[:, :num_frames]
