"""Where a trained MotionDiffuse's error sits: noise-prediction error and x0 roughness by timestep.

    python benchmarks/motiondiffuse_levels.py [--items 32] [key=value ...]

The first ``--items`` validation motions (normalised features, their own captions) are noised to
x_t at a ladder of timesteps t and the model predicts the noise. Per t the table gives:

- ``eps MSE``: the masked mean squared error of the predicted noise (1.0: no better than
  predicting 0);
- ``x0 MSE``: the error of the implied clean motion, ``(x_t - sqrt(1 - a) eps_hat) / sqrt(a)``
  with ``a`` the cumulative alpha at t;
- ``rough``: the mean squared frame-to-frame second difference of that x0 estimate over the same
  of the real motions (1.0: as smooth as the data; white noise left in x0 raises it).

A DDPM or DDIM sample ends on an x0 estimate taken at a small t, so a model whose ``rough`` is far
above 1 at small t leaves high-frequency noise in its samples (the jitter that
``benchmarks/contrasts.py`` measures on the joints).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from data.motion_dataset import MotionTextDataset, collate_trimmed_words  # noqa: E402
from models.transformer import lengths_to_mask  # noqa: E402
from pipelines.cli import artifacts_dir  # noqa: E402
from pipelines.config import load_params  # noqa: E402
from pipelines.motiondiffuse_family import TRAIN_STAGE, load_motiondiffuse  # noqa: E402

LADDER = (1, 5, 10, 25, 50, 100, 200, 400, 600, 800, 999)


def roughness(x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Mean squared second difference over frames of (B, N, D) features, counting valid triples only."""
    second = x[:, 2:] - 2 * x[:, 1:-1] + x[:, :-2]
    mask = valid[:, 2:] & valid[:, :-2]
    return (second**2 * mask).sum() / (mask.sum() * x.shape[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--items", type=int, default=32)
    parser.add_argument("overrides", nargs="*")
    args = parser.parse_args()
    params = load_params(args.overrides)
    model, schedule, config = load_motiondiffuse(artifacts_dir(params) / TRAIN_STAGE)
    data = MotionTextDataset(config["features_dir"], "val", config["mean"], config["std"], 196, word_tokens=64)
    torch.manual_seed(0)  # the dataset's caption and window draws
    batch = collate_trimmed_words([data[i] for i in range(min(args.items, len(data)))])
    x0, lengths, tokens, mask = batch["motion"], batch["length"], batch["tokens"], batch["token_mask"]
    valid = lengths_to_mask(lengths, x0.shape[1])[..., None]
    count = valid.sum() * x0.shape[-1]
    real_rough = roughness(x0, valid)
    rng = torch.Generator().manual_seed(0)
    print("| t | alpha_bar | eps MSE | x0 MSE | rough |\n|---|---|---|---|---|")
    with torch.inference_mode():
        text = model.encode_text(tokens, mask)
        for t in LADDER:
            noise = torch.randn(x0.shape, generator=rng)
            a = schedule.alphas_cumprod[t]
            x_t = torch.where(valid, a.sqrt() * x0 + (1 - a).sqrt() * noise, 0.0)
            eps = model.denoise(x_t, torch.full((x0.shape[0],), t), text, lengths)
            x0_hat = torch.where(valid, (x_t - (1 - a).sqrt() * eps) / a.sqrt(), 0.0)
            eps_mse = float(((eps - noise) ** 2 * valid).sum() / count)
            x0_mse = float(((x0_hat - x0) ** 2 * valid).sum() / count)
            print(f"| {t} | {float(a):.4f} | {eps_mse:.3f} | {x0_mse:.3f} | "
                  f"{float(roughness(x0_hat, valid) / real_rough):.1f} |")


if __name__ == "__main__":
    main()
