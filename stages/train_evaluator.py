"""Stage ``train_evaluator``: the T2M text-motion matching model every metric is measured with.

``python -m stages.train_evaluator [key=value ...]`` trains, as three Ray Train jobs through the
one runner (reference humanml3d_eval.md B.3 for the first two):

1. the movement autoencoder (conv encoder + decoder) on random ``movement_window``-frame windows,
   loss L1 + 0.001 sparsity + 0.001 smoothness -> ``artifacts/train_evaluator_movement/``
   (runner settings ``train_evaluator.movement_loop``);
2. the text and motion encoders on (caption, cropped motion) pairs with the movement encoder
   frozen, contrastive loss with margin 10 and batch-shifted negatives ->
   ``artifacts/train_evaluator/`` (runner settings ``train_evaluator.loop``);
3. the action recogniser of the action-to-motion protocol (a GRU over joint positions, HumanAct12
   style; :mod:`pipelines.recogniser`) on random crops of the action-labelled training motions,
   cross-entropy -> ``artifacts/train_evaluator_recogniser/`` (params ``train_evaluator.recogniser``,
   runner settings ``train_evaluator.recogniser.loop``).

The vocabulary (built from the training captions' word/POS tokens), the network sizes and the
evaluator's own normalisation statistics travel in the saved model's config, so
:func:`pipelines.evaluation.load_evaluator` rebuilds it from ``model.pt`` alone.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from data.evaluator_data import CaptionMotionPairs, MovementWindows
from data.vocab import WordVocab, load_glove
from models.evaluator import (
    PROFILE_SIZES,
    UNIT_LENGTH,
    EvaluatorConfig,
    MovementAutoencoder,
    T2MEvaluator,
    contrastive_loss,
    movement_ae_loss,
)
from pipelines.checkpoint import load_final_model
from pipelines.cli import artifacts_dir, param, repo_path, run_main
from pipelines.config import check_choice, check_keys, check_number, check_type, is_integer, refuse
from pipelines.evaluation import build_evaluator
from pipelines.feature_store import FeatureStore
from pipelines.recogniser import GROUP as RECOGNISER_GROUP
from pipelines.recogniser import SPEC as RECOGNISER_SPEC
from pipelines.recogniser import check_section as check_recogniser
from pipelines.recogniser import missing_actions, recogniser_config
from pipelines.runner import Components, StepContext, TrainSpec, ray_connection
from pipelines.stage import TrainingStage, checks, loop_config, run_fingerprint, train, train_unless_skipped

if TYPE_CHECKING:
    from pipelines.sweep import SweepTarget

SECTION = "train_evaluator"
PARAMS = (SECTION, "features.out", "paths", "ray")
SECTION_KEYS = ("profile", "lr", "margin", "max_words", "min_word_count", "glove_path", "movement_window",
                "movement_loop", "loop", "recogniser")


def _new_evaluator(config: dict) -> T2MEvaluator:
    word_vectors = None
    if config.get("glove_path"):
        word_vectors = torch.from_numpy(load_glove(config["glove_path"], WordVocab.from_dict(config["vocab"])))
    model_cfg = EvaluatorConfig.from_dict(config["model"])
    return build_evaluator(model_cfg, config["mean"], config["std"], word_vectors)


def build_movement(config: dict) -> Components:
    """The movement autoencoder: only the movement encoder and the decoder train (and require grad, so that
    DistributedDataParallel does not wait for gradients of the evaluator's unused parts)."""
    model = MovementAutoencoder(_new_evaluator(config))
    model.requires_grad_(False)
    trained = [model.evaluator.movement_encoder, model.decoder]
    for module in trained:
        module.requires_grad_(True)
    opt = torch.optim.Adam([p for module in trained for p in module.parameters()], lr=config["lr"])
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


def _common_config(params: dict[str, Any]) -> dict[str, Any]:
    """Keys both runs share: paths, statistics, the vocabulary of the training captions, network sizes."""
    cfg = params["train_evaluator"]
    store = FeatureStore(repo_path(params, "features.out"))
    items = store.split("train")
    vocab = WordVocab.build([tokens for item in items for tokens in item.tokens], min_count=cfg["min_word_count"])
    model = EvaluatorConfig.for_profile(cfg["profile"], vocab_size=len(vocab), feature_dim=store.feature_dim)
    return {"features_dir": str(store.path), "lr": cfg["lr"], "model": model.to_dict(), "vocab": vocab.to_dict(),
            "mean": store.mean.tolist(), "std": store.std.tolist(), "glove_path": cfg["glove_path"],
            "max_words": cfg["max_words"]}


def movement_config(params: dict[str, Any]) -> dict[str, Any]:
    return _common_config(params) | {"movement_window": params["train_evaluator"]["movement_window"]}


def matching_config(params: dict[str, Any]) -> dict[str, Any]:
    return _common_config(params) | {"margin": params["train_evaluator"]["margin"],
                                     "movement_dir": str(artifacts_dir(params) / "train_evaluator_movement")}


def check_section(params: dict[str, Any]) -> None:
    """The ``train_evaluator`` section less its loop groups and ``recogniser`` (each checked by its own
    run), before any work; a ValueError naming the key, its value and what is allowed."""
    cfg = check_keys(params[SECTION], SECTION, SECTION_KEYS)
    check_choice(cfg, "profile", SECTION, choices=sorted(PROFILE_SIZES))
    check_number(cfg, "lr", SECTION, low=0.0, low_open=True)
    check_number(cfg, "margin", SECTION, low=0.0)
    for key in ("max_words", "min_word_count", "movement_window"):
        check_number(cfg, key, SECTION, low=1, integer=True)
    window = cfg["movement_window"]  # the movement encoder downsamples by UNIT_LENGTH (T2MEvaluator.autoencode)
    if is_integer(window) and window >= 1 and window % UNIT_LENGTH:
        refuse(f"{SECTION}.movement_window: expected a multiple of {UNIT_LENGTH} (the movement encoder's unit "
               f"length), got {window}")
    check_type(cfg, "glove_path", SECTION, kind=str, nullable=True)


MOVEMENT = TrainingStage(
    name="train_evaluator_movement", module=__name__, params=PARAMS, config=movement_config,
    spec=TrainSpec(build=build_movement, dataset=MovementWindows, step=movement_step),
    inputs=("features_dir",), loop_group="train_evaluator.movement_loop", check=check_section,
)
MATCHING = TrainingStage(
    name="train_evaluator", module=__name__, params=PARAMS, config=matching_config,
    spec=TrainSpec(build=build_matching, dataset=CaptionMotionPairs, step=matching_step),
    inputs=("features_dir", "movement_dir"),
)
RECOGNISER = TrainingStage(
    name="train_evaluator_recogniser", module=__name__, params=PARAMS, config=recogniser_config,
    spec=RECOGNISER_SPEC, inputs=("features_dir",), loop_group="train_evaluator.recogniser.loop",
    check=lambda params: check_recogniser(param(params, RECOGNISER_GROUP)), skip=missing_actions,
)


def run(params: dict[str, Any]) -> Path:
    """Train the evaluator's two parts and the action recogniser (three runs on one Ray connection);
    returns the evaluator's output directory."""
    with ray_connection(params["ray"]):
        train(MOVEMENT, params)
        out = train(MATCHING, params).out_dir
        train_unless_skipped(RECOGNISER, params)
    return out


# --------------------------------------------------------------------------- sweeps


def movement_prerequisite(params: dict[str, Any], work_dir: Path, storage: str) -> dict:
    """Train the movement autoencoder once (under ``work_dir``) for every sweep trial to build on."""
    from pipelines.sweep import train_once  # imports Ray Tune: only when sweeping

    config = loop_config(MOVEMENT, params)
    out = train_once(MOVEMENT.name, MOVEMENT.spec, config, params["ray"], work_dir / MOVEMENT.name, storage,
                     fingerprint=run_fingerprint(MOVEMENT.module, MOVEMENT.inputs, config))
    return {"movement_dir": str(out.resolve())}


def matching_loop_config(params: dict[str, Any]) -> dict[str, Any]:
    """The matching run's loop config (what sweep trials vary)."""
    return loop_config(MATCHING, params)


def sweep_target(params: dict[str, Any]) -> SweepTarget:
    """``python -m stages.sweep train_evaluator``: trials vary the matching run on one movement encoder,
    ranked by their own validation R-precision (top 3)."""
    from pipelines.sweep import SweepTarget  # imports Ray Tune: only when sweeping
    from pipelines.validation import evaluator_scores  # evaluation code: only when sweeping

    return SweepTarget(stage="train_evaluator", spec=MATCHING.spec, loop_config=matching_loop_config,
                       prerequisite=movement_prerequisite, validate=evaluator_scores,
                       metric="val_R_precision_top3", mode="max", checks=[*checks(MATCHING), check_section],
                       module=MATCHING.module, inputs=("features_dir",))  # movement_dir: the prerequisite's


def main(argv: Sequence[str] | None = None) -> None:
    """``python -m stages.train_evaluator [key=value ...] [--cfg] [--help]``: every part's params checked first."""
    run_main(SECTION, run, PARAMS, argv, checks=[*checks(MOVEMENT), *checks(MATCHING), *checks(RECOGNISER)])


if __name__ == "__main__":
    main()
