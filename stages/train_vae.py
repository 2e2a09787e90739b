"""Stage ``train_vae``: MLD's motion VAE, the latent space of MLD, MotionLCM and its ControlNet.

``python -m stages.train_vae [key=value ...]`` trains :class:`models.vae.MotionVAE` on the
training motions of the feature store (normalised with its Mean/Std) through the one runner:
smooth-L1 on features and on joints (``recover_from_ric``; global as MLD, or root-aligned with
``joint_space: root``) + KL weight 1e-4, AdamW, cosine schedule with warm-up, gradient clipping.
Writes ``artifacts/train_vae/`` (model.pt, metrics.json, loss.csv/png).
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from data.motion_dataset import MotionTextDataset, collate_trimmed
from models.vae import MotionVAE, MotionVAEConfig, vae_loss
from pipelines.checkpoint import load_final_model
from pipelines.config import REPO_ROOT, load_params
from pipelines.runner import Components, StepContext, TrainSpec, run_training

RUNNER_KEYS = ("seed", "batch_size", "max_steps", "grad_clip", "log_every", "lr_schedule", "warmup_steps",
               "min_lr_ratio", "length_buckets")


def dataset(config: dict) -> MotionTextDataset:
    return MotionTextDataset(config["features_dir"], "train", config["mean"], config["std"], config["max_frames"])


def build(config: dict) -> Components:
    vae = MotionVAE(MotionVAEConfig(**config["model"]))
    opt = torch.optim.AdamW(vae.parameters(), lr=config["lr"], weight_decay=config["weight_decay"])
    stats = {"mean": torch.tensor(config["mean"]), "std": torch.tensor(config["std"])}
    return Components(models={"vae": vae}, optimizers={"adamw": opt}, frozen=stats)


def step(batch: dict, ctx: StepContext) -> dict[str, torch.Tensor]:
    cfg = ctx.config
    losses = vae_loss(ctx.models["vae"], batch["motion"], batch["length"], ctx.frozen["mean"], ctx.frozen["std"],
                      cfg["joints_num"], kl_weight=cfg["kl_weight"], joint_weight=cfg["joint_weight"],
                      joint_space=cfg["joint_space"])
    ctx.update(losses["total"])
    return {"loss": losses["total"].detach(), "feature": losses["feature"].detach(),
            "joint": losses["joint"].detach(), "kl": losses["kl"].detach()}


SPEC = TrainSpec(build=build, dataset=dataset, step=step, collate=collate_trimmed)


def loop_config(params: dict[str, Any]) -> dict[str, Any]:
    """The runner's loop config from params (absolute paths, dataset statistics included)."""
    cfg = params["train_vae"]
    features = (REPO_ROOT / params["features"]["out"]).resolve()
    mean, std = np.load(features / "mean.npy"), np.load(features / "std.npy")
    joints_num = (mean.shape[0] + 1) // 12
    model = {**cfg["model"], "feature_dim": int(mean.shape[0])}
    return {key: cfg[key] for key in RUNNER_KEYS} | {
        "features_dir": str(features), "mean": mean.tolist(), "std": std.tolist(), "joints_num": joints_num,
        "max_frames": cfg["max_frames"], "model": model, "lr": cfg["lr"], "weight_decay": cfg["weight_decay"],
        "kl_weight": cfg["kl_weight"], "joint_weight": cfg["joint_weight"], "joint_space": cfg["joint_space"],
    }


def load_vae(out_dir: Path) -> MotionVAE:
    """The trained VAE of a ``train_vae`` output folder, in eval mode."""
    payload = load_final_model(out_dir)
    vae = MotionVAE(MotionVAEConfig(**payload["config"]["model"]))
    vae.load_state_dict(payload["models"]["vae"])
    return vae.eval()


def run(params: dict[str, Any]) -> Path:
    out = REPO_ROOT / params["paths"]["artifacts"] / "train_vae"
    storage = str((REPO_ROOT / params["paths"]["ray_storage"]).resolve())
    result = run_training("train_vae", SPEC, loop_config(params), params["ray"], out, storage)
    print(f"train_vae: final loss {result.metrics.get('loss', float('nan')):.4f} -> {result.out_dir}")
    return result.out_dir


def main(argv: Sequence[str] | None = None) -> None:
    try:
        run(load_params(argv))
    except (ValueError, FileNotFoundError) as err:
        sys.exit(f"train_vae: {err}")


if __name__ == "__main__":
    main()
