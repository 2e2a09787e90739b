"""MotionLCM: latent consistency distillation of the MLD teacher (MotionLCM §3.2; reference motionlcm_mld.md §4).

The student is a copy of the teacher denoiser (:class:`models.mld.MLDDenoiser`, word-token
attention included) whose timestep embedding also takes the guidance scale w through a
zero-initialised projection of its 256-d sinusoidal embedding (:func:`guidance_embedding`): at
initialisation the student's output equals the teacher's conditional output.

One distillation step (:func:`lcm_distillation_loss`) on diffusion-space latents z0:

1. a grid point ``t_{n+k}`` of the DDIM-solver grid with skipping interval k, and ``t_n = t_{n+k} - k``
   (0 below the first grid point); ``z_{n+k} = sqrt(ab) z0 + sqrt(1 - ab) eps``;
2. ``w ~ U[w_min, w_max]`` per sample;
3. the frozen teacher's guided estimate in the LCM form ``eps_w = eps_c + w (eps_c - eps_u)``
   (classifier-free guidance with scale 1 + w; x̂0 follows from eps_w, which equals guiding x̂0
   and eps separately since both are affine in the network output), one DDIM step to ``t_n``:
   ``ẑ_n = sqrt(ab_n) x̂0_w + sqrt(1 - ab_n) eps_w``;
4. the consistency function ``f(z, t) = c_skip(t) z + c_out(t) x̂0(z, t)`` (σ_data 0.5, timestep
   scaling 10) of the student at ``(z_{n+k}, t_{n+k})`` and of the target network (the EMA of the
   student, rate μ) at ``(ẑ_n, t_n)``, both with the same w;
5. ``d(f_θ, f_θ⁻)``: Huber ``mean(sqrt((a - b)^2 + c^2) - c)`` or L2.

Sampling (:func:`sample_motionlcm`) makes one network pass per step, no classifier-free doubling:
the guidance lives in the student's w input. Documented choice: the timestep lists are MotionLCM V2's
released ones (1: [799], 2: [699, 299], 4: [699, 399, 299, 299]), all on the 10-point solver grid
(k = 100) the student is distilled on; the multistep rule is LCM's (denoise, re-noise to the next
listed timestep, return the last denoised latent), then VAE decoding.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor

from models.diffusion import (
    NoiseSchedule,
    cfg_combine,
    ddim_solver_step,
    lcm_consistency_fn,
    lcm_multistep_sample,
    lcm_training_timesteps,
)
from models.mld import MLDDenoiser
from models.rng import normal, uniform
from models.transformer import eval_mode, timestep_embedding
from models.vae import MotionVAE

GUIDANCE_EMBED_DIM = 256
#: MotionLCM V2's sampling timesteps per number of steps (on the 10-point grid, k = 100).
TIMESTEPS = {1: (799,), 2: (699, 299), 4: (699, 399, 299, 299)}
DistanceKind = Literal["huber", "l2"]


def guidance_embedding(w: Tensor, dim: int = GUIDANCE_EMBED_DIM) -> Tensor:
    """MotionLCM's embedding of the guidance scale: w (B,) -> (B, dim) float32.

    ``w * 1000`` through sinusoids with frequencies ``exp(-log(10000) i / (dim/2 - 1))``, output
    ``[sin, cos]`` (not flipped).
    """
    return timestep_embedding(w.float() * 1000.0, dim, flip_sin_to_cos=False, freq_shift=1.0)


def student_from_teacher(teacher: MLDDenoiser, cond_dim: int = GUIDANCE_EMBED_DIM) -> MLDDenoiser:
    """A trainable copy of ``teacher`` with the zero-initialised guidance projection added."""
    config = dataclasses.replace(teacher.config, time_cond_dim=cond_dim)
    student = MLDDenoiser(config)
    missing, unexpected = student.load_state_dict(teacher.state_dict(), strict=False)
    if unexpected or missing != ["time_embedding.cond_proj.weight"]:
        raise ValueError(f"teacher and student differ beyond the guidance projection: missing {missing}, "
                         f"unexpected {unexpected}")
    return student.train()


def distance(a: Tensor, b: Tensor, kind: DistanceKind = "huber", huber_c: float = 0.5) -> Tensor:
    """The consistency distance: pseudo-Huber ``mean(sqrt((a - b)^2 + c^2) - c)`` or L2 ``mean((a - b)^2)``."""
    if kind == "huber":
        return (torch.sqrt((a.float() - b.float()) ** 2 + huber_c**2) - huber_c).mean()
    if kind == "l2":
        return F.mse_loss(a.float(), b.float())
    raise ValueError(f"unknown consistency distance {kind!r}: huber | l2")


def lcm_distillation_loss(
    student: MLDDenoiser,
    target: MLDDenoiser,
    teacher: MLDDenoiser,
    schedule: NoiseSchedule,
    z0: Tensor,
    text_emb: Tensor,
    *,
    w_range: tuple[float, float],
    num_ddim_steps: int = 10,
    kind: DistanceKind = "huber",
    huber_c: float = 0.5,
    text_tokens: Tensor | None = None,
    text_mask: Tensor | None = None,
    generator: torch.Generator | None = None,
) -> dict[str, Tensor]:
    """One step of latent consistency distillation (module docstring) on z0 (B, L, C) and captions.

    ``w_range`` (w_min, w_max): w ~ U[w_min, w_max] per sample (equal bounds: a fixed w). Randomness
    comes from ``generator`` (or torch's global RNG). Returns ``{"total", "w"}``; gradients reach the
    student only.
    """
    b = z0.shape[0]
    t, t_prev = lcm_training_timesteps(b, schedule.num_steps, num_ddim_steps, generator, z0.device)
    noise = normal(z0.shape, z0, generator)
    z_t = schedule.q_sample(z0, t, noise)
    w = w_range[0] + (w_range[1] - w_range[0]) * uniform((b,), z0, generator)
    w_emb = guidance_embedding(w)
    words = {"text_tokens": text_tokens, "text_mask": text_mask}
    # the student's parameterisation read from its EMA copy: under DDP the student is wrapped (no .config)
    kind_s, kind_t = target.config.prediction_type, teacher.config.prediction_type
    f_student = lcm_consistency_fn(schedule, student(z_t, t, text_emb, time_cond=w_emb, **words), z_t, t, kind_s)
    with torch.no_grad():
        null_mask = None if text_mask is None else torch.zeros_like(text_mask, dtype=torch.bool)
        _, eps_c = schedule.split_prediction(teacher(z_t, t, text_emb, **words), z_t, t, kind_t)
        uncond = teacher(z_t, t, teacher.null_text_like(text_emb), text_tokens=text_tokens, text_mask=null_mask)
        _, eps_u = schedule.split_prediction(uncond, z_t, t, kind_t)
        eps_w = cfg_combine(eps_u, eps_c, (1.0 + w)[:, None, None])
        z_prev = ddim_solver_step(schedule, z_t, eps_w, t, t_prev)
        f_target = lcm_consistency_fn(schedule, target(z_prev, t_prev, text_emb, time_cond=w_emb, **words),
                                      z_prev, t_prev, kind_s)
    return {"total": distance(f_student, f_target, kind, huber_c), "w": w.mean()}


def motionlcm_latents(
    student: MLDDenoiser,
    schedule: NoiseSchedule,
    text_emb: Tensor,
    num_steps: int = 1,
    w: float = 2.5,
    generator: torch.Generator | None = None,
    *,
    timesteps: Sequence[int] | None = None,
    text_tokens: Tensor | None = None,
    text_mask: Tensor | None = None,
    x_T: Tensor | None = None,
) -> Tensor:
    """MotionLCM's diffusion-space latents z0 (B, L, C) for text_emb (B, E); see :func:`sample_motionlcm`.

    ``x_T`` (B, L, C): the initial noise, instead of a draw from ``generator``. Gradients are off,
    except toward an ``x_T`` that requires grad (test-time noise optimisation differentiates through
    this function; the networks' weights are then still never trained by it).
    """
    cfg = student.config
    if timesteps is None:
        if num_steps not in TIMESTEPS:
            raise ValueError(f"MotionLCM samples with {sorted(TIMESTEPS)} steps (or explicit timesteps), "
                             f"got {num_steps}")
        timesteps = TIMESTEPS[num_steps]
    b = text_emb.shape[0]
    shape = (b, cfg.latent_tokens, cfg.latent_dim)
    cond = {"text_emb": text_emb, "time_cond": guidance_embedding(torch.full((b,), float(w), device=text_emb.device))}
    if cfg.word_tokens != "none":
        if text_tokens is None or text_mask is None:
            raise ValueError(f"this student has word_tokens={cfg.word_tokens!r}: pass text_tokens and text_mask")
        cond |= {"text_tokens": text_tokens, "text_mask": text_mask.bool()}
    with eval_mode(student), torch.set_grad_enabled(x_T is not None and x_T.requires_grad):
        return lcm_multistep_sample(student, shape, schedule, generator=generator, cond=cond, x_T=x_T,
                                    timesteps=timesteps, prediction_type=cfg.prediction_type, device=text_emb.device)


@torch.no_grad()
def sample_motionlcm(
    student: MLDDenoiser,
    vae: MotionVAE,
    schedule: NoiseSchedule,
    text_emb: Tensor,
    lengths: Tensor | Sequence[int],
    num_steps: int = 1,
    w: float = 2.5,
    generator: torch.Generator | None = None,
    *,
    timesteps: Sequence[int] | None = None,
    text_tokens: Tensor | None = None,
    text_mask: Tensor | None = None,
) -> Tensor:
    """Text-to-motion with MotionLCM: text_emb (B, E), lengths (B,) -> normalised features (B, T, D).

    ``z_T ~ N(0, I)`` from ``generator``; LCM multistep sampling over :data:`TIMESTEPS`\\[num_steps]
    (or ``timesteps``) with the embedded guidance ``w`` (the classifier-free scale minus one), one
    student pass per step (:func:`motionlcm_latents`); then ``vae.decode_by_length(latent_scale * z0, lengths)``.
    """
    z0 = motionlcm_latents(student, schedule, text_emb, num_steps, w, generator, timesteps=timesteps,
                           text_tokens=text_tokens, text_mask=text_mask)
    with eval_mode(vae):
        return vae.decode_by_length(z0 * student.config.latent_scale, lengths)
