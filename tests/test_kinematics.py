"""Forward/inverse kinematics in HumanML3D's convention (data.kinematics)."""

from __future__ import annotations

import numpy as np
import torch

from data import rotations as R
from data.features import features_from_joints, recover_from_ric
from data.kinematics import facing_forward, forward_kinematics, inverse_kinematics, root_heading
from data.skeleton import HUMANML3D, KIT, Skeleton


def _random_pose_clip(skeleton: Skeleton, frames: int, seed: int) -> np.ndarray:
    """(T, J, 3) joints from FK of random local rotations (0.4 rad scale) and a moving root."""
    rng = np.random.default_rng(seed)
    local = R.axis_angle_to_quat(0.4 * rng.normal(size=(frames, skeleton.joints_num, 3)))
    root = (np.cumsum(0.05 * rng.normal(size=(frames, 3)), axis=0) + [0.0, 0.9, 0.0]) / skeleton.unit
    return forward_kinematics(local, root, skeleton.offsets(), skeleton)


def test_rest_pose_faces_plus_z() -> None:
    identity = np.tile([1.0, 0, 0, 0], (1, HUMANML3D.joints_num, 1))
    rest = forward_kinematics(identity, np.zeros((1, 3)), HUMANML3D.offsets(), HUMANML3D)
    np.testing.assert_allclose(rest[0, 1, 0], HUMANML3D.bone_lengths[1])  # left hip on +x
    np.testing.assert_allclose(rest[0, 10, 2] - rest[0, 7, 2], HUMANML3D.bone_lengths[10])  # toe forward
    forward = R.normalize(facing_forward(rest, HUMANML3D.face_joints, hip_quirk=False))
    np.testing.assert_allclose(forward, [[0, 0, 1]], atol=1e-12)


def test_joint_names_name_the_side_the_rest_pose_puts_them_on() -> None:
    """Each ``l_``/``left_`` joint lies on the body's left in the rest pose, the left judged from where the toes
    point (y up: left = up x toe direction), not from labels. HumanML3D's face joints and feet carry its
    names' sides; KIT's keep HumanML3D's indices, whose side labels are the MMM names' opposite."""
    for skeleton in (HUMANML3D, KIT):
        identity = np.tile([1.0, 0, 0, 0], (1, skeleton.joints_num, 1))
        rest = forward_kinematics(identity, np.zeros((1, 3)), skeleton.offsets(), skeleton)[0]
        ankle, toe = skeleton.feet_left
        left_of_body = np.cross([0.0, 1.0, 0.0], rest[toe] - rest[ankle])
        sides = {j: np.sign(np.dot(rest[j] - rest[0], left_of_body)) for j in range(skeleton.joints_num)}
        named = [(j, name) for j, name in enumerate(skeleton.joint_names) if name.startswith(("l", "r"))]
        assert len(named) >= 16
        for j, name in named:
            if sides[j] != 0:
                assert sides[j] == (1 if name.startswith("l") else -1), (skeleton.name, name)
    hml = [HUMANML3D.joint_names[j] for j in (*HUMANML3D.face_joints, *HUMANML3D.feet_left)]
    assert hml == ["right_hip", "left_hip", "right_shoulder", "left_shoulder", "left_ankle", "left_foot"]
    kit = [KIT.joint_names[j] for j in (*KIT.face_joints, *KIT.feet_left)]
    assert kit == ["l_hip", "r_hip", "l_shoulder", "r_shoulder", "r_mt", "r_toe"]


def walk_toward_the_toes(skeleton: Skeleton, frames: int = 12) -> np.ndarray:
    """(T, J, 3) the rest pose turned 40 degrees about y, gliding 1.2 m/s along where its toes point."""
    local = np.tile([1.0, 0, 0, 0], (frames, skeleton.joints_num, 1))
    local[:, 0] = R.axis_angle_to_quat(np.array([0.0, np.radians(40.0), 0.0]))
    ahead = np.array([np.sin(np.radians(40.0)), 0.0, np.cos(np.radians(40.0))])
    root = ([0.0, 0.9, 0.0] + np.arange(frames)[:, None] * 1.2 / skeleton.fps * ahead) / skeleton.unit
    return forward_kinematics(local, root, skeleton.offsets(), skeleton)


def test_front_is_where_canonical_motions_face() -> None:
    """Features turn the face joints' named forward onto +z. HumanML3D's bodies then face +z; KIT-ML's named
    sides are the other way round, so its bodies face -z (``Skeleton.front``), judged from the toes and
    from the recovered travel of a body walking toward its toes."""
    assert (HUMANML3D.front, KIT.front) == (1.0, -1.0)
    for skeleton in (HUMANML3D, KIT):
        joints = recover_from_ric(features_from_joints(walk_toward_the_toes(skeleton), skeleton), skeleton.joints_num)
        toes = sum(joints[0, toe] - joints[0, ankle] for ankle, toe in (skeleton.feet_left, skeleton.feet_right))
        travel = joints[-1, 0] - joints[0, 0]
        for direction in (toes, travel):
            horizontal = direction[[0, 2]] / np.linalg.norm(direction[[0, 2]])
            np.testing.assert_allclose(horizontal, [0.0, skeleton.front], atol=1e-6)


def test_hip_quirk_reverses_only_the_hip_term() -> None:
    p = np.zeros((22, 3))
    p[2], p[1] = [-0.1, 0, 0.05], [0.1, 0, -0.05]  # r_hip, l_hip
    p[17], p[16] = [-0.2, 0, -0.1], [0.2, 0, 0.1]  # r_shoulder, l_shoulder
    y = np.array([0.0, 1.0, 0.0])
    correct = np.cross(y, R.normalize((p[2] - p[1]) + (p[17] - p[16])))
    quirk = np.cross(y, R.normalize((p[1] - p[2]) + (p[17] - p[16])))
    np.testing.assert_allclose(facing_forward(p, HUMANML3D.face_joints, hip_quirk=False), correct)
    np.testing.assert_allclose(facing_forward(p, HUMANML3D.face_joints, hip_quirk=True), quirk)
    assert not np.allclose(correct, quirk)


def test_root_heading_identity_at_frame_0_and_smoothing() -> None:
    # Character spinning about y at 0.05 rad/frame: headings are yaw rotations.
    yaw = 0.05 * np.arange(60)
    identity = np.tile([1.0, 0, 0, 0], (60, HUMANML3D.joints_num, 1))
    identity[:, 0] = R.yaw_to_quat(yaw)
    clip = forward_kinematics(identity, np.zeros((60, 3)), HUMANML3D.offsets(), HUMANML3D)
    raw = root_heading(clip, HUMANML3D, smooth_sigma=None, hip_quirk=False)
    np.testing.assert_allclose(raw[0], [1, 0, 0, 0])
    # Root heading maps the facing direction (rotated +z) back to +z: the inverse yaw.
    np.testing.assert_allclose(np.abs((raw[1:] * R.yaw_to_quat(-yaw[1:])).sum(-1)), 1.0, atol=1e-12)
    smooth = root_heading(clip, HUMANML3D, smooth_sigma=20.0, hip_quirk=False)
    np.testing.assert_allclose(smooth[0], [1, 0, 0, 0])
    assert np.allclose(smooth[30], raw[30], atol=1e-3)  # linear yaw: smoothing ~ no-op mid-clip
    assert not np.allclose(smooth[-1], raw[-1], atol=1e-3)  # ... but not at the 'nearest' edge


def test_fk_of_ik_reproduces_bone_directions_and_positions() -> None:
    for skeleton in (HUMANML3D, KIT):
        clip = _random_pose_clip(skeleton, 12, seed=7)
        local = inverse_kinematics(clip, skeleton, smooth_sigma=20.0, hip_quirk=True)
        parents = np.array(skeleton.parents)
        # Other bone lengths: directions are kept.
        offsets = skeleton.offsets(skeleton.bone_lengths * np.linspace(0.5, 1.5, skeleton.joints_num))
        redone = forward_kinematics(local, clip[:, 0], offsets, skeleton)
        bones = (clip - clip[:, parents])[:, 1:]
        new_bones = (redone - redone[:, parents])[:, 1:]
        np.testing.assert_allclose(R.normalize(new_bones), R.normalize(bones), atol=1e-10)
        # Same bone lengths: positions are kept.
        same = forward_kinematics(local, clip[:, 0], skeleton.offsets(), skeleton)
        np.testing.assert_allclose(same, clip, atol=1e-9 * skeleton.bone_lengths.max())


def test_ik_is_swing_only_and_collars_follow_root_heading() -> None:
    clip = _random_pose_clip(HUMANML3D, 5, seed=8)
    local = inverse_kinematics(clip, HUMANML3D, smooth_sigma=None, hip_quirk=True)
    collar = 13  # chain (9, 13, ...): global rotation of the collar = root ⊗ local
    swing = R.qmul(local[:, 0], local[:, collar])
    np.testing.assert_allclose((swing[:, 1:] * HUMANML3D.raw_offsets[collar]).sum(-1), 0.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(local, axis=-1), 1.0, atol=1e-12)


def test_torch_fk_matches_numpy_and_has_gradients() -> None:
    clip = _random_pose_clip(HUMANML3D, 4, seed=9)
    local = inverse_kinematics(clip, HUMANML3D)
    t_local = torch.tensor(local, requires_grad=True)
    t_root = torch.tensor(clip[:, 0], requires_grad=True)
    out = forward_kinematics(t_local, t_root, HUMANML3D.offsets(), HUMANML3D)
    np.testing.assert_allclose(out.detach().numpy(), forward_kinematics(local, clip[:, 0], HUMANML3D.offsets(),
                                                                        HUMANML3D), atol=1e-12)  # fmt: skip
    out.square().sum().backward()
    assert t_local.grad is not None and t_local.grad.abs().sum() > 0
    assert t_root.grad is not None and t_root.grad.abs().sum() > 0
    small = (t_local[:1].detach().requires_grad_(), t_root[:1].detach().requires_grad_())
    assert torch.autograd.gradcheck(lambda q, r: forward_kinematics(q, r, HUMANML3D.offsets(), HUMANML3D), small)
