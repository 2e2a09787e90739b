"""The T2M evaluation protocol (DESIGN.md "Evaluation protocol"; reference humanml3d_eval.md C).

One replication:

1. Shuffle the test items; per item pick one caption at random and a crop length
   L' = 4*floor(L/4) (probability 2/3) or 4*(floor(L/4) - 1) (1/3) at a random offset.
2. A second, independent draw of the real test motions gives the FID reference statistics
   (so "Real" vs reference FID is small but not zero, as in the reference).
3. Every row (Real, then each generator) answers the same captions with the same lengths; the
   evaluator embeds texts and motions; R-precision top-1/2/3 within consecutive groups of
   ``group_size`` (32), MM-Dist, FID, Diversity; MultiModality for stochastic generators
   (``mm_texts`` texts x ``mm_repeats`` samples, ``mm_times`` pairs); physical measures
   (skating, penetration, floating) of the motions recovered as joints.

Each metric is reported as mean and 1.96*std/sqrt(R) over R replications (``<key>_ci``).
AITS (seconds per sentence, batch 1, warm, loading excluded) and ms per frame are timed once
per generator on ``timing_sentences`` test captions.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from data.features import recover_from_ric
from data.skeleton import Skeleton
from data.store import StoredItem
from data.vocab import WordVocab
from models import metrics as M
from models.evaluator import EvaluatorConfig, T2MEvaluator
from models.generator import Generator, Reconstructor, TextBatch
from pipelines.checkpoint import load_final_model
from pipelines.generators import pad_motions

REAL = "Real"


@dataclass(frozen=True)
class EvalConfig:
    """The ``evaluate`` params section (paper values in brackets)."""

    replications: int = 20
    group_size: int = 32
    diversity_times: int = 300
    mm_texts: int = 100
    mm_repeats: int = 30
    mm_times: int = 10
    timing_sentences: int = 10
    unit_length: int = 4
    max_words: int = 20
    seed: int = 0


def build_evaluator(config: EvaluatorConfig, mean: Sequence[float], std: Sequence[float],
                    word_vectors: torch.Tensor | None = None) -> T2MEvaluator:
    """A fresh evaluator with its normalisation statistics set from the dataset's Mean/Std."""
    evaluator = T2MEvaluator(config, word_vectors=word_vectors)
    evaluator.set_normalization(np.asarray(mean, np.float32), np.asarray(std, np.float32))
    return evaluator


def load_evaluator(out_dir: Path) -> MotionEmbedder:
    """The trained evaluator of ``train_evaluator``'s output folder, ready to embed."""
    payload = load_final_model(out_dir)
    config = payload["config"]
    evaluator = build_evaluator(EvaluatorConfig.from_dict(config["model"]), config["mean"], config["std"])
    evaluator.load_state_dict(payload["models"]["evaluator"])
    return MotionEmbedder(evaluator, WordVocab.from_dict(config["vocab"]), config["max_words"])


class MotionEmbedder:
    """The trained evaluator as two functions: captions -> (B, E), raw motions -> (B, E)."""

    def __init__(self, evaluator: T2MEvaluator, vocab: WordVocab, max_words: int, batch: int = 256) -> None:
        self.evaluator = evaluator.eval()
        self.vocab = vocab
        self.max_words = max_words
        self.batch = batch

    @torch.inference_mode()
    def texts(self, tokens: Sequence[Sequence[str]]) -> np.ndarray:
        out = []
        for first in range(0, len(tokens), self.batch):
            ids, pos, lens = self.vocab.encode_batch(tokens[first : first + self.batch], self.max_words)
            out.append(self.evaluator.embed_text(ids, pos, lens).numpy())
        return np.concatenate(out)

    @torch.inference_mode()
    def motions(self, raw: np.ndarray, lengths: np.ndarray) -> np.ndarray:
        """``raw`` (B, T, D) un-normalised features, zero or anything past ``lengths``."""
        out = []
        for first in range(0, len(raw), self.batch):
            x = self.evaluator.normalize(torch.as_tensor(raw[first : first + self.batch]))
            out.append(self.evaluator.embed_motion(x, lengths[first : first + self.batch]).numpy())
        return np.concatenate(out)


def crop_lengths(lengths: np.ndarray, rng: np.random.Generator, unit: int = 4) -> np.ndarray:
    """Reference crop lengths: 4*floor(L/4) w.p. 2/3, else 4*(floor(L/4) - 1); at least ``unit``."""
    units = lengths // unit
    double = rng.random(len(lengths)) < 1 / 3
    return np.maximum(np.where(double, units - 1, units), 1) * unit


@dataclass
class Draw:
    """One random pass over the test items: captions, crop lengths and real crops."""

    text: TextBatch
    tokens: list[list[str]]
    lengths: np.ndarray
    real: np.ndarray  # (B, max L', D) raw features


def draw(items: Sequence[StoredItem], rng: np.random.Generator, unit: int) -> Draw:
    """Shuffle ``items``, pick a caption of each and crop its motion (step 1 of a replication)."""
    order = rng.permutation(len(items))
    chosen = [items[k] for k in order]
    captions = [int(rng.integers(len(item.captions))) for item in chosen]
    lengths = crop_lengths(np.array([item.length for item in chosen]), rng, unit)
    crops = []
    for item, length in zip(chosen, lengths, strict=True):
        start = int(rng.integers(0, item.length - length + 1))
        crops.append(item.features[start : start + length])
    text = TextBatch(
        texts=[item.captions[c] for item, c in zip(chosen, captions, strict=True)],
        pooled=np.stack([item.text_pooled[c] for item, c in zip(chosen, captions, strict=True)]),
        tokens=[item.text_tokens[c] for item, c in zip(chosen, captions, strict=True)],
    )
    tokens = [item.tokens[c] for item, c in zip(chosen, captions, strict=True)]
    return Draw(text, tokens, lengths, pad_motions(crops, lengths))


def physical(raw: np.ndarray, lengths: np.ndarray, skeleton: Skeleton) -> dict[str, float]:
    """Skating ratio, penetration and floating (mm) of raw features recovered as joints."""
    joints = [recover_from_ric(raw[b, :length], skeleton.joints_num) for b, length in enumerate(lengths)]
    return M.physical_metrics(joints, skeleton)


def mpjpe_mm(real: np.ndarray, recon: np.ndarray, lengths: np.ndarray, joints_num: int) -> float:
    """Root-aligned mean per-joint position error (mm) of two raw feature sets' recovered joints.

    As MLD's reconstruction metric: per frame, both skeletons are moved so their root joints
    coincide, then the joint distances are averaged over valid frames and joints.
    """
    errors = []
    for b, n in enumerate(lengths):
        a, r = recover_from_ric(real[b, :n], joints_num), recover_from_ric(recon[b, :n], joints_num)
        errors.append(np.linalg.norm((a - a[:, :1]) - (r - r[:, :1]), axis=-1).reshape(-1))
    return 1000.0 * float(np.concatenate(errors).mean())


def text_metrics(text_emb: np.ndarray, motion_emb: np.ndarray, ref: tuple[np.ndarray, np.ndarray],
                 cfg: EvalConfig, rng: np.random.Generator) -> dict[str, float]:
    """R-precision top-1/2/3, MM-Dist, FID against ``ref`` (mu, sigma) and Diversity."""
    top = M.r_precision(text_emb, motion_emb, cfg.group_size, top_k=3)
    usable = cfg.group_size * (len(text_emb) // cfg.group_size)
    return {
        "R_precision_top1": float(top[0]),
        "R_precision_top2": float(top[1]),
        "R_precision_top3": float(top[2]),
        "MM_Dist": M.matching_score(text_emb[:usable], motion_emb[:usable]),
        "FID": M.frechet_distance(*M.gaussian_statistics(motion_emb), *ref),
        "Diversity": M.diversity(motion_emb, cfg.diversity_times, rng),
    }


def denormalise(features: np.ndarray, mean: np.ndarray, std: np.ndarray) -> np.ndarray:
    return features * std + mean


def multimodality(gen: Generator, d: Draw, embedder: MotionEmbedder, mean: np.ndarray, std: np.ndarray,
                  cfg: EvalConfig, seed: int, rng: np.random.Generator) -> float:
    """MultiModality of ``gen`` on the first ``mm_texts`` captions of a draw."""
    index = np.arange(min(cfg.mm_texts, len(d.lengths)))
    text, lengths = d.text.select(index), d.lengths[index]
    emb = []
    for r in range(cfg.mm_repeats):
        raw = denormalise(gen.sample(text, lengths, seed=seed * 1000 + r), mean, std)
        emb.append(embedder.motions(raw, lengths))
    return M.multimodality(np.stack(emb, axis=1), cfg.mm_times, rng)


def time_generator(gen: Generator, d: Draw, n: int) -> dict[str, float]:
    """AITS (s per sentence, batch 1, warm) and ms per generated frame over ``n`` captions."""
    gen.sample(d.text.select([0]), d.lengths[:1], seed=0)  # warm-up
    seconds, frames = [], []
    for k in range(min(n, len(d.lengths))):
        start = time.perf_counter()
        gen.sample(d.text.select([k]), d.lengths[k : k + 1], seed=k)
        seconds.append(time.perf_counter() - start)
        frames.append(int(d.lengths[k]))
    return {"AITS_s": float(np.mean(seconds)), "ms_per_frame": 1000.0 * float(np.sum(seconds)) / float(np.sum(frames))}


def replicate(generators: Sequence[Generator], items: Sequence[StoredItem], mean: np.ndarray, std: np.ndarray,
              embedder: MotionEmbedder, skeleton: Skeleton, cfg: EvalConfig, r: int,
              reconstructors: Sequence[Reconstructor] = ()) -> dict[str, dict[str, float]]:
    """Metrics of the Real row, every reconstructor and every generator for replication ``r``."""
    rng = np.random.default_rng([cfg.seed, r])
    d = draw(items, rng, cfg.unit_length)
    ref_draw = draw(items, rng, cfg.unit_length)
    ref = M.gaussian_statistics(embedder.motions(ref_draw.real, ref_draw.lengths))
    text_emb = embedder.texts(d.tokens)
    rows = {REAL: d.real}
    for rec in reconstructors:
        rows[rec.name] = denormalise(rec.reconstruct((d.real - mean) / std, d.lengths), mean, std)
    for gen in generators:
        rows[gen.name] = denormalise(gen.sample(d.text, d.lengths, seed=r), mean, std)
    result = {}
    for name, raw in rows.items():
        result[name] = {
            **text_metrics(text_emb, embedder.motions(raw, d.lengths), ref, cfg, rng),
            **physical(raw, d.lengths, skeleton),
        }
    for rec in reconstructors:
        result[rec.name]["MPJPE_mm"] = mpjpe_mm(d.real, rows[rec.name], d.lengths, skeleton.joints_num)
    for gen in generators:
        if gen.stochastic and cfg.mm_repeats > cfg.mm_times:
            result[gen.name]["MultiModality"] = multimodality(gen, d, embedder, mean, std, cfg, r, rng)
    return result


def aggregate(per_replication: Sequence[Mapping[str, Mapping[str, float]]]) -> dict[str, dict[str, float]]:
    """{row: {metric: mean, metric_ci: 1.96 std / sqrt(R)}} over replications."""
    table = {}
    for row in per_replication[0]:
        table[row] = {}
        for key in per_replication[0][row]:
            mean, ci = M.mean_and_ci(np.array([rep[row][key] for rep in per_replication]))
            table[row][key] = float(mean)
            table[row][f"{key}_ci"] = float(ci)
    return table


def evaluate(generators: Sequence[Generator], items: Sequence[StoredItem], mean: np.ndarray, std: np.ndarray,
             embedder: MotionEmbedder, skeleton: Skeleton, cfg: EvalConfig,
             reconstructors: Sequence[Reconstructor] = ()) -> dict[str, dict[str, float]]:
    """The full protocol: R replications, aggregated, plus timings of each generator."""
    if len(items) < cfg.group_size:
        raise ValueError(f"the test split has {len(items)} items, fewer than one R-precision group "
                         f"({cfg.group_size})")
    reps = [replicate(generators, items, mean, std, embedder, skeleton, cfg, r, reconstructors)
            for r in range(cfg.replications)]
    table = aggregate(reps)
    timing_draw = draw(items, np.random.default_rng([cfg.seed, cfg.replications]), cfg.unit_length)
    for gen in generators:
        table[gen.name].update(time_generator(gen, timing_draw, cfg.timing_sentences))
        table[gen.name]["NFE"] = gen.nfe
    return table
