"""Stage ``eval_<name>``: the papers' metrics for one model family (or the real motions).

``python -m stages.evaluate <name> [key=value ...]`` runs the protocol of
:mod:`pipelines.evaluation` on the test split with the trained evaluator and writes, atomically,
``artifacts/eval/<name>/``:

- ``metrics.json``: one object per row with ``R_precision_top1/2/3``, ``FID``, ``MM_Dist``,
  ``Diversity``, ``MultiModality`` (stochastic generators only), ``AITS_s``, ``ms_per_frame`` and
  ``NFE`` (generators only), ``MPJPE_mm`` (reconstructions only), physical measures, and
  ``<key>_ci`` for each replicated metric, ``action_accuracy`` for Real and the rows of
  ``evaluate.paraphrase_rows``, whose twins ``<row>@paraphrase`` answer held-out paraphrases
  (:mod:`pipelines.paraphrase`). A metric that does not apply to a row is absent.
- ``samples/<row>_<k>.gif``: the fixed prompts of ``evaluate.samples`` for the chosen rows.
- ``protocol.json``: the evaluation settings and the number of test items the rows were scored with
  (0 when the family trained nothing; :mod:`pipelines.tables`); the report refuses a folder with rows
  whose protocol is not ``real``'s.

A family whose rows are action-conditioned (:class:`pipelines.action_evaluation.ActionGenerator`)
is scored by the action-to-motion protocol instead (``Real-action`` and its rows: recogniser
Accuracy, FID, Diversity, MultiModality), with the action recogniser the evaluator stage trains.

``<name>`` is ``real`` or a family of the model registry (:mod:`pipelines.registry`). ``real``
computes the protocol's draws and the evaluator's embeddings of the captions and of the reference
motions once (``references.npz``, with the ``Real`` row and ``meta.json``); every family's stage
reuses them. The ``report`` stage merges all folders into ``artifacts/eval/metrics.json``.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Sequence
from dataclasses import asdict, fields
from pathlib import Path
from typing import Any

import numpy as np

from data.atomic import atomic_directory, check_output
from data.humanml3d import PARAPHRASES_DIR
from data.render import render_animation
from data.skeleton import get_skeleton
from models.generator import Generator, Reconstructor
from pipelines.action_evaluation import ActionGenerator, evaluate_action_rows, load_recogniser
from pipelines.checkpoint import skipped
from pipelines.cli import HELP_FLAGS, repo_path, run_main
from pipelines.config import check_fields, check_keys, check_number, check_type, refuse
from pipelines.devices import deterministic_gpu, device_name
from pipelines.evaluation import (
    EvalConfig,
    check_protocol,
    evaluate,
    load_evaluator,
    load_references,
    references,
    save_references,
)
from pipelines.paraphrase import semantics
from pipelines.registry import FAMILIES, EvalContext, family
from pipelines.tables import write_table

REAL = "real"
#: Params every evaluation stage reads; a family's stage also reads its registry entry's ``params``.
PARAMS = ("evaluate", "features.out", "data.root", "data.name", "data.skeleton", "paths.artifacts", "sample.device")
REFERENCES = "references.npz"
#: The evaluator stage's output holding the action recogniser.
RECOGNISER = "train_evaluator_recogniser"
USAGE = (f"usage: python -m stages.evaluate <{' | '.join([REAL, *FAMILIES])}> [key=value ...] [--cfg] [--help]")


def eval_config(section: dict[str, Any]) -> EvalConfig:
    """The ``evaluate`` params section (less ``samples``) as an EvalConfig; unknown keys are an error."""
    section = {key: value for key, value in section.items() if key != "samples"}
    unknown = set(section) - {f.name for f in fields(EvalConfig)}
    if unknown:
        raise ValueError(f"unknown evaluate param(s): {sorted(unknown)}")
    return EvalConfig(**section)


def check_section(params: dict[str, Any]) -> None:
    """The ``evaluate`` section checked before any work; a ValueError naming the key, its value and what is allowed."""
    cfg = check_type(params, "evaluate", "", kind=dict)
    check_fields({key: value for key, value in cfg.items() if key != "samples"}, EvalConfig, "evaluate")
    check_protocol(cfg)
    rows = cfg.get("paraphrase_rows", [])
    if not isinstance(rows, list) or not all(isinstance(row, str) for row in rows):
        raise ValueError(f"evaluate.paraphrase_rows must be a list of row names, got {rows!r}")
    samples = check_keys(cfg.get("samples"), "evaluate.samples", ("rows", "length", "prompts"))
    check_type(samples, "rows", "evaluate.samples", kind=list)
    check_number(samples, "length", "evaluate.samples", low=4, high=196, integer=True)
    check_type(samples, "prompts", "evaluate.samples", kind=list)
    if samples["rows"] and not samples["prompts"]:
        refuse(f"evaluate.samples.prompts: rows {samples['rows']} are drawn for these prompts, and there are none")


def render_samples(rows: Sequence[Generator], ctx: EvalContext, out: Path) -> None:
    """GIFs of the fixed prompts (``evaluate.samples``) for the chosen rows, to look at."""
    cfg = ctx.params["evaluate"]["samples"]
    chosen = [row for row in rows if row.name in cfg["rows"]]
    if not chosen:
        return
    out.mkdir()
    text = ctx.store.encode_prompts(cfg["prompts"])
    lengths = np.full(len(text), cfg["length"])
    skeleton = get_skeleton(ctx.params["data"]["skeleton"])
    for gen in chosen:
        for k, (joints, prompt) in enumerate(zip(ctx.store.to_joints(gen.sample(text, lengths, seed=0), lengths),
                                                 text.texts, strict=True)):
            render_animation(joints, out / f"{gen.name}_{k}.gif", prompt, skeleton)


def run(name: str, params: dict[str, Any]) -> dict[str, dict[str, float]]:
    """Evaluate ``name``'s rows on ``sample.device`` and write ``artifacts/eval/<name>``; returns its rows."""
    ctx = EvalContext.from_params(params)
    with deterministic_gpu(ctx.device):
        return score(name, ctx)


def score(name: str, ctx: EvalContext) -> dict[str, dict[str, float]]:
    """:func:`run`'s work, with its networks on ``ctx.device``."""
    params, artifacts = ctx.params, ctx.artifacts
    cfg = eval_config(params["evaluate"])
    out = artifacts / "eval" / name
    check_output(out, owner="evaluate")
    # protocol.json, with the test items scored: the report merges tables of one protocol and one device
    settings = asdict(cfg) | {"device": device_name(ctx.device)}
    untrained = [] if name == REAL else [(stage, reason) for stage in family(name).train_stages
                                         if (reason := skipped(artifacts / stage))]
    if untrained:  # e.g. the action stages on a dataset without action labels
        print(f"eval_{name}: no rows: {untrained[0][0]} trained nothing: {untrained[0][1]}")
        with atomic_directory(out, owner="evaluate") as tmp:
            write_table(tmp, {}, settings, 0)
        return {}
    rows = [] if name == REAL else family(name).build_rows(ctx)
    actions = [row for row in rows if isinstance(row, ActionGenerator)]
    headline = any(row.name in cfg.paraphrase_rows for row in rows)
    generators = [row for row in rows if isinstance(row, Generator)]
    reconstructors = [row for row in rows if isinstance(row, Reconstructor) and not isinstance(row, Generator)]
    scored = name == REAL or headline or bool(reconstructors)  # the text-conditioned rows with an action accuracy
    recognised = bool(actions) or scored  # the rows the action recogniser scores
    test = ctx.store.split("test")
    recogniser = (load_recogniser(ctx.trained(RECOGNISER), ctx.device)
                  if recognised and not skipped(artifacts / RECOGNISER) else None)
    if actions:  # the action-to-motion protocol: the recogniser, not the T2M evaluator, and its own pair counts
        table = evaluate_action_rows(actions, ctx.store, recogniser, cfg.replications, cfg.seed,
                                     unit_length=cfg.unit_length)
        with atomic_directory(out, owner="evaluate") as tmp:
            write_table(tmp, table, settings, len(test))
        return table
    embedder = load_evaluator(ctx.trained("train_evaluator"), ctx.device)
    skeleton = get_skeleton(params["data"]["skeleton"])
    sem = None
    if scored:
        sem = semantics(repo_path(params, "data.root"), test, ctx.store, recogniser, cfg.seed, skeleton.fps,
                        paraphrases=headline)
    if headline and sem.paraphrase is None:
        print(f"eval_{name}: {params['data']['root']} has no {PARAPHRASES_DIR}/: no paraphrase rows")
    if name == REAL:
        refs = references(test, embedder, cfg)
        table = evaluate(refs, test, ctx.store.mean, ctx.store.std, embedder, skeleton, cfg, real=True, semantics=sem)
        meta = {"dataset": params["data"]["name"], "test_items": len(test), "replications": cfg.replications,
                "device": settings["device"]}
        with atomic_directory(out, owner="evaluate") as tmp:
            save_references(tmp / REFERENCES, refs)
            (tmp / "meta.json").write_text(json.dumps(meta, indent=2) + "\n")
            write_table(tmp, table, settings, len(test))
        return table
    refs = load_references(artifacts / "eval" / REAL / REFERENCES, test, cfg)
    table = evaluate(refs, test, ctx.store.mean, ctx.store.std, embedder, skeleton, cfg, generators, reconstructors,
                     semantics=sem)
    with atomic_directory(out, owner="evaluate") as tmp:
        write_table(tmp, table, settings, len(test))
        render_samples(generators, ctx, tmp / "samples")
    return table


def main(argv: Sequence[str] | None = None) -> None:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] in HELP_FLAGS:
        print(f"{USAGE}\n  <name> --help lists the keys that evaluation reads")
        return
    if not argv or "=" in argv[0] or argv[0].startswith("-"):
        sys.exit(USAGE)
    name, overrides = argv[0], argv[1:]
    keys = PARAMS
    if name != REAL:
        try:
            keys = PARAMS + family(name).params
        except ValueError as err:
            sys.exit(f"evaluate: {err}")

    def run_and_print(params: dict[str, Any]) -> None:
        table = run(name, params)
        print(f"eval_{name}: " + "; ".join(
            f"{row} " + (f"accuracy {m['Accuracy']:.3f}" if "Accuracy" in m else f"R@3 {m['R_precision_top3']:.3f}")
            + f" FID {m['FID']:.3f}" for row, m in table.items()))

    run_main(f"eval_{name}", run_and_print, keys, overrides, checks=[check_section])


if __name__ == "__main__":
    main()
