"""Upper-body actions of the synthetic motion library: wave, raise the arms, clap, punch, look
around and stretch.

The legs keep the start posture (standing or seated), so a carrier action (walking, turning...)
can take one of these on top (:func:`data.synthetic_library.build_segment`).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from data.synthetic_builders import SIGN, other, pick, pick_side, timed, uniform, upper_body_piece
from data.synthetic_motion import Body, Piece, State, arm, pose


def build_wave(body: Body, state: State, p: Mapping) -> Piece:
    """Wave one hand (forearm swinging side to side) or both hands."""
    side, tempo = p["side"], p["tempo"]
    raised = arm(side, flex=0.3, abd=1.55, twist=1.35, elbow=1.3)
    keys = [(0.0, {}), (0.5, raised)]
    for k in range(2 * p["reps"]):
        keys.append((0.5 + 0.22 * (k + 1), {**raised, **arm(side, elbow=0.8 if k % 2 == 0 else 1.7)}))
    keys += [(keys[-1][0] + 0.2, raised), (keys[-1][0] + 0.75, {})]
    return upper_body_piece(body, state, timed(keys, tempo))


def build_raise_arms(body: Body, state: State, p: Mapping) -> Piece:
    """Raise one or both arms up, forward or out to the side, hold, lower."""
    target = {
        "up": dict(flex=2.95, abd=0.15, elbow=0.1),
        "forward": dict(flex=1.5, abd=0.1, elbow=0.05),
        "sideways": dict(flex=0.05, abd=1.5, elbow=0.05),
    }[p["direction"]]
    up = arm(p["side"], **target)
    keys = [(0.0, {}), (0.8, up), (0.8 + p["hold"], up), (1.6 + p["hold"], {})]
    return upper_body_piece(body, state, timed(keys, p["tempo"]))


def build_clap(body: Body, state: State, p: Mapping) -> Piece:
    """Clap in front of the chest (or above the head)."""
    if p["overhead"]:
        apart, together = arm("both", flex=0.3, abd=2.85, elbow=0.35), arm("both", flex=0.3, abd=3.45, elbow=0.3)
    else:
        apart = arm("both", flex=0.75, abd=0.45, twist=-0.5, elbow=1.45)
        together = arm("both", flex=0.75, abd=-0.22, twist=-0.5, elbow=1.3)
    keys = [(0.0, {}), (0.5, apart)]
    for k in range(p["reps"]):
        keys += [(0.5 + 0.42 * k + 0.21, together), (0.5 + 0.42 * (k + 1), apart)]
    keys.append((keys[-1][0] + 0.6, {}))
    return upper_body_piece(body, state, timed(keys, p["tempo"]))


def build_punch(body: Body, state: State, p: Mapping) -> Piece:
    """Punch straight ahead from a guard, with one hand or alternating hands."""
    guard = arm("both", flex=0.75, abd=0.25, twist=-0.6, elbow=2.1)
    keys = [(0.0, {}), (0.5, guard)]
    sides = ["left", "right"] * p["reps"] if p["side"] == "both" else [p["side"]] * p["reps"]
    for k, side in enumerate(sides[: p["reps"]]):
        t = 0.5 + 0.5 * k
        hit = {**guard, **arm(side, flex=1.5, abd=0.1, twist=0.0, elbow=0.05, reach=0.3),
               "spine_twist": -0.35 * SIGN[side], "pelvis_twist": -0.1 * SIGN[side]}
        keys += [(t + 0.2, hit), (t + 0.5, guard)]
    keys.append((keys[-1][0] + 0.6, {}))
    return upper_body_piece(body, state, timed(keys, p["tempo"]))


def build_look_around(body: Body, state: State, p: Mapping) -> Piece:
    """Look to one side, then the other (``reps`` times), then ahead again."""
    keys: list[tuple[float, Mapping[str, float]]] = [(0.0, {})]
    sides = [p["first"], other(p["first"])] * p["reps"]
    for side in sides:
        look = pose(neck_twist=1.0 * SIGN[side], spine_twist=0.3 * SIGN[side], neck_pitch=-0.05)
        keys += [(keys[-1][0] + 0.7, look), (keys[-1][0] + 0.7 + p["hold"], look)]
    keys.append((keys[-1][0] + 0.7, {}))
    return upper_body_piece(body, state, timed(keys, p["tempo"]))


def build_stretch(body: Body, state: State, p: Mapping) -> Piece:
    """Stretch the arms overhead, to a side (with a side bend), or out to the sides."""
    overhead = arm("both", flex=2.95, abd=0.2, elbow=0.05)
    target = {
        "up": {**overhead, "spine_pitch": -0.15, "neck_pitch": -0.2},
        "left": {**overhead, "spine_lean": 0.45, "pelvis_lean": 0.05},
        "right": {**overhead, "spine_lean": -0.45, "pelvis_lean": -0.05},
        "out": {**arm("both", flex=0.0, abd=1.55, elbow=0.0, reach=-0.2), "spine_pitch": -0.1},
    }[p["mode"]]
    keys = [(0.0, {}), (1.0, target), (1.0 + p["hold"], target), (2.0 + p["hold"], {})]
    return upper_body_piece(body, state, timed(keys, p["tempo"]))


# ---------------------------------------------------------------------------------------------
# Parameter samplers
# ---------------------------------------------------------------------------------------------


def sample_punch(rng: np.random.Generator) -> dict:
    side = pick_side(rng, both=0.2)
    reps = int(rng.integers(2, 7)) if side == "both" else int(rng.integers(1, 5))
    return dict(side=side, reps=reps, tempo=uniform(rng, 0.8, 1.2))


def sample_wave(rng: np.random.Generator) -> dict:
    return dict(side=pick_side(rng, both=0.2), reps=int(rng.integers(2, 6)), tempo=uniform(rng, 0.8, 1.2))


def sample_raise_arms(rng: np.random.Generator) -> dict:
    return dict(side=pick_side(rng, both=0.5), direction=pick(rng, ("up", "forward", "sideways"), (0.5, 0.25, 0.25)),
                hold=uniform(rng, 0.5, 2.0), tempo=uniform(rng, 0.8, 1.2))


def sample_clap(rng: np.random.Generator) -> dict:
    return dict(reps=int(rng.integers(3, 8)), overhead=bool(rng.random() < 0.25), tempo=uniform(rng, 0.8, 1.2))


def sample_stretch(rng: np.random.Generator) -> dict:
    return dict(mode=pick(rng, ("up", "left", "right", "out")), hold=uniform(rng, 0.8, 2.0),
                tempo=uniform(rng, 0.85, 1.2))


def sample_look_around(rng: np.random.Generator) -> dict:
    return dict(first=pick_side(rng), reps=pick(rng, (1, 2), (0.7, 0.3)), hold=uniform(rng, 0.2, 0.8),
                tempo=uniform(rng, 0.8, 1.2))
