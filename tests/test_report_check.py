"""The results-table check CI runs after the smoke pipeline (pipelines/report_check.py): a complete table
passes; a missing family, a dropped or changed row, a missing core metric or a NaN fails with one line each,
and so does a missing, empty or incomplete speed table."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from pipelines.registry import FAMILIES
from pipelines.report_check import SOURCES, check_rows, main

TEXT_ROW = {"R_precision_top1": 0.2, "R_precision_top2": 0.3, "R_precision_top3": 0.4, "FID": 1.5, "MM_Dist": 3.0,
            "Diversity": 2.0, "FID_ci": 0.1}
ACTION_ROW = {"Accuracy": 0.8, "FID": 2.0, "Diversity": 1.0, "MultiModality": 0.5}
SPEED_ROW = {"ms_per_frame": 0.5, "AITS_s": 0.05, "NFE": 20.0, "params_M": 1.2, "speedup": 100.0, "rounds": 2.0}


def _write(path: Path, table: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(table))


def eval_dir(root: Path) -> Path:
    """Every source's table as its stage writes it, and the merged table the report stage writes."""
    merged = {}
    for source in SOURCES:
        table = {f"{source}-row": dict(ACTION_ROW if source == "emdm-action" else TEXT_ROW)}
        _write(root / source / "metrics.json", table)
        merged |= table
    _write(root / "metrics.json", merged)
    _write(root / "speed" / "metrics.json", {"EMDM-10": dict(SPEED_ROW), "MotionDiffuse-1000": dict(SPEED_ROW)})
    return root


def test_sources_are_real_and_every_registered_family() -> None:
    assert SOURCES == ("real", *FAMILIES) and "motiondiffuse" in SOURCES


def test_a_complete_table_passes(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    root = eval_dir(tmp_path)
    assert check_rows(root) == []
    main([str(root)])
    assert capsys.readouterr().out == (f"report check: {len(SOURCES)} rows from {len(SOURCES)} evaluation stages "
                                       f"in {root / 'metrics.json'}\n")


def test_every_problem_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    root = eval_dir(tmp_path)
    merged_path = root / "metrics.json"
    merged = json.loads(merged_path.read_text())
    del merged["mld-row"]                       # a family's row dropped by the merge
    merged["vae-row"]["FID"] = 9.0              # a row changed on the way
    del merged["real-row"]["MM_Dist"]           # a core metric missing (also: differs from its source)
    merged["emdm-row"]["Diversity"] = float("nan")
    _write(merged_path, merged)
    (root / "baselines" / "metrics.json").unlink()  # a family's stage wrote nothing
    _write(root / "motionlcm" / "metrics.json", {})
    expected = [
        f"{merged_path}: row 'real-row' differs from {root / 'real' / 'metrics.json'}",
        f"{root / 'baselines' / 'metrics.json'}: missing",
        f"{merged_path}: row 'vae-row' differs from {root / 'vae' / 'metrics.json'}",
        f"{merged_path}: row 'mld-row' of mld is missing",
        f"{root / 'motionlcm' / 'metrics.json'}: no rows",
        f"{merged_path}: row 'emdm-row' differs from {root / 'emdm' / 'metrics.json'}",
        f"{merged_path}: row 'real-row' has no MM_Dist",
        f"{merged_path}: row 'emdm-row': not a finite number: Diversity=nan",
    ]
    assert check_rows(root) == expected
    with pytest.raises(SystemExit) as exc:
        main([str(root)])
    assert exc.value.code == 1
    assert capsys.readouterr().err.splitlines() == [f"report check: {line}" for line in expected]


def test_action_rows_need_the_action_metrics(tmp_path: Path) -> None:
    root = eval_dir(tmp_path)
    merged = json.loads((root / "metrics.json").read_text())
    del merged["emdm-action-row"]["Accuracy"]  # without an Accuracy it is judged as a text row
    _write(root / "metrics.json", merged)
    problems = check_rows(root)
    assert f"{root / 'metrics.json'}: row 'emdm-action-row' has no R_precision_top1" in problems


def test_the_speed_table_must_be_there_with_its_timing_figures(tmp_path: Path) -> None:
    root = eval_dir(tmp_path)
    speed_path = root / "speed" / "metrics.json"
    _write(speed_path, {"EMDM-10": {**SPEED_ROW, "speedup": float("inf")},
                        "MotionDiffuse-1000": {k: v for k, v in SPEED_ROW.items() if k != "params_M"}})
    assert check_rows(root) == [f"{speed_path}: row 'EMDM-10' has no finite speedup",
                                f"{speed_path}: row 'MotionDiffuse-1000' has no finite params_M"]
    _write(speed_path, {})
    assert check_rows(root) == [f"{speed_path}: no rows"]
    speed_path.unlink()
    assert check_rows(root) == [f"{speed_path}: missing"]


def test_a_missing_report_is_the_only_problem(tmp_path: Path) -> None:
    assert check_rows(tmp_path) == [f"{tmp_path / 'metrics.json'}: missing"]
