"""Inference speed of several families' rows side by side, in one process, on the evaluation's timing.

    python benchmarks/speed.py <family> [<family> ...] [key=value ...] [--rows NAME ...] [--rounds 2]

The pipeline's ``eval_speed`` stage does this for EMDM and MotionDiffuse (``speed.rows``); this script
does it for any families: it builds the named families' generator rows from ``paths.artifacts`` and
times them with :func:`pipelines.speed.side_by_side` (the evaluation's timing, batch 1, rounds in
alternating row order), then prints each row's ms/frame, AITS, NFE, parameters and speed-up over the
slowest row. Overrides go before ``--rows``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from data.skeleton import get_skeleton  # noqa: E402
from models.generator import Generator  # noqa: E402
from pipelines.cli import artifacts_dir, repo_path  # noqa: E402
from pipelines.config import load_params  # noqa: E402
from pipelines.evaluation import draw  # noqa: E402
from pipelines.registry import EvalContext, family  # noqa: E402
from pipelines.speed import side_by_side  # noqa: E402
from stages.evaluate import eval_config  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("families", nargs="+", help="family names (e.g. emdm motiondiffuse), then key=value overrides")
    parser.add_argument("--rows", nargs="*", default=None, help="row names (default: every generator row)")
    parser.add_argument("--rounds", type=int, default=2, help="timing rounds, the row order alternating")
    args = parser.parse_args()
    if any("=" in row for row in args.rows or []):
        parser.error(f"--rows {args.rows}: key=value overrides go before --rows")
    names = [arg for arg in args.families if "=" not in arg]
    params = load_params([arg for arg in args.families if "=" in arg])
    cfg = eval_config(params["evaluate"])
    ctx = EvalContext(params, artifacts_dir(params), repo_path(params, "features.out"))
    rows = [row for name in names for row in family(name).build_rows(ctx)
            if isinstance(row, Generator) and (not args.rows or row.name in args.rows)]
    if not rows:
        raise SystemExit(f"no generator rows in {names} (rows {args.rows})")
    d = draw(ctx.store.split("test"), np.random.default_rng([cfg.seed, cfg.replications]), cfg.unit_length)
    table = side_by_side(rows, d, cfg, get_skeleton(params["data"]["skeleton"]).joints_num, args.rounds)
    for name, t in table.items():
        print(f"{name}: {t['ms_per_frame']:.3f} ms/frame, AITS {t['AITS_s']:.4f} s (means of {args.rounds} rounds), "
              f"NFE {t['NFE']:.0f}, {t['params_M']:.2f} M parameters, {t['speedup']:.1f}x faster than the slowest row")


if __name__ == "__main__":
    main()
