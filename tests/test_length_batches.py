"""Sampling in length-sorted batches: every row once, in its place, zero past its length; the batches sorted
and seeded per batch; one batch is the plain call."""

from __future__ import annotations

import numpy as np
import pytest

from pipelines.length_batches import batch_seed, sample_by_length

D = 3


class Recorder:
    """A sampler whose output row b is (global row id + 1, seed % 1000, 7) over its length, 0 past it, padded to
    the batch's longest motion plus two spare frames (a sampler may return more frames than asked)."""

    def __init__(self, lengths: np.ndarray) -> None:
        self.lengths, self.calls = lengths, []

    def __call__(self, index: np.ndarray, seed: int) -> np.ndarray:
        self.calls.append((np.asarray(index).copy(), seed))
        out = np.zeros((len(index), int(self.lengths[index].max()) + 2, D), np.float32)
        for row, i in enumerate(index):
            out[row, : self.lengths[i]] = (i + 1, seed % 1000, 7)
        return out


LENGTHS = np.array([40, 12, 40, 28, 8, 196, 28, 60])


def test_rows_come_back_in_place_zero_past_their_lengths() -> None:
    sampler = Recorder(LENGTHS)
    out = sample_by_length(sampler, LENGTHS, seed=5, batch=3)
    assert out.shape == (len(LENGTHS), 196, D)
    for i, n in enumerate(LENGTHS):
        assert (out[i, :n, 0] == i + 1).all() and (out[i, :n, 2] == 7).all()
        assert not out[i, n:].any()


def test_batches_are_sorted_by_length_stable_and_cover_every_row_once() -> None:
    sampler = Recorder(LENGTHS)
    sample_by_length(sampler, LENGTHS, seed=5, batch=3)
    batches = [index for index, _ in sampler.calls]
    assert [len(b) for b in batches] == [3, 3, 2]
    np.testing.assert_array_equal(np.concatenate(batches), [4, 1, 3, 6, 0, 2, 7, 5])  # ties keep their order
    assert all(LENGTHS[a].max() <= LENGTHS[b].min() for a, b in zip(batches, batches[1:], strict=False))


def test_each_batch_has_its_own_seed_and_the_first_keeps_the_call_s() -> None:
    sampler = Recorder(LENGTHS)
    sample_by_length(sampler, LENGTHS, seed=5, batch=3)
    seeds = [seed for _, seed in sampler.calls]
    assert seeds[0] == 5 and len(set(seeds)) == 3
    assert seeds == [batch_seed(5, k) for k in range(3)]
    assert all(0 <= s < 2**63 for s in seeds)  # a valid torch.Generator seed
    assert batch_seed(6, 1) != batch_seed(5, 1)
    again = Recorder(LENGTHS)
    np.testing.assert_array_equal(sample_by_length(again, LENGTHS, 5, 3), sample_by_length(sampler, LENGTHS, 5, 3))


@pytest.mark.parametrize("batch", [None, 8, 100])
def test_one_batch_is_the_plain_call(batch: int | None) -> None:
    sampler = Recorder(LENGTHS)
    out = sample_by_length(sampler, LENGTHS, seed=9, batch=batch)
    assert len(sampler.calls) == 1
    index, seed = sampler.calls[0]
    np.testing.assert_array_equal(index, np.arange(len(LENGTHS)))
    assert seed == 9 and out.shape == (len(LENGTHS), 196, D)


@pytest.mark.parametrize("batch", [0, -2, True, 1.5, "16"])
def test_bad_batch_is_named(batch: object) -> None:
    with pytest.raises(ValueError, match="batch: expected null or an integer >= 1"):
        sample_by_length(Recorder(LENGTHS), LENGTHS, 0, batch)  # type: ignore[arg-type]


def test_empty_or_nested_lengths_are_refused() -> None:
    with pytest.raises(ValueError, match="non-empty 1-D"):
        sample_by_length(Recorder(LENGTHS), np.array([], np.int64), 0, 4)
    with pytest.raises(ValueError, match="non-empty 1-D"):
        sample_by_length(Recorder(LENGTHS), LENGTHS.reshape(2, 4), 0, 4)
