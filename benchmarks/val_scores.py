"""A trained family's rows scored on the validation split (what sweeps rank by), without the test set.

    python benchmarks/val_scores.py <family> [key=value ...] [--rows NAME] [--rows NAME ...]

One replication of the evaluation protocol on the ``val`` split (:func:`pipelines.validation.
generator_scores`): ``val_FID`` and ``val_R_precision_top3`` per row, with the evaluator of
``paths.artifacts``. Overrides pick the trained models, e.g. ``paths.artifacts=/tmp/probe``
(the evaluator is then read from there too: copy or link ``train_evaluator`` into it).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from models.generator import Generator  # noqa: E402
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
    parser.add_argument("overrides", nargs="*", help="params overrides, e.g. paths.artifacts=/tmp/probe")
    return parser.parse_intermixed_args(argv)


def main() -> None:
    args = parse_args()
    params = load_params(args.overrides)
    ctx = EvalContext(params, artifacts_dir(params), repo_path(params, "features.out"))
    for row in family(args.family).build_rows(ctx):
        if not isinstance(row, Generator) or (args.rows and row.name not in args.rows):
            continue
        start = time.perf_counter()
        with torch.inference_mode():
            scores = generator_scores(params, row)
        print(f"{row.name}: val FID {scores['val_FID']:.3f}, val R@3 {scores['val_R_precision_top3']:.3f} "
              f"({time.perf_counter() - start:.0f} s)")


if __name__ == "__main__":
    main()
