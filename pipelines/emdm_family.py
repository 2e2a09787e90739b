"""The EMDM family's loader, generator and registry functions (``train_emdm`` outputs).

- :func:`load_emdm`: the trained generator (EMA weights when present), its schedule and loop config.
- :class:`EMDMGeneratorRow`: EMDM's sampler (Alg. 1) behind the :class:`models.generator.Generator`
  interface: T steps, a fresh z per step, classifier-free guidance with the unconditional and
  conditional passes batched into one forward.
- :class:`EMDMActionRow`: the same sampler conditioned on action labels, behind
  :class:`pipelines.action_evaluation.ActionGenerator` (``train_emdm_action``'s generator).
- :class:`EMDMActionPrompts`: that row behind the text interface for ``stages.generate --model
  emdm-action``, each prompt an action label.
- :func:`emdm_rows`, :func:`emdm_generator`, :func:`emdm_action_rows`, :func:`emdm_action_generator`:
  the registry's entries
  (``pipelines/registry.py``); the guidance scales are ``sample.emdm_guidance`` for text and
  ``sample.emdm_action_guidance`` for action labels. EMDM's released evaluation uses 2.5 for text and
  none for action labels (``--cond_mask_prob 0 --guidance_param 1``); the paper states neither, and the
  ``paper`` profile follows the code.

NFE counts network evaluations per sample: ``2 T`` with guidance (the two passes run as one batched
forward, but each sample is evaluated twice, as MLD's rows count it), ``T`` at guidance 1.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from data.motion_dataset import pad_tokens
from models.emdm import EMDMConfig, EMDMGenerator, EMDMSchedule, sample_emdm
from models.generator import CPU, Generator, TextBatch
from pipelines.checkpoint import load_final_model, skipped
from pipelines.length_batches import sample_by_length

if TYPE_CHECKING:  # annotations only: the registry imports this module, not the reverse
    from pipelines.registry import EvalContext, GenerateOptions

TRAIN_STAGE = "train_emdm"
ACTION_STAGE = "train_emdm_action"


def load_emdm(out_dir: Path, use_ema: bool = True,
              device: torch.device = CPU) -> tuple[EMDMGenerator, EMDMSchedule, dict[str, Any]]:
    """The trained generator of a ``train_emdm`` output folder in eval mode on ``device`` (its EMA weights when
    present and ``use_ema``), its few-step schedule (on ``device`` too) and its loop config.
    :func:`models.emdm.sample_emdm` moves its inputs to the generator's device."""
    payload = load_final_model(out_dir)
    config = payload["config"]
    model = EMDMConfig(**config["model"])
    generator = EMDMGenerator(model)
    weights = payload["ema"].get("generator") if use_ema else None
    generator.load_state_dict(weights or payload["models"]["generator"])
    return generator.eval().to(device), model.make_schedule().to(device), config


class EMDMGeneratorRow:
    """EMDM: ``T`` denoising-GAN steps from ``x_T ~ N(0, I)``, guided on x0 (Eq. 13), text-conditioned; a call
    samples its captions in length-sorted batches of ``batch`` (:func:`pipelines.length_batches.sample_by_length`;
    None: all at once)."""

    stochastic = True

    def __init__(self, name: str, generator: EMDMGenerator, schedule: EMDMSchedule, guidance: float,
                 batch: int | None = None) -> None:
        if generator.config.condition != "text":
            raise ValueError(f"{name}: the generator is conditioned on {generator.config.condition!r}, "
                             "the evaluation rows on text")
        self.name, self.generator, self.schedule = name, generator.eval(), schedule
        self.guidance, self.batch = float(guidance), batch
        self.nfe = schedule.num_steps * (2 if self.guidance != 1.0 else 1)

    @torch.inference_mode()
    def sample(self, text: TextBatch, lengths: np.ndarray, seed: int) -> np.ndarray:
        lengths = np.asarray(lengths, np.int64)
        return sample_by_length(lambda index, s: self._sample(text.select(index), lengths[index], s), lengths, seed,
                                self.batch)

    def _sample(self, text: TextBatch, lengths: np.ndarray, seed: int) -> np.ndarray:
        rng = torch.Generator().manual_seed(seed)
        cond = torch.from_numpy(np.asarray(text.pooled, np.float32))
        words = pad_tokens(text.tokens) if self.generator.config.word_tokens else None
        out = sample_emdm(self.generator, self.schedule, cond, torch.as_tensor(np.asarray(lengths, np.int64)),
                          self.guidance, rng, words=words)
        return out.float().cpu().numpy()


class EMDMActionRow:
    """EMDM conditioned on action labels: ``T`` steps from noise, guided on x0 (Eq. 13), in length-sorted
    batches of ``batch`` as :class:`EMDMGeneratorRow`."""

    stochastic = True

    def __init__(self, name: str, generator: EMDMGenerator, schedule: EMDMSchedule, guidance: float,
                 classes: Sequence[str], batch: int | None = None) -> None:
        if generator.config.condition != "action" or generator.config.num_actions != len(classes):
            raise ValueError(f"{name}: the generator is conditioned on {generator.config.condition!r} with "
                             f"{generator.config.num_actions} actions, not on the {len(classes)} action classes")
        self.name, self.generator, self.schedule = name, generator.eval(), schedule
        self.guidance, self.classes, self.batch = float(guidance), tuple(classes), batch
        self.nfe = schedule.num_steps * (2 if self.guidance != 1.0 else 1)

    @torch.inference_mode()
    def sample_actions(self, action_ids: np.ndarray, lengths: np.ndarray, seed: int) -> np.ndarray:
        action_ids, lengths = np.asarray(action_ids, np.int64), np.asarray(lengths, np.int64)
        return sample_by_length(lambda index, s: self._sample(action_ids[index], lengths[index], s), lengths, seed,
                                self.batch)

    def _sample(self, action_ids: np.ndarray, lengths: np.ndarray, seed: int) -> np.ndarray:
        rng = torch.Generator().manual_seed(seed)
        out = sample_emdm(self.generator, self.schedule, torch.as_tensor(np.asarray(action_ids, np.int64)),
                          torch.as_tensor(np.asarray(lengths, np.int64)), self.guidance, rng)
        return out.float().cpu().numpy()


class EMDMActionPrompts:
    """``stages.generate --model emdm-action``: an :class:`EMDMActionRow` behind the text interface. Each
    prompt's text is an action label, one of the row's classes (``train_emdm_action``'s, e.g. ``walk``),
    matched after trimming and lower-casing; the text embeddings are not used."""

    stochastic = True

    def __init__(self, row: EMDMActionRow) -> None:
        self.row, self.name, self.nfe = row, row.name, row.nfe
        self.index = {label.lower(): i for i, label in enumerate(row.classes)}

    def label_ids(self, labels: Sequence[str]) -> np.ndarray:
        """Class ids of ``labels``; ValueError naming the first unknown label and listing the classes."""
        for label in labels:
            if label.strip().lower() not in self.index:
                raise ValueError(f"--model emdm-action: {label!r} is not an action label; the model knows "
                                 f"{', '.join(self.row.classes)}")
        return np.array([self.index[label.strip().lower()] for label in labels], np.int64)

    def sample(self, text: TextBatch, lengths: np.ndarray, seed: int) -> np.ndarray:
        return self.row.sample_actions(self.label_ids(text.texts), lengths, seed)


def _emdm_action(ctx: EvalContext, guidance: float) -> EMDMActionRow:
    generator, schedule, config = load_emdm(ctx.trained(ACTION_STAGE), device=ctx.device)
    return EMDMActionRow("EMDM-action", generator, schedule, guidance, config["classes"],
                         ctx.params["sample"]["motion_batch"])


def emdm_action_rows(ctx: EvalContext) -> list[EMDMActionRow]:
    """``EMDM-action``: the action-conditioned generator of ``train_emdm_action`` with
    ``sample.emdm_action_guidance``."""
    return [_emdm_action(ctx, ctx.params["sample"]["emdm_action_guidance"])]


def _emdm(ctx: EvalContext, guidance: float) -> EMDMGeneratorRow:
    generator, schedule, _ = load_emdm(ctx.trained(TRAIN_STAGE), device=ctx.device)
    return EMDMGeneratorRow(f"EMDM-{schedule.num_steps}", generator, schedule, guidance,
                            ctx.params["sample"]["motion_batch"])


def emdm_row_names(params: dict[str, Any]) -> list[str]:
    """The names :func:`emdm_rows` gives its rows: T is ``train_emdm.num_steps``, which the model was trained with."""
    return [f"EMDM-{params[TRAIN_STAGE]['num_steps']}"]


def emdm_rows(ctx: EvalContext) -> list[Generator]:
    """EMDM with the T steps it was trained with (``EMDM-10``) and ``sample.emdm_guidance``."""
    return [_emdm(ctx, ctx.params["sample"]["emdm_guidance"])]


def _check_steps(options: GenerateOptions, schedule: EMDMSchedule, model: str, stage: str) -> None:
    """``--steps`` must be the T steps the model was trained with (``<stage>.num_steps``)."""
    if options.steps is not None and options.steps != schedule.num_steps:
        raise ValueError(f"--steps {options.steps}: {model} samples with the {schedule.num_steps} steps it was "
                         f"trained with ({stage}.num_steps)")


def emdm_generator(ctx: EvalContext, options: GenerateOptions) -> Generator:
    """``stages.generate --model emdm``: the trained T steps (``--steps`` must equal it) and the
    configured guidance unless told otherwise."""
    guidance = ctx.params["sample"]["emdm_guidance"] if options.guidance is None else options.guidance
    row = _emdm(ctx, guidance)
    _check_steps(options, row.schedule, "EMDM", TRAIN_STAGE)
    return row


def emdm_action_generator(ctx: EvalContext, options: GenerateOptions) -> EMDMActionPrompts:
    """``stages.generate --model emdm-action``: the action model with its trained T steps (``--steps`` must
    equal it) and ``sample.emdm_action_guidance`` unless told otherwise; ValueError with the stage's reason
    when the dataset had no action labels to train it on."""
    reason = skipped(ctx.artifacts / ACTION_STAGE)
    if reason is not None:
        raise ValueError(f"--model emdm-action: {ACTION_STAGE} trained nothing: {reason}")
    guidance = ctx.params["sample"]["emdm_action_guidance"] if options.guidance is None else options.guidance
    row = _emdm_action(ctx, guidance)
    _check_steps(options, row.schedule, "EMDM-action", ACTION_STAGE)
    return EMDMActionPrompts(row)
