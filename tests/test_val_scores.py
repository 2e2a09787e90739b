"""benchmarks/val_scores.py's command line (overrides are never taken for row names) and its summary of draws."""

from __future__ import annotations

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


def test_summary_gives_the_draws_mean_and_95_percent_half_width() -> None:
    # FID: mean 3, std (ddof 0) sqrt(3.5), half-width 1.96 * sqrt(3.5) / 2 = 1.833; R@3: mean 0.5, std 0.1, 0.098
    line = val_scores.summary("EMDM-10", [1.0, 2.0, 3.0, 6.0], [0.4, 0.6, 0.4, 0.6])
    assert line == "EMDM-10: 4 draws: val FID 3.000 ± 1.833, val R@3 0.500 ± 0.098 (mean ± 95 % half-width)"
