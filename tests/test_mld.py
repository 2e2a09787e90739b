"""Tests for models/transformer.py (skip transformer, embeddings, ControlNet hook) and models/mld.py."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from tolerance import float32_atol

from models.diffusion import NoiseSchedule, ddim_sample, sample_timesteps
from models.mld import MLDConfig, MLDDenoiser, drop_text, latent_std, mld_loss, sample_mld
from models.transformer import SkipTransformer, lengths_to_mask, sinusoidal_positions, timestep_embedding
from models.vae import MotionVAE

E = 16  # text dims
L, C = 2, 8  # latent tokens x channels
D = 263


pytestmark = pytest.mark.usefixtures("one_thread")  # tiny networks (tests/conftest.py)


@pytest.fixture(scope="module")
def schedule() -> NoiseSchedule:
    return NoiseSchedule.from_name("scaled_linear", 1000)


def _gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _denoiser(**overrides: object) -> MLDDenoiser:
    torch.manual_seed(0)
    cfg = {
        "latent_tokens": L, "latent_dim": C, "hidden_dim": 16, "text_dim": E, "layers": 3, "heads": 2,
        "ff_dim": 32, "dropout": 0.0, "time_freq_dim": 16,
    }
    return MLDDenoiser({**cfg, **overrides})


def _vae() -> MotionVAE:
    torch.manual_seed(1)
    return MotionVAE({"latent_tokens": L, "latent_dim": C, "hidden_dim": 16, "layers": 3, "heads": 2, "ff_dim": 32})


# --------------------------------------------------------------------------------------------------
# Embeddings, masks, skip transformer
# --------------------------------------------------------------------------------------------------


def test_embeddings_known_values() -> None:
    pe = sinusoidal_positions(3, 4)
    expected = torch.tensor(
        [[0.0, 1.0, 0.0, 1.0], [math.sin(1), math.cos(1), math.sin(0.01), math.cos(0.01)],
         [math.sin(2), math.cos(2), math.sin(0.02), math.cos(0.02)]]
    )
    torch.testing.assert_close(pe, expected)
    # diffusers Timesteps(4, flip_sin_to_cos=True, freq_shift=0): freqs exp(-ln(1e4) i / 2) = [1, 0.01]; [cos, sin]
    emb = timestep_embedding(torch.tensor([0, 3]), 4)
    torch.testing.assert_close(emb[0], torch.tensor([1.0, 1.0, 0.0, 0.0]))
    torch.testing.assert_close(emb[1], torch.tensor([math.cos(3), math.cos(0.03), math.sin(3), math.sin(0.03)]))
    assert lengths_to_mask(torch.tensor([2, 0, 3])).tolist() == [
        [True, True, False], [False, False, False], [True, True, True]
    ]


def test_skip_transformer_structure() -> None:
    with pytest.raises(ValueError):
        SkipTransformer(8, 4, 2, 16)
    net = SkipTransformer(8, 5, 2, 16, dropout=0.0)
    assert len(net.input_blocks) == len(net.output_blocks) == len(net.skip_projections) == 2
    assert net.skip_projections[0].in_features == 16 and net.skip_projections[0].out_features == 8
    x = torch.randn(2, 6, 8)
    out, hidden = net.run(x)
    assert len(hidden) == 5 and all(h.shape == x.shape for h in hidden)
    torch.testing.assert_close(out, net.norm(hidden[-1]))
    with pytest.raises(ValueError):
        net(x, residuals=[None] * 4)


def test_skip_transformer_residual_hook() -> None:
    net = SkipTransformer(8, 5, 2, 16, dropout=0.0).eval()
    x = torch.randn(2, 6, 8, generator=_gen(0))
    base, base_hidden = net.run(x)
    zeros = [torch.zeros(2, 6, 8) for _ in range(5)]
    torch.testing.assert_close(net(x, residuals=zeros), base, atol=0, rtol=0)
    torch.testing.assert_close(net(x, residuals=[None] * 5), base, atol=0, rtol=0)
    for i in range(5):
        res: list[torch.Tensor | None] = [None] * 5
        res[i] = torch.randn(2, 6, 8, generator=_gen(i + 1))
        out, hidden = net.run(x, residuals=res)
        assert not torch.allclose(out, base)
        for j in range(i):  # layers before i are untouched
            torch.testing.assert_close(hidden[j], base_hidden[j], atol=0, rtol=0)
        # layer i's input is untouched, so its hidden state is its usual output plus the residual
        torch.testing.assert_close(hidden[i], base_hidden[i] + res[i])
    # the residual of input block 0 reaches the last output block through the skip (not only the chain)
    net2 = SkipTransformer(8, 3, 2, 16, dropout=0.0).eval()
    x2 = torch.randn(1, 4, 8)
    _, h = net2.run(x2)
    r = torch.randn(1, 4, 8)
    _, h_r = net2.run(x2, residuals=[r, None, None])
    skip_in = net2.skip_projections[0](torch.cat([h_r[1], h_r[0]], dim=-1))
    torch.testing.assert_close(net2.output_blocks[0](skip_in), h_r[2])
    torch.testing.assert_close(h_r[0], h[0] + r)


def test_key_padding_mask_hides_padded_tokens() -> None:
    net = SkipTransformer(8, 3, 2, 16, dropout=0.0).eval()
    x = torch.randn(2, 5, 8)
    pad = ~lengths_to_mask(torch.tensor([5, 3]), 5)
    y = x.clone()
    y[1, 3:] = 50.0
    out = net(x, pad)[1, :3]
    torch.testing.assert_close(net(y, pad)[1, :3], out, atol=float32_atol(out), rtol=0)  # tests/tolerance.py


# --------------------------------------------------------------------------------------------------
# Denoiser
# --------------------------------------------------------------------------------------------------


def test_denoiser_depends_on_text_and_t() -> None:
    net = _denoiser().eval()
    z, text = torch.randn(3, L, C, generator=_gen(0)), torch.randn(3, E, generator=_gen(1))
    t = torch.tensor([10, 500, 999])
    out = net(z, t, text)
    assert out.shape == (3, L, C)
    assert not torch.allclose(out, net(z, t, torch.randn(3, E, generator=_gen(2))), atol=1e-4)
    assert not torch.allclose(out, net(z, torch.tensor([11, 501, 998]), text), atol=1e-4)
    torch.testing.assert_close(net(z[:1], 10, text[:1]), out[:1])  # scalar t broadcasts; batch-independent
    # MLD proper: no latent projections, width = latent_dim, ReLU before the text projection
    mld = MLDDenoiser(MLDConfig(latent_tokens=1, latent_dim=16, text_dim=E, layers=1, ff_dim=8))
    assert mld.config.width == 16 and mld.config.latent_scale == 1.0 and mld.config.prediction_type == "epsilon"
    assert isinstance(mld.latent_in, torch.nn.Identity) and isinstance(mld.text_proj[0], torch.nn.ReLU)
    assert mld(torch.randn(2, 1, 16), torch.tensor([1, 2]), torch.randn(2, E)).shape == (2, 1, 16)


def test_drop_text_and_null_condition() -> None:
    net = _denoiser().eval()
    text = torch.randn(64, E, generator=_gen(0)) + 3.0
    assert torch.equal(net.null_text, torch.zeros(E))
    assert torch.equal(drop_text(text, 0.0, _gen(1))[0], text)
    assert torch.equal(drop_text(text, 1.0, _gen(1))[0], torch.zeros_like(text))
    mask = torch.ones(64, 5, dtype=torch.bool)
    half, half_mask = drop_text(text, 0.5, _gen(1), text_mask=mask)
    dropped = (half == 0).all(-1)
    assert bool(((half == text).all(-1) | dropped).all()) and 10 < int(dropped.sum()) < 54
    expected = torch.rand(64, generator=_gen(1)) < 0.5
    assert torch.equal(dropped, expected)
    assert torch.equal(half_mask, ~expected[:, None].expand(64, 5))  # a dropped caption loses its words
    torch.testing.assert_close(drop_text(text, 0.5, _gen(1))[0], half, atol=0, rtol=0)
    z, t = torch.randn(64, L, C), torch.randint(0, 1000, (64,))
    torch.testing.assert_close(
        net(z, t, drop_text(text, 1.0)[0]), net(z, t, net.null_text_like(text)), atol=0, rtol=0
    )


def test_mld_loss_value(schedule: NoiseSchedule) -> None:
    net = _denoiser().eval()
    z0, text = torch.randn(4, L, C, generator=_gen(0)), torch.randn(4, E, generator=_gen(1))
    out = mld_loss(net, schedule, z0, text, p_uncond=0.5, generator=_gen(7))
    # replay the same draws in the documented order: t, noise, dropout
    g = _gen(7)
    t = sample_timesteps(4, 1000, g)
    noise = torch.randn(z0.shape, generator=g)
    cond, _ = drop_text(text, 0.5, g)
    x_t = schedule.sqrt_alphas_cumprod[t].float()[:, None, None] * z0 + (
        schedule.sqrt_one_minus_alphas_cumprod[t].float()[:, None, None] * noise
    )
    expected = ((net(x_t, t, cond) - noise) ** 2).mean()
    torch.testing.assert_close(out["mse"], expected)
    assert torch.equal(out["total"], out["mse"])


@pytest.mark.slow
def test_mld_loss_decreases_on_tiny_overfit(schedule: NoiseSchedule) -> None:
    g = _gen(0)
    z0, text = torch.randn(8, L, C, generator=g), torch.randn(8, E, generator=g)
    net = _denoiser(hidden_dim=32, ff_dim=64, time_freq_dim=32)

    def held_out() -> float:
        with torch.no_grad():
            return mld_loss(net, schedule, z0.repeat(16, 1, 1), text.repeat(16, 1), 0.0, _gen(123))["mse"].item()

    before = held_out()
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    for _ in range(150):
        loss = mld_loss(net, schedule, z0, text, 0.1, g)["total"]
        opt.zero_grad()
        loss.backward()
        opt.step()
    after = held_out()
    assert after < 0.5 * before, (before, after)


def test_lcm_time_condition_starts_as_the_teacher() -> None:
    teacher = _denoiser().eval()
    student = _denoiser(time_cond_dim=8).eval()
    missing, unexpected = student.load_state_dict(teacher.state_dict(), strict=False)
    assert missing == ["time_embedding.cond_proj.weight"] and unexpected == []
    z, t, text = torch.randn(2, L, C), torch.tensor([5, 700]), torch.randn(2, E)
    w = torch.randn(2, 8)
    torch.testing.assert_close(student(z, t, text, time_cond=w), teacher(z, t, text), atol=0, rtol=0)
    with pytest.raises(ValueError):
        teacher(z, t, text, time_cond=w)


def test_denoiser_controlnet_hook() -> None:
    net = _denoiser().eval()
    z, t, text = torch.randn(2, L, C), torch.tensor([5, 700]), torch.randn(2, E)
    base, hidden = net.run(z, t, text)
    assert len(hidden) == 3 and hidden[0].shape == (2, L + 2, 16)
    torch.testing.assert_close(net(z, t, text, residuals=[torch.zeros_like(h) for h in hidden]), base, atol=0, rtol=0)
    assert not torch.allclose(net(z, t, text, residuals=[None, torch.ones(2, L + 2, 16), None]), base)


# --------------------------------------------------------------------------------------------------
# Latents and sampling
# --------------------------------------------------------------------------------------------------


def test_latent_std() -> None:
    assert latent_std(torch.full((4, 1, 2), 3.0)) == 0.0
    assert latent_std(torch.tensor([[[1.0, -1.0]]])) == pytest.approx(math.sqrt(2.0))


def test_sample_mld_deterministic_shapes_and_padding(schedule: NoiseSchedule) -> None:
    net, vae = _denoiser(dropout=0.1).train(), _vae().train()
    text, lengths = torch.randn(3, E, generator=_gen(0)), torch.tensor([10, 7, 3])
    a = sample_mld(net, vae, schedule, text, lengths, num_steps=5, guidance=7.5, generator=_gen(1))
    b = sample_mld(net, vae, schedule, text, lengths, num_steps=5, guidance=7.5, generator=_gen(1))
    assert a.shape == (3, 10, D) and not a.requires_grad
    torch.testing.assert_close(a, b, atol=0, rtol=0)
    assert net.training and vae.training  # modes restored
    valid = lengths_to_mask(lengths)
    assert bool((a[~valid] == 0).all()) and bool((a[valid].abs().sum(-1) > 0).all())
    c = sample_mld(net, vae, schedule, text, lengths, num_steps=5, guidance=7.5, generator=_gen(2))
    assert not torch.allclose(a, c)


def test_sample_mld_guidance_and_latent_scale(schedule: NoiseSchedule) -> None:
    net, vae = _denoiser().eval(), _vae().eval()
    text, lengths = torch.randn(2, E, generator=_gen(0)), torch.tensor([8, 5])
    x_T = torch.randn(2, L, C, generator=_gen(3))
    # guidance 1 = plain conditional DDIM on MLD's grid, then decode
    z0 = ddim_sample(lambda x, t: net(x, t, text), (2, L, C), schedule, 4, x_T=x_T)
    out = sample_mld(net, vae, schedule, text, lengths, num_steps=4, guidance=1.0, x_T=x_T)
    torch.testing.assert_close(out, vae.decode(z0, lengths))
    # guidance 0 = unconditional (null text)
    uncond = sample_mld(net, vae, schedule, torch.zeros_like(text), lengths, num_steps=4, guidance=1.0, x_T=x_T)
    torch.testing.assert_close(sample_mld(net, vae, schedule, text, lengths, 4, 0.0, x_T=x_T), uncond)
    # guidance 7.5 differs from both
    guided = sample_mld(net, vae, schedule, text, lengths, num_steps=4, guidance=7.5, x_T=x_T)
    assert not torch.allclose(guided, out) and not torch.allclose(guided, uncond)
    # the latent scale multiplies the sampled latent before decoding (config value or argument)
    seen: list[torch.Tensor] = []
    decode = vae.decode_by_length
    vae.decode_by_length = lambda z, lengths, num_frames=None: seen.append(z) or decode(z, lengths, num_frames)  # type: ignore[method-assign]
    sample_mld(net, vae, schedule, text, lengths, num_steps=4, guidance=1.0, x_T=x_T, latent_scale=2.5)
    scaled_net = _denoiser(latent_scale=0.5).eval()
    sample_mld(scaled_net, vae, schedule, text, lengths, num_steps=4, guidance=1.0, x_T=x_T)
    torch.testing.assert_close(seen[0], 2.5 * z0)
    torch.testing.assert_close(seen[1], 0.5 * z0)


# --------------------------------------------------------------------------------------------------
# Word-token conditioning (word_tokens="sequence" | "cross_attention")
# --------------------------------------------------------------------------------------------------


def _words(b: int, n: int, seed: int = 5) -> tuple[torch.Tensor, torch.Tensor]:
    tokens = torch.randn(b, n, 12, generator=_gen(seed))
    mask = torch.arange(n)[None] < torch.tensor([n, n - 2, 1])[:b, None]
    return tokens, mask


@pytest.mark.parametrize("word_tokens", ["sequence", "cross_attention"])
def test_word_tokens_padding_and_order(word_tokens: str) -> None:
    """Padded word tokens change nothing; the order of the real ones does (a pooled mean cannot see it)."""
    net = _denoiser(word_tokens=word_tokens, token_dim=12).eval()
    z, t, text = torch.randn(3, L, C, generator=_gen(0)), torch.tensor([5, 400, 999]), torch.randn(3, E)
    tokens, mask = _words(3, 6)
    base = net(z, t, text, text_tokens=tokens, text_mask=mask)
    garbage = torch.where(mask[..., None], tokens, torch.randn(3, 6, 12, generator=_gen(9)) * 100)
    torch.testing.assert_close(net(z, t, text, text_tokens=garbage, text_mask=mask), base, atol=1e-5, rtol=1e-5)
    longer = torch.cat([tokens, torch.randn(3, 4, 12)], 1), torch.cat([mask, torch.zeros(3, 4, dtype=torch.bool)], 1)
    torch.testing.assert_close(net(z, t, text, text_tokens=longer[0], text_mask=longer[1]), base, atol=1e-5, rtol=1e-5)
    swapped = tokens.clone()
    swapped[0, [0, 1]] = tokens[0, [1, 0]]
    out = net(z, t, text, text_tokens=swapped, text_mask=mask)
    assert not torch.allclose(out[0], base[0]) and torch.equal(out[1:], base[1:])
    _, hidden = net.run(z, t, text, text_tokens=tokens, text_mask=mask)
    assert hidden[0].shape == (3, L + 2 + (6 if word_tokens == "sequence" else 0), 16)
    no_words = net(z, t, text, text_tokens=tokens, text_mask=torch.zeros_like(mask))  # the null caption's case
    assert torch.isfinite(no_words).all() and not torch.allclose(no_words, base)
    with pytest.raises(ValueError, match="text_tokens"):
        net(z, t, text)
    with pytest.raises(ValueError, match="word_tokens"):
        _denoiser(word_tokens="concat")


@pytest.mark.parametrize("word_tokens", ["sequence", "cross_attention"])
def test_word_tokens_null_caption_in_loss_and_sampler(schedule: NoiseSchedule, word_tokens: str) -> None:
    """The unconditional pass is the null embedding with no word tokens, in training and in CFG. The null
    buffer is made non-zero, so a path that used zeros instead of it would fail."""
    net, vae = _denoiser(word_tokens=word_tokens, token_dim=12).eval(), _vae().eval()
    text, lengths = torch.randn(3, E, generator=_gen(0)), torch.tensor([8, 5, 3])
    net.null_text.copy_(torch.randn(E, generator=_gen(9)))
    null_text = net.null_text.clone().expand_as(text)
    tokens, mask = _words(3, 6)
    z0 = torch.randn(3, L, C, generator=_gen(1))
    out = mld_loss(net, schedule, z0, text, 1.0, _gen(7), text_tokens=tokens, text_mask=mask)
    g = _gen(7)
    t = sample_timesteps(3, 1000, g)
    noise = torch.randn(z0.shape, generator=g)
    x_t = schedule.q_sample(z0, t, noise)
    null = net(x_t, t, null_text, text_tokens=tokens, text_mask=torch.zeros_like(mask))
    torch.testing.assert_close(out["mse"], ((null - noise) ** 2).mean())
    x_T = torch.randn(3, L, C, generator=_gen(3))
    kw = {"num_steps": 4, "x_T": x_T, "text_tokens": tokens, "text_mask": mask}
    uncond = ddim_sample(lambda x, t: net(x, t, null_text, text_tokens=tokens,
                                          text_mask=torch.zeros_like(mask)), (3, L, C), schedule, 4, x_T=x_T)
    torch.testing.assert_close(sample_mld(net, vae, schedule, text, lengths, guidance=0.0, **kw),
                               vae.decode(uncond, lengths), atol=1e-5, rtol=1e-5)
    cond = ddim_sample(lambda x, t: net(x, t, text, text_tokens=tokens, text_mask=mask), (3, L, C), schedule, 4,
                       x_T=x_T)
    torch.testing.assert_close(sample_mld(net, vae, schedule, text, lengths, guidance=1.0, **kw),
                               vae.decode(cond, lengths), atol=1e-5, rtol=1e-5)


def test_pad_tokens() -> None:
    import numpy as np

    from data.motion_dataset import pad_tokens

    words = [np.ones((2, 3), np.float16), np.full((4, 3), 2.0, np.float16), np.zeros((0, 3), np.float16)]
    tokens, mask = pad_tokens(words)
    assert tokens.shape == (3, 4, 3) and tokens.dtype == torch.float32
    assert mask.tolist() == [[True, True, False, False], [True] * 4, [False] * 4]
    assert torch.equal(tokens[0, :2], torch.ones(2, 3)) and not tokens[0, 2:].any() and not tokens[2].any()
    assert pad_tokens(words, 6)[0].shape == (3, 6, 3)
    with pytest.raises(ValueError, match="max_tokens=3"):
        pad_tokens(words, 3)


def test_mld_rows_start_their_ddim_grid_at_pure_noise(schedule: NoiseSchedule) -> None:
    """MLD's published leading grid where it starts in the last tenth of the schedule (50 and 10 steps), the
    trailing grid elsewhere: the few-step rows, whose leading grid would start at t = 751, 501 or 1, and
    step counts such as 112, 400 or 600, whose leading grid starts at 889, 799 or 600."""
    from models.diffusion import ddim_timesteps
    from models.generator import TextBatch
    from pipelines.mld_family import MLDGenerator, ddim_spacing

    leading = [100, 111, 50, 10, 200, 333, 999]
    trailing = [112, 150, 300, 400, 501, 600, 9, 4, 2, 1, 1000]
    assert [ddim_spacing(n, 1000) for n in leading + trailing] == ["leading"] * 7 + ["trailing"] * 11
    for n in range(1, 1001):  # every count's grid starts in the last tenth, whichever spacing it gets
        assert ddim_timesteps(1000, n, ddim_spacing(n, 1000))[0] >= 900, n
    net, vae = _denoiser().eval(), _vae().eval()
    seen: list[list[int]] = []
    forward = net.forward
    net.forward = lambda x, t, *a, **k: seen.append(t.tolist()) or forward(x, t, *a, **k)  # type: ignore[method-assign]
    pooled = torch.randn(1, E, generator=_gen(0)).numpy()
    text = TextBatch(texts=["a"], pooled=pooled, tokens=[np.zeros((1, 5), np.float32)])
    for steps, first in ((50, 981), (4, 999), (1, 999)):
        seen.clear()
        MLDGenerator("MLD", net, vae, schedule, steps, 1.0).sample(text, torch.tensor([6]).numpy(), seed=0)
        assert len(seen) == steps and seen[0] == [first]
    assert seen == [[999]]
    seen.clear()
    MLDGenerator("MLD", net, vae, schedule, 1000, 1.0).sample(text, torch.tensor([6]).numpy(), seed=0)
    assert seen[0] == [999] and seen[-1] == [0] and len(seen) == 1000
