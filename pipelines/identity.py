"""What determines a stage's result: the project modules it imports and the digests of its inputs.

Two uses, one definition:

- :func:`module_files` is the transitive closure of a module's imports *within the project*
  (the packages in :data:`PROJECT_PACKAGES`), found by reading the source (``ast``), not by
  importing it. ``dvc.yaml`` must list exactly these files as a stage's code deps (a test checks
  it), so editing any of them re-runs the stage.
- :func:`fingerprint` hashes those files' contents and the contents of the stage's input folders.
  The runner puts it in the Ray run name, so changed code or inputs start a fresh run from step 0,
  while an interrupted run of the same code, params and inputs resumes (``pipelines/runner.py``).

An import is resolved to the module file if one exists (``from models import vae`` names
``models/vae.py``), else to its package's ``__init__.py``. Only imports that run when the module is
imported count (top level, also inside top-level ``if``/``try``; not ``if TYPE_CHECKING:``). Imports
inside functions are for optional paths that do not make a stage's result, such as sweeps;
:func:`function_level_imports` lists them so a test can keep it that way.
"""

from __future__ import annotations

import ast
import hashlib
from collections.abc import Iterable, Iterator
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
PROJECT_PACKAGES = ("data", "models", "pipelines", "stages")
#: Files a training run writes beside ``model.pt`` to record how it went (wall time, attempts,
#: curves), not what it produced: left out of an input's digest, so a resumed or re-run identical
#: upstream stage does not make its downstream stages train again.
RUN_LOG_FILES = frozenset({"metrics.json", "run.json", "loss.csv", "loss.png"})


def _module_path(name: str, root: Path) -> Path | None:
    """``a.b.c`` -> ``root/a/b/c.py`` or ``root/a/b/c/__init__.py``; None outside the project."""
    if name.split(".")[0] not in PROJECT_PACKAGES:
        return None
    base = root.joinpath(*name.split("."))
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _module_level_imports(body: list[ast.stmt]) -> Iterator[ast.Import | ast.ImportFrom]:
    """Import statements run when the module is imported: top level, in top-level ``if``/``try`` blocks."""
    for node in body:
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
        elif isinstance(node, ast.If) and not _is_type_checking(node):
            yield from _module_level_imports(node.body + node.orelse)
        elif isinstance(node, ast.Try):
            yield from _module_level_imports(node.body + node.orelse + node.finalbody
                                             + [stmt for handler in node.handlers for stmt in handler.body])


def _imported_names(path: Path) -> set[str]:
    """Absolute module names ``path`` imports at module level, including ``from pkg import module`` names."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    names: set[str] = set()
    for node in _module_level_imports(tree.body):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif node.module and node.level == 0:
            names.add(node.module)
            names.update(f"{node.module}.{alias.name}" for alias in node.names)
    return names


def function_level_imports(path: Path) -> set[str]:
    """Project modules ``path`` imports only inside functions (not part of :func:`module_files`)."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    functions = [node for node in ast.walk(tree) if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))]
    names = set()
    for node in (inner for function in functions for inner in ast.walk(function)):
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            module = node.module if isinstance(node, ast.ImportFrom) else node.names[0].name
            if module and module.split(".")[0] in PROJECT_PACKAGES:
                names.add(module)
    return names


def module_files(module: str, root: Path = REPO_ROOT) -> list[Path]:
    """Project source files ``module`` depends on, itself included, transitively; sorted, relative to root.

    Parent packages' ``__init__.py`` files are included (Python runs them on import).
    """
    start = _module_path(module, root)
    if start is None:
        raise ValueError(f"{module!r} is not a module of this project (packages: {', '.join(PROJECT_PACKAGES)})")
    seen: set[Path] = set()
    parts = module.split(".")
    todo = [found for depth in range(1, len(parts) + 1)
            if (found := _module_path(".".join(parts[:depth]), root)) is not None]
    while todo:
        path = todo.pop()
        if path in seen:
            continue
        seen.add(path)
        for name in _imported_names(path):
            parts = name.split(".")
            for depth in range(1, len(parts) + 1):
                found = _module_path(".".join(parts[:depth]), root)
                if found is not None:
                    todo.append(found)
    return sorted(path.relative_to(root) for path in seen)


def _hash_tree(digest: hashlib._Hash, path: Path, label: str) -> None:
    """Feed every file under ``path`` (name and content, sorted) into ``digest``."""
    if not path.exists():
        raise FileNotFoundError(f"{path}: input of the run does not exist")
    files = [path] if path.is_file() else sorted(
        p for p in path.rglob("*") if p.is_file() and p.name not in RUN_LOG_FILES)
    for file in files:
        digest.update(f"{label}/{file.relative_to(path) if file != path else ''}\0".encode())
        with file.open("rb") as handle:
            for block in iter(lambda: handle.read(1 << 20), b""):
                digest.update(block)
        digest.update(b"\0")


def fingerprint(module: str, inputs: Iterable[str | Path] = (), root: Path = REPO_ROOT) -> str:
    """Hex digest of the code ``module`` imports (file contents) and of the files under ``inputs``
    (all but :data:`RUN_LOG_FILES`)."""
    digest = hashlib.sha256()
    for rel in module_files(module, root):
        digest.update(f"code/{rel.as_posix()}\0".encode())
        digest.update((root / rel).read_bytes())
    for k, path in enumerate(inputs):
        _hash_tree(digest, Path(path), f"input{k}")
    return digest.hexdigest()
