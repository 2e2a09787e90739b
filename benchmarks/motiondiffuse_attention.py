"""MotionDiffuse's efficient (linear) attention against softmax attention: time and memory of a training step.

The whole :class:`models.motiondiffuse.MotionDiffuse` (default :class:`~models.motiondiffuse.MotionDiffuseConfig`
sizes, ``max_len`` raised to the longest sequence) runs :func:`models.motiondiffuse.training_loss` forward and
backward (no optimiser step) on random features of N frames (every frame valid) and 16 word tokens, at
batch 1 and 32 and N = 60, 196 and 400 frames, with ``attention="linear"`` (Eq. 8) and ``"softmax"``
(PyTorch's ``scaled_dot_product_attention``; on CPU it may pick a fused kernel that never stores the N x N
matrix, so the softmax memory here is a lower bound on the naive O(N^2)). Columns:

- ``ms/step``: median wall time of ``--repeats`` steps after ``--warmup`` untimed ones, ``--threads`` torch
  threads. Other processes on the cores slow it (the load average is printed).
- ``peak MiB``: the peak resident set size (``ru_maxrss``) of a fresh process that runs the steps of that
  one configuration, minus its RSS just before the first of them (model, inputs, torch and its lazy
  initialisation, done by one step on 1 x 8 frames, already there): the memory the steps themselves needed
  at their peak, temporaries and allocator caching included. Page granularity; a few MiB of noise.
- ``saved MiB``: bytes of the distinct tensor storages autograd saves for the backward of one step (a
  ``saved_tensors_hooks`` count): the activation memory, deterministic and independent of the allocator.

Each configuration runs in its own subprocess, so one cannot inherit another's peak. Prints a markdown table.

Usage: ``python benchmarks/motiondiffuse_attention.py [--threads 2] [--repeats 7] [--quick] [--json PATH]``
(``--quick``: a smoke check at tiny sizes, seconds; not a measurement).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a script from anywhere

from models.motiondiffuse import MotionDiffuse, MotionDiffuseConfig, training_loss  # noqa: E402

FULL = {"frames": (60, 196, 400), "batches": (1, 32), "model": {}}
QUICK = {"frames": (16, 32), "batches": (1, 4),
         "model": {"width": 32, "layers": 1, "heads": 2, "ff_dim": 64, "text_layers": 1, "text_heads": 2,
                   "text_ff_dim": 64}}
WORDS = 16
PAGE = os.sysconf("SC_PAGE_SIZE")


def rss_bytes() -> int:
    """This process' current resident set size (/proc/self/statm)."""
    return int(Path("/proc/self/statm").read_text().split()[1]) * PAGE


def saved_bytes(model: MotionDiffuse, batch: dict[str, Any]) -> int:
    """Bytes of the distinct storages autograd saves for one step's backward."""
    seen: dict[int, int] = {}

    def pack(t: torch.Tensor) -> torch.Tensor:
        storage = t.untyped_storage()
        seen[storage.data_ptr()] = storage.nbytes()
        return t

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        loss = training_loss(model, batch["schedule"], batch["x0"], batch["lengths"], batch["words"], batch["mask"])
    loss.backward()
    model.zero_grad(set_to_none=True)
    return sum(seen.values())


def run_one(spec: dict[str, Any]) -> dict[str, Any]:
    """One configuration in this process: ms/step (median), peak RSS delta and saved-activation bytes."""
    torch.set_num_threads(spec["threads"])
    torch.manual_seed(0)
    n, b = spec["frames"], spec["batch"]
    config = MotionDiffuseConfig(**{**spec["model"], "attention": spec["attention"], "max_len": max(n, 196)})
    model = MotionDiffuse(config).train()
    batch = {"schedule": config.make_schedule(), "x0": torch.randn(b, n, config.feature_dim),
             "lengths": torch.full((b,), n), "words": torch.randn(b, WORDS, config.text_dim),
             "mask": torch.ones(b, WORDS, dtype=torch.bool)}
    # one step on 1 x 8 frames first: torch's lazy initialisation (kernels, thread pools) joins the baseline
    small = training_loss(model, batch["schedule"], batch["x0"][:1, :8], batch["lengths"][:1].clamp(max=8),
                          batch["words"][:1], batch["mask"][:1])
    small.backward()
    model.zero_grad(set_to_none=True)
    base = rss_bytes()
    times = []
    for k in range(spec["warmup"] + spec["repeats"]):
        start = time.perf_counter()
        loss = training_loss(model, batch["schedule"], batch["x0"], batch["lengths"], batch["words"], batch["mask"])
        loss.backward()
        model.zero_grad(set_to_none=True)
        if k >= spec["warmup"]:
            times.append(time.perf_counter() - start)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # KiB on Linux
    return {**{k: spec[k] for k in ("attention", "batch", "frames")}, "ms_per_step": 1000 * statistics.median(times),
            "peak_mib": max(0, peak - base) / 2**20, "saved_mib": saved_bytes(model, batch) / 2**20,
            "params": sum(p.numel() for p in model.parameters())}


def table(rows: list[dict[str, Any]]) -> str:
    """Markdown: one line per (batch, frames), linear and softmax side by side."""
    by = {(r["batch"], r["frames"], r["attention"]): r for r in rows}
    lines = ["| batch | frames | linear ms/step | softmax ms/step | linear peak MiB | softmax peak MiB | "
             "linear saved MiB | softmax saved MiB |", "|---" * 8 + "|"]
    for b, n in sorted({(r["batch"], r["frames"]) for r in rows}):
        lin, soft = by[(b, n, "linear")], by[(b, n, "softmax")]
        lines.append(f"| {b} | {n} | {lin['ms_per_step']:.1f} | {soft['ms_per_step']:.1f} | {lin['peak_mib']:.1f} | "
                     f"{soft['peak_mib']:.1f} | {lin['saved_mib']:.1f} | {soft['saved_mib']:.1f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--quick", action="store_true", help="tiny sizes, to check that the script runs")
    parser.add_argument("--json", type=Path, default=None, help="also write the rows here")
    parser.add_argument("--one", default=None, help=argparse.SUPPRESS)  # internal: one configuration (JSON)
    args = parser.parse_args(argv)
    if args.one is not None:
        print(json.dumps(run_one(json.loads(args.one))))
        return []
    sizes = QUICK if args.quick else FULL
    repeats, warmup = (2, 1) if args.quick else (args.repeats, args.warmup)
    rows = []
    for batch in sizes["batches"]:
        for frames in sizes["frames"]:
            for attention in ("linear", "softmax"):
                spec = {"attention": attention, "batch": batch, "frames": frames, "model": sizes["model"],
                        "threads": args.threads, "repeats": repeats, "warmup": warmup}
                done = subprocess.run([sys.executable, __file__, "--one", json.dumps(spec)], check=True,
                                      capture_output=True, text=True)
                rows.append(json.loads(done.stdout.strip().splitlines()[-1]))
    model = MotionDiffuseConfig(**sizes["model"])
    print(f"MotionDiffuse width {model.width}, {model.layers} layers, {model.heads} heads, ff {model.ff_dim}, text "
          f"{model.text_layers} x {model.text_ff_dim} ({rows[0]['params'] / 1e6:.2f}M parameters with max_len 196); "
          f"{WORDS} word tokens; {args.threads} thread(s); median of {repeats} steps after {warmup}; "
          f"load average {os.getloadavg()[0]:.2f}" + (" [--quick: not a measurement]" if args.quick else ""))
    print(table(rows))
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=2) + "\n")
    return rows


if __name__ == "__main__":
    main()
