"""T2M evaluator networks, losses and embedding calls (models/evaluator.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from tolerance import float32_atol
from torch import nn

from data.vocab import NUM_POS, OTHER
from models.evaluator import (
    EvaluatorConfig,
    MotionEncoderBiGRUCo,
    MovementConvDecoder,
    MovementConvEncoder,
    T2MEvaluator,
    TextEncoderBiGRUCo,
    contrastive_loss,
    contrastive_terms,
    movement_ae_loss,
)

D = 16  # 12 motion dims + 4 contacts
SMALL = dict(word_dim=16, text_hidden=16, movement_hidden=16, movement_dim=16, motion_hidden=16, output_dim=8)


pytestmark = pytest.mark.usefixtures("one_thread")  # tiny networks (tests/conftest.py)


def make_evaluator(vocab_size: int = 20, **overrides: object) -> T2MEvaluator:
    torch.manual_seed(0)
    return T2MEvaluator(EvaluatorConfig(vocab_size=vocab_size, feature_dim=D, **{**SMALL, **overrides})).eval()


def random_text(batch: int, vocab_size: int = 20, length: int = 22, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    sent_lens = torch.randint(2, length + 1, (batch,), generator=g)
    word_ids = torch.randint(0, vocab_size, (batch, length), generator=g)
    classes = torch.randint(0, NUM_POS, (batch, length), generator=g)
    return word_ids, nn.functional.one_hot(classes, NUM_POS).float(), sent_lens


# ---------------------------------------------------------------------------------------------
# losses


def test_contrastive_loss_known_answer() -> None:
    text = torch.tensor([[0.0, 0.0], [3.0, 0.0]])
    motion = torch.tensor([[0.0, 4.0], [3.0, 1.0]])
    # positives: d = 4 and 1 -> (16 + 1) / 2; negatives (shift 1): t0-m1 = sqrt(10), t1-m0 = 5
    pos = 8.5
    neg10 = ((10 - math.sqrt(10)) ** 2 + 5.0**2) / 2
    neg4 = ((4 - math.sqrt(10)) ** 2 + 0.0) / 2  # d = 5 beyond the margin contributes nothing
    assert contrastive_loss(text, motion, margin=10.0, shift=1).item() == pytest.approx(pos + neg10, rel=1e-6)
    assert contrastive_loss(text, motion, margin=4.0, shift=1).item() == pytest.approx(pos + neg4, rel=1e-6)
    assert contrastive_loss(text, motion).item() == pytest.approx(pos + neg10, rel=1e-6)  # B=2: shift must be 1
    terms = contrastive_terms(text, motion, margin=4.0)
    assert terms.shift == 1 and terms.positive.item() == pytest.approx(pos) and terms.negative.item() == (
        pytest.approx(neg4, rel=1e-6)
    )


def test_contrastive_shift_pairs_row_i_with_motion_i_plus_s() -> None:
    text = torch.zeros(3, 1)
    motion = torch.tensor([[1.0], [2.0], [4.0]])
    # shift 1: t_i vs m_{i+1} -> d = 2, 4, 1; margin 5 -> (9 + 1 + 16) / 3
    assert contrastive_terms(text, motion, margin=5.0, shift=1).negative.item() == pytest.approx(26 / 3)
    # shift 2: d = 4, 1, 2 -> same multiset; margin 3 -> (0 + 4 + 1) / 3
    assert contrastive_terms(text, motion, margin=3.0, shift=2).negative.item() == pytest.approx(5 / 3)
    for bad in (0, 3, -1):
        with pytest.raises(ValueError, match="shift"):
            contrastive_loss(text, motion, shift=bad)
    with pytest.raises(ValueError, match="at least 2"):
        contrastive_loss(text[:1], motion[:1])
    g = torch.Generator().manual_seed(0)
    shifts = {contrastive_terms(torch.zeros(5, 2), torch.ones(5, 2), generator=g).shift for _ in range(200)}
    assert shifts == {1, 2, 3, 4}  # never 0 (the reference's quirk), B-1 included


def test_contrastive_gradient_step_reduces_loss() -> None:
    torch.manual_seed(0)
    text = torch.randn(6, 4, requires_grad=True)
    motion = torch.randn(6, 4, requires_grad=True)
    loss = contrastive_loss(text, motion, shift=2)
    loss.backward()
    # d/dt of the positive term mean|t - m|^2 is 2 (t - m) / B; the negative term pushes t away from m_{i+2}
    d_neg = (text - motion.roll(-2, 0)).norm(dim=-1, keepdim=True)
    expected = 2 * (text - motion) / 6 - 2 * (10 - d_neg) * (text - motion.roll(-2, 0)) / d_neg / 6
    torch.testing.assert_close(text.grad, expected.detach())
    with torch.no_grad():
        text -= 0.01 * text.grad
        motion -= 0.01 * motion.grad
        assert contrastive_loss(text, motion, shift=2).item() < loss.item()


def test_movement_ae_loss_known_answer() -> None:
    recon = torch.tensor([[[1.0, 2.0], [3.0, 4.0]]])
    target = torch.tensor([[[0.0, 2.0], [3.0, 6.0]]])  # |diff| = 1, 0, 0, 2 -> 0.75
    z = torch.tensor([[[1.0, -1.0], [3.0, -1.0], [3.0, 1.0]]])  # mean|z| = 10/6; smooth |dz| = (2,0,0,2) -> 1
    expected = 0.75 + 0.001 * 10 / 6 + 0.001 * 1.0
    assert movement_ae_loss(recon, target, z).item() == pytest.approx(expected, rel=1e-6)
    assert movement_ae_loss(recon, target, z, sparsity=0, smoothness=0).item() == pytest.approx(0.75)


# ---------------------------------------------------------------------------------------------
# networks


def test_init_shapes_and_reference_names() -> None:
    ev = make_evaluator()
    for module in ev.modules():
        if isinstance(module, nn.Linear | nn.Conv1d | nn.ConvTranspose1d):
            assert torch.all(module.bias == 0)
    assert ev.text_encoder.hidden.shape == (2, 1, 16) and ev.motion_encoder.hidden.shape == (2, 1, 16)
    names = set(ev.state_dict())
    for key in ("text_encoder.pos_emb.weight", "text_encoder.input_emb.weight", "text_encoder.gru.weight_hh_l0_reverse",
                "text_encoder.output_net.3.weight", "movement_encoder.main.0.weight", "movement_encoder.main.3.weight",
                "movement_encoder.out_net.weight", "motion_encoder.output_net.1.weight", "mean", "std"):
        assert key in names
    # Xavier-normal: std = sqrt(2 / (fan_in + fan_out)) on a big layer
    torch.manual_seed(0)
    big = MovementConvEncoder(300, 400, 400).main[0].weight  # fan_in 1200, fan_out 1600
    assert big.std().item() == pytest.approx(math.sqrt(2 / 2800), rel=0.02)


def test_conv_shapes_and_receptive_field() -> None:
    torch.manual_seed(0)
    enc = MovementConvEncoder(6, 8, 8).eval()
    dec = MovementConvDecoder(8, 8, 10)
    x = torch.randn(2, 24, 6)
    z = enc(x)
    assert z.shape == (2, 6, 8) and dec(z).shape == (2, 24, 10)
    # latent j covers frames 4j-3 .. 4j+6: for a length-16 motion the last latent (j = 3) sees 16..18, not 19+
    base = enc(x)[:, :4]
    for frame, changes in ((18, True), (19, False), (23, False)):
        y = x.clone()
        y[:, frame] += 5.0
        assert (not torch.allclose(enc(y)[:, :4], base)) == changes, frame


def test_text_encoder_ignores_padding_and_follows_permutation() -> None:
    ev = make_evaluator()
    word_ids, pos, sent_lens = random_text(8)
    sent_lens[0], sent_lens[1] = 2, 22
    out = ev.embed_text(word_ids, pos, sent_lens)
    assert out.shape == (8, 8)
    changed_ids, changed_pos = word_ids.clone(), pos.clone()
    for b, n in enumerate(sent_lens.tolist()):
        changed_ids[b, n:] = (changed_ids[b, n:] + 7) % 20
        changed_pos[b, n:] = 0.0
        changed_pos[b, n:, 3] = 1.0
    torch.testing.assert_close(ev.embed_text(changed_ids, changed_pos, sent_lens), out, rtol=0, atol=0)
    # ... but not to the words inside the sentence
    changed_ids[2, 1] = (changed_ids[2, 1] + 1) % 20
    assert not torch.allclose(ev.embed_text(changed_ids, changed_pos, sent_lens)[2], out[2])
    perm = torch.randperm(8, generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(ev.embed_text(word_ids[perm], pos[perm], sent_lens[perm]), out[perm])


def test_embed_motion_ignores_contacts_and_frames_beyond_length() -> None:
    ev = make_evaluator()
    torch.manual_seed(1)
    x = torch.randn(6, 32, D)
    lengths = torch.tensor([32, 4, 17, 20, 28, 9])
    out = ev.embed_motion(x, lengths)
    assert out.shape == (6, 8)
    y = x.clone()
    y[..., -4:] = torch.randn(6, 32, 4) * 10  # contacts
    for b, n in enumerate(lengths.tolist()):
        y[b, n:] = float("nan")  # whatever lies beyond the length, right after it included
    torch.testing.assert_close(ev.embed_motion(y, lengths), out, rtol=0, atol=0)
    # extra padding does not matter once the window exceeds 4 * (length // 4)
    longer = torch.cat([x, torch.randn(6, 8, D)], dim=1)
    out_longer = ev.embed_motion(longer, lengths)
    torch.testing.assert_close(out_longer[1:], out[1:], rtol=1e-5, atol=float32_atol(out))  # tests/tolerance.py
    # ... but a motion filling the whole window (row 0: length 32 = T) sees the conv's own padding instead
    assert not torch.allclose(out_longer[0], out[0], rtol=1e-5, atol=1e-6)
    # a time axis that is not a multiple of 4 is padded: T = 30 equals T = 32 for lengths <= 28
    torch.testing.assert_close(ev.embed_motion(x[:, :30, :], lengths.clamp(max=28))[1:], out[1:])
    # the frames inside the length matter, the last one included (length 17: frame 16 is in the last window)
    z = x.clone()
    z[2, 16, :4] += 1.0
    assert not torch.allclose(ev.embed_motion(z, lengths)[2], out[2])
    with pytest.raises(ValueError, match=">= 4"):
        ev.embed_motion(x, torch.tensor([32, 3, 17, 20, 28, 9]))
    with pytest.raises(ValueError, match=r"\[1, 32\]"):
        ev.embed_motion(x, torch.tensor([33, 4, 17, 20, 28, 9]))
    with pytest.raises(ValueError, match="features"):
        ev.embed_motion(x[..., :-1], lengths)


def test_embed_motion_follows_batch_permutation() -> None:
    ev = make_evaluator()
    torch.manual_seed(2)
    x = torch.randn(7, 24, D)
    lengths = torch.tensor([24, 8, 16, 13, 4, 21, 12])
    out = ev.embed_motion(x, lengths)
    perm = torch.randperm(7, generator=torch.Generator().manual_seed(3))
    torch.testing.assert_close(ev.embed_motion(x[perm], lengths[perm]), out[perm])
    # each row equals the motion embedded alone
    torch.testing.assert_close(ev.embed_motion(x[3:4, :16], lengths[3:4]), out[3:4], rtol=1e-5, atol=float32_atol(out))


def test_normalization_buffers_apply_feat_bias_once() -> None:
    ev = make_evaluator()
    mean = np.arange(D, dtype=np.float32)
    std = np.full(D, 2.0, dtype=np.float32)
    ev.set_normalization(mean, std)
    expected_std = np.full(D, 2.0, dtype=np.float32)
    expected_std[:4] = 0.4
    expected_std[-4:] = 0.4
    np.testing.assert_allclose(ev.std.numpy(), expected_std)
    raw = torch.tensor(mean + 1.0).expand(3, 5, D)
    norm = ev.normalize(raw)
    np.testing.assert_allclose(norm[0, 0].numpy(), 1.0 / expected_std, rtol=1e-6)
    torch.testing.assert_close(ev.denormalize(norm), raw)
    # a generator's normalisation (x * 4 + 1) -> evaluator normalisation
    gen = torch.ones(1, 1, D)
    expected = ev.normalize(torch.full((1, 1, D), 5.0))
    torch.testing.assert_close(ev.renormalize(gen, np.ones(D), np.full(D, 4.0)), expected)
    other = make_evaluator()
    other.load_state_dict(ev.state_dict())
    torch.testing.assert_close(other.std, ev.std)
    torch.testing.assert_close(other.mean, ev.mean)
    with pytest.raises(ValueError, match="positive"):
        ev.set_normalization(mean, np.zeros(D))
    with pytest.raises(ValueError, match="entries"):
        ev.set_normalization(mean[:-1], std[:-1])


def test_word_vectors_initialise_and_freeze() -> None:
    vectors = np.random.default_rng(0).standard_normal((20, 16)).astype(np.float32)
    config = EvaluatorConfig(vocab_size=20, feature_dim=D, **SMALL, freeze_word_vectors=True)
    ev = T2MEvaluator(config, word_vectors=vectors)
    np.testing.assert_array_equal(ev.text_encoder.word_emb.weight.detach().numpy(), vectors)
    assert not ev.text_encoder.word_emb.weight.requires_grad
    word_ids, pos, sent_lens = random_text(4)
    ev.embed_text(word_ids, pos, sent_lens).sum().backward()
    assert ev.text_encoder.word_emb.weight.grad is None and ev.text_encoder.pos_emb.weight.grad is not None
    learned = T2MEvaluator(config.replace(freeze_word_vectors=False), word_vectors=vectors)
    assert learned.text_encoder.word_emb.weight.requires_grad
    with pytest.raises(ValueError, match="shape"):
        T2MEvaluator(config, word_vectors=vectors[:, :8])


def test_freeze_movement_encoder_and_autoencode() -> None:
    ev = make_evaluator()
    decoder = ev.make_movement_decoder()
    x = torch.randn(3, 12, D)
    recon, z = ev.autoencode(x, decoder)
    assert recon.shape == (3, 12, D) and z.shape == (3, 3, 16)
    assert movement_ae_loss(recon, x, z).item() > 0
    ev.freeze_movement_encoder()
    ev.train()
    assert ev.text_encoder.training and not ev.movement_encoder.training
    ev.embed_motion(x, torch.tensor([12, 8, 4])).sum().backward()
    assert all(p.grad is None for p in ev.movement_encoder.parameters())
    assert ev.motion_encoder.input_emb.weight.grad is not None
    with pytest.raises(ValueError, match="multiple of 4"):
        ev.autoencode(x[:, :10], decoder)


def test_config_profiles_and_round_trip() -> None:
    paper = EvaluatorConfig.for_profile("paper", vocab_size=4199)
    assert (paper.word_dim, paper.text_hidden, paper.movement_dim, paper.motion_hidden, paper.output_dim) == (
        300, 512, 512, 1024, 512,
    )
    smoke = EvaluatorConfig.for_profile("smoke", vocab_size=50, feature_dim=263, output_dim=16)
    assert smoke.output_dim == 16 and smoke.word_dim == 32
    assert EvaluatorConfig.from_dict(smoke.to_dict()) == smoke
    with pytest.raises(ValueError, match="profile"):
        EvaluatorConfig.for_profile("huge", vocab_size=5)
    with pytest.raises(ValueError, match="positive integer"):
        EvaluatorConfig(vocab_size=0)
    with pytest.raises(ValueError, match="unknown"):
        EvaluatorConfig.from_dict({"vocab_size": 3, "bogus": 1})


def test_standalone_modules_reject_bad_lengths() -> None:
    torch.manual_seed(0)
    text = TextEncoderBiGRUCo(10, 8, 8, 4)
    word_ids = torch.zeros(2, 5, dtype=torch.int64)
    pos = torch.zeros(2, 5, NUM_POS)
    pos[..., OTHER] = 1
    assert text(word_ids, pos, torch.tensor([5, 2])).shape == (2, 4)
    with pytest.raises(ValueError, match="sent_lens"):
        text(word_ids, pos, torch.tensor([6, 2]))
    motion = MotionEncoderBiGRUCo(8, 8, 4)
    with pytest.raises(ValueError, match="m_lens"):
        motion(torch.zeros(2, 3, 8), torch.tensor([0, 2]))


@pytest.mark.slow
def test_tiny_overfit_reaches_perfect_r_at_1() -> None:
    """16 random (caption, motion) pairs; joint training makes every caption retrieve its motion."""
    torch.manual_seed(0)
    dims = dict(word_dim=16, text_hidden=32, movement_hidden=16, movement_dim=16, motion_hidden=32, output_dim=16)
    ev = T2MEvaluator(EvaluatorConfig(vocab_size=30, feature_dim=D, dropout=0.0, **dims))
    g = torch.Generator().manual_seed(5)
    sent_lens = torch.randint(4, 13, (16,), generator=g)
    word_ids = torch.randint(3, 30, (16, 12), generator=g)
    pos = nn.functional.one_hot(torch.randint(0, NUM_POS, (16, 12), generator=g), NUM_POS).float()
    motions = torch.randn(16, 24, D, generator=g)
    lengths = torch.randint(8, 25, (16,), generator=g)
    opt = torch.optim.Adam(ev.parameters(), lr=1e-2)

    def r_at_1() -> float:
        ev.eval()
        with torch.no_grad():
            t, m = ev(word_ids, pos, sent_lens, motions, lengths)
        ev.train()
        return (torch.cdist(t, m).argmin(dim=1) == torch.arange(16)).float().mean().item()

    before = r_at_1()
    for _ in range(100):
        t, m = ev(word_ids, pos, sent_lens, motions, lengths)
        loss = contrastive_loss(t, m, generator=g)
        opt.zero_grad()
        loss.backward()
        nn.utils.clip_grad_norm_(ev.parameters(), 0.5)  # reference B.3b
        opt.step()
    assert before < 0.5
    assert r_at_1() == 1.0
