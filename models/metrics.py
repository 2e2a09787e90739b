"""Evaluation metrics for text-to-motion generation (pure numpy, no file or cluster I/O).

Follows the standard T2M protocol (Guo et al. 2022, as used by MDM / MLD / MotionLCM / EMDM) and
OmniControl's control metrics; see ``reference/humanml3d_eval.md`` sections C.3-C.5 and DESIGN.md
"Evaluation protocol". Embeddings are evaluator outputs (512-d for the T2M evaluator); every
function accepts any float dtype and computes in float64.

Standard metrics (per replication):

- R-precision top-k: within consecutive groups of ``group_size`` (32) rows, the fraction of text
  rows whose own motion is among the k nearest motions of the group.
- MM-Dist (matching score): mean Euclidean distance between matched text/motion embeddings.
- FID: Frechet distance between Gaussians fitted to real and generated motion embeddings.
- Diversity: mean distance between ``times`` (300) random pairs of motion embeddings.
- MultiModality: mean distance between ``times`` (10) random pairs of motions generated for the
  same text, averaged over texts.
- Replications are summarised as mean and 1.96 * std (ddof 0) / sqrt(R).

Control and physical metrics: :func:`control_errors` (OmniControl, controlled keyframes only) and
:func:`physical_metrics` (averages of :mod:`data.physics` over motions; its module docstring
states the floor convention).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import scipy.linalg

from data.physics import floating, foot_skating_ratio, ground_penetration
from data.skeleton import Skeleton

RngLike = np.random.Generator | int | None

FID_EPS = 1e-6
FID_MAX_IMAG = 1e-3
CI_Z = 1.96


# --------------------------------------------------------------------------------------------
# helpers


def _as_2d(x: np.ndarray, name: str) -> np.ndarray:
    arr = np.asarray(x, dtype=np.float64)
    if arr.ndim != 2:
        raise ValueError(f"{name} must have shape (N, D), got {arr.shape}")
    return arr


def _matched_pair(text_emb: np.ndarray, motion_emb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    text = _as_2d(text_emb, "text_emb")
    motion = _as_2d(motion_emb, "motion_emb")
    if text.shape != motion.shape:
        raise ValueError(f"text_emb {text.shape} and motion_emb {motion.shape} must have equal shapes")
    return text, motion


def _paired_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise ||a_i - b_i||_2 over the last axis."""
    return np.linalg.norm(a - b, axis=-1)


# --------------------------------------------------------------------------------------------
# distances, R-precision, MM-Dist


def euclidean_distance_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pairwise Euclidean distances.

    Args:
        a: (N, D) array.
        b: (M, D) array.

    Returns:
        (N, M) float64 array with ``D_ij = ||a_i - b_j||_2``, computed as in the T2M code by the
        expansion ``sqrt(|a_i|^2 + |b_j|^2 - 2 a_i . b_j)``; tiny negative values from
        cancellation are clipped to 0 before the square root.
    """
    a = _as_2d(a, "a")
    b = _as_2d(b, "b")
    if a.shape[1] != b.shape[1]:
        raise ValueError(f"a and b must share the feature dimension, got {a.shape} and {b.shape}")
    sq = np.sum(a**2, axis=1)[:, None] + np.sum(b**2, axis=1)[None, :] - 2.0 * (a @ b.T)
    return np.sqrt(np.maximum(sq, 0.0))


def r_precision(text_emb: np.ndarray, motion_emb: np.ndarray, group_size: int = 32, top_k: int = 3) -> np.ndarray:
    """R-precision at k = 1..top_k, computed within consecutive groups of rows.

    Row i of ``text_emb`` and row i of ``motion_emb`` form a matched pair. The rows are cut into
    consecutive groups of ``group_size`` (the reference evaluates one DataLoader batch of 32 with
    ``drop_last=True``); an incomplete last group (``N % group_size`` rows) is dropped, so
    ``n = group_size * (N // group_size)`` rows count. Within each group G the distance matrix
    ``D = euclidean_distance_matrix(text[G], motion[G])`` is ranked row-wise (stable argsort) and

        R@k = (1 / n) * sum_i [ rank of motion i in row i of D  <  k ]   (rank 0 = nearest).

    Args:
        text_emb: (N, D) text embeddings.
        motion_emb: (N, D) motion embeddings, matched row by row.
        group_size: rows per group (32 in the standard protocol).
        top_k: largest k reported.

    Returns:
        (top_k,) array; element k-1 is R@k (non-decreasing in k).

    Raises:
        ValueError: on mismatched shapes, ``top_k > group_size`` or fewer than ``group_size`` rows.
    """
    text, motion = _matched_pair(text_emb, motion_emb)
    if group_size < 1 or not 1 <= top_k <= group_size:
        raise ValueError(f"need group_size >= 1 and 1 <= top_k <= group_size, got {group_size}, {top_k}")
    num_groups = text.shape[0] // group_size
    if num_groups == 0:
        raise ValueError(f"r_precision needs at least group_size={group_size} rows, got {text.shape[0]}")
    hits = np.zeros(top_k, dtype=np.int64)
    own = np.arange(group_size)
    for g in range(num_groups):
        rows = slice(g * group_size, (g + 1) * group_size)
        order = np.argsort(euclidean_distance_matrix(text[rows], motion[rows]), axis=1, kind="stable")
        rank = np.argmax(order == own[:, None], axis=1)  # position of the own motion per row
        hits += np.array([np.sum(rank < k) for k in range(1, top_k + 1)])
    return hits / float(num_groups * group_size)


def matching_score(text_emb: np.ndarray, motion_emb: np.ndarray) -> float:
    """MM-Dist: mean distance of matched pairs, ``(1/N) * sum_i ||t_i - m_i||_2``.

    Equals the reference's ``sum_batches trace(D) / N``. All N rows count; to reproduce the
    rows used by :func:`r_precision` pass only the complete groups, ``x[: 32 * (N // 32)]``.

    Args:
        text_emb: (N, D) text embeddings.
        motion_emb: (N, D) motion embeddings, matched row by row.
    """
    text, motion = _matched_pair(text_emb, motion_emb)
    if text.shape[0] == 0:
        raise ValueError("matching_score needs at least one pair")
    return float(np.mean(_paired_distances(text, motion)))


# --------------------------------------------------------------------------------------------
# FID


def _sqrtm_product(sigma1: np.ndarray, sigma2: np.ndarray, eps: float) -> np.ndarray:
    """sqrtm(sigma1 @ sigma2); retried with ``eps * I`` added to both if the result is non-finite."""
    covmean = scipy.linalg.sqrtm(sigma1 @ sigma2)
    if not np.all(np.isfinite(covmean)):
        offset = eps * np.eye(sigma1.shape[0])
        covmean = scipy.linalg.sqrtm((sigma1 + offset) @ (sigma2 + offset))
    if not np.all(np.isfinite(covmean)):
        raise ValueError("matrix square root of the covariance product is not finite")
    if np.iscomplexobj(covmean):
        max_imag = float(np.max(np.abs(np.diagonal(covmean).imag)))
        if max_imag > FID_MAX_IMAG:
            raise ValueError(f"imaginary component {max_imag:.3g} in sqrtm exceeds {FID_MAX_IMAG}")
        covmean = covmean.real
    return covmean


def frechet_distance(
    mu1: np.ndarray, sigma1: np.ndarray, mu2: np.ndarray, sigma2: np.ndarray, eps: float = FID_EPS
) -> float:
    """Frechet distance between N(mu1, sigma1) and N(mu2, sigma2).

        d^2 = ||mu1 - mu2||^2 + Tr(sigma1) + Tr(sigma2) - 2 Tr( sqrtm(sigma1 @ sigma2) )

    ``scipy.linalg.sqrtm`` is applied to the product; if it is not finite, ``eps * I`` is added
    to both covariances and it is retried. The real part is kept; an imaginary diagonal entry
    larger than 1e-3 raises ValueError.

    Args:
        mu1, mu2: (D,) means.
        sigma1, sigma2: (D, D) covariances.
    """
    mu1 = np.atleast_1d(np.asarray(mu1, dtype=np.float64))
    mu2 = np.atleast_1d(np.asarray(mu2, dtype=np.float64))
    sigma1 = np.atleast_2d(np.asarray(sigma1, dtype=np.float64))
    sigma2 = np.atleast_2d(np.asarray(sigma2, dtype=np.float64))
    dim = mu1.shape[0]
    if mu1.shape != (dim,) or mu2.shape != (dim,) or sigma1.shape != (dim, dim) or sigma2.shape != (dim, dim):
        raise ValueError(
            f"inconsistent shapes: mu1 {mu1.shape}, sigma1 {sigma1.shape}, mu2 {mu2.shape}, sigma2 {sigma2.shape}"
        )
    diff = mu1 - mu2
    covmean = _sqrtm_product(sigma1, sigma2, eps)
    return float(diff @ diff + np.trace(sigma1) + np.trace(sigma2) - 2.0 * np.trace(covmean))


def gaussian_statistics(emb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean (D,) and unbiased covariance (D, D) of (N, D) embeddings (``np.cov``, rowvar=False)."""
    emb = _as_2d(emb, "emb")
    if emb.shape[0] < 2:
        raise ValueError(f"need at least 2 embeddings for a covariance, got {emb.shape[0]}")
    return emb.mean(axis=0), np.atleast_2d(np.cov(emb, rowvar=False))


def fid(real_emb: np.ndarray, gen_emb: np.ndarray) -> float:
    """FID between real (N, D) and generated (M, D) motion embeddings.

    ``frechet_distance(*gaussian_statistics(real_emb), *gaussian_statistics(gen_emb))``.
    """
    real = _as_2d(real_emb, "real_emb")
    gen = _as_2d(gen_emb, "gen_emb")
    if real.shape[1] != gen.shape[1]:
        raise ValueError(f"real_emb {real.shape} and gen_emb {gen.shape} differ in dimension")
    mu_r, sigma_r = gaussian_statistics(real)
    mu_g, sigma_g = gaussian_statistics(gen)
    return frechet_distance(mu_r, sigma_r, mu_g, sigma_g)


# --------------------------------------------------------------------------------------------
# Diversity and MultiModality


def diversity(emb: np.ndarray, times: int = 300, rng: RngLike = None) -> float:
    """Diversity: mean distance between ``times`` random pairs of embeddings.

    Two index sets a and b of size ``times`` are drawn independently, each without replacement,
    from range(N) (a_i == b_i can occur):

        Div = (1 / times) * sum_i ||emb[a_i] - emb[b_i]||_2

    Args:
        emb: (N, D) motion embeddings; N must exceed ``times`` (as in the reference).
        times: number of pairs (300 in the standard protocol).
        rng: numpy Generator or seed.

    Raises:
        ValueError: if ``N <= times``.
    """
    emb = _as_2d(emb, "emb")
    num = emb.shape[0]
    if times < 1 or num <= times:
        raise ValueError(f"diversity needs more embeddings than pairs (N > times >= 1); got N={num}, times={times}")
    gen = np.random.default_rng(rng)
    first = gen.choice(num, times, replace=False)
    second = gen.choice(num, times, replace=False)
    return float(np.mean(_paired_distances(emb[first], emb[second])))


def multimodality(emb: np.ndarray, times: int = 10, rng: RngLike = None) -> float:
    """MultiModality: mean distance between motions generated for the same text.

    One pair of index sets a and b of size ``times`` is drawn from range(num_repeats), each
    without replacement, and shared by all texts:

        MM = mean over texts c and i of ||emb[c, a_i] - emb[c, b_i]||_2

    Args:
        emb: (num_texts, num_repeats, D) embeddings; num_repeats must exceed ``times``.
        times: pairs per text (10 in the standard protocol).
        rng: numpy Generator or seed.

    Raises:
        ValueError: on a wrong rank, no texts, or ``num_repeats <= times``.
    """
    emb = np.asarray(emb, dtype=np.float64)
    if emb.ndim != 3 or emb.shape[0] == 0:
        raise ValueError(f"emb must have shape (num_texts >= 1, num_repeats, D), got {emb.shape}")
    repeats = emb.shape[1]
    if times < 1 or repeats <= times:
        raise ValueError(f"multimodality needs num_repeats > times >= 1; got num_repeats={repeats}, times={times}")
    gen = np.random.default_rng(rng)
    first = gen.choice(repeats, times, replace=False)
    second = gen.choice(repeats, times, replace=False)
    return float(np.mean(_paired_distances(emb[:, first], emb[:, second])))


def mean_and_ci(values: Sequence[float] | np.ndarray) -> tuple[float, float]:
    """Mean and 95% half-width over R replications: ``(mean, 1.96 * std(ddof=0) / sqrt(R))``."""
    vals = np.asarray(values, dtype=np.float64).ravel()
    if vals.size == 0:
        raise ValueError("mean_and_ci needs at least one value")
    return float(vals.mean()), float(CI_Z * vals.std() / np.sqrt(vals.size))


# --------------------------------------------------------------------------------------------
# control errors (OmniControl)


def _threshold_name(threshold: float) -> str:
    return f"{round(threshold * 100)}cm"


def _sample_control_errors(errors: np.ndarray, thresholds: Sequence[float]) -> dict[str, float]:
    """Metrics of one sample from its (M,) keyframe errors in metres, M >= 1."""
    out = {"avg_err_m": float(errors.mean())}
    for th in thresholds:
        fails = errors > th
        out[f"traj_err_{_threshold_name(th)}"] = float(fails.any())
        out[f"loc_err_{_threshold_name(th)}"] = float(fails.mean())
    return out


def control_errors(
    pred_joints: np.ndarray,
    hint_joints: np.ndarray,
    mask: np.ndarray,
    thresholds: Sequence[float] = (0.5, 0.2),
    unit: float = 1.0,
) -> dict[str, float]:
    """OmniControl's control errors on controlled keyframes only.

    Per sample b, ``e = ||pred[b, t, j] - hint[b, t, j]||_2 * unit`` over the M_b masked (t, j)
    entries; then for each threshold th (metres):

        Traj. err = 1 if any e > th else 0       (a trajectory fails if any keyframe misses)
        Loc. err  = #(e > th) / M_b              (fraction of keyframes that miss)
        Avg. err  = sum(e) / M_b                 (metres)

    Each is averaged over samples. Samples with no masked entry (M_b = 0) are excluded from the
    averages (they have no keyframe to judge), rather than counted as successes.

    Args:
        pred_joints: (B, T, J, 3) generated global joint positions.
        hint_joints: (B, T, J, 3) target positions (values outside ``mask`` are ignored).
        mask: (B, T, J) bool, True at controlled keyframe joints.
        thresholds: thresholds in metres; keys are named by centimetres (0.5 -> ``50cm``).
        unit: metres per input unit (1.0 for HumanML3D, 0.001 for KIT-ML).

    Returns:
        dict with ``traj_err_<X>cm`` and ``loc_err_<X>cm`` per threshold and ``avg_err_m``
        (with the defaults: traj_err_50cm, loc_err_50cm, traj_err_20cm, loc_err_20cm, avg_err_m).

    Raises:
        ValueError: on shape mismatches or if no sample has a keyframe.
    """
    pred = np.asarray(pred_joints, dtype=np.float64)
    hint = np.asarray(hint_joints, dtype=np.float64)
    mask = np.asarray(mask)
    if pred.ndim != 4 or pred.shape[-1] != 3 or hint.shape != pred.shape or mask.shape != pred.shape[:-1]:
        raise ValueError(
            f"expected pred/hint (B, T, J, 3) and mask (B, T, J); got {pred.shape}, {hint.shape}, {mask.shape}"
        )
    if mask.dtype != np.bool_:
        raise ValueError(f"mask must be boolean, got {mask.dtype}")
    dist = np.linalg.norm(pred - hint, axis=-1) * unit  # (B, T, J)
    per_sample = [_sample_control_errors(d[m], thresholds) for d, m in zip(dist, mask, strict=True) if m.any()]
    if not per_sample:
        raise ValueError("control_errors: no sample has a controlled keyframe")
    return {key: float(np.mean([s[key] for s in per_sample])) for key in per_sample[0]}


# --------------------------------------------------------------------------------------------
# physical plausibility


def physical_metrics(joints_list: Sequence[np.ndarray], skeleton: Skeleton) -> dict[str, float]:
    """Physical plausibility averaged over motions (each motion weighs the same).

    Uses :mod:`data.physics` (floor y = 0, 5 mm tolerance, OmniControl's skating rule; see that
    module's docstring) on each (T_i, J, 3) global-joint motion in the skeleton's units:

        skating_ratio  = mean_i foot_skating_ratio(motion_i)              (fraction of frame pairs)
        penetration_mm = 1000 * mean_i ground_penetration(motion_i)       (mean depth below floor)
        floating_mm    = 1000 * mean_i floating(motion_i)                 (mean height above floor)

    Raises:
        ValueError: on an empty list (or a motion of the wrong shape, from data.physics).
    """
    if len(joints_list) == 0:
        raise ValueError("physical_metrics needs at least one motion")
    skate = [foot_skating_ratio(j, skeleton) for j in joints_list]
    pen = [ground_penetration(j, skeleton) for j in joints_list]
    flo = [floating(j, skeleton) for j in joints_list]
    return {
        "skating_ratio": float(np.mean(skate)),
        "penetration_mm": 1000.0 * float(np.mean(pen)),
        "floating_mm": 1000.0 * float(np.mean(flo)),
    }
