"""MotionDiffuse's fine-grained control, measured on the joints: the body-part and time-varied demos.

    python benchmarks/motiondiffuse_control.py [--seeds 4] [--first-seed 0] [--guidance W] [--render out/] [k=v ...]

- Body parts (Eq. 10): upper body "a person waves with the right hand", lower body "a person walks
  forward", 120 frames. Pass: the pelvis travels >= 1.5 m and the right wrist is above the head for
  >= 20 frames.
- Time-varied (Eq. 11): "a person walks forward" on frames 0-60, "a person jumps in place" on
  60-120. Pass: the pelvis travels >= 0.5 m in the first segment, and both feet are off the floor
  (>= 5 cm above the floor, as benchmarks/prompt_probe.py) for >= 5 frames of the second.

Sampled with the trained model's DDPM (1000 steps; ``--steps K`` for DDIM with K steps), each part or
segment guided with ``--guidance`` (default: ``sample.motiondiffuse_guidance``). Each seed draws
``--batch`` motions (one noise draw of B motions; default 1, the demo); the table prints per seed
the passes and the median measures, the last line the pass rates over all motions. ``--velocities
joint`` gives each joint's velocity features to the joint's part, as the masks did before
2026-12-04 (an ablation; the model's masks give every joint's velocity to the part that holds the
root, :func:`models.motiondiffuse.part_feature_mask`). ``--render`` writes a frame strip per demo
(the first motion of the first seed).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from prompt_probe import eval_context, measures, probe_parser  # noqa: E402

from data.render import render_strip  # noqa: E402
from data.skeleton import HUMANML3D  # noqa: E402
from models.motiondiffuse import PART_JOINTS, PART_UNIONS, joint_feature_indices, part_feature_mask  # noqa: E402
from pipelines.motiondiffuse_family import sample_body_parts, sample_time_varied  # noqa: E402
from pipelines.registry import GenerateOptions, family  # noqa: E402

LENGTH = 120
WAVE, WALK, JUMP = "a person waves with the right hand", "a person walks forward", "a person jumps in place"


def _median(ms: list[dict[str, float]], key: str) -> float:
    return float(np.median([m[key] for m in ms]))


def upper_mask(velocities: str) -> torch.Tensor:
    """The upper body's feature mask: the model's (``"root"``: no velocity dims) or, for ``"joint"``, plus
    the velocity dims of its own joints (the masks before 2026-12-04)."""
    mask = part_feature_mask("upper")
    if velocities == "joint":
        for atom in PART_UNIONS["upper"]:
            for joint in PART_JOINTS["humanml3d"][atom]:
                mask[joint_feature_indices(joint)] = True  # its position, rotation and velocity dims
    return mask


def main() -> None:
    parser = probe_parser(__doc__)
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--batch", type=int, default=1, help="motions per seed (default 1, the demo)")
    parser.add_argument("--steps", type=int, default=None, help="DDIM steps (default: DDPM over all T steps)")
    parser.add_argument("--guidance", type=float, default=None)
    parser.add_argument("--velocities", choices=("root", "joint"), default="root",
                        help="the part that owns the joint velocity features in the body-part demo")
    args = parser.parse_args()
    ctx = eval_context(args.overrides)
    row = family("motiondiffuse").build_generator(ctx, GenerateOptions(steps=args.steps, guidance=args.guidance))
    store = ctx.store
    text = {t: store.encode_prompts([t] * args.batch) for t in (WAVE, WALK, JUMP)}
    upper = upper_mask(args.velocities)
    lengths = [LENGTH] * args.batch
    part_pass = segment_pass = 0
    print(f"{row.name}, {args.batch} motion(s) per seed, velocities: {args.velocities}\n"
          "| seed | body parts: passes; travel (m), wrist above head (frames) | time-varied: passes; walk travel (m), "
          "jump airborne (frames) |\n|---|---|---|")
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        parts = store.to_joints(sample_body_parts(row, [(upper, text[WAVE]), (~upper, text[WALK])], LENGTH, seed),
                                lengths)
        segments = store.to_joints(sample_time_varied(row, [(0, 60, text[WALK]), (60, LENGTH, text[JUMP])], LENGTH,
                                                      seed), lengths)
        p = [measures(joints) for joints in parts]
        walk, jump = [measures(j[:60]) for j in segments], [measures(j[60:]) for j in segments]
        part_ok = sum(m["travel"] >= 1.5 and m["wrist_up"] >= 20 for m in p)
        segment_ok = sum(w["travel"] >= 0.5 and j["airborne"] >= 5 for w, j in zip(walk, jump, strict=True))
        part_pass += part_ok
        segment_pass += segment_ok
        print(f"| {seed} | {part_ok}/{args.batch}; {_median(p, 'travel'):.2f}, {_median(p, 'wrist_up'):.0f} | "
              f"{segment_ok}/{args.batch}; {_median(walk, 'travel'):.2f}, {_median(jump, 'airborne'):.0f} |")
        if args.render is not None and seed == args.first_seed:
            args.render.mkdir(parents=True, exist_ok=True)
            render_strip(parts[0], args.render / "body_parts.png", f"upper: {WAVE} / lower: {WALK}", HUMANML3D)
            render_strip(segments[0], args.render / "time_varied.png", f"0-60: {WALK} / 60-120: {JUMP}", HUMANML3D)
    total = args.seeds * args.batch
    print(f"\nbody parts: {part_pass}/{total} pass; time-varied: {segment_pass}/{total} pass")


if __name__ == "__main__":
    main()
