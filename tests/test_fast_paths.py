"""The fast code paths compute what the plain ones do: batch-first attention and the yaw unrotation."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from tolerance import float32_atol
from torch import nn

from data.features import recover_from_ric, recover_root_rot_pos
from data.rotations import qinv, qrot, yaw_to_quat
from models.transformer import batch_first_attention


@pytest.mark.parametrize("cross", [False, True])
@pytest.mark.parametrize("train", [True, False])
def test_batch_first_attention_matches_multihead_attention(cross: bool, train: bool) -> None:
    torch.manual_seed(0)
    mha = nn.MultiheadAttention(32, 4, dropout=0.0, batch_first=True).train(train)
    x = torch.randn(5, 11, 32, requires_grad=True)
    memory = torch.randn(5, 3 if cross else 11, 32, requires_grad=True) if cross else x
    mask = torch.arange(memory.shape[1])[None] >= torch.tensor([1, 2, 3, 3, 2])[:, None] + (0 if cross else 8)
    params = [x, mha.in_proj_weight, mha.in_proj_bias, mha.out_proj.weight] + ([memory] if cross else [])

    expected = mha(x, memory, memory, key_padding_mask=mask, need_weights=False)[0]
    expected_grads = torch.autograd.grad(expected.square().sum(), params)
    got = batch_first_attention(mha, x, memory, mask)
    got_grads = torch.autograd.grad(got.square().sum(), params)

    torch.testing.assert_close(got, expected, rtol=0, atol=float32_atol(expected))  # tests/tolerance.py
    for g, e in zip(got_grads, expected_grads, strict=True):
        torch.testing.assert_close(g, e, rtol=1e-5, atol=1e-5)


def _recover_with_quaternions(features: torch.Tensor, joints_num: int) -> torch.Tensor:
    """recover_from_ric written with the general quaternion rotation (reference A.5)."""
    angle = torch.cat([torch.zeros_like(features[..., :1, 0]), torch.cumsum(features[..., :-1, 0], -1)], -1)
    r_rot = yaw_to_quat(2.0 * angle)
    vel = torch.stack([features[..., :-1, 1], torch.zeros_like(features[..., :-1, 1]), features[..., :-1, 2]], -1)
    vel = qrot(qinv(r_rot[..., 1:, :]), vel)
    xz = torch.cat([torch.zeros_like(vel[..., :1, :]), torch.cumsum(vel, -2)], -2)
    r_pos = torch.stack([xz[..., 0], features[..., 3], xz[..., 2]], -1)
    ric = features[..., 4 : 4 + 3 * (joints_num - 1)].reshape(*features.shape[:-1], joints_num - 1, 3)
    ric = qrot(qinv(r_rot[..., None, :]), ric) + r_pos[..., None, :] * torch.tensor([1.0, 0.0, 1.0])
    return torch.cat([r_pos[..., None, :], ric], -2)


def test_recover_from_ric_equals_the_quaternion_formula() -> None:
    torch.manual_seed(0)
    features = 0.3 * torch.randn(3, 40, 12 * 22 - 1, dtype=torch.float64)
    a = features.clone().requires_grad_()
    b = features.clone().requires_grad_()
    got, expected = recover_from_ric(a, 22), _recover_with_quaternions(b, 22)
    assert torch.equal(got, expected)  # the same products in the same order: bit for bit
    weights = torch.randn_like(got)
    (got * weights).sum().backward()
    (expected * weights).sum().backward()
    torch.testing.assert_close(a.grad, b.grad, rtol=1e-12, atol=1e-12)

    r_rot, r_pos = recover_root_rot_pos(features)
    angle = torch.cat([torch.zeros(3, 1, dtype=features.dtype), torch.cumsum(features[..., :-1, 0], -1)], -1)
    assert torch.equal(r_rot, yaw_to_quat(2.0 * angle)) and torch.equal(r_pos, expected[..., 0, :].detach())
    np.testing.assert_array_equal(recover_from_ric(features.numpy(), 22), expected.detach().numpy())
