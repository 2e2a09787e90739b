"""benchmarks/motiondiffuse_control.py's ablation masks: who owns the joint velocity features."""

from __future__ import annotations

import sys

import torch
from bench_module import BENCHMARKS, load_benchmark

from models.motiondiffuse import PART_MASKS

sys.path.insert(0, str(BENCHMARKS))  # the benchmark imports prompt_probe as a sibling script
control = load_benchmark("motiondiffuse_control")


def test_root_velocities_are_the_models_masks() -> None:
    assert torch.equal(control.upper_mask("root"), PART_MASKS["upper"])


def test_joint_velocities_give_the_upper_body_its_own_velocities_only() -> None:
    joint, root = control.upper_mask("joint"), control.upper_mask("root")
    added = joint & ~root
    assert not (root & ~joint).any() and int(added.sum()) == 13 * 3  # torso 5 + arms 8 joints, xyz each
    upper_joints = [3, 6, 9, 12, 13, 14, 15, 16, 17, 18, 19, 20, 21]  # spine, neck, head, collars, arms
    expected = torch.tensor([193 + 3 * j + k for j in upper_joints for k in range(3)])
    assert torch.equal(added.nonzero().flatten(), expected)
