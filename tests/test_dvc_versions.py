"""Versions and views of the DVC project: the trained models are registry artifacts, the default
remote round-trips a stage's outputs, `dvc metrics show` fits 200 columns and `dvc plots show`
needs no network.

The slow tests run the real `dvc`, `gto` and `git` commands in a scratch copy of the project with
$HOME in a temporary folder, so the default remote (`~/.cache/motionforge/dvc-remote`) is a
temporary folder too.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from pipelines.identity import REPO_ROOT
from stages import report as report_stage
from stages.report import SUMMARY, summary

DVC_YAML = yaml.safe_load((REPO_ROOT / "dvc.yaml").read_text())
STAGES = DVC_YAML["stages"]
BIN = Path(sys.executable).parent
#: A small dataset on the smoke profile, without preview renders: make_dataset takes seconds.
SMOKE = ["scale=smoke", "synthetic.previews=0"]


def training_outs() -> list[str]:
    """The output folders of the training stages (the stages that read the ``ray`` params)."""
    return [out for stage in STAGES.values() if "ray" in stage.get("params", []) for out in stage["outs"]]


def test_every_trained_model_is_a_registry_artifact() -> None:
    """Each training stage's output folder is an artifact of type model with a description and labels."""
    from gto.constants import assert_name_is_valid

    artifacts = DVC_YAML["artifacts"]
    by_path = {entry["path"]: name for name, entry in artifacts.items()}
    for out in training_outs():
        assert out in by_path, f"dvc.yaml artifacts: no entry with path {out}"
        entry = artifacts[by_path[out]]
        assert entry.get("type") == "model", f"dvc.yaml artifacts.{by_path[out]}: type must be model"
        assert entry.get("desc") and entry.get("labels"), f"dvc.yaml artifacts.{by_path[out]}: desc and labels"
    outs = {out for stage in STAGES.values() for out in stage.get("outs", [])}
    for name, entry in artifacts.items():
        assert_name_is_valid(name)
        assert entry["path"] in outs, f"dvc.yaml artifacts.{name}: {entry['path']} is no stage's output"


def test_metrics_are_the_report_summary_and_plots_are_images() -> None:
    """Only the report's summary.json is a metrics file; every plot is a PNG (no Vega, no CDN)."""
    declared = [m for stage in STAGES.values() for m in stage.get("metrics", [])] + DVC_YAML.get("metrics", [])
    assert declared == ["artifacts/eval/summary.json"]
    plots = DVC_YAML["plots"]
    assert all(isinstance(p, str) and p.endswith(".png") for p in plots), plots
    assert {f"{out}/loss.png" for out in training_outs()} | {"artifacts/eval/fid_vs_time.png"} == set(plots)


def test_summary_keeps_the_headline_figures_of_the_table() -> None:
    """summary.json is the table's SUMMARY figures, shaped like metrics.json; absent rows are left out."""
    table: dict[str, dict[str, float]] = {}
    expected: dict[str, dict[str, float]] = {}
    for i, (row, metric) in enumerate(SUMMARY):  # a row may give several figures (EMDM-action: Accuracy, FID)
        table.setdefault(row, {"FID_ci": 0.1, "AITS_s": 2.0})[metric] = float(i)
        expected.setdefault(row, {})[metric] = float(i)
    table["Random"] = {"FID": 9.0}
    assert summary(table) == expected
    del table["VAE"]
    assert "VAE" not in summary(table) and len(summary(table)) == len(expected) - 1


def test_report_writes_every_summary_figure_of_a_real_evaluation(tmp_path: Path) -> None:
    """On a real tiny evaluation (tests/fixtures/eval), summary.json holds every SUMMARY figure,
    equal to metrics.json's: the headline rows exist under these names."""
    shutil.copytree(REPO_ROOT / "tests" / "fixtures" / "eval", tmp_path / "eval")
    report_stage.run({"paths": {"artifacts": str(tmp_path)}})
    table = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    written = json.loads((tmp_path / "eval" / "summary.json").read_text())
    expected: dict[str, dict[str, float]] = {}
    for row, metric in SUMMARY:
        expected.setdefault(row, {})[metric] = table[row][metric]
    assert written == expected


# --- the real commands in a scratch copy ------------------------------------------------------------


@pytest.fixture
def scratch(tmp_path: Path) -> tuple[Path, dict[str, str]]:
    """A git repository holding a copy of the project's tracked files, and the environment to run in it."""
    repo = tmp_path / "repo"
    tracked = subprocess.run(["git", "ls-files", "-z"], cwd=REPO_ROOT, capture_output=True, text=True,
                             check=True).stdout.split("\0")
    for name in tracked:
        if name and not name.startswith(("tests/", "docs/", "benchmarks/")) and (REPO_ROOT / name).is_file():
            (repo / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO_ROOT / name, repo / name)
    env = {
        **os.environ,
        "PATH": f"{BIN}{os.pathsep}{os.environ['PATH']}",  # `python` in dvc.yaml's commands is this venv's
        "HOME": str(tmp_path / "home"),
        "MPLCONFIGDIR": os.environ.get("MPLCONFIGDIR", str(Path.home() / ".cache" / "matplotlib")),
        "GIT_AUTHOR_NAME": "test", "GIT_AUTHOR_EMAIL": "test@example.com",
        "GIT_COMMITTER_NAME": "test", "GIT_COMMITTER_EMAIL": "test@example.com",
        "DVC_NO_ANALYTICS": "1",
        "DVC_SITE_CACHE_DIR": str(tmp_path / "dvc-site-cache"),  # not /var/tmp/dvc
    }
    env.pop("DVC_ROOT", None)
    run(repo, env, "git", "init", "-q")
    return repo, env


def run(repo: Path, env: dict[str, str], *cmd: str) -> str:
    """Run a command in the scratch repository; its stdout, or a failure showing its output."""
    exe = str(BIN / cmd[0]) if (BIN / cmd[0]).exists() else cmd[0]
    proc = subprocess.run([exe, *cmd[1:]], cwd=repo, env=env, capture_output=True, text=True)
    assert proc.returncode == 0, f"{' '.join(cmd)} exited {proc.returncode}:\n{proc.stdout}\n{proc.stderr}"
    return proc.stdout


def commit(repo: Path, env: dict[str, str], message: str) -> None:
    run(repo, env, "git", "add", "-A")
    run(repo, env, "git", "commit", "-q", "-m", message)


def tree_digest(folder: Path) -> dict[str, str]:
    """sha256 of every file under ``folder``, by relative path."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def locked_out(repo: Path, stage: str) -> dict:
    """The single output entry of ``stage`` in dvc.lock (path, md5 of the folder listing, size, nfiles)."""
    (out,) = yaml.safe_load((repo / "dvc.lock").read_text())["stages"][stage]["outs"]
    return out


def wipe(repo: Path) -> None:
    """Delete the DVC cache and the stage outputs: what a fresh clone has."""
    shutil.rmtree(repo / ".dvc" / "cache", ignore_errors=True)
    shutil.rmtree(repo / "artifacts", ignore_errors=True)


@pytest.mark.slow
def test_push_wipe_pull_and_earlier_versions_come_back(scratch: tuple[Path, dict[str, str]]) -> None:
    """The README's version workflow with the default remote: run, commit dvc.lock, register, push;
    after a new version, `git checkout <rev>` + `dvc pull` with the cache and outputs wiped brings back
    the earlier version's exact bytes; `dvc artifacts get` fetches a registered version by name."""
    repo, env = scratch
    run(repo, env, "python", "-m", "pipelines.config", *SMOKE, "synthetic.num_motions=12")
    commit(repo, env, "smoke params")
    run(repo, env, "dvc", "repro", "make_dataset")
    commit(repo, env, "dataset v1")
    run(repo, env, "gto", "register", "dataset", "--version", "v1.0.0")
    run(repo, env, "dvc", "push")
    first, first_lock = tree_digest(repo / "artifacts" / "dataset"), locked_out(repo, "make_dataset")
    remote = Path(env["HOME"]) / ".cache" / "motionforge" / "dvc-remote"
    assert any(remote.rglob("*.dir")), f"dvc push wrote no folder listing under {remote}"

    run(repo, env, "python", "-m", "pipelines.config", *SMOKE, "synthetic.num_motions=14")
    run(repo, env, "dvc", "repro", "make_dataset")
    commit(repo, env, "dataset v2")
    assert tree_digest(repo / "artifacts" / "dataset") != first
    assert locked_out(repo, "make_dataset")["md5"] != first_lock["md5"]

    wipe(repo)
    run(repo, env, "git", "checkout", "-q", "dataset@v1.0.0")
    run(repo, env, "dvc", "pull", "make_dataset")  # with a full dvc.lock: `make pull`, i.e. `dvc pull`
    assert tree_digest(repo / "artifacts" / "dataset") == first
    assert "make_dataset" not in run(repo, env, "dvc", "status", "make_dataset")  # up to date: nothing to re-run

    wipe(repo)
    got = repo.parent / "got"
    run(repo, env, "dvc", "artifacts", "get", str(repo), "dataset", "--rev", "v1.0.0", "-o", str(got))
    assert tree_digest(got) == first


@pytest.mark.slow
def test_metrics_show_fits_200_columns_and_plots_need_no_network(scratch: tuple[Path, dict[str, str]]) -> None:
    """`dvc metrics show` of a full summary (wide values) fits 200 columns; `dvc plots show` writes
    HTML that loads nothing from the network and shows every declared PNG."""
    repo, env = scratch
    # The committed dvc.lock names outputs this copy has in neither its workspace nor a cache: dvc would
    # try to load them. Here only dvc.yaml's declarations are under test, on stand-in files.
    (repo / "dvc.lock").unlink(missing_ok=True)
    table = {row: {metric: 123.456789} for row, metric in SUMMARY}
    (repo / "artifacts" / "eval").mkdir(parents=True)
    (repo / "artifacts" / "eval" / "summary.json").write_text(json.dumps(summary(table)))
    shown = run(repo, env, "dvc", "metrics", "show")
    assert all(row in shown for row, _ in SUMMARY), shown
    width = max(len(line.rstrip()) for line in shown.splitlines())
    assert width <= 200, f"dvc metrics show is {width} columns wide:\n{shown}"

    for plot in DVC_YAML["plots"]:
        (repo / plot).parent.mkdir(parents=True, exist_ok=True)
        (repo / plot).write_bytes(b"\x89PNG\r\n\x1a\n")  # dvc copies image plots as they are
    run(repo, env, "dvc", "plots", "show", "-o", "plots")
    html = (repo / "plots" / "index.html").read_text()
    assert not re.search(r"""(src|href)=["']?(https?:)?//""", html), "the plots page loads from the network"
    assert html.count("<img") == len(DVC_YAML["plots"])
