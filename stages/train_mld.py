"""Stage ``train_mld``: MLD's latent diffusion teacher over the frozen motion VAE.

``python -m stages.train_mld [key=value ...]`` trains :class:`models.mld.MLDDenoiser` through the
one runner: each step encodes the batch with the frozen VAE (a *sampled* latent, as MLD does),
draws t ~ U{0..T-1} on the scaled_linear schedule (0.00085-0.012, 1000 steps), drops the text
with probability 0.1 and regresses epsilon. Writes ``artifacts/train_mld/``.

Latent cache (exact, and an order of magnitude cheaper): the frozen VAE's encoder is deterministic,
so the stage encodes every training item once into its posterior (mu, log sigma^2) and each step
samples ``z = mu + sigma * eps`` afresh, the same distribution as encoding every batch. Items longer
than ``max_frames`` are encoded over their first ``max_frames`` frames (the motion loader would draw
a random window; none of the embedded dataset's items is that long).

Latent scale (documented choice): with ``normalize_latents`` the driver measures the std of the
training latents once and diffusion runs on ``z / std`` (as latent diffusion models do); MLD itself
uses 1.0 (the ``paper`` profile sets ``normalize_latents: false``).
"""

from __future__ import annotations

import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset, default_collate

from data.motion_dataset import MotionTextDataset, pad_tokens
from models.diffusion import NoiseSchedule
from models.mld import MLDConfig, MLDDenoiser, latent_std, mld_loss
from models.vae import LatentDistribution, MotionVAE
from pipelines.checkpoint import load_final_model
from pipelines.config import REPO_ROOT, load_params
from pipelines.runner import Components, StepContext, TrainSpec, run_training
from stages.train_vae import load_vae

RUNNER_KEYS = ("seed", "batch_size", "max_steps", "grad_clip", "log_every", "lr_schedule", "warmup_steps",
               "min_lr_ratio")


def schedule_of(config: dict) -> NoiseSchedule:
    return NoiseSchedule.from_name(config["beta_schedule"], config["num_train_timesteps"],
                                   beta_start=config["beta_start"], beta_end=config["beta_end"])


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


def collate_words(items: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """Stack items and cut ``tokens`` (B, N, H) / ``token_mask`` (B, N) to the longest caption (padding only)."""
    batch = default_collate(items)
    if "token_mask" in batch:
        n = max(1, int(batch["token_mask"].sum(1).max()))
        batch["tokens"], batch["token_mask"] = batch["tokens"][:, :n], batch["token_mask"][:, :n]
    return batch


def dataset(config: dict) -> LatentTextDataset:
    motions = MotionTextDataset(config["features_dir"], "train", config["mean"], config["std"], config["max_frames"])
    words = config["max_text_tokens"] if config["model"].get("word_tokens", "none") != "none" else 0
    return LatentTextDataset(motions, load_vae(Path(config["vae_dir"])), word_tokens=words)


def build(config: dict) -> Components:
    denoiser = MLDDenoiser(MLDConfig(**config["model"]))
    opt = torch.optim.AdamW(denoiser.parameters(), lr=config["lr"], weight_decay=config["weight_decay"])
    return Components(models={"denoiser": denoiser}, optimizers={"adamw": opt}, ema=config["ema"],
                      frozen={"schedule": schedule_of(config)})


def step(batch: dict, ctx: StepContext) -> dict[str, torch.Tensor]:
    """z0 = (mu + sigma * eps) / s with a fresh eps (MLD samples the posterior), then MLD's eps loss."""
    z0 = LatentDistribution(batch["mu"], batch["logvar"]).sample() / ctx.config["model"]["latent_scale"]
    losses = mld_loss(ctx.models["denoiser"], ctx.frozen["schedule"], z0, batch["text"],
                      p_uncond=ctx.config["p_uncond"], text_tokens=batch.get("tokens"),
                      text_mask=batch.get("token_mask"))
    ctx.update(losses["total"])
    return {"loss": losses["total"].detach()}


SPEC = TrainSpec(build=build, dataset=dataset, step=step, collate=collate_words)


def measure_latent_std(data: LatentTextDataset, seed: int = 0) -> float:
    """Std of one sampled latent per training item (the LDM scale factor s)."""
    z = LatentDistribution(data.mu, data.logvar).sample(torch.Generator().manual_seed(seed))
    return latent_std(z)


def loop_config(params: dict[str, Any]) -> dict[str, Any]:
    """The runner's loop config from params: paths, statistics, VAE-matching model sizes."""
    cfg = params["train_mld"]
    features = (REPO_ROOT / params["features"]["out"]).resolve()
    vae_dir = (REPO_ROOT / params["paths"]["artifacts"] / "train_vae").resolve()
    mean, std = np.load(features / "mean.npy"), np.load(features / "std.npy")
    vae_model = load_final_model(vae_dir)["config"]["model"]
    encoder = json.loads((features / "meta.json").read_text())["text_encoder"]
    model = {**cfg["model"], "latent_tokens": vae_model["latent_tokens"], "latent_dim": vae_model["latent_dim"],
             "text_dim": encoder["dim"], "token_dim": encoder["token_dim"]}
    config = {key: cfg[key] for key in RUNNER_KEYS} | {
        "features_dir": str(features), "vae_dir": str(vae_dir), "mean": mean.tolist(), "std": std.tolist(),
        "max_frames": cfg["max_frames"], "max_text_tokens": encoder["max_length"], "lr": cfg["lr"],
        "weight_decay": cfg["weight_decay"],
        "p_uncond": cfg["p_uncond"], "ema": {"denoiser": cfg["ema_decay"]} if cfg["ema_decay"] else {},
        "beta_schedule": cfg["beta_schedule"], "beta_start": cfg["beta_start"], "beta_end": cfg["beta_end"],
        "num_train_timesteps": cfg["num_train_timesteps"], "model": model,
    }
    scale = 1.0
    if cfg["normalize_latents"]:
        scale = measure_latent_std(dataset(config), seed=cfg["seed"])
    config["model"]["latent_scale"] = round(float(scale), 6)
    return config


def load_mld(out_dir: Path, use_ema: bool = True) -> tuple[MLDDenoiser, NoiseSchedule, dict[str, Any]]:
    """The trained denoiser (EMA weights when present), its noise schedule and its loop config."""
    payload = load_final_model(out_dir)
    config = payload["config"]
    denoiser = MLDDenoiser(MLDConfig(**config["model"]))
    weights = payload["ema"].get("denoiser") if use_ema else None
    denoiser.load_state_dict(weights or payload["models"]["denoiser"])
    return denoiser.eval(), schedule_of(config), config


def run(params: dict[str, Any]) -> Path:
    out = REPO_ROOT / params["paths"]["artifacts"] / "train_mld"
    storage = str((REPO_ROOT / params["paths"]["ray_storage"]).resolve())
    result = run_training("train_mld", SPEC, loop_config(params), params["ray"], out, storage)
    print(f"train_mld: final loss {result.metrics.get('loss', float('nan')):.4f} -> {result.out_dir}")
    return result.out_dir


def main(argv: Sequence[str] | None = None) -> None:
    try:
        run(load_params(argv))
    except (ValueError, FileNotFoundError) as err:
        sys.exit(f"train_mld: {err}")


if __name__ == "__main__":
    main()
