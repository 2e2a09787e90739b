"""data/joint_measures.py: turns, swings and the reconstruction-detail fractions on joints with known answers.

The foot, wrist and jump measures are also tested through benchmarks/contrasts.py (test_contrasts.py),
whose synthetic bodies these tests reuse."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_contrasts import _PELVIS_HEIGHT, T, body, jumps, kick

from data import joint_measures as jm


def waving(amplitude: float = 0.1, blocks: int = 8, side: str = "right") -> np.ndarray:
    """The standing body with one wrist above the head for frames 30-70, its forearm held at +amplitude and
    -amplitude (left-right of its elbow) in turn, ``blocks`` blocks of 5 frames: ``blocks - 1`` swings."""
    j = body()
    wrist, elbow = (jm.L_WRIST, jm.L_ELBOW) if side == "left" else (jm.R_WRIST, jm.R_ELBOW)
    frames = np.arange(30, 30 + 5 * blocks)
    sign = np.where((frames - 30) // 5 % 2 == 0, 1.0, -1.0)
    j[frames, wrist] = j[frames, elbow] + np.stack([amplitude * sign, np.full(len(frames), 0.5),
                                                    np.zeros(len(frames))], axis=1)
    return j


def turning(degrees: float) -> np.ndarray:
    """The standing body turning by ``degrees`` about y between frames 40 and 80."""
    return body(np.clip((np.arange(T) - 40) / 40, 0, 1) * math.radians(degrees))


@pytest.mark.parametrize("degrees", [180.0, -90.0, 360.0])
def test_net_turn_is_the_yaw_change(degrees):
    assert jm.net_turn(turning(degrees)) == pytest.approx(degrees, abs=1e-6)


def test_swings_are_counted_once_each():
    assert jm.swing_count(waving(), "right") == 7
    assert jm.swing_count(waving(blocks=3, side="left"), "left") == 2
    assert jm.swing_count(waving(), "left") == 0  # the left hand is down


def test_small_sways_and_a_hand_down_are_no_swings():
    assert jm.swing_count(waving(amplitude=0.02), "right") == 0  # 4 cm from side to side: below SWING_MIN
    down = waving()
    down[:, jm.R_WRIST, 1] -= 1.0  # the same swings below the head
    assert jm.swing_count(down, "right") == 0


def test_a_wave_is_four_swings_in_one_raised_stretch_with_the_hands_apart():
    assert jm.waving_side(waving()) == "right"
    assert jm.waving_side(waving(side="left")) == "left"
    assert jm.waving_side(waving(blocks=4)) is None  # 3 swings
    assert jm.waving_side(body()) is None
    split = waving()
    split[45:50, jm.R_WRIST, 1] -= 1.0  # lowered for a block: 2 and 3 swings in two stretches
    assert jm.swing_count(split, "right") >= 4 and jm.waving_side(split) is None
    clap = waving()
    clap[30:70, jm.L_WRIST] = clap[30:70, jm.R_WRIST] + np.array([0.2, 0.0, 0.0])  # hands 0.2 m apart
    assert jm.waving_side(clap) is None
    clap[30:70, jm.L_WRIST] += np.array([0.15, 0.0, 0.0])  # 0.35 m apart: two raised hands, not meeting
    assert jm.waving_side(clap) == "right"


def test_a_perfect_reconstruction_keeps_everything():
    motions = [turning(180), kick(0), waving(), jumps([20, 45, 70]), body()]
    out = jm.reconstruction_detail(motions, [m.copy() for m in motions])
    assert out["path_err_m"] == 0.0
    for name in ("turn", "kick", "wave", "jumps"):
        assert out[f"{name}_kept"] == 1.0
        assert out[f"{name}_refs"] == 1.0  # one reference each: the standing body is none of them


def test_a_reconstruction_that_loses_each_action_keeps_none():
    real = [turning(180), kick(0, height=0.6), waving(), jumps([20, 45, 70])]
    lost = [turning(90), kick(0, height=0.4), waving(amplitude=0.02), jumps([45])]
    out = jm.reconstruction_detail(real, lost)
    assert (out["turn_kept"], out["kick_kept"], out["wave_kept"], out["jumps_kept"]) == (0.0, 0.0, 0.0, 0.0)
    kept = [turning(150), kick(0, height=0.5), waving(blocks=5), jumps([20, 45, 70])]
    out = jm.reconstruction_detail(real, kept)  # within 45 degrees, 0.8 of the rise, half the swings
    assert (out["turn_kept"], out["kick_kept"], out["wave_kept"], out["jumps_kept"]) == (1.0, 1.0, 1.0, 1.0)


def test_the_other_foot_or_both_feet_are_no_kept_kick():
    out = jm.reconstruction_detail([kick(0)], [kick(1)])
    assert out["kick_refs"] == 1.0 and out["kick_kept"] == 0.0
    assert jm.reconstruction_detail([jumps([50], height=0.5)], [body()])["kick_refs"] == 0.0  # both feet: a jump


def test_path_error_is_the_pelvis_distance_and_without_references_a_fraction_is_absent():
    shifted = body(pelvis=np.tile([0.3, _PELVIS_HEIGHT, 0.4], (T, 1)))
    out = jm.reconstruction_detail([body()], [shifted])
    assert out["path_err_m"] == pytest.approx(0.5)
    assert "turn_kept" not in out and out["turn_refs"] == 0.0


def test_mismatched_inputs_are_an_error():
    with pytest.raises(ValueError, match="1 real motions but 2"):
        jm.reconstruction_detail([body()], [body(), body()])
    with pytest.raises(ValueError, match="differ"):
        jm.reconstruction_detail([body()], [body()[:60]])
