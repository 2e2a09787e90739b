"""benchmarks/val_scores.py's command line: overrides are never taken for row names."""

from __future__ import annotations

from bench_module import load_benchmark

val_scores = load_benchmark("val_scores")


def test_overrides_after_rows_stay_overrides() -> None:
    args = val_scores.parse_args(["emdm", "--rows", "EMDM-10", "evaluate.seed=1", "paths.artifacts=/tmp/x"])
    assert (args.family, args.rows) == ("emdm", ["EMDM-10"])
    assert args.overrides == ["evaluate.seed=1", "paths.artifacts=/tmp/x"]


def test_rows_repeat_and_default_to_every_row() -> None:
    args = val_scores.parse_args(["mld", "a=1", "--rows", "MLD-DDIM50", "--rows", "MLD-DDIM4", "b=2"])
    assert (args.rows, args.overrides) == (["MLD-DDIM50", "MLD-DDIM4"], ["a=1", "b=2"])
    assert val_scores.parse_args(["mld"]).rows is None
