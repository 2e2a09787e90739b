"""The T2M text-motion matching evaluator (Guo et al., CVPR 2022), pure torch.

Reference: ``reference/humanml3d_eval.md`` B.2 (networks), B.3 (training), C.1-C.2 (use in the
evaluation protocol); DESIGN.md "Models -> Evaluator". Shapes: B batch, L = max_words + 2 (22) text
positions, T frames, D feature dims (263 / 251) of which the last 4 are foot contacts, P = 15 POS
classes.

Networks (module and parameter names follow the reference's, so a state dict maps one to one):

- :class:`TextEncoderBiGRUCo`: ``x = E_word[w] + Linear_pos(pos)``, ``Linear(E->H)``, a BiGRU packed
  by ``sent_len``, ``[h_fwd; h_bwd]`` (2H) ``-> Linear(2H->H) -> LayerNorm -> LeakyReLU(0.2) ->
  Linear(H->out)``. Unlike the reference (which looks GloVe vectors up outside the network), the
  word embedding is a learned ``nn.Embedding``, optionally initialised from GloVe vectors
  (:func:`data.vocab.load_glove`) and optionally frozen.
- :class:`MovementConvEncoder`: two ``Conv1d(k=4, s=2, p=1) -> Dropout(0.2) -> LeakyReLU(0.2)``
  and a per-step Linear: (B, T, D-4) -> (B, T/4, C).
- :class:`MovementConvDecoder`: two ``ConvTranspose1d(k=4, s=2, p=1) -> LeakyReLU(0.2)`` and a
  per-step Linear: (B, T/4, C) -> (B, T, D), used only to pre-train the movement encoder.
- :class:`MotionEncoderBiGRUCo`: ``Linear(C->H_m)``, a BiGRU packed by ``lengths // 4``, the same
  head as the text encoder.

Every Linear / Conv1d / ConvTranspose1d starts Xavier-normal with zero bias; every GRU has a
learnable initial state of shape (2, 1, H). Losses: :func:`contrastive_loss` (matching,
reference B.3b) and :func:`movement_ae_loss` (movement autoencoder, reference B.3a).

:class:`T2MEvaluator` wraps the three encoders with the evaluator's own normalisation statistics
(buffers in its state dict) and the embedding calls used by training and by the metrics.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import nn
from torch.nn.utils.rnn import pack_padded_sequence

from data.vocab import NUM_POS
from models.rng import rng_device

#: Feature dims at the end of every frame that the movement encoder never sees (foot contacts).
CONTACT_DIMS = 4
#: Leading feature dims of the root group (yaw velocity, XZ velocity, height).
ROOT_DIMS = 4
#: Temporal downsampling of the movement encoder (two stride-2 convolutions).
UNIT_LENGTH = 4
#: The reference's ``feat_bias``: root and contact std are divided by it (once, here).
FEAT_BIAS = 5.0

TensorLike = torch.Tensor | np.ndarray


def _float_tensor(x: TensorLike, device: torch.device | None = None) -> torch.Tensor:
    """float32 tensor of ``x`` (numpy array, sequence or tensor on any device)."""
    if not isinstance(x, torch.Tensor):
        x = torch.as_tensor(np.asarray(x))
    return x.detach().to(device=device, dtype=torch.float32)


def init_weights(module: nn.Module) -> None:
    """Xavier-normal weights and zero biases for Linear / Conv1d / ConvTranspose1d (reference B.2)."""
    if isinstance(module, nn.Linear | nn.Conv1d | nn.ConvTranspose1d):
        nn.init.xavier_normal_(module.weight)
        if module.bias is not None:
            nn.init.zeros_(module.bias)


def _output_net(hidden_size: int, output_size: int) -> nn.Sequential:
    """``Linear(2H->H) -> LayerNorm(H) -> LeakyReLU(0.2) -> Linear(H->out)``."""
    return nn.Sequential(
        nn.Linear(2 * hidden_size, hidden_size),
        nn.LayerNorm(hidden_size),
        nn.LeakyReLU(0.2),
        nn.Linear(hidden_size, output_size),
    )


def _check_lengths(lengths: torch.Tensor, batch: int, max_len: int, name: str) -> torch.Tensor:
    """``lengths`` as a CPU int64 (B,) tensor with 1 <= l <= max_len (pack_padded_sequence needs CPU)."""
    lengths = torch.as_tensor(lengths).detach().to("cpu", torch.int64).reshape(-1)
    if lengths.numel() != batch:
        raise ValueError(f"{name} has {lengths.numel()} entries for a batch of {batch}")
    if batch and (int(lengths.min()) < 1 or int(lengths.max()) > max_len):
        raise ValueError(f"{name} must lie in [1, {max_len}], got min {int(lengths.min())} max {int(lengths.max())}")
    return lengths


def _bigru_last(gru: nn.GRU, hidden: nn.Parameter, x: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
    """Final forward and backward states of a packed BiGRU: (B, S, H_in) -> (B, 2H).

    Packs with ``enforce_sorted=False``; PyTorch returns ``h_n`` in the input order, so no manual
    sort/unsort is needed (the reference sorts the batch by length instead).
    """
    packed = pack_padded_sequence(x, lengths, batch_first=True, enforce_sorted=False)
    h0 = hidden.expand(-1, x.shape[0], -1).contiguous()
    _, h_n = gru(packed, h0)
    return torch.cat([h_n[0], h_n[1]], dim=-1)


class TextEncoderBiGRUCo(nn.Module):
    """Caption -> embedding (reference B.2 ``TextEncoderBiGRUCo``).

    ``e = Linear(LeakyReLU(LN(Linear([h_fwd; h_bwd]))))`` where ``h`` are the last states of a
    BiGRU over ``Linear(E_word[w_t] + Linear_pos(pos_t))``, t < sent_len.

    Args:
        vocab_size, word_size: the word embedding table (V, E).
        hidden_size: H, GRU width per direction.
        output_size: embedding width.
        word_vectors: optional (V, E) initial table (e.g. GloVe); ``None`` keeps PyTorch's N(0, 1).
        freeze_word_vectors: keep the table fixed (``requires_grad=False``).
        pos_size: number of POS classes (15).
    """

    def __init__(
        self,
        vocab_size: int,
        word_size: int,
        hidden_size: int,
        output_size: int,
        word_vectors: TensorLike | None = None,
        freeze_word_vectors: bool = False,
        pos_size: int = NUM_POS,
    ) -> None:
        super().__init__()
        self.word_emb = nn.Embedding(vocab_size, word_size)
        self.pos_emb = nn.Linear(pos_size, word_size)
        self.input_emb = nn.Linear(word_size, hidden_size)
        self.gru = nn.GRU(hidden_size, hidden_size, batch_first=True, bidirectional=True)
        self.output_net = _output_net(hidden_size, output_size)
        self.hidden = nn.Parameter(torch.randn(2, 1, hidden_size))
        self.apply(init_weights)
        if word_vectors is not None:
            table = _float_tensor(word_vectors)
            if tuple(table.shape) != (vocab_size, word_size):
                raise ValueError(f"word_vectors must have shape {(vocab_size, word_size)}, got {tuple(table.shape)}")
            with torch.no_grad():
                self.word_emb.weight.copy_(table)
        self.word_emb.weight.requires_grad_(not freeze_word_vectors)

    def forward(self, word_ids: torch.Tensor, pos_onehot: torch.Tensor, sent_lens: torch.Tensor) -> torch.Tensor:
        """(B, L) int64, (B, L, P) float, (B,) int -> (B, output_size). Positions >= sent_len are ignored."""
        if word_ids.ndim != 2 or pos_onehot.shape[:2] != word_ids.shape:
            raise ValueError(f"word_ids (B, L) and pos_onehot (B, L, P) disagree: {word_ids.shape}, {pos_onehot.shape}")
        lengths = _check_lengths(sent_lens, word_ids.shape[0], word_ids.shape[1], "sent_lens")
        x = self.word_emb(word_ids) + self.pos_emb(pos_onehot.to(self.pos_emb.weight.dtype))
        x = self.input_emb(x)
        return self.output_net(_bigru_last(self.gru, self.hidden, x, lengths))


class MovementConvEncoder(nn.Module):
    """Normalised features without contacts -> movement latents, time / 4 (reference B.2).

    ``z = Linear(LReLU(Drop(Conv(LReLU(Drop(Conv(x)))))))``, each Conv1d k=4, s=2, p=1. For even T
    each conv halves time exactly; latent step j sees input frames ``4j-3 .. 4j+6`` (zero outside
    [0, T)), so the last latent of a length-L motion also sees frames L..L+2 when they exist.

    Args:
        input_size: D - 4 (259 / 247). hidden_size, output_size: conv widths (512 / 512).
    """

    def __init__(self, input_size: int, hidden_size: int, output_size: int, dropout: float = 0.2) -> None:
        super().__init__()
        self.main = nn.Sequential(
            nn.Conv1d(input_size, hidden_size, 4, 2, 1),
            nn.Dropout(dropout),
            nn.LeakyReLU(0.2),
            nn.Conv1d(hidden_size, output_size, 4, 2, 1),
            nn.Dropout(dropout),
            nn.LeakyReLU(0.2),
        )
        self.out_net = nn.Linear(output_size, output_size)
        self.apply(init_weights)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, T, input_size) -> (B, T // 4, output_size) for T a multiple of 4."""
        return self.out_net(self.main(x.transpose(1, 2)).transpose(1, 2))


class MovementConvDecoder(nn.Module):
    """Movement latents -> full features, time x 4 (reference B.3a decoder).

    ``x = Linear(LReLU(ConvT(LReLU(ConvT(z)))))``, each ConvTranspose1d k=4, s=2, p=1 (doubles time).

    Args:
        input_size: latent width C. hidden_size: first deconv width. output_size: D (263, contacts included).
    """

    def __init__(self, input_size: int, hidden_size: int, output_size: int) -> None:
        super().__init__()
        self.main = nn.Sequential(
            nn.ConvTranspose1d(input_size, hidden_size, 4, 2, 1),
            nn.LeakyReLU(0.2),
            nn.ConvTranspose1d(hidden_size, output_size, 4, 2, 1),
            nn.LeakyReLU(0.2),
        )
        self.out_net = nn.Linear(output_size, output_size)
        self.apply(init_weights)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        """(B, S, input_size) -> (B, 4S, output_size)."""
        return self.out_net(self.main(z.transpose(1, 2)).transpose(1, 2))


class MotionEncoderBiGRUCo(nn.Module):
    """Movement latents -> motion embedding (reference B.2 ``MotionEncoderBiGRUCo``).

    ``e = Linear(LeakyReLU(LN(Linear([h_fwd; h_bwd]))))`` over a BiGRU of ``Linear(z_s)``,
    s < m_len (= frames // 4).

    Args:
        input_size: C (512). hidden_size: H_m (1024). output_size: embedding width (512).
    """

    def __init__(self, input_size: int, hidden_size: int, output_size: int) -> None:
        super().__init__()
        self.input_emb = nn.Linear(input_size, hidden_size)
        self.gru = nn.GRU(hidden_size, hidden_size, batch_first=True, bidirectional=True)
        self.output_net = _output_net(hidden_size, output_size)
        self.hidden = nn.Parameter(torch.randn(2, 1, hidden_size))
        self.apply(init_weights)

    def forward(self, latents: torch.Tensor, m_lens: torch.Tensor) -> torch.Tensor:
        """(B, S, C), (B,) int with 1 <= m_len <= S -> (B, output_size). Steps >= m_len are ignored."""
        lengths = _check_lengths(m_lens, latents.shape[0], latents.shape[1], "m_lens")
        return self.output_net(_bigru_last(self.gru, self.hidden, self.input_emb(latents), lengths))


# ---------------------------------------------------------------------------------------------
# Losses


class ContrastiveTerms(NamedTuple):
    """The two halves of :func:`contrastive_loss` (scalars) and the shift used."""

    positive: torch.Tensor
    negative: torch.Tensor
    shift: int


def contrastive_terms(
    text_emb: torch.Tensor,
    motion_emb: torch.Tensor,
    margin: float = 10.0,
    shift: int | None = None,
    generator: torch.Generator | None = None,
) -> ContrastiveTerms:
    """Positive and negative terms of :func:`contrastive_loss` (see there)."""
    if text_emb.ndim != 2 or text_emb.shape != motion_emb.shape:
        raise ValueError(f"text_emb and motion_emb must both be (B, E), got {text_emb.shape}, {motion_emb.shape}")
    batch = text_emb.shape[0]
    if batch < 2:
        raise ValueError(f"contrastive_loss needs a batch of at least 2 for negatives, got {batch}")
    if shift is None:
        shift = int(torch.randint(1, batch, (1,), generator=generator, device=rng_device(generator, "cpu")))
    elif int(shift) != shift or not 1 <= shift <= batch - 1:
        raise ValueError(f"shift must be an integer in [1, {batch - 1}], got {shift!r}")
    shift = int(shift)
    positive = (text_emb - motion_emb).pow(2).sum(-1).mean()
    mismatched = torch.roll(motion_emb, shifts=-shift, dims=0)  # row i -> motion (i + shift) % B
    d_neg = torch.sqrt((text_emb - mismatched).pow(2).sum(-1) + 1e-12)
    negative = torch.clamp(margin - d_neg, min=0.0).pow(2).mean()
    return ContrastiveTerms(positive, negative, shift)


def contrastive_loss(
    text_emb: torch.Tensor,
    motion_emb: torch.Tensor,
    margin: float = 10.0,
    shift: int | None = None,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Matching loss with batch-shifted negatives (reference B.3b).

    ``L = mean_i d(t_i, m_i)^2 + mean_i max(0, margin - d(t_i, m_{(i+s) mod B}))^2``, d Euclidean.

    The reference draws ``s`` from ``[0, B-2]``, so ``s = 0`` sometimes turns the "negatives" into the
    positives themselves (and ``s = B-1`` is never drawn). Here ``s`` is drawn uniformly from
    ``[1, B-1]`` with ``generator``, so every negative pair is a real mismatch; an explicit ``shift``
    must lie in that range too. The negative distance is ``sqrt(|.|^2 + 1e-12)`` to keep the gradient
    finite at coincident points (the reference's ``pairwise_distance`` adds 1e-6 to the difference).

    Args:
        text_emb, motion_emb: (B, E), row i of each a matched pair, B >= 2.
        margin: the negative margin (10; the reference's option overrides its class default 3).
        shift: fixed shift, or ``None`` to draw one.

    Returns:
        scalar loss.
    """
    terms = contrastive_terms(text_emb, motion_emb, margin, shift, generator)
    return terms.positive + terms.negative


def movement_ae_loss(
    recon: torch.Tensor,
    target: torch.Tensor,
    z: torch.Tensor,
    sparsity: float = 0.001,
    smoothness: float = 0.001,
) -> torch.Tensor:
    """Movement autoencoder loss (reference B.3a).

    ``L = mean|recon - target| + sparsity * mean|z| + smoothness * mean|z[:, 1:] - z[:, :-1]|``:
    L1 reconstruction of the full features (contacts included), latent sparsity, and latent
    smoothness along time (dim 1).

    Args:
        recon, target: (B, T, D). z: (B, T/4, C) movement latents.
    """
    if recon.shape != target.shape:
        raise ValueError(f"recon {tuple(recon.shape)} and target {tuple(target.shape)} differ")
    if z.ndim != 3:
        raise ValueError(f"z must be (B, S, C), got {tuple(z.shape)}")
    loss = (recon - target).abs().mean() + sparsity * z.abs().mean()
    if z.shape[1] > 1:
        loss = loss + smoothness * (z[:, 1:] - z[:, :-1]).abs().mean()
    return loss


# ---------------------------------------------------------------------------------------------
# Wrapper


@dataclass(frozen=True)
class EvaluatorConfig:
    """Sizes of the evaluator. Defaults are the paper's (reference B.2) for HumanML3D.

    Attributes:
        vocab_size: V, rows of the word table (``len(WordVocab)``).
        feature_dim: D, contacts included (263 HumanML3D, 251 KIT-ML).
        word_dim: E (300, GloVe's width). text_hidden: H (512).
        movement_hidden, movement_dim: conv widths of the movement encoder, C = movement_dim (512, 512).
        motion_hidden: H_m (1024). output_dim: embedding width (512).
        dropout: movement-encoder dropout (0.2).
        freeze_word_vectors: keep the word table fixed (sensible only when initialised from GloVe).
    """

    vocab_size: int
    feature_dim: int = 263
    word_dim: int = 300
    text_hidden: int = 512
    movement_hidden: int = 512
    movement_dim: int = 512
    motion_hidden: int = 1024
    output_dim: int = 512
    dropout: float = 0.2
    freeze_word_vectors: bool = False

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if f.type in ("int", int) and (not isinstance(value, int) or value < 1):
                raise ValueError(f"EvaluatorConfig.{f.name} must be a positive integer, got {value!r}")
        if self.feature_dim <= CONTACT_DIMS + ROOT_DIMS:
            raise ValueError(f"feature_dim must exceed {CONTACT_DIMS + ROOT_DIMS}, got {self.feature_dim}")
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"dropout must lie in [0, 1), got {self.dropout}")

    @classmethod
    def for_profile(cls, profile: str, vocab_size: int, feature_dim: int = 263, **overrides: Any) -> EvaluatorConfig:
        """Sizes for a scale profile: ``paper`` (reference), ``tiny`` (default laptop run), ``smoke`` (tests)."""
        if profile not in PROFILE_SIZES:
            raise ValueError(f"unknown profile {profile!r}; expected one of {sorted(PROFILE_SIZES)}")
        return cls(vocab_size=vocab_size, feature_dim=feature_dim, **{**PROFILE_SIZES[profile], **overrides})

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> EvaluatorConfig:
        names = {f.name for f in fields(cls)}
        unknown = set(data) - names
        if unknown:
            raise ValueError(f"unknown EvaluatorConfig keys: {sorted(unknown)}")
        return cls(**data)

    def replace(self, **changes: Any) -> EvaluatorConfig:
        return replace(self, **changes)


#: Network sizes per scale profile (``vocab_size`` and ``feature_dim`` come from the data).
PROFILE_SIZES: dict[str, dict[str, int]] = {
    "paper": dict(word_dim=300, text_hidden=512, movement_hidden=512, movement_dim=512, motion_hidden=1024,
                  output_dim=512),
    "tiny": dict(word_dim=128, text_hidden=128, movement_hidden=128, movement_dim=128, motion_hidden=256,
                 output_dim=128),
    "smoke": dict(word_dim=32, text_hidden=32, movement_hidden=32, movement_dim=32, motion_hidden=32,
                  output_dim=32),
}


class T2MEvaluator(nn.Module):
    """Text encoder + movement encoder + motion encoder + normalisation statistics.

    Normalisation: the evaluator sees ``x = (raw - mean) / std`` with its own ``mean``/``std``
    buffers (saved in the state dict), set once from the training statistics by
    :meth:`set_normalization`. The reference's dataset divides the root [0:4] and contact std by
    ``feat_bias = 5`` in place on an array shared by its train and val sets, so its shipped
    ``t2m_std`` ended up divided by ~25 (reference A.6). We do **not** reproduce that double
    division: ``feat_bias`` is applied exactly once, to the root [0:4] and contact [D-4:D] groups, as
    the evaluator's options describe. (Contacts never reach the movement encoder but are part of the
    autoencoder's reconstruction target.)

    Embedding calls (reference B.2 wrapper): :meth:`embed_text` and :meth:`embed_motion`; training
    uses :meth:`forward` (both at once, so DDP sees one forward), :meth:`autoencode` and
    :func:`contrastive_loss` / :func:`movement_ae_loss`.

    Args:
        config: sizes. word_vectors: optional (V, E) initial word table (GloVe).
    """

    def __init__(self, config: EvaluatorConfig, word_vectors: TensorLike | None = None) -> None:
        super().__init__()
        self.config = config
        d = config.feature_dim
        self.text_encoder = TextEncoderBiGRUCo(
            config.vocab_size, config.word_dim, config.text_hidden, config.output_dim,
            word_vectors=word_vectors, freeze_word_vectors=config.freeze_word_vectors,
        )
        self.movement_encoder = MovementConvEncoder(
            d - CONTACT_DIMS, config.movement_hidden, config.movement_dim, dropout=config.dropout
        )
        self.motion_encoder = MotionEncoderBiGRUCo(config.movement_dim, config.motion_hidden, config.output_dim)
        self.register_buffer("mean", torch.zeros(d))
        self.register_buffer("std", torch.ones(d))
        self._movement_frozen = False

    # -- normalisation ----------------------------------------------------------------------

    def set_normalization(self, mean: TensorLike, std: TensorLike, feat_bias: float = FEAT_BIAS) -> None:
        """Store ``mean`` and ``std`` (D,) of the raw training features; ``std`` of the root [0:4] and
        contact [D-4:D] dims is divided by ``feat_bias`` (once). Zero std entries raise ValueError."""
        d = self.config.feature_dim
        mean_t = _float_tensor(mean).reshape(-1)
        std_t = _float_tensor(std).reshape(-1).clone()
        if mean_t.numel() != d or std_t.numel() != d:
            raise ValueError(f"mean/std must have {d} entries, got {mean_t.numel()}/{std_t.numel()}")
        if not (torch.isfinite(mean_t).all() and torch.isfinite(std_t).all() and (std_t > 0).all()):
            raise ValueError("mean must be finite and std finite and positive")
        if feat_bias <= 0:
            raise ValueError(f"feat_bias must be positive, got {feat_bias}")
        std_t[:ROOT_DIMS] /= feat_bias
        std_t[d - CONTACT_DIMS:] /= feat_bias
        with torch.no_grad():
            self.mean.copy_(mean_t)
            self.std.copy_(std_t)

    def normalize(self, features: torch.Tensor) -> torch.Tensor:
        """Raw features (..., D) -> evaluator-normalised features."""
        return (features - self.mean) / self.std

    def denormalize(self, features_norm: torch.Tensor) -> torch.Tensor:
        """Inverse of :meth:`normalize`."""
        return features_norm * self.std + self.mean

    def renormalize(self, features: torch.Tensor, mean: TensorLike, std: TensorLike) -> torch.Tensor:
        """Features normalised with another ``mean``/``std`` (a generator's) -> evaluator-normalised
        (reference C.2: ``x_eval = (x * Std + Mean - eval_mean) / eval_std``)."""
        mean_t = _float_tensor(mean, features.device)
        std_t = _float_tensor(std, features.device)
        return self.normalize(features * std_t + mean_t)

    # -- movement encoder -------------------------------------------------------------------

    def freeze_movement_encoder(self, frozen: bool = True) -> None:
        """Freeze the pre-trained movement encoder for matching training (reference B.3b): no
        gradients, eval mode (no dropout) even inside ``train()``, and :meth:`embed_motion` runs it
        without autograd."""
        self._movement_frozen = bool(frozen)
        self.movement_encoder.requires_grad_(not frozen)
        self.train(self.training)

    @property
    def movement_frozen(self) -> bool:
        return self._movement_frozen

    def train(self, mode: bool = True) -> T2MEvaluator:
        super().train(mode)
        if self._movement_frozen:
            self.movement_encoder.eval()
        return self

    def make_movement_decoder(self) -> MovementConvDecoder:
        """A fresh decoder matching this evaluator's movement encoder (latent C -> D features)."""
        c = self.config
        return MovementConvDecoder(c.movement_dim, c.movement_hidden, c.feature_dim).to(self.mean.device)

    def autoencode(
        self, features_norm: torch.Tensor, decoder: MovementConvDecoder
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Movement-autoencoder pass (reference B.3a) on full windows (no length masking).

        Args:
            features_norm: (B, T, D) evaluator-normalised, T a multiple of 4.

        Returns:
            ``recon`` (B, T, D) and latents ``z`` (B, T/4, C); train with
            ``movement_ae_loss(recon, features_norm, z)``.
        """
        x = self._check_features(features_norm)
        if x.shape[1] % UNIT_LENGTH:
            raise ValueError(f"autoencoder windows need T a multiple of {UNIT_LENGTH}, got {x.shape[1]}")
        z = self.movement_encoder(x[..., : self.config.feature_dim - CONTACT_DIMS])
        return decoder(z), z

    # -- embeddings -------------------------------------------------------------------------

    def _check_features(self, features_norm: TensorLike) -> torch.Tensor:
        x = torch.as_tensor(features_norm, dtype=torch.float32, device=self.mean.device)
        if x.ndim != 3 or x.shape[-1] != self.config.feature_dim:
            raise ValueError(f"features must be (B, T, {self.config.feature_dim}), got {tuple(x.shape)}")
        return x

    def embed_text(self, word_ids: TensorLike, pos_onehot: TensorLike, sent_lens: TensorLike) -> torch.Tensor:
        """Caption embeddings (reference B.2 text path).

        Args:
            word_ids: (B, L) int64 from :meth:`data.vocab.WordVocab.encode_batch`.
            pos_onehot: (B, L, 15). sent_lens: (B,) with 1 <= sent_len <= L; positions >= sent_len
                (the unk/OTHER padding) do not affect the result.

        Returns:
            (B, output_dim).
        """
        device = self.mean.device
        word_ids = torch.as_tensor(word_ids, dtype=torch.int64, device=device)
        pos_onehot = torch.as_tensor(pos_onehot, dtype=torch.float32, device=device)
        return self.text_encoder(word_ids, pos_onehot, torch.as_tensor(sent_lens))

    def embed_motion(self, features_norm: TensorLike, lengths: TensorLike) -> torch.Tensor:
        """Motion embeddings (reference B.2 motion path).

        1. Drop the last 4 (contact) dims: (B, T, D) -> (B, T, D-4).
        2. Zero every frame ``t >= lengths[b]``, then zero-pad time to a multiple of 4. The reference
           zero-pads its (normalised) motions to 196 frames; zeroing here makes that hold whatever
           the caller put beyond the length (e.g. a generator's frames past L', which the
           reference's MDM-style loader feeds in unzeroed), so the embedding depends only on the
           first ``lengths[b]`` frames.
        3. Movement encoder -> (B, T/4, C); BiGRU packed by ``lengths // 4`` -> (B, output_dim).

        As in the reference the padding still leaks into the last GRU step: latent step j covers
        frames 4j-3 .. 4j+6, so the last one used (j = L//4 - 1) covers frames 4*(L//4) .. 4*(L//4)+2
        past the packed span: zeros from L on, real frames below L when L is not a multiple of 4.
        A motion that fills the padded window exactly (4*(L//4) = padded T, e.g. a 196-frame crop in
        the reference's 196-frame batches) sees the second conv's own zero padding there instead, so
        its embedding differs slightly from the same motion padded further; every shorter motion's
        embedding does not depend on how far the batch is padded.

        Args:
            features_norm: (B, T, D) evaluator-normalised (see :meth:`normalize` / :meth:`renormalize`).
            lengths: (B,) frames, 4 <= length <= T.

        Returns:
            (B, output_dim).
        """
        x = self._check_features(features_norm)
        batch, frames = x.shape[:2]
        lengths_cpu = _check_lengths(lengths, batch, frames, "lengths")
        if batch and int(lengths_cpu.min()) < UNIT_LENGTH:
            raise ValueError(f"motion lengths must be >= {UNIT_LENGTH}, got {int(lengths_cpu.min())}")
        x = x[..., : self.config.feature_dim - CONTACT_DIMS]
        valid = torch.arange(frames, device=x.device)[None, :] < lengths_cpu.to(x.device)[:, None]
        x = torch.where(valid[..., None], x, torch.zeros((), dtype=x.dtype, device=x.device))
        pad = (-frames) % UNIT_LENGTH
        if pad:
            x = torch.nn.functional.pad(x, (0, 0, 0, pad))
        if self._movement_frozen:
            with torch.no_grad():
                latents = self.movement_encoder(x)
        else:
            latents = self.movement_encoder(x)
        return self.motion_encoder(latents, torch.div(lengths_cpu, UNIT_LENGTH, rounding_mode="floor"))

    def forward(
        self,
        word_ids: TensorLike,
        pos_onehot: TensorLike,
        sent_lens: TensorLike,
        features_norm: TensorLike,
        lengths: TensorLike,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``(embed_text(...), embed_motion(...))``, both (B, output_dim), row i a caption/motion pair."""
        return self.embed_text(word_ids, pos_onehot, sent_lens), self.embed_motion(features_norm, lengths)


class MovementAutoencoder(nn.Module):
    """The evaluator's movement encoder with a decoder, for pretraining (DDP needs one forward)."""

    def __init__(self, evaluator: T2MEvaluator) -> None:
        super().__init__()
        self.evaluator = evaluator
        self.decoder = evaluator.make_movement_decoder()

    def forward(self, window: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(B, W, D) raw -> (reconstruction, normalised target, latents), (B, W, D), (B, W, D), (B, W/4, C)."""
        x = self.evaluator.normalize(window)
        recon, z = self.evaluator.autoencode(x, self.decoder)
        return recon, x, z
