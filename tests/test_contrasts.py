"""benchmarks/contrasts.py: the side, order and count measures on joint arrays with known answers."""

from __future__ import annotations

import numpy as np
import pytest
from bench_module import load_benchmark

contrasts = load_benchmark("contrasts")
PAIRS = {pair.name: pair for pair in contrasts.PAIRS}
T = 120

# A standing body, pelvis-relative (x left, y up, z forward), HumanML3D joint order.
_OFFSETS = np.zeros((22, 3))
_OFFSETS[1], _OFFSETS[2] = (0.1, -0.05, 0), (-0.1, -0.05, 0)  # hips
_OFFSETS[4], _OFFSETS[5] = (0.1, -0.5, 0), (-0.1, -0.5, 0)  # knees
_OFFSETS[7], _OFFSETS[8] = (0.1, -0.87, 0), (-0.1, -0.87, 0)  # ankles
_OFFSETS[10], _OFFSETS[11] = (0.1, -0.93, 0.12), (-0.1, -0.93, 0.12)  # toes
_OFFSETS[[3, 6, 9, 12]] = [(0, 0.1, 0), (0, 0.25, 0), (0, 0.4, 0), (0, 0.5, 0)]  # spine, neck
_OFFSETS[15] = (0, 0.65, 0)  # head
_OFFSETS[16], _OFFSETS[17] = (0.18, 0.45, 0), (-0.18, 0.45, 0)  # shoulders
_OFFSETS[18], _OFFSETS[19] = (0.2, 0.18, 0), (-0.2, 0.18, 0)  # elbows
_OFFSETS[20], _OFFSETS[21] = (0.2, -0.08, 0), (-0.2, -0.08, 0)  # wrists
_PELVIS_HEIGHT = 0.95


def body(yaw: np.ndarray | None = None, pelvis: np.ndarray | None = None) -> np.ndarray:
    """(T, 22, 3) joints of the standing body turned by ``yaw`` (T,) radians about y, pelvis at ``pelvis`` (T, 3)."""
    yaw = np.zeros(T) if yaw is None else yaw
    if pelvis is None:
        pelvis = np.tile([0.0, _PELVIS_HEIGHT, 0.0], (T, 1))
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    x, y, z = _OFFSETS[:, 0], _OFFSETS[:, 1], _OFFSETS[:, 2]
    turned = np.stack([c * x + s * z, np.broadcast_to(y, (T, 22)), -s * x + c * z], axis=-1)
    return turned + pelvis[:, None, :]


def bump(start: int, end: int, height: float) -> np.ndarray:
    """(T,) a half-sine of ``height`` over frames [start, end), 0 elsewhere."""
    out = np.zeros(T)
    out[start:end] = height * np.sin(np.linspace(0, np.pi, end - start + 2)[1:-1])
    return out


def passes(pair: str, joints: np.ndarray) -> list[bool]:
    """Whether each of the pair's two prompts passes on ``joints``."""
    return [bool(p.passes(PAIRS[pair].measure(joints))) for p in PAIRS[pair].prompts]


def kick(side: int, height: float = 0.6) -> np.ndarray:
    j = body()
    foot = (7, 10) if side == 0 else (8, 11)
    j[:, foot, 1] += bump(40, 60, height)[:, None]
    return j


@pytest.mark.parametrize("side", [0, 1])
def test_kick_side(side):
    left, right = contrasts.foot_rise(kick(side))
    assert (left > 0.5 > right) if side == 0 else (right > 0.5 > left)
    assert passes("side: kick", kick(side)) == [side == 0, side == 1]


def test_small_lift_or_jitter_is_no_kick():
    assert passes("side: kick", kick(0, height=0.12)) == [False, False]  # a walking step's swing
    jitter = body() + np.random.default_rng(0).normal(0, 0.01, (T, 22, 3))
    assert passes("side: kick", jitter) == [False, False]


@pytest.mark.parametrize("side", [0, 1])
def test_wave_side(side):
    j = body()
    j[30:70, 20 + side, 1] = j[30:70, 15, 1] + 0.15  # the wrist above the head for 40 frames
    j[60:65, 21 - side, 1] = j[60:65, 15, 1] + 0.05  # the other one briefly
    assert contrasts.wrist_up(j) == ((40, 5) if side == 0 else (5, 40))
    assert passes("side: wave", j) == [side == 0, side == 1]


def test_wave_needs_ten_frames():
    j = body()
    j[30:38, 20, 1] = j[30:38, 15, 1] + 0.1
    assert passes("side: wave", j) == [False, False]


def walk_and_turn(walk_first: bool) -> np.ndarray:
    """Walk 2.4 m forward over 2 s and turn 180 degrees over 1.5 s, in that order or the other."""
    walk = np.clip((np.arange(T) - 10) / 40, 0, 1) * 2.4  # frames 10-50
    turn = np.clip((np.arange(T) - 70) / 30, 0, 1) * np.pi  # frames 70-100
    if not walk_first:
        walk, turn = np.clip((np.arange(T) - 70) / 40, 0, 1) * 2.4, np.clip((np.arange(T) - 10) / 30, 0, 1) * np.pi
        walk = walk * -1  # facing back: walking "forward" goes to -z
    pelvis = np.stack([np.zeros(T), np.full(T, _PELVIS_HEIGHT), walk], axis=1)
    return body(turn, pelvis)


@pytest.mark.parametrize("walk_first", [True, False])
def test_order(walk_first):
    m = contrasts.order(walk_and_turn(walk_first))
    assert m["path"] == pytest.approx(2.4)
    assert m["turn"] == pytest.approx(180, abs=1)
    assert (m["walk_t"] < m["turn_t"]) == walk_first
    assert passes("order: walk/turn", walk_and_turn(walk_first)) == [walk_first, not walk_first]


def test_stride_yaw_swing_is_no_turn():
    """Walking straight with the hips swinging +-10 degrees each stride: no turn, neither prompt passes."""
    pelvis = np.stack([np.zeros(T), np.full(T, _PELVIS_HEIGHT), np.linspace(0, 6, T)], axis=1)
    yaw = np.radians(10) * np.sin(2 * np.pi * np.arange(T) / 20)
    m = contrasts.order(body(yaw, pelvis))
    assert m["turn"] < 10
    assert passes("order: walk/turn", body(yaw, pelvis)) == [False, False]


def test_standing_still_passes_neither_order():
    assert passes("order: walk/turn", body()) == [False, False]


def jumps(starts: list[int], frames: int = 6, height: float = 0.2) -> np.ndarray:
    lift = sum((bump(s, s + frames, height) for s in starts), np.zeros(T))
    return body() + np.stack([np.zeros(T), lift, np.zeros(T)], axis=1)[:, None, :]


def test_three_separated_jumps_count_three():
    j = jumps([20, 45, 70])
    assert contrasts.jump_count(j) == 3
    assert passes("count: jumps", j) == [False, True]


def test_one_jump_counts_one():
    assert contrasts.jump_count(jumps([50])) == 1
    assert passes("count: jumps", jumps([50])) == [True, False]


def test_one_grounded_frame_inside_a_jump_does_not_split_it():
    j = jumps([50], frames=12)
    j[56, :, 1] = body()[56, :, 1]  # one jittery frame back on the floor
    assert contrasts.jump_count(j) == 1


def test_one_frame_spike_and_one_foot_lift_are_no_jump():
    spike = body()
    spike[60, :, 1] += 0.2
    assert contrasts.jump_count(spike) == 0
    assert contrasts.jump_count(kick(0)) == 0  # one foot up: not airborne


def test_standing_is_no_jump():
    assert contrasts.jump_count(body()) == 0
    assert passes("count: jumps", body()) == [False, False]


def test_jittery_motion_fails_every_criterion():
    """Noise of a few centimetres per frame fakes a kick on both feet and jump episodes: the jitter guard fails them."""
    assert contrasts.jitter(body()) == 0
    assert contrasts.jitter(kick(0)) < contrasts.JITTER_MAX  # a clean kick is smooth enough
    noisy = kick(0) + np.random.default_rng(1).normal(0, 0.08, (T, 22, 3))
    assert contrasts.jitter(noisy) > contrasts.JITTER_MAX
    joints = {"a person kicks with their left leg": noisy, "a person kicks with their right leg": noisy}
    out = contrasts.evaluate(joints, PAIRS["side: kick"])
    assert not any(out[p.text]["pass"] for p in PAIRS["side: kick"].prompts)
    assert "jittery" in contrasts._cell(out["a person kicks with their left leg"]["measures"])


def test_differ_is_root_relative():
    a = kick(0)
    moved = a + np.array([1.0, 0.0, 2.0])
    assert contrasts.root_relative_distance(a, moved) == pytest.approx(0, abs=1e-12)
    assert contrasts.root_relative_distance(kick(0), kick(1)) > 0.01


def test_evaluate_and_table():
    joints = {"a person kicks with their left leg": kick(0), "a person kicks with their right leg": kick(0)}
    pair = PAIRS["side: kick"]
    out = contrasts.evaluate(joints, pair)
    assert out["differ"] == 0
    assert [out[p.text]["pass"] for p in pair.prompts] == [True, False]
    seeds = [{p.name: {"differ": 0.0, **{q.text: {"measures": p.measure(body()), "pass": False} for q in p.prompts}}
              for p in contrasts.PAIRS}]
    text = contrasts.table("Fake", seeds)
    assert text.count("| 0/1 |") == 8
    assert "a person jumps in place three times" in text


def test_prompts_use_the_dataset_wording():
    """Every word of the prompts is in the synthetic captions' lexicon (data/synthetic_text.py)."""
    from data.synthetic_text import LEXICON

    words = {w.strip(",").lower() for pair in contrasts.PAIRS for p in pair.prompts for w in p.text.split()}
    assert words <= set(LEXICON) | {"jumps", "kicks", "waves", "walks", "turns"}


def test_jitter_is_the_mean_length_of_the_second_difference():
    """Constant velocity has no jitter; one joint of 22 accelerating at 0.02 m/frame² gives 0.02 / 22."""
    n = np.arange(10, dtype=float)
    steady = np.zeros((10, 22, 3))
    steady[..., 0] = 0.1 * n[:, None]
    assert contrasts.jitter(steady) == pytest.approx(0.0, abs=1e-12)
    accelerating = np.zeros((10, 22, 3))
    accelerating[:, 0, 0] = 0.01 * n**2
    assert contrasts.jitter(accelerating) == pytest.approx(0.02 / 22, rel=1e-9)
