"""EMDM's training recipe (``train_emdm`` and ``train_emdm_action``): data, networks, one GAN step, params.

The stages :mod:`stages.train_emdm` (text) and :mod:`stages.train_emdm_action` (action labels) are
:func:`training_stage` of their params sections; their docstrings describe the recipe.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import fields
from functools import partial
from typing import Any

import numpy as np
import torch

from data.motion_dataset import MotionTextDataset, collate_trimmed
from data.store import StoredItem
from models.diffusion import lag_moments, wiener_taps
from models.emdm import (
    EMDMConfig,
    EMDMDiscriminator,
    EMDMGenerator,
    action_from_text,
    discriminator_step_losses,
    generator_step_losses,
    lazy_r1_scale,
)
from pipelines.checkpoint import load_final_model
from pipelines.cli import artifacts_dir, repo_path
from pipelines.config import check_fields, check_heads, check_number, check_odd, dotted, is_integer, refuse
from pipelines.feature_store import FeatureStore
from pipelines.recogniser import ActionClips, action_classes, labelled_items, missing_actions
from pipelines.runner import Components, StepContext, TrainSpec
from pipelines.stage import TrainingStage

#: Adam's betas for both networks (EMDM's and DDGAN's code).
ADAM_BETAS = (0.5, 0.9)
#: Keys of the ``train_emdm`` params section (``loop`` is the runner's, checked by the skeleton).
SECTION_KEYS = ("condition", "num_steps", "lr_g", "lr_d", "ema_decay", "geometric_weight", "geometric_lambda",
                "foot_lambda", "r1_gamma", "r1_interval", "p_uncond", "crop_frames", "model", "loop")
#: The action section's one more key: ``init_from``, the text stage whose G and D start it, or null.
ACTION_KEYS = ("init_from",)
#: Keys of ``train_emdm.model``: the network sizes (the rest of :class:`EMDMConfig` comes from the store
#: and the training keys above).
MODEL_KEYS = ("width", "layers", "heads", "ff_dim", "dropout", "activation", "norm_first", "z_dim", "mapping_layers",
              "d_width", "d_layers", "d_heads", "d_ff_dim", "d_time_dim", "patch_frames", "overlap_out", "d_condition",
              "input_skip", "skip_kernel", "word_tokens", "text_norm")
#: Keys that decide the networks' weight shapes, which a warm start needs equal: every model key but the
#: two that shape no weight (``dropout``, and ``text_norm``, a fixed standardisation of the embedding).
SHAPE_KEYS = ("feature_dim", "num_steps") + tuple(k for k in MODEL_KEYS if k not in ("dropout", "text_norm"))
CONDITIONS = ("text", "action")


def dataset(config: dict) -> MotionTextDataset | ActionClips:
    """Text: every training motion with one of its captions. Action: the labelled single-action motions,
    whole (up to ``crop_frames``), with the index of their label in ``classes``."""
    if config["model"]["condition"] == "action":
        return ActionClips(config["features_dir"], config["classes"], config["mean"], config["std"],
                           config["crop_frames"])
    return MotionTextDataset(config["features_dir"], "train", config["mean"], config["std"], config["crop_frames"],
                             word_tokens=config["max_text_tokens"] if config["model"]["word_tokens"] else 0)


def build(config: dict) -> Components:
    """G (its input-skip filter set to the Wiener taps of ``skip_moments`` when it has one), D, their Adams;
    an action stage with ``init_dir`` starts G and D from that text stage's (:func:`warm_start`)."""
    model = EMDMConfig(**config["model"])
    generator, discriminator = EMDMGenerator(model), EMDMDiscriminator(model)
    if generator.skip is not None and generator.skip.ndim == 3:
        taps = wiener_taps(torch.tensor(config["skip_moments"]), model.make_schedule().alphas_cumprod[1:],
                           model.skip_kernel)
        with torch.no_grad():
            generator.skip.copy_(taps)
    if config.get("init_dir") is not None:
        warm_start(generator, discriminator, config)
    opt_g = torch.optim.Adam(generator.parameters(), lr=config["lr_g"], betas=ADAM_BETAS)
    opt_d = torch.optim.Adam(discriminator.parameters(), lr=config["lr_d"], betas=ADAM_BETAS)
    return Components(
        models={"generator": generator, "discriminator": discriminator}, optimizers={"g": opt_g, "d": opt_d},
        ema={"generator": config["ema_decay"]} if config["ema_decay"] else {},
        frozen={"schedule": model.make_schedule(), "mean": torch.tensor(config["mean"]),
                "std": torch.tensor(config["std"])})


def warm_start(generator: EMDMGenerator, discriminator: EMDMDiscriminator, config: dict) -> None:
    """Start the action G and D from the text stage in ``config["init_dir"]`` (:func:`models.emdm.action_from_text`):
    G from its EMA weights, D from its weights; label c from the :func:`class_captions` of class c's training
    motions."""
    payload = load_final_model(config["init_dir"])
    text_config = EMDMConfig(**payload["config"]["model"])
    items = labelled_items(FeatureStore(config["features_dir"]).split("train"), config["classes"])
    captions = [class_captions([item for item in items if item.action == label]) for label in config["classes"]]
    action_from_text(generator, payload["ema"].get("generator") or payload["models"]["generator"], text_config,
                     captions)
    action_from_text(discriminator, payload["models"]["discriminator"], text_config, captions)


def class_captions(items: Sequence[StoredItem]) -> tuple[torch.Tensor, torch.Tensor]:
    """The captions of a class's ``items`` for :func:`models.emdm.action_from_text`: all their pooled
    embeddings (n, E), and the word-token states (m, token_dim) of the caption nearest their centre (the
    largest dot product of its unit-norm pooled embedding with the mean; the first on a tie), float32."""
    pooled = np.concatenate([item.text_pooled for item in items]).astype(np.float32)
    words = [tokens for item in items for tokens in item.text_tokens]
    nearest = int(np.argmax(pooled @ pooled.mean(0)))
    return torch.from_numpy(pooled), torch.from_numpy(np.asarray(words[nearest], np.float32))


def step(batch: dict, ctx: StepContext) -> dict[str, torch.Tensor]:
    """One D update (with lazy R1 when ``ctx.step`` is due), then one G update with D frozen."""
    generator, discriminator = ctx.models["generator"], ctx.models["discriminator"]
    schedule = ctx.frozen["schedule"]
    x0, lengths = batch["motion"], batch["length"]
    text = generator.config.condition == "text"
    cond = batch["text"] if text else batch["label"]
    words = (batch["tokens"], batch["token_mask"]) if generator.config.word_tokens and text else None

    d = discriminator_step_losses(generator, discriminator, schedule, x0, cond, lengths, ctx.step, words=words)
    ctx.update(d["total"], "d")

    discriminator.requires_grad_(False)  # G's loss needs dD/dx only; D's gradients would be thrown away
    try:
        g = generator_step_losses(generator, discriminator, schedule, x0, cond, lengths, ctx.frozen["mean"],
                                  ctx.frozen["std"], words=words)
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


def check_section(cfg: dict[str, Any], section: str = "train_emdm") -> None:
    """Validate a ``train_emdm``-like section (the ``loop`` group is the skeleton's); ValueError naming the key."""
    if not isinstance(cfg, dict):
        raise ValueError(f"{section}: expected a mapping, got {cfg!r}")
    if cfg.get("condition") not in CONDITIONS:
        raise ValueError(f"{section}.condition: expected one of {list(CONDITIONS)}, got {cfg.get('condition')!r}")
    keys = SECTION_KEYS + (ACTION_KEYS if cfg["condition"] == "action" else ())
    unknown, missing = sorted(set(cfg) - set(keys)), [k for k in keys if k not in cfg]
    if unknown or missing:
        raise ValueError(f"{section}: unknown key(s) {unknown}, missing key(s) {missing}")
    if cfg.get("init_from") is not None and (not isinstance(cfg["init_from"], str) or not cfg["init_from"]):
        raise ValueError(f"{section}.init_from: expected the name of a text EMDM stage (train_emdm) or null, "
                         f"got {cfg['init_from']!r}")
    check_number(cfg, "num_steps", section, low=1, integer=True)
    for key in ("lr_g", "lr_d"):
        check_number(cfg, key, section, low=0.0, low_open=True)
    check_number(cfg, "ema_decay", section, low=0.0, high=1.0)
    if cfg["geometric_weight"] is not None:
        check_number(cfg, "geometric_weight", section, low=0.0)
    check_number(cfg, "geometric_lambda", section, low=0.0)
    if cfg["foot_lambda"] is not None:
        check_number(cfg, "foot_lambda", section, low=0.0)
    check_number(cfg, "r1_gamma", section, low=0.0)
    check_number(cfg, "r1_interval", section, low=1, integer=True)
    check_number(cfg, "p_uncond", section, low=0.0, high=1.0)
    check_number(cfg, "crop_frames", section, low=1, integer=True)
    model = cfg["model"]
    if not isinstance(model, dict):
        raise ValueError(f"{section}.model: expected a mapping, got {model!r}")
    unknown, missing = sorted(set(model) - set(MODEL_KEYS)), [k for k in MODEL_KEYS if k not in model]
    if unknown or missing:
        raise ValueError(f"{section}.model: unknown key(s) {unknown}, missing key(s) {missing}")
    check_fields(model, EMDMConfig, f"{section}.model")  # types and choices
    check_model(model, f"{section}.model")
    check_heads(model, "heads", f"{section}.model", width=model["width"])
    check_heads(model, "d_heads", f"{section}.model", width=model["d_width"])


def check_model(model: dict[str, Any], where: str) -> None:
    """The ranges of a section's ``model`` group (every key of :data:`MODEL_KEYS` present, types checked), as
    :class:`models.emdm.EMDMGenerator` and :class:`models.emdm.EMDMDiscriminator` need them: positive sizes and
    depths, dropout in [0, 1), D's time sinusoid of at least one sin/cos pair, an even ``patch_frames`` for
    ``overlap_out`` and an odd ``skip_kernel``."""
    for key in ("width", "layers", "ff_dim", "z_dim", "mapping_layers", "d_width", "d_layers", "d_ff_dim",
                "patch_frames"):
        check_number(model, key, where, low=1, integer=True)
    check_number(model, "d_time_dim", where, low=2, integer=True)
    check_number(model, "dropout", where, low=0.0, high=1.0, high_open=True)
    patch = model["patch_frames"]
    if model["overlap_out"] is True and is_integer(patch) and patch % 2:
        refuse(f"{dotted(where, 'overlap_out')}: needs an even patch_frames, got {patch!r}")
    check_odd(model, "skip_kernel", where)


def model_config(cfg: dict[str, Any], feature_dim: int, text_dim: int, num_actions: int = 0,
                 section: str = "train_emdm", token_dim: int | None = None) -> dict[str, Any]:
    """The :class:`EMDMConfig` of a checked section, as a plain dict (sampling guidance left out: it is
    ``sample.emdm_guidance``, a sampling setting). ``model.text_norm`` holds for text only; an action G with
    ``model.word_tokens`` cross-attends to its label token (and to word slots, which :func:`stage_config` adds
    for a warm start)."""
    text = cfg["condition"] == "text"
    model = {**cfg["model"], "text_norm": cfg["model"]["text_norm"] and text,
             "feature_dim": feature_dim, "condition": cfg["condition"], "text_dim": text_dim,
             "num_actions": num_actions, "token_dim": token_dim or text_dim, "p_uncond": cfg["p_uncond"],
             "r1_gamma": cfg["r1_gamma"], "r1_interval": cfg["r1_interval"], "geo_weight": cfg["geometric_weight"],
             "geo_lambda": cfg["geometric_lambda"], "geo_foot_lambda": cfg["foot_lambda"],
             "num_steps": cfg["num_steps"]}
    try:
        checked = EMDMConfig(**model)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{section}.model: {err}") from err
    names = {f.name for f in fields(EMDMConfig)} - {"guidance"}
    return {f.name: getattr(checked, f.name) for f in fields(EMDMConfig) if f.name in names}


def stage_config(params: dict[str, Any], section: str = "train_emdm") -> dict[str, Any]:
    """The stage's loop-config keys: absolute paths, the dataset statistics, the model and the losses.

    Action conditioning adds ``classes``: the sorted labels of the training split's labelled motions
    (the action recogniser's classes, :func:`pipelines.recogniser.action_classes`), and ``init_dir``
    (:func:`warm_start_dir`).
    """
    cfg = params[section]
    check_section(cfg, section)
    store = FeatureStore(repo_path(params, "features.out"))
    classes: list[str] = []
    if cfg["condition"] == "action":
        classes = list(action_classes(store.split("train")))
        if len(classes) < 2:
            raise ValueError(f"{section}.condition: action needs labelled motions of at least 2 actions; "
                             f"{store.path} has {len(classes)} (does the dataset have actions.txt?)")
    encoder = store.text_encoder_meta
    out = {
        "features_dir": str(store.path), "mean": store.mean.tolist(), "std": store.std.tolist(),
        "max_text_tokens": int(encoder["max_length"]),
        "crop_frames": cfg["crop_frames"], "lr_g": float(cfg["lr_g"]), "lr_d": float(cfg["lr_d"]),
        "ema_decay": float(cfg["ema_decay"]),
        "model": model_config(cfg, store.feature_dim, int(encoder["dim"]), len(classes), section,
                              int(encoder["token_dim"])),
    }
    if out["model"]["input_skip"] and out["model"]["skip_kernel"] > 1:
        motions = [torch.from_numpy(x) for x in store.normalised_motions("train")]
        out["skip_moments"] = lag_moments(motions, out["model"]["skip_kernel"]).tolist()
    if cfg["condition"] == "action":
        out |= {"classes": classes, "init_dir": warm_start_dir(params, section, out["model"])}
        if out["init_dir"] is not None and out["model"]["word_tokens"]:  # word slots for the start's caption
            out["model"]["label_words"] = out["max_text_tokens"]
    return out


def warm_start_dir(params: dict[str, Any], section: str, model: dict[str, Any]) -> str | None:
    """The output folder of the text stage ``<section>.init_from`` names (None when null), checked to hold
    a text EMDM with the weight shapes of ``model``; a ValueError naming the key otherwise."""
    name = params[section]["init_from"]
    if name is None:
        return None
    folder = artifacts_dir(params) / name
    try:
        text_model = load_final_model(folder)["config"]["model"]
    except (OSError, KeyError, ValueError) as err:
        raise ValueError(f"{section}.init_from: {folder} holds no trained EMDM ({err}); run that stage first") from err
    if text_model.get("condition") != "text":
        raise ValueError(f"{section}.init_from: {folder} holds no text-conditioned EMDM")
    differ = [f"{key} {text_model.get(key)!r} != {model[key]!r}" for key in SHAPE_KEYS
              if text_model.get(key) != model[key]]
    if differ:
        raise ValueError(f"{section}.init_from: {name}'s networks differ from this section's: {', '.join(differ)}")
    return str(folder)


def training_stage(section: str, module: str) -> TrainingStage:
    """The EMDM training stage named ``section`` reading its params section of the same name."""
    return TrainingStage(
        name=section, module=module, config=partial(stage_config, section=section),
        spec=TrainSpec(build=build, dataset=dataset, step=step, collate=collate_trimmed, ddp=False),
        inputs=("features_dir", "init_dir"), params=(section, "features.out", "paths", "ray"),
        check=lambda params: check_section(params[section], section),
        skip=lambda params: missing_actions(params) if params[section]["condition"] == "action" else None,
    )
