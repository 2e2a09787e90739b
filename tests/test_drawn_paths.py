"""benchmarks/drawn_paths.py: the measures of a pelvis against a drawn path, on known answers."""

import numpy as np
import pytest

from tests.bench_module import load_benchmark

drawn_paths = load_benchmark("drawn_paths")
path_measures, horizontal_speed = drawn_paths.path_measures, drawn_paths.horizontal_speed


def _line(length: float, frames: int = 41, height: float = 0.9) -> np.ndarray:
    path = np.zeros((frames, 3))
    path[:, 1], path[:, 2] = height, np.linspace(0.0, length, frames)
    return path


def test_following_the_path_scores_zero_and_the_path_speed() -> None:
    line = _line(2.0)
    assert path_measures(line, line, 20.0) == pytest.approx({"error": 0.0, "off_path": 0.0, "end": 0.0, "speed": 1.0})


def test_standing_at_the_start_is_on_the_path_but_far_from_it_frame_by_frame() -> None:
    line, standing = _line(2.0), np.zeros((41, 3))
    standing[:, 1] = 0.9
    m = path_measures(standing, line, 20.0)
    assert m == pytest.approx({"error": 1.0, "off_path": 0.0, "end": 2.0, "speed": 0.0})


def test_a_late_start_at_twice_the_pace_reaches_the_end_with_a_timing_error_only() -> None:
    """Standing for the first half, then walking the whole line in the second: on the path everywhere,
    at its end on the last frame, off it frame by frame (the benchmark's timing effect)."""
    line = _line(2.0)
    late = line.copy()
    late[:21, 2] = 0.0
    late[20:, 2] = np.linspace(0.0, 2.0, 21)
    m = path_measures(late, line, 20.0)
    assert m["off_path"] == pytest.approx(0.0) and m["end"] == pytest.approx(0.0)
    assert m["error"] == pytest.approx(np.abs(late[:, 2] - line[:, 2]).mean())
    assert m["error"] > 0.4 and m["speed"] == pytest.approx(1.0)


def test_a_parallel_offset_is_off_the_path_by_the_offset() -> None:
    line = _line(2.0)
    beside = line + np.array([0.3, 0.0, 0.0])
    assert path_measures(beside, line, 20.0) == pytest.approx({"error": 0.3, "off_path": 0.3, "end": 0.3, "speed": 1.0})


def test_horizontal_speed_ignores_height() -> None:
    """2 m along x and z (2.83 m) in 40 frames at 20 fps, rising 1 m on the way: 2.83 / 2 s."""
    track = np.zeros((41, 3))
    track[:, 0] = track[:, 2] = np.linspace(0.0, 2.0, 41)
    track[:, 1] = np.linspace(0.0, 1.0, 41)
    assert horizontal_speed(track, 20.0) == pytest.approx(np.sqrt(8.0) / 2.0)
