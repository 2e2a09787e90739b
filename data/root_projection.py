"""Root projection: steer a generated motion's root, frame by frame, onto a trajectory hint.

A test-time step after any sampler (used by ``MotionLCM-Control+refine``, ``docs/controlnet.md``).
For each motion of length L with controlled frames C (a hint as in :mod:`data.control`):

1. the offset at a controlled frame t is ``delta_t = mean_j (hint[t, j] - joints[t, j])`` over the
   joints controlled at t, ``joints = recover_from_ric(features)``, in x and z only;
2. ``delta`` is linearly interpolated over all L frames between controlled frames and held after the
   last (per axis, ``np.interp``). Frame 0's horizontal root position is the representation's
   origin (``recover_root_rot_pos`` starts the integration at 0), so ``delta_0 = 0`` is an
   interpolation anchor (it replaces a controlled frame 0's offset). The target root path is
   ``root_t + delta_t``;
3. :func:`steer` puts the root on that path: each frame's heading turns by the angle from the
   motion's own horizontal root step to the target's step (measured where both move at least
   :data:`MIN_STEP_M` per frame, below which a step's direction is noise; interpolated between
   those frames, unwrapped and Gaussian-smoothed over :data:`TURN_SMOOTH_FRAMES`; frame 0
   keeps its heading, which the representation also pins), and the root's local linear velocity
   becomes the target step in the new heading (the inverse of the integration in
   :func:`data.features.recover_root_rot_pos`), so the root follows the path exactly. A motion that
   walks straight on a curved path turns with it and keeps stepping forward; one that stands is slid.
   The root's yaw velocity changes with the turn, every joint's local velocity (the ``vel`` group)
   is recomputed from the new joints as extraction's step 10 does; heights, joint positions relative
   to the root in its own frame (RIC), rotations and contacts are unchanged.

So a pelvis controlled on every frame lands on its hint horizontally (frame 0 excepted), and the
posture is untouched. Heights are left alone on purpose: a vertical shift of the whole body pushes
the feet through the floor or lifts them off it (measured in ``docs/controlnet.md``); the height
error stays, and the sampler (the ControlNet, the noise refinement) must get it right. What the
projection cannot fix it makes visible: a speed the legs do not step at, or a turn they do not
step through, shows as foot skating, which the evaluation's physical columns measure.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter1d

from data.features import feature_groups, recover_from_ric, recover_root_rot_pos
from data.rotations import qrot

#: Root steps shorter than this (metres per frame; 0.1 m/s at 20 fps) give no direction to turn by.
MIN_STEP_M = 0.005
#: Standard deviation (frames) of the Gaussian that smooths the turn angles.
TURN_SMOOTH_FRAMES = 2.0


def root_offsets(joints: np.ndarray, hint: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The per-frame horizontal offset (L, 3), y = 0, of steps 1-2 (module docstring) for one motion.

    ``joints`` and ``hint`` (L, J, 3), ``mask`` (L, J) bool. Zero when no frame after 0 is controlled.
    """
    length = joints.shape[0]
    frames = np.flatnonzero(mask.any(-1))
    frames = frames[frames > 0]  # frame 0 is the anchor at the origin
    delta = np.zeros((length, 3))
    if frames.size == 0:
        return delta
    diff = np.where(mask[..., None], hint - joints, 0.0).sum(1)[frames] / mask[frames].sum(-1, keepdims=True)
    anchors = np.concatenate([[0], frames])
    for axis in (0, 2):
        delta[:, axis] = np.interp(np.arange(length), anchors, np.concatenate([[0.0], diff[:, axis]]))
    return delta


def _turn_angles(own: np.ndarray, target: np.ndarray, min_step: float, smooth: float) -> np.ndarray:
    """Per-frame yaw (radians, about +y) that turns the motion's own horizontal steps ``own`` (L-1, 3)
    onto the target's ``target`` (L-1, 3): measured where both move at least ``min_step`` per frame,
    interpolated between those frames, unwrapped, Gaussian-smoothed over ``smooth`` frames; 0 when
    the motion never moves."""
    moving = np.flatnonzero((np.hypot(own[:, 0], own[:, 2]) >= min_step)
                            & (np.hypot(target[:, 0], target[:, 2]) >= min_step))
    if moving.size == 0:
        return np.zeros(len(own))
    angle = np.arctan2(own[:, 2] * target[:, 0] - own[:, 0] * target[:, 2],
                       own[:, 0] * target[:, 0] + own[:, 2] * target[:, 2])
    angle = np.interp(np.arange(len(own)), moving, np.unwrap(angle[moving]))
    return gaussian_filter1d(angle, smooth, mode="nearest", truncate=3.0)


def steer(features: np.ndarray, target: np.ndarray, joints_num: int) -> np.ndarray:
    """Features (L, D) of one motion (denormalised) whose root follows ``target`` (L, 3) horizontally
    (step 3, module docstring) -> a new (L, D) float64 array. ``target[0]`` must be the origin in x, z
    (where every motion starts); its y is ignored."""
    if np.any(target[0, [0, 2]] != 0):
        raise ValueError("steer: the target path must start at the origin in x and z")
    out = np.array(features, dtype=np.float64)
    length = len(out)
    if length < 2:
        return out
    yaw = np.concatenate([[0.0], np.cumsum(out[:-1, 0])])  # a_t; the heading quaternion turns by 2 a_t
    _, root = recover_root_rot_pos(out)
    own, wanted = np.diff(root, axis=0), np.diff(target, axis=0) * np.array([1.0, 0.0, 1.0])
    # turning the heading by beta turns the world step by beta too: a_{t+1} += -beta_t / 2
    new_yaw = yaw + np.concatenate([[0.0], -0.5 * _turn_angles(own, wanted, MIN_STEP_M, TURN_SMOOTH_FRAMES)])
    out[:-1, 0] = np.diff(new_yaw)
    quats, _ = recover_root_rot_pos(out)  # the new headings, integrated as recovery does
    out[:-1, 1:3] = qrot(quats[1:], wanted)[:, [0, 2]]  # world step -> local, as recovery inverts it
    joints = recover_from_ric(out, joints_num)
    vel = qrot(quats[:-1, None], joints[1:] - joints[:-1])  # extraction's step 10 on the new joints
    out[:-1, feature_groups(joints_num)["vel"]] = vel.reshape(length - 1, -1)
    return out


def project_root(features: np.ndarray, hint: np.ndarray, mask: np.ndarray, lengths: np.ndarray,
                 joints_num: int) -> np.ndarray:
    """A batch of denormalised features (B, N, D) projected onto hints (B, >= N, J, 3) with masks
    (B, >= N, J) bool, each motion on its first ``lengths[b]`` frames; padded frames are unchanged.
    Returns float32 (B, N, D)."""
    n = features.shape[1]
    if hint.shape[0] != features.shape[0] or hint.shape[1] < n or hint.shape[2] != joints_num \
            or mask.shape != hint.shape[:-1]:
        raise ValueError(f"project_root: hint {hint.shape} and mask {mask.shape} do not cover features "
                         f"{features.shape} with {joints_num} joints")
    out = np.array(features, dtype=np.float32)
    for b, length in enumerate(np.asarray(lengths, dtype=int)):
        if not mask[b, 1:length].any():
            continue  # nothing to follow after frame 0: the motion as it is
        motion = features[b, :length].astype(np.float64)
        joints = recover_from_ric(motion, joints_num)
        delta = root_offsets(joints, hint[b, :length].astype(np.float64), mask[b, :length])
        out[b, :length] = steer(motion, joints[:, 0] + delta, joints_num)
    return out
