"""Building blocks shared by the action families of the synthetic motion library.

Sides and feet by name, the body's size, key timing, the two common shapes of an action (upper
body only, or standing with pelvis keys) and the helpers of the parameter samplers. Builders take
``(body, start state, params)`` and return a :class:`~data.synthetic_motion.Piece`; params are plain
JSON-able dicts drawn by the matching ``sample_*`` function.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TypeVar

import numpy as np

from data.synthetic_motion import LEFT, RIGHT, Body, Piece, State, frames, hold, interp_keys, pose_track, shift_root

T = TypeVar("T")

SIGN = {"left": 1.0, "right": -1.0}
FOOT = {"left": LEFT, "right": RIGHT}


def other(side: str) -> str:
    """The opposite side."""
    return "right" if side == "left" else "left"


def body_scale(body: Body) -> float:
    """Body size relative to the reference skeleton (pelvis about 0.96 m)."""
    return body.stand_height / 0.96


def timed(keys: Sequence[tuple[float, Mapping[str, float]]], tempo: float) -> list[tuple[float, Mapping[str, float]]]:
    """Keys with their times stretched by ``tempo``."""
    return [(t * tempo, k) for t, k in keys]


def upper_body_piece(body: Body, state: State, keys: Sequence[tuple[float, Mapping[str, float]]],
                     tail: float = 0.15) -> Piece:
    """An action of the upper body only: the legs keep the state's posture."""
    n = frames(keys[-1][0] + tail)
    plan = hold(body, state, n)
    plan.channels = pose_track(keys, n, state.rest)
    return Piece(plan, state)


def standing_piece(body: Body, state: State, keys: Sequence[tuple[float, Mapping[str, float]]],
                   root_keys: Sequence[tuple[float, float, float, float]], tail: float = 0.15) -> Piece:
    """A standing action: channel keys plus pelvis keys ``(t, ahead, up, left)`` relative to rest."""
    piece = upper_body_piece(body, state, keys, tail)
    rel = interp_keys([k[0] for k in root_keys], [k[1:] for k in root_keys], len(piece.plan))
    shift_root(piece.plan, rel[:, 0], rel[:, 1], rel[:, 2])
    return piece


# ---------------------------------------------------------------------------------------------
# Parameter samplers
# ---------------------------------------------------------------------------------------------


def pick(rng: np.random.Generator, options: Sequence[T], weights: Sequence[float] | None = None) -> T:
    """One of ``options`` (weighted), as a plain Python value."""
    p = None if weights is None else np.asarray(weights, dtype=np.float64) / np.sum(weights)
    return options[int(rng.choice(len(options), p=p))]


def uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    """A uniform draw from [lo, hi), rounded to 3 decimals."""
    return round(float(rng.uniform(lo, hi)), 3)


def pick_side(rng: np.random.Generator, both: float = 0.0) -> str:
    """``"left"`` or ``"right"``, or ``"both"`` with probability ``both``."""
    return pick(rng, ("left", "right", "both"), ((1 - both) / 2, (1 - both) / 2, both))
