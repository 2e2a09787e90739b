"""The two files of an evaluation folder (``artifacts/eval/<name>/``), written by ``stages.evaluate`` and
``stages.speed`` and read by ``stages.report``:

- ``metrics.json``: the rows, ``{row: {metric: finite number}}``;
- ``protocol.json``: what the figures were measured with besides the models, the ``evaluate``
  settings (less ``samples``) and the number of test items.

The report merges the folders into one table only when every folder's protocol is the real motions'
(``eval_real``): under DVC they always are, since every evaluation stage reads the whole ``evaluate``
section, but a stage run by hand with other settings (``python -m stages.evaluate emdm
evaluate.mm_times=2``) would otherwise put figures of two protocols side by side without a word.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

METRICS = "metrics.json"
PROTOCOL = "protocol.json"


def write_table(folder: Path, table: Mapping[str, Mapping[str, float]], settings: Mapping[str, Any],
                test_items: int) -> None:
    """``metrics.json`` (``table``) and ``protocol.json`` (``settings``, the evaluate fields, and
    ``test_items``) into ``folder``."""
    (folder / METRICS).write_text(json.dumps(table, indent=2) + "\n")
    (folder / PROTOCOL).write_text(json.dumps({"test_items": test_items, **settings}, indent=2) + "\n")


def _stage(folder: Path) -> str:
    return f"eval_{folder.name}"


def read_json(path: Path) -> Any:
    """A JSON file of an evaluation folder; one-line errors naming the file and the stage that writes it."""
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise FileNotFoundError(f"{path} is missing: run `dvc repro {_stage(path.parent)}` first") from None
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}: not valid JSON ({err})") from err


def read_table(folder: Path) -> dict[str, dict[str, float]]:
    """``folder``'s ``metrics.json``; ValueError naming the file and the first bad entry if it is not
    ``{row: {metric: finite number}}`` (a row dropped or a NaN carried into the report, without a word)."""
    path = folder / METRICS
    table = read_json(path)
    again = f"run `dvc repro {_stage(folder)}` to write it again"
    if not isinstance(table, dict) or not all(isinstance(metrics, dict) for metrics in table.values()):
        raise ValueError(f"{path}: expected {{row: {{metric: number}}}}; {again}")
    for row, metrics in table.items():
        for key, value in metrics.items():
            if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
                raise ValueError(f"{path}: {row}: {key} is {value!r}, not a finite number; {again}")
    return table


def check_protocols(reference: Path, folders: list[Path]) -> None:
    """Each folder's ``protocol.json`` equals ``reference``'s; ValueError naming the folder, each setting that
    differs with both values, and the command that scores it again. Pass only folders with rows: one whose
    family trained nothing (action labels on a dataset without them) adds nothing to mix."""
    expected = read_json(reference / PROTOCOL)
    for folder in folders:
        found = read_json(folder / PROTOCOL)
        if found != expected:
            keys = sorted(set(found) | set(expected), key=lambda k: (k != "test_items", k))
            differ = [f"{key} {found.get(key)!r} against {expected.get(key)!r}" for key in keys
                      if found.get(key) != expected.get(key)]
            raise ValueError(f"{folder / PROTOCOL}: scored with another protocol than {reference.name} "
                             f"({'; '.join(differ)}): run `dvc repro {_stage(folder)}` to score it again "
                             f"with the same settings")
