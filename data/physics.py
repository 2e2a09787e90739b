"""Physical plausibility measures computed from global joint positions.

Convention (documented choice, DESIGN.md "Evaluation protocol"): the floor is the plane y = 0,
which is where HumanML3D's processing puts the lowest *joint centre* of a clip. All inputs are
global joint positions of shape (T, J, 3) in the skeleton's units; results are in metres.

- Foot skating follows OmniControl's ``calculate_skating_ratio``: toe joints (HumanML3D 10/11),
  horizontal speed v_t = |Δxz| * fps, v̄ = 5-frame box filter of v (zero padded); frame t skates
  when, for either foot, the toe is below 5 cm at t and t+1 and both v_t and v̄_t exceed 0.5 m/s.
  The ratio divides by the T-1 frame pairs.
- Ground penetration: per frame, the depth of the lowest joint below the floor when it lies
  deeper than the tolerance (0 otherwise); averaged over frames.
- Floating: per frame, how far the lowest joint lies above the floor beyond the tolerance
  (0 otherwise); averaged over frames. Tolerance 5 mm, as in the public PhysDiff re-implementation.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import uniform_filter1d

from data.skeleton import Skeleton

SKATE_HEIGHT_M = 0.05
SKATE_SPEED_MPS = 0.5
FLOOR_TOLERANCE_M = 0.005


def _metres(joints: np.ndarray, skeleton: Skeleton) -> np.ndarray:
    joints = np.asarray(joints, dtype=np.float64)
    if joints.ndim != 3 or joints.shape[1:] != (skeleton.joints_num, 3):
        raise ValueError(
            f"expected joints of shape (T, {skeleton.joints_num}, 3), got {joints.shape}"
        )
    return joints * skeleton.unit


def toe_tracks(joints: np.ndarray, skeleton: Skeleton) -> tuple[np.ndarray, np.ndarray]:
    """Both toes' heights (T, 2) in metres and horizontal speeds over each frame pair (T-1, 2) in m/s."""
    toes = _metres(joints, skeleton)[:, [skeleton.feet_left[1], skeleton.feet_right[1]]]  # (T, 2, 3)
    return toes[..., 1], np.linalg.norm(np.diff(toes[..., [0, 2]], axis=0), axis=-1) * skeleton.fps


def skating_toes(joints: np.ndarray, skeleton: Skeleton) -> np.ndarray:
    """Boolean (T-1, 2) mask: in frame pair (t, t+1), the left / right toe is low and slides."""
    height, speed = toe_tracks(joints, skeleton)
    smooth = uniform_filter1d(speed, size=5, axis=0, mode="constant")
    low = height < SKATE_HEIGHT_M
    return low[:-1] & low[1:] & (speed > SKATE_SPEED_MPS) & (smooth > SKATE_SPEED_MPS)


def skating_frames(joints: np.ndarray, skeleton: Skeleton) -> np.ndarray:
    """Boolean (T-1,) mask of frame pairs (t, t+1) in which a planted toe slides."""
    return np.any(skating_toes(joints, skeleton), axis=1)


def foot_skating_ratio(joints: np.ndarray, skeleton: Skeleton) -> float:
    """Fraction of the T-1 frame pairs that skate (see module docstring)."""
    return float(skating_frames(joints, skeleton).mean())


def ground_penetration(joints: np.ndarray, skeleton: Skeleton, tol: float = FLOOR_TOLERANCE_M) -> float:
    """Mean over frames of the lowest joint's depth -min_j y when deeper than ``tol``, else 0, in metres."""
    lowest = _metres(joints, skeleton)[..., 1].min(axis=1)
    return float(np.where(lowest < -tol, -lowest, 0.0).mean())


def floating(joints: np.ndarray, skeleton: Skeleton, tol: float = FLOOR_TOLERANCE_M) -> float:
    """Mean over frames of the lowest joint's height when above ``tol``, else 0, in metres."""
    lowest = _metres(joints, skeleton)[..., 1].min(axis=1)
    return float(np.where(lowest > tol, lowest, 0.0).mean())
