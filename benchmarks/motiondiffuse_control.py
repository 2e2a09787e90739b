"""MotionDiffuse's fine-grained control, measured on the joints: the body-part and time-varied demos.

    python benchmarks/motiondiffuse_control.py [--seeds 4] [--first-seed 0] [--guidance W] [--render out/] [k=v ...]

- Body parts (Eq. 10): upper body "a person waves with the right hand", lower body "a person walks
  forward", 120 frames. Pass: the pelvis travels >= 1.5 m and the right wrist is above the head for
  >= 20 frames.
- Time-varied (Eq. 11): "a person walks forward" on frames 0-60, "a person jumps in place" on
  60-120. Pass: the pelvis travels >= 0.5 m in the first segment, and both feet are off the floor
  (>= 5 cm above the floor, as benchmarks/prompt_probe.py) for >= 5 frames of the second.

Sampled with the trained model's DDPM (1000 steps), one seed per sample, each part or segment guided
with ``--guidance`` (default: ``sample.motiondiffuse_guidance``); the table prints each seed's measures.
``--render`` writes a frame strip per demo (the first seed).
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from prompt_probe import eval_context, measures, probe_parser  # noqa: E402

from data.render import render_strip  # noqa: E402
from data.skeleton import HUMANML3D  # noqa: E402
from pipelines.motiondiffuse_family import sample_body_parts, sample_time_varied  # noqa: E402
from pipelines.registry import GenerateOptions, family  # noqa: E402

LENGTH = 120
WAVE, WALK, JUMP = "a person waves with the right hand", "a person walks forward", "a person jumps in place"


def main() -> None:
    parser = probe_parser(__doc__)
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--guidance", type=float, default=None)
    args = parser.parse_args()
    ctx = eval_context(args.overrides)
    row = family("motiondiffuse").build_generator(ctx, GenerateOptions(guidance=args.guidance))
    store = ctx.store
    text = {t: store.encode_prompts([t]) for t in (WAVE, WALK, JUMP)}
    part_pass = segment_pass = 0
    print("| seed | body parts: travel (m), wrist above head (frames) | time-varied: walk travel (m), "
          "jump airborne (frames) |\n|---|---|---|")
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        parts = sample_body_parts(row, [("upper", text[WAVE]), ("lower", text[WALK])], LENGTH, seed)
        segments = sample_time_varied(row, [(0, 60, text[WALK]), (60, LENGTH, text[JUMP])], LENGTH, seed)
        joints_parts = store.to_joints(parts, [LENGTH])[0]
        joints_segments = store.to_joints(segments, [LENGTH])[0]
        p = measures(joints_parts)
        walk, jump = measures(joints_segments[:60]), measures(joints_segments[60:])
        part_ok = p["travel"] >= 1.5 and p["wrist_up"] >= 20
        segment_ok = walk["travel"] >= 0.5 and jump["airborne"] >= 5
        part_pass += part_ok
        segment_pass += segment_ok
        print(f"| {seed} | {p['travel']:.2f}, {p['wrist_up']:.0f} {'pass' if part_ok else 'fail'} | "
              f"{walk['travel']:.2f}, {jump['airborne']:.0f} {'pass' if segment_ok else 'fail'} |")
        if args.render is not None and seed == args.first_seed:
            args.render.mkdir(parents=True, exist_ok=True)
            render_strip(joints_parts, args.render / "body_parts.png", f"upper: {WAVE} / lower: {WALK}", HUMANML3D)
            render_strip(joints_segments, args.render / "time_varied.png", f"0-60: {WALK} / 60-120: {JUMP}",
                         HUMANML3D)
    print(f"\nbody parts: {part_pass}/{args.seeds} pass; time-varied: {segment_pass}/{args.seeds} pass")


if __name__ == "__main__":
    main()
