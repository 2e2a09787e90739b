"""A trained family's rows scored on the validation split (what sweeps rank by), without the test set.

    python benchmarks/val_scores.py <family> [key=value ...] [--rows NAME] [--rows NAME ...] [--draws N]

One replication of the evaluation protocol on the ``val`` split (:func:`pipelines.validation.
generator_scores`): ``val_FID`` and ``val_R_precision_top3`` per row, with the evaluator of
``paths.artifacts``. Overrides pick the trained models, e.g. ``paths.artifacts=/tmp/probe``
(the evaluator is then read from there too: copy or link ``train_evaluator`` into it).

``--draws N`` repeats it with ``evaluate.seed`` = s, s + 1, ..., s + N - 1 (s: the configured seed) and
prints each draw, then the mean and its 95 % half-width as the evaluation's tables give them
(:func:`models.metrics.mean_and_ci`). On a small validation split one draw is noisy: compare two
settings by their means, and only by differences well above those intervals.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from models.generator import Generator  # noqa: E402
from models.metrics import mean_and_ci  # noqa: E402
from pipelines.cli import artifacts_dir, repo_path  # noqa: E402
from pipelines.config import load_params  # noqa: E402
from pipelines.registry import EvalContext, family  # noqa: E402
from pipelines.validation import generator_scores  # noqa: E402


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The family, the overrides and the rows, in any order: ``--rows`` takes one name and repeats, so an
    override after it stays an override (with ``nargs="*"`` it was taken as a row name, silently)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("family")
    parser.add_argument("--rows", action="append", default=None, metavar="NAME",
                        help="a row to score, repeatable (default: every generator row)")
    parser.add_argument("--draws", type=int, default=1, metavar="N",
                        help="draws with evaluate.seed, seed + 1, ...; prints their mean and 95%% half-width")
    parser.add_argument("overrides", nargs="*", help="params overrides, e.g. paths.artifacts=/tmp/probe")
    args = parser.parse_intermixed_args(argv)
    if args.draws < 1:
        parser.error(f"--draws must be >= 1, got {args.draws}")
    return args


def summary(name: str, fids: list[float], r3s: list[float]) -> str:
    """The line that sums up a row's draws: each score's mean and 95 % half-width (:func:`mean_and_ci`)."""
    (fid, fid_ci), (r3, r3_ci) = mean_and_ci(fids), mean_and_ci(r3s)
    return (f"{name}: {len(fids)} draws: val FID {fid:.3f} ± {fid_ci:.3f}, val R@3 {r3:.3f} ± {r3_ci:.3f} "
            "(mean ± 95 % half-width)")


def main() -> None:
    args = parse_args()
    params = load_params(args.overrides)
    ctx = EvalContext(params, artifacts_dir(params), repo_path(params, "features.out"))
    for row in family(args.family).build_rows(ctx):
        if not isinstance(row, Generator) or (args.rows and row.name not in args.rows):
            continue
        fids, r3s = [], []
        for draw in range(args.draws):
            seeded = params | {"evaluate": params["evaluate"] | {"seed": params["evaluate"]["seed"] + draw}}
            start = time.perf_counter()
            with torch.inference_mode():
                scores = generator_scores(seeded, row)
            fids.append(scores["val_FID"])
            r3s.append(scores["val_R_precision_top3"])
            print(f"{row.name}: val FID {fids[-1]:.3f}, val R@3 {r3s[-1]:.3f} (evaluate.seed "
                  f"{seeded['evaluate']['seed']}, {time.perf_counter() - start:.0f} s)")
        if args.draws > 1:
            print(summary(row.name, fids, r3s))


if __name__ == "__main__":
    main()
