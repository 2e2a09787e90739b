"""Validation metrics for sweeps: a trial's generator scored on the validation split.

Sweeps rank trials by what a user cares about, not by training loss: :func:`generator_scores`
runs one replication of the evaluation protocol (:mod:`pipelines.evaluation`) on the ``val`` split
with the trained evaluator; :func:`motionlcm_scores` is ``distill_lcm``'s sweep hook (its
one-step FID and R@3), :func:`emdm_scores` ``train_emdm``'s (its T-step FID and R@3) and
:func:`vae_scores` ``train_vae``'s (the MPJPE of its reconstructions of the validation motions,
the VAE's metric in the results table) and :func:`evaluator_scores` ``train_evaluator``'s (its own
text-to-motion retrieval on the validation split). Imported only when sweeping, so the training
stages do not depend on it.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import torch

from data.motion_dataset import pad_motions
from data.skeleton import get_skeleton
from data.vocab import WordVocab
from models import metrics as M
from models.emdm import EMDMConfig, EMDMGenerator
from models.evaluator import EvaluatorConfig
from models.generator import Generator
from models.mld import MLDConfig, MLDDenoiser
from models.vae import MotionVAE, MotionVAEConfig
from pipelines.cli import artifacts_dir, repo_path
from pipelines.emdm_family import EMDMGeneratorRow
from pipelines.evaluation import (
    EvalConfig,
    MotionEmbedder,
    build_evaluator,
    check_group_size,
    denormalise,
    draw,
    evaluate,
    load_evaluator,
    mpjpe_mm,
    references,
)
from pipelines.feature_store import FeatureStore
from pipelines.mld_family import MotionLCMGenerator, VAEReconstruction, load_mld, load_vae


def eval_config(params: dict[str, Any]) -> EvalConfig:
    """The ``evaluate`` params section as the protocol's settings (its ``samples`` group aside)."""
    return EvalConfig(**{key: value for key, value in params["evaluate"].items() if key != "samples"})


def generator_scores(params: dict[str, Any], generator: Generator, split: str = "val") -> dict[str, float]:
    """``val_FID`` and ``val_R_precision_top3`` of ``generator`` (one replication, no MultiModality)."""
    store = FeatureStore(repo_path(params, "features.out"))
    items = store.split(split)
    cfg = eval_config(params)
    cfg = replace(cfg, replications=1, mm_repeats=0, timing_sentences=1,
                  diversity_times=min(cfg.diversity_times, len(items) - 1))
    embedder = load_evaluator(artifacts_dir(params) / "train_evaluator")
    refs = references(items, embedder, cfg, split=split)
    row = evaluate(refs, items, store.mean, store.std, embedder, get_skeleton(params["data"]["skeleton"]), cfg,
                   [generator])[generator.name]
    return {f"{split}_FID": row["FID"], f"{split}_R_precision_top3": row["R_precision_top3"]}


def motionlcm_scores(params: dict[str, Any], loop_config: dict[str, Any], state: dict[str, Any]) -> dict[str, float]:
    """A ``distill_lcm`` trial's online student, sampled in one step, scored on the validation split."""
    student = MLDDenoiser(MLDConfig(**loop_config["model"]))
    student.load_state_dict(state["models"]["student"])
    _, schedule, _ = load_mld(artifacts_dir(params) / "train_mld")
    generator = MotionLCMGenerator("MotionLCM-1", student.eval(), load_vae(artifacts_dir(params) / "train_vae"),
                                   schedule, 1, params["sample"]["motionlcm_guidance"])
    with torch.inference_mode():
        return generator_scores(params, generator)


def emdm_scores(params: dict[str, Any], loop_config: dict[str, Any], state: dict[str, Any]) -> dict[str, float]:
    """A ``train_emdm`` trial's generator (its EMA weights when kept), sampled in its T steps with
    ``sample.emdm_guidance``, scored on the validation split."""
    model = EMDMConfig(**loop_config["model"])
    generator = EMDMGenerator(model)
    generator.load_state_dict(state.get("ema", {}).get("generator", {}).get("module") or state["models"]["generator"])
    row = EMDMGeneratorRow(f"EMDM-{model.num_steps}", generator.eval(), model.make_schedule(),
                           params["sample"]["emdm_guidance"], params["sample"]["motion_batch"])
    with torch.inference_mode():
        return generator_scores(params, row)


def vae_scores(params: dict[str, Any], loop_config: dict[str, Any], state: dict[str, Any]) -> dict[str, float]:
    """A ``train_vae`` trial's VAE: ``val_MPJPE_mm``, the root-aligned joint error (mm) of its
    reconstructions (posterior mean) of the whole validation motions, as the evaluation measures it."""
    vae = MotionVAE(MotionVAEConfig(**loop_config["model"]))
    vae.load_state_dict(state["models"]["vae"])
    store = FeatureStore(repo_path(params, "features.out"))
    items = store.split("val")
    if not items:
        raise ValueError(f"{store.path}: the val split is empty; a VAE sweep ranks trials on it")
    lengths = np.array([item.length for item in items])
    raw = pad_motions([item.features for item in items], lengths)
    recon = VAEReconstruction(vae).reconstruct((raw - store.mean) / store.std, lengths)
    skeleton = get_skeleton(store.meta["skeleton"])
    return {"val_MPJPE_mm": mpjpe_mm(raw, denormalise(recon, store.mean, store.std), lengths, skeleton)}


def evaluator_scores(params: dict[str, Any], loop_config: dict[str, Any], state: dict[str, Any]) -> dict[str, float]:
    """A ``train_evaluator`` trial's matching model: ``val_R_precision_top1`` and ``val_R_precision_top3``
    of the validation captions against their own motions.

    The protocol's first step on the ``val`` split (one caption and one crop per motion, seeded by
    ``evaluate.seed``), then R-precision in groups of ``evaluate.group_size``: how often a caption
    ranks its own motion first (top 3) among the group. A rank, so it compares trials whose
    margins give their embeddings different scales, which their training losses cannot.
    """
    evaluator = build_evaluator(EvaluatorConfig.from_dict(loop_config["model"]), loop_config["mean"],
                                loop_config["std"])
    evaluator.load_state_dict(state["models"]["evaluator"])
    embedder = MotionEmbedder(evaluator, WordVocab.from_dict(loop_config["vocab"]), loop_config["max_words"])
    items = FeatureStore(repo_path(params, "features.out")).split("val")
    cfg = eval_config(params)
    check_group_size(len(items), cfg, split="val")
    d = draw(items, np.random.default_rng([cfg.seed, 0]), cfg.unit_length)
    top = M.r_precision(embedder.texts(d.tokens), embedder.motions(d.real, d.lengths), cfg.group_size, top_k=3)
    return {"val_R_precision_top1": float(top[0]), "val_R_precision_top3": float(top[2])}
