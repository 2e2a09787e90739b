"""EMDM: a conditional denoising-diffusion GAN for few-step text/action-to-motion (pure torch).

Paper: Zhou et al., "EMDM: Efficient Motion Diffusion Model for Fast and High-Quality Motion
Generation" (``shared/papers/000_*.txt``): Sec. 3.1 (Eqs. 3-12), Sec. 3.2 (Eq. 13, Algs. 1-2),
Appendix C (architectures, Eqs. 14-16) and D; the released code as summarised in
``reference/emdm_motiondiffuse.md`` section 1; DDGAN (Xiao et al. 2022) for the schedule. Shapes:
B batch, N frames (padded), D feature dims (263), h transformer width. Features are the normalised
HumanML3D vectors; padded frames are those at or after each sample's length.

Contents:

- :class:`EMDMSchedule`: the few-step VP schedule (T = 10), forward pairs and the posterior
  ``q(x_t | x_{t+1}, x0)`` (Alg. 2); :func:`q_sample_pairs` draws DDGAN's training pairs.
- :class:`EMDMConfig`, :class:`EMDMGenerator` ``G(x_{t+1}, t, z, c) -> x0_hat`` (Eq. 3) and
  :class:`EMDMDiscriminator` ``D(x_t, x_{t+1}, t, c) -> logit`` (Eqs. 4-5).
- Losses: :func:`d_adversarial_loss` (Eq. 4), :func:`g_adversarial_loss` (Eq. 6), :func:`r1_penalty`
  (Eq. 16) with :func:`lazy_r1_scale`, :func:`geometric_losses` (Eqs. 7-12), and the two per-step
  compositions :func:`discriminator_step_losses` / :func:`generator_step_losses` (Eqs. 14-15).
- Sampling: :func:`guided_x0` (Eq. 13) and :func:`sample_emdm` (Alg. 1), which computes G's
  condition part (:meth:`EMDMGenerator.conditioning`, :func:`guidance_batch`) once, not per step.

Indexing (DDGAN's, which the code of both papers uses). States are levels ``k = 0..T``: ``x_0`` is
the data, ``x_T`` ~ N(0, I). A step index ``t in 0..T-1`` names the transition ``x_t -> x_{t+1}``:
a training pair is ``(x_t, x_{t+1})`` (the paper's ``(x_{t-1}, x_t)``), the generator sees
``(x_{t+1}, t)`` and the posterior at ``t`` maps ``x_{t+1}`` to ``x_t``; sampling runs
``t = T-1, ..., 0`` and the step at ``t = 0`` returns ``x0_hat`` exactly.

Choices where the paper (or its code) is ambiguous or where we depart from it, each deliberate:

1. Schedule: the data level ``x_0`` is exactly x0. DDGAN prepends a dummy ``beta_0 = 1e-8`` to its
   forward arrays, which leaves 1e-4 noise on ``x_0``; we drop it (as ``models.diffusion`` does), so
   ``alpha_bar_k = alpha_bar(u_k) / alpha_bar(u_0)`` and the posterior tables equal DDGAN's.
   ``posterior_log_variance[0] = log(1e-20)`` as in DDGAN (its variance is 0; no noise is added).
2. Generator: the released code's plain post-LN encoder stack (``nn.TransformerEncoder``), not the
   "skip connections" that Sec. 4.1 mentions; SELU feed-forward activation (App. C.1); the timestep
   token is ``MLP(sinusoid_h(t))`` of the integer step (MDM/EMDM code); the z token comes from a
   5-layer mapping network ``[Linear, LeakyReLU(0.2)] x 5``; sinusoidal positions on all tokens;
   unlike the code, padded frames are masked as attention keys and the output is 0 at padding.
3. Condition dropout (Sec. 3.2, 10%): a dropped sample's condition token is a learned null token
   (zero-initialised), for text and action alike; the code zeroes the CLIP feature before the
   Linear, i.e. a fixed null token equal to that Linear's bias. Dropout is decided outside the
   network (:func:`models.diffusion.condition_dropout`) and passed as ``drop_cond``, so the training
   step owns its randomness. The discriminator always sees the real condition (never dropped), as in the code.
4. Discriminator: the paper's D is a 7-layer MLP over the flattened padded tensors with no masking
   (App. C.2), so padding leaks into it. Ours is a small transformer over the frames of
   ``Linear([x_t; x_{t+1}])`` plus a timestep token (a 128-d sinusoid, then dense-LeakyReLU-dense, as
   DDGAN's; its frequencies are ``exp(-ln(1e4) i / 64)`` where DDGAN divides by 63, which the MLP absorbs)
   and a condition token (text: Linear of the raw pooled embedding; action: a learned table, i.e. a
   Linear of the one-hot), padded frames masked as keys and excluded from a masked mean pool, then
   an MLP head to one logit. Padding therefore cannot change D's output.
5. R1 (Eq. 16): ``gamma/2 * E_b sum_{valid entries} (dD/dx_t)^2`` on the real ``x_t`` (padded
   frames excluded), gamma = 0.02. Lazy regularisation as in StyleGAN2 (Karras et al. 2020, Sec.
   3.1): applied every k = 15 D steps and multiplied by k, so that its average strength equals
   gamma applied every step. (EMDM's code applies it every 15 steps without the factor k; StyleGAN2
   also rescales Adam's lr and betas by k/(k+1), which is the optimiser's business, not done here.)
   The R1 forward runs attention through PyTorch's "math" kernel: the fused CPU/CUDA kernels have
   no double backward.
6. Geometric loss (Eqs. 7-12): ``R * (L_recon + lambda (L_pos + L_vel + L_foot))``. Every term is a
   masked mean: squared error summed over valid frames (or valid consecutive pairs) and elements,
   divided by their count, per sample, then averaged over the batch (MDM's ``masked_l2``).
   ``L_recon`` on the normalised features; ``L_pos`` on global joints ``recover_from_ric`` of the
   denormalised features (the feature representation has no rotations-to-FK path that the paper's
   FK needs, and recovery is causal, so padding cannot leak into valid frames); ``L_vel`` on joint
   velocities (frame differences of those joints, pairs with both frames valid; Eq. 10 writes it on
   x, the issue asks for joints); ``L_foot`` (Eq. 9) penalises the predicted velocity of the four
   foot joints (ankles, toes) from frame i to i+1 where the ground-truth contact label of frame i
   (the features' contacts group, denormalised and thresholded at 0.5) is on; HumanML3D defines
   that label from the same i -> i+1 displacement. R = 100 for text, 1 for action (Sec. 5.2);
   lambda defaults to 1 (the paper uses 1 for action, 0 for text: set ``geo_lambda``). Ours: the foot
   term may take its own weight (``geo_foot_lambda``; None: lambda). Unlike ``L_pos``, which compares
   global positions and so grows with any early heading error, ``L_foot`` is a speed, which a heading
   error does not change; it is the term that says a planted foot does not slide.
7. One generator step uses ONE draw of (t, pair, z) for both the adversarial and the geometric
   term (the code draws them independently, which costs a second G forward). The fake ``x_t`` of
   the D step is computed without gradient into G (the code builds that graph and discards it).
8. Classifier-free guidance (Eq. 13) on x0 with the same z for both passes; the unconditional and
   conditional passes run in one forward on the doubled batch; guidance 1 runs the conditional
   pass only.
9. Frame patches (``patch_frames`` P, ours; the paper's P is 1, one token per frame as MDM): G and
   D may read and write P consecutive frames per token (``Linear(P D -> h)`` in, ``Linear(h -> P D)``
   out, as ViT patches), so attention and the per-token layers run on N / P tokens. Sequences are
   zero-padded to a multiple of P; a token is valid when its first frame is, padded frames are
   zeroed on input and output, and patch boundaries sit at multiples of P from frame 0, so the valid
   frames' outputs do not depend on the amount of padding. At 20 fps motion is smooth over 4
   frames; the small CPU profile uses P = 4 to fit its time budget, the ``paper`` profile P = 1.
   ``overlap_out`` (ours; P even): G's output layer writes 2P frames per token, centred on its patch
   and tapered by a triangular window, and neighbouring tokens' frames are added
   (:func:`models.patches.from_patches_overlapped`), so no frame-to-frame step sits at a patch
   boundary: with plain patches the joints' acceleration there was 1.4 times that inside a patch
   (docs/emdm.md, "Roughness").
10. Input skip (``input_skip``, ours; off in the paper): ``x0_hat = G_out + s_t * x_{t+1}`` with a
   learned scalar ``s_t`` per step, initialised to ``sqrt(alpha_bar_{t+1})``: the least-squares
   linear estimate of x0 from ``x_{t+1}`` for unit-variance data (the features are normalised), as
   EDM's c_skip (Karras et al. 2022). Near the data (small t) x0 is almost ``x_{t+1}``: the paper's
   G must carry every one of the D feature values through its width-h tokens to reproduce it, which
   its h = 1024 > 263 allows and a small CPU width (or P D > h with patches) does not. The skip
   carries it around the network, which then models the correction.
   ``skip_kernel`` k > 1 (ours) widens the scalar into a per-step, per-feature filter over k
   neighbouring frames, ``x0_hat = G_out + sum_j s_{t,d,j} x_{t+1}[n + j - k // 2, d]`` (padded frames
   and the ends read as 0), initialised by the training recipe to the Wiener filter: the least-squares
   linear estimate of x0 from the window under the training features' lag moments
   (:func:`models.diffusion.wiener_taps`; with uncorrelated frames it is the scalar ``sqrt(alpha_bar)`` at the
   centre). The scalar passes s_t times the noise of x_{t+1} into x0_hat, frame by frame: jitter in
   every sample, whose last step returns the level-1 estimate. Motion is smooth over neighbouring
   frames, so the window's estimate is a temporal low-pass that leaves most of that noise out.
11. Word tokens (``word_tokens``, ours; the paper: False): every layer of G cross-attends to the
   caption's word-token states (``Linear(token_dim -> h)``, sinusoidal positions) behind the pooled
   condition token, as ``models.mld`` does for MLD. Padded words are masked; a dropped condition
   (training dropout, CFG's unconditional pass) masks every word, so the memory is the null token
   alone and the unconditional model cannot read the caption. D keeps the pooled embedding only.
   An action label has no words: an action G with ``word_tokens`` cross-attends to its label token
   and to ``label_words`` fixed word slots per label (buffers, not trained), which start empty (masked)
   and which :func:`action_from_text` fills with the word-token states of one training caption of the
   class. Without them (``label_words`` 0, or an empty label) it reads its label token alone. Its
   layers have the text G's shapes, so a trained text G can start it: a text G trained long enough
   reads the words more than the pooled token, and given the pooled token alone it loses the action
   (docs/emdm.md, 2026-12-05).
12. Text normalisation (``text_norm``, ours; the paper: False): G's and D's condition tokens are
   ``Linear(LayerNorm(e))`` of the pooled embedding e (no affine), i.e. unit variance per dimension
   whatever the encoder's scale. A unit-norm sentence embedding (MiniLM's) has entries of about
   1 / sqrt(E); through a default-initialised Linear its token is then an order of magnitude smaller
   than the sinusoidal position added to it, and the condition starts almost unread.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, Literal, NamedTuple

import numpy as np
import torch
from torch import Tensor, nn
from torch.nn import functional as F
from torch.nn.attention import SDPBackend, sdpa_kernel

from data.features import feature_groups, recover_from_ric
from data.skeleton import SKELETONS
from models.diffusion import cfg_combine, condition_dropout, gather, sample_timesteps
from models.patches import from_output_patches, output_width, to_patches
from models.rng import normal
from models.transformer import (
    PositionalEncoding,
    TransformerLayer,
    checked_lengths,
    eval_mode,
    lengths_to_mask,
    timestep_embedding,
)

Condition = Literal["text", "action"]
EMDMActivation = Literal["selu", "gelu", "relu", "silu"]
Lengths = Tensor | Sequence[int]
Words = tuple[Tensor, Tensor]  # word-token states (B, M, H) and mask (B, M) bool, True on real tokens

_F64 = torch.float64
_PREFIX_G = 3  # generator tokens before the frames: timestep, condition, z
_PREFIX_D = 2  # discriminator tokens before the frames: timestep, condition


class Conditioning(NamedTuple):
    """G's step-independent inputs (:meth:`EMDMGenerator.conditioning`): the condition token (B, h)
    and the word memory with its padding mask (``()`` without word tokens)."""

    token: Tensor
    memory: tuple[Tensor, ...]


# --------------------------------------------------------------------------------------------------
# Small helpers
# --------------------------------------------------------------------------------------------------


def _valid_mask(lengths: Lengths, num_frames: int, device: torch.device) -> Tensor:
    """(B, N) bool, True on valid frames."""
    return lengths_to_mask(torch.as_tensor(lengths, device=device), num_frames)


def _per_sample_steps(t: Tensor | int, batch: int, device: torch.device) -> Tensor:
    t = torch.as_tensor(t, device=device).long()
    return t.expand(batch) if t.ndim == 0 else t


# --------------------------------------------------------------------------------------------------
# Schedule
# --------------------------------------------------------------------------------------------------


class EMDMSchedule:
    """DDGAN's few-step discretised VP schedule (EMDM: T = 10, beta_min 0.1, beta_max 20).

    Continuous VP SDE with linear ``beta(u) = beta_min + u (beta_max - beta_min)`` (Song et al. 2021)::

        alpha_bar(u) = exp(-0.5 u^2 (beta_max - beta_min) - u beta_min)
        u_k          = eps + (1 - eps) k / T,  k = 0..T,  eps = 1e-3

    Levels (signal of ``x_k``; ``alpha_bar_0 = 1``, the data) and step betas::

        alpha_bar_k  = alpha_bar(u_k) / alpha_bar(u_0)
        beta_{k}     = 1 - alpha_bar_k / alpha_bar_{k-1},  k = 1..T     (so alpha_bar_k = prod (1 - beta))

    Forward process: ``q(x_k | x0) = N(sqrt(alpha_bar_k) x0, (1 - alpha_bar_k) I)`` and one step
    ``x_{t+1} = sqrt(1 - beta_{t+1}) x_t + sqrt(beta_{t+1}) eps``.

    Posterior at step t = 0..T-1 (DDPM Eqs. 6-7; DDGAN ``Posterior_Coefficients``), with
    ``b = beta_{t+1}``, ``a = alpha_bar_{t+1}``, ``a_prev = alpha_bar_t``::

        q(x_t | x_{t+1}, x0) = N(coef1 x0 + coef2 x_{t+1}, var)
        var    = b (1 - a_prev) / (1 - a)
        coef1  = b sqrt(a_prev) / (1 - a)
        coef2  = (1 - a_prev) sqrt(1 - b) / (1 - a)
        logvar = log(max(var, 1e-20))

    At t = 0 (``a_prev = 1``): var = 0, coef1 = 1, coef2 = 0 exactly, so the posterior returns x0.
    T = 10 values: ``betas = [.105, .266, ..., .850]``, ``alpha_bar_1 = .8947``,
    ``alpha_bar_10 = 4.3e-5``, ``coef2[9] = .387``. Tables are float64 (T,) (``alphas_cumprod`` and
    ``time_points`` (T + 1,)); gathered values are cast to the tensor they multiply.
    """

    def __init__(
        self, num_steps: int = 10, beta_min: float = 0.1, beta_max: float = 20.0, eps_small: float = 1e-3
    ) -> None:
        if num_steps < 1:
            raise ValueError(f"num_steps must be >= 1, got {num_steps}")
        self.num_steps, self.beta_min, self.beta_max, self.eps_small = num_steps, beta_min, beta_max, eps_small
        u = eps_small + (1.0 - eps_small) * torch.arange(num_steps + 1, dtype=_F64) / num_steps
        log_ab = -0.5 * u**2 * (beta_max - beta_min) - u * beta_min
        ab = torch.exp(log_ab - log_ab[0])  # levels k = 0..T, ab[0] = 1 exactly
        self.time_points = u
        self.alphas_cumprod = ab
        self.betas = 1.0 - ab[1:] / ab[:-1]
        a, a_prev, b = ab[1:], ab[:-1], self.betas
        self.posterior_variance = b * (1.0 - a_prev) / (1.0 - a)
        self.posterior_log_variance = self.posterior_variance.clamp(min=1e-20).log()
        self.posterior_mean_coef1 = b * a_prev.sqrt() / (1.0 - a)
        self.posterior_mean_coef2 = (1.0 - a_prev) * (1.0 - b).sqrt() / (1.0 - a)
        self.noise_on = (torch.arange(num_steps) > 0).to(_F64)  # 1 where the posterior adds noise (t > 0)

    def to(self, device: torch.device | str) -> EMDMSchedule:
        """This schedule with every table on ``device`` (itself when they are there already); the sampler moves
        it to G's device once (:mod:`models.diffusion`'s conventions)."""
        device = torch.device(device)
        if self.alphas_cumprod.device == device:
            return self
        moved = copy.copy(self)
        for name, value in vars(self).items():
            if isinstance(value, Tensor):
                setattr(moved, name, value.to(device))
        return moved

    def q_sample(self, x0: Tensor, level: Tensor | int, noise: Tensor) -> Tensor:
        """``x_k = sqrt(alpha_bar_k) x0 + sqrt(1 - alpha_bar_k) noise`` for levels k in 0..T (k = 0: x0)."""
        a = gather(self.alphas_cumprod, level, x0)
        return a.sqrt() * x0 + (1.0 - a).sqrt() * noise

    def q_step(self, x_t: Tensor, t: Tensor | int, noise: Tensor) -> Tensor:
        """One forward step ``x_{t+1} = sqrt(1 - beta_{t+1}) x_t + sqrt(beta_{t+1}) noise``, t in 0..T-1."""
        b = gather(self.betas, t, x_t)
        return (1.0 - b).sqrt() * x_t + b.sqrt() * noise

    def posterior_mean_variance(self, x0: Tensor, x_next: Tensor, t: Tensor | int) -> tuple[Tensor, Tensor, Tensor]:
        """Mean, variance and log-variance of ``q(x_t | x_{t+1} = x_next, x0)`` (class docstring)."""
        mean = gather(self.posterior_mean_coef1, t, x0) * x0 + gather(
            self.posterior_mean_coef2, t, x_next
        ) * x_next
        return mean, gather(self.posterior_variance, t, x_next), gather(
            self.posterior_log_variance, t, x_next
        )

    def posterior_sample(self, x0: Tensor, x_next: Tensor, t: Tensor | int, noise: Tensor) -> Tensor:
        """EMDM Alg. 2: ``mean + [t > 0] exp(logvar / 2) noise``; at t = 0 exactly x0."""
        mean, _, log_var = self.posterior_mean_variance(x0, x_next, t)
        nonzero = gather(self.noise_on, t, x_next)
        return mean + nonzero * (0.5 * log_var).exp() * noise


def q_sample_pairs(
    schedule: EMDMSchedule, x0: Tensor, t: Tensor | int, generator: torch.Generator | None = None
) -> tuple[Tensor, Tensor]:
    """DDGAN's training pair ``(x_t, x_{t+1})`` at steps t (B,) in 0..T-1.

    ``x_t ~ q(x_t | x0)`` (x0 itself where t = 0) and ``x_{t+1}`` is one forward step from it
    (:meth:`EMDMSchedule.q_step`), so the pair is a consecutive draw of one forward trajectory. Both
    noises come from ``generator``.
    """
    x_t = schedule.q_sample(x0, t, normal(x0.shape, x0, generator))
    return x_t, schedule.q_step(x_t, t, normal(x0.shape, x0, generator))


# --------------------------------------------------------------------------------------------------
# Configuration and networks
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class EMDMConfig:
    """Hyper-parameters of EMDM; generator defaults are the paper's (App. C.1), the rest ours or the code's.

    ``condition``: "text" (a pooled frozen text embedding (B, ``text_dim``); 384 for MiniLM) or
    "action" (label indices (B,) in ``[0, num_actions)``). Generator: ``width`` h, ``layers``,
    ``heads``, ``ff_dim``, ``dropout``, ``activation``, ``norm_first`` (False: post-LN as the code),
    ``z_dim`` (64) through ``mapping_layers`` (5) Linear+LeakyReLU layers. Discriminator: ``d_*``
    (a small masked transformer, module docstring item 4; no dropout), ``d_time_dim`` (DDGAN's 128).
    ``patch_frames``: frames per token of G and D (module docstring item 9; the paper: 1);
    ``overlap_out``: G writes overlapping, tapered output patches (item 9; P even).
    ``d_condition``: False gives D no condition (its condition token is 0): naive DDGAN (EMDM Table D8).
    ``word_tokens``: G also cross-attends to the caption's word-token states (B, M, ``token_dim``) in
    every layer (module docstring item 11; the paper: False, the pooled token only); an action G to its
    label token and ``label_words`` fixed word slots per label (0: none). ``text_norm``: G
    and D standardise the pooled text embedding before their Linear (item 12; the paper: False).
    ``input_skip``: add a learned per-step multiple of x_{t+1} to G's output (module docstring item 10);
    ``skip_kernel`` (odd; 1: that multiple) widens it to a learned per-step filter over frames.
    Training: ``p_uncond`` (condition dropout, 0.1), ``r1_gamma`` (0.02), ``r1_interval`` (lazy R1
    every k steps, scaled by k), ``geo_weight`` R (None: 100 for text, 1 for action), ``geo_lambda``,
    ``geo_foot_lambda`` (the foot term's own lambda; None: ``geo_lambda``; module docstring item 6).
    Schedule: ``num_steps``, ``beta_min``, ``beta_max``. Sampling: ``guidance`` (2.5).
    """

    feature_dim: int = 263
    condition: Condition = "text"
    text_dim: int = 384
    num_actions: int = 0
    width: int = 1024
    layers: int = 12
    heads: int = 32
    ff_dim: int = 1024
    dropout: float = 0.1
    activation: EMDMActivation = "selu"
    norm_first: bool = False
    z_dim: int = 64
    mapping_layers: int = 5
    d_width: int = 256
    d_layers: int = 2
    d_heads: int = 4
    d_ff_dim: int = 512
    d_time_dim: int = 128
    patch_frames: int = 1
    overlap_out: bool = False
    d_condition: bool = True
    input_skip: bool = False
    skip_kernel: int = 1
    word_tokens: bool = False
    token_dim: int = 384
    label_words: int = 0
    text_norm: bool = False
    p_uncond: float = 0.1
    r1_gamma: float = 0.02
    r1_interval: int = 15
    geo_weight: float | None = None
    geo_lambda: float = 1.0
    geo_foot_lambda: float | None = None
    num_steps: int = 10
    beta_min: float = 0.1
    beta_max: float = 20.0
    guidance: float = 2.5

    def __post_init__(self) -> None:
        if self.condition not in ("text", "action"):
            raise ValueError(f"condition must be 'text' or 'action', got {self.condition!r}")
        if self.condition == "action" and self.num_actions < 1:
            raise ValueError("condition='action' needs num_actions >= 1")
        if self.activation not in ("selu", "gelu", "relu", "silu"):
            raise ValueError(f"unknown activation {self.activation!r}")
        if self.mapping_layers < 1:
            raise ValueError(f"mapping_layers must be >= 1, got {self.mapping_layers}")
        if self.patch_frames < 1:
            raise ValueError(f"patch_frames must be >= 1, got {self.patch_frames}")
        if self.overlap_out and self.patch_frames % 2:
            raise ValueError(f"overlap_out needs an even patch_frames, got {self.patch_frames}")
        if isinstance(self.skip_kernel, bool) or not isinstance(self.skip_kernel, int) or self.skip_kernel < 1 \
                or self.skip_kernel % 2 == 0:
            raise ValueError(f"skip_kernel must be an odd integer >= 1, got {self.skip_kernel!r}")
        if self.label_words < 0 or (self.label_words and (self.condition != "action" or not self.word_tokens)):
            raise ValueError(f"label_words {self.label_words}: word slots per label need condition 'action' and "
                             "word_tokens (0: none)")

    @property
    def geometric_weight(self) -> float:
        """R of Eq. 12: ``geo_weight``, or 100 for text and 1 for action (Sec. 5.2)."""
        if self.geo_weight is not None:
            return float(self.geo_weight)
        return 100.0 if self.condition == "text" else 1.0

    @property
    def joints_num(self) -> int:
        """J of the 12J - 1 feature layout (22 for 263 dims, 21 for 251)."""
        if (self.feature_dim + 1) % 12:
            raise ValueError(f"feature_dim {self.feature_dim} is not 12J - 1")
        return (self.feature_dim + 1) // 12

    def make_schedule(self) -> EMDMSchedule:
        return EMDMSchedule(self.num_steps, self.beta_min, self.beta_max)


def _as_config(config: EMDMConfig | Mapping[str, Any] | None) -> EMDMConfig:
    return config if isinstance(config, EMDMConfig) else EMDMConfig(**dict(config or {}))


def _transformer_layers(
    num: int, dim: int, heads: int, ff_dim: int, dropout: float, activation: str, norm_first: bool,
    cross_attention: bool = False,
) -> nn.ModuleList:
    """``num`` :class:`TransformerLayer` s; SELU (not offered by the shared layer) replaces its FF activation."""
    layers = nn.ModuleList()
    for _ in range(num):
        layer = TransformerLayer(
            dim, heads, ff_dim, dropout, "gelu" if activation == "selu" else activation,  # type: ignore[arg-type]
            norm_first=norm_first, cross_attention=cross_attention,
        )
        if activation == "selu":
            layer.ff[1] = nn.SELU()
        layers.append(layer)
    return layers


class ConditionEmbedding(nn.Module):
    """Condition -> (B, dim): text (B, E) through ``Linear(E -> dim)``; action (B,) through a learned table.

    The action table starts N(0, 1) as EMDM's ``nn.Parameter(randn(num_actions, d))``. ``text_norm``:
    the text embedding is standardised first (a LayerNorm without affine, module docstring item 12).
    """

    def __init__(self, condition: Condition, dim: int, text_dim: int, num_actions: int,
                 text_norm: bool = False) -> None:
        super().__init__()
        self.condition, self.text_norm = condition, text_norm
        if condition == "text":
            self.embed: nn.Module = nn.Linear(text_dim, dim)
        else:
            self.embed = nn.Embedding(num_actions, dim)
            nn.init.normal_(self.embed.weight)

    def forward(self, cond: Tensor) -> Tensor:
        if self.condition == "text":
            cond = cond.to(self.embed.weight.dtype)
            return self.embed(F.layer_norm(cond, cond.shape[-1:]) if self.text_norm else cond)
        return self.embed(cond.long())


def mapping_network(z_dim: int, dim: int, num_layers: int = 5) -> nn.Sequential:
    """EMDM's z mapping: ``[Linear, LeakyReLU(0.2)]`` x ``num_layers`` (z_dim -> dim -> ... -> dim)."""
    mods: list[nn.Module] = []
    for i in range(num_layers):
        mods += [nn.Linear(z_dim if i == 0 else dim, dim), nn.LeakyReLU(0.2)]
    return nn.Sequential(*mods)


class EMDMGenerator(nn.Module):
    """EMDM's conditional generator ``G(x_{t+1}, t, z, c) -> x0_hat`` (Eq. 3, App. C.1).

    Tokens ``[MLP(sinusoid(t)), cond or null, mapping(z), Linear(x_{t+1})_1..N]`` plus sinusoidal
    positions, a post-LN transformer with the padded frames masked as keys, the first 3 outputs
    discarded and ``Linear(h -> D)`` on the rest; padded frames of the output are 0 and padded inputs
    are ignored. ``config`` is an :class:`EMDMConfig` or its dict.
    """

    def __init__(self, config: EMDMConfig | Mapping[str, Any] | None = None) -> None:
        super().__init__()
        cfg = _as_config(config)
        self.config = cfg
        h = cfg.width
        self.frame_in = nn.Linear(cfg.patch_frames * cfg.feature_dim, h)
        self.time_mlp = nn.Sequential(nn.Linear(h, h), nn.SiLU(), nn.Linear(h, h))
        self.cond_embed = ConditionEmbedding(cfg.condition, h, cfg.text_dim, cfg.num_actions, cfg.text_norm)
        self.null_cond = nn.Parameter(torch.zeros(h))
        self.mapping = mapping_network(cfg.z_dim, h, cfg.mapping_layers)
        self.pos_encoding = PositionalEncoding(h, "sinusoidal")
        self.layers = _transformer_layers(
            cfg.layers, h, cfg.heads, cfg.ff_dim, cfg.dropout, cfg.activation, cfg.norm_first, cfg.word_tokens
        )
        reads_words = cfg.word_tokens and (cfg.condition == "text" or cfg.label_words > 0)
        self.token_proj = nn.Linear(cfg.token_dim, h) if reads_words else None
        self.label_word_states: Tensor | None
        self.label_word_mask: Tensor | None
        slots = cfg.label_words > 0
        self.register_buffer("label_word_states", torch.zeros(cfg.num_actions, cfg.label_words, cfg.token_dim)
                             if slots else None)
        self.register_buffer("label_word_mask", torch.zeros(cfg.num_actions, cfg.label_words, dtype=torch.bool)
                             if slots else None)
        self.frame_out = nn.Linear(h, output_width(cfg.patch_frames, cfg.feature_dim, cfg.overlap_out))
        self.skip = None
        if cfg.input_skip:
            scalar = cfg.make_schedule().alphas_cumprod[1:].sqrt().float()
            if cfg.skip_kernel == 1:
                self.skip = nn.Parameter(scalar)
            else:  # the scalar at the centre tap until the recipe sets the Wiener taps
                taps = torch.zeros(cfg.num_steps, cfg.feature_dim, cfg.skip_kernel)
                taps[:, :, cfg.skip_kernel // 2] = scalar[:, None]
                self.skip = nn.Parameter(taps)

    def condition_tokens(self, cond: Tensor, drop_cond: Tensor | None = None) -> Tensor:
        """(B, h) condition tokens; rows where ``drop_cond`` (B,) bool is True get the null token."""
        tokens = self.cond_embed(cond)
        if drop_cond is None:
            return tokens
        null = self.null_cond.to(tokens.dtype).expand_as(tokens)
        return torch.where(drop_cond.to(tokens.device).bool()[:, None], null, tokens)

    def forward(
        self,
        x_next: Tensor,
        t: Tensor | int,
        z: Tensor,
        cond: Tensor,
        lengths: Lengths,
        drop_cond: Tensor | None = None,
        words: Words | None = None,
    ) -> Tensor:
        """x0_hat (B, N, D) from x_next (B, N, D) at step t (B,) int, z (B, z_dim), cond, lengths (B,).

        ``cond``: (B, text_dim) float for text, (B,) int for action. ``drop_cond`` (B,) bool: use the
        null condition for those samples (condition dropout in training, the unconditional pass of CFG).
        ``words``: (word-token states (B, M, token_dim), mask (B, M) bool True on real tokens), required
        exactly when a text G has ``config.word_tokens`` (never for action: an action G reads its labels'
        word slots); a dropped sample attends to the null token alone.
        """
        return self.denoise(x_next, t, z, lengths, self.conditioning(cond, drop_cond, words))

    def conditioning(self, cond: Tensor, drop_cond: Tensor | None = None, words: Words | None = None) -> Conditioning:
        """The step-independent part of :meth:`forward` (its arguments as there): a sampler computes it
        once per batch and calls :meth:`denoise` at every step."""
        if (words is None) == (self.config.word_tokens and self.config.condition == "text"):
            raise ValueError("words (word-token states and mask) must be given exactly when a text generator has "
                             f"word_tokens (this {self.config.condition} generator has word_tokens="
                             f"{self.config.word_tokens})")
        if self.label_word_states is not None and self.label_word_mask is not None:
            labels = cond.long().to(self.label_word_states.device)
            words = (self.label_word_states[labels], self.label_word_mask[labels])
        cond_token = self.condition_tokens(cond, drop_cond)
        return Conditioning(cond_token, self.word_memory(cond_token, words, drop_cond))

    def denoise(
        self, x_next: Tensor, t: Tensor | int, z: Tensor, lengths: Lengths, conditioning: Conditioning
    ) -> Tensor:
        """:meth:`forward` on a precomputed :meth:`conditioning` of the same batch."""
        b, n, _ = x_next.shape
        valid = _valid_mask(lengths, n, x_next.device)
        steps = _per_sample_steps(t, b, x_next.device)
        patches, token_valid = to_patches(x_next, valid, self.config.patch_frames)
        frames = self.frame_in(patches)
        prefix = torch.stack(
            [
                self.time_mlp(timestep_embedding(steps, self.config.width).to(frames.dtype)),
                conditioning.token.to(frames.dtype),
                self.mapping(z.to(frames.dtype)),
            ],
            dim=1,
        )
        tokens = self.pos_encoding(torch.cat([prefix, frames], dim=1))
        padding = torch.cat([valid.new_zeros(b, _PREFIX_G), ~token_valid], dim=1)
        for layer in self.layers:
            tokens = layer(tokens, padding, *conditioning.memory)
        out = from_output_patches(self.frame_out(tokens[:, _PREFIX_G:]), token_valid, n, self.config.patch_frames,
                                  self.config.overlap_out)
        if self.skip is not None:
            out = out + self.skipped(x_next, steps, valid).to(out.dtype)
        return torch.where(valid[..., None], out, 0.0)

    def word_memory(self, cond_token: Tensor, words: Words | None, drop_cond: Tensor | None) -> tuple[Tensor, ...]:
        """The cross-attention memory ``[cond token, Linear(words)]`` (B, 1 + M, h) and its padding mask
        (True = ignored): padded words, and every word of a dropped sample; the cond token alone (B, 1, h)
        for an action G without word slots; () without word tokens."""
        if words is None:
            if not self.config.word_tokens:
                return ()
            alone = cond_token.new_zeros(cond_token.shape[0], 1, dtype=torch.bool)
            return self.pos_encoding(cond_token[:, None]), alone
        states, mask = words
        if states.shape[:2] != mask.shape or states.shape[0] != cond_token.shape[0]:
            raise ValueError(f"words: states {tuple(states.shape)} and mask {tuple(mask.shape)} do not match a "
                             f"batch of {cond_token.shape[0]}")
        ignored = ~mask.to(cond_token.device).bool()
        if drop_cond is not None:
            ignored = ignored | drop_cond.to(cond_token.device).bool()[:, None]
        memory = self.pos_encoding(torch.cat([cond_token[:, None], self.token_proj(states.to(cond_token.dtype))], 1))
        return memory, torch.cat([ignored.new_zeros(ignored.shape[0], 1), ignored], dim=1)

    def skipped(self, x_next: Tensor, steps: Tensor, valid: Tensor) -> Tensor:
        """The input skip of ``x_next`` (B, N, D) at ``steps`` (B,): its per-step multiple, or its per-step
        filter over frames (``skip_kernel`` > 1), reading padded frames and the ends as 0."""
        if self.skip is None:
            raise RuntimeError("this generator has no input skip (input_skip: false)")
        # index_select, not skip[steps]: the backward of advanced indexing (index_put_ with
        # accumulate) sums repeated steps in an order that varies between runs on more than one CPU thread.
        taps = self.skip.index_select(0, steps)
        if self.skip.ndim == 1:
            return taps[:, None, None] * x_next
        k = self.skip.shape[-1]
        x = torch.where(valid[..., None], x_next, 0.0)
        windows = F.pad(x, (0, 0, k // 2, k // 2)).unfold(1, k, 1)  # (B, N, D, k)
        return torch.einsum("bndk,bdk->bnd", windows, taps.to(x.dtype))


class EMDMDiscriminator(nn.Module):
    """Conditional discriminator ``D(x_t, x_{t+1}, t, c) -> logit`` (B,) (Eqs. 4-5; module docstring item 4).

    Tokens ``[time(t), cond(c), Linear([x_t; x_{t+1}])_1..N]`` plus sinusoidal positions, a small
    post-LN transformer with padded frames masked as keys, a mean over the valid frames' outputs and
    ``Linear -> LeakyReLU(0.2) -> Linear(-> 1)``. The output does not depend on padded values or on the
    amount of padding. No dropout (R1 and the GAN game want a deterministic D).
    """

    def __init__(self, config: EMDMConfig | Mapping[str, Any] | None = None) -> None:
        super().__init__()
        cfg = _as_config(config)
        self.config = cfg
        h, td = cfg.d_width, cfg.d_time_dim
        self.frame_in = nn.Linear(2 * cfg.patch_frames * cfg.feature_dim, h)
        self.time_mlp = nn.Sequential(nn.Linear(td, td), nn.LeakyReLU(0.2), nn.Linear(td, h))
        self.cond_embed = (ConditionEmbedding(cfg.condition, h, cfg.text_dim, cfg.num_actions, cfg.text_norm)
                           if cfg.d_condition else None)
        self.pos_encoding = PositionalEncoding(h, "sinusoidal")
        self.layers = _transformer_layers(cfg.d_layers, h, cfg.d_heads, cfg.d_ff_dim, 0.0, "gelu", False)
        self.head = nn.Sequential(nn.Linear(h, h), nn.LeakyReLU(0.2), nn.Linear(h, 1))

    def forward(self, x_t: Tensor, x_next: Tensor, t: Tensor | int, cond: Tensor, lengths: Lengths) -> Tensor:
        """Logits (B,) for the pair (x_t, x_next), each (B, N, D), at step t (B,), condition and lengths."""
        b, n, _ = x_t.shape
        valid = _valid_mask(lengths, n, x_t.device)
        steps = _per_sample_steps(t, b, x_t.device)
        pair, token_valid = to_patches(torch.cat([x_t, x_next], dim=-1), valid, self.config.patch_frames)
        frames = self.frame_in(pair)
        time = timestep_embedding(steps, self.config.d_time_dim, flip_sin_to_cos=False).to(frames.dtype)
        time = self.time_mlp(time)
        condition = time.new_zeros(time.shape) if self.cond_embed is None else self.cond_embed(cond).to(frames.dtype)
        prefix = torch.stack([time, condition], dim=1)
        tokens = self.pos_encoding(torch.cat([prefix, frames], dim=1))
        padding = torch.cat([valid.new_zeros(b, _PREFIX_D), ~token_valid], dim=1)
        for layer in self.layers:
            tokens = layer(tokens, padding)
        weights = token_valid.to(tokens.dtype)[..., None]
        pooled = (tokens[:, _PREFIX_D:] * weights).sum(1) / weights.sum(1).clamp(min=1.0)
        return self.head(pooled).squeeze(-1)


def action_from_text(action_model: EMDMGenerator | EMDMDiscriminator, text_state: Mapping[str, Tensor],
                     text_config: EMDMConfig, class_captions: Sequence[tuple[Tensor, Tensor]]) -> None:
    """Start an action-conditioned G or D from a trained text-conditioned one of the same sizes (ours).

    Every weight but the condition embedding is copied from ``text_state`` (the text model's state dict,
    ``text_config`` its config). ``class_captions[c]`` holds class c's captions: their pooled embeddings
    (n_c, E) and the word-token states (n, token_dim) of one of them. Row c of the label table becomes the
    mean of the text model's condition tokens of the n_c captions, and a G with word slots
    (``label_words``) gets the first ``label_words`` word states. With one caption per class, the started
    model given label c is the text model given that caption, output for output (a G without slots: with
    no words). The paper trains its action models from scratch; the warm start carries the motion a text
    model learnt from every training motion into the smaller labelled set. A size that differs is a
    ValueError naming the weight.
    """
    cfg = action_model.config
    if cfg.condition != "action" or text_config.condition != "text":
        raise ValueError("action_from_text starts an action model from a text model")
    if len(class_captions) != cfg.num_actions:
        raise ValueError(f"{len(class_captions)} captions for {cfg.num_actions} actions")
    state = action_model.state_dict()
    for key, value in state.items():
        if key.startswith("cond_embed.") or key.startswith("label_word_"):
            continue
        if key not in text_state or text_state[key].shape != value.shape:
            found = tuple(text_state[key].shape) if key in text_state else "missing"
            raise ValueError(f"{key}: the text model's is {found}, the action model's {tuple(value.shape)} "
                             "(the two must have the same sizes)")
        state[key] = text_state[key]
    if action_model.cond_embed is not None:
        text_embed = ConditionEmbedding("text", action_model.cond_embed.embed.embedding_dim, text_config.text_dim,
                                        0, text_config.text_norm)
        text_embed.load_state_dict({k.removeprefix("cond_embed."): v for k, v in text_state.items()
                                    if k.startswith("cond_embed.")})
        with torch.no_grad():
            rows = [text_embed(pooled.to(torch.float32)).mean(0) for pooled, _ in class_captions]
        state["cond_embed.embed.weight"] = torch.stack(rows)
    if "label_word_states" in state:
        states, mask = torch.zeros_like(state["label_word_states"]), torch.zeros_like(state["label_word_mask"])
        for c, (_, words) in enumerate(class_captions):
            n = min(len(words), cfg.label_words)
            states[c, :n], mask[c, :n] = words[:n].to(states.dtype), True
        state["label_word_states"], state["label_word_mask"] = states, mask
    action_model.load_state_dict(state)


# --------------------------------------------------------------------------------------------------
# Adversarial losses and R1
# --------------------------------------------------------------------------------------------------


def d_adversarial_loss(real_logits: Tensor, fake_logits: Tensor) -> Tensor:
    """Non-saturating D loss (Eq. 4): ``mean softplus(-D(real)) + mean softplus(D(fake))``."""
    return F.softplus(-real_logits).mean() + F.softplus(fake_logits).mean()


def g_adversarial_loss(fake_logits: Tensor) -> Tensor:
    """Non-saturating G loss (Eq. 6): ``mean softplus(-D(fake))``."""
    return F.softplus(-fake_logits).mean()


def r1_penalty(real_logits: Tensor, x_real: Tensor, lengths: Lengths | None = None, gamma: float = 0.02) -> Tensor:
    """R1 (Eq. 16; Mescheder et al. 2018): ``gamma / 2 * mean_b sum_{valid (n, d)} (dD_b / dx_real[b, n, d])^2``.

    ``x_real`` (B, N, D) must require grad and ``real_logits`` (B,) be computed from it (through
    :func:`double_backward_attention` for a transformer D); padded frames (``lengths``) are excluded.
    The graph is kept (``create_graph``) so the penalty can be back-propagated into D.
    """
    (grad,) = torch.autograd.grad(real_logits.sum(), x_real, create_graph=True)
    if lengths is not None:
        grad = torch.where(_valid_mask(lengths, x_real.shape[1], x_real.device)[..., None], grad, 0.0)
    return 0.5 * gamma * grad.square().flatten(1).sum(1).mean()


def lazy_r1_scale(step: int, interval: int = 15) -> float:
    """Lazy regularisation weight (StyleGAN2): ``interval`` on steps divisible by it, else 0 (skip R1).

    ``interval <= 1`` means R1 every step with weight 1.
    """
    if interval <= 1:
        return 1.0
    return float(interval) if step % interval == 0 else 0.0


@contextmanager
def double_backward_attention() -> Iterator[None]:
    """Run scaled-dot-product attention with the "math" kernel, whose graph supports double backward (R1)."""
    with sdpa_kernel(SDPBackend.MATH):
        yield


# --------------------------------------------------------------------------------------------------
# Geometric losses
# --------------------------------------------------------------------------------------------------


def _stat(x: Tensor | np.ndarray | Sequence[float], like: Tensor) -> Tensor:
    return torch.as_tensor(np.asarray(x) if not isinstance(x, Tensor) else x).to(like.device, like.dtype)


def masked_mse(pred: Tensor, target: Tensor, valid: Tensor) -> Tensor:
    """Squared error over valid frames: per sample ``sum_{valid n, all elements} (pred - target)^2 /
    (valid frames * elements per frame)``, then the mean over the batch. pred/target (B, N, ...), valid (B, N)."""
    per_frame = (pred - target).square().flatten(2).sum(-1)
    elements = per_frame.new_tensor(float(math.prod(pred.shape[2:])))
    count = valid.sum(1).to(per_frame.dtype).clamp(min=1.0) * elements
    return (torch.where(valid, per_frame, 0.0).sum(1) / count).mean()


def _feet_of(joints_num: int) -> tuple[int, ...]:
    for skeleton in SKELETONS.values():
        if skeleton.joints_num == joints_num:
            return skeleton.feet
    raise ValueError(f"no known skeleton with {joints_num} joints: pass feet explicitly")


def geometric_losses(
    pred: Tensor,
    target: Tensor,
    lengths: Lengths,
    mean: Tensor | np.ndarray,
    std: Tensor | np.ndarray,
    joints_num: int,
    *,
    weight: float = 100.0,
    lam: float = 1.0,
    feet: Sequence[int] | None = None,
    foot_lam: float | None = None,
) -> dict[str, Tensor]:
    """EMDM's geometric loss ``R (L_recon + lambda (L_pos + L_vel + L_foot))`` (Eqs. 7-12; docstring item 6);
    ``foot_lam`` replaces lambda on ``L_foot`` (None: lambda).

    pred = x0_hat, target = x0: normalised features (B, N, D); ``mean``/``std`` (D,) the statistics
    they were normalised with; joints ``J(x) = recover_from_ric(x * std + mean)`` (B, N, J, 3).

    - ``recon``: :func:`masked_mse` of the features;
    - ``pos``: :func:`masked_mse` of J(pred) against J(target);
    - ``vel``: of the joint velocities ``J[n+1] - J[n]``, over pairs with both frames valid;
    - ``foot``: of ``(J(pred)[n+1, feet] - J(pred)[n, feet]) * contact[n]`` against 0, over valid
      pairs, ``contact`` (B, N, 4) = ground-truth contacts group denormalised, > 0.5.

    ``feet``: the 4 contact joints in contacts order (default: the skeleton with ``joints_num``
    joints, HumanML3D (7, 10, 8, 11) or KIT). Returns ``recon``, ``pos``, ``vel``, ``foot``,
    ``geo`` (the bracket) and ``total = weight * geo``.
    """
    groups = feature_groups(joints_num)
    feet = tuple(_feet_of(joints_num) if feet is None else feet)
    valid = _valid_mask(lengths, pred.shape[1], pred.device)
    pairs = valid[:, 1:] & valid[:, :-1]
    mean_t, std_t = _stat(mean, pred), _stat(std, pred)
    used = groups["ric"].stop  # recovery reads only the root and RIC groups
    j_hat = recover_from_ric(pred[..., :used] * std_t[:used] + mean_t[:used], joints_num)
    j = recover_from_ric(target[..., :used] * std_t[:used] + mean_t[:used], joints_num)
    v_hat, v = j_hat[:, 1:] - j_hat[:, :-1], j[:, 1:] - j[:, :-1]
    contacts = target[..., groups["contacts"]] * std_t[groups["contacts"]] + mean_t[groups["contacts"]]
    on = (contacts[:, :-1] > 0.5).to(pred.dtype)[..., None]  # (B, N-1, 4, 1)
    foot_vel = v_hat[:, :, list(feet)] * on
    terms = {
        "recon": masked_mse(pred, target, valid),
        "pos": masked_mse(j_hat, j, valid),
        "vel": masked_mse(v_hat, v, pairs),
        "foot": masked_mse(foot_vel, torch.zeros_like(foot_vel), pairs),
    }
    geo = terms["recon"] + lam * (terms["pos"] + terms["vel"]) + (lam if foot_lam is None else foot_lam) * terms["foot"]
    return {**terms, "geo": geo, "total": weight * geo}


# --------------------------------------------------------------------------------------------------
# One training step's losses (DDGAN's loop, EMDM App. C.3)
# --------------------------------------------------------------------------------------------------


def discriminator_step_losses(
    generator: EMDMGenerator,
    discriminator: EMDMDiscriminator,
    schedule: EMDMSchedule,
    x0: Tensor,
    cond: Tensor,
    lengths: Lengths,
    step: int,
    generator_rng: torch.Generator | None = None,
    words: Words | None = None,
) -> dict[str, Tensor]:
    """D's objective on a batch x0 (B, N, D) (Eq. 14 + lazy R1): ``total = real + fake + scale * r1``.

    t ~ U{0..T-1}, a real pair (x_t, x_{t+1}) (:func:`q_sample_pairs`), a fake ``x_t`` = posterior
    sample around ``G(x_{t+1}, t, z, c)`` (condition dropped w.p. ``p_uncond``, no gradient into G);
    ``real = mean softplus(-D(x_t))``, ``fake = mean softplus(D(fake x_t))``; R1 on the real x_t with
    weight :func:`lazy_r1_scale` (``step``, ``r1_interval``), ``r1`` reported unscaled (0 when skipped).
    Only D's parameters receive gradients. All randomness from ``generator_rng``.
    """
    cfg = generator.config
    b = x0.shape[0]
    t = sample_timesteps(b, schedule.num_steps, generator_rng, x0.device)
    x_t, x_next = q_sample_pairs(schedule, x0, t, generator_rng)
    scale = lazy_r1_scale(step, cfg.r1_interval)
    if scale > 0:
        x_t = x_t.detach().requires_grad_(True)
        with double_backward_attention():
            real_logits = discriminator(x_t, x_next, t, cond, lengths)
        r1 = r1_penalty(real_logits, x_t, lengths, cfg.r1_gamma)
    else:
        real_logits = discriminator(x_t, x_next, t, cond, lengths)
        r1 = real_logits.new_zeros(())
    with torch.no_grad():
        drop = condition_dropout(b, cfg.p_uncond, generator_rng, x0.device)
        x0_hat = generator(x_next, t, normal((b, cfg.z_dim), x0, generator_rng), cond, lengths, drop_cond=drop,
                           words=words)
        fake_t = schedule.posterior_sample(x0_hat, x_next, t, normal(x0.shape, x0, generator_rng))
    fake_logits = discriminator(fake_t, x_next, t, cond, lengths)
    real, fake = F.softplus(-real_logits).mean(), F.softplus(fake_logits).mean()
    return {"real": real, "fake": fake, "r1": r1, "total": real + fake + scale * r1}


def generator_step_losses(
    generator: EMDMGenerator,
    discriminator: EMDMDiscriminator,
    schedule: EMDMSchedule,
    x0: Tensor,
    cond: Tensor,
    lengths: Lengths,
    mean: Tensor | np.ndarray,
    std: Tensor | np.ndarray,
    generator_rng: torch.Generator | None = None,
    words: Words | None = None,
) -> dict[str, Tensor]:
    """G's objective on a batch x0 (B, N, D) (Eqs. 12, 15): ``total = adv + R * geo``.

    One draw of t, pair, z and condition dropout (docstring item 7): ``x0_hat = G(x_{t+1}, t, z, c)``,
    fake ``x_t`` = posterior sample, ``adv = mean softplus(-D(fake x_t, x_{t+1}, t, c))`` and
    :func:`geometric_losses` of x0_hat against x0 (R = ``config.geometric_weight``, lambda =
    ``geo_lambda``). Returns ``adv`` and the geometric terms (``recon``, ``pos``, ``vel``, ``foot``,
    ``geo``), ``total``. Gradients also reach D's parameters: freeze D (``requires_grad_(False)``) or
    zero its gradients before its own step.
    """
    cfg = generator.config
    b = x0.shape[0]
    t = sample_timesteps(b, schedule.num_steps, generator_rng, x0.device)
    _, x_next = q_sample_pairs(schedule, x0, t, generator_rng)
    drop = condition_dropout(b, cfg.p_uncond, generator_rng, x0.device)
    x0_hat = generator(x_next, t, normal((b, cfg.z_dim), x0, generator_rng), cond, lengths, drop_cond=drop,
                       words=words)
    fake_t = schedule.posterior_sample(x0_hat, x_next, t, normal(x0.shape, x0, generator_rng))
    adv = g_adversarial_loss(discriminator(fake_t, x_next, t, cond, lengths))
    geo = geometric_losses(
        x0_hat, x0, lengths, mean, std, cfg.joints_num, weight=cfg.geometric_weight, lam=cfg.geo_lambda,
        foot_lam=cfg.geo_foot_lambda,
    )
    return {"adv": adv, **{k: v for k, v in geo.items() if k != "total"}, "total": adv + geo["total"]}


# --------------------------------------------------------------------------------------------------
# Sampling
# --------------------------------------------------------------------------------------------------


def guided_x0(
    generator: EMDMGenerator,
    x_next: Tensor,
    t: Tensor | int,
    z: Tensor,
    cond: Tensor,
    lengths: Lengths,
    guidance: float = 2.5,
    words: Words | None = None,
) -> Tensor:
    """Classifier-free guided prediction (Eq. 13): ``G(null) + s (G(c) - G(null))``, same z for both.

    The two passes run as ONE forward on the doubled batch ``[unconditional; conditional]``
    (:func:`guidance_batch`); ``guidance == 1`` runs the conditional pass alone.
    """
    lengths_g, conditioning = guidance_batch(generator, cond, lengths, guidance, words)
    return _guided(generator, x_next, t, z, lengths_g, conditioning, guidance)


def guidance_batch(
    generator: EMDMGenerator, cond: Tensor, lengths: Lengths, guidance: float, words: Words | None = None,
) -> tuple[Tensor, Conditioning]:
    """The lengths and the :meth:`EMDMGenerator.conditioning` that guided steps run on: for B samples,
    the doubled batch ``[unconditional; conditional]`` (2B), or the B samples alone at guidance 1."""
    device = next(generator.parameters()).device
    lengths_t = torch.as_tensor(lengths, device=device)
    if guidance == 1.0:
        return lengths_t, generator.conditioning(cond, None, words)
    b = lengths_t.shape[0]
    drop = torch.cat([torch.ones(b, dtype=torch.bool), torch.zeros(b, dtype=torch.bool)]).to(device)
    doubled = None if words is None else (torch.cat([words[0], words[0]]), torch.cat([words[1], words[1]]))
    return torch.cat([lengths_t, lengths_t]), generator.conditioning(torch.cat([cond, cond]), drop, doubled)


def _guided(
    generator: EMDMGenerator, x_next: Tensor, t: Tensor | int, z: Tensor, lengths: Tensor,
    conditioning: Conditioning, guidance: float,
) -> Tensor:
    """Eq. 13 on a :func:`guidance_batch` (``lengths`` and ``conditioning`` as it returns them)."""
    if guidance == 1.0:
        return generator.denoise(x_next, t, z, lengths, conditioning)
    steps = _per_sample_steps(t, x_next.shape[0], x_next.device)
    out = generator.denoise(
        torch.cat([x_next, x_next]), torch.cat([steps, steps]), torch.cat([z, z]), lengths, conditioning
    )
    uncond, conditional = out.chunk(2)
    return cfg_combine(uncond, conditional, guidance)


@torch.no_grad()
def sample_emdm(
    generator: EMDMGenerator,
    schedule: EMDMSchedule,
    cond: Tensor,
    lengths: Lengths,
    guidance: float = 2.5,
    generator_rng: torch.Generator | None = None,
    *,
    num_frames: int | None = None,
    x_T: Tensor | None = None,
    words: Words | None = None,
) -> Tensor:
    """EMDM sampling (Alg. 1): cond (B, ...) and lengths (B,) -> normalised features (B, N, D).

    ``x_T ~ N(0, I)`` (or ``x_T``), N = ``num_frames`` or ``max(lengths)``; for t = T-1..0 draw a fresh
    z, ``x0_hat = guided_x0(x_{t+1}, t, z)`` and ``x_t = posterior_sample(x0_hat, x_{t+1}, t)``
    (Alg. 2); the last step returns x0_hat itself (the posterior at t = 0). Padded frames are 0 (G
    zeroes its output there). The condition's part of G (:func:`guidance_batch`) is computed once,
    not at every step. Runs G in eval mode (restored afterwards); every draw comes from
    ``generator_rng`` (deterministic for a seeded generator).
    """
    cfg = generator.config
    device = next(generator.parameters()).device
    cond = cond.to(device)
    words = None if words is None else (words[0].to(device), words[1].to(device))
    lengths_t, n = checked_lengths(lengths, num_frames)
    lengths_t = lengths_t.to(device)
    b = lengths_t.shape[0]
    valid = _valid_mask(lengths_t, n, device)[..., None]
    dtype = next(generator.parameters()).dtype
    ref = torch.empty(0, device=device, dtype=dtype)
    x = normal((b, n, cfg.feature_dim), ref, generator_rng) if x_T is None else x_T.to(device, dtype)
    x = torch.where(valid, x, 0.0)
    schedule = schedule.to(device)
    with eval_mode(generator):
        lengths_g, conditioning = guidance_batch(generator, cond, lengths_t, guidance, words)
        for step in reversed(range(schedule.num_steps)):
            t = torch.full((b,), step, dtype=torch.long, device=device)
            z = normal((b, cfg.z_dim), ref, generator_rng)
            x0_hat = _guided(generator, x, t, z, lengths_g, conditioning, guidance)
            if step == 0:
                return x0_hat
            x = torch.where(valid, schedule.posterior_sample(x0_hat, x, t, normal(x.shape, ref, generator_rng)), 0.0)
    raise AssertionError("unreachable: a schedule has at least one step")
