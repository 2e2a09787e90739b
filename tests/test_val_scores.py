"""benchmarks/val_scores.py's command line (overrides are never taken for row names) and its summary of draws."""

from __future__ import annotations

import math

import pytest
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


def test_draws_default_to_one_and_must_be_positive() -> None:
    assert val_scores.parse_args(["emdm"]).draws == 1
    assert val_scores.parse_args(["emdm", "a=1", "--draws", "3", "b=2"]).overrides == ["a=1", "b=2"]
    with pytest.raises(SystemExit):
        val_scores.parse_args(["emdm", "--draws", "0"])


def test_mean_and_standard_error_of_known_values() -> None:
    mean, error = val_scores.mean_and_error([1.0, 2.0, 3.0, 6.0])  # sample variance 14 / 3, n = 4
    assert mean == 3.0 and math.isclose(error, math.sqrt(14 / 3 / 4))
    assert val_scores.mean_and_error([2.5]) == (2.5, 0.0)
