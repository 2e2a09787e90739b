"""Seeded generators and the networks' device: every random draw of a loss or sampler happens on the
generator's device and is then moved to the tensors' device (``models.rng``).

CUDA refuses to draw a CUDA tensor from a CPU generator, and a CPU generator is what the evaluation seeds
(the same numbers on any machine). No GPU is needed to hold the code to that rule: a generator here
claims to live on another device than the tensors (``Elsewhere``), and torch's draws are wrapped to refuse
any draw asked for on a device other than its generator's, as CUDA does, before drawing on the CPU.
Before the fix the distillation, ControlNet, VAE and DDPM/DDIM noise draws asked the generator for
tensors on the networks' device."""

from __future__ import annotations

from collections.abc import Callable

import pytest
import torch
import torch.utils._pytree as pytree
from test_controlnet import D, control_config, randomise, student, tiny_vae
from test_controlnet import batch as control_batch
from test_emdm_model import _nets as emdm_nets
from test_motiondiffuse_model import _model as motiondiffuse_model
from test_motiondiffuse_model import _text as motiondiffuse_text
from test_motionlcm import teacher as mld_teacher

from data.control import training_mask
from models.controlnet import MotionControlNet, controlnet_loss
from models.diffusion import NoiseSchedule, ddim_sample, ddpm_sample, lcm_training_timesteps
from models.emdm import EMDMSchedule, discriminator_step_losses, generator_step_losses
from models.evaluator import contrastive_loss
from models.mld import mld_loss, sample_mld
from models.motiondiffuse import training_loss
from models.motionlcm import lcm_distillation_loss, sample_motionlcm, student_from_teacher
from models.rng import normal, uniform
from models.vae import LatentDistribution

pytestmark = pytest.mark.usefixtures("one_thread")

SCHEDULE = NoiseSchedule.from_name("scaled_linear", 1000, beta_start=0.00085, beta_end=0.012)
OTHER = torch.device("meta")


class Elsewhere(torch.Generator):
    """A CPU generator that says it lives on another device (the role a GPU's generator plays)."""

    @property
    def device(self) -> torch.device:
        return OTHER


def elsewhere(seed: int) -> torch.Generator:
    return Elsewhere().manual_seed(seed)


class OnGeneratorDevice(torch.Tensor):
    """A draw still on the generator's device: used alone or with scalars it works, mixed with the tensors'
    (any plain tensor of one or more dimensions) it raises, as a CUDA tensor mixed with CPU ones does;
    ``.to`` / ``.cpu`` bring it over."""

    @classmethod
    def __torch_function__(cls, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        with torch._C.DisableTorchFunctionSubclass():
            if getattr(func, "__name__", "") in ("to", "cpu"):
                return func(*args, **kwargs).as_subclass(torch.Tensor)
            leaves, _ = pytree.tree_flatten((args, kwargs))
            if any(type(x) is torch.Tensor and x.dim() > 0 for x in leaves):
                raise RuntimeError(f"{getattr(func, '__name__', func)}: a draw on the generator's device met "
                                   "a tensor on another device")
            out = func(*args, **kwargs)
        return pytree.tree_map(lambda x: x.as_subclass(cls) if type(x) is torch.Tensor else x, out)


def cuda_rule(draw: Callable) -> Callable:
    def checked(*args, generator: torch.Generator | None = None, device=None, **kwargs):
        if not isinstance(generator, Elsewhere):
            return draw(*args, generator=generator, device=device, **kwargs)
        if torch.device(device or "cpu") != OTHER:
            raise RuntimeError(f"a generator on {OTHER} asked for a tensor on {device or 'cpu'}")
        return draw(*args, generator=generator, device="cpu", **kwargs).as_subclass(OnGeneratorDevice)
    return checked


@pytest.fixture(autouse=True)
def strict_draws(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in ("randn", "rand", "randint"):
        monkeypatch.setattr(torch, name, cuda_rule(getattr(torch, name)))


def test_the_rule_refuses_a_draw_on_another_device_than_the_generators_and_a_draw_left_there() -> None:
    with pytest.raises(RuntimeError, match="asked for a tensor on cpu"):
        torch.randn(3, generator=elsewhere(0))
    draw = torch.randn(3, generator=elsewhere(0), device=OTHER)
    assert torch.isfinite(draw * 2.0 + 1.0).all()  # alone and with scalars: fine
    with pytest.raises(RuntimeError, match="met a tensor on another device"):
        draw + torch.ones(3)
    assert type(draw.to("cpu") + torch.ones(3)) is torch.Tensor  # moved: fine


def test_draws_are_the_generators_numbers_on_the_tensors_device() -> None:
    like = torch.zeros(1)
    torch.testing.assert_close(normal((4, 3), like, elsewhere(0)),
                               torch.randn(4, 3, generator=torch.Generator().manual_seed(0)), rtol=0, atol=0)
    torch.testing.assert_close(uniform((5,), like, elsewhere(1)),
                               torch.rand(5, generator=torch.Generator().manual_seed(1)), rtol=0, atol=0)
    t, t_prev = lcm_training_timesteps(64, 1000, 10, elsewhere(2), "cpu")
    assert set(t.tolist()) <= set(range(99, 1000, 100)) and torch.equal(t_prev, (t - 100).clamp(min=0))


def test_training_losses_draw_on_the_generators_device() -> None:
    teacher, x = mld_teacher(), control_batch(b=3)
    z0, text, words = x["z_t"], x["text_emb"], {"text_tokens": x["text_tokens"], "text_mask": x["text_mask"]}
    loss = mld_loss(teacher, SCHEDULE, z0, text, p_uncond=0.5, generator=elsewhere(0), **words)
    assert torch.isfinite(loss["total"])
    distilled = lcm_distillation_loss(student_from_teacher(teacher), student_from_teacher(teacher), teacher,
                                      SCHEDULE, z0, text, w_range=(1.5, 4.5), num_ddim_steps=10,
                                      generator=elsewhere(1), **words)
    assert torch.isfinite(distilled["total"])
    assert LatentDistribution(z0, z0).sample(elsewhere(2)).shape == z0.shape

    base = student()
    controlnet = MotionControlNet(base, control_config())
    randomise(controlnet)
    x = control_batch(b=2, frames=12)
    control = controlnet_loss(controlnet, base, tiny_vae(), SCHEDULE, z0[:2], x["text_emb"], x["hint"],
                              x["mask"], torch.tensor([12, 9]), mean=torch.zeros(D), std=torch.full((D,), 0.1),
                              w_range=(1.0, 2.0), text_dropout=0.5, generator=elsewhere(3),
                              text_tokens=x["text_tokens"], text_mask=x["text_mask"])
    assert torch.isfinite(control["total"])

    model = motiondiffuse_model()
    states, mask = motiondiffuse_text()
    assert torch.isfinite(training_loss(model, model.config.make_schedule(), torch.randn(2, 6, D),
                                        torch.tensor([6, 3]), states, mask, elsewhere(4), p_uncond=0.5))

    g, d = emdm_nets()
    x0, cond = torch.randn(2, 8, D), torch.randn(2, g.config.text_dim)
    schedule = EMDMSchedule(4)
    losses = discriminator_step_losses(g, d, schedule, x0, cond, [8, 5], step=0, generator_rng=elsewhere(5))
    assert all(torch.isfinite(v) for v in losses.values())
    losses = generator_step_losses(g, d, schedule, x0, cond, [8, 5], torch.zeros(D), torch.ones(D),
                                   generator_rng=elsewhere(6))
    assert all(torch.isfinite(v) for v in losses.values())


def test_samplers_draw_on_the_generators_device_and_give_its_numbers() -> None:
    short = NoiseSchedule.from_name("linear", 4)
    x = ddpm_sample(lambda x, t: torch.zeros_like(x), (2, 3), short, elsewhere(0), device="cpu")
    y = ddpm_sample(lambda x, t: torch.zeros_like(x), (2, 3), short, torch.Generator().manual_seed(0))
    torch.testing.assert_close(x, y, rtol=0, atol=0)
    assert torch.isfinite(ddim_sample(lambda x, t: torch.zeros_like(x), (2, 3), short, 2, eta=1.0,
                                      generator=elsewhere(1), device="cpu")).all()
    teacher, vae, x = mld_teacher(), tiny_vae(), control_batch(b=2)
    words = {"text_tokens": x["text_tokens"], "text_mask": x["text_mask"]}
    motion = sample_mld(teacher, vae, SCHEDULE, x["text_emb"], [8, 5], num_steps=2, eta=1.0, generator=elsewhere(2),
                        **words)
    assert torch.isfinite(motion).all()
    motion = sample_motionlcm(student_from_teacher(teacher), vae, SCHEDULE, x["text_emb"], [8, 5], num_steps=2,
                              generator=elsewhere(3), **words)
    assert torch.isfinite(motion).all()


def test_training_masks_draw_on_the_generators_device() -> None:
    mask = training_mask(torch.tensor([12, 9]), 12, 22, [0, 10], generator=elsewhere(7))
    again = training_mask(torch.tensor([12, 9]), 12, 22, [0, 10], generator=torch.Generator().manual_seed(7))
    assert torch.equal(mask, again) and mask.device == torch.device("cpu")


def test_the_evaluators_negative_shift_draws_on_the_generators_device() -> None:
    text, motion = torch.randn(4, 3), torch.randn(4, 3)
    assert torch.equal(contrastive_loss(text, motion, generator=elsewhere(8)),
                       contrastive_loss(text, motion, generator=torch.Generator().manual_seed(8)))
