"""Known answers and invariants of data.rotations (numpy and torch)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from data import rotations as R


def _random_quats(rng: np.random.Generator, *shape: int) -> np.ndarray:
    q = rng.normal(size=(*shape, 4))
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def test_known_answers() -> None:
    quarter_y = R.axis_angle_to_quat(np.array([0.0, np.pi / 2, 0.0]))
    np.testing.assert_allclose(quarter_y, [np.cos(np.pi / 4), 0, np.sin(np.pi / 4), 0], atol=1e-12)
    # +90 degrees about y turns +x into -z and +z into +x (right-handed, y up).
    np.testing.assert_allclose(R.qrot(quarter_y, np.array([1.0, 0, 0])), [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(R.qrot(quarter_y, np.array([0.0, 0, 1])), [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(R.yaw_to_quat(np.array(np.pi / 2)), quarter_y, atol=1e-12)
    # Hamilton product: i * j = k.
    i, j = np.array([0.0, 1, 0, 0]), np.array([0.0, 0, 1, 0])
    np.testing.assert_allclose(R.qmul(i, j), [0, 0, 0, 1])
    np.testing.assert_allclose(R.axis_angle_to_matrix(np.array([0.0, np.pi / 2, 0])),
                               [[0, 0, 1], [0, 1, 0], [-1, 0, 0]], atol=1e-12)  # fmt: skip
    np.testing.assert_allclose(R.axis_angle_to_quat(np.zeros(3)), [1, 0, 0, 0])


def test_qmul_qinv_qrot_consistency() -> None:
    rng = np.random.default_rng(0)
    q, r = _random_quats(rng, 50), _random_quats(rng, 50)
    v = rng.normal(size=(50, 3))
    np.testing.assert_allclose(R.qmul(q, R.qinv(q)), np.tile([1.0, 0, 0, 0], (50, 1)), atol=1e-12)
    np.testing.assert_allclose(R.qrot(R.qmul(q, r), v), R.qrot(q, R.qrot(r, v)), atol=1e-12)
    np.testing.assert_allclose(R.qrot(q, v), np.einsum("nij,nj->ni", R.quat_to_matrix(q), v), atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(R.qrot(q, v), axis=-1), np.linalg.norm(v, axis=-1))


def test_qbetween_maps_u_onto_v() -> None:
    rng = np.random.default_rng(1)
    u, v = rng.normal(size=(100, 3)), 3.0 * rng.normal(size=(100, 3))  # not unit length
    q = R.qbetween(u, v)
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-12)
    np.testing.assert_allclose(R.normalize(R.qrot(q, u)), R.normalize(v), atol=1e-12)
    # Shortest arc: the rotation axis is perpendicular to both (no twist about u).
    np.testing.assert_allclose((q[:, 1:] * u).sum(-1), 0.0, atol=1e-12)
    np.testing.assert_allclose(R.qbetween(u, u), np.tile([1.0, 0, 0, 0], (100, 1)), atol=1e-12)
    # Opposite directions: a half turn instead of NaN.
    for a in (np.array([0.0, -1.0, 0.0]), np.array([1.0, 0.0, 0.0]), np.array([0.3, 0.2, -0.9])):
        q = R.qbetween(a, -2.0 * a)
        assert np.isfinite(q).all()
        np.testing.assert_allclose(R.qrot(q, a), -a, atol=1e-12)


def test_matrix_quat_and_6d_round_trips() -> None:
    rng = np.random.default_rng(2)
    q = _random_quats(rng, 200)
    q[:4] = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]  # every Shepperd branch
    m = R.quat_to_matrix(q)
    np.testing.assert_allclose(m @ np.swapaxes(m, -1, -2), np.broadcast_to(np.eye(3), m.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(m), 1.0, atol=1e-12)
    q_back = R.matrix_to_quat(m)
    np.testing.assert_allclose(np.abs((q_back * q).sum(-1)), 1.0, atol=1e-12)  # equal up to sign
    d6 = R.matrix_to_cont6d(m)
    np.testing.assert_array_equal(d6[:, :3], m[:, :, 0])  # first column, then second column
    np.testing.assert_array_equal(d6[:, 3:], m[:, :, 1])
    np.testing.assert_allclose(R.cont6d_to_matrix(d6), m, atol=1e-12)
    np.testing.assert_allclose(R.quat_to_cont6d(q), d6, atol=1e-15)
    np.testing.assert_allclose(np.abs((R.cont6d_to_quat(d6) * q).sum(-1)), 1.0, atol=1e-12)


def test_cont6d_decodes_any_vector_to_a_rotation() -> None:
    d6 = np.random.default_rng(3).normal(size=(30, 6))
    m = R.cont6d_to_matrix(d6)
    np.testing.assert_allclose(np.linalg.det(m), 1.0, atol=1e-12)
    np.testing.assert_allclose(m[:, :, 0], R.normalize(d6[:, :3]), atol=1e-12)  # x = n(a)
    assert ((m[:, :, 1] * d6[:, 3:]).sum(-1) > 0).all()  # y on b's side


def test_torch_matches_numpy_and_broadcasts() -> None:
    rng = np.random.default_rng(4)
    q, v = _random_quats(rng, 2, 5, 4), rng.normal(size=(2, 5, 4, 3))
    tq = torch.from_numpy(q)
    for fn, args in [
        (R.qrot, (q, v)),
        (R.qmul, (q, q[::-1])),
        (R.qbetween, (v, v[::-1])),
        (R.quat_to_matrix, (q,)),
        (R.cont6d_to_matrix, (np.concatenate([v, v[::-1]], -1),)),
        (R.axis_angle_to_quat, (v,)),
    ]:
        expected = fn(*args)
        got = fn(*(torch.from_numpy(np.ascontiguousarray(a)) for a in args))
        assert isinstance(got, torch.Tensor)
        np.testing.assert_allclose(got.numpy(), expected, atol=1e-12, err_msg=fn.__name__)
    m = R.quat_to_matrix(tq)
    np.testing.assert_allclose(R.matrix_to_quat(m).numpy(), R.matrix_to_quat(m.numpy()), atol=1e-12)
    # One quaternion per (2, 5) broadcast over 4 vectors; mixed numpy/torch arguments.
    out = R.qrot(tq[:, :, :1], v)
    assert isinstance(out, torch.Tensor) and out.shape == (2, 5, 4, 3)


def test_torch_gradients() -> None:
    rng = np.random.default_rng(5)
    u = torch.tensor(rng.normal(size=(3, 3)), requires_grad=True)
    v = torch.tensor(rng.normal(size=(3, 3)), requires_grad=True)
    d6 = torch.tensor(rng.normal(size=(3, 6)), requires_grad=True)
    aa = torch.tensor(rng.normal(size=(3, 3)), requires_grad=True)
    assert torch.autograd.gradcheck(R.qbetween, (u, v))
    assert torch.autograd.gradcheck(R.cont6d_to_matrix, (d6,))
    assert torch.autograd.gradcheck(lambda a: R.matrix_to_quat(R.axis_angle_to_matrix(a)), (aa,))
    assert torch.autograd.gradcheck(lambda a, b: R.qrot(R.axis_angle_to_quat(a), b), (aa, u))


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-3, 3.0])
def test_axis_angle_small_and_large(angle: float) -> None:
    axis = np.array([0.6, 0.0, 0.8])
    q = R.axis_angle_to_quat(axis * angle)
    np.testing.assert_allclose(q, [np.cos(angle / 2), *(axis * np.sin(angle / 2))], atol=1e-15)


def test_matrix_to_quat_returns_the_sign_with_nonnegative_w():
    """A quaternion and its negative are one rotation; the round trip gives the one with w >= 0."""
    q = np.array([[-0.1, 0.9, 0.3, 0.3], [-0.2, 0.1, -0.3, 0.9]])
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    np.testing.assert_allclose(R.matrix_to_quat(R.quat_to_matrix(q)), -q, atol=1e-12)
