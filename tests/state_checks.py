"""Checks shared by the exact-resume tests of the training stages: bit-for-bit state equality and the
latest checkpoint of a Ray run."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from pipelines import checkpoint as ckpt


def assert_same(a: Any, b: Any, where: str) -> None:
    """Nested state dicts equal exactly (tensors bit for bit)."""
    if isinstance(a, torch.Tensor):
        assert isinstance(b, torch.Tensor) and a.dtype == b.dtype and torch.equal(a, b), where
    elif isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), where
        for key in a:
            assert_same(a[key], b[key], f"{where}.{key}")
    elif isinstance(a, list | tuple):
        assert isinstance(b, list | tuple) and len(a) == len(b), where
        for k, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same(x, y, f"{where}[{k}]")
    else:
        assert a == b, where


def final_state(run_path: str) -> dict[str, Any]:
    latest = sorted(p for p in Path(run_path).glob("checkpoint_*") if p.is_dir())[-1]
    return ckpt.load_state(latest)
