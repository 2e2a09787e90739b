"""pipelines/speed.py and the eval_speed stage's checks: alternating rounds, means, speed-ups, parameter counts."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pipelines import speed
from pipelines.evaluation import EvalConfig
from stages.speed import check_section


class FakeRow:
    """A generator row holding two networks that share a layer (its parameters must count once)."""

    stochastic = True

    def __init__(self, name: str, nfe: int, width: int) -> None:
        self.name, self.nfe = name, nfe
        shared = torch.nn.Linear(width, width)  # width * width + width parameters
        self.net = torch.nn.Sequential(shared, torch.nn.Linear(width, 1))  # + width + 1
        self.ema = torch.nn.Sequential(shared)
        self.scale = torch.ones(3)  # a tensor attribute, not a network: not counted

    def sample(self, text: object, lengths: np.ndarray, seed: int) -> np.ndarray:
        raise AssertionError("time_generator is replaced in these tests")


def test_parameter_count_counts_each_network_parameter_once() -> None:
    assert speed.parameter_count(FakeRow("a", 1, 4)) == (4 * 4 + 4) + (4 + 1)


def test_side_by_side_alternates_the_order_and_reports_means_and_speedups(monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[str] = []
    ms = {"fast": [1.0, 3.0, 2.0], "slow": [100.0, 300.0, 200.0]}  # per round

    def fake_time(row: FakeRow, d: object, n: int, hint: object, budget: object) -> dict[str, float]:
        k = sum(name == row.name for name in calls)
        calls.append(row.name)
        return {"AITS_s": ms[row.name][k] / 10, "ms_per_frame": ms[row.name][k]}

    monkeypatch.setattr(speed, "time_generator", fake_time)
    rows = [FakeRow("fast", 20, 2), FakeRow("slow", 1000, 8)]
    table = speed.side_by_side(rows, d=None, cfg=EvalConfig(), joints_num=22, rounds=3)
    assert calls == ["fast", "slow", "slow", "fast", "fast", "slow"]  # A B, B A, A B
    assert table["fast"]["ms_per_frame"] == pytest.approx(2.0) and table["slow"]["ms_per_frame"] == pytest.approx(200.0)
    assert table["fast"]["AITS_s"] == pytest.approx(0.2)
    assert table["fast"]["speedup"] == pytest.approx(100.0) and table["slow"]["speedup"] == pytest.approx(1.0)
    assert table["slow"]["NFE"] == 1000 and table["slow"]["rounds"] == 3
    assert table["slow"]["params_M"] == pytest.approx(((8 * 8 + 8) + (8 + 1)) / 1e6)


def test_side_by_side_refuses_duplicate_rows_and_zero_rounds() -> None:
    with pytest.raises(ValueError, match="distinct names"):
        speed.side_by_side([FakeRow("a", 1, 2), FakeRow("a", 1, 2)], None, EvalConfig(), 22)
    with pytest.raises(ValueError, match="rounds"):
        speed.side_by_side([FakeRow("a", 1, 2)], None, EvalConfig(), 22, rounds=0)


@pytest.mark.parametrize(("section", "message"), [
    ({"rows": ["EMDM-10"], "rounds": 2}, "two or more row names"),
    ({"rows": "EMDM-10", "rounds": 2}, "two or more row names"),
    ({"rows": ["EMDM-10", "MotionDiffuse-1000"], "rounds": 0}, "speed.rounds"),
    ({"rows": ["EMDM-10", "MotionDiffuse-1000"], "rounds": 2, "warmup": 1}, "warmup"),
    ({"rows": ["EMDM-10", "EMDM-10", "MotionDiffuse-1000"], "rounds": 2}, "names a row twice"),  # failed after loading
    ({"rows": [{"a": 1}, "EMDM-10"], "rounds": 2}, "two or more row names"),
])
def test_the_stage_names_a_bad_speed_key(section: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        check_section({"speed": section, "evaluate": {"replications": 3}})


def test_the_stage_refuses_a_protocol_count_it_would_divide_by() -> None:
    """eval_speed reads the evaluate section's timing counts: 0 captions divided by zero after the models loaded."""
    with pytest.raises(ValueError, match=r"evaluate.timing_sentences: expected an integer >= 1, got 0"):
        check_section({"speed": {"rows": ["EMDM-10", "MotionDiffuse-1000"], "rounds": 2},
                       "evaluate": {"timing_sentences": 0}})


def test_the_stage_accepts_the_default_section() -> None:
    check_section({"speed": {"rows": ["EMDM-10", "MotionDiffuse-1000"], "rounds": 2}, "evaluate": {"seed": 0}})
