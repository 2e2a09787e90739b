"""Training steps under DistributedDataParallel, as a multi-worker Ray Train run wraps its models.

``Session.wrap`` (pipelines/runner.py) wraps each trained model in DDP when ``ray.num_workers`` > 1. A
step that reads an attribute through the wrapper fails on its first step, and a model whose trainable
parameters do not all receive a gradient fails on its second (DDP waits for their reduction). Both
show with a one-process gloo group, so these tests need neither Ray nor a second process.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel

from models.diffusion import NoiseSchedule
from models.evaluator import EvaluatorConfig, movement_ae_loss
from models.mld import MLDDenoiser, mld_loss
from models.motiondiffuse import MotionDiffuse, MotionDiffuseConfig, training_loss
from models.motionlcm import lcm_distillation_loss, student_from_teacher
from models.vae import MotionVAE, vae_loss
from pipelines.schedules import EMA
from stages.train_evaluator import build_movement

pytestmark = pytest.mark.usefixtures("one_thread")  # tiny networks (tests/conftest.py)

D = 263


@pytest.fixture(scope="module")
def process_group(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """A gloo process group of one rank, destroyed afterwards."""
    store = Path(tmp_path_factory.mktemp("ddp")) / "store"
    dist.init_process_group("gloo", init_method=f"file://{store}", rank=0, world_size=1)
    yield
    dist.destroy_process_group()


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _two_updates(wrapped: torch.nn.Module, optimizer: torch.optim.Optimizer, loss_fn) -> list[float]:
    """Two optimiser steps on ``loss_fn(wrapped)``; DDP raises on the second if a gradient went missing."""
    losses = []
    for _ in range(2):
        loss = loss_fn(wrapped)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    return losses


def _check_under_ddp(net: torch.nn.Module, loss) -> None:
    """``loss(model)`` through DDP equals the plain loss, and two updates run and move the module."""
    plain = loss(net).item()
    losses = _two_updates(DistributedDataParallel(net), torch.optim.SGD(net.parameters(), lr=0.1), loss)
    assert losses[0] == pytest.approx(plain, rel=1e-6)
    assert losses[1] != losses[0]  # the first update reached the module


def _denoiser(**overrides: object) -> MLDDenoiser:
    torch.manual_seed(0)
    return MLDDenoiser({"latent_tokens": 2, "latent_dim": 8, "hidden_dim": 16, "text_dim": 16, "layers": 3,
                        "heads": 2, "ff_dim": 32, "dropout": 0.0, "time_freq_dim": 16, **overrides})


@pytest.mark.usefixtures("process_group")
def test_mld_loss_through_ddp_equals_the_plain_loss() -> None:
    net, schedule = _denoiser(), NoiseSchedule.from_name("scaled_linear", 1000)
    z0, text = torch.randn(4, 2, 8, generator=_gen(1)), torch.randn(4, 16, generator=_gen(2))
    _check_under_ddp(net, lambda model: mld_loss(net, schedule, z0, text, p_uncond=0.5, generator=_gen(3),
                                                 net=model)["total"])


@pytest.mark.usefixtures("process_group")
def test_vae_loss_through_ddp_equals_the_plain_loss() -> None:
    torch.manual_seed(0)
    vae = MotionVAE({"latent_tokens": 2, "latent_dim": 8, "hidden_dim": 16, "layers": 3, "heads": 2, "ff_dim": 32,
                     "dropout": 0.0})  # dropout draws from the global RNG, not from the loss's generator
    x, lengths = 0.1 * torch.randn(2, 12, D, generator=_gen(1)), torch.tensor([12, 8])
    mean, std = torch.zeros(D), torch.ones(D)
    _check_under_ddp(vae, lambda model: vae_loss(model, x, lengths, mean, std, 22, generator=_gen(2))["total"])


@pytest.mark.usefixtures("process_group")
def test_lcm_distillation_loss_through_ddp_equals_the_plain_loss() -> None:
    teacher = _denoiser().eval()
    student = student_from_teacher(teacher)
    target = EMA(student, 0.95).module
    schedule = NoiseSchedule.from_name("scaled_linear", 1000, beta_start=0.00085, beta_end=0.012)
    z0, text = torch.randn(3, 2, 8, generator=_gen(1)), torch.randn(3, 16, generator=_gen(2))
    _check_under_ddp(student, lambda model: lcm_distillation_loss(
        model, target, teacher, schedule, z0, text, w_range=(1.5, 4.5), num_ddim_steps=10, generator=_gen(3))["total"])


@pytest.mark.usefixtures("process_group")
def test_motiondiffuse_loss_through_ddp_equals_the_plain_loss() -> None:
    torch.manual_seed(0)
    model = MotionDiffuse(MotionDiffuseConfig(feature_dim=D, text_dim=8, width=16, layers=2, heads=2, ff_dim=32,
                                              text_layers=1, text_heads=2, text_ff_dim=32, max_len=32,
                                              num_train_timesteps=50))
    words, mask = torch.randn(2, 5, 8, generator=_gen(1)), torch.arange(5)[None] < torch.tensor([[3], [5]])
    x0, lengths = torch.randn(2, 6, D, generator=_gen(2)), torch.tensor([6, 3])
    schedule = model.config.make_schedule()
    _check_under_ddp(model, lambda net: training_loss(net, schedule, x0, lengths, words, mask, _gen(3), p_uncond=0.5))


@pytest.mark.usefixtures("process_group")
def test_movement_autoencoder_trains_under_ddp() -> None:
    """Only the movement encoder and decoder require grad: the evaluator's other parts are in the model
    (its state dict feeds the matching run) but take no part in the autoencoder's forward."""
    torch.manual_seed(0)
    model_cfg = EvaluatorConfig.for_profile("smoke", vocab_size=30, feature_dim=D)
    parts = build_movement({"model": model_cfg.to_dict(), "mean": [0.0] * D, "std": [1.0] * D,
                            "glove_path": None, "lr": 1e-3})
    model, optimizer = parts.models["movement"], parts.optimizers["adam"]
    trainable = {id(p) for p in model.parameters() if p.requires_grad}
    assert trainable == {id(p) for group in optimizer.param_groups for p in group["params"]}
    assert not any(p.requires_grad for p in model.evaluator.text_encoder.parameters())
    window = torch.randn(3, 40, D, generator=torch.Generator().manual_seed(1))

    def loss(wrapped: torch.nn.Module) -> torch.Tensor:
        return movement_ae_loss(*wrapped(window))

    losses = _two_updates(DistributedDataParallel(model), optimizer, loss)
    assert losses[1] < losses[0]
