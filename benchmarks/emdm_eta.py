"""Probe: EMDM's trained generator sampled with DDIM(eta) updates instead of the posterior draw of Alg. 1.

    python benchmarks/emdm_eta.py [key=value ...] [--eta 1 0.5 0]

Each step keeps x0_hat = G(x_{t+1}, t, z, c) and moves to level t along DDIM (Song et al. 2021, Eq. 12)::

    eps_hat = (x_{t+1} - sqrt(a) x0_hat) / sqrt(1 - a)
    x_t     = sqrt(a_prev) x0_hat + sqrt(1 - a_prev - s^2) eps_hat + s noise,   s^2 = eta^2 var

with ``a = alpha_bar_{t+1}``, ``a_prev = alpha_bar_t`` and ``var`` the posterior variance of
:class:`models.emdm.EMDMSchedule`. ``eta = 1`` is the posterior sample itself (EMDM); ``eta = 0`` the
deterministic update, which suits a generator that predicts the conditional mean of x0 (a GAN that
has not learnt to sample). Scores each setting as ``benchmarks/val_scores.py`` does (one
replication on the validation split). Used for docs/emdm.md.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
from torch import Tensor

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from models.diffusion import gather  # noqa: E402
from models.emdm import EMDMSchedule  # noqa: E402
from pipelines.cli import artifacts_dir, repo_path  # noqa: E402
from pipelines.config import load_params  # noqa: E402
from pipelines.emdm_family import emdm_rows  # noqa: E402
from pipelines.registry import EvalContext  # noqa: E402
from pipelines.validation import generator_scores  # noqa: E402


def ddim_step(schedule: EMDMSchedule, x0: Tensor, x_next: Tensor, t: Tensor, noise: Tensor, eta: float) -> Tensor:
    """The module docstring's update from level t + 1 to level t (t = 0: x0_hat, as the posterior)."""
    a = gather(schedule.alphas_cumprod[1:], t, x_next)
    a_prev = gather(schedule.alphas_cumprod[:-1], t, x_next)
    s2 = eta**2 * gather(schedule.posterior_variance, t, x_next)
    eps = (x_next - a.sqrt() * x0) / (1.0 - a).sqrt()
    return a_prev.sqrt() * x0 + (1.0 - a_prev - s2).clamp(min=0.0).sqrt() * eps + s2.sqrt() * noise


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--eta", type=float, nargs="+", default=[1.0, 0.5, 0.0])
    parser.add_argument("overrides", nargs="*", help="params overrides, e.g. paths.artifacts=/tmp/probe")
    args = parser.parse_args()
    if not all(0.0 <= eta <= 1.0 for eta in args.eta):
        parser.error(f"--eta: each value must lie in [0, 1], got {args.eta}")
    params = load_params(args.overrides)
    ctx = EvalContext(params, artifacts_dir(params), repo_path(params, "features.out"))
    (row,) = emdm_rows(ctx)
    for eta in args.eta:
        row.schedule.posterior_sample = (  # this row's schedule only; the sampler calls it at every step
            lambda x0, x_next, t, noise, eta=eta: ddim_step(row.schedule, x0, x_next, t, noise, eta))
        with torch.inference_mode():
            scores = generator_scores(params, row)
        print(f"eta {eta:g}: val FID {scores['val_FID']:.3f}, val R@3 {scores['val_R_precision_top3']:.3f}")


if __name__ == "__main__":
    main()
