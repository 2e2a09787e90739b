"""Tests for models/foot_contact.py: MDM's foot contact loss (known answers, masks, labels)."""

from __future__ import annotations

import pytest
import torch

from models.foot_contact import foot_contact_loss, masked_mse, skeleton_feet

FEET = (7, 10, 8, 11)  # HumanML3D's contact joints, in the order of the contact features


def _walk(frames: int = 6) -> torch.Tensor:
    """(1, frames, 22, 3) joints at rest except joint 10 (left toe), moving 0.1 m along x per frame."""
    joints = torch.zeros(1, frames, 22, 3)
    joints[0, :, 10, 0] = 0.1 * torch.arange(frames, dtype=torch.float32)
    return joints


def test_known_answer_and_contact_labels() -> None:
    joints, valid = _walk(), torch.ones(1, 6, dtype=torch.bool)
    contacts = torch.zeros(1, 6, 4)
    assert foot_contact_loss(joints, contacts, valid, FEET).item() == 0.0  # nothing planted
    contacts[..., 1] = 1.0  # the moving toe planted throughout: each pair errs 0.1^2 over 4 feet x 3 axes
    assert foot_contact_loss(joints, contacts, valid, FEET).item() == pytest.approx(0.01 / 12, rel=1e-6)
    contacts[0, :3, 1] = 0.4  # a label at or below 0.5 is not a contact: pairs 0-2 drop out of 5
    assert foot_contact_loss(joints, contacts, valid, FEET).item() == pytest.approx(0.01 / 12 * 2 / 5, rel=1e-6)
    still = torch.ones(1, 6, 4)  # every foot planted, a still body: 0
    assert foot_contact_loss(torch.zeros(1, 6, 22, 3), still, valid, FEET).item() == 0.0


def test_padded_frames_never_count() -> None:
    joints, contacts = _walk(), torch.ones(1, 6, 4)
    short = torch.tensor([[True, True, True, False, False, False]])  # 3 valid frames: 2 pairs
    padded = joints.clone()
    padded[0, 3:] = 100.0  # garbage in the padding
    expect = foot_contact_loss(joints[:, :3], contacts[:, :3], torch.ones(1, 3, dtype=torch.bool), FEET)
    assert foot_contact_loss(padded, contacts, short, FEET).item() == pytest.approx(expect.item(), rel=1e-6)


def test_gradient_reaches_only_planted_feet() -> None:
    joints = _walk().requires_grad_(True)
    contacts = torch.zeros(1, 6, 4)
    contacts[..., 1] = 1.0
    foot_contact_loss(joints, contacts, torch.ones(1, 6, dtype=torch.bool), FEET).backward()
    moved = joints.grad.abs().sum(dim=(0, 1, 3))
    assert moved[10] > 0 and float(moved.sum() - moved[10]) == 0.0


def test_masked_mse_and_feet() -> None:
    pred, target = torch.ones(2, 3, 2), torch.zeros(2, 3, 2)
    valid = torch.tensor([[True, True, False], [True, False, False]])
    pred[0, 2] = 50.0  # padded: ignored
    assert masked_mse(pred, target, valid).item() == pytest.approx(1.0)
    assert skeleton_feet(22) == FEET
    with pytest.raises(ValueError, match="13 joints"):
        skeleton_feet(13)
