"""HumanML3D motion features (12J - 1 dims) from global joints, their recovery, and Mean/Std.

Feature layout per frame t (reference A.4), D = 12J - 1 (263 HumanML3D, 251 KIT-ML):

    [0]      root yaw velocity: half the yaw change from t to t+1 (rad/frame)
    [1:3]    root XZ velocity, expressed in the facing frame of t+1
    [3]      root height
    ric      joints 1..J-1, root-relative in XZ, rotated into the facing frame of t (3(J-1))
    rot      continuous 6-D local rotations of joints 1..J-1 (6(J-1))
    vel      velocities t -> t+1 of all J joints in the facing frame of t (3J)
    contacts left ankle, left toe, right ankle, right toe (4)

``features_from_joints`` follows HumanML3D's ``process_file`` step by step (reference A.3), with
its known hip-index quirk in the heading used for features; ``recover_from_ric`` inverts the
root and RIC groups (reference A.5).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from data.kinematics import Z_AXIS, facing_forward, forward_kinematics, inverse_kinematics
from data.rotations import Array, normalize, qbetween, qinv, qmul, qrot, quat_to_cont6d
from data.skeleton import Skeleton

HEADING_SMOOTH_SIGMA = 20.0
GROUP_NAMES = ("root_yaw", "root_xz", "root_y", "ric", "rot", "vel", "contacts")


# ---------------------------------------------------------------------------------------------
# Layout


def feature_groups(joints_num: int) -> dict[str, slice]:
    """The 7 feature groups of a J-joint representation, in order, covering [0, 12J - 1)."""
    if int(joints_num) != joints_num or joints_num < 2:
        raise ValueError(f"joints_num must be an integer >= 2, got {joints_num!r}")
    j = int(joints_num)
    sizes = (1, 2, 1, 3 * (j - 1), 6 * (j - 1), 3 * j, 4)
    bounds = np.cumsum((0, *sizes))
    return {name: slice(int(a), int(b)) for name, a, b in zip(GROUP_NAMES, bounds[:-1], bounds[1:], strict=True)}


# ---------------------------------------------------------------------------------------------
# Extraction (reference A.3)


def features_from_joints(
    joints: np.ndarray, skeleton: Skeleton, target_offsets: np.ndarray | None = None
) -> np.ndarray:
    """HumanML3D features of a clip of global joint positions (``process_file``).

    Args:
        joints: (T, J, 3) global joint positions, y up, in the skeleton's unit, T >= 2.
        skeleton: the dataset skeleton (chains, face joints, feet, contact threshold).
        target_offsets: (J, 3) bone vectors of the target skeleton (rest direction * length,
            root row zero); None means ``skeleton.offsets()``.

    Returns:
        (T - 1, 12J - 1) float32 features.

    Raises:
        ValueError: on a wrong shape, T < 2, non-finite values, or a degenerate pose (zero-length
            bones or a facing direction that cannot be determined).
    """
    positions = _check_joints(joints, skeleton)
    target = _check_offsets(skeleton.offsets() if target_offsets is None else target_offsets, skeleton)

    positions = _retarget(positions, skeleton, target)  # step 1
    positions[..., 1] -= positions[..., 1].min()  # step 2: floor
    positions -= positions[0, 0] * np.array([1.0, 0.0, 1.0])  # step 3: frame-0 root to origin
    positions = _face_z(positions, skeleton)  # step 4
    contacts = _foot_contacts(positions, skeleton)  # step 5

    local = inverse_kinematics(positions, skeleton, smooth_sigma=HEADING_SMOOTH_SIGMA, hip_quirk=True)
    r_rot = local[:, 0]  # step 6
    rot6d = quat_to_cont6d(local[:, 1:])  # step 7
    omega, lin_xz = _root_velocities(positions[:, 0], r_rot)  # step 8
    ric = _rifke(positions, r_rot)  # step 9
    local_vel = qrot(r_rot[:-1, None], positions[1:] - positions[:-1])  # step 10

    n = len(positions) - 1  # step 11
    features = np.concatenate(
        [
            omega[:, None],
            lin_xz,
            positions[:-1, 0, 1:2],
            ric[:-1, 1:].reshape(n, -1),
            rot6d[:-1].reshape(n, -1),
            local_vel.reshape(n, -1),
            contacts,
        ],
        axis=-1,
    )
    if not np.isfinite(features).all():
        raise ValueError(
            "feature extraction produced non-finite values: degenerate pose "
            "(zero-length bone, or hips/shoulders giving no horizontal facing direction)"
        )
    return features.astype(np.float32)


def _check_joints(joints: np.ndarray, skeleton: Skeleton) -> np.ndarray:
    """Validate (T, J, 3) finite joints with T >= 2; returns a float64 copy."""
    arr = np.array(joints, dtype=np.float64)
    expected = f"(T, {skeleton.joints_num}, 3) for skeleton {skeleton.name!r}"
    if arr.ndim != 3 or arr.shape[1:] != (skeleton.joints_num, 3):
        raise ValueError(f"joints must have shape {expected}, got {arr.shape}")
    if arr.shape[0] < 2:
        raise ValueError(f"joints need at least 2 frames to make features, got T={arr.shape[0]}")
    if not np.isfinite(arr).all():
        bad = np.unique(np.nonzero(~np.isfinite(arr))[0])
        raise ValueError(f"joints contain NaN or inf (frames {bad[:10].tolist()})")
    return arr


def _check_offsets(offsets: np.ndarray, skeleton: Skeleton) -> np.ndarray:
    """Validate (J, 3) finite target bone vectors; returns float64."""
    arr = np.asarray(offsets, dtype=np.float64)
    if arr.shape != (skeleton.joints_num, 3):
        raise ValueError(f"target_offsets must have shape ({skeleton.joints_num}, 3), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError("target_offsets contain NaN or inf")
    return arr


def _leg_length(offsets: np.ndarray, skeleton: Skeleton) -> float:
    """Leg length as the reference measures it: sum of max |component| of the two leg bones."""
    return float(sum(np.abs(offsets[i]).max() for i in skeleton.leg_bones))


def _retarget(positions: np.ndarray, skeleton: Skeleton, target: np.ndarray) -> np.ndarray:
    """Step 1 (``uniform_skeleton``): (T, J, 3) -> (T, J, 3) with the target's bone lengths.

    Source bones come from frame 0; the root trajectory is scaled by the leg-length ratio; the
    joint rotations come from IK (heading quirk, no smoothing) and FK runs with the target bones.
    """
    source = skeleton.offsets(skeleton.bone_lengths_of(positions[0]))
    src_leg = _leg_length(source, skeleton)
    if src_leg <= 0.0:
        raise ValueError("joints have zero leg length at frame 0; cannot retarget")
    scale = _leg_length(target, skeleton) / src_leg
    local = inverse_kinematics(positions, skeleton, smooth_sigma=None, hip_quirk=True)
    return forward_kinematics(local, positions[:, 0] * scale, target, skeleton)


def _face_z(positions: np.ndarray, skeleton: Skeleton) -> np.ndarray:
    """Step 4: rotate all frames about y so that frame 0's forward as the face joints name it turns onto +z
    (correct hip order): the body faces +z, or -z where the face joints' sides are named the other way round
    (``Skeleton.front``, KIT-ML)."""
    forward = normalize(facing_forward(positions[0], skeleton.face_joints, hip_quirk=False))
    q0 = qbetween(forward, Z_AXIS)
    return qrot(q0, positions)


def _foot_contacts(positions: np.ndarray, skeleton: Skeleton) -> np.ndarray:
    """Step 5: (T, J, 3) -> (T-1, 4) floats, 1 where the squared per-frame foot displacement is
    below ``skeleton.contact_threshold`` (no height test); order left ankle/toe, right ankle/toe."""
    feet = list(skeleton.feet)
    step = positions[1:, feet] - positions[:-1, feet]
    return ((step**2).sum(-1) < skeleton.contact_threshold).astype(np.float64)


def _root_velocities(root: np.ndarray, r_rot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Step 8: (T, 3) root positions, (T, 4) headings -> yaw velocity (T-1,), XZ velocity (T-1, 2).

    ``lin_t = qrot(r_rot_{t+1}, root_{t+1} - root_t)`` and ``omega_t = arcsin(dq_t.y)`` with
    ``dq_t = r_rot_{t+1} ⊗ r_rot_t⁻¹`` (half the yaw change).
    """
    lin = qrot(r_rot[1:], root[1:] - root[:-1])
    dq = qmul(r_rot[1:], qinv(r_rot[:-1]))
    return np.arcsin(np.clip(dq[:, 2], -1.0, 1.0)), lin[:, [0, 2]]


def _rifke(positions: np.ndarray, r_rot: np.ndarray) -> np.ndarray:
    """Step 9: root-relative XZ (y kept absolute), rotated into each frame's heading: (T, J, 3)."""
    centred = positions - positions[:, :1] * np.array([1.0, 0.0, 1.0])
    return qrot(r_rot[:, None], centred)


# ---------------------------------------------------------------------------------------------
# Recovery (reference A.5)


def _as_torch(features: Array, min_dim: int) -> tuple[torch.Tensor, np.dtype | None]:
    """(..., T, D) array -> (tensor, numpy dtype to return or None for torch input)."""
    if isinstance(features, torch.Tensor):
        tensor, np_dtype = features, None
        if not tensor.is_floating_point():
            tensor = tensor.float()
    else:
        arr = np.asarray(features)
        np_dtype = arr.dtype if np.issubdtype(arr.dtype, np.floating) else np.dtype(np.float64)
        tensor = torch.from_numpy(arr.astype(np.float64))
    if tensor.ndim < 2 or tensor.shape[-1] < min_dim:
        raise ValueError(f"features must have shape (..., T, D) with D >= {min_dim}, got {tuple(tensor.shape)}")
    return tensor, np_dtype


def _unrotate_yaw(c: torch.Tensor, s: torch.Tensor, x: torch.Tensor, z: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """x and z of ``qrot(qinv(q), v)`` for yaw quaternions ``q = (c, 0, s, 0)``; y is unchanged.

    The products and sums that :func:`qrot`'s two cross products reduce to when the quaternion's x
    and z parts are 0, in the same order, so the result is the same bit for bit (finite input)
    without the cross products' work on the zero parts.
    """
    sx, sz = s * x, s * z
    return x + 2.0 * (c * -sz - s * sx), z + 2.0 * (c * sx - s * sz)


def root_angle(omega: torch.Tensor) -> torch.Tensor:
    """(..., T) root angular velocities (feature 0, raw) -> (..., T) ``a_t = sum_{k<t} omega_k``.

    The heading quaternion of frame t is ``(cos a_t, 0, sin a_t, 0)``, a turn by ``2 a_t`` about y.
    Frame t reads only the frames before it.
    """
    return torch.cat([torch.zeros_like(omega[..., :1]), torch.cumsum(omega[..., :-1], -1)], -1)


def _recover_root_torch(data: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(..., T, D) tensor -> cos and sin of the heading angle (..., T) each, root positions (..., T, 3).

    The heading quaternion of frame t is ``(cos a_t, 0, sin a_t, 0)`` (:func:`root_angle`).
    """
    angle = root_angle(data[..., 0])
    c, s = torch.cos(angle), torch.sin(angle)
    vel = torch.stack(_unrotate_yaw(c[..., 1:], s[..., 1:], data[..., :-1, 1], data[..., :-1, 2]), -1)
    xz = torch.cat([torch.zeros_like(vel[..., :1, :]), torch.cumsum(vel, -2)], -2)
    r_pos = torch.stack([xz[..., 0], data[..., 3], xz[..., 1]], -1)
    return c, s, r_pos


def recover_root_rot_pos(features: Array) -> tuple[Array, Array]:
    """Integrate the root groups (reference A.5 ``recover_root_rot_pos``).

    ``a_t = sum_{k<t} f[k, 0]``, heading ``q_t = (cos a_t, 0, sin a_t, 0)``;
    ``r_t.xz = sum_{k=1..t} qrot(q_k⁻¹, (f[k-1, 1], 0, f[k-1, 2]))``, ``r_t.y = f[t, 3]``.

    Args:
        features: (..., T, D) numpy array or torch tensor, D >= 4.

    Returns:
        (heading quaternions (..., T, 4), root positions (..., T, 3)), same kind as the input;
        numpy results keep the input's float dtype (computed in float64), torch results are
        differentiable.
    """
    data, np_dtype = _as_torch(features, 4)
    c, s, r_pos = _recover_root_torch(data)
    zero = torch.zeros_like(c)
    r_rot = torch.stack([c, zero, s, zero], -1)
    if np_dtype is None:
        return r_rot, r_pos
    return r_rot.numpy().astype(np_dtype), r_pos.numpy().astype(np_dtype)


def recover_from_ric(features: Array, joints_num: int) -> Array:
    """Global joint positions from the root and RIC groups (reference A.5 ``recover_from_ric``).

    Args:
        features: (..., T, D) numpy array or torch tensor, D >= 4 + 3(J-1) (normally 12J-1).
        joints_num: J.

    Returns:
        (..., T, J, 3), same kind as the input (numpy keeps its float dtype, torch is
        differentiable).
    """
    groups = feature_groups(joints_num)
    data, np_dtype = _as_torch(features, groups["ric"].stop)
    c, s, r_pos = _recover_root_torch(data)
    ric = data[..., groups["ric"]].reshape(*data.shape[:-1], joints_num - 1, 3)
    x, z = _unrotate_yaw(c[..., None], s[..., None], ric[..., 0], ric[..., 2])  # heading -> world, plus root XZ
    ric = torch.stack([x + r_pos[..., None, 0], ric[..., 1], z + r_pos[..., None, 2]], -1)
    joints = torch.cat([r_pos[..., None, :], ric], -2)
    return joints if np_dtype is None else joints.numpy().astype(np_dtype)


# ---------------------------------------------------------------------------------------------
# Normalisation statistics (reference A.6)


def grouped_mean_std(frames: np.ndarray, joints_num: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-dimension Mean and grouped Std of stacked feature frames (``cal_mean_variance``).

    Std is the population std (ddof 0) per dimension; then every dimension of each of the 7
    groups gets the group's mean std (no joints_num scaling). Zero-std guard: a group whose mean
    std is 0 (every dimension constant, e.g. contacts that never change in a tiny dataset) gets
    std 1.0, so normalising leaves that group as ``x - mean`` (zeros) instead of dividing by 0.
    A dimension counts as constant when all its values are equal (its std is then exactly 0,
    not float rounding noise).

    Args:
        frames: (N, 12J - 1) feature frames of all clips, N >= 2.
        joints_num: J.

    Returns:
        (mean (D,), std (D,)) float32.
    """
    groups = feature_groups(joints_num)
    dim = groups["contacts"].stop
    arr = np.asarray(frames, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != dim:
        raise ValueError(f"frames must have shape (N, {dim}) for joints_num={joints_num}, got {arr.shape}")
    if arr.shape[0] < 2:
        raise ValueError(f"need at least 2 frames for mean/std, got N={arr.shape[0]}")
    if not np.isfinite(arr).all():
        raise ValueError("frames contain NaN or inf; drop those clips first (the reference skips them)")
    mean = arr.mean(axis=0)
    std = arr.std(axis=0)
    std[np.ptp(arr, axis=0) == 0.0] = 0.0  # exactly constant dims: no rounding-noise std
    for sl in groups.values():
        group_std = std[sl].mean()
        std[sl] = group_std if group_std > 0.0 else 1.0
    return mean.astype(np.float32), std.astype(np.float32)


def stats_problem(name: str, values: np.ndarray, feature_dim: int) -> str | None:
    """Why ``values`` cannot be the normalisation ``name`` ("mean" or "std") of ``feature_dim``-dim features.

    Both must be finite ``(feature_dim,)`` arrays, and a std must be > 0 in every dimension:
    normalising divides by it, and a zero turns that dimension of every frame into NaN or inf
    (a model then trains on NaN). None when ``values`` is fine.
    """
    if values.shape != (feature_dim,):
        return f"{name} has shape {values.shape}, the features have {feature_dim} dims: expected ({feature_dim},)"
    dims = np.flatnonzero(~np.isfinite(values))
    if dims.size:
        return f"{name} is not finite for dims {_dims_text(dims, feature_dim)}"
    if name == "std":
        dims = np.flatnonzero(~(values > 0))
        if dims.size:
            value = "0" if np.all(values[dims] == 0) else "<= 0"
            return f"std is {value} for dims {_dims_text(dims, feature_dim)}; normalising would divide by it"
    return None


def check_stats(mean: np.ndarray, std: np.ndarray, directory: Path, feature_dim: int | None = None) -> None:
    """Raise ValueError naming ``directory``'s mean.npy or std.npy if they cannot normalise the features.

    ``feature_dim`` is the features' dimension; None takes the mean's, which must then be 12J - 1.
    """
    if feature_dim is None:
        feature_dim = int(np.shape(mean)[0]) if np.ndim(mean) == 1 else -1
        if feature_dim < 23 or feature_dim % 12 != 11:
            raise ValueError(f"{directory / 'mean.npy'}: mean has shape {np.shape(mean)}, "
                             f"not (12 J - 1,) of a J-joint skeleton's features")
    for name, values in (("mean", mean), ("std", std)):
        reason = stats_problem(name, np.asarray(values), feature_dim)
        if reason:
            raise ValueError(f"{directory / f'{name}.npy'}: {reason}")


def _dims_text(dims: np.ndarray, total: int, shown: int = 8) -> str:
    """``[4, 5, ...] (12 of 263)``: the first ``shown`` dimension indices and the count."""
    head = ", ".join(str(int(d)) for d in dims[:shown])
    return f"[{head}{', ...' if len(dims) > shown else ''}] ({len(dims)} of {total})"
