"""Do trained generators respect side, order and count words? Contrast pairs, measured on the joints.

    python benchmarks/contrasts.py [--models mld,motionlcm,emdm,motiondiffuse] [--seeds 4] [--length 120]
                                   [--json out.json] [key=value ...]

Four pairs of prompts that differ only in a side, order or count word, worded as the synthetic
captions word them (``data/synthetic_text.py``: "kicks with their left leg", "waves with the left
hand", "A, then B", "jumps in place" for one jump and "jumps in place three times"). Every prompt
is sampled alone (a batch of one) for each seed, so the two prompts of a pair start from the same
noise and differ only by their text, as two ``stages.generate --text ... --seed S`` calls do.
On the global joints (T, 22, 3) (metres, y up, HumanML3D order) each prompt has a measure and a
pass criterion:

``side`` pairs (kick, wave): the side whose limb does more. ``rise`` of a foot is the highest
lift, over the motion, of its ankle or toe above that joint's own 10th-percentile height
(standing height): a synthetic kick lifts the kicking foot to about hip height or above and the
standing foot not at all. A kick passes when the named foot rises highest and by at least 0.20 m,
above the 0.10-0.15 m that a walking step's swing lifts an ankle, so that a model that stands
still does not pass half the time by chance. ``up`` of a hand is the number of frames its wrist
is above the head joint: a synthetic wave holds the waving wrist above the head for a second or
more while the other arm hangs. A wave passes when the named wrist is up for more frames than
the other and for at least 10 frames (0.5 s, the criterion of ``prompt_probe.py``).

``order`` pair (walk forward / turn around): ``walk_t`` is the time centroid (seconds) of the
pelvis's horizontal speed and ``turn_t`` that of the heading's rate of change. The heading comes
from the hip axis plus the shoulder axis (so that a hip axis squeezed short does not swing it),
unwrapped and smoothed over 0.45 s (so that the pelvis's yaw swing within each stride does not
add up to a turn). "walks forward, then turns around" passes when ``walk_t < turn_t``, the
reverse prompt when ``turn_t < walk_t``; both need the motion to hold the two actions: ``path``
(horizontal pelvis path length) at least 0.5 m and ``turn`` (net heading change, degrees) at
least 90 (the synthetic "turns around" is 180).

``count`` pair (jumps): ``jumps`` counts airborne episodes: runs of at least 2 frames (0.1 s)
with both feet (lowest of ankle and toe) more than 5 cm above the floor (the 10th percentile of
the lowest foot, as in ``prompt_probe.py``), where runs split by a single grounded frame are one.
A synthetic jump is 12-30 cm high (``sample_jump``), so its feet stay more than 5 cm up for
several frames, and repeated jumps stay landed for more than 0.1 s in between. "jumps in place"
passes on exactly 1, "jumps in place three times" on exactly 3.

``jitter`` (every motion): the mean length of the joints' second difference over time (metres
per frame squared). A motion above 0.1 fails every criterion: its per-frame heights and body
axes are noise that fakes kicks, jumps (every jittery landing is an "episode") and turns. The
threshold is about three times the largest value over the dataset's motions and far below the
jittery samples of EMDM and MotionDiffuse (``docs/emdm.md``, ``docs/motiondiffuse.md``).

``differ`` (per pair and seed): the mean per-joint distance (metres) between the two prompts'
motions of the same seed, root-relative (pelvis subtracted) so that a different route alone does
not count; near 0 means that the contrast word changed nothing.

The criteria were checked on the dataset's own motions with these captions (``docs/contrasts.md``).
The table prints, per model and prompt, each seed's measures and the pass count; ``--json``
writes the same numbers.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.prompt_probe import eval_context  # noqa: E402
from data.joint_measures import (  # noqa: E402
    FPS,
    PELVIS,
    foot_rise,
    heading,
    jump_count,
    wrist_up,
)
from pipelines.registry import GenerateOptions, family  # noqa: E402

KICK_RISE = 0.20  # metres
WAVE_FRAMES = 10
MIN_PATH, MIN_TURN = 0.5, 90.0  # metres, degrees
JITTER_MAX = 0.1  # metres per frame squared

#: model -> generate options: the family's generator as ``stages.generate --model`` builds it,
#: MotionDiffuse with DDIM 10 steps (its default DDPM takes 1000 steps).
MODELS = {"mld": GenerateOptions(), "motionlcm": GenerateOptions(), "emdm": GenerateOptions(),
          "motiondiffuse": GenerateOptions(steps=10)}


# --------------------------------------------------------------------------------------------------
# Measures on global joints (T, 22, 3)
# --------------------------------------------------------------------------------------------------






def _centroid(weights: np.ndarray) -> float:
    """Time (seconds) of the centroid of per-interval ``weights`` (interval k is centred at k + 0.5 frames)."""
    total = weights.sum()
    if total <= 0:
        return float("nan")
    return float(((np.arange(len(weights)) + 0.5) * weights).sum() / total / FPS)




def order(joints: np.ndarray) -> dict[str, float]:
    """``walk_t``/``turn_t``: time centroids (s) of pelvis speed and of heading change; ``path`` (m), ``turn`` (deg)."""
    steps = np.linalg.norm(np.diff(joints[:, PELVIS][:, [0, 2]], axis=0), axis=1)
    h = heading(joints)
    rate = np.abs(np.diff(h))
    return {"walk_t": _centroid(steps), "turn_t": _centroid(rate), "path": float(steps.sum()),
            "turn": float(np.degrees(abs(h[-1] - h[0])))}






def jitter(joints: np.ndarray) -> float:
    """Mean length (m per frame squared) of the joints' second difference over time."""
    return float(np.linalg.norm(np.diff(joints, 2, axis=0), axis=-1).mean())


def root_relative_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Mean per-joint distance (m) between two motions' pelvis-relative joints (first ``min(T)`` frames)."""
    n = min(len(a), len(b))
    a, b = a[:n] - a[:n, PELVIS:PELVIS + 1], b[:n] - b[:n, PELVIS:PELVIS + 1]
    return float(np.linalg.norm(a - b, axis=-1).mean())


# --------------------------------------------------------------------------------------------------
# Prompts and criteria
# --------------------------------------------------------------------------------------------------


def kick_measures(joints: np.ndarray) -> dict[str, float]:
    left, right = foot_rise(joints)
    return {"rise_l": left, "rise_r": right}


def wave_measures(joints: np.ndarray) -> dict[str, float]:
    left, right = wrist_up(joints)
    return {"up_l": float(left), "up_r": float(right)}


def jump_measures(joints: np.ndarray) -> dict[str, float]:
    return {"jumps": float(jump_count(joints))}


@dataclass(frozen=True)
class Prompt:
    """One prompt of a pair: its text, what passes (words) and the test on its measures."""

    text: str
    criterion: str
    passes: object  # (dict[str, float]) -> bool


@dataclass(frozen=True)
class Pair:
    name: str
    measure: object  # (joints) -> dict[str, float]
    prompts: tuple[Prompt, Prompt]


def _kick(side: str) -> Prompt:
    named, other = ("rise_l", "rise_r") if side == "left" else ("rise_r", "rise_l")
    return Prompt(f"a person kicks with their {side} leg", f"{side} foot rises highest, >= {KICK_RISE:.2f} m",
                  lambda m: m[named] > m[other] and m[named] >= KICK_RISE)


def _wave(side: str) -> Prompt:
    named, other = ("up_l", "up_r") if side == "left" else ("up_r", "up_l")
    return Prompt(f"a person waves with the {side} hand",
                  f"{side} wrist above head longer, >= {WAVE_FRAMES} frames",
                  lambda m: m[named] > m[other] and m[named] >= WAVE_FRAMES)


def _both(m: dict[str, float]) -> bool:
    return m["path"] >= MIN_PATH and m["turn"] >= MIN_TURN


PAIRS = (
    Pair("side: kick", kick_measures, (_kick("left"), _kick("right"))),
    Pair("side: wave", wave_measures, (_wave("left"), _wave("right"))),
    Pair("order: walk/turn", order, (
        Prompt("a person walks forward, then turns around",
               f"walk_t < turn_t, path >= {MIN_PATH} m, turn >= {MIN_TURN:.0f} deg",
               lambda m: _both(m) and m["walk_t"] < m["turn_t"]),
        Prompt("a person turns around, then walks forward",
               f"turn_t < walk_t, path >= {MIN_PATH} m, turn >= {MIN_TURN:.0f} deg",
               lambda m: _both(m) and m["turn_t"] < m["walk_t"]),
    )),
    Pair("count: jumps", jump_measures, (
        Prompt("a person jumps in place", "jumps == 1", lambda m: m["jumps"] == 1),
        Prompt("a person jumps in place three times", "jumps == 3", lambda m: m["jumps"] == 3),
    )),
)


def evaluate(joints: dict[str, np.ndarray], pair: Pair) -> dict:
    """``pair``'s measures and passes for one seed's motions (``joints``: prompt text -> (T, 22, 3))."""
    a, b = (joints[p.text] for p in pair.prompts)
    out = {"differ": root_relative_distance(a, b)}
    for prompt in pair.prompts:
        m = {**pair.measure(joints[prompt.text]), "jitter": jitter(joints[prompt.text])}
        out[prompt.text] = {"measures": m, "pass": m["jitter"] <= JITTER_MAX and bool(prompt.passes(m))}
    return out


# --------------------------------------------------------------------------------------------------
# Running and printing
# --------------------------------------------------------------------------------------------------


def sample_joints(generator, store, texts: list[str], length: int, seed: int) -> dict[str, np.ndarray]:
    """Each prompt alone (a batch of one) with ``seed``: prompt text -> global joints (length, 22, 3)."""
    lengths = np.array([length])
    out = {}
    for text in texts:
        features = generator.sample(store.encode_prompts([text]), lengths, seed)
        out[text] = store.to_joints(features, lengths)[0]
    return out


def _cell(measures: dict[str, float]) -> str:
    """The measures, and "jittery" when the jitter is over :data:`JITTER_MAX`."""
    cell = " ".join(f"{k} {v:.0f}" if k in ("up_l", "up_r", "jumps", "turn") else f"{k} {v:.2f}"
                    for k, v in measures.items() if k != "jitter")
    return cell + (" jittery" if measures.get("jitter", 0.0) > JITTER_MAX else "")


def table(name: str, seeds: list[dict]) -> str:
    """Markdown table of one model's results (``seeds``: per seed, pair name -> :func:`evaluate` output)."""
    n = len(seeds)
    head = f"| {name} | prompt | criterion (and jitter <= {JITTER_MAX}) | "
    lines = [head + " | ".join(f"seed {s}" for s in range(n)) + " | pass |",
             "|---|---|---|" + "---|" * n + "---|"]
    for pair in PAIRS:
        for prompt in pair.prompts:
            results = [seed[pair.name][prompt.text] for seed in seeds]
            passed = sum(r["pass"] for r in results)
            lines.append(f"| {pair.name} | {prompt.text} | {prompt.criterion} | "
                         + " | ".join(_cell(r["measures"]) + (" ✓" if r["pass"] else "") for r in results)
                         + f" | {passed}/{n} |")
        lines.append(f"| {pair.name} | (pair) | differ: mean joint distance (m) | "
                     + " | ".join(f"{seed[pair.name]['differ']:.3f}" for seed in seeds) + " | |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--models", default=",".join(MODELS), help="comma-separated model families")
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--length", type=int, default=120, help="frames (20 fps)")
    parser.add_argument("--json", type=Path, default=None, help="write the results here")
    parser.add_argument("overrides", nargs="*", help="params overrides, e.g. paths.artifacts=elsewhere")
    args = parser.parse_args(argv)
    ctx = eval_context(args.overrides)
    texts = [prompt.text for pair in PAIRS for prompt in pair.prompts]
    report = {}
    for model in args.models.split(","):
        start = time.perf_counter()
        generator = family(model).build_generator(ctx, MODELS.get(model, GenerateOptions()))
        seeds = []
        for seed in range(args.seeds):
            joints = sample_joints(generator, ctx.store, texts, args.length, seed)
            seeds.append({pair.name: evaluate(joints, pair) for pair in PAIRS})
        seconds = time.perf_counter() - start
        print(table(generator.name, seeds) + f"\n\n{generator.name}: {seconds:.0f} s\n", flush=True)
        report[model] = {"generator": generator.name, "seconds": seconds, "seeds": seeds}
    if args.json is not None:
        args.json.write_text(json.dumps({"length": args.length, "models": report}, indent=1), encoding="utf-8")


if __name__ == "__main__":
    main()
