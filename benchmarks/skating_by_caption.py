"""Foot skating and pelvis speed of the test motions a caption's words pick, real, through the VAE and generated.

    python benchmarks/skating_by_caption.py [key=value ...] [--words walk forward] [--models mld motionlcm]

The evaluation's skating column averages over every test motion, most of which barely move their
feet. This splits the test split in two: the motions with a caption holding every one of
``--words`` (as substrings, lower case) and the rest. For each group it prints the foot skating
ratio (:func:`data.physics.foot_skating_ratio`) and the mean horizontal pelvis speed (m/s) of the
real motions, of their round trip through the motion VAE (posterior mean), and of each
``--models`` generator (``stages.generate``'s, defaults) given each motion's first matching caption
(the rest: its first caption) and its length, in one batch per group, seed 0. Then, per group, where
the VAE's round trip skates, what the real motion does there (:func:`skating_causes`). Used for
docs/findings.md.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from data.motion_dataset import pad_motions  # noqa: E402
from data.physics import SKATE_HEIGHT_M, SKATE_SPEED_MPS, foot_skating_ratio, skating_toes, toe_tracks  # noqa: E402
from data.skeleton import Skeleton, get_skeleton  # noqa: E402
from pipelines.cli import artifacts_dir, repo_path  # noqa: E402
from pipelines.config import load_params  # noqa: E402
from pipelines.mld_family import VAEReconstruction, load_vae  # noqa: E402
from pipelines.registry import EvalContext, GenerateOptions, family  # noqa: E402


def first_match(captions: Sequence[str], words: Sequence[str]) -> str | None:
    """The first caption holding every word (lower case substrings), or None."""
    for caption in captions:
        if all(word.lower() in caption.lower() for word in words):
            return caption
    return None


def group_measures(joints: Sequence[np.ndarray], skeleton: Skeleton) -> dict[str, float]:
    """Mean foot skating ratio and mean horizontal pelvis speed (m/s) over motions (T_i, J, 3)."""
    speeds = [np.linalg.norm(np.diff(j[:, 0, [0, 2]], axis=0), axis=1).mean() * skeleton.fps for j in joints]
    return {"skating": float(np.mean([foot_skating_ratio(j, skeleton) for j in joints])),
            "speed": float(np.mean(speeds))}


def skating_causes(real: Sequence[np.ndarray], recon: Sequence[np.ndarray], skeleton: Skeleton) -> dict[str, float]:
    """Where a reconstruction skates, what its real motion does, over paired motions (T_i, J, 3).

    ``planted``: share of the reconstruction's skating (toe, pair)s where the real toe is below the
    skating height and slower than the skating speed (the foot should stand); ``lifted``: where the
    real toe is above the height (a swinging foot kept too low). ``swing_height_real`` /
    ``swing_height_recon``: mean height (m) of the toes the real motion moves faster than the skating
    speed, in each. ``swing_low_real`` / ``swing_low_recon``: the share of those below the height.
    """
    planted = lifted = skating = 0
    swing_real, swing_recon = [], []
    for r, x in zip(real, recon, strict=True):
        (h_real, v_real), (h_recon, _) = toe_tracks(r, skeleton), toe_tracks(x, skeleton)
        h_real, h_recon = h_real[:-1], h_recon[:-1]  # at each pair's first frame
        skates = skating_toes(x, skeleton)
        skating += int(skates.sum())
        planted += int((skates & (h_real < SKATE_HEIGHT_M) & (v_real < SKATE_SPEED_MPS)).sum())
        lifted += int((skates & (h_real >= SKATE_HEIGHT_M)).sum())
        swinging = v_real > SKATE_SPEED_MPS
        swing_real.append(h_real[swinging])
        swing_recon.append(h_recon[swinging])
    a, b = np.concatenate(swing_real), np.concatenate(swing_recon)
    if a.size == 0:  # nothing in the real motions swings: no swing heights to compare
        a = b = np.full(1, np.nan)
    return {"planted": planted / max(skating, 1), "lifted": lifted / max(skating, 1),
            "swing_height_real": float(a.mean()), "swing_height_recon": float(b.mean()),
            "swing_low_real": float((a < SKATE_HEIGHT_M).mean()), "swing_low_recon": float((b < SKATE_HEIGHT_M).mean())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--words", nargs="+", default=["walk", "forward"])
    parser.add_argument("--models", nargs="*", default=["mld", "motionlcm"])
    parser.add_argument("overrides", nargs="*")
    args = parser.parse_args()
    swallowed = [arg for arg in args.words + args.models if "=" in arg]
    if swallowed:
        parser.error(f"{swallowed}: key=value overrides go before --words and --models")
    torch.set_num_threads(2)
    params = load_params(args.overrides)
    ctx = EvalContext(params, artifacts_dir(params), repo_path(params, "features.out"))
    skeleton = get_skeleton(params["data"]["skeleton"])
    items, motions = ctx.store.split("test"), ctx.store.normalised_motions("test")
    matched = [first_match(item.captions, args.words) for item in items]
    groups = {"matching": [k for k, c in enumerate(matched) if c is not None],
              "rest": [k for k, c in enumerate(matched) if c is None]}
    vae = VAEReconstruction(load_vae(ctx.trained("train_vae")))
    generators = {name: family(name).build_generator(ctx, GenerateOptions()) for name in args.models}
    for group, index in groups.items():
        lengths = np.array([len(motions[k]) for k in index])
        x = pad_motions([motions[k] for k in index], lengths)
        rows = {"real": ctx.store.to_joints(x, lengths),
                "VAE": ctx.store.to_joints(vae.reconstruct(x, lengths), lengths)}
        text = ctx.store.encode_prompts([matched[k] or items[k].captions[0] for k in index])
        for name, generator in generators.items():
            rows[name] = ctx.store.to_joints(generator.sample(text, lengths, 0), lengths)
        for row, joints in rows.items():
            print(json.dumps({"words": args.words, "group": group, "motions": len(index), "row": row,
                              **{key: round(value, 3) for key, value in group_measures(joints, skeleton).items()}}),
                  flush=True)
        causes = skating_causes(rows["real"], rows["VAE"], skeleton)
        print(json.dumps({"words": args.words, "group": group, "row": "VAE against real",
                          **{key: round(value, 3) for key, value in causes.items()}}), flush=True)


if __name__ == "__main__":
    main()
