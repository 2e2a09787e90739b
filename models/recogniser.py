"""The action recogniser of the action-to-motion protocol (HumanAct12-style), pure torch.

As the GRU classifier HumanAct12's metrics are measured with (Action2Motion's
``MotionDiscriminator``, used by MDM/EMDM's ``eval/a2m``): a GRU over per-frame joint positions
whose output goes through ``Linear(. -> E) -> tanh``, the *embedding* (the penultimate features
every FID / Diversity / MultiModality of the protocol is computed on), then ``Linear(E -> C)``
class logits. Per frame:

1. the input is the dataset's normalised HumanML3D features ``x``; the recogniser's own
   ``mean``/``std`` buffers (the training statistics, saved in its state dict) turn them back
   into raw features;
2. :func:`data.features.recover_from_ric` integrates them into (T, J, 3) joint positions in
   metres. **Invariance**: the recovery starts every sequence at the origin of the floor (root
   XZ = 0) facing +Z at its first frame, so the joints depend only on the motion relative to its
   own start position and heading, never on where or which way it started (the root's height
   above the floor is kept: sitting and crouching need it). A crop of a motion is recovered
   from its own first frame the same way;
3. the GRU input (:meth:`ActionRecogniser.frames`, 6J + 1 values): the pose (joints minus the
   root's XZ, 3J), every joint's velocity (3J) and the root's horizontal speed (1), in metres
   and m/s. Velocities make cadence and speed (walk / jog / run, waving) directly visible: the
   positions-only GRU of HumanAct12 learned far more slowly here;
4. every ``frame_stride``-th frame (10 fps by default), ``Linear(6J + 1 -> H) -> LayerNorm ->
   LeakyReLU(0.2)``, a ``layers``-layer GRU of width H packed by ``lengths`` (frames past a
   motion's length never reach it); the readout concatenates the last valid hidden state (as
   HumanAct12's) with the mean and the max of the top layer's outputs over the valid frames
   (3H -> E): the mean trains faster than the last state alone, the max told jog from run better.

Shapes: B batch, T frames, D = 12J - 1 feature dims, E embedding width, C classes.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.nn.utils.rnn import pack_padded_sequence, pad_packed_sequence

from data.features import recover_from_ric

TensorLike = torch.Tensor | np.ndarray
#: Frame rate of the features (HumanML3D: 20 fps); scales the root velocity input to m/s.
FPS = 20.0


@dataclass(frozen=True)
class RecogniserConfig:
    """Classes and sizes of the recogniser.

    Attributes:
        classes: action labels in class-index order (the sorted labels of the training split).
        feature_dim: D = 12J - 1 of the features (263 for HumanML3D's 22 joints).
        hidden: GRU (and input projection) width H (HumanAct12's: 128).
        layers: GRU layers (HumanAct12's: 2).
        embed_dim: E, width of the tanh embedding (HumanAct12's: 30).
        dropout: between GRU layers (0 for our size).
        frame_stride: the GRU sees every ``frame_stride``-th frame (2: 10 fps for 20 fps data, half the cost).
    """

    classes: tuple[str, ...]
    feature_dim: int = 263
    hidden: int = 128
    layers: int = 2
    embed_dim: int = 30
    dropout: float = 0.0
    frame_stride: int = 2

    def __post_init__(self) -> None:
        object.__setattr__(self, "classes", tuple(self.classes))
        if len(self.classes) < 2 or len(set(self.classes)) != len(self.classes):
            raise ValueError(f"RecogniserConfig.classes must be >= 2 distinct labels, got {self.classes}")
        for name in ("feature_dim", "hidden", "layers", "embed_dim", "frame_stride"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"RecogniserConfig.{name} must be a positive integer, got {value!r}")
        if (self.feature_dim + 1) % 12:
            raise ValueError(f"feature_dim must be 12J - 1 (HumanML3D layout), got {self.feature_dim}")
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"dropout must lie in [0, 1), got {self.dropout}")

    @property
    def joints_num(self) -> int:
        return (self.feature_dim + 1) // 12

    @property
    def num_classes(self) -> int:
        return len(self.classes)

    def to_dict(self) -> dict[str, Any]:
        data = asdict(self)
        data["classes"] = list(self.classes)
        return data

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> RecogniserConfig:
        unknown = set(data) - {f.name for f in fields(cls)}
        if unknown:
            raise ValueError(f"unknown RecogniserConfig keys: {sorted(unknown)}")
        return cls(**data)


def _lengths(lengths: TensorLike, batch: int, max_len: int) -> torch.Tensor:
    """``lengths`` as a CPU int64 (B,) tensor with 1 <= l <= max_len (pack_padded_sequence needs CPU)."""
    out = torch.as_tensor(np.asarray(lengths) if not isinstance(lengths, torch.Tensor) else lengths)
    out = out.detach().to("cpu", torch.int64).reshape(-1)
    if out.numel() != batch:
        raise ValueError(f"lengths has {out.numel()} entries for a batch of {batch}")
    if batch and (int(out.min()) < 1 or int(out.max()) > max_len):
        raise ValueError(f"lengths must lie in [1, {max_len}], got min {int(out.min())} max {int(out.max())}")
    return out


class ActionRecogniser(nn.Module):
    """GRU action classifier over recovered joint positions (module docstring)."""

    def __init__(self, config: RecogniserConfig, mean: TensorLike | None = None, std: TensorLike | None = None) -> None:
        super().__init__()
        self.config = config
        d = config.feature_dim
        self.register_buffer("mean", torch.zeros(d))
        self.register_buffer("std", torch.ones(d))
        if mean is not None or std is not None:
            self.set_normalization(np.zeros(d) if mean is None else mean, np.ones(d) if std is None else std)
        self.input = nn.Linear(6 * config.joints_num + 1, config.hidden)
        self.input_norm = nn.LayerNorm(config.hidden)
        self.gru = nn.GRU(config.hidden, config.hidden, num_layers=config.layers, batch_first=True,
                          dropout=config.dropout if config.layers > 1 else 0.0)
        self.embedding = nn.Linear(3 * config.hidden, config.embed_dim)
        self.classifier = nn.Linear(config.embed_dim, config.num_classes)

    def set_normalization(self, mean: TensorLike, std: TensorLike) -> None:
        """The Mean/Std the input features were normalised with (D,) each."""
        mean_t = torch.as_tensor(np.asarray(mean, np.float32)).reshape(-1)
        std_t = torch.as_tensor(np.asarray(std, np.float32)).reshape(-1)
        if mean_t.shape != self.mean.shape or std_t.shape != self.std.shape:
            raise ValueError(f"mean/std must have shape ({self.config.feature_dim},)")
        if not torch.all(std_t > 0):
            raise ValueError("std must be positive")
        self.mean.copy_(mean_t)
        self.std.copy_(std_t)

    def joints(self, features: torch.Tensor) -> torch.Tensor:
        """Normalised (B, T, D) features -> (B, T, J, 3) joints relative to each sequence's start."""
        return recover_from_ric(features * self.std + self.mean, self.config.joints_num)

    def frames(self, features: torch.Tensor) -> torch.Tensor:
        """Normalised (B, T, D) features -> (B, T, 6J + 1) GRU inputs (every frame, before striding).

        Per frame: the joints with the root's XZ subtracted (the pose, in the start heading's frame,
        root height kept; 3J), every joint's velocity in m/s (3J) and the root's horizontal speed in
        m/s (1; heading-free, so a run reads the same whichever way it goes). Velocities are 0 at
        the first frame; frame t uses frames <= t only.
        """
        joints = self.joints(features)
        root_xz = joints[..., :1, :] * joints.new_tensor([1.0, 0.0, 1.0])
        pose = (joints - root_xz).flatten(2)
        velocity = torch.cat([torch.zeros_like(joints[:, :1]), joints[:, 1:] - joints[:, :-1]], 1) * FPS
        speed = velocity[..., 0, [0, 2]].norm(dim=-1, keepdim=True)
        return torch.cat([pose, velocity.flatten(2), speed], -1)

    def embed(self, features: TensorLike, lengths: TensorLike) -> torch.Tensor:
        """Normalised (B, T, D) features (anything past ``lengths``) -> (B, E) embeddings."""
        x = features if isinstance(features, torch.Tensor) else torch.as_tensor(np.asarray(features))
        x = x.to(self.mean.device, torch.float32)
        if x.ndim != 3 or x.shape[-1] != self.config.feature_dim:
            raise ValueError(f"features must have shape (B, T, {self.config.feature_dim}), got {tuple(x.shape)}")
        lens = _lengths(lengths, x.shape[0], x.shape[1])
        if x.shape[0] == 0:
            return x.new_zeros(0, self.config.embed_dim)
        x = x[:, : int(lens.max())]
        stride = self.config.frame_stride
        frames = self.frames(x)[:, ::stride]  # (B, ceil(T / stride), 6J + 1)
        lens = (lens + stride - 1) // stride
        h = nn.functional.leaky_relu(self.input_norm(self.input(frames)), 0.2)
        packed = pack_padded_sequence(h, lens, batch_first=True, enforce_sorted=False)
        out, h_n = self.gru(packed)  # h_n: (layers, B, H), in the input order
        out, _ = pad_packed_sequence(out, batch_first=True)  # (B, T', H), zero past each length
        valid = (torch.arange(out.shape[1])[None, :] < lens[:, None]).to(out.device)[..., None]
        mean = out.sum(1) / lens.to(out.device, out.dtype)[:, None]
        peak = out.masked_fill(~valid, float("-inf")).amax(1)
        return torch.tanh(self.embedding(torch.cat([h_n[-1], mean, peak], -1)))

    def classify(self, embedding: torch.Tensor) -> torch.Tensor:
        """(B, E) embeddings -> (B, C) logits."""
        return self.classifier(embedding)

    def forward(self, features: TensorLike, lengths: TensorLike) -> torch.Tensor:
        """Normalised (B, T, D) features -> (B, C) class logits."""
        return self.classify(self.embed(features, lengths))
