"""What the run-time safety checks cost a training stage, measured inside a real run.

Two checks run during training: the non-finite guard (``pipelines.runner.FiniteGuard``: every
step's losses and gradient norms, and every log row's window means) and the plain-type check of
every checkpoint and model before it is saved (``pipelines.checkpoint.check_plain``). This trains
one stage in-process on the feature store with the committed params (``--steps`` steps, a
checkpoint every ``--checkpoint-every``, outputs in a temporary folder), times every call of the
two checks, and prints their total as a share of the run's wall time. Both are measured in the
same run as the steps they guard, so the ratio does not depend on the machine's speed.

Usage: ``python benchmarks/guard_overhead.py [--stage train_vae] [--steps 200] [--checkpoint-every 50]``
(needs ``dvc repro extract_features``).
"""

from __future__ import annotations

import argparse
import importlib
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from pipelines import checkpoint, runner
from pipelines.config import read_params
from pipelines.stage import train


class Timer:
    """Wraps a function; adds up the wall time of its outermost calls (recursive calls count once)."""

    def __init__(self, fn: Callable[..., Any]) -> None:
        self.fn, self.seconds, self.calls, self.depth = fn, 0.0, 0, 0

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        self.depth += 1
        start = time.perf_counter()
        try:
            return self.fn(*args, **kwargs)
        finally:
            self.depth -= 1
            if self.depth == 0:
                self.seconds += time.perf_counter() - start
                self.calls += 1


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stage", default="train_vae", help="a training stage module with a STAGE (default train_vae)")
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--checkpoint-every", type=int, default=50)
    args = parser.parse_args(argv)
    stage = importlib.import_module(f"stages.{args.stage}").STAGE
    params = read_params()
    timers = {"FiniteGuard.add": Timer(runner.FiniteGuard.add), "FiniteGuard.check": Timer(runner.FiniteGuard.check),
              "check_plain": Timer(checkpoint.check_plain)}
    runner.FiniteGuard.add = lambda self, *a: timers["FiniteGuard.add"](self, *a)
    runner.FiniteGuard.check = lambda self, *a: timers["FiniteGuard.check"](self, *a)
    checkpoint.check_plain = timers["check_plain"]
    with tempfile.TemporaryDirectory() as tmp:
        params["paths"].update(artifacts=str(Path(tmp) / "artifacts"), ray_storage=str(Path(tmp) / "ray"))
        params["ray"].update(num_workers=0, checkpoint_every=args.checkpoint_every)
        params[args.stage]["loop"].update(max_steps=args.steps)
        start = time.perf_counter()
        train(stage, params)
        wall = time.perf_counter() - start
    checks = sum(t.seconds for t in timers.values())
    print(f"\n{args.stage}: {args.steps} steps in-process in {wall:.1f} s ({1000 * wall / args.steps:.1f} ms/step)")
    for name, t in timers.items():
        print(f"  {name:>18}: {t.calls:5d} calls, {1000 * t.seconds:8.2f} ms in all")
    print(f"  checks: {1000 * checks:.1f} ms = {100 * checks / wall:.3f} % of the run")


if __name__ == "__main__":
    main()
