"""Tolerances for float32 network outputs computed two ways that are equal in exact arithmetic.

A padded and an unpadded batch, a masked and a trimmed sequence, or two attention implementations
run different kernels (other shapes and blockings; AVX2 on one CPU, AVX-512 on another; 1 or 2
threads), so their sums round in a different order. A float32 dot product of K terms of size s then
differs by about sqrt(K) * eps * s (K * eps * s at worst), and a network's layers add such errors up,
so a fixed ``atol=1e-6`` (8 eps at magnitude 1) held on one CPU and failed on another (1.57e-6).
"""

from __future__ import annotations

import torch

F32_EPS = torch.finfo(torch.float32).eps


def float32_atol(*values: torch.Tensor, ulps: int = 64) -> float:
    """``ulps`` float32 epsilons at the largest magnitude of ``values`` (at least 1).

    64 eps (7.6e-6 at magnitude 1) covers the rounding of a few layers of width <= 256 in any order,
    and stays orders of magnitude below what a real leak changes (padding of size 50-100 that reaches
    a valid output moves it by far more than 1e-3).
    """
    scale = max(1.0, *(float(value.detach().abs().max()) for value in values))
    return ulps * F32_EPS * scale
