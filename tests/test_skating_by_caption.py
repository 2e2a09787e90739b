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
