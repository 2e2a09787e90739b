"""Forward and inverse kinematics in HumanML3D's convention (``common/skeleton.py``).

Rotation convention. ``local[..., 0]`` is the root rotation. Every kinematic chain starts its
accumulated rotation at the root rotation -- also the chains that start at a non-root joint
(the arms, which start at spine3) -- and multiplies the local rotations of the chain's joints
in order: ``R_b = R_a ⊗ local_b`` and ``p_b = p_a + qrot(R_b, offset_b)``. ``offset_b`` is the
bone vector of joint ``b`` in the rest pose (``Skeleton.offsets``: rest direction * length).

HumanML3D's inverse kinematics is swing-only: the global rotation of each bone is the
shortest arc from its rest direction to its observed direction, so the bone's twist is lost.
FK(IK(x)) therefore reproduces every bone *direction* of x exactly, and x itself when the
offsets carry x's bone lengths.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.ndimage import gaussian_filter1d

from data.rotations import Array, as_like, normalize, qbetween, qinv, qmul, qrot
from data.skeleton import Skeleton

Y_AXIS = np.array([0.0, 1.0, 0.0])
Z_AXIS = np.array([0.0, 0.0, 1.0])
IDENTITY_QUAT = np.array([1.0, 0.0, 0.0, 0.0])


def forward_kinematics(local_quats: Array, root_pos: Array, offsets: Array, skeleton: Skeleton) -> Array:
    """Global joint positions from local rotations (HumanML3D ``forward_kinematics_np``).

    Args:
        local_quats: (..., J, 4) local joint rotations; slot 0 holds the root rotation.
        root_pos: (..., 3) root positions.
        offsets: (J, 3) rest bone vectors (root row unused).
        skeleton: supplies the kinematic chains.

    Returns:
        (..., J, 3) global joint positions, numpy or torch like ``local_quats``; differentiable
        in torch with respect to all three arrays.
    """
    offsets = as_like(offsets, local_quats)
    root_pos = as_like(root_pos, local_quats)
    positions: list[Array | None] = [None] * skeleton.joints_num
    positions[0] = root_pos
    for chain in skeleton.kinematic_chain:
        rot = local_quats[..., 0, :]
        for a, b in zip(chain[:-1], chain[1:], strict=True):
            rot = qmul(rot, local_quats[..., b, :])
            positions[b] = positions[a] + qrot(rot, offsets[b])
    if isinstance(local_quats, torch.Tensor):
        return torch.stack(torch.broadcast_tensors(*positions), -2)
    return np.stack(np.broadcast_arrays(*positions), -2)


def facing_forward(joints: np.ndarray, face_joints: tuple[int, int, int, int], *, hip_quirk: bool) -> np.ndarray:
    """Un-normalised facing direction ``ŷ × n(across)`` per frame: (..., J, 3) -> (..., 3).

    ``face_joints = (r_hip, l_hip, r_shoulder, l_shoulder)``. The correct across vector
    (reference A.3 step 4) is ``(p[r_hip] - p[l_hip]) + (p[r_sho] - p[l_sho])``. With
    ``hip_quirk=True`` the hip term is reversed, ``(p[l_hip] - p[r_hip]) + (p[r_sho] - p[l_sho])``,
    as in HumanML3D's ``inverse_kinematics_np`` (reference A.3 step 6, issues #55/#107): the data
    was made that way, so feature extraction must reproduce it.

    The result is left un-normalised because the reference smooths it before normalising.
    """
    r_hip, l_hip, r_sho, l_sho = face_joints
    if hip_quirk:
        r_hip, l_hip = l_hip, r_hip
    across = (joints[..., r_hip, :] - joints[..., l_hip, :]) + (joints[..., r_sho, :] - joints[..., l_sho, :])
    return np.cross(Y_AXIS, normalize(across))


def root_heading(
    joints: np.ndarray, skeleton: Skeleton, *, smooth_sigma: float | None, hip_quirk: bool = True
) -> np.ndarray:
    """Root rotations that turn each frame's facing direction onto +z (reference A.3 step 6).

    Args:
        joints: (T, J, 3) global joint positions.
        smooth_sigma: if given, the forward vectors are smoothed over time with
            ``gaussian_filter1d(sigma, mode='nearest')`` before normalising (HumanML3D: 20).
        hip_quirk: reproduce HumanML3D's swapped hip indices (see ``facing_forward``).

    Returns:
        (T, 4) quaternions ``qbetween(forward_t, ẑ)``, with frame 0 forced to the identity
        as the reference does.
    """
    forward = facing_forward(joints, skeleton.face_joints, hip_quirk=hip_quirk)
    if smooth_sigma is not None:
        forward = gaussian_filter1d(forward, smooth_sigma, axis=0, mode="nearest")
    root_q = qbetween(normalize(forward), np.broadcast_to(Z_AXIS, forward.shape))
    root_q[0] = IDENTITY_QUAT
    return root_q


def inverse_kinematics(
    joints: np.ndarray, skeleton: Skeleton, *, smooth_sigma: float | None = None, hip_quirk: bool = True
) -> np.ndarray:
    """HumanML3D's swing-only IK (``inverse_kinematics_np``, reference A.3 step 6).

    For each chain the accumulated rotation starts at the root heading; for each bone a -> b
    the swing ``s = qbetween(raw_dir_b, n(p_b - p_a))`` is the bone's global rotation and its
    local rotation is ``R⁻¹ ⊗ s`` (so the collars are relative to the root heading).

    Args:
        joints: (T, J, 3) global joint positions.
        smooth_sigma, hip_quirk: see ``root_heading``.

    Returns:
        (T, J, 4) local quaternions; slot 0 holds the root heading (identity at frame 0).
    """
    joints = np.asarray(joints, dtype=np.float64)
    root_q = root_heading(joints, skeleton, smooth_sigma=smooth_sigma, hip_quirk=hip_quirk)
    local = np.zeros(joints.shape[:-1] + (4,))
    local[:, 0] = root_q
    for chain in skeleton.kinematic_chain:
        rot = root_q
        for a, b in zip(chain[:-1], chain[1:], strict=True):
            rest_dir = np.broadcast_to(skeleton.raw_offsets[b], joints[:, b].shape)
            swing = qbetween(rest_dir, normalize(joints[:, b] - joints[:, a]))
            local[:, b] = qmul(qinv(rot), swing)
            rot = qmul(rot, local[:, b])
    return local
