"""benchmarks/path_stats.py: speed and heading change of a pelvis path, on known paths."""

import math

import numpy as np
import pytest

from tests.bench_module import load_benchmark

path_stats = load_benchmark("path_stats").path_stats


def _walk(yaw_rate: float, step: float, frames: int = 41) -> np.ndarray:
    """Features of a root stepping ``step`` m forward per frame, turning by ``yaw_rate`` per frame (the
    features' half-angle: the heading turns by twice it); every joint at the root."""
    features = np.zeros((frames, 263))
    features[:, 0], features[:, 2] = yaw_rate, step
    return features


def test_a_straight_walk_and_a_half_circle() -> None:
    assert path_stats(_walk(0.0, 0.05), 22, 20.0, 0.4) == pytest.approx((1.0, 0.0))
    speed, turn = path_stats(_walk(math.pi / 80, 0.05), 22, 20.0, 0.4)
    assert speed == pytest.approx(1.0) and turn == pytest.approx(2 * 39 * 180 / 80)  # 39 step-to-step turns
    assert path_stats(_walk(math.pi / 80, 0.01), 22, 20.0, 0.4) == pytest.approx((0.2, 0.0))  # too slow to count
