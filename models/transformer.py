"""MLD's skip-connected transformer and the embeddings shared by the MLD family (pure torch).

Reference: ``reference/motionlcm_mld.md`` sections 2-3 and 5 (``SkipTransformerEncoder/Decoder`` of
MLD's ``operator/cross_attention.py`` and MotionLCM's ``operator/attention.py``); DESIGN.md "Models".
Used by :mod:`models.vae` (encoder and decoder), :mod:`models.mld` (denoiser) and, later, by
MotionLCM's student and its ControlNet. Shapes are batch-first: B batch, S sequence positions,
d model width, M memory positions.

:class:`SkipTransformer` with ``N = 2K + 1`` layers is a U-Net over depth:

- K input blocks ``h_i = Layer_i(h_{i-1})`` whose outputs are stored;
- 1 middle block;
- K output blocks, each ``h = Layer(Linear_{2d->d}([h; h_skip]))`` where ``h_skip`` is the stored
  input-block output popped last-in-first-out (output block j meets input block K - 1 - j);
- a final LayerNorm (optional: MotionLCM's ControlNet copy has none).

Each layer is a DETR-style transformer layer (self-attention, optional cross-attention to a memory,
feed-forward ``Linear(d->ff) -> act -> Dropout -> Linear(ff->d)``), post-norm by default
(``normalize_before: false`` in MLD) or pre-norm. Positional information is added once to the
input sequence by the caller (MLD adds its PE to the tokens, not inside every layer).

ControlNet hook: ``residuals`` (one tensor or None per layer, in the order input blocks, middle,
output blocks) are added to the output of layer i over the whole token sequence, before that output
is stored as a skip or fed on (MotionLCM's ``controlnet_residuals``); :meth:`SkipTransformer.run`
also returns every layer's output (``hidden_states``), which a ControlNet copy projects through its
zero-initialised per-layer Linears to make those residuals.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import Literal, NamedTuple

import torch
from torch import Tensor, nn
from torch.nn import functional as F

Activation = Literal["gelu", "relu", "silu"]
PositionalEncodingKind = Literal["sinusoidal", "learned"]

_ACTIVATIONS: dict[str, type[nn.Module]] = {"gelu": nn.GELU, "relu": nn.ReLU, "silu": nn.SiLU}


# --------------------------------------------------------------------------------------------------
# Masks and embeddings
# --------------------------------------------------------------------------------------------------


@contextmanager
def eval_mode(*modules: nn.Module) -> Iterator[None]:
    """Switch modules to eval for the block and restore their previous train/eval flags."""
    flags = [m.training for m in modules]
    try:
        for m in modules:
            m.eval()
        yield
    finally:
        for m, flag in zip(modules, flags, strict=True):
            m.train(flag)


def lengths_to_mask(lengths: Tensor | Sequence[int], max_len: int | None = None) -> Tensor:
    """Validity mask (B, T) bool, True on frames ``t < lengths[b]``; ``T = max_len`` or ``max(lengths)``.

    The key-padding masks of :class:`SkipTransformer` are the negation (True = padding). Lengths outside
    [0, T] raise a ValueError when they are on the CPU; lengths on a GPU are not read back to be checked
    (a wait for the GPU's queue at every denoising step): check them before moving them.
    """
    lengths = torch.as_tensor(lengths).long()
    t = int(lengths.max()) if max_len is None else int(max_len)
    if lengths.device.type == "cpu" and lengths.numel() and (int(lengths.min()) < 0 or int(lengths.max()) > t):
        raise ValueError(f"lengths must lie in [0, {t}], got {lengths.tolist()}")
    return torch.arange(t, device=lengths.device)[None, :] < lengths[:, None]


def checked_lengths(lengths: Tensor | Sequence[int], num_frames: int | None = None) -> tuple[Tensor, int]:
    """``lengths`` (B,) as int64 where they are, and the frame count T (``num_frames`` or their maximum), once each
    lies in [1, T] (else a ValueError). A sampler checks its lengths with it once, before its steps: on a GPU
    :func:`lengths_to_mask` does not read them back."""
    lengths = torch.as_tensor(lengths).long()
    t = int(lengths.max()) if num_frames is None else int(num_frames)
    if lengths.numel() and (int(lengths.min()) < 1 or int(lengths.max()) > t):
        raise ValueError(f"lengths must lie in [1, {t}], got {lengths.tolist()}")
    return lengths, t


def sinusoidal_positions(num_positions: int, dim: int, *, device: torch.device | None = None) -> Tensor:
    """Transformer positional encoding (Vaswani et al. 2017, Sec. 3.5), (S, dim) float32.

    ``PE[p, 2i] = sin(p / 10000^(2i/dim))``, ``PE[p, 2i+1] = cos(p / 10000^(2i/dim))`` (odd ``dim``
    drops the last cosine).
    """
    pos = torch.arange(num_positions, dtype=torch.float32, device=device)[:, None]
    inv_freq = torch.exp(torch.arange(0, dim, 2, dtype=torch.float32, device=device) * (-math.log(10000.0) / dim))
    pe = torch.zeros(num_positions, dim, device=device)
    pe[:, 0::2] = torch.sin(pos * inv_freq)
    pe[:, 1::2] = torch.cos(pos * inv_freq)[:, : dim // 2]
    return pe


def timestep_embedding(
    t: Tensor, dim: int, *, flip_sin_to_cos: bool = True, freq_shift: float = 0.0, max_period: float = 10000.0
) -> Tensor:
    """Sinusoidal embedding of (possibly fractional) timesteps, (B,) -> (B, dim) float32.

    diffusers' ``Timesteps`` / DDPM's embedding: ``f_i = exp(-log(max_period) i / (half - freq_shift))``
    for ``i < half = dim // 2``; output ``[sin(t f), cos(t f)]``, or ``[cos, sin]`` with
    ``flip_sin_to_cos`` (MLD: ``Timesteps(768, flip_sin_to_cos=True, freq_shift=0)``); odd ``dim`` is
    zero-padded.
    """
    half = dim // 2
    exponent = -math.log(max_period) * torch.arange(half, dtype=torch.float32, device=t.device) / (half - freq_shift)
    args = t.float()[:, None] * torch.exp(exponent)[None, :]
    emb = torch.cat([torch.sin(args), torch.cos(args)], dim=-1)
    if flip_sin_to_cos:
        emb = torch.cat([emb[:, half:], emb[:, :half]], dim=-1)
    if dim % 2:
        emb = nn.functional.pad(emb, (0, 1))
    return emb


class PositionalEncoding(nn.Module):
    """Adds a positional encoding to a batch-first sequence: ``x + PE[:S]`` for x (B, S, d).

    ``kind="sinusoidal"`` (fixed, any length) or ``"learned"`` (MLD's ``PE_TYPE: mld``: a parameter
    (max_len, d) with uniform init, so at most ``max_len`` positions). :meth:`encoding` returns the
    (S, d) table itself, e.g. for the VAE decoder's per-frame queries.
    """

    def __init__(self, dim: int, kind: PositionalEncodingKind = "sinusoidal", max_len: int = 512) -> None:
        super().__init__()
        if kind not in ("sinusoidal", "learned"):
            raise ValueError(f"unknown positional encoding {kind!r}")
        self.dim, self.kind, self.max_len = dim, kind, max_len
        self.table = nn.Parameter(torch.rand(max_len, dim)) if kind == "learned" else None

    def encoding(self, num_positions: int, device: torch.device | None = None) -> Tensor:
        """The (S, d) encoding of positions 0..S-1."""
        if self.table is None:
            return sinusoidal_positions(num_positions, self.dim, device=device)
        if num_positions > self.max_len:
            raise ValueError(f"learned positional encoding holds {self.max_len} positions, got {num_positions}")
        return self.table[:num_positions]

    def forward(self, x: Tensor) -> Tensor:
        """x (B, S, d) -> x + PE (B, S, d)."""
        return x + self.encoding(x.shape[1], x.device).to(x.dtype)[None]


# --------------------------------------------------------------------------------------------------
# Transformer layer and the skip transformer
# --------------------------------------------------------------------------------------------------


def batch_first_attention(
    mha: nn.MultiheadAttention, query: Tensor, memory: Tensor, key_padding_mask: Tensor | None = None
) -> Tensor:
    """``mha(query, memory, memory, key_padding_mask=mask, need_weights=False)[0]``, computed batch-first.

    query (B, S, d), memory (B, M, d) (``memory is query`` for self-attention), mask (B, M) bool
    True = ignored -> (B, S, d). The same parameters and arithmetic as PyTorch's batch-first
    ``nn.MultiheadAttention`` (packed in-projection, a float mask with -inf on ignored keys,
    ``scaled_dot_product_attention`` with the module's dropout in training, out-projection), without
    its round trip through the sequence-first layout and the copies that forces, forward and backward
    (and in place of its inference fast path, which is slower here with a padding mask).
    """
    b, s, d = query.shape
    heads = mha.num_heads
    split = (heads, d // heads)
    weight, bias = mha.in_proj_weight, mha.in_proj_bias
    if memory is query:
        qkv = F.linear(query, weight, bias).unflatten(-1, (3, *split))  # (B, S, 3, heads, d/heads)
        q, k, v = qkv.permute(2, 0, 3, 1, 4).unbind(0)
    else:
        q = F.linear(query, weight[:d], None if bias is None else bias[:d]).unflatten(-1, split).transpose(1, 2)
        kv = F.linear(memory, weight[d:], None if bias is None else bias[d:]).unflatten(-1, (2, *split))
        k, v = kv.permute(2, 0, 3, 1, 4).unbind(0)
    mask = None
    if key_padding_mask is not None:
        mask = torch.zeros(b, 1, 1, memory.shape[1], dtype=q.dtype, device=q.device)
        mask.masked_fill_(key_padding_mask[:, None, None, :], float("-inf"))
    out = F.scaled_dot_product_attention(q, k, v, mask, mha.dropout if mha.training else 0.0)
    return mha.out_proj(out.transpose(1, 2).reshape(b, s, d))


class TransformerLayer(nn.Module):
    """One DETR-style layer: self-attention, optional cross-attention, feed-forward; post- or pre-norm.

    Post-norm (MLD): ``x = LN(x + Drop(SA(x)))``, ``x = LN(x + Drop(CA(x, mem)))``, ``x = LN(x + Drop(FF(x)))``.
    Pre-norm: ``x = x + Drop(SA(LN(x)))`` and likewise. ``FF = Linear(d->ff) -> act -> Drop -> Linear(ff->d)``.
    """

    def __init__(
        self,
        dim: int,
        heads: int,
        ff_dim: int,
        dropout: float = 0.1,
        activation: Activation = "gelu",
        *,
        norm_first: bool = False,
        cross_attention: bool = False,
    ) -> None:
        super().__init__()
        self.norm_first = norm_first
        self.self_attn = nn.MultiheadAttention(dim, heads, dropout=dropout, batch_first=True)
        self.cross_attn = (
            nn.MultiheadAttention(dim, heads, dropout=dropout, batch_first=True) if cross_attention else None
        )
        self.ff = nn.Sequential(
            nn.Linear(dim, ff_dim), _ACTIVATIONS[activation](), nn.Dropout(dropout), nn.Linear(ff_dim, dim)
        )
        self.norm_sa = nn.LayerNorm(dim)
        self.norm_ca = nn.LayerNorm(dim) if cross_attention else None
        self.norm_ff = nn.LayerNorm(dim)
        self.drop_sa, self.drop_ca, self.drop_ff = nn.Dropout(dropout), nn.Dropout(dropout), nn.Dropout(dropout)

    def _sa(self, x: Tensor, mask: Tensor | None) -> Tensor:
        return self.drop_sa(batch_first_attention(self.self_attn, x, x, mask))

    def _ca(self, x: Tensor, memory: Tensor, mask: Tensor | None) -> Tensor:
        assert self.cross_attn is not None
        return self.drop_ca(batch_first_attention(self.cross_attn, x, memory, mask))

    def forward(
        self,
        x: Tensor,
        key_padding_mask: Tensor | None = None,
        memory: Tensor | None = None,
        memory_key_padding_mask: Tensor | None = None,
    ) -> Tensor:
        """x (B, S, d), masks (B, S) / (B, M) bool True = ignored, memory (B, M, d) -> (B, S, d)."""
        if (memory is None) != (self.cross_attn is None):
            raise ValueError("memory must be given exactly when the layer has cross-attention")
        if self.norm_first:
            x = x + self._sa(self.norm_sa(x), key_padding_mask)
            if memory is not None:
                x = x + self._ca(self.norm_ca(x), memory, memory_key_padding_mask)  # type: ignore[misc]
            return x + self.drop_ff(self.ff(self.norm_ff(x)))
        x = self.norm_sa(x + self._sa(x, key_padding_mask))
        if memory is not None:
            x = self.norm_ca(x + self._ca(x, memory, memory_key_padding_mask))  # type: ignore[misc]
        return self.norm_ff(x + self.drop_ff(self.ff(x)))


class SkipOutput(NamedTuple):
    """Result of :meth:`SkipTransformer.run`: the final output (B, S, d) and each layer's output.

    ``hidden_states`` has one (B, S, d) tensor per layer (input blocks, middle, output blocks), taken
    after that layer's residual (if any) and before the final norm.
    """

    output: Tensor
    hidden_states: list[Tensor]


class SkipTransformer(nn.Module):
    """MLD's skip-connected transformer (encoder, or decoder with ``cross_attention=True``).

    ``num_layers = 2K + 1`` (odd, >= 1; MLD: 9): K input blocks, a middle block, K output blocks that
    concatenate the matching input-block output and project ``Linear(2d -> d)`` before their layer,
    then a final LayerNorm (``final_norm``). All weights with more than one dimension start
    Xavier-uniform (MLD's ``_reset_parameters``).
    """

    def __init__(
        self,
        dim: int,
        num_layers: int,
        heads: int,
        ff_dim: int,
        dropout: float = 0.1,
        activation: Activation = "gelu",
        *,
        norm_first: bool = False,
        cross_attention: bool = False,
        final_norm: bool = True,
    ) -> None:
        super().__init__()
        if num_layers < 1 or num_layers % 2 == 0:
            raise ValueError(f"num_layers must be odd and >= 1 (2K + 1), got {num_layers}")
        k = (num_layers - 1) // 2
        self.num_layers = num_layers

        def layer() -> TransformerLayer:
            return TransformerLayer(
                dim, heads, ff_dim, dropout, activation, norm_first=norm_first, cross_attention=cross_attention
            )

        self.input_blocks = nn.ModuleList(layer() for _ in range(k))
        self.middle_block = layer()
        self.output_blocks = nn.ModuleList(layer() for _ in range(k))
        self.skip_projections = nn.ModuleList(nn.Linear(2 * dim, dim) for _ in range(k))
        self.norm: nn.Module = nn.LayerNorm(dim) if final_norm else nn.Identity()
        for p in self.parameters():
            if p.dim() > 1:
                nn.init.xavier_uniform_(p)

    def run(
        self,
        x: Tensor,
        key_padding_mask: Tensor | None = None,
        memory: Tensor | None = None,
        memory_key_padding_mask: Tensor | None = None,
        residuals: Sequence[Tensor | None] | None = None,
    ) -> SkipOutput:
        """Run all layers; returns the output and the per-layer hidden states.

        Args:
            x: (B, S, d) input tokens (positional encoding already added).
            key_padding_mask: (B, S) bool, True = padding (never attended to as a key).
            memory: (B, M, d) cross-attention memory (decoders only).
            memory_key_padding_mask: (B, M) bool, True = padding.
            residuals: ``num_layers`` entries (each (B, S, d), broadcastable, or None), added to the output
                of layer i in the order input blocks, middle, output blocks (ControlNet hook).
        """
        if residuals is not None and len(residuals) != self.num_layers:
            raise ValueError(f"expected {self.num_layers} residuals, got {len(residuals)}")
        kwargs = {
            "key_padding_mask": key_padding_mask, "memory": memory, "memory_key_padding_mask": memory_key_padding_mask
        }
        hidden: list[Tensor] = []

        def add_residual(h: Tensor) -> Tensor:
            r = None if residuals is None else residuals[len(hidden)]
            h = h if r is None else h + r
            hidden.append(h)
            return h

        skips: list[Tensor] = []
        for block in self.input_blocks:
            x = add_residual(block(x, **kwargs))
            skips.append(x)
        x = add_residual(self.middle_block(x, **kwargs))
        for block, proj in zip(self.output_blocks, self.skip_projections, strict=True):
            x = add_residual(block(proj(torch.cat([x, skips.pop()], dim=-1)), **kwargs))
        return SkipOutput(self.norm(x), hidden)

    def forward(
        self,
        x: Tensor,
        key_padding_mask: Tensor | None = None,
        memory: Tensor | None = None,
        memory_key_padding_mask: Tensor | None = None,
        residuals: Sequence[Tensor | None] | None = None,
    ) -> Tensor:
        """(B, S, d) -> (B, S, d); see :meth:`run` for the arguments."""
        return self.run(x, key_padding_mask, memory, memory_key_padding_mask, residuals).output
