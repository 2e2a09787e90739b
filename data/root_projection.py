"""Root projection: slide a generated motion horizontally, frame by frame, onto a trajectory hint.

A test-time step after any sampler (used by ``MotionLCM-Control+refine``, ``docs/controlnet.md``).
For each motion of length L with controlled frames C (a hint as in :mod:`data.control`):

1. the offset at a controlled frame t is ``delta_t = mean_j (hint[t, j] - joints[t, j])`` over the
   joints controlled at t, ``joints = recover_from_ric(features)``, in x and z only;
2. ``delta`` is linearly interpolated over all L frames between controlled frames and held after the
   last (per axis, ``np.interp``). Frame 0's horizontal root position is the representation's
   origin (``recover_root_rot_pos`` starts the integration at 0), so ``delta_0 = 0`` is an
   interpolation anchor (it replaces a controlled frame 0's offset);
3. the body slides by ``delta_t`` at every frame: the root's local linear velocity ``f[t, 1:3]``
   gets the change of displacement ``Delta_t = delta_{t+1} - delta_t`` rotated into the heading of
   frame t + 1 (the inverse of the integration in :func:`data.features.recover_root_rot_pos`), and
   every joint's local velocity (the ``vel`` group, heading of frame t, as extraction's step 10)
   gets the same Delta_t. Headings, heights, joint positions relative to the root (RIC), rotations
   and contacts are unchanged.

So the recovered joints of the result equal the input's plus ``delta_t`` (to float precision): a
pelvis controlled on every frame lands on its hint horizontally (frame 0 excepted), and the posture
is untouched. Heights are left alone on purpose: a vertical shift of the whole body pushes the feet
through the floor or lifts them off it (measured in ``docs/controlnet.md``); the height error
stays, and the sampler (the ControlNet, the noise refinement) must get it right. What the
projection cannot fix it makes visible: a slide the legs do not step with shows as foot skating,
which the evaluation's physical columns measure.
"""

from __future__ import annotations

import numpy as np

from data.features import feature_groups, recover_from_ric, recover_root_rot_pos
from data.rotations import qrot


def root_offsets(joints: np.ndarray, hint: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The per-frame horizontal slide (L, 3), y = 0, of steps 1-2 (module docstring) for one motion.

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


def translate(features: np.ndarray, delta: np.ndarray, joints_num: int) -> np.ndarray:
    """Features (L, D) of one motion (denormalised) slid by ``delta`` (L, 3), ``delta[0] == 0`` and
    ``delta[:, 1] == 0`` (step 3, module docstring) -> a new (L, D) float64 array."""
    if np.any(delta[0] != 0) or np.any(delta[:, 1] != 0):
        raise ValueError("translate: the slide must be horizontal (delta[:, 1] == 0) and 0 at frame 0")
    out = np.array(features, dtype=np.float64)
    heading, _ = recover_root_rot_pos(out)
    step = delta[1:] - delta[:-1]  # (L-1, 3): the change of displacement from t to t+1
    out[:-1, 1:3] += qrot(heading[1:], step)[:, [0, 2]]
    out[:-1, feature_groups(joints_num)["vel"]] += np.tile(qrot(heading[:-1], step), joints_num)
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
        motion = features[b, :length].astype(np.float64)
        joints = recover_from_ric(motion, joints_num)
        delta = root_offsets(joints, hint[b, :length].astype(np.float64), mask[b, :length])
        out[b, :length] = translate(motion, delta, joints_num)
    return out
