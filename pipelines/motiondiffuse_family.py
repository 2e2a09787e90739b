"""The MotionDiffuse family's loader, generator rows and registry functions (``train_motiondiffuse`` outputs).

- :func:`load_motiondiffuse`: the trained noise predictor (EMA weights when present), its schedule and
  loop config.
- :class:`MotionDiffuseRow`: MotionDiffuse's samplers behind the :class:`models.generator.Generator`
  interface: the paper's ancestral DDPM over all T steps, or DDIM with few steps (a baseline the paper
  does not report). The text branch reads the prompts' word-token states (``TextBatch.tokens``).
- :func:`motiondiffuse_rows`, :func:`motiondiffuse_generator`: the registry's entries
  (``pipelines/registry.py``).
- :func:`sample_body_parts`, :func:`sample_time_varied`: the paper's fine-grained control (Eqs. 10-11,
  :func:`models.motiondiffuse.body_part_model_fn` / :func:`~models.motiondiffuse.time_varied_model_fn`)
  with a row's sampler, for ``stages.generate --part`` / ``--segment``.

Rows: ``MotionDiffuse-<T>`` (DDPM over T steps, the paper's sampler) and ``MotionDiffuse-DDIM10``, both
with classifier-free guidance ``sample.motiondiffuse_guidance`` (ours, :mod:`models.motiondiffuse` item
13; 1 = none, the paper's). NFE is the number of steps, doubled with guidance (the two passes run as one
batched forward, but each sample is evaluated twice, as the MLD and EMDM rows count it). On CPU the DDPM row is
too slow for the whole test set: ``sample.motiondiffuse_ddpm_items`` = K (null: no bound) makes it
answer only the first K captions of each replication's draw, without MultiModality
(:mod:`pipelines.evaluation`, ``eval_items``); the DDIM row always runs the full protocol.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from data.motion_dataset import pad_tokens
from models.diffusion import NoiseSchedule, ddim_sample, ddpm_sample
from models.generator import CPU, Generator, TextBatch, device_of
from models.motiondiffuse import (
    ModelFn,
    MotionDiffuse,
    MotionDiffuseConfig,
    SamplingMethod,
    body_part_model_fn,
    sample_motiondiffuse,
    time_varied_model_fn,
)
from pipelines.checkpoint import load_final_model
from pipelines.config import check_number
from pipelines.length_batches import sample_by_length

if TYPE_CHECKING:  # annotations only: the registry imports this module, not the reverse
    from pipelines.registry import EvalContext, GenerateOptions

TRAIN_STAGE = "train_motiondiffuse"
#: The model's name in ``train_motiondiffuse``'s checkpoints (stages/train_motiondiffuse.py ``MODEL``).
MODEL = "denoiser"
#: DDIM steps of the few-step evaluation row.
DDIM_ROW_STEPS = 10


def load_motiondiffuse(out_dir: Path, use_ema: bool = True,
                       device: torch.device = CPU) -> tuple[MotionDiffuse, NoiseSchedule, dict[str, Any]]:
    """The trained noise predictor of a ``train_motiondiffuse`` output folder in eval mode on ``device`` (its EMA
    weights when present and ``use_ema``; the paper trains none), its noise schedule (on ``device`` too) and its
    loop config."""
    payload = load_final_model(out_dir)
    config = payload["config"]
    model = MotionDiffuse(MotionDiffuseConfig(**config["model"]))
    weights = payload["ema"].get(MODEL) if use_ema else None
    model.load_state_dict(weights or payload["models"][MODEL])
    return model.eval().to(device), model.config.make_schedule().to(device), config


class MotionDiffuseRow:
    """MotionDiffuse: DDPM over all T steps (``method="ddpm"``) or DDIM with ``steps`` (eta 0, trailing grid),
    with classifier-free ``guidance`` (1 = none).

    ``eval_items``: None, or the number of each evaluation draw's captions the row answers, and
    ``eval_replications``: None (all), or how many of the replications it is evaluated in (bounds for
    slow samplers, :mod:`pipelines.evaluation`); ``note`` says so in words (nothing reads it: the
    :class:`~models.generator.Generator` protocol has no notes). ``batch``: a call samples its captions in
    length-sorted batches of this many (:func:`pipelines.length_batches.sample_by_length`; None: at once).
    """

    stochastic = True

    def __init__(self, name: str, model: MotionDiffuse, schedule: NoiseSchedule, method: SamplingMethod = "ddpm",
                 steps: int | None = None, eval_items: int | None = None,
                 eval_replications: int | None = None, guidance: float = 1.0, batch: int | None = None) -> None:
        if method == "ddpm":
            if steps not in (None, schedule.num_steps):
                raise ValueError(f"{name}: DDPM runs all {schedule.num_steps} steps, got steps={steps}")
            steps = schedule.num_steps
        elif method == "ddim":
            if steps is None or not 1 <= steps <= schedule.num_steps:
                raise ValueError(f"{name}: DDIM needs 1..{schedule.num_steps} steps, got {steps}")
        else:
            raise ValueError(f"{name}: unknown method {method!r}: ddpm | ddim")
        self.name, self.model, self.schedule = name, model.eval(), schedule
        self.method, self.steps, self.guidance = method, int(steps), float(guidance)
        self.nfe = self.steps * (2 if self.guidance != 1.0 else 1)
        self.eval_items, self.eval_replications, self.batch = eval_items, eval_replications, batch
        reps = "each replication" if eval_replications is None else f"the first {eval_replications} replication(s)"
        self.note = ("" if eval_items is None else
                     f"evaluated on the first {eval_items} captions of {reps}' draws, no MultiModality")

    @torch.inference_mode()
    def sample(self, text: TextBatch, lengths: np.ndarray, seed: int) -> np.ndarray:
        """(B, max(lengths), D) normalised features, 0 past each length; the same ``seed`` gives the same output."""
        lengths = np.asarray(lengths, np.int64)
        if int(lengths.max()) > self.model.config.max_len:
            raise ValueError(f"{self.name}: lengths up to {int(lengths.max())} frames, the model was trained "
                             f"with max_len={self.model.config.max_len}")
        return sample_by_length(lambda index, s: self._sample(text.select(index), lengths[index], s), lengths, seed,
                                self.batch)

    def _sample(self, text: TextBatch, lengths: np.ndarray, seed: int) -> np.ndarray:
        tokens, mask = _word_states(text)
        out = sample_motiondiffuse(self.model, self.schedule, torch.as_tensor(lengths), tokens, mask,
                                   method=self.method, steps=self.steps,
                                   generator=torch.Generator().manual_seed(seed), guidance=self.guidance)
        return out.float().cpu().numpy()


def _guidance(ctx: EvalContext) -> float:
    """``sample.motiondiffuse_guidance``, checked (a number >= 0)."""
    return float(check_number(ctx.params["sample"], "motiondiffuse_guidance", "sample", low=0.0))


def _load(ctx: EvalContext) -> tuple[MotionDiffuse, NoiseSchedule]:
    model, schedule, _ = load_motiondiffuse(ctx.trained(TRAIN_STAGE), device=ctx.device)
    return model, schedule


def motiondiffuse_row_names(params: dict[str, Any]) -> list[str]:
    """The names :func:`motiondiffuse_rows` gives its rows: T is ``train_motiondiffuse.num_train_timesteps``."""
    return [f"MotionDiffuse-{params[TRAIN_STAGE]['num_train_timesteps']}", f"MotionDiffuse-DDIM{DDIM_ROW_STEPS}"]


def motiondiffuse_rows(ctx: EvalContext) -> list[Generator]:
    """``MotionDiffuse-<T>`` (DDPM, bounded by ``sample.motiondiffuse_ddpm_items`` and
    ``sample.motiondiffuse_ddpm_replications``) and ``MotionDiffuse-DDIM10`` (one load), both with
    ``sample.motiondiffuse_guidance`` and in batches of ``sample.motion_batch``."""
    model, schedule = _load(ctx)
    guidance = _guidance(ctx)
    bounds = {}
    for key in ("motiondiffuse_ddpm_items", "motiondiffuse_ddpm_replications"):
        value = bounds[key] = ctx.params["sample"][key]
        if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
            raise ValueError(f"sample.{key}: expected null or an integer >= 1, got {value!r}")
    batch = ctx.params["sample"]["motion_batch"]
    return [MotionDiffuseRow(f"MotionDiffuse-{schedule.num_steps}", model, schedule, "ddpm",
                             eval_items=bounds["motiondiffuse_ddpm_items"],
                             eval_replications=bounds["motiondiffuse_ddpm_replications"], guidance=guidance,
                             batch=batch),
            MotionDiffuseRow(f"MotionDiffuse-DDIM{DDIM_ROW_STEPS}", model, schedule, "ddim", DDIM_ROW_STEPS,
                             guidance=guidance, batch=batch)]


def motiondiffuse_generator(ctx: EvalContext, options: GenerateOptions) -> Generator:
    """``stages.generate --model motiondiffuse``: DDPM over all T steps (``--steps`` omitted or T), or DDIM
    with ``--steps`` 1..T-1; ``sample.motiondiffuse_guidance`` unless ``--guidance`` says otherwise."""
    guidance = _guidance(ctx) if options.guidance is None else options.guidance
    model, schedule = _load(ctx)
    t = schedule.num_steps
    batch = ctx.params["sample"]["motion_batch"]
    if options.steps is None or options.steps == t:
        return MotionDiffuseRow(f"MotionDiffuse-{t}", model, schedule, "ddpm", guidance=guidance, batch=batch)
    if not 1 <= options.steps < t:
        raise ValueError(f"--steps {options.steps}: MotionDiffuse samples with DDPM over all {t} steps (omit "
                         f"--steps) or DDIM with 1..{t - 1} steps")
    return MotionDiffuseRow(f"MotionDiffuse-DDIM{options.steps}", model, schedule, "ddim", options.steps,
                            guidance=guidance, batch=batch)


# --------------------------------------------------------------------------------------------------
# Fine-grained control (stages.generate --part / --segment)
# --------------------------------------------------------------------------------------------------


def _word_states(text: TextBatch) -> tuple[torch.Tensor, torch.Tensor]:
    """The prompts' padded word states (B, L, E) and mask (B, L) (the model's functions move them to its device)."""
    return pad_tokens([np.asarray(t, np.float32) for t in text.tokens])


def _sample_with(row: MotionDiffuseRow, model_fn: ModelFn, batch: int, num_frames: int, seed: int) -> np.ndarray:
    """``row``'s sampler (as :func:`models.motiondiffuse.sample_motiondiffuse`: x_T from ``seed``, DDPM with the
    posterior variance or DDIM eta 0 on the trailing grid ending on x0) with a composed ``model_fn``."""
    shape = (batch, num_frames, row.model.config.feature_dim)
    generator = torch.Generator().manual_seed(seed)
    x_T = torch.randn(shape, generator=generator).to(device_of(row.model))
    with torch.no_grad():  # the compositions' gradient terms enable autograd (w.r.t. x_t) themselves
        if row.method == "ddpm":
            x0 = ddpm_sample(model_fn, shape, row.schedule, generator, x_T=x_T, variance_type="fixed_small")
        else:
            x0 = ddim_sample(model_fn, shape, row.schedule, row.steps, 0.0, generator, x_T=x_T,
                             timestep_spacing="trailing", set_alpha_to_one=True)
    return x0.float().cpu().numpy()


def sample_body_parts(row: MotionDiffuseRow, parts: Sequence[tuple[str | torch.Tensor, TextBatch]], length: int,
                      seed: int, lambda1: float = 0.01) -> np.ndarray:
    """Body part-independent control (Eq. 10): each part (a name of
    :data:`models.motiondiffuse.PART_UNIONS`, "rest", or a bool (D,) feature mask) with its own prompts (a
    TextBatch of B captions); the parts must partition the features. Returns (B, length, D) normalised
    features."""
    prompts = [(name, *_word_states(text)) for name, text in parts]
    batch = len(parts[0][1]) if parts else 0
    model_fn = body_part_model_fn(row.model, prompts, [length] * batch, lambda1=lambda1, guidance=row.guidance)
    return _sample_with(row, model_fn, batch, length, seed)


def sample_time_varied(row: MotionDiffuseRow, segments: Sequence[tuple[int, int, TextBatch]], length: int,
                       seed: int, lambda2: float = 0.01) -> np.ndarray:
    """Time-varied control (Eq. 11): frames [start, end) of each segment follow its prompts (a TextBatch of B
    captions); the segments must cover [0, length). Returns (B, length, D) normalised features."""
    windows = [(start, end, *_word_states(text)) for start, end, text in segments]
    batch = len(segments[0][2]) if segments else 0
    model_fn = time_varied_model_fn(row.model, windows, length, lambda2=lambda2, guidance=row.guidance)
    return _sample_with(row, model_fn, batch, length, seed)
