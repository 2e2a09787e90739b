"""Where EMDM-action loses the action: the recogniser on reverse chains started part-way.

    python benchmarks/emdm_action_levels.py [--raw] [key=value ...]

The labelled test motions (one crop each, the action protocol's first draw) are noised to level k
(k = 0..T) and denoised by the action-conditioned generator (``train_emdm_action``) from there: for
t = k-1..0 a fresh z, the guided x0 (``sample.emdm_action_guidance``) and the posterior sample, the last
step returning x0 itself, as :func:`models.emdm.sample_emdm` does from k = T. The table gives the
action recogniser's accuracy on the result, its feature MSE to the real crops (normalised) and its
jitter (the mean length of the joints' second difference over time, m per frame squared, over each
crop's own frames) with its seam ratio (with G's frame patches of P frames, the mean acceleration
centred on the two frames either side of a patch boundary over that centred on the frames inside a
patch; 1 when a boundary is not special), and, for the lowest levels, the accuracy and jitter of the
noisy x_k itself and of the generator's input skip alone (what G adds on top of it). k = T is the
evaluation's sampling; k = 0 is the real crops.
``--raw``: the raw weights instead of the EMA.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))  # the sibling benchmark emdm_levels, also when imported

from contrasts import jitter  # noqa: E402
from emdm_levels import load_from_command_line  # noqa: E402

from models.emdm import EMDMGenerator, EMDMSchedule, guided_x0  # noqa: E402
from pipelines.action_evaluation import (  # noqa: E402
    draw_actions,
    labelled_items,
    load_recogniser,
    recognise,
    renormalise,
)
from pipelines.cli import artifacts_dir, repo_path  # noqa: E402
from pipelines.emdm_family import ACTION_STAGE  # noqa: E402
from pipelines.feature_store import FeatureStore  # noqa: E402


def chain_from(generator: EMDMGenerator, schedule: EMDMSchedule, x_k: torch.Tensor, k: int, ids: torch.Tensor,
               lengths: torch.Tensor, valid: torch.Tensor, guidance: float, rng: torch.Generator) -> torch.Tensor:
    """Algorithm 1 from level ``k`` instead of T: x_k (B, N, D) -> x0 (padded frames 0)."""
    x = x_k
    for t in range(k - 1, -1, -1):
        z = torch.randn(x.shape[0], generator.config.z_dim, generator=rng)
        x0_hat = guided_x0(generator, x, t, z, ids, lengths, guidance)
        x = x0_hat if t == 0 else schedule.posterior_sample(x0_hat, x, t, torch.randn(x.shape, generator=rng))
        x = torch.where(valid, x, 0.0)
    return x


def crop_jitter(joints: np.ndarray, lengths: np.ndarray) -> float:
    """Mean over crops (B, T, J, 3) of :func:`contrasts.jitter` (m per frame squared), each crop read up to
    its own length (crops of fewer than 3 frames are skipped)."""
    return float(np.mean([jitter(j[:n]) for j, n in zip(joints, lengths, strict=True) if n >= 3]))


def seam_ratio(joints: np.ndarray, lengths: np.ndarray, patch: int) -> float:
    """Over crops (B, T, J, 3) read to their own lengths: the mean second-difference length centred on frames
    n with n mod P in {P - 1, 0} (either side of a patch boundary) over that on the other frames (P > 2)."""
    seam, inside = [], []
    for j, n in zip(joints, lengths, strict=True):
        acc = np.linalg.norm(np.diff(j[:n], 2, axis=0), axis=-1).mean(-1)  # centred on frames 1 .. n - 2
        phase = np.arange(1, n - 1) % patch
        at_seam = (phase == 0) | (phase == patch - 1)
        seam.append(acc[at_seam])
        inside.append(acc[~at_seam])
    return float(np.concatenate(seam).mean() / np.concatenate(inside).mean())


def main() -> None:
    torch.set_num_threads(2)
    generator, schedule, config, params = load_from_command_line(__doc__, ACTION_STAGE)
    store = FeatureStore(repo_path(params, "features.out"))
    recogniser = load_recogniser(artifacts_dir(params) / "train_evaluator_recogniser")
    items = labelled_items(store.split("test"), recogniser.config.classes)
    draw = draw_actions(items, recogniser, np.random.default_rng([0, 0]), 4)
    mean, std = np.asarray(store.mean, np.float32), np.asarray(store.std, np.float32)
    r_mean, r_std = recogniser.mean.numpy(), recogniser.std.numpy()
    lengths = torch.as_tensor(draw.lengths)
    valid = (torch.arange(draw.real.shape[1])[None] < lengths[:, None])[..., None]
    x0 = torch.where(valid, torch.from_numpy(((draw.real - mean) / std).astype(np.float32)), 0.0)
    ids = torch.as_tensor([config["classes"].index(a) for a in draw.actions])
    guidance = float(params["sample"]["emdm_action_guidance"])

    def accuracy(x: torch.Tensor) -> float:
        _, logits = recognise(recogniser, renormalise(x.numpy(), mean, std, r_mean, r_std), draw.lengths)
        return float((logits.argmax(-1) == draw.labels).mean())

    def joints(x: torch.Tensor) -> np.ndarray:
        return recogniser.joints(torch.as_tensor(renormalise(x.numpy(), mean, std, r_mean, r_std))).numpy()

    def jitter(x: torch.Tensor) -> float:
        return crop_jitter(joints(x), draw.lengths)

    patch = generator.config.patch_frames

    def rough(x: torch.Tensor) -> str:
        """Jitter and seam ratio, one joint recovery."""
        joints_x = joints(x)
        ratio = f"{seam_ratio(joints_x, draw.lengths, patch):.2f}" if patch > 2 else "–"
        return f"{crop_jitter(joints_x, draw.lengths):.4f} | {ratio}"

    def mse(x: torch.Tensor) -> float:
        return float(((x - x0) ** 2 * valid).sum() / (valid.sum() * x0.shape[-1]))

    rng = torch.Generator().manual_seed(0)
    print(f"{len(draw.lengths)} labelled test crops, guidance {guidance}\n")
    print("| start level k | alpha_bar_k | accuracy ↑ | feature MSE ↓ | jitter (m/frame²) | seam ratio | x_k alone: "
          "accuracy, jitter | input skip alone: accuracy, jitter |")
    print("|---|---|---|---|---|---|---|---|")
    with torch.inference_mode():
        for k in range(schedule.num_steps + 1):
            x_k = torch.where(valid, schedule.q_sample(x0, k, torch.randn(x0.shape, generator=rng)), 0.0) if k else x0
            out = chain_from(generator, schedule, x_k, k, ids, lengths, valid, guidance, rng)
            alone = skip = "–"
            if 0 < k <= 3:
                alone = f"{accuracy(x_k):.3f}, {jitter(x_k):.4f}"
                if generator.config.input_skip:
                    steps = torch.full((x0.shape[0],), k - 1)
                    skipped = torch.where(valid, generator.skipped(x_k, steps, valid[..., 0]), 0.0)
                    skip = f"{accuracy(skipped):.3f}, {jitter(skipped):.4f}"
            ab = float(schedule.alphas_cumprod[k])
            print(f"| {k} | {ab:.4f} | {accuracy(out):.3f} | {mse(out):.3f} | {rough(out)} | {alone} | {skip} |",
                  flush=True)


if __name__ == "__main__":
    main()
