"""benchmarks/skating_by_caption.py: caption selection and the group measures, on known answers."""

import numpy as np
import pytest

from data.skeleton import get_skeleton
from tests.bench_module import load_benchmark

bench = load_benchmark("skating_by_caption")
SKELETON = get_skeleton("humanml3d")


def test_first_match_needs_every_word_in_one_caption() -> None:
    captions = ["A man turns around", "a man Walks forward then stops", "he walks"]
    assert bench.first_match(captions, ["walk", "forward"]) == "a man Walks forward then stops"
    assert bench.first_match(captions, ["walk"]) == "a man Walks forward then stops"
    assert bench.first_match(captions, ["walk", "back"]) is None


def _gliding(speed: float, frames: int = 41) -> np.ndarray:
    """Every joint at floor height, the whole body sliding forward at ``speed`` m/s: planted feet that move."""
    joints = np.zeros((frames, 22, 3))
    joints[:, :, 2] = (np.arange(frames) * speed / SKELETON.fps)[:, None]
    return joints


def test_a_body_gliding_on_its_feet_skates_and_a_still_one_does_not() -> None:
    still, glide = _gliding(0.0), _gliding(1.0)
    assert bench.group_measures([still], SKELETON) == pytest.approx({"skating": 0.0, "speed": 0.0})
    measured = bench.group_measures([still, glide], SKELETON)
    assert measured["speed"] == pytest.approx(0.5)
    assert 0.4 < measured["skating"] <= 0.5  # the glide skates except where the 5-frame smoothing fades at the ends


def _one_toe(height: float, speed: float, frames: int = 41) -> np.ndarray:
    """Every joint still on the floor but the left toe, at ``height`` m, moving forward at ``speed`` m/s."""
    joints = np.zeros((frames, 22, 3))
    toe = SKELETON.feet_left[1]
    joints[:, toe, 1] = height
    joints[:, toe, 2] = np.arange(frames) * speed / SKELETON.fps
    return joints


def test_skating_causes_tell_a_sliding_stance_from_a_swing_kept_low() -> None:
    low_swing = bench.skating_causes([_one_toe(0.10, 1.0)], [_one_toe(0.0, 1.0)], SKELETON)
    assert low_swing["lifted"] == 1.0 and low_swing["planted"] == 0.0
    assert low_swing["swing_height_real"] == pytest.approx(0.10) and low_swing["swing_height_recon"] == 0.0
    assert low_swing["swing_low_real"] == 0.0 and low_swing["swing_low_recon"] == 1.0
    slide = bench.skating_causes([_one_toe(0.0, 0.0)], [_one_toe(0.0, 1.0)], SKELETON)
    assert slide["planted"] == 1.0 and slide["lifted"] == 0.0
    assert np.isnan(slide["swing_height_real"])  # nothing swings in the real motion
    exact = bench.skating_causes([_one_toe(0.10, 1.0)], [_one_toe(0.10, 1.0)], SKELETON)
    assert exact["planted"] == exact["lifted"] == 0.0  # no skating to attribute
