"""Generators (and the VAE reconstructor) behind :class:`models.generator.Generator`.

They prove the metrics work before any model is trained (issue: evaluate stage):

- :class:`RandomMotion` answers every caption with a random training motion, so its
  R-precision must sit at chance (k/32).
- :class:`Retrieval` answers with the training motion whose caption's frozen text embedding is
  nearest (cosine) to the query's: a strong non-generative baseline.

Both crop the chosen training motion to the requested length (a random window for Random, the
first frames for Retrieval); only motions at least that long are candidates.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from data.features import recover_from_ric
from data.motion_dataset import pad_tokens
from data.store import StoredItem
from data.text_encoders import build_text_encoder
from models.diffusion import NoiseSchedule
from models.generator import TextBatch
from models.mld import MLDDenoiser, sample_mld
from models.vae import MotionVAE, length_sorted_chunks


def pad_motions(motions: Sequence[np.ndarray], lengths: np.ndarray) -> np.ndarray:
    """Stack (L_b, D) motions into (B, max L, D) float32, zero past each length."""
    out = np.zeros((len(motions), int(max(lengths, default=0)), motions[0].shape[1] if motions else 0), np.float32)
    for b, (motion, length) in enumerate(zip(motions, lengths, strict=True)):
        out[b, :length] = motion[:length]
    return out


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


class MLDGenerator:
    """MLD: DDIM over the VAE latent with classifier-free guidance, then VAE decoding."""

    stochastic = True

    def __init__(self, name: str, denoiser: MLDDenoiser, vae: MotionVAE, schedule: NoiseSchedule,
                 num_steps: int, guidance: float) -> None:
        self.name, self.denoiser, self.vae, self.schedule = name, denoiser, vae, schedule
        self.num_steps, self.guidance = num_steps, guidance
        self.nfe = num_steps * (2 if guidance != 1.0 else 1)

    @torch.inference_mode()
    def sample(self, text: TextBatch, lengths: np.ndarray, seed: int) -> np.ndarray:
        generator = torch.Generator().manual_seed(seed)
        words = {}
        if self.denoiser.config.word_tokens != "none":
            tokens, mask = pad_tokens([np.asarray(t, np.float32) for t in text.tokens])
            words = {"text_tokens": tokens, "text_mask": mask}
        out = sample_mld(self.denoiser, self.vae, self.schedule, torch.from_numpy(text.pooled.astype(np.float32)),
                         torch.as_tensor(lengths), self.num_steps, self.guidance, generator, **words)
        return out.numpy()


class VAEReconstruction:
    """The motion VAE's encode (posterior mean) -> decode of real motions."""

    name = "VAE"

    def __init__(self, vae: MotionVAE) -> None:
        self.vae = vae.eval()

    @torch.inference_mode()
    def reconstruct(self, motions: np.ndarray, lengths: np.ndarray, chunk_size: int = 64) -> np.ndarray:
        """Normalised motions (B, T, D) -> reconstructions (B, T, D), in chunks of similar length."""
        x, lengths_t = torch.from_numpy(motions.astype(np.float32)), torch.as_tensor(lengths)
        out = torch.zeros_like(x)
        for idx, longest in length_sorted_chunks(lengths_t, chunk_size):
            z, _ = self.vae.encode(x[idx, :longest], lengths_t[idx], sample=False)
            out[idx, :longest] = self.vae.decode(z, lengths_t[idx], longest)
        return out.numpy()


def encode_prompts(texts: Sequence[str], features_dir: Path) -> TextBatch:
    """Prompts encoded by the same frozen text encoder the feature store was built with."""
    encoder_meta = json.loads((Path(features_dir) / "meta.json").read_text())["text_encoder"]
    path = encoder_meta["path"]  # None: the encoder packaged in the environment
    encoder = build_text_encoder(encoder_meta["name"], path=path, max_length=encoder_meta["max_length"])
    enc = encoder.encode(list(texts))
    return TextBatch(list(texts), enc.pooled, [enc.tokens[k][enc.mask[k]] for k in range(len(texts))])


def motions_to_joints(features: np.ndarray, lengths: np.ndarray, mean: np.ndarray, std: np.ndarray) -> list[np.ndarray]:
    """Normalised (B, T, D) generator output -> B global joint arrays (L_b, J, 3)."""
    joints_num = (features.shape[-1] + 1) // 12
    return [recover_from_ric(features[b, :n] * std + mean, joints_num) for b, n in enumerate(lengths)]
