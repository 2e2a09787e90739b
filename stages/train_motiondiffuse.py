"""Stage ``train_motiondiffuse``: MotionDiffuse, a text-conditioned DDPM with a linear-attention transformer.

``python -m stages.train_motiondiffuse [key=value ...]`` trains :class:`models.motiondiffuse.MotionDiffuse`
through the one runner: one model, Adam (lr ``lr``, PyTorch's default betas, no weight decay; the
released code), the runner's gradient-norm clip (``loop.grad_clip``; the code: 0.5) and LR schedule
(the code: constant), no EMA unless ``ema_decay`` > 0 (the code has none). One runner step is
Eq. 4: t ~ U{0..T-1}, eps ~ N(0, I), the masked squared error of the predicted noise
(:func:`models.motiondiffuse.training_loss`).

The data are the training motions of the feature store (normalised with its Mean/Std, random windows
of ``crop_frames``), each with the word-token states of one of its captions from the store's frozen
encoder (``tokens``/``token_mask``, at most the encoder's ``max_length`` tokens): the model's text
branch reads the tokens, not the pooled embedding. All randomness (caption, window, t, eps) comes from
the process-global torch RNG, which the runner seeds per rank and checkpoints, so a resumed run is
bit-identical to an uninterrupted one. Writes ``artifacts/train_motiondiffuse/`` (model.pt).

Section keys: ``lr``, ``ema_decay`` (0 = off), ``p_uncond`` (the caption dropout that classifier-free
guidance needs, ours: :mod:`models.motiondiffuse` item 13; the code: 0), ``crop_frames`` (<= ``model.max_len``),
``num_train_timesteps``, ``beta_start``, ``beta_end`` (linear betas, rescaled by 1000 / T as the code),
``model`` (the network sizes of :class:`models.motiondiffuse.MotionDiffuseConfig`; ``feature_dim`` and
``text_dim`` = the encoder's ``token_dim`` come from the store) and ``loop`` (the runner's).
"""

from __future__ import annotations

from dataclasses import asdict
from typing import Any

import torch

from data.motion_dataset import MotionTextDataset, collate_trimmed_words
from models.diffusion import lag_moments
from models.motiondiffuse import MotionDiffuse, MotionDiffuseConfig, training_loss
from pipelines.cli import repo_path
from pipelines.config import check_heads, check_number, is_integer, refuse
from pipelines.feature_store import FeatureStore
from pipelines.runner import Components, StepContext, TrainSpec
from pipelines.stage import TrainingStage, main

SECTION = "train_motiondiffuse"
#: The model's name in checkpoints (``model.pt``'s ``models`` / ``ema``).
MODEL = "denoiser"
#: Keys of the ``train_motiondiffuse`` params section (``loop`` is the runner's, checked by the skeleton).
SECTION_KEYS = ("lr", "ema_decay", "p_uncond", "crop_frames", "num_train_timesteps", "beta_start", "beta_end", "model",
                "loop")
#: Keys of ``train_motiondiffuse.model``: the network sizes (``feature_dim``/``text_dim`` come from the store,
#: the schedule from the section's keys above).
MODEL_KEYS = ("width", "layers", "heads", "ff_dim", "dropout", "text_layers", "text_heads", "text_ff_dim",
              "time_embed_mult", "max_len", "attention", "input_skip", "skip_kernel", "temporal_kernel", "patch_frames",
              "overlap_out")


def dataset(config: dict) -> MotionTextDataset:
    return MotionTextDataset(config["features_dir"], "train", config["mean"], config["std"], config["crop_frames"],
                             word_tokens=config["max_text_tokens"])


def build(config: dict) -> Components:
    """The model (its input-skip filter set from ``skip_moments`` when it has one), Adam, the schedule."""
    model = MotionDiffuse(config["model"])
    if model.skip_taps is not None:
        model.set_skip_taps(torch.tensor(config["skip_moments"]))
    optimizer = torch.optim.Adam(model.parameters(), lr=config["lr"])
    return Components(models={MODEL: model}, optimizers={MODEL: optimizer},
                      ema={MODEL: config["ema_decay"]} if config["ema_decay"] else {},
                      frozen={"schedule": model.config.make_schedule()})


def step(batch: dict, ctx: StepContext) -> dict[str, torch.Tensor]:
    """One Adam step on Eq. 4's masked epsilon MSE (t, eps, then the caption dropout, from the global RNG)."""
    loss = training_loss(ctx.models[MODEL], ctx.frozen["schedule"], batch["motion"], batch["length"],
                         batch["tokens"], batch["token_mask"], p_uncond=ctx.config["p_uncond"])
    ctx.update(loss)
    return {"loss": loss.detach()}


# --------------------------------------------------------------------------------------------------
# params -> loop config
# --------------------------------------------------------------------------------------------------


def check_section(cfg: dict[str, Any]) -> None:
    """Validate the ``train_motiondiffuse`` section (the ``loop`` group is the skeleton's); ValueError naming
    the key."""
    if not isinstance(cfg, dict):
        raise ValueError(f"{SECTION}: expected a mapping, got {cfg!r}")
    unknown, missing = sorted(set(cfg) - set(SECTION_KEYS)), [k for k in SECTION_KEYS if k not in cfg]
    if unknown or missing:
        raise ValueError(f"{SECTION}: unknown key(s) {unknown}, missing key(s) {missing}")
    check_number(cfg, "lr", SECTION, low=0.0, low_open=True)
    check_number(cfg, "ema_decay", SECTION, low=0.0, high=1.0, high_open=True)
    check_number(cfg, "p_uncond", SECTION, low=0.0, high=1.0, high_open=True)
    check_number(cfg, "crop_frames", SECTION, low=1, integer=True)
    steps = check_number(cfg, "num_train_timesteps", SECTION, low=1, integer=True)
    check_number(cfg, "beta_start", SECTION, low=0.0, low_open=True)
    check_number(cfg, "beta_end", SECTION, low=0.0, low_open=True)
    if cfg["beta_end"] <= cfg["beta_start"]:
        raise ValueError(f"{SECTION}.beta_end: must exceed beta_start ({cfg['beta_start']}), got {cfg['beta_end']!r}")
    if cfg["beta_end"] * 1000.0 / steps >= 1.0:
        raise ValueError(f"{SECTION}.beta_end: beta_end x 1000 / num_train_timesteps (the code's rescaling) must stay "
                         f"below 1, got {cfg['beta_end']} x 1000 / {steps}")
    model = cfg["model"]
    if not isinstance(model, dict):
        raise ValueError(f"{SECTION}.model: expected a mapping, got {model!r}")
    unknown, missing = sorted(set(model) - set(MODEL_KEYS)), [k for k in MODEL_KEYS if k not in model]
    if unknown or missing:
        raise ValueError(f"{SECTION}.model: unknown key(s) {unknown}, missing key(s) {missing}")
    for key in ("width", "layers", "heads", "ff_dim", "text_heads", "text_ff_dim", "time_embed_mult", "max_len",
                "patch_frames"):
        check_number(model, key, f"{SECTION}.model", low=1, integer=True)
    check_number(model, "text_layers", f"{SECTION}.model", low=0, integer=True)
    check_number(model, "dropout", f"{SECTION}.model", low=0.0, high=1.0, high_open=True)
    for key in ("input_skip", "overlap_out"):
        if not isinstance(model[key], bool):
            refuse(f"{SECTION}.model.{key}: expected true or false, got {model[key]!r}")
    if model["overlap_out"] is True and is_integer(model["patch_frames"]) and model["patch_frames"] % 2:
        refuse(f"{SECTION}.model.overlap_out: needs an even patch_frames, got {model['patch_frames']}")
    check_number(model, "skip_kernel", f"{SECTION}.model", low=1, integer=True)
    if is_integer(model["skip_kernel"]) and (model["skip_kernel"] % 2 == 0
                                         or (model["skip_kernel"] > 1 and model["input_skip"] is not True)):
        refuse(f"{SECTION}.model.skip_kernel: expected 1, or an odd number with input_skip true, got "
               f"{model['skip_kernel']!r} (input_skip {model['input_skip']!r})")
    kernel = model["temporal_kernel"]  # models.motiondiffuse item 12: 0 = no temporal convolution (the code)
    if not is_integer(kernel) or kernel < 0 or (kernel and kernel % 2 == 0):
        refuse(f"{SECTION}.model.temporal_kernel: expected 0 or an odd integer >= 1, got {kernel!r}")
    if model["attention"] not in ("linear", "softmax"):
        refuse(f"{SECTION}.model.attention: expected 'linear' or 'softmax', got {model['attention']!r}")
    for key in ("heads", "text_heads"):
        check_heads(model, key, f"{SECTION}.model", width=model["width"])
    if cfg["crop_frames"] > model["max_len"]:
        raise ValueError(f"{SECTION}.crop_frames: {cfg['crop_frames']} exceeds model.max_len {model['max_len']} "
                         "(the learned positional table)")


def model_config(cfg: dict[str, Any], feature_dim: int, text_dim: int) -> dict[str, Any]:
    """The :class:`MotionDiffuseConfig` of a checked section as a plain dict (every field, defaults included)."""
    values = {**cfg["model"], "feature_dim": feature_dim, "text_dim": text_dim,
              "num_train_timesteps": cfg["num_train_timesteps"], "beta_start": float(cfg["beta_start"]),
              "beta_end": float(cfg["beta_end"])}
    try:
        checked = MotionDiffuseConfig(**values)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{SECTION}.model: {err}") from err
    return asdict(checked)


def stage_config(params: dict[str, Any]) -> dict[str, Any]:
    """The stage's loop-config keys: absolute paths, the dataset statistics, the token length and the model."""
    cfg = params[SECTION]
    check_section(cfg)
    store = FeatureStore(repo_path(params, "features.out"))
    encoder = store.text_encoder_meta
    out = {
        "features_dir": str(store.path), "mean": store.mean.tolist(), "std": store.std.tolist(),
        "crop_frames": cfg["crop_frames"], "max_text_tokens": int(encoder["max_length"]), "lr": float(cfg["lr"]),
        "ema_decay": float(cfg["ema_decay"]), "p_uncond": float(cfg["p_uncond"]),
        "model": model_config(cfg, store.feature_dim, int(encoder["token_dim"])),
    }
    if out["model"]["input_skip"] and out["model"]["skip_kernel"] > 1:
        motions = [torch.from_numpy(x) for x in store.normalised_motions("train")]
        out["skip_moments"] = lag_moments(motions, out["model"]["skip_kernel"]).tolist()
    return out


STAGE = TrainingStage(
    name=SECTION, module=__name__, config=stage_config,
    spec=TrainSpec(build=build, dataset=dataset, step=step, collate=collate_trimmed_words),
    inputs=("features_dir",), params=(SECTION, "features.out", "paths", "ray"),
    check=lambda params: check_section(params[SECTION]),
)

if __name__ == "__main__":
    main(STAGE)
