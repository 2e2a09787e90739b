"""dvc.yaml cannot drift from the code: every stage depends on exactly the project modules it imports
(transitively) and declares exactly the params keys it may read; the import direction holds.

A failure message says which lines to add to or remove from dvc.yaml.
"""

from __future__ import annotations

import importlib
import shlex
from pathlib import Path

import pytest
import yaml

from pipelines.identity import PROJECT_PACKAGES, REPO_ROOT, function_level_imports, module_files
from pipelines.registry import FAMILIES

DVC = yaml.safe_load((REPO_ROOT / "dvc.yaml").read_text())["stages"]


def stage_module(cmd: str) -> tuple[str, list[str]]:
    words = shlex.split(cmd)
    assert words[:3] == ["python", "-m", words[2]] and words[2].startswith("stages."), cmd
    return words[2], words[3:]


def declared(name: str) -> tuple[list[str], tuple[str, ...]]:
    """(modules, params keys) a DVC stage's command imports and may read, from the code."""
    module, args = stage_module(DVC[name]["cmd"])
    mod = importlib.import_module(module)
    if module == "stages.evaluate":
        if args == ["real"]:
            return [module], mod.PARAMS
        family = FAMILIES[args[0]]
        return [module, family.module], mod.PARAMS + family.params
    if module == "stages.speed":  # builds the rows of the families it times, through the registry
        return [module, *(FAMILIES[name].module for name in mod.TIMED)], mod.PARAMS
    params = mod.STAGE.params if hasattr(mod, "STAGE") else mod.PARAMS
    return [module], params


@pytest.mark.parametrize("name", sorted(DVC))
def test_code_deps_are_exactly_the_imported_modules(name: str) -> None:
    modules, _ = declared(name)
    expected = sorted({str(path) for module in modules for path in module_files(module)})
    listed = sorted(dep for dep in DVC[name]["deps"] if dep.split("/")[0] in PROJECT_PACKAGES)
    missing, extra = sorted(set(expected) - set(listed)), sorted(set(listed) - set(expected))
    assert not missing and not extra, f"dvc.yaml stage {name}: add deps {missing}, remove deps {extra}"


@pytest.mark.parametrize("name", sorted(DVC))
def test_no_dep_or_out_is_listed_twice(name: str) -> None:
    for key in ("deps", "outs"):
        listed = [str(entry) for entry in DVC[name].get(key, [])]
        twice = sorted({entry for entry in listed if listed.count(entry) > 1})
        assert not twice, f"dvc.yaml stage {name}: {key} {twice} listed more than once"


@pytest.mark.parametrize("name", sorted(DVC))
def test_params_are_exactly_the_keys_the_stage_reads(name: str) -> None:
    _, params = declared(name)
    assert sorted(DVC[name].get("params", [])) == sorted(params), (
        f"dvc.yaml stage {name}: params must be {sorted(params)}")


def test_every_family_has_its_evaluation_stage_with_its_training_outputs() -> None:
    for family in FAMILIES.values():
        stage = DVC.get(f"eval_{family.name}")
        assert stage is not None, f"dvc.yaml has no eval_{family.name} stage"
        assert stage_module(stage["cmd"]) == ("stages.evaluate", [family.name])
        for train in family.train_stages:
            assert f"artifacts/{train}" in stage["deps"], f"eval_{family.name} must depend on artifacts/{train}"
        assert f"artifacts/eval/{family.name}" in DVC["report"]["deps"]
        assert f"artifacts/eval/{family.name}" in stage["outs"]


def test_a_warm_started_stage_depends_on_the_stage_it_starts_from() -> None:
    params = yaml.safe_load((REPO_ROOT / "params.yaml").read_text())
    started = {name: params[name]["init_from"] for name in DVC
               if isinstance(params.get(name), dict) and params[name].get("init_from")}
    assert started, "no stage of params.yaml has an init_from"
    for name, source in started.items():
        assert f"artifacts/{source}" in DVC[name]["deps"], f"{name} must depend on artifacts/{source}"


def test_the_speed_stage_depends_on_the_training_outputs_of_the_families_it_times() -> None:
    from stages.speed import OUT, TIMED

    stage = DVC["eval_speed"]
    for name in TIMED:
        for train in FAMILIES[name].train_stages:
            assert f"artifacts/{train}" in stage["deps"], f"eval_speed must depend on artifacts/{train}"
    assert f"artifacts/eval/{OUT}" in stage["outs"] and f"artifacts/eval/{OUT}" in DVC["report"]["deps"]


def test_a_model_edit_touches_its_family_only() -> None:
    """Editing models/transformer.py re-runs the VAE and MLD stages and their evaluations, not the baselines'."""
    touched = {name for name in DVC if "models/transformer.py" in DVC[name]["deps"]}
    assert {"train_vae", "train_mld", "eval_vae", "eval_mld"} <= touched
    assert not touched & {"eval_baselines", "eval_real", "train_evaluator", "report", "extract_features"}


def _project_sources() -> list[Path]:
    return sorted(p for package in PROJECT_PACKAGES for p in (REPO_ROOT / package).rglob("*.py"))


def test_no_module_imports_a_stage() -> None:
    """Import direction: stages -> pipelines -> models, data; nothing imports a stage module."""
    offenders = []
    for path in _project_sources():
        text = path.read_text(encoding="utf-8")
        if "from stages" in text or "import stages" in text:
            offenders.append(str(path.relative_to(REPO_ROOT)))
    assert offenders == []


def test_layers_import_downwards_only() -> None:
    """data imports no models/pipelines; models imports no pipelines."""
    forbidden = {"data": ("models", "pipelines"), "models": ("pipelines",)}
    for package, banned in forbidden.items():
        for path in (REPO_ROOT / package).rglob("*.py"):
            files = module_files(f"{package}.{path.stem}") if path.stem != "__init__" else []
            wrong = [str(f) for f in files if f.parts[0] in banned]
            assert not wrong, f"{path.relative_to(REPO_ROOT)} imports {wrong}"


def test_the_evaluator_stage_does_not_import_model_families() -> None:
    files = {str(p) for p in module_files("stages.train_evaluator")}
    assert "models/mld.py" not in files and "models/vae.py" not in files


def test_imports_inside_functions_are_sweep_only() -> None:
    """Module files ignore function-level imports: they may only reach optional code (sweeps)."""
    for path in _project_sources():
        lazy = function_level_imports(path) - {"pipelines.sweep", "pipelines.validation", "data.features"}
        assert not lazy, f"{path.relative_to(REPO_ROOT)} imports {sorted(lazy)} inside a function"
