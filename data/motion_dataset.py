"""A torch Dataset of (normalised motion, caption embedding) pairs from the feature store.

Used by every generator's training stage. Each access picks one of the item's captions at random
and, when the item is longer than ``max_frames``, a random ``max_frames`` window, as the
reference loaders do. Randomness comes from the process-global torch RNG, which the training
runner seeds per rank and saves in its checkpoints, so a resumed run draws the same pairs.
With ``word_tokens`` > 0 an item also carries the chosen caption's word-token states (no extra
random draw: the draws, and so every pair served, are the same as without them).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset, default_collate

from data.store import read_split


class MotionTextDataset(Dataset):
    """Items of one split of the store.

    Each element is a dict of ``motion`` (P, D) float32 normalised with ``mean``/``std`` and
    zero past ``length``; ``length`` (int64); ``text`` (E,) pooled caption embedding; ``index``.
    P is ``max_frames``; :func:`collate_trimmed` cuts a batch to its longest item.

    ``word_tokens`` > 0 adds, for the same caption as ``text``, its word-token states ``tokens``
    (word_tokens, H) float32 zero-padded and ``token_mask`` (word_tokens,) bool True on the real
    tokens (:func:`pad_tokens`; a caption with more tokens is an error);
    :func:`collate_trimmed_words` also cuts them to the batch's longest caption.
    """

    def __init__(self, store_dir: str | Path, split: str, mean: np.ndarray, std: np.ndarray, max_frames: int,
                 word_tokens: int = 0) -> None:
        if isinstance(word_tokens, bool) or not isinstance(word_tokens, int) or word_tokens < 0:
            raise ValueError(f"word_tokens must be an integer >= 0, got {word_tokens!r}")
        self.items = read_split(Path(store_dir) / f"{split}.parquet")
        if not self.items:
            raise ValueError(f"{store_dir}/{split}.parquet has no items")
        self.mean = np.asarray(mean, np.float32)
        self.std = np.asarray(std, np.float32)
        self.max_frames = max_frames
        self.word_tokens = word_tokens

    def __len__(self) -> int:
        return len(self.items)

    @property
    def lengths(self) -> np.ndarray:
        """(N,) int64 frames of each item as served (at most ``max_frames``): what a length-bucketed
        batch order (the runner's ``length_buckets``) sorts by."""
        return np.array([min(item.length, self.max_frames) for item in self.items], dtype=np.int64)

    def window(self, index: int, start: int = 0) -> tuple[np.ndarray, int]:
        """Item ``index`` from frame ``start``: normalised (P, D) zero-padded motion and its length."""
        item = self.items[index]
        length = min(item.length - start, self.max_frames)
        motion = np.zeros((self.max_frames, item.features.shape[1]), np.float32)
        motion[:length] = (item.features[start : start + length] - self.mean) / self.std
        return motion, length

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        item = self.items[index]
        caption = int(torch.randint(0, len(item.captions), ()).item())
        start = int(torch.randint(0, max(0, item.length - self.max_frames) + 1, ()).item())
        motion, length = self.window(index, start)
        out = {
            "motion": torch.from_numpy(motion),
            "length": torch.tensor(length),
            "text": torch.from_numpy(item.text_pooled[caption].astype(np.float32)),
            "index": torch.tensor(index),
        }
        if self.word_tokens:
            tokens, mask = pad_tokens([np.asarray(item.text_tokens[caption], np.float32)], self.word_tokens)
            out |= {"tokens": tokens[0], "token_mask": mask[0]}
        return out


def pad_tokens(tokens: list[np.ndarray], max_tokens: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """B word-token embedding arrays (n_b, H) -> zero-padded (B, N, H) float32 and mask (B, N) bool.

    ``N = max_tokens`` or the longest n_b (at least 1, so an empty caption still has a shape);
    ``mask[b, i]`` is True for the real tokens ``i < n_b``. Raises if an array is longer than N.
    """
    counts = [len(t) for t in tokens]
    n = max([1, *counts]) if max_tokens is None else max_tokens
    if max(counts, default=0) > n:
        raise ValueError(f"a caption has {max(counts)} word tokens, more than max_tokens={n}")
    dim = tokens[0].shape[-1] if tokens else 0
    out = np.zeros((len(tokens), n, dim), np.float32)
    for b, t in enumerate(tokens):
        out[b, : len(t)] = t
    mask = torch.arange(n)[None] < torch.tensor(counts, dtype=torch.long)[:, None]
    return torch.from_numpy(out), mask


def collate_trimmed(items: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """Stack items and cut ``motion`` (B, P, D) to (B, max(length), D).

    Only padding is removed, and every model masks padded frames, so the result is the same as on
    the full padding, computed on fewer frames (mean length instead of ``max_frames``).
    """
    batch = default_collate(items)
    batch["motion"] = batch["motion"][:, : int(batch["length"].max())]
    return batch


def collate_trimmed_words(items: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """:func:`collate_trimmed`, and ``tokens`` (B, W, H) / ``token_mask`` (B, W) cut to the batch's longest
    caption (at least 1 position). Only padding is removed: a model that masks padded tokens gives the same."""
    batch = collate_trimmed(items)
    if "token_mask" in batch:
        n = max(1, int(batch["token_mask"].sum(1).max()))
        batch["tokens"], batch["token_mask"] = batch["tokens"][:, :n], batch["token_mask"][:, :n]
    return batch


def pad_motions(motions: Sequence[np.ndarray], lengths: np.ndarray) -> np.ndarray:
    """Stack (L_b, D) motions into (B, max L, D) float32, zero past each length."""
    out = np.zeros((len(motions), int(max(lengths, default=0)), motions[0].shape[1] if motions else 0), np.float32)
    for b, (motion, length) in enumerate(zip(motions, lengths, strict=True)):
        out[b, :length] = motion[:length]
    return out
