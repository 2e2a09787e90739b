"""Where a ControlNet training step's time goes: the trajectory encoder, decoding for Eq. 9, the whole loss.

    python benchmarks/controlnet_step.py [--frames 196] [--batch 32] [key=value ...]

Builds the stage's ControlNet on the pipeline's student and VAE (``paths.artifacts``; overrides such
as ``train_controlnet.encoder.patch_frames=1`` change the encoder) and times, on random hints of
``--frames`` frames with 5 % of the entries controlled, forward and backward of: the trajectory
encoder alone, the frozen decoder with the joint recovery alone, and the whole loss of
:func:`models.controlnet.controlnet_loss` at the configured λ and at λ = 0 (the loss then decodes
without gradients, for logging). Milliseconds per call, the mean of 5 after one warm-up. Used for
docs/controlnet.md.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from models.controlnet import ControlConfig, MotionControlNet, controlnet_loss, decode_joints  # noqa: E402
from pipelines.config import load_params  # noqa: E402
from pipelines.mld_family import load_mld, load_motionlcm, load_vae  # noqa: E402
from stages import train_controlnet  # noqa: E402


def milliseconds(fn: Callable[[], None], repeats: int = 5) -> float:
    fn()
    start = time.perf_counter()
    for _ in range(repeats):
        fn()
    return (time.perf_counter() - start) / repeats * 1000.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=196)
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("overrides", nargs="*", help="params overrides, e.g. train_controlnet.encoder.patch_frames=1")
    args = parser.parse_args()
    torch.manual_seed(0)
    cfg = train_controlnet.stage_config(load_params(args.overrides))
    student = load_motionlcm(Path(cfg["student_dir"])).requires_grad_(False)
    vae = load_vae(Path(cfg["vae_dir"])).requires_grad_(False)
    _, schedule, _ = load_mld(Path(cfg["teacher_dir"]))
    controlnet = MotionControlNet(student, ControlConfig(**cfg["control"]))
    b, t, joints = args.batch, args.frames, controlnet.config.joints_num
    hint, mask = torch.randn(b, t, joints, 3), torch.rand(b, t, joints) < 0.05
    z0 = torch.randn(b, student.config.latent_tokens, student.config.latent_dim)
    lengths = torch.full((b,), t)
    mean, std = torch.tensor(cfg["mean"]), torch.tensor(cfg["std"])
    text = torch.randn(b, student.config.text_dim)
    tokens, token_mask = torch.randn(b, 12, student.config.token_dim), torch.ones(b, 12, dtype=torch.bool)

    def encoder() -> None:
        controlnet.encoder(hint, mask).sum().backward()

    def decoder() -> None:
        z = z0.clone().requires_grad_(True)
        decode_joints(vae, z, lengths, t, mean, std, student.config.latent_scale).sum().backward()

    def loss(weight: float) -> Callable[[], None]:
        def run() -> None:
            controlnet_loss(controlnet, student, vae, schedule, z0, text, hint, mask, lengths, mean=mean, std=std,
                            w_range=tuple(cfg["w_range"]), control_weight=weight,
                            num_ddim_steps=cfg["num_ddim_steps"], text_tokens=tokens,
                            text_mask=token_mask)["total"].backward()
        return run

    print(f"batch {b}, {t} frames, {controlnet.config.patch_frames} frame(s) per encoder token, "
          f"{torch.get_num_threads()} threads (ms, forward and backward):")
    print(f"  trajectory encoder       {milliseconds(encoder):7.1f}")
    print(f"  decoder + joint recovery {milliseconds(decoder):7.1f}")
    print(f"  whole loss, λ = {cfg['control_weight']:<8g} {milliseconds(loss(cfg['control_weight'])):7.1f}")
    print(f"  whole loss, λ = 0        {milliseconds(loss(0.0)):7.1f}")


if __name__ == "__main__":
    main()
