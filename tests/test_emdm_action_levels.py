"""benchmarks/emdm_action_levels.py: a chain from level T is the evaluation's sampling; from level 0, the input."""

import numpy as np
import torch

from models.emdm import EMDMConfig, EMDMGenerator, sample_emdm
from tests.bench_module import load_benchmark

BENCH = load_benchmark("emdm_action_levels")
chain_from = BENCH.chain_from


def _generator() -> EMDMGenerator:
    torch.manual_seed(0)
    gen = EMDMGenerator(EMDMConfig(
        feature_dim=263, condition="action", num_actions=3, width=16, layers=1, heads=2, ff_dim=32, dropout=0.0,
        z_dim=4, mapping_layers=2, d_width=16, d_layers=1, d_heads=2, d_ff_dim=16, d_time_dim=8,
        input_skip=True, skip_kernel=3,
    ))
    with torch.no_grad():  # away from the zero-initialised output, so G's network matters
        for p in gen.parameters():
            p.add_(0.1 * torch.randn_like(p))
    return gen.eval()


def test_chain_from_level_T_equals_sampling_and_level_0_returns_the_input() -> None:
    gen = _generator()
    schedule = gen.config.make_schedule()
    ids, lengths = torch.tensor([0, 2]), torch.tensor([12, 8])
    valid = (torch.arange(12)[None] < lengths[:, None])[..., None]
    x_T = torch.where(valid, torch.randn(2, 12, 263, generator=torch.Generator().manual_seed(1)), 0.0)
    with torch.inference_mode():
        expected = sample_emdm(gen, schedule, ids, lengths, 2.5, torch.Generator().manual_seed(7), x_T=x_T)
        got = chain_from(gen, schedule, x_T, schedule.num_steps, ids, lengths, valid, 2.5,
                         torch.Generator().manual_seed(7))
        assert torch.allclose(got, expected, atol=1e-5)
        assert float(got[1, 8:].abs().max()) == 0.0  # padding stays 0
        other_label = chain_from(gen, schedule, x_T, schedule.num_steps, torch.tensor([1, 1]), lengths, valid, 2.5,
                                 torch.Generator().manual_seed(7))
        assert not torch.allclose(other_label, expected, atol=1e-3)  # the label reaches the chain
        assert torch.equal(chain_from(gen, schedule, x_T, 0, ids, lengths, valid, 2.5, torch.Generator()), x_T)


def test_crop_jitter_is_the_second_difference_length_over_each_crops_own_frames() -> None:
    t = np.arange(6.0)
    joints = np.zeros((2, 6, 2, 3))
    joints[0, :, :, 0] = (0.5 * 0.02 * t**2)[:, None]  # constant acceleration 0.02 m/frame² along x
    joints[1, :4, :, 1] = (0.5 * 0.04 * t[:4] ** 2)[:, None]  # 0.04 over its 4 frames, then padding
    joints[1, 4:] = 99.0  # past the crop's length: never read
    assert np.isclose(BENCH.crop_jitter(joints, np.array([6, 4])), 0.03)
    assert BENCH.crop_jitter(np.zeros((1, 5, 2, 3)), np.array([5])) == 0.0


def test_seam_ratio_compares_acceleration_at_patch_boundaries_with_inside() -> None:
    t = np.arange(13.0)
    smooth = np.zeros((1, 13, 1, 3))
    smooth[0, :, 0, 0] = 0.5 * 0.02 * t**2  # the same acceleration, 0.02, on every frame
    assert np.isclose(BENCH.seam_ratio(smooth, np.array([13]), 4), 1.0)
    stepped = smooth.copy()
    stepped[0, :, 0, 1] = t // 4  # a step of 1 at each boundary: acceleration 1 on the frames either side of it
    padded = np.concatenate([stepped, np.full((1, 3, 1, 3), 99.0)], 1)  # past the crop's length: never read
    assert np.isclose(BENCH.seam_ratio(padded, np.array([13]), 4), np.hypot(1.0, 0.02) / 0.02)
