"""Every pipeline stage's params checked in one process, in seconds.

    python -m pipelines.preflight [key=value ...]

A bad value in a late stage's section (``train_motiondiffuse.lr=-1``, ``ray.address=headnode``) would
otherwise stop ``dvc repro`` only when that stage starts, an hour in. This runs each ``dvc.yaml``
stage's own command with ``--cfg``: the checks the stage runs when it starts, on ``params.yaml`` with
the overrides given (as ``make params ARGS=...`` would compose them), nothing read from ``artifacts/``
and nothing trained. ``make repro`` runs it before ``dvc repro``, ``make params`` after composing;
``dvc repro`` and ``dvc exp run`` alone do not. It checks params values only: a missing dataset
folder or a wrong ``$RAY_ADDRESS`` still stops the stage that reads it. Prints every problem once,
naming its key and the stages it stops, and exits 1 if there is any; prints one line and exits 0
otherwise.
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

import yaml

from pipelines.config import REPO_ROOT

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
    for name, (module, arguments) in commands.items():
        for line in stage_problems(name, module, arguments, overrides):
            stage, _, problem = line.partition(": ")
            stages = stages_by_problem.setdefault(problem, [])
            stages += [stage] if stage not in stages else []
    if stages_by_problem:
        sys.exit("\n".join(["preflight: these params would stop the pipeline (fix them in conf/ or the overrides):",
                            *(f"  {problem} ({where(stages, len(commands))})"
                              for problem, stages in stages_by_problem.items())]))
    print(f"preflight: the params of all {len(commands)} stages pass their checks")


if __name__ == "__main__":
    main()
