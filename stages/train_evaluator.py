"""Stage ``train_evaluator``: the T2M text-motion matching model every metric is measured with.

``python -m stages.train_evaluator [key=value ...]`` trains, as two Ray Train jobs through the
one runner (reference humanml3d_eval.md B.3):

1. the movement autoencoder (conv encoder + decoder) on random ``movement_window``-frame windows,
   loss L1 + 0.001 sparsity + 0.001 smoothness -> ``artifacts/train_evaluator_movement/``;
2. the text and motion encoders on (caption, cropped motion) pairs with the movement encoder
   frozen, contrastive loss with margin 10 and batch-shifted negatives ->
   ``artifacts/train_evaluator/``.

The vocabulary (built from the training captions' word/POS tokens), the network sizes and the
evaluator's own normalisation statistics travel in the saved model's config, so
:func:`pipelines.evaluation.load_evaluator` rebuilds it from ``model.pt`` alone.

Item sampling uses the process-global torch RNG, which the runner seeds per rank and saves in
every checkpoint, so resumed runs draw the same captions and crops (``num_data_workers`` 0).
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import nn
from torch.utils.data import Dataset

from data.store import read_split
from data.vocab import WordVocab, load_glove
from models.evaluator import EvaluatorConfig, T2MEvaluator, contrastive_loss, movement_ae_loss
from pipelines.checkpoint import load_final_model
from pipelines.config import REPO_ROOT, load_params
from pipelines.evaluation import build_evaluator
from pipelines.runner import Components, StepContext, TrainSpec, run_training

if TYPE_CHECKING:
    from pipelines.sweep import SweepTarget

RUNNER_KEYS = ("seed", "batch_size", "grad_clip", "log_every", "lr_schedule", "warmup_steps")


# --------------------------------------------------------------------------- data


def _crop(features: np.ndarray, length: int) -> np.ndarray:
    """A random ``length``-frame window of ``features`` (torch global RNG)."""
    start = int(torch.randint(0, features.shape[0] - length + 1, ()).item())
    return features[start : start + length]


class MovementWindows(Dataset):
    """Random fixed-size windows of training motions: ``{"window": (W, D) raw features}``."""

    def __init__(self, config: dict) -> None:
        items = read_split(Path(config["features_dir"]) / "train.parquet")
        self.window = config["movement_window"]
        self.motions = [item.features for item in items if item.length >= self.window]
        if not self.motions:
            raise ValueError(f"no training motion has {self.window} frames for the movement autoencoder")

    def __len__(self) -> int:
        return len(self.motions)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        return {"window": torch.from_numpy(_crop(self.motions[index], self.window).copy())}


class CaptionMotionPairs(Dataset):
    """One random caption and a reference-style crop (length rounded to 4) of each training item.

    Returns ``word_ids`` (22,), ``pos`` (22, 15), ``sent_len``, ``motion`` (P, D) raw features
    zero-padded to P (the longest item rounded up to 4) and ``length``.
    """

    def __init__(self, config: dict) -> None:
        self.items = read_split(Path(config["features_dir"]) / "train.parquet")
        self.vocab = WordVocab.from_dict(config["vocab"])
        self.max_words = config["max_words"]
        self.padded = 4 * -(-max(item.length for item in self.items) // 4)

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        item = self.items[index]
        caption = int(torch.randint(0, len(item.captions), ()).item())
        word_ids, pos, sent_len = self.vocab.encode_tokens(item.tokens[caption], self.max_words)
        units = item.length // 4 - int(torch.rand(()).item() < 1 / 3)
        length = max(units, 1) * 4
        motion = np.zeros((self.padded, item.features.shape[1]), np.float32)
        motion[:length] = _crop(item.features, length)
        return {"word_ids": torch.from_numpy(word_ids), "pos": torch.from_numpy(pos),
                "sent_len": torch.tensor(sent_len), "motion": torch.from_numpy(motion),
                "length": torch.tensor(length)}


# --------------------------------------------------------------------------- models and steps


class MovementAutoencoder(nn.Module):
    """The evaluator's movement encoder with a decoder, for pretraining (DDP needs one forward)."""

    def __init__(self, evaluator: T2MEvaluator) -> None:
        super().__init__()
        self.evaluator = evaluator
        self.decoder = evaluator.make_movement_decoder()

    def forward(self, window: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(B, W, D) raw -> (reconstruction, normalised target, latents), (B, W, D), (B, W, D), (B, W/4, C)."""
        x = self.evaluator.normalize(window)
        recon, z = self.evaluator.autoencode(x, self.decoder)
        return recon, x, z


def _new_evaluator(config: dict) -> T2MEvaluator:
    word_vectors = None
    if config.get("glove_path"):
        word_vectors = torch.from_numpy(load_glove(config["glove_path"], WordVocab.from_dict(config["vocab"])))
    model_cfg = EvaluatorConfig.from_dict(config["model"])
    return build_evaluator(model_cfg, config["mean"], config["std"], word_vectors)


def build_movement(config: dict) -> Components:
    model = MovementAutoencoder(_new_evaluator(config))
    opt = torch.optim.Adam(list(model.evaluator.movement_encoder.parameters()) + list(model.decoder.parameters()),
                           lr=config["lr"])
    return Components(models={"movement": model}, optimizers={"adam": opt})


def movement_step(batch: dict, ctx: StepContext) -> dict[str, torch.Tensor]:
    recon, target, z = ctx.models["movement"](batch["window"])
    loss = movement_ae_loss(recon, target, z)
    ctx.update(loss)
    return {"loss": loss.detach()}


def build_matching(config: dict) -> Components:
    evaluator = _new_evaluator(config)
    movement = load_final_model(Path(config["movement_dir"]))["models"]["movement"]
    prefix = "evaluator.movement_encoder."
    encoder = {key[len(prefix) :]: value for key, value in movement.items() if key.startswith(prefix)}
    evaluator.movement_encoder.load_state_dict(encoder)
    evaluator.freeze_movement_encoder()
    opt = torch.optim.Adam([p for p in evaluator.parameters() if p.requires_grad], lr=config["lr"])
    return Components(models={"evaluator": evaluator}, optimizers={"adam": opt})


def matching_step(batch: dict, ctx: StepContext) -> dict[str, torch.Tensor]:
    x = ctx.unwrap("evaluator").normalize(batch["motion"])
    text, motion = ctx.models["evaluator"](batch["word_ids"], batch["pos"], batch["sent_len"], x, batch["length"])
    loss = contrastive_loss(text, motion, margin=ctx.config["margin"])
    ctx.update(loss)
    return {"loss": loss.detach()}


MOVEMENT = TrainSpec(build=build_movement, dataset=MovementWindows, step=movement_step)
MATCHING = TrainSpec(build=build_matching, dataset=CaptionMotionPairs, step=matching_step)


# --------------------------------------------------------------------------- driver


def loop_configs(params: dict[str, Any]) -> tuple[dict, dict]:
    """The two runs' loop configs from params (absolute paths; vocab and stats included)."""
    cfg = params["train_evaluator"]
    features = (REPO_ROOT / params["features"]["out"]).resolve()
    items = read_split(features / "train.parquet")
    vocab = WordVocab.build([tokens for item in items for tokens in item.tokens], min_count=cfg["min_word_count"])
    mean, std = np.load(features / "mean.npy"), np.load(features / "std.npy")
    model = EvaluatorConfig.for_profile(cfg["profile"], vocab_size=len(vocab), feature_dim=int(mean.shape[0]))
    common = {key: cfg[key] for key in RUNNER_KEYS} | {
        "features_dir": str(features), "lr": cfg["lr"], "model": model.to_dict(), "vocab": vocab.to_dict(),
        "mean": mean.tolist(), "std": std.tolist(), "glove_path": cfg["glove_path"], "max_words": cfg["max_words"],
    }
    movement = common | {"max_steps": cfg["movement_steps"], "movement_window": cfg["movement_window"]}
    out = REPO_ROOT / params["paths"]["artifacts"]
    matching = common | {"max_steps": cfg["matching_steps"], "margin": cfg["margin"],
                         "movement_dir": str((out / "train_evaluator_movement").resolve())}
    return movement, matching


def run(params: dict[str, Any]) -> Path:
    """Train both parts; returns the evaluator's output directory."""
    movement, matching = loop_configs(params)
    storage = str((REPO_ROOT / params["paths"]["ray_storage"]).resolve())
    out = REPO_ROOT / params["paths"]["artifacts"]
    run_training("train_evaluator_movement", MOVEMENT, movement, params["ray"], out / "train_evaluator_movement",
                 storage)
    result = run_training("train_evaluator", MATCHING, matching, params["ray"], out / "train_evaluator", storage)
    print(f"train_evaluator: {result.metrics.get('loss', float('nan')):.4f} final loss -> {result.out_dir}")
    return result.out_dir


# --------------------------------------------------------------------------- sweeps


def matching_loop_config(params: dict[str, Any]) -> dict:
    """The matching run's loop config (what sweep trials vary)."""
    return loop_configs(params)[1]


def movement_prerequisite(params: dict[str, Any], work_dir: Path, storage: str) -> dict:
    """Train the movement autoencoder once (under ``work_dir``) for every sweep trial to build on."""
    from pipelines.sweep import train_once  # imports Ray Tune: only when sweeping

    movement, _ = loop_configs(params)
    out = train_once("train_evaluator_movement", MOVEMENT, movement, params["ray"],
                     work_dir / "train_evaluator_movement", storage)
    return {"movement_dir": str(out.resolve())}


def sweep_target(params: dict[str, Any]) -> SweepTarget:
    """``python -m stages.sweep train_evaluator``: trials vary the matching run on one movement encoder."""
    from pipelines.sweep import SweepTarget  # imports Ray Tune: only when sweeping

    return SweepTarget(stage="train_evaluator", spec=MATCHING, loop_config=matching_loop_config,
                       prerequisite=movement_prerequisite)


def main(argv: Sequence[str] | None = None) -> None:
    try:
        run(load_params(argv))
    except (ValueError, FileNotFoundError) as err:
        sys.exit(f"train_evaluator: {err}")


if __name__ == "__main__":
    main()
