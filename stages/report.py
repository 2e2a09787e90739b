"""Stage ``report``: the evaluation stages' rows merged into the one results table.

``python -m stages.report [key=value ...]`` reads ``artifacts/eval/real/`` and
``artifacts/eval/<family>/`` for every family of the model registry and writes
``artifacts/eval/metrics.json`` (``{row: {metric: value}}``, the rows in registry order after
``Real``), and ``artifacts/eval/speed/`` (stage ``eval_speed``: the rows timed side by side),
``summary.json`` (its headline figures, the DVC metrics file), ``report.md`` (the
paper-style table, also printed), ``fid_vs_time.png``, ``samples/`` (every family's rendered sample
animations) and ``report.html`` (the tables, the plot and the samples in one self-contained page that
opens offline). Each file is replaced atomically. It refuses folders scored with other evaluation
settings than ``artifacts/eval/real/`` (their ``protocol.json``, :mod:`pipelines.tables`).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from data.atomic import atomic_directory, check_output, replace_file
from pipelines.cli import artifacts_dir, run_main
from pipelines.registry import FAMILIES
from pipelines.report import merge_tables, plot_fid_vs_time, report_markdown
from pipelines.report_html import report_html
from pipelines.tables import check_protocols, read_json, read_table

PARAMS = ("paths.artifacts",)
SOURCES = ("real", *FAMILIES)
SPEED = "speed"  # stages/speed.py's folder
#: The files the report writes in ``artifacts/eval`` (beside the ``samples`` folder).
OUTPUTS = ("metrics.json", "summary.json", "report.md", "fid_vs_time.png", "report.html")

#: The figures ``summary.json`` keeps, ``(row, metric)``: the evaluator's R-precision on real motions,
#: the FID of each text family's headline row, and the action family's accuracy and FID (in the action
#: recogniser's features). Few enough for one line of ``dvc metrics show`` and ``dvc exp show``; the
#: whole table is ``metrics.json``.
SUMMARY = (("Real", "R_precision_top3"), ("VAE", "FID"), ("MLD-DDIM50", "FID"), ("MotionLCM-1", "FID"),
           ("MotionLCM-Control", "FID"), ("EMDM-10", "FID"), ("MotionDiffuse-DDIM10", "FID"),
           ("EMDM-action", "Accuracy"), ("EMDM-action", "FID"))


def _read_samples(eval_dir: Path) -> list[tuple[str, bytes]]:
    """Every family's sample files ``(name, bytes)``, families in ``SOURCES`` order, names sorted."""
    return [(path.name, path.read_bytes())
            for name in SOURCES for path in sorted((eval_dir / name / "samples").glob("*"))]


def _write_html(eval_dir: Path, table: dict[str, dict[str, float]], meta: dict[str, Any],
                samples: list[tuple[str, bytes]], speed: dict[str, dict[str, float]]) -> None:
    """``report.html`` from the merged table, the plot already written, the samples and the speed table."""
    page = report_html(table, meta, (eval_dir / "fid_vs_time.png").read_bytes(), samples, speed)
    replace_file(eval_dir / "report.html", lambda p: p.write_text(page, encoding="utf-8"))


def summary(table: dict[str, dict[str, float]]) -> dict[str, dict[str, float]]:
    """The ``SUMMARY`` figures of the merged table, shaped like it (``{row: {metric: value}}``).

    A row or metric the table lacks (a family left out of the registry) is left out here too.
    """
    picked: dict[str, dict[str, float]] = {}
    for row, metric in SUMMARY:
        if metric in table.get(row, {}):
            picked.setdefault(row, {})[metric] = table[row][metric]
    return picked


def run(params: dict[str, Any]) -> dict[str, dict[str, float]]:
    """Merge, write and print the report; returns the merged table."""
    eval_dir = artifacts_dir(params) / "eval"
    check_output(eval_dir / "samples", owner="report")
    for name in OUTPUTS:  # checked before any is replaced, so that a failure leaves the old report whole
        if (eval_dir / name).is_dir():
            raise ValueError(f"{eval_dir / name} is a directory, where the report writes a file; move it away")
    folders = [eval_dir / name for name in (*SOURCES, SPEED)]
    tables = [read_table(folder) for folder in folders]
    check_protocols(folders[0], [folder for folder, rows in zip(folders[1:], tables[1:], strict=True) if rows])
    table, speed = merge_tables(tables[:-1]), tables[-1]
    meta = read_json(eval_dir / "real" / "meta.json")
    samples = _read_samples(eval_dir)
    report = report_markdown(table, meta, speed)
    replace_file(eval_dir / "metrics.json", lambda p: p.write_text(json.dumps(table, indent=2) + "\n"))
    replace_file(eval_dir / "summary.json", lambda p: p.write_text(json.dumps(summary(table), indent=2) + "\n"))
    replace_file(eval_dir / "report.md", lambda p: p.write_text(report, encoding="utf-8"))
    replace_file(eval_dir / "fid_vs_time.png", lambda p: plot_fid_vs_time(table, p))
    with atomic_directory(eval_dir / "samples", owner="report") as tmp:
        for name, data in samples:
            (tmp / name).write_bytes(data)
    _write_html(eval_dir, table, meta, samples, speed)
    print(report)
    return table


def main(argv: Sequence[str] | None = None) -> None:
    """``python -m stages.report [key=value ...] [--cfg] [--help]``."""
    run_main("report", run, PARAMS, argv)


if __name__ == "__main__":
    main()
