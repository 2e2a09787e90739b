"""Random draws on a seeded generator's device.

Every draw of the models' losses and samplers happens on the generator's device (torch's global RNG:
the tensors' device) and is then moved to the tensors' device, so a seeded CPU generator gives the same
numbers whether the networks run on the CPU or a GPU (a CUDA tensor cannot be drawn from a CPU generator
at all). A module of its own, so that the networks that draw (the VAE, the evaluator) do not depend on
the diffusion schedules.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor


def rng_device(generator: torch.Generator | None, fallback: torch.device | str) -> torch.device:
    """Where a random draw happens: on ``generator``'s device, else (torch's global RNG) on ``fallback``."""
    return generator.device if generator is not None else torch.device(fallback)


def normal(shape: Sequence[int], like: Tensor, generator: torch.Generator | None) -> Tensor:
    """N(0, I) of ``shape`` drawn on :func:`rng_device`, returned on ``like``'s device and dtype."""
    dev = rng_device(generator, like.device)
    return torch.randn(tuple(shape), generator=generator, device=dev, dtype=like.dtype).to(like.device)


def uniform(shape: Sequence[int], like: Tensor, generator: torch.Generator | None) -> Tensor:
    """U[0, 1) of ``shape`` drawn on :func:`rng_device`, returned on ``like``'s device (float32)."""
    return torch.rand(tuple(shape), generator=generator, device=rng_device(generator, like.device)).to(like.device)
