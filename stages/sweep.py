"""``python -m stages.sweep <stage> [key=value ...]``: a Ray Tune sweep over a training stage.

The stage's module (``stages/<stage>.py``) provides ``sweep_target(params)``; the search
space is ``sweep.<stage>`` and the settings ``sweep.settings`` in params (see
:mod:`pipelines.sweep`). Overrides work as for every stage, e.g.::

    python -m stages.sweep train_evaluator sweep.settings.num_samples=8 \\
        'sweep.train_evaluator.lr=loguniform(1e-4, 1e-2)' scale=smoke

Trials are ranked by the stage's validation metric (``train_vae``: ``val_MPJPE_mm``;
``distill_lcm``, ``train_emdm``: ``val_FID``; ``train_evaluator``: ``val_R_precision_top3``) unless
``sweep.settings.metric`` names another. Before any work the stage's params and inputs are
checked and one trial must fit on the cluster. Writes ``artifacts/sweeps/<stage>/``
(results.parquet, results.md, best_params.yaml).

``--cfg`` (anywhere after the stage) runs every check that needs no Ray (params, space, settings,
inputs, output folder), prints the plan and exits without starting Ray. ``--help`` or ``-h``
(anywhere) prints this text and exits.

Exit status:

- 0: the sweep finished (failed trials are rows of the table);
- 1: every trial failed, the sweep was interrupted (run the same command again to resume
  it), or an input is missing (e.g. no feature store: ``dvc repro extract_features``);
- 2: a usage or configuration error, including a trial that cannot fit on the cluster
  (``ray.num_workers x ray.cpus_per_worker`` CPUs).
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Sequence
from typing import Any

from pipelines.cli import CFG_FLAG, HELP_FLAGS
from pipelines.config import REPO_ROOT, ConfigError, load_params
from pipelines.sweep import (
    ERROR,
    SweepConfigError,
    SweepError,
    SweepResult,
    SweepTarget,
    markdown_table,
    plan_sweep,
    run_sweep,
)

USAGE = "usage: python -m stages.sweep <stage> [key=value ...] [--cfg] [--help]"


def load_target(stage: str, params: dict[str, Any]) -> SweepTarget:
    """``stages.<stage>.sweep_target(params)``; SweepConfigError if the stage has none."""
    if not stage.isidentifier():
        raise SweepConfigError(f"{stage!r} is not a stage name")
    try:
        module = importlib.import_module(f"stages.{stage}")
    except ModuleNotFoundError as err:
        if err.name != f"stages.{stage}":
            raise
        raise SweepConfigError(f"no stage module stages/{stage}.py") from None
    if not hasattr(module, "sweep_target"):
        raise SweepConfigError(f"stage {stage!r} cannot be swept: stages/{stage}.py has no sweep_target(params)")
    if stage not in params:
        raise SweepConfigError(f"params have no {stage!r} section")
    return module.sweep_target(params)


def _report(result: SweepResult) -> None:
    """Print the outcome: best trial, its metric and where the outputs are."""
    failed = sum(row["status"] == ERROR for row in result.table)
    print(f"sweep: {len(result.table)} trial(s), {failed} failed; best {result.metric} "
          f"{result.best[result.metric]:.6g} (trial {result.best['trial_id']}) -> {result.out_dir}")


def main(argv: Sequence[str] | None = None) -> None:
    """Run the sweep; exit 1 if every trial failed or it was interrupted, 2 on a config error."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if any(arg in HELP_FLAGS for arg in argv):  # anywhere, e.g. `stages.sweep train_vae --help`
        print(__doc__.strip())
        return
    if not argv or "=" in argv[0] or argv[0].startswith("-"):
        sys.stderr.write(USAGE + "\n")
        sys.exit(2)
    stage, overrides = argv[0], [arg for arg in argv[1:] if arg != CFG_FLAG]
    try:
        params = load_params(overrides)
        if CFG_FLAG in argv:
            print(plan_sweep(load_target(stage, params), params, REPO_ROOT).describe())
            return
        result = run_sweep(load_target(stage, params), params, REPO_ROOT)
    except (ConfigError, SweepConfigError) as err:
        sys.stderr.write(f"sweep {stage}: {err}\n")
        sys.exit(2)
    except SweepError as err:
        columns = list(err.table[0]) if err.table else []
        sys.stderr.write(markdown_table(err.table, columns) if columns else "")
        sys.exit(f"sweep {stage}: {err}")
    except (ValueError, FileNotFoundError) as err:  # e.g. a missing feature store
        sys.exit(f"sweep {stage}: {err}")
    except KeyboardInterrupt:
        sys.exit(f"sweep {stage}: interrupted; run the same command again to resume")
    _report(result)


if __name__ == "__main__":
    main()
