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


@pytest.mark.usefixtures("process_group")
def test_mld_loss_through_ddp_equals_the_plain_loss() -> None:
    torch.manual_seed(0)
    net = MLDDenoiser({"latent_tokens": 2, "latent_dim": 8, "hidden_dim": 16, "text_dim": 16, "layers": 3,
                       "heads": 2, "ff_dim": 32, "dropout": 0.0, "time_freq_dim": 16})
    schedule = NoiseSchedule.from_name("scaled_linear", 1000)
    z0, text = torch.randn(4, 2, 8), torch.randn(4, 16)

    def loss(model: torch.nn.Module) -> torch.Tensor:
        return mld_loss(model, schedule, z0, text, p_uncond=0.5, generator=torch.Generator().manual_seed(3))["total"]

    plain = loss(net).item()
    losses = _two_updates(DistributedDataParallel(net), torch.optim.SGD(net.parameters(), lr=0.1), loss)
    assert losses[0] == pytest.approx(plain, rel=1e-6)
    assert losses[1] != losses[0]  # the first update reached the module


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
