"""Every pipeline stage's params checked in one process, before anything runs.

    python -m pipelines.preflight [key=value ...]

A bad value in a late stage's section (``train_motiondiffuse.lr=-1``, ``ray.address=headnode``) would
otherwise stop ``dvc repro`` only when that stage starts, an hour in. This runs each ``dvc.yaml``
stage's own command with ``--cfg``: the stage's checks exactly as ``dvc repro`` will run them, with the
same overrides, nothing read from ``artifacts/`` and nothing trained. ``make repro`` runs it first and
``make params`` after composing. Prints every problem once, naming its key and the stages it stops,
and exits 1 if there is any; prints one line and exits 0 otherwise.
"""

from __future__ import annotations

import contextlib
import io
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


def stage_problems(module: str, arguments: Sequence[str], overrides: Sequence[str]) -> list[str]:
    """The lines ``python -m <module> <arguments> <overrides> --cfg`` exits with (empty when its params pass).

    The module runs as ``__main__`` (as ``python -m`` runs it) with ``sys.argv`` set for the call; its
    YAML output is dropped. runpy warns when the module was imported before (a test, or another stage
    importing it): harmless here, as with ``python -m``, the ``__main__`` copy only reads params.
    """
    saved = sys.argv
    sys.argv = [module, *arguments, *overrides, "--cfg"]
    try:
        with contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*found in sys.modules", category=RuntimeWarning)
            runpy.run_module(module, run_name="__main__", alter_sys=False)
    except SystemExit as exit_:
        if exit_.code not in (None, 0):
            return str(exit_.code).splitlines()
    finally:
        sys.argv = saved
    return []


def where(stages: Sequence[str], total: int) -> str:
    """The stages a problem stops, or "every stage"."""
    return "every stage" if len(stages) == total else ", ".join(stages)


def main(argv: Sequence[str] | None = None) -> None:
    overrides = list(sys.argv[1:] if argv is None else argv)
    commands = stage_commands()
    stages_by_problem: dict[str, list[str]] = {}
    for module, arguments in commands.values():
        for line in stage_problems(module, arguments, overrides):
            stage, _, problem = line.partition(": ")
            stages_by_problem.setdefault(problem, []).append(stage)
    if stages_by_problem:
        sys.exit("\n".join(["preflight: these params would stop the pipeline (fix them in conf/ or the overrides):",
                            *(f"  {problem} ({where(stages, len(commands))})"
                              for problem, stages in stages_by_problem.items())]))
    print(f"preflight: the params of all {len(commands)} stages pass their checks")


if __name__ == "__main__":
    main()
