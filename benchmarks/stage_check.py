"""Every training stage for a few steps under settings the pipeline does not run here.

    python benchmarks/stage_check.py [--workers 2] [--steps 4] [--chain] [--artifacts artifacts]
        [--scratch /tmp/motionforge_stage_check] [--stages STAGE ...] [OVERRIDE ...]

Two uses: several Ray Train workers (DDP) as on a cluster (``--workers 2``, the default), and the
papers' sizes (``--workers 0 --chain scale=paper``, in-process). Needs a finished pipeline's ``artifacts/`` for the
stages' inputs; nothing under it changes. Each stage runs as ``python -m stages.<stage>
ray.num_workers=<workers> ray.cpus_per_worker=1 paths.artifacts=<scratch> <section>.loop.max_steps=<steps>
OVERRIDE ...``. Without ``--chain`` each stage gets its own scratch folder, in which every artifact but
its own outputs is a link to ``--artifacts``. With ``--chain`` the stages share one scratch folder, run
in pipeline order, and each reads the outputs the stages before it wrote there (needed when the
overrides change the models' shapes). Prints one line per stage (exit status, wall seconds, the first
error line) and exits 1 if any stage failed.
"""
import argparse
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

#: stage -> (its output folders, the loops whose max_steps are cut), in pipeline order
STAGES = {
    "train_evaluator": (("train_evaluator", "train_evaluator_movement", "train_evaluator_recogniser"),
                        ("train_evaluator.loop", "train_evaluator.movement_loop",
                         "train_evaluator.recogniser.loop")),
    "train_vae": (("train_vae",), ("train_vae.loop",)),
    "train_mld": (("train_mld",), ("train_mld.loop",)),
    "distill_lcm": (("distill_lcm",), ("distill_lcm.loop",)),
    "train_controlnet": (("train_controlnet",), ("train_controlnet.loop",)),
    "train_emdm": (("train_emdm",), ("train_emdm.loop",)),
    "train_emdm_action": (("train_emdm_action",), ("train_emdm_action.loop",)),
    "train_motiondiffuse": (("train_motiondiffuse",), ("train_motiondiffuse.loop",)),
}


def scratch_folder(folder: Path, artifacts: Path, fresh: set[str]) -> Path:
    """``folder``, emptied, with a link to every artifact whose name is not in ``fresh``."""
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    for entry in sorted(artifacts.iterdir()):
        if entry.name not in fresh:
            (folder / entry.name).symlink_to(entry.resolve())
    return folder


def first_error(log: str) -> str:
    """The first line of ``log`` that names an exception, or ''."""
    match = re.search(r"^.*\b\w*(Error|Exception): .*$", log, re.MULTILINE)
    return match.group(0).strip()[:160] if match else ""


def run_stage(stage: str, folder: Path, workers: int, steps: int, overrides: list[str]) -> tuple[int, float, str]:
    """Runs the stage in ``folder``; returns (exit status, wall seconds, :func:`first_error` of its log)."""
    cmd = [sys.executable, "-m", f"stages.{stage}", f"ray.num_workers={workers}", "ray.cpus_per_worker=1",
           f"paths.artifacts={folder}", f"paths.ray_storage={folder / 'ray'}",
           *[f"{loop}.max_steps={steps}" for loop in STAGES[stage][1]], *overrides]
    start = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=Path(__file__).resolve().parents[1])
    log = done.stdout + done.stderr
    (folder / f"{stage}.log").write_text(log)
    return done.returncode, time.perf_counter() - start, first_error(log)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("overrides", nargs="*", metavar="OVERRIDE", help="params overrides for every stage")
    parser.add_argument("--stages", nargs="+", default=list(STAGES), choices=list(STAGES), metavar="STAGE")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--steps", type=int, default=4)
    parser.add_argument("--chain", action="store_true", help="one scratch folder; each stage reads the last ones'")
    parser.add_argument("--artifacts", type=Path, default=Path("artifacts"))
    parser.add_argument("--scratch", type=Path, default=Path("/tmp/motionforge_stage_check"))
    args = parser.parse_args(argv)
    if args.steps < 2:
        parser.error("--steps must be at least 2 (DDP's checks act from the second step)")
    if not args.artifacts.is_dir():
        parser.error(f"{args.artifacts} is not a folder; run the pipeline first (make repro)")
    stages = [stage for stage in STAGES if stage in args.stages]
    if args.chain:
        shared = scratch_folder(args.scratch, args.artifacts, {out for s in stages for out in STAGES[s][0]})
    failed = 0
    for stage in stages:
        folder = shared if args.chain else scratch_folder(args.scratch / stage, args.artifacts, set(STAGES[stage][0]))
        code, seconds, error = run_stage(stage, folder, args.workers, args.steps, args.overrides)
        failed += code != 0
        print(f"{stage:20s} rc={code} {seconds:6.1f} s {error}".rstrip(), flush=True)
        if code != 0:
            print(f"{'':20s} log: {folder / f'{stage}.log'}", flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
