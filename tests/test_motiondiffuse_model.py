"""Tests for models/motiondiffuse.py: linear attention, masking, zero-init, loss, samplers, fine-grained control."""

from __future__ import annotations

import pytest
import torch
from standin_device import STANDIN, syncs_of
from tolerance import float32_atol
from torch import Tensor

from models.diffusion import NoiseSchedule, ddpm_sample, sample_timesteps
from models.motiondiffuse import (
    PART_MASKS,
    DecoderLayer,
    MotionAttention,
    MotionDiffuse,
    MotionDiffuseConfig,
    StylizationBlock,
    StylizedFFN,
    TextEncoding,
    body_part_model_fn,
    drop_captions,
    guided_denoise,
    guided_text,
    joint_feature_indices,
    linear_attention,
    null_caption,
    part_feature_mask,
    sample_motiondiffuse,
    softmax_attention,
    time_varied_model_fn,
    training_loss,
)

pytestmark = pytest.mark.usefixtures("one_thread")  # tiny networks (tests/conftest.py)

D, E = 263, 8
TINY = {
    "feature_dim": D, "text_dim": E, "width": 16, "layers": 2, "heads": 2, "ff_dim": 32, "text_layers": 1,
    "text_heads": 2, "text_ff_dim": 32, "max_len": 32, "num_train_timesteps": 50,
}


def _gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _model(randomise: bool = True, **overrides: object) -> MotionDiffuse:
    """A tiny model; ``randomise`` perturbs every parameter so the zero-initialised layers act."""
    torch.manual_seed(0)
    model = MotionDiffuse(MotionDiffuseConfig(**{**TINY, **overrides}))
    if randomise:
        with torch.no_grad():
            for p in model.parameters():
                p.add_(0.2 * torch.randn(p.shape, generator=_gen(p.numel())))
    return model.eval()


def _text(b: int = 2, length: int = 5, valid: tuple[int, ...] = (3, 5), seed: int = 1) -> tuple[Tensor, Tensor]:
    states = torch.randn(b, length, E, generator=_gen(seed))
    mask = torch.arange(length)[None] < torch.tensor(valid)[:, None]
    return states, mask


def _qkv(b: int = 2, n: int = 7, m: int = 6, h: int = 2, d: int = 4) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    g = _gen(3)
    q, k, v = (torch.randn(b, s, h, d, generator=g, dtype=torch.float64) for s in (n, m, m))
    key_mask = torch.arange(m)[None] < torch.tensor([4, m])[:, None]
    return q, k, v, key_mask


# --------------------------------------------------------------------------------------------------
# Attention
# --------------------------------------------------------------------------------------------------


def test_linear_attention_equals_hand_computed_and_explicit_matrix_forms() -> None:
    q, k, v, key_mask = _qkv()
    out = linear_attention(q, k, v, key_mask)
    for b in range(q.shape[0]):
        m = int(key_mask[b].sum())  # only the valid keys exist for the hand computation
        qs, ks, vs = q[b].softmax(-1), k[b, :m].softmax(0), v[b, :m]
        context = torch.einsum("mhd,mhe->hde", ks, vs)  # F_g = softmax_seq(K)^T V, (H, d, d)
        torch.testing.assert_close(out[b], torch.einsum("nhd,hde->nhe", qs, context))
        weights = torch.einsum("nhd,mhd->hnm", qs, ks)  # the explicit (N x M) attention matrix
        torch.testing.assert_close(weights.sum(-1), torch.ones(weights.shape[:2], dtype=weights.dtype))
        torch.testing.assert_close(out[b], torch.einsum("hnm,mhe->nhe", weights, vs))


@pytest.mark.parametrize("attention", [linear_attention, softmax_attention])
def test_attention_kernels_ignore_masked_keys(attention: object) -> None:
    q, k, v, key_mask = _qkv()
    k2, v2 = k.clone(), v.clone()
    k2[0, 4:], v2[0, 4:] = 1e4, float("inf")
    out = attention(q, k, v, key_mask)  # type: ignore[operator]
    torch.testing.assert_close(attention(q, k2, v2, key_mask), out, rtol=0, atol=1e-12)  # type: ignore[operator]
    assert torch.isfinite(out).all()


def test_softmax_attention_matches_explicit_masked_softmax() -> None:
    q, k, v, key_mask = _qkv()
    logits = torch.einsum("bnhd,bmhd->bhnm", q, k) / q.shape[-1] ** 0.5
    logits = logits.masked_fill(~key_mask[:, None, None, :], float("-inf"))
    expected = torch.einsum("bhnm,bmhe->bnhe", logits.softmax(-1), v)
    torch.testing.assert_close(softmax_attention(q, k, v, key_mask), expected)


def test_self_attention_block_is_residual_plus_stylised_linear_attention() -> None:
    model = _model()
    block = model.layers[0].self_attn
    x, emb = torch.randn(2, 6, 16, generator=_gen(4)), torch.randn(2, 64, generator=_gen(5))
    mask = torch.arange(6)[None] < torch.tensor([4, 6])[:, None]
    h = torch.nn.functional.layer_norm(x, (16,), block.norm.weight, block.norm.bias)
    q, k, v = (lin(h).unflatten(-1, (2, 8)) for lin in (block.query, block.key, block.value))
    k = k.masked_fill(~mask[:, :, None, None], float("-inf")).softmax(1)
    weights = torch.einsum("bnhd,bmhd->bhnm", q.softmax(-1), k)  # explicit matrix form, masked keys weigh 0
    y = torch.einsum("bhnm,bmhe->bnhe", weights, v * mask[:, :, None, None]).flatten(2)
    with torch.no_grad():
        torch.testing.assert_close(block(x, emb, mask), x + block.style(y, emb), rtol=1e-5, atol=1e-5)


# --------------------------------------------------------------------------------------------------
# Masking and initialisation
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["linear", "softmax"])
def test_attention_block_valid_outputs_ignore_padded_frames(kind: str) -> None:
    torch.manual_seed(0)
    block = MotionAttention(16, 2, 64, kind=kind)  # type: ignore[arg-type]
    with torch.no_grad():
        for p in block.parameters():
            p.add_(0.2 * torch.randn(p.shape))
    x, emb = torch.randn(2, 6, 16, generator=_gen(4)), torch.randn(2, 64, generator=_gen(5))
    mask = torch.arange(6)[None] < torch.tensor([4, 6])[:, None]
    x2 = x.clone()
    x2[0, 4:] = 100.0 * torch.randn(2, 16, generator=_gen(6))
    with torch.no_grad():
        a, b = block(x, emb, mask), block(x2, emb, mask)
    torch.testing.assert_close(a[0, :4], b[0, :4], rtol=0, atol=float32_atol(a))  # tests/tolerance.py
    torch.testing.assert_close(a[1], b[1], rtol=0, atol=0)


@pytest.mark.parametrize(("attention", "kernel", "patch", "overlap"),
                         [("linear", 0, 1, False), ("softmax", 0, 1, False), ("linear", 3, 1, False),
                          ("linear", 3, 4, False), ("linear", 3, 4, True)])
def test_model_ignores_padding_and_amount_of_padding(attention: str, kernel: int, patch: int, overlap: bool) -> None:
    """Lengths 6 and 10 are no multiples of the patch: the token of frames 4-7 is half padding in sample 0."""
    model = _model(attention=attention, temporal_kernel=kernel, patch_frames=patch, overlap_out=overlap)
    ws, wm = _text()
    x, t, lengths = torch.randn(2, 10, D, generator=_gen(7)), torch.tensor([3, 40]), torch.tensor([6, 10])
    x2 = x.clone()
    x2[0, 6:] = float("inf")
    with torch.no_grad():
        out, out2 = model(x, t, ws, wm, lengths), model(x2, t, ws, wm, lengths)
        short = model(x[:1, :6], t[:1], ws[:1], wm[:1], lengths[:1])
    torch.testing.assert_close(out, out2, rtol=0, atol=0)
    assert (out[0, 6:] == 0).all() and out[0, :6].abs().min() > 0
    torch.testing.assert_close(out[:1, :6], short, rtol=1e-4, atol=1e-5)  # same up to matmul-shape rounding


def test_text_padding_is_masked() -> None:
    model = _model()
    ws, wm = _text(valid=(2, 5))
    ws2 = ws.clone()
    ws2[0, 2:] = 50.0 * torch.randn(3, E, generator=_gen(8))
    x, t, lengths = torch.randn(2, 8, D, generator=_gen(7)), torch.tensor([5, 17]), torch.tensor([8, 5])
    with torch.no_grad():
        torch.testing.assert_close(model(x, t, ws2, wm, lengths), model(x, t, ws, wm, lengths), rtol=0, atol=0)
        wm2 = wm.clone()
        wm2[0, 3] = True  # a token that was padding now counts
        assert not torch.equal(model(x, t, ws2, wm2, lengths)[0], model(x, t, ws, wm, lengths)[0])
    with pytest.raises(ValueError, match="no valid token"):
        model(x, t, ws, torch.zeros_like(wm), lengths)


def test_fresh_blocks_are_identities_and_fresh_model_predicts_zero() -> None:
    torch.manual_seed(0)
    x, emb = torch.randn(2, 6, 16), torch.randn(2, 64)
    assert torch.count_nonzero(StylizationBlock(16, 64)(x, emb)) == 0
    layer = DecoderLayer(MotionDiffuseConfig(**TINY))
    mask = torch.ones(2, 6, dtype=torch.bool)
    assert torch.equal(layer(x, emb, mask, torch.randn(2, 3, 16), mask[:, :3]), x)
    model = _model(randomise=False)
    ws, wm = _text()
    out = model(torch.randn(2, 9, D), torch.tensor([0, 49]), ws, wm, torch.tensor([9, 4]))
    assert out.shape == (2, 9, D) and torch.count_nonzero(out) == 0


def test_patches_read_and_write_their_frames_and_a_fresh_patched_model_predicts_zero() -> None:
    """P = 4: the first linear reads frames 4k..4k+3 into token k and the output linear writes them back."""
    fresh = _model(randomise=False, patch_frames=4)
    ws, wm = _text()
    x, t, lengths = torch.randn(2, 10, D, generator=_gen(7)), torch.tensor([3, 40]), torch.tensor([6, 10])
    with torch.no_grad():
        assert torch.count_nonzero(fresh(x, t, ws, wm, lengths)) == 0
    model = _model(patch_frames=4, layers=1)
    assert model.frame_in.in_features == 4 * D and model.frame_out.out_features == 4 * D
    assert model.positions.shape == (8, 16)  # ceil(32 / 4) tokens
    with torch.no_grad():  # the token mixing off: each token's output depends on its own four frames only
        for layer in model.layers:
            for block in (layer.self_attn, layer.cross_attn, layer.ffn):
                block.style.out_layers[-1].weight.zero_()
                block.style.out_layers[-1].bias.zero_()
        base = model(x, t, ws, wm, lengths)
        x2 = x.clone()
        x2[1, 5] += 1.0  # frame 5 belongs to token 1 (frames 4-7)
        changed = (model(x2, t, ws, wm, lengths) - base).abs().sum(-1)[1] > 0
    assert changed.tolist() == [False] * 4 + [True] * 4 + [False] * 2


def test_temporal_kernel_starts_as_the_identity_and_reaches_only_its_neighbours() -> None:
    torch.manual_seed(0)
    x, emb = torch.randn(1, 9, 16), torch.randn(1, 64)
    mask = torch.ones(1, 9, dtype=torch.bool)
    plain, conv = StylizedFFN(16, 32, 64), StylizedFFN(16, 32, 64, kernel=3)
    for p in (*plain.outer.parameters(), *plain.style.out_layers.parameters()):
        torch.nn.init.normal_(p)  # non-zero outputs (the output Linears start at 0)
    conv.load_state_dict(plain.state_dict(), strict=False)  # same Linears; the kernel is the identity
    same = plain(x, emb, mask)
    torch.testing.assert_close(conv(x, emb, mask), same, rtol=0, atol=float32_atol(same))  # layout rounding only
    torch.nn.init.normal_(conv.conv.weight)
    x2 = x.clone()
    x2[0, 4] += 1.0  # a change at frame 4 reaches frames 3..5 only (kernel 3), through the FFN
    changed = (conv(x2, emb, mask) - conv(x, emb, mask)).abs().sum(-1)[0] > 0
    assert changed.tolist() == [False, False, False, True, True, True, False, False, False]
    with pytest.raises(ValueError, match="frame mask"):
        conv(x, emb)


def test_forward_input_validation() -> None:
    model = _model(randomise=False)
    ws, wm = _text()
    with pytest.raises(ValueError, match="max_len"):
        model(torch.randn(2, 33, D), 0, ws, wm, torch.tensor([33, 33]))
    with pytest.raises(ValueError, match="lengths"):
        model(torch.randn(2, 5, D), 0, ws, wm, torch.tensor([0, 5]))
    with pytest.raises(ValueError, match="word_mask"):
        model(torch.randn(2, 5, D), 0, ws, wm[:, :3], torch.tensor([5, 5]))


# --------------------------------------------------------------------------------------------------
# Loss and sampling
# --------------------------------------------------------------------------------------------------


class _Oracle(MotionDiffuse):
    """Predicts the exact noise of a point mass at ``target``: ``eps = (x_t - sqrt(ab) x0) / sqrt(1 - ab)``."""

    def __init__(self, schedule: NoiseSchedule, target: Tensor) -> None:
        super().__init__(MotionDiffuseConfig(**TINY))
        self.schedule, self.target = schedule, target

    def denoise(self, x_t: Tensor, t: Tensor | int, text: TextEncoding, lengths: object) -> Tensor:
        return self.schedule.predict_eps_from_x0(x_t, t, self.target[:, : x_t.shape[1]])


def test_training_loss_of_oracle_is_zero_and_of_zero_model_is_masked_noise_energy() -> None:
    cfg = MotionDiffuseConfig(**TINY)
    schedule = cfg.make_schedule()
    x0, lengths = torch.randn(3, 8, D, generator=_gen(9)), torch.tensor([8, 5, 2])
    ws, wm = _text(b=3, valid=(3, 5, 1))
    oracle = _Oracle(schedule, x0)
    assert float(training_loss(oracle, schedule, x0, lengths, ws, wm, _gen(10))) < 1e-9

    def zero_model(x_t: Tensor, *args: object) -> Tensor:
        return torch.zeros_like(x_t)

    loss = training_loss(zero_model, schedule, x0, lengths, ws, wm, _gen(10))  # type: ignore[arg-type]
    g = _gen(10)
    sample_timesteps(3, schedule.num_steps, g)  # draw order: t, then the noise
    noise = torch.randn(x0.shape, generator=g)
    expected = sum(float(noise[b, : int(n)].square().sum()) for b, n in enumerate(lengths)) / (15 * D)
    assert float(loss) == pytest.approx(expected, rel=1e-5)


def test_training_loss_draws_t_over_every_level_from_its_generator() -> None:
    """t ~ U{0..T-1} is the generator's first draw (T - 1, the noisiest level, included)."""
    schedule = MotionDiffuseConfig(**TINY).make_schedule()
    seen: list[Tensor] = []

    def records_t(x_t: Tensor, t: Tensor, *_: object) -> Tensor:
        seen.append(t.clone())
        return torch.zeros_like(x_t)

    ws, wm = _text(b=2)
    highest = 0
    for seed in range(60):
        training_loss(records_t, schedule, torch.randn(2, 8, D), torch.tensor([8, 5]), ws, wm, _gen(seed))
        expected = torch.randint(0, schedule.num_steps, (2,), generator=_gen(seed))
        assert torch.equal(seen[-1], expected)
        highest = max(highest, int(seen[-1].max()))
    assert highest == schedule.num_steps - 1


def test_training_loss_backpropagates_into_the_network() -> None:
    model = _model(randomise=False).train()
    schedule = model.config.make_schedule()
    ws, wm = _text()
    loss = training_loss(model, schedule, torch.randn(2, 6, D), torch.tensor([6, 3]), ws, wm, _gen(11))
    loss.backward()
    assert float(loss.detach()) > 0 and model.frame_out.weight.grad is not None
    assert model.frame_out.weight.grad.abs().sum() > 0


@pytest.mark.parametrize(("method", "steps"), [("ddpm", None), ("ddim", 5)])
def test_sampling_with_oracle_recovers_point_mass(method: str, steps: int | None) -> None:
    schedule = MotionDiffuseConfig(**TINY).make_schedule()
    target = torch.randn(2, 7, D, generator=_gen(12))
    ws, wm = _text()
    out = sample_motiondiffuse(_Oracle(schedule, target), schedule, torch.tensor([7, 4]), ws, wm,
                               method=method, steps=steps, generator=_gen(13))  # type: ignore[arg-type]
    torch.testing.assert_close(out[0], target[0], rtol=0, atol=1e-4)
    torch.testing.assert_close(out[1, :4], target[1, :4], rtol=0, atol=1e-4)
    assert (out[1, 4:] == 0).all()


def test_sampling_waits_for_the_gpu_a_fixed_number_of_times_whatever_its_steps() -> None:
    """On a GPU (the stand-in counts the host's waits: tests/standin_device.py) the sampler checks the lengths
    once, before the loop, and no step reads anything back: DDIM with twice the steps, and DDPM over twice
    the timesteps, make the host wait as often. Lengths outside [1, N] are still refused."""
    ws, wm = _text()

    def sample(timesteps: int, method: str, steps: int | None) -> None:
        model = _model(input_skip=True, skip_kernel=3, num_train_timesteps=timesteps).to(STANDIN)
        sample_motiondiffuse(model, model.config.make_schedule(), [6, 4], ws, wm, method=method,  # type: ignore[arg-type]
                             steps=steps, guidance=2.5)

    assert syncs_of(lambda: sample(50, "ddim", 2)) == syncs_of(lambda: sample(50, "ddim", 4))
    assert syncs_of(lambda: sample(100, "ddpm", None)) == syncs_of(lambda: sample(200, "ddpm", None))
    schedule = MotionDiffuseConfig(**TINY).make_schedule()
    for lengths in ([6, 0], [6, 9]):
        with pytest.raises(ValueError, match=r"lengths must lie in \[1, 6\]"):
            sample_motiondiffuse(_model(), schedule, lengths, ws, wm, method="ddim", steps=2, num_frames=6)


def test_sampling_arguments_are_validated() -> None:
    model = _model(randomise=False)
    schedule, (ws, wm) = model.config.make_schedule(), _text()
    with pytest.raises(ValueError, match="DDPM runs all"):
        sample_motiondiffuse(model, schedule, [4, 4], ws, wm, method="ddpm", steps=10)
    with pytest.raises(ValueError, match="method"):
        sample_motiondiffuse(model, schedule, [4, 4], ws, wm, method="euler")  # type: ignore[arg-type]


# --------------------------------------------------------------------------------------------------
# Classifier-free guidance (ours, module docstring item 13)
# --------------------------------------------------------------------------------------------------


def test_drop_captions_replaces_the_drawn_rows_by_the_null_caption() -> None:
    ws, wm = _text(b=6, valid=(3, 5, 1, 2, 4, 5))
    assert drop_captions(ws, wm, 0.0, _gen(5)) == (ws, wm)
    null_states, null_mask = null_caption(6, 5, E)
    assert not null_states.any() and null_mask.tolist() == [[True, False, False, False, False]] * 6
    assert all(torch.equal(a, b) for a, b in zip(drop_captions(ws, wm, 1.0, _gen(5)), (null_states, null_mask),
                                                 strict=True))
    states, mask = drop_captions(ws, wm, 0.5, _gen(5))
    dropped = torch.rand(6, generator=_gen(5)) < 0.5
    assert 0 < int(dropped.sum()) < 6  # this seed drops some rows and keeps others
    for b in range(6):
        expected = (null_states[b], null_mask[b]) if dropped[b] else (ws[b], wm[b])
        assert torch.equal(states[b], expected[0]) and torch.equal(mask[b], expected[1])


def test_guided_denoise_combines_the_text_and_null_passes() -> None:
    model = _model()
    ws, wm = _text()
    x, t, lengths = torch.randn(2, 6, D, generator=_gen(6)), torch.tensor([3, 40]), torch.tensor([6, 4])
    with torch.no_grad():
        eps_text = model.denoise(x, t, model.encode_text(ws, wm), lengths)
        eps_null = model.denoise(x, t, model.encode_text(*null_caption(2, 5, E)), lengths)
        assert not torch.allclose(eps_text, eps_null)
        assert torch.equal(guided_denoise(model, x, t, guided_text(model, ws, wm), lengths), eps_text)
        for w in (0.0, 2.5):
            guided = guided_denoise(model, x, t, guided_text(model, ws, wm, w), lengths, w)
            expected = eps_null + w * (eps_text - eps_null)
            torch.testing.assert_close(guided, expected, rtol=0, atol=float32_atol(expected))
        assert not guided[1, 4:].any()  # padded frames stay 0


def test_training_loss_with_every_caption_dropped_is_the_loss_on_the_null_caption() -> None:
    model = _model()
    schedule = model.config.make_schedule()
    x0, lengths = torch.randn(2, 6, D, generator=_gen(9)), torch.tensor([6, 3])
    ws, wm = _text()
    with torch.no_grad():
        dropped = training_loss(model, schedule, x0, lengths, ws, wm, _gen(10), p_uncond=1.0)
        null = training_loss(model, schedule, x0, lengths, *null_caption(2, 5, E), _gen(10))
        text = training_loss(model, schedule, x0, lengths, ws, wm, _gen(10))
    assert float(dropped) == float(null)  # draw order t, eps, then the dropout: the same t and eps
    assert float(text) != float(null)


def test_guided_compositions_with_one_part_or_segment_equal_guided_sampling() -> None:
    model = _model()
    ws, wm = _text()
    lengths = torch.tensor([6, 6])
    plain = sample_motiondiffuse(model, model.config.make_schedule(), lengths, ws, wm, generator=_gen(14),
                                 guidance=3.0)
    assert not torch.allclose(plain, _plain(model, ws, wm, lengths))
    parts = body_part_model_fn(model, [("whole", ws, wm)], lengths, lambda1=0.5, guidance=3.0)
    segments = time_varied_model_fn(model, [(0, 6, ws, wm)], 6, lambda2=0.5, guidance=3.0)
    for fn in (parts, segments):
        assert torch.equal(_composed(model, fn, (2, 6, D), lengths), plain)


# --------------------------------------------------------------------------------------------------
# Body-part control
# --------------------------------------------------------------------------------------------------


def test_part_masks_partition_the_features() -> None:
    upper, lower = PART_MASKS["upper"], PART_MASKS["lower"]
    assert upper.shape == (D,) and upper.dtype == torch.bool
    assert not (upper & lower).any() and (upper | lower).all()
    atoms = ["root", "left_leg", "right_leg", "torso", "left_arm", "right_arm"]
    assert int(sum(PART_MASKS[a].long() for a in atoms).max()) == 1 and PART_MASKS["whole"].all()
    assert not (PART_MASKS["left_arm"] & ~upper).any() and not (PART_MASKS["legs"] & ~lower).any()
    assert lower[0:4].all() and lower[259:263].all()  # root features and foot contacts are lower body
    assert joint_feature_indices(20) == [*range(61, 64), *range(181, 187), *range(253, 256)]  # left wrist
    # the wrist's position and rotation are the arm's; its velocity (global, carries the travel) the root's
    assert PART_MASKS["left_arm"][[*range(61, 64), *range(181, 187)]].all()
    assert not PART_MASKS["left_arm"][253:256].any() and PART_MASKS["root"][253:256].all()
    assert PART_MASKS["root"][193:259].all() and lower[193:259].all() and not upper[193:259].any()
    assert PART_MASKS["left_leg"][[259, 260]].all() and PART_MASKS["right_leg"][[261, 262]].all()
    kit_upper, kit_lower = part_feature_mask("upper", 21), part_feature_mask("lower", 21)
    assert kit_upper.shape == (251,) and not (kit_upper & kit_lower).any() and (kit_upper | kit_lower).all()
    with pytest.raises(ValueError, match="'tail'"):
        part_feature_mask("tail")


def _plain(model: MotionDiffuse, ws: Tensor, wm: Tensor, lengths: Tensor, seed: int = 14) -> Tensor:
    return sample_motiondiffuse(model, model.config.make_schedule(), lengths, ws, wm, generator=_gen(seed))


def _composed(model: MotionDiffuse, fn: object, shape: tuple[int, ...], lengths: Tensor, seed: int = 14) -> Tensor:
    with torch.no_grad():
        x = ddpm_sample(fn, shape, model.config.make_schedule(), _gen(seed))  # type: ignore[arg-type]
    return torch.where(torch.arange(shape[1])[None, :, None] < lengths[:, None, None], x, 0.0)


def test_body_part_one_whole_part_equals_plain_sampling_bit_for_bit() -> None:
    model = _model()
    ws, wm = _text()
    lengths = torch.tensor([6, 4])
    plain = _plain(model, ws, wm, lengths)
    for part in ("whole", torch.ones(D, dtype=torch.bool)):
        fn = body_part_model_fn(model, [(part, ws, wm)], lengths, lambda1=0.5)
        assert torch.equal(_composed(model, fn, (2, 6, D), lengths), plain)


def test_body_part_same_text_on_every_part_equals_plain_sampling() -> None:
    model = _model()
    ws, wm = _text()
    lengths = torch.tensor([6, 6])
    plain = _plain(model, ws, wm, lengths)
    for parts in (["upper", "lower"], ["left_arm", "right_arm", "torso", "rest"]):
        fn = body_part_model_fn(model, [(p, ws, wm) for p in parts], lengths, lambda1=0.5)
        torch.testing.assert_close(_composed(model, fn, (2, 6, D), lengths), plain, rtol=0, atol=float32_atol(plain))


def test_body_part_composition_is_masked_sum_plus_disagreement_gradient() -> None:
    model = _model()
    (ws1, wm1), (ws2, wm2) = _text(seed=1), _text(seed=2)
    x, t, lengths = torch.randn(2, 5, D, generator=_gen(15)), torch.tensor([30, 30]), torch.tensor([5, 3])
    fn = body_part_model_fn(model, [("upper", ws1, wm1), ("lower", ws2, wm2)], lengths, lambda1=0.3)
    xg = x.clone().requires_grad_(True)
    e1, e2 = model(xg, t, ws1, wm1, lengths), model(xg, t, ws2, wm2, lengths)
    (grad,) = torch.autograd.grad((e1 - e2).square().sum(), xg)
    masked = torch.where(PART_MASKS["upper"], e1, e2).detach()
    assert grad.abs().sum() > 0
    with torch.no_grad():
        torch.testing.assert_close(fn(x, t), masked + 0.3 * grad, rtol=1e-5, atol=float32_atol(masked, grad))
        torch.testing.assert_close(body_part_model_fn(model, [("upper", ws1, wm1), ("rest", ws2, wm2)], lengths,
                                                      lambda1=0.0)(x, t), masked, rtol=0, atol=0)


def test_body_part_validation_names_the_culprit() -> None:
    model = _model(randomise=False)
    ws, wm = _text()
    lengths = torch.tensor([4, 4])
    with pytest.raises(ValueError, match="'tail'"):
        body_part_model_fn(model, [("tail", ws, wm), ("rest", ws, wm)], lengths)
    with pytest.raises(ValueError, match="'upper' and 'arms' overlap"):
        body_part_model_fn(model, [("upper", ws, wm), ("arms", ws, wm), ("lower", ws, wm)], lengths)
    with pytest.raises(ValueError, match="uncovered"):
        body_part_model_fn(model, [("upper", ws, wm)], lengths)
    with pytest.raises(ValueError, match="'rest' is empty"):
        body_part_model_fn(model, [("whole", ws, wm), ("rest", ws, wm)], lengths)
    with pytest.raises(ValueError, match="mask #0"):
        body_part_model_fn(model, [(torch.ones(10, dtype=torch.bool), ws, wm)], lengths)


# --------------------------------------------------------------------------------------------------
# Time-varied control
# --------------------------------------------------------------------------------------------------


def test_time_varied_one_full_segment_equals_plain_sampling_bit_for_bit() -> None:
    model = _model()
    ws, wm = _text()
    plain = _plain(model, ws, wm, torch.tensor([7, 7]))
    fn = time_varied_model_fn(model, [(0, 7, ws, wm)], 7, lambda2=0.5)
    assert torch.equal(_composed(model, fn, (2, 7, D), torch.tensor([7, 7])), plain)


def test_time_varied_averages_overlaps_and_adds_overlap_gradient_beyond_max_len() -> None:
    model = _model()
    (ws1, wm1), (ws2, wm2) = _text(seed=1), _text(seed=2)
    n = 40  # longer than max_len = 32: each window fits, the whole does not
    x, t = torch.randn(2, n, D, generator=_gen(16)), torch.tensor([20, 20])
    segments = [(0, 24, ws1, wm1), (16, 40, ws2, wm2)]
    xg = x.clone().requires_grad_(True)
    e1 = model(xg[:, :24], t, ws1, wm1, torch.tensor([24, 24]))
    e2 = model(xg[:, 16:], t, ws2, wm2, torch.tensor([24, 24]))
    (grad,) = torch.autograd.grad((e1[:, 16:] - e2[:, :8]).square().sum(), xg)
    expected = torch.cat([e1[:, :16], (e1[:, 16:] + e2[:, :8]) / 2, e2[:, 8:]], dim=1).detach()
    with torch.no_grad():
        torch.testing.assert_close(time_varied_model_fn(model, segments, n, lambda2=0.0)(x, t), expected)
        torch.testing.assert_close(time_varied_model_fn(model, segments, n, lambda2=0.2)(x, t),
                                   expected + 0.2 * grad, rtol=1e-5, atol=float32_atol(expected, grad))
    assert grad[:, 16:24].abs().sum() > 0


def test_time_varied_validation_names_the_segment() -> None:
    model = _model(randomise=False)
    ws, wm = _text()
    with pytest.raises(ValueError, match=r"segment #1 \[5, 12\) is out of range"):
        time_varied_model_fn(model, [(0, 6, ws, wm), (5, 12, ws, wm)], 10)
    with pytest.raises(ValueError, match=r"segment #0 \[-1, 4\)"):
        time_varied_model_fn(model, [(-1, 4, ws, wm), (4, 10, ws, wm)], 10)
    with pytest.raises(ValueError, match=r"segment #0 \[3, 3\)"):
        time_varied_model_fn(model, [(3, 3, ws, wm), (0, 10, ws, wm)], 10)
    with pytest.raises(ValueError, match="uncovered"):
        time_varied_model_fn(model, [(0, 4, ws, wm), (6, 10, ws, wm)], 10)
    with pytest.raises(ValueError, match="max_len=32"):
        time_varied_model_fn(model, [(0, 40, ws, wm)], 40)


# --------------------------------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("overrides", "field"),
    [
        ({"width": 10, "heads": 4}, "heads"),
        ({"text_heads": 3}, "text_heads"),
        ({"layers": 0}, "layers"),
        ({"text_layers": -1}, "text_layers"),
        ({"dropout": 1.0}, "dropout"),
        ({"attention": "flash"}, "attention"),
        ({"beta_start": 0.03}, "beta_start"),
        ({"num_train_timesteps": 20}, "beta_end"),
        ({"max_len": 0}, "max_len"),
        ({"temporal_kernel": 4}, "temporal_kernel"),
        ({"temporal_kernel": -1}, "temporal_kernel"),
        ({"patch_frames": 0}, "patch_frames"),
        ({"patch_frames": 3, "overlap_out": True}, "overlap_out"),
    ],
)
def test_config_validation_names_the_field(overrides: dict[str, object], field: str) -> None:
    with pytest.raises(ValueError, match=field):
        MotionDiffuseConfig(**overrides)  # type: ignore[arg-type]


def test_config_defaults_schedule_and_dict_construction() -> None:
    cfg = MotionDiffuseConfig()
    assert (cfg.feature_dim, cfg.text_dim, cfg.width, cfg.max_len, cfg.attention) == (263, 384, 128, 196, "linear")
    assert cfg.latent_dim == 128 and cfg.time_embed_dim == 512
    betas = cfg.make_schedule().betas
    assert betas.shape == (1000,) and float(betas[0]) == pytest.approx(1e-4) and float(betas[-1]) == pytest.approx(0.02)
    assert float(MotionDiffuseConfig(num_train_timesteps=50).make_schedule().betas[-1]) == pytest.approx(0.4)
    assert MotionDiffuse(TINY).config == MotionDiffuseConfig(**TINY)
    with pytest.raises(ValueError, match="widht"):
        MotionDiffuse({"widht": 8})


def test_input_skip_adds_a_per_timestep_multiple_of_x_t_starting_at_the_linear_estimate() -> None:
    plain, skipped = _model(randomise=False), _model(randomise=False, input_skip=True)
    schedule = skipped.config.make_schedule()
    torch.testing.assert_close(skipped.skip, (1.0 - schedule.alphas_cumprod).sqrt().float())
    g = _gen(3)
    x, words = torch.randn(2, 7, D, generator=g), torch.randn(2, 4, E, generator=g)
    mask = torch.tensor([[1, 1, 0, 0], [1, 1, 1, 1]]).bool()
    t, lengths = torch.tensor([5, 45]), torch.tensor([7, 3])
    out, base = skipped(x, t, words, mask, lengths), plain(x, t, words, mask, lengths)
    assert torch.equal(base, torch.zeros_like(base))  # zero-initialised output: a fresh model predicts 0
    torch.testing.assert_close(out[0], skipped.skip[5] * x[0])
    torch.testing.assert_close(out[1, :3], skipped.skip[45] * x[1, :3])
    assert torch.equal(out[1, 3:], torch.zeros(4, D))


def test_skip_filter_starts_as_the_scalar_skip_and_reads_beyond_the_ends_as_the_end_frames() -> None:
    scalar, filtered = _model(input_skip=True), _model(input_skip=True, skip_kernel=3)
    assert filtered.skip is None and tuple(filtered.skip_taps.shape) == (50, D, 3)
    g = _gen(4)
    x, (words, mask) = torch.randn(2, 7, D, generator=g), _text()
    t, lengths = torch.tensor([5, 45]), torch.tensor([7, 3])
    with torch.no_grad():  # undo _model's perturbation of the scalar: the same weights elsewhere
        scalar.skip.copy_((1.0 - scalar.config.make_schedule().alphas_cumprod).sqrt())
    # a fresh filter is the scalar skip at the centre tap
    torch.testing.assert_close(filtered(x, t, words, mask, lengths), scalar(x, t, words, mask, lengths))
    # taps (1, 2, 3) at t = 45: frame n reads 1 x[n-1] + 2 x[n] + 3 x[n+1], the ends replicated
    with torch.no_grad():
        filtered.skip_taps[45] = torch.tensor([1.0, 2.0, 3.0])
    encoded = filtered.encode_text(words, mask)
    skip = filtered.skip_filter(x, t, lengths)
    first, last = x[1, 0], x[1, 2]
    torch.testing.assert_close(skip[1, 0], 3 * first + 3 * x[1, 1])
    torch.testing.assert_close(skip[1, 2], x[1, 1] + 5 * last)
    # the output on valid frames does not depend on the padding's values or amount
    longer = torch.cat([x, torch.randn(2, 4, D, generator=g)], 1)
    padded, unpadded = filtered.denoise(longer, t, encoded, lengths)[:, :7], filtered.denoise(x, t, encoded, lengths)
    torch.testing.assert_close(padded, unpadded, atol=float32_atol(unpadded), rtol=0)
    reloaded = MotionDiffuse(filtered.config).eval()
    reloaded.load_state_dict(filtered.state_dict())
    assert torch.equal(reloaded.skip_taps, filtered.skip_taps)


def test_set_skip_taps_is_the_wiener_noise_estimate_that_beats_the_scalar_on_smooth_motion() -> None:
    model = _model(randomise=False, input_skip=True, skip_kernel=5, num_train_timesteps=1000)
    with pytest.raises(RuntimeError, match="no input-skip filter"):
        _model(input_skip=True).set_skip_taps(torch.ones(5, D))
    g = _gen(5)
    # sinusoids of 0.5-3 cycles over 120 frames with random phases: smooth over neighbouring frames
    cycles, phase = 0.5 + 2.5 * torch.rand(D, generator=g), 6.3 * torch.rand(4, 1, D, generator=g)
    motion = 2**0.5 * torch.sin(2 * torch.pi * cycles * torch.arange(120)[:, None] / 120 + phase)
    moments = torch.stack([(motion[:, : 120 - j] * motion[:, j:]).mean((0, 1)) for j in range(5)])
    model.set_skip_taps(moments)
    schedule, lengths = model.config.make_schedule(), torch.full((4,), 120)
    for level in (10, 50, 200):
        t = torch.full((4,), level)
        noise = torch.randn(motion.shape, generator=g)
        x_t = schedule.q_sample(motion, t, noise)
        filtered = ((model.skip_filter(x_t, t, lengths) - noise) ** 2).mean()
        scalar = (((1 - schedule.alphas_cumprod[level]).sqrt().float() * x_t - noise) ** 2).mean()
        assert filtered < 0.6 * scalar, (level, float(filtered), float(scalar))


def test_skip_kernel_must_be_odd_and_needs_the_input_skip() -> None:
    with pytest.raises(ValueError, match="skip_kernel must be an odd"):
        MotionDiffuseConfig(**TINY, input_skip=True, skip_kernel=4)
    with pytest.raises(ValueError, match="needs input_skip"):
        MotionDiffuseConfig(**TINY, skip_kernel=3)
