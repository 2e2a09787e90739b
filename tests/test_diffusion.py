"""Known-answer tests for models/diffusion.py (schedules, forward process, DDPM, DDIM, CFG, LCM, Wiener taps)."""

from __future__ import annotations

import math
from dataclasses import fields

import pytest
import torch
from standin_device import STANDIN, syncs_of

from models import diffusion as D
from models.diffusion import NoiseSchedule

F64 = torch.float64


def _gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _perfect_fn(schedule: NoiseSchedule, x0: torch.Tensor, prediction_type: str = "epsilon"):
    """A network that knows x0: returns the eps / x0 / v consistent with (x_t, x0) at t."""

    def fn(x_t: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        ab = schedule.alphas_cumprod[t].to(x_t.dtype).reshape(-1, *([1] * (x_t.ndim - 1)))
        eps = (x_t - ab.sqrt() * x0) / (1 - ab).sqrt()
        if prediction_type == "epsilon":
            return eps
        if prediction_type == "sample":
            return x0.expand_as(x_t).clone()
        return ab.sqrt() * eps - (1 - ab).sqrt() * x0

    return fn


def _gaussian_eps_fn(schedule: NoiseSchedule, mean: float, std: float):
    """Bayes-optimal eps for data ~ N(mean, std^2 I): sqrt(1-ab) (x_t - sqrt(ab) m) / (ab s^2 + 1 - ab)."""

    def fn(x_t: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        ab = schedule.alphas_cumprod[t].to(x_t.dtype).reshape(-1, *([1] * (x_t.ndim - 1)))
        return (1 - ab).sqrt() * (x_t - ab.sqrt() * mean) / (ab * std**2 + 1 - ab)

    return fn


# ------------------------------------------------------------------------------------------ schedules


def test_linear_schedule_closed_form() -> None:
    s = NoiseSchedule.from_name("linear", 1000)
    assert s.betas[0].item() == pytest.approx(1e-4) and s.betas[-1].item() == pytest.approx(0.02)
    assert s.alphas_cumprod[0].item() == pytest.approx(0.9999, abs=1e-12)
    beta1 = 1e-4 + (0.02 - 1e-4) / 999
    assert s.alphas_cumprod[1].item() == pytest.approx(0.9999 * (1 - beta1), abs=1e-12)
    # prod_{i<1000} (1 - beta_i), computed once with numpy (sum of log1p): 4.0358e-5 (sqrt 0.00635).
    assert s.alphas_cumprod[-1].item() == pytest.approx(4.035829765375687e-05, rel=1e-9)


def test_linear_rescale_to_steps_matches_guided_diffusion() -> None:
    b = D.linear_betas(100, rescale_to_steps=True)
    assert b[0].item() == pytest.approx(1e-3) and b[-1].item() == pytest.approx(0.2)
    assert torch.equal(D.linear_betas(1000, rescale_to_steps=True), D.linear_betas(1000))


def test_scaled_linear_schedule_closed_form() -> None:
    s = NoiseSchedule.from_name("scaled_linear", 1000)
    assert s.betas[0].item() == pytest.approx(0.00085, abs=1e-15)
    assert s.betas[-1].item() == pytest.approx(0.012, abs=1e-15)
    step = s.betas.sqrt().diff()  # linear in sqrt(beta), so beta_500 is not the linear midpoint
    torch.testing.assert_close(step, torch.full_like(step, (0.012**0.5 - 0.00085**0.5) / 999))
    assert s.betas[500].item() == pytest.approx((0.00085**0.5 + 500 / 999 * (0.012**0.5 - 0.00085**0.5)) ** 2)
    assert s.alphas_cumprod[0].item() == pytest.approx(0.99915, abs=1e-12)
    assert s.alphas_cumprod[-1].item() == pytest.approx(0.004660098513077238, rel=1e-9)  # SD/MLD: 0.00466


def test_cosine_schedule_matches_formula() -> None:
    big_t, s0 = 1000, 0.008
    sched = NoiseSchedule.from_name("cosine", big_t)

    def f(t: int) -> float:
        return math.cos((t / big_t + s0) / (1 + s0) * math.pi / 2) ** 2

    for t in (0, 1, 250, 500, 900, 998):
        assert sched.alphas_cumprod[t].item() == pytest.approx(f(t + 1) / f(0), rel=1e-9, abs=1e-15)
    assert sched.betas.max().item() == pytest.approx(0.999)
    assert sched.betas[-1].item() == pytest.approx(0.999)  # the clipped one
    assert bool((sched.betas[:-1] < 0.999).all())


def test_vp_schedule_ddgan_values() -> None:
    s = NoiseSchedule.from_name("vp", 10)
    ab = s.alphas_cumprod
    assert bool((ab[1:] < ab[:-1]).all())
    t1 = 1e-3 + 0.999 / 10  # alpha_bar(u_1)/alpha_bar(u_0), by hand from the VP formula
    assert ab[0].item() == pytest.approx(math.exp(-0.5 * (t1**2 - 1e-6) * 19.9 - (t1 - 1e-3) * 0.1), rel=1e-12)
    assert ab[0].item() == pytest.approx(0.8946889978778536, rel=1e-12)
    # ab_T = exp(-0.5 (1 - 1e-6) 19.9 - 0.0999) = 4.319e-5: almost pure noise after 10 steps.
    assert ab[-1].item() == pytest.approx(4.319049759449644e-05, rel=1e-9)
    # The DDGAN/EMDM table in reference/emdm_motiondiffuse.md (rounded there).
    betas = [0.105, 0.266, 0.399, 0.507, 0.596, 0.669, 0.728, 0.777, 0.817, 0.850]
    coef1 = [1.0, 0.733, 0.534, 0.395, 0.285, 0.193, 0.118, 0.066, 0.033, 0.014]
    coef2 = [0.0, 0.262, 0.440, 0.528, 0.556, 0.545, 0.511, 0.469, 0.427, 0.387]
    logvar = [-2.51, -1.49, -0.97, -0.65, -0.46, -0.34, -0.26, -0.20, -0.16]
    torch.testing.assert_close(s.betas, torch.tensor(betas, dtype=F64), atol=6e-4, rtol=0)
    torch.testing.assert_close(s.posterior_mean_coef1, torch.tensor(coef1, dtype=F64), atol=6e-4, rtol=0)
    torch.testing.assert_close(s.posterior_mean_coef2, torch.tensor(coef2, dtype=F64), atol=6e-4, rtol=0)
    torch.testing.assert_close(s.posterior_log_variance_clipped[1:], torch.tensor(logvar, dtype=F64), atol=6e-3, rtol=0)


def test_schedule_fields_consistent() -> None:
    s = NoiseSchedule.from_name("linear", 50)
    torch.testing.assert_close(s.alphas_cumprod_prev[1:], s.alphas_cumprod[:-1])
    assert s.alphas_cumprod_prev[0].item() == 1.0
    assert s.posterior_variance[0].item() == 0.0
    assert s.posterior_mean_coef1[0].item() == pytest.approx(1.0) and s.posterior_mean_coef2[0].item() == 0.0
    expected = s.betas * (1 - s.alphas_cumprod_prev) / (1 - s.alphas_cumprod)
    torch.testing.assert_close(s.posterior_variance, expected)
    assert s.num_steps == 50
    with pytest.raises(ValueError):
        NoiseSchedule.from_name("quadratic", 10)


# ---------------------------------------------------------------------------------- forward process


def test_q_sample_monte_carlo() -> None:
    s = NoiseSchedule.from_name("linear", 1000)
    n, t = 200_000, 400
    x0 = torch.tensor([1.5, -0.5, 0.0, 2.0], dtype=F64).expand(n, 4)
    xt = s.q_sample(x0, torch.full((n,), t), torch.randn(n, 4, generator=_gen(), dtype=F64))
    ab = s.alphas_cumprod[t]
    torch.testing.assert_close(xt.mean(0), ab.sqrt() * x0[0], atol=0.01, rtol=0)
    torch.testing.assert_close(xt.var(0), (1 - ab).expand(4), atol=0, rtol=0.02)
    mean, var = s.q_mean_variance(x0[:1], t)
    torch.testing.assert_close(mean[0], ab.sqrt() * x0[0])
    assert var.item() == pytest.approx((1 - ab).item())


def test_posterior_marginalises_to_q_and_pairs() -> None:
    """x_t ~ q(x_t|x0), x_{t-1} ~ q(x_{t-1}|x_t,x0)  =>  x_{t-1} ~ q(x_{t-1}|x0); pairs have the q marginals."""
    s = NoiseSchedule.from_name("scaled_linear", 1000)
    g, n, t = _gen(1), 200_000, 300
    x0 = torch.full((n, 2), 0.7, dtype=F64)
    xt = s.q_sample(x0, t, torch.randn(n, 2, generator=g, dtype=F64))
    x_prev = s.q_posterior_sample(x0, xt, t, torch.randn(n, 2, generator=g, dtype=F64))
    ab_prev = s.alphas_cumprod[t - 1]
    assert x_prev.mean().item() == pytest.approx(ab_prev.sqrt().item() * 0.7, abs=0.005)
    assert x_prev.var().item() == pytest.approx((1 - ab_prev).item(), rel=0.02)
    z1, z2 = torch.randn(n, 2, generator=g, dtype=F64), torch.randn(n, 2, generator=g, dtype=F64)
    p_prev, p_t = s.q_sample_pair(x0, t, z1, z2)
    assert p_t.var().item() == pytest.approx((1 - s.alphas_cumprod[t]).item(), rel=0.02)
    assert p_prev.var().item() == pytest.approx((1 - ab_prev).item(), rel=0.02)
    z0, _ = s.q_sample_pair(x0[:3], 0, torch.randn(3, 2, dtype=F64), torch.randn(3, 2, dtype=F64))
    torch.testing.assert_close(z0, x0[:3])
    # at t = 0 the posterior is the point mass at x0
    torch.testing.assert_close(s.q_posterior_sample(x0[:3], xt[:3], 0, torch.randn(3, 2, dtype=F64)), x0[:3])


# --------------------------------------------------------------------------------------- conversions


@pytest.mark.parametrize("name", ["linear", "scaled_linear", "cosine", "vp"])
def test_conversions_round_trip(name: str) -> None:
    s = NoiseSchedule.from_name(name, 10 if name == "vp" else 1000)
    g = _gen(2)
    x0, eps = torch.randn(6, 3, 5, generator=g, dtype=F64), torch.randn(6, 3, 5, generator=g, dtype=F64)
    t = torch.tensor([0, 1, 3, 5, 8, 9]) if name == "vp" else torch.tensor([0, 1, 10, 500, 900, 998])
    xt = s.q_sample(x0, t, eps)
    torch.testing.assert_close(s.predict_x0_from_eps(xt, t, eps), x0)
    torch.testing.assert_close(s.predict_eps_from_x0(xt, t, s.predict_x0_from_eps(xt, t, eps)), eps)
    v = s.v_from(x0, eps, t)
    torch.testing.assert_close(s.predict_x0_from_v(xt, t, v), x0)
    torch.testing.assert_close(s.predict_eps_from_v(xt, t, v), eps)
    for kind, out in (("epsilon", eps), ("sample", x0), ("v_prediction", v)):
        got_x0, got_eps = s.split_prediction(out, xt, t, kind)
        torch.testing.assert_close(got_x0, x0)
        torch.testing.assert_close(got_eps, eps)
        target = s.prediction_target(x0, eps, t, kind)
        torch.testing.assert_close(target, out)


def test_v_hand_value_and_clip() -> None:
    s = NoiseSchedule.from_betas(torch.tensor([0.36]))  # ab = 0.64: sqrt 0.8, sqrt(1-ab) 0.6
    x0, eps = torch.tensor([[1.0]], dtype=F64), torch.tensor([[2.0]], dtype=F64)
    assert s.v_from(x0, eps, 0).item() == pytest.approx(0.8 * 2 - 0.6 * 1)
    xt = s.q_sample(x0, 0, eps)
    assert xt.item() == pytest.approx(0.8 + 1.2)
    x0c, epsc = s.split_prediction(torch.tensor([[-3.0]], dtype=F64), xt, 0, "sample", clip_x0=1.0)
    assert x0c.item() == -1.0 and epsc.item() == pytest.approx((2.0 + 0.8) / 0.6)


# -------------------------------------------------------------------------------------------- DDPM


@pytest.mark.parametrize(("name", "steps", "kind"), [("linear", 1000, "epsilon"), ("vp", 10, "sample"),
                                                     ("scaled_linear", 1000, "v_prediction")])
def test_ddpm_perfect_predictor_recovers_x0(name: str, steps: int, kind: str) -> None:
    s = NoiseSchedule.from_name(name, steps)
    x0 = torch.randn(3, 4, 2, generator=_gen(3), dtype=F64)
    out = D.ddpm_sample(_perfect_fn(s, x0, kind), (3, 4, 2), s, _gen(4), prediction_type=kind, dtype=F64)
    torch.testing.assert_close(out, x0, atol=1e-5, rtol=0)


def test_ddpm_step_noise_and_t0() -> None:
    s = NoiseSchedule.from_name("linear", 100)
    x0, xt, z = torch.zeros(2, 3, dtype=F64), torch.ones(2, 3, dtype=F64), torch.randn(2, 3, dtype=F64)
    t = torch.tensor([0, 50])
    out = D.ddpm_step(s, x0, xt, t, prediction_type="sample", noise=z)
    torch.testing.assert_close(out.prev_sample[0], x0[0])  # t = 0: posterior mean, no noise
    expected = s.posterior_mean_coef2[50] * xt[1] + s.posterior_variance[50].sqrt() * z[1]
    torch.testing.assert_close(out.prev_sample[1], expected)
    g = _gen(5)
    state = g.get_state()
    D.ddpm_step(s, x0, xt, 0, prediction_type="sample", generator=g)
    assert torch.equal(g.get_state(), state)  # nothing drawn when every t is 0


# -------------------------------------------------------------------------------------------- DDIM


def test_ddim_grid_known_answers() -> None:
    assert D.ddim_timesteps(1000, 50, "leading", steps_offset=1).tolist() == list(range(981, 0, -20))
    assert D.ddim_timesteps(1000, 50, "leading", steps_offset=0).tolist() == list(range(980, -1, -20))
    assert D.ddim_timesteps(1000, 50, "trailing").tolist() == list(range(999, 18, -20))
    assert D.ddim_timesteps(1000, 1, "leading", steps_offset=1).tolist() == [1]
    assert D.ddim_timesteps(1000, 4, "leading", steps_offset=1).tolist() == [751, 501, 251, 1]
    assert D.ddim_timesteps(1000, 1, "trailing").tolist() == [999]
    assert D.ddim_timesteps(1000, 3, "trailing").tolist() == [999, 666, 332]
    assert D.ddim_timesteps(1000, 3, "linspace").tolist() == [999, 500, 0]
    with pytest.raises(ValueError):
        D.ddim_timesteps(1000, 1000, "leading", steps_offset=1)  # would reach t = 1000


@pytest.mark.parametrize("num_steps", [1, 2, 7, 50])
@pytest.mark.parametrize("kind", ["epsilon", "sample", "v_prediction"])
def test_ddim_perfect_predictor_recovers_x0(num_steps: int, kind: str) -> None:
    s = NoiseSchedule.from_name("scaled_linear", 1000)
    x0 = torch.randn(2, 3, 4, generator=_gen(6), dtype=F64)
    x_T = torch.randn(2, 3, 4, generator=_gen(7), dtype=F64)
    fn = _perfect_fn(s, x0, kind)
    for spacing in ("leading", "trailing"):
        out = D.ddim_sample(fn, x_T.shape, s, num_steps, 0.0, None, kind, x_T=x_T, timestep_spacing=spacing,
                            set_alpha_to_one=True)
        torch.testing.assert_close(out, x0, atol=1e-5, rtol=0)
    # set_alpha_to_one=False (MLD/diffusers): the last step lands on ab_0, keeping sqrt(1 - ab_0) of eps.
    t_first = int(D.ddim_timesteps(1000, num_steps)[0])
    ab_first = s.alphas_cumprod[t_first]
    e = (x_T - ab_first.sqrt() * x0) / (1 - ab_first).sqrt()
    out = D.ddim_sample(fn, x_T.shape, s, num_steps, 0.0, None, kind, x_T=x_T)
    expected = s.alphas_cumprod[0].sqrt() * x0 + (1 - s.alphas_cumprod[0]).sqrt() * e
    torch.testing.assert_close(out, expected, atol=1e-5, rtol=1e-6)


def test_ddim_float32_perfect_predictor() -> None:
    s = NoiseSchedule.from_name("linear", 1000)
    x0 = torch.randn(4, 8, generator=_gen(8))
    out = D.ddim_sample(_perfect_fn(s, x0), (4, 8), s, 50, generator=_gen(9), set_alpha_to_one=True)
    torch.testing.assert_close(out, x0, atol=1e-5, rtol=0)
    assert out.dtype == torch.float32


def test_ddim_eta0_deterministic_and_draws_nothing() -> None:
    s = NoiseSchedule.from_name("scaled_linear", 1000)
    fn = _gaussian_eps_fn(s, 0.3, 0.5)
    x_T = torch.randn(2, 5, generator=_gen(10))
    g = _gen(11)
    state = g.get_state()
    a = D.ddim_sample(fn, (2, 5), s, 20, 0.0, g, x_T=x_T)
    b = D.ddim_sample(fn, (2, 5), s, 20, 0.0, g, x_T=x_T)
    assert torch.equal(a, b)
    assert torch.equal(g.get_state(), state)
    c = D.ddim_sample(fn, (2, 5), s, 20, 1.0, _gen(1), x_T=x_T)
    d = D.ddim_sample(fn, (2, 5), s, 20, 1.0, _gen(2), x_T=x_T)
    assert not torch.allclose(c, d)


def test_ddim_eta1_on_full_grid_is_ddpm() -> None:
    """DDIM Eq. 16: eta = 1 with t_prev = t - 1 has sigma^2 = posterior variance, i.e. one DDPM step."""
    s = NoiseSchedule.from_name("linear", 1000)
    g = _gen(12)
    xt, eps, z = (torch.randn(3, 4, generator=g, dtype=F64) for _ in range(3))
    t = torch.tensor([1, 400, 999])
    ddim = D.ddim_step(s, eps, xt, t, t - 1, eta=1.0, noise=z).prev_sample
    ddpm = D.ddpm_step(s, eps, xt, t, noise=z).prev_sample
    torch.testing.assert_close(ddim, ddpm)


def test_ddim_gaussian_data_ode_known_answer_and_inversion() -> None:
    """For data N(m, s^2), the probability-flow ODE keeps (x_t - sqrt(ab) m) / sqrt(ab s^2 + 1 - ab) fixed."""
    m, sd = 0.4, 0.6
    s = NoiseSchedule.from_name("scaled_linear", 1000)
    fn = _gaussian_eps_fn(s, m, sd)
    x_T = torch.randn(4, 6, generator=_gen(13), dtype=F64)
    ab_T = s.alphas_cumprod[999]
    expected = m + sd * (x_T - ab_T.sqrt() * m) / (ab_T * sd**2 + 1 - ab_T).sqrt()
    ode_err, inv_err = {}, {}
    for n in (100, 1000):  # DDIM is a first-order ODE solver: errors shrink ~ 1/n
        x0 = D.ddim_sample(fn, x_T.shape, s, n, x_T=x_T, timestep_spacing="trailing", set_alpha_to_one=True)
        ode_err[n] = (x0 - expected).abs().max().item()
        x0 = D.ddim_sample(fn, x_T.shape, s, n, x_T=x_T, timestep_spacing="trailing")
        inv_err[n] = (D.ddim_invert(fn, x0, s, n, timestep_spacing="trailing") - x_T).abs().max().item()
    assert ode_err[1000] < 1e-2 and ode_err[1000] < ode_err[100] / 5  # measured 0.0058 and 0.046
    assert inv_err[1000] < 2e-2 and inv_err[1000] < inv_err[100] / 5  # measured 0.013 and 0.118


def test_ddim_sampler_passes_cond_and_timesteps() -> None:
    s = NoiseSchedule.from_name("linear", 1000)
    seen: list[tuple[list[int], float]] = []

    def fn(x: torch.Tensor, t: torch.Tensor, *, bias: float) -> torch.Tensor:
        seen.append((t.tolist(), bias))
        return torch.zeros_like(x)

    D.ddim_sample(fn, (2, 3), s, 4, generator=_gen(), cond={"bias": 1.5})
    assert seen == [([751, 751], 1.5), ([501, 501], 1.5), ([251, 251], 1.5), ([1, 1], 1.5)]


# ---------------------------------------------------------------------------------------------- CFG


def test_cfg_combine() -> None:
    u, c = torch.tensor([1.0, 2.0]), torch.tensor([3.0, -1.0])
    assert torch.equal(D.cfg_combine(u, c, 1.0), c)
    assert torch.equal(D.cfg_combine(u, c, 0.0), u)
    torch.testing.assert_close(D.cfg_combine(u, c, 7.5), torch.tensor([16.0, -20.5]))


def test_classifier_free_guidance_wrapper() -> None:
    calls: list[int] = []

    def model(x: torch.Tensor, t: torch.Tensor, *, emb: torch.Tensor, texts: list[str], flag: int = 0) -> torch.Tensor:
        calls.append(x.shape[0])
        assert len(texts) == x.shape[0] and t.shape[0] == x.shape[0]
        return x * 2 + emb + t.reshape(-1, 1).to(x.dtype) + flag

    b = 3
    x, t = torch.randn(b, 4, generator=_gen(14)), torch.full((b,), 5)
    emb = torch.randn(b, 4, generator=_gen(15))
    cond = {"emb": emb, "texts": ["a", "b", "c"]}
    null = torch.zeros(1, 4)
    manual = D.cfg_combine(model(x, t, emb=null.expand(b, 4), texts=[""] * b), model(x, t, **cond), 7.5)
    calls.clear()
    guided = D.classifier_free_guidance(model, 7.5, {"emb": null, "texts": [""]})
    torch.testing.assert_close(guided(x, t, **cond), manual)
    assert calls == [2 * b]  # one batched call
    calls.clear()
    two_pass = D.classifier_free_guidance(model, 7.5, {"flag": 10}, batched=False)
    expected = D.cfg_combine(model(x, t, **cond, flag=10), model(x, t, **cond), 7.5)
    torch.testing.assert_close(two_pass(x, t, **cond), expected)
    calls.clear()
    assert torch.equal(D.classifier_free_guidance(model, 1.0, {"emb": null})(x, t, **cond), model(x, t, **cond))
    assert calls == [b, b]
    with pytest.raises(ValueError):
        D.classifier_free_guidance(model, 2.0, {"flag": 10})(x, t, **cond)


# ---------------------------------------------------------------------------------------------- LCM


def test_lcm_boundary_scalings() -> None:
    c_skip, c_out = D.lcm_boundary_scalings(0)
    assert c_skip.item() == 1.0 and c_out.item() == 0.0
    c_skip, c_out = D.lcm_boundary_scalings(torch.tensor([1, 99, 999]))
    assert c_skip[0].item() == pytest.approx(0.25 / 100.25, rel=1e-12)  # 0.0024938
    assert c_out[0].item() == pytest.approx(10 / math.sqrt(100.25), rel=1e-12)  # 0.9987523
    assert c_skip[1].item() == pytest.approx(0.25 / (990**2 + 0.25)) and c_skip[1].item() < 3e-7
    assert c_out[2].item() == pytest.approx(1.0, abs=1e-8)
    assert c_skip.shape == c_out.shape == (3,)
    torch.testing.assert_close(c_skip, 0.25 / (100 * torch.tensor([1.0, 99.0, 999.0], dtype=F64) ** 2 + 0.25))
    c_skip, c_out = D.lcm_boundary_scalings(2, sigma_data=1.0, timestep_scaling=1.0)
    assert c_skip.item() == pytest.approx(0.2) and c_out.item() == pytest.approx(2 / math.sqrt(5))


def test_lcm_solver_grid_and_training_pairs() -> None:
    grid = D.lcm_solver_timesteps(1000, 50)
    assert grid.tolist() == list(range(19, 1000, 20))
    assert D.lcm_solver_timesteps(1000, 10).tolist() == list(range(99, 1000, 100))
    t, t_prev = D.lcm_training_timesteps(4096, 1000, 50, _gen(16))
    assert set(t.tolist()) <= set(grid.tolist()) and len(set(t.tolist())) == 50
    assert torch.equal(t_prev, torch.where(t == 19, torch.zeros_like(t), t - 20))


def test_ddim_solver_step_follows_trajectory() -> None:
    s = NoiseSchedule.from_name("scaled_linear", 1000)
    g = _gen(17)
    x0, eps = torch.randn(3, 2, 8, generator=g, dtype=F64), torch.randn(3, 2, 8, generator=g, dtype=F64)
    t, t_prev = torch.tensor([19, 519, 999]), torch.tensor([0, 499, 979])
    z_prev = D.ddim_solver_step(s, s.q_sample(x0, t, eps), eps, t, t_prev)
    torch.testing.assert_close(z_prev, s.q_sample(x0, t_prev, eps))


def test_lcm_timesteps() -> None:
    assert D.lcm_timesteps(1).tolist() == [999]
    assert D.lcm_timesteps(2).tolist() == [999, 499]
    assert D.lcm_timesteps(4).tolist() == [999, 759, 519, 279]
    assert D.lcm_timesteps(4, rule="linspace").tolist() == [999, 759, 499, 259]
    assert D.lcm_timesteps(2, rule="linspace").tolist() == [999, 499]
    assert D.lcm_timesteps(2, original_steps=10).tolist() == [999, 499]


@pytest.mark.parametrize("num_steps", [1, 2, 4])
def test_lcm_perfect_x0_predictor_returns_x0(num_steps: int) -> None:
    s = NoiseSchedule.from_name("scaled_linear", 1000)
    x0 = torch.randn(2, 16, 32, generator=_gen(18))
    out = D.lcm_multistep_sample(_perfect_fn(s, x0, "sample"), x0.shape, s, num_steps, _gen(19), "sample")
    torch.testing.assert_close(out, x0, atol=1e-6, rtol=1e-6)


@pytest.mark.parametrize("t", [1, 3])
def test_lcm_sampler_applies_c_skip_and_c_out_where_they_matter(t: int) -> None:
    """On the usual grids c_skip < 3e-8 and c_out > 1 - 2e-8, so only small t shows that the sampler
    uses both: eps_hat = 0.5 x gives f = c_skip x + c_out x0_hat, c_skip = 0.25 / ((10 t)^2 + 0.25) and
    c_out = 10 t / sqrt((10 t)^2 + 0.25) (0.0024938 and 0.9987523 at t = 1)."""
    s = NoiseSchedule.from_name("scaled_linear", 1000)
    x_T = torch.randn(2, 3, generator=_gen(22), dtype=F64)
    out = D.lcm_multistep_sample(lambda x, t: 0.5 * x, (2, 3), s, 1, None, "epsilon", x_T=x_T, timesteps=[t])
    ab = s.alphas_cumprod[t]
    x0_hat = (x_T - (1 - ab).sqrt() * 0.5 * x_T) / ab.sqrt()
    denom = (10.0 * t) ** 2 + 0.25
    torch.testing.assert_close(out, 0.25 / denom * x_T + 10.0 * t / denom**0.5 * x0_hat)
    assert (out - x0_hat).abs().max() > 1e-4  # resolvable: plain x0_hat would fail the line above


def test_lcm_multistep_renoises_with_fresh_noise() -> None:
    s = NoiseSchedule.from_name("scaled_linear", 1000)
    seen: list[torch.Tensor] = []

    def fn(x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        seen.append(x.clone())
        return torch.zeros_like(x)  # x0_hat = 0  ->  denoised = c_skip x

    x_T = torch.randn(1, 3, generator=_gen(20), dtype=F64)
    out = D.lcm_multistep_sample(fn, (1, 3), s, 2, _gen(21), "sample", x_T=x_T, timesteps=[699, 299])
    c1, _ = D.lcm_boundary_scalings(699)
    c2, _ = D.lcm_boundary_scalings(299)
    z = torch.randn(1, 3, generator=_gen(21), dtype=F64)  # the one re-noising draw
    x1 = s.alphas_cumprod[299].sqrt() * (c1 * x_T) + (1 - s.alphas_cumprod[299]).sqrt() * z
    torch.testing.assert_close(seen[1], x1)
    torch.testing.assert_close(out, c2 * x1)


def test_wiener_taps_known_answers() -> None:
    alphas = torch.tensor([0.9, 0.5, 0.1], dtype=torch.float64)
    white = torch.tensor([[1.0, 2.0], [0.0, 0.0], [0.0, 0.0]])  # uncorrelated frames, variances 1 and 2
    taps = D.wiener_taps(white, alphas, 3)
    a, s2 = alphas.sqrt(), 1 - alphas
    torch.testing.assert_close(taps[:, 0, 1], a.float())  # unit variance: the scalar skip sqrt(alpha_bar)
    torch.testing.assert_close(taps[:, 1, 1], (2 * a / (2 * alphas + s2)).float())  # variance 2: a m / (a^2 m + s^2)
    assert torch.count_nonzero(taps[:, :, [0, 2]]) == 0
    # a constant signal (every lag moment equal) with k = 3: by symmetry all taps equal, sum = 3 a / (3 a^2 + s^2)
    const = D.wiener_taps(torch.ones(3, 1), alphas, 3)[:, 0]
    torch.testing.assert_close(const, const[:, :1].expand(-1, 3))
    torch.testing.assert_close(const.sum(1), (3 * a / (3 * alphas + s2)).float())
    with pytest.raises(ValueError, match="odd kernel"):
        D.wiener_taps(white, alphas, 2)


def test_wiener_taps_are_the_least_squares_estimate_on_the_data_they_come_from() -> None:
    g = torch.Generator().manual_seed(10)
    smooth = torch.cumsum(torch.randn(4, 400, 3, generator=g), 1) / 10  # random walks: correlated frames
    smooth = smooth - smooth.mean(1, keepdim=True)
    moments = D.lag_moments(list(smooth), 3)
    taps = D.wiener_taps(moments, torch.tensor([0.5], dtype=torch.float64), 3)[0]  # (D, 3)
    noisy = 0.5**0.5 * smooth + 0.5**0.5 * torch.randn(smooth.shape, generator=g)
    windows = torch.nn.functional.pad(noisy, (0, 0, 1, 1)).unfold(1, 3, 1)  # (B, N, D, 3)
    wiener = torch.einsum("bndk,dk->bnd", windows, taps)
    scalar = 0.5**0.5 * noisy
    assert ((wiener - smooth) ** 2).mean() < 0.6 * ((scalar - smooth) ** 2).mean()


def test_lag_moments_known_answer() -> None:
    x = torch.tensor([[1.0], [2.0], [3.0]])
    torch.testing.assert_close(D.lag_moments([x], 3), torch.tensor([[14 / 3], [8 / 2], [3 / 1]]))
    with pytest.raises(ValueError, match="too short"):
        D.lag_moments([x[:1]], 2)


def test_wiener_noise_taps_known_answers() -> None:
    alphas = torch.tensor([0.9, 0.5, 0.1], dtype=F64)
    white = torch.tensor([[1.0, 2.0], [0.0, 0.0], [0.0, 0.0]])
    taps = D.wiener_taps(white, alphas, 3, target="epsilon")
    s, s2 = (1 - alphas).sqrt(), 1 - alphas
    torch.testing.assert_close(taps[:, 0, 1], s.float())  # unit variance: the scalar skip sqrt(1 - alpha_bar)
    torch.testing.assert_close(taps[:, 1, 1], (s / (2 * alphas + s2)).float())  # variance 2: s / (a^2 m + s^2)
    assert torch.count_nonzero(taps[:, :, [0, 2]]) == 0
    # the two estimates add up: x = a x0 + s eps at the centre, so a x0_taps + s eps_taps = e
    smooth = torch.tensor([[1.0], [0.9], [0.7]])
    x0_taps = D.wiener_taps(smooth, alphas, 3)
    eps_taps = D.wiener_taps(smooth, alphas, 3, target="epsilon")
    centre = torch.tensor([0.0, 1.0, 0.0]).expand(3, 1, 3)
    torch.testing.assert_close(alphas.sqrt().float()[:, None, None] * x0_taps + s.float()[:, None, None] * eps_taps,
                               centre)
    with pytest.raises(ValueError, match="target"):
        D.wiener_taps(white, alphas, 3, target="v")


def test_wiener_eig_floor_keeps_the_taps_finite_where_the_moments_are_not_positive_definite() -> None:
    # lag moments 1, 0.999, 0.99 make no valid autocorrelation (the 3 x 3 Toeplitz matrix has a negative
    # eigenvalue): near the data the window's covariance is singular and the raw taps explode
    moments = torch.tensor([[1.0], [0.999], [0.99]])
    lag = (torch.arange(3)[:, None] - torch.arange(3)[None]).abs()
    assert float(torch.linalg.eigvalsh(moments[lag, 0].double()).min()) < 0
    alphas = 1 - torch.logspace(-5, -1, 50, dtype=F64)
    raw = D.wiener_taps(moments, alphas, 3, target="epsilon")
    floored = D.wiener_taps(moments, alphas, 3, target="epsilon", eig_floor=1e-3)
    assert float(raw.abs().max()) > 100
    # floored: the estimate of eps from a window of x never weighs x by more than 1 / sqrt(floor)
    assert float(floored.abs().max()) < 1e-3 ** -0.5
    # a floor below every eigenvalue changes nothing
    valid = torch.tensor([[1.0], [0.5], [0.25]])
    torch.testing.assert_close(D.wiener_taps(valid, alphas, 3, eig_floor=1e-3), D.wiener_taps(valid, alphas, 3))
    with pytest.raises(ValueError, match="eig_floor"):
        D.wiener_taps(moments, alphas, 3, eig_floor=-1.0)


def test_ddpm_fixed_large_variance_is_beta_t() -> None:
    """DDPM's sigma_t^2 = beta_t (fixed_large): with an x0 prediction of 0 and x_t = 1 the step is
    coef2_t x_t + sqrt(beta_t) z."""
    s = NoiseSchedule.from_name("linear", 100)
    x0, xt = torch.zeros(1, 3, dtype=torch.float64), torch.ones(1, 3, dtype=torch.float64)
    z = torch.randn(1, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    out = D.ddpm_step(s, x0, xt, torch.tensor([50]), prediction_type="sample", variance_type="fixed_large", noise=z)
    torch.testing.assert_close(out.prev_sample, s.posterior_mean_coef2[50] * xt + s.betas[50].sqrt() * z)


def test_samplers_wait_for_the_gpu_a_fixed_number_of_times_whatever_their_steps() -> None:
    """On a GPU a step that reads a timestep back to the host, or copies a coefficient onto the device, waits
    for the device's queue to drain. The samplers move their schedule to the device once (its tables) and
    then index it there, so twice the steps make the host wait no more often (the stand-in counts the waits;
    the noise is drawn on the device, with no CPU generator to copy from)."""
    def model(x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        return 0.1 * x + 1e-3 * t[:, None, None]

    schedules = {n: NoiseSchedule.from_name("linear", n) for n in (5, 10)}
    x0 = torch.randn(2, 3, 4)
    runs = {
        "ddpm": lambda n: D.ddpm_sample(model, (2, 3, 4), schedules[5 * n], device=STANDIN),
        "ddim": lambda n: D.ddim_sample(model, (2, 3, 4), schedules[10], 2 * n, eta=0.5, device=STANDIN),
        "lcm": lambda n: D.lcm_multistep_sample(model, (2, 3, 4), schedules[10], 2 * n, original_steps=5,
                                                device=STANDIN),
        "ddim_invert": lambda n: D.ddim_invert(model, x0.to(STANDIN), schedules[10], 2 * n),
    }
    for name, run in runs.items():
        once, twice = syncs_of(lambda run=run: run(1)), syncs_of(lambda run=run: run(2))
        assert once == twice, (name, once, twice)
        assert 0 < sum(once.values()) <= len(fields(NoiseSchedule)), (name, once)  # the 12 tables' copies (+ x0's)
