"""``python -m pipelines.report_check [<eval dir>]``: the results table has every row.

The ``report`` stage merges ``<eval dir>/real/metrics.json`` and, for every model family of the
registry (:data:`pipelines.registry.FAMILIES`), ``<eval dir>/<family>/metrics.json`` (the rows its
``rows`` function builds, as its ``eval_<family>`` stage wrote them) into ``<eval dir>/metrics.json``.
This check fails (exit status 1, one line per problem on stderr) when a source has no table or an
empty one, one of its rows is missing from the merged table or differs there, or a row lacks its
protocol's core metrics or holds a value that is not a finite number, or when the side-by-side speed
table (``<eval dir>/speed/metrics.json``, stage ``eval_speed``) is missing, empty, or has a row without
its timing figures. CI runs it after the smoke
pipeline (``.ci/smoke``); the default ``<eval dir>`` is ``artifacts/eval``.
"""

from __future__ import annotations

import json
import math
import numbers
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from pipelines.registry import FAMILIES

#: The evaluation folders the report merges: the real motions, then every registered family.
SOURCES = ("real", *FAMILIES)
#: Metrics every row of the text-to-motion protocol has (pipelines/evaluation.py).
TEXT_METRICS = ("R_precision_top1", "R_precision_top2", "R_precision_top3", "FID", "MM_Dist", "Diversity")
#: Metrics every row of the action-to-motion protocol has (pipelines/action_evaluation.py).
ACTION_METRICS = ("Accuracy", "FID", "Diversity")
#: The side-by-side speed table (stages/speed.py) and the figures each of its rows has.
SPEED = "speed"
SPEED_METRICS = ("ms_per_frame", "AITS_s", "NFE", "params_M", "speedup")


def _read_table(path: Path, problems: list[str]) -> dict[str, dict[str, Any]] | None:
    """The ``{row: {metric: value}}`` table at ``path``, or None with a problem recorded."""
    try:
        table = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        problems.append(f"{path}: missing")
        return None
    except json.JSONDecodeError as err:
        problems.append(f"{path}: not valid JSON ({err})")
        return None
    if not isinstance(table, dict) or not all(isinstance(row, dict) for row in table.values()):
        problems.append(f"{path}: not a table of rows ({{row: {{metric: value}}}})")
        return None
    return table


def row_problems(name: str, metrics: dict[str, Any]) -> list[str]:
    """What is wrong with one merged row: missing core metrics, values that are not finite numbers."""
    required = ACTION_METRICS if "Accuracy" in metrics else TEXT_METRICS
    problems = [f"row {name!r} has no {key}" for key in required if key not in metrics]
    bad = [key for key, value in metrics.items()
           if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value)]
    if bad:
        problems.append(f"row {name!r}: not a finite number: {', '.join(f'{k}={metrics[k]!r}' for k in bad)}")
    return problems


def check_rows(eval_dir: Path) -> list[str]:
    """Every problem of ``eval_dir``'s merged table against its sources (empty: every row is there)."""
    problems: list[str] = []
    merged_path = Path(eval_dir) / "metrics.json"
    merged = _read_table(merged_path, problems)
    if merged is None:
        return problems
    for source in SOURCES:
        path = Path(eval_dir) / source / "metrics.json"
        table = _read_table(path, problems)
        if table is None:
            continue
        if not table:
            problems.append(f"{path}: no rows")
        for name, metrics in table.items():
            if name not in merged:
                problems.append(f"{merged_path}: row {name!r} of {source} is missing")
            elif merged[name] != metrics:
                problems.append(f"{merged_path}: row {name!r} differs from {path}")
    for name, metrics in merged.items():
        problems += [f"{merged_path}: {problem}" for problem in row_problems(name, metrics)]
    speed_path = Path(eval_dir) / SPEED / "metrics.json"
    speed = _read_table(speed_path, problems)
    if speed is not None and not speed:
        problems.append(f"{speed_path}: no rows")
    for name, metrics in (speed or {}).items():
        missing = [key for key in SPEED_METRICS if not _finite(metrics.get(key))]
        if missing:
            problems.append(f"{speed_path}: row {name!r} has no finite {', '.join(missing)}")
    return problems


def _finite(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)


def main(argv: Sequence[str] | None = None) -> None:
    """Check ``argv[0]`` (default ``artifacts/eval``); exit 1 with one line per problem."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if len(argv) > 1 or (argv and argv[0].startswith("-")):
        sys.exit("usage: python -m pipelines.report_check [<eval dir>]")
    eval_dir = Path(argv[0] if argv else "artifacts/eval")
    problems = check_rows(eval_dir)
    if problems:
        sys.stderr.write("".join(f"report check: {problem}\n" for problem in problems))
        sys.exit(1)
    rows = len(json.loads((eval_dir / "metrics.json").read_text(encoding="utf-8")))
    print(f"report check: {rows} rows from {len(SOURCES)} evaluation stages in {eval_dir / 'metrics.json'}")


if __name__ == "__main__":
    main()
