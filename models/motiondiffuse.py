"""MotionDiffuse: a text-conditioned DDPM on motion features with a cross-modality linear transformer.

Paper: Zhang et al., "MotionDiffuse: Text-Driven Human Motion Generation with Diffusion Model"
(``shared/papers/002_*.txt``): Sec. 3.3 (Eqs. 3-5), Sec. 3.4 (Eqs. 6-9), Sec. 3.5 (Eqs. 10-11); the
released code as summarised in ``reference/emdm_motiondiffuse.md`` section 2; DESIGN.md "Models ->
MotionDiffuse". Shapes: B batch, N frames (padded), D feature dims (263), L word tokens, E frozen
token width (384 for MiniLM), h model width, H heads. Features are the normalised HumanML3D vectors;
padded frames are those at or after each sample's length.

Equations (paper numbering):

- (3) ``x_t = sqrt(ab_t) x0 + sqrt(1 - ab_t) eps``, eps ~ N(0, I), linear betas 1e-4..0.02, T = 1000.
- (4) ``L = E_{t, x0, eps} ||eps - eps_theta(x_t, t, text)||`` (squared, see item 7).
- (5) ``mu_theta = (x_t - beta_t / sqrt(1 - ab_t) eps_theta) / sqrt(alpha_t)`` (the paper prints
  ``1/sqrt(x_t)``, a typo), i.e. DDPM's ancestral step.
- (6-7) text encoder: standard multi-head attention ``softmax(Q K^T / sqrt(d)) V`` over word tokens.
- (8) efficient attention (Shen et al. 2021), per head: ``F_g = softmax_seq(K)^T V`` (d_k x d_k),
  ``Y = softmax_feat(Q) F_g``; O(N d d_k) instead of O(N^2 d).
- (9) stylization: ``B = psi_b(phi(e))``, ``W = psi_w(phi(e))``, ``Y' = Y . W + B`` with
  ``e = e_text + e_t``; the code writes it ``SiLU -> Linear`` for (scale, shift),
  ``h = LN(Y) (1 + scale) + shift``, then ``SiLU -> Dropout -> zero-init Linear``, added to the
  residual stream after every self-attention, cross-attention and FFN sub-block.
- (10) body parts: ``eps = sum_i M_i . eps_i + lambda1 grad_{x_t} sum_{1<=i,j<=m} ||eps_i - eps_j||``,
  ``eps_i = eps_theta(x_t, t, text_i)``, M_i in {0, 1}^D a feature mask.
- (11) time-varied: ``eps = sum_i eps'_i + lambda2 grad_{x_t} sum_{1<=i,j<=m} ||eps'_i - eps'_j||``,
  eps'_i the prediction on frames [l_i, r_i] zero-padded to the full length.

Choices (each deliberate; "code" = the released MotionDiffuse code):

1. Text branch: the frozen encoder's word-token states (B, L, E) (MiniLM here, CLIP's 77 token
   features in the code) -> ``Linear(E -> h)`` -> ``text_layers`` trainable post-LN transformer
   layers (:class:`models.transformer.TransformerLayer`, GELU) -> LayerNorm. No positional encoding is
   added: the frozen states are already contextual. Unlike the code (issue #32), padded word tokens
   are masked: as keys of the text transformer, of the cross-attention and in the pooling, so they
   cannot change the output. Every caption needs at least one valid token (MiniLM's mask includes
   [CLS]/[SEP], so even "" has two); a row with none raises ValueError.
2. Pooled text embedding: the masked MEAN of the text transformer's outputs (the code takes CLIP's
   end-of-text token, which is CLIP's own sentence summary because CLIP is causal). MiniLM is
   bidirectional and its sentence embedding is itself a masked mean; its [SEP] state was never
   trained as a summary, and the mean needs nothing but ``word_mask`` (no tokenizer ids).
   ``e = MLP(sinusoid_h(t)) + Linear(pooled)`` with ``MLP = Linear(h -> 4h) -> SiLU -> Linear(4h -> 4h)``
   (code: time_embed_dim = 4 x latent_dim); the sinusoid is guided-diffusion's ``[cos, sin]``
   (``timestep_embedding(t, h, flip_sin_to_cos=True)``).
3. Motion branch as the code: ``Linear(D -> h)`` + a learned positional table ``randn(max_len, h)``
   sliced to N; ``layers`` x [linear self-attention, linear cross-attention, FFN], each
   ``x + Stylization(sublayer(x), e)``; queries/keys/values from ``LN(x)`` (and ``LN_text(tokens)``
   for cross-attention keys/values); FFN ``Linear(h -> ff) -> GELU -> Dropout -> zero-init Linear``
   on the un-normalised x (as the code); final zero-init ``Linear(h -> D)``. So a fresh model predicts
   exactly 0 and every fresh block is an identity. No final LayerNorm (the code has none).
4. Masking of frames: keys of padded frames are set to -inf before the softmax over the sequence
   (the code adds -1e6: same result up to exp(-1e6) = 0) and their values are zeroed (with
   ``torch.where``, so non-finite padding cannot leak as 0 * inf); padded input frames are zeroed on
   entry and the output is 0 on padded frames. Valid outputs therefore do not depend on padded
   inputs. ``attention="softmax"`` (the code's ``--no_eff``) swaps in ordinary scaled-dot-product
   attention with the same projections and the same key mask. lengths must lie in [1, N] and
   N <= ``max_len``.
5. Schedule: :func:`models.diffusion.linear_betas` with ``rescale_to_steps`` (``rescale_betas``, the
   code's ``get_named_beta_schedule``; no change at T = 1000). epsilon prediction.
6. Sampling: DDPM with the posterior ("fixed_small") variance, as the code (the paper's text says
   Sigma = beta_t); no x0 clipping; no classifier-free guidance by default (item 13).
   DDIM (for the few-step evaluation row) uses the "trailing" grid (its first step is at T - 1, where
   DDPM starts) and ``set_alpha_to_one=True`` (its last step lands on the x0 prediction, where DDPM
   ends). Padded frames of the result are 0.
7. Loss: squared error (the paper prints a plain norm), masked: ``sum over valid (frame, dim) of
   (eps_hat - eps)^2 / (valid frames * D)`` over the whole batch, as the code. Draw order from
   ``generator``: t, then eps.
8. Body parts (Eq. 10): the masks must partition the D dims (disjoint, covering; at most one part
   may be ``"rest"`` = whatever the others leave), because ``sum_i M_i . eps_i`` is a valid noise
   estimate only then. The correction uses the SQUARED distance over the pairs i < j:
   ``eps = sum_i M_i . eps_i + lambda1 grad_{x_t} sum_{i<j} ||eps_i - eps_j||^2``. Eq. 10's plain norm
   has no gradient where two predictions agree, and its sum over all ordered pairs counts each pair
   twice (plus zero diagonal terms). Sign as the paper: ``+``; since the sampler subtracts eps from
   x_t, this moves x_t down the disagreement's gradient. The term is exactly 0 when all parts share
   one text (identical predictions). ``lambda1 = 0.01``: the paper's number for Fig. 5, not its
   strength. Per pair the squared form's gradient ``2 J^T d`` (``d = eps_i - eps_j``, ``J`` its Jacobian)
   is ``||d||`` times the plain norm's over ordered pairs (``2 J^T d / ||d||``), with ``||d||`` over the
   whole batch's tensor, so the same lambda pulls harder the more the parts disagree. The demos were
   measured at 0.01 and at 0, 0.1 and 1 (docs/motiondiffuse.md, "Fine-grained control").
   The named parts (:func:`part_feature_mask`; the paper names no dims) give each joint's root-relative
   position and rotation dims to the joint's part, and the velocity dims of EVERY joint, with the root
   features, to the part that holds the root. HumanML3D's joint velocity is the global velocity in the
   root's heading frame: it carries the body's travel. Split by joint, a waving upper body's near-zero
   velocities told the walking lower body's prediction that the body stands, and the walk shrank
   (docs/motiondiffuse.md, "Fine-grained control", 2026-12-04).
9. Time-varied (Eq. 11): each window [a_i, b_i) is run as its own sequence (positions from 0,
   length b_i - a_i <= max_len), zero-padded back to N frames. Windows may overlap (the smoothing
   term only acts where they do) and must cover all N frames: MotionDiffuse has no unconditional
   model to fill gaps. Where windows overlap the padded predictions are AVERAGED (Eq. 11 sums them,
   which doubles the noise scale there; on frames covered once the two agree). The correction is
   ``lambda2 grad_{x_t} sum_{i<j} ||O_ij . (eps'_i - eps'_j)||^2`` with O_ij the frames shared by windows
   i and j: outside the overlap the zero-padded difference is just +-eps_i, whose gradient would only
   shrink the predictions. ``lambda2 = 0.01`` (the same caveat as lambda1's). All samples of the batch share the segment
   boundaries (texts may differ per sample) and have length N.
10. Both compositions are ``model_fn(x_t, t) -> eps`` for :func:`models.diffusion.ddpm_sample` /
    :func:`models.diffusion.ddim_sample`. They call the network once per part/segment with the
    sample's own batch (no batching across parts), so one all-dims part, or one full-length segment,
    reproduces plain sampling bit for bit. The gradient term runs the parts under autograd
    (w.r.t. x_t only) and is skipped when lambda is 0 or no pair exists. They do not switch the
    network's train/eval mode: sample under ``model.eval()`` and ``torch.no_grad()``.
11. Input skip (``input_skip``, ours; off in the code): ``eps = F(x_t, t, text) + s_t x_t`` with a
    learned scalar per timestep, initialised to ``sqrt(1 - alpha_bar_t)``: the least-squares linear
    estimate of eps from x_t for unit-variance (normalised) data, as EDM's c_skip (Karras et al.
    2022). At high noise eps is almost x_t: the code's width 512 > 263 can carry every feature value
    through the network, a small CPU width cannot, and its eps error has a floor there. The skip
    carries x_t around the network, which then models the correction. A fresh model then predicts
    the linear estimate instead of 0.
    ``skip_kernel`` k > 1 (ours) widens the scalar into a fixed per-timestep, per-feature filter over
    k frames, ``eps = F + sum_j w_{t,d,j} x_t[n + j - k // 2, d]``: the Wiener estimate of the noise
    from the window (:func:`models.diffusion.wiener_taps`, ``target="epsilon"``, eigenvalue floor
    :data:`SKIP_EIG_FLOOR`), which the training recipe sets from the training features' lag moments;
    a fresh model holds the scalar's initial value at the centre tap. Near the data the noise is white
    and the motion smooth over neighbouring frames, so the window tells the two apart where one frame
    cannot, and where the network (after a CPU budget) predicts the noise no better than 0: the x0 a
    DDPM chain ends on then keeps the noise of its last hundred steps. The window reads a sample's
    first or last valid frame in place of frames beyond its ends (replicate padding: a motion is
    smooth there too, zeros are not), so the output does not depend on the batch's padding. The taps
    are a buffer, not parameters: each of the 1000 per-step filters would see a few dozen updates in
    ``tiny``'s budget.
12. Temporal kernel (``temporal_kernel`` k > 0, ours; the code: none, k = 0). Every FFN runs a
    depthwise convolution over frames (kernel k, zero padding, one filter per channel, initialised to
    the identity) between its first Linear and the GELU, with padded frames zeroed before it, so a
    valid frame sees only valid neighbours and a sample's output does not depend on the batch's
    padding. Nothing else in the network relates neighbouring frames: linear attention mixes all
    frames by content, so at small t, where eps is white noise on a smooth motion, the network has no
    local filter to tell the two apart and its eps estimate is no better than 0
    (``benchmarks/motiondiffuse_levels.py``); what it leaves in x0 is frame-to-frame jitter.
13. Classifier-free guidance (ours; the paper and the code have none). Training may replace a
    caption by the null caption with probability ``p_uncond`` (:func:`drop_captions`); sampling with
    ``guidance`` w != 1 predicts ``eps = eps_null + w (eps_text - eps_null)`` (Ho & Salimans 2022), the
    two passes batched (:func:`guided_text`, :func:`guided_denoise`), so NFE doubles. The null caption
    has no frozen encoder input: ONE valid word token whose state is all zeros (:func:`null_caption`),
    so ``Linear(E -> h)`` maps it to its bias, a learned vector. It needs no new parameters, so a
    model trained with ``p_uncond = 0`` loads unchanged (and samples at w = 1 exactly as before).
    The compositions (items 8-9) guide each part's or segment's prediction before combining them.
14. Frame patches (``patch_frames`` P, ours; the code: 1, one token per frame): the motion branch
    reads and writes P consecutive frames per token (``Linear(P D -> h)`` in, zero-initialised
    ``Linear(h -> P D)`` out, the positional table over ceil(max_len / P) tokens) through
    :mod:`models.patches`, as EMDM's item 9, so attention, the FFNs and their temporal kernel run on
    N / P tokens. The input skip still filters x_t frame by frame. A token is valid when its first
    frame is; the valid frames' outputs do not depend on the amount of padding. ``overlap_out`` (ours;
    P even): the output layer writes 2P frames per token, tapered and added to the neighbours'
    (:func:`models.patches.from_patches_overlapped`, as EMDM's item 9), so no step sits at a boundary.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, fields
from types import MappingProxyType
from typing import Any, Literal, NamedTuple

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from data.features import feature_groups
from data.skeleton import SKELETONS
from models.diffusion import (
    NoiseSchedule,
    TimestepSpacing,
    condition_dropout,
    ddim_sample,
    ddpm_sample,
    linear_betas,
    sample_timesteps,
    wiener_taps,
)
from models.patches import from_output_patches, output_width, to_patches
from models.rng import normal, rng_device
from models.transformer import TransformerLayer, checked_lengths, eval_mode, lengths_to_mask, timestep_embedding

AttentionKind = Literal["linear", "softmax"]
SamplingMethod = Literal["ddpm", "ddim"]
Lengths = Tensor | Sequence[int]
ModelFn = Callable[[Tensor, Tensor], Tensor]
#: The eigenvalue floor of the input-skip filter's Wiener taps, relative to each feature's variance (item 11).
SKIP_EIG_FLOOR = 1e-3

# --------------------------------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class MotionDiffuseConfig:
    """Hyper-parameters of :class:`MotionDiffuse` (defaults: a small CPU model; the code's are noted).

    ``feature_dim`` D (263). ``text_dim`` E: width of the frozen encoder's word-token states (384 for
    MiniLM; CLIP 512 in the code). Motion decoder: ``width`` h (code 512), ``layers`` (8), ``heads``
    (8), ``ff_dim`` (1024), ``dropout`` (0 in the code), ``max_len`` frames of the learned positional
    table (196), ``attention`` "linear" (efficient attention) or "softmax". Text branch:
    ``text_layers`` trainable transformer layers (4) of ``text_heads`` heads and ``text_ff_dim`` (2048)
    at width h. ``time_embed_mult``: the conditioning vector e has ``time_embed_mult * h`` dims (4).
    Schedule: ``num_train_timesteps`` T, ``beta_start``, ``beta_end``, ``rescale_betas`` (scale both
    by 1000 / T as the code). ``input_skip``: add a learned per-timestep multiple of x_t to the
    prediction (module docstring item 11; the code: off); ``skip_kernel`` (odd; 1: that multiple)
    widens it to a fixed per-timestep Wiener filter over frames. ``temporal_kernel``: frames of the depthwise
    convolution in every FFN (item 12; 0 = none, the code). ``patch_frames``: frames per token of the motion
    branch (item 14; 1, the code); ``overlap_out``: overlapping, tapered output patches (item 14; P even).
    """

    feature_dim: int = 263
    text_dim: int = 384
    width: int = 128
    layers: int = 4
    heads: int = 4
    ff_dim: int = 256
    dropout: float = 0.0
    text_layers: int = 2
    text_heads: int = 4
    text_ff_dim: int = 256
    time_embed_mult: int = 4
    max_len: int = 196
    attention: AttentionKind = "linear"
    num_train_timesteps: int = 1000
    beta_start: float = 1e-4
    beta_end: float = 0.02
    rescale_betas: bool = True
    input_skip: bool = False
    skip_kernel: int = 1
    temporal_kernel: int = 0
    patch_frames: int = 1
    overlap_out: bool = False

    def __post_init__(self) -> None:
        for name in ("feature_dim", "text_dim", "width", "layers", "heads", "ff_dim", "text_heads", "text_ff_dim",
                     "time_embed_mult", "max_len", "num_train_timesteps", "patch_frames"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        if isinstance(self.text_layers, bool) or not isinstance(self.text_layers, int) or self.text_layers < 0:
            raise ValueError(f"text_layers must be an integer >= 0, got {self.text_layers!r}")
        if (isinstance(self.temporal_kernel, bool) or not isinstance(self.temporal_kernel, int)
                or self.temporal_kernel < 0 or (self.temporal_kernel and self.temporal_kernel % 2 == 0)):
            raise ValueError(f"temporal_kernel must be 0 or an odd integer >= 1, got {self.temporal_kernel!r}")
        if (isinstance(self.skip_kernel, bool) or not isinstance(self.skip_kernel, int) or self.skip_kernel < 1
                or self.skip_kernel % 2 == 0):
            raise ValueError(f"skip_kernel must be an odd integer >= 1, got {self.skip_kernel!r}")
        if self.overlap_out and self.patch_frames % 2:
            raise ValueError(f"overlap_out needs an even patch_frames, got {self.patch_frames}")
        if self.skip_kernel > 1 and not self.input_skip:
            raise ValueError(f"skip_kernel {self.skip_kernel} needs input_skip: true")
        if self.width % self.heads:
            raise ValueError(f"width ({self.width}) must be divisible by heads ({self.heads})")
        if self.width % self.text_heads:
            raise ValueError(f"width ({self.width}) must be divisible by text_heads ({self.text_heads})")
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"dropout must lie in [0, 1), got {self.dropout!r}")
        if self.attention not in ("linear", "softmax"):
            raise ValueError(f"attention must be 'linear' or 'softmax', got {self.attention!r}")
        if not 0.0 < self.beta_start < self.beta_end:
            raise ValueError(f"beta_start/beta_end must satisfy 0 < beta_start < beta_end, got "
                             f"{self.beta_start!r}, {self.beta_end!r}")
        scale = 1000.0 / self.num_train_timesteps if self.rescale_betas else 1.0
        if self.beta_end * scale >= 1.0:
            raise ValueError(f"beta_end ({self.beta_end}) x {scale:g} (rescale_betas, num_train_timesteps="
                             f"{self.num_train_timesteps}) must stay below 1")

    @property
    def latent_dim(self) -> int:
        """The code's name for ``width``."""
        return self.width

    @property
    def time_embed_dim(self) -> int:
        """Width of the conditioning vector e (``time_embed_mult * width``)."""
        return self.time_embed_mult * self.width

    def make_schedule(self) -> NoiseSchedule:
        """The linear-beta :class:`NoiseSchedule` of this config (float64 tables)."""
        betas = linear_betas(self.num_train_timesteps, self.beta_start, self.beta_end,
                             rescale_to_steps=self.rescale_betas)
        return NoiseSchedule.from_betas(betas, name="linear")


def _as_config(config: MotionDiffuseConfig | Mapping[str, Any] | None) -> MotionDiffuseConfig:
    if isinstance(config, MotionDiffuseConfig):
        return config
    values = dict(config or {})
    unknown = set(values) - {f.name for f in fields(MotionDiffuseConfig)}
    if unknown:
        raise ValueError(f"unknown MotionDiffuseConfig fields: {sorted(unknown)}")
    return MotionDiffuseConfig(**values)


# --------------------------------------------------------------------------------------------------
# Attention kernels (heads split: (B, S, H, d_k))
# --------------------------------------------------------------------------------------------------


def linear_attention(q: Tensor, k: Tensor, v: Tensor, key_mask: Tensor) -> Tensor:
    """Efficient attention (Eq. 8; Shen et al. 2021): ``softmax_feat(q) @ (softmax_seq(k)^T @ v)`` per head.

    q (B, N, H, d), k and v (B, M, H, d), key_mask (B, M) bool True = valid -> (B, N, H, d). Queries
    are softmaxed over their d features, keys over the M positions with invalid ones at -inf (weight
    exactly 0); values are zeroed at invalid positions. Every row of ``key_mask`` needs a True.
    """
    keep = key_mask[:, :, None, None]
    q = q.softmax(dim=-1)
    k = k.masked_fill(~keep, float("-inf")).softmax(dim=1)
    v = torch.where(keep, v, 0.0)
    context = torch.einsum("bmhd,bmhe->bhde", k, v)  # the global feature map F_g, (B, H, d, d)
    return torch.einsum("bnhd,bhde->bnhe", q, context)


def softmax_attention(q: Tensor, k: Tensor, v: Tensor, key_mask: Tensor) -> Tensor:
    """Scaled-dot-product attention ``softmax(q k^T / sqrt(d)) v`` per head with invalid keys masked.

    Same shapes and mask convention as :func:`linear_attention` (the code's ``--no_eff`` variant).
    """
    keep = key_mask[:, :, None, None]
    v = torch.where(keep, v, 0.0)
    out = F.scaled_dot_product_attention(
        q.transpose(1, 2), k.transpose(1, 2), v.transpose(1, 2), attn_mask=key_mask[:, None, None, :]
    )
    return out.transpose(1, 2)


_ATTENTION: dict[str, Callable[[Tensor, Tensor, Tensor, Tensor], Tensor]] = {
    "linear": linear_attention,
    "softmax": softmax_attention,
}


# --------------------------------------------------------------------------------------------------
# Network blocks
# --------------------------------------------------------------------------------------------------


def _zero(module: nn.Linear) -> nn.Linear:
    nn.init.zeros_(module.weight)
    if module.bias is not None:
        nn.init.zeros_(module.bias)
    return module


class StylizationBlock(nn.Module):
    """Eq. 9 as the code: ``(scale, shift) = Linear(SiLU(e))``, ``h = LN(y) (1 + scale) + shift``,
    then ``SiLU -> Dropout -> Linear`` with the last Linear zero-initialised (a fresh block returns 0).

    y (B, N, h), e (B, E_t) -> (B, N, h).
    """

    def __init__(self, dim: int, emb_dim: int, dropout: float = 0.0) -> None:
        super().__init__()
        self.emb_layers = nn.Sequential(nn.SiLU(), nn.Linear(emb_dim, 2 * dim))
        self.norm = nn.LayerNorm(dim)
        self.out_layers = nn.Sequential(nn.SiLU(), nn.Dropout(dropout), _zero(nn.Linear(dim, dim)))

    def forward(self, y: Tensor, emb: Tensor) -> Tensor:
        scale, shift = self.emb_layers(emb)[:, None].chunk(2, dim=-1)
        return self.out_layers(self.norm(y) * (1.0 + scale) + shift)


class MotionAttention(nn.Module):
    """Self- or cross-attention sub-block: ``x + Stylization(Attn(LN(x), memory), e)``.

    Self-attention: queries, keys and values from ``LN(x)`` with the frame mask. Cross-attention
    (``cross=True``): keys and values from ``LN_text(memory)`` with the word mask. ``kind``: "linear"
    (:func:`linear_attention`) or "softmax" (:func:`softmax_attention`). Projections have biases, as
    the code's.
    """

    def __init__(self, dim: int, heads: int, emb_dim: int, dropout: float = 0.0, *,
                 kind: AttentionKind = "linear", cross: bool = False) -> None:
        super().__init__()
        if kind not in _ATTENTION:
            raise ValueError(f"unknown attention {kind!r}: linear | softmax")
        self.heads, self.kind = heads, kind
        self.norm = nn.LayerNorm(dim)
        self.memory_norm = nn.LayerNorm(dim) if cross else None
        self.query, self.key, self.value = nn.Linear(dim, dim), nn.Linear(dim, dim), nn.Linear(dim, dim)
        self.style = StylizationBlock(dim, emb_dim, dropout)

    def heads_of(self, x: Tensor, memory: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """Projected (q, k, v), each split into heads (B, S, H, d_k), from x (B, N, h) [and memory (B, M, h)]."""
        h = self.norm(x)
        src = h if self.memory_norm is None else self.memory_norm(memory)  # type: ignore[arg-type]
        split = (self.heads, -1)
        return (self.query(h).unflatten(-1, split), self.key(src).unflatten(-1, split),
                self.value(src).unflatten(-1, split))

    def forward(self, x: Tensor, emb: Tensor, key_mask: Tensor, memory: Tensor | None = None) -> Tensor:
        """x (B, N, h), e (B, E_t), key_mask (B, N) or (B, M) bool True = valid key, memory (B, M, h)."""
        if (memory is None) != (self.memory_norm is None):
            raise ValueError("memory must be given exactly for a cross-attention block")
        q, k, v = self.heads_of(x, memory)
        y = _ATTENTION[self.kind](q, k, v, key_mask).flatten(2)
        return x + self.style(y, emb)


class StylizedFFN(nn.Module):
    """``x + Stylization(Linear(GELU(Conv(Linear(x)))), e)``, the output Linear zero-initialised (code).

    ``kernel`` > 0: ``Conv`` is a depthwise convolution over frames initialised to the identity, with
    padded frames zeroed before it (module docstring item 12); 0: no convolution (the code).
    """

    def __init__(self, dim: int, ff_dim: int, emb_dim: int, dropout: float = 0.0, kernel: int = 0) -> None:
        super().__init__()
        self.inner = nn.Linear(dim, ff_dim)
        self.conv = None
        if kernel:
            self.conv = nn.Conv1d(ff_dim, ff_dim, kernel, padding=kernel // 2, groups=ff_dim)
            nn.init.zeros_(self.conv.weight)
            nn.init.zeros_(self.conv.bias)
            with torch.no_grad():
                self.conv.weight[:, 0, kernel // 2] = 1.0
        self.outer = nn.Sequential(nn.GELU(), nn.Dropout(dropout), _zero(nn.Linear(ff_dim, dim)))
        self.style = StylizationBlock(dim, emb_dim, dropout)

    def forward(self, x: Tensor, emb: Tensor, frame_mask: Tensor | None = None) -> Tensor:
        """x (B, N, h), e (B, E_t), frame_mask (B, N) bool True = valid frame (needed with a kernel)."""
        h = self.inner(x)
        if self.conv is not None:
            if frame_mask is None:
                raise ValueError("a temporal kernel needs the frame mask")
            h = self.conv(torch.where(frame_mask[..., None], h, 0.0).transpose(1, 2)).transpose(1, 2)
        return x + self.style(self.outer(h), emb)


class DecoderLayer(nn.Module):
    """One motion-decoder layer: linear self-attention, linear cross-attention to the text, FFN."""

    def __init__(self, cfg: MotionDiffuseConfig) -> None:
        super().__init__()
        h, e = cfg.width, cfg.time_embed_dim
        self.self_attn = MotionAttention(h, cfg.heads, e, cfg.dropout, kind=cfg.attention)
        self.cross_attn = MotionAttention(h, cfg.heads, e, cfg.dropout, kind=cfg.attention, cross=True)
        self.ffn = StylizedFFN(h, cfg.ff_dim, e, cfg.dropout, cfg.temporal_kernel)

    def forward(self, x: Tensor, emb: Tensor, frame_mask: Tensor, text: Tensor, text_mask: Tensor) -> Tensor:
        x = self.self_attn(x, emb, frame_mask)
        x = self.cross_attn(x, emb, text_mask, text)
        return self.ffn(x, emb, frame_mask)


class TextEncoding(NamedTuple):
    """Output of :meth:`MotionDiffuse.encode_text`, reusable across denoising steps.

    ``tokens`` (B, L, h): text-transformer states (the cross-attention memory); ``mask`` (B, L) bool
    True = valid token; ``emb`` (B, time_embed_dim): ``Linear(masked mean of tokens)``, added to the
    timestep embedding.
    """

    tokens: Tensor
    mask: Tensor
    emb: Tensor


class MotionDiffuse(nn.Module):
    """MotionDiffuse's noise predictor ``eps_theta(x_t, t, text)`` (module docstring items 1-4).

    ``config`` is a :class:`MotionDiffuseConfig` or its dict. :meth:`forward` encodes the text and
    denoises; samplers call :meth:`encode_text` once and :meth:`denoise` per step.
    """

    def __init__(self, config: MotionDiffuseConfig | Mapping[str, Any] | None = None) -> None:
        super().__init__()
        cfg = _as_config(config)
        self.config = cfg
        h, e = cfg.width, cfg.time_embed_dim
        # text branch
        self.text_in = nn.Linear(cfg.text_dim, h)
        self.text_layers = nn.ModuleList(
            TransformerLayer(h, cfg.text_heads, cfg.text_ff_dim, cfg.dropout, "gelu") for _ in range(cfg.text_layers)
        )
        self.text_norm = nn.LayerNorm(h)
        self.text_proj = nn.Linear(h, e)
        # timestep embedding
        self.time_mlp = nn.Sequential(nn.Linear(h, e), nn.SiLU(), nn.Linear(e, e))
        # motion branch
        p = cfg.patch_frames
        self.frame_in = nn.Linear(p * cfg.feature_dim, h)
        self.positions = nn.Parameter(torch.randn(-(-cfg.max_len // p), h))
        self.layers = nn.ModuleList(DecoderLayer(cfg) for _ in range(cfg.layers))
        self.frame_out = _zero(nn.Linear(h, output_width(p, cfg.feature_dim, cfg.overlap_out)))
        scalar = (1.0 - cfg.make_schedule().alphas_cumprod).sqrt().float()
        self.skip = nn.Parameter(scalar) if cfg.input_skip and cfg.skip_kernel == 1 else None
        taps = None
        if cfg.input_skip and cfg.skip_kernel > 1:  # the scalar at the centre tap until the recipe sets the taps
            taps = torch.zeros(cfg.num_train_timesteps, cfg.feature_dim, cfg.skip_kernel)
            taps[:, :, cfg.skip_kernel // 2] = scalar[:, None]
        self.skip_taps: Tensor | None
        self.register_buffer("skip_taps", taps)

    def set_skip_taps(self, moments: Tensor) -> None:
        """Set the input-skip filter (``skip_kernel`` > 1) to the Wiener estimate of the noise under the lag
        moments (L >= k, D) of the normalised training features (module docstring item 11)."""
        if self.skip_taps is None:
            raise RuntimeError("this model has no input-skip filter (needs input_skip and skip_kernel > 1)")
        taps = wiener_taps(moments, self.config.make_schedule().alphas_cumprod, self.config.skip_kernel,
                           target="epsilon", eig_floor=SKIP_EIG_FLOOR)
        self.skip_taps.copy_(taps.to(self.skip_taps))

    def encode_text(self, word_states: Tensor, word_mask: Tensor) -> TextEncoding:
        """Frozen word-token states (B, L, text_dim), their mask (B, L) bool True = valid -> :class:`TextEncoding`."""
        if word_states.ndim != 3 or word_states.shape[-1] != self.config.text_dim:
            raise ValueError(f"word_states must be (B, L, {self.config.text_dim}), got {tuple(word_states.shape)}")
        if tuple(word_mask.shape) != tuple(word_states.shape[:2]):
            raise ValueError(f"word_mask {tuple(word_mask.shape)} does not match word_states "
                             f"{tuple(word_states.shape)}")
        mask = word_mask.to(word_states.device).bool()
        if not bool(mask.any(dim=1).all()):
            raise ValueError("word_mask has a caption with no valid token; every row needs at least one True")
        dtype = self.text_in.weight.dtype
        tokens = self.text_in(torch.where(mask[..., None], word_states.to(dtype), 0.0))
        for layer in self.text_layers:
            tokens = layer(tokens, key_padding_mask=~mask)
        tokens = self.text_norm(tokens)
        weights = mask.to(tokens.dtype)[..., None]
        pooled = (tokens * weights).sum(1) / weights.sum(1)
        return TextEncoding(tokens, mask, self.text_proj(pooled))

    def denoise(self, x_t: Tensor, t: Tensor | int, text: TextEncoding, lengths: Lengths) -> Tensor:
        """Predicted noise (B, N, D), 0 on padded frames, from x_t (B, N, D), t (B,) int, an encoded text."""
        b, n, d = x_t.shape
        if d != self.config.feature_dim:
            raise ValueError(f"x_t has {d} features, the model {self.config.feature_dim}")
        if n > self.config.max_len:
            raise ValueError(f"x_t has {n} frames, more than max_len={self.config.max_len}")
        lengths_t = torch.as_tensor(lengths, device=x_t.device).long()
        if lengths_t.shape != (b,):
            raise ValueError(f"lengths must have shape ({b},), got {tuple(lengths_t.shape)}")
        if lengths_t.device.type == "cpu":  # on a GPU: checked by the sampler, before its steps
            checked_lengths(lengths_t, n)
        valid = lengths_to_mask(lengths_t, n)
        steps = torch.as_tensor(t, device=x_t.device).long()
        steps = steps.expand(b) if steps.ndim == 0 else steps
        dtype = self.frame_in.weight.dtype
        emb = self.time_mlp(timestep_embedding(steps, self.config.width, flip_sin_to_cos=True).to(dtype))
        emb = emb + text.emb.to(dtype)
        patches, token_valid = to_patches(x_t.to(dtype), valid, self.config.patch_frames)
        h = self.frame_in(patches) + self.positions[: patches.shape[1]]
        tokens = text.tokens.to(dtype)
        for layer in self.layers:
            h = layer(h, emb, token_valid, tokens, text.mask)
        out = from_output_patches(self.frame_out(h), token_valid, n, self.config.patch_frames, self.config.overlap_out)
        if self.skip is not None:
            out = out + self.skip[steps].to(dtype)[:, None, None] * x_t.to(dtype)
        if self.skip_taps is not None:
            out = out + self.skip_filter(x_t.to(dtype), steps, lengths_t)
        return torch.where(valid[..., None], out, 0.0)

    def skip_filter(self, x_t: Tensor, steps: Tensor, lengths: Tensor) -> Tensor:
        """The input-skip filter of x_t (B, N, D) at ``steps`` (B,), frames beyond a sample's ends read as its
        first or last valid frame (module docstring item 11)."""
        if self.skip_taps is None:
            raise RuntimeError("this model has no input-skip filter (needs input_skip and skip_kernel > 1)")
        b, n, _ = x_t.shape
        k = self.skip_taps.shape[-1]
        frames = torch.arange(n, device=x_t.device)[:, None] + torch.arange(k, device=x_t.device)[None] - k // 2
        frames = torch.minimum(frames[None].clamp_min(0), (lengths - 1)[:, None, None])  # (B, N, k)
        windows = x_t[torch.arange(b, device=x_t.device)[:, None, None], frames]  # (B, N, k, D)
        return torch.einsum("bnkd,bdk->bnd", windows, self.skip_taps.index_select(0, steps).to(x_t.dtype))

    def forward(self, x_t: Tensor, t: Tensor | int, word_states: Tensor, word_mask: Tensor,
                lengths: Lengths) -> Tensor:
        """eps_theta (B, N, D) from x_t (B, N, D), t (B,) int, word_states (B, L, text_dim), word_mask (B, L)
        bool True = valid token, lengths (B,) in [1, N]; 0 on padded frames."""
        return self.denoise(x_t, t, self.encode_text(word_states, word_mask), lengths)


# --------------------------------------------------------------------------------------------------
# Training loss and sampling
# --------------------------------------------------------------------------------------------------


def null_caption(batch: int, length: int, dim: int, device: torch.device | str | None = None,
                 dtype: torch.dtype = torch.float32) -> tuple[Tensor, Tensor]:
    """The null caption (module docstring item 13) as word states (B, L, E) of zeros and a mask (B, L) with
    only the first token valid. L >= 1."""
    if length < 1:
        raise ValueError(f"the null caption needs at least one token slot, got length {length}")
    states = torch.zeros(batch, length, dim, device=device, dtype=dtype)
    mask = torch.zeros(batch, length, dtype=torch.bool, device=device)
    mask[:, 0] = True
    return states, mask


def drop_captions(word_states: Tensor, word_mask: Tensor, p: float,
                  generator: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
    """Condition dropout for classifier-free guidance: each row becomes :func:`null_caption` w.p. ``p``.

    One uniform per row from ``generator`` (:func:`models.diffusion.condition_dropout`; none drawn when
    p <= 0, which returns the inputs).
    """
    if p <= 0:
        return word_states, word_mask
    b, length, dim = word_states.shape
    drop = condition_dropout(b, p, generator, word_states.device)
    null_states, null_mask = null_caption(b, length, dim, word_states.device, word_states.dtype)
    return (torch.where(drop[:, None, None], null_states, word_states),
            torch.where(drop[:, None], null_mask, word_mask.to(word_states.device).bool()))


def guided_text(model: MotionDiffuse, word_states: Tensor, word_mask: Tensor, guidance: float = 1.0) -> TextEncoding:
    """The text encoding a guided sampler needs: the B captions, then (guidance != 1) B null captions."""
    device = next(model.parameters()).device
    word_states, word_mask = word_states.to(device), word_mask.to(device)
    if guidance == 1.0:
        return model.encode_text(word_states, word_mask)
    null_states, null_mask = null_caption(*word_states.shape, device=device, dtype=word_states.dtype)
    return model.encode_text(torch.cat([word_states, null_states]), torch.cat([word_mask.bool(), null_mask]))


def guided_denoise(model: MotionDiffuse, x_t: Tensor, t: Tensor | int, text: TextEncoding, lengths: Tensor,
                   guidance: float = 1.0) -> Tensor:
    """``eps_null + guidance (eps_text - eps_null)`` (module docstring item 13) for a :func:`guided_text`
    encoding, both passes in one batch; ``guidance == 1`` is the plain model (one pass)."""
    if guidance == 1.0:
        return model.denoise(x_t, t, text, lengths)
    steps = torch.as_tensor(t, device=x_t.device).long()
    steps = steps.expand(x_t.shape[0]) if steps.ndim == 0 else steps
    eps = model.denoise(torch.cat([x_t, x_t]), torch.cat([steps, steps]), text, torch.cat([lengths, lengths]))
    eps_text, eps_null = eps.chunk(2)
    return eps_null + guidance * (eps_text - eps_null)


def training_loss(
    model: MotionDiffuse,
    schedule: NoiseSchedule,
    x0: Tensor,
    lengths: Lengths,
    word_states: Tensor,
    word_mask: Tensor,
    generator: torch.Generator | None = None,
    p_uncond: float = 0.0,
) -> Tensor:
    """Eq. 4, masked: ``sum_{valid (b, n, d)} (eps_theta(x_t, t, text) - eps)^2 / (valid frames * D)``.

    t ~ U{0..T-1} (B,), then eps ~ N(0, I) like x0 (B, N, D), then (``p_uncond`` > 0) the caption
    dropout of :func:`drop_captions`, all from ``generator`` in that order;
    ``x_t = schedule.q_sample(x0, t, eps)``. A scalar over the whole batch (the code's mean).
    """
    b, n, d = x0.shape
    t = sample_timesteps(b, schedule.num_steps, generator, x0.device)
    noise = normal(x0.shape, x0, generator)
    lengths_t = torch.as_tensor(lengths, device=x0.device).long()
    valid = lengths_to_mask(lengths_t, n)[..., None]
    word_states, word_mask = drop_captions(word_states, word_mask, p_uncond, generator)
    pred = model(schedule.q_sample(x0, t, noise), t, word_states, word_mask, lengths_t)
    sq = torch.where(valid, (pred - noise).square(), 0.0)
    return sq.sum() / (valid.sum().to(sq.dtype) * d).clamp(min=1.0)


def _model_device_dtype(model: nn.Module) -> tuple[torch.device, torch.dtype]:
    p = next(model.parameters())
    return p.device, p.dtype


@torch.no_grad()
def sample_motiondiffuse(
    model: MotionDiffuse,
    schedule: NoiseSchedule,
    lengths: Lengths,
    word_states: Tensor,
    word_mask: Tensor,
    *,
    method: SamplingMethod = "ddpm",
    steps: int | None = None,
    generator: torch.Generator | None = None,
    eta: float = 0.0,
    timestep_spacing: TimestepSpacing = "trailing",
    num_frames: int | None = None,
    x_T: Tensor | None = None,
    guidance: float = 1.0,
) -> Tensor:
    """Text-to-motion: lengths (B,), word_states (B, L, E), word_mask (B, L) -> normalised features (B, N, D).

    N = ``num_frames`` or ``max(lengths)``. ``x_T ~ N(0, I)`` from ``generator`` (or ``x_T``), then
    ``method="ddpm"``: :func:`models.diffusion.ddpm_sample` over all T steps (``steps`` None or T),
    fixed_small variance; ``"ddim"``: :func:`models.diffusion.ddim_sample` with ``steps`` (default 50),
    ``eta``, the ``timestep_spacing`` grid and ``set_alpha_to_one=True`` (module docstring item 6), with
    classifier-free ``guidance`` (item 13; 1 = none). The text is encoded once. Padded frames are 0. Runs
    the model in eval mode (restored) under no_grad.
    """
    cfg = model.config
    device, dtype = _model_device_dtype(model)
    lengths_t, n = checked_lengths(lengths, num_frames)
    lengths_t = lengths_t.to(device)
    shape = (int(lengths_t.shape[0]), n, cfg.feature_dim)
    if x_T is None:
        x_T = torch.randn(shape, generator=generator, device=rng_device(generator, device), dtype=dtype)
    x_T = x_T.to(device, dtype)
    with eval_mode(model):
        text = guided_text(model, word_states, word_mask, guidance)

        def model_fn(x: Tensor, t: Tensor) -> Tensor:
            return guided_denoise(model, x, t, text, lengths_t, guidance)

        if method == "ddpm":
            if steps is not None and steps != schedule.num_steps:
                raise ValueError(f"DDPM runs all {schedule.num_steps} steps; got steps={steps} (use method='ddim')")
            x0 = ddpm_sample(model_fn, shape, schedule, generator, x_T=x_T, variance_type="fixed_small")
        elif method == "ddim":
            x0 = ddim_sample(model_fn, shape, schedule, 50 if steps is None else steps, eta, generator, x_T=x_T,
                             timestep_spacing=timestep_spacing, set_alpha_to_one=True)
        else:
            raise ValueError(f"unknown method {method!r}: ddpm | ddim")
    return torch.where(lengths_to_mask(lengths_t, n)[..., None], x0, 0.0)


# --------------------------------------------------------------------------------------------------
# Fine-grained control: body parts (Eq. 10)
# --------------------------------------------------------------------------------------------------

#: Joints of each body part per skeleton (joint ids of :mod:`data.skeleton`). "root" is the pelvis
#: (root features and its velocity); the legs own the foot contacts of their joints.
PART_JOINTS: Mapping[str, Mapping[str, tuple[int, ...]]] = MappingProxyType({
    "humanml3d": MappingProxyType({
        "root": (0,),
        "left_leg": (1, 4, 7, 10),
        "right_leg": (2, 5, 8, 11),
        "torso": (3, 6, 9, 12, 15),  # spine1-3, neck, head
        "left_arm": (13, 16, 18, 20),  # collar, shoulder, elbow, wrist
        "right_arm": (14, 17, 19, 21),
    }),
    "kit": MappingProxyType({
        "root": (0,),
        "left_leg": (11, 12, 13, 14, 15),
        "right_leg": (16, 17, 18, 19, 20),
        "torso": (1, 2, 3, 4),
        "left_arm": (5, 6, 7),
        "right_arm": (8, 9, 10),
    }),
})

#: Named parts as unions of the atomic parts of :data:`PART_JOINTS`. "upper" and "lower" partition
#: the features (the paper's example); so do {root, legs, torso, arms} and the six atoms.
PART_UNIONS: Mapping[str, tuple[str, ...]] = MappingProxyType({
    "root": ("root",),
    "left_leg": ("left_leg",),
    "right_leg": ("right_leg",),
    "torso": ("torso",),
    "left_arm": ("left_arm",),
    "right_arm": ("right_arm",),
    "legs": ("left_leg", "right_leg"),
    "arms": ("left_arm", "right_arm"),
    "lower": ("root", "left_leg", "right_leg"),
    "upper": ("torso", "left_arm", "right_arm"),
    "whole": ("root", "left_leg", "right_leg", "torso", "left_arm", "right_arm"),
})

#: The name a composition accepts for "every dim the other parts leave".
REST = "rest"


def _skeleton_for(joints_num: int) -> str:
    for name, skeleton in SKELETONS.items():
        if skeleton.joints_num == joints_num and name in PART_JOINTS:
            return name
    raise ValueError(f"no body-part table for joints_num={joints_num}; known: "
                     f"{ {n: SKELETONS[n].joints_num for n in PART_JOINTS} }")


def joint_feature_indices(joint: int, joints_num: int = 22) -> list[int]:
    """Feature dims of one joint in the 12J - 1 layout: ric (3), rot (6) and vel (3) for j >= 1; the
    root (j = 0) owns root_yaw, root_xz, root_y and its vel (3). Contacts are not included."""
    g = feature_groups(joints_num)
    if not 0 <= joint < joints_num:
        raise ValueError(f"joint must lie in [0, {joints_num}), got {joint}")
    vel = list(range(g["vel"].start + 3 * joint, g["vel"].start + 3 * joint + 3))
    if joint == 0:
        return list(range(g["root_yaw"].start, g["root_y"].stop)) + vel
    ric = list(range(g["ric"].start + 3 * (joint - 1), g["ric"].start + 3 * joint))
    rot = list(range(g["rot"].start + 6 * (joint - 1), g["rot"].start + 6 * joint))
    return ric + rot + vel


def part_feature_mask(name: str, joints_num: int = 22) -> Tensor:
    """Bool (12J - 1,) mask of the feature dims of a named part (:data:`PART_UNIONS`), a fresh tensor.

    A part owns the root-relative position and rotation dims of its joints (:func:`joint_feature_indices`
    less the velocities); a leg also owns the foot contacts of its foot joints (the skeleton's ``feet``).
    The part that holds the root owns the root features and the velocity dims of EVERY joint (module
    docstring item 8: a joint's velocity feature is its global velocity in the root's heading frame,
    so it carries the root's travel). "upper" and "lower" partition the 263 HumanML3D dims.
    """
    if name not in PART_UNIONS:
        raise ValueError(f"unknown body part {name!r}; known: {sorted(PART_UNIONS)}")
    skeleton_name = _skeleton_for(joints_num)
    table, feet = PART_JOINTS[skeleton_name], SKELETONS[skeleton_name].feet
    groups = feature_groups(joints_num)
    mask = torch.zeros(12 * joints_num - 1, dtype=torch.bool)
    for atom in PART_UNIONS[name]:
        for joint in table[atom]:
            mask[joint_feature_indices(joint, joints_num)] = True
            for k, foot in enumerate(feet):
                if foot == joint:
                    mask[groups["contacts"].start + k] = True
    mask[groups["vel"]] = "root" in PART_UNIONS[name]
    return mask


#: HumanML3D (22 joints, 263 dims) masks of every named part; read-only, use
#: :func:`part_feature_mask` for a tensor you may modify.
PART_MASKS: Mapping[str, Tensor] = MappingProxyType({name: part_feature_mask(name) for name in PART_UNIONS})


class PartPrompt(NamedTuple):
    """One body part's prompt: ``part`` a name (:data:`PART_UNIONS` or "rest") or a bool (D,) mask, and its
    caption's word-token states (B, L, E) and mask (B, L)."""

    part: str | Tensor
    word_states: Tensor
    word_mask: Tensor


def _resolve_part_masks(parts: Sequence[str | Tensor], dim: int) -> list[Tensor]:
    """Bool (D,) masks of the parts (names or masks), checked to partition the D dims."""
    joints_num = (dim + 1) // 12
    masks: list[Tensor | None] = []
    labels: list[str] = []
    for i, part in enumerate(parts):
        if isinstance(part, str):
            labels.append(repr(part))
            if part == REST:
                masks.append(None)
                continue
            if (dim + 1) % 12:
                raise ValueError(f"named part {part!r} needs a 12J - 1 feature layout, got D={dim}; pass a mask")
            masks.append(part_feature_mask(part, joints_num))
        else:
            labels.append(f"mask #{i}")
            mask = torch.as_tensor(part).cpu()
            if mask.dtype != torch.bool or mask.shape != (dim,):
                raise ValueError(f"part mask #{i} must be a bool tensor of shape ({dim},), got "
                                 f"{mask.dtype} {tuple(mask.shape)}")
            masks.append(mask)
    if sum(m is None for m in masks) > 1:
        raise ValueError(f"at most one part may be {REST!r}")
    covered = torch.zeros(dim, dtype=torch.bool)
    for i, mask in enumerate(masks):
        if mask is None:
            continue
        for j in range(i):
            other = masks[j]
            if other is not None and bool((mask & other).any()):
                raise ValueError(f"body parts {labels[j]} and {labels[i]} overlap in "
                                 f"{int((mask & other).sum())} feature dims; the masks must be disjoint")
        covered |= mask
    if None in masks:
        rest = ~covered
        if not bool(rest.any()):
            raise ValueError(f"part {REST!r} is empty: the other parts already cover all {dim} dims")
        masks[masks.index(None)] = rest
        covered = torch.ones(dim, dtype=torch.bool)
    if not bool(covered.all()):
        raise ValueError(f"body parts {', '.join(labels)} leave {int((~covered).sum())} of {dim} feature dims "
                         f"uncovered; add a part or use {REST!r}")
    return [m for m in masks if m is not None]


def _pairwise_correction(preds: Sequence[Tensor], x: Tensor, weights: Sequence[tuple[int, int, Tensor | None]],
                         lam: float) -> Tensor:
    """``lam * grad_x sum_{(i, j, w)} ||w . (preds_i - preds_j)||^2`` (w None: all entries)."""
    total = x.new_zeros(())
    for i, j, w in weights:
        diff = preds[i] - preds[j]
        total = total + (diff if w is None else diff * w).square().sum()
    (grad,) = torch.autograd.grad(total, x)
    return lam * grad


def body_part_model_fn(
    model: MotionDiffuse,
    parts: Sequence[PartPrompt | tuple[str | Tensor, Tensor, Tensor]],
    lengths: Lengths,
    *,
    lambda1: float = 0.01,
    guidance: float = 1.0,
) -> ModelFn:
    """Body part-independent control (Eq. 10; module docstring item 8) as ``model_fn(x_t, t) -> eps``.

    ``parts``: one :class:`PartPrompt` (part, word_states (B, L, E), word_mask (B, L)) per part; the
    part masks must partition the D feature dims (a name from :data:`PART_UNIONS`, ``"rest"``, or a
    bool (D,) mask). Returns ``eps = sum_i M_i . eps_i + lambda1 grad_{x_t} sum_{i<j} ||eps_i - eps_j||^2``
    with ``eps_i = model(x_t, t, text_i)`` (guided with ``guidance``, item 13). One part covering every dim
    gives exactly the plain model.
    Raises ValueError for unknown names, overlapping or non-covering masks, or no parts.
    """
    prompts = [PartPrompt(*p) for p in parts]
    if not prompts:
        raise ValueError("body_part_model_fn needs at least one part")
    device, _ = _model_device_dtype(model)
    masks = [m.to(device) for m in _resolve_part_masks([p.part for p in prompts], model.config.feature_dim)]
    with torch.no_grad():
        texts = [guided_text(model, p.word_states, p.word_mask, guidance) for p in prompts]
    lengths_t = checked_lengths(lengths)[0].to(device)
    pairs = [(i, j, None) for i in range(len(prompts)) for j in range(i + 1, len(prompts))]
    use_grad = lambda1 != 0.0 and bool(pairs)

    def model_fn(x_t: Tensor, t: Tensor) -> Tensor:
        with torch.enable_grad() if use_grad else torch.no_grad():
            x = x_t.detach().requires_grad_(True) if use_grad else x_t
            preds = [guided_denoise(model, x, t, text, lengths_t, guidance) for text in texts]
            correction = _pairwise_correction(preds, x, pairs, lambda1) if use_grad else None
        eps = torch.zeros_like(x_t)
        for mask, pred in zip(masks, preds, strict=True):
            eps = torch.where(mask, pred.detach(), eps)
        return eps if correction is None else eps + correction

    return model_fn


# --------------------------------------------------------------------------------------------------
# Fine-grained control: time-varied prompts (Eq. 11)
# --------------------------------------------------------------------------------------------------


class TimeSegment(NamedTuple):
    """One time-varied prompt: frames ``[start, end)`` and the caption's word states (B, L, E) and mask (B, L)."""

    start: int
    end: int
    word_states: Tensor
    word_mask: Tensor


def _check_segments(segments: Sequence[TimeSegment], num_frames: int, max_len: int) -> None:
    if not segments:
        raise ValueError("time_varied_model_fn needs at least one segment")
    covered = torch.zeros(num_frames, dtype=torch.bool)
    for i, s in enumerate(segments):
        if not 0 <= s.start < s.end <= num_frames:
            raise ValueError(f"segment #{i} [{s.start}, {s.end}) is out of range: need 0 <= start < end <= "
                             f"num_frames={num_frames}")
        if s.end - s.start > max_len:
            raise ValueError(f"segment #{i} [{s.start}, {s.end}) has {s.end - s.start} frames, more than the "
                             f"model's max_len={max_len}")
        covered[s.start:s.end] = True
    if not bool(covered.all()):
        gaps = torch.nonzero(~covered).flatten().tolist()
        raise ValueError(f"segments leave frames uncovered (first: {gaps[:5]}, {len(gaps)} in all); they must "
                         f"cover [0, {num_frames}) (MotionDiffuse has no unconditional model to fill gaps)")


def time_varied_model_fn(
    model: MotionDiffuse,
    segments: Sequence[TimeSegment | tuple[int, int, Tensor, Tensor]],
    num_frames: int,
    *,
    lambda2: float = 0.01,
    guidance: float = 1.0,
) -> ModelFn:
    """Time-varied control (Eq. 11; module docstring item 9) as ``model_fn(x_t, t) -> eps`` for x_t (B, N, D).

    Each segment's eps_i is the model on ``x_t[:, start:end]`` (its own sequence, length end - start;
    guided with ``guidance``, item 13) zero-padded to N = ``num_frames``; ``eps = (sum_i eps'_i) /
    (windows covering each frame) + lambda2 grad_{x_t} sum_{i<j} ||O_ij . (eps'_i - eps'_j)||^2`` with
    O_ij the frames windows i and j share. Segments may overlap and must cover [0, N); one segment
    [0, N) gives exactly the plain model with lengths N. Raises ValueError for out-of-range, too long
    (> max_len) or non-covering segments.
    """
    segs = [TimeSegment(int(s[0]), int(s[1]), s[2], s[3]) for s in segments]
    _check_segments(segs, num_frames, model.config.max_len)
    device, dtype = _model_device_dtype(model)
    with torch.no_grad():
        texts = [guided_text(model, s.word_states, s.word_mask, guidance) for s in segs]
    count = torch.zeros(num_frames, device=device, dtype=dtype)
    for s in segs:
        count[s.start:s.end] += 1.0
    count = count[None, :, None]
    pairs: list[tuple[int, int, Tensor | None]] = []
    for i in range(len(segs)):
        for j in range(i + 1, len(segs)):
            lo, hi = max(segs[i].start, segs[j].start), min(segs[i].end, segs[j].end)
            if lo < hi:
                overlap = torch.zeros(num_frames, device=device, dtype=dtype)
                overlap[lo:hi] = 1.0
                pairs.append((i, j, overlap[None, :, None]))
    use_grad = lambda2 != 0.0 and bool(pairs)

    def model_fn(x_t: Tensor, t: Tensor) -> Tensor:
        b, n, _ = x_t.shape
        if n != num_frames:
            raise ValueError(f"x_t has {n} frames, the segments were built for num_frames={num_frames}")
        with torch.enable_grad() if use_grad else torch.no_grad():
            x = x_t.detach().requires_grad_(True) if use_grad else x_t
            padded = []
            for s, text in zip(segs, texts, strict=True):
                pred = guided_denoise(model, x[:, s.start:s.end], t, text,
                                      torch.full((b,), s.end - s.start, device=device), guidance)
                padded.append(F.pad(pred, (0, 0, s.start, n - s.end)))
            correction = _pairwise_correction(padded, x, pairs, lambda2) if use_grad else None
        total = torch.zeros_like(x_t)
        for pred in padded:
            total = total + pred.detach()
        eps = total / count.to(total.dtype)
        return eps if correction is None else eps + correction

    return model_fn
