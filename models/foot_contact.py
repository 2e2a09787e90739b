"""The foot contact loss of MDM (Tevet et al. 2023, Eq. 8 ``L_foot``), shared by EMDM and the motion VAE.

``L_foot = mean over valid frame pairs of || (J(x_hat)[n+1, feet] - J(x_hat)[n, feet]) * f[n] ||^2``:
the predicted global velocity of the four contact joints, wherever the *ground-truth* contact label
``f[n]`` (HumanML3D's foot-contact feature group, denormalised, > 0.5) says the foot is planted,
pulled toward zero. The label is the target's, not the prediction's, so the term cannot be met by
predicting no contact. EMDM uses it as its Eq. 9 (``models.emdm.geometric_losses``); the motion VAE
as ``train_vae.foot_weight`` (``models.vae.vae_loss``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from data.skeleton import SKELETONS


def masked_mse(pred: Tensor, target: Tensor, valid: Tensor) -> Tensor:
    """Squared error over valid frames: per sample ``sum_{valid n, all elements} (pred - target)^2 /
    (valid frames * elements per frame)``, then the mean over the batch. pred/target (B, N, ...), valid (B, N)."""
    per_frame = (pred - target).square().flatten(2).sum(-1)
    elements = per_frame.new_tensor(float(math.prod(pred.shape[2:])))
    count = valid.sum(1).to(per_frame.dtype).clamp(min=1.0) * elements
    return (torch.where(valid, per_frame, 0.0).sum(1) / count).mean()


def skeleton_feet(joints_num: int) -> tuple[int, ...]:
    """The four contact joints, in the order of the contact features, of the skeleton with ``joints_num``
    joints (HumanML3D (7, 10, 8, 11), KIT); a ValueError for an unknown joint count."""
    for skeleton in SKELETONS.values():
        if skeleton.joints_num == joints_num:
            return skeleton.feet
    raise ValueError(f"no known skeleton with {joints_num} joints: pass feet explicitly")


def foot_contact_loss(joints_hat: Tensor, contacts: Tensor, valid: Tensor, feet: Sequence[int]) -> Tensor:
    """MDM's ``L_foot`` (module docstring) in metres per frame, squared.

    ``joints_hat`` (B, N, J, 3): predicted global joints; ``contacts`` (B, N, 4): the target's contact
    labels, denormalised (planted where > 0.5), in the order of ``feet``; ``valid`` (B, N) the valid
    frames (a pair counts when both its frames are valid). A motion with no planted foot scores 0.
    """
    velocity = joints_hat[:, 1:, list(feet)] - joints_hat[:, :-1, list(feet)]
    planted = (contacts[:, :-1] > 0.5).to(joints_hat.dtype)[..., None]
    moving = velocity * planted
    return masked_mse(moving, torch.zeros_like(moving), valid[:, 1:] & valid[:, :-1])
