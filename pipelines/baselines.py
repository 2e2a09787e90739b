"""Non-neural baselines: they prove the metrics work before any model is trained.

- :class:`RandomMotion` answers every caption with a random training motion, so its
  R-precision must sit at chance (k/32).
- :class:`Retrieval` answers with the training motion whose caption's frozen text embedding is
  nearest (cosine) to the query's: a strong non-generative baseline.

Both crop the chosen training motion to the requested length (a random window for Random, the
first frames for Retrieval); only motions at least that long are candidates. :func:`rows` is the
model registry's entry (``pipelines/registry.py``).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from data.motion_dataset import pad_motions
from data.store import StoredItem
from models.generator import Generator, TextBatch

if TYPE_CHECKING:  # annotations only: the registry imports this module, not the reverse
    from pipelines.registry import EvalContext


class _TrainingMotions:
    """Training motions, normalised with the dataset's Mean/Std."""

    def __init__(self, items: Sequence[StoredItem], mean: np.ndarray, std: np.ndarray) -> None:
        if not items:
            raise ValueError("baseline generators need at least one training item")
        self.motions = [((item.features - mean) / std).astype(np.float32) for item in items]
        self.lengths = np.array([len(m) for m in self.motions])

    def long_enough(self, length: int) -> np.ndarray:
        candidates = np.flatnonzero(self.lengths >= length)
        if not len(candidates):
            raise ValueError(f"no training motion has {length} frames (longest: {self.lengths.max()})")
        return candidates


class RandomMotion(_TrainingMotions):
    """A random training motion (random window) per caption, ignoring the text."""

    name = "Random"
    nfe = 0
    stochastic = True

    def sample(self, text: TextBatch, lengths: np.ndarray, seed: int) -> np.ndarray:
        rng = np.random.default_rng(seed)
        motions = []
        for length in lengths:
            motion = self.motions[rng.choice(self.long_enough(int(length)))]
            start = rng.integers(0, len(motion) - length + 1)
            motions.append(motion[start : start + length])
        return pad_motions(motions, lengths)


class Retrieval(_TrainingMotions):
    """The training motion whose caption embedding is nearest to the query's (first frames)."""

    name = "Retrieval"
    nfe = 0
    stochastic = False

    def __init__(self, items: Sequence[StoredItem], mean: np.ndarray, std: np.ndarray) -> None:
        super().__init__(items, mean, std)
        self.caption_emb = np.concatenate([item.text_pooled for item in items]).astype(np.float32)
        self.caption_owner = np.concatenate([np.full(len(item.captions), k) for k, item in enumerate(items)])

    def sample(self, text: TextBatch, lengths: np.ndarray, seed: int) -> np.ndarray:
        scores = text.pooled.astype(np.float32) @ self.caption_emb.T  # (B, captions): cosine (unit vectors)
        motions = []
        for b, length in enumerate(lengths):
            allowed = np.isin(self.caption_owner, self.long_enough(int(length)))
            best = int(np.argmax(np.where(allowed, scores[b], -np.inf)))
            motions.append(self.motions[self.caption_owner[best]][:length])
        return pad_motions(motions, lengths)


def row_names(params: dict[str, Any]) -> list[str]:
    """The names :func:`rows` gives its rows."""
    return [RandomMotion.name, Retrieval.name]


def rows(ctx: EvalContext) -> list[Generator]:
    """Random (chance level) and Retrieval (nearest training caption) rows."""
    train = ctx.store.split("train")
    return [RandomMotion(train, ctx.store.mean, ctx.store.std), Retrieval(train, ctx.store.mean, ctx.store.std)]
