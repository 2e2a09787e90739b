"""Probe: train ``train_controlnet`` with overrides and measure its control error and the refinement's.

    python benchmarks/control_probe.py <name> [key=value ...]     # env: ARTIFACTS=artifacts ITEMS=128 DENSITY=100%

Trains in-process into ``/tmp/probe/cn_<name>`` on top of the student, teacher, VAE and features
under ``$ARTIFACTS`` (symlinked); with the name ``existing`` it skips training and probes
``$ARTIFACTS/train_controlnet``; with ``TRAIN=0`` it scores the ControlNet an earlier probe of that
name trained, if there is one (e.g. again with another ``ITEMS``). Then, on the first ``$ITEMS``
test motions (first caption, full length, seed 0, ``sample.motionlcm_guidance``), pelvis hints at
``$DENSITY``: the control errors of MotionLCM-1 without control, of the ControlNet (again with each
step count of ``LCM_STEPS``, e.g. "2 4": MotionLCM's multistep sampling, fresh noise between steps
from seed 1; with ``HINT_ABLATION=1`` also given no hint and given the next motion's hint, still
scored against each motion's own path: what it owes to the hint; with ``RESIDUAL_SCALES``, e.g. "0.5
1.5 2", also with the ControlNet's residuals multiplied by each factor at sampling, as diffusers'
``controlnet_conditioning_scale``; with ``HINT_GUIDANCE``, e.g. "1.5 2", guided toward the hint:
``r(no hint) + s (r(hint) - r(no hint))``, two ControlNet passes), and of the noise refinement at
several (steps, lr) settings (``REFINE_SETTINGS``, default "5:0.1 10:0.1 ..."), plus batch-1 seconds
per motion of the ControlNet with 0/10/20/30 refinement steps (``REFINE=0`` skips the refinement
rows and timings). Each row also gets the T2M evaluator's FID against the same items' real motions,
R@3 (groups of 32), Diversity (``ITEMS=all`` for the whole test split) and the physical metrics;
``PROJECT=1`` adds each row again after the root projection (:mod:`data.root_projection`). Prints
one JSON line per measurement. Used for docs/controlnet.md.
"""
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from data.control import evaluation_mask  # noqa: E402
from data.features import recover_from_ric  # noqa: E402
from data.motion_dataset import pad_tokens  # noqa: E402
from data.root_projection import project_root  # noqa: E402
from data.skeleton import get_skeleton  # noqa: E402
from models import metrics as M  # noqa: E402
from models.controlnet import ControlledStudent, refine_noise  # noqa: E402
from models.motionlcm import motionlcm_latents  # noqa: E402
from pipelines.config import load_params  # noqa: E402
from pipelines.controlnet_family import load_controlnet  # noqa: E402
from pipelines.evaluation import load_evaluator  # noqa: E402
from pipelines.feature_store import FeatureStore  # noqa: E402
from pipelines.mld_family import load_mld, load_motionlcm, load_vae  # noqa: E402
from pipelines.stage import train  # noqa: E402
from stages import train_controlnet  # noqa: E402

REFINE = [(int(steps), float(lr)) for steps, lr in (pair.split(":") for pair in
          os.environ.get("REFINE_SETTINGS", "5:0.1 10:0.1 20:0.1 30:0.1 10:0.05 10:0.3").split())]

torch.set_num_threads(2)
if len(sys.argv) < 2 or sys.argv[1] in ("-h", "--help") or "=" in sys.argv[1]:
    raise SystemExit(__doc__)  # a name first: without this guard --help would start a training
name, overrides = sys.argv[1], sys.argv[2:]
source = Path(os.environ.get("ARTIFACTS", "artifacts")).resolve()
art = source if name == "existing" else Path(f"/tmp/probe/cn_{name}")
params = load_params([f"paths.artifacts={art}", f"features.out={source / 'features'}",
                      "paths.ray_storage=/tmp/probe/ray", "ray.num_workers=0", *overrides])
if name != "existing" and not (os.environ.get("TRAIN") == "0" and (art / "train_controlnet").is_dir()):
    art.mkdir(parents=True, exist_ok=True)
    for d in ("train_vae", "train_mld", "distill_lcm"):
        if not (art / d).exists():
            os.symlink(source / d, art / d)
    start = time.time()
    train(train_controlnet.STAGE, params)
    print(json.dumps({"name": name, "overrides": overrides, "train_s": round(time.time() - start)}))

store = FeatureStore(source / "features")
vae, (_, schedule, _) = load_vae(source / "train_vae"), load_mld(source / "train_mld")
student = load_motionlcm(source / "distill_lcm")
controlnet = load_controlnet(art / "train_controlnet", student)
count = os.environ.get("ITEMS", "128")
items = store.split("test")[: None if count == "all" else int(count)]
lengths = torch.tensor([item.length for item in items])
raw = np.zeros((len(items), int(lengths.max()), store.feature_dim), np.float32)
for k, item in enumerate(items):
    raw[k, : item.length] = item.features
target = recover_from_ric(raw, store.joints_num)
mask = evaluation_mask(lengths.numpy(), raw.shape[1], store.joints_num, [0], os.environ.get("DENSITY", "100%"),
                       np.random.default_rng(0))
hint, hint_mask = torch.from_numpy(target).float(), torch.from_numpy(mask)
text = torch.from_numpy(np.stack([item.text_pooled[0] for item in items]).astype(np.float32))
tokens, token_mask = pad_tokens([np.asarray(item.text_tokens[0], np.float32) for item in items])
w = params["sample"]["motionlcm_guidance"] - 1.0
mean, std = torch.from_numpy(store.mean), torch.from_numpy(store.std)
scale = student.config.latent_scale
embedder = load_evaluator(source / "train_evaluator")
skeleton = get_skeleton(params["data"]["skeleton"])
valid = np.arange(raw.shape[1])[None, :] < lengths.numpy()[:, None]
text_emb = embedder.texts([item.tokens[0] for item in items])
real_stats = M.gaussian_statistics(embedder.motions(raw, lengths.numpy()))


def noise(index: slice = slice(None)) -> torch.Tensor:
    """The initial noise of the first ``len(items)`` samples drawn at once with seed 0, rows ``index``."""
    shape = (len(items), student.config.latent_tokens, student.config.latent_dim)
    return torch.randn(shape, generator=torch.Generator().manual_seed(0))[index]


def latents(model: torch.nn.Module, index: slice = slice(None), x_T: torch.Tensor | None = None,
            steps: int = 1) -> torch.Tensor:
    return motionlcm_latents(model, schedule, text[index], steps, w, torch.Generator().manual_seed(1),
                             text_tokens=tokens[index], text_mask=token_mask[index],
                             x_T=noise(index) if x_T is None else x_T)


def errors(z: torch.Tensor, project: bool = False) -> dict[str, float]:
    with torch.no_grad():
        features = vae.decode_by_length(z * scale, lengths).numpy()
    generated = np.where(valid[..., None], features * store.std + store.mean, 0.0).astype(np.float32)
    if project:
        generated = project_root(generated, target, mask, lengths.numpy(), store.joints_num)
    joints = recover_from_ric(generated, store.joints_num)
    motion_emb = embedder.motions(generated, lengths.numpy())
    quality = {"FID": M.frechet_distance(*M.gaussian_statistics(motion_emb), *real_stats),
               "R@3": float(M.r_precision(text_emb, motion_emb, 32, top_k=3)[2]),
               "Diversity": M.diversity(motion_emb, min(300, len(motion_emb) - 1), np.random.default_rng(0))}
    physics = M.physical_metrics([joints[k, :n] for k, n in enumerate(lengths.numpy())], skeleton)
    control = M.control_errors(joints, target, mask, unit=skeleton.unit)
    return {k: round(v, 3) for k, v in (control | quality | physics).items()}


def report(row: str, z: torch.Tensor) -> None:
    print(json.dumps({"name": name, "row": row, **errors(z)}), flush=True)
    if os.environ.get("PROJECT") == "1":
        print(json.dumps({"name": name, "row": row + " +project", **errors(z, project=True)}), flush=True)


def refine(model: torch.nn.Module, steps: int, lr: float, index: slice = slice(None)) -> torch.Tensor:
    return refine_noise(lambda x: latents(model, index, x), vae, noise(index), model.hint, model.mask,
                        lengths[index], mean=mean, std=std, latent_scale=scale, steps=steps, lr=lr)


class ScaledResiduals(torch.nn.Module):
    """The ControlNet with its residuals multiplied by ``factor`` (sampling only; 1 is the trained model)."""

    def __init__(self, controlnet: torch.nn.Module, factor: float) -> None:
        super().__init__()
        self.controlnet, self.factor = controlnet, factor

    def forward(self, *args: torch.Tensor, **kwargs: torch.Tensor | None) -> list[torch.Tensor]:
        return [self.factor * r for r in self.controlnet(*args, **kwargs)]


class HintGuided(torch.nn.Module):
    """The ControlNet's residuals guided toward the hint, ``r(no hint) + s (r(hint) - r(no hint))`` (sampling only)."""

    def __init__(self, controlnet: torch.nn.Module, scale: float) -> None:
        super().__init__()
        self.controlnet, self.scale = controlnet, scale

    def forward(self, z_t: torch.Tensor, t: torch.Tensor | int, text_emb: torch.Tensor, hint: torch.Tensor,
                mask: torch.Tensor, **kwargs: torch.Tensor | None) -> list[torch.Tensor]:
        guided = self.controlnet(z_t, t, text_emb, hint, mask, **kwargs)
        free = self.controlnet(z_t, t, text_emb, hint, torch.zeros_like(mask), **kwargs)
        return [r0 + self.scale * (r1 - r0) for r0, r1 in zip(free, guided, strict=True)]


report("uncontrolled", latents(student))
controlled = ControlledStudent(student, controlnet, hint, hint_mask)
report("controlnet", latents(controlled))
if os.environ.get("HINT_ABLATION") == "1":
    report("controlnet, no hint", latents(ControlledStudent(student, controlnet, hint, torch.zeros_like(hint_mask))))
    other_mask = hint_mask.roll(1, 0) & torch.from_numpy(valid)[..., None]  # within each motion's own length
    report("controlnet, the next motion's hint",
           latents(ControlledStudent(student, controlnet, hint.roll(1, 0), other_mask)))
for factor in os.environ.get("RESIDUAL_SCALES", "").split():
    report(f"controlnet, residuals x {factor}",
           latents(ControlledStudent(student, ScaledResiduals(controlnet, float(factor)), hint, hint_mask)))
for strength in os.environ.get("HINT_GUIDANCE", "").split():
    report(f"controlnet, hint guidance {strength}",
           latents(ControlledStudent(student, HintGuided(controlnet, float(strength)), hint, hint_mask)))
for lcm_steps in os.environ.get("LCM_STEPS", "").split():
    report(f"uncontrolled steps={lcm_steps}", latents(student, steps=int(lcm_steps)))
    report(f"controlnet steps={lcm_steps}", latents(controlled, steps=int(lcm_steps)))
if os.environ.get("REFINE", "1") == "0":
    sys.exit(0)
for steps, lr in REFINE:
    report(f"refine steps={steps} lr={lr}", refine(controlled, steps, lr))

first = int(lengths[0])
single = ControlledStudent(student, controlnet, hint[:1, :first], hint_mask[:1, :first])
for steps in (0, 10, 20, 30):
    seconds = []
    for _ in range(6):  # the first is a warm-up
        start = time.perf_counter()
        z = refine(single, steps, 0.1, slice(0, 1))
        with torch.no_grad():
            vae.decode_by_length(z * scale, lengths[:1])
        seconds.append(time.perf_counter() - start)
    print(json.dumps({"name": name, "batch1_refine_steps": steps, "frames": first,
                      "seconds": round(float(np.mean(seconds[1:])), 4)}))
