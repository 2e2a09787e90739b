"""The synthetic motion library: every parametric action, and segments of a motion built from them.

:data:`ACTIONS` names each action with its builder and parameter sampler (one module per action
family: :mod:`data.synthetic_locomotion`, :mod:`data.synthetic_jumps`,
:mod:`data.synthetic_postures`, :mod:`data.synthetic_kick_throw`, :mod:`data.synthetic_upper_body`)
and how often it is drawn. A :class:`Segment` is one drawn action, optionally with an upper-body
action on top; :func:`build_segment` plans it.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

from data.synthetic_jumps import (
    build_hop,
    build_jump,
    build_jumping_jacks,
    sample_hop,
    sample_jump,
    sample_jumping_jacks,
)
from data.synthetic_kick_throw import build_kick, build_throw, sample_kick, sample_throw
from data.synthetic_locomotion import (
    build_circle,
    build_run,
    build_turn,
    build_walk,
    sample_circle,
    sample_jog,
    sample_run,
    sample_turn,
    sample_walk,
)
from data.synthetic_motion import FPS, GROUPS, Body, Piece, State, frames, window
from data.synthetic_postures import (
    build_bow,
    build_crouch,
    build_pick_up,
    build_sit_down,
    build_squat,
    build_stand_up,
    sample_bow,
    sample_crouch,
    sample_duration,
    sample_pick_up,
    sample_squat,
)
from data.synthetic_upper_body import (
    build_clap,
    build_look_around,
    build_punch,
    build_raise_arms,
    build_stretch,
    build_wave,
    sample_clap,
    sample_look_around,
    sample_punch,
    sample_raise_arms,
    sample_stretch,
    sample_wave,
)


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
# Segments
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Segment:
    """One action of a motion: its kind, parameters and an optional upper-body action on top."""

    kind: str
    params: dict
    upper: Segment | None = None

    @property
    def label(self) -> str:
        """The action class of the segment's action."""
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
