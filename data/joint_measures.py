"""Measures of what a motion does, read off its global joints (T, 22, 3): metres, y up, HumanML3D order, 20 fps.

Used to check generated motions against their prompts (``benchmarks/prompt_probe.py``,
``benchmarks/contrasts.py``) and reconstructions against their originals
(:func:`reconstruction_detail`, the VAE row's detail columns):

- :func:`foot_rise`: each foot's highest lift of its ankle or toe above that joint's own
  10th-percentile height (its standing height). A synthetic kick lifts the kicking foot to about hip
  height; a walking step lifts an ankle 0.10-0.15 m.
- :func:`wrist_up`: frames with each wrist above the head joint.
- :func:`heading`: the facing (radians, unwrapped) from the hip plus shoulder axes, smoothed over
  ``SMOOTH`` frames so that the pelvis's yaw swing within a stride does not add up to a turn;
  :func:`net_turn` its change from the first to the last frame (degrees).
- :func:`airborne_runs` / :func:`jump_count`: runs of at least ``AIR_FRAMES`` frames with both feet
  (lowest of ankle and toe) more than ``AIR_MARGIN`` above the floor (the 10th percentile of the lowest
  foot), runs split by one grounded frame merged.
- :func:`swing_count`: the side-to-side swings of a raised hand: reversals of the wrist's position
  relative to its elbow along the body's left-right axis, while the wrist is above the head, each at
  least ``SWING_MIN`` from the previous extreme (hysteresis, so that jitter is not a swing). A
  synthetic wave swings the forearm 4 to 10 times, about 0.2 s a swing. :func:`waving_side` tells a
  wave from the other raised-arm motions that swing a forearm.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

PELVIS, L_HIP, R_HIP, HEAD = 0, 1, 2, 15
L_SHOULDER, R_SHOULDER, L_ELBOW, R_ELBOW, L_WRIST, R_WRIST = 16, 17, 18, 19, 20, 21
LEFT_FOOT, RIGHT_FOOT = (7, 10), (8, 11)  # (ankle, toe)
FPS = 20
SMOOTH = 9  # frames (0.45 s)
AIR_MARGIN, AIR_FRAMES = 0.05, 2  # metres, frames
SWING_MIN = 0.05  # metres

#: reconstruction_detail's references and what keeping one means (see its docstring)
TURN_MIN, TURN_TOL = 135.0, 45.0  # degrees
KICK_MIN, KICK_KEEP = 0.40, 0.8  # metres, fraction of the real rise (the other foot below half of it)
WAVE_UP, WAVE_SWINGS, WAVE_KEEP = 10, 4, 0.5  # raised frames, swings in one raised stretch, fraction kept
HANDS_APART = 0.30  # metres: raised hands that come closer meet, as a clap's do


def foot_rise(joints: np.ndarray) -> tuple[float, float]:
    """(left, right): each foot's highest lift of its ankle or toe above that joint's standing height."""
    def rise(idx: tuple[int, int]) -> float:
        y = joints[:, idx, 1]
        return float((y - np.percentile(y, 10, axis=0)).max())
    return rise(LEFT_FOOT), rise(RIGHT_FOOT)


def wrist_up(joints: np.ndarray) -> tuple[int, int]:
    """(left, right): frames with each wrist above the head joint."""
    head = joints[:, HEAD, 1]
    return int((joints[:, L_WRIST, 1] > head).sum()), int((joints[:, R_WRIST, 1] > head).sum())


def heading(joints: np.ndarray) -> np.ndarray:
    """(T,) unwrapped heading (radians) from the hip plus shoulder axes, smoothed over ``SMOOTH`` frames."""
    axis = joints[:, L_HIP] - joints[:, R_HIP] + joints[:, L_SHOULDER] - joints[:, R_SHOULDER]
    angle = np.unwrap(np.arctan2(axis[:, 0], axis[:, 2]))
    pad = SMOOTH // 2
    padded = np.concatenate([np.full(pad, angle[0]), angle, np.full(pad, angle[-1])])
    return np.convolve(padded, np.ones(SMOOTH) / SMOOTH, mode="valid")


def net_turn(joints: np.ndarray) -> float:
    """Signed heading change (degrees) from the first frame to the last (:func:`heading`)."""
    h = heading(joints)
    return float(np.degrees(h[-1] - h[0]))


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(start, end) of each run of True frames in ``mask`` (T,), end exclusive."""
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist(), strict=True))


def airborne_runs(joints: np.ndarray) -> list[tuple[int, int]]:
    """(start, end) frames of the airborne episodes: both feet above the floor + ``AIR_MARGIN`` for
    ``AIR_FRAMES`` frames or more, runs split by one grounded frame merged."""
    left, right = joints[:, LEFT_FOOT, 1].min(1), joints[:, RIGHT_FOOT, 1].min(1)
    floor = np.percentile(np.minimum(left, right), 10)
    air = (left > floor + AIR_MARGIN) & (right > floor + AIR_MARGIN)
    merged: list[list[int]] = []
    for start, end in _runs(air):
        if merged and start - merged[-1][1] <= 1:
            merged[-1][1] = end
        else:
            merged.append([int(start), int(end)])
    return [(s, e) for s, e in merged if e - s >= AIR_FRAMES]


def jump_count(joints: np.ndarray) -> int:
    """Airborne episodes (:func:`airborne_runs`)."""
    return len(airborne_runs(joints))


def swing_count(joints: np.ndarray, side: str) -> int:
    """Side-to-side swings of the ``side`` ("left" | "right") hand while its wrist is above the head.

    The signal is the wrist minus its elbow along the hips' horizontal left-right axis; a swing is a
    move of that signal by at least ``SWING_MIN`` from the last extreme against the previous move (the
    first move counts from the first raised frame).
    """
    wrist, elbow = (L_WRIST, L_ELBOW) if side == "left" else (R_WRIST, R_ELBOW)
    axis = joints[:, L_HIP] - joints[:, R_HIP]
    axis[:, 1] = 0.0
    axis /= np.maximum(np.linalg.norm(axis, axis=-1, keepdims=True), 1e-9)
    signal = ((joints[:, wrist] - joints[:, elbow]) * axis).sum(-1)[joints[:, wrist, 1] > joints[:, HEAD, 1]]
    moves, direction, extreme = 0, 0, signal[0] if len(signal) else 0.0
    for value in signal[1:]:
        if direction * (value - extreme) > 0:
            extreme = value  # the current move goes on
        elif abs(value - extreme) >= SWING_MIN:
            moves, direction, extreme = moves + 1, (1 if value > extreme else -1), value
    return moves


def waving_side(joints: np.ndarray) -> str | None:
    """The hand that waves ("left" | "right"), or None when the motion does not wave.

    The hand is the one above the head longer (:func:`wrist_up`). It waves when it is raised for
    ``WAVE_UP`` frames or more, swings (:func:`swing_count`) ``WAVE_SWINGS`` times or more within its
    longest raised stretch, and never comes within ``HANDS_APART`` of the other wrist while raised.
    Claps overhead, jumping jacks and stretches also move a raised forearm from side to side; the
    last two conditions leave them out (on the embedded dataset's test split, 55 of the 62 motions
    whose captions say "wave", and 2 others, whose captions describe the same swing in other words).
    """
    up = wrist_up(joints)
    side = "left" if up[0] > up[1] else "right"
    if max(up) < WAVE_UP:
        return None
    wrist = L_WRIST if side == "left" else R_WRIST
    raised = joints[:, wrist, 1] > joints[:, HEAD, 1]
    if np.linalg.norm(joints[raised, L_WRIST] - joints[raised, R_WRIST], axis=-1).min() < HANDS_APART:
        return None
    start, end = max(_runs(raised), key=lambda run: run[1] - run[0])
    if swing_count(joints[start:end], side) < WAVE_SWINGS:
        return None
    return side


def reconstruction_detail(real: Sequence[np.ndarray], recon: Sequence[np.ndarray]) -> dict[str, float]:
    """What of each real motion's action a reconstruction keeps, over pairs of global joints (T, 22, 3).

    References are chosen on the real motion alone, so the check needs no caption or label:

    - ``path_err_m``: the pelvis's mean distance (m) from its real path, over all frames of all pairs;
    - ``turn_kept``: of the real motions turning by ``TURN_MIN`` degrees or more (:func:`net_turn`),
      the fraction whose reconstruction turns by the real angle within ``TURN_TOL``;
    - ``kick_kept``: of the real motions lifting one foot ``KICK_MIN`` or more and the other less than
      half as high (:func:`foot_rise`; jumps lift both), the fraction whose reconstruction lifts the
      same foot highest, to ``KICK_KEEP`` of the real rise;
    - ``wave_kept``: of the real motions that wave (:func:`waving_side`), the fraction whose
      reconstruction swings that hand (:func:`swing_count`) at least ``WAVE_KEEP`` times as often;
    - ``jumps_kept``: of the real motions with a jump (:func:`jump_count`), the fraction whose
      reconstruction has the same number of jumps;
    - ``<name>_refs``: how many references each fraction has (a fraction with none is absent: it does
      not apply, as a metric that does not apply to a row is absent from its metrics).
    """
    if len(real) != len(recon):
        raise ValueError(f"reconstruction_detail: {len(real)} real motions but {len(recon)} reconstructions")
    path, kept = [], {"turn": [], "kick": [], "wave": [], "jumps": []}
    for a, b in zip(real, recon, strict=True):
        if a.shape != b.shape:
            raise ValueError(f"reconstruction_detail: real {a.shape} and reconstruction {b.shape} differ")
        path.append(np.linalg.norm(a[:, PELVIS] - b[:, PELVIS], axis=-1))
        turn = net_turn(a)
        if abs(turn) >= TURN_MIN:
            kept["turn"].append(abs(net_turn(b) - turn) <= TURN_TOL)
        rise_a, rise_b = foot_rise(a), foot_rise(b)
        foot = int(np.argmax(rise_a))
        if rise_a[foot] >= KICK_MIN and rise_a[1 - foot] < 0.5 * rise_a[foot]:
            kept["kick"].append(int(np.argmax(rise_b)) == foot and rise_b[foot] >= KICK_KEEP * rise_a[foot])
        side = waving_side(a)
        if side is not None:
            kept["wave"].append(swing_count(b, side) >= WAVE_KEEP * swing_count(a, side))
        jumps = jump_count(a)
        if jumps >= 1:
            kept["jumps"].append(jump_count(b) == jumps)
    out = {"path_err_m": float(np.concatenate(path).mean())}
    for name, flags in kept.items():
        if flags:
            out[f"{name}_kept"] = float(np.mean(flags))
        out[f"{name}_refs"] = float(len(flags))
    return out
