"""The MLD teacher's training data: the training motions as frozen-VAE posteriors (the latent cache).

The frozen VAE's encoder is deterministic, so every training item is encoded once into its
posterior (mu, log sigma^2); each training step then samples ``z = mu + sigma * eps`` afresh, the
same distribution as encoding every batch, without a VAE pass per step. Items longer than the
motion dataset's ``crop_frames`` are encoded over their first ``crop_frames`` frames (the motion
loader would draw a random window).

Used by ``train_mld`` and by every stage that trains in MLD's latent space;
:class:`ControlLatentDataset` adds each window's global joints for ``train_controlnet``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset, default_collate

from data.features import recover_from_ric
from data.motion_dataset import MotionTextDataset, pad_tokens
from models.mld import latent_std
from models.vae import LatentDistribution, MotionVAE
from pipelines.mld_family import load_vae


class LatentTextDataset(Dataset):
    """Training items as frozen-VAE posteriors: ``mu``/``logvar`` (L, C) per item, plus a random caption.

    Elements: ``mu``, ``logvar`` (L, C) float32, ``text`` (E,) pooled embedding of a caption drawn
    with the process-global torch RNG (as :class:`MotionTextDataset` draws it), ``index``; with
    ``word_tokens`` > 0 also that caption's ``tokens`` (word_tokens, H) float32, zero-padded, and
    ``token_mask`` (word_tokens,) bool (:func:`collate_words` trims a batch to its longest caption).
    """

    def __init__(self, motions: MotionTextDataset, vae: MotionVAE, batch_size: int = 64, word_tokens: int = 0) -> None:
        self.motions, self.word_tokens = motions, word_tokens
        mu, logvar = [], []
        with torch.no_grad():
            for first in range(0, len(motions), batch_size):
                windows = [motions.window(k) for k in range(first, min(first + batch_size, len(motions)))]
                x = torch.from_numpy(np.stack([w[0] for w in windows]))
                lengths = torch.tensor([w[1] for w in windows])
                dist = vae.eval().encode_distribution(x[:, : int(lengths.max())], lengths)
                mu.append(dist.mu)
                logvar.append(dist.logvar)
        self.mu, self.logvar = torch.cat(mu), torch.cat(logvar)

    def __len__(self) -> int:
        return len(self.motions)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        item = self.motions.items[index]
        caption = int(torch.randint(0, len(item.captions), ()).item())
        out = {"mu": self.mu[index], "logvar": self.logvar[index], "index": torch.tensor(index),
               "text": torch.from_numpy(item.text_pooled[caption].astype(np.float32))}
        if self.word_tokens:
            tokens, mask = pad_tokens([item.text_tokens[caption]], self.word_tokens)
            out |= {"tokens": tokens[0], "token_mask": mask[0]}
        return out


class ControlLatentDataset(LatentTextDataset):
    """:class:`LatentTextDataset` plus each encoded window's global joints and length (the hint source).

    Extra elements: ``joints`` (P, J, 3) float32 global positions in metres recovered from the
    window's features (zero past the length; P = ``crop_frames``), ``length`` int64.
    """

    def __init__(self, motions: MotionTextDataset, vae: MotionVAE, batch_size: int = 64, word_tokens: int = 0) -> None:
        super().__init__(motions, vae, batch_size, word_tokens)
        joints_num = (motions.mean.shape[0] + 1) // 12
        self.joints, self.lengths = [], []
        for k in range(len(motions)):
            window, length = motions.window(k)
            joints = np.zeros((motions.max_frames, joints_num, 3), np.float32)
            joints[:length] = recover_from_ric(window[:length] * motions.std + motions.mean, joints_num)
            self.joints.append(torch.from_numpy(joints))
            self.lengths.append(length)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        return super().__getitem__(index) | {"joints": self.joints[index],
                                            "length": torch.tensor(self.lengths[index])}


def collate_words(items: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """Stack items and cut ``tokens`` (B, N, H) / ``token_mask`` (B, N) to the longest caption (padding only)."""
    batch = default_collate(items)
    if "token_mask" in batch:
        n = max(1, int(batch["token_mask"].sum(1).max()))
        batch["tokens"], batch["token_mask"] = batch["tokens"][:, :n], batch["token_mask"][:, :n]
    return batch


def measure_latent_std(data: LatentTextDataset, seed: int = 0) -> float:
    """Std of one sampled latent per training item (the LDM scale factor s)."""
    z = LatentDistribution(data.mu, data.logvar).sample(torch.Generator().manual_seed(seed))
    return latent_std(z)


def _cache_args(config: dict) -> tuple[MotionTextDataset, MotionVAE, int]:
    motions = MotionTextDataset(config["features_dir"], "train", config["mean"], config["std"], config["crop_frames"])
    words = config["max_text_tokens"] if config["model"].get("word_tokens", "none") != "none" else 0
    return motions, load_vae(Path(config["vae_dir"])), words


def latent_dataset(config: dict) -> LatentTextDataset:
    """The latent cache of a loop config with ``features_dir``, ``mean``, ``std``, ``crop_frames``, ``vae_dir``,
    ``max_text_tokens`` and the denoiser's ``model.word_tokens`` (word tokens are served unless "none")."""
    motions, vae, words = _cache_args(config)
    return LatentTextDataset(motions, vae, word_tokens=words)


def control_dataset(config: dict) -> ControlLatentDataset:
    """:func:`latent_dataset` with the windows' global joints (``train_controlnet``)."""
    motions, vae, words = _cache_args(config)
    return ControlLatentDataset(motions, vae, word_tokens=words)
