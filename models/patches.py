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


def overlap_window(patch: int) -> Tensor:
    """The triangular synthesis window (2P,) of :func:`from_patches_overlapped`: ``(j + 1/2) / P`` rising
    over the first P taps, falling over the last P. Shifted by P it sums to 1 (Bartlett overlap-add)."""
    j = torch.arange(patch, dtype=torch.float32) + 0.5
    return torch.cat([j, j.flip(0)]) / patch


def from_patches_overlapped(x: Tensor, token_valid: Tensor, num_frames: int, patch: int) -> Tensor:
    """Overlapping output patches (B, M, 2P C) -> frames (B, num_frames, C), P even.

    Token m writes the 2P frames ``[m P - P/2, m P + 3P/2)`` centred on its own patch, tapered by
    :func:`overlap_window` and added to its neighbours' (overlap-add with hop P, as a synthesis
    filter bank): every frame is a blend of two tokens whose weights shift a quarter-patch per frame,
    so no frame-to-frame step sits at a patch boundary. Invalid tokens (``token_valid`` (B, M) False)
    write nothing, and each frame is divided by the window weight its valid tokens give it, so the
    first P/2 frames and the frames past the last valid token's centre (one token only) are that
    token's own values, and the valid frames do not depend on the padding that follows them.
    """
    if patch % 2:
        raise ValueError(f"overlapping patches need an even patch_frames, got {patch}")
    b, m, twice = x.shape
    c = twice // (2 * patch)
    w = overlap_window(patch).to(x)
    keep = token_valid.to(x.dtype)[:, :, None, None]
    tapered = x.reshape(b, m, 2 * patch, c) * w[:, None] * keep
    weight = w[None, None, :, None] * keep  # (B, M, 2P, 1)

    def overlap_add(v: Tensor) -> Tensor:  # (B, M, 2P, K) -> (B, (M + 1) P, K) starting at frame -P/2
        first = F.pad(v[:, :, :patch].reshape(b, m * patch, -1), (0, 0, 0, patch))
        second = F.pad(v[:, :, patch:].reshape(b, m * patch, -1), (0, 0, patch, 0))
        return first + second

    half = patch // 2
    total = overlap_add(weight)[:, half:half + num_frames]
    return overlap_add(tapered)[:, half:half + num_frames] / total.clamp_min(1e-6)


def output_width(patch: int, channels: int, overlapped: bool) -> int:
    """Values per token of an output layer writing P frames of C channels, 2P with ``overlapped``."""
    return (2 if overlapped else 1) * patch * channels


def from_output_patches(x: Tensor, token_valid: Tensor, num_frames: int, patch: int, overlapped: bool) -> Tensor:
    """An output layer's tokens (B, M, :func:`output_width`) -> frames (B, num_frames, C):
    :func:`from_patches_overlapped` with ``overlapped``, else :func:`from_patches`."""
    if overlapped:
        return from_patches_overlapped(x, token_valid, num_frames, patch)
    return from_patches(x, num_frames, patch)
