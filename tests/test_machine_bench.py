"""benchmarks/machine.py: one line per shape, the summary line, and the JSON file."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "machine.py"


def _load():
    spec = importlib.util.spec_from_file_location("machine_bench", BENCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.usefixtures("one_thread")  # main() sets torch's thread count; the fixture restores it
def test_machine_benchmark_prints_and_writes_json(tmp_path, capsys, monkeypatch):
    bench = _load()
    monkeypatch.setattr(bench, "SHAPES", {"tiny": (32, 16, 8)})
    result = bench.main(["--threads", "1", "--repeats", "2", "--json", str(tmp_path / "m.json")])
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0].strip().startswith("tiny:") and lines[0].endswith("GFLOP/s")
    assert lines[-1].startswith(f"machine: {bench.cpu_model()}, 1 threads, fp32 matmul ")
    saved = json.loads((tmp_path / "m.json").read_text())
    assert saved == json.loads(json.dumps(result))
    assert saved["threads"] == 1 and saved["gflops"]["tiny"] > 0 and saved["gflops_median"] == saved["gflops"]["tiny"]
