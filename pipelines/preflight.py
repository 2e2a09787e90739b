"""Every pipeline stage's params checked in one process, in seconds.

    python -m pipelines.preflight [key=value ...]

A bad value in a late stage's section (``train_motiondiffuse.lr=-1``, ``ray.address=headnode``) would
otherwise stop ``dvc repro`` only when that stage starts, an hour in. This runs each ``dvc.yaml``
stage's own command with ``--cfg``: the checks the stage runs when it starts, on ``params.yaml`` with
the overrides given (as ``make params ARGS=...`` would compose them), nothing read from ``artifacts/``
and nothing trained. Then the row names that ``evaluate.paraphrase_rows``, ``evaluate.samples.rows``
and ``speed.rows`` give, against the rows the model registry's families will have (a misspelt name
there is not an error of any one stage: ``eval_<family>`` would skip it without a word). ``make
repro`` runs it before ``dvc repro``, ``make params`` after composing; ``dvc repro`` and ``dvc exp
run`` alone do not. It checks params values only: a missing dataset folder or a wrong
``$RAY_ADDRESS`` still stops the stage that reads it. Prints every problem once, naming its key and
the stages it concerns, and exits 1 if there is any; prints one line and exits 0 otherwise.
"""

from __future__ import annotations

import contextlib
import io
import os
import runpy
import shlex
import sys
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import yaml

from pipelines.config import REPO_ROOT, load_params
from pipelines.registry import FAMILIES
from pipelines.speed import TIMED

DVC_YAML = REPO_ROOT / "dvc.yaml"


def stage_commands(dvc_yaml: Path = DVC_YAML) -> dict[str, tuple[str, list[str]]]:
    """``{stage: (module, arguments)}`` of every ``python -m stages.<module> ...`` command in ``dvc_yaml``."""
    commands = {}
    for name, stage in yaml.safe_load(dvc_yaml.read_text(encoding="utf-8"))["stages"].items():
        words = shlex.split(stage["cmd"])
        if words[:2] != ["python", "-m"] or not words[2].startswith("stages."):
            raise ValueError(f"{dvc_yaml}: stage {name!r} runs {stage['cmd']!r}, not python -m stages.<module>")
        commands[name] = (words[2], words[3:])
    return commands


def stage_problems(stage: str, module: str, arguments: Sequence[str], overrides: Sequence[str]) -> list[str]:
    """The lines ``python -m <module> <arguments> <overrides> --cfg`` exits with (empty when its params pass),
    each ``<stage>: <problem>``; a check that crashes is one such line, so the other stages still run.

    The module runs as ``__main__`` (as ``python -m`` runs it) with ``sys.argv`` set for the call; its
    YAML output is dropped. runpy warns when the module was imported before (a test, or another stage
    importing it): harmless here, as with ``python -m``, the ``__main__`` copy only reads params.
    """
    saved_argv, saved_env = sys.argv, dict(os.environ)
    sys.argv = [module, *arguments, *overrides, "--cfg"]
    try:
        with contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*found in sys.modules", category=RuntimeWarning)
            runpy.run_module(module, run_name="__main__", alter_sys=False)
    except SystemExit as exit_:
        if exit_.code not in (None, 0):
            return str(exit_.code).splitlines()
    except Exception as err:  # noqa: BLE001 - a check that crashes is reported with the others, not instead of them
        return [f"{stage}: its checks crashed ({type(err).__name__}: {err})"]
    finally:
        sys.argv = saved_argv
        os.environ.clear()
        os.environ.update(saved_env)
    return []


def row_problems(params: dict[str, Any], commands: dict[str, tuple[str, list[str]]]) -> list[str]:
    """``<stage>: <problem>`` for each row name in ``evaluate.paraphrase_rows``, ``evaluate.samples.rows`` or
    ``speed.rows`` that no family's rows will have (:meth:`pipelines.registry.ModelFamily.text_row_names`):
    ``samples.rows`` against the families that need no trajectory (their samples are drawn from captions
    alone), ``speed.rows`` against the families ``eval_speed`` times. Empty when the params these read are malformed:
    the stages' own checks name those."""
    try:
        names = {name: family.text_row_names(params) for name, family in FAMILIES.items()}
        evaluate, speed = params["evaluate"], params["speed"]
        every = [row for rows in names.values() for row in rows]
        free = [row for name, rows in names.items() if not FAMILIES[name].controlled for row in rows]
        timed = [row for name in TIMED for row in names[name]]
        evaluating = [stage for stage, (module, _) in commands.items() if module == "stages.evaluate"]
        checked = [  # (key, the names it gives, what it takes, the known names, the stages it concerns)
            ("evaluate.paraphrase_rows", evaluate["paraphrase_rows"], "the rows that answer captions", every,
             evaluating),
            ("evaluate.samples.rows", evaluate["samples"]["rows"], "the rows that answer captions without a "
             "trajectory", free, evaluating),
            ("speed.rows", speed["rows"], f"the rows of {' and '.join(TIMED)}, which eval_speed times", timed,
             ["eval_speed"])]
    except (KeyError, TypeError):
        return []
    problems = []
    for key, rows, what, known, stages in checked:
        unknown = [row for row in rows if row not in known] if isinstance(rows, list) else []
        if unknown:
            problem = f"{key}: unknown row(s) {', '.join(map(repr, unknown))} (it takes {what}: {', '.join(known)})"
            problems += [f"{stage}: {problem}" for stage in stages]
    return problems


def where(stages: Sequence[str], total: int) -> str:
    """The stages a problem stops, or "every stage"."""
    return "every stage" if len(stages) == total else ", ".join(stages)


def main(argv: Sequence[str] | None = None) -> None:
    overrides = list(sys.argv[1:] if argv is None else argv)
    if any(arg in ("-h", "--help") for arg in overrides):
        print(__doc__.strip())
        return
    options = [arg for arg in overrides if arg.startswith("-")]
    if options:
        sys.exit(f"preflight: unknown option(s) {options}; it takes key=value overrides and --help")
    commands = stage_commands()
    stages_by_problem: dict[str, list[str]] = {}
    lines = [line for name, (module, arguments) in commands.items()
             for line in stage_problems(name, module, arguments, overrides)]
    with contextlib.suppress(ValueError):  # overrides that do not compose: the stages' lines above say why
        lines += row_problems(load_params(overrides), commands)
    for line in lines:
        stage, _, problem = line.partition(": ")
        stages = stages_by_problem.setdefault(problem, [])
        stages += [stage] if stage not in stages else []
    if stages_by_problem:
        heading = ("preflight: these params would stop the pipeline or be ignored by it (fix them in conf/ or the "
                   "overrides):")
        sys.exit("\n".join([heading,
                            *(f"  {problem} ({where(stages, len(commands))})"
                              for problem, stages in stages_by_problem.items())]))
    print(f"preflight: the params of all {len(commands)} stages pass their checks")


if __name__ == "__main__":
    main()
