"""MotionLCM (models/motionlcm.py): the guidance embedding, the student's initialisation, the
consistency boundary, the distillation target and the samplers, on tiny networks with known answers."""

from __future__ import annotations

import math

import pytest
import torch

from models.diffusion import NoiseSchedule, lcm_boundary_scalings, lcm_consistency_fn
from models.mld import MLDConfig, MLDDenoiser
from models.motionlcm import (
    TIMESTEPS,
    distance,
    guidance_embedding,
    lcm_distillation_loss,
    sample_motionlcm,
    student_from_teacher,
)
from pipelines.schedules import EMA

pytestmark = pytest.mark.usefixtures("one_thread")

TINY = MLDConfig(latent_tokens=2, latent_dim=8, hidden_dim=16, text_dim=6, layers=1, heads=2, ff_dim=16,
                 dropout=0.0, time_freq_dim=16, word_tokens="cross_attention", token_dim=5)
SCHEDULE = NoiseSchedule.from_name("scaled_linear", 1000, beta_start=0.00085, beta_end=0.012)


def teacher() -> MLDDenoiser:
    torch.manual_seed(0)
    net = MLDDenoiser(TINY)
    with torch.no_grad():  # a teacher whose output is not ~0 everywhere
        for p in net.parameters():
            p.add_(0.2 * torch.randn_like(p))
    return net.eval()


def inputs(b: int = 3) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(1)
    mask = torch.tensor([[True, True, False], [True, False, False], [True, True, True]])[:b]
    return {"z": torch.randn(b, 2, 8, generator=g), "text": torch.randn(b, 6, generator=g),
            "tokens": torch.randn(b, 3, 5, generator=g), "mask": mask}


def test_guidance_embedding_known_values() -> None:
    w = torch.tensor([0.0, 2.5])
    emb = guidance_embedding(w)
    assert emb.shape == (2, 256)
    torch.testing.assert_close(emb[0, :128], torch.zeros(128))  # sin(0)
    torch.testing.assert_close(emb[0, 128:], torch.ones(128))  # cos(0)
    freq = math.exp(-math.log(10000) * 5 / 127)  # frequency i = 5 of half = 128
    assert emb[1, 5].item() == pytest.approx(math.sin(2500 * freq), abs=1e-4)
    assert emb[1, 128 + 5].item() == pytest.approx(math.cos(2500 * freq), abs=1e-4)
    assert emb[1, 0].item() == pytest.approx(math.sin(2500.0), abs=1e-3)  # frequency 1


def test_student_equals_the_teachers_conditional_output_at_initialisation() -> None:
    net, x = teacher(), inputs()
    student = student_from_teacher(net).eval()
    assert student.time_embedding.cond_proj.weight.abs().sum() == 0
    t = torch.tensor([10, 500, 999])
    for w in (0.0, 3.0, 12.0):
        out = student(x["z"], t, x["text"], text_tokens=x["tokens"], text_mask=x["mask"],
                      time_cond=guidance_embedding(torch.full((3,), w)))
        torch.testing.assert_close(out, net(x["z"], t, x["text"], text_tokens=x["tokens"], text_mask=x["mask"]))


def test_boundary_scalings() -> None:
    c_skip, c_out = lcm_boundary_scalings(torch.tensor([0, 999]))
    assert (c_skip[0].item(), c_out[0].item()) == (1.0, 0.0)
    assert c_skip[1].item() < 1e-6 and c_out[1].item() == pytest.approx(1.0, abs=1e-6)
    z, out = torch.randn(2, 2, 8), torch.randn(2, 2, 8)  # f(z, 0) = z whatever the network says
    torch.testing.assert_close(lcm_consistency_fn(SCHEDULE, out, z, torch.zeros(2, dtype=torch.long)), z)


def test_ema_update_moves_the_target_by_one_minus_mu() -> None:
    a, b = torch.nn.Linear(2, 2), torch.nn.Linear(2, 2)
    ema = EMA(a, 0.95)
    with torch.no_grad():
        a.weight.copy_(b.weight)
    before = ema.module.weight.clone()
    ema.update(a)
    torch.testing.assert_close(ema.module.weight, 0.95 * before + 0.05 * b.weight)
    zero = EMA(a, 0.0)  # mu = 0: the target is the student
    with torch.no_grad():
        a.weight.add_(1.0)
    zero.update(a)
    torch.testing.assert_close(zero.module.weight, a.weight)


class Recorder(torch.nn.Module):
    """Wraps a denoiser and records its calls' timesteps."""

    def __init__(self, net: MLDDenoiser) -> None:
        super().__init__()
        self.net, self.config, self.calls = net, net.config, []

    def null_text_like(self, text: torch.Tensor) -> torch.Tensor:
        return self.net.null_text_like(text)

    def forward(self, z, t, *args, **kw):  # noqa: ANN001, ANN002, ANN003, ANN201
        self.calls.append((t.clone(), z.clone()))
        return self.net(z, t, *args, **kw)


def test_distillation_target_is_the_teacher_ddim_step_through_the_target_network() -> None:
    """Recompute the step's target by hand from the recorded (t, z) pairs; at t_n = 0 the target is z_n."""
    net, x = teacher(), inputs()
    student = student_from_teacher(net)
    target = Recorder(EMA(student, 0.95).module)
    tutor = Recorder(net)
    loss = lcm_distillation_loss(student, target, tutor, SCHEDULE, x["z"], x["text"], w_range=(2.0, 2.0),
                                 num_ddim_steps=10, kind="l2", text_tokens=x["tokens"], text_mask=x["mask"],
                                 generator=torch.Generator().manual_seed(4))
    (t, z_t), _ = tutor.calls  # conditional, then unconditional pass
    (t_prev, z_prev), = target.calls
    assert set(t.tolist()) <= {99 + 100 * i for i in range(10)}
    torch.testing.assert_close(t_prev, (t - 100).clamp(min=0))
    with torch.no_grad():
        eps_c = net(z_t, t, x["text"], text_tokens=x["tokens"], text_mask=x["mask"])
        null_mask = torch.zeros_like(x["mask"])
        eps_u = net(z_t, t, net.null_text_like(x["text"]), text_tokens=x["tokens"], text_mask=null_mask)
        eps = eps_c + 2.0 * (eps_c - eps_u)  # LCM form, w = 2
        ab, ab_prev = SCHEDULE.alphas_cumprod[t][:, None, None], SCHEDULE.alphas_cumprod[t_prev][:, None, None]
        x0 = (z_t - (1 - ab).sqrt() * eps) / ab.sqrt()
        torch.testing.assert_close(z_prev, (ab_prev.sqrt() * x0 + (1 - ab_prev).sqrt() * eps).float())
        w_emb = guidance_embedding(torch.full((3,), 2.0))
        f_t = lcm_consistency_fn(SCHEDULE, target.net(z_prev, t_prev, x["text"], time_cond=w_emb,
                                                       text_tokens=x["tokens"], text_mask=x["mask"]), z_prev, t_prev)
        f_s = lcm_consistency_fn(SCHEDULE, student(z_t, t, x["text"], time_cond=w_emb, text_tokens=x["tokens"],
                                                   text_mask=x["mask"]), z_t, t)
    assert loss["total"].item() == pytest.approx(((f_s - f_t) ** 2).mean().item(), rel=1e-5)
    first = t == 99
    if first.any():  # boundary: c_skip(0) = 1, so the target is z_n itself
        torch.testing.assert_close(f_t[first], z_prev[first])
    loss["total"].backward()
    assert student.time_embedding.linear_1.weight.grad is not None
    assert all(p.grad is None for p in net.parameters())


class Oracle(torch.nn.Module):
    """The exact denoiser of one data point ``x0``, answering in its ``prediction_type``."""

    def __init__(self, x0: torch.Tensor, kind: str) -> None:
        super().__init__()
        self.x0, self.config = x0, MLDConfig(**{**TINY.__dict__, "prediction_type": kind})
        self.steps: list[torch.Tensor] = []

    def null_text_like(self, text: torch.Tensor) -> torch.Tensor:
        return torch.zeros_like(text)

    def forward(self, z: torch.Tensor, t: torch.Tensor, text: torch.Tensor, **_: object) -> torch.Tensor:
        self.steps.append(t)
        ab = SCHEDULE.alphas_cumprod[t].float()[:, None, None]
        eps = (z - ab.sqrt() * self.x0) / (1 - ab).sqrt()
        kind = self.config.prediction_type
        return {"epsilon": eps, "sample": self.x0, "v_prediction": ab.sqrt() * eps - (1 - ab).sqrt() * self.x0}[kind]


@pytest.mark.parametrize("kind", ["epsilon", "sample", "v_prediction"])
def test_distillation_reads_each_network_in_its_prediction_type(kind: str) -> None:
    """With an exact teacher, student and target of one point, the consistency outputs are that point (but at
    the boundary t_n = 0, where the target is z_n itself), whatever the parameterisation. Read as epsilon,
    a sample-predicting oracle's student output was far from the data while its loss stayed near 0."""
    x0 = torch.randn(16, 2, 8, generator=torch.Generator().manual_seed(0))
    oracle = Oracle(x0, kind)
    seen = []

    def spy(*args: object, **kwargs: object) -> torch.Tensor:
        seen.append(lcm_consistency_fn(*args, **kwargs))
        return seen[-1]

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr("models.motionlcm.lcm_consistency_fn", spy)
        loss = lcm_distillation_loss(oracle, oracle, oracle, SCHEDULE, x0, torch.zeros(16, 6), w_range=(1.5, 4.5),
                                     num_ddim_steps=10, kind="l2", generator=torch.Generator().manual_seed(1))
    f_student, f_target = seen
    inner = oracle.steps[-1] > 0  # the target network's call: t_n
    assert inner.sum() >= 8
    torch.testing.assert_close(f_student, x0, atol=1e-4, rtol=0)
    torch.testing.assert_close(f_target[inner], x0[inner], atol=1e-4, rtol=0)
    assert loss["total"].item() == pytest.approx(((f_student - f_target) ** 2).mean().item(), rel=1e-5)
    assert loss["total"].item() < 1e-3


def test_distance_known_values() -> None:
    a, b = torch.zeros(4), torch.tensor([0.0, 1.2, -1.2, 0.0])
    assert distance(a, b, "huber", 0.5).item() == pytest.approx((2 * (1.3 - 0.5)) / 4)
    assert distance(a, b, "l2").item() == pytest.approx(2 * 1.44 / 4)
    with pytest.raises(ValueError, match="unknown consistency distance"):
        distance(a, b, "l1")


class Affine(torch.nn.Module):
    """A known 'student': eps_hat = 0.5 z, ignoring everything else."""

    def __init__(self) -> None:
        super().__init__()
        self.config = MLDConfig(latent_tokens=2, latent_dim=8, word_tokens="none", latent_scale=2.0)

    def forward(self, z, t, text_emb, **kw):  # noqa: ANN001, ANN003, ANN201
        return 0.5 * z


class Identity(torch.nn.Module):
    def decode_by_length(self, z, lengths):  # noqa: ANN001, ANN201
        return z


def test_one_step_sampler_is_c_out_x0_plus_c_skip_z() -> None:
    g = torch.Generator().manual_seed(7)
    z_T = torch.randn(3, 2, 8, generator=torch.Generator().manual_seed(7))
    out = sample_motionlcm(Affine(), Identity(), SCHEDULE, torch.zeros(3, 6), [10, 10, 10], 1, 2.5, g)
    t = TIMESTEPS[1][0]
    ab = SCHEDULE.alphas_cumprod[t]
    x0 = (z_T - (1 - ab).sqrt() * 0.5 * z_T) / ab.sqrt()
    c_skip, c_out = lcm_boundary_scalings(torch.tensor(t))
    torch.testing.assert_close(out, (2.0 * (c_out * x0 + c_skip * z_T)).float())  # decoded at latent_scale 2
    with pytest.raises(ValueError, match="samples with"):
        sample_motionlcm(Affine(), Identity(), SCHEDULE, torch.zeros(3, 6), [10] * 3, 3, 2.5, g)


def test_multistep_sampler_makes_one_pass_per_listed_timestep() -> None:
    rec = Recorder(student_from_teacher(teacher()))
    x = inputs()
    vae = Identity()
    for steps in (1, 2, 4):
        rec.calls.clear()
        sample_motionlcm(rec, vae, SCHEDULE, x["text"], [5] * 3, steps, 2.5, torch.Generator().manual_seed(0),
                         text_tokens=x["tokens"], text_mask=x["mask"])
        assert [int(t[0]) for t, _ in rec.calls] == list(TIMESTEPS[steps])
