"""Procedural human motion on the HumanML3D skeleton: bodies, motion plans and their realisation.

The shared core of the embedded dataset's generator (:mod:`data.synthetic`); the actions are
written on it by one module per action family, registered in :mod:`data.synthetic_library`.

A motion is first *planned* as per-frame targets (:class:`Plan`): the pelvis position and
heading, the angles of the trunk, head and arms (the named :data:`CHANNELS`), and for each foot a
toe target (position, yaw and extra plantar flexion). :func:`realize` turns a plan into global
joint positions on a :class:`Body`:

1. the channels become local rotation matrices of the spine, neck, collars, shoulders, elbows;
2. the pelvis is lowered wherever a leg could not reach its foot target;
3. analytic two-bone leg IK (knee hinge along the foot's lateral axis) gives hip, knee and ankle
   rotations that put each toe exactly on its target;
4. forward kinematics with the body's constant rest bone vectors gives the joints.

A foot in stance keeps a fixed toe target, so it does not slide. Bone lengths are constant by
construction. An action writes a :class:`Piece` (its plan and the :class:`State` it ends in) and
:func:`assemble` plays pieces back to back.

Conventions: y up, the body faces +z at heading 0 and its left is +x; a positive heading turns it
to its left (counter-clockwise seen from above). Units are metres, seconds and radians.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import PchipInterpolator
from scipy.ndimage import gaussian_filter1d, maximum_filter1d

from data.skeleton import HUMANML3D

FPS = HUMANML3D.fps
J = HUMANML3D.joints_num
PARENTS = np.array(HUMANML3D.parents)
LEFT, RIGHT = 0, 1  # foot / leg index in plans
FOOT_SIGN = (1.0, -1.0)  # +x is the body's left
LEGS = ((1, 4, 7, 10), (2, 5, 8, 11))  # hip, knee, ankle, toe joints of the left and right leg

CHANNELS: tuple[str, ...] = (
    "pelvis_pitch", "pelvis_twist", "pelvis_lean",
    "spine_pitch", "spine_twist", "spine_lean",
    "neck_pitch", "neck_twist", "neck_lean",
    "l_shrug", "l_reach", "l_flex", "l_abd", "l_twist", "l_elbow",
    "r_shrug", "r_reach", "r_flex", "r_abd", "r_twist", "r_elbow",
)  # fmt: skip
"""Upper-body angle channels. Pitch bends forward, twist turns to the body's left, lean tilts
to its left. Arm channels are side-relative: flex raises the arm forward, abd raises it out to
its own side, twist rotates it outward, elbow flexes; shrug lifts and reach protracts the collar."""
CH: dict[str, int] = {name: i for i, name in enumerate(CHANNELS)}
ARM_KEYS = ("shrug", "reach", "flex", "abd", "twist", "elbow")
GROUPS: dict[str, tuple[int, ...]] = {
    "left_arm": tuple(CH[f"l_{k}"] for k in ARM_KEYS),
    "right_arm": tuple(CH[f"r_{k}"] for k in ARM_KEYS),
    "both_arms": tuple(CH[f"{s}_{k}"] for s in "lr" for k in ARM_KEYS),
    "head": (CH["neck_pitch"], CH["neck_twist"], CH["neck_lean"]),
}
_SPINE_SHARE = {3: 0.3, 6: 0.35, 9: 0.35}  # how spine channels spread over spine1..3


def pose(**values: float) -> dict[str, float]:
    """A partial pose: channel name -> angle (checks the names)."""
    unknown = set(values) - set(CH)
    if unknown:
        raise KeyError(f"unknown channels {sorted(unknown)}")
    return values


def arm(side: str, **values: float) -> dict[str, float]:
    """A partial pose of one arm (``side`` left/right) or both (``both``), e.g. ``arm("left", flex=1)``."""
    prefixes = ("l", "r") if side == "both" else (side[0],)
    return pose(**{f"{p}_{k}": v for p in prefixes for k, v in values.items()})


NEUTRAL = np.zeros(len(CHANNELS))
for _name, _value in {**pose(spine_pitch=0.03), **arm("both", abd=0.12, elbow=0.25)}.items():
    NEUTRAL[CH[_name]] = _value
SEATED = NEUTRAL.copy()  # hands resting on the thighs
for _name, _value in {**pose(spine_pitch=0.08), **arm("both", flex=0.45, abd=0.1, elbow=1.0)}.items():
    SEATED[CH[_name]] = _value


# ---------------------------------------------------------------------------------------------
# Rotations (numpy only: the generator's worker processes do not import torch, which
# data.rotations does)
# ---------------------------------------------------------------------------------------------


def axis_rotation(axis: int, angle: np.ndarray | float) -> np.ndarray:
    """(..., 3, 3) rotation matrices about coordinate axis 0 (x), 1 (y) or 2 (z)."""
    angle = np.asarray(angle, dtype=np.float64)
    c, s = np.cos(angle), np.sin(angle)
    out = np.zeros(angle.shape + (3, 3))
    i, j = ((1, 2), (2, 0), (0, 1))[axis]
    out[..., axis, axis] = 1.0
    out[..., i, i] = c
    out[..., j, j] = c
    out[..., i, j] = -s
    out[..., j, i] = s
    return out


def expmap(v: np.ndarray) -> np.ndarray:
    """(..., 3) rotation vectors -> (..., 3, 3) matrices (Rodrigues)."""
    v = np.asarray(v, dtype=np.float64)
    theta = np.linalg.norm(v, axis=-1)[..., None, None]
    k = np.zeros(v.shape + (3,))
    k[..., 0, 1], k[..., 0, 2], k[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    k = k - np.swapaxes(k, -1, -2)
    safe = np.where(theta < 1e-9, 1.0, theta)
    return np.eye(3) + np.sin(theta) / safe * k + (1.0 - np.cos(theta)) / safe**2 * (k @ k)


def _normalize(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def _frame(bone: np.ndarray, hinge: np.ndarray) -> np.ndarray:
    """Right-handed frames (..., 3, 3), columns: hinge made orthogonal to bone, bone, their cross."""
    b = _normalize(bone)
    h = _normalize(hinge - np.sum(hinge * b, axis=-1, keepdims=True) * b)
    return np.stack([h, b, np.cross(h, b)], axis=-1)


def _align(rest_bone: np.ndarray, bone: np.ndarray, hinge: np.ndarray) -> np.ndarray:
    """Global rotation taking a rest bone (hinge +x) onto ``bone`` with its hinge on ``hinge``."""
    rest = _frame(rest_bone, np.array([1.0, 0.0, 0.0]))
    return _frame(bone, hinge) @ rest.T


def forward(heading: np.ndarray | float) -> np.ndarray:
    """(..., 2) unit x/z vector the body faces at ``heading``."""
    heading = np.asarray(heading, dtype=np.float64)
    return np.stack([np.sin(heading), np.cos(heading)], axis=-1)


def leftward(heading: np.ndarray | float) -> np.ndarray:
    """(..., 2) unit x/z vector to the body's left at ``heading``."""
    heading = np.asarray(heading, dtype=np.float64)
    return np.stack([np.cos(heading), -np.sin(heading)], axis=-1)


def wrap(angle: np.ndarray | float) -> np.ndarray:
    """Angles wrapped to (-pi, pi]."""
    return np.pi - np.mod(np.pi - np.asarray(angle, dtype=np.float64), 2 * np.pi)


# ---------------------------------------------------------------------------------------------
# Bodies
# ---------------------------------------------------------------------------------------------

# Rest bone directions (y up, facing +z, left +x), the SMPL neutral template with the legs and
# arms hanging straight down; right-side joints mirror the left ones.
_REST_LEFT = {
    1: (0.059, -0.086, -0.016), 3: (0.0, 0.124, -0.038), 4: (0.0, -1.0, 0.0), 6: (0.0, 0.138, 0.027),
    7: (0.0, -1.0, 0.0), 9: (0.0, 0.056, 0.003), 12: (0.0, 0.212, -0.034), 13: (0.077, 0.113, -0.021),
    15: (0.0, 0.089, 0.050), 16: (0.118, 0.046, -0.014), 18: (0.0, -1.0, 0.0), 20: (0.0, -1.0, 0.0),
}  # fmt: skip
_MIRROR = dict(HUMANML3D.mirror_pairs)
FOOT_PITCH = 0.43  # rest foot bone: the toe joint lies 25 degrees below the ankle (SMPL)
_LENGTH_GROUPS = {  # bone groups whose lengths vary together, and how much (+-)
    (4, 5, 7, 8): 0.05, (3, 6, 9, 12): 0.07, (15,): 0.08, (1, 2): 0.1,
    (13, 14, 16, 17): 0.1, (18, 19, 20, 21): 0.05, (10, 11): 0.06,
}  # fmt: skip


def rest_directions() -> np.ndarray:
    """(J, 3) unit rest bone directions (root row zero)."""
    dirs = np.zeros((J, 3))
    for joint, d in _REST_LEFT.items():
        dirs[joint] = d
        if joint in _MIRROR:
            dirs[_MIRROR[joint]] = (-d[0], d[1], d[2])
    dirs[10] = dirs[11] = (0.0, -np.sin(FOOT_PITCH), np.cos(FOOT_PITCH))
    dirs[1:] = _normalize(dirs[1:])
    return dirs


@dataclass(frozen=True)
class Body:
    """One subject: rest bone vectors and the standing/sitting geometry derived from them.

    Attributes:
        offsets: (J, 3) rest bone vectors (direction * length), constant over a motion.
        half_width: lateral distance of each toe from the pelvis when standing.
        toe_out: outward yaw of each foot when standing.
        toe_forward: how far the toes are ahead of the pelvis when standing.
        stand_height: pelvis height when standing at ease.
        seat_height / seat_back: pelvis height and backward shift when seated on a chair.
    """

    offsets: np.ndarray
    half_width: float
    toe_out: float
    toe_forward: float
    stand_height: float
    seat_height: float
    seat_back: float

    @property
    def lengths(self) -> np.ndarray:
        """(J,) bone lengths."""
        return np.linalg.norm(self.offsets, axis=-1)

    @property
    def thigh(self) -> float:
        return float(self.lengths[4])

    @property
    def shank(self) -> float:
        return float(self.lengths[7])

    @property
    def foot(self) -> float:
        return float(self.lengths[10])

    @property
    def leg(self) -> float:
        """Hip-to-ankle length of the straight leg."""
        return self.thigh + self.shank

    @property
    def ankle_height(self) -> float:
        """Ankle height above a flat foot's toe joint."""
        return self.foot * np.sin(FOOT_PITCH)


def _stand_height(offsets: np.ndarray, half_width: float, toe_out: float) -> tuple[float, float]:
    """(pelvis height, toe forward offset) of an at-ease stance (legs at 98.5% of full length)."""
    hip = offsets[1]
    foot = np.linalg.norm(offsets[10])
    reach = np.cos(FOOT_PITCH) * foot
    toe_forward = hip[2] + reach * np.cos(toe_out)
    lateral = half_width - reach * np.sin(toe_out) - hip[0]
    leg = 0.985 * (np.linalg.norm(offsets[4]) + np.linalg.norm(offsets[7]))
    return foot * np.sin(FOOT_PITCH) + np.sqrt(leg**2 - lateral**2) - hip[1], toe_forward


def make_body(lengths: np.ndarray, half_width_factor: float = 1.2, toe_out: float = 0.12) -> Body:
    """A body with the given (J,) bone lengths and stance."""
    offsets = rest_directions() * np.asarray(lengths, dtype=np.float64)[:, None]
    half_width = abs(offsets[1, 0]) * half_width_factor
    stand, toe_forward = _stand_height(offsets, half_width, toe_out)
    thigh, shank, foot = (float(np.linalg.norm(offsets[j])) for j in (4, 7, 10))
    seat = foot * np.sin(FOOT_PITCH) + 0.97 * shank - offsets[1, 1]
    return Body(offsets, half_width, toe_out, toe_forward, stand, seat, 0.92 * thigh)


def sample_body(rng: np.random.Generator, pelvis_height: tuple[float, float] = (0.9, 1.0)) -> Body:
    """A random adult: limb proportions jittered per bone group, scaled to a pelvis height."""
    lengths = HUMANML3D.bone_lengths.astype(np.float64).copy()
    for a, b in HUMANML3D.mirror_pairs:  # symmetric bodies
        lengths[[a, b]] = lengths[[a, b]].mean()
    for joints, spread in _LENGTH_GROUPS.items():
        lengths[list(joints)] *= rng.uniform(1.0 - spread, 1.0 + spread)
    width, toe_out = rng.uniform(1.0, 1.5), rng.uniform(0.05, 0.22)
    unit = make_body(lengths, width, toe_out)
    scale = rng.uniform(*pelvis_height) / unit.stand_height
    return make_body(lengths * scale, width, toe_out)


# ---------------------------------------------------------------------------------------------
# Plans and states
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class State:
    """Where a motion stands between two actions: planted toes, heading and posture."""

    toes: np.ndarray  # (2, 3) toe positions, left then right
    yaws: np.ndarray  # (2,) foot yaws
    heading: float
    posture: str = "stand"  # "stand" | "sit"

    @property
    def rest(self) -> np.ndarray:
        """The posture's resting channel values."""
        return SEATED if self.posture == "sit" else NEUTRAL


def stance_toes(body: Body, xz: np.ndarray, heading: float) -> tuple[np.ndarray, np.ndarray]:
    """Toe positions (2, 3) and yaws (2,) of the at-ease stance with the pelvis over ``xz``."""
    toes = np.zeros((2, 3))
    yaws = np.zeros(2)
    for foot in (LEFT, RIGHT):
        sign = FOOT_SIGN[foot]
        toes[foot, [0, 2]] = xz + forward(heading) * body.toe_forward + leftward(heading) * sign * body.half_width
        yaws[foot] = heading + sign * body.toe_out
    return toes, yaws


def initial_state(body: Body, heading: float = 0.0, posture: str = "stand") -> State:
    """At ease at the origin facing ``heading`` (seated: the pelvis is at the origin)."""
    toes, yaws = stance_toes(body, np.zeros(2), heading)
    if posture == "sit":
        toes[:, [0, 2]] += forward(heading) * body.seat_back
    return State(toes, yaws, heading, posture)


def rest_root(body: Body, state: State) -> np.ndarray:
    """(3,) pelvis position of the state's posture over its planted feet."""
    heading = state.heading
    back = body.toe_forward + (body.seat_back if state.posture == "sit" else 0.0)
    xz = state.toes[:, [0, 2]].mean(axis=0) - forward(heading) * back
    height = body.seat_height if state.posture == "sit" else body.stand_height
    return np.array([xz[0], height, xz[1]])


@dataclass
class Plan:
    """Per-frame targets of a motion or of one action (N frames at :data:`FPS`).

    Attributes:
        root: (N, 3) pelvis position; y is the desired height (lowered by :func:`realize` where a
            leg cannot reach).
        heading: (N,) facing yaw.
        channels: (N, C) upper-body angles, see :data:`CHANNELS`.
        toes: (N, 2, 3) toe targets of the left and right foot.
        yaws: (N, 2) foot yaws.
        pitch: (N, 2) plantar flexion added to the flat foot (heel raised, toe pointed).
    """

    root: np.ndarray
    heading: np.ndarray
    channels: np.ndarray
    toes: np.ndarray
    yaws: np.ndarray
    pitch: np.ndarray

    def __len__(self) -> int:
        return len(self.heading)

    @property
    def times(self) -> np.ndarray:
        """(N,) frame times in seconds from the plan's start."""
        return np.arange(len(self)) / FPS


def hold(body: Body, state: State, n: int) -> Plan:
    """``n`` frames of standing (or sitting) still in ``state``."""
    return Plan(
        root=np.tile(rest_root(body, state), (n, 1)),
        heading=np.full(n, state.heading),
        channels=np.tile(state.rest, (n, 1)),
        toes=np.tile(state.toes, (n, 1, 1)),
        yaws=np.tile(state.yaws, (n, 1)),
        pitch=np.zeros((n, 2)),
    )


def concat(plans: Sequence[Plan]) -> Plan:
    """Plans one after another."""
    return Plan(*(np.concatenate([getattr(p, name) for p in plans]) for name in Plan.__dataclass_fields__))


def frames(seconds: float) -> int:
    """Frame count covering ``seconds`` (at least 1)."""
    return max(1, int(round(seconds * FPS)))


@dataclass
class Piece:
    """An action's plan, the state it ends in, and its steady-speed frames (locomotion)."""

    plan: Plan
    end: State
    steady: tuple[int, int] | None = None


# ---------------------------------------------------------------------------------------------
# Curves
# ---------------------------------------------------------------------------------------------


def interp_keys(times: Sequence[float], values: np.ndarray | Sequence, n: int) -> np.ndarray:
    """(n, ...) shape-preserving cubic (PCHIP) through timed keys, held outside their range.

    A key no later than an earlier one is ignored (so key lists may be built back to back).
    """
    times = np.asarray(times, dtype=np.float64)
    keep = np.concatenate([[True], times[1:] > np.maximum.accumulate(times)[:-1] + 1e-9])
    times, values = times[keep], np.asarray(values, dtype=np.float64)[keep]
    t = np.clip(np.arange(n) / FPS, times[0], times[-1])
    if len(times) == 1:
        return np.repeat(values[:1], n, axis=0)
    return PchipInterpolator(times, values, axis=0)(t)


def pose_track(keys: Sequence[tuple[float, Mapping[str, float]]], n: int, base: np.ndarray) -> np.ndarray:
    """(n, C) channels through timed key poses; a key's missing channels take ``base``."""
    values = np.tile(base, (len(keys), 1))
    for row, (_, partial) in enumerate(keys):
        for name, value in partial.items():
            values[row, CH[name]] = value
    return interp_keys([t for t, _ in keys], values, n)


def smoothstep(x: np.ndarray | float) -> np.ndarray:
    """Minimum-jerk 0->1 ease on [0, 1] (clipped outside)."""
    x = np.clip(np.asarray(x, dtype=np.float64), 0.0, 1.0)
    return x**3 * (10.0 - 15.0 * x + 6.0 * x**2)


def window(t: np.ndarray, start: float, end: float, ramp: float) -> np.ndarray:
    """0 outside [start, end], 1 inside, with smooth ramps of ``ramp`` seconds at both ends."""
    ramp = max(ramp, 1e-6)
    return smoothstep((t - start) / ramp) * smoothstep((end - t) / ramp)


# ---------------------------------------------------------------------------------------------
# Plan edits shared by the actions
# ---------------------------------------------------------------------------------------------


def shift_root(plan: Plan, ahead: np.ndarray | float = 0.0, up: np.ndarray | float = 0.0,
               left: np.ndarray | float = 0.0) -> None:
    """Move the pelvis by body-frame offsets (per frame or constant), in place."""
    n = len(plan)
    ahead, up, left = (np.broadcast_to(np.asarray(v, dtype=np.float64), (n,)) for v in (ahead, up, left))
    xz = forward(plan.heading) * ahead[:, None] + leftward(plan.heading) * left[:, None]
    plan.root[:, [0, 2]] += xz
    plan.root[:, 1] += up


def swing_height(s: np.ndarray, clearance: float, kick: bool = False) -> np.ndarray:
    """Toe height along a swing (s in [0, 1]): up fast, down late, so a low toe barely moves.
    ``kick``: the running heel kick, highest a third of the way through the swing."""
    s = np.clip(s, 0.0, 1.0)
    return clearance * np.sin(np.pi * (s**0.6 if kick else s)) ** 0.5


def swing_progress(s: np.ndarray, kick: bool = False) -> np.ndarray:
    """Horizontal progress along a swing: none while the toe lifts off (unless it kicks up) or
    touches down."""
    s = np.asarray(s)
    return smoothstep(s / 0.9) if kick else smoothstep((s - 0.12) / 0.76)


def move_foot(plan: Plan, foot: int, t0: float, t1: float, toe: np.ndarray, yaw: float,
              clearance: float = 0.08) -> None:
    """Step ``foot`` to a new toe position and yaw during [t0, t1] and keep it there, in place."""
    t = plan.times
    start = np.searchsorted(t, t0)
    if start >= len(t):
        return
    origin, yaw0 = plan.toes[start, foot].copy(), plan.yaws[start, foot]
    s = np.clip((t[start:] - t0) / (t1 - t0), 0.0, 1.0)
    p = swing_progress(s)[:, None]
    plan.toes[start:, foot] = origin + (toe - origin) * p
    plan.toes[start:, foot, 1] = toe[1] * p[:, 0] + origin[1] * (1 - p[:, 0]) + swing_height(s, clearance)
    plan.yaws[start:, foot] = yaw0 + wrap(yaw - yaw0) * p[:, 0]


def foot_keys(plan: Plan, foot: int, keys: Sequence[tuple[float, float, float, float, float]]) -> None:
    """Drive a free foot through keys ``(t, ahead, up, out, pitch)`` relative to its plant at the
    first key (body frame; ``out`` is away from the body's midline), in place."""
    t = plan.times
    start = min(np.searchsorted(t, keys[0][0]), len(t) - 1)
    plant, heading = plan.toes[start, foot].copy(), plan.heading[start]
    rel = interp_keys([k[0] for k in keys], [k[1:] for k in keys], len(t))
    span = slice(start, min(np.searchsorted(t, keys[-1][0], side="right"), len(t)))
    xz = forward(heading) * rel[span, :1] + leftward(heading) * FOOT_SIGN[foot] * rel[span, 2:3]
    plan.toes[span, foot, 0] = plant[0] + xz[:, 0]
    plan.toes[span, foot, 2] = plant[2] + xz[:, 1]
    plan.toes[span, foot, 1] = plant[1] + rel[span, 1]
    plan.pitch[span, foot] = rel[span, 3]


# ---------------------------------------------------------------------------------------------
# Realisation: channels -> rotations, leg IK, FK
# ---------------------------------------------------------------------------------------------


def _euler(pitch: np.ndarray, twist: np.ndarray, lean: np.ndarray) -> np.ndarray:
    """Trunk-style rotation: twist about y, then pitch forward about x, then lean left."""
    return axis_rotation(1, twist) @ axis_rotation(0, pitch) @ axis_rotation(2, -lean)


def pelvis_rotation(plan: Plan) -> np.ndarray:
    """(N, 3, 3) global pelvis rotations from heading and pelvis channels."""
    ch = plan.channels
    return _euler(ch[:, CH["pelvis_pitch"]], plan.heading + ch[:, CH["pelvis_twist"]], ch[:, CH["pelvis_lean"]])


def upper_rotations(channels: np.ndarray) -> np.ndarray:
    """(N, J, 3, 3) local rotations of the non-leg joints from channels (legs: identity)."""
    n = len(channels)
    local = np.tile(np.eye(3), (n, J, 1, 1))

    def c(name: str) -> np.ndarray:
        return channels[:, CH[name]]

    for joint, share in _SPINE_SHARE.items():
        local[:, joint] = _euler(share * c("spine_pitch"), share * c("spine_twist"), share * c("spine_lean"))
    local[:, 12] = _euler(c("neck_pitch"), c("neck_twist"), c("neck_lean"))
    for prefix, sign, (collar, shoulder, elbow) in (("l", 1.0, (13, 16, 18)), ("r", -1.0, (14, 17, 19))):
        shrug, reach = c(f"{prefix}_shrug"), c(f"{prefix}_reach")
        local[:, collar] = axis_rotation(2, sign * shrug) @ axis_rotation(1, -sign * reach)
        swing = np.stack([-c(f"{prefix}_flex"), np.zeros(n), sign * c(f"{prefix}_abd")], axis=-1)
        local[:, shoulder] = expmap(swing) @ axis_rotation(1, sign * c(f"{prefix}_twist"))
        local[:, elbow] = axis_rotation(0, -c(f"{prefix}_elbow"))
    return local


def _foot_direction(yaw: np.ndarray, pitch: np.ndarray) -> np.ndarray:
    """(..., 3) unit ankle-to-toe direction of a foot with extra plantar flexion ``pitch``."""
    p = FOOT_PITCH + pitch
    return np.stack([np.sin(yaw) * np.cos(p), -np.sin(p), np.cos(yaw) * np.cos(p)], axis=-1)


def _lateral(yaw: np.ndarray) -> np.ndarray:
    """(..., 3) a foot's lateral (knee hinge) axis, pointing to the body's left."""
    return np.stack([np.cos(yaw), np.zeros_like(yaw), -np.sin(yaw)], axis=-1)


def ankle_targets(plan: Plan, body: Body) -> np.ndarray:
    """(N, 2, 3) ankle positions that put each toe on its target."""
    return plan.toes - body.foot * _foot_direction(plan.yaws, plan.pitch)


def _hips(root: np.ndarray, pelvis: np.ndarray, body: Body) -> np.ndarray:
    """(N, 2, 3) hip joint positions."""
    return root[:, None] + np.einsum("nij,kj->nki", pelvis, body.offsets[[1, 2]])


def reachable_root(plan: Plan, body: Body, pelvis: np.ndarray, margin: float = 0.995) -> np.ndarray:
    """(N, 3) pelvis positions lowered (smoothly) so that both legs reach their ankle targets."""
    ankles = ankle_targets(plan, body)
    hips = _hips(plan.root, pelvis, body)
    horizontal = np.linalg.norm((hips - ankles)[..., [0, 2]], axis=-1)
    reach = np.sqrt(np.maximum((margin * body.leg) ** 2 - horizontal**2, 0.0))
    drop = np.maximum(hips[..., 1] - ankles[..., 1] - reach, 0.0).max(axis=1)
    smooth = gaussian_filter1d(maximum_filter1d(drop, 5), 1.5, mode="nearest")
    root = plan.root.copy()
    root[:, 1] -= np.maximum(smooth, drop)
    return root


def _leg_ik(hip: np.ndarray, ankle: np.ndarray, hinge: np.ndarray, thigh: float, shank: float
            ) -> tuple[np.ndarray, np.ndarray]:
    """Knee and (reachable) ankle positions of a two-bone leg bending about ``hinge``."""
    delta = ankle - hip
    dist = np.linalg.norm(delta, axis=-1, keepdims=True)
    u = delta / np.maximum(dist, 1e-9)
    dist = np.clip(dist, abs(thigh - shank) + 1e-4, (thigh + shank) * (1 - 1e-4))
    side = _normalize(hinge - np.sum(hinge * u, axis=-1, keepdims=True) * u)
    bend = np.cross(u, side)  # the knee bends forward of the hip-ankle line
    cos_a = np.clip((thigh**2 + dist**2 - shank**2) / (2 * thigh * dist), -1.0, 1.0)
    knee = hip + thigh * (cos_a * u + np.sqrt(1 - cos_a**2) * bend)
    return knee, hip + dist * u


def _leg_rotations(plan: Plan, body: Body, pelvis: np.ndarray, root: np.ndarray) -> dict[int, np.ndarray]:
    """Local rotations (N, 3, 3) of hips, knees and ankles by two-bone IK."""
    down = np.array([0.0, -1.0, 0.0])
    rest_foot = body.offsets[10] / body.foot
    hips = _hips(root, pelvis, body)
    ankles = ankle_targets(plan, body)
    local = {}
    for foot, (hip_j, knee_j, ankle_j, _) in enumerate(LEGS):
        hinge = _lateral(plan.yaws[:, foot])
        knee, ankle = _leg_ik(hips[:, foot], ankles[:, foot], hinge, body.thigh, body.shank)
        thigh = _align(down, knee - hips[:, foot], hinge)
        shank = _align(down, ankle - knee, hinge)
        toe_dir = _foot_direction(plan.yaws[:, foot], plan.pitch[:, foot])
        foot_rot = _align(rest_foot, toe_dir, hinge)
        local[hip_j] = np.swapaxes(pelvis, -1, -2) @ thigh
        local[knee_j] = np.swapaxes(thigh, -1, -2) @ shank
        local[ankle_j] = np.swapaxes(shank, -1, -2) @ foot_rot
    return local


def forward_kinematics(local: np.ndarray, root: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """(N, J, 3) joint positions from local rotations (N, J, 3, 3) (slot 0: global pelvis).

    Each joint's global rotation is its parent's times its own local one, so the arms follow the
    spine (unlike :func:`data.kinematics.forward_kinematics`, whose arm chains start from the root).
    """
    glob = np.empty_like(local)
    pos = np.empty(local.shape[:2] + (3,))
    glob[:, 0], pos[:, 0] = local[:, 0], root
    for j in range(1, J):
        p = PARENTS[j]
        glob[:, j] = glob[:, p] @ local[:, j]
        pos[:, j] = pos[:, p] + glob[:, p] @ offsets[j]
    return pos


def realize(plan: Plan, body: Body) -> np.ndarray:
    """(N, J, 3) float32 global joint positions of a plan on a body."""
    pelvis = pelvis_rotation(plan)
    root = reachable_root(plan, body, pelvis)
    local = upper_rotations(plan.channels)
    local[:, 0] = pelvis
    for joint, rot in _leg_rotations(plan, body, pelvis, root).items():
        local[:, joint] = rot
    return forward_kinematics(local, root, body.offsets).astype(np.float32)


# ---------------------------------------------------------------------------------------------
# Playing pieces back to back
# ---------------------------------------------------------------------------------------------


def style_noise(rng: np.random.Generator, n: int, amount: float) -> np.ndarray:
    """(n, C) slowly varying channel offsets: a personal posture plus a little drift."""
    scale = np.full(len(CHANNELS), 0.03)
    scale[list(GROUPS["head"])] = 0.06
    scale[[CH["pelvis_twist"], CH["spine_twist"]]] = 0.02
    posture = rng.normal(0.0, 1.0, len(CHANNELS)) * scale
    drift = gaussian_filter1d(rng.normal(0.0, 1.0, (n, len(CHANNELS))), 8.0, axis=0, mode="nearest") * 3.0
    return amount * (posture + drift * scale)


def assemble(body: Body, pieces: Sequence[Piece], noise: np.ndarray | None = None) -> np.ndarray:
    """(N, J, 3) joints of pieces played back to back; upper-body seams are smoothed."""
    plan = concat([p.plan for p in pieces])
    plan.channels = gaussian_filter1d(plan.channels, 1.2, axis=0, mode="nearest")
    if noise is not None:
        plan.channels = plan.channels + noise
    plan.root = gaussian_filter1d(plan.root, 0.8, axis=0, mode="nearest")
    return realize(plan, body)
