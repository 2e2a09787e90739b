"""Tests for models/emdm.py: the few-step VP schedule, EMDM's generator/discriminator, losses and sampler."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from standin_device import STANDIN, syncs_of
from torch import nn

from models.diffusion import condition_dropout
from models.emdm import (
    Conditioning,
    EMDMConfig,
    EMDMDiscriminator,
    EMDMGenerator,
    EMDMSchedule,
    action_from_text,
    d_adversarial_loss,
    discriminator_step_losses,
    g_adversarial_loss,
    generator_step_losses,
    geometric_losses,
    guided_x0,
    lazy_r1_scale,
    q_sample_pairs,
    r1_penalty,
    sample_emdm,
)
from models.patches import from_patches, from_patches_overlapped, overlap_window, to_patches
from models.transformer import lengths_to_mask

pytestmark = pytest.mark.usefixtures("one_thread")  # tiny networks (tests/conftest.py)

FIXTURES = Path(__file__).parent / "fixtures" / "humanml3d"
D, E, J = 263, 8, 22
TINY = {
    "feature_dim": D, "text_dim": E, "width": 16, "layers": 2, "heads": 2, "ff_dim": 32, "dropout": 0.0,
    "z_dim": 4, "mapping_layers": 2, "d_width": 16, "d_layers": 1, "d_heads": 2, "d_ff_dim": 16, "d_time_dim": 8,
}


def _gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _nets(**overrides: object) -> tuple[EMDMGenerator, EMDMDiscriminator]:
    torch.manual_seed(0)
    cfg = EMDMConfig(**{**TINY, **overrides})
    return EMDMGenerator(cfg), EMDMDiscriminator(cfg)


@pytest.fixture(scope="module")
def real() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Two normalised 16-frame windows of the real fixture clip (B=2, 16, 263), Mean and Std (263,)."""
    feats = torch.tensor(np.load(FIXTURES / "new_joint_vecs_012314.npy"))
    mean, std = torch.tensor(np.load(FIXTURES / "Mean.npy")), torch.tensor(np.load(FIXTURES / "Std.npy"))
    x0 = torch.stack([feats[0:16], feats[40:56]])
    return ((x0 - mean) / std).float(), mean.float(), std.float()


# --------------------------------------------------------------------------------------------------
# Schedule (values computed here by hand from DDGAN's formulas)
# --------------------------------------------------------------------------------------------------


def _hand_schedule(T: int = 10, bmin: float = 0.1, bmax: float = 20.0) -> dict[str, list[float]]:
    """DDGAN's get_sigma_schedule + Posterior_Coefficients in plain floats (dummy beta_0 dropped)."""
    u = [1e-3 + (1 - 1e-3) * i / T for i in range(T + 1)]
    abar = [math.exp(-0.5 * v * v * (bmax - bmin) - v * bmin) for v in u]
    betas = [1 - abar[i] / abar[i - 1] for i in range(1, T + 1)]
    ab, prod = [], 1.0
    for b in betas:
        prod *= 1 - b
        ab.append(prod)
    ab_prev = [1.0, *ab[:-1]]
    var = [b * (1 - p) / (1 - a) for b, p, a in zip(betas, ab_prev, ab, strict=True)]
    return {
        "betas": betas, "ab": ab, "var": var,
        "logvar": [math.log(max(v, 1e-20)) for v in var],
        "coef1": [b * math.sqrt(p) / (1 - a) for b, p, a in zip(betas, ab_prev, ab, strict=True)],
        "coef2": [(1 - p) * math.sqrt(1 - b) / (1 - a) for b, p, a in zip(betas, ab_prev, ab, strict=True)],
    }


def test_schedule_matches_hand_formulas_at_T10() -> None:
    s, hand = EMDMSchedule(), _hand_schedule()
    assert s.num_steps == 10 and s.time_points[0] == 1e-3 and s.time_points[-1] == 1.0
    torch.testing.assert_close(s.betas, torch.tensor(hand["betas"], dtype=torch.float64), rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(s.alphas_cumprod[1:], torch.tensor(hand["ab"], dtype=torch.float64), rtol=1e-12,
                               atol=1e-14)
    assert s.alphas_cumprod[0] == 1.0
    for name, table in [("var", s.posterior_variance), ("logvar", s.posterior_log_variance),
                        ("coef1", s.posterior_mean_coef1), ("coef2", s.posterior_mean_coef2)]:
        torch.testing.assert_close(table, torch.tensor(hand[name], dtype=torch.float64), rtol=1e-10, atol=1e-12)
    # the reference's table (3 digits): beta, alpha_bar, coef1, coef2, logvar
    assert s.betas[0] == pytest.approx(0.105, abs=5e-4) and s.betas[9] == pytest.approx(0.850, abs=5e-4)
    assert s.alphas_cumprod[1] == pytest.approx(0.8947, abs=1e-4)
    assert s.alphas_cumprod[10] == pytest.approx(4.32e-5, rel=1e-2)
    assert s.posterior_mean_coef1[1] == pytest.approx(0.733, abs=5e-4)
    assert s.posterior_mean_coef2[1] == pytest.approx(0.262, abs=5e-4)
    assert s.posterior_mean_coef2[9] == pytest.approx(0.387, abs=5e-4)
    assert s.posterior_log_variance[0] == pytest.approx(math.log(1e-20))
    assert s.posterior_log_variance[1] == pytest.approx(-2.51, abs=5e-3)


def test_posterior_sample_known_values_and_exact_x0_at_t0() -> None:
    s, hand = EMDMSchedule(), _hand_schedule()
    t = torch.tensor([0, 3, 9])
    x0, x_next, noise = torch.full((3, 2, 1), 2.0), torch.full((3, 2, 1), -1.0), torch.full((3, 2, 1), 0.5)
    out = s.posterior_sample(x0, x_next, t, noise)
    for row, k in enumerate(t.tolist()):
        expect = hand["coef1"][k] * 2.0 - hand["coef2"][k] + (k > 0) * math.exp(0.5 * hand["logvar"][k]) * 0.5
        assert out[row].flatten().tolist() == pytest.approx([expect] * 2, rel=1e-6)
    mean, var, _ = s.posterior_mean_variance(x0, x_next, t)
    assert var[0].item() == 0.0 and mean[1, 0, 0].item() == pytest.approx(hand["coef1"][3] * 2 - hand["coef2"][3])
    g = _gen(1)
    a, b, n = (torch.randn(4, 5, 3, generator=g) for _ in range(3))
    assert torch.equal(s.posterior_sample(a, b, 0, n), a)  # t = 0: exactly x0_hat


def test_q_sample_pairs_exact_at_t0_and_forward_marginals() -> None:
    s = EMDMSchedule()
    x0 = torch.randn(3, 4, 2, generator=_gen(0))
    x_t, x_next = q_sample_pairs(s, x0, torch.zeros(3, dtype=torch.long), _gen(1))
    assert torch.equal(x_t, x0)
    assert not torch.equal(x_next, x0)
    # statistics of the pair at t = 4 from a constant x0 = 1.5
    n, k = 40000, 4
    ones = torch.full((n, 1, 1), 1.5, dtype=torch.float64)
    x_t, x_next = q_sample_pairs(s, ones, torch.full((n,), k), _gen(2))
    ab_t, ab_next, beta = s.alphas_cumprod[k].item(), s.alphas_cumprod[k + 1].item(), s.betas[k].item()
    assert x_t.mean().item() == pytest.approx(1.5 * math.sqrt(ab_t), abs=0.02)
    assert x_next.mean().item() == pytest.approx(1.5 * math.sqrt(ab_next), abs=0.02)
    assert x_next.var().item() == pytest.approx(1 - ab_next, abs=0.02)
    step = x_next - math.sqrt(1 - beta) * x_t  # the one-step noise sqrt(beta) eps'
    assert step.mean().item() == pytest.approx(0.0, abs=0.02) and step.var().item() == pytest.approx(beta, rel=0.03)


# --------------------------------------------------------------------------------------------------
# Losses
# --------------------------------------------------------------------------------------------------


def test_adversarial_losses_known_values() -> None:
    real, fake = torch.tensor([2.0, -1.0]), torch.tensor([0.5, -3.0])
    sp = lambda v: math.log1p(math.exp(v))  # noqa: E731
    assert d_adversarial_loss(real, fake).item() == pytest.approx((sp(-2) + sp(1)) / 2 + (sp(0.5) + sp(-3)) / 2)
    assert g_adversarial_loss(fake).item() == pytest.approx((sp(-0.5) + sp(3)) / 2)


def test_r1_on_a_linear_discriminator_and_lazy_scale() -> None:
    gamma, lengths = 0.02, torch.tensor([4, 2])
    w = nn.Parameter(torch.randn(4, 3, generator=_gen(0)))
    x = torch.randn(2, 4, 3, generator=_gen(1), requires_grad=True)
    logits = (x * w).sum((1, 2)) + 0.3  # dD/dx = w everywhere, padded frames included
    r1 = r1_penalty(logits, x, lengths, gamma)
    w2 = w.detach().square()
    expect = gamma / 2 * (w2.sum() + w2[:2].sum()) / 2  # mean over the batch of the valid-entry sums
    assert r1.item() == pytest.approx(expect.item(), rel=1e-6)
    r1.backward()  # create_graph: d r1 / d w = gamma * w * (samples in which the frame is valid) / B
    counts = torch.tensor([2.0, 2.0, 1.0, 1.0])[:, None]
    torch.testing.assert_close(w.grad, gamma * w.detach() * counts / 2)
    unmasked = r1_penalty((x * w).sum((1, 2)), x, None, gamma)
    assert unmasked.item() == pytest.approx((gamma / 2 * w2.sum()).item(), rel=1e-6)
    assert [lazy_r1_scale(s, 15) for s in (0, 1, 14, 15, 30, 31)] == [15.0, 0.0, 0.0, 15.0, 15.0, 0.0]
    assert lazy_r1_scale(7, 1) == 1.0


def _sliding(lengths: list[int], frames: int, v: tuple[float, float], moving: slice = slice(None)) -> tuple:
    """mean 0 / std 1 features: a static pose (target) and the same pose sliding with root velocity v."""
    g = _gen(3)
    target = torch.zeros(len(lengths), frames, D)
    target[..., 3] = 0.9
    target[..., 4:67] = torch.randn(63, generator=g)
    target[..., 259:263] = 1.0  # every foot in contact
    pred = target.clone()
    pred[:, moving, 1], pred[:, moving, 2] = v
    return pred, target, torch.zeros(D), torch.ones(D)


def test_geometric_loss_hand_values_on_a_sliding_pose() -> None:
    vx, vz = 0.3, -0.4
    sq = vx * vx + vz * vz
    pred, target, mean, std = _sliding([5, 3], 6, (vx, vz))
    out = geometric_losses(pred, target, [5, 3], mean, std, J, weight=100.0, lam=1.0)
    # joint i of frame n is offset by n (vx, 0, vz): pos per sample = sq/3 * sum_{n<len} n^2 / len
    expect = {"recon": sq / D, "pos": (sq / 3 * 30 / 5 + sq / 3 * 5 / 3) / 2, "vel": sq / 3, "foot": sq / 3}
    for key, value in expect.items():
        assert out[key].item() == pytest.approx(value, rel=1e-5), key
    geo = sum(expect.values())
    assert out["geo"].item() == pytest.approx(geo, rel=1e-5)
    assert out["total"].item() == pytest.approx(100 * geo, rel=1e-5)
    assert geometric_losses(pred, target, [5, 3], mean, std, J, lam=0.0)["geo"].item() == pytest.approx(sq / D)
    # the foot term's own lambda: recon + 0 (pos + vel) + 7 foot, and lambda on pos and vel alone
    only_feet = geometric_losses(pred, target, [5, 3], mean, std, J, lam=0.0, foot_lam=7.0)["geo"].item()
    assert only_feet == pytest.approx(sq / D + 7 * sq / 3, rel=1e-5)
    no_feet = geometric_losses(pred, target, [5, 3], mean, std, J, lam=1.0, foot_lam=0.0)["geo"].item()
    assert no_feet == pytest.approx(geo - expect["foot"], rel=1e-5)
    # contacts: only the left ankle on -> a quarter; none on -> 0 although the feet slide
    target[..., 260:263] = 0.0
    assert geometric_losses(pred, target, [5, 3], mean, std, J)["foot"].item() == pytest.approx(sq / 12, rel=1e-5)
    target[..., 259] = 0.0
    assert geometric_losses(pred, target, [5, 3], mean, std, J)["foot"].item() == 0.0


def test_foot_loss_zero_where_feet_are_static_during_contact() -> None:
    # contacts on for frames 0-2, off after; the pose slides only during frames 3 -> 5
    pred, target, mean, std = _sliding([6], 6, (0.2, 0.1), moving=slice(3, 5))
    target[:, 3:, 259:263] = 0.0
    out = geometric_losses(pred, target, [6], mean, std, J)
    assert out["foot"].item() == 0.0
    assert out["pos"].item() > 0 and out["vel"].item() > 0 and out["recon"].item() > 0
    target[:, 3, 259] = 1.0  # a contact during the slide (frame 3 -> 4) now counts
    assert geometric_losses(pred, target, [6], mean, std, J)["foot"].item() > 0


def test_geometric_loss_zero_when_equal_positive_otherwise_and_ignores_padding(real) -> None:
    x0, mean, std = real
    lengths = [16, 10]
    same = geometric_losses(x0, x0.clone(), lengths, mean, std, J)
    assert same["recon"].item() == same["pos"].item() == same["vel"].item() == 0.0
    # Eq. 9 compares the prediction's foot motion with 0, not with the ground truth: real feet in
    # contact still move a little (squared step < 0.002 m^2 by HumanML3D's labelling), so pred == target
    # leaves that residual, bounded by 0.002 / 3 per element; a static pose leaves exactly 0.
    assert 0.0 < same["foot"].item() < 0.002 / 3
    static, _, zeros, ones = _sliding([4, 2], 4, (0.0, 0.0))
    assert all(v.item() == 0.0 for v in geometric_losses(static, static.clone(), [4, 2], zeros, ones, J).values())
    pred = x0 + 0.1 * torch.randn(x0.shape, generator=_gen(4))
    out = geometric_losses(pred, x0, lengths, mean, std, J)
    assert all(out[k].item() > 0 for k in ("recon", "pos", "vel", "foot", "geo", "total"))
    moved = pred.clone()
    moved[1, 10:] += 5.0  # padded frames of sample 1
    again = geometric_losses(moved, x0, lengths, mean, std, J)
    for key in out:
        assert again[key].item() == pytest.approx(out[key].item(), rel=1e-6), key


# --------------------------------------------------------------------------------------------------
# Networks: padding, condition dropout
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("patch", "overlap"), [(1, False), (4, False), (4, True)])
def test_generator_ignores_padding_and_zeroes_it(patch: int, overlap: bool) -> None:
    gen, _ = _nets(patch_frames=patch, overlap_out=overlap)
    gen.eval()
    g = _gen(5)
    x, z, cond = torch.randn(2, 6, D, generator=g), torch.randn(2, 4, generator=g), torch.randn(2, E, generator=g)
    t, lengths = torch.tensor([3, 7]), torch.tensor([6, 3])
    out = gen(x, t, z, cond, lengths)
    assert out.shape == (2, 6, D) and out.abs().sum() > 0
    assert torch.equal(out[1, 3:], torch.zeros(3, D))
    changed = x.clone()
    changed[1, 3:] = 100.0 * torch.randn(3, D, generator=g)
    torch.testing.assert_close(gen(changed, t, z, cond, lengths), out, rtol=0, atol=0)
    padded = torch.cat([x, torch.randn(2, 4, D, generator=g)], 1)  # more padding, same valid frames
    torch.testing.assert_close(gen(padded, t, z, cond, lengths)[:, :6], out, rtol=1e-5, atol=1e-5)
    alone = gen(x[1:, :3], t[1:], z[1:], cond[1:], lengths[1:])
    torch.testing.assert_close(alone, out[1:, :3], rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("patch", [1, 4])
def test_discriminator_ignores_padding(patch: int) -> None:
    _, disc = _nets(patch_frames=patch)
    g = _gen(6)
    x_t, x_next = torch.randn(2, 6, D, generator=g), torch.randn(2, 6, D, generator=g)
    cond = torch.randn(2, E, generator=g)
    t, lengths = torch.tensor([0, 9]), torch.tensor([6, 2])
    logits = disc(x_t, x_next, t, cond, lengths)
    assert logits.shape == (2,)
    a, b = x_t.clone(), x_next.clone()
    a[1, 2:], b[1, 2:] = 50.0, -50.0
    torch.testing.assert_close(disc(a, b, t, cond, lengths), logits, rtol=0, atol=0)
    more = [torch.cat([v, torch.randn(2, 5, D, generator=g)], 1) for v in (x_t, x_next)]
    torch.testing.assert_close(disc(*more, t, cond, lengths), logits, rtol=1e-5, atol=1e-5)
    assert not torch.allclose(disc(x_t, x_next, t, cond, torch.tensor([6, 3])), logits)  # a valid frame counts
    assert not torch.allclose(disc(x_t, x_next, t, -cond, lengths), logits)  # the condition counts


def test_input_skip_adds_a_per_step_multiple_of_the_input_starting_at_sqrt_alpha_bar() -> None:
    plain, _ = _nets()
    skipped, _ = _nets(input_skip=True)
    schedule = skipped.config.make_schedule()
    torch.testing.assert_close(skipped.skip, schedule.alphas_cumprod[1:].sqrt().float())
    g = _gen(8)
    x, z, cond = torch.randn(2, 6, D, generator=g), torch.randn(2, 4, generator=g), torch.randn(2, E, generator=g)
    t, lengths = torch.tensor([0, 9]), torch.tensor([6, 4])
    with torch.no_grad():
        skipped.skip[0], skipped.skip[9] = 2.0, -1.0
    out, base = skipped(x, t, z, cond, lengths), plain(x, t, z, cond, lengths)
    torch.testing.assert_close(out[0], base[0] + 2.0 * x[0])
    torch.testing.assert_close(out[1, :4], base[1, :4] - x[1, :4])
    assert torch.equal(out[1, 4:], torch.zeros(2, D))


def test_skip_kernel_starts_as_the_scalar_skip_and_filters_valid_neighbours_only() -> None:
    scalar, _ = _nets(input_skip=True)
    wide, _ = _nets(input_skip=True, skip_kernel=3)
    assert wide.skip.shape == (10, D, 3)
    torch.testing.assert_close(wide.skip[:, 0, 1], scalar.skip)
    assert torch.count_nonzero(wide.skip[:, :, [0, 2]]) == 0
    g = _gen(9)
    x, z, cond = torch.randn(2, 6, D, generator=g), torch.randn(2, 4, generator=g), torch.randn(2, E, generator=g)
    t, lengths = torch.tensor([0, 9]), torch.tensor([6, 4])
    with torch.no_grad():
        torch.testing.assert_close(wide(x, t, z, cond, lengths), scalar(x, t, z, cond, lengths))
        base = wide(x, t, z, cond, lengths) - wide.skipped(x, t, lengths_to_mask(lengths, 6))
        wide.skip[0] = torch.tensor([1.0, 0.0, 0.0])  # step 0: each frame takes its predecessor
        wide.skip[9] = torch.tensor([0.0, 0.0, 2.0])  # step 9: twice its successor
        out = wide(x, t, z, cond, lengths)
    torch.testing.assert_close(out[0, 1:], base[0, 1:] + x[0, :-1])
    torch.testing.assert_close(out[0, 0], base[0, 0])  # nothing before frame 0
    torch.testing.assert_close(out[1, :3], base[1, :3] + 2.0 * x[1, 1:4])
    torch.testing.assert_close(out[1, 3], base[1, 3])  # frame 4 is padding: read as 0
    assert torch.equal(out[1, 4:], torch.zeros(2, D))
    with pytest.raises(ValueError, match="skip_kernel"):
        _nets(skip_kernel=2)


def test_skip_filter_equals_the_window_sum_with_its_gradients() -> None:
    """The filter against its definition: out[n] = sum_j taps[j] x[n + j - k//2] over valid frames, zero
    outside; values and both gradients, for random taps and mixed lengths."""
    gen, _ = _nets(input_skip=True, skip_kernel=5)
    g = _gen(4)
    with torch.no_grad():
        gen.skip.copy_(torch.randn(gen.skip.shape, generator=g))
    x = torch.randn(3, 9, D, generator=g, requires_grad=True)
    w = torch.randn(3, 9, D, generator=g)
    steps, lengths = torch.tensor([2, 7, 2]), torch.tensor([9, 5, 1])
    valid = lengths_to_mask(lengths, 9)
    got = gen.skipped(x, steps, valid)
    grads = torch.autograd.grad((got * w).sum(), (x, gen.skip))
    taps = gen.skip[steps]  # (B, D, 5)
    padded = torch.nn.functional.pad(torch.where(valid[..., None], x, 0.0), (0, 0, 2, 2))
    want = sum(padded[:, j:j + 9] * taps[:, None, :, j] for j in range(5))
    torch.testing.assert_close(got, want)
    for a, b in zip(grads, torch.autograd.grad((want * w).sum(), (x, gen.skip)), strict=True):
        torch.testing.assert_close(a, b)
    assert torch.equal(grads[0][1, 5:], torch.zeros(4, D))  # padded frames get no gradient


def test_skip_filter_gradient_is_bit_identical_run_to_run() -> None:
    """Repeated steps in a batch: the skip taps' gradient must not depend on summation order (the
    backward of ``skip[steps]`` made EMDM's training differ run to run on two threads; ``index_select``'s
    does not)."""
    gen, _ = _nets(input_skip=True, skip_kernel=5)
    g = _gen(3)
    x, w = torch.randn(32, 196, D, generator=g), torch.randn(32, 196, D, generator=g)
    steps, valid = torch.randint(0, 10, (32,), generator=g), torch.ones(32, 196, dtype=torch.bool)

    def grad() -> torch.Tensor:
        gen.skip.grad = None
        (gen.skipped(x, steps, valid) * w).sum().backward()
        return gen.skip.grad.clone()

    threads = torch.get_num_threads()
    torch.set_num_threads(2)  # the order varied with more than one intra-op thread
    try:
        first = grad()
        assert all(torch.equal(grad(), first) for _ in range(4))
    finally:
        torch.set_num_threads(threads)


def test_naive_ddgan_discriminator_ignores_the_condition() -> None:
    _, disc = _nets(d_condition=False)
    g = _gen(7)
    x_t, x_next = torch.randn(2, 6, D, generator=g), torch.randn(2, 6, D, generator=g)
    cond, t, lengths = torch.randn(2, E, generator=g), torch.tensor([0, 9]), torch.tensor([6, 4])
    logits = disc(x_t, x_next, t, cond, lengths)
    torch.testing.assert_close(disc(x_t, x_next, t, -cond, lengths), logits, rtol=0, atol=0)
    assert not any("cond_embed" in name for name, _ in disc.named_parameters())


def test_patches_round_trip_and_validity() -> None:
    x = torch.arange(2 * 7 * 3, dtype=torch.float32).reshape(2, 7, 3)
    valid = torch.tensor([[True] * 7, [True] * 5 + [False] * 2])
    patches, token_valid = to_patches(x, valid, 4)
    assert patches.shape == (2, 2, 12)
    assert torch.equal(patches[0, 1, :9], x[0, 4:7].flatten()) and torch.equal(patches[0, 1, 9:], torch.zeros(3))
    assert torch.equal(token_valid, torch.tensor([[True, True], [True, True]]))
    back = from_patches(patches, 7, 4)
    assert torch.equal(back[0], x[0]) and torch.equal(back[1, :5], x[1, :5])
    assert torch.equal(back[1, 5:], torch.zeros(2, 3))
    assert torch.equal(to_patches(x, torch.tensor([[True] * 7, [True] * 3 + [False] * 4]), 4)[1][1],
                       torch.tensor([True, False]))


def test_overlapped_patches_blend_neighbours_and_ignore_invalid_tokens() -> None:
    torch.testing.assert_close(overlap_window(4), torch.tensor([1, 3, 5, 7, 7, 5, 3, 1]) / 8)
    valid = torch.ones(1, 3, dtype=torch.bool)
    ones = from_patches_overlapped(torch.ones(1, 3, 16), valid, 12, 4)  # 2 channels
    torch.testing.assert_close(ones, torch.ones(1, 12, 2))
    # token m writes m everywhere: frames hold their own token's value at its centre and ramp by 1/4
    # per frame across each boundary (plain patches would step by 1 there)
    steps = torch.arange(3.0).repeat_interleave(8).reshape(1, 3, 8)
    frames = from_patches_overlapped(steps, valid, 12, 4)[0, :, 0]
    torch.testing.assert_close(frames, torch.tensor([0, 0, 1 / 8, 3 / 8, 5 / 8, 7 / 8, 9 / 8, 11 / 8, 13 / 8, 15 / 8,
                                                     2, 2]))
    # an invalid token writes nothing: the frames its window reaches are the valid neighbour's own values
    last_invalid = from_patches_overlapped(steps, torch.tensor([[True, True, False]]), 12, 4)[0, :, 0]
    torch.testing.assert_close(last_invalid[:6], frames[:6])
    torch.testing.assert_close(last_invalid[6:8], torch.ones(2))
    with pytest.raises(ValueError, match="even"):
        from_patches_overlapped(torch.ones(1, 2, 6), torch.ones(1, 2, dtype=torch.bool), 6, 3)
    with pytest.raises(ValueError, match="overlap_out needs an even"):
        EMDMConfig(patch_frames=3, overlap_out=True)


def test_condition_dropout_rate_and_null_condition() -> None:
    drop = condition_dropout(20000, 0.1, _gen(7))
    assert drop.dtype == torch.bool and drop.float().mean().item() == pytest.approx(0.1, abs=0.01)
    assert not condition_dropout(100, 0.0, _gen(7)).any() and condition_dropout(100, 1.0, _gen(7)).all()
    gen, _ = _nets()
    with torch.no_grad():
        gen.null_cond.copy_(torch.randn(16, generator=_gen(8)))  # a trained, non-zero null token
    cond, mask = torch.randn(3, E, generator=_gen(9)), torch.tensor([True, False, True])
    tokens = gen.condition_tokens(cond, mask)
    torch.testing.assert_close(tokens[0], gen.null_cond.detach())
    torch.testing.assert_close(tokens[2], gen.null_cond.detach())
    torch.testing.assert_close(tokens[1], gen.cond_embed(cond[1:2])[0])
    gen.eval()
    g = _gen(10)
    x, z, t = torch.randn(3, 5, D, generator=g), torch.randn(3, 4, generator=g), torch.tensor([1, 2, 3])
    other = torch.randn(3, E, generator=g)
    a, b = gen(x, t, z, cond, [5, 5, 4], drop_cond=mask), gen(x, t, z, other, [5, 5, 4], drop_cond=mask)
    torch.testing.assert_close(a[mask], b[mask], rtol=0, atol=0)  # dropped: the condition is ignored
    assert not torch.allclose(a[1], b[1])


def test_word_tokens_read_real_words_only_and_never_when_dropped() -> None:
    gen, _ = _nets(word_tokens=True, token_dim=6)
    gen.eval()
    g = _gen(13)
    x, z, t = torch.randn(3, 5, D, generator=g), torch.randn(3, 4, generator=g), torch.tensor([1, 2, 3])
    cond, states = torch.randn(3, E, generator=g), torch.randn(3, 4, 6, generator=g)
    mask = torch.tensor([[True, True, False, False], [True, True, True, True], [True, False, False, False]])
    drop = torch.tensor([False, False, True])
    out = gen(x, t, z, cond, [5, 5, 4], drop_cond=drop, words=(states, mask))
    padded = torch.where(mask[..., None], states, torch.randn(3, 4, 6, generator=g))
    torch.testing.assert_close(gen(x, t, z, cond, [5, 5, 4], drop_cond=drop, words=(padded, mask)), out,
                               rtol=0, atol=0)  # padded words are ignored
    other = gen(x, t, z, cond, [5, 5, 4], drop_cond=drop, words=(states.flip(0), mask.flip(0)))
    torch.testing.assert_close(other[2], out[2], rtol=0, atol=0)  # dropped: no word is read
    assert not torch.allclose(other[0], out[0])  # kept: the words steer the output
    uncond = gen(x, t, z, cond, [5, 5, 4], drop_cond=torch.ones(3, dtype=torch.bool), words=(states, mask))
    guided = guided_x0(gen, x, t, z, cond, [5, 5, 4], 2.5, words=(states, mask))
    conditional = gen(x, t, z, cond, [5, 5, 4], words=(states, mask))
    torch.testing.assert_close(guided, uncond + 2.5 * (conditional - uncond), rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match="word_tokens"):
        gen(x, t, z, cond, [5, 5, 4])
    with pytest.raises(ValueError, match="word_tokens"):
        _nets()[0](x, t, z, cond, [5, 5, 4], words=(states, mask))


def test_text_norm_standardises_the_pooled_embedding_for_g_and_d() -> None:
    gen, disc = _nets(text_norm=True)
    cond = torch.randn(2, E, generator=_gen(14))
    for embed in (gen.cond_embed, disc.cond_embed):
        standard = (cond - cond.mean(-1, keepdim=True)) / cond.std(-1, unbiased=False, keepdim=True)
        torch.testing.assert_close(embed(cond), embed.embed(standard), rtol=1e-4, atol=1e-5)
        torch.testing.assert_close(embed(10.0 * cond + 3.0), embed(cond), rtol=1e-4, atol=1e-4)  # any scale
    plain, _ = _nets()
    torch.testing.assert_close(plain.cond_embed(cond), plain.cond_embed.embed(cond))


def test_action_condition() -> None:
    gen, disc = _nets(condition="action", num_actions=5)
    assert gen.config.geometric_weight == 1.0 and EMDMConfig(**TINY).geometric_weight == 100.0
    labels = torch.tensor([0, 4])
    tokens = gen.condition_tokens(labels, torch.tensor([False, True]))
    torch.testing.assert_close(tokens[0], gen.cond_embed.embed.weight[0])
    torch.testing.assert_close(tokens[1], gen.null_cond)
    gen.eval()
    x, z = torch.randn(2, 4, D, generator=_gen(11)), torch.randn(2, 4, generator=_gen(12))
    t = torch.tensor([2, 2])
    out = guided_x0(gen, x, t, z, labels, [4, 3], 2.5)
    assert out.shape == (2, 4, D) and torch.isfinite(out).all() and torch.equal(out[1, 3], torch.zeros(D))
    assert disc(x, x, t, labels, [4, 3]).shape == (2,)
    with pytest.raises(ValueError, match="num_actions"):
        EMDMConfig(condition="action")


def test_an_action_generator_with_word_tokens_cross_attends_to_its_label_alone() -> None:
    gen, _ = _nets(condition="action", num_actions=3, word_tokens=True)
    assert gen.token_proj is None and gen.layers[0].cross_attn is not None
    memory, ignored = gen.word_memory(gen.condition_tokens(torch.tensor([1, 2])), None, None)
    assert memory.shape == (2, 1, 16) and not ignored.any()
    gen.eval()
    x, z, t = torch.randn(2, 4, D, generator=_gen(15)), torch.randn(2, 4, generator=_gen(16)), torch.tensor([3, 3])
    a, b = gen(x, t, z, torch.tensor([0, 0]), [4, 4]), gen(x, t, z, torch.tensor([0, 2]), [4, 4])
    torch.testing.assert_close(a[0], b[0], rtol=0, atol=0)
    assert not torch.allclose(a[1], b[1])  # the label steers the output
    with pytest.raises(ValueError, match="word_tokens"):  # labels have no words
        gen(x, t, z, torch.tensor([0, 2]), [4, 4], words=(torch.zeros(2, 3, E), torch.ones(2, 3, dtype=torch.bool)))


def test_empty_word_slots_leave_an_action_generator_reading_its_label_alone() -> None:
    plain, _ = _nets(condition="action", num_actions=3, word_tokens=True)
    slots, _ = _nets(condition="action", num_actions=3, word_tokens=True, token_dim=6, label_words=2)
    missing = slots.load_state_dict(plain.state_dict(), strict=False).missing_keys
    assert sorted(missing) == ["label_word_mask", "label_word_states", "token_proj.bias", "token_proj.weight"]
    assert not slots.label_word_mask.any()
    for gen in (plain, slots):
        gen.eval()
    x, z, t = torch.randn(2, 4, D, generator=_gen(20)), torch.randn(2, 4, generator=_gen(21)), torch.tensor([1, 7])
    labels = torch.tensor([2, 0])
    torch.testing.assert_close(slots(x, t, z, labels, [4, 3]), plain(x, t, z, labels, [4, 3]), rtol=1e-6, atol=1e-6)
    for bad in ({"label_words": 2}, {"condition": "action", "num_actions": 2, "label_words": 2},
                {"condition": "action", "num_actions": 2, "word_tokens": True, "label_words": -1}):
        with pytest.raises(ValueError, match="label_words"):
            EMDMConfig(**{**TINY, **bad})


def test_action_from_text_starts_the_action_model_as_the_text_model_of_each_class_caption() -> None:
    """With one caption per class, the started action G (D) given label c is the text G (D) given that
    caption, output for output: with its words when G has word slots (cut to the slots), with none when it
    has none. With several, the label row is the mean of their condition tokens."""
    text_g, text_d = _nets(word_tokens=True, token_dim=6, text_norm=True, input_skip=True, skip_kernel=3)
    act_g, act_d = _nets(condition="action", num_actions=3, word_tokens=True, token_dim=6, label_words=3,
                         input_skip=True, skip_kernel=3)
    bare_g, _ = _nets(condition="action", num_actions=3, word_tokens=True, token_dim=6, input_skip=True,
                      skip_kernel=3)
    pooled = torch.randn(3, E, generator=_gen(17))
    words = [torch.randn(n, 6, generator=_gen(30 + n)) for n in (2, 4, 3)]  # class 1's is cut to 3 slots
    captions = [(p[None], w) for p, w in zip(pooled, words, strict=True)]
    for action, text in ((act_g, text_g), (act_d, text_d), (bare_g, text_g)):
        action_from_text(action, text.state_dict(), text.config, captions)
    for net in (text_g, act_g, text_d, act_d, bare_g):
        net.eval()
    x, z = torch.randn(3, 5, D, generator=_gen(18)), torch.randn(3, 4, generator=_gen(19))
    t, labels, lengths = torch.tensor([0, 4, 9]), torch.tensor([2, 0, 1]), [5, 3, 4]
    states, mask = torch.zeros(3, 3, 6), torch.zeros(3, 3, dtype=torch.bool)
    for row, label in enumerate(labels.tolist()):
        n = min(len(words[label]), 3)
        states[row, :n], mask[row, :n] = words[label][:n], True
    torch.testing.assert_close(act_g(x, t, z, labels, lengths),
                               text_g(x, t, z, pooled[labels], lengths, words=(states, mask)), rtol=1e-5, atol=1e-5)
    no_words = (torch.zeros(3, 2, 6), torch.zeros(3, 2, dtype=torch.bool))
    torch.testing.assert_close(bare_g(x, t, z, labels, lengths),
                               text_g(x, t, z, pooled[labels], lengths, words=no_words), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(act_d(x, x.flip(1), t, labels, lengths),
                               text_d(x, x.flip(1), t, pooled[labels], lengths), rtol=1e-5, atol=1e-5)
    several = [(pooled[:2], words[0]), (pooled[1:], words[1]), (pooled[::2], words[2])]
    action_from_text(act_g, text_g.state_dict(), text_g.config, several)
    torch.testing.assert_close(act_g.cond_embed.embed.weight[0], text_g.cond_embed(pooled[:2]).mean(0))
    with pytest.raises(ValueError, match="2 captions for 3 actions"):
        action_from_text(act_g, text_g.state_dict(), text_g.config, captions[:2])
    wider, _ = _nets(word_tokens=True, token_dim=6, ff_dim=48, input_skip=True, skip_kernel=3)
    with pytest.raises(ValueError, match=r"layers\.0\.ff\.0\.weight: the text model's is \(48, 16\).*\(32, 16\)"):
        action_from_text(act_g, wider.state_dict(), wider.config, captions)
    with pytest.raises(ValueError, match="skip: the text model's is missing"):
        action_from_text(act_g, _nets(word_tokens=True, token_dim=6)[0].state_dict(), wider.config, captions)
    with pytest.raises(ValueError, match="from a text model"):
        action_from_text(text_g, text_g.state_dict(), text_g.config, captions)


# --------------------------------------------------------------------------------------------------
# Guidance and sampling
# --------------------------------------------------------------------------------------------------


def test_classifier_free_guidance() -> None:
    gen, _ = _nets()
    gen.eval()
    g = _gen(13)
    x, z, cond = torch.randn(2, 5, D, generator=g), torch.randn(2, 4, generator=g), torch.randn(2, E, generator=g)
    t, lengths = torch.tensor([4, 8]), [5, 3]
    c = gen(x, t, z, cond, lengths)
    u = gen(x, t, z, cond, lengths, drop_cond=torch.ones(2, dtype=torch.bool))
    assert not torch.allclose(c, u)
    torch.testing.assert_close(guided_x0(gen, x, t, z, cond, lengths, 1.0), c, rtol=0, atol=0)
    torch.testing.assert_close(guided_x0(gen, x, t, z, cond, lengths, 0.0), u, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(guided_x0(gen, x, t, z, cond, lengths, 2.5), u + 2.5 * (c - u), rtol=1e-5, atol=1e-5)


class _ConstantX0(nn.Module):
    """A stand-in generator predicting a fixed x0 (zero at padding); records each step's batch, steps and
    dropped conditions, and each :meth:`conditioning` call."""

    def __init__(self, x0: torch.Tensor) -> None:
        super().__init__()
        self.config = EMDMConfig(**TINY)
        self.x0 = nn.Parameter(x0)
        self.calls: list[tuple[int, list[int], list[bool] | None]] = []
        self.conditionings = 0

    def conditioning(
        self, cond: torch.Tensor, drop_cond: torch.Tensor | None = None,
        words: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> Conditioning:
        assert words is None
        self.conditionings += 1
        return Conditioning(cond, () if drop_cond is None else (drop_cond,))

    def denoise(
        self, x: torch.Tensor, t: torch.Tensor, z: torch.Tensor, lengths: torch.Tensor, conditioning: Conditioning,
    ) -> torch.Tensor:
        dropped = conditioning.memory[0].tolist() if conditioning.memory else None
        self.calls.append((x.shape[0], sorted(set(t.tolist())), dropped))
        valid = torch.arange(x.shape[1])[None, :] < torch.as_tensor(lengths)[:, None]
        return self.x0.repeat(x.shape[0] // self.x0.shape[0], 1, 1) * valid[..., None]


def test_sampler_returns_x0_hat_with_one_batched_forward_per_step() -> None:
    target = torch.randn(2, 5, D, generator=_gen(14))
    stub, schedule = _ConstantX0(target), EMDMSchedule()
    out = sample_emdm(stub, schedule, torch.randn(2, E), [5, 3], guidance=2.5, generator_rng=_gen(15))
    torch.testing.assert_close(out[0], target[0].detach())
    torch.testing.assert_close(out[1, :3], target[1, :3].detach())
    assert torch.equal(out[1, 3:], torch.zeros(2, D))
    # one call per step t = 9..0 on the doubled batch [unconditional; conditional]
    assert stub.calls == [(4, [s], [True, True, False, False]) for s in range(9, -1, -1)]
    assert stub.conditionings == 1  # the condition's part of G once per sampling call, not per step
    stub.calls.clear()
    sample_emdm(stub, schedule, torch.randn(2, E), [5, 3], guidance=1.0, generator_rng=_gen(15))
    assert stub.calls == [(2, [s], None) for s in range(9, -1, -1)] and stub.conditionings == 2


def test_sampler_is_deterministic_and_zero_on_padding() -> None:
    gen, _ = _nets()
    schedule, cond, lengths = EMDMSchedule(), torch.randn(2, E, generator=_gen(16)), [6, 4]
    a = sample_emdm(gen, schedule, cond, lengths, 2.5, _gen(17))
    b = sample_emdm(gen, schedule, cond, lengths, 2.5, _gen(17))
    c = sample_emdm(gen, schedule, cond, lengths, 2.5, _gen(18))
    assert a.shape == (2, 6, D) and torch.isfinite(a).all()
    assert torch.equal(a, b) and not torch.allclose(a, c)
    assert torch.equal(a[1, 4:], torch.zeros(2, D)) and a[1, :4].abs().sum() > 0
    assert gen.training  # the mode is restored
    assert sample_emdm(gen, schedule, cond, lengths, 2.5, _gen(17), num_frames=9).shape == (2, 9, D)


def test_sampler_waits_for_the_gpu_a_fixed_number_of_times_whatever_its_steps() -> None:
    """On a GPU (the stand-in counts the host's waits: tests/standin_device.py) the schedule moves to G's device
    once and no step reads a timestep back or copies a coefficient over: a chain of 4 steps makes the host
    wait as often as one of 2 (z and the posterior noise drawn on the device, with no CPU generator)."""
    def sample(steps: int) -> None:
        gen, _ = _nets(num_steps=steps, word_tokens=True, token_dim=6, input_skip=True, skip_kernel=3)
        words = (torch.randn(2, 3, 6), torch.tensor([[True, True, False], [True, True, True]]))
        sample_emdm(gen.to(STANDIN), gen.config.make_schedule(), torch.randn(2, E), [6, 4], 2.5, words=words)

    assert syncs_of(lambda: sample(2)) == syncs_of(lambda: sample(4))


def test_sampler_with_conditioning_computed_once_equals_algorithm_1_step_by_step() -> None:
    """sample_emdm computes G's condition part once; Alg. 1 written out with guided_x0 at every step
    (the condition recomputed each time) must give the same sample, bit for bit."""
    gen, _ = _nets(word_tokens=True, token_dim=6, input_skip=True, skip_kernel=3)
    g = _gen(19)
    cond, states = torch.randn(2, E, generator=g), torch.randn(2, 3, 6, generator=g)
    words, lengths = (states, torch.tensor([[True, True, False], [True, True, True]])), torch.tensor([7, 5])
    schedule = EMDMSchedule()
    for guidance in (2.5, 1.0):
        out = sample_emdm(gen, schedule, cond, lengths, guidance, _gen(20), words=words)
        rng, valid = _gen(20), lengths_to_mask(lengths, 7)[..., None]
        x = torch.randn(2, 7, D, generator=rng) * valid
        gen.eval()
        with torch.no_grad():
            for step in range(9, -1, -1):
                t, z = torch.full((2,), step), torch.randn(2, 4, generator=rng)
                x0_hat = guided_x0(gen, x, t, z, cond, lengths, guidance, words)
                if step > 0:
                    x = schedule.posterior_sample(x0_hat, x, t, torch.randn(x.shape, generator=rng)) * valid
        gen.train()
        assert torch.equal(out, x0_hat) and torch.equal(out[1, 5:], torch.zeros(2, D))


# --------------------------------------------------------------------------------------------------
# One optimisation step
# --------------------------------------------------------------------------------------------------


def _grads_ok(module: nn.Module) -> bool:
    return all(p.grad is not None and torch.isfinite(p.grad).all() for p in module.parameters())


def test_discriminator_step_softplus_signs() -> None:
    """With a D that says 2 to every pair: real term softplus(-2) = 0.126928, fake term softplus(2) = 2.126928."""
    gen, _ = _nets()

    def says_two(x_t, x_next, t, cond, lengths, **_):
        return torch.full((x_t.shape[0],), 2.0)

    x0 = torch.randn(2, 6, D, generator=_gen(1))
    d = discriminator_step_losses(gen, says_two, EMDMSchedule(), x0, torch.randn(2, E), [6, 4], step=1,
                                  generator_rng=_gen(2))
    assert d["real"].item() == pytest.approx(0.126928, abs=1e-6)
    assert d["fake"].item() == pytest.approx(2.126928, abs=1e-6)


def test_discriminator_step_real_pairs_come_from_data_and_fake_pairs_from_g() -> None:
    """Two generators, the same draws and a D that reads x_t: the real term cannot depend on G, the fake
    term must (a swap of the two would fail both assertions)."""
    gen, _ = _nets()
    other, _ = _nets()
    with torch.no_grad():
        for q in other.parameters():
            q.add_(0.5 * torch.randn(q.shape, generator=_gen(3)))

    def reads_x_t(x_t, x_next, t, cond, lengths, **_):
        return 10.0 * x_t.flatten(1).mean(1)

    x0, cond = torch.randn(2, 6, D, generator=_gen(1)), torch.randn(2, E, generator=_gen(4))
    a, b = (discriminator_step_losses(g, reads_x_t, EMDMSchedule(), x0, cond, [6, 4], step=1, generator_rng=_gen(2))
            for g in (gen, other))
    assert a["real"].item() == b["real"].item()
    assert abs(a["fake"].item() - b["fake"].item()) > 1e-3


def test_generators_adversarial_term_reaches_the_generator() -> None:
    """The adversarial term judges G's own x0_hat (through the posterior sample), so it has gradients in G."""
    gen, disc = _nets()
    disc.requires_grad_(False)
    x0 = torch.randn(2, 16, D, generator=_gen(1))
    out = generator_step_losses(gen, disc, EMDMSchedule(), x0, torch.randn(2, E), [16, 10], torch.zeros(D),
                                torch.ones(D), generator_rng=_gen(2))
    grads = torch.autograd.grad(out["adv"], list(gen.parameters()), allow_unused=True)
    assert sum(float(g.abs().sum()) for g in grads if g is not None) > 0


def test_one_training_step_of_d_and_g(real) -> None:
    x0, mean, std = real
    gen, disc = _nets(p_uncond=0.5)
    schedule, cond, lengths = EMDMSchedule(), torch.randn(2, E, generator=_gen(19)), [16, 10]
    opt_d = torch.optim.Adam(disc.parameters(), lr=1e-4, betas=(0.5, 0.9))
    opt_g = torch.optim.Adam(gen.parameters(), lr=1e-4, betas=(0.5, 0.9))

    # D step with R1 (step 0 of the lazy interval): finite gradients on every D parameter, none into G
    d = discriminator_step_losses(gen, disc, schedule, x0, cond, lengths, step=0, generator_rng=_gen(20))
    assert d["r1"].item() > 0 and d["total"].item() == pytest.approx(
        (d["real"] + d["fake"] + 15 * d["r1"]).item(), rel=1e-6)
    d["total"].backward()
    assert _grads_ok(disc) and all(p.grad is None for p in gen.parameters())
    opt_d.step()
    opt_d.zero_grad()
    # a D step without R1 lowers D's loss on the same draw
    before = discriminator_step_losses(gen, disc, schedule, x0, cond, lengths, step=1, generator_rng=_gen(21))
    assert before["r1"].item() == 0.0
    before["total"].backward()
    opt_d.step()
    opt_d.zero_grad()
    after = discriminator_step_losses(gen, disc, schedule, x0, cond, lengths, step=1, generator_rng=_gen(21))
    assert after["total"].item() < before["total"].item()

    # G step: finite gradients on every G parameter (null token included: p_uncond 0.5), loss goes down
    disc.requires_grad_(False)
    g_before = generator_step_losses(gen, disc, schedule, x0, cond, lengths, mean, std, generator_rng=_gen(22))
    assert set(g_before) == {"adv", "recon", "pos", "vel", "foot", "geo", "total"}
    assert g_before["total"].item() == pytest.approx((g_before["adv"] + 100 * g_before["geo"]).item(), rel=1e-6)
    g_before["total"].backward()
    assert _grads_ok(gen)
    opt_g.step()
    g_after = generator_step_losses(gen, disc, schedule, x0, cond, lengths, mean, std, generator_rng=_gen(22))
    assert g_after["total"].item() < g_before["total"].item()
