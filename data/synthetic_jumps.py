"""Jumping actions of the synthetic motion library: jump with both feet, hop on one leg and
jumping jacks.

The pelvis follows a ballistic arc during each flight; the feet leave the floor at take-off,
follow the pelvis and land on their new toe targets, with the heels raised around take-off and
landing.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from data.synthetic_builders import FOOT, SIGN, body_scale, other, pick, pick_side, uniform
from data.synthetic_motion import (
    FOOT_PITCH,
    FOOT_SIGN,
    FPS,
    LEFT,
    RIGHT,
    Body,
    Piece,
    Plan,
    State,
    arm,
    forward,
    frames,
    hold,
    interp_keys,
    leftward,
    pose_track,
    rest_root,
    shift_root,
)

GRAVITY = 9.81


def _flight_time(height: float) -> float:
    """Seconds in the air of a jump whose centre of mass rises ``height`` metres."""
    return 2.0 * np.sqrt(2.0 * height / GRAVITY)


def _flights(t: np.ndarray, take_offs: Sequence[float], flight: float) -> np.ndarray:
    """(N,) number of flights completed by ``t`` (fractional while in the air)."""
    return sum(np.clip((t - t0) / flight, 0.0, 1.0) for t0 in take_offs)


def _ballistic(plan: Plan, take_offs: Sequence[float], flight: float, lift: float) -> None:
    """Pelvis height on a ballistic arc during each flight, from ``lift`` above rest, in place."""
    t = plan.times
    base = plan.root[0, 1]
    for t0 in take_offs:
        air = (t >= t0) & (t < t0 + flight)
        tau = t[air] - t0
        plan.root[air, 1] = base + lift + GRAVITY * flight / 2 * tau - GRAVITY * tau**2 / 2


def _airborne(plan: Plan, feet: Sequence[int], t0: float, flight: float, lift: float, tuck: float,
              targets: np.ndarray, pitch: float) -> None:
    """Feet leave the floor at ``t0`` following the pelvis (tucking up ``tuck``), land on
    ``targets`` (2, 3) and stay there, in place; ``lift`` is the pelvis rise at take-off."""
    t = plan.times
    air = (t >= t0) & (t < t0 + flight)
    s = (t[air] - t0) / flight
    rise = plan.root[air, 1] - plan.root[0, 1] - lift
    for f in feet:
        start = plan.toes[max(np.searchsorted(t, t0) - 1, 0), f].copy()
        plan.toes[air, f] = start + np.outer(s, targets[f] - start)
        plan.toes[air, f, 1] = rise + tuck * np.sin(np.pi * s)
        plan.pitch[air, f] = pitch
        plan.toes[t >= t0 + flight, f] = targets[f]


def _heel_lift(body: Body, heel: float) -> float:
    """How much the ankle rises when the heel lifts by ``heel`` radians about the toe."""
    return body.foot * (np.sin(FOOT_PITCH + heel) - np.sin(FOOT_PITCH))


def _curve(keys: Sequence[tuple[float, float]], n: int) -> np.ndarray:
    """(n,) scalar curve through ``(t, value)`` keys."""
    return interp_keys([k[0] for k in keys], [k[1] for k in keys], n)


def build_jump(body: Body, state: State, p: Mapping) -> Piece:
    """Jump in place or forward with both feet, ``reps`` times, swinging the arms."""
    height, distance, reps = p["height"], p["distance"], p["reps"]
    flight, heel, crouch = _flight_time(height), 0.65, 0.14 * body_scale(body)
    lift = _heel_lift(body, heel) + 0.01
    prep, push, absorb = 0.45, 0.15, 0.45
    period = prep + push + flight + absorb + p["pause"]
    n = frames(period * reps + 0.3)
    plan = hold(body, state, n)
    load = {**arm("both", flex=-0.6, abd=0.15, elbow=0.3), "pelvis_pitch": 0.3, "spine_pitch": 0.25}
    reach = arm("both", flex=1.8 + height, abd=0.1, elbow=0.3)
    keys: list[tuple[float, Mapping[str, float]]] = [(0.0, {})]
    heights, heels = [(0.0, 0.0)], [(0.0, 0.0)]
    take_offs = [period * k + prep + push for k in range(reps)]
    for t0 in take_offs:
        land = t0 + flight
        keys += [(t0 - push, load), (t0, reach), (land + 0.15, load), (land + absorb, {})]
        heights += [(t0 - push, -crouch), (t0, lift), (land, lift), (land + 0.15, -1.1 * crouch), (land + absorb, 0.0)]
        heels += [(t0 - push, 0.0), (t0, heel), (land, heel), (land + 0.1, 0.0)]
    plan.channels = pose_track(keys + [(n / FPS, {})], n, state.rest)
    plan.root[:, 1] += _curve(heights, n)
    plan.pitch[:] = _curve(heels, n)[:, None]
    step = forward(state.heading) * distance
    plan.root[:, [0, 2]] += np.outer(_flights(plan.times, take_offs, flight), step)
    _ballistic(plan, take_offs, flight, lift)
    toes = state.toes.copy()
    for t0 in take_offs:
        toes[:, [0, 2]] += step
        _airborne(plan, (LEFT, RIGHT), t0, flight, lift, 0.1 * height / 0.3, toes.copy(), heel)
    return Piece(plan, State(toes, state.yaws.copy(), state.heading))


def _carry_foot(plan: Plan, body: Body, state: State, foot: int,
                keys: Sequence[tuple[float, float, float, float, float]]) -> None:
    """Carry a lifted foot with the pelvis: toe = pelvis + rest offset + keyed body-frame offset
    ``(t, ahead, up, out, pitch)``; zero offsets at the first and last key put it on the floor."""
    n = len(plan)
    rel = interp_keys([k[0] for k in keys], [k[1:] for k in keys], n)
    root0 = rest_root(body, state)
    rest = state.toes[foot] - root0
    fwd, lat = forward(state.heading), leftward(state.heading) * FOOT_SIGN[foot]
    xz = rest[[0, 2]] + np.outer(rel[:, 0], fwd) + np.outer(rel[:, 2], lat)
    plan.toes[:, foot, 0] = plan.root[:, 0] + xz[:, 0]
    plan.toes[:, foot, 2] = plan.root[:, 2] + xz[:, 1]
    plan.toes[:, foot, 1] = np.maximum(plan.root[:, 1] - root0[1] + rel[:, 1], 0.0)
    plan.pitch[:, foot] = rel[:, 3]


def build_hop(body: Body, state: State, p: Mapping) -> Piece:
    """Hop ``reps`` times on one leg, the other foot held up behind."""
    side, height, distance, reps = p["side"], p["height"], p["distance"], p["reps"]
    stance, free = FOOT[side], FOOT[other(side)]
    flight, heel = _flight_time(height), 0.6
    lift = _heel_lift(body, heel)
    prep, absorb, settle = 0.3, 0.2, 0.6
    period = prep + flight + absorb
    end = settle + period * reps
    n = frames(end + 0.8)
    plan = hold(body, state, n)
    arms = {**arm("both", flex=0.3, abd=0.45, elbow=0.8), "spine_lean": 0.08 * SIGN[side]}
    plan.channels = pose_track([(0.0, {}), (settle, arms), (end, arms), (end + 0.7, {})], n, state.rest)
    take_offs = [settle + period * k + prep for k in range(reps)]
    heights, heels = [(0.0, 0.0), (settle, -0.02)], [(0.0, 0.0), (settle, 0.0)]
    for t0 in take_offs:
        heights += [(t0 - 0.1, -0.06), (t0, lift), (t0 + flight, lift), (t0 + flight + 0.1, -0.07)]
        heels += [(t0 - 0.1, 0.0), (t0, heel), (t0 + flight, heel), (t0 + flight + 0.08, 0.0)]
    heights.append((end + 0.7, 0.0))
    plan.root[:, 1] += _curve(heights, n)
    plan.pitch[:, stance] = _curve(heels, n)
    step = forward(state.heading) * distance
    sideways = interp_keys([0.0, settle, end, end + 0.7], [0.0, 0.9, 0.9, 0.0], n) * SIGN[side] * body.half_width
    shift_root(plan, left=sideways)
    plan.root[:, [0, 2]] += np.outer(_flights(plan.times, take_offs, flight), step)
    _ballistic(plan, take_offs, flight, lift)
    toes = state.toes.copy()
    for t0 in take_offs:
        toes[stance, [0, 2]] += step
        _airborne(plan, (stance,), t0, flight, lift, 0.03, toes.copy(), heel)
    toes[free, [0, 2]] += step * reps
    _carry_foot(plan, body, state, free, [(0.0, 0, 0, 0, 0), (0.2, 0, 0.06, 0, 0.2), (settle, -0.15, 0.3, -0.05, 0.7),
                                          (end, -0.15, 0.3, -0.05, 0.7), (end + 0.55, 0, 0.05, 0, 0.1),
                                          (end + 0.7, 0, 0, 0, 0)])
    return Piece(plan, State(toes, state.yaws.copy(), state.heading))


def build_jumping_jacks(body: Body, state: State, p: Mapping) -> Piece:
    """Jumping jacks: hop the feet apart with the arms overhead and back together, ``reps`` times."""
    height, reps = 0.06, p["reps"]
    flight, heel = _flight_time(height), 0.5
    lift = _heel_lift(body, heel)
    half = 0.3 + flight + 0.15
    n = frames(0.3 + 2 * half * reps + 0.6)
    plan = hold(body, state, n)
    wide = state.toes.copy()
    wide[:, [0, 2]] += np.outer([1.0, -1.0], leftward(state.heading)) * 0.2 * body_scale(body)
    keys: list[tuple[float, Mapping[str, float]]] = [(0.0, {})]
    heights, heels = [(0.0, 0.0)], [(0.0, 0.0)]
    take_offs = [0.3 + half * k + 0.2 for k in range(2 * reps)]
    for k, t0 in enumerate(take_offs):
        spread = k % 2 == 0
        keys.append((t0 + flight, arm("both", abd=2.7, elbow=0.2) if spread else arm("both", abd=0.3, elbow=0.25)))
        heights += [(t0 - 0.12, -0.05), (t0, lift), (t0 + flight, lift), (t0 + flight + 0.1, -0.06)]
        heels += [(t0 - 0.12, 0.0), (t0, heel), (t0 + flight, heel), (t0 + flight + 0.08, 0.0)]
    end = heights[-1][0] + 0.3
    plan.channels = pose_track(keys + [(end, {})], n, state.rest)
    plan.root[:, 1] += _curve(heights + [(end, 0.0)], n)
    plan.pitch[:] = _curve(heels, n)[:, None]
    _ballistic(plan, take_offs, flight, lift)
    for k, t0 in enumerate(take_offs):
        _airborne(plan, (LEFT, RIGHT), t0, flight, lift, 0.03, wide if k % 2 == 0 else state.toes, heel)
    return Piece(plan, state)


# ---------------------------------------------------------------------------------------------
# Parameter samplers
# ---------------------------------------------------------------------------------------------


def sample_jump(rng: np.random.Generator) -> dict:
    forward_ = bool(rng.random() < 0.4)
    return dict(reps=pick(rng, (1, 2, 3), (0.45, 0.35, 0.2)), distance=uniform(rng, 0.5, 1.1) if forward_ else 0.0,
                height=uniform(rng, 0.15, 0.3) if forward_ else uniform(rng, 0.12, 0.3), pause=uniform(rng, 0.1, 0.4))


def sample_hop(rng: np.random.Generator) -> dict:
    forward_ = bool(rng.random() < 0.3)
    return dict(side=pick_side(rng), reps=int(rng.integers(2, 6)), height=uniform(rng, 0.05, 0.1),
                distance=uniform(rng, 0.15, 0.3) if forward_ else 0.0)


def sample_jumping_jacks(rng: np.random.Generator) -> dict:
    return dict(reps=int(rng.integers(2, 6)))
