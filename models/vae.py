"""MLD's motion VAE: a skip-transformer encoder to L latent tokens and a frame-query decoder (pure torch).

Reference: ``reference/motionlcm_mld.md`` section 2 (``MldVae``); DESIGN.md "Models -> Motion VAE";
issue 5 item 2. Shapes: B batch, T frames (padded), D feature dims (263), L latent tokens, C latent
channels (``latent_dim``), h transformer width (``hidden_dim``, = C unless set).

Encoder (MLD Sec. 3.1): frames are embedded ``Linear(D -> h)``; 2L learned *distribution tokens* are
prepended, a positional encoding is added to ``[tokens; frames]`` and the skip transformer runs with a
key-padding mask over the padded frames (the tokens are never masked). The first L outputs are mu,
the next L log sigma^2 (through ``Linear(h -> C)`` when h != C, MotionLCM V2's ``force_pre_post_proj``;
plus the constant ``logvar_offset``, 0 in MLD, see :class:`MotionVAEConfig`).
``z = mu + sigma * eps`` (reparameterisation). MLD trains the VAE *and* encodes the diffusion
training set with sampled z, not mu.

Decoder (``decoder_arch``):

- ``"cross_attention"`` (default; MLD's ``encoder_decoder``): queries are zeros plus the positional
  encoding of each frame; a skip transformer *decoder* runs self-attention over the frames (key
  padding mask over padded frames) and cross-attention to the L latent tokens (``Linear(C -> h)`` when
  h != C), which get no positional encoding. Final LayerNorm (inside the transformer), ``Linear(h -> D)``.
- ``"self_attention"`` (MLD's ``all_encoder``): the L latent tokens and the T queries are concatenated,
  encoded with the positional encoding over all L + T positions, and the last T outputs are read.

Either way padded frames are set to 0 in the output, and valid frames never attend to padded ones,
so a valid frame's output depends only on z and its own length, not on the padding.

Losses (:func:`vae_loss`): ``L = w_f SmoothL1(x_hat, x) + w_j SmoothL1(FK(x_hat), FK(x)) + w_kl KL(q || N(0, I))``
with FK = ``recover_from_ric`` of the denormalised features (global joint positions, differentiable),
``w_kl = 1e-4``. The reconstruction terms are masked to valid frames as MotionLCM V2 does (mean over
channels, length-masked mean over frames per sequence, mean over the batch; MLD's original loss is
unmasked); the KL is the mean over all latent elements (MLD).

``joint_space`` chooses the joints the joint term compares: ``"global"`` (MLD) or ``"root"``, each
frame's joints minus its root joint (still in the global orientation, so a wrong facing is still an
error: the root-aligned positions MLD's MPJPE measures). Why ``"root"`` exists: the global positions
integrate the root velocity over the whole clip, so their error is dominated by trajectory drift that
the per-frame root-velocity features already supervise, and the gradient goes there instead of to
the pose (measurements: docs/findings.md, "The root-aligned joint loss"). What it cannot see: the
whole body's rise in a jump (HumanML3D stores every joint's height above the floor); the feature
term's root height still does.

``joint_beta`` is the SmoothL1 beta of the joint term, in metres (MLD: 1, as the feature term's). With
beta 1 the joint term is a squared error for every error a pose has, and its gradient fades as the
error shrinks; a beta of a few centimetres makes it an L1 error beyond that, which keeps pulling on a
body that faces the wrong way (docs/findings.md, 2026-12-02 (night)).

``heading_weight`` (ours; MLD has no such term: 0, the default, is MLD's loss) adds
``w_h L1(h(x_hat), h(x))`` with ``h_t = 2 sum_{k<t} x[k, 0]`` the body's heading angle in radians,
the integral of the root's angular velocity that ``recover_root_rot_pos`` turns into the heading
quaternion. The per-frame feature term sees a turn as a short run of angular velocities; a run
returned a little low ends the turn short, and every later frame faces the wrong way. The L1 on the
integral charges that miss on every later frame, at any size of error.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import torch
from torch import Tensor, nn
from torch.nn import functional as F

from data.features import feature_groups, recover_from_ric, root_angle
from models.rng import normal
from models.transformer import (
    Activation,
    PositionalEncoding,
    PositionalEncodingKind,
    SkipTransformer,
    checked_lengths,
    lengths_to_mask,
)

DecoderArch = Literal["cross_attention", "self_attention"]
JointSpace = Literal["global", "root"]


@dataclass(frozen=True)
class MotionVAEConfig:
    """Hyper-parameters of :class:`MotionVAE`; defaults are MLD's paper settings (HumanML3D).

    ``hidden_dim`` None means the transformer width equals ``latent_dim`` and no latent projections
    exist (MLD, MotionLCM V1: 1 x 256); MotionLCM V2 is ``latent_tokens=16, latent_dim=32,
    hidden_dim=256``. ``pos_encoding`` "sinusoidal" works for any length; "learned" is MLD's own
    (a (max_len, h) parameter, uniform init; MLD uses max_len 500).

    ``logvar_offset`` is a constant added to the encoder's log sigma^2 (MLD: 0). MLD reads log sigma^2
    straight off the encoder's final LayerNorm, so it starts near 0 (sigma ~ 1, as wide as the prior)
    and the reconstruction loss narrows it only slowly, so the decoder trains on latents that are
    mostly noise (docs/findings.md, "The VAE posterior offset"). A negative offset starts the
    posterior narrow (sigma = exp(offset / 2) at init); the KL term is unchanged and can widen it
    again. It is a reparameterisation, not a new parameter.
    """

    feature_dim: int = 263
    latent_tokens: int = 1
    latent_dim: int = 256
    hidden_dim: int | None = None
    layers: int = 9
    heads: int = 4
    ff_dim: int = 1024
    dropout: float = 0.1
    activation: Activation = "gelu"
    norm_first: bool = False
    pos_encoding: PositionalEncodingKind = "sinusoidal"
    max_len: int = 512
    decoder_arch: DecoderArch = "cross_attention"
    logvar_offset: float = 0.0

    @property
    def width(self) -> int:
        """Transformer width h."""
        return self.latent_dim if self.hidden_dim is None else self.hidden_dim


@dataclass(frozen=True)
class LatentDistribution:
    """Diagonal Gaussian posterior ``q(z | x) = N(mu, diag(exp(logvar)))``, mu/logvar (B, L, C)."""

    mu: Tensor
    logvar: Tensor

    @property
    def std(self) -> Tensor:
        """sigma = exp(logvar / 2), (B, L, C)."""
        return torch.exp(0.5 * self.logvar)

    def sample(self, generator: torch.Generator | None = None) -> Tensor:
        """Reparameterised sample ``z = mu + sigma * eps``, eps ~ N(0, I) (Kingma & Welling 2014, Eq. 10)."""
        eps = normal(self.mu.shape, self.mu, generator)
        return self.mu + self.std * eps

    def kl(self) -> Tensor:
        """Mean over all elements of KL(q || N(0, I)); see :func:`kl_to_standard_normal`."""
        return kl_to_standard_normal(self.mu, self.logvar)


def kl_to_standard_normal(mu: Tensor, logvar: Tensor) -> Tensor:
    """``mean(0.5 (mu^2 + sigma^2 - 1 - log sigma^2))`` over all elements (Kingma & Welling 2014, App. B).

    Element-wise KL of N(mu, sigma^2) to N(0, 1), averaged (MLD's ``KLLoss``); 0 exactly at mu = 0,
    logvar = 0.
    """
    return (0.5 * (mu.square() + logvar.exp() - 1.0 - logvar)).mean()


class MotionVAE(nn.Module):
    """MLD's motion VAE; see the module docstring. ``config`` is a :class:`MotionVAEConfig` or its dict."""

    def __init__(self, config: MotionVAEConfig | Mapping[str, Any] | None = None) -> None:
        super().__init__()
        cfg = config if isinstance(config, MotionVAEConfig) else MotionVAEConfig(**dict(config or {}))
        self.config = cfg
        h, c, n = cfg.width, cfg.latent_dim, cfg.latent_tokens
        common = {
            "dim": h, "num_layers": cfg.layers, "heads": cfg.heads, "ff_dim": cfg.ff_dim, "dropout": cfg.dropout,
            "activation": cfg.activation, "norm_first": cfg.norm_first,
        }
        # encoder
        self.skel_embedding = nn.Linear(cfg.feature_dim, h)
        self.dist_tokens = nn.Parameter(torch.randn(2 * n, h))
        self.encoder_pe = PositionalEncoding(h, cfg.pos_encoding, cfg.max_len)
        self.encoder = SkipTransformer(**common)
        self.latent_out: nn.Module = nn.Linear(h, c) if cfg.hidden_dim is not None else nn.Identity()
        # decoder
        self.latent_in: nn.Module = nn.Linear(c, h) if cfg.hidden_dim is not None else nn.Identity()
        self.decoder_pe = PositionalEncoding(h, cfg.pos_encoding, cfg.max_len)
        if cfg.decoder_arch not in ("cross_attention", "self_attention"):
            raise ValueError(f"unknown decoder_arch {cfg.decoder_arch!r}")
        self.decoder = SkipTransformer(**common, cross_attention=cfg.decoder_arch == "cross_attention")
        self.final_layer = nn.Linear(h, cfg.feature_dim)

    # ------------------------------------------------------------------------------------------ encoder
    def encode_distribution(self, features: Tensor, lengths: Tensor | Sequence[int]) -> LatentDistribution:
        """q(z | x): features (B, T, D) normalised, lengths (B,) -> mu, logvar (B, L, C).

        Padded frames (t >= lengths[b]) are masked out as attention keys, so they do not change the result.
        """
        b, t, _ = features.shape
        n = self.config.latent_tokens
        valid = lengths_to_mask(torch.as_tensor(lengths, device=features.device), t)
        x = torch.cat([self.dist_tokens[None].expand(b, -1, -1), self.skel_embedding(features)], dim=1)
        pad = torch.cat([valid.new_zeros(b, 2 * n), ~valid], dim=1)
        out = self.latent_out(self.encoder(self.encoder_pe(x), key_padding_mask=pad)[:, : 2 * n])
        return LatentDistribution(out[:, :n], out[:, n:] + self.config.logvar_offset)

    def encode(
        self,
        features: Tensor,
        lengths: Tensor | Sequence[int],
        generator: torch.Generator | None = None,
        *,
        sample: bool = True,
    ) -> tuple[Tensor, LatentDistribution]:
        """Encode and reparameterise: features (B, T, D), lengths (B,) -> (z (B, L, C), distribution).

        ``z = mu + sigma * eps`` with eps from ``generator`` (MLD samples both for VAE training and when
        encoding latents for diffusion); ``sample=False`` returns ``z = mu``.
        """
        dist = self.encode_distribution(features, lengths)
        return (dist.sample(generator) if sample else dist.mu), dist

    # ------------------------------------------------------------------------------------------ decoder
    def decode(self, z: Tensor, lengths: Tensor | Sequence[int], num_frames: int | None = None) -> Tensor:
        """p(x | z): z (B, L, C), lengths (B,) -> normalised features (B, T, D), padded frames exactly 0.

        ``T = num_frames`` or ``max(lengths)``. Queries are the positional encodings of the frames.
        """
        b = z.shape[0]
        lengths = torch.as_tensor(lengths, device=z.device)
        valid = lengths_to_mask(lengths, num_frames)
        t = valid.shape[1]
        memory = self.latent_in(z)
        queries = self.decoder_pe.encoding(t, z.device).to(memory.dtype)[None].expand(b, -1, -1)
        if self.config.decoder_arch == "cross_attention":
            out = self.decoder(queries, key_padding_mask=~valid, memory=memory)
        else:
            n = memory.shape[1]
            x = self.decoder_pe(torch.cat([memory, torch.zeros_like(queries)], dim=1))
            pad = torch.cat([valid.new_zeros(b, n), ~valid], dim=1)
            out = self.decoder(x, key_padding_mask=pad)[:, n:]
        return torch.where(valid[..., None], self.final_layer(out), 0.0)  # where, not *: no NaN can leak

    def decode_by_length(self, z: Tensor, lengths: Tensor | Sequence[int], num_frames: int | None = None,
                         chunk_size: int = 64) -> Tensor:
        """:meth:`decode` over chunks of ``chunk_size`` items of similar length, each cut to its longest.

        z (B, L, C), lengths (B,) -> (B, T, D) as :meth:`decode` (padded frames exactly 0). Valid frames
        only attend to valid frames, so the result equals one padded batch up to float rounding, while
        the quadratic self-attention runs on ~mean instead of max length (inference: evaluation and
        sampling of large batches).
        """
        lengths, t = checked_lengths(lengths, num_frames)
        lengths = lengths.to(z.device)
        out = z.new_zeros(z.shape[0], t, self.config.feature_dim)
        for idx, longest in length_sorted_chunks(lengths, chunk_size):
            out[idx, :longest] = self.decode(z[idx], lengths[idx], longest)
        return out

    def forward(
        self, features: Tensor, lengths: Tensor | Sequence[int], generator: torch.Generator | None = None
    ) -> tuple[Tensor, LatentDistribution]:
        """Reconstruct: features (B, T, D) -> (reconstruction (B, T, D), distribution), z sampled."""
        z, dist = self.encode(features, lengths, generator)
        return self.decode(z, lengths, features.shape[1]), dist


def length_sorted_chunks(lengths: Tensor, chunk_size: int) -> Iterator[tuple[Tensor, int]]:
    """(indices, longest length) of consecutive chunks of ``chunk_size`` items in length order."""
    for idx in torch.argsort(lengths, stable=True).split(chunk_size):
        yield idx, int(lengths[idx].max())


# --------------------------------------------------------------------------------------------------
# Losses
# --------------------------------------------------------------------------------------------------


def masked_smooth_l1(pred: Tensor, target: Tensor, valid: Tensor, beta: float = 1.0) -> Tensor:
    """Smooth-L1 averaged over channels, then over each sequence's valid frames, then over the batch.

    pred/target (B, T, ...), valid (B, T) bool. Per element ``0.5 x^2 / beta`` if ``|x| < beta`` else
    ``|x| - 0.5 beta`` (PyTorch ``SmoothL1Loss``, beta 1 as in MLD).
    """
    per = F.smooth_l1_loss(pred, target, reduction="none", beta=beta).flatten(2).mean(-1)
    w = valid.to(per.dtype)
    return (torch.where(valid, per, 0.0).sum(1) / w.sum(1).clamp(min=1.0)).mean()


def _stat(x: Tensor | np.ndarray | Sequence[float], like: Tensor) -> Tensor:
    return torch.as_tensor(np.asarray(x) if not isinstance(x, Tensor) else x).to(like.device, like.dtype)


def heading_angle(omega: Tensor) -> Tensor:
    """(..., T) root angular velocities (feature 0, denormalised) -> (..., T) heading angles in radians.

    ``h_t = 2 a_t`` with ``a_t`` of :func:`data.features.root_angle`, the angle ``recover_root_rot_pos``
    turns frame t by. Frame t depends on frames before it only, so padding after a motion's end never
    reaches it.
    """
    return 2.0 * root_angle(omega)


def reconstruction_losses(
    recon: Tensor,
    target: Tensor,
    lengths: Tensor | Sequence[int],
    mean: Tensor | np.ndarray,
    std: Tensor | np.ndarray,
    joints_num: int,
    joint_space: JointSpace = "global",
    joint_beta: float = 1.0,
) -> dict[str, Tensor]:
    """Feature, joint and heading reconstruction terms on normalised features (B, T, D), masked to valid frames.

    ``feature = SmoothL1(x_hat, x)``; ``joint = SmoothL1(J(x_hat), J(x))`` with
    ``J(x) = recover_from_ric(x * std + mean, joints_num)`` (B, T, J, 3), global positions in metres,
    minus each frame's root joint when ``joint_space="root"``; SmoothL1 beta 1 on the features and
    ``joint_beta`` (metres) on the joints; ``heading = L1(h(x_hat), h(x))`` on :func:`heading_angle`
    (radians) (see the module docstring).
    """
    if joint_space not in ("global", "root"):
        raise ValueError(f"joint_space must be 'global' or 'root', got {joint_space!r}")
    valid = lengths_to_mask(torch.as_tensor(lengths, device=recon.device), recon.shape[1])
    used = feature_groups(joints_num)["ric"].stop  # recover_from_ric reads the root and RIC groups only
    mean_t, std_t = _stat(mean, recon)[:used], _stat(std, recon)[:used]
    j_hat = recover_from_ric(recon[..., :used] * std_t + mean_t, joints_num)
    j = recover_from_ric(target[..., :used] * std_t + mean_t, joints_num)
    if joint_space == "root":
        j_hat, j = j_hat - j_hat[..., :1, :], j - j[..., :1, :]
    h_hat = heading_angle(recon[..., 0] * std_t[0] + mean_t[0]).unsqueeze(-1)
    h = heading_angle(target[..., 0] * std_t[0] + mean_t[0]).unsqueeze(-1)
    return {"feature": masked_smooth_l1(recon, target, valid), "joint": masked_smooth_l1(j_hat, j, valid, joint_beta),
            "heading": masked_smooth_l1(h_hat, h, valid, beta=0.0)}


def vae_loss(
    model: MotionVAE,
    features: Tensor,
    lengths: Tensor | Sequence[int],
    mean: Tensor | np.ndarray,
    std: Tensor | np.ndarray,
    joints_num: int,
    kl_weight: float = 1e-4,
    joint_weight: float = 1.0,
    feature_weight: float = 1.0,
    generator: torch.Generator | None = None,
    joint_space: JointSpace = "global",
    joint_beta: float = 1.0,
    heading_weight: float = 0.0,
) -> dict[str, Tensor]:
    """MLD's VAE objective on a batch of normalised features (B, T, D) with lengths (B,).

    Returns scalars ``feature``, ``joint``, ``heading``, ``kl`` (unweighted) and
    ``total = feature_weight * feature + joint_weight * joint + heading_weight * heading + kl_weight * kl``.
    ``mean``/``std`` (D,) are the dataset statistics the features were normalised with;
    ``joint_space`` and ``joint_beta`` are those of :func:`reconstruction_losses`.
    """
    recon, dist = model(features, lengths, generator)
    terms = reconstruction_losses(recon, features, lengths, mean, std, joints_num, joint_space, joint_beta)
    kl = dist.kl()
    total = (feature_weight * terms["feature"] + joint_weight * terms["joint"] + heading_weight * terms["heading"]
             + kl_weight * kl)
    return {**terms, "kl": kl, "total": total}
