"""Locomotion actions of the synthetic motion library: walk, jog, run, circle and turn on the spot.

A gait planner puts footsteps along a ground path (:class:`Path`) with a stepping pattern
(:class:`Gait`); each foot stays planted during its stance, and the pelvis moves over the stance
feet with the gait's bob, sway, lean and arm swing.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from scipy.integrate import cumulative_trapezoid

from data.synthetic_builders import FOOT, SIGN, body_scale, pick, pick_side, uniform
from data.synthetic_motion import (
    CH,
    FOOT_SIGN,
    FPS,
    LEFT,
    NEUTRAL,
    RIGHT,
    Body,
    Piece,
    State,
    forward,
    frames,
    hold,
    leftward,
    rest_root,
    smoothstep,
    swing_height,
    swing_progress,
    window,
    wrap,
)

# ---------------------------------------------------------------------------------------------
# Gait: a path, footsteps along it, the pelvis over them
# ---------------------------------------------------------------------------------------------

_DT = 1.0 / (4 * FPS)


@dataclass(frozen=True)
class Gait:
    """A stepping pattern.

    Attributes:
        cadence: steps per second at full speed.
        duty: fraction of its stride a foot spends on the ground at full speed (< 0.5: flight).
        speed: full speed (m/s); a running gait's duty grows back to a walk's as it slows.
        clearance: toe height at mid-swing.
        width: stance half-width as a multiple of the body's.
        lead_bias: 0 for alternating feet, 1 for step-close (side stepping).
        toe_off: heel lift (rad) when the toe leaves the ground.
        strike: toe pointing (rad) at touch-down (forefoot strike when running).
        dip: how much lower than standing the pelvis travels.
        bob: amplitude of the pelvis' vertical oscillation.
        sway: amplitude of its lateral oscillation.
        lean: forward lean (rad).
        arm_swing / elbow: arm swing amplitude and elbow flexion (rad).
        running: pelvis low at mid-stance and high in flight (else the reverse).
        over: when (as a fraction of its stance) the pelvis passes over a planted foot.
        heel_off: last fraction of the stance during which the heel rises.
    """

    cadence: float
    duty: float
    clearance: float
    width: float = 1.0
    lead_bias: float = 0.0
    toe_off: float = 0.5
    strike: float = 0.0
    dip: float = 0.015
    bob: float = 0.015
    sway: float = 0.02
    lean: float = 0.04
    arm_swing: float = 0.3
    elbow: float = 0.35
    running: bool = False
    speed: float = 0.0
    over: float = 0.5
    heel_off: float = 0.35

    def duty_at(self, activity: float) -> float:
        """Stance fraction at a fraction ``activity`` of full speed."""
        if not self.running:
            return self.duty
        speed = activity * self.speed
        return float(np.interp(speed, (1.2, 1.8), (0.62, 0.44 - 0.025 * speed)))


def walk_gait(speed: float, scale: float = 1.0) -> Gait:
    """Walking at ``speed`` m/s (cadence grows with speed; a taller body takes longer steps)."""
    return Gait(cadence=(1.2 + 0.6 * speed) / scale, duty=0.62 - 0.03 * (speed - 1.0), clearance=0.11,
                toe_off=0.7, arm_swing=0.2 + 0.15 * speed, elbow=0.3 + 0.1 * speed, lean=0.02 + 0.03 * speed,
                over=0.4)


def run_gait(speed: float, scale: float = 1.0) -> Gait:
    """Jogging (about 2 m/s) or running at ``speed`` m/s."""
    return Gait(cadence=(2.45 + 0.14 * speed) / scale, duty=0.44 - 0.025 * speed, clearance=0.15 + 0.08 * speed,
                toe_off=0.6, strike=0.3, dip=0.05 + 0.01 * speed, bob=0.03, sway=0.01, lean=0.08 + 0.04 * speed,
                arm_swing=0.35 + 0.1 * speed, elbow=1.4, running=True, speed=speed, over=0.4)


def side_gait(speed: float, scale: float = 1.0) -> Gait:
    """Side stepping (feet never cross)."""
    return Gait(cadence=2.1 / scale, duty=0.65, clearance=0.09, width=1.5, lead_bias=0.6, toe_off=0.25,
                sway=0.0, lean=0.02, arm_swing=0.05, elbow=0.3)


def turn_gait(scale: float = 1.0) -> Gait:
    """Stepping round on the spot."""
    return Gait(cadence=2.0 / scale, duty=0.66, clearance=0.08, width=1.1, toe_off=0.2, dip=0.01, bob=0.005,
                sway=0.015, lean=0.0, arm_swing=0.05, elbow=0.3)


def ramp_time(speed: float) -> float:
    """Seconds to reach (or stop from) ``speed`` m/s (peak acceleration under 3.5 m/s^2)."""
    return 0.5 + speed / 2.5


@dataclass(frozen=True)
class Path:
    """The pelvis' ground path sampled on a fine grid; it stops moving at ``end`` seconds."""

    t: np.ndarray
    xz: np.ndarray
    heading: np.ndarray
    activity: np.ndarray  # 0..1: how much of the full speed / turning is under way

    @property
    def end(self) -> float:
        return float(self.t[-1])

    def at(self, time: np.ndarray | float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(xz, heading, activity) at ``time`` (held after the end)."""
        time = np.clip(np.asarray(time, dtype=np.float64), 0.0, self.end)
        xz = np.stack([np.interp(time, self.t, self.xz[:, k]) for k in (0, 1)], axis=-1)
        return xz, np.interp(time, self.t, self.heading), np.interp(time, self.t, self.activity)


def make_path(start: np.ndarray, heading: float, move_time: float, speed: float = 0.0, travel: float = 0.0,
              turn: float = 0.0, turn_span: tuple[float, float] = (0.0, 1.0), curvature: float = 0.0,
              ramp: float | None = None) -> Path:
    """A path that speeds up, travels at ``speed`` in direction ``travel`` relative to the heading,
    turns by ``turn`` radians during ``turn_span`` (fractions of ``move_time``) and/or along a
    constant ``curvature`` (1/m, positive to the left), and slows to a stop at ``move_time``.
    Speeding up and slowing down take ``ramp`` seconds (default: longer for faster motion)."""
    t = np.arange(0.0, move_time + _DT / 2, _DT)
    activity = window(t, 0.0, move_time, ramp if ramp is not None else ramp_time(speed))
    velocity = speed * activity
    a, b = (f * move_time for f in turn_span)
    x = np.clip((t - a) / (b - a), 0.0, 1.0)
    yaw_rate = turn * 30.0 * x**2 * (1.0 - x) ** 2 / (b - a) + curvature * velocity
    headings = heading + cumulative_trapezoid(yaw_rate, t, initial=0.0)
    step = forward(headings + travel) * velocity[:, None]
    xz = np.asarray(start, dtype=np.float64) + cumulative_trapezoid(step, t, axis=0, initial=0.0)
    if speed == 0.0:
        activity = np.maximum(activity, np.abs(yaw_rate) / max(np.abs(yaw_rate).max(), 1e-9))
    return Path(t, xz, headings, activity)


@dataclass
class Stance:
    """A foot on the ground from ``start`` to ``end`` seconds at a fixed toe position and yaw."""

    start: float
    end: float
    toe: np.ndarray
    yaw: float


def _plant(body: Body, path: Path, gait: Gait, time: float, foot: int) -> tuple[np.ndarray, float]:
    """Toe position and yaw of ``foot`` when the pelvis is at the path point of ``time``."""
    xz, heading, _ = path.at(time)
    sign = FOOT_SIGN[foot]
    toe_xz = xz + forward(heading) * body.toe_forward + leftward(heading) * sign * body.half_width * gait.width
    return np.array([toe_xz[0], 0.0, toe_xz[1]]), float(heading + sign * body.toe_out)


def footsteps(body: Body, state: State, path: Path, gait: Gait, first: int, start: float = 0.1
              ) -> tuple[list[list[Stance]], list[tuple[float, int]]]:
    """Stances of each foot along ``path`` and the (time, foot) of every touch-down.

    Steps alternate from ``first``; each foot lands where the pelvis will be at its mid-stance
    (shifted by ``lead_bias`` for side stepping) and keeps stepping until it stands on the
    path's final stance.
    """
    stances = [[Stance(-np.inf, np.inf, state.toes[f].copy(), float(state.yaws[f]))] for f in (LEFT, RIGHT)]
    done = [False, False]
    landings: list[tuple[float, int]] = []
    time, foot = start, first
    while not all(done):
        cadence = gait.cadence
        if not done[foot]:
            land = time
            for _ in range(3):  # the stance that follows the landing has the duty of the landing speed
                duty = gait.duty_at(float(path.at(land)[2]))
                land = time + 2.0 / cadence * (1.0 - duty)
            lead = 1.0 if foot == first else -1.0
            target = land + (2 * gait.over * duty + lead * gait.lead_bias / 2) / cadence
            done[foot] = target >= path.end
            toe, yaw = _plant(body, path, gait, min(target, path.end), foot)
            stances[foot][-1].end = time
            stances[foot].append(Stance(land, np.inf, toe, yaw))
            landings.append((land, foot))
        time += 1.0 / cadence
        foot = 1 - foot
    return stances, sorted(landings)


def foot_track(stances: list[Stance], t: np.ndarray, gait: Gait) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-frame toe position (N, 3), yaw (N,) and pitch (N,) of one foot through its stances."""
    toes, yaws, pitch = np.zeros((len(t), 3)), np.zeros(len(t)), np.zeros(len(t))
    for i, st in enumerate(stances):
        on = (t >= st.start) & (t < st.end)
        toes[on], yaws[on] = st.toe, st.yaw
        if np.isfinite(st.start):
            pitch[on] += gait.strike * (1.0 - smoothstep((t[on] - st.start) / 0.12))
        if np.isfinite(st.end):
            lift = max(gait.heel_off * (st.end - max(st.start, st.end - 1.0)), 1e-3)
            pitch[on] += gait.toe_off * smoothstep((t[on] - (st.end - lift)) / lift)
            nxt = stances[i + 1]
            air = (t >= st.end) & (t < nxt.start)
            s = (t[air] - st.end) / (nxt.start - st.end)
            p = swing_progress(s, gait.running)[:, None]
            toes[air] = st.toe + (nxt.toe - st.toe) * p
            toes[air, 1] = swing_height(s, gait.clearance, gait.running)
            yaws[air] = st.yaw + wrap(nxt.yaw - st.yaw) * p[:, 0]
            pitch[air] = gait.toe_off * (1.0 - smoothstep(s / 0.7)) + gait.strike * s**2
    return toes, yaws, pitch


def _step_phase(t: np.ndarray, landings: list[tuple[float, int]]) -> tuple[np.ndarray, np.ndarray]:
    """Continuous step count at ``t`` and the left leg's gait phase (0 at a left touch-down)."""
    times = np.array([time for time, _ in landings])
    count = np.interp(t, times, np.arange(len(times)), left=0.0, right=len(times) - 1.0)
    left_index = next(i for i, (_, foot) in enumerate(landings) if foot == LEFT)
    return count, (count - left_index) / 2.0


def locomotion(body: Body, state: State, path: Path, gait: Gait, first: int) -> Piece:
    """Walk/run/step along ``path`` with ``gait``, starting with foot ``first``."""
    stances, landings = footsteps(body, state, path, gait, first)
    end = max(st[-1].start for st in stances) + 0.35
    n = frames(end)
    t = np.arange(n) / FPS
    plan = hold(body, state, n)
    for foot in (LEFT, RIGHT):
        plan.toes[:, foot], plan.yaws[:, foot], plan.pitch[:, foot] = foot_track(stances[foot], t, gait)
    xz, heading, activity = path.at(t)
    count, phase = _step_phase(t, landings)
    mid = count - (0.36 if gait.running else 0.5)
    bob = gait.bob * np.cos(2 * np.pi * mid) * (1.0 if gait.running else -1.0)
    plan.heading = heading
    plan.root[:, [0, 2]] = xz + leftward(heading) * (gait.sway * activity * np.cos(2 * np.pi * (phase - 0.25)))[:, None]
    plan.root[:, 1] = body.stand_height + activity * (bob - gait.dip)
    swing = np.cos(2 * np.pi * phase) * activity
    ch = plan.channels
    ch[:, CH["pelvis_twist"]] = -0.08 * swing * gait.arm_swing / 0.4
    ch[:, CH["spine_twist"]] = 0.12 * swing * gait.arm_swing / 0.4
    ch[:, CH["pelvis_pitch"]] += gait.lean * activity
    ch[:, CH["spine_pitch"]] += 0.5 * gait.lean * activity
    for prefix, sign in (("l", -1.0), ("r", 1.0)):
        flex = sign * gait.arm_swing * swing
        ch[:, CH[f"{prefix}_flex"]] = flex
        elbow = CH[f"{prefix}_elbow"]
        ch[:, elbow] += activity * (gait.elbow - NEUTRAL[elbow]) + 0.3 * np.maximum(flex, 0)
    toes = np.stack([st[-1].toe for st in stances])
    yaws = np.array([st[-1].yaw for st in stances])
    steady = np.flatnonzero(activity > 0.999)
    window_ = (int(steady[0]), int(steady[-1]) + 1) if len(steady) > 1 else None
    return Piece(plan, State(toes, yaws, float(path.heading[-1])), window_)


# ---------------------------------------------------------------------------------------------
# Builders
# ---------------------------------------------------------------------------------------------

_TRAVEL = {"forward": 0.0, "backward": np.pi, "left": np.pi / 2, "right": -np.pi / 2}


def _start_xz(body: Body, state: State) -> np.ndarray:
    return rest_root(body, state)[[0, 2]]


def build_walk(body: Body, state: State, p: Mapping) -> Piece:
    """Walk forward/backward/sideways; forward walks may veer left or right by 90 degrees."""
    direction, speed = p["direction"], p["speed"]
    gait = side_gait(speed, body_scale(body)) if direction in ("left", "right") else walk_gait(speed, body_scale(body))
    veer = SIGN[p["veer"]] * np.pi / 2 if p.get("veer") else 0.0
    path = make_path(_start_xz(body, state), state.heading, p["move_time"], speed, _TRAVEL[direction],
                     turn=veer, turn_span=(0.4, 0.75))
    first = FOOT[direction] if direction in FOOT else FOOT[p["lead"]]
    return locomotion(body, state, path, gait, first)


def build_run(body: Body, state: State, p: Mapping) -> Piece:
    """Jog or run forward."""
    path = make_path(_start_xz(body, state), state.heading, p["move_time"], p["speed"])
    return locomotion(body, state, path, run_gait(p["speed"], body_scale(body)), FOOT[p["lead"]])


def build_circle(body: Body, state: State, p: Mapping) -> Piece:
    """Walk (or jog) one full circle, counter-clockwise = turning left."""
    speed, radius = p["speed"], p["radius"]
    sign = 1.0 if p["direction"] == "counterclockwise" else -1.0
    ramp = ramp_time(speed)
    move_time = 2 * np.pi * radius / speed + ramp
    path = make_path(_start_xz(body, state), state.heading, move_time, speed, curvature=sign / radius, ramp=ramp)
    gait = run_gait(speed, body_scale(body)) if p.get("jog") else walk_gait(speed, body_scale(body))
    return locomotion(body, state, path, gait, LEFT if sign > 0 else RIGHT)


def build_turn(body: Body, state: State, p: Mapping) -> Piece:
    """Turn on the spot by ``angle`` degrees to the left or right, stepping round."""
    angle = np.radians(p["angle"]) * SIGN[p["direction"]]
    path = make_path(_start_xz(body, state), state.heading, abs(angle) / p["rate"] + 0.3, turn=angle, ramp=0.3)
    piece = locomotion(body, state, path, turn_gait(body_scale(body)), FOOT[p["direction"]])
    t = piece.plan.times
    piece.plan.channels[:, CH["neck_twist"]] += 0.25 * np.sign(angle) * window(t, 0.0, path.end, 0.3)
    piece.plan.channels[:, CH["spine_twist"]] += 0.12 * np.sign(angle) * window(t, 0.0, path.end, 0.3)
    return piece


# ---------------------------------------------------------------------------------------------
# Parameter samplers
# ---------------------------------------------------------------------------------------------

_PACES = {"slow": (0.82, 1.05), "normal": (1.1, 1.45), "fast": (1.5, 1.78)}
_RUN_PACES = {"normal": (2.6, 3.3), "fast": (3.3, 3.95)}


def sample_walk(rng: np.random.Generator) -> dict:
    direction = pick(rng, ("forward", "backward", "left", "right"), (0.55, 0.15, 0.15, 0.15))
    lead = pick_side(rng)
    if direction == "forward":
        pace = pick(rng, ("slow", "normal", "fast"), (0.3, 0.4, 0.3))
        veer = pick(rng, (None, "left", "right"), (0.8, 0.1, 0.1))
        move = uniform(rng, 4.0, 6.0) if veer else uniform(rng, 2.5, 6.0)
        return dict(direction=direction, pace=pace, speed=uniform(rng, *_PACES[pace]), move_time=move, veer=veer,
                    lead=lead)
    if direction == "backward":
        pace = pick(rng, ("slow", "normal"))
        speed = uniform(rng, 0.6, 0.8) if pace == "slow" else uniform(rng, 0.8, 1.1)
        return dict(direction=direction, pace=pace, speed=speed, move_time=uniform(rng, 2.0, 4.0), veer=None, lead=lead)
    speed = uniform(rng, 0.45, 0.75)
    pace = "slow" if speed < 0.55 else "normal"
    return dict(direction=direction, pace=pace, speed=speed, move_time=uniform(rng, 2.0, 3.5), veer=None, lead=lead)


def sample_jog(rng: np.random.Generator) -> dict:
    speed = uniform(rng, 1.9, 2.5)
    return dict(pace="normal", speed=speed, move_time=round(2 * ramp_time(speed) + uniform(rng, 0.6, 2.0), 3),
                lead=pick_side(rng))


def sample_run(rng: np.random.Generator) -> dict:
    pace = pick(rng, ("normal", "fast"))
    speed = uniform(rng, *_RUN_PACES[pace])
    return dict(pace=pace, speed=speed, move_time=round(2 * ramp_time(speed) + uniform(rng, 0.6, 1.6), 3),
                lead=pick_side(rng))


def sample_circle(rng: np.random.Generator) -> dict:
    jog = bool(rng.random() < 0.15)
    speed = uniform(rng, 1.9, 2.3) if jog else uniform(rng, 0.8, 1.2)
    radius = uniform(rng, 0.7, min(1.4, 6.5 * speed / (2 * np.pi)) if not jog else 1.6)
    pace = "normal" if jog or speed > 0.95 else "slow"
    return dict(direction=pick(rng, ("clockwise", "counterclockwise")), speed=speed, radius=radius, jog=jog, pace=pace)


def sample_turn(rng: np.random.Generator) -> dict:
    angle = pick(rng, (45, 90, 135, 180, 360), (0.1, 0.35, 0.1, 0.3, 0.15))
    return dict(direction=pick_side(rng), angle=angle, rate=uniform(rng, 1.6, 2.6))
