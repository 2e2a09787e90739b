"""Root projection (data/root_projection.py): landing on the hint, interpolation, consistency."""

from pathlib import Path

import numpy as np
import pytest

from data.features import feature_groups, recover_from_ric, recover_root_rot_pos
from data.root_projection import project_root, root_offsets, steer

FIXTURES = Path(__file__).parent / "fixtures" / "humanml3d"
J = 22


@pytest.fixture(scope="module")
def clip() -> np.ndarray:
    """The real fixture clip's first 60 frames (60, 263), float64: it walks and turns."""
    return np.load(FIXTURES / "new_joint_vecs_012314.npy")[:60].astype(np.float64)


def _yaw(angle: float) -> np.ndarray:
    """The matrix of a rotation by ``angle`` about +y, as the features' heading quaternions turn."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def test_a_dense_pelvis_hint_is_reached_horizontally_with_heights_and_limbs_kept(clip) -> None:
    joints = recover_from_ric(clip, J)
    rng = np.random.default_rng(0)
    hint = joints + np.cumsum(rng.normal(0.0, 0.02, joints.shape), axis=0)  # a drifting path, heights too
    mask = np.zeros((60, J), bool)
    mask[:, 0] = True
    out = project_root(clip[None], hint[None], mask[None], np.array([60]), J)[0]
    moved = recover_from_ric(out.astype(np.float64), J)
    np.testing.assert_allclose(moved[1:, 0, [0, 2]], hint[1:, 0, [0, 2]], atol=2e-4)  # float32 output
    np.testing.assert_allclose(moved[0], joints[0], atol=2e-4)  # frame 0 stays at the origin
    np.testing.assert_allclose(moved[..., 1], joints[..., 1], atol=2e-4)  # heights untouched
    reach = np.hypot(*(moved - moved[:, :1])[..., [0, 2]].transpose(2, 0, 1))  # turned, not bent
    np.testing.assert_allclose(reach, np.hypot(*(joints - joints[:, :1])[..., [0, 2]].transpose(2, 0, 1)), atol=2e-4)
    groups = feature_groups(J)
    for name in ("root_y", "ric", "rot", "contacts"):
        np.testing.assert_allclose(out[:, groups[name]], clip[:, groups[name]], atol=1e-6)


def test_steering_onto_the_own_path_changes_nothing_and_onto_a_turned_path_turns_the_motion(clip) -> None:
    _, root = recover_root_rot_pos(clip)
    np.testing.assert_allclose(steer(clip, root, J)[:-1], clip[:-1], atol=1e-5)  # vel recomputed: float32 data
    turn = _yaw(np.deg2rad(60.0))
    out = steer(clip, root @ turn.T, J)
    before, after = recover_from_ric(clip, J), recover_from_ric(out, J)
    # from frame 1 on it is the same motion turned by 60 degrees about its start (frame 0 keeps its heading)
    np.testing.assert_allclose(after[1:], before[1:] @ turn.T, atol=1e-9)
    np.testing.assert_allclose(out[1:-1, 1:3], clip[1:-1, 1:3], atol=1e-9)  # the same steps in its own frame
    with pytest.raises(ValueError, match="origin"):
        steer(clip, root + [0.1, 0.0, 0.0], J)


def test_a_motion_that_does_not_move_is_slid_not_turned(clip) -> None:
    still = clip.copy()
    still[:, 0:3] = 0.0  # no turning, no root steps
    path = np.stack([np.linspace(0.0, 1.0, 60), np.zeros(60), np.zeros(60)], -1)
    out = steer(still, path, J)
    assert np.array_equal(out[:, 0], still[:, 0])  # headings kept
    moved = recover_from_ric(out, J)
    np.testing.assert_allclose(moved - path[:, None], recover_from_ric(still, J), atol=1e-9)


def test_sparse_offsets_interpolate_from_the_origin_and_hold_after_the_last_frame() -> None:
    joints = np.zeros((20, 2, 3))
    hint = np.zeros((20, 2, 3))
    mask = np.zeros((20, 2), bool)
    hint[0, 0], mask[0, 0] = (9.0, 9.0, 9.0), True  # frame 0 cannot move: ignored
    hint[5, 0], mask[5, 0] = (1.0, 0.5, -2.0), True
    hint[15, 0], mask[15, 0] = (2.0, 1.5, 0.0), True
    hint[15, 1], mask[15, 1] = (4.0, 1.5, 0.0), True  # two joints at one frame: their mean offset (3, ., 0)
    delta = root_offsets(joints, hint, mask)
    np.testing.assert_allclose(delta[0], [0.0, 0.0, 0.0])
    np.testing.assert_allclose(delta[1], [0.2, 0.0, -0.4])  # 1/5 of the way from the origin to frame 5
    np.testing.assert_allclose(delta[10], [2.0, 0.0, -1.0])  # halfway from frame 5 to frame 15
    np.testing.assert_allclose(delta[19], [3.0, 0.0, 0.0])  # held after the last controlled frame
    mask[1:] = False
    assert np.array_equal(root_offsets(joints, hint, mask), np.zeros((20, 3)))


def test_padding_and_uncontrolled_motions_are_unchanged_and_bad_shapes_rejected(clip) -> None:
    features = np.stack([clip, clip]).astype(np.float32)
    hint = recover_from_ric(clip, J)[None].repeat(2, 0) + 0.3
    mask = np.zeros((2, 60, J), bool)
    mask[0, :40, 0] = True  # motion 0 has 40 frames; motion 1 is not controlled
    out = project_root(features, hint, mask, np.array([40, 60]), J)
    assert np.array_equal(out[0, 40:], features[0, 40:]) and np.array_equal(out[1], features[1])
    assert not np.allclose(out[0, :40], features[0, :40])
    with pytest.raises(ValueError, match="do not cover"):
        project_root(features, hint[:, :30], mask[:, :30], np.array([40, 60]), J)
