"""The MLD family's loaders, generators and registry functions (the motion VAE and the MLD teacher).

- :func:`load_vae` / :func:`load_mld`: trained models from ``train_vae`` / ``train_mld`` outputs.
- :class:`MLDGenerator`: DDIM over the VAE latent with classifier-free guidance, then decoding.
- :class:`MotionLCMGenerator`: the distilled student, one pass per step, then decoding.
- :class:`VAEReconstruction`: the VAE's encode (posterior mean) -> decode of real motions.
- :func:`vae_rows`, :func:`mld_rows`, :func:`mld_generator`, :func:`motionlcm_rows`,
  :func:`motionlcm_generator`: the registry's entries (``pipelines/registry.py``).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from data.motion_dataset import pad_tokens
from models.diffusion import NoiseSchedule, TimestepSpacing, ddim_timesteps
from models.generator import CPU, Generator, Reconstructor, TextBatch, device_of
from models.mld import MLDConfig, MLDDenoiser, sample_mld
from models.motionlcm import TIMESTEPS, sample_motionlcm
from models.vae import MotionVAE, MotionVAEConfig, length_sorted_chunks
from pipelines.checkpoint import load_final_model

#: DDIM step counts of the MLD rows: 50 (MLD's sampler) and the few-step baselines of MotionLCM's Table 4.
MLD_ROW_STEPS = (50, 1, 2, 4)
DEFAULT_STEPS = 50

if TYPE_CHECKING:  # annotations only: the registry imports this module, not the reverse
    from pipelines.registry import EvalContext, GenerateOptions


def noise_schedule(config: dict[str, Any]) -> NoiseSchedule:
    """The teacher's noise schedule from its loop config."""
    return NoiseSchedule.from_name(config["beta_schedule"], config["num_train_timesteps"],
                                   beta_start=config["beta_start"], beta_end=config["beta_end"])


def load_vae(out_dir: Path, device: torch.device = CPU) -> MotionVAE:
    """The trained VAE of a ``train_vae`` output folder, in eval mode, on ``device``."""
    payload = load_final_model(out_dir)
    vae = MotionVAE(MotionVAEConfig(**payload["config"]["model"]))
    vae.load_state_dict(payload["models"]["vae"])
    return vae.eval().to(device)


def load_motionlcm(out_dir: Path, use_ema: bool = False, device: torch.device = CPU) -> MLDDenoiser:
    """The distilled student of a ``distill_lcm`` output folder (the online student, as MotionLCM
    releases it, unless ``use_ema``: the target network), on ``device``."""
    payload = load_final_model(out_dir)
    student = MLDDenoiser(MLDConfig(**payload["config"]["model"]))
    weights = payload["ema"].get("student") if use_ema else None
    student.load_state_dict(weights or payload["models"]["student"])
    return student.eval().to(device)


def load_mld(out_dir: Path, use_ema: bool = True,
             device: torch.device = CPU) -> tuple[MLDDenoiser, NoiseSchedule, dict[str, Any]]:
    """The trained denoiser (EMA weights when present) and its noise schedule on ``device`` (a sampler then
    finds its schedule where it runs: no copy per call), and its loop config."""
    payload = load_final_model(out_dir)
    config = payload["config"]
    denoiser = MLDDenoiser(MLDConfig(**config["model"]))
    weights = payload["ema"].get("denoiser") if use_ema else None
    denoiser.load_state_dict(weights or payload["models"]["denoiser"])
    return denoiser.eval().to(device), noise_schedule(config).to(device), config


def text_inputs(denoiser: MLDDenoiser, text: TextBatch) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The prompts' pooled embeddings and, for a ``word_tokens`` denoiser, their padded word tokens and mask, on
    the denoiser's device."""
    device = device_of(denoiser)
    pooled = torch.from_numpy(text.pooled.astype(np.float32)).to(device)
    if denoiser.config.word_tokens == "none":
        return pooled, {}
    tokens, mask = pad_tokens([np.asarray(t, np.float32) for t in text.tokens])
    return pooled, {"text_tokens": tokens.to(device), "text_mask": mask.to(device)}


def ddim_spacing(num_steps: int, num_train_steps: int) -> TimestepSpacing:
    """MLD's DDIM grid for ``num_steps`` n of T: its published ``leading`` grid (``steps_offset`` 1) where
    that grid starts in the last tenth of the schedule, else ``trailing``, whose first step is T - 1.

    Sampling starts from z_T ~ N(0, I), the latent of the last timestep. The leading grid's first step is
    (n - 1) (T // n) + 1: 981 for 50 steps and 901 for 10, but 751, 667, 501 and 1 for 4, 3, 2 and 1 step,
    and below 0.9 T again for many n above 111 (889 for 112, 799 for 400, n itself for n from 501 to 899),
    where pure noise would be handed to the network as a much less noisy latent (with one step the network
    is asked only at t = 1 and returns about the noise: MLD-DDIM1 scored chance R-precision); at n = T it
    would leave the schedule. So the few-step baselines of MotionLCM's Table 4 (MLD-DDIM1/2/4) use the
    trailing grid, which starts at pure noise, and MLD-DDIM50 keeps MLD's own sampler (the two grids score
    alike at 50 steps: docs/findings.md, 2026-12-07 (late morning)).
    """
    if num_steps < num_train_steps and int(ddim_timesteps(num_train_steps, num_steps)[0]) >= 0.9 * num_train_steps:
        return "leading"
    return "trailing"


class MLDGenerator:
    """MLD: DDIM over the VAE latent with classifier-free guidance (the grid of :func:`ddim_spacing`), then VAE
    decoding."""

    stochastic = True

    def __init__(self, name: str, denoiser: MLDDenoiser, vae: MotionVAE, schedule: NoiseSchedule,
                 num_steps: int, guidance: float) -> None:
        self.name, self.denoiser, self.vae, self.schedule = name, denoiser, vae, schedule
        self.num_steps, self.guidance = num_steps, guidance
        self.spacing = ddim_spacing(num_steps, schedule.num_steps)
        self.nfe = num_steps * (2 if guidance != 1.0 else 1)

    @torch.inference_mode()
    def sample(self, text: TextBatch, lengths: np.ndarray, seed: int) -> np.ndarray:
        generator = torch.Generator().manual_seed(seed)
        pooled, words = text_inputs(self.denoiser, text)
        out = sample_mld(self.denoiser, self.vae, self.schedule, pooled, torch.as_tensor(lengths, device=pooled.device),
                         self.num_steps, self.guidance, generator, timestep_spacing=self.spacing, **words)
        return out.cpu().numpy()


class MotionLCMGenerator:
    """MotionLCM: LCM multistep sampling with the guidance-embedded student, then VAE decoding."""

    stochastic = True

    def __init__(self, name: str, student: MLDDenoiser, vae: MotionVAE, schedule: NoiseSchedule,
                 num_steps: int, guidance: float) -> None:
        self.name, self.student, self.vae, self.schedule = name, student, vae, schedule
        self.num_steps, self.w = num_steps, guidance - 1.0
        self.nfe = num_steps

    @torch.inference_mode()
    def sample(self, text: TextBatch, lengths: np.ndarray, seed: int) -> np.ndarray:
        pooled, words = text_inputs(self.student, text)
        out = sample_motionlcm(self.student, self.vae, self.schedule, pooled,
                               torch.as_tensor(lengths, device=pooled.device), self.num_steps, self.w,
                               torch.Generator().manual_seed(seed), **words)
        return out.cpu().numpy()


class VAEReconstruction:
    """The motion VAE's encode (posterior mean) -> decode of real motions.

    A departure: MLD's and MotionLCM's ``vae`` rows decode a posterior sample. The mean makes the row
    deterministic; with ``tiny``'s ``logvar_offset`` the posterior's sigma is small beside the spread of
    its means, but under the ``paper`` profile (offset 0) the two differ more."""

    name = "VAE"

    def __init__(self, vae: MotionVAE) -> None:
        self.vae = vae.eval()

    @torch.inference_mode()
    def reconstruct(self, motions: np.ndarray, lengths: np.ndarray, chunk_size: int = 64) -> np.ndarray:
        """Normalised motions (B, T, D) -> reconstructions (B, T, D), in chunks of similar length."""
        device = device_of(self.vae)
        x, lengths_t = torch.from_numpy(motions.astype(np.float32)).to(device), torch.as_tensor(lengths)
        out = torch.zeros_like(x)
        for idx, longest in length_sorted_chunks(lengths_t, chunk_size):
            z, _ = self.vae.encode(x[idx, :longest], lengths_t[idx].to(device), sample=False)
            out[idx, :longest] = self.vae.decode(z, lengths_t[idx].to(device), longest)
        return out.cpu().numpy()


def vae_rows(ctx: EvalContext) -> list[Reconstructor]:
    """The motion VAE's reconstruction of the test motions."""
    return [VAEReconstruction(load_vae(ctx.trained("train_vae"), ctx.device))]


def _mld(ctx: EvalContext, steps: int, guidance: float) -> MLDGenerator:
    denoiser, schedule, _ = load_mld(ctx.trained("train_mld"), device=ctx.device)
    return MLDGenerator(f"MLD-DDIM{steps}", denoiser, load_vae(ctx.trained("train_vae"), ctx.device), schedule, steps,
                        guidance)


def mld_row_names(params: dict[str, Any]) -> list[str]:
    """The names :func:`mld_rows` gives its rows."""
    return [f"MLD-DDIM{n}" for n in MLD_ROW_STEPS]


def mld_rows(ctx: EvalContext) -> list[Generator]:
    """MLD with DDIM 50 (its published sampler) and the few-step DDIM 1/2/4 baselines (one load)."""
    first = _mld(ctx, MLD_ROW_STEPS[0], ctx.params["sample"]["mld_guidance"])
    return [first] + [MLDGenerator(f"MLD-DDIM{n}", first.denoiser, first.vae, first.schedule, n, first.guidance)
                      for n in MLD_ROW_STEPS[1:]]


def mld_generator(ctx: EvalContext, options: GenerateOptions) -> Generator:
    """``stages.generate --model mld``: DDIM-50 and the trained guidance unless told otherwise."""
    guidance = ctx.params["sample"]["mld_guidance"] if options.guidance is None else options.guidance
    return _mld(ctx, options.steps or DEFAULT_STEPS, guidance)


def _motionlcm(ctx: EvalContext, steps: int, guidance: float) -> MotionLCMGenerator:
    _, schedule, _ = load_mld(ctx.trained("train_mld"), device=ctx.device)
    student = load_motionlcm(ctx.trained("distill_lcm"), device=ctx.device)
    return MotionLCMGenerator(f"MotionLCM-{steps}", student, load_vae(ctx.trained("train_vae"), ctx.device), schedule,
                              steps, guidance)


def motionlcm_row_names(params: dict[str, Any]) -> list[str]:
    """The names :func:`motionlcm_rows` gives its rows."""
    return [f"MotionLCM-{n}" for n in sorted(TIMESTEPS)]


def motionlcm_rows(ctx: EvalContext) -> list[Generator]:
    """MotionLCM with 1, 2 and 4 steps (one load), all at ``sample.motionlcm_guidance`` (V2's code has a
    scale per step count; docs/motionlcm.md, "Choices")."""
    first = _motionlcm(ctx, 1, ctx.params["sample"]["motionlcm_guidance"])
    return [first] + [MotionLCMGenerator(f"MotionLCM-{n}", first.student, first.vae, first.schedule, n,
                                         first.w + 1.0) for n in sorted(TIMESTEPS)[1:]]


def motionlcm_generator(ctx: EvalContext, options: GenerateOptions) -> Generator:
    """``stages.generate --model motionlcm``: one step and the configured guidance unless told otherwise."""
    steps = options.steps or 1
    if steps not in TIMESTEPS:
        raise ValueError(f"--steps {steps}: MotionLCM samples with {sorted(TIMESTEPS)} steps")
    guidance = ctx.params["sample"]["motionlcm_guidance"] if options.guidance is None else options.guidance
    return _motionlcm(ctx, steps, guidance)
