"""MotionLCM's ControlNet as evaluation rows and a ``stages.generate`` model (registry entry ``motionlcm-control``).

Rows (all one-step MotionLCM, the configured guidance, pelvis hints from the test crops):

- ``MotionLCM-Control``: every frame controlled (100 %);
- ``MotionLCM-Control-5f``: 5 random frames;
- ``MotionLCM-Control+refine``: 100 %, with test-time noise optimisation
  (:func:`models.controlnet.refine_noise`, ``sample.control_refine_steps`` and ``_lr``, on
  ``sample.control_refine_batch`` motions at a time), then the root projection onto the hint
  (:mod:`data.root_projection`) when ``sample.control_refine_project``;
- ``MotionLCM-1-uncontrolled``: MotionLCM-1 without a ControlNet, scored against the same 100 % hints
  (the control error of a model that ignores them).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from data.root_projection import project_root
from models.controlnet import ControlConfig, ControlledStudent, MotionControlNet, refine_noise
from models.diffusion import NoiseSchedule
from models.generator import ControlSpec, Hint, TextBatch, device_of
from models.mld import MLDDenoiser
from models.motionlcm import motionlcm_latents
from models.transformer import checked_lengths, lengths_to_mask
from models.vae import MotionVAE
from pipelines.checkpoint import load_final_model
from pipelines.mld_family import MotionLCMGenerator, load_mld, load_motionlcm, load_vae, text_inputs

if TYPE_CHECKING:
    from pipelines.registry import EvalContext, GenerateOptions


def load_controlnet(out_dir: Path, student: MLDDenoiser) -> MotionControlNet:
    """The trained ControlNet of a ``train_controlnet`` output folder, on ``student`` (and its device), in eval
    mode."""
    payload = load_final_model(out_dir)
    controlnet = MotionControlNet(student, ControlConfig(**payload["config"]["control"]))
    controlnet.load_state_dict(payload["models"]["controlnet"])
    return controlnet.eval().to(device_of(student))


class ControlNetGenerator:
    """One-step MotionLCM with the ControlNet (and optionally test-time refinement), then VAE decoding."""

    stochastic = True

    def __init__(self, name: str, student: MLDDenoiser, controlnet: MotionControlNet, vae: MotionVAE,
                 schedule: NoiseSchedule, guidance: float, control: ControlSpec, mean: np.ndarray, std: np.ndarray,
                 refine: dict[str, Any] | None = None) -> None:
        self.name, self.student, self.controlnet, self.vae, self.schedule = name, student, controlnet, vae, schedule
        self.w, self.control, self.refine = guidance - 1.0, control, refine
        # forward passes of the ControlNet copy and the student: once each, and once more per refinement step
        # (each step also runs both backward and the decoder forward and backward, which NFE does not count)
        self.nfe = 2 * (1 + (refine["steps"] if refine else 0))
        self.mean, self.std = torch.from_numpy(mean.astype(np.float32)), torch.from_numpy(std.astype(np.float32))

    @torch.inference_mode(False)
    def sample(self, text: TextBatch, lengths: np.ndarray, seed: int, hint: Hint) -> np.ndarray:
        frames, joints_num = int(np.max(lengths)), self.controlnet.config.joints_num
        if hint.joints.shape[0] != len(text) or hint.joints.shape[1] < frames or hint.joints.shape[2] != joints_num:
            raise ValueError(f"hint {hint.joints.shape} does not cover {len(text)} motions of up to {frames} frames "
                             f"and {joints_num} joints")
        device = device_of(self.student)
        lengths_t = checked_lengths(lengths, frames)[0].to(device)
        joints = torch.from_numpy(hint.joints[:, :frames].astype(np.float32)).to(device)
        mask = torch.from_numpy(hint.mask[:, :frames]).to(device) & lengths_to_mask(lengths_t, frames)[..., None]
        text_emb, words = text_inputs(self.student, text)
        cfg = self.student.config
        x_T = torch.randn((len(text), cfg.latent_tokens, cfg.latent_dim),
                          generator=torch.Generator().manual_seed(seed)).to(device)
        chunk = max(1, len(text) if self.refine is None or self.refine["batch"] is None else self.refine["batch"])
        z0 = torch.cat([self.latents(x_T[rows], text_emb[rows], {k: v[rows] for k, v in words.items()}, joints[rows],
                                     mask[rows], lengths_t[rows])
                        for rows in (slice(first, first + chunk) for first in range(0, len(text), chunk))])
        with torch.no_grad():
            out = self.vae.eval().decode_by_length(z0 * cfg.latent_scale, lengths_t).cpu().numpy()
        if self.refine is None or not self.refine["project"]:
            return out
        mean, std = self.mean.numpy(), self.std.numpy()
        projected = project_root(out * std + mean, hint.joints, hint.mask, np.asarray(lengths), joints_num)
        return ((projected - mean) / std).astype(np.float32)

    def latents(self, x_T: torch.Tensor, text_emb: torch.Tensor, words: dict[str, torch.Tensor], joints: torch.Tensor,
                mask: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        """One-step latents (B, L, C) of these motions from their noise ``x_T``, refined when the row refines (a
        refined row calls this on ``refine["batch"]`` motions at a time: refinement backpropagates through the
        decoder, and its memory grows with the motions it holds)."""
        model = ControlledStudent(self.student, self.controlnet, joints, mask)

        def denoise(x: torch.Tensor) -> torch.Tensor:
            return motionlcm_latents(model, self.schedule, text_emb, 1, self.w, x_T=x, **words)

        if self.refine is None:
            return denoise(x_T)
        return refine_noise(denoise, self.vae, x_T, joints, mask, lengths, mean=self.mean.to(x_T.device),
                            std=self.std.to(x_T.device), latent_scale=self.student.config.latent_scale,
                            steps=int(self.refine["steps"]), lr=self.refine["lr"])


class Uncontrolled:
    """A text-only generator scored against a :class:`ControlSpec`'s hints, which it ignores."""

    def __init__(self, name: str, generator: MotionLCMGenerator, control: ControlSpec) -> None:
        self.name, self.generator, self.control = name, generator, control
        self.nfe, self.stochastic = generator.nfe, generator.stochastic

    def sample(self, text: TextBatch, lengths: np.ndarray, seed: int, hint: Hint) -> np.ndarray:
        return self.generator.sample(text, lengths, seed)


def _refine_settings(ctx: EvalContext) -> dict[str, Any]:
    sample = ctx.params["sample"]
    return {"steps": sample["control_refine_steps"], "lr": sample["control_refine_lr"],
            "project": sample["control_refine_project"], "batch": sample["control_refine_batch"]}


def _controlnet(ctx: EvalContext, name: str, density: str, refine: bool = False,
                base: ControlNetGenerator | None = None) -> ControlNetGenerator:
    if base is None:
        student = load_motionlcm(ctx.trained("distill_lcm"), device=ctx.device)
        _, schedule, _ = load_mld(ctx.trained("train_mld"), device=ctx.device)
        controlnet = load_controlnet(ctx.trained("train_controlnet"), student)
        vae = load_vae(ctx.trained("train_vae"), ctx.device)
    else:
        student, controlnet, vae, schedule = base.student, base.controlnet, base.vae, base.schedule
    return ControlNetGenerator(name, student, controlnet, vae, schedule, ctx.params["sample"]["motionlcm_guidance"],
                               ControlSpec(density), ctx.store.mean, ctx.store.std,
                               _refine_settings(ctx) if refine else None)


def controlnet_row_names(params: dict[str, Any]) -> list[str]:
    """The names :func:`controlnet_rows` gives its rows."""
    return ["MotionLCM-Control", "MotionLCM-Control-5f", "MotionLCM-Control+refine", "MotionLCM-1-uncontrolled"]


def controlnet_rows(ctx: EvalContext) -> list[ControlNetGenerator | Uncontrolled]:
    """MotionLCM-Control (100 %), -5f, +refine and the uncontrolled reference (one load)."""
    full = _controlnet(ctx, "MotionLCM-Control", "100%")
    text_only = MotionLCMGenerator("MotionLCM-1", full.student, full.vae, full.schedule, 1, full.w + 1.0)
    return [full, _controlnet(ctx, "MotionLCM-Control-5f", "5", base=full),
            _controlnet(ctx, "MotionLCM-Control+refine", "100%", refine=True, base=full),
            Uncontrolled("MotionLCM-1-uncontrolled", text_only, ControlSpec("100%"))]


def controlnet_generator(ctx: EvalContext, options: GenerateOptions) -> ControlNetGenerator:
    """``stages.generate --model motionlcm-control``: one step, refinement when ``options.refine``."""
    if options.steps not in (None, 1):
        raise ValueError(f"--steps {options.steps}: the ControlNet samples with one MotionLCM step")
    generator = _controlnet(ctx, "MotionLCM-Control", "100%", refine=options.refine)
    if options.guidance is not None:
        generator.w = options.guidance - 1.0
    return generator
