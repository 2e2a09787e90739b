"""Stage ``evaluate``: the papers' metrics table for every available generator.

``python -m stages.evaluate [key=value ...]`` runs the protocol of :mod:`pipelines.evaluation`
on the test split with the trained evaluator and writes atomically to ``artifacts/eval/``:

- ``metrics.json`` (DVC metrics): one object per row (``Real``, ``Random``, ``Retrieval``,
  then each trained model's rows) with ``R_precision_top1/2/3``, ``FID``, ``MM_Dist``,
  ``Diversity``, ``MultiModality`` (stochastic generators only), ``AITS_s`` and
  ``ms_per_frame`` (generators only), physical measures, and ``<key>_ci`` for each
  replicated metric. A metric that does not apply to a row is absent.
- ``report.md``: the paper-style table; ``fid_vs_time.png``: FID against inference time;
  ``samples/<row>_<k>.gif``: the fixed prompts of ``evaluate.samples`` for the chosen rows.

Rows come from :data:`GENERATOR_FACTORIES`: each factory returns the generators it can build
from the artefacts present (model stages register theirs there).
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import numpy as np

from data.atomic import atomic_directory
from data.render import render_animation
from data.skeleton import get_skeleton
from data.store import StoredItem, read_split
from models.generator import Generator, Reconstructor
from pipelines.config import REPO_ROOT, load_params
from pipelines.evaluation import REAL, EvalConfig, evaluate, load_evaluator
from pipelines.generators import (
    MLDGenerator,
    RandomMotion,
    Retrieval,
    VAEReconstruction,
    encode_prompts,
    motions_to_joints,
)
from stages.train_mld import load_mld
from stages.train_vae import load_vae


@dataclass
class EvalContext:
    """What a generator factory may use: params, artefact folder, training data and stats."""

    params: dict[str, Any]
    artifacts: Path
    train: list[StoredItem]
    mean: np.ndarray
    std: np.ndarray


def baselines(ctx: EvalContext) -> list[Generator]:
    """Random (chance level) and Retrieval (nearest training caption) rows."""
    return [RandomMotion(ctx.train, ctx.mean, ctx.std), Retrieval(ctx.train, ctx.mean, ctx.std)]


def _trained(ctx: EvalContext, stage: str) -> Path | None:
    """A training stage's output folder, or None (with a note) when it has not been run."""
    out = ctx.artifacts / stage
    if (out / "model.pt").exists():
        return out
    print(f"evaluate: no {out}/model.pt, its rows are left out (run `dvc repro {stage}`)")
    return None


def mld_rows(ctx: EvalContext) -> list[Generator]:
    """MLD with DDIM 50 (its published sampler) and the few-step DDIM 1/2/4 baselines."""
    mld_dir, vae_dir = _trained(ctx, "train_mld"), _trained(ctx, "train_vae")
    if mld_dir is None or vae_dir is None:
        return []
    denoiser, schedule, _ = load_mld(mld_dir)
    vae, guidance = load_vae(vae_dir), ctx.params["train_mld"]["guidance"]
    return [MLDGenerator(f"MLD-DDIM{n}", denoiser, vae, schedule, n, guidance) for n in (50, 1, 2, 4)]


def vae_rows(ctx: EvalContext) -> list[Reconstructor]:
    """The motion VAE's reconstruction of the test motions."""
    vae_dir = _trained(ctx, "train_vae")
    return [] if vae_dir is None else [VAEReconstruction(load_vae(vae_dir))]


GENERATOR_FACTORIES: list[Callable[[EvalContext], list[Generator]]] = [baselines, mld_rows]
RECONSTRUCTOR_FACTORIES: list[Callable[[EvalContext], list[Reconstructor]]] = [vae_rows]

COLUMNS = [  # (metrics.json key, report header, decimals)
    ("R_precision_top1", "R@1 ↑", 3), ("R_precision_top2", "R@2 ↑", 3), ("R_precision_top3", "R@3 ↑", 3),
    ("FID", "FID ↓", 3), ("MM_Dist", "MM-Dist ↓", 3), ("Diversity", "Diversity →", 3),
    ("MultiModality", "MModality ↑", 3), ("NFE", "NFE", 0), ("AITS_s", "AITS (s) ↓", 4),
    ("ms_per_frame", "ms/frame ↓", 3),
    ("MPJPE_mm", "MPJPE (mm) ↓", 1), ("skating_ratio", "Skate ↓", 3), ("penetration_mm", "Penetrate (mm) ↓", 2),
    ("floating_mm", "Float (mm) ↓", 2),
]


def _cell(row: dict[str, float], key: str, decimals: int) -> str:
    if key not in row:
        return "–"
    text = f"{row[key]:.{decimals}f}"
    return f"{text} ± {row[key + '_ci']:.{decimals}f}" if f"{key}_ci" in row else text


def report_markdown(table: dict[str, dict[str, float]], meta: dict[str, Any]) -> str:
    """The paper-style table (mean ± 95% CI over replications)."""
    lines = [
        f"# Evaluation on {meta['dataset']} ({meta['test_items']} test items, {meta['replications']} replications)",
        "",
        "| Method | " + " | ".join(h for _, h, _ in COLUMNS) + " |",
        "|---" * (len(COLUMNS) + 1) + "|",
    ]
    lines += ["| " + name + " | " + " | ".join(_cell(row, k, d) for k, _, d in COLUMNS) + " |"
              for name, row in table.items()]
    lines += ["", "→: closer to Real is better. ± is 1.96·std/√R over replications. "
              "AITS: seconds per sentence, batch 1, warm, loading excluded."]
    return "\n".join(lines) + "\n"


def plot_fid_vs_time(table: dict[str, dict[str, float]], path: Path) -> None:
    """FID against AITS for every timed row; the Real row's FID as a dashed line."""
    fig, ax = plt.subplots(figsize=(6, 4))
    for name, row in table.items():
        if "AITS_s" in row:
            ax.scatter(row["AITS_s"], row["FID"], s=40)
            ax.annotate(name, (row["AITS_s"], row["FID"]), textcoords="offset points", xytext=(5, 5))
    ax.axhline(table[REAL]["FID"], linestyle="--", color="grey", label="Real")
    ax.set_xscale("log")
    ax.set_xlabel("AITS (s per sentence, log)")
    ax.set_ylabel("FID")
    ax.set_title("FID vs inference time")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def render_samples(generators: Sequence[Generator], ctx: EvalContext, out: Path) -> None:
    """GIFs of the fixed prompts (``evaluate.samples``) for the chosen rows, to look at."""
    cfg = ctx.params["evaluate"]["samples"]
    chosen = [gen for gen in generators if gen.name in cfg["rows"]]
    if not chosen:
        return
    out.mkdir()
    text = encode_prompts(cfg["prompts"], REPO_ROOT / ctx.params["features"]["out"])
    lengths = np.full(len(text), cfg["length"])
    skeleton = get_skeleton(ctx.params["data"]["skeleton"])
    for gen in chosen:
        motions = motions_to_joints(gen.sample(text, lengths, seed=0), lengths, ctx.mean, ctx.std)
        for k, (joints, prompt) in enumerate(zip(motions, text.texts, strict=True)):
            render_animation(joints, out / f"{gen.name}_{k}.gif", prompt, skeleton)


def eval_config(section: dict[str, Any]) -> EvalConfig:
    """The ``evaluate`` params section (less ``samples``) as an EvalConfig; unknown keys are an error."""
    section = {key: value for key, value in section.items() if key != "samples"}
    names = {f.name for f in fields(EvalConfig)}
    unknown = set(section) - names
    if unknown:
        raise ValueError(f"unknown evaluate param(s): {sorted(unknown)}")
    return EvalConfig(**section)


def run(params: dict[str, Any]) -> dict[str, dict[str, float]]:
    """Evaluate every row and write ``artifacts/eval``; returns the metrics table."""
    artifacts = REPO_ROOT / params["paths"]["artifacts"]
    features = REPO_ROOT / params["features"]["out"]
    cfg = eval_config(params["evaluate"])
    test, train = read_split(features / "test.parquet"), read_split(features / "train.parquet")
    ctx = EvalContext(params, artifacts, train, np.load(features / "mean.npy"), np.load(features / "std.npy"))
    generators = [gen for factory in GENERATOR_FACTORIES for gen in factory(ctx)]
    reconstructors = [rec for factory in RECONSTRUCTOR_FACTORIES for rec in factory(ctx)]
    embedder = load_evaluator(artifacts / "train_evaluator")
    skeleton = get_skeleton(params["data"]["skeleton"])
    table = evaluate(generators, test, ctx.mean, ctx.std, embedder, skeleton, cfg, reconstructors)
    meta = {"dataset": params["data"]["name"], "test_items": len(test), "replications": cfg.replications}
    report = report_markdown(table, meta)
    with atomic_directory(artifacts / "eval") as tmp:
        (tmp / "metrics.json").write_text(json.dumps(table, indent=2) + "\n")
        (tmp / "report.md").write_text(report)
        plot_fid_vs_time(table, tmp / "fid_vs_time.png")
        render_samples(generators, ctx, tmp / "samples")
    print(report)
    return table


def main(argv: Sequence[str] | None = None) -> None:
    try:
        run(load_params(argv))
    except (ValueError, FileNotFoundError) as err:
        sys.exit(f"evaluate: {err}")


if __name__ == "__main__":
    main()
