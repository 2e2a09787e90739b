"""MLD's latent-diffusion denoiser, its training loss and its sampler (pure torch).

Reference: ``reference/motionlcm_mld.md`` section 3 (``MldDenoiser``, ``arch: trans_enc``); DESIGN.md
"Models -> MLD denoiser"; issue 5 item 3. Shapes: B batch, L latent tokens, C latent channels, h
transformer width, E text-embedding dims (384 for MiniLM; 768 for MLD's CLIP), T frames, D features.

Denoiser (MLD Sec. 3.2): the skip transformer of :mod:`models.transformer` over the token sequence
``[z_t (L tokens); time token; text token]`` plus a positional encoding, no attention mask; the
first L outputs are the prediction (epsilon by default). Time token: ``MLP(sinusoid(t))`` with
``MLP = Linear(F -> h) -> SiLU -> Linear(h -> h)`` (diffusers ``Timesteps(F, flip_sin_to_cos=True,
freq_shift=0)`` + ``TimestepEmbedding``; MLD's F is 768). Text token: ``Linear(E -> h)`` of the pooled
frozen text embedding, after a ReLU in MLD / MotionLCM V1 (``text_activation="relu"``) or without one
in MotionLCM V2 (``"none"``). When h != C the latent goes through ``Linear(C -> h)`` in and
``Linear(h -> C)`` out (MotionLCM V2); otherwise there are no latent projections (MLD 1 x 256).

Word tokens (``word_tokens``; our addition, ``"none"`` in MLD and in the ``paper`` profile): the
caption's N frozen token embeddings (B, N, H), each through ``Linear(H -> h)``, either join the
sequence (``"sequence"``: ``[z_t; time; text; words]`` with a key-padding mask over missing tokens)
or are a cross-attention memory of every layer (``"cross_attention"``: memory ``[text; words]`` plus
a positional encoding, missing tokens masked; the pooled text token keeps the memory non-empty for
the null caption). Cross-attention costs less: the words are keys and values only, not queries
through the feed-forward. Why word tokens at all: MLD's pooled CLIP token is the causal
transformer's end-of-text state, which sees word order; our MiniLM substitute is a mean over tokens
and does not, so a denoiser that sees only the pooled vector can hardly tell order or side apart,
while the evaluator's word-level GRU can (measurements: docs/findings.md, "Word tokens for MLD's
text conditioning").

MotionLCM hooks: ``time_cond_dim`` adds the LCM guidance-scale embedding, ``Linear(time_cond_dim -> F,
bias=False)`` zero-initialised and added to the sinusoid before the MLP (so a student loaded from a
teacher with ``strict=False`` starts identical to it); ``residuals`` in :meth:`MLDDenoiser.forward` and
the hidden states of :meth:`MLDDenoiser.run` are the ControlNet hook of :class:`SkipTransformer`.

Training (MLD Eq. 3): ``L = E ||eps - eps_theta(z_t, t, c)||^2`` with ``z_t = sqrt(ab_t) z_0 +
sqrt(1 - ab_t) eps``, t ~ U{0..T-1} on the scaled_linear schedule (0.00085-0.012, T = 1000) and the
text dropped with probability 0.1 for classifier-free guidance.

Null condition: MLD replaces the caption by "" and encodes it; our text embeddings are precomputed
in the feature store, so the unconditional input is the denoiser's ``null_text`` buffer (E,), zeros
by default (a persistent buffer: set it to the encoder's embedding of "" to follow MLD exactly).

Sampling: DDIM (50 steps, eta 0, MLD's ``leading`` grid with ``steps_offset=1`` and
``set_alpha_to_one=False``) with CFG ``eps = eps_u + w (eps_c - eps_u)``, w = 7.5, from N(0, I), then
``vae.decode(latent_scale * z)``.

Latent scale: latent diffusion (LDM) trains on ``z / s`` with s ~ the std of the training latents
(Stable Diffusion's 0.18215 is 1 / s). MLD does *not* rescale (its VAE scale factor is 1.0, the KL
keeps latents near unit variance), so ``MLDConfig.latent_scale`` defaults to 1.0. Convention here:
``latent_scale`` is s, the std (:func:`latent_std`); :func:`mld_loss` expects ``z / s`` (the diffusion
space) and :func:`sample_mld` decodes ``s * z``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from models.diffusion import (
    NoiseSchedule,
    PredictionType,
    TimestepSpacing,
    classifier_free_guidance,
    condition_dropout,
    ddim_sample,
    sample_timesteps,
)
from models.rng import normal, rng_device
from models.transformer import (
    Activation,
    PositionalEncoding,
    PositionalEncodingKind,
    SkipOutput,
    SkipTransformer,
    eval_mode,
    timestep_embedding,
)
from models.vae import MotionVAE

TextActivation = Literal["relu", "none"]
WordTokens = Literal["none", "sequence", "cross_attention"]


@dataclass(frozen=True)
class MLDConfig:
    """Hyper-parameters of :class:`MLDDenoiser`; defaults are MLD's (with our 384-d MiniLM text).

    ``latent_tokens``/``latent_dim`` must match the VAE's; ``hidden_dim`` None = width ``latent_dim``
    with no latent projections. ``time_freq_dim`` is the sinusoid size F (MLD 768). ``time_cond_dim``
    is None for MLD and 256 for a MotionLCM student. ``latent_scale`` s: diffusion runs on ``z / s``
    (MLD: 1.0). ``word_tokens`` feeds the caption's word-token embeddings (H = ``token_dim``, None:
    ``text_dim``) to the denoiser: "none" (MLD), "sequence" or "cross_attention" (module docstring).
    """

    latent_tokens: int = 1
    latent_dim: int = 256
    hidden_dim: int | None = None
    text_dim: int = 384
    layers: int = 9
    heads: int = 4
    ff_dim: int = 1024
    dropout: float = 0.1
    activation: Activation = "gelu"
    norm_first: bool = False
    pos_encoding: PositionalEncodingKind = "sinusoidal"
    max_len: int = 512
    time_freq_dim: int = 768
    flip_sin_to_cos: bool = True
    freq_shift: float = 0.0
    text_activation: TextActivation = "relu"
    time_cond_dim: int | None = None
    prediction_type: PredictionType = "epsilon"
    latent_scale: float = 1.0
    word_tokens: WordTokens = "none"
    token_dim: int | None = None

    @property
    def width(self) -> int:
        """Transformer width h."""
        return self.latent_dim if self.hidden_dim is None else self.hidden_dim


class TimestepEmbedder(nn.Module):
    """``MLP(sinusoid(t) + cond_proj(w_emb))``: t (B,) [, w_emb (B, P)] -> (B, h) (diffusers ``TimestepEmbedding``).

    ``cond_proj`` exists only with ``cond_dim`` (MotionLCM's w-embedding) and starts at zero.
    """

    def __init__(
        self, freq_dim: int, dim: int, cond_dim: int | None = None, *, flip_sin_to_cos: bool = True,
        freq_shift: float = 0.0,
    ) -> None:
        super().__init__()
        self.freq_dim, self.flip_sin_to_cos, self.freq_shift = freq_dim, flip_sin_to_cos, freq_shift
        self.cond_proj = nn.Linear(cond_dim, freq_dim, bias=False) if cond_dim is not None else None
        if self.cond_proj is not None:
            nn.init.zeros_(self.cond_proj.weight)
        self.linear_1 = nn.Linear(freq_dim, dim)
        self.act = nn.SiLU()
        self.linear_2 = nn.Linear(dim, dim)

    def forward(self, t: Tensor, cond: Tensor | None = None) -> Tensor:
        emb = timestep_embedding(t, self.freq_dim, flip_sin_to_cos=self.flip_sin_to_cos, freq_shift=self.freq_shift)
        if cond is not None:
            if self.cond_proj is None:
                raise ValueError("time_cond given but the denoiser has no time_cond_dim")
            emb = emb + self.cond_proj(cond.to(emb.dtype))
        return self.linear_2(self.act(self.linear_1(emb.to(self.linear_1.weight.dtype))))


class MLDDenoiser(nn.Module):
    """MLD's latent denoiser ``eps_theta(z_t, t, c)``; see the module docstring.

    ``config`` is an :class:`MLDConfig` or its dict.
    """

    null_text: Tensor

    def __init__(self, config: MLDConfig | Mapping[str, Any] | None = None) -> None:
        super().__init__()
        cfg = config if isinstance(config, MLDConfig) else MLDConfig(**dict(config or {}))
        if cfg.text_activation not in ("relu", "none"):
            raise ValueError(f"unknown text_activation {cfg.text_activation!r}")
        if cfg.word_tokens not in ("none", "sequence", "cross_attention"):
            raise ValueError(f"unknown word_tokens {cfg.word_tokens!r}: none | sequence | cross_attention")
        self.config = cfg
        h = cfg.width
        self.latent_in: nn.Module = nn.Linear(cfg.latent_dim, h) if cfg.hidden_dim is not None else nn.Identity()
        self.latent_out: nn.Module = nn.Linear(h, cfg.latent_dim) if cfg.hidden_dim is not None else nn.Identity()
        self.time_embedding = TimestepEmbedder(
            cfg.time_freq_dim, h, cfg.time_cond_dim, flip_sin_to_cos=cfg.flip_sin_to_cos, freq_shift=cfg.freq_shift
        )
        self.text_proj = nn.Sequential(
            nn.ReLU() if cfg.text_activation == "relu" else nn.Identity(), nn.Linear(cfg.text_dim, h)
        )
        self.token_proj = nn.Linear(cfg.token_dim or cfg.text_dim, h) if cfg.word_tokens != "none" else None
        self.pos_encoding = PositionalEncoding(h, cfg.pos_encoding, cfg.max_len)
        self.transformer = SkipTransformer(
            h, cfg.layers, cfg.heads, cfg.ff_dim, cfg.dropout, cfg.activation, norm_first=cfg.norm_first,
            cross_attention=cfg.word_tokens == "cross_attention",
        )
        self.register_buffer("null_text", torch.zeros(cfg.text_dim))

    def null_text_like(self, text_emb: Tensor) -> Tensor:
        """The unconditional embedding broadcast to ``text_emb``'s shape (B, E), dtype and device."""
        return self.null_text.to(text_emb.device, text_emb.dtype).expand_as(text_emb)

    def run(
        self,
        z_t: Tensor,
        t: Tensor | int,
        text_emb: Tensor,
        *,
        text_tokens: Tensor | None = None,
        text_mask: Tensor | None = None,
        time_cond: Tensor | None = None,
        residuals: Sequence[Tensor | None] | None = None,
    ) -> SkipOutput:
        """Like :meth:`forward` but also returns the transformer's per-layer hidden states (B, S, h),
        S = L + 2 (+ N with ``word_tokens="sequence"``)."""
        b, n, _ = z_t.shape
        t = torch.as_tensor(t, device=z_t.device)
        t = t.expand(b) if t.ndim == 0 else t
        parts = [
            self.latent_in(z_t),
            self.time_embedding(t, time_cond)[:, None],
            self.text_proj(text_emb.to(z_t.dtype))[:, None],
        ]
        extra: dict[str, Tensor] = {}
        if self.token_proj is not None:
            if text_tokens is None or text_mask is None:
                raise ValueError(f"this denoiser has word_tokens={self.config.word_tokens!r}: pass text_tokens "
                                 "(B, N, H) and text_mask (B, N)")
            if text_mask.shape != text_tokens.shape[:2]:
                raise ValueError(f"text_mask {tuple(text_mask.shape)} does not match text_tokens "
                                 f"{tuple(text_tokens.shape)}")
            words, missing = self.token_proj(text_tokens.to(z_t.dtype)), ~text_mask.bool()
            if self.config.word_tokens == "sequence":
                parts.append(words)
                extra["key_padding_mask"] = torch.cat([missing.new_zeros(b, n + 2), missing], dim=1)
            else:
                extra["memory"] = self.pos_encoding(torch.cat([parts[-1], words], dim=1))
                extra["memory_key_padding_mask"] = torch.cat([missing.new_zeros(b, 1), missing], dim=1)
        tokens = self.pos_encoding(torch.cat(parts, dim=1))
        out, hidden = self.transformer.run(tokens, **extra, residuals=residuals)
        return SkipOutput(self.latent_out(out[:, :n]), hidden)

    def forward(
        self,
        z_t: Tensor,
        t: Tensor | int,
        text_emb: Tensor,
        *,
        text_tokens: Tensor | None = None,
        text_mask: Tensor | None = None,
        time_cond: Tensor | None = None,
        residuals: Sequence[Tensor | None] | None = None,
    ) -> Tensor:
        """Predict epsilon (``prediction_type``) from z_t (B, L, C), t (B,) int, text_emb (B, E) -> (B, L, C).

        ``text_tokens`` (B, N, H) and ``text_mask`` (B, N) bool (True = a real token): the word tokens,
        required unless ``word_tokens="none"`` and ignored then. ``time_cond`` (B, time_cond_dim):
        MotionLCM's guidance-scale embedding. ``residuals``: one (B, S, h) tensor or None per
        transformer layer (ControlNet).
        """
        return self.run(z_t, t, text_emb, text_tokens=text_tokens, text_mask=text_mask, time_cond=time_cond,
                        residuals=residuals).output


# --------------------------------------------------------------------------------------------------
# Condition dropout and training loss
# --------------------------------------------------------------------------------------------------


def drop_text(
    text_emb: Tensor,
    p: float,
    generator: torch.Generator | None = None,
    null: Tensor | None = None,
    text_mask: Tensor | None = None,
) -> tuple[Tensor, Tensor | None]:
    """Classifier-free-guidance condition dropout: each caption is replaced by the null one w.p. ``p``.

    text_emb (B, E): a dropped row becomes ``null`` ((E,) or (B, E); zeros by default, the default
    ``MLDDenoiser.null_text``). text_mask (B, N) bool, optional: a dropped row loses all its word tokens
    (the null caption has none). Returns ``(text_emb, text_mask)``; p = 0 returns the inputs unchanged,
    p = 1 all null. One uniform per row decides both.
    """
    null = torch.zeros_like(text_emb) if null is None else null.to(text_emb.device, text_emb.dtype).expand_as(text_emb)
    if p <= 0:
        return text_emb, text_mask
    drop = condition_dropout(text_emb.shape[0], p, generator, text_emb.device)[:, None]
    return torch.where(drop, null, text_emb), None if text_mask is None else text_mask & ~drop


def mld_loss(
    denoiser: MLDDenoiser,
    schedule: NoiseSchedule,
    z0: Tensor,
    text_emb: Tensor,
    p_uncond: float = 0.1,
    generator: torch.Generator | None = None,
    *,
    text_tokens: Tensor | None = None,
    text_mask: Tensor | None = None,
    time_cond: Tensor | None = None,
    net: nn.Module | None = None,
) -> dict[str, Tensor]:
    """MLD's diffusion loss on diffusion-space latents z0 (B, L, C) (i.e. ``z / latent_scale``).

    ``t ~ U{0..T-1}``, ``eps ~ N(0, I)``, ``z_t = q_sample(z0, t, eps)``, the caption (text_emb (B, E)
    and, for a ``word_tokens`` denoiser, its word tokens (B, N, H) with text_mask (B, N)) dropped to
    the null caption w.p. ``p_uncond``; ``mse = mean ||target - net(z_t, t, c)||^2`` with target = eps
    for epsilon prediction. All randomness comes from ``generator``. Returns ``{"mse", "total"}`` (equal).
    ``net`` is the module called for the prediction, ``denoiser`` by default; a multi-worker run passes
    the denoiser's DDP wrapper, so that gradients are synchronised (the null caption and the prediction
    type are always read from ``denoiser``).
    """
    net = denoiser if net is None else net
    t = sample_timesteps(z0.shape[0], schedule.num_steps, generator, z0.device)
    noise = normal(z0.shape, z0, generator)
    text, mask = drop_text(text_emb, p_uncond, generator, denoiser.null_text, text_mask)
    pred = net(schedule.q_sample(z0, t, noise), t, text, text_tokens=text_tokens, text_mask=mask,
                    time_cond=time_cond)
    target = schedule.prediction_target(z0, noise, t, denoiser.config.prediction_type)
    mse = F.mse_loss(pred, target)
    return {"mse": mse, "total": mse}


# --------------------------------------------------------------------------------------------------
# Latents and sampling
# --------------------------------------------------------------------------------------------------




def latent_std(latents: Tensor) -> float:
    """Std over all elements of a set of VAE latents (N, L, C): the LDM-style ``latent_scale`` s."""
    return float(latents.float().std())


@torch.no_grad()
def sample_mld(
    denoiser: MLDDenoiser,
    vae: MotionVAE,
    schedule: NoiseSchedule,
    text_emb: Tensor,
    lengths: Tensor | Sequence[int],
    num_steps: int = 50,
    guidance: float = 7.5,
    generator: torch.Generator | None = None,
    latent_scale: float | None = None,
    *,
    eta: float = 0.0,
    timestep_spacing: TimestepSpacing = "leading",
    timesteps: Sequence[int] | Tensor | None = None,
    x_T: Tensor | None = None,
    num_frames: int | None = None,
    text_tokens: Tensor | None = None,
    text_mask: Tensor | None = None,
) -> Tensor:
    """Text-to-motion with MLD: text_emb (B, E), lengths (B,) -> normalised features (B, T, D).

    A ``word_tokens`` denoiser also needs the word tokens (B, N, H) and text_mask (B, N); the
    unconditional pass gets the null embedding and no tokens.

    ``z_T ~ N(0, I)`` (B, L, C) from ``generator`` (or ``x_T``); DDIM (:func:`models.diffusion.ddim_sample`,
    ``num_steps`` on MLD's grid unless ``timesteps``/``timestep_spacing`` say otherwise, ``eta``) on the
    guided epsilon ``eps_u + guidance (eps_c - eps_u)`` (one batched call on ``[null; text]``; guidance 1
    skips the unconditional pass); then ``vae.decode_by_length(latent_scale * z_0, lengths)`` with
    ``T = num_frames`` or ``max(lengths)``, padded frames 0. ``latent_scale`` None uses the denoiser's
    config. Both networks run in eval mode under no_grad (their modes are restored).
    """
    cfg = denoiser.config
    scale = cfg.latent_scale if latent_scale is None else latent_scale
    device = text_emb.device
    shape = (text_emb.shape[0], cfg.latent_tokens, cfg.latent_dim)
    if x_T is None:
        x_T = torch.randn(shape, generator=generator, device=rng_device(generator, device)).to(device)

    def model_fn(x: Tensor, t: Tensor, text_emb: Tensor, **tokens: Tensor) -> Tensor:
        return denoiser(x, t, text_emb, **tokens)

    cond, uncond = {"text_emb": text_emb}, {"text_emb": denoiser.null_text_like(text_emb[:1])}
    if cfg.word_tokens != "none":
        if text_tokens is None or text_mask is None:
            raise ValueError(f"this denoiser has word_tokens={cfg.word_tokens!r}: pass text_tokens and text_mask")
        cond |= {"text_tokens": text_tokens, "text_mask": text_mask.bool()}
        uncond["text_mask"] = torch.zeros_like(text_mask[:1], dtype=torch.bool)
    guided = classifier_free_guidance(model_fn, guidance, uncond)
    with eval_mode(denoiser, vae):
        z0 = ddim_sample(
            guided, shape, schedule, num_steps, eta, generator, cfg.prediction_type,
            cond=cond, x_T=x_T, timestep_spacing=timestep_spacing, timesteps=timesteps,
        )
        return vae.decode_by_length(z0 * scale, lengths, num_frames)
