"""Stage ``train_emdm``: EMDM, a conditional denoising-diffusion GAN for few-step text-to-motion.

``python -m stages.train_emdm [key=value ...]`` trains :class:`models.emdm.EMDMGenerator` and
:class:`models.emdm.EMDMDiscriminator` through the one runner, as two models with two Adam
optimisers (betas (0.5, 0.9), no weight decay; EMDM's code) and an EMA of the generator. The data
are the training motions of the feature store (normalised with its Mean/Std, random windows of
``crop_frames``), each with the pooled frozen embedding of one of its captions. One runner step is
DDGAN's iteration (EMDM App. C.3, :mod:`models.emdm` docstring items 5-7):

1. one D update: non-saturating softplus loss on a real pair ``(x_t, x_{t+1})`` and a fake ``x_t``
   posterior-sampled around ``G(x_{t+1}, t, z, c)``; R1 (gamma ``r1_gamma``) on the real ``x_t``
   every ``r1_interval`` steps (lazy regularisation, weighted by the interval; the runner's step
   count decides when, so a resumed run regularises on the same steps);
2. one G update with D frozen: non-saturating adversarial loss plus ``R * geo`` (Eqs. 7-12), R =
   ``geometric_weight`` (null: 100 for text, 1 for action), lambda = ``geometric_lambda``.

All randomness (t, pairs, z, condition dropout) comes from the process-global torch RNG, which the
runner seeds per rank and checkpoints, so a resumed run is bit-identical to an uninterrupted one.
The runner's ``grad_clip`` applies to each optimiser separately, and its LR schedule to both (each
relative to its own learning rate). Writes ``artifacts/train_emdm/`` (model.pt with the generator,
the discriminator and the generator's EMA).

Conditions: ``text`` (the pooled caption embedding of the store's frozen encoder). ``action`` is a
valid value of ``train_emdm.condition`` but not wired yet (the store has no action labels): it is
an error for now. The stage trains on one Ray Train worker whatever ``ray.num_workers`` says (a
note is printed): the D step runs D twice and double-backpropagates for R1, which DDP's reducer
does not allow, and :mod:`models.emdm` reads the networks' ``config``, which a DDP wrapper hides.
"""

from __future__ import annotations

from dataclasses import fields
from typing import Any

import torch

from data.motion_dataset import MotionTextDataset, collate_trimmed
from models.emdm import (
    EMDMConfig,
    EMDMDiscriminator,
    EMDMGenerator,
    discriminator_step_losses,
    generator_step_losses,
    lazy_r1_scale,
)
from pipelines.cli import repo_path
from pipelines.feature_store import FeatureStore
from pipelines.runner import Components, StepContext, TrainSpec
from pipelines.stage import TrainingStage, main

#: Adam's betas for both networks (EMDM's and DDGAN's code).
ADAM_BETAS = (0.5, 0.9)
#: Keys of the ``train_emdm`` params section (``loop`` is the runner's, checked by the skeleton).
SECTION_KEYS = ("condition", "num_steps", "lr_g", "lr_d", "ema_decay", "geometric_weight", "geometric_lambda",
                "r1_gamma", "r1_interval", "p_uncond", "crop_frames", "model", "loop")
#: Keys of ``train_emdm.model``: the network sizes (the rest of :class:`EMDMConfig` comes from the store
#: and the training keys above).
MODEL_KEYS = ("width", "layers", "heads", "ff_dim", "dropout", "activation", "norm_first", "z_dim", "mapping_layers",
              "d_width", "d_layers", "d_heads", "d_ff_dim", "d_time_dim", "patch_frames")
CONDITIONS = ("text", "action")


def dataset(config: dict) -> MotionTextDataset:
    return MotionTextDataset(config["features_dir"], "train", config["mean"], config["std"], config["crop_frames"])


def build(config: dict) -> Components:
    model = EMDMConfig(**config["model"])
    generator, discriminator = EMDMGenerator(model), EMDMDiscriminator(model)
    opt_g = torch.optim.Adam(generator.parameters(), lr=config["lr_g"], betas=ADAM_BETAS)
    opt_d = torch.optim.Adam(discriminator.parameters(), lr=config["lr_d"], betas=ADAM_BETAS)
    return Components(
        models={"generator": generator, "discriminator": discriminator}, optimizers={"g": opt_g, "d": opt_d},
        ema={"generator": config["ema_decay"]} if config["ema_decay"] else {},
        frozen={"schedule": model.make_schedule(), "mean": torch.tensor(config["mean"]),
                "std": torch.tensor(config["std"])})


def step(batch: dict, ctx: StepContext) -> dict[str, torch.Tensor]:
    """One D update (with lazy R1 when ``ctx.step`` is due), then one G update with D frozen."""
    if ctx.world_size > 1:
        raise NotImplementedError("train_emdm runs on one worker (ray.num_workers: 1): its D step is not DDP-safe")
    generator, discriminator = ctx.models["generator"], ctx.models["discriminator"]
    schedule = ctx.frozen["schedule"]
    x0, lengths, cond = batch["motion"], batch["length"], batch["text"]

    d = discriminator_step_losses(generator, discriminator, schedule, x0, cond, lengths, ctx.step)
    ctx.update(d["total"], "d")

    discriminator.requires_grad_(False)  # G's loss needs dD/dx only; D's gradients would be thrown away
    try:
        g = generator_step_losses(generator, discriminator, schedule, x0, cond, lengths, ctx.frozen["mean"],
                                  ctx.frozen["std"])
        ctx.update(g["total"], "g")
    finally:
        discriminator.requires_grad_(True)

    out = {"loss": g["total"], "g_adv": g["adv"], "geo": g["geo"], "recon": g["recon"], "pos": g["pos"],
           "vel": g["vel"], "foot": g["foot"], "d_loss": d["real"] + d["fake"], "d_real": d["real"],
           "d_fake": d["fake"]}
    if lazy_r1_scale(ctx.step, generator.config.r1_interval) > 0:
        out["r1"] = d["r1"]  # only on R1 steps: the logged value is the mean over those
    return {key: value.detach() for key, value in out.items()}


# --------------------------------------------------------------------------------------------------
# params -> loop config
# --------------------------------------------------------------------------------------------------


def _number(cfg: dict[str, Any], key: str, *, low: float, high: float | None = None, low_open: bool = False,
            integer: bool = False) -> float:
    """``cfg[key]`` checked to be a number (an int if ``integer``) in its range; ValueError naming the key."""
    value = cfg[key]
    kinds = (int,) if integer else (int, float)
    bad_type = isinstance(value, bool) or not isinstance(value, kinds)
    if bad_type or value < low or (low_open and value == low) or (high is not None and value > high):
        bounds = f"{'>' if low_open else '>='} {low}" + ("" if high is None else f" and <= {high}")
        kind = "an integer" if integer else "a number"
        raise ValueError(f"train_emdm.{key}: expected {kind} {bounds}, got {value!r}")
    return value


def check_section(cfg: dict[str, Any]) -> None:
    """Validate the ``train_emdm`` section (the ``loop`` group is the skeleton's); ValueError naming the key."""
    if not isinstance(cfg, dict):
        raise ValueError(f"train_emdm: expected a mapping, got {cfg!r}")
    unknown, missing = sorted(set(cfg) - set(SECTION_KEYS)), [k for k in SECTION_KEYS if k not in cfg]
    if unknown or missing:
        raise ValueError(f"train_emdm: unknown key(s) {unknown}, missing key(s) {missing}")
    if cfg["condition"] not in CONDITIONS:
        raise ValueError(f"train_emdm.condition: expected one of {list(CONDITIONS)}, got {cfg['condition']!r}")
    if cfg["condition"] == "action":
        raise ValueError("train_emdm.condition: 'action' is not wired yet (the feature store has no action "
                         "labels); use 'text'")
    _number(cfg, "num_steps", low=1, integer=True)
    _number(cfg, "lr_g", low=0.0, low_open=True)
    _number(cfg, "lr_d", low=0.0, low_open=True)
    _number(cfg, "ema_decay", low=0.0, high=1.0)
    if cfg["geometric_weight"] is not None:
        _number(cfg, "geometric_weight", low=0.0)
    _number(cfg, "geometric_lambda", low=0.0)
    _number(cfg, "r1_gamma", low=0.0)
    _number(cfg, "r1_interval", low=1, integer=True)
    _number(cfg, "p_uncond", low=0.0, high=1.0)
    _number(cfg, "crop_frames", low=1, integer=True)
    model = cfg["model"]
    if not isinstance(model, dict):
        raise ValueError(f"train_emdm.model: expected a mapping, got {model!r}")
    unknown, missing = sorted(set(model) - set(MODEL_KEYS)), [k for k in MODEL_KEYS if k not in model]
    if unknown or missing:
        raise ValueError(f"train_emdm.model: unknown key(s) {unknown}, missing key(s) {missing}")


def model_config(cfg: dict[str, Any], feature_dim: int, text_dim: int) -> dict[str, Any]:
    """The :class:`EMDMConfig` of a checked section, as a plain dict (sampling guidance left out: it is
    ``sample.emdm_guidance``, a sampling setting)."""
    model = {**cfg["model"], "feature_dim": feature_dim, "condition": cfg["condition"], "text_dim": text_dim,
             "num_actions": 0, "p_uncond": cfg["p_uncond"], "r1_gamma": cfg["r1_gamma"],
             "r1_interval": cfg["r1_interval"], "geo_weight": cfg["geometric_weight"],
             "geo_lambda": cfg["geometric_lambda"], "num_steps": cfg["num_steps"]}
    try:
        checked = EMDMConfig(**model)
    except (TypeError, ValueError) as err:
        raise ValueError(f"train_emdm.model: {err}") from err
    if checked.width % checked.heads or checked.d_width % checked.d_heads:
        raise ValueError(f"train_emdm.model: width {checked.width} / d_width {checked.d_width} must be divisible "
                         f"by heads {checked.heads} / d_heads {checked.d_heads}")
    names = {f.name for f in fields(EMDMConfig)} - {"guidance"}
    return {f.name: getattr(checked, f.name) for f in fields(EMDMConfig) if f.name in names}


def stage_config(params: dict[str, Any]) -> dict[str, Any]:
    """The stage's loop-config keys: absolute paths, the dataset statistics, the model and the losses."""
    cfg = params["train_emdm"]
    check_section(cfg)
    store = FeatureStore(repo_path(params, "features.out"))
    return {
        "features_dir": str(store.path), "mean": store.mean.tolist(), "std": store.std.tolist(),
        "crop_frames": cfg["crop_frames"], "lr_g": float(cfg["lr_g"]), "lr_d": float(cfg["lr_d"]),
        "ema_decay": float(cfg["ema_decay"]),
        "model": model_config(cfg, store.feature_dim, int(store.text_encoder_meta["dim"])),
    }


STAGE = TrainingStage(
    name="train_emdm", module=__name__, config=stage_config,
    spec=TrainSpec(build=build, dataset=dataset, step=step, collate=collate_trimmed),
    inputs=("features_dir",), params=("train_emdm", "features.out", "paths", "ray"), max_workers=1,
)

if __name__ == "__main__":
    main(STAGE)
