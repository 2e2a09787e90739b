"""Stage ``train_mld``: MLD's latent diffusion teacher over the frozen motion VAE.

``python -m stages.train_mld [key=value ...]`` trains :class:`models.mld.MLDDenoiser` through the
one runner: each step encodes the batch with the frozen VAE (a *sampled* latent, as MLD does),
draws t ~ U{0..T-1} on the scaled_linear schedule (0.00085-0.012, 1000 steps), drops the text
with probability 0.1 and regresses epsilon. Writes ``artifacts/train_mld/``.

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
from torch.utils.data import DataLoader

from data.motion_dataset import MotionTextDataset
from models.diffusion import NoiseSchedule
from models.mld import MLDConfig, MLDDenoiser, encode_latents, latent_std, mld_loss
from pipelines.checkpoint import load_final_model
from pipelines.config import REPO_ROOT, load_params
from pipelines.runner import Components, StepContext, TrainSpec, run_training
from stages.train_vae import load_vae

RUNNER_KEYS = ("seed", "batch_size", "max_steps", "grad_clip", "log_every", "lr_schedule", "warmup_steps",
               "min_lr_ratio")


def schedule_of(config: dict) -> NoiseSchedule:
    return NoiseSchedule.from_name(config["beta_schedule"], config["num_train_timesteps"],
                                   beta_start=config["beta_start"], beta_end=config["beta_end"])


def dataset(config: dict) -> MotionTextDataset:
    return MotionTextDataset(config["features_dir"], "train", config["mean"], config["std"], config["max_frames"])


def build(config: dict) -> Components:
    denoiser = MLDDenoiser(MLDConfig(**config["model"]))
    opt = torch.optim.AdamW(denoiser.parameters(), lr=config["lr"], weight_decay=config["weight_decay"])
    vae = load_vae(Path(config["vae_dir"]))
    for p in vae.parameters():
        p.requires_grad_(False)
    return Components(models={"denoiser": denoiser}, optimizers={"adamw": opt}, ema=config["ema"],
                      frozen={"vae": vae, "schedule": schedule_of(config)})


def step(batch: dict, ctx: StepContext) -> dict[str, torch.Tensor]:
    schedule = ctx.frozen["schedule"]
    scale = ctx.config["model"]["latent_scale"]
    z0 = encode_latents(ctx.frozen["vae"], batch["motion"], batch["length"], latent_scale=scale)
    losses = mld_loss(ctx.models["denoiser"], schedule, z0, batch["text"], p_uncond=ctx.config["p_uncond"])
    ctx.update(losses["total"])
    return {"loss": losses["total"].detach()}


SPEC = TrainSpec(build=build, dataset=dataset, step=step)


def measure_latent_std(vae_dir: Path, data: MotionTextDataset, batches: int = 8, seed: int = 0) -> float:
    """Std of sampled training latents over a few batches (the LDM scale factor)."""
    torch.manual_seed(seed)
    vae = load_vae(vae_dir)
    loader = DataLoader(data, batch_size=64, shuffle=True, generator=torch.Generator().manual_seed(seed))
    latents = []
    for k, batch in enumerate(loader):
        if k == batches:
            break
        latents.append(encode_latents(vae, batch["motion"], batch["length"]))
    return latent_std(torch.cat(latents))


def loop_config(params: dict[str, Any]) -> dict[str, Any]:
    """The runner's loop config from params: paths, statistics, VAE-matching model sizes."""
    cfg = params["train_mld"]
    features = (REPO_ROOT / params["features"]["out"]).resolve()
    vae_dir = (REPO_ROOT / params["paths"]["artifacts"] / "train_vae").resolve()
    mean, std = np.load(features / "mean.npy"), np.load(features / "std.npy")
    vae_model = load_final_model(vae_dir)["config"]["model"]
    text_dim = json.loads((features / "meta.json").read_text())["text_encoder"]["dim"]
    model = {**cfg["model"], "latent_tokens": vae_model["latent_tokens"], "latent_dim": vae_model["latent_dim"],
             "text_dim": text_dim}
    config = {key: cfg[key] for key in RUNNER_KEYS} | {
        "features_dir": str(features), "vae_dir": str(vae_dir), "mean": mean.tolist(), "std": std.tolist(),
        "max_frames": cfg["max_frames"], "lr": cfg["lr"], "weight_decay": cfg["weight_decay"],
        "p_uncond": cfg["p_uncond"], "ema": {"denoiser": cfg["ema_decay"]} if cfg["ema_decay"] else {},
        "beta_schedule": cfg["beta_schedule"], "beta_start": cfg["beta_start"], "beta_end": cfg["beta_end"],
        "num_train_timesteps": cfg["num_train_timesteps"], "model": model,
    }
    scale = 1.0
    if cfg["normalize_latents"]:
        scale = measure_latent_std(vae_dir, dataset(config), seed=cfg["seed"])
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
