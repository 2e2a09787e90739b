"""Sampling many motions in batches of similar length (the motion-space rows: EMDM, MotionDiffuse).

A motion-space sampler runs its network on (B, max(lengths), D) at every step, so one call over a whole
evaluation draw pays for the longest crop in every row, and on a CPU a large batch also costs more per
motion than a small one (the activations leave the caches). :func:`sample_by_length` sorts the rows by
length and samples them ``batch`` at a time, each batch padded only to its own longest motion.

Seeds: batch k (in length order) samples with :func:`batch_seed` (``seed`` itself for k = 0), so a call
that fits in one batch is exactly the unbatched call, and the same (rows, lengths, seed, batch) give the
same output. A row's sample depends on which rows share its batch, as it did on the whole call before.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

#: ``sample(index, seed)``: the rows ``index`` of the call, sampled with ``seed``: (len(index), N, D)
#: features with N >= max(lengths[index]), 0 past each length.
SampleFn = Callable[[np.ndarray, int], np.ndarray]


def batch_seed(seed: int, k: int) -> int:
    """The seed of the k-th batch: ``seed`` for k = 0, else a 63-bit draw of ``SeedSequence([seed, k])``."""
    if k == 0:
        return int(seed)
    return int(np.random.SeedSequence([int(seed), k]).generate_state(1, np.uint64)[0] >> np.uint64(1))


def sample_by_length(sample: SampleFn, lengths: np.ndarray, seed: int, batch: int | None) -> np.ndarray:
    """(B, max(lengths), D): ``sample`` over the rows sorted by length (stable), ``batch`` rows at a time
    (None: all at once), each output cropped to max(lengths), put back in the rows' order."""
    lengths = np.asarray(lengths, np.int64)
    if lengths.ndim != 1 or len(lengths) == 0:
        raise ValueError(f"lengths: expected a non-empty 1-D array, got shape {lengths.shape}")
    if batch is not None and (isinstance(batch, bool) or not isinstance(batch, int) or batch < 1):
        raise ValueError(f"batch: expected null or an integer >= 1, got {batch!r}")
    n, width = len(lengths), int(lengths.max())
    if batch is None or batch >= n:
        return sample(np.arange(n), int(seed))[:, :width]
    order = np.argsort(lengths, kind="stable")
    out: np.ndarray | None = None
    for k, first in enumerate(range(0, n, batch)):
        index = order[first : first + batch]
        part = sample(index, batch_seed(seed, k))
        if out is None:
            out = np.zeros((n, width, part.shape[-1]), part.dtype)
        frames = min(part.shape[1], width)
        out[index, :frames] = part[:, :frames]
    assert out is not None
    return out
