"""The devices the networks run on: ``sample.device`` resolved for this machine, and the deterministic kernels
of a GPU's scope. No GPU is needed: torch's CUDA queries are stubbed where a test needs one."""

from __future__ import annotations

import os
from collections import Counter

import numpy as np
import pytest
import torch
from standin_device import STANDIN, StandIn, syncs_of
from torch.nn.utils.rnn import pack_padded_sequence

from pipelines.devices import deterministic_gpu, device_name, sampling_device


def test_sample_device_names_the_machines_devices(monkeypatch: pytest.MonkeyPatch) -> None:
    assert sampling_device("cpu") == torch.device("cpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert sampling_device("auto") == torch.device("cpu")
    with pytest.raises(ValueError, match=r"sample.device=cuda: this machine has 0 CUDA device\(s\)"):
        sampling_device("cuda")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert sampling_device("auto") == torch.device("cuda") and sampling_device("cuda:1") == torch.device("cuda:1")
    with pytest.raises(ValueError, match="sample.device=cuda:2: this machine has 2 CUDA"):
        sampling_device("cuda:2")
    assert device_name(torch.device("cpu")) == "cpu"
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda device: "NVIDIA H100")
    assert device_name(torch.device("cuda", 1)) == "cuda NVIDIA H100"


def test_gpu_runs_ask_for_deterministic_kernels_for_the_loop_only(monkeypatch: pytest.MonkeyPatch) -> None:
    """On a GPU the loop's scope turns on what the CPU path has by default, and restores the settings after; on
    the CPU it changes nothing (the training loop and the evaluation stages enter this scope)."""
    cudnn = torch.backends.cudnn
    monkeypatch.setenv("CUBLAS_WORKSPACE_CONFIG", "")  # recorded, so the test leaves the variable as it found it
    monkeypatch.delenv("CUBLAS_WORKSPACE_CONFIG")
    before = (torch.are_deterministic_algorithms_enabled(), cudnn.deterministic, cudnn.benchmark, cudnn.allow_tf32)
    with deterministic_gpu(torch.device("cpu")):
        assert "CUBLAS_WORKSPACE_CONFIG" not in os.environ and not torch.are_deterministic_algorithms_enabled()
    with deterministic_gpu(torch.device("cuda", 0)):
        assert os.environ["CUBLAS_WORKSPACE_CONFIG"] == ":4096:8"
        assert torch.are_deterministic_algorithms_enabled() and torch.is_deterministic_algorithms_warn_only_enabled()
        assert cudnn.deterministic and not cudnn.benchmark and not cudnn.allow_tf32
    after = (torch.are_deterministic_algorithms_enabled(), cudnn.deterministic, cudnn.benchmark, cudnn.allow_tf32)
    assert after == before


def test_the_standin_gpu_refuses_what_cuda_refuses() -> None:
    """tests/standin_device.py, which the evaluation's device test runs on, holds code to CUDA's rules."""
    with StandIn():
        on_device, on_cpu = torch.ones(3, device=STANDIN), torch.ones(3)
        refused = {
            "mixing": lambda: on_device + on_cpu,
            "numpy": lambda: on_device.numpy(),
            "asarray": lambda: np.asarray(on_device),
            "a CPU tensor indexed on the device": lambda: on_cpu[torch.tensor([0, 1], device="cuda")],
            "concatenating a CPU scalar": lambda: torch.stack([on_device[0], torch.tensor(1.0)]),
            "a CPU generator's draw on the device": lambda: torch.randn(3, device=STANDIN, generator=torch.Generator()),
            "packing with lengths on the device": lambda: pack_padded_sequence(
                torch.ones(2, 3, 1, device=STANDIN), torch.tensor([3, 2], device=STANDIN), batch_first=True),
        }
        for what, op in refused.items():
            with pytest.raises((RuntimeError, TypeError)):
                op()
                pytest.fail(f"the stand-in allowed {what}")
        allowed = [on_device * torch.tensor(2.0), on_device[torch.tensor([0, 1])], on_device.clone().copy_(on_cpu),
                   torch.zeros(2).to("cuda"), pack_padded_sequence(torch.ones(2, 3, 1, device=STANDIN),
                                                                   torch.tensor([3, 2]), batch_first=True).data]
        assert all(x.device == STANDIN for x in allowed)
        assert type(on_device.cpu() + on_cpu) is torch.Tensor


def test_the_standin_gpu_counts_what_makes_the_host_wait() -> None:
    """Reading a device tensor back and copying host data onto the device each count once (a GPU's host waits for
    its queue to drain); making, computing and indexing on the device, and CPU scalars, count nothing."""
    def work() -> None:
        on_device = torch.arange(3.0, device=STANDIN)
        on_device.sum().item()
        bool(on_device[0] > 0)
        int(on_device[1])
        on_device.tolist()
        on_device.cpu()
        on_device.to("cpu")
        torch.ones(2).to("cuda")
        on_device.clone().copy_(torch.zeros(3))
        torch.tensor([1, 2], device=STANDIN)
        on_device[torch.tensor([0, 2])]
        on_device[torch.tensor(1)]  # a 0-d CPU index is read on the host, not copied
        torch.full((2,), 3.0, device=STANDIN) * on_device[1] + torch.tensor(2.0)
        on_device[torch.arange(0, 3, 2, device=STANDIN)].exp()

    assert syncs_of(work) == Counter({"item": 1, "__bool__": 1, "__int__": 1, "tolist": 1, "cpu": 1, "to cpu": 1,
                                      "to device": 1, "copy_ from the host": 1, "tensor to device": 1,
                                      "__getitem__ from the host": 1})
