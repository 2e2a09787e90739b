"""How much more does ``stages.generate`` take for ten prompts than for one? The whole command, timed.

Runs ``python -m stages.generate --model MODEL`` as a user does (a fresh process: imports, model
and text-encoder loading, sampling, writing) with one prompt and with ten (``--prompts``, the
same lengths), alternating, ``--repeats`` times per format, and prints the median wall times and
their ratio. The issue's target is a ratio of at most 2 (the models and the text encoder are
loaded once; drawn formats are written on one process per core).

Usage: ``python benchmarks/generate_prompts.py [--model mld] [--formats gif,bvh] [--repeats 3]``
(needs the model's stage outputs, e.g. ``dvc repro train_mld``).
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

PROMPTS = [
    "a person walks forward", "a person jumps in place", "a person waves with the right hand",
    "a person runs forward quickly", "a person turns around", "a person squats down and stands up",
    "a person kicks with the left leg", "a person walks backward slowly", "a person raises both arms",
    "a person steps to the left",
]
LENGTH = 120


def timed(args: list[str]) -> float:
    """Wall seconds of ``python -m stages.generate ARGS`` (raises if it fails)."""
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "stages.generate", *args], check=True, capture_output=True)
    return time.perf_counter() - start


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="mld")
    parser.add_argument("--formats", default="gif,bvh", help="comma-separated output formats")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        prompts = Path(tmp) / "prompts.txt"
        prompts.write_text("".join(f"{text} | {LENGTH}\n" for text in PROMPTS), encoding="utf-8")
        for fmt in args.formats.split(","):
            one, ten = [], []
            for k in range(args.repeats):
                one.append(timed(["--model", args.model, "--text", PROMPTS[0], "--length", str(LENGTH),
                                  "--out", f"{tmp}/one_{k}.{fmt}"]))
                ten.append(timed(["--model", args.model, "--prompts", str(prompts), "--format", fmt,
                                  "--out", f"{tmp}/ten_{k}"]))
            a, b = statistics.median(one), statistics.median(ten)
            runs = f"one: {', '.join(f'{t:.2f}' for t in one)}; ten: {', '.join(f'{t:.2f}' for t in ten)}"
            print(f"{args.model} {fmt}: one prompt {a:.2f} s, ten prompts {b:.2f} s (medians of {args.repeats}): "
                  f"{b / a:.2f}x   [{runs}]")


if __name__ == "__main__":
    main()
