"""Where the networks run, and the deterministic kernels they run with on a GPU.

- :func:`sampling_device`: the device ``sample.device`` names, for the evaluation stages, ``eval_speed`` and
  ``stages.generate`` (training chooses its own from ``ray.use_gpu``: :mod:`pipelines.runner`).
- :func:`device_name`: that device in words, for ``protocol.json`` (figures from two devices differ, so the
  report does not merge them).
- :func:`deterministic_gpu`: the scope of a training loop or an evaluation on a GPU.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator

import torch


def sampling_device(spec: str) -> torch.device:
    """The device ``sample.device`` names: ``auto`` (a GPU when one is present, else the CPU), ``cpu``, ``cuda`` or
    ``cuda:<index>``; ValueError naming the key when it names a GPU that this machine does not have."""
    if spec == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(spec)
    if device.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        index = 0 if device.index is None else device.index
        if index >= count:
            raise ValueError(f"sample.device={spec}: this machine has {count} CUDA device(s); "
                             "use sample.device=auto or cpu")
    return device


def device_name(device: torch.device) -> str:
    """``cpu``, or ``cuda`` and the GPU's model (``cuda NVIDIA H100 80GB HBM3``): what a table was computed on."""
    return f"cuda {torch.cuda.get_device_name(device)}" if device.type == "cuda" else device.type


@contextlib.contextmanager
def deterministic_gpu(device: torch.device) -> Iterator[None]:
    """On a GPU, the deterministic kernels the CPU path has, for the scope of a training loop or an evaluation:
    torch's deterministic algorithms (a warning where an op has none), cuDNN without autotuning and without
    TF32, and cuBLAS's fixed workspace (``CUBLAS_WORKSPACE_CONFIG``, which CUDA reads once per process, at the
    first cuBLAS call: a Ray worker's loop makes that call; an in-process run after other GPU work keeps the
    workspace it had). The previous settings come back afterwards. Nothing changes on the CPU."""
    if device.type != "cuda":
        yield
        return
    cudnn = torch.backends.cudnn
    saved = (torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled(),
             cudnn.deterministic, cudnn.benchmark, cudnn.allow_tf32)
    os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    torch.use_deterministic_algorithms(True, warn_only=True)
    cudnn.deterministic, cudnn.benchmark, cudnn.allow_tf32 = True, False, False
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(saved[0], warn_only=saved[1])
        cudnn.deterministic, cudnn.benchmark, cudnn.allow_tf32 = saved[2:]
