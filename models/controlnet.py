"""Motion ControlNet on MotionLCM: trajectory control in latent space (MotionLCM §3.3, Eqs. 9-10).

Reference: ``reference/motionlcm_mld.md`` section 5. Shapes: B batch, T frames, J joints, L latent
tokens, C latent channels, h denoiser width.

Architecture (:class:`MotionControlNet`):

- **Trajectory encoder** (:class:`TrajectoryEncoder`): the hint's global joint positions,
  normalised ``(p - mean) / std`` with the training joints' per-(joint, axis) statistics and
  multiplied by the control mask, flattened per frame (J·3); with ``patch_frames = P > 1`` each
  token carries P consecutive frames (the positions and the J mask bits of each, ``Linear(4PJ ->
  d)``; the paper: one frame per token, ``Linear(3J -> d)``). L learned global tokens in front, a
  sinusoidal positional encoding, a skip transformer whose self-attention ignores every token
  without a controlled joint (a motion with no control at all sees only its global tokens), then
  the global tokens' outputs through a **zero-initialised** ``Linear(d -> C)``: a condition c_h
  (B, L, C) of the latent's shape. Documented choice for P > 1: a masked position reads 0, as a
  controlled one at the mean would; at P = 1 that ambiguity is only between the joints of one
  frame, but a patch also mixes controlled and uncontrolled frames, so the mask bits go in beside
  the positions. At P = 1 the encoder (a transformer over T + L tokens) is about half the cost of
  a training step (the other half: decoding for Eq. 9); P = 4 shortens its sequence fourfold
  (``benchmarks/controlnet_step.py``, docs/controlnet.md).
- **ControlNet**: a trainable copy of the MotionLCM student denoiser (its guidance projection and
  word-token attention included), given ``z_t + c_h`` and the same t, text and w. Layer i's output
  goes through its own **zero-initialised** ``Linear(h -> h)``; the results are the residuals the
  frozen student adds to the output of its layer i (the hook of :class:`models.transformer.SkipTransformer`).
  The copy's final LayerNorm and output projection are dropped (unused: its output is its hidden states).

Both zero initialisations make the controlled student's output equal the student's at initialisation.

Training loss (:func:`controlnet_loss`, Eq. 10): ``||ẑ0 - z0||² + λ · L_control`` with ``ẑ0`` the
controlled student's consistency output at ``z_t`` (t on the LCM solver grid, the paper's, or uniform
over a given list of timesteps; w ~ U[w_min, w_max]),
and ``L_control`` (Eq. 9, :func:`control_loss`): ẑ0 decoded by the **frozen** VAE (gradients flow
through it), global joints recovered differentiably (``recover_from_ric``), squared error to the
hint averaged over the controlled (frame, joint) entries and the 3 axes (the reference divides the
per-sample sum by #controlled entries × 3). That is Eq. 9 divided by 3: Eq. 9 sums the squared
error over the axes, so the paper's λ is our 3λ. Documented choice: the squared error in metres (the
issue's masked L2) rather than the reference's smooth-L1, which equals half of it below 1 m.
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import torch
from torch import Tensor, nn

from data.features import recover_from_ric
from models.diffusion import NoiseSchedule, lcm_consistency_fn, lcm_training_timesteps
from models.mld import MLDDenoiser
from models.motionlcm import guidance_embedding
from models.rng import normal, rng_device, uniform
from models.transformer import SkipTransformer, lengths_to_mask, sinusoidal_positions
from models.vae import MotionVAE


@dataclass(frozen=True)
class ControlConfig:
    """The trajectory encoder's settings and the hint statistics (saved with the model).

    ``hint_mean``/``hint_std``: (J·3) per-(joint, axis) mean and std of the training motions'
    global joint positions (metres).
    """

    joints_num: int
    hint_mean: Sequence[float]
    hint_std: Sequence[float]
    dim: int = 128
    layers: int = 3
    heads: int = 4
    ff_dim: int = 256
    dropout: float = 0.0
    patch_frames: int = 1
    train_joints: Sequence[int] = field(default=(0,))

    def __post_init__(self) -> None:
        n = 3 * self.joints_num
        if len(self.hint_mean) != n or len(self.hint_std) != n:
            raise ValueError(f"hint_mean and hint_std need {n} values (3 per joint), got "
                             f"{len(self.hint_mean)} and {len(self.hint_std)}")
        if min(self.hint_std) <= 0:
            raise ValueError("hint_std must be positive")
        if self.patch_frames < 1:
            raise ValueError(f"patch_frames must be >= 1, got {self.patch_frames}")

    def to_dict(self) -> dict[str, Any]:
        return {k: list(v) if isinstance(v, tuple | list) else v for k, v in asdict(self).items()}


class TrajectoryEncoder(nn.Module):
    """Hint (B, T, J, 3) and mask (B, T, J) -> condition (B, L, C); see the module docstring."""

    hint_mean: Tensor
    hint_std: Tensor

    def __init__(self, config: ControlConfig, latent_tokens: int, latent_dim: int) -> None:
        super().__init__()
        self.config = config
        self.register_buffer("hint_mean", torch.tensor(config.hint_mean, dtype=torch.float32).view(-1, 3))
        self.register_buffer("hint_std", torch.tensor(config.hint_std, dtype=torch.float32).view(-1, 3))
        per_frame = 3 * config.joints_num if config.patch_frames == 1 else 4 * config.joints_num
        self.input = nn.Linear(config.patch_frames * per_frame, config.dim)
        self.global_tokens = nn.Parameter(torch.randn(latent_tokens, config.dim) * 0.02)
        self.transformer = SkipTransformer(config.dim, config.layers, config.heads, config.ff_dim, config.dropout)
        self.output = nn.Linear(config.dim, latent_dim)
        nn.init.zeros_(self.output.weight)
        nn.init.zeros_(self.output.bias)

    def forward(self, hint: Tensor, mask: Tensor) -> Tensor:
        b, t, j, _ = hint.shape
        p = self.config.patch_frames
        x = torch.where(mask[..., None], (hint - self.hint_mean) / self.hint_std, 0.0)  # NaN outside: ignored
        x = x.reshape(b, t, 3 * j)
        controlled = mask.any(-1)
        if p > 1:  # P frames per token, each frame's mask bits beside its positions (module docstring)
            pad = (-t) % p
            x = nn.functional.pad(torch.cat([x, mask.to(x.dtype)], dim=-1), (0, 0, 0, pad)).reshape(b, -1, p * 4 * j)
            controlled = nn.functional.pad(controlled, (0, pad)).reshape(b, -1, p).any(-1)
        tokens = torch.cat([self.global_tokens.expand(b, -1, -1), self.input(x)], dim=1)
        tokens = tokens + sinusoidal_positions(tokens.shape[1], tokens.shape[2], device=hint.device)[None]
        n = self.global_tokens.shape[0]
        ignored = torch.cat([mask.new_zeros(b, n), ~controlled], dim=1)
        return self.output(self.transformer(tokens, key_padding_mask=ignored)[:, :n])


class MotionControlNet(nn.Module):
    """The ControlNet of a MotionLCM student: :meth:`residuals` for its frozen layers."""

    def __init__(self, student: MLDDenoiser, config: ControlConfig) -> None:
        super().__init__()
        self.config = config
        self.copy = copy.deepcopy(student).train().requires_grad_(True)
        self.copy.transformer.norm = nn.Identity()
        self.copy.latent_out = nn.Identity()
        width = student.config.width
        self.projections = nn.ModuleList(nn.Linear(width, width) for _ in range(student.transformer.num_layers))
        for proj in self.projections:
            nn.init.zeros_(proj.weight)
            nn.init.zeros_(proj.bias)
        self.encoder = TrajectoryEncoder(config, student.config.latent_tokens, student.config.latent_dim)

    def forward(self, z_t: Tensor, t: Tensor | int, text_emb: Tensor, hint: Tensor, mask: Tensor,
                **kwargs: Tensor | None) -> list[Tensor]:
        """One residual (B, S, h) per student layer; ``kwargs``: the student's time_cond/text_tokens/text_mask.

        (``forward``, not a named method, so a DDP-wrapped ControlNet synchronises its gradients.)
        """
        hidden = self.copy.run(z_t + self.encoder(hint, mask), t, text_emb, **kwargs).hidden_states
        return [proj(h) for proj, h in zip(self.projections, hidden, strict=True)]


class ControlledStudent(nn.Module):
    """The frozen student with a ControlNet for one hint: a denoiser with the student's call signature."""

    def __init__(self, student: MLDDenoiser, controlnet: MotionControlNet, hint: Tensor, mask: Tensor) -> None:
        super().__init__()
        self.student, self.controlnet, self.hint, self.mask = student, controlnet, hint, mask
        self.config = student.config
        self.training = controlnet.training  # the flag a sampler's eval-mode block restores (no recursion here)

    def forward(self, z_t: Tensor, t: Tensor | int, text_emb: Tensor, **kwargs: Tensor | None) -> Tensor:
        residuals = self.controlnet(z_t, t, text_emb, self.hint, self.mask, **kwargs)
        return self.student(z_t, t, text_emb, residuals=residuals, **kwargs)


def decode_joints(vae: MotionVAE, z0: Tensor, lengths: Tensor, num_frames: int, mean: Tensor, std: Tensor,
                  latent_scale: float) -> Tensor:
    """Diffusion-space latents (B, L, C) -> global joints (B, T, J, 3), differentiable through the decoder."""
    features = vae.decode(z0 * latent_scale, lengths, num_frames) * std + mean
    return recover_from_ric(features, (features.shape[-1] + 1) // 12)


def control_loss(joints: Tensor, hint: Tensor, mask: Tensor) -> Tensor:
    """Eq. 9 / 3: squared error (metres²) averaged over the batch's controlled entries and the 3 axes
    (Eq. 9 sums the axes); 0 when nothing is controlled.

    Documented choice: one mean over all controlled entries of the batch (a sample with many
    keyframes weighs more), where the reference averages each sample's mean over the batch.
    Hint values outside ``mask`` (even NaN) are ignored.
    """
    error = torch.where(mask[..., None], joints - hint, 0.0)
    return (error**2).sum() / (3.0 * mask.sum()).clamp(min=1.0)


def training_timesteps(timesteps: Sequence[int], batch: int, num_train_steps: int,
                       generator: torch.Generator | None = None) -> Tensor:
    """``batch`` int64 timesteps drawn uniformly from ``timesteps``; a ValueError names a value outside
    ``[0, num_train_steps)`` or an empty list."""
    choices = torch.as_tensor(list(timesteps), dtype=torch.long)
    if choices.numel() == 0 or choices.min() < 0 or choices.max() >= num_train_steps:
        raise ValueError(f"timesteps: expected a non-empty list in [0, {num_train_steps}), got {list(timesteps)}")
    device = rng_device(generator, "cpu")
    return choices.to(device)[torch.randint(0, len(choices), (batch,), generator=generator, device=device)]


def controlnet_loss(
    controlnet: MotionControlNet,
    student: MLDDenoiser,
    vae: MotionVAE,
    schedule: NoiseSchedule,
    z0: Tensor,
    text_emb: Tensor,
    hint: Tensor,
    mask: Tensor,
    lengths: Tensor,
    *,
    mean: Tensor,
    std: Tensor,
    w_range: tuple[float, float],
    control_weight: float = 1.0,
    num_ddim_steps: int = 10,
    timesteps: Sequence[int] | None = None,
    text_dropout: float = 0.0,
    text_tokens: Tensor | None = None,
    text_mask: Tensor | None = None,
    generator: torch.Generator | None = None,
) -> dict[str, Tensor]:
    """Eq. 10 on diffusion-space latents z0 (B, L, C) with hints (B, T, J, 3) / masks (B, T, J).

    t is uniform on the LCM solver grid of ``num_ddim_steps`` points (MotionLCM), or uniform over
    ``timesteps`` when given (e.g. ``[799]``, the one step every controlled row samples at).
    ``mean``/``std``: the feature normalisation (D,).
    ``text_dropout`` (ours; MotionLCM: 0): each sample's caption is replaced, with that probability, by
    the student's unconditional embedding and no word tokens, for the student and the ControlNet alike.
    Such a sample's motion can only be told by its hint, which pushes the ControlNet to read the hint
    rather than learn a correction from the text. No random number is drawn when it is 0.
    Returns ``{"total", "latent", "control"}`` (``control`` is computed, for logging, even when
    ``control_weight`` is 0; its gradient is then unused).
    """
    b = z0.shape[0]
    if timesteps is None:
        t, _ = lcm_training_timesteps(b, schedule.num_steps, num_ddim_steps, generator, z0.device)
    else:
        t = training_timesteps(timesteps, b, schedule.num_steps, generator).to(z0.device)
    z_t = schedule.q_sample(z0, t, normal(z0.shape, z0, generator))
    w = w_range[0] + (w_range[1] - w_range[0]) * uniform((b,), z0, generator)
    if text_dropout > 0:
        drop = uniform((b,), z0, generator) < text_dropout
        text_emb = torch.where(drop[:, None], student.null_text_like(text_emb), text_emb)
        text_mask = None if text_mask is None else text_mask & ~drop[:, None]
    words = {"time_cond": guidance_embedding(w), "text_tokens": text_tokens, "text_mask": text_mask}
    mask = mask & lengths_to_mask(lengths, hint.shape[1]).to(mask.device)[..., None]  # padding is never a hint
    out = ControlledStudent(student, controlnet, hint, mask)(z_t, t, text_emb, **words)
    z0_hat = lcm_consistency_fn(schedule, out, z_t, t, student.config.prediction_type)
    latent = ((z0_hat - z0) ** 2).mean()
    with torch.set_grad_enabled(torch.is_grad_enabled() and control_weight > 0):
        joints = decode_joints(vae, z0_hat, lengths, hint.shape[1], mean, std, student.config.latent_scale)
        control = control_loss(joints, hint, mask)
    return {"total": latent + control_weight * control, "latent": latent.detach(), "control": control.detach()}


def refine_noise(
    denoise: Callable[[Tensor], Tensor],
    vae: MotionVAE,
    x_T: Tensor,
    hint: Tensor,
    mask: Tensor,
    lengths: Tensor,
    *,
    mean: Tensor,
    std: Tensor,
    latent_scale: float,
    steps: int = 10,
    lr: float = 0.1,
) -> Tensor:
    """Test-time refinement by noise optimisation (our addition; MotionLCM V2 and DNO optimise the noise).

    ``denoise`` maps initial noise x (B, L, C) to the one-step sample z0 (B, L, C): the controlled
    student's consistency output. Adam on x from ``x_T`` minimises ``L_control(decode(denoise(x)))``;
    after each step every sample's x is rescaled to the norm of its ``x_T`` (DNO's hypersphere
    constraint: Gaussian draws of this dimension concentrate on that sphere). The sample therefore
    stays one the model produces for some noise, rather than any latent that happens to pass the
    keyframes, which is what keeps the motion natural: there is no realism weight to tune.
    Controlled entries on frames at or past ``lengths`` are ignored. Gradients are taken for x only
    (never a network's weights). Returns ``denoise(x)`` of the final x (no grad); ``steps=0`` returns
    ``denoise(x_T)``.
    """
    frames = hint.shape[1]
    mask = mask & lengths_to_mask(lengths, frames).to(mask.device)[..., None]
    radius = x_T.flatten(1).norm(dim=1).view(-1, *[1] * (x_T.dim() - 1))
    x = x_T.detach().clone().requires_grad_(True)
    opt = torch.optim.Adam([x], lr=lr)
    with torch.enable_grad():
        for _ in range(steps):
            joints = decode_joints(vae, denoise(x), lengths, frames, mean, std, latent_scale)
            (x.grad,) = torch.autograd.grad(control_loss(joints, hint, mask), [x])
            opt.step()
            with torch.no_grad():
                x.mul_(radius / x.flatten(1).norm(dim=1).view_as(radius))
    with torch.no_grad():
        return denoise(x.detach())
