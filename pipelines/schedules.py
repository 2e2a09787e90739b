"""Learning-rate schedules and exponential moving averages of model weights.

Both objects are checkpointable (``state_dict``/``load_state_dict``), so a resumed run
continues them exactly.
"""

from __future__ import annotations

import copy
import math

import torch
from torch import nn
from torch.optim import Optimizer
from torch.optim.lr_scheduler import LambdaLR


class CosineWarmup:
    """LR multiplier: linear warm-up to 1, then cosine decay to ``min_ratio`` at ``total``.

    A callable object (not a lambda) so ``LambdaLR.state_dict`` stores its settings.
    """

    def __init__(self, warmup_steps: int, total_steps: int, min_ratio: float = 0.0) -> None:
        self.warmup_steps = max(0, int(warmup_steps))
        self.total_steps = max(1, int(total_steps))
        self.min_ratio = float(min_ratio)

    def __call__(self, step: int) -> float:
        """Multiplier for the learning rate used at optimiser step ``step`` (0-based)."""
        if step < self.warmup_steps:
            return (step + 1) / self.warmup_steps
        span = max(1, self.total_steps - self.warmup_steps)
        progress = min(1.0, (step - self.warmup_steps) / span)
        return self.min_ratio + (1.0 - self.min_ratio) * 0.5 * (1.0 + math.cos(math.pi * progress))


class Constant:
    """LR multiplier that is always 1 (a schedule that does nothing, but checkpoints like one)."""

    def __call__(self, step: int) -> float:
        """Return 1.0 whatever the step."""
        return 1.0


def make_scheduler(
    optimizer: Optimizer, kind: str, warmup_steps: int, total_steps: int, min_ratio: float
) -> LambdaLR:
    """Build the per-step LR scheduler named ``kind`` ("cosine" or "constant").

    "constant" keeps the optimiser's LR throughout: it has no warm-up and no floor (a loop group asking
    for either with it is refused by ``LoopSettings.parse``).
    """
    if kind == "cosine":
        return LambdaLR(optimizer, CosineWarmup(warmup_steps, total_steps, min_ratio))
    if kind == "constant":
        return LambdaLR(optimizer, Constant())
    raise ValueError(f"unknown lr_schedule {kind!r}; expected 'cosine' or 'constant'")


class EMA:
    """Exponential moving average of a module's parameters (buffers are copied).

    ``ema.module`` is a frozen copy in eval mode, usable directly (e.g. as the target
    network of consistency distillation or for sampling).
    """

    def __init__(self, model: nn.Module, decay: float) -> None:
        if not 0.0 <= decay <= 1.0:
            raise ValueError(f"EMA decay must be in [0, 1], got {decay}")
        self.decay = float(decay)
        self.module = copy.deepcopy(model).eval()
        self.module.requires_grad_(False)

    @torch.no_grad()
    def update(self, model: nn.Module) -> None:
        """Move the average one step towards ``model``'s current weights."""
        for avg, cur in zip(self.module.parameters(), model.parameters(), strict=True):
            avg.lerp_(cur.detach(), 1.0 - self.decay)
        for avg, cur in zip(self.module.buffers(), model.buffers(), strict=True):
            avg.copy_(cur)

    def state_dict(self) -> dict:
        """Averaged weights plus the decay."""
        return {"decay": self.decay, "module": self.module.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        """Restore what :meth:`state_dict` returned."""
        self.decay = float(state["decay"])
        self.module.load_state_dict(state["module"])
