"""Diffusion maths shared by every diffusion model in motionforge (pure torch, no I/O).

Sections: beta schedules; :class:`NoiseSchedule` (forward process, posterior, parameterisation
conversions); DDPM ancestral sampling; DDIM timestep grids, steps, sampling and inversion;
classifier-free guidance; LCM boundary scalings, DDIM-solver skip grid and multistep sampling; Wiener
estimates of x0 or the noise from a window of frames.

Conventions (the diffusers / guided-diffusion ones):

- A schedule has ``T`` steps; timesteps are integer indices ``t in 0..T-1`` into its arrays.
  ``alphas_cumprod[t] = prod_{s<=t} (1 - beta_s)`` is the signal level of ``x_t``, so ``x_0`` (index 0)
  already carries ``beta_0`` of noise and the clean sample sits "before" index 0.
- Tensors are batch-first: ``x`` has shape ``(B, ...)`` (e.g. latents ``(B, L, C)`` or features
  ``(B, frames, D)``); per-sample timesteps are int64 of shape ``(B,)`` (a Python int or a 0-d tensor is
  broadcast).
- Networks are passed to samplers as functions ``model_fn(x_t, t, **cond) -> Tensor`` of the shape of
  ``x_t``, predicting ``prediction_type``: ``"epsilon"`` (the noise), ``"sample"`` (x0) or
  ``"v_prediction"`` (``v = sqrt(ab) eps - sqrt(1 - ab) x0``, Salimans & Ho 2022). Networks never own
  samplers.
- Schedules are computed and stored in float64; values gathered at ``t`` are cast to the dtype and
  device of the tensor they multiply. A gather happens on its table's device. The samplers move their
  schedule to the device of ``x`` once (:meth:`NoiseSchedule.to`) and index it with Python ints or
  device timesteps, so that on a GPU no step reads a timestep back to the host or copies a coefficient
  to the device (each would wait for the GPU's queue to drain); only the noise a CPU generator draws is
  copied over (:mod:`models.rng`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, fields, replace
from typing import Any, Literal, NamedTuple

import torch
from torch import Tensor

from models.rng import normal, rng_device

PredictionType = Literal["epsilon", "sample", "v_prediction"]
TimestepSpacing = Literal["leading", "trailing", "linspace"]
LCMTimestepRule = Literal["strided", "linspace"]
ModelFn = Callable[..., Tensor]
Timesteps = Tensor | int

_F64 = torch.float64

# --------------------------------------------------------------------------------------------------
# Beta schedules (all return float64 betas of shape (T,))
# --------------------------------------------------------------------------------------------------


def linear_betas(
    num_steps: int, beta_start: float = 1e-4, beta_end: float = 0.02, *, rescale_to_steps: bool = False
) -> Tensor:
    """DDPM's linear schedule (Ho et al. 2020, Sec. 4): ``beta_t = linspace(beta_start, beta_end, T)``.

    MotionDiffuse uses 1e-4..0.02 with T = 1000. ``rescale_to_steps`` multiplies both ends by ``1000 / T``
    as guided-diffusion's ``get_named_beta_schedule("linear", T)`` does (so MotionDiffuse run with
    ``diffusion_steps != 1000`` keeps a comparable total noise); at T = 1000 it changes nothing.
    """
    if rescale_to_steps:
        scale = 1000.0 / num_steps
        beta_start, beta_end = beta_start * scale, beta_end * scale
    return torch.linspace(beta_start, beta_end, num_steps, dtype=_F64)


def scaled_linear_betas(num_steps: int, beta_start: float = 0.00085, beta_end: float = 0.012) -> Tensor:
    """Latent-diffusion's "scaled_linear" schedule (MLD, Stable Diffusion): linear in sqrt(beta).

    ``beta_t = linspace(sqrt(beta_start), sqrt(beta_end), T) ** 2``; MLD uses 0.00085..0.012, T = 1000.
    """
    return torch.linspace(beta_start**0.5, beta_end**0.5, num_steps, dtype=_F64) ** 2


def cosine_alpha_bar(u: Tensor, s: float = 0.008) -> Tensor:
    """Nichol & Dhariwal (2021) Eq. 17 numerator ``f(u) = cos(((u + s) / (1 + s)) * pi / 2) ** 2``, u = t/T.

    The schedule's cumulative product is ``alpha_bar(t) = f(t / T) / f(0)``.
    """
    return torch.cos((u + s) / (1 + s) * math.pi / 2) ** 2


def cosine_betas(num_steps: int, s: float = 0.008, max_beta: float = 0.999) -> Tensor:
    """Cosine schedule (Nichol & Dhariwal 2021, Eq. 17 and the beta clipping below it).

    ``beta_t = min(1 - f((t + 1) / T) / f(t / T), max_beta)`` for t = 0..T-1, so that
    ``alphas_cumprod[t] = f((t + 1) / T) / f(0)`` wherever no clipping happened (every t but the last
    for T >= 2; the last beta would be 1 and is clipped to 0.999). Used by MDM.
    """
    f = cosine_alpha_bar(torch.arange(num_steps + 1, dtype=_F64) / num_steps, s)
    return (1.0 - f[1:] / f[:-1]).clamp(max=max_beta)


def vp_alpha_bar(u: Tensor, beta_min: float = 0.1, beta_max: float = 20.0) -> Tensor:
    """Signal level of the continuous VP SDE (Song et al. 2021, Eq. 33 with a linear beta(u)).

    ``alpha_bar(u) = exp(-0.5 u^2 (beta_max - beta_min) - u beta_min)`` for u in [0, 1]; DDGAN's
    ``var_func_vp`` writes it as ``1 - var`` with ``var = 1 - exp(2 * log_mean_coeff)``,
    ``log_mean_coeff = -0.25 u^2 (beta_max - beta_min) - 0.5 u beta_min``.
    """
    return torch.exp(-0.5 * u**2 * (beta_max - beta_min) - u * beta_min)


def vp_betas(num_steps: int, beta_min: float = 0.1, beta_max: float = 20.0, eps_small: float = 1e-3) -> Tensor:
    """DDGAN's few-step discretised VP schedule (Xiao et al. 2022, ``get_sigma_schedule``), used by EMDM.

    Time points ``u_i = eps_small + (1 - eps_small) i / T`` for i = 0..T; ``beta_i = 1 -
    alpha_bar(u_i) / alpha_bar(u_{i-1})`` for i = 1..T (:func:`vp_alpha_bar`). DDGAN prepends a dummy
    ``beta_0 = 1e-8`` to its forward-process arrays and drops it in its posterior coefficients; this
    function returns the T real betas, i.e. DDGAN's posterior arrays. Hence ``alphas_cumprod[t] =
    alpha_bar(u_{t+1}) / alpha_bar(u_0)`` (telescoping), and our index t is DDGAN's ``x_{t+1}``: the
    generator sees ``(x_{t+1}, t)`` in DDGAN and ``(x_t, t)`` here, same noise level. For T = 10:
    ``alphas_cumprod[0] = 0.89469``, ``alphas_cumprod[9] = 4.319e-5``.
    """
    u = eps_small + (1.0 - eps_small) * torch.arange(num_steps + 1, dtype=_F64) / num_steps
    ab = vp_alpha_bar(u, beta_min, beta_max)
    return 1.0 - ab[1:] / ab[:-1]


_BETA_SCHEDULES: dict[str, Callable[..., Tensor]] = {
    "linear": linear_betas,
    "scaled_linear": scaled_linear_betas,
    "cosine": cosine_betas,
    "vp": vp_betas,
}


def make_betas(name: str, num_steps: int, **kwargs: Any) -> Tensor:
    """Betas (T,) float64 of a named schedule: ``linear``, ``scaled_linear``, ``cosine`` or ``vp`` (DDGAN).

    ``kwargs`` go to the schedule function (e.g. ``beta_start``/``beta_end``, ``beta_min``/``beta_max``).
    """
    if name not in _BETA_SCHEDULES:
        raise ValueError(f"unknown beta schedule {name!r}; expected one of {sorted(_BETA_SCHEDULES)}")
    if num_steps < 1:
        raise ValueError(f"num_steps must be >= 1, got {num_steps}")
    return _BETA_SCHEDULES[name](num_steps, **kwargs)


# --------------------------------------------------------------------------------------------------
# Gathering helpers
# --------------------------------------------------------------------------------------------------


def _as_long(t: Timesteps) -> Tensor:
    """``t`` as an int64 tensor where it is (a Python int: on the CPU)."""
    return torch.as_tensor(t).detach().long()


def _bcast(values: Tensor, like: Tensor) -> Tensor:
    """Per-sample values (B,) or () -> shape (B, 1, ..., 1) on ``like``'s device and dtype."""
    values = values.to(like.dtype).to(like.device)
    return values.reshape(-1, *([1] * (like.ndim - 1)))


def gather(values: Tensor, t: Timesteps, like: Tensor) -> Tensor:
    """``values[t]`` broadcast against ``like``, indexed on the table's device.

    A Python int selects without a copy; timesteps on another device than the table are moved to it (a
    read back to the host when the table is on the CPU and ``t`` on a GPU). Out-of-range timesteps raise
    an IndexError here when they are a Python int or on the CPU; on a GPU the indexing kernel refuses
    them (checking them here would read them back at every step)."""
    if isinstance(t, int):
        if not 0 <= t < values.shape[0]:
            raise IndexError(f"timestep out of range [0, {values.shape[0] - 1}]: {t}")
        return _bcast(values[t], like)
    idx = _as_long(t).to(values.device)
    if idx.device.type == "cpu" and idx.numel() and (int(idx.min()) < 0 or int(idx.max()) >= values.shape[0]):
        raise IndexError(f"timestep out of range [0, {values.shape[0] - 1}]: {idx.tolist()}")
    return _bcast(values[idx], like)


def _full_timesteps(t: int, batch: int, device: torch.device) -> Tensor:
    return torch.full((batch,), int(t), dtype=torch.long, device=device)


def split_prediction_at(
    model_out: Tensor, x_t: Tensor, alpha_cumprod: Tensor, prediction_type: PredictionType = "epsilon"
) -> tuple[Tensor, Tensor]:
    """(x0, eps) from a network output at signal level ``alpha_cumprod`` (broadcastable to ``x_t``).

    With ``x_t = sqrt(ab) x0 + sqrt(1-ab) eps`` (DDPM Eq. 4) and ``v = sqrt(ab) eps - sqrt(1-ab) x0``:
    epsilon: ``x0 = (x_t - sqrt(1-ab) eps) / sqrt(ab)``; sample: ``eps = (x_t - sqrt(ab) x0) / sqrt(1-ab)``;
    v: ``x0 = sqrt(ab) x_t - sqrt(1-ab) v``, ``eps = sqrt(1-ab) x_t + sqrt(ab) v``.
    """
    a, s = alpha_cumprod.sqrt(), (1.0 - alpha_cumprod).sqrt()
    if prediction_type == "epsilon":
        return (x_t - s * model_out) / a, model_out
    if prediction_type == "sample":
        return model_out, (x_t - a * model_out) / s
    if prediction_type == "v_prediction":
        return a * x_t - s * model_out, s * x_t + a * model_out
    raise ValueError(f"unknown prediction_type {prediction_type!r}")


# --------------------------------------------------------------------------------------------------
# NoiseSchedule
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class NoiseSchedule:
    """All per-timestep coefficients of a discrete Gaussian diffusion; every field is float64 of shape (T,).

    ``posterior_*`` describe ``q(x_{t-1} | x_t, x0) = N(coef1 x0 + coef2 x_t, posterior_variance)``
    (DDPM Eqs. 6-7): ``var = beta_t (1 - ab_{t-1}) / (1 - ab_t)``, ``coef1 = beta_t sqrt(ab_{t-1}) / (1 -
    ab_t)``, ``coef2 = (1 - ab_{t-1}) sqrt(alpha_t) / (1 - ab_t)``, with ``ab_{-1} = 1`` (so at t = 0 the
    posterior is the point mass at x0: var 0, coef1 1, coef2 0). ``posterior_log_variance_clipped``
    replaces the log of the zero variance at t = 0 by that at t = 1 (guided-diffusion); t = 0 never adds
    noise anyway.
    """

    betas: Tensor
    alphas: Tensor
    alphas_cumprod: Tensor
    alphas_cumprod_prev: Tensor
    sqrt_alphas_cumprod: Tensor
    sqrt_one_minus_alphas_cumprod: Tensor
    sqrt_recip_alphas_cumprod: Tensor
    sqrt_recipm1_alphas_cumprod: Tensor
    posterior_variance: Tensor
    posterior_log_variance_clipped: Tensor
    posterior_mean_coef1: Tensor
    posterior_mean_coef2: Tensor
    name: str = "custom"

    # ---------------------------------------------------------------------------------- construction
    @classmethod
    def from_betas(cls, betas: Tensor, name: str = "custom") -> NoiseSchedule:
        """Build every coefficient from betas (T,), each in (0, 1) (no zero-terminal-SNR schedules)."""
        betas = torch.as_tensor(betas, dtype=_F64).flatten().clone()
        if betas.numel() < 1 or bool((betas <= 0).any()) or bool((betas >= 1).any()):
            raise ValueError("betas must be a non-empty vector with values in (0, 1)")
        alphas = 1.0 - betas
        ab = torch.cumprod(alphas, 0)
        ab_prev = torch.cat([ab.new_ones(1), ab[:-1]])
        post_var = betas * (1.0 - ab_prev) / (1.0 - ab)
        log_src = torch.cat([post_var[1:2], post_var[1:]]) if len(betas) > 1 else post_var.clamp(min=1e-20)
        return cls(
            betas=betas,
            alphas=alphas,
            alphas_cumprod=ab,
            alphas_cumprod_prev=ab_prev,
            sqrt_alphas_cumprod=ab.sqrt(),
            sqrt_one_minus_alphas_cumprod=(1.0 - ab).sqrt(),
            sqrt_recip_alphas_cumprod=(1.0 / ab).sqrt(),
            sqrt_recipm1_alphas_cumprod=(1.0 / ab - 1.0).sqrt(),
            posterior_variance=post_var,
            posterior_log_variance_clipped=log_src.log(),
            posterior_mean_coef1=betas * ab_prev.sqrt() / (1.0 - ab),
            posterior_mean_coef2=(1.0 - ab_prev) * alphas.sqrt() / (1.0 - ab),
            name=name,
        )

    @classmethod
    def from_name(cls, name: str, num_steps: int, **kwargs: Any) -> NoiseSchedule:
        """E.g. ``from_name("scaled_linear", 1000)`` (MLD), ``("linear", 1000)`` (MotionDiffuse), ``("vp", 10)``."""
        return cls.from_betas(make_betas(name, num_steps, **kwargs), name=name)

    @property
    def num_steps(self) -> int:
        return int(self.betas.shape[0])

    def to(self, device: torch.device | str) -> NoiseSchedule:
        """This schedule with every table on ``device`` (itself when they are there already)."""
        device = torch.device(device)
        if self.betas.device == device:
            return self
        return replace(self, **{f.name: getattr(self, f.name).to(device) for f in fields(self) if f.name != "name"})

    # ---------------------------------------------------------------------------------- forward process
    def q_sample(self, x0: Tensor, t: Timesteps, noise: Tensor) -> Tensor:
        """Sample ``q(x_t | x0)``: ``x_t = sqrt(ab_t) x0 + sqrt(1 - ab_t) noise`` (DDPM Eq. 4). Shapes (B, ...)."""
        a, s = gather(self.sqrt_alphas_cumprod, t, x0), gather(self.sqrt_one_minus_alphas_cumprod, t, x0)
        return a * x0 + s * noise

    def q_mean_variance(self, x0: Tensor, t: Timesteps) -> tuple[Tensor, Tensor]:
        """Mean ``sqrt(ab_t) x0`` and variance ``1 - ab_t`` (broadcastable) of ``q(x_t | x0)``."""
        return gather(self.sqrt_alphas_cumprod, t, x0) * x0, gather(1.0 - self.alphas_cumprod, t, x0)

    def q_sample_pair(self, x0: Tensor, t: Timesteps, noise_prev: Tensor, noise_step: Tensor) -> tuple[Tensor, Tensor]:
        """Consecutive pair ``(x_{t-1}, x_t)`` of one forward trajectory (DDGAN's ``q_sample_pairs``).

        ``x_{t-1} ~ q(x_{t-1} | x0)`` (exactly x0 where t = 0; DDGAN's dummy beta_0 = 1e-8 adds 1e-4 noise
        there) and ``x_t = sqrt(alpha_t) x_{t-1} + sqrt(beta_t) noise_step`` (DDPM Eq. 2).
        """
        t = _as_long(t)
        prev = self.q_sample(x0, (t - 1).clamp(min=0), noise_prev)
        x_prev = torch.where(_bcast(t == 0, x0).bool(), x0, prev)
        x_t = gather(self.alphas.sqrt(), t, x0) * x_prev + gather(self.betas.sqrt(), t, x0) * noise_step
        return x_prev, x_t

    def posterior_mean_variance(self, x0: Tensor, x_t: Tensor, t: Timesteps) -> tuple[Tensor, Tensor, Tensor]:
        """Mean, variance and clipped log-variance of ``q(x_{t-1} | x_t, x0)`` (DDPM Eqs. 6-7)."""
        mean = gather(self.posterior_mean_coef1, t, x_t) * x0 + gather(self.posterior_mean_coef2, t, x_t) * x_t
        return mean, gather(self.posterior_variance, t, x_t), gather(self.posterior_log_variance_clipped, t, x_t)

    def q_posterior_sample(self, x0: Tensor, x_t: Tensor, t: Timesteps, noise: Tensor) -> Tensor:
        """Sample ``q(x_{t-1} | x_t, x0)``; no noise where t = 0 (DDGAN ``sample_posterior``, EMDM's fake x_t)."""
        mean, _, log_var = self.posterior_mean_variance(x0, x_t, t)
        nonzero = _bcast(_as_long(t) > 0, x_t)
        return mean + nonzero * (0.5 * log_var).exp() * noise

    # ---------------------------------------------------------------------------------- conversions
    def predict_x0_from_eps(self, x_t: Tensor, t: Timesteps, eps: Tensor) -> Tensor:
        """``x0 = (x_t - sqrt(1 - ab_t) eps) / sqrt(ab_t)`` (DDPM Eq. 4 solved for x0)."""
        recip = gather(self.sqrt_recip_alphas_cumprod, t, x_t)
        recipm1 = gather(self.sqrt_recipm1_alphas_cumprod, t, x_t)
        return recip * x_t - recipm1 * eps

    def predict_eps_from_x0(self, x_t: Tensor, t: Timesteps, x0: Tensor) -> Tensor:
        """``eps = (x_t - sqrt(ab_t) x0) / sqrt(1 - ab_t)``."""
        a, s = gather(self.sqrt_alphas_cumprod, t, x_t), gather(self.sqrt_one_minus_alphas_cumprod, t, x_t)
        return (x_t - a * x0) / s

    def v_from(self, x0: Tensor, eps: Tensor, t: Timesteps) -> Tensor:
        """Velocity target ``v = sqrt(ab_t) eps - sqrt(1 - ab_t) x0`` (Salimans & Ho 2022, Sec. 4)."""
        return gather(self.sqrt_alphas_cumprod, t, x0) * eps - gather(self.sqrt_one_minus_alphas_cumprod, t, x0) * x0

    def predict_x0_from_v(self, x_t: Tensor, t: Timesteps, v: Tensor) -> Tensor:
        """``x0 = sqrt(ab_t) x_t - sqrt(1 - ab_t) v``."""
        return gather(self.sqrt_alphas_cumprod, t, x_t) * x_t - gather(self.sqrt_one_minus_alphas_cumprod, t, x_t) * v

    def predict_eps_from_v(self, x_t: Tensor, t: Timesteps, v: Tensor) -> Tensor:
        """``eps = sqrt(1 - ab_t) x_t + sqrt(ab_t) v``."""
        return gather(self.sqrt_one_minus_alphas_cumprod, t, x_t) * x_t + gather(self.sqrt_alphas_cumprod, t, x_t) * v

    def split_prediction(
        self,
        model_out: Tensor,
        x_t: Tensor,
        t: Timesteps,
        prediction_type: PredictionType = "epsilon",
        clip_x0: float | None = None,
    ) -> tuple[Tensor, Tensor]:
        """(x0, eps) implied by a network output at timestep t (see :func:`split_prediction_at`).

        ``clip_x0`` clamps x0 to ``[-clip_x0, clip_x0]`` and re-derives eps from the clamped x0 (diffusers'
        ``clip_sample`` with ``use_clipped_model_output=True``). MLD and MotionDiffuse do not clip.
        """
        x0, eps = split_prediction_at(model_out, x_t, gather(self.alphas_cumprod, t, x_t), prediction_type)
        if clip_x0 is not None:
            x0 = x0.clamp(-clip_x0, clip_x0)
            eps = self.predict_eps_from_x0(x_t, t, x0)
        return x0, eps

    def prediction_target(self, x0: Tensor, noise: Tensor, t: Timesteps, prediction_type: PredictionType) -> Tensor:
        """Regression target of a network trained with ``prediction_type`` on ``x_t = q_sample(x0, t, noise)``."""
        if prediction_type == "epsilon":
            return noise
        if prediction_type == "sample":
            return x0
        if prediction_type == "v_prediction":
            return self.v_from(x0, noise, t)
        raise ValueError(f"unknown prediction_type {prediction_type!r}")


def sample_timesteps(
    batch: int, num_steps: int, generator: torch.Generator | None = None, device: torch.device | str | None = None
) -> Tensor:
    """Training timesteps ``t ~ U{0..T-1}``, int64 (B,) on ``device`` (default: the generator's), drawn on
    the generator's device (:func:`rng_device`) (MLD, MotionDiffuse)."""
    dev = _device(generator, device)
    return torch.randint(0, num_steps, (batch,), generator=generator, device=rng_device(generator, dev)).to(dev)


def condition_dropout(
    batch: int, p: float, generator: torch.Generator | None = None, device: torch.device | str | None = None
) -> Tensor:
    """Which samples lose their condition for classifier-free guidance (Ho & Salimans 2022): (B,) bool on
    ``device``, each True w.p. ``p``, decided by one uniform per sample drawn on the generator's device
    (none drawn when p <= 0). MLD, EMDM and MotionDiffuse train with it."""
    dev = _device(generator, device)
    if p <= 0:
        return torch.zeros(batch, dtype=torch.bool, device=dev)
    draw = torch.rand(batch, generator=generator, device=rng_device(generator, dev))
    return (draw < p).to(dev)


# --------------------------------------------------------------------------------------------------
# Sampling helpers
# --------------------------------------------------------------------------------------------------


class StepOutput(NamedTuple):
    """One reverse step: the next (less noisy) sample and the x0 predicted on the way."""

    prev_sample: Tensor
    pred_x0: Tensor


def _device(generator: torch.Generator | None, device: torch.device | str | None) -> torch.device:
    """Where a draw's result goes: ``device``, else the generator's device, else the CPU."""
    return torch.device(device) if device is not None else rng_device(generator, "cpu")


def _initial_noise(
    shape: Sequence[int],
    x_T: Tensor | None,
    generator: torch.Generator | None,
    device: torch.device | str | None,
    dtype: torch.dtype,
) -> Tensor:
    if x_T is not None:
        if tuple(x_T.shape) != tuple(shape):
            raise ValueError(f"x_T has shape {tuple(x_T.shape)}, expected {tuple(shape)}")
        return x_T
    dev = _device(generator, device)
    return torch.randn(tuple(shape), generator=generator, device=rng_device(generator, dev), dtype=dtype).to(dev)


# --------------------------------------------------------------------------------------------------
# DDPM
# --------------------------------------------------------------------------------------------------


def ddpm_step(
    schedule: NoiseSchedule,
    model_out: Tensor,
    x_t: Tensor,
    t: Timesteps,
    *,
    generator: torch.Generator | None = None,
    prediction_type: PredictionType = "epsilon",
    variance_type: Literal["fixed_small", "fixed_large"] = "fixed_small",
    clip_x0: float | None = None,
    noise: Tensor | None = None,
) -> StepOutput:
    """Ancestral step ``x_{t-1} ~ p(x_{t-1} | x_t) = q(x_{t-1} | x_t, x0_hat)`` (DDPM Alg. 2; Eqs. 6-7, 11).

    x0_hat comes from the network output; the variance is the posterior's (``fixed_small``, MLD and
    MotionDiffuse) or beta_t (``fixed_large``; guided-diffusion's, with beta_0 replaced by the posterior
    variance at 1). No noise is added where t = 0 (and none is drawn when every t is 0). With a
    ``"sample"`` network on :func:`vp_betas` this is exactly DDGAN/EMDM's ``sample_posterior`` step.
    """
    x0, _ = schedule.split_prediction(model_out, x_t, t, prediction_type, clip_x0)
    mean, _, log_var = schedule.posterior_mean_variance(x0, x_t, t)
    if variance_type == "fixed_large":
        large = torch.cat([schedule.posterior_variance[1:2], schedule.betas[1:]])
        log_var = gather((large if schedule.num_steps > 1 else schedule.betas).log(), t, x_t)
    elif variance_type != "fixed_small":
        raise ValueError(f"unknown variance_type {variance_type!r}")
    if isinstance(t, int):  # decided on the host (the samplers' case)
        if t == 0:
            return StepOutput(mean, x0)
        keep: Tensor | float = 1.0
    else:
        nonzero = _as_long(t) > 0
        if not bool(nonzero.any()):  # a read back to the host for timesteps on a GPU
            return StepOutput(mean, x0)
        keep = _bcast(nonzero, x_t)
    noise = normal(x_t.shape, x_t, generator) if noise is None else noise
    return StepOutput(mean + keep * (0.5 * log_var).exp() * noise, x0)


def ddpm_sample(
    model_fn: ModelFn,
    shape: Sequence[int],
    schedule: NoiseSchedule,
    generator: torch.Generator | None = None,
    *,
    prediction_type: PredictionType = "epsilon",
    cond: Mapping[str, Any] | None = None,
    x_T: Tensor | None = None,
    variance_type: Literal["fixed_small", "fixed_large"] = "fixed_small",
    clip_x0: float | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> Tensor:
    """Full ancestral sampling ``x_T ~ N(0, I)`` then :func:`ddpm_step` for t = T-1..0 (DDPM Alg. 2).

    ``shape`` is (B, ...); ``model_fn(x_t, t, **cond)`` gets int64 ``t`` of shape (B,). Returns x at
    index "-1", i.e. the final x0 prediction (the t = 0 step is noiseless). MotionDiffuse: 1000 linear
    steps, epsilon; EMDM/DDGAN (Alg. 2): ``vp`` T = 10 with an x0 ("sample") generator that draws its own
    latent z per call.
    """
    cond = dict(cond or {})
    x = _initial_noise(shape, x_T, generator, device, dtype)
    schedule = schedule.to(x.device)
    for step in reversed(range(schedule.num_steps)):
        out = model_fn(x, _full_timesteps(step, x.shape[0], x.device), **cond)
        x = ddpm_step(
            schedule, out, x, step, generator=generator, prediction_type=prediction_type,
            variance_type=variance_type, clip_x0=clip_x0,
        ).prev_sample
    return x


# --------------------------------------------------------------------------------------------------
# DDIM
# --------------------------------------------------------------------------------------------------


def ddim_timesteps(
    num_train_steps: int,
    num_inference_steps: int,
    spacing: TimestepSpacing = "leading",
    steps_offset: int = 1,
) -> Tensor:
    """Descending int64 grid of DDIM inference timesteps, exactly as diffusers' ``DDIMScheduler.set_timesteps``.

    - ``leading``: ``r = T // n``; ``arange(n) * r`` reversed, plus ``steps_offset`` (only this spacing
      uses the offset). MLD/MotionLCM configure ``steps_offset=1`` (the motionforge default; diffusers'
      own default is 0): 1000 train / 50 steps -> [981, 961, ..., 21, 1]. Note that few steps start far
      from pure noise: n = 1 -> [1], n = 2 -> [501, 1], n = 4 -> [751, 501, 251, 1].
    - ``trailing``: ``r = T / n``; ``round(arange(T, 0, -r)) - 1`` -> 50 steps: [999, 979, ..., 19];
      n = 1 -> [999].
    - ``linspace``: ``round(linspace(0, T - 1, n))`` reversed.
    """
    n, big_t = num_inference_steps, num_train_steps
    if not 1 <= n <= big_t:
        raise ValueError(f"num_inference_steps must be in [1, {big_t}], got {n}")
    if spacing == "leading":
        ts = torch.arange(n, dtype=_F64).mul(big_t // n).round().flip(0) + steps_offset
    elif spacing == "trailing":
        ts = (big_t - torch.arange(n, dtype=_F64) * (big_t / n)).round() - 1
    elif spacing == "linspace":
        ts = torch.linspace(0, big_t - 1, n, dtype=_F64).round().flip(0)
    else:
        raise ValueError(f"unknown timestep spacing {spacing!r}")
    ts = ts.long()
    if int(ts.max()) >= big_t or int(ts.min()) < 0:
        raise ValueError(f"DDIM grid {ts.tolist()} leaves [0, {big_t - 1}] (steps_offset={steps_offset})")
    return ts


def final_alpha_cumprod(schedule: NoiseSchedule, set_alpha_to_one: bool = False) -> Tensor:
    """Signal level after the last DDIM step (diffusers' ``final_alpha_cumprod``), float64 () on the schedule's
    device (no read back to the host).

    ``set_alpha_to_one=True``: 1.0, the last step lands on the clean x0 prediction.
    ``set_alpha_to_one=False`` (MLD/MotionLCM, Stable Diffusion): ``alphas_cumprod[0]``, the last step
    lands on the noise level of timestep 0, so the output keeps ``sqrt(1 - ab_0)`` (0.029 for
    scaled_linear) of the current eps estimate.
    """
    return schedule.alphas_cumprod.new_ones(()) if set_alpha_to_one else schedule.alphas_cumprod[0]


def _alpha_cumprod_or_final(schedule: NoiseSchedule, t: Timesteps, like: Tensor, set_alpha_to_one: bool) -> Tensor:
    """``alphas_cumprod[t]`` where t >= 0, :func:`final_alpha_cumprod` where t < 0 (the step after the last
    one), both taken on the table's device."""
    table, final = schedule.alphas_cumprod, final_alpha_cumprod(schedule, set_alpha_to_one)
    if isinstance(t, int):
        return _bcast(table[t] if t >= 0 else final, like)
    idx = _as_long(t).to(table.device)
    return _bcast(torch.where(idx >= 0, table[idx.clamp(min=0)], final), like)


def ddim_step(
    schedule: NoiseSchedule,
    model_out: Tensor,
    x_t: Tensor,
    t: Timesteps,
    t_prev: Timesteps,
    *,
    eta: float = 0.0,
    generator: torch.Generator | None = None,
    prediction_type: PredictionType = "epsilon",
    set_alpha_to_one: bool = False,
    clip_x0: float | None = None,
    noise: Tensor | None = None,
) -> StepOutput:
    """DDIM step from t to t_prev (Song et al. 2021, Eq. 12 with sigma from Eq. 16).

    ``x_prev = sqrt(ab_prev) x0 + sqrt(1 - ab_prev - sigma^2) eps + sigma z``,
    ``sigma = eta sqrt((1 - ab_prev) / (1 - ab_t)) sqrt(1 - ab_t / ab_prev)``. ``t_prev < 0`` marks the last
    step, whose ab_prev is :func:`final_alpha_cumprod`. eta = 0 is deterministic and draws nothing from
    ``generator``; eta = 1 is DDPM-like ancestral sampling on the sub-grid.
    """
    x0, eps = schedule.split_prediction(model_out, x_t, t, prediction_type, clip_x0)
    ab_t = gather(schedule.alphas_cumprod, t, x_t)
    ab_prev = _alpha_cumprod_or_final(schedule, t_prev, x_t, set_alpha_to_one)
    sigma = eta * ((1.0 - ab_prev) / (1.0 - ab_t) * (1.0 - ab_t / ab_prev)).clamp(min=0).sqrt()
    prev = ab_prev.sqrt() * x0 + (1.0 - ab_prev - sigma**2).clamp(min=0).sqrt() * eps
    if eta > 0:
        noise = normal(x_t.shape, x_t, generator) if noise is None else noise
        prev = prev + sigma * noise
    return StepOutput(prev, x0)


def _grid(
    schedule: NoiseSchedule,
    num_steps: int,
    timesteps: Sequence[int] | Tensor | None,
    spacing: TimestepSpacing,
    steps_offset: int,
) -> list[int]:
    if timesteps is not None:
        return [int(t) for t in timesteps]
    return ddim_timesteps(schedule.num_steps, num_steps, spacing, steps_offset).tolist()


def ddim_sample(
    model_fn: ModelFn,
    shape: Sequence[int],
    schedule: NoiseSchedule,
    num_steps: int = 50,
    eta: float = 0.0,
    generator: torch.Generator | None = None,
    prediction_type: PredictionType = "epsilon",
    *,
    cond: Mapping[str, Any] | None = None,
    x_T: Tensor | None = None,
    timestep_spacing: TimestepSpacing = "leading",
    steps_offset: int = 1,
    set_alpha_to_one: bool = False,
    timesteps: Sequence[int] | Tensor | None = None,
    clip_x0: float | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> Tensor:
    """DDIM sampling over :func:`ddim_timesteps` (or an explicit descending ``timesteps`` list).

    Each step goes from a grid timestep to the next one on the grid (for T divisible by n this equals
    diffusers' ``prev = t - T // n``), the last one to :func:`final_alpha_cumprod`. Defaults are MLD's
    (``leading``, ``steps_offset=1``, ``set_alpha_to_one=False``, 50 steps, eta 0, epsilon). ``shape`` is
    (B, ...); the initial noise is ``x_T`` or N(0, I) (``init_noise_sigma`` 1).
    """
    cond = dict(cond or {})
    grid = _grid(schedule, num_steps, timesteps, timestep_spacing, steps_offset)
    x = _initial_noise(shape, x_T, generator, device, dtype)
    schedule = schedule.to(x.device)
    for i, step in enumerate(grid):
        t_prev = grid[i + 1] if i + 1 < len(grid) else -1
        out = model_fn(x, _full_timesteps(step, x.shape[0], x.device), **cond)
        x = ddim_step(
            schedule, out, x, step, t_prev, eta=eta, generator=generator, prediction_type=prediction_type,
            set_alpha_to_one=set_alpha_to_one, clip_x0=clip_x0,
        ).prev_sample
    return x


def ddim_invert(
    model_fn: ModelFn,
    x0: Tensor,
    schedule: NoiseSchedule,
    num_steps: int = 50,
    prediction_type: PredictionType = "epsilon",
    *,
    cond: Mapping[str, Any] | None = None,
    timestep_spacing: TimestepSpacing = "leading",
    steps_offset: int = 1,
    set_alpha_to_one: bool = False,
    timesteps: Sequence[int] | Tensor | None = None,
) -> Tensor:
    """Deterministic DDIM inversion: run the eta = 0 update upwards along the same grid.

    Starts at the level where :func:`ddim_sample` ends (:func:`final_alpha_cumprod`) and moves level a ->
    next level b using the network at a (timestep 0 for the final level): ``x_b = sqrt(ab_b) x0_hat +
    sqrt(1 - ab_b) eps_hat``. It inverts ``ddim_sample`` up to the discretisation error of the ODE, which
    vanishes in the small-step limit for a smooth model.
    """
    cond = dict(cond or {})
    grid = _grid(schedule, num_steps, timesteps, timestep_spacing, steps_offset)[::-1]
    x = x0
    schedule = schedule.to(x.device)
    levels = [-1, *grid]
    for a, b in zip(levels[:-1], levels[1:], strict=True):
        ab_a = _alpha_cumprod_or_final(schedule, a, x, set_alpha_to_one)
        out = model_fn(x, _full_timesteps(max(a, 0), x.shape[0], x.device), **cond)
        x0_hat, eps_hat = split_prediction_at(out, x, ab_a, prediction_type)
        ab_b = gather(schedule.alphas_cumprod, b, x)
        x = ab_b.sqrt() * x0_hat + (1.0 - ab_b).sqrt() * eps_hat
    return x


# --------------------------------------------------------------------------------------------------
# Classifier-free guidance
# --------------------------------------------------------------------------------------------------


def cfg_combine(out_uncond: Tensor, out_cond: Tensor, scale: float | Tensor) -> Tensor:
    """Classifier-free guidance (Ho & Salimans 2022, Eq. 6): ``uncond + scale * (cond - uncond)``.

    scale 1 returns cond; 0 returns uncond. MLD uses 7.5 on eps, EMDM 2.5 on x0. MotionLCM's teacher
    writes ``cond + w (cond - uncond)``, which is this with ``scale = 1 + w``. A tensor scale must
    broadcast against the outputs (e.g. (B, 1, 1) for per-sample w).
    """
    return out_uncond + scale * (out_cond - out_uncond)


def _stack_pair(key: str, uncond: Any, cond: Any, batch: int) -> Any:
    """Concatenate the unconditional and conditional value of one keyword along the batch, uncond first."""
    if isinstance(cond, Tensor) and cond.ndim > 0 and cond.shape[0] == batch:
        u = torch.as_tensor(uncond, dtype=cond.dtype, device=cond.device)
        if u.shape[0] == 1 and batch != 1:
            u = u.expand(batch, *u.shape[1:])
        if u.shape != cond.shape:
            raise ValueError(f"cond {key!r}: unconditional shape {tuple(u.shape)}, expected {tuple(cond.shape)}")
        return torch.cat([u, cond], 0)
    if isinstance(cond, list | tuple) and len(cond) == batch:
        u = list(uncond) * batch if len(uncond) == 1 and batch != 1 else list(uncond)
        if len(u) != batch:
            raise ValueError(f"cond {key!r}: unconditional list has length {len(u)}, expected {batch}")
        return type(cond)([*u, *cond])
    if uncond is cond or (not isinstance(cond, Tensor) and uncond == cond):
        return cond
    raise ValueError(f"cond {key!r} is not batched (B={batch}) and differs when unconditional; use batched=False")


def classifier_free_guidance(
    model_fn: ModelFn, scale: float, uncond: Mapping[str, Any], *, batched: bool = True
) -> ModelFn:
    """Wrap a conditional ``model_fn(x, t, **cond)`` into a guided one with the same signature.

    ``uncond`` gives the keyword values of the unconditional pass (e.g. ``{"text_emb": null_emb}``,
    null_emb (1, D) or (B, D)); keywords it does not name are shared. ``batched=True`` runs one
    network call on the doubled batch ``[uncond; cond]`` (MLD; tensors/lists with batch B are
    concatenated, other values must be equal), ``batched=False`` two calls (EMDM, where the
    unconditional pass is a flag such as ``{"force_mask": True}``). The network outputs are combined by
    :func:`cfg_combine`; scale 1 skips the unconditional pass.
    """

    def guided(x: Tensor, t: Tensor, **cond: Any) -> Tensor:
        if isinstance(scale, int | float) and scale == 1.0:
            return model_fn(x, t, **cond)
        uncond_kwargs = {**cond, **uncond}
        if not batched:
            return cfg_combine(model_fn(x, t, **uncond_kwargs), model_fn(x, t, **cond), scale)
        missing = set(uncond) - set(cond)
        if missing:
            raise ValueError(f"unconditional keywords {sorted(missing)} are not model inputs; use batched=False")
        b = x.shape[0]
        kwargs = {k: _stack_pair(k, uncond_kwargs[k], v, b) for k, v in cond.items()}
        t2 = torch.cat([t, t]) if isinstance(t, Tensor) and t.ndim > 0 else t
        out_u, out_c = model_fn(torch.cat([x, x]), t2, **kwargs).chunk(2)
        return cfg_combine(out_u, out_c, scale)

    return guided


# --------------------------------------------------------------------------------------------------
# Latent consistency models (LCM / MotionLCM)
# --------------------------------------------------------------------------------------------------


def lcm_boundary_scalings(
    t: Timesteps | float, sigma_data: float = 0.5, timestep_scaling: float = 10.0
) -> tuple[Tensor, Tensor]:
    """Consistency-model skip/out scalings on integer timesteps (LCM Eq. 9; MotionLCM; diffusers LCM).

    ``c_skip = sd^2 / ((s t)^2 + sd^2)``, ``c_out = s t / sqrt((s t)^2 + sd^2)`` with sd = sigma_data = 0.5
    and s = timestep_scaling = 10 (diffusers <= 0.24 writes ``t / 0.1``). Boundary: c_skip(0) = 1,
    c_out(0) = 0, so ``f(x, 0) = x``; c_skip(1) = 0.25 / 100.25 = 0.0024938, c_out(1) = 10 / sqrt(100.25)
    = 0.9987523; c_skip(99) = 2.6e-7. Returns float64 tensors of t's shape.
    """
    scaled = torch.as_tensor(t, dtype=_F64) * timestep_scaling
    denom = scaled**2 + sigma_data**2
    return sigma_data**2 / denom, scaled / denom.sqrt()


def lcm_consistency_fn(
    schedule: NoiseSchedule,
    model_out: Tensor,
    x_t: Tensor,
    t: Timesteps,
    prediction_type: PredictionType = "epsilon",
    *,
    sigma_data: float = 0.5,
    timestep_scaling: float = 10.0,
) -> Tensor:
    """Consistency output ``f(x_t, t) = c_skip(t) x_t + c_out(t) x0_hat`` (LCM Eq. 9), x0_hat from the network.

    Used for the student and the EMA target during distillation and as the LCM denoiser at sampling.
    """
    x0, _ = schedule.split_prediction(model_out, x_t, t, prediction_type)
    c_skip, c_out = lcm_boundary_scalings(_as_long(t), sigma_data, timestep_scaling)
    return _bcast(c_skip, x_t) * x_t + _bcast(c_out, x_t) * x0


def lcm_solver_timesteps(num_train_steps: int = 1000, num_ddim_steps: int = 50) -> Tensor:
    """Ascending DDIM-solver grid of LCM distillation: ``arange(1, N + 1) * k - 1`` with skip ``k = T // N``.

    1000/50 -> k = 20, [19, 39, ..., 999] (LCM, MotionLCM V1); 1000/10 -> k = 100, [99, ..., 999] (V2).
    """
    if not 1 <= num_ddim_steps <= num_train_steps:
        raise ValueError(f"num_ddim_steps must be in [1, {num_train_steps}], got {num_ddim_steps}")
    k = num_train_steps // num_ddim_steps
    return torch.arange(1, num_ddim_steps + 1, dtype=torch.long) * k - 1


def lcm_training_timesteps(
    batch: int,
    num_train_steps: int = 1000,
    num_ddim_steps: int = 50,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
) -> tuple[Tensor, Tensor]:
    """Distillation pair ``(t_{n+k}, t_n)``, int64 (B,) each: a uniform grid point and ``max(t - k, 0)``.

    ``t_n`` is the previous grid point, or 0 at the first one (where MotionLCM's solver then uses
    ``alphas_cumprod[0]`` and the target's c_skip(0) = 1 makes ``f(z_n, 0) = z_n``).
    """
    dev = _device(generator, device)
    grid = lcm_solver_timesteps(num_train_steps, num_ddim_steps).to(dev)
    idx = torch.randint(0, num_ddim_steps, (batch,), generator=generator, device=rng_device(generator, dev))
    t = grid[idx.to(dev)]
    return t, (t - num_train_steps // num_ddim_steps).clamp(min=0)


def ddim_solver_step(
    schedule: NoiseSchedule, x_t: Tensor, eps: Tensor, t: Timesteps, t_prev: Timesteps, x0: Tensor | None = None
) -> Tensor:
    """One deterministic DDIM step of the distillation ODE solver, t -> t_prev (both >= 0).

    ``z_prev = sqrt(ab_prev) x0 + sqrt(1 - ab_prev) eps`` with ``x0 = (x_t - sqrt(1 - ab_t) eps) / sqrt(ab_t)``
    unless given. Guiding the teacher's eps with :func:`cfg_combine` and deriving x0 from the guided eps
    equals MotionLCM's separate guidance of x0 and eps (both are affine in the network output).
    """
    if x0 is None:
        x0 = schedule.predict_x0_from_eps(x_t, t, eps)
    ab_prev = gather(schedule.alphas_cumprod, t_prev, x_t)
    return ab_prev.sqrt() * x0 + (1.0 - ab_prev).sqrt() * eps


def lcm_timesteps(
    num_inference_steps: int,
    num_train_steps: int = 1000,
    original_steps: int = 50,
    rule: LCMTimestepRule = "strided",
) -> Tensor:
    """Descending LCM inference timesteps, chosen on the solver grid from ``T - 1`` down (diffusers ``LCMScheduler``).

    The candidates are :func:`lcm_solver_timesteps` (``original_inference_steps`` N, skip k = T // N)
    reversed: [999, 979, ..., 19] for 1000/50.
    - ``strided`` (diffusers <= 0.24, pinned by MotionLCM V1): every ``N // n``-th candidate starting at
      the first, first n of them: 1 -> [999], 2 -> [999, 499], 4 -> [999, 759, 519, 279].
    - ``linspace`` (diffusers >= 0.25): candidates at ``floor(linspace(0, N, n, endpoint=False))``:
      1 -> [999], 2 -> [999, 499], 4 -> [999, 759, 499, 259].
    MotionLCM V2 instead fixes lists ([799], [699, 299], [699, 399, 299, 299]); pass those to
    :func:`lcm_multistep_sample` as ``timesteps``.
    """
    candidates = lcm_solver_timesteps(num_train_steps, original_steps).flip(0)
    n = num_inference_steps
    if not 1 <= n <= original_steps:
        raise ValueError(f"num_inference_steps must be in [1, {original_steps}], got {n}")
    if rule == "strided":
        return candidates[:: original_steps // n][:n].clone()
    if rule == "linspace":
        idx = torch.floor(torch.arange(n, dtype=_F64) * (original_steps / n)).long()
        return candidates[idx].clone()
    raise ValueError(f"unknown LCM timestep rule {rule!r}")


def lcm_multistep_sample(
    model_fn: ModelFn,
    shape: Sequence[int],
    schedule: NoiseSchedule,
    num_steps: int = 1,
    generator: torch.Generator | None = None,
    prediction_type: PredictionType = "epsilon",
    *,
    cond: Mapping[str, Any] | None = None,
    x_T: Tensor | None = None,
    original_steps: int = 50,
    rule: LCMTimestepRule = "strided",
    timesteps: Sequence[int] | Tensor | None = None,
    sigma_data: float = 0.5,
    timestep_scaling: float = 10.0,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> Tensor:
    """LCM multistep sampling (LCM Alg. 3; diffusers ``LCMScheduler.step``).

    ``x ~ N(0, I)``; for each timestep t_i of :func:`lcm_timesteps` (or ``timesteps``):
    ``denoised = f(x, t_i)`` (:func:`lcm_consistency_fn`); if a next timestep exists re-noise
    ``x = sqrt(ab_{t_{i+1}}) denoised + sqrt(1 - ab_{t_{i+1}}) z`` with fresh z from ``generator``,
    otherwise return ``denoised``. One network call per step; guidance lives inside the student (its
    w-embedding is part of ``cond``), so no CFG pass is made here.
    """
    cond = dict(cond or {})
    grid = [int(t) for t in timesteps] if timesteps is not None else lcm_timesteps(
        num_steps, schedule.num_steps, original_steps, rule
    ).tolist()
    x = _initial_noise(shape, x_T, generator, device, dtype)
    schedule = schedule.to(x.device)
    for i, step in enumerate(grid):
        t = _full_timesteps(step, x.shape[0], x.device)
        out = model_fn(x, t, **cond)
        denoised = lcm_consistency_fn(
            schedule, out, x, t, prediction_type, sigma_data=sigma_data, timestep_scaling=timestep_scaling
        )
        if i + 1 == len(grid):
            return denoised
        x = schedule.q_sample(denoised, grid[i + 1], normal(denoised.shape, denoised, generator))
    return x


# --------------------------------------------------------------------------------------------------
# Linear (Wiener) estimates of x0 or the noise from a window of frames (the input skips of EMDM and
# MotionDiffuse)
# --------------------------------------------------------------------------------------------------


def lag_moments(motions: Sequence[Tensor], lags: int) -> Tensor:
    """(lags, D) ``E[x[n, d] x[n + j, d]]`` for j < lags over every pair of frames within each motion (T_i, D)."""
    sums, counts = torch.zeros(lags, motions[0].shape[-1], dtype=_F64), torch.zeros(lags, 1, dtype=_F64)
    for x in motions:
        x = x.double()
        for j in range(min(lags, len(x))):
            sums[j] += (x[: len(x) - j] * x[j:]).sum(0)
            counts[j] += len(x) - j
    if bool((counts == 0).any()):
        raise ValueError(f"motions too short for {lags} lags")
    return (sums / counts).float()


def wiener_taps(moments: Tensor, alphas_cumprod: Tensor, kernel: int, *, target: Literal["x0", "epsilon"] = "x0",
                eig_floor: float = 0.0) -> Tensor:
    """Per-level, per-feature Wiener taps (T, D, k): the least-squares linear estimate of ``target`` at the
    centre frame from a window of k frames of ``x = a x0 + s eps``.

    ``moments`` (L, D), L >= k: ``m_d(j) = E[x0[n, d] x0[n + j, d]]`` of the normalised training
    features (:func:`lag_moments`); ``alphas_cumprod`` (T,): the level ``a^2`` of each input. With R_d
    the k x k Toeplitz matrix of m_d, C = a^2 R_d + s^2 I the window's covariance and e the centre:

    - ``target="x0"``: ``C^-1 a R_d e``; uncorrelated unit-variance frames give ``a`` at the centre.
    - ``target="epsilon"``: ``C^-1 s e`` (the noise is white, so it correlates with the centre frame
      only); uncorrelated unit-variance frames give ``s`` at the centre.

    Lag moments pooled over motions of different lengths need not form a positive semi-definite R_d
    (the HumanML3D features' lowest eigenvalues are negative), and near the data (s -> 0) C is then
    singular and the taps explode. ``eig_floor`` > 0 raises R_d's eigenvalues to at least
    ``eig_floor * m_d(0)`` first, as if the data carried that much white noise of their own.
    """
    if kernel < 1 or kernel % 2 == 0 or moments.ndim != 2 or moments.shape[0] < kernel:
        raise ValueError(f"need an odd kernel >= 1 and moments (L >= kernel, D); got kernel={kernel}, "
                         f"moments {tuple(moments.shape)}")
    if target not in ("x0", "epsilon"):
        raise ValueError(f"target must be 'x0' or 'epsilon', got {target!r}")
    if eig_floor < 0:
        raise ValueError(f"eig_floor must be >= 0, got {eig_floor!r}")
    m = moments.double()
    lag = (torch.arange(kernel)[:, None] - torch.arange(kernel)[None]).abs()
    r = m[lag].permute(2, 0, 1)  # (D, k, k) Toeplitz per feature
    if eig_floor > 0:
        values, vectors = torch.linalg.eigh(r)
        values = torch.maximum(values, eig_floor * m[0][:, None])
        r = vectors @ torch.diag_embed(values) @ vectors.transpose(-1, -2)
    a = alphas_cumprod.double().sqrt()[:, None, None, None]
    s2 = (1.0 - alphas_cumprod.double())[:, None, None, None]
    cov = a**2 * r[None] + s2 * torch.eye(kernel, dtype=_F64)
    if target == "x0":
        cross = a * r[None, :, :, kernel // 2 : kernel // 2 + 1]
    else:
        centre = torch.zeros(kernel, 1, dtype=_F64)
        centre[kernel // 2] = 1.0
        cross = s2.sqrt() * centre
    return torch.linalg.solve(cov, cross.expand(*cov.shape[:-1], 1))[..., 0].float()
