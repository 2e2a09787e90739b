"""Experiment tracking: progress lines, a rank-0 W&B run, and DVC metrics/plots files.

History rows are plain dicts such as ``{"step": 100, "epoch": 1, "lr": 3e-4,
"loss": 0.12, "steps_per_s": 41.0}``; every row that rank 0 logs becomes one line of the
loss-curve CSV and one point per series in the PNG.
"""

from __future__ import annotations

import csv
import json
import math
import os
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

#: The project checkout this module runs from (a temporary copy under ``dvc exp run --temp``).
CHECKOUT = Path(__file__).resolve().parents[1]

#: Columns of a history row that are bookkeeping, not curves to plot.
NON_CURVE_KEYS = frozenset({"step", "epoch", "lr", "steps_per_s", "samples_per_s", "time_s"})


def format_duration(seconds: float) -> str:
    """``3725`` -> ``"1h02m05s"``; ``65`` -> ``"1m05s"``; ``4.2`` -> ``"4s"``."""
    if not math.isfinite(seconds):
        return "?"
    s = int(round(max(0.0, seconds)))
    hours, rest = divmod(s, 3600)
    minutes, secs = divmod(rest, 60)
    if hours:
        return f"{hours}h{minutes:02d}m{secs:02d}s"
    return f"{minutes}m{secs:02d}s" if minutes else f"{secs}s"


class Progress:
    """Measures step rate between calls and formats one progress line per log interval."""

    def __init__(self, stage: str, start_step: int, max_steps: int) -> None:
        self.stage = stage
        self.max_steps = max_steps
        self._last_step = start_step
        self._last_time = time.perf_counter()

    def rate(self, step: int) -> float:
        """Steps per second since the previous call (the window restarts here)."""
        now = time.perf_counter()
        steps, elapsed = step - self._last_step, now - self._last_time
        self._last_step, self._last_time = step, now
        return steps / elapsed if elapsed > 0 and steps > 0 else float("nan")

    def line(self, step: int, rate: float, metrics: Mapping[str, float]) -> str:
        """``[stage] step 120/1000 (12.0%) loss=0.1234 lr=1.00e-04 | 3.50 step/s ETA 4m11s``."""
        pct = 100.0 * step / max(1, self.max_steps)
        shown = " ".join(f"{k}={_fmt(v)}" for k, v in metrics.items() if k not in NON_CURVE_KEYS)
        lr = f" lr={metrics['lr']:.2e}" if "lr" in metrics else ""
        eta = format_duration((self.max_steps - step) / rate) if rate and rate > 0 else "?"
        return (
            f"[{self.stage}] step {step}/{self.max_steps} ({pct:.1f}%) {shown}{lr} | "
            f"{rate:.2f} step/s ETA {eta}"
        )


def _fmt(value: float) -> str:
    """Compact number formatting for progress lines."""
    return f"{value:.4g}" if isinstance(value, float) else str(value)


def start_wandb(
    *,
    rank: int,
    mode: str,
    project: str,
    name: str,
    group: str,
    config: Mapping[str, Any],
    directory: str | None,
) -> Any | None:
    """Start a W&B run on rank 0 only; None elsewhere or when ``mode == "disabled"``.

    ``ray.air.integrations.wandb.setup_wandb(rank_zero_only=True)`` does not guard ranks
    under Ray Train V2, hence this explicit check. ``wandb`` is imported lazily (0.7 s).
    """
    if rank != 0 or mode == "disabled":
        return None
    import wandb

    if directory:
        Path(directory).mkdir(parents=True, exist_ok=True)
    return wandb.init(
        project=project,
        name=name,
        group=group,
        config=dict(config),
        mode=mode,
        dir=directory,
        reinit="create_new",
    )


def write_metrics_json(path: Path, metrics: Mapping[str, Any]) -> None:
    """DVC metrics file (sorted keys, pretty-printed)."""
    Path(path).write_text(json.dumps(dict(metrics), indent=2, sort_keys=True) + "\n")


def history_columns(history: Sequence[Mapping[str, Any]]) -> list[str]:
    """Union of the rows' keys, ``step`` first, then in order of first appearance."""
    columns: dict[str, None] = {"step": None}
    for row in history:
        columns.update(dict.fromkeys(row))
    return list(columns)


def write_history_csv(path: Path, history: Sequence[Mapping[str, Any]]) -> None:
    """Loss curve as CSV (one row per logged step), for ``dvc plots``."""
    columns = history_columns(history)
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=columns, restval="")
        writer.writeheader()
        writer.writerows(history)


def plot_history_png(path: Path, history: Sequence[Mapping[str, Any]], title: str) -> None:
    """PNG of every curve in the history against step (``dvc plots`` HTML needs the web)."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    curves = [c for c in history_columns(history) if c not in NON_CURVE_KEYS]
    fig, ax = plt.subplots(figsize=(6, 4), dpi=100)
    for name in curves:
        points = [(r["step"], r[name]) for r in history if name in r]
        if points:
            ax.plot(*zip(*points, strict=True), label=name)
    values = [r[c] for r in history for c in curves if c in r]
    if values and min(values) > 0:
        ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    ax.set_title(title)
    if curves:
        ax.legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def default_wandb_dir(storage: str) -> str:
    """W&B's ``dir`` (W&B adds ``wandb/`` under it): the same folder for every kind of ``dvc exp run``.

    ``$WANDB_DIR`` if set; else a local Ray storage outside this checkout (a cluster's shared
    ``ray.storage``, which every node can reach); else the DVC workspace, where ``wandb sync`` finds
    the runs: ``$DVC_ROOT``, which DVC sets to the workspace also for ``dvc exp run --temp`` and
    ``--queue`` (they run in a temporary copy that is then deleted), or else this checkout.
    """
    if os.environ.get("WANDB_DIR"):
        return os.environ["WANDB_DIR"]
    if "://" not in storage and not Path(storage).resolve().is_relative_to(CHECKOUT):
        return storage
    return os.environ.get("DVC_ROOT") or str(CHECKOUT)
