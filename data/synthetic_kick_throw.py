"""Kick and throw actions of the synthetic motion library.

One foot leaves the floor while the body balances on the other: front kicks from a standing
posture, and an overarm throw that steps forward with the foot opposite the throwing arm.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from data.synthetic_builders import FOOT, SIGN, body_scale, other, pick, pick_side, standing_piece, timed, uniform
from data.synthetic_motion import Body, Piece, State, arm, foot_keys, forward, move_foot


def build_kick(body: Body, state: State, p: Mapping) -> Piece:
    """Front kicks with one leg while standing on the other."""
    side, reps, tempo = p["side"], p["reps"], p["tempo"]
    foot, scale = FOOT[side], body_scale(body)
    apex = p["height"] * scale
    period = 1.1 * tempo
    keys: list[tuple[float, Mapping[str, float]]] = [(0.0, {})]
    roots: list[tuple[float, float, float, float]] = [(0.0, 0, 0, 0)]
    feet: list[tuple[float, float, float, float, float]] = []
    shift = -0.7 * SIGN[side] * body.half_width
    balance = {**arm(other(side), flex=0.5, abd=0.5, elbow=0.6), **arm(side, flex=-0.2, abd=0.5, elbow=0.4)}
    kick = {**balance, "pelvis_pitch": -0.12 - 0.2 * p["height"], "spine_pitch": 0.1}
    for k in range(reps):
        t = 0.45 + period * k
        keys += [(t, balance), (t + 0.45 * period, kick), (t + period, balance)]
        roots += [(t, 0, -0.01, shift), (t + period, 0, -0.01, shift)]
        feet += [(t, 0, 0, 0, 0), (t + 0.1 * period, 0, 0.06, 0, 0.3), (t + 0.3 * period, -0.18, 0.14, 0, 0.5),
                 (t + 0.48 * period, 0.62 * scale, apex, 0, 0.9), (t + 0.72 * period, 0.12, 0.2, 0, 0.4),
                 (t + 0.9 * period, 0.0, 0.05, 0, 0.1), (t + period, 0, 0, 0, 0)]
    end = 0.45 + period * reps + 0.5
    keys.append((end, {}))
    roots.append((end, 0, 0, 0))
    piece = standing_piece(body, state, keys, roots)
    foot_keys(piece.plan, foot, feet)
    return piece


def build_throw(body: Body, state: State, p: Mapping) -> Piece:
    """Overarm throw: wind up, step forward with the other foot, throw, step back."""
    side, tempo = p["side"], p["tempo"]
    s = SIGN[side]
    windup = {**arm(side, flex=0.3, abd=1.5, twist=1.4, elbow=1.7), **arm(other(side), flex=0.9, abd=0.2, elbow=0.4),
              "spine_twist": 0.5 * s, "spine_lean": -0.1 * s, "spine_pitch": -0.1}
    release = {**arm(side, flex=1.9, abd=0.3, twist=0.3, elbow=0.3), **arm(other(side), flex=0.2, abd=0.3, elbow=0.4),
               "spine_twist": -0.4 * s, "spine_pitch": 0.25}
    follow = {**arm(side, flex=0.7, abd=-0.2, twist=0.0, elbow=0.3), "spine_twist": -0.5 * s, "spine_pitch": 0.35}
    keys = timed([(0.0, {}), (0.8, windup), (1.05, release), (1.3, follow), (2.2, {})], tempo)
    stride = p["stride"] * body_scale(body)
    roots = [(0.0, 0, 0, 0), (keys[1][0], -0.03, -0.02, 0), (keys[2][0], 0.5 * stride, -0.04, 0),
             (keys[3][0], 0.55 * stride, -0.04, 0), (keys[4][0], 0, 0, 0)]
    piece = standing_piece(body, state, keys, roots, tail=0.4)
    plan, foot = piece.plan, FOOT[other(side)]
    toe, yaw = state.toes[foot].copy(), float(state.yaws[foot])
    toe[[0, 2]] += forward(state.heading) * stride
    move_foot(plan, foot, keys[1][0] - 0.35 * tempo, keys[2][0] - 0.05 * tempo, toe, yaw)
    move_foot(plan, foot, keys[3][0] + 0.2 * tempo, keys[4][0], state.toes[foot], yaw)
    return piece


# ---------------------------------------------------------------------------------------------
# Parameter samplers
# ---------------------------------------------------------------------------------------------


def sample_kick(rng: np.random.Generator) -> dict:
    high = bool(rng.random() < 0.4)
    return dict(side=pick_side(rng), reps=pick(rng, (1, 2, 3), (0.5, 0.3, 0.2)),
                height=uniform(rng, 0.7, 0.95) if high else uniform(rng, 0.35, 0.6), tempo=uniform(rng, 0.85, 1.15))


def sample_throw(rng: np.random.Generator) -> dict:
    return dict(side=pick_side(rng), stride=uniform(rng, 0.2, 0.35), tempo=uniform(rng, 0.85, 1.15))
