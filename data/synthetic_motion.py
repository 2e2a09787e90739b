"""Procedural human motion on the HumanML3D skeleton: bodies, kinematics and motion plans.

A motion is first *planned* as per-frame targets (:class:`Plan`): the pelvis position and
heading, the angles of the trunk, head and arms (the named :data:`CHANNELS`), and for each foot a
toe target (position, yaw and extra plantar flexion). :func:`realize` turns a plan into global
joint positions on a :class:`Body`:

1. the channels become local rotation matrices of the spine, neck, collars, shoulders, elbows;
2. the pelvis is lowered wherever a leg could not reach its foot target;
3. analytic two-bone leg IK (knee hinge along the foot's lateral axis) gives hip, knee and ankle
   rotations that put each toe exactly on its target;
4. forward kinematics with the body's constant rest bone vectors gives the joints.

A foot in stance keeps a fixed toe target, so it does not slide, and the pelvis trajectory is
planned from the footstep plan (the body moves over its stance feet). Bone lengths are constant
by construction.

The second half of the module is the action library: a gait planner (footsteps along a path
for walking, jogging, running, side-stepping, circling and turning on the spot) and one builder
per parametric action (:data:`ACTIONS`), each writing a plan from a start :class:`State`.

Conventions: y up, the body faces +z at heading 0 and its left is +x; a positive heading turns it
to its left (counter-clockwise seen from above). Units are metres, seconds and radians.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.integrate import cumulative_trapezoid
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
# Rotations
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
    """(N, J, 3) joint positions from local rotations (N, J, 3, 3) (slot 0: global pelvis)."""
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
# Gait: a path, footsteps along it, the pelvis over them
# ---------------------------------------------------------------------------------------------

GRAVITY = 9.81
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


@dataclass
class Piece:
    """An action's plan, the state it ends in, and its steady-speed frames (locomotion)."""

    plan: Plan
    end: State
    steady: tuple[int, int] | None = None


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
# Action builders. Each takes (body, start state, params) and returns a Piece; params are plain
# JSON-able dicts sampled by the matching ``sample_*`` function further down.
# ---------------------------------------------------------------------------------------------

_TRAVEL = {"forward": 0.0, "backward": np.pi, "left": np.pi / 2, "right": -np.pi / 2}
SIGN = {"left": 1.0, "right": -1.0}
FOOT = {"left": LEFT, "right": RIGHT}


def other(side: str) -> str:
    """The opposite side."""
    return "right" if side == "left" else "left"


def _scale(body: Body) -> float:
    """Body size relative to the reference skeleton (pelvis about 0.96 m)."""
    return body.stand_height / 0.96


def _start_xz(body: Body, state: State) -> np.ndarray:
    return rest_root(body, state)[[0, 2]]


def build_walk(body: Body, state: State, p: Mapping) -> Piece:
    """Walk forward/backward/sideways; forward walks may veer left or right by 90 degrees."""
    direction, speed = p["direction"], p["speed"]
    gait = side_gait(speed, _scale(body)) if direction in ("left", "right") else walk_gait(speed, _scale(body))
    veer = SIGN[p["veer"]] * np.pi / 2 if p.get("veer") else 0.0
    path = make_path(_start_xz(body, state), state.heading, p["move_time"], speed, _TRAVEL[direction],
                     turn=veer, turn_span=(0.4, 0.75))
    first = FOOT[direction] if direction in FOOT else FOOT[p["lead"]]
    return locomotion(body, state, path, gait, first)


def build_run(body: Body, state: State, p: Mapping) -> Piece:
    """Jog or run forward."""
    path = make_path(_start_xz(body, state), state.heading, p["move_time"], p["speed"])
    return locomotion(body, state, path, run_gait(p["speed"], _scale(body)), FOOT[p["lead"]])


def build_circle(body: Body, state: State, p: Mapping) -> Piece:
    """Walk (or jog) one full circle, counter-clockwise = turning left."""
    speed, radius = p["speed"], p["radius"]
    sign = 1.0 if p["direction"] == "counterclockwise" else -1.0
    ramp = ramp_time(speed)
    move_time = 2 * np.pi * radius / speed + ramp
    path = make_path(_start_xz(body, state), state.heading, move_time, speed, curvature=sign / radius, ramp=ramp)
    gait = run_gait(speed, _scale(body)) if p.get("jog") else walk_gait(speed, _scale(body))
    return locomotion(body, state, path, gait, LEFT if sign > 0 else RIGHT)


def build_turn(body: Body, state: State, p: Mapping) -> Piece:
    """Turn on the spot by ``angle`` degrees to the left or right, stepping round."""
    angle = np.radians(p["angle"]) * SIGN[p["direction"]]
    path = make_path(_start_xz(body, state), state.heading, abs(angle) / p["rate"] + 0.3, turn=angle, ramp=0.3)
    piece = locomotion(body, state, path, turn_gait(_scale(body)), FOOT[p["direction"]])
    t = piece.plan.times
    piece.plan.channels[:, CH["neck_twist"]] += 0.25 * np.sign(angle) * window(t, 0.0, path.end, 0.3)
    piece.plan.channels[:, CH["spine_twist"]] += 0.12 * np.sign(angle) * window(t, 0.0, path.end, 0.3)
    return piece


def _timed(keys: Sequence[tuple[float, Mapping[str, float]]], tempo: float) -> list[tuple[float, Mapping[str, float]]]:
    """Keys with their times stretched by ``tempo``."""
    return [(t * tempo, k) for t, k in keys]


def _upper(body: Body, state: State, keys: Sequence[tuple[float, Mapping[str, float]]], tail: float = 0.15) -> Piece:
    """An action of the upper body only: the legs keep the state's posture."""
    n = frames(keys[-1][0] + tail)
    plan = hold(body, state, n)
    plan.channels = pose_track(keys, n, state.rest)
    return Piece(plan, state)


def build_wave(body: Body, state: State, p: Mapping) -> Piece:
    """Wave one hand (forearm swinging side to side) or both hands."""
    side, tempo = p["side"], p["tempo"]
    raised = arm(side, flex=0.3, abd=1.55, twist=1.35, elbow=1.3)
    keys = [(0.0, {}), (0.5, raised)]
    for k in range(2 * p["reps"]):
        keys.append((0.5 + 0.22 * (k + 1), {**raised, **arm(side, elbow=0.8 if k % 2 == 0 else 1.7)}))
    keys += [(keys[-1][0] + 0.2, raised), (keys[-1][0] + 0.75, {})]
    return _upper(body, state, _timed(keys, tempo))


def build_raise_arms(body: Body, state: State, p: Mapping) -> Piece:
    """Raise one or both arms up, forward or out to the side, hold, lower."""
    target = {
        "up": dict(flex=2.95, abd=0.15, elbow=0.1),
        "forward": dict(flex=1.5, abd=0.1, elbow=0.05),
        "sideways": dict(flex=0.05, abd=1.5, elbow=0.05),
    }[p["direction"]]
    up = arm(p["side"], **target)
    keys = [(0.0, {}), (0.8, up), (0.8 + p["hold"], up), (1.6 + p["hold"], {})]
    return _upper(body, state, _timed(keys, p["tempo"]))


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
    return _upper(body, state, _timed(keys, p["tempo"]))


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
    return _upper(body, state, _timed(keys, p["tempo"]))


def build_look_around(body: Body, state: State, p: Mapping) -> Piece:
    """Look to one side, then the other (``reps`` times), then ahead again."""
    keys: list[tuple[float, Mapping[str, float]]] = [(0.0, {})]
    sides = [p["first"], other(p["first"])] * p["reps"]
    for side in sides:
        look = pose(neck_twist=1.0 * SIGN[side], spine_twist=0.3 * SIGN[side], neck_pitch=-0.05)
        keys += [(keys[-1][0] + 0.7, look), (keys[-1][0] + 0.7 + p["hold"], look)]
    keys.append((keys[-1][0] + 0.7, {}))
    return _upper(body, state, _timed(keys, p["tempo"]))


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
    return _upper(body, state, _timed(keys, p["tempo"]))


def _standing(body: Body, state: State, keys: Sequence[tuple[float, Mapping[str, float]]],
              root_keys: Sequence[tuple[float, float, float, float]], tail: float = 0.15) -> Piece:
    """A standing action: channel keys plus pelvis keys ``(t, ahead, up, left)`` relative to rest."""
    piece = _upper(body, state, keys, tail)
    rel = interp_keys([k[0] for k in root_keys], [k[1:] for k in root_keys], len(piece.plan))
    shift_root(piece.plan, rel[:, 0], rel[:, 1], rel[:, 2])
    return piece


def build_bow(body: Body, state: State, p: Mapping) -> Piece:
    """Bow from the hips (the arms hang), hold, straighten up."""
    depth, hold_time = p["depth"], p["hold"]
    bent = {"pelvis_pitch": 0.45 * depth, "spine_pitch": 0.55 * depth, "neck_pitch": 0.15,
            **arm("both", flex=0.85 * depth, abd=0.1, elbow=0.2)}
    keys = _timed([(0.0, {}), (0.9, bent), (0.9 + hold_time, bent), (1.9 + hold_time, {})], p["tempo"])
    back = -0.07 * depth
    roots = [(keys[0][0], 0, 0, 0), (keys[1][0], back, -0.02, 0), (keys[2][0], back, -0.02, 0), (keys[3][0], 0, 0, 0)]
    return _standing(body, state, keys, roots)


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
    return _standing(body, state, keys, roots)


def build_crouch(body: Body, state: State, p: Mapping) -> Piece:
    """Crouch down low (heels up, hands near the knees), stay, get back up."""
    drop = p["depth"] * body.leg
    low = {"pelvis_pitch": 0.55, "spine_pitch": 0.4, "neck_pitch": -0.3,
           **arm("both", flex=0.9, abd=0.25, elbow=0.5)}
    keys = _timed([(0.0, {}), (0.9, low), (0.9 + p["hold"], low), (1.9 + p["hold"], {})], p["tempo"])
    roots = [(keys[0][0], 0, 0, 0), (keys[1][0], -0.25 * drop, -drop, 0), (keys[2][0], -0.25 * drop, -drop, 0),
             (keys[3][0], 0, 0, 0)]
    piece = _standing(body, state, keys, roots)
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
    piece = _standing(body, state, keys, roots)
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
    piece = _standing(body, state, keys, roots)
    piece.end = stand
    return piece


def build_kick(body: Body, state: State, p: Mapping) -> Piece:
    """Front kicks with one leg while standing on the other."""
    side, reps, tempo = p["side"], p["reps"], p["tempo"]
    foot, scale = FOOT[side], _scale(body)
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
    piece = _standing(body, state, keys, roots)
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
    keys = _timed([(0.0, {}), (0.8, windup), (1.05, release), (1.3, follow), (2.2, {})], tempo)
    stride = p["stride"] * _scale(body)
    roots = [(0.0, 0, 0, 0), (keys[1][0], -0.03, -0.02, 0), (keys[2][0], 0.5 * stride, -0.04, 0),
             (keys[3][0], 0.55 * stride, -0.04, 0), (keys[4][0], 0, 0, 0)]
    piece = _standing(body, state, keys, roots, tail=0.4)
    plan, foot = piece.plan, FOOT[other(side)]
    toe, yaw = state.toes[foot].copy(), float(state.yaws[foot])
    toe[[0, 2]] += forward(state.heading) * stride
    move_foot(plan, foot, keys[1][0] - 0.35 * tempo, keys[2][0] - 0.05 * tempo, toe, yaw)
    move_foot(plan, foot, keys[3][0] + 0.2 * tempo, keys[4][0], state.toes[foot], yaw)
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
    keys = _timed([(0.0, {}), (1.2, reach), (1.6, grab), (2.8, carry), (3.2, carry)], tempo)
    if not p["keep"]:
        keys.append((keys[-1][0] + 0.8, {}))
    roots = [(0.0, 0, 0, 0), (keys[1][0], -0.12, -drop, 0), (keys[2][0], -0.12, -drop, 0), (keys[3][0], 0, 0, 0)]
    return _standing(body, state, keys, roots)


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
    flight, heel, crouch = _flight_time(height), 0.65, 0.14 * _scale(body)
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
    wide[:, [0, 2]] += np.outer([1.0, -1.0], leftward(state.heading)) * 0.2 * _scale(body)
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


def build_idle(body: Body, state: State, p: Mapping) -> Piece:
    """Stand (or sit) still, shifting the weight a little."""
    n = frames(p["duration"])
    plan = hold(body, state, n)
    shift_root(plan, 0.0, 0.0, 0.02 * np.sin(2 * np.pi * plan.times / 3.0) * (state.posture == "stand"))
    return Piece(plan, state)


# ---------------------------------------------------------------------------------------------
# Parameter samplers: one per action, returning plain (JSON-able) dicts
# ---------------------------------------------------------------------------------------------

_PACES = {"slow": (0.82, 1.05), "normal": (1.1, 1.45), "fast": (1.5, 1.78)}
_RUN_PACES = {"normal": (2.6, 3.3), "fast": (3.3, 3.95)}


def _pick(rng: np.random.Generator, options: Sequence, weights: Sequence[float] | None = None):
    """One of ``options`` (weighted), as a plain Python value."""
    p = None if weights is None else np.asarray(weights, dtype=np.float64) / np.sum(weights)
    return options[int(rng.choice(len(options), p=p))]


def _u(rng: np.random.Generator, lo: float, hi: float) -> float:
    return round(float(rng.uniform(lo, hi)), 3)


def _side(rng: np.random.Generator, both: float = 0.0) -> str:
    return _pick(rng, ("left", "right", "both"), ((1 - both) / 2, (1 - both) / 2, both))


def sample_walk(rng: np.random.Generator) -> dict:
    direction = _pick(rng, ("forward", "backward", "left", "right"), (0.55, 0.15, 0.15, 0.15))
    lead = _side(rng)
    if direction == "forward":
        pace = _pick(rng, ("slow", "normal", "fast"), (0.3, 0.4, 0.3))
        veer = _pick(rng, (None, "left", "right"), (0.8, 0.1, 0.1))
        move = _u(rng, 4.0, 6.0) if veer else _u(rng, 2.5, 6.0)
        return dict(direction=direction, pace=pace, speed=_u(rng, *_PACES[pace]), move_time=move, veer=veer, lead=lead)
    if direction == "backward":
        pace = _pick(rng, ("slow", "normal"))
        speed = _u(rng, 0.6, 0.8) if pace == "slow" else _u(rng, 0.8, 1.1)
        return dict(direction=direction, pace=pace, speed=speed, move_time=_u(rng, 2.0, 4.0), veer=None, lead=lead)
    speed = _u(rng, 0.45, 0.75)
    pace = "slow" if speed < 0.55 else "normal"
    return dict(direction=direction, pace=pace, speed=speed, move_time=_u(rng, 2.0, 3.5), veer=None, lead=lead)


def sample_jog(rng: np.random.Generator) -> dict:
    speed = _u(rng, 1.9, 2.5)
    return dict(pace="normal", speed=speed, move_time=round(2 * ramp_time(speed) + _u(rng, 0.6, 2.0), 3),
                lead=_side(rng))


def sample_run(rng: np.random.Generator) -> dict:
    pace = _pick(rng, ("normal", "fast"))
    speed = _u(rng, *_RUN_PACES[pace])
    return dict(pace=pace, speed=speed, move_time=round(2 * ramp_time(speed) + _u(rng, 0.6, 1.6), 3), lead=_side(rng))


def sample_circle(rng: np.random.Generator) -> dict:
    jog = bool(rng.random() < 0.15)
    speed = _u(rng, 1.9, 2.3) if jog else _u(rng, 0.8, 1.2)
    radius = _u(rng, 0.7, min(1.4, 6.5 * speed / (2 * np.pi)) if not jog else 1.6)
    pace = "normal" if jog or speed > 0.95 else "slow"
    return dict(direction=_pick(rng, ("clockwise", "counterclockwise")), speed=speed, radius=radius, jog=jog, pace=pace)


def sample_turn(rng: np.random.Generator) -> dict:
    angle = _pick(rng, (45, 90, 135, 180, 360), (0.1, 0.35, 0.1, 0.3, 0.15))
    return dict(direction=_side(rng), angle=angle, rate=_u(rng, 1.6, 2.6))


def sample_jump(rng: np.random.Generator) -> dict:
    forward_ = bool(rng.random() < 0.4)
    return dict(reps=_pick(rng, (1, 2, 3), (0.45, 0.35, 0.2)), distance=_u(rng, 0.5, 1.1) if forward_ else 0.0,
                height=_u(rng, 0.15, 0.3) if forward_ else _u(rng, 0.12, 0.3), pause=_u(rng, 0.1, 0.4))


def sample_hop(rng: np.random.Generator) -> dict:
    forward_ = bool(rng.random() < 0.3)
    return dict(side=_side(rng), reps=int(rng.integers(2, 6)), height=_u(rng, 0.05, 0.1),
                distance=_u(rng, 0.15, 0.3) if forward_ else 0.0)


def sample_squat(rng: np.random.Generator) -> dict:
    return dict(reps=_pick(rng, (1, 2, 3, 4), (0.35, 0.3, 0.2, 0.15)), depth=_u(rng, 0.3, 0.45),
                period=_u(rng, 1.4, 2.2))


def sample_duration(lo: float, hi: float) -> Callable[[np.random.Generator], dict]:
    """A sampler of ``{"duration": seconds}``."""
    return lambda rng: dict(duration=_u(rng, lo, hi))


def sample_crouch(rng: np.random.Generator) -> dict:
    return dict(depth=_u(rng, 0.45, 0.55), hold=_u(rng, 0.6, 2.0), tempo=_u(rng, 0.85, 1.2))


def sample_kick(rng: np.random.Generator) -> dict:
    high = bool(rng.random() < 0.4)
    return dict(side=_side(rng), reps=_pick(rng, (1, 2, 3), (0.5, 0.3, 0.2)),
                height=_u(rng, 0.7, 0.95) if high else _u(rng, 0.35, 0.6), tempo=_u(rng, 0.85, 1.15))


def sample_punch(rng: np.random.Generator) -> dict:
    side = _side(rng, both=0.2)
    reps = int(rng.integers(2, 7)) if side == "both" else int(rng.integers(1, 5))
    return dict(side=side, reps=reps, tempo=_u(rng, 0.8, 1.2))


def sample_wave(rng: np.random.Generator) -> dict:
    return dict(side=_side(rng, both=0.2), reps=int(rng.integers(2, 6)), tempo=_u(rng, 0.8, 1.2))


def sample_raise_arms(rng: np.random.Generator) -> dict:
    return dict(side=_side(rng, both=0.5), direction=_pick(rng, ("up", "forward", "sideways"), (0.5, 0.25, 0.25)),
                hold=_u(rng, 0.5, 2.0), tempo=_u(rng, 0.8, 1.2))


def sample_clap(rng: np.random.Generator) -> dict:
    return dict(reps=int(rng.integers(3, 8)), overhead=bool(rng.random() < 0.25), tempo=_u(rng, 0.8, 1.2))


def sample_bow(rng: np.random.Generator) -> dict:
    return dict(depth=_u(rng, 0.4, 1.0), hold=_u(rng, 0.4, 1.5), tempo=_u(rng, 0.85, 1.2))


def sample_stretch(rng: np.random.Generator) -> dict:
    return dict(mode=_pick(rng, ("up", "left", "right", "out")), hold=_u(rng, 0.8, 2.0), tempo=_u(rng, 0.85, 1.2))


def sample_look_around(rng: np.random.Generator) -> dict:
    return dict(first=_side(rng), reps=_pick(rng, (1, 2), (0.7, 0.3)), hold=_u(rng, 0.2, 0.8), tempo=_u(rng, 0.8, 1.2))


def sample_throw(rng: np.random.Generator) -> dict:
    return dict(side=_side(rng), stride=_u(rng, 0.2, 0.35), tempo=_u(rng, 0.85, 1.15))


def sample_pick_up(rng: np.random.Generator) -> dict:
    return dict(side=_side(rng, both=0.2), keep=bool(rng.random() < 0.3), tempo=_u(rng, 0.85, 1.2))


def sample_jumping_jacks(rng: np.random.Generator) -> dict:
    return dict(reps=int(rng.integers(2, 6)))


# ---------------------------------------------------------------------------------------------
# The library
# ---------------------------------------------------------------------------------------------


def _arm_group(p: Mapping) -> str:
    return "both_arms" if p["side"] == "both" else f"{p['side']}_arm"


@dataclass(frozen=True)
class Action:
    """One parametric action of the library.

    Attributes:
        label: its action class (``actions.txt``).
        build / sample: the plan builder and its parameter sampler.
        weight: how often it is drawn.
        postures: postures it can start from.
        carries: whether it can carry an upper-body action (lower body from this one).
        lends: for an upper-body action, the channel group it lends to a carrier.
    """

    label: str
    build: Callable[[Body, State, Mapping], Piece]
    sample: Callable[[np.random.Generator], dict]
    weight: float = 1.0
    postures: tuple[str, ...] = ("stand",)
    carries: bool = False
    lends: Callable[[Mapping], str] | None = None


ACTIONS: dict[str, Action] = {
    "walk": Action("walk", build_walk, sample_walk, 3.0, carries=True),
    "jog": Action("jog", build_run, sample_jog, 1.0, carries=True),
    "run": Action("run", build_run, sample_run, 1.2),
    "circle": Action("walk", build_circle, sample_circle, 0.8, carries=True),
    "turn": Action("turn", build_turn, sample_turn, 1.5, carries=True),
    "jump": Action("jump", build_jump, sample_jump, 1.0),
    "hop": Action("hop", build_hop, sample_hop, 0.8),
    "jumping_jacks": Action("jumping_jacks", build_jumping_jacks, sample_jumping_jacks, 0.6),
    "squat": Action("squat", build_squat, sample_squat, 1.0),
    "sit_down": Action("sit", build_sit_down, sample_duration(1.5, 2.4), 0.8),
    "stand_up": Action("sit", build_stand_up, sample_duration(1.4, 2.2), 0.8, postures=("sit",)),
    "crouch": Action("crouch", build_crouch, sample_crouch, 0.7),
    "kick": Action("kick", build_kick, sample_kick, 1.0),
    "punch": Action("punch", build_punch, sample_punch, 1.0, lends=_arm_group),
    "throw": Action("throw", build_throw, sample_throw, 0.8),
    "wave": Action("wave", build_wave, sample_wave, 1.0, ("stand", "sit"), lends=_arm_group),
    "raise_arms": Action("raise_arms", build_raise_arms, sample_raise_arms, 1.0, ("stand", "sit"), lends=_arm_group),
    "clap": Action("clap", build_clap, sample_clap, 0.8, ("stand", "sit"), lends=lambda p: "both_arms"),
    "bow": Action("bow", build_bow, sample_bow, 0.7),
    "stretch": Action("stretch", build_stretch, sample_stretch, 0.7),
    "look_around": Action("look_around", build_look_around, sample_look_around, 0.7, ("stand", "sit"),
                          lends=lambda p: "head"),
    "pick_up": Action("pick_up", build_pick_up, sample_pick_up, 0.8),
}
LABELS: tuple[str, ...] = tuple(dict.fromkeys(a.label for a in ACTIONS.values()))


# ---------------------------------------------------------------------------------------------
# Composition: segments -> one motion
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Segment:
    """One action of a motion: its kind, parameters and an optional upper-body action on top."""

    kind: str
    params: dict
    upper: Segment | None = None

    @property
    def label(self) -> str:
        return ACTIONS[self.kind].label


def _overlay(piece: Piece, upper: Piece, group: str, margin: float = 0.3) -> None:
    """Replace ``group``'s channels of ``piece`` with the upper-body action's, fitted (time-
    stretched if needed) into the piece and blended in and out, in place."""
    n, m = len(piece.plan), len(upper.plan)
    inner = max(n - 2 * frames(margin), 1)
    source = upper.plan.channels
    if m > inner:  # stretch the upper action over the carrier
        idx = np.linspace(0, m - 1, inner)
        source = np.stack([np.interp(idx, np.arange(m), source[:, c]) for c in range(source.shape[1])], axis=1)
    start = (n - len(source)) // 2
    cols = list(GROUPS[group])
    weight = window(np.arange(n) / FPS, start / FPS, (start + len(source)) / FPS, margin)[:, None]
    target = piece.plan.channels[:, cols].copy()
    target[start : start + len(source)] = source[:, cols]
    piece.plan.channels[:, cols] = (1 - weight) * piece.plan.channels[:, cols] + weight * target


def build_segment(body: Body, state: State, segment: Segment) -> Piece:
    """The piece of one segment (with its upper-body action blended in) from ``state``."""
    piece = ACTIONS[segment.kind].build(body, state, segment.params)
    if segment.upper is not None:
        upper = ACTIONS[segment.upper.kind]
        _overlay(piece, upper.build(body, state, segment.upper.params), upper.lends(segment.upper.params))
    return piece


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
