"""EMDM-action scored on one split, with what the recogniser calls each action.

    python benchmarks/action_scores.py [--split val|test] [--replications R] [key=value ...]

Runs the action-to-motion protocol (:func:`pipelines.action_evaluation.evaluate_action_rows`) on
``--split``'s action-labelled clips, without the ``Real-action`` row: with ``--split test`` and the
evaluation's replications it gives the ``EMDM-action`` row of ``eval_emdm-action``. Then, over the
same draws, each action's accuracy and the labels its samples were given most often. The
validation split has few labelled clips, so its figures move more between draws.
"""

from __future__ import annotations

import sys
from collections import Counter
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from prompt_probe import eval_context, probe_parser  # noqa: E402

from pipelines.action_evaluation import (  # noqa: E402
    draw_actions,
    evaluate_action_rows,
    generator_ids,
    labelled_items,
    load_recogniser,
    recognise,
    renormalise,
)
from pipelines.emdm_family import emdm_action_rows  # noqa: E402


def main() -> None:
    parser = probe_parser(__doc__)
    parser.add_argument("--split", choices=("val", "test"), default="test")
    parser.add_argument("--replications", type=int, default=None, help="default: evaluate.replications")
    args = parser.parse_args()
    ctx = eval_context(args.overrides)
    reps = args.replications or int(ctx.params["evaluate"]["replications"])
    seed = int(ctx.params["evaluate"]["seed"])
    [row] = emdm_action_rows(ctx)
    recogniser = load_recogniser(ctx.trained("train_evaluator_recogniser"))
    with torch.inference_mode():
        table = evaluate_action_rows([row], ctx.store, recogniser, reps, seed, real=False, split=args.split)
    scores = table[row.name]
    print(f"{row.name} on {args.split} ({reps} replications): accuracy {scores['Accuracy']:.3f} "
          f"± {scores['Accuracy_ci']:.3f}, FID {scores['FID']:.2f} ± {scores['FID_ci']:.2f}")

    # The protocol's draws again (same seeds), keeping each sample's predicted label.
    items = labelled_items(ctx.store.split(args.split), recogniser.config.classes)
    mean, std = np.asarray(ctx.store.mean, np.float32), np.asarray(ctx.store.std, np.float32)
    r_mean, r_std = recogniser.mean.cpu().numpy(), recogniser.std.cpu().numpy()
    called: dict[str, Counter] = {}
    for r in range(reps):
        draw = draw_actions(items, recogniser, np.random.default_rng([seed, r]))
        with torch.inference_mode():
            x = row.sample_actions(generator_ids(row, draw.actions), draw.lengths.copy(), seed=r)
        _, logits = recognise(recogniser, renormalise(x, mean, std, r_mean, r_std), draw.lengths)
        for action, k in zip(draw.actions, logits.argmax(-1), strict=True):
            called.setdefault(action, Counter())[recogniser.config.classes[k]] += 1
    print("\n| action | samples | accuracy | recognised as (most often) |\n|---|---|---|---|")
    for action in sorted(called):
        n = sum(called[action].values())
        top = ", ".join(f"{label} {count}" for label, count in called[action].most_common(3))
        print(f"| {action} | {n} | {called[action][action] / n:.2f} | {top} |")


if __name__ == "__main__":
    main()
