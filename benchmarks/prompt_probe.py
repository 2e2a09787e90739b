"""What a trained generator does with the README's five prompts, measured on its joints.

    python benchmarks/prompt_probe.py --model emdm [--seeds 4] [--length 120] [--render out/] [key=value ...]

For each prompt and seed the motion's global joints (metres, y up) give: ``travel`` (horizontal
distance of the pelvis from the first to the last frame), ``airborne`` (frames with both feet at
least 5 cm above the floor, the 10th percentile of the lowest foot's height over the motion),
``wrist_up`` (frames with the right wrist above the head), ``drop`` (standing pelvis height minus
the lowest pelvis height), ``turn`` (heading change from the first to the last frame, degrees,
from the hip axis). Jittery motion inflates ``airborne``: read it with the rendered strips. Each
prompt has a pass criterion on these; the table prints every seed's measures and the pass count.
``--render`` writes a frame strip (PNG) per prompt (seed 0) to look at.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from data.joint_measures import HEAD, L_HIP, LEFT_FOOT, PELVIS, R_HIP, R_WRIST, RIGHT_FOOT  # noqa: E402
from data.render import render_strip  # noqa: E402
from data.skeleton import HUMANML3D  # noqa: E402
from pipelines.cli import artifacts_dir, repo_path  # noqa: E402
from pipelines.config import load_params  # noqa: E402
from pipelines.registry import EvalContext, GenerateOptions, family  # noqa: E402


def measures(joints: np.ndarray) -> dict[str, float]:
    """The probe's measures of one motion's global joints (T, 22, 3)."""
    pelvis = joints[:, PELVIS]
    left, right = joints[:, LEFT_FOOT, 1].min(1), joints[:, RIGHT_FOOT, 1].min(1)
    floor = np.percentile(np.minimum(left, right), 10)  # robust to a few jittery frames
    hips = joints[:, L_HIP] - joints[:, R_HIP]
    heading = np.arctan2(hips[:, 0], hips[:, 2])
    turn = np.degrees(np.abs(np.angle(np.exp(1j * (heading[-1] - heading[0])))))
    return {
        "travel": float(np.linalg.norm(pelvis[-1, [0, 2]] - pelvis[0, [0, 2]])),
        "airborne": float(((left > floor + 0.05) & (right > floor + 0.05)).sum()),
        "wrist_up": float((joints[:, R_WRIST, 1] > joints[:, HEAD, 1]).sum()),
        "drop": float(max(pelvis[0, 1], pelvis[-1, 1]) - pelvis[:, 1].min()),
        "turn": float(turn),
    }


#: prompt -> (criterion text, test on the measures)
PROMPTS = {
    "a person walks forward": ("travel >= 1 m", lambda m: m["travel"] >= 1.0),
    "a person jumps in place": ("airborne >= 5 frames, travel < 1 m",
                                lambda m: m["airborne"] >= 5 and m["travel"] < 1.0),
    "someone waves with the right hand": ("wrist above head >= 10 frames", lambda m: m["wrist_up"] >= 10),
    "a person walks forward then turns around": ("travel >= 0.5 m, turn >= 120 deg",
                                                 lambda m: m["travel"] >= 0.5 and m["turn"] >= 120),
    "a person squats down and stands up": ("pelvis drop >= 0.25 m", lambda m: m["drop"] >= 0.25),
}


def probe_parser(doc: str) -> argparse.ArgumentParser:
    """A probe script's parser: its docstring's first paragraph, ``--render DIR`` and params overrides."""
    parser = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    parser.add_argument("--render", type=Path, default=None, help="folder for frame strips to look at")
    parser.add_argument("overrides", nargs="*", help="params overrides, e.g. paths.artifacts=elsewhere")
    return parser


def eval_context(overrides: list[str]) -> EvalContext:
    """The trained models and feature store that ``params.yaml`` plus ``overrides`` point at."""
    params = load_params(overrides)
    return EvalContext(params, artifacts_dir(params), repo_path(params, "features.out"))


def main() -> None:
    parser = probe_parser(__doc__)
    parser.add_argument("--model", required=True)
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--length", type=int, default=120)
    args = parser.parse_args()
    ctx = eval_context(args.overrides)
    generator = family(args.model).build_generator(ctx, GenerateOptions())
    store = ctx.store
    texts = list(PROMPTS)
    batch = store.encode_prompts(texts)
    lengths = np.full(len(texts), args.length)
    print(f"| {generator.name} | criterion | " + " | ".join(f"seed {s}" for s in range(args.seeds)) + " | pass |")
    print("|---|---|" + "---|" * args.seeds + "---|")
    results = {text: [] for text in texts}
    for seed in range(args.seeds):
        motions = store.to_joints(generator.sample(batch, lengths, seed), lengths)
        for k, (text, joints) in enumerate(zip(texts, motions, strict=True)):
            results[text].append(measures(joints))
            if args.render is not None and seed == 0:
                args.render.mkdir(parents=True, exist_ok=True)
                render_strip(joints, args.render / f"{args.model}_{k}.png", text, HUMANML3D)
    total = 0
    for text, (criterion, test) in PROMPTS.items():
        cells = [" ".join(f"{key[:4]} {value:.2f}" if key in ("travel", "drop") else f"{key[:4]} {value:.0f}"
                          for key, value in m.items()) for m in results[text]]
        passed = sum(test(m) for m in results[text])
        total += passed
        print(f"| {text} | {criterion} | " + " | ".join(cells) + f" | {passed}/{args.seeds} |")
    print(f"\n{total}/{len(texts) * args.seeds} pass")


if __name__ == "__main__":
    main()
