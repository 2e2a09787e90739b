"""The one sampling interface every motion generator implements (DESIGN.md, "Models").

``evaluate`` and the user CLI only ever talk to a :class:`Generator`: texts (with their frozen
text-encoder embeddings) and lengths in, dataset-normalised features out. A
:class:`ControlledGenerator` also takes a :class:`Hint` (target joint positions on some frames).
Both sides are NumPy arrays on the host, so a generator whose networks run on a GPU moves its inputs to
:func:`device_of` its networks and brings its output back.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np
import torch

#: The default device of the loaders (``sample.device`` chooses another).
CPU = torch.device("cpu")


def device_of(module: torch.nn.Module) -> torch.device:
    """Where a network's parameters live: the device a generator moves its inputs to."""
    return next(module.parameters()).device


@dataclass(frozen=True)
class TextBatch:
    """B prompts and their frozen text-encoder embeddings.

    Attributes:
        texts: the B captions.
        pooled: (B, E) float32 sentence embeddings (L2-normalised).
        tokens: B arrays (n_b, H) of token embeddings (real tokens only).
    """

    texts: list[str]
    pooled: np.ndarray
    tokens: list[np.ndarray]

    def __post_init__(self) -> None:
        if self.pooled.ndim != 2 or len(self.pooled) != len(self.texts) or len(self.tokens) != len(self.texts):
            raise ValueError(f"TextBatch: {len(self.texts)} texts, pooled {self.pooled.shape}, "
                             f"{len(self.tokens)} token arrays")

    def __len__(self) -> int:
        return len(self.texts)

    def select(self, index: np.ndarray | list[int]) -> TextBatch:
        """The sub-batch at ``index`` (in that order)."""
        index = list(index)
        return TextBatch([self.texts[i] for i in index], self.pooled[index], [self.tokens[i] for i in index])


@runtime_checkable
class Generator(Protocol):
    """A text-to-motion generator as seen by ``evaluate`` and ``stages.generate``.

    Attributes:
        name: row name in the metrics table (e.g. ``"MLD-DDIM50"``).
        nfe: network evaluations per sample (0 for non-neural baselines).
        stochastic: whether two samples for the same text differ (MultiModality applies).
    """

    name: str
    nfe: int
    stochastic: bool

    def sample(self, text: TextBatch, lengths: np.ndarray, seed: int) -> np.ndarray:
        """Motions for ``text`` with ``lengths`` (B,) frames.

        Returns:
            (B, max(lengths), D) float32 features normalised with the dataset's Mean/Std;
            frames at or past ``lengths[b]`` are zero. The same ``seed`` gives the same output.
        """
        ...


@dataclass(frozen=True)
class Hint:
    """Target global joint positions for trajectory control (``data/control.py``).

    Attributes:
        joints: (B, T, J, 3) float32 positions in metres; only entries under ``mask`` matter.
        mask: (B, T, J) bool, True at the controlled (frame, joint) entries (never on padded frames).
    """

    joints: np.ndarray
    mask: np.ndarray

    def __post_init__(self) -> None:
        if self.joints.ndim != 4 or self.joints.shape[-1] != 3 or self.mask.shape != self.joints.shape[:-1]:
            raise ValueError(f"Hint: joints {self.joints.shape} must be (B, T, J, 3) and mask {self.mask.shape} "
                             "(B, T, J)")
        if self.mask.dtype != np.bool_:
            raise ValueError(f"Hint: mask must be boolean, got {self.mask.dtype}")
        if not np.isfinite(self.joints[self.mask]).all():
            raise ValueError("Hint: controlled joint positions contain NaN or inf")

    def select(self, index: np.ndarray | list[int]) -> Hint:
        """The sub-batch at ``index`` (in that order)."""
        return Hint(self.joints[list(index)], self.mask[list(index)])


@dataclass(frozen=True)
class ControlSpec:
    """How an evaluation row is controlled: ``density`` (``data.control.TEST_DENSITIES``) on ``joints`` (ids)."""

    density: str
    joints: tuple[int, ...] = (0,)


@runtime_checkable
class ControlledGenerator(Protocol):
    """A :class:`Generator` whose ``sample`` also takes a :class:`Hint`; ``control`` says which hints
    the evaluation gives it (a row scored against hints it ignores, such as an uncontrolled reference,
    is one too)."""

    name: str
    nfe: int
    stochastic: bool
    control: ControlSpec

    def sample(self, text: TextBatch, lengths: np.ndarray, seed: int, hint: Hint) -> np.ndarray: ...


@runtime_checkable
class Reconstructor(Protocol):
    """An autoencoder evaluated on real motions (e.g. the motion VAE's reconstruction row).

    ``reconstruct`` maps (B, T, D) normalised features with ``lengths`` (B,) to their
    reconstruction (B, T, D), zero at or past each length.
    """

    name: str

    def reconstruct(self, motions: np.ndarray, lengths: np.ndarray) -> np.ndarray: ...
