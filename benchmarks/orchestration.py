"""Orchestration overhead of the training runner: plain PyTorch vs Ray Train.

Runs one training loop (an MLP regression, ~16 ms per step on one CPU thread) as

1. a bare hand-written PyTorch loop (DataLoader + forward/backward/AdamW),
2. the runner in-process (``num_workers=0``: the same loop, no Ray),
3. a bare DDP loop in 2 processes (torch.multiprocessing, gloo; no Ray),
4. the runner under Ray Train with 1 worker, and
5. the runner under Ray Train with 2 workers (DDP over gloo),

all with one torch thread per process, and prints the steady-state step time (median
over 50-step windows, first window skipped), the Ray/plain step-time ratio (target
<= 1.10), the fixed start-up seconds (wall time minus steps x steady step time) and
samples/s for 1 vs 2 workers.

Usage: ``python benchmarks/orchestration.py [--steps 800] [--batch 128] [--json out.json]``.
Starts a private local Ray cluster (or joins ``$RAY_ADDRESS``) and removes its storage.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

for _key, _value in {"WANDB_MODE": "disabled", "RAY_USAGE_STATS_ENABLED": "0",
                     "RAY_AUTH_MODE": "disabled"}.items():
    os.environ.setdefault(_key, _value)

import torch  # noqa: E402
from torch import nn  # noqa: E402
from torch.utils.data import DataLoader, DistributedSampler, TensorDataset  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from pipelines.runner import Components, StepContext, TrainSpec, run_training  # noqa: E402

WINDOW = 50
DIM, HIDDEN, N_ITEMS = 256, 1024, 8192


def make_net() -> nn.Module:
    """Three-layer MLP autoencoder-ish regression net (1.6 M parameters)."""
    return nn.Sequential(nn.Linear(DIM, HIDDEN), nn.ReLU(), nn.Linear(HIDDEN, HIDDEN), nn.ReLU(),
                         nn.Linear(HIDDEN, DIM))


def build(cfg: dict) -> Components:
    """Runner spec: the net and its AdamW."""
    net = make_net()
    return Components({"net": net}, {"net": torch.optim.AdamW(net.parameters(), lr=cfg["lr"])})


def dataset(cfg: dict) -> TensorDataset:
    """Random inputs with a fixed target map."""
    x = torch.randn(N_ITEMS, DIM, generator=torch.Generator().manual_seed(0))
    return TensorDataset(x, torch.tanh(x.flip(1)))


def step(batch: Any, ctx: StepContext) -> dict[str, torch.Tensor]:
    """MSE step through the runner's update."""
    x, y = batch
    loss = nn.functional.mse_loss(ctx.models["net"](x), y)
    ctx.update(loss)
    return {"loss": loss}


SPEC = TrainSpec(build=build, dataset=dataset, step=step)


def steady_step_s(window_rates: list[float]) -> tuple[float, float]:
    """Median and best (min) seconds per step over the windows after the first one.

    The best window is the figure least disturbed by other users of a shared machine.
    """
    times = [1.0 / r for r in (window_rates[1:] or window_rates)]
    return statistics.median(times), min(times)


def bare_loop(cfg: dict, rank: int = 0, world: int = 1) -> dict[str, float]:
    """The hand-written PyTorch loop (DDP when ``world`` > 1): wall time and step time."""
    start = time.perf_counter()
    torch.set_num_threads(1)
    torch.manual_seed(cfg["seed"])
    net = make_net()
    if world > 1:
        net = nn.parallel.DistributedDataParallel(net)
    opt = torch.optim.AdamW(net.parameters(), lr=cfg["lr"])
    data = dataset(cfg)
    sampler = DistributedSampler(data, num_replicas=world, rank=rank, drop_last=True)
    loader = DataLoader(data, batch_size=cfg["batch_size"], sampler=sampler, drop_last=True)
    rates, steps, t0 = [], 0, time.perf_counter()
    while steps < cfg["max_steps"]:
        for x, y in loader:
            loss = nn.functional.mse_loss(net(x), y)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            steps += 1
            if steps % WINDOW == 0:
                loss.item()
                now = time.perf_counter()
                rates.append(WINDOW / (now - t0))
                t0 = now
            if steps == cfg["max_steps"]:
                break
    median, best = steady_step_s(rates)
    return {"wall_s": time.perf_counter() - start, "step_s": median, "best_step_s": best, "world": world}


def _ddp_worker(rank: int, cfg: dict, port: int, result_file: str) -> None:
    """One process of the bare DDP baseline (gloo on localhost)."""
    import torch.distributed as dist

    start = time.perf_counter()
    dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank, world_size=2)
    try:
        run = bare_loop(cfg, rank, 2)
    finally:
        dist.destroy_process_group()
    if rank == 0:
        Path(result_file).write_text(json.dumps({**run, "wall_s": time.perf_counter() - start}))


def bare_ddp(cfg: dict) -> dict[str, float]:
    """Two processes of the bare loop under DDP (no Ray), for the 2-worker comparison."""
    import socket

    import torch.multiprocessing as mp

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    with tempfile.NamedTemporaryFile(suffix=".json") as fh:
        start = time.perf_counter()
        mp.spawn(_ddp_worker, args=(cfg, port, fh.name), nprocs=2)
        run = json.loads(Path(fh.name).read_text())
    return {**run, "wall_s": time.perf_counter() - start}


def runner_run(cfg: dict, ray_cfg: dict, storage: Path, label: str) -> dict[str, float]:
    """One ``run_training`` call: wall time and steady step time from its history."""
    start = time.perf_counter()
    result = run_training("bench", SPEC, cfg, ray_cfg, storage / label / "out", str(storage))
    wall = time.perf_counter() - start
    rates = [row["steps_per_s"] for row in result.history if row["steps_per_s"] > 0]
    median, best = steady_step_s(rates)
    return {"wall_s": wall, "step_s": median, "best_step_s": best, "world": max(1, ray_cfg["num_workers"])}


def summarise(name: str, run: dict[str, float], steps: int, batch: int) -> dict[str, float]:
    """Derived figures: fixed start-up seconds and steady samples/s."""
    fixed = run["wall_s"] - steps * run["step_s"]
    samples = batch * run["world"] / run["step_s"]
    return {"name": name, **run, "fixed_s": fixed, "samples_per_s": samples}


def print_table(rows: list[dict[str, Any]], ray_init_s: float) -> None:
    """Human-readable results."""
    print(f"\n{'run':<24}{'step ms':>9}{'best ms':>9}{'wall s':>9}{'fixed s':>9}{'samples/s':>11}")
    for r in rows:
        print(f"{r['name']:<24}{1e3 * r['step_s']:>9.2f}{1e3 * r['best_step_s']:>9.2f}{r['wall_s']:>9.1f}"
              f"{r['fixed_s']:>9.1f}{r['samples_per_s']:>11.0f}")
    by = {r["name"]: r for r in rows}
    ray1, plain = by["ray-1-worker"], by["plain-pytorch"]
    print(f"\nray.init: {ray_init_s:.1f} s (once per process)")
    print(f"steady-state step-time ratio Ray(1 worker) / plain PyTorch: median {ray1['step_s'] / plain['step_s']:.3f}, "
          f"best window {ray1['best_step_s'] / plain['best_step_s']:.3f} (target <= 1.10)")
    print(f"steady-state step-time ratio Ray(1 worker) / runner in-process: "
          f"{by['ray-1-worker']['step_s'] / by['runner-in-process']['step_s']:.3f}")
    print(f"fixed start-up of a Ray Train run (1 worker): {by['ray-1-worker']['fixed_s']:.1f} s")
    print(f"samples/s 1 -> 2 workers: {by['ray-1-worker']['samples_per_s']:.0f} -> "
          f"{by['ray-2-workers']['samples_per_s']:.0f} "
          f"(x{by['ray-2-workers']['samples_per_s'] / by['ray-1-worker']['samples_per_s']:.2f}); "
          f"plain DDP 1 -> 2 processes: {by['plain-pytorch']['samples_per_s']:.0f} -> "
          f"{by['plain-ddp-2-processes']['samples_per_s']:.0f}")


def main(argv: list[str] | None = None) -> None:
    """Run the five variants and print (and optionally save) the figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=800)
    parser.add_argument("--batch", type=int, default=128, help="per-worker batch size")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    cfg = {"seed": 0, "batch_size": args.batch, "max_steps": args.steps, "lr": 1e-3,
           "lr_schedule": "constant", "log_every": WINDOW}
    ray_base = {"checkpoint_every": args.steps, "max_failures": 0}
    import ray

    with tempfile.TemporaryDirectory(prefix="motionforge-bench-") as tmp:
        storage = Path(tmp)
        rows = [summarise("plain-pytorch", bare_loop(cfg), args.steps, args.batch),
                summarise("runner-in-process", runner_run(cfg, {**ray_base, "num_workers": 0}, storage,
                                                          "local"), args.steps, args.batch),
                summarise("plain-ddp-2-processes", bare_ddp(cfg), args.steps, args.batch)]
        t0 = time.perf_counter()
        ray.init(address=os.environ.get("RAY_ADDRESS"))
        ray_init_s = time.perf_counter() - t0
        try:
            for name, workers in [("ray-1-worker", 1), ("ray-2-workers", 2)]:
                run = runner_run(cfg, {**ray_base, "num_workers": workers}, storage, name)
                rows.append(summarise(name, run, args.steps, args.batch))
        finally:
            ray.shutdown()
    print_table(rows, ray_init_s)
    if args.json:
        args.json.write_text(json.dumps({"ray_init_s": ray_init_s, "runs": rows}, indent=2))


if __name__ == "__main__":
    main()
