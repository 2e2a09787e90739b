"""Training data of the T2M evaluator (``train_evaluator``; reference humanml3d_eval.md B.3).

- :class:`MovementWindows`: random fixed-size windows of training motions, for the movement autoencoder.
- :class:`CaptionMotionPairs`: a random caption and a reference-style crop of each training item,
  for the text/motion matching model.

Item sampling uses the process-global torch RNG, which the runner seeds per rank and saves in
every checkpoint, so resumed runs draw the same captions and crops.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from data.store import read_split
from data.vocab import WordVocab


def _crop(features: np.ndarray, length: int) -> np.ndarray:
    """A random ``length``-frame window of ``features`` (torch global RNG)."""
    start = int(torch.randint(0, features.shape[0] - length + 1, ()).item())
    return features[start : start + length]


class MovementWindows(Dataset):
    """Random fixed-size windows of training motions: ``{"window": (W, D) raw features}``."""

    def __init__(self, config: dict) -> None:
        items = read_split(Path(config["features_dir"]) / "train.parquet")
        self.window = config["movement_window"]
        self.motions = [item.features for item in items if item.length >= self.window]
        if not self.motions:
            raise ValueError(f"no training motion has {self.window} frames for the movement autoencoder")

    def __len__(self) -> int:
        return len(self.motions)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        return {"window": torch.from_numpy(_crop(self.motions[index], self.window).copy())}


class CaptionMotionPairs(Dataset):
    """One random caption and a reference-style crop (length rounded to 4) of each training item.

    Returns ``word_ids`` (22,), ``pos`` (22, 15), ``sent_len``, ``motion`` (P, D) raw features
    zero-padded to P (the longest item rounded up to 4) and ``length``.
    """

    def __init__(self, config: dict) -> None:
        self.items = read_split(Path(config["features_dir"]) / "train.parquet")
        self.vocab = WordVocab.from_dict(config["vocab"])
        self.max_words = config["max_words"]
        self.padded = 4 * -(-max(item.length for item in self.items) // 4)

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        item = self.items[index]
        caption = int(torch.randint(0, len(item.captions), ()).item())
        word_ids, pos, sent_len = self.vocab.encode_tokens(item.tokens[caption], self.max_words)
        units = item.length // 4 - int(torch.rand(()).item() < 1 / 3)
        length = max(units, 1) * 4
        motion = np.zeros((self.padded, item.features.shape[1]), np.float32)
        motion[:length] = _crop(item.features, length)
        return {"word_ids": torch.from_numpy(word_ids), "pos": torch.from_numpy(pos),
                "sent_len": torch.tensor(sent_len), "motion": torch.from_numpy(motion),
                "length": torch.tensor(length)}
