"""Stage ``distill_lcm``: MotionLCM, the MLD teacher distilled into a few-step latent consistency model.

``python -m stages.distill_lcm [key=value ...]`` trains the student of :mod:`models.motionlcm`
through the one runner: the student starts as a copy of the frozen ``train_mld`` teacher (EMA
weights, word-token attention included) plus the zero-initialised guidance projection; the target
network is the runner's EMA of the student (rate ``ema_decay``, MotionLCM's μ), which starts equal
to the teacher. Each step samples latents from the cached frozen-VAE posteriors
(:mod:`pipelines.latent_cache`, as ``train_mld``), so no VAE pass is made. AdamW, cosine schedule
with warm-up, gradient clipping. Writes ``artifacts/distill_lcm/``.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from models.motionlcm import GUIDANCE_EMBED_DIM, lcm_distillation_loss, student_from_teacher
from models.vae import LatentDistribution
from pipelines.checkpoint import load_final_model
from pipelines.cli import artifacts_dir
from pipelines.config import check_choice, check_keys, check_number
from pipelines.latent_cache import collate_words, latent_dataset
from pipelines.mld_family import load_mld
from pipelines.runner import Components, StepContext, TrainSpec
from pipelines.stage import TrainingStage, checks, loop_config, main

if TYPE_CHECKING:
    from pipelines.sweep import SweepTarget


def build(config: dict) -> Components:
    teacher, schedule, _ = load_mld(Path(config["teacher_dir"]))
    student = student_from_teacher(teacher)
    opt = torch.optim.AdamW(student.parameters(), lr=config["lr"], weight_decay=config["weight_decay"])
    return Components(models={"student": student}, optimizers={"adamw": opt}, ema={"student": config["ema_decay"]},
                      frozen={"teacher": teacher.requires_grad_(False), "schedule": schedule})


def step(batch: dict, ctx: StepContext) -> dict[str, torch.Tensor]:
    cfg, teacher = ctx.config, ctx.frozen["teacher"]
    z0 = LatentDistribution(batch["mu"], batch["logvar"]).sample() / teacher.config.latent_scale
    losses = lcm_distillation_loss(
        ctx.models["student"], ctx.ema["student"].module, teacher, ctx.frozen["schedule"], z0, batch["text"],
        w_range=tuple(cfg["w_range"]), num_ddim_steps=cfg["num_ddim_steps"], kind=cfg["distance"],
        huber_c=cfg["huber_c"], text_tokens=batch.get("tokens"), text_mask=batch.get("token_mask"))
    ctx.update(losses["total"])
    return {"loss": losses["total"].detach()}


SECTION = "distill_lcm"
SECTION_KEYS = ("lr", "weight_decay", "ema_decay", "num_ddim_steps", "w_range", "distance", "huber_c", "loop")


def check_section(params: dict[str, Any]) -> None:
    """The ``distill_lcm`` section checked before any work (its ``loop`` group is the skeleton's); a ValueError
    naming the key, its value and what is allowed."""
    cfg = check_keys(params[SECTION], SECTION, SECTION_KEYS)
    check_number(cfg, "lr", SECTION, low=0.0, low_open=True)
    check_number(cfg, "weight_decay", SECTION, low=0.0)
    check_number(cfg, "ema_decay", SECTION, low=0.0, high=1.0)
    check_number(cfg, "num_ddim_steps", SECTION, low=1, integer=True)
    w_range = cfg["w_range"]
    if not (isinstance(w_range, list | tuple) and len(w_range) == 2
            and all(isinstance(w, int | float) and not isinstance(w, bool) for w in w_range)
            and 0 <= w_range[0] <= w_range[1]):
        raise ValueError(f"{SECTION}.w_range: expected [w_min, w_max] with 0 <= w_min <= w_max, got {w_range!r}")
    check_choice(cfg, "distance", SECTION, choices=("huber", "l2"))
    check_number(cfg, "huber_c", SECTION, low=0.0, low_open=True)


def stage_config(params: dict[str, Any]) -> dict[str, Any]:
    """The stage's loop-config keys: the teacher's data settings and the distillation settings."""
    check_section(params)  # again: a sweep trial changes the section
    cfg = params[SECTION]
    w_range = cfg["w_range"]
    teacher_dir = artifacts_dir(params) / "train_mld"
    teacher = load_final_model(teacher_dir)["config"]
    return {
        "teacher_dir": str(teacher_dir), "features_dir": teacher["features_dir"], "vae_dir": teacher["vae_dir"],
        "mean": teacher["mean"], "std": teacher["std"], "crop_frames": teacher["crop_frames"],
        "max_text_tokens": teacher["max_text_tokens"],
        "model": teacher["model"] | {"time_cond_dim": GUIDANCE_EMBED_DIM},
        "w_range": [float(w) for w in w_range],
        **{key: cfg[key] for key in ("lr", "weight_decay", "ema_decay", "num_ddim_steps", "distance", "huber_c")},
    }


STAGE = TrainingStage(
    name="distill_lcm", module=__name__, config=stage_config,
    spec=TrainSpec(build=build, dataset=latent_dataset, step=step, collate=collate_words),
    inputs=("teacher_dir", "features_dir", "vae_dir"), params=(SECTION, "paths", "ray"), check=check_section,
)



def sweep_loop_config(params: dict[str, Any]) -> dict[str, Any]:
    """A sweep trial's loop config (its values applied to ``params``)."""
    return loop_config(STAGE, params)


def sweep_target(params: dict[str, Any]) -> SweepTarget:
    """``python -m stages.sweep distill_lcm``: trials vary the distillation, scored by 1-step validation metrics."""
    from pipelines.sweep import SweepTarget  # imports Ray Tune: only when sweeping
    from pipelines.validation import motionlcm_scores  # evaluation code: only when sweeping

    return SweepTarget(stage="distill_lcm", spec=STAGE.spec, loop_config=sweep_loop_config,
                       validate=motionlcm_scores, metric="val_FID", mode="min", checks=checks(STAGE),
                       module=STAGE.module, inputs=STAGE.inputs)


if __name__ == "__main__":
    main(STAGE)
