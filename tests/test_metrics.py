"""Known-answer tests for models.metrics."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg

from data.skeleton import HUMANML3D
from models import metrics
from models.metrics import (
    control_errors,
    diversity,
    euclidean_distance_matrix,
    fid,
    frechet_distance,
    matching_score,
    mean_and_ci,
    multimodality,
    physical_metrics,
    r_precision,
)

# ------------------------------------------------------------------ distances, R-precision, MM-Dist


def test_distance_matrix_matches_brute_force() -> None:
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(5, 7)), rng.normal(size=(3, 7))
    expected = np.array([[np.linalg.norm(x - y) for y in b] for x in a])
    d = euclidean_distance_matrix(a, b)
    assert d.shape == (5, 3)
    np.testing.assert_allclose(d, expected, rtol=1e-10)
    same = euclidean_distance_matrix(a, a)
    assert np.all(np.isfinite(same)) and np.all(np.diag(same) < 1e-6)


def test_distance_matrix_hand_example() -> None:
    d = euclidean_distance_matrix(np.array([[0.0, 0.0], [1.0, 1.0]]), np.array([[3.0, 4.0], [1.0, 1.0]]))
    np.testing.assert_allclose(d, [[5.0, np.sqrt(2.0)], [np.sqrt(13.0), 0.0]], atol=1e-12)


def test_r_precision_perfect_match_is_one() -> None:
    emb = np.random.default_rng(1).normal(size=(96, 16))
    np.testing.assert_array_equal(r_precision(emb, emb.copy()), [1.0, 1.0, 1.0])


def test_r_precision_random_is_chance() -> None:
    rng = np.random.default_rng(2)
    text, motion = rng.normal(size=(2, 32 * 200, 8))
    r = r_precision(text, motion, group_size=32, top_k=3)
    assert r.shape == (3,)
    # chance k/32; binomial std over 6400 rows is <= 0.0036
    np.testing.assert_allclose(r, np.array([1, 2, 3]) / 32, atol=0.012)


def test_r_precision_hand_ranks() -> None:
    # 1-D, one group of 4. Own-motion ranks: row0 1st, row1 2nd, row2 2nd, row3 4th.
    text = np.array([[0.0], [10.0], [20.0], [30.0]])
    motion = np.array([[0.0], [15.0], [12.0], [100.0]])
    np.testing.assert_allclose(r_precision(text, motion, group_size=4, top_k=3), [0.25, 0.75, 0.75])


def test_r_precision_ranks_only_within_group() -> None:
    # Group 0: motion i sits 3 from its text (neighbours 7 away). Group 1's motions sit 0.5 from
    # group 0's texts, so ranking against all rows would give group 0 a top-1 of 0; within its
    # own group each text still finds its own motion first.
    base = np.arange(8, dtype=float)[:, None] * 10.0
    text = np.concatenate([base, base + 0.5])
    motion = np.concatenate([base + 3.0, base + 0.5])
    assert r_precision(text, motion, group_size=8, top_k=1)[0] == 1.0
    assert r_precision(text, motion, group_size=16, top_k=1)[0] == 0.5


def test_r_precision_drops_incomplete_last_group() -> None:
    rng = np.random.default_rng(3)
    text = rng.normal(size=(40, 4))
    motion = text.copy()
    motion[32:] = motion[32:][::-1]  # last 8 rows mismatched, but they form an incomplete group
    np.testing.assert_array_equal(r_precision(text, motion), [1.0, 1.0, 1.0])
    with pytest.raises(ValueError, match="at least group_size"):
        r_precision(text[:31], motion[:31])


def test_matching_score_hand_example() -> None:
    text = np.array([[0.0, 0.0], [1.0, 1.0], [0.0, 0.0]])
    motion = np.array([[3.0, 4.0], [1.0, 1.0], [0.0, -2.0]])  # distances 5, 0, 2
    assert matching_score(text, motion) == pytest.approx(7.0 / 3.0)
    with pytest.raises(ValueError):
        matching_score(text, motion[:2])


# ------------------------------------------------------------------ FID


def test_frechet_distance_diagonal_closed_form() -> None:
    mu1, mu2 = np.array([0.0, 1.0, -2.0]), np.array([1.0, 3.0, -2.0])
    s1, s2 = np.array([1.0, 4.0, 0.25]), np.array([4.0, 9.0, 1.0])
    # |mu1 - mu2|^2 + sum_i (sqrt(s1_i) - sqrt(s2_i))^2 = 5 + (1 + 1 + 0.25)
    expected = 5.0 + 2.25
    assert frechet_distance(mu1, np.diag(s1), mu2, np.diag(s2)) == pytest.approx(expected, abs=1e-9)
    # invariant under a common rotation (exercises sqrtm on a non-diagonal product)
    q, _ = np.linalg.qr(np.random.default_rng(4).normal(size=(3, 3)))
    rotated = frechet_distance(q @ mu1, q @ np.diag(s1) @ q.T, q @ mu2, q @ np.diag(s2) @ q.T)
    assert rotated == pytest.approx(expected, abs=1e-8)


def test_fid_identical_samples_is_zero() -> None:
    emb = np.random.default_rng(5).normal(size=(500, 6)) @ np.diag([1.0, 2.0, 0.5, 1.0, 3.0, 1.0])
    assert abs(fid(emb, emb.copy())) < 1e-6


def test_fid_shifted_gaussian_is_squared_shift() -> None:
    rng = np.random.default_rng(6)
    mu = np.array([1.0, -1.0, 0.5, 0.0])  # |mu|^2 = 2.25
    real = rng.normal(size=(20000, 4))
    gen = rng.normal(size=(20000, 4)) + mu
    # sampling std of the estimate is ~0.03 here
    assert fid(real, gen) == pytest.approx(2.25, abs=0.15)


def test_fid_uses_unbiased_sample_covariance() -> None:
    rng = np.random.default_rng(13)
    real = rng.normal(size=(6, 3)) * [1.0, 2.0, 3.0]
    gen = rng.normal(size=(5, 3)) + 1.0
    expected = frechet_distance(real.mean(0), np.cov(real.T, ddof=1), gen.mean(0), np.cov(gen.T, ddof=1))
    assert fid(real, gen) == pytest.approx(expected, rel=1e-12)
    # scaled Gaussians: N(0, diag(1, 4)) vs N(0, diag(4, 9)) -> (1 - 2)^2 + (2 - 3)^2 = 2
    wide = rng.normal(size=(20000, 2)) * [2.0, 3.0]
    narrow = rng.normal(size=(20000, 2)) * [1.0, 2.0]
    assert fid(narrow, wide) == pytest.approx(2.0, abs=0.15)


def test_fid_retries_with_eps_when_sqrtm_not_finite(monkeypatch: pytest.MonkeyPatch) -> None:
    real_sqrtm = scipy.linalg.sqrtm
    seen: list[np.ndarray] = []

    def flaky(a: np.ndarray) -> np.ndarray:
        seen.append(a)
        return np.full_like(a, np.nan) if len(seen) == 1 else real_sqrtm(a)

    monkeypatch.setattr(scipy.linalg, "sqrtm", flaky)
    value = frechet_distance(np.zeros(2), np.eye(2), np.zeros(2), np.eye(2))
    assert len(seen) == 2
    np.testing.assert_allclose(seen[1], (1 + metrics.FID_EPS) ** 2 * np.eye(2))
    assert value == pytest.approx(0.0, abs=1e-5)


def test_fid_rejects_large_imaginary_part(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(scipy.linalg, "sqrtm", lambda a: np.eye(2) * (1 + 0.01j))
    with pytest.raises(ValueError, match="imaginary"):
        frechet_distance(np.zeros(2), np.eye(2), np.zeros(2), np.eye(2))
    monkeypatch.setattr(scipy.linalg, "sqrtm", lambda a: np.eye(2) * (1 + 1e-5j))
    assert frechet_distance(np.zeros(2), np.eye(2), np.zeros(2), np.eye(2)) == pytest.approx(0.0)


# ------------------------------------------------------------------ Diversity, MultiModality, CI


def test_diversity_equal_embeddings_is_zero() -> None:
    assert diversity(np.ones((301, 5)), times=300, rng=0) == 0.0


def test_diversity_two_clusters() -> None:
    # Half the points at 0, half at distance 10: a random pair straddles the clusters with
    # probability 1/2, so Div ~ 5 (std of the estimate ~0.08 for 4000 pairs).
    emb = np.zeros((8002, 3))
    emb[4001:, 0] = 10.0
    assert diversity(emb, times=4000, rng=7) == pytest.approx(5.0, abs=0.35)


def test_diversity_requires_more_samples_than_pairs() -> None:
    with pytest.raises(ValueError, match="N > times"):
        diversity(np.zeros((300, 4)), times=300, rng=0)
    emb = np.random.default_rng(8).normal(size=(400, 4))
    assert diversity(emb, rng=9) == diversity(emb, rng=9)  # reproducible for a seed


def test_multimodality_equal_repeats_is_zero() -> None:
    # texts differ wildly, repeats of one text are identical -> 0 (pairs stay within a text)
    per_text = np.random.default_rng(10).normal(size=(5, 1, 8)) * 100.0
    emb = np.repeat(per_text, 30, axis=1)
    assert multimodality(emb, times=10, rng=0) == 0.0


def test_multimodality_two_clusters_per_text() -> None:
    # Text c has its repeats split between two points at distance d_c; E[MM] = mean(d_c) / 2.
    d = np.array([2.0, 4.0, 6.0])
    emb = np.zeros((3, 4002, 2))
    emb[:, 2001:, 1] = d[:, None]
    assert multimodality(emb, times=4000, rng=11) == pytest.approx(2.0, abs=0.2)
    with pytest.raises(ValueError, match="num_repeats > times"):
        multimodality(emb[:, :10], times=10)


def test_mean_and_ci_hand_example() -> None:
    mean, ci = mean_and_ci([1.0, 2.0, 3.0, 4.0])
    # std (ddof 0) = sqrt(1.25); ci = 1.96 * sqrt(1.25) / 2
    assert mean == pytest.approx(2.5)
    assert ci == pytest.approx(1.96 * np.sqrt(1.25) / 2.0)
    assert mean_and_ci(np.array([3.0])) == (3.0, 0.0)
    with pytest.raises(ValueError):
        mean_and_ci([])


# ------------------------------------------------------------------ control errors


def _offset(length: float) -> np.ndarray:
    return length * np.array([2.0, 1.0, 2.0]) / 3.0  # unit direction (2, 1, 2) / 3


def test_control_errors_hand_case() -> None:
    rng = np.random.default_rng(12)
    b, t, j = 3, 10, 22
    hint = rng.normal(size=(b, t, j, 3))
    pred = hint + 5.0  # every unmasked entry is far off: it must be ignored
    mask = np.zeros((b, t, j), dtype=bool)
    # sample 0: pelvis keyframes off by 0, 0.3, 0.6, 0.1 m
    for frame, err in zip([0, 3, 6, 9], [0.0, 0.3, 0.6, 0.1], strict=True):
        mask[0, frame, 0] = True
        pred[0, frame, 0] = hint[0, frame, 0] + _offset(err)
    # sample 1: two wrist keyframes, both off by 0.3 m
    for frame in (2, 7):
        mask[1, frame, 21] = True
        pred[1, frame, 21] = hint[1, frame, 21] + _offset(0.3)
    # sample 2: no keyframes -> excluded (would otherwise add zeros or huge errors)
    out = control_errors(pred, hint, mask)
    expected = {
        "traj_err_50cm": (1.0 + 0.0) / 2,
        "loc_err_50cm": (1 / 4 + 0.0) / 2,
        "traj_err_20cm": (1.0 + 1.0) / 2,
        "loc_err_20cm": (2 / 4 + 2 / 2) / 2,
        "avg_err_m": (1.0 / 4 + 0.3) / 2,
    }
    assert set(out) == set(expected)
    for key, value in expected.items():
        assert out[key] == pytest.approx(value, abs=1e-12), key


def test_control_errors_unit_and_errors() -> None:
    hint = np.zeros((1, 2, 1, 3))
    pred = hint.copy()
    pred[0, 0, 0] = [300.0, 0.0, 0.0]  # 300 mm in KIT units
    mask = np.array([[[True], [False]]])
    out = control_errors(pred, hint, mask, unit=0.001)
    assert out["avg_err_m"] == pytest.approx(0.3)
    assert out["loc_err_20cm"] == 1.0 and out["loc_err_50cm"] == 0.0
    with pytest.raises(ValueError, match="no sample"):
        control_errors(pred, hint, np.zeros_like(mask))
    with pytest.raises(ValueError, match="boolean"):
        control_errors(pred, hint, mask.astype(int))


# ------------------------------------------------------------------ physical metrics


def _standing(frames: int, lowest: float) -> np.ndarray:
    """(T, 22, 3) pose: all joints at 1 m except the toes (10, 11) at height ``lowest``."""
    joints = np.zeros((frames, HUMANML3D.joints_num, 3))
    joints[..., 1] = 1.0
    joints[:, 10, 1] = lowest
    joints[:, 11, 1] = lowest
    joints[:, 11, 0] = 0.2
    return joints


def test_physical_metrics_sliding_foot() -> None:
    # Motion A: toes at 2 cm (floating 20 mm); the left toe slides at 0.6 m/s over frame pairs
    # 10..19 of 20. With the 5-frame zero-padded box filter the smoothed speed exceeds 0.5 m/s
    # only at pairs 12..17 -> 6 / 20 = 0.3.
    sliding = _standing(21, 0.02)
    step = 0.6 / HUMANML3D.fps
    sliding[11:, 10, 0] = step * np.arange(1, 11)
    # Motion B: static, toes 2 cm below the floor (penetration 20 mm), no skating.
    sunk = _standing(30, -0.02)
    out = physical_metrics([sliding, sunk], HUMANML3D)
    assert set(out) == {"skating_ratio", "penetration_mm", "floating_mm"}
    assert out["skating_ratio"] == pytest.approx((0.3 + 0.0) / 2)
    assert out["penetration_mm"] == pytest.approx((0.0 + 20.0) / 2)
    assert out["floating_mm"] == pytest.approx((20.0 + 0.0) / 2)
    with pytest.raises(ValueError):
        physical_metrics([], HUMANML3D)


def test_control_errors_count_an_error_only_above_the_threshold() -> None:
    """OmniControl's strict ``e > th``: an error of exactly 20 cm or 50 cm is not a miss at that threshold."""
    hint = np.zeros((2, 1, 1, 3))
    pred = hint.copy()
    pred[0, 0, 0], pred[1, 0, 0] = [0.2, 0.0, 0.0], [0.5, 0.0, 0.0]
    out = metrics.control_errors(pred, hint, np.ones((2, 1, 1), dtype=bool))
    assert out["traj_err_20cm"] == 0.5 and out["loc_err_20cm"] == 0.5
    assert out["traj_err_50cm"] == 0.0 and out["loc_err_50cm"] == 0.0
    assert out["avg_err_m"] == pytest.approx(0.35)


def test_diversity_and_multimodality_pair_two_draws_without_replacement() -> None:
    """The pairs are two index sets, each drawn without replacement from one generator in that order."""
    emb = np.random.default_rng(8).normal(size=(301, 4))
    g = np.random.default_rng(9)
    a, b = g.choice(301, 300, replace=False), g.choice(301, 300, replace=False)
    expected = np.linalg.norm(emb[a] - emb[b], axis=1).mean()
    assert metrics.diversity(emb, 300, rng=9) == pytest.approx(expected, rel=1e-12)
    per_text = np.random.default_rng(10).normal(size=(3, 11, 4))
    g = np.random.default_rng(11)
    a, b = g.choice(11, 10, replace=False), g.choice(11, 10, replace=False)
    expected = np.linalg.norm(per_text[:, a] - per_text[:, b], axis=-1).mean()
    assert metrics.multimodality(per_text, 10, rng=11) == pytest.approx(expected, rel=1e-12)
