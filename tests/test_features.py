"""HumanML3D feature extraction, recovery and statistics (data.features).

Conformance data: clip 012314 of HumanML3D (MIT, tests/fixtures/humanml3d/LICENSE).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from data import rotations as R
from data.features import (
    check_stats,
    feature_groups,
    features_from_joints,
    grouped_mean_std,
    recover_from_ric,
    recover_root_rot_pos,
)
from data.kinematics import forward_kinematics
from data.skeleton import HUMANML3D, KIT, Skeleton

FIXTURES = Path(__file__).parent / "fixtures" / "humanml3d"


@pytest.fixture(scope="module")
def vecs() -> np.ndarray:
    return np.load(FIXTURES / "new_joint_vecs_012314.npy")  # (170, 263)


@pytest.fixture(scope="module")
def joints() -> np.ndarray:
    return np.load(FIXTURES / "new_joints_012314.npy")  # (170, 22, 3)


def _synthetic_clip(skeleton: Skeleton, frames: int = 60, seed: int = 0) -> np.ndarray:
    """(T, J, 3) walking-like clip: sinusoidal joint swings, a turning root moving forward."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames)[:, None, None] / skeleton.fps
    amp = 0.3 * rng.uniform(0.2, 1.0, size=(1, skeleton.joints_num, 3))
    phase = rng.uniform(0, 2 * np.pi, size=(1, skeleton.joints_num, 3))
    local = R.axis_angle_to_quat(amp * np.sin(2 * np.pi * 1.2 * t + phase))
    yaw = 0.4 + 0.6 * t[:, 0, 0]
    local[:, 0] = R.qmul(R.yaw_to_quat(yaw), local[:, 0])
    step = 1.2 / skeleton.fps * np.stack([np.sin(yaw), np.zeros_like(yaw), np.cos(yaw)], -1)
    root = np.cumsum(step, axis=0) + [1.0, 0.95, -2.0]
    return forward_kinematics(local, root / skeleton.unit, skeleton.offsets(), skeleton)


def _report(capsys: pytest.CaptureFixture[str], text: str) -> None:
    with capsys.disabled():
        print(f"\n{text}")


# --------------------------------------------------------------------------- conformance


def test_conformance_recover_from_ric(vecs, joints, capsys) -> None:
    err_np = np.abs(recover_from_ric(vecs, 22) - joints).max()
    err_t32 = (recover_from_ric(torch.from_numpy(vecs), 22) - torch.from_numpy(joints)).abs().max().item()
    batch = torch.from_numpy(np.stack([vecs, vecs])).double()
    err_batch = (recover_from_ric(batch, 22) - torch.from_numpy(joints).double()).abs().max().item()
    err_np_batch = np.abs(recover_from_ric(np.stack([vecs, vecs]), 22) - joints).max()
    _report(capsys, f"[conformance] recover_from_ric 012314 max abs err: numpy {err_np:.2e}, torch f32 "
                    f"{err_t32:.2e}, torch f64 batch {err_batch:.2e}, numpy batch {err_np_batch:.2e}")  # fmt: skip
    assert max(err_np, err_t32, err_batch, err_np_batch) <= 1e-5


def test_conformance_features_from_joints(vecs, joints, capsys) -> None:
    target = HUMANML3D.offsets(HUMANML3D.bone_lengths_of(joints[0]))
    feats = features_from_joints(joints, HUMANML3D, target_offsets=target)
    ref = vecs[: len(joints) - 1]
    assert feats.shape == ref.shape == (169, 263) and feats.dtype == np.float32
    errors = {name: float(np.abs(feats[:, sl] - ref[:, sl]).max()) for name, sl in feature_groups(22).items()}
    interior = {name: float(np.abs(feats[:130, sl] - ref[:130, sl]).max()) for name, sl in feature_groups(22).items()}
    _report(capsys, "[conformance] features_from_joints 012314 max abs err per group (all 169 rows): "
                    + ", ".join(f"{k} {v:.2e}" for k, v in errors.items())
                    + "\n[conformance]   rows 0..129 (away from the sigma-20 smoothing edge): "
                    + ", ".join(f"{k} {v:.2e}" for k, v in interior.items()))  # fmt: skip
    assert max(errors.values()) <= 0.02, errors
    for group in ("root_yaw", "root_xz", "root_y", "vel"):
        assert errors[group] <= 1e-3, (group, errors[group])
    np.testing.assert_array_equal(feats[:, feature_groups(22)["contacts"]], ref[:, 259:263])
    # Row 0 yaw velocity carries the identity-at-frame-0 artefact of the reference.
    assert feats[0, 0] > 0.1 and abs(feats[0, 0] - ref[0, 0]) < 1e-5
    assert abs(feats[0, 0] - feats[1, 0]) > 0.05 and abs(feats[1, 0] - feats[2, 0]) < 1e-3


def test_round_trip_on_real_clip(joints, capsys) -> None:
    target = HUMANML3D.offsets(HUMANML3D.bone_lengths_of(joints[0]))
    recovered = recover_from_ric(features_from_joints(joints, HUMANML3D, target), 22)
    err = np.abs(recovered - joints[:-1]).max()
    _report(capsys, f"[round trip] recover_from_ric(features_from_joints(012314)) vs joints: {err:.2e}")
    assert err < 1e-4


def test_fixture_std_has_the_seven_group_values() -> None:
    std = np.load(FIXTURES / "Std.npy")
    mean = np.load(FIXTURES / "Mean.npy")
    assert std.shape == mean.shape == (263,)
    assert len(np.unique(std)) == 7
    expected = [0.012826, 0.016927, 0.153766, 0.122244, 0.299692, 0.019470, 0.355933]
    for (name, sl), value in zip(feature_groups(22).items(), expected, strict=True):
        assert np.all(std[sl] == std[sl][0]), name
        assert abs(std[sl][0] - value) < 1e-6, name


# --------------------------------------------------------------------------- invariants


def test_synthetic_round_trip_is_idempotent() -> None:
    clip = _synthetic_clip(HUMANML3D, 60)
    once = recover_from_ric(features_from_joints(clip, HUMANML3D), 22)  # processed positions
    twice = recover_from_ric(features_from_joints(once, HUMANML3D), 22)
    # Processing processed positions changes nothing but the floor, which moves if the lowest
    # joint was in the dropped last frame.
    diff = twice - once[:-1]
    np.testing.assert_allclose(diff[..., [0, 2]], 0.0, atol=1e-5)
    np.testing.assert_allclose(diff[..., 1], diff[0, 0, 1], atol=1e-5)
    assert abs(once[..., 1].min()) < 1e-6  # on the floor
    np.testing.assert_allclose(once[0, 0, [0, 2]], 0.0, atol=1e-6)  # frame-0 root at origin
    np.testing.assert_allclose(HUMANML3D.bone_lengths_of(once), np.broadcast_to(HUMANML3D.bone_lengths, (59, 22)),
                               atol=1e-5)  # fmt: skip


def test_features_invariant_to_yaw_translation_and_scale() -> None:
    clip = _synthetic_clip(HUMANML3D, 50, seed=1)
    base = features_from_joints(clip, HUMANML3D)
    moved = R.qrot(R.yaw_to_quat(np.array(2.3)), clip) + [3.0, 0.7, -5.0]
    np.testing.assert_allclose(features_from_joints(moved, HUMANML3D), base, atol=2e-5)
    np.testing.assert_allclose(features_from_joints(1.3 * clip, HUMANML3D), base, atol=2e-5)


def test_contacts_velocities_and_heights_mean_what_they_say() -> None:
    clip = _synthetic_clip(HUMANML3D, 40, seed=2)
    feats = features_from_joints(clip, HUMANML3D)
    g = feature_groups(22)
    processed = recover_from_ric(feats, 22).astype(np.float64)
    # Contacts: squared displacement of the feet against the threshold.
    step = processed[1:, list(HUMANML3D.feet)] - processed[:-1, list(HUMANML3D.feet)]
    expected = ((step**2).sum(-1) < HUMANML3D.contact_threshold)[:, :]
    np.testing.assert_array_equal(feats[:-1, g["contacts"]], expected.astype(np.float32))
    # Local velocities of the root rotate back to the root's world displacement.
    heading, root = recover_root_rot_pos(feats.astype(np.float64))
    vel = feats[:, g["vel"]].reshape(-1, 22, 3).astype(np.float64)
    world = R.qrot(R.qinv(heading[:-1, None]), vel[:-1])
    np.testing.assert_allclose(world, processed[1:] - processed[:-1], atol=1e-5)
    np.testing.assert_allclose(feats[:, 3], processed[:, 0, 1], atol=1e-6)
    # 6-D rotations hold orthonormal columns.
    rot = feats[:, g["rot"]].reshape(-1, 21, 6).astype(np.float64)
    np.testing.assert_allclose(np.linalg.norm(rot[..., :3], axis=-1), 1.0, atol=1e-5)
    np.testing.assert_allclose((rot[..., :3] * rot[..., 3:]).sum(-1), 0.0, atol=1e-5)


def test_kit_synthetic_clip() -> None:
    clip = _synthetic_clip(KIT, 30, seed=3)
    feats = features_from_joints(clip, KIT)
    assert feats.shape == (29, 251) and KIT.feature_dim == 251
    assert np.isfinite(feats).all()
    assert feature_groups(21)["contacts"] == slice(247, 251)
    recovered = recover_from_ric(feats, 21)
    assert recovered.shape == (29, 21, 3)
    np.testing.assert_allclose(KIT.bone_lengths_of(recovered), np.broadcast_to(KIT.bone_lengths, (29, 21)),
                               rtol=1e-5, atol=1e-2)  # fmt: skip


def test_recover_torch_gradients(vecs) -> None:
    tiny = torch.tensor(vecs[:4, :35].astype(np.float64), requires_grad=True)  # J = 3 layout prefix
    assert torch.autograd.gradcheck(lambda x: recover_from_ric(x, 3), (tiny,))
    full = torch.tensor(vecs[None, :20], requires_grad=True)
    out = recover_from_ric(full, 22)
    assert out.shape == (1, 20, 22, 3)
    out[..., -1, :, :].sum().backward()
    assert full.grad is not None and full.grad[..., :4].abs().sum() > 0 and full.grad[..., 4:67].abs().sum() > 0
    heading, root = recover_root_rot_pos(full)
    assert heading.shape == (1, 20, 4) and root.shape == (1, 20, 3)


# --------------------------------------------------------------------------- statistics


def test_feature_groups_layout() -> None:
    groups = feature_groups(22)
    assert list(groups) == ["root_yaw", "root_xz", "root_y", "ric", "rot", "vel", "contacts"]
    assert [(s.start, s.stop) for s in groups.values()] == [
        (0, 1), (1, 3), (3, 4), (4, 67), (67, 193), (193, 259), (259, 263)]  # fmt: skip
    with pytest.raises(ValueError, match="joints_num"):
        feature_groups(1)


def test_grouped_mean_std_groups_population_std() -> None:
    rng = np.random.default_rng(4)
    scales = rng.uniform(0.1, 2.0, size=263)
    frames = rng.normal(size=(500, 263)) * scales + rng.normal(size=263)
    mean, std = grouped_mean_std(frames, 22)
    assert mean.dtype == std.dtype == np.float32 and mean.shape == std.shape == (263,)
    np.testing.assert_allclose(mean, frames.mean(0), rtol=1e-6)
    assert len(np.unique(std)) == 7
    for sl in feature_groups(22).values():
        np.testing.assert_allclose(std[sl], frames[:, sl].std(0, ddof=0).mean(), rtol=1e-6)


def test_grouped_mean_std_reproduces_fixture_grouping(vecs) -> None:
    # Regrouping an already-grouped Std is a no-op; the fixture clip gets 7 values too.
    _, std = grouped_mean_std(vecs, 22)
    assert len(np.unique(std)) == 7


def test_grouped_mean_std_zero_std_group_gets_one() -> None:
    frames = np.random.default_rng(5).normal(size=(10, 263))
    frames[:, 259:263] = 1.0  # contacts always on
    frames[:, 3] = 0.8  # constant root height
    _, std = grouped_mean_std(frames, 22)
    np.testing.assert_array_equal(std[259:263], 1.0)
    assert std[3] == 1.0


def test_grouped_mean_std_rejects_bad_input() -> None:
    frames = np.zeros((5, 263))
    frames[2, 7] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        grouped_mean_std(frames, 22)
    with pytest.raises(ValueError, match="at least 2"):
        grouped_mean_std(np.zeros((1, 263)), 22)
    with pytest.raises(ValueError, match="shape"):
        grouped_mean_std(np.zeros((5, 251)), 22)


def test_statistics_that_cannot_normalise_are_refused_naming_file_and_dims(tmp_path) -> None:
    mean, std = np.zeros(263, np.float32), np.ones(263, np.float32)
    check_stats(mean, std, tmp_path)  # a fine pair
    check_stats(*grouped_mean_std(np.random.default_rng(0).normal(size=(9, 263)), 22), tmp_path, 263)
    zero = std.copy()
    zero[[4, 5, 6, 7, 8, 9, 10, 11, 200]] = 0.0
    with pytest.raises(ValueError) as info:
        check_stats(mean, zero, tmp_path)
    assert str(info.value) == (f"{tmp_path}/std.npy: std is 0 for dims [4, 5, 6, 7, 8, 9, 10, 11, ...] (9 of 263); "
                               "normalising would divide by it")
    with pytest.raises(ValueError, match=r"std.npy: std is <= 0 for dims \[3\] \(1 of 263\)"):
        check_stats(mean, np.where(np.arange(263) == 3, -1.0, 1.0), tmp_path)
    with pytest.raises(ValueError, match=r"mean.npy: mean is not finite for dims \[0, 262\] \(2 of 263\)"):
        check_stats(np.where(np.isin(np.arange(263), [0, 262]), np.nan, 0.0), std, tmp_path)
    with pytest.raises(ValueError, match=r"std.npy: std is not finite for dims \[1\]"):
        check_stats(mean, np.where(np.arange(263) == 1, np.inf, 1.0), tmp_path)


def test_statistics_must_match_the_feature_dim(tmp_path) -> None:
    with pytest.raises(ValueError) as info:
        check_stats(np.zeros(7), np.ones(7), tmp_path, feature_dim=263)
    assert str(info.value) == f"{tmp_path}/mean.npy: mean has shape (7,), the features have 263 dims: expected (263,)"
    with pytest.raises(ValueError, match=r"std.npy: std has shape \(262,\), the features have 263 dims"):
        check_stats(np.zeros(263), np.ones(262), tmp_path)
    with pytest.raises(ValueError, match=r"mean.npy: mean has shape \(7,\), not \(12 J - 1,\)"):
        check_stats(np.zeros(7), np.ones(7), tmp_path)  # no declared dim: the layout decides
    with pytest.raises(ValueError, match=r"mean.npy: mean has shape \(2, 263\)"):
        check_stats(np.zeros((2, 263)), np.ones(263), tmp_path)


# --------------------------------------------------------------------------- bad input


def test_features_reject_bad_input(joints) -> None:
    with pytest.raises(ValueError, match=r"shape \(T, 22, 3\)"):
        features_from_joints(joints[:, :21], HUMANML3D)
    with pytest.raises(ValueError, match="shape"):
        features_from_joints(joints[0], HUMANML3D)
    with pytest.raises(ValueError, match="at least 2 frames"):
        features_from_joints(joints[:1], HUMANML3D)
    bad = joints.copy()
    bad[3, 5, 1] = np.nan
    with pytest.raises(ValueError, match=r"NaN or inf \(frames \[3\]\)"):
        features_from_joints(bad, HUMANML3D)
    with pytest.raises(ValueError, match="target_offsets"):
        features_from_joints(joints, HUMANML3D, target_offsets=np.zeros((21, 3)))
    degenerate = np.zeros_like(joints[:5])
    with pytest.raises(ValueError):
        features_from_joints(degenerate, HUMANML3D)
    with pytest.raises(ValueError, match="D >= 67"):
        recover_from_ric(np.zeros((5, 40)), 22)
