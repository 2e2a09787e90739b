"""Skeleton definitions for HumanML3D (22 SMPL joints) and KIT-ML (21 joints).

Conventions (HumanML3D's ``paramUtil.py``): y is up, the character faces +z and its left side
is +x in the rest pose. ``raw_offsets[j]`` is the unit rest direction of the bone that ends at
joint ``j`` (root: zero). A bone vector is ``raw_offsets[j] * length[j]`` -- the convention of
HumanML3D's ``Skeleton.get_offsets_joints``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Skeleton:
    """Static description of a dataset's skeleton and its feature-extraction constants.

    Attributes:
        name: dataset name (``"humanml3d"`` or ``"kit"``).
        joint_names: one name per joint, index = joint id.
        kinematic_chain: chains from the root; the parent of a joint is the element before it.
        raw_offsets: (J, 3) unit rest direction of each joint's bone.
        bone_lengths: (J,) default target bone lengths (root 0), in ``unit`` metres.
        feet_left / feet_right: (ankle, toe) joint ids of each foot (KIT-ML: metatarsal, toe, with
            HumanML3D's side labels, the opposite of the MMM joint names).
        face_joints: (r_hip, l_hip, r_shoulder, l_shoulder) used for the facing direction.
        leg_bones: the two joints whose bone lengths define leg length (retarget scale).
        contact_threshold: squared per-frame foot displacement below which a foot is in contact.
        fps: frames per second of the feature files.
        unit: metres per dataset unit (KIT-ML stores millimetres).
        mirror_pairs: left/right joint pairs swapped by mirroring.
        min_frames: the standard loader's minimum clip length in feature frames.
    """

    name: str
    joint_names: tuple[str, ...]
    kinematic_chain: tuple[tuple[int, ...], ...]
    raw_offsets: np.ndarray
    bone_lengths: np.ndarray
    feet_left: tuple[int, int]
    feet_right: tuple[int, int]
    face_joints: tuple[int, int, int, int]
    leg_bones: tuple[int, int]
    contact_threshold: float
    fps: float
    unit: float
    mirror_pairs: tuple[tuple[int, int], ...]
    min_frames: int
    parents: tuple[int, ...] = field(init=False)

    def __post_init__(self) -> None:
        parents = [-1] * len(self.joint_names)
        for chain in self.kinematic_chain:
            for a, b in zip(chain[:-1], chain[1:], strict=True):
                parents[b] = a
        object.__setattr__(self, "parents", tuple(parents))
        assert self.raw_offsets.shape == (self.joints_num, 3)
        assert self.bone_lengths.shape == (self.joints_num,)

    @property
    def joints_num(self) -> int:
        return len(self.joint_names)

    @property
    def feature_dim(self) -> int:
        """Feature vector size 12J - 1 (263 for HumanML3D, 251 for KIT-ML)."""
        return 12 * self.joints_num - 1

    @property
    def feet(self) -> tuple[int, int, int, int]:
        """Contact joints in feature order: left ankle, left toe, right ankle, right toe."""
        return (*self.feet_left, *self.feet_right)

    @property
    def front(self) -> float:
        """+1.0 if a motion's body faces +z in the features' canonical frame, -1.0 if it faces -z.

        Feature extraction turns frame 0's forward as the face joints name it, ``y x ((r_hip - l_hip) +
        (r_shoulder - l_shoulder))``, onto +z. The body's real forward is where the rest pose's toes point
        (+z); where the face joints' side labels name the other side (HumanML3D's KIT-ML code, see the KIT
        skeleton below), the named forward is the body's back, and canonical motions face -z. The
        presentation follows it: drawings look at the body's front, and ``generate``'s paths lead ahead.
        """
        rest = self.rest_directions()
        r_hip, l_hip, r_sho, l_sho = self.face_joints
        named_forward = np.cross([0.0, 1.0, 0.0], (rest[r_hip] - rest[l_hip]) + (rest[r_sho] - rest[l_sho]))
        toes = sum(rest[toe] - rest[ankle] for ankle, toe in (self.feet_left, self.feet_right))
        return 1.0 if float(named_forward @ toes) > 0 else -1.0

    def rest_directions(self) -> np.ndarray:
        """(J, 3) joint positions of the rest pose built from the unit ``raw_offsets`` (every bone 1 long): the
        body faces +z (its toes), its left at +x. For sides and directions, not for sizes."""
        rest = np.zeros((self.joints_num, 3))
        for chain in self.kinematic_chain:  # each chain starts at the root or on an earlier chain
            for parent, joint in zip(chain[:-1], chain[1:], strict=True):
                rest[joint] = rest[parent] + self.raw_offsets[joint]
        return rest

    def offsets(self, bone_lengths: np.ndarray | None = None) -> np.ndarray:
        """(J, 3) bone vectors ``raw_offsets * lengths``; default: the target skeleton."""
        lengths = self.bone_lengths if bone_lengths is None else np.asarray(bone_lengths)
        return (self.raw_offsets * lengths[:, None]).astype(np.float64)

    def bone_lengths_of(self, joints: np.ndarray) -> np.ndarray:
        """(..., J) bone lengths of global joint positions (..., J, 3); root length 0."""
        joints = np.asarray(joints, dtype=np.float64)
        parents = np.array(self.parents)
        lengths = np.linalg.norm(joints - joints[..., np.maximum(parents, 0), :], axis=-1)
        lengths[..., 0] = 0.0
        return lengths


_HML_NAMES = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar",
    "right_collar", "head", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
    "left_wrist", "right_wrist",
)  # fmt: skip

_HML_RAW_OFFSETS = np.array(
    [
        [0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, -1, 0], [0, 1, 0],
        [0, -1, 0], [0, -1, 0], [0, 1, 0], [0, 0, 1], [0, 0, 1], [0, 1, 0], [1, 0, 0],
        [-1, 0, 0], [0, 0, 1], [0, -1, 0], [0, -1, 0], [0, -1, 0], [0, -1, 0], [0, -1, 0],
        [0, -1, 0],
    ],
    dtype=np.float64,
)  # fmt: skip

# Bone lengths (m) of HumanML3D's target skeleton. Every clip in HumanML3D's ``new_joints`` is
# retargeted to the bones of clip 000021; these were measured on frame 0 of ``new_joints/012314``
# (they are constant over its frames to 5e-7 m).
_HML_BONE_LENGTHS = np.array(
    [
        0.0, 0.103074, 0.109883, 0.131568, 0.393623, 0.390188, 0.143190, 0.432433,
        0.425643, 0.057365, 0.143382, 0.149419, 0.219360, 0.137487, 0.143383, 0.103039,
        0.131614, 0.122984, 0.256840, 0.263092, 0.266012, 0.269876,
    ],
)  # fmt: skip

HUMANML3D = Skeleton(
    name="humanml3d",
    joint_names=_HML_NAMES,
    kinematic_chain=((0, 2, 5, 8, 11), (0, 1, 4, 7, 10), (0, 3, 6, 9, 12, 15),
                     (9, 14, 17, 19, 21), (9, 13, 16, 18, 20)),
    raw_offsets=_HML_RAW_OFFSETS,
    bone_lengths=_HML_BONE_LENGTHS,
    feet_left=(7, 10),
    feet_right=(8, 11),
    face_joints=(2, 1, 17, 16),
    leg_bones=(5, 8),
    contact_threshold=0.002,
    fps=20.0,
    unit=1.0,
    mirror_pairs=((1, 2), (4, 5), (7, 8), (10, 11), (13, 14), (16, 17), (18, 19), (20, 21)),
    min_frames=40,
)  # fmt: skip

# The MMM model's joint order (KIT-ML; TEMOS and MotionGPT name it so): 5-7 and 11-15 are the left arm and
# leg, at +x in the rest offsets, whose toes point +z. HumanML3D's KIT code labels its face joints 11, 16,
# 5, 8 "r_hip, l_hip, sdr_r, sdr_l" and its feet 19, 20 "fid_l": the opposite sides. face_joints and
# feet_left/feet_right below keep HumanML3D's indices (the features' facing and contact channels are
# computed with them), so for KIT they name the other side than the joint names do.
_KIT_NAMES = (
    "root", "bp", "bt", "bln", "bun", "l_shoulder", "l_elbow", "l_wrist", "r_shoulder",
    "r_elbow", "r_wrist", "l_hip", "l_knee", "l_ankle", "l_mt", "l_toe", "r_hip", "r_knee",
    "r_ankle", "r_mt", "r_toe",
)  # fmt: skip

_KIT_RAW_OFFSETS = np.array(
    [
        [0, 0, 0], [0, 1, 0], [0, 1, 0], [0, 1, 0], [0, 1, 0], [1, 0, 0], [0, -1, 0],
        [0, -1, 0], [-1, 0, 0], [0, -1, 0], [0, -1, 0], [1, 0, 0], [0, -1, 0], [0, -1, 0],
        [0, 0, 1], [0, 0, 1], [-1, 0, 0], [0, -1, 0], [0, -1, 0], [0, 0, 1], [0, 0, 1],
    ],
    dtype=np.float64,
)  # fmt: skip

# KIT-ML's reference target clip (03950_gt) is not shipped with motionforge. These are adult
# MMM-model proportions in millimetres; pass ``target_offsets`` measured on your own KIT copy
# to reproduce its ``new_joint_vecs`` exactly.
_KIT_BONE_LENGTHS = np.array(
    [
        0.0, 110.0, 120.0, 190.0, 150.0, 180.0, 280.0, 250.0, 180.0, 280.0, 250.0,
        100.0, 420.0, 410.0, 110.0, 50.0, 100.0, 420.0, 410.0, 110.0, 50.0,
    ],
)  # fmt: skip

KIT = Skeleton(
    name="kit",
    joint_names=_KIT_NAMES,
    kinematic_chain=((0, 11, 12, 13, 14, 15), (0, 16, 17, 18, 19, 20), (0, 1, 2, 3, 4),
                     (3, 5, 6, 7), (3, 8, 9, 10)),
    raw_offsets=_KIT_RAW_OFFSETS,
    bone_lengths=_KIT_BONE_LENGTHS,
    feet_left=(19, 20),
    feet_right=(14, 15),
    face_joints=(11, 16, 5, 8),
    leg_bones=(17, 18),
    contact_threshold=0.05,
    fps=12.5,
    unit=0.001,
    mirror_pairs=((5, 8), (6, 9), (7, 10), (11, 16), (12, 17), (13, 18), (14, 19), (15, 20)),
    min_frames=24,
)  # fmt: skip

SKELETONS: dict[str, Skeleton] = {"humanml3d": HUMANML3D, "kit": KIT}


def get_skeleton(name: str) -> Skeleton:
    """Return the skeleton for a dataset name; raises ValueError naming the known ones."""
    try:
        return SKELETONS[name.lower()]
    except KeyError:
        raise ValueError(f"unknown skeleton {name!r}; known: {sorted(SKELETONS)}") from None
