"""Posture actions of the synthetic motion library: squat, crouch, bow, pick up, sit down, stand
up, and standing (or sitting) still.

Each lowers or bends the body in place over planted feet: channel keys for the trunk and arms
plus pelvis keys relative to the rest posture. Sitting down and standing up change the posture
the next action starts from.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import numpy as np

from data.synthetic_builders import other, pick, pick_side, standing_piece, timed, uniform
from data.synthetic_motion import (
    CHANNELS,
    NEUTRAL,
    SEATED,
    Body,
    Piece,
    State,
    arm,
    frames,
    hold,
    interp_keys,
    shift_root,
)


def build_bow(body: Body, state: State, p: Mapping) -> Piece:
    """Bow from the hips (the arms hang), hold, straighten up."""
    depth, hold_time = p["depth"], p["hold"]
    bent = {"pelvis_pitch": 0.45 * depth, "spine_pitch": 0.55 * depth, "neck_pitch": 0.15,
            **arm("both", flex=0.85 * depth, abd=0.1, elbow=0.2)}
    keys = timed([(0.0, {}), (0.9, bent), (0.9 + hold_time, bent), (1.9 + hold_time, {})], p["tempo"])
    back = -0.07 * depth
    roots = [(keys[0][0], 0, 0, 0), (keys[1][0], back, -0.02, 0), (keys[2][0], back, -0.02, 0), (keys[3][0], 0, 0, 0)]
    return standing_piece(body, state, keys, roots)


def build_squat(body: Body, state: State, p: Mapping) -> Piece:
    """Squat down and up ``reps`` times, arms forward for balance."""
    drop = p["depth"] * body.leg
    down = {"pelvis_pitch": 0.55 * p["depth"] / 0.4, "spine_pitch": 0.15, "neck_pitch": -0.1,
            **arm("both", flex=1.45, abd=0.15, elbow=0.1)}
    ready = arm("both", flex=1.3, abd=0.15, elbow=0.15)
    half = p["period"] / 2
    keys: list[tuple[float, Mapping[str, float]]] = [(0.0, {}), (0.4, ready)]
    roots: list[tuple[float, float, float, float]] = [(0.0, 0, 0, 0), (0.4, 0, 0, 0)]
    for k in range(p["reps"]):
        t = 0.4 + 2 * half * k
        keys += [(t + half, down), (t + 2 * half, ready)]
        roots += [(t + half, -0.35 * drop, -drop, 0), (t + 2 * half, 0, 0, 0)]
    keys.append((keys[-1][0] + 0.5, {}))
    roots.append((keys[-1][0], 0, 0, 0))
    return standing_piece(body, state, keys, roots)


def build_crouch(body: Body, state: State, p: Mapping) -> Piece:
    """Crouch down low (heels up, hands near the knees), stay, get back up."""
    drop = p["depth"] * body.leg
    low = {"pelvis_pitch": 0.55, "spine_pitch": 0.4, "neck_pitch": -0.3,
           **arm("both", flex=0.9, abd=0.25, elbow=0.5)}
    keys = timed([(0.0, {}), (0.9, low), (0.9 + p["hold"], low), (1.9 + p["hold"], {})], p["tempo"])
    roots = [(keys[0][0], 0, 0, 0), (keys[1][0], -0.25 * drop, -drop, 0), (keys[2][0], -0.25 * drop, -drop, 0),
             (keys[3][0], 0, 0, 0)]
    piece = standing_piece(body, state, keys, roots)
    heels = interp_keys([k[0] for k in keys], [0.0, 0.45, 0.45, 0.0], len(piece.plan))
    piece.plan.pitch[:] = heels[:, None]
    return piece


def build_sit_down(body: Body, state: State, p: Mapping) -> Piece:
    """Sit down on a (invisible) chair behind: lean forward, lower, sit upright."""
    d = p["duration"]
    seat = State(state.toes, state.yaws, state.heading, "sit")
    drop, back = body.stand_height - body.seat_height, body.seat_back
    keys = [(0.0, {}), (0.5 * d, {"pelvis_pitch": 0.35, "spine_pitch": 0.35, **arm("both", flex=0.5, elbow=0.6)}),
            (d, {**{CHANNELS[i]: v for i, v in enumerate(SEATED)}})]
    roots = [(0.0, 0, 0, 0), (0.55 * d, -0.55 * back, -0.45 * drop, 0), (d, -back, -drop, 0)]
    piece = standing_piece(body, state, keys, roots)
    piece.end = seat
    return piece


def build_stand_up(body: Body, state: State, p: Mapping) -> Piece:
    """Stand up from sitting: lean forward over the feet, rise, straighten."""
    d = p["duration"]
    stand = State(state.toes, state.yaws, state.heading, "stand")
    drop, back = body.stand_height - body.seat_height, body.seat_back
    keys = [(0.0, {}), (0.35 * d, {"pelvis_pitch": 0.55, "spine_pitch": 0.35, **arm("both", flex=0.6, elbow=0.5)}),
            (d, {CHANNELS[i]: v for i, v in enumerate(NEUTRAL)})]
    roots = [(0.0, 0, 0, 0), (0.35 * d, 0.2 * back, 0.0, 0), (0.7 * d, 0.75 * back, 0.6 * drop, 0),
             (d, back, drop, 0)]
    piece = standing_piece(body, state, keys, roots)
    piece.end = stand
    return piece


def build_pick_up(body: Body, state: State, p: Mapping) -> Piece:
    """Bend down, pick something up from the floor with one or both hands, bring it up (and keep
    holding it, or lower the arms again)."""
    side, tempo = p["side"], p["tempo"]
    drop = 0.6 * body.leg
    trunk = {"pelvis_pitch": 0.95, "spine_pitch": 0.75, "neck_pitch": -0.2}
    if side != "both":  # the free arm hangs
        trunk.update(arm(other(side), flex=1.3, abd=0.15, elbow=0.4))
    reach = {**trunk, **arm(side, flex=1.7, abd=0.05, elbow=0.1)}
    grab = {**trunk, **arm(side, flex=1.6, abd=0.05, elbow=0.3)}
    carry = arm(side, flex=0.55, abd=0.1, elbow=1.5, twist=-0.3)
    keys = timed([(0.0, {}), (1.2, reach), (1.6, grab), (2.8, carry), (3.2, carry)], tempo)
    if not p["keep"]:
        keys.append((keys[-1][0] + 0.8, {}))
    roots = [(0.0, 0, 0, 0), (keys[1][0], -0.12, -drop, 0), (keys[2][0], -0.12, -drop, 0), (keys[3][0], 0, 0, 0)]
    return standing_piece(body, state, keys, roots)


def build_idle(body: Body, state: State, p: Mapping) -> Piece:
    """Stand (or sit) still, shifting the weight a little."""
    n = frames(p["duration"])
    plan = hold(body, state, n)
    shift_root(plan, 0.0, 0.0, 0.02 * np.sin(2 * np.pi * plan.times / 3.0) * (state.posture == "stand"))
    return Piece(plan, state)


# ---------------------------------------------------------------------------------------------
# Parameter samplers
# ---------------------------------------------------------------------------------------------


def sample_squat(rng: np.random.Generator) -> dict:
    return dict(reps=pick(rng, (1, 2, 3, 4), (0.35, 0.3, 0.2, 0.15)), depth=uniform(rng, 0.3, 0.45),
                period=uniform(rng, 1.4, 2.2))


def sample_duration(lo: float, hi: float) -> Callable[[np.random.Generator], dict]:
    """A sampler of ``{"duration": seconds}``."""
    return lambda rng: dict(duration=uniform(rng, lo, hi))


def sample_crouch(rng: np.random.Generator) -> dict:
    return dict(depth=uniform(rng, 0.45, 0.55), hold=uniform(rng, 0.6, 2.0), tempo=uniform(rng, 0.85, 1.2))


def sample_bow(rng: np.random.Generator) -> dict:
    return dict(depth=uniform(rng, 0.4, 1.0), hold=uniform(rng, 0.4, 1.5), tempo=uniform(rng, 0.85, 1.2))


def sample_pick_up(rng: np.random.Generator) -> dict:
    return dict(side=pick_side(rng, both=0.2), keep=bool(rng.random() < 0.3), tempo=uniform(rng, 0.85, 1.2))
