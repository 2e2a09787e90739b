"""Stage ``eval_speed``: EMDM's and MotionDiffuse's inference speed side by side, in one process.

``python -m stages.speed [key=value ...]`` builds the generator rows named in ``speed.rows`` (by default
``EMDM-10`` and ``MotionDiffuse-1000``, the comparison of EMDM's Table D7) from the ``emdm`` and
``motiondiffuse`` families of the model registry and times them with
:func:`pipelines.speed.side_by_side`: the evaluation's timing (batch 1, warm, its timing draw of the
test split, ``evaluate.timing_sentences`` and ``timing_seconds``), in ``speed.rounds`` rounds whose row
order alternates. Their family stages time each row in its own run, hours apart; the ratio of two
rows is measured here. Writes, atomically, ``artifacts/eval/speed/metrics.json``:
``{row: {ms_per_frame, AITS_s, NFE, params_M, speedup, rounds}}`` (``speedup``: the slowest row's
ms/frame over the row's), which the report prints as its speed table, and ``protocol.json``
(:mod:`pipelines.tables`). If a family's training stage
trained nothing, the table is empty.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict
from typing import Any

import numpy as np

from data.atomic import atomic_directory, check_output
from data.skeleton import get_skeleton
from models.generator import Generator
from pipelines.checkpoint import skipped
from pipelines.cli import artifacts_dir, run_main
from pipelines.config import check_fields, check_keys, check_number, check_type
from pipelines.devices import deterministic_gpu, device_name
from pipelines.evaluation import EvalConfig, check_protocol, draw
from pipelines.registry import FAMILIES, EvalContext
from pipelines.speed import TIMED, side_by_side
from pipelines.tables import write_table

PARAMS = ("evaluate", "features.out", "data.skeleton", "paths.artifacts", "speed", "sample.device",
          *dict.fromkeys(key for name in TIMED for key in FAMILIES[name].params))
OUT = "speed"


def timing_section(params: dict[str, Any]) -> dict[str, Any]:
    """The ``evaluate`` section less its ``samples`` group: the fields of :class:`EvalConfig`."""
    return {key: value for key, value in params["evaluate"].items() if key != "samples"}


def check_section(params: dict[str, Any]) -> None:
    """The ``speed`` section (and ``evaluate``'s fields) checked before any work; a ValueError naming the
    key, its value and what is allowed."""
    check_type(params, "evaluate", "", kind=dict)
    check_fields(timing_section(params), EvalConfig, "evaluate")
    check_protocol(params["evaluate"])
    cfg = check_keys(params["speed"], "speed", ("rows", "rounds"))
    rows = cfg["rows"]
    if not isinstance(rows, list) or not all(isinstance(row, str) for row in rows) or len(rows) < 2:
        raise ValueError(f"speed.rows must be a list of two or more row names, got {rows!r}")
    if len(set(rows)) != len(rows):
        raise ValueError(f"speed.rows names a row twice: {rows!r}")
    check_number(cfg, "rounds", "speed", low=1, integer=True)


def run(params: dict[str, Any]) -> dict[str, dict[str, float]]:
    """Time ``speed.rows`` side by side and write ``artifacts/eval/speed``; returns the table."""
    artifacts = artifacts_dir(params)
    out = artifacts / "eval" / OUT
    check_output(out, owner="speed")
    untrained = [stage for name in TIMED for stage in FAMILIES[name].train_stages if skipped(artifacts / stage)]
    table: dict[str, dict[str, float]] = {}
    cfg = EvalConfig(**timing_section(params))
    test: list = []
    ctx = EvalContext.from_params(params)
    if untrained:
        print(f"eval_speed: no rows: {untrained[0]} trained nothing")
    else:
        test = ctx.store.split("test")
        wanted = params["speed"]["rows"]
        built = {row.name: row for name in TIMED for row in FAMILIES[name].build_rows(ctx)
                 if isinstance(row, Generator)}
        missing = [name for name in wanted if name not in built]
        if missing:
            raise ValueError(f"speed.rows: no generator row(s) {missing} in the families {list(TIMED)} "
                             f"(their rows: {sorted(built)})")
        d = draw(test, np.random.default_rng([cfg.seed, cfg.replications]), cfg.unit_length)
        with deterministic_gpu(ctx.device):
            table = side_by_side([built[name] for name in wanted], d, cfg,
                                 get_skeleton(params["data"]["skeleton"]).joints_num, params["speed"]["rounds"])
    with atomic_directory(out, owner="speed") as tmp:
        write_table(tmp, table, asdict(cfg) | {"device": device_name(ctx.device)}, len(test))
    return table


def main(argv: Sequence[str] | None = None) -> None:
    """``python -m stages.speed [key=value ...] [--cfg] [--help]``."""

    def run_and_print(params: dict[str, Any]) -> None:
        for name, t in run(params).items():
            print(f"eval_speed: {name} {t['ms_per_frame']:.3f} ms/frame, NFE {t['NFE']:.0f}, "
                  f"{t['params_M']:.2f} M parameters, {t['speedup']:.1f}x the slowest row's speed")

    run_main("eval_speed", run_and_print, PARAMS, argv, checks=[check_section])


if __name__ == "__main__":
    main()
