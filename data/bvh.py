"""BVH motion files (Biovision Hierarchy), the format animation tools import: writer and minimal reader.

Writing. :func:`write_bvh` turns global joint positions (T, J, 3) into a BVH of a dataset
skeleton (:mod:`data.skeleton`): the hierarchy follows ``skeleton.parents``, each joint's OFFSET
is its rest bone vector ``raw_offsets[j] * bone_lengths[j]`` (the rest pose is the skeleton's, not a
T-pose: for HumanML3D facing +z with y up, the legs and arms hanging straight down, hips and collars
sideways, the neck-to-head bone and the feet pointing forward), the root has position channels (its
offset is zero, so they are the pelvis position) and every joint three rotation channels in degrees,
continuous in time (:func:`continuous_euler`): ``Zrotation Xrotation Yrotation``, or for a joint that
order would put near gimbal lock in the clip, the order that keeps it farthest from it
(:func:`rotation_orders`). Units are the joints' (metres for HumanML3D, millimetres for KIT-ML).

Rotations are solved from the positions. In BVH a joint's rotation turns the offsets of its
children, so:

* a joint with one child gets the *swing* that turns the child's rest direction onto its
  direction in the frame, taken relative to the parent's rotation (the smallest rotation of the
  bone with respect to its parent). The child then lands exactly on its position when the motion
  has the skeleton's bone lengths, and along the right direction otherwise.
* a joint with several children (HumanML3D: the pelvis and spine3) gets the rotation that best
  fits all its children's rest directions onto theirs (Wahba's problem, solved by SVD). One
  rotation cannot place several children exactly when their angles differ from the rest pose
  (HumanML3D's pelvis-hip-spine angles are not those of ``raw_offsets``), so each child hangs
  from a helper joint ``<parent>_to_<child>`` with a zero offset at the parent, whose rotation is
  the child's swing relative to the fit (CMU's BVH files use such joints: ``LHipJoint``). Every
  skeleton joint is then placed exactly.
* a leaf joint keeps its parent's rotation (zero local angles); its End Site continues its bone
  by half its length, so that importers draw a visible tip.

Twist, the rotation of a bone about its own axis, is not determined by positions. The choice
here: a single-child bone takes no twist relative to its parent (the swing is the shortest arc
in the parent's frame), and a multi-child joint's twist is set by its children's fit, so twist
comes from the body's own geometry (the hips and the shoulders) and is passed down the chains.
When a bone points exactly opposite to its rest direction in its parent's frame (an arm raised
straight up from a hanging rest, in the arm's chain) the swing's axis is arbitrary; positions
stay exact, the twist may jump.

Reading. :func:`read_bvh` parses the HIERARCHY (ROOT/JOINT/End Site, OFFSET, CHANNELS in any order
of ``X/Y/Zposition`` and ``X/Y/Zrotation``) and the MOTION block and computes global joint
positions by forward kinematics: a joint's translation is its OFFSET, with the axes that have
position channels replaced by their values; its rotation is the product of its rotation channels'
elementary rotations in the listed order (``Zrotation Xrotation Yrotation`` is ``Rz Rx Ry``).
End Sites are not joints of the result.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from data.rotations import normalize, qbetween, quat_to_matrix
from data.skeleton import Skeleton

#: Rotation orders a joint's channels may take: the first (the most common BVH order) unless
#: :func:`rotation_orders` finds it near gimbal lock for that joint.
ROTATION_ORDERS = ("ZXY", "XYZ", "XZY", "YXZ", "YZX", "ZYX")
#: The first order is kept while its middle angle stays within this many degrees of zero.
KEEP_FIRST_ORDER_DEG = 60.0
POSITION_CHANNELS = ("Xposition", "Yposition", "Zposition")
#: Length of an End Site relative to its leaf joint's bone.
END_SITE_FRACTION = 0.5
AXES = {"X": 0, "Y": 1, "Z": 2}


@dataclass(frozen=True)
class _Node:
    """One BVH joint of a written skeleton.

    ``joint`` is the skeleton joint at the node's position; ``aims`` the skeleton joints whose
    bones (``joint -> aim``) its rotation turns onto their observed directions.
    """

    name: str
    parent: int
    offset: np.ndarray
    joint: int
    aims: tuple[int, ...]
    end_site: np.ndarray | None


def bvh_nodes(skeleton: Skeleton) -> list[_Node]:
    """The written hierarchy in file (depth-first) order, helper joints included (module docstring)."""
    children = [[c for c in range(skeleton.joints_num) if skeleton.parents[c] == j] for j in range(skeleton.joints_num)]
    offsets = skeleton.offsets()
    nodes: list[_Node] = []

    def add(joint: int, parent: int) -> None:
        kids = children[joint]
        end_site = None if kids else offsets[joint] * END_SITE_FRACTION
        nodes.append(_Node(skeleton.joint_names[joint], parent, offsets[joint] if parent >= 0 else np.zeros(3),
                           joint, tuple(kids), end_site))
        index = len(nodes) - 1
        if len(kids) == 1:
            add(kids[0], index)
            return
        for kid in kids:
            nodes.append(_Node(f"{skeleton.joint_names[joint]}_to_{skeleton.joint_names[kid]}", index, np.zeros(3),
                               joint, (kid,), None))
            add(kid, len(nodes) - 1)

    add(0, -1)
    return nodes


def _swing(parent: np.ndarray, rest: np.ndarray, bone: np.ndarray) -> np.ndarray:
    """(T, 3, 3) global rotations: ``parent`` then the shortest arc from ``rest`` to ``bone`` in its frame."""
    local_dir = np.einsum("tji,tj->ti", parent, bone)  # parent^T @ bone
    length = np.linalg.norm(local_dir, axis=-1, keepdims=True)
    local_dir = np.where(length > 1e-9, local_dir, rest)  # a zero-length bone keeps its rest direction
    return parent @ quat_to_matrix(qbetween(np.broadcast_to(rest, local_dir.shape), local_dir))


def _fit(rest: np.ndarray, bones: np.ndarray) -> np.ndarray:
    """(T, 3, 3) rotations R minimising sum_k |R rest_k - n(bone_k)|^2 (Kabsch): rest (K, 3), bones (T, K, 3)."""
    observed = normalize(bones + 1e-12)
    u, _, vt = np.linalg.svd(np.einsum("tki,kj->tij", observed, rest))
    flip = np.ones((len(u), 3))
    flip[:, 2] = np.sign(np.linalg.det(u @ vt))  # a rotation, not a reflection
    return (u * flip[:, None, :]) @ vt


def solve_rotations(joints: np.ndarray, skeleton: Skeleton, nodes: Sequence[_Node]) -> np.ndarray:
    """(T, N, 3, 3) local rotation matrices of ``nodes`` (their parents' frames) for positions (T, J, 3)."""
    joints = np.asarray(joints, np.float64)
    frames = len(joints)
    identity = np.broadcast_to(np.eye(3), (frames, 3, 3))
    global_rot: list[np.ndarray] = []
    local = np.empty((frames, len(nodes), 3, 3))
    for n, node in enumerate(nodes):
        parent = identity if node.parent < 0 else global_rot[node.parent]
        bones = joints[:, list(node.aims)] - joints[:, node.joint, None]
        if not node.aims:
            rot = parent
        elif len(node.aims) == 1:
            rot = _swing(parent, skeleton.raw_offsets[node.aims[0]], bones[:, 0])
        else:
            rot = _fit(skeleton.raw_offsets[list(node.aims)], bones)
        global_rot.append(rot)
        local[:, n] = np.swapaxes(parent, -1, -2) @ rot
    return local


def _euler(local: np.ndarray, order: str) -> np.ndarray:
    """(T, 3) intrinsic Euler angles (degrees) of rotation matrices (T, 3, 3) in ``order``, e.g. ``"ZXY"``."""
    with warnings.catch_warnings():  # gimbal lock: scipy picks one of the equivalent angle triples
        warnings.simplefilter("ignore", UserWarning)
        return Rotation.from_matrix(local).as_euler(order, degrees=True)


def euler_curves(local: np.ndarray, orders: Sequence[str]) -> np.ndarray:
    """(T, N, 3) the BVH's angle curves (degrees): local rotations (T, N, 3, 3), node ``n`` in ``orders[n]``,
    made continuous (:func:`continuous_euler`)."""
    return continuous_euler(np.stack([_euler(local[:, n], order) for n, order in enumerate(orders)], axis=1))


def rotation_orders(local: np.ndarray) -> list[str]:
    """Each node's rotation channel order for its local rotations ``local`` (T, N, 3, 3).

    The middle angle of a Tait-Bryan order is in gimbal lock at +-90 degrees: there the other two
    angles are not unique, and near it they trade large opposite changes for a small rotation, curves
    an animator cannot edit. A node keeps ``ZXY`` (:data:`ROTATION_ORDERS`' first) while its middle
    angle stays within :data:`KEEP_FIRST_ORDER_DEG` of zero in every frame; otherwise it takes the
    order whose largest middle angle over the clip is smallest (the first of those in a tie). BVH
    declares channels per joint, so each joint may have its own order.
    """
    orders = []
    for n in range(local.shape[1]):
        worst = [np.abs(_euler(local[:, n], order)[:, 1]).max() for order in ROTATION_ORDERS]
        keep = worst[0] <= KEEP_FIRST_ORDER_DEG
        orders.append(ROTATION_ORDERS[0] if keep else ROTATION_ORDERS[int(np.argmin(worst))])
    return orders


def _hierarchy_lines(nodes: Sequence[_Node], orders: Sequence[str]) -> list[str]:
    """The HIERARCHY section, nested by indentation; ``orders`` holds each node's rotation channel order."""
    lines = ["HIERARCHY"]
    depth = [0] * len(nodes)
    open_blocks: list[int] = []
    for n, node in enumerate(nodes):
        while open_blocks and open_blocks[-1] != node.parent:
            open_blocks.pop()
            lines.append("\t" * len(open_blocks) + "}")
        depth[n] = len(open_blocks)
        pad = "\t" * depth[n]
        channels = (POSITION_CHANNELS if node.parent < 0 else ()) + tuple(f"{axis}rotation" for axis in orders[n])
        lines += [f"{pad}{'ROOT' if node.parent < 0 else 'JOINT'} {node.name}", pad + "{",
                  f"{pad}\tOFFSET {_numbers(node.offset)}", f"{pad}\tCHANNELS {len(channels)} {' '.join(channels)}"]
        if node.end_site is not None:
            lines += [f"{pad}\tEnd Site", f"{pad}\t{{", f"{pad}\t\tOFFSET {_numbers(node.end_site)}", f"{pad}\t}}"]
        open_blocks.append(n)
    while open_blocks:
        open_blocks.pop()
        lines.append("\t" * len(open_blocks) + "}")
    return lines


def _numbers(values: np.ndarray) -> str:
    return " ".join(f"{v:.6f}" for v in np.asarray(values, np.float64).ravel() + 0.0)  # + 0.0: no "-0.000000"


def continuous_euler(angles: np.ndarray) -> np.ndarray:
    """(T, N, 3) intrinsic Tait-Bryan angles (degrees, any order of three distinct axes, such as ``Z X Y``)
    made continuous in time, every frame's rotation kept.

    A rotation has two angle triples, ``(a, b, c)`` and ``(a + 180, 180 - b, c + 180)`` (in any such
    order ``Ra(180) Rb(180 - b) Rc(180) = Rb(b)``), and each angle may move by whole turns. Frame by
    frame, each angle of both triples is moved by whole turns to the nearest of the previous frame's,
    and the triple nearer to it (summed absolute change) is kept. Without this a spin wraps from +180
    to -180 degrees, and near gimbal lock (b near +-90) the per-frame solution jumps between the two
    triples, so an animation tool that interpolates or retimes the curves would twist the joint through
    a full turn. The angles must be finite (a NaN would carry to every later frame; :func:`write_bvh`
    refuses non-finite joints before solving).
    """
    out = np.array(angles, np.float64)
    for t in range(1, len(out)):
        a, b, c = np.moveaxis(out[t], -1, 0)
        triples = np.stack([out[t], np.stack([a + 180.0, 180.0 - b, c + 180.0], axis=-1)])  # (2, N, 3)
        triples += 360.0 * np.round((out[t - 1] - triples) / 360.0)
        other = np.abs(triples - out[t - 1]).sum(-1)  # (2, N)
        out[t] = np.where((other[1] < other[0])[:, None], triples[1], triples[0])
    return out


def write_bvh(joints: np.ndarray, skeleton: Skeleton, path: Path | str, fps: float) -> Path:
    """Write global joint positions (T, J, 3) as a BVH of ``skeleton`` at ``fps``; returns the path.

    Each skeleton joint is placed exactly when the motion has the skeleton's bone lengths (else
    along each bone's observed direction, at the skeleton's length); see the module docstring.
    """
    joints = np.asarray(joints, np.float64)
    if joints.ndim != 3 or joints.shape[1:] != (skeleton.joints_num, 3) or len(joints) == 0:
        raise ValueError(f"{path}: expected joints (T, {skeleton.joints_num}, 3), got {joints.shape}")
    if not np.all(np.isfinite(joints)):
        raise ValueError(f"{path}: the joint positions are not all finite")
    nodes = bvh_nodes(skeleton)
    local = solve_rotations(joints, skeleton, nodes)
    orders = rotation_orders(local)
    angles = euler_curves(local, orders)
    values = np.concatenate([joints[:, 0], angles.reshape(len(joints), -1)], axis=1)
    lines = _hierarchy_lines(nodes, orders)
    lines += ["MOTION", f"Frames: {len(joints)}", f"Frame Time: {1.0 / fps:.8f}"]
    lines += [_numbers(row) for row in values]
    path = Path(path)
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


# --------------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class BVHMotion:
    """A parsed BVH file.

    Attributes:
        names: joint names in file order (End Sites excluded).
        parents: index of each joint's parent (-1 for the root).
        offsets: (N, 3) OFFSETs.
        channels: each joint's channel names.
        frame_time: seconds per frame.
        positions: (T, N, 3) global joint positions.
    """

    names: list[str]
    parents: list[int]
    offsets: np.ndarray
    channels: list[tuple[str, ...]]
    frame_time: float
    positions: np.ndarray

    def joints(self, names: Sequence[str]) -> np.ndarray:
        """(T, len(names), 3) positions of the named joints, in that order."""
        missing = [name for name in names if name not in self.names]
        if missing:
            raise KeyError(f"no joint {missing[0]!r} in the BVH file")
        return self.positions[:, [self.names.index(name) for name in names]]


class _Tokens:
    """Whitespace-separated tokens of a file with their line numbers, for error messages."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.items = [(token, number) for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
                      for token in line.split()]
        self.at = 0

    def error(self, message: str) -> ValueError:
        line = self.items[min(self.at, len(self.items) - 1)][1] if self.items else 1
        return ValueError(f"{self.path}:{line}: {message}")

    def next(self, what: str) -> str:
        if self.at >= len(self.items):
            raise self.error(f"unexpected end of file, expected {what}")
        token = self.items[self.at][0]
        self.at += 1
        return token

    def expect(self, *expected: str) -> None:
        for word in expected:
            token = self.next(repr(word))
            if token != word:
                self.at -= 1
                raise self.error(f"expected {word!r}, got {token!r}")

    def number(self, what: str, kind: type = float) -> float:
        token = self.next(what)
        try:
            return kind(token)
        except ValueError:
            self.at -= 1
            raise self.error(f"expected {what}, got {token!r}") from None


def _parse_joint(tokens: _Tokens, parent: int, names: list[str], parents: list[int], offsets: list[np.ndarray],
                 channels: list[tuple[str, ...]]) -> None:
    """One ROOT/JOINT block after its keyword, recursively."""
    names.append(tokens.next("a joint name"))
    index = len(names) - 1
    parents.append(parent)
    tokens.expect("{", "OFFSET")
    offsets.append(np.array([tokens.number("an OFFSET value") for _ in range(3)]))
    tokens.expect("CHANNELS")
    count = int(tokens.number("the channel count", int))
    own = tuple(tokens.next("a channel name") for _ in range(count))
    for name in own:
        if len(name) != 9 or name[0] not in AXES or name[1:] not in ("position", "rotation"):
            tokens.at -= 1
            raise tokens.error(f"unknown channel {name!r} of joint {names[index]!r}")
    channels.append(own)
    while True:
        keyword = tokens.next("JOINT, End Site or '}'")
        if keyword == "}":
            return
        if keyword == "JOINT":
            _parse_joint(tokens, index, names, parents, offsets, channels)
        elif keyword == "End":
            tokens.expect("Site", "{", "OFFSET")
            for _ in range(3):
                tokens.number("an OFFSET value")
            tokens.expect("}")
        else:
            tokens.at -= 1
            raise tokens.error(f"expected JOINT, End Site or '}}', got {keyword!r}")


def _axis_rotation(axis: int, degrees: np.ndarray) -> np.ndarray:
    """(T, 3, 3) elementary rotations about x, y or z."""
    angle = np.radians(degrees)
    c, s = np.cos(angle), np.sin(angle)
    m = np.zeros((len(angle), 3, 3))
    i, j = (axis + 1) % 3, (axis + 2) % 3
    m[:, axis, axis] = 1.0
    m[:, i, i], m[:, j, j] = c, c
    m[:, j, i], m[:, i, j] = s, -s
    return m


def forward_kinematics(offsets: np.ndarray, parents: Sequence[int], channels: Sequence[tuple[str, ...]],
                       values: np.ndarray) -> np.ndarray:
    """(T, N, 3) global positions from per-frame channel ``values`` (T, sum of channel counts)."""
    frames = len(values)
    positions = np.zeros((frames, len(parents), 3))
    rotations = np.zeros((frames, len(parents), 3, 3))
    column = 0
    for j, (parent, own) in enumerate(zip(parents, channels, strict=True)):
        translation = np.tile(offsets[j], (frames, 1))
        rotation = np.broadcast_to(np.eye(3), (frames, 3, 3))
        for name in own:
            axis = AXES[name[0]]
            if name.endswith("position"):
                translation[:, axis] = values[:, column]
            else:
                rotation = rotation @ _axis_rotation(axis, values[:, column])
            column += 1
        if parent < 0:
            positions[:, j], rotations[:, j] = translation, rotation
        else:
            positions[:, j] = positions[:, parent] + np.einsum("tij,tj->ti", rotations[:, parent], translation)
            rotations[:, j] = rotations[:, parent] @ rotation
    return positions


def read_bvh(path: Path | str) -> BVHMotion:
    """Parse a BVH file and compute its global joint positions (module docstring); ValueError naming the
    file and line of the first problem."""
    tokens = _Tokens(Path(path))
    names: list[str] = []
    parents: list[int] = []
    offsets: list[np.ndarray] = []
    channels: list[tuple[str, ...]] = []
    tokens.expect("HIERARCHY", "ROOT")
    _parse_joint(tokens, -1, names, parents, offsets, channels)
    tokens.expect("MOTION", "Frames:")
    frames = int(tokens.number("the frame count", int))
    tokens.expect("Frame", "Time:")
    frame_time = tokens.number("the frame time")
    width = sum(len(own) for own in channels)
    values = np.array([tokens.number(f"{frames} frames of {width} channel values") for _ in range(frames * width)])
    if tokens.at != len(tokens.items):
        raise tokens.error(f"more values than {frames} frames of {width} channels")
    positions = forward_kinematics(np.array(offsets), parents, channels, values.reshape(frames, width))
    return BVHMotion(names, parents, np.array(offsets), channels, frame_time, positions)
