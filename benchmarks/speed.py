"""Inference speed of several families' rows side by side, in one process, on the evaluation's timing.

    python benchmarks/speed.py <family> [<family> ...] [--rows NAME ...] [--rounds 2] [key=value ...]

Each family's evaluation stage times its rows in its own run, so two rows' ms/frame can come from
different hours of a machine whose speed drifts (`benchmarks/machine.py`). This script builds the
named families' generator rows from ``paths.artifacts`` and times each one with the evaluation's own
:func:`pipelines.evaluation.time_generator` (batch 1, warm, the evaluation's timing draw of the test
split and ``evaluate.timing_sentences`` / ``evaluate.timing_seconds``), in ``--rounds`` rounds whose
row order alternates (A B, then B A, ...), and prints AITS and ms/frame per round, their means, and
each row's ms/frame ratio to the slowest row's. Overrides go before ``--rows``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from data.skeleton import get_skeleton  # noqa: E402
from models.generator import ControlledGenerator, Generator  # noqa: E402
from pipelines.cli import artifacts_dir, repo_path  # noqa: E402
from pipelines.config import load_params  # noqa: E402
from pipelines.evaluation import control_hint, draw, time_generator  # noqa: E402
from pipelines.registry import EvalContext, family  # noqa: E402
from stages.evaluate import eval_config  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("families", nargs="+", help="family names (e.g. emdm motiondiffuse), then key=value overrides")
    parser.add_argument("--rows", nargs="*", default=None, help="row names (default: every generator row)")
    parser.add_argument("--rounds", type=int, default=2, help="timing rounds, the row order alternating")
    args = parser.parse_args()
    names = [arg for arg in args.families if "=" not in arg]
    params = load_params([arg for arg in args.families if "=" in arg])
    cfg = eval_config(params["evaluate"])
    ctx = EvalContext(params, artifacts_dir(params), repo_path(params, "features.out"))
    rows = [row for name in names for row in family(name).build_rows(ctx)
            if isinstance(row, Generator) and (not args.rows or row.name in args.rows)]
    if not rows:
        raise SystemExit(f"no generator rows in {names} (rows {args.rows})")
    d = draw(ctx.store.split("test"), np.random.default_rng([cfg.seed, cfg.replications]), cfg.unit_length)
    joints = get_skeleton(params["data"]["skeleton"]).joints_num
    times: dict[str, list[dict[str, float]]] = {row.name: [] for row in rows}
    for r in range(args.rounds):
        for row in rows if r % 2 == 0 else rows[::-1]:
            hint = control_hint(d, row.control, cfg, cfg.replications, joints) \
                if isinstance(row, ControlledGenerator) else None
            t = time_generator(row, d, cfg.timing_sentences, hint, cfg.timing_seconds)
            times[row.name].append(t)
            print(f"round {r}: {row.name}: AITS {t['AITS_s']:.4f} s, {t['ms_per_frame']:.3f} ms/frame", flush=True)
    mean = {name: float(np.mean([t["ms_per_frame"] for t in ts])) for name, ts in times.items()}
    slowest = max(mean.values())
    for row in rows:
        print(f"{row.name}: {mean[row.name]:.3f} ms/frame (mean of {args.rounds}), NFE {row.nfe}, "
              f"{slowest / mean[row.name]:.1f}x faster than the slowest row")


if __name__ == "__main__":
    main()
