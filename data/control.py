"""Control signals (hints) for trajectory-controlled generation (MotionLCM §3.3; OmniControl).

A hint is the ground truth's (or a user's) global joint positions ``joints`` (B, T, J, 3) in metres
with a mask (B, T, J) bool, True at the controlled (frame, joint) entries; everything outside the
mask is ignored. Padded frames (t >= length) are never controlled.

Densities (MotionLCM's ``TEST_DENSITY``): ``"100%"`` and ``"25%"`` control that share of each
motion's frames, rounded down as MotionLCM's ``int(length * density / 100)`` (at least one); an
integer string (``"5"``, ``"2"``, ``"1"``) that many frames (at most the motion's length); frames
are drawn at random without replacement. Training draws, per sample, one joint of
``train_joints`` and a uniform number of frames in [1, T - 1] (T the sample's length; 1 when
T = 1), MotionLCM's ``TRAIN_DENSITY: random``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

#: MotionLCM's joints for spatial control (HumanML3D ids): pelvis, left/right foot, head, left/right wrist.
CONTROL_JOINTS = {"pelvis": 0, "left_foot": 10, "right_foot": 11, "head": 15, "left_wrist": 20, "right_wrist": 21}
#: The same body points on KIT-ML's 21 joints: the root, each leg's and arm's last joint (l_toe, r_toe,
#: l_wrist, r_wrist) and the spine's (bun), as HumanML3D's are the last of its chains.
KIT_CONTROL_JOINTS = {"pelvis": 0, "left_foot": 15, "right_foot": 20, "head": 4, "left_wrist": 7, "right_wrist": 10}
#: The tables by the skeleton's joint count (HumanML3D 22, KIT-ML 21).
CONTROL_JOINTS_BY_COUNT = {22: CONTROL_JOINTS, 21: KIT_CONTROL_JOINTS}
TEST_DENSITIES = ("100%", "25%", "5", "2", "1")


def joint_ids(names: Sequence[str], joints_num: int = 22) -> tuple[int, ...]:
    """Joint names of :data:`CONTROL_JOINTS` -> their ids on the skeleton of ``joints_num`` joints; ValueError
    naming an unknown name or joint count."""
    if joints_num not in CONTROL_JOINTS_BY_COUNT:
        raise ValueError(f"no control joints for a skeleton of {joints_num} joints (known: HumanML3D's 22, KIT-ML's "
                         f"21)")
    table = CONTROL_JOINTS_BY_COUNT[joints_num]
    unknown = [n for n in names if n not in table]
    if unknown or not names:
        raise ValueError(f"control joints {list(names)!r}: choose one or more of {', '.join(table)}")
    return tuple(table[n] for n in names)


def keyframe_count(length: int, density: str) -> int:
    """Number of controlled frames of a ``length``-frame motion at ``density`` (module docstring)."""
    if density.endswith("%"):
        share = float(density[:-1])
        if not 0 < share <= 100:
            raise ValueError(f"control density {density!r}: a percentage must lie in (0, 100]")
        return max(1, min(length, int(length * share / 100)))
    if not density.isdigit() or int(density) < 1:
        raise ValueError(f"control density {density!r}: use a percentage ('100%', '25%') or a frame count ('5')")
    return min(length, int(density))


def evaluation_mask(lengths: np.ndarray, num_frames: int, joints_num: int, joints: Sequence[int], density: str,
                    rng: np.random.Generator) -> np.ndarray:
    """(B, T, J) bool: every joint of ``joints`` on the same ``density`` random frames of each motion."""
    mask = np.zeros((len(lengths), num_frames, joints_num), dtype=bool)
    for b, length in enumerate(lengths):
        frames = rng.choice(int(length), keyframe_count(int(length), density), replace=False)
        mask[b, np.sort(frames)[:, None], list(joints)] = True
    return mask


def training_mask(lengths: torch.Tensor, num_frames: int, joints_num: int, joints: Sequence[int],
                  generator: torch.Generator | None = None) -> torch.Tensor:
    """(B, T, J) bool, MotionLCM's random training density (module docstring), from ``generator``.

    Per sample: one joint of ``joints``, ``n ~ U{1, ..., max(1, L - 1)}`` distinct random valid frames.
    """
    b = len(lengths)
    lengths = lengths.long().cpu()
    at = generator.device if generator is not None else torch.device("cpu")  # drawn there, used on the CPU
    joint = torch.as_tensor(joints)[torch.randint(len(joints), (b,), generator=generator, device=at).cpu()]
    count = 1 + (torch.rand(b, generator=generator, device=at).cpu() * (lengths - 1).clamp(min=1)).long()
    # n random valid frames: the n smallest of random keys, padded frames keyed past every valid one
    keys = torch.rand(b, num_frames, generator=generator, device=at).cpu()
    keys[torch.arange(num_frames)[None] >= lengths[:, None]] = 2.0
    rank = keys.argsort(1).argsort(1)
    frames = rank < count[:, None]
    mask = torch.zeros(b, num_frames, joints_num, dtype=torch.bool)
    mask[torch.arange(b), :, joint] = frames
    return mask
