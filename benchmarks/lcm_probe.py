"""Probe: distill ``distill_lcm`` with overrides and score MotionLCM-1/2/4 on the validation split.

    python benchmarks/lcm_probe.py <name> [key=value ...]     # env: GUIDES=2.5,3.5 MLD=1 ARTIFACTS=artifacts

Trains in-process into ``/tmp/probe/art_<name>`` on top of the teacher, VAE and evaluator under
``$ARTIFACTS`` (symlinked), then prints and appends to ``/tmp/probe/results.jsonl`` the validation
FID and R@3 (one replication) of each step count at each sampling guidance in ``$GUIDES``; with
``MLD=1`` also MLD-DDIM50 and DDIM1 for reference. Used for docs/motionlcm.md.
"""
import json
import os
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from pipelines.config import load_params  # noqa: E402
from pipelines.mld_family import MLDGenerator, MotionLCMGenerator, load_mld, load_motionlcm, load_vae  # noqa: E402
from pipelines.stage import train  # noqa: E402
from pipelines.validation import generator_scores  # noqa: E402
from stages import distill_lcm  # noqa: E402

if len(sys.argv) < 2 or sys.argv[1] in ("-h", "--help") or "=" in sys.argv[1]:
    raise SystemExit(__doc__)  # a name first: without this guard --help would start a training
name, overrides = sys.argv[1], sys.argv[2:]
art = Path(f"/tmp/probe/art_{name}")
art.mkdir(parents=True, exist_ok=True)
source = Path(os.environ.get("ARTIFACTS", "artifacts")).resolve()
for d in ("train_evaluator", "train_vae", "train_mld"):
    if not (art / d).exists():
        os.symlink(source / d, art / d)
params = load_params([f"paths.artifacts={art}", f"features.out={source / 'features'}",
                      "paths.ray_storage=/tmp/probe/ray", "ray.num_workers=0", *overrides])
t0 = time.time()
train(distill_lcm.STAGE, params)
t1 = time.time()
_, schedule, _ = load_mld(art / "train_mld")
vae = load_vae(art / "train_vae")
student = load_motionlcm(art / "distill_lcm")
out = {"name": name, "overrides": overrides, "train_s": round(t1 - t0)}
torch.set_num_threads(2)
for n in (1, 2, 4):
    for g in [float(x) for x in os.environ.get("GUIDES", str(params["sample"]["motionlcm_guidance"])).split(",")]:
        gen = MotionLCMGenerator(f"MotionLCM-{n}", student, vae, schedule, n, g)
        with torch.inference_mode():
            s = generator_scores(params, gen)
        out[f"lcm{n}_g{g}"] = {k: round(v, 3) for k, v in s.items()}
if os.environ.get("MLD"):
    denoiser, schedule, _ = load_mld(art / "train_mld")
    for n in (50, 1):
        gen = MLDGenerator(f"MLD-DDIM{n}", denoiser, vae, schedule, n, params["sample"]["mld_guidance"])
        with torch.inference_mode():
            out[f"mld{n}"] = {k: round(v, 3) for k, v in generator_scores(params, gen).items()}
print(json.dumps(out))
with open("/tmp/probe/results.jsonl", "a") as f:
    f.write(json.dumps(out) + "\n")
