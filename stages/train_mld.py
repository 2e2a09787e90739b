"""Stage ``train_mld``: MLD's latent diffusion teacher over the frozen motion VAE.

``python -m stages.train_mld [key=value ...]`` trains :class:`models.mld.MLDDenoiser` through the
one runner: each step samples a latent of the batch from its frozen-VAE posterior (MLD samples,
it does not take the mean; :mod:`pipelines.latent_cache` encodes the training set once), draws
t ~ U{0..T-1} on the scaled_linear schedule (0.00085-0.012, 1000 steps), drops the text with
probability 0.1 and regresses epsilon. Writes ``artifacts/train_mld/``.

Latent scale (documented choice): with ``normalize_latents`` the driver measures the std of the
training latents once and diffusion runs on ``z / std`` (as latent diffusion models do); MLD itself
uses 1.0 (the ``paper`` profile sets ``normalize_latents: false``).
"""

from __future__ import annotations

import math
from dataclasses import asdict
from typing import Any

import torch

from models.mld import MLDConfig, MLDDenoiser, mld_loss
from models.vae import LatentDistribution
from pipelines.checkpoint import load_final_model
from pipelines.cli import artifacts_dir, repo_path
from pipelines.config import (
    check_choice,
    check_fields,
    check_heads,
    check_keys,
    check_number,
    check_odd,
    check_type,
    is_integer,
    refuse,
)
from pipelines.feature_store import FeatureStore
from pipelines.latent_cache import collate_words, latent_dataset, measure_latent_std
from pipelines.mld_family import noise_schedule
from pipelines.runner import Components, StepContext, TrainSpec
from pipelines.stage import TrainingStage, main


def build(config: dict) -> Components:
    denoiser = MLDDenoiser(MLDConfig(**config["model"]))
    opt = torch.optim.AdamW(denoiser.parameters(), lr=config["lr"], weight_decay=config["weight_decay"])
    return Components(models={"denoiser": denoiser}, optimizers={"adamw": opt}, ema=config["ema"],
                      frozen={"schedule": noise_schedule(config)})


def step(batch: dict, ctx: StepContext) -> dict[str, torch.Tensor]:
    """z0 = (mu + sigma * eps) / s with a fresh eps (MLD samples the posterior), then MLD's eps loss."""
    z0 = LatentDistribution(batch["mu"], batch["logvar"]).sample() / ctx.config["model"]["latent_scale"]
    losses = mld_loss(ctx.unwrap("denoiser"), ctx.frozen["schedule"], z0, batch["text"],
                      p_uncond=ctx.config["p_uncond"], text_tokens=batch.get("tokens"),
                      text_mask=batch.get("token_mask"), net=ctx.models["denoiser"])
    ctx.update(losses["total"])
    return {"loss": losses["total"].detach()}


SECTION = "train_mld"
SECTION_KEYS = ("lr", "weight_decay", "crop_frames", "p_uncond", "ema_decay", "normalize_latents", "beta_schedule",
                "beta_start", "beta_end", "num_train_timesteps", "model", "loop")
#: MLDConfig fields the stage fills in from the VAE and the feature store (not params).
DERIVED_MODEL_KEYS = ("latent_tokens", "latent_dim", "text_dim", "token_dim", "time_cond_dim", "latent_scale")


def check_section(params: dict[str, Any]) -> None:
    """The ``train_mld`` section checked before any work (its ``loop`` group is the skeleton's); a ValueError
    naming the key, its value and what is allowed."""
    cfg = check_keys(params[SECTION], SECTION, SECTION_KEYS)
    check_number(cfg, "lr", SECTION, low=0.0, low_open=True)
    check_number(cfg, "weight_decay", SECTION, low=0.0)
    check_number(cfg, "crop_frames", SECTION, low=1, integer=True)
    check_number(cfg, "p_uncond", SECTION, low=0.0, high=1.0)
    check_number(cfg, "ema_decay", SECTION, low=0.0, high=1.0, high_open=True)
    check_type(cfg, "normalize_latents", SECTION, kind=bool)
    check_choice(cfg, "beta_schedule", SECTION, choices=("linear", "scaled_linear"))
    check_number(cfg, "beta_start", SECTION, low=0.0, low_open=True)
    check_number(cfg, "beta_end", SECTION, low=cfg["beta_start"], low_open=True, high=1.0, high_open=True)
    check_number(cfg, "num_train_timesteps", SECTION, low=1, integer=True)
    check_fields(cfg["model"], MLDConfig, f"{SECTION}.model", exclude=DERIVED_MODEL_KEYS)
    check_model(cfg["model"])
    if cfg["model"].get("hidden_dim") is not None:  # else the width is the VAE's latent_dim, checked with the VAE
        check_heads(cfg["model"], "heads", f"{SECTION}.model", width=cfg["model"]["hidden_dim"])


def check_model(model: dict[str, Any]) -> None:
    """The ranges of ``train_mld.model`` (its types are :func:`check_fields`'; a key left out takes its
    :class:`~models.mld.MLDConfig` default), as :class:`~models.mld.MLDDenoiser` needs them: positive sizes, an
    odd skip-transformer depth, dropout in [0, 1), a time sinusoid of at least one sin/cos pair whose frequency
    denominator ``time_freq_dim // 2 - freq_shift`` stays positive (:func:`models.transformer.timestep_embedding`)."""
    where, given = f"{SECTION}.model", {**asdict(MLDConfig()), **model}
    for key in ("heads", "ff_dim", "max_len"):
        check_number(given, key, where, low=1, integer=True)
    if given["hidden_dim"] is not None:  # null: the width is the VAE's latent_dim
        check_number(given, "hidden_dim", where, low=1, integer=True)
    check_odd(given, "layers", where)  # models.transformer.SkipTransformer: 2K + 1
    check_number(given, "dropout", where, low=0.0, high=1.0, high_open=True)
    freq_dim, shift = given["time_freq_dim"], given["freq_shift"]
    check_number(given, "time_freq_dim", where, low=2, integer=True)
    if is_integer(freq_dim) and freq_dim >= 2 and isinstance(shift, int | float) and not isinstance(shift, bool):
        half = freq_dim // 2
        if not (math.isfinite(shift) and shift < half):
            refuse(f"{where}.freq_shift: expected a number < time_freq_dim // 2 = {half}, got {shift!r}")


def stage_config(params: dict[str, Any]) -> dict[str, Any]:
    """The stage's loop-config keys: paths, statistics, VAE-matching model sizes, the latent scale."""
    cfg = params["train_mld"]
    store = FeatureStore(repo_path(params, "features.out"))
    vae_dir = artifacts_dir(params) / "train_vae"
    vae_model = load_final_model(vae_dir)["config"]["model"]
    encoder = store.text_encoder_meta
    model = {**cfg["model"], "latent_tokens": vae_model["latent_tokens"], "latent_dim": vae_model["latent_dim"],
             "text_dim": encoder["dim"], "token_dim": encoder["token_dim"]}
    config = {
        "features_dir": str(store.path), "vae_dir": str(vae_dir), "mean": store.mean.tolist(),
        "std": store.std.tolist(), "crop_frames": cfg["crop_frames"], "max_text_tokens": encoder["max_length"],
        "lr": cfg["lr"], "weight_decay": cfg["weight_decay"], "p_uncond": cfg["p_uncond"],
        "ema": {"denoiser": cfg["ema_decay"]} if cfg["ema_decay"] else {},
        "beta_schedule": cfg["beta_schedule"], "beta_start": cfg["beta_start"], "beta_end": cfg["beta_end"],
        "num_train_timesteps": cfg["num_train_timesteps"], "model": model,
    }
    scale = 1.0
    if cfg["normalize_latents"]:
        scale = measure_latent_std(latent_dataset(config), seed=cfg["loop"]["seed"])
    config["model"]["latent_scale"] = round(float(scale), 6)
    return config


STAGE = TrainingStage(
    name="train_mld", module=__name__, config=stage_config,
    spec=TrainSpec(build=build, dataset=latent_dataset, step=step, collate=collate_words),
    inputs=("features_dir", "vae_dir"),
    params=(SECTION, "features.out", "paths", "ray"), check=check_section,
)

if __name__ == "__main__":
    main(STAGE)
