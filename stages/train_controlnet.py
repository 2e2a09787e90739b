"""Stage ``train_controlnet``: MotionLCM's motion ControlNet for trajectory control (MotionLCM §3.3).

``python -m stages.train_controlnet [key=value ...]`` trains :class:`models.controlnet.MotionControlNet`
(a trainable copy of the ``distill_lcm`` student plus the trajectory encoder) through the one runner;
the student, the VAE and the noise schedule stay frozen. Each step samples latents from the cached
frozen-VAE posteriors (:func:`pipelines.latent_cache.control_dataset`), hints from the same windows'
global joints (:func:`data.control.training_mask`: one of ``train_joints`` per sample, a random number
of frames), t on the student's LCM solver grid (or uniform over ``timesteps``) and w over the
student's ``w_range``, and minimises Eq. 10 (``||ẑ0 - z0||² + control_weight · L_control``). AdamW,
cosine schedule with warm-up, gradient clipping. Writes ``artifacts/train_controlnet/``.
"""

from __future__ import annotations

from dataclasses import MISSING, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch

from data.control import joint_ids, training_mask
from data.features import recover_from_ric
from models.controlnet import ControlConfig, MotionControlNet, controlnet_loss
from models.vae import LatentDistribution
from pipelines.checkpoint import load_final_model
from pipelines.cli import artifacts_dir
from pipelines.config import ConfigError, check_fields, check_heads, check_keys, check_number, check_odd
from pipelines.feature_store import FeatureStore
from pipelines.latent_cache import collate_words, control_dataset
from pipelines.mld_family import load_mld, load_motionlcm, load_vae
from pipelines.runner import Components, StepContext, TrainSpec
from pipelines.stage import TrainingStage, main


def build(config: dict) -> Components:
    student = load_motionlcm(Path(config["student_dir"])).requires_grad_(False)
    _, schedule, _ = load_mld(Path(config["teacher_dir"]))
    controlnet = MotionControlNet(student, ControlConfig(**config["control"]))
    params = [p for p in controlnet.parameters() if p.requires_grad]
    opt = torch.optim.AdamW(params, lr=config["lr"], weight_decay=config["weight_decay"])
    vae = load_vae(Path(config["vae_dir"])).requires_grad_(False)
    return Components(models={"controlnet": controlnet}, optimizers={"adamw": opt},
                      frozen={"student": student, "vae": vae, "schedule": schedule})


def step(batch: dict, ctx: StepContext) -> dict[str, torch.Tensor]:
    cfg, student = ctx.config, ctx.frozen["student"]
    lengths = batch["length"]
    frames = int(lengths.max())
    joints = batch["joints"][:, :frames]
    mask = training_mask(lengths, frames, joints.shape[2], cfg["control"]["train_joints"]).to(joints.device)
    z0 = LatentDistribution(batch["mu"], batch["logvar"]).sample() / student.config.latent_scale
    losses = controlnet_loss(
        ctx.models["controlnet"], student, ctx.frozen["vae"], ctx.frozen["schedule"], z0, batch["text"], joints,
        mask, lengths, mean=torch.tensor(cfg["mean"], device=z0.device), std=torch.tensor(cfg["std"], device=z0.device),
        w_range=tuple(cfg["w_range"]), control_weight=cfg["control_weight"], num_ddim_steps=cfg["num_ddim_steps"],
        timesteps=cfg["timesteps"], text_dropout=cfg["text_dropout"], text_tokens=batch.get("tokens"),
        text_mask=batch.get("token_mask"))
    ctx.update(losses["total"])
    return {"loss": losses["total"].detach(), "latent": losses["latent"], "control": losses["control"]}


def hint_statistics(features_dir: Path) -> tuple[list[float], list[float]]:
    """Per-(joint, axis) mean and std of the training motions' global joint positions, (3J) each."""
    store = FeatureStore(features_dir)
    joints = np.concatenate([recover_from_ric(item.features, store.joints_num).reshape(item.length, -1)
                             for item in store.split("train")])
    return joints.mean(0).tolist(), np.maximum(joints.std(0), 1e-3).tolist()


SECTION = "train_controlnet"
SECTION_KEYS = ("lr", "weight_decay", "control_weight", "timesteps", "text_dropout", "train_joints", "encoder", "loop")


def check_section(params: dict[str, Any]) -> None:
    """The ``train_controlnet`` section checked before any work (its ``loop`` group is the skeleton's); a
    ValueError naming the key, its value and what is allowed."""
    cfg = check_keys(params[SECTION], SECTION, SECTION_KEYS)
    check_number(cfg, "lr", SECTION, low=0.0, low_open=True)
    check_number(cfg, "weight_decay", SECTION, low=0.0)
    check_number(cfg, "control_weight", SECTION, low=0.0)
    check_number(cfg, "text_dropout", SECTION, low=0.0, high=1.0)
    steps = cfg["timesteps"]  # the upper bound, the student's schedule length, is checked by the loss
    if steps is not None and (not isinstance(steps, list) or not steps
                              or not all(isinstance(t, int) and not isinstance(t, bool) and t >= 0 for t in steps)):
        raise ConfigError(f"{SECTION}.timesteps: expected null or a non-empty list of integers >= 0, got {steps!r}")
    joints = cfg["train_joints"]
    try:
        joint_ids(joints if isinstance(joints, list) else [joints])
    except (TypeError, ValueError) as err:
        raise ValueError(f"{SECTION}.train_joints: {err}") from err
    check_fields(cfg["encoder"], ControlConfig, f"{SECTION}.encoder",
                 exclude=("joints_num", "hint_mean", "hint_std", "train_joints"))
    check_encoder(cfg["encoder"])
    check_heads(cfg["encoder"], "heads", f"{SECTION}.encoder", width=cfg["encoder"]["dim"])


def check_encoder(encoder: dict[str, Any]) -> None:
    """The ranges of ``train_controlnet.encoder`` (its types are :func:`check_fields`'; a key left out takes its
    :class:`~models.controlnet.ControlConfig` default), as :class:`~models.controlnet.TrajectoryEncoder` needs
    them: positive sizes, an odd skip-transformer depth, dropout in [0, 1)."""
    where = f"{SECTION}.encoder"
    defaults = {f.name: f.default for f in fields(ControlConfig) if f.default is not MISSING}
    given = {**defaults, **encoder}
    for key in ("dim", "ff_dim", "patch_frames"):
        check_number(given, key, where, low=1, integer=True)
    check_odd(given, "layers", where)  # models.transformer.SkipTransformer: 2K + 1
    check_number(given, "dropout", where, low=0.0, high=1.0, high_open=True)


def stage_config(params: dict[str, Any]) -> dict[str, Any]:
    """The stage's loop-config keys: the student's data settings, the encoder and the loss settings."""
    cfg = params[SECTION]
    student_dir = artifacts_dir(params) / "distill_lcm"
    student = load_final_model(student_dir)["config"]
    mean, std = hint_statistics(Path(student["features_dir"]))
    joints_num = len(mean) // 3
    control = ControlConfig(joints_num=joints_num, hint_mean=mean, hint_std=std,
                            train_joints=joint_ids(cfg["train_joints"], joints_num), **cfg["encoder"])
    return {
        "student_dir": str(student_dir), "teacher_dir": student["teacher_dir"],
        **{key: student[key] for key in ("features_dir", "vae_dir", "mean", "std", "crop_frames", "max_text_tokens",
                                         "model", "w_range", "num_ddim_steps")},
        "control": control.to_dict(),
        **{key: cfg[key] for key in ("lr", "weight_decay", "control_weight", "timesteps", "text_dropout")},
    }


STAGE = TrainingStage(
    name="train_controlnet", module=__name__, config=stage_config,
    spec=TrainSpec(build=build, dataset=control_dataset, step=step, collate=collate_words),
    inputs=("student_dir", "teacher_dir", "features_dir", "vae_dir"), params=(SECTION, "paths", "ray"),
    check=check_section,
)


if __name__ == "__main__":
    main(STAGE)
