"""Tests for models/vae.py: MLD's motion VAE (masks, reparameterisation, losses, a tiny overfit)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from tolerance import float32_atol

from models.vae import (
    LatentDistribution,
    MotionVAE,
    MotionVAEConfig,
    heading_angle,
    kl_to_standard_normal,
    masked_smooth_l1,
    reconstruction_losses,
    vae_loss,
)

FIXTURES = Path(__file__).parent / "fixtures" / "humanml3d"
JOINTS = 22
D = 263


pytestmark = pytest.mark.usefixtures("one_thread")  # tiny networks (tests/conftest.py)


def _gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _tiny(**overrides: object) -> MotionVAE:
    torch.manual_seed(0)
    cfg = {"latent_tokens": 2, "latent_dim": 8, "layers": 3, "heads": 2, "ff_dim": 16, "dropout": 0.1}
    return MotionVAE({**cfg, **overrides})


@pytest.fixture(scope="module")
def stats() -> tuple[torch.Tensor, torch.Tensor]:
    """The real HumanML3D Mean/Std (263,)."""
    return torch.tensor(np.load(FIXTURES / "Mean.npy")), torch.tensor(np.load(FIXTURES / "Std.npy"))


def _smooth_motions(batch: int, frames: int, lengths: torch.Tensor, seed: int = 0) -> torch.Tensor:
    """Random smooth normalised features (B, T, D): 4 random sinusoids per motion on a shared random basis."""
    g = _gen(seed)
    t = torch.arange(frames, dtype=torch.float32)
    freq = torch.rand(batch, 4, 1, generator=g) * 0.3 + 0.05
    phase = torch.rand(batch, 4, 1, generator=g) * 2 * math.pi
    basis = torch.randn(4, D, generator=g) / 2.0
    x = torch.einsum("brt,rd->btd", torch.sin(freq * t + phase), basis)
    return x * (t[None, :, None] < lengths[:, None, None])


# --------------------------------------------------------------------------------------------------
# Shapes, masks and padding invariance
# --------------------------------------------------------------------------------------------------


def test_shapes_and_latent_projection() -> None:
    vae = _tiny(latent_dim=4, hidden_dim=16).eval()
    x, lengths = torch.randn(3, 10, D), torch.tensor([10, 6, 3])
    z, dist = vae.encode(x, lengths, _gen())
    assert z.shape == dist.mu.shape == dist.logvar.shape == (3, 2, 4)
    assert vae.decode(z, lengths).shape == (3, 10, D)
    assert vae.decode(z, lengths, num_frames=14).shape == (3, 14, D)
    assert isinstance(vae.latent_out, torch.nn.Linear) and vae.latent_out.out_features == 4
    assert isinstance(_tiny().latent_out, torch.nn.Identity)  # hidden_dim None: MLD, no projections
    paper = MotionVAEConfig()
    assert (paper.feature_dim, paper.latent_tokens, paper.width, paper.layers, paper.ff_dim) == (263, 1, 256, 9, 1024)
    small = {"latent_dim": 8, "layers": 1, "ff_dim": 8}
    assert MotionVAE(small).config == MotionVAE(MotionVAEConfig(**small)).config == MotionVAEConfig(**small)


@pytest.mark.parametrize(
    "overrides",
    [{}, {"decoder_arch": "self_attention"}, {"pos_encoding": "learned", "max_len": 32}, {"norm_first": True}],
)
def test_padding_does_not_change_valid_outputs(overrides: dict[str, object]) -> None:
    vae = _tiny(**overrides).eval()
    lengths = torch.tensor([12, 7, 4])
    x = torch.randn(3, 12, D, generator=_gen(1))
    valid = torch.arange(12)[None, :] < lengths[:, None]
    x_other = torch.where(valid[..., None], x, 100.0 * torch.randn(3, 12, D, generator=_gen(2)))
    d1, d2 = vae.encode_distribution(x, lengths), vae.encode_distribution(x_other, lengths)
    # padding is masked: equal in exact arithmetic, rounding of other kernels only (tests/tolerance.py)
    torch.testing.assert_close(d1.mu, d2.mu, atol=float32_atol(d1.mu), rtol=0)
    torch.testing.assert_close(d1.logvar, d2.logvar, atol=float32_atol(d1.logvar), rtol=0)
    # extra padding frames (a longer batch) change nothing either
    d3 = vae.encode_distribution(torch.cat([x, torch.randn(3, 5, D)], dim=1), lengths)
    torch.testing.assert_close(d1.mu, d3.mu, atol=float32_atol(d1.mu), rtol=0)

    r1 = vae.decode(vae.encode(x, lengths, _gen(3))[0], lengths)
    r2 = vae.decode(vae.encode(x_other, lengths, _gen(3))[0], lengths)
    torch.testing.assert_close(r1, r2, atol=float32_atol(r1), rtol=0)
    r3 = vae.decode(vae.encode(x, lengths, _gen(3))[0], lengths, num_frames=20)
    torch.testing.assert_close(r1, r3[:, :12], atol=float32_atol(r1), rtol=0)


def test_decode_zeroes_padded_frames() -> None:
    vae = _tiny(dropout=0.0)
    lengths = torch.tensor([9, 5, 1])
    out = vae.decode(torch.randn(3, 2, 8), lengths, num_frames=11)
    valid = torch.arange(11)[None, :] < lengths[:, None]
    assert bool((out[~valid] == 0).all())
    assert bool((out[valid].abs().sum(-1) > 0).all())


@pytest.mark.parametrize("decoder_arch", ["cross_attention", "self_attention"])
def test_decode_by_length_equals_one_padded_batch(decoder_arch: str) -> None:
    """Chunks of similar length (each cut to its longest) decode exactly what one padded batch does."""
    vae = _tiny(decoder_arch=decoder_arch).eval()
    lengths = torch.tensor([30, 4, 17, 9, 30, 1, 22])
    z = torch.randn(7, 2, 8, generator=_gen(4))
    full = vae.decode(z, lengths, num_frames=33)
    chunked = vae.decode_by_length(z, lengths, num_frames=33, chunk_size=3)
    torch.testing.assert_close(chunked, full, atol=1e-5, rtol=0)
    assert bool((chunked[torch.arange(33)[None, :] >= lengths[:, None]] == 0).all())
    assert vae.decode_by_length(z, lengths).shape == (7, 30, D)


def test_reparameterisation_uses_the_generator() -> None:
    vae = _tiny().eval()
    x, lengths = torch.randn(2, 6, D), torch.tensor([6, 4])
    z1, dist = vae.encode(x, lengths, _gen(5))
    z2, _ = vae.encode(x, lengths, _gen(5))
    torch.testing.assert_close(z1, z2, atol=0, rtol=0)
    eps = torch.randn(dist.mu.shape, generator=_gen(5))
    torch.testing.assert_close(z1, dist.mu + torch.exp(0.5 * dist.logvar) * eps)
    z_mean, _ = vae.encode(x, lengths, sample=False)
    torch.testing.assert_close(z_mean, dist.mu, atol=0, rtol=0)


def test_logvar_offset_shifts_log_sigma2_only() -> None:
    """The offset is a constant on log sigma^2 (same weights: mu equal, logvar - 6, sigma x e^-3), no parameter."""
    mld, narrow = _tiny().eval(), _tiny(logvar_offset=-6.0).eval()
    assert sum(p.numel() for p in mld.parameters()) == sum(p.numel() for p in narrow.parameters())
    x, lengths = torch.randn(2, 6, D, generator=_gen(6)), torch.tensor([6, 4])
    d0, d6 = mld.encode_distribution(x, lengths), narrow.encode_distribution(x, lengths)
    torch.testing.assert_close(d6.mu, d0.mu, atol=0, rtol=0)
    torch.testing.assert_close(d6.logvar, d0.logvar - 6.0, atol=1e-6, rtol=0)
    torch.testing.assert_close(d6.std, d0.std * math.exp(-3.0), atol=1e-7, rtol=1e-5)
    assert MotionVAEConfig().logvar_offset == 0.0  # MLD


# --------------------------------------------------------------------------------------------------
# Losses
# --------------------------------------------------------------------------------------------------


def test_kl_known_values() -> None:
    zeros = torch.zeros(2, 1, 4)
    assert float(kl_to_standard_normal(zeros, zeros)) == 0.0
    assert float(LatentDistribution(zeros, zeros).kl()) == 0.0
    # KL(N(mu, s^2) || N(0, 1)) = 0.5 (mu^2 + s^2 - 1 - log s^2) per element, averaged
    mu = torch.tensor([1.0, 0.0, 2.0, 0.0])
    logvar = torch.tensor([0.0, math.log(2.0), 0.0, -1.0])
    per = [0.5, 0.5 * (1.0 - math.log(2.0)), 2.0, 0.5 * (math.exp(-1.0) - 1.0 + 1.0)]
    assert float(kl_to_standard_normal(mu, logvar)) == pytest.approx(sum(per) / 4, rel=1e-6)


def test_masked_smooth_l1_averages_per_sequence() -> None:
    pred = torch.zeros(2, 4, 3)
    target = torch.zeros(2, 4, 3)
    target[0, :2] = 0.5  # smooth-L1 0.125 on sequence 0's 2 valid frames
    target[1, 0] = 3.0  # 2.5 on sequence 1's only valid frame
    target[:, 3] = 100.0  # padding, ignored
    valid = torch.tensor([[True, True, False, False], [True, False, False, False]])
    assert float(masked_smooth_l1(pred, target, valid)) == pytest.approx((0.125 + 2.5) / 2)
    # beta 0.01: |x| - beta / 2 beyond beta (nearly L1): 0.495 and 2.995
    assert float(masked_smooth_l1(pred, target, valid, beta=0.01)) == pytest.approx((0.495 + 2.995) / 2)


def test_joint_term_zero_on_equal_and_positive_differentiable_otherwise(stats: tuple[torch.Tensor, ...]) -> None:
    mean, std = stats
    feats = torch.tensor(np.load(FIXTURES / "new_joint_vecs_012314.npy")[:20])
    target = ((feats - mean) / std)[None].repeat(2, 1, 1)
    lengths = torch.tensor([20, 13])
    same = reconstruction_losses(target.clone(), target, lengths, mean, std, JOINTS)
    assert float(same["joint"]) == 0.0 and float(same["feature"]) == 0.0

    recon = (target + 0.1 * torch.randn(target.shape, generator=_gen(0))).requires_grad_(True)
    terms = reconstruction_losses(recon, target, lengths, mean, std, JOINTS)
    assert terms["joint"].item() > 0 and terms["feature"].item() > 0
    (grad,) = torch.autograd.grad(terms["joint"], recon)
    assert bool(torch.isfinite(grad).all()) and float(grad[:, :, :4].abs().sum()) > 0  # root drives joints
    assert float(grad[1, 13:].abs().sum()) == 0.0  # padded frames get no gradient

    # padded frames of the reconstruction do not count
    recon2 = recon.detach().clone()
    recon2[1, 13:] += 5.0
    terms2 = reconstruction_losses(recon2, target, lengths, mean, std, JOINTS)
    for key in ("feature", "joint"):
        torch.testing.assert_close(terms2[key], terms[key].detach())


def test_root_joint_space_ignores_translation_but_not_facing(stats: tuple[torch.Tensor, ...]) -> None:
    """``joint_space="root"`` compares each frame's joints minus its root joint: a reconstruction that
    only drifts (a constant root-velocity error) costs nothing there but does globally; a wrong
    facing (a root-rotation-velocity error) costs in both."""
    mean, std = stats
    feats = torch.tensor(np.load(FIXTURES / "new_joint_vecs_012314.npy")[:20])
    target = ((feats - mean) / std)[None]
    lengths = torch.tensor([20])
    drift = feats.clone()
    drift[:, 1] += 0.05  # root x-velocity (m/frame, root frame): the whole body translates
    drift = ((drift - mean) / std)[None]
    turn = feats.clone()
    turn[:, 0] += 0.05  # root yaw velocity (rad/frame): the body turns
    turn = ((turn - mean) / std)[None]
    global_drift = reconstruction_losses(drift, target, lengths, mean, std, JOINTS)["joint"]
    root_drift = reconstruction_losses(drift, target, lengths, mean, std, JOINTS, "root")["joint"]
    root_turn = reconstruction_losses(turn, target, lengths, mean, std, JOINTS, "root")["joint"]
    assert float(global_drift) > 1e-3 and float(root_drift) < 1e-10 and float(root_turn) > 1e-4
    with pytest.raises(ValueError, match="joint_space"):
        reconstruction_losses(target, target, lengths, mean, std, JOINTS, "local")


def test_joint_beta_known_answer(stats: tuple[torch.Tensor, ...]) -> None:
    """Every joint 0.10 m higher (root height and RIC heights): only the y third of the channels errs,
    by 0.5 * 0.1^2 = 0.005 with beta 1 (MLD) and by 0.1 - 0.01 / 2 = 0.095 with beta 0.01."""
    mean, std = stats
    feats = torch.tensor(np.load(FIXTURES / "new_joint_vecs_012314.npy")[:20])
    target = ((feats - mean) / std)[None]
    rise = feats.clone()
    rise[:, 3] += 0.10  # root height (m)
    rise[:, 5 : 4 + 3 * (JOINTS - 1) : 3] += 0.10  # the other joints' heights above the floor
    rise = ((rise - mean) / std)[None]
    lengths = torch.tensor([20])
    mse_like = reconstruction_losses(rise, target, lengths, mean, std, JOINTS)["joint"]
    l1_like = reconstruction_losses(rise, target, lengths, mean, std, JOINTS, joint_beta=0.01)["joint"]
    assert float(mse_like) == pytest.approx(0.005 / 3, rel=1e-3)
    assert float(l1_like) == pytest.approx(0.095 / 3, rel=1e-3)
    # vae_loss passes joint_beta through (eval mode: no dropout, so both forwards agree)
    vae = _tiny().eval()
    x = _smooth_motions(1, 8, torch.tensor([8]))
    out = vae_loss(vae, x, torch.tensor([8]), mean, std, JOINTS, joint_beta=0.01, generator=_gen(0))
    recon, _ = vae(x, torch.tensor([8]), _gen(0))
    expected = reconstruction_losses(recon, x, torch.tensor([8]), mean, std, JOINTS, joint_beta=0.01)["joint"]
    torch.testing.assert_close(out["joint"], expected)


def test_heading_angle_is_the_heading_recover_root_rot_pos_turns_by() -> None:
    """h_t = 2 * sum_{k<t} omega_k is the angle of the quaternion (cos a_t, 0, sin a_t, 0) of features.py."""
    from data.features import recover_root_rot_pos

    omega = torch.randn(2, 30, generator=_gen(3)) * 0.05
    feats = torch.zeros(2, 30, D)
    feats[..., 0] = omega
    quat, _ = recover_root_rot_pos(feats)
    h = heading_angle(omega)
    torch.testing.assert_close(torch.cos(h / 2), quat[..., 0])
    torch.testing.assert_close(torch.sin(h / 2), quat[..., 2])
    torch.testing.assert_close(h[:, 0], torch.zeros(2))


def test_heading_term_charges_a_short_turn_on_every_later_frame(stats: tuple[torch.Tensor, ...]) -> None:
    """A turn of 10 frames returned at 0.9 of its angular velocity ends 0.1 of the turn short: the L1 of the
    heading term grows over the turn and holds the full miss on every frame after it; padding adds nothing."""
    mean, std = stats
    frames, turn = 30, math.pi  # a 180 degree turn over frames 5..14
    omega = torch.zeros(frames)
    omega[5:15] = turn / 2 / 10  # h = 2 * cumsum: 10 frames of turn / 20
    target_raw = torch.zeros(1, frames, D) + mean
    target_raw[0, :, 0] = omega
    short_raw = target_raw.clone()
    short_raw[0, :, 0] = 0.9 * omega
    target, short = (target_raw - mean) / std, (short_raw - mean) / std
    h = heading_angle(omega)
    miss = (h - heading_angle(0.9 * omega)).abs()
    assert float(miss[-1]) == pytest.approx(0.1 * turn, rel=1e-5) and float(miss[:6].abs().max()) == 0.0
    got = reconstruction_losses(short, target, torch.tensor([frames]), mean, std, JOINTS)["heading"]
    assert float(got) == pytest.approx(float(miss.mean()), rel=1e-4)
    # padding: the same motion in a longer padded batch with a wrong tail costs the same
    pad = torch.cat([short, torch.randn(1, 10, D, generator=_gen(0))], 1)
    pad_target = torch.cat([target, torch.zeros(1, 10, D)], 1)
    padded = reconstruction_losses(pad, pad_target, torch.tensor([frames]), mean, std, JOINTS)["heading"]
    torch.testing.assert_close(padded, got)


def test_vae_loss_combines_terms(stats: tuple[torch.Tensor, ...]) -> None:
    mean, std = stats
    vae = _tiny()
    lengths = torch.tensor([8, 5])
    x = _smooth_motions(2, 8, lengths)
    torch.manual_seed(5)  # the same dropout draws for both calls
    out = vae_loss(vae, x, lengths, mean.numpy(), std.numpy(), JOINTS, kl_weight=0.1, joint_weight=2.0,
                   generator=_gen(0))
    assert set(out) == {"feature", "joint", "heading", "kl", "total"}
    torch.testing.assert_close(out["total"], out["feature"] + 2.0 * out["joint"] + 0.1 * out["kl"])
    torch.manual_seed(5)
    weighted = vae_loss(vae, x, lengths, mean.numpy(), std.numpy(), JOINTS, kl_weight=0.1, joint_weight=2.0,
                        heading_weight=3.0, generator=_gen(0))
    torch.testing.assert_close(weighted["total"], out["total"] + 3.0 * out["heading"])
    out["total"].backward()
    assert all(p.grad is not None for p in vae.encoder.parameters())
    assert vae.dist_tokens.grad is not None and vae.final_layer.weight.grad is not None


@pytest.mark.slow
def test_tiny_vae_overfits_eight_motions(stats: tuple[torch.Tensor, ...]) -> None:
    mean, std = stats
    lengths = torch.tensor([16, 12, 16, 10, 14, 16, 11, 16])
    x = _smooth_motions(8, 16, lengths)
    vae = _tiny(latent_tokens=2, latent_dim=8, hidden_dim=32, ff_dim=64, dropout=0.0)
    opt = torch.optim.Adam(vae.parameters(), lr=3e-3)
    g = _gen(0)
    losses = []
    for _ in range(120):
        loss = vae_loss(vae, x, lengths, mean, std, JOINTS, generator=g)["total"]
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert np.mean(losses[-5:]) < losses[0] / 5, (losses[0], losses[-5:])


def test_trimmed_batches_give_the_padded_batch_loss(stats: tuple[torch.Tensor, ...]) -> None:
    """collate_trimmed only removes padding: the masked VAE loss is the same on the trimmed batch."""
    from data.motion_dataset import collate_trimmed

    mean, std = stats
    lengths = torch.tensor([9, 5, 12])
    x = _smooth_motions(3, 20, lengths)
    items = [{"motion": x[b], "length": lengths[b], "index": torch.tensor(b)} for b in range(3)]
    batch = collate_trimmed(items)
    assert batch["motion"].shape == (3, 12, D)
    torch.testing.assert_close(batch["motion"], x[:, :12])
    vae = _tiny(dropout=0.0).eval()
    full = vae_loss(vae, x, lengths, mean, std, JOINTS, generator=_gen(1))
    trimmed = vae_loss(vae, batch["motion"], batch["length"], mean, std, JOINTS, generator=_gen(1))
    for key in ("feature", "joint", "kl"):
        torch.testing.assert_close(trimmed[key], full[key], rtol=1e-5, atol=1e-6)
