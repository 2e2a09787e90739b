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
The draws and the evaluator's embeddings of the captions and of the reference motions
(:class:`Reference`) are computed once and saved by the ``Real`` row's stage; every model
family's stage loads them. Each row draws its Diversity and MultiModality pairs from its own
random stream (:func:`row_rng`), so its metrics do not depend on the rows evaluated beside it.
AITS (seconds per sentence, batch 1, warm, loading and text encoding excluded) and ms per frame are timed once
per generator on ``timing_sentences`` test captions (fewer, but at least three, once they
have taken ``timing_seconds``).

Controlled rows (:class:`~models.generator.ControlledGenerator`) answer the same captions and lengths
with hints taken from the real crops' own global joints (:func:`control_hint`: the row's joints on
random frames at the row's density); their motions are also scored by the control errors
(``traj_err_*``, ``loc_err_*``, ``avg_err_m``) on the controlled entries. The frames are drawn from a
stream seeded by the density, so every row of one density (a ControlNet and the uncontrolled
reference scored against its hints) is judged on the same keyframes.

The rows named in ``paraphrase_rows`` (each family's headline row) are also scored for what their
motions *do*, and for captions they never saw (:class:`Semantics`, :mod:`pipelines.paraphrase`):
``action_accuracy`` is the action recogniser's accuracy on the row's motions of the draw's
action-labelled items (the Real row gets it too: the ceiling; so does each reconstruction row, the
ceiling a latent model's decoder allows), and a twin row ``<row>@paraphrase``
answers the same items, lengths and seeds from held-out paraphrases of their captions. The twin is
judged exactly as its row, against the draw's *original* captions: the evaluator's word vocabulary
comes from the training captions, so it cannot read the paraphrases, and both captions state the same
facts. It has no MultiModality and no timing.

A generator too slow for the whole test set (e.g. a 1000-step DDPM on CPU) may carry an optional
attribute ``eval_items`` = K (an int, or None for no bound; no other row sets it): in each replication
it answers only the first K captions of the draw (the draw is shuffled, so a fresh random subset each
time, the same one for every row with the same K), and its R-precision, MM-Dist, FID (against the
same reference statistics as every row), Diversity (at most K - 1 pairs) and physical measures are
computed on those K motions. Its MultiModality is not measured (it would cost ``mm_repeats`` times
the row itself), and its table row records ``eval_items``. FID from K samples is biased upward: such a
row compares only with rows of the same K. K must hold one R-precision group; K >= the test set is
no bound (the full protocol). Such a row may also carry ``eval_replications`` = R' (an int, or None
for all): it is then evaluated in the first R' replications only, its metrics averaged over those,
with no ``_ci`` when R' = 1, and its table row records ``eval_replications``.
"""

from __future__ import annotations

import time
import zipfile
import zlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from data.control import evaluation_mask
from data.features import recover_from_ric
from data.joint_measures import reconstruction_detail
from data.motion_dataset import pad_motions
from data.skeleton import HUMANML3D, Skeleton
from data.store import StoredItem
from data.vocab import WordVocab
from models import metrics as M
from models.evaluator import EvaluatorConfig, T2MEvaluator
from models.generator import CPU, ControlledGenerator, ControlSpec, Generator, Hint, Reconstructor, TextBatch, device_of
from pipelines.checkpoint import load_final_model
from pipelines.config import check_number, refuse

REAL = "Real"
#: Suffix of a row answering the held-out paraphrases (``evaluate.paraphrase_rows``).
PARAPHRASE = "@paraphrase"
#: Captions every generator is timed on before ``evaluate.timing_seconds`` may stop its timing.
MIN_TIMED_SENTENCES = 3


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
    timing_seconds: float | None = None
    unit_length: int = 4
    seed: int = 0
    paraphrase_rows: Sequence[str] = ()


def check_protocol(cfg: Mapping[str, Any]) -> None:
    """The numbers of the ``evaluate`` section (:class:`EvalConfig`) checked before any work, each refusal one
    line naming the key (:func:`pipelines.config.refuse`): counts that the protocol divides by or draws
    from are at least 1, and MultiModality draws ``mm_times`` pairs from ``mm_repeats`` samples (0: none)."""
    cfg = {field.name: field.default for field in fields(EvalConfig)} | dict(cfg)  # keys left out: the defaults
    for key in ("replications", "group_size", "unit_length", "diversity_times", "mm_texts", "mm_times",
                "timing_sentences"):
        check_number(cfg, key, "evaluate", low=1, integer=True)
    for key in ("mm_repeats", "seed"):
        check_number(cfg, key, "evaluate", low=0, integer=True)
    repeats, times = cfg["mm_repeats"], cfg["mm_times"]
    if isinstance(repeats, int) and isinstance(times, int) and 0 < repeats <= times:
        refuse(f"evaluate.mm_repeats: expected 0 (no MultiModality) or more than evaluate.mm_times ({times}), "
               f"got {repeats}")
    if cfg.get("timing_seconds") is not None:
        check_number(cfg, "timing_seconds", "evaluate", low=0.0, low_open=True)


def build_evaluator(config: EvaluatorConfig, mean: Sequence[float], std: Sequence[float],
                    word_vectors: torch.Tensor | None = None) -> T2MEvaluator:
    """A fresh evaluator with its normalisation statistics set from the dataset's Mean/Std."""
    evaluator = T2MEvaluator(config, word_vectors=word_vectors)
    evaluator.set_normalization(np.asarray(mean, np.float32), np.asarray(std, np.float32))
    return evaluator


def load_evaluator(out_dir: Path, device: torch.device = CPU) -> MotionEmbedder:
    """The trained evaluator of ``train_evaluator``'s output folder on ``device``, ready to embed."""
    payload = load_final_model(out_dir)
    config = payload["config"]
    evaluator = build_evaluator(EvaluatorConfig.from_dict(config["model"]), config["mean"], config["std"])
    evaluator.load_state_dict(payload["models"]["evaluator"])
    return MotionEmbedder(evaluator.to(device), WordVocab.from_dict(config["vocab"]), config["max_words"])


class MotionEmbedder:
    """The trained evaluator as two functions: captions -> (B, E), raw motions -> (B, E) (host arrays in and out,
    whatever device the evaluator runs on)."""

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
            out.append(self.evaluator.embed_text(ids, pos, lens).cpu().numpy())
        return np.concatenate(out)

    @torch.inference_mode()
    def motions(self, raw: np.ndarray, lengths: np.ndarray) -> np.ndarray:
        """``raw`` (B, T, D) un-normalised features, zero or anything past ``lengths``."""
        out, device = [], device_of(self.evaluator)
        for first in range(0, len(raw), self.batch):
            x = self.evaluator.normalize(torch.as_tensor(raw[first : first + self.batch], device=device))
            out.append(self.evaluator.embed_motion(x, lengths[first : first + self.batch]).cpu().numpy())
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
    item_ids: list[str]  # the store item each row answers


@dataclass
class Semantics:
    """Scores beyond the T2M evaluator, for Real, the reconstruction rows and the rows in
    ``evaluate.paraphrase_rows`` (built by :func:`pipelines.paraphrase.semantics`).

    Attributes:
        paraphrase: the held-out paraphrase of each item of a draw in replication r (a TextBatch in
            the draw's order), or None when the dataset has no paraphrase set.
        action_accuracy: the action recogniser's accuracy on raw motions answering a draw, over the
            draw's action-labelled items (None when it has none).
    """

    paraphrase: Callable[[Draw, int], TextBatch] | None
    action_accuracy: Callable[[np.ndarray, Draw], float | None]


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
    return Draw(text, tokens, lengths, pad_motions(crops, lengths), [item.item_id for item in chosen])


def physical(raw: np.ndarray, lengths: np.ndarray, skeleton: Skeleton) -> dict[str, float]:
    """Skating ratio, penetration and floating (mm) of raw features recovered as joints."""
    joints = [recover_from_ric(raw[b, :length], skeleton.joints_num) for b, length in enumerate(lengths)]
    return M.physical_metrics(joints, skeleton)


def mpjpe_mm(real: np.ndarray, recon: np.ndarray, lengths: np.ndarray, skeleton: Skeleton) -> float:
    """Root-aligned mean per-joint position error (mm) of two raw feature sets' recovered joints.

    As MLD's reconstruction metric: per frame, both skeletons are moved so their root joints
    coincide, then the joint distances are averaged over valid frames and joints, in the skeleton's
    units times ``skeleton.unit`` (metres per unit: KIT-ML is stored in millimetres).
    """
    errors = []
    for b, n in enumerate(lengths):
        a, r = (recover_from_ric(x[b, :n], skeleton.joints_num) for x in (real, recon))
        errors.append(np.linalg.norm((a - a[:, :1]) - (r - r[:, :1]), axis=-1).reshape(-1))
    return 1000.0 * skeleton.unit * float(np.concatenate(errors).mean())


def detail(real: np.ndarray, recon: np.ndarray, lengths: np.ndarray, skeleton: Skeleton) -> dict[str, float]:
    """:func:`data.joint_measures.reconstruction_detail` of two raw feature sets (B, T, D): what of each
    real motion's path, turns, kicks, waves and jumps the reconstruction keeps. Its joint indices and
    thresholds are HumanML3D's (metres, 22 joints), so other skeletons get no detail columns."""
    if skeleton.name != HUMANML3D.name:
        return {}
    joints_num = skeleton.joints_num
    a, b = recover_from_ric(real, joints_num), recover_from_ric(recon, joints_num)
    return reconstruction_detail([a[k, :n] for k, n in enumerate(lengths)], [b[k, :n] for k, n in enumerate(lengths)])


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


def control_hint(d: Draw, spec: ControlSpec, cfg: EvalConfig, r: int, joints_num: int) -> Hint:
    """Hints for replication ``r``'s draw: the crops' global joints on ``spec``'s joints and random frames."""
    joints = recover_from_ric(d.real, joints_num).astype(np.float32)
    rng = np.random.default_rng([cfg.seed, r, zlib.crc32(f"control {spec.density}".encode())])
    return Hint(joints, evaluation_mask(d.lengths, joints.shape[1], joints_num, spec.joints, spec.density, rng))


def sample_rows(gen: Generator, text: TextBatch, lengths: np.ndarray, seed: int, hint: Hint | None,
                index: np.ndarray | list[int]) -> np.ndarray:
    """``gen`` on the rows ``index`` of a batch (with their hints for a controlled generator); ValueError naming
    the row when its motions are not finite (they would fail far from the cause, in the FID's matrix root)."""
    if hint is None:
        motions = gen.sample(text.select(index), lengths[index], seed=seed)
    else:
        motions = gen.sample(text.select(index), lengths[index], seed=seed, hint=hint.select(index))  # type: ignore[call-arg]
    if not np.isfinite(motions).all():
        raise ValueError(f"row {gen.name}: its sampled motions are not finite (NaN or infinity); check its "
                         "sampling settings (the sample section, e.g. a guidance scale) and its trained model")
    return motions


def multimodality(gen: Generator, d: Draw, embedder: MotionEmbedder, mean: np.ndarray, std: np.ndarray,
                  cfg: EvalConfig, seed: int, rng: np.random.Generator, hint: Hint | None = None) -> float:
    """MultiModality of ``gen`` on the first ``mm_texts`` captions of a draw."""
    index = np.arange(min(cfg.mm_texts, len(d.lengths)))
    emb = []
    for r in range(cfg.mm_repeats):
        raw = denormalise(sample_rows(gen, d.text, d.lengths, seed * 1000 + r, hint, index), mean, std)
        emb.append(embedder.motions(raw, d.lengths[index]))
    return M.multimodality(np.stack(emb, axis=1), cfg.mm_times, rng)


def time_generator(gen: Generator, d: Draw, n: int, hint: Hint | None = None,
                   budget_s: float | None = None) -> dict[str, float]:
    """AITS (s per sentence, batch 1, warm) and ms per generated frame over the first ``n`` captions.

    With ``budget_s``, timing stops early once :data:`MIN_TIMED_SENTENCES` captions are timed and their
    total time reaches ``budget_s``: a 1000-step DDPM row need not spend minutes on a figure that three
    captions already pin down, while fast rows still average all ``n``.
    """
    sample_rows(gen, d.text, d.lengths, 0, hint, [0])  # warm-up
    seconds, frames = [], []
    for k in range(min(n, len(d.lengths))):
        if budget_s is not None and len(seconds) >= MIN_TIMED_SENTENCES and sum(seconds) >= budget_s:
            break
        start = time.perf_counter()
        sample_rows(gen, d.text, d.lengths, k, hint, [k])
        seconds.append(time.perf_counter() - start)
        frames.append(int(d.lengths[k]))
    return {"AITS_s": float(np.mean(seconds)), "ms_per_frame": 1000.0 * float(np.sum(seconds)) / float(np.sum(frames))}


@dataclass
class Reference:
    """One replication: the draw every row answers, its caption embeddings and the FID reference.

    Attributes:
        draw: step 1 of the replication (captions, crop lengths, real crops).
        text_emb: (B, E) evaluator embeddings of the draw's captions.
        ref_mu, ref_sigma: Gaussian statistics of a second, independent draw of real motions.
    """

    draw: Draw
    text_emb: np.ndarray
    ref_mu: np.ndarray
    ref_sigma: np.ndarray


def _replication_draws(items: Sequence[StoredItem], cfg: EvalConfig, r: int) -> tuple[Draw, Draw]:
    rng = np.random.default_rng([cfg.seed, r])
    return draw(items, rng, cfg.unit_length), draw(items, rng, cfg.unit_length)


def check_group_size(num_items: int, cfg: EvalConfig, split: str = "test") -> None:
    """ValueError unless ``split``'s ``num_items`` hold at least one R-precision group.

    Smaller data sets (the smoke profile's) set a smaller ``evaluate.group_size``.
    """
    if num_items < cfg.group_size:
        raise ValueError(f"evaluate.group_size={cfg.group_size} is larger than the {split} split "
                         f"({num_items} items): R-precision needs one full group; set a smaller evaluate.group_size")


def references(items: Sequence[StoredItem], embedder: MotionEmbedder, cfg: EvalConfig,
               split: str = "test") -> list[Reference]:
    """The ``replications`` references of the protocol (a pure function of the items and ``cfg.seed``)."""
    check_group_size(len(items), cfg, split)
    refs = []
    for r in range(cfg.replications):
        d, ref_draw = _replication_draws(items, cfg, r)
        mu, sigma = M.gaussian_statistics(embedder.motions(ref_draw.real, ref_draw.lengths))
        refs.append(Reference(d, embedder.texts(d.tokens), mu, sigma))
    return refs


def save_references(path: Path, refs: Sequence[Reference]) -> None:
    """The embeddings of ``refs`` as one ``.npz`` (no pickles); the draws are recomputed on load."""
    arrays = {}
    for r, ref in enumerate(refs):
        arrays |= {f"lengths_{r}": ref.draw.lengths, f"text_emb_{r}": ref.text_emb,
                   f"ref_mu_{r}": ref.ref_mu, f"ref_sigma_{r}": ref.ref_sigma}
    np.savez(path, **arrays)


def load_references(path: Path, items: Sequence[StoredItem], cfg: EvalConfig) -> list[Reference]:
    """:func:`references` as saved by :func:`save_references`; an error if they belong to other items or cfg."""
    check_group_size(len(items), cfg)
    refs = []
    try:
        with np.load(path, allow_pickle=False) as saved:
            if f"lengths_{cfg.replications - 1}" not in saved or f"lengths_{cfg.replications}" in saved:
                raise ValueError(f"{path}: saved for another number of replications than {cfg.replications}")
            for r in range(cfg.replications):
                d, _ = _replication_draws(items, cfg, r)
                if not np.array_equal(saved[f"lengths_{r}"], d.lengths):
                    raise ValueError(f"{path}: saved for other test items or another evaluate.seed")
                ref = Reference(d, saved[f"text_emb_{r}"], saved[f"ref_mu_{r}"], saved[f"ref_sigma_{r}"])
                dim = ref.ref_mu.shape[0] if ref.ref_mu.ndim == 1 else -1
                if ref.ref_sigma.shape != (dim, dim) or ref.text_emb.ndim != 2:
                    raise ValueError(f"{path}: replication {r}'s arrays do not fit together (mu {ref.ref_mu.shape}, "
                                     f"sigma {ref.ref_sigma.shape}, text {ref.text_emb.shape})")
                refs.append(ref)
    except FileNotFoundError:
        raise
    except (OSError, ValueError, KeyError, zipfile.BadZipFile, EOFError) as err:
        message = str(err) if str(err).startswith(str(path)) else f"{path}: unreadable ({err})"
        raise ValueError(f"{message}; run `dvc repro eval_real` to write it again") from None
    return refs


def row_rng(cfg: EvalConfig, r: int, row: str) -> np.random.Generator:
    """The random stream of one row in one replication (Diversity and MultiModality pairs).

    Seeded by the row's name, so a row's metrics do not depend on which other rows are evaluated
    with it: each model family is evaluated by its own stage.
    """
    return np.random.default_rng([cfg.seed, r, zlib.crc32(row.encode())])


def eval_items(gen: Generator, n: int, cfg: EvalConfig) -> int | None:
    """The subset size K a generator's ``eval_items`` asks for on a draw of ``n`` captions (module
    docstring), or None for the full protocol (no attribute, None, or K >= n)."""
    k = getattr(gen, "eval_items", None)
    if k is None:
        return None
    if isinstance(k, bool) or not isinstance(k, int) or k < max(cfg.group_size, 2):
        raise ValueError(f"{gen.name}: eval_items must be an integer >= group_size ({cfg.group_size}), got {k!r}")
    return None if k >= n else k


def eval_replications(gen: Generator, cfg: EvalConfig) -> int:
    """How many of the replications a generator is evaluated in: its ``eval_replications`` (module
    docstring), at most ``cfg.replications``; all of them without the attribute or with None."""
    r = getattr(gen, "eval_replications", None)
    if r is None:
        return cfg.replications
    if isinstance(r, bool) or not isinstance(r, int) or r < 1:
        raise ValueError(f"{gen.name}: eval_replications must be an integer >= 1, got {r!r}")
    return min(r, cfg.replications)


def subset_reference(ref: Reference, k: int) -> Reference:
    """The first ``k`` captions of a replication's draw (a random subset: the draw is shuffled) with their
    caption embeddings, and the same FID reference statistics."""
    d, index = ref.draw, np.arange(k)
    lengths = d.lengths[:k]
    sub = Draw(d.text.select(index), d.tokens[:k], lengths, d.real[:k, : int(lengths.max())], d.item_ids[:k])
    return Reference(sub, ref.text_emb[:k], ref.ref_mu, ref.ref_sigma)


def _row_metrics(name: str, raw: np.ndarray, ref: Reference, embedder: MotionEmbedder, skeleton: Skeleton,
                 cfg: EvalConfig, rng: np.random.Generator) -> dict[str, float]:
    motion_emb = embedder.motions(raw, ref.draw.lengths)
    return {**text_metrics(ref.text_emb, motion_emb, (ref.ref_mu, ref.ref_sigma), cfg, rng),
            **physical(raw, ref.draw.lengths, skeleton)}


def replicate(ref: Reference, r: int, embedder: MotionEmbedder, skeleton: Skeleton, cfg: EvalConfig,
              mean: np.ndarray, std: np.ndarray, generators: Sequence[Generator] = (),
              reconstructors: Sequence[Reconstructor] = (), real: bool = False,
              semantics: Semantics | None = None) -> dict[str, dict[str, float]]:
    """Metrics of the Real row (``real``), every reconstructor and every generator for replication ``r``;
    with ``semantics``, the action accuracy of Real, of the reconstructors and of the ``paraphrase_rows`` and
    their paraphrase rows."""
    d, result = ref.draw, {}
    if real:
        result[REAL] = _row_metrics(REAL, d.real, ref, embedder, skeleton, cfg, row_rng(cfg, r, REAL))
        if semantics is not None:
            result[REAL] |= _action_accuracy(semantics, d.real, d)
    for rec in reconstructors:
        raw = denormalise(rec.reconstruct((d.real - mean) / std, d.lengths), mean, std)
        result[rec.name] = _row_metrics(rec.name, raw, ref, embedder, skeleton, cfg, row_rng(cfg, r, rec.name))
        result[rec.name]["MPJPE_mm"] = mpjpe_mm(d.real, raw, d.lengths, skeleton)
        result[rec.name] |= detail(d.real, raw, d.lengths, skeleton)
        if semantics is not None:
            result[rec.name] |= _action_accuracy(semantics, raw, d)
    for gen in generators:
        if r >= eval_replications(gen, cfg):
            continue
        rng = row_rng(cfg, r, gen.name)
        k = eval_items(gen, len(d.lengths), cfg)
        g_ref, g_cfg = (ref, cfg) if k is None else (subset_reference(ref, k),
                                                     replace(cfg, diversity_times=min(cfg.diversity_times, k - 1)))
        g_draw = g_ref.draw
        hint = _hint_of(gen, g_draw, cfg, r, skeleton)
        raw = denormalise(sample_rows(gen, g_draw.text, g_draw.lengths, r, hint, np.arange(len(g_draw.lengths))),
                          mean, std)
        result[gen.name] = _row_metrics(gen.name, raw, g_ref, embedder, skeleton, g_cfg, rng)
        if hint is not None:
            joints = recover_from_ric(raw, skeleton.joints_num)
            result[gen.name] |= M.control_errors(joints, hint.joints, hint.mask, unit=skeleton.unit)
        if gen.stochastic and k is None and cfg.mm_repeats > cfg.mm_times:
            result[gen.name]["MultiModality"] = multimodality(gen, d, embedder, mean, std, cfg, r, rng, hint)
        if semantics is not None and gen.name in cfg.paraphrase_rows:
            result[gen.name] |= _action_accuracy(semantics, raw, g_draw)
            if semantics.paraphrase is not None:
                name = gen.name + PARAPHRASE
                text = semantics.paraphrase(g_draw, r)
                raw = denormalise(sample_rows(gen, text, g_draw.lengths, r, hint, np.arange(len(g_draw.lengths))),
                                  mean, std)
                result[name] = _row_metrics(name, raw, g_ref, embedder, skeleton, g_cfg, row_rng(cfg, r, name))
                result[name] |= _action_accuracy(semantics, raw, g_draw)
    return result


def _action_accuracy(semantics: Semantics, raw: np.ndarray, d: Draw) -> dict[str, float]:
    accuracy = semantics.action_accuracy(raw, d)
    return {} if accuracy is None else {"action_accuracy": accuracy}


def _hint_of(gen: Generator, d: Draw, cfg: EvalConfig, r: int, skeleton: Skeleton) -> Hint | None:
    return control_hint(d, gen.control, cfg, r, skeleton.joints_num) if isinstance(gen, ControlledGenerator) else None


def aggregate(per_replication: Sequence[Mapping[str, Mapping[str, float]]]) -> dict[str, dict[str, float]]:
    """{row: {metric: mean, metric_ci: 1.96 std / sqrt(R)}} over the replications that hold the row and the
    metric (no ``_ci`` from one replication only: ``eval_replications``, or a reconstruction-detail
    fraction whose draw had references in one replication only)."""
    table = {}
    for row in dict.fromkeys(name for rep in per_replication for name in rep):
        reps = [rep[row] for rep in per_replication if row in rep]
        table[row] = {}
        for key in dict.fromkeys(key for rep in reps for key in rep):
            values = np.array([rep[key] for rep in reps if key in rep])
            mean, ci = M.mean_and_ci(values)
            table[row][key] = float(mean)
            if len(values) > 1:
                table[row][f"{key}_ci"] = float(ci)
    return table


def evaluate(refs: Sequence[Reference], items: Sequence[StoredItem], mean: np.ndarray, std: np.ndarray,
             embedder: MotionEmbedder, skeleton: Skeleton, cfg: EvalConfig, generators: Sequence[Generator] = (),
             reconstructors: Sequence[Reconstructor] = (), real: bool = False,
             semantics: Semantics | None = None) -> dict[str, dict[str, float]]:
    """The protocol over ``refs`` (one per replication), aggregated, plus timings of each generator."""
    reps = [replicate(ref, r, embedder, skeleton, cfg, mean, std, generators, reconstructors, real, semantics)
            for r, ref in enumerate(refs)]
    table = aggregate(reps) if reps and reps[0] else {}
    timing_draw = draw(items, np.random.default_rng([cfg.seed, cfg.replications]), cfg.unit_length)
    for gen in generators:
        hint = _hint_of(gen, timing_draw, cfg, cfg.replications, skeleton)
        table[gen.name].update(time_generator(gen, timing_draw, cfg.timing_sentences, hint, cfg.timing_seconds))
        table[gen.name]["NFE"] = gen.nfe
        k = eval_items(gen, len(refs[0].draw.lengths), cfg) if refs else None
        if k is not None:
            table[gen.name]["eval_items"] = k
        if eval_replications(gen, cfg) < cfg.replications:
            table[gen.name]["eval_replications"] = eval_replications(gen, cfg)
    return table
