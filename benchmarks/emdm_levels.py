"""Where a trained EMDM generator's error sits: x0-prediction MSE by noise level on validation motions.

    python benchmarks/emdm_levels.py [--raw] [key=value ...]

For each level k = 1..T the validation motions (the first 32, normalised) are noised to x_k and the
generator predicts x0 from (x_k, t = k - 1, z, caption); the table gives the masked MSE beside the
linear estimate's (sqrt(alpha_bar_k) x_k, the least-squares estimate for unit-variance data), so a
generator worse than that estimate at small k shows a bottleneck. ``--raw``: the raw weights
instead of the EMA.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from data.motion_dataset import MotionTextDataset, collate_trimmed_words  # noqa: E402
from models.emdm import EMDMGenerator, EMDMSchedule  # noqa: E402
from pipelines.cli import artifacts_dir  # noqa: E402
from pipelines.config import load_params  # noqa: E402
from pipelines.emdm_family import TRAIN_STAGE, load_emdm  # noqa: E402


def load_from_command_line(doc: str, stage: str) -> tuple[EMDMGenerator, EMDMSchedule, dict[str, Any], dict[str, Any]]:
    """``[--raw] [key=value ...]`` parsed (``doc``'s first paragraph as the description): the generator of
    ``paths.artifacts/<stage>`` (its EMA weights unless ``--raw``), its schedule and loop config, and the params."""
    parser = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    parser.add_argument("--raw", action="store_true", help="the raw weights instead of the EMA")
    parser.add_argument("overrides", nargs="*")
    args = parser.parse_args()
    params = load_params(args.overrides)
    return *load_emdm(artifacts_dir(params) / stage, use_ema=not args.raw), params


def main() -> None:
    generator, schedule, config, _ = load_from_command_line(__doc__, TRAIN_STAGE)
    reads_words = generator.config.word_tokens
    data = MotionTextDataset(config["features_dir"], "val", config["mean"], config["std"], 196,
                             word_tokens=config["max_text_tokens"] if reads_words else 0)
    batch = collate_trimmed_words([data[i] for i in range(min(32, len(data)))])
    x0, lengths, text = batch["motion"], batch["length"], batch["text"]
    words = (batch["tokens"], batch["token_mask"]) if reads_words else None
    valid = (torch.arange(x0.shape[1])[None] < lengths[:, None])[..., None]
    count = valid.sum() * x0.shape[-1]
    rng = torch.Generator().manual_seed(0)
    print("| level k | alpha_bar | MSE | linear estimate |\n|---|---|---|---|")
    with torch.inference_mode():
        for k in range(1, schedule.num_steps + 1):
            x_k = torch.where(valid, schedule.q_sample(x0, k, torch.randn(x0.shape, generator=rng)), 0.0)
            z = torch.randn(x0.shape[0], generator.config.z_dim, generator=rng)
            pred = generator(x_k, torch.full((x0.shape[0],), k - 1), z, text, lengths, words=words)
            ab = float(schedule.alphas_cumprod[k])
            mse = float(((pred - x0) ** 2 * valid).sum() / count)
            linear = float(((ab**0.5 * x_k - x0) ** 2 * valid).sum() / count)
            print(f"| {k} | {ab:.4f} | {mse:.3f} | {linear:.3f} |")


if __name__ == "__main__":
    main()
