"""How fast is this machine for our models? fp32 matmul throughput with torch on the CPU.

Measures GFLOP/s (``2 M K N / seconds``) of ``torch.matmul`` in float32 at a fixed thread count
(default 2, the stages' thread count) for shapes typical of the models: 256 and 1024 square, and a
batch of frames through a linear layer, (64 * 196, 128) x (128, 256); each warmed up, then the
median of several repetitions. The summary (median over the shapes) compares stage times between
machines of one kind. Other processes on the cores lower the numbers, so the load average is shown.

Usage: ``python benchmarks/machine.py [--threads 2] [--repeats 15] [--json PATH]``
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

import torch

#: name -> (M, K, N): an (M, K) x (K, N) product.
SHAPES: dict[str, tuple[int, int, int]] = {
    "square-256": (256, 256, 256),
    "square-1024": (1024, 1024, 1024),
    "frames-64x196-128x256": (64 * 196, 128, 256),
}


def cpu_model() -> str:
    """The first CPU's ``model name`` from /proc/cpuinfo, with its family and model numbers (which tell
    apart CPUs a virtual machine names alike); "unknown" without /proc/cpuinfo."""
    try:
        text = Path("/proc/cpuinfo").read_text().split("\n\n")[0]
    except OSError:
        return "unknown"
    info = dict(line.split(":", 1) for line in text.splitlines() if ":" in line)
    info = {key.strip(): value.strip() for key, value in info.items()}
    return f"{info.get('model name', 'unknown')} (family {info.get('cpu family', '?')} model {info.get('model', '?')})"


def matmul_gflops(m: int, k: int, n: int, repeats: int, min_seconds: float = 0.05) -> float:
    """Median GFLOP/s of ``a @ b`` (float32); each repetition loops until ``min_seconds`` passed."""
    gen = torch.Generator().manual_seed(0)
    a, b = torch.randn(m, k, generator=gen), torch.randn(k, n, generator=gen)
    out = torch.empty(m, n)
    for _ in range(3):  # warm-up: allocation, thread pool, caches
        torch.matmul(a, b, out=out)
    rates = []
    for _ in range(repeats):
        calls, start = 0, time.perf_counter()
        while (elapsed := time.perf_counter() - start) < min_seconds or calls == 0:
            torch.matmul(a, b, out=out)
            calls += 1
        rates.append(2.0 * m * k * n * calls / elapsed / 1e9)
    return statistics.median(rates)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2, help="torch intra-op threads (stages use 2)")
    parser.add_argument("--repeats", type=int, default=15, help="timed repetitions per shape")
    parser.add_argument("--json", type=Path, help="also write the numbers to this JSON file")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    load = os.getloadavg()[0]
    shapes = {name: matmul_gflops(*mkn, args.repeats) for name, mkn in SHAPES.items()}
    for name, rate in shapes.items():
        print(f"{name:>24}: {rate:7.1f} GFLOP/s")
    summary = statistics.median(shapes.values())
    result = {"cpu": cpu_model(), "threads": args.threads, "torch": torch.__version__,
              "gflops": shapes, "gflops_median": summary, "load_before": load}
    print(f"machine: {result['cpu']}, {args.threads} threads, fp32 matmul {summary:.0f} GFLOP/s (load {load:.2f})")
    if args.json:
        args.json.write_text(json.dumps(result, indent=2) + "\n")
    return result


if __name__ == "__main__":
    main()
