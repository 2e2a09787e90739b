"""Stage ``train_vae``: MLD's motion VAE, the latent space of MLD, MotionLCM and its ControlNet.

``python -m stages.train_vae [key=value ...]`` trains :class:`models.vae.MotionVAE` on the
training motions of the feature store (normalised with its Mean/Std) through the one runner:
smooth-L1 on features and on joints (``recover_from_ric``; global as MLD, or root-aligned with
``joint_space: root``; beta ``joint_beta`` metres) + ``heading_weight`` x L1 on the integrated heading
+ KL weight 1e-4, AdamW, cosine schedule with warm-up, gradient clipping.
Writes ``artifacts/train_vae/`` (model.pt, metrics.json, loss.csv/png).

``python -m stages.sweep train_vae`` sweeps it (:func:`sweep_target`), ranking the trials by
``val_MPJPE_mm``, the reconstruction error of the validation motions.
"""

from __future__ import annotations

import math
from dataclasses import asdict
from typing import TYPE_CHECKING, Any

import torch

from data.motion_dataset import MotionTextDataset, collate_trimmed
from models.vae import MotionVAE, MotionVAEConfig, vae_loss
from pipelines.cli import repo_path
from pipelines.config import check_choice, check_fields, check_heads, check_keys, check_number, check_odd, refuse
from pipelines.feature_store import FeatureStore
from pipelines.runner import Components, StepContext, TrainSpec
from pipelines.stage import TrainingStage, checks, loop_config, main

if TYPE_CHECKING:
    from pipelines.sweep import SweepTarget


def dataset(config: dict) -> MotionTextDataset:
    return MotionTextDataset(config["features_dir"], "train", config["mean"], config["std"], config["crop_frames"])


def build(config: dict) -> Components:
    vae = MotionVAE(MotionVAEConfig(**config["model"]))
    opt = torch.optim.AdamW(vae.parameters(), lr=config["lr"], weight_decay=config["weight_decay"])
    stats = {"mean": torch.tensor(config["mean"]), "std": torch.tensor(config["std"])}
    return Components(models={"vae": vae}, optimizers={"adamw": opt}, frozen=stats)


def step(batch: dict, ctx: StepContext) -> dict[str, torch.Tensor]:
    cfg = ctx.config
    losses = vae_loss(ctx.models["vae"], batch["motion"], batch["length"], ctx.frozen["mean"], ctx.frozen["std"],
                      cfg["joints_num"], kl_weight=cfg["kl_weight"], joint_weight=cfg["joint_weight"],
                      joint_space=cfg["joint_space"], joint_beta=cfg["joint_beta"],
                      heading_weight=cfg["heading_weight"])
    ctx.update(losses["total"])
    return {"loss": losses["total"].detach(), "feature": losses["feature"].detach(),
            "joint": losses["joint"].detach(), "heading": losses["heading"].detach(), "kl": losses["kl"].detach()}


SECTION = "train_vae"
SECTION_KEYS = ("lr", "weight_decay", "crop_frames", "kl_weight", "joint_weight", "joint_space", "joint_beta",
                "heading_weight", "model", "loop")


def check_section(params: dict[str, Any]) -> None:
    """The ``train_vae`` section checked before any work (its ``loop`` group is the skeleton's); a ValueError
    naming the key, its value and what is allowed."""
    cfg = check_keys(params[SECTION], SECTION, SECTION_KEYS)
    check_number(cfg, "lr", SECTION, low=0.0, low_open=True)
    for key in ("weight_decay", "kl_weight", "joint_weight", "heading_weight"):
        check_number(cfg, key, SECTION, low=0.0)
    check_number(cfg, "joint_beta", SECTION, low=0.0, low_open=True)
    check_number(cfg, "crop_frames", SECTION, low=1, integer=True)
    check_choice(cfg, "joint_space", SECTION, choices=("global", "root"))
    model = cfg["model"]
    check_fields(model, MotionVAEConfig, f"{SECTION}.model", exclude=("feature_dim",))
    check_model(model, crop_frames=cfg["crop_frames"], below=params["data"]["feature_frames_below"])
    check_heads(model, "heads", f"{SECTION}.model", width=MotionVAEConfig(**model).width)


def check_model(model: dict[str, Any], crop_frames: Any, below: Any) -> None:
    """The ranges of ``train_vae.model`` (its types are :func:`check_fields`'; a key left out takes its
    :class:`~models.vae.MotionVAEConfig` default), as :class:`~models.vae.MotionVAE` needs them: positive sizes,
    an odd skip-transformer depth, dropout in [0, 1), a finite log-variance offset, and a learned positional
    table that holds the encoder's ``2 latent_tokens`` and the longest motion it encodes: a training crop
    (``crop_frames``) or a whole motion of the evaluation and of MLD's latents (below
    ``data.feature_frames_below`` frames)."""
    where, given = f"{SECTION}.model", {**asdict(MotionVAEConfig()), **model}
    for key in ("latent_tokens", "latent_dim", "ff_dim", "max_len"):
        check_number(given, key, where, low=1, integer=True)
    if given["hidden_dim"] is not None:  # null: the width is latent_dim
        check_number(given, "hidden_dim", where, low=1, integer=True)
    check_odd(given, "layers", where)  # models.transformer.SkipTransformer: 2K + 1
    check_number(given, "dropout", where, low=0.0, high=1.0, high_open=True)
    offset = given["logvar_offset"]
    if isinstance(offset, float) and not math.isfinite(offset):
        refuse(f"{where}.logvar_offset: expected a finite number, got {offset!r}")
    tokens, positions = given["latent_tokens"], given["max_len"]
    if given["pos_encoding"] == "learned" and all(type(n) is int for n in (tokens, positions, crop_frames, below)):
        needed = 2 * tokens + max(crop_frames, below - 1)
        if positions < needed:
            refuse(f"{where}.max_len: the learned positional encoding holds {positions} positions, the encoder "
                   f"reads 2 x latent_tokens + the longest motion (crop_frames, or data.feature_frames_below - 1 "
                   f"frames) = {needed}")


def stage_config(params: dict[str, Any]) -> dict[str, Any]:
    """The stage's loop-config keys: absolute paths, the dataset statistics and the model sizes."""
    cfg = params["train_vae"]
    store = FeatureStore(repo_path(params, "features.out"))
    return {
        "features_dir": str(store.path), "mean": store.mean.tolist(), "std": store.std.tolist(),
        "joints_num": store.joints_num, "crop_frames": cfg["crop_frames"],
        "model": {**cfg["model"], "feature_dim": store.feature_dim}, "lr": cfg["lr"],
        "weight_decay": cfg["weight_decay"], "kl_weight": cfg["kl_weight"], "joint_weight": cfg["joint_weight"],
        "joint_space": cfg["joint_space"], "joint_beta": cfg["joint_beta"], "heading_weight": cfg["heading_weight"],
    }


STAGE = TrainingStage(
    name="train_vae", module=__name__, spec=TrainSpec(build=build, dataset=dataset, step=step, collate=collate_trimmed),
    config=stage_config, inputs=("features_dir",),
    params=(SECTION, "data.feature_frames_below", "features.out", "paths", "ray"), check=check_section,
)


def sweep_loop_config(params: dict[str, Any]) -> dict[str, Any]:
    """A sweep trial's loop config (its values applied to ``params``, checked as the stage checks them)."""
    check_section(params)
    return loop_config(STAGE, params)


def sweep_target(params: dict[str, Any]) -> SweepTarget:
    """``python -m stages.sweep train_vae``: trials ranked by the validation MPJPE of their reconstructions."""
    from pipelines.sweep import SweepTarget  # imports Ray Tune: only when sweeping
    from pipelines.validation import vae_scores  # evaluation code: only when sweeping

    return SweepTarget(stage="train_vae", spec=STAGE.spec, loop_config=sweep_loop_config, validate=vae_scores,
                       metric="val_MPJPE_mm", mode="min", checks=checks(STAGE), module=STAGE.module,
                       inputs=STAGE.inputs)


if __name__ == "__main__":
    main(STAGE)
