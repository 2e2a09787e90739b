"""One EMDM-action sample per action class, rendered and recognised.

    python benchmarks/action_samples.py [--length 60] [--render out/] [key=value ...]

For each class the action-conditioned generator (``train_emdm_action``) draws one motion (seed 0);
the table gives the action recogniser's prediction and the pelvis travel; ``--render`` writes a
frame strip per class to look at.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from prompt_probe import eval_context, probe_parser  # noqa: E402

from data.render import render_strip  # noqa: E402
from data.skeleton import HUMANML3D  # noqa: E402
from pipelines.action_evaluation import load_recogniser, recognise  # noqa: E402
from pipelines.emdm_family import emdm_action_rows  # noqa: E402


def main() -> None:
    parser = probe_parser(__doc__)
    parser.add_argument("--length", type=int, default=60)
    args = parser.parse_args()
    ctx = eval_context(args.overrides)
    [row] = emdm_action_rows(ctx)
    recogniser = load_recogniser(ctx.trained("train_evaluator_recogniser"))
    ids = np.arange(len(row.classes))
    lengths = np.full(len(ids), args.length)
    x = row.sample_actions(ids, lengths, seed=0)
    raw = x * ctx.store.std + ctx.store.mean
    _, logits = recognise(recogniser, (raw - recogniser.mean.numpy()) / recogniser.std.numpy(), lengths)
    predicted = [recogniser.config.classes[k] for k in logits.argmax(-1)]
    print("| action | recognised as | pelvis travel (m) |\n|---|---|---|")
    for k, (action, joints) in enumerate(zip(row.classes, ctx.store.to_joints(x, lengths), strict=True)):
        travel = float(np.linalg.norm(joints[-1, 0, [0, 2]] - joints[0, 0, [0, 2]]))
        print(f"| {action} | {predicted[k]} | {travel:.2f} |")
        if args.render is not None:
            args.render.mkdir(parents=True, exist_ok=True)
            render_strip(joints, args.render / f"{action}.png", f"EMDM-action: {action}", HUMANML3D)
    print(f"\n{sum(p == a for p, a in zip(predicted, row.classes, strict=True))}/{len(ids)} recognised")


if __name__ == "__main__":
    main()
