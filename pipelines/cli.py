"""What every stage's command line shares: the params it may read, paths from params, one-line errors.

``python -m stages.<name> [key=value ...]`` composes params (:mod:`pipelines.config`), keeps only
the keys the stage declares (its DVC ``params`` list: reading any other key is an error, so the
two cannot drift; ``tests/test_dvc_deps.py`` checks ``dvc.yaml``) and runs it; user errors (bad
params, missing files) end the process with status 1 and one line naming the problem.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from pipelines.config import REPO_ROOT, ConfigError, load_params, restrict_params


def param(params: dict[str, Any], dotted: str) -> Any:
    """``params['a']['b']`` for ``'a.b'``; ConfigError naming the key when it is missing."""
    node: Any = params
    for depth, part in enumerate(dotted.split(".")):
        if not isinstance(node, dict) or part not in node:
            raise ConfigError(f"params have no {'.'.join(dotted.split('.')[: depth + 1])!r}")
        node = node[part]
    return node


def repo_path(params: dict[str, Any], dotted: str) -> Path:
    """The path at params key ``dotted`` made absolute (relative paths are relative to the repository root)."""
    return (REPO_ROOT / param(params, dotted)).resolve()


def artifacts_dir(params: dict[str, Any]) -> Path:
    """``paths.artifacts`` as an absolute path."""
    return repo_path(params, "paths.artifacts")


def run_main(name: str, run: Callable[[dict[str, Any]], Any], keys: Sequence[str],
             argv: Sequence[str] | None = None) -> None:
    """A stage's command line: params (+ ``key=value`` overrides) restricted to ``keys``, then ``run``.

    User errors (bad params, missing files) exit with status 1 and one line naming the problem.
    """
    try:
        run(restrict_params(load_params(argv), keys))
    except (ValueError, FileNotFoundError) as err:
        sys.exit(f"{name}: {err}")
