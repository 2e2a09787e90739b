"""MotionTextDataset's word tokens (``word_tokens`` > 0) and collate_trimmed_words, on a tiny hand-made store.

The tokens must belong to the same caption as ``text``, and serving them must not change a single random
draw: other stages' exact resume and determinism rest on the dataset's draw order.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from data.motion_dataset import MotionTextDataset, collate_trimmed, collate_trimmed_words
from data.store import StoredItem, write_split

D, E, H, W = 7, 4, 5, 6
#: Word-token counts of each item's captions (item k has len(TOKENS[k]) captions).
TOKENS = [(2, 3, 5), (4,), (1, 6), (3, 2, 2, 4)]


def _item(k: int, counts: tuple[int, ...]) -> StoredItem:
    rng = np.random.default_rng(k)
    features = rng.standard_normal((20 + 7 * k, D)).astype(np.float32)
    # caption c of item k: pooled entries and every token entry carry 10 k + c, so a pair can be matched
    pooled = np.stack([np.full(E, 10 * k + c, np.float32) for c in range(len(counts))])
    tokens = [np.full((n, H), 10 * k + c, np.float16) + np.arange(n, dtype=np.float16)[:, None] / 100
              for c, n in enumerate(counts)]
    return StoredItem(f"i{k}", f"c{k}", None, 0, features, [f"cap {k} {c}" for c in range(len(counts))],
                      [[f"w{c}/NOUN"] for c in range(len(counts))], pooled, tokens)


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("words_store")
    write_split(root / "train.parquet", [_item(k, c) for k, c in enumerate(TOKENS)], D, E, H)
    return root


def _dataset(store: Path, word_tokens: int = 0, max_frames: int = 24) -> MotionTextDataset:
    return MotionTextDataset(store, "train", np.zeros(D), np.ones(D), max_frames, word_tokens=word_tokens)


def _serve(data: MotionTextDataset, seed: int, rounds: int = 6) -> tuple[list[dict[str, torch.Tensor]], torch.Tensor]:
    torch.manual_seed(seed)
    items = [data[k] for _ in range(rounds) for k in range(len(data))]
    return items, torch.get_rng_state()


def test_word_tokens_change_no_draw_and_no_existing_element(store: Path) -> None:
    plain, plain_rng = _serve(_dataset(store), seed=3)
    words, words_rng = _serve(_dataset(store, W), seed=3)
    assert torch.equal(plain_rng, words_rng)  # the same number of draws from the global RNG
    assert all(set(item) == {"motion", "length", "text", "index"} for item in plain)
    for a, b in zip(plain, words, strict=True):
        assert set(b) == set(a) | {"tokens", "token_mask"}
        for key in a:
            assert torch.equal(a[key], b[key]), key


def test_tokens_are_the_same_captions_zero_padded(store: Path) -> None:
    items, _ = _serve(_dataset(store, W), seed=0, rounds=10)
    seen = set()
    for item in items:
        k, c = int(item["index"]), int(item["text"][0]) % 10
        n = TOKENS[k][c]
        seen.add((k, c))
        assert item["tokens"].shape == (W, H) and item["tokens"].dtype == torch.float32
        assert item["token_mask"].dtype == torch.bool and item["token_mask"].tolist() == [i < n for i in range(W)]
        expected = 10 * k + c + np.arange(n)[:, None] / 100
        np.testing.assert_allclose(item["tokens"][:n].numpy(), np.broadcast_to(expected, (n, H)), atol=0.02)
        assert not item["tokens"][n:].any()
    assert len(seen) > 6  # several captions of several items were drawn


def test_bad_word_tokens_and_too_long_captions_are_errors(store: Path) -> None:
    for bad in (-1, True, 2.0):
        with pytest.raises(ValueError, match="word_tokens"):
            _dataset(store, bad)  # type: ignore[arg-type]
    data = _dataset(store, 3)
    torch.manual_seed(0)
    with pytest.raises(ValueError, match="more than max_tokens=3"):
        for _ in range(20):
            data[2]  # its second caption has 6 tokens


def test_collate_trimmed_words_cuts_motion_and_tokens_to_padding_only(store: Path) -> None:
    data = _dataset(store, W, max_frames=40)
    torch.manual_seed(1)
    items = [data[0], data[1], data[2]]
    batch = collate_trimmed_words(items)
    longest_caption = max(int(i["token_mask"].sum()) for i in items)
    assert batch["motion"].shape == (3, int(max(i["length"] for i in items)), D)
    assert batch["tokens"].shape == (3, longest_caption, H) and batch["token_mask"].shape == (3, longest_caption)
    for b, item in enumerate(items):
        n = int(item["token_mask"].sum())
        assert torch.equal(batch["tokens"][b, :n], item["tokens"][:n]) and int(batch["token_mask"][b].sum()) == n
    plain = [{k: v for k, v in i.items() if k not in ("tokens", "token_mask")} for i in items]
    for key, value in collate_trimmed(plain).items():  # without tokens it is collate_trimmed
        assert torch.equal(collate_trimmed_words(plain)[key], value)
