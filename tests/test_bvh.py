"""BVH export (data/bvh.py): positions written then read back, known answers, standard files, bad files.

The round trip is checked on a real HumanML3D clip (the fixture has the skeleton's bone lengths) and
on synthetic motions retargeted to the skeleton's bones, to 1 mm; a motion with other bone lengths
keeps every bone's direction. A 2-joint chain has known angles; a hand-written BVH in XYZ and ZXY
channel orders has known positions.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from data.bvh import ROTATION_ORDERS, continuous_euler, read_bvh, rotation_orders, write_bvh
from data.kinematics import forward_kinematics, inverse_kinematics
from data.skeleton import HUMANML3D, Skeleton
from data.synthetic import SyntheticConfig, generate_motion

FIXTURE = Path(__file__).parent / "fixtures" / "humanml3d" / "new_joints_012314.npy"
MM = 1e-3


def retargeted(joints: np.ndarray) -> np.ndarray:
    """The motion with the skeleton's bone lengths (HumanML3D's own retargeting: swing IK, then FK)."""
    return forward_kinematics(inverse_kinematics(joints, HUMANML3D), joints[:, 0], HUMANML3D.offsets(), HUMANML3D)


def real_motions() -> list[np.ndarray]:
    synthetic = [generate_motion(7, k, SyntheticConfig(num_motions=4, workers=1)).joints for k in range(3)]
    return [np.load(FIXTURE), *[retargeted(j) for j in synthetic]]


def round_trip(joints: np.ndarray, tmp_path: Path, skeleton: Skeleton = HUMANML3D) -> np.ndarray:
    path = write_bvh(joints, skeleton, tmp_path / "motion.bvh", skeleton.fps)
    return read_bvh(path).joints(skeleton.joint_names)


def test_round_trip_is_within_a_millimetre_on_real_motions(tmp_path: Path) -> None:
    for joints in real_motions():
        assert np.abs(HUMANML3D.bone_lengths_of(joints) - HUMANML3D.bone_lengths).max() < 1e-4
        back = round_trip(joints, tmp_path)
        assert back.shape == joints.shape
        assert np.linalg.norm(back - joints, axis=-1).max() < MM


def test_other_bone_lengths_keep_every_bone_direction(tmp_path: Path) -> None:
    """A synthetic motion's bones differ from the skeleton's by centimetres: directions kept, lengths the skeleton's."""
    joints = generate_motion(7, 0, SyntheticConfig(num_motions=4, workers=1)).joints.astype(np.float64)
    assert np.abs(HUMANML3D.bone_lengths_of(joints) - HUMANML3D.bone_lengths).max() > 0.005
    back = round_trip(joints, tmp_path)
    parents = np.array(HUMANML3D.parents[1:])

    def directions(x: np.ndarray) -> np.ndarray:
        bones = x[:, 1:] - x[:, parents]
        return bones / np.linalg.norm(bones, axis=-1, keepdims=True)

    np.testing.assert_allclose(directions(back), directions(joints), atol=1e-5)
    np.testing.assert_allclose(HUMANML3D.bone_lengths_of(back), np.broadcast_to(HUMANML3D.bone_lengths, back.shape[:2]),
                               atol=1e-5)
    np.testing.assert_allclose(back[:, 0], joints[:, 0], atol=1e-6)


def chain_skeleton() -> Skeleton:
    """Two joints, the bone 1 m along +x in the rest pose."""
    return Skeleton(name="chain", joint_names=("base", "tip"), kinematic_chain=((0, 1),),
                    raw_offsets=np.array([[0.0, 0, 0], [1, 0, 0]]), bone_lengths=np.array([0.0, 1.0]),
                    feet_left=(0, 1), feet_right=(0, 1), face_joints=(0, 1, 0, 1), leg_bones=(0, 1),
                    contact_threshold=0.0, fps=20.0, unit=1.0, mirror_pairs=(), min_frames=1)


def test_two_joint_chain_known_answer(tmp_path: Path) -> None:
    """Up: Rz(90) turns +x onto +y; towards -z: Ry(90); the file is exactly this."""
    base = np.array([1.0, 2.0, 3.0])
    joints = np.array([[base, base + [0, 1, 0]], [base, base + [0, 0, -1]]])
    path = write_bvh(joints, chain_skeleton(), tmp_path / "chain.bvh", fps=20.0)
    assert path.read_text().splitlines() == [
        "HIERARCHY", "ROOT base", "{", "\tOFFSET 0.000000 0.000000 0.000000",
        "\tCHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation",
        "\tJOINT tip", "\t{", "\t\tOFFSET 1.000000 0.000000 0.000000", "\t\tCHANNELS 3 Zrotation Xrotation Yrotation",
        "\t\tEnd Site", "\t\t{", "\t\t\tOFFSET 0.500000 0.000000 0.000000", "\t\t}", "\t}", "}",
        "MOTION", "Frames: 2", "Frame Time: 0.05000000",
        "1.000000 2.000000 3.000000 90.000000 0.000000 0.000000 0.000000 0.000000 0.000000",
        "1.000000 2.000000 3.000000 0.000000 0.000000 90.000000 0.000000 0.000000 0.000000",
    ]
    np.testing.assert_allclose(read_bvh(path).positions, joints, atol=1e-6)


STANDARD = """HIERARCHY
ROOT Hips
{
  OFFSET 5.0 0.0 0.0
  CHANNELS 6 Xposition Yposition Zposition Xrotation Yrotation Zrotation
  JOINT Arm
  {
    OFFSET 1.0 0.0 0.0
    CHANNELS 3 Zrotation Xrotation Yrotation
    End Site
    {
      OFFSET 0.0 2.0 0.0
    }
  }
  JOINT Leg
  {
    OFFSET 0.0 -1.0 0.0
    CHANNELS 3 Zrotation Xrotation Yrotation
    JOINT Foot
    {
      OFFSET 0.0 0.0 1.0
      CHANNELS 3 Xrotation Yrotation Zrotation
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.0333333
0 0 0  0 0 0  0 0 0  0 0 0  0 0 0
1 2 3  90 90 0  0 0 0  90 90 0  0 0 90
"""


def test_reads_standard_bvh_in_xyz_and_zxy_orders(tmp_path: Path) -> None:
    """Frame 1: the root's Rx(90) Ry(90) (XYZ order) turns +x onto +y, +y onto +z and +z onto +x; Leg's
    Rz(90) Rx(90) (ZXY order) turns Foot's +z onto +x (the other order would give -y)."""
    path = tmp_path / "standard.bvh"
    path.write_text(STANDARD)
    motion = read_bvh(path)
    assert motion.names == ["Hips", "Arm", "Leg", "Foot"] and motion.parents == [-1, 0, 0, 2]
    assert motion.channels[0][:3] == ("Xposition", "Yposition", "Zposition") and motion.frame_time == 0.0333333
    np.testing.assert_allclose(motion.positions[0], [[0, 0, 0], [1, 0, 0], [0, -1, 0], [0, -1, 1]], atol=1e-12)
    # the root's offset is replaced by its position channels; Foot's own rotation moves nothing below it
    np.testing.assert_allclose(motion.positions[1], [[1, 2, 3], [1, 3, 3], [1, 2, 2], [1, 3, 2]], atol=1e-12)


def test_written_header_parses_with_the_skeleton_hierarchy(tmp_path: Path) -> None:
    joints = np.load(FIXTURE)[:10]
    motion = read_bvh(write_bvh(joints, HUMANML3D, tmp_path / "m.bvh", HUMANML3D.fps))
    assert motion.positions.shape == (10, len(motion.names), 3) and motion.frame_time == 0.05
    assert set(HUMANML3D.joint_names) <= set(motion.names)
    helpers = [name for name in motion.names if name not in HUMANML3D.joint_names]
    assert helpers == ["pelvis_to_left_hip", "pelvis_to_right_hip", "pelvis_to_spine1", "spine3_to_neck",
                       "spine3_to_left_collar", "spine3_to_right_collar"]
    offsets = HUMANML3D.offsets()
    for j, name in enumerate(HUMANML3D.joint_names[1:], 1):
        index = motion.names.index(name)
        parent = motion.names[motion.parents[index]]
        if parent in helpers:  # a zero-offset helper at the skeleton parent
            assert not motion.offsets[motion.names.index(parent)].any()
            parent = motion.names[motion.parents[motion.names.index(parent)]]
        assert parent == HUMANML3D.joint_names[HUMANML3D.parents[j]]
        np.testing.assert_allclose(motion.offsets[index], offsets[j], atol=1e-6)
    assert motion.channels[0][:3] == ("Xposition", "Yposition", "Zposition")
    orders = ["".join(name[0] for name in own[-3:]) for own in motion.channels]
    assert all(order in ROTATION_ORDERS and own[-3:] == tuple(f"{a}rotation" for a in order)
               for order, own in zip(orders, motion.channels, strict=True))
    assert len(motion.channels[0]) == 6 and all(len(own) == 3 for own in motion.channels[1:])


def test_a_joint_near_gimbal_lock_takes_the_order_farthest_from_it() -> None:
    """Z X Y's middle angle swept through 90 degrees: X Z Y keeps its middle angle within 10 degrees (Z Y X
    within 10 too, X Y Z and Y Z X within 31, Y X Z at 88); a joint that stays far from lock keeps Z X Y."""
    x = np.linspace(80.0, 100.0, 40)
    lock = Rotation.from_euler("ZXY", np.stack([30 + x, x, -20 + x], -1), degrees=True).as_matrix()
    mild = Rotation.from_euler("ZXY", np.stack([x / 4, -x / 4, x / 8], -1), degrees=True).as_matrix()
    assert rotation_orders(np.stack([lock, mild], axis=1)) == ["XZY", "ZXY"]


def test_rest_pose_writes_every_joint_in_zxy(tmp_path: Path) -> None:
    """No joint is near gimbal lock in the rest pose: every joint keeps the common Z X Y order."""
    rest = np.repeat(HUMANML3D.rest_directions()[None], 3, axis=0)  # every bone along its rest direction
    motion = read_bvh(write_bvh(rest, HUMANML3D, tmp_path / "rest.bvh", HUMANML3D.fps))
    assert all(own[-3:] == ("Zrotation", "Xrotation", "Yrotation") for own in motion.channels)


@pytest.mark.parametrize(("text", "message"), [
    (STANDARD.replace("Frames: 2", "Frames: 3"), r"standard\.bvh:30: unexpected end of file"),
    (STANDARD.replace("CHANNELS 3 Zrotation Xrotation Yrotation\n    End", "CHANNELS 3 Zrotation Xrot Yrotation\n"
                      "    End"), r"standard\.bvh:9: unknown channel 'Xrot' of joint 'Arm'"),
    (STANDARD.replace("OFFSET 1.0 0.0 0.0", "OFFSET 1.0 zero 0.0"), r"standard\.bvh:8: expected an OFFSET value"),
    (STANDARD + "7\n", r"standard\.bvh:31: more values than 2 frames of 15 channels"),
])
def test_bad_files_name_the_line(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "standard.bvh"
    path.write_text(text)
    with pytest.raises(ValueError, match=message):
        read_bvh(path)


def test_write_refuses_joints_of_another_skeleton(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"expected joints \(T, 22, 3\), got \(5, 21, 3\)"):
        write_bvh(np.zeros((5, 21, 3)), HUMANML3D, tmp_path / "x.bvh", 20.0)
    assert not (tmp_path / "x.bvh").exists()


def test_angle_curves_are_continuous_and_every_frame_exact(tmp_path: Path) -> None:
    """A spin of two turns and a rotation swung through gimbal lock (x = 90 in Z X Y) write angle curves
    without wraps or flips between the two equivalent triples, and the positions still round-trip."""
    joints = np.load(FIXTURE)
    t = np.linspace(0.0, 4.0 * np.pi, len(joints))
    spin = Rotation.from_euler("y", t[:, None]).as_matrix()  # (T, 3, 3): two turns about the vertical
    root = joints[:, :1]
    spun = np.einsum("tij,tkj->tki", spin, joints - root) + root
    path = write_bvh(spun, HUMANML3D, tmp_path / "spin.bvh", HUMANML3D.fps)
    values = np.loadtxt(path.read_text().split("Frame Time:")[1].splitlines()[1:])
    channels = read_bvh(path).channels
    angles = values[:, 3:].reshape(len(values), -1, 3)  # (T, N, 3): every joint's three rotation channels
    orders = ["".join(name[0] for name in own[-3:]) for own in channels]
    local = np.stack([Rotation.from_euler(order, angles[:, n], degrees=True).as_matrix()
                      for n, order in enumerate(orders)], axis=1)
    turned = np.degrees(Rotation.from_matrix((np.swapaxes(local[:-1], -1, -2) @ local[1:]).reshape(-1, 3, 3))
                        .magnitude()).reshape(len(values) - 1, -1)
    # no wrap, no flip between the two triples, and no gimbal-lock trade (with Z X Y on every joint the
    # curves moved up to 147 degrees more than 3 x the rotation between two frames): each joint's three
    # curves move about as much as the joint turns
    assert (np.abs(np.diff(angles, axis=0)).sum(-1) - 3 * turned).max() < 15.0
    assert np.abs(values[:, 5]).max() > 360.0  # the pelvis's yaw keeps counting past a turn (it stays Z X Y)
    assert orders[0] == "ZXY"
    assert np.linalg.norm(read_bvh(path).joints(HUMANML3D.joint_names) - spun, axis=-1).max() < MM
    # near gimbal lock the solver's triple flips; the chosen curve does not, and the rotations are the same
    x = np.linspace(80.0, 100.0, 40)  # through x = 90, not on it (there z and y are not unique)
    raw = Rotation.from_euler("ZXY", np.stack([30 + x, x, -20 + x], -1), degrees=True).as_euler("ZXY", degrees=True)
    smooth = continuous_euler(raw[:, None])[:, 0]
    assert np.abs(np.diff(raw, axis=0)).max() > 90.0 and np.abs(np.diff(smooth, axis=0)).max() < 10.0
    np.testing.assert_allclose(Rotation.from_euler("ZXY", smooth, degrees=True).as_matrix(),
                               Rotation.from_euler("ZXY", raw, degrees=True).as_matrix(), atol=1e-9)
