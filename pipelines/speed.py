"""Inference speed of several generator rows side by side: one process, batch 1, alternating rounds.

Each family's evaluation stage times its own rows (``AITS_s``, ``ms_per_frame``), so two rows' figures
can come from different hours of a machine whose speed drifts (``benchmarks/machine.py``). A speed
ratio between families (EMDM against MotionDiffuse: EMDM Table D7, issue 17) is measured here instead:
:func:`side_by_side` times every row with the evaluation's own
:func:`pipelines.evaluation.time_generator` (batch 1, warm, loading excluded, the evaluation's timing
draw and ``evaluate.timing_sentences`` / ``timing_seconds``) in ``rounds`` rounds whose row order
alternates (A B, then B A, ...), so a drift of the machine's speed during the run weighs on every
row alike.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from models.generator import ControlledGenerator, Generator
from pipelines.evaluation import Draw, EvalConfig, control_hint, time_generator

#: The model families whose rows stage ``eval_speed`` times (their modules and params are its DVC deps).
TIMED = ("emdm", "motiondiffuse")


def parameter_count(row: Generator) -> int:
    """The parameters of the networks a row holds (the ``torch.nn.Module`` attributes of the row object,
    each parameter counted once). The frozen text encoder is not among them: rows receive encoded text,
    and every row shares the same encoder."""
    seen: dict[int, int] = {}
    for value in vars(row).values():
        if isinstance(value, torch.nn.Module):
            seen.update({id(p): p.numel() for p in value.parameters()})
    return sum(seen.values())


def side_by_side(rows: Sequence[Generator], d: Draw, cfg: EvalConfig, joints_num: int, rounds: int = 2
                 ) -> dict[str, dict[str, float]]:
    """Time ``rows`` on the draw ``d`` in ``rounds`` alternating rounds.

    Returns ``{row: {"ms_per_frame", "AITS_s", "NFE", "params_M", "speedup", "rounds"}}``: the means over
    the rounds, the row's NFE and parameter count (millions), and ``speedup``, the slowest row's
    ms/frame over this row's (1 for the slowest). A controlled row is timed with the evaluation's hints.
    """
    if rounds < 1:
        raise ValueError(f"rounds must be >= 1, got {rounds}")
    if len({row.name for row in rows}) != len(rows) or not rows:
        raise ValueError(f"side_by_side needs one or more rows with distinct names, got {[r.name for r in rows]}")
    timed: dict[str, list[dict[str, float]]] = {row.name: [] for row in rows}
    for r in range(rounds):
        for row in rows if r % 2 == 0 else rows[::-1]:
            hint = (control_hint(d, row.control, cfg, cfg.replications, joints_num)
                    if isinstance(row, ControlledGenerator) else None)
            timed[row.name].append(time_generator(row, d, cfg.timing_sentences, hint, cfg.timing_seconds))
    ms = {name: float(np.mean([t["ms_per_frame"] for t in ts])) for name, ts in timed.items()}
    slowest = max(ms.values())
    return {row.name: {"ms_per_frame": ms[row.name],
                       "AITS_s": float(np.mean([t["AITS_s"] for t in timed[row.name]])),
                       "NFE": float(row.nfe), "params_M": parameter_count(row) / 1e6,
                       "speedup": slowest / ms[row.name], "rounds": float(rounds)}
            for row in rows}
