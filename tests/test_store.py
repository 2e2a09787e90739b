"""Feature store: Parquet round trip of variable-length motions, captions and text embeddings."""

import numpy as np
import pyarrow.parquet as pq
import pytest

from data.store import StoredItem, read_split, write_split

D, E, H = 7, 5, 3


def _item(rng, k, n_captions, length):
    return StoredItem(
        item_id=f"{k:06d}",
        clip_id=f"{k:06d}",
        action="walk" if k % 2 else None,
        start=k,
        features=rng.standard_normal((length, D)).astype(np.float32),
        captions=[f"caption {k}.{c}" for c in range(n_captions)],
        tokens=[["a/DET", f"w{c}/NOUN"] for c in range(n_captions)],
        text_pooled=rng.standard_normal((n_captions, E)).astype(np.float32),
        text_tokens=[rng.standard_normal((2 + c, H)).astype(np.float16) for c in range(n_captions)],
    )


def test_round_trip_preserves_every_value(tmp_path):
    rng = np.random.default_rng(0)
    items = [_item(rng, k, n_captions=1 + k % 3, length=40 + 3 * k) for k in range(6)]
    path = tmp_path / "train.parquet"
    write_split(path, items, D, E, H)
    back = read_split(path)
    assert len(back) == len(items)
    for a, b in zip(items, back, strict=True):
        assert (a.item_id, a.clip_id, a.action, a.start) == (b.item_id, b.clip_id, b.action, b.start)
        assert b.length == a.features.shape[0]
        np.testing.assert_array_equal(a.features, b.features)
        np.testing.assert_array_equal(a.text_pooled, b.text_pooled)
        assert a.captions == b.captions and a.tokens == b.tokens
        assert len(b.text_tokens) == len(a.text_tokens)
        for ta, tb in zip(a.text_tokens, b.text_tokens, strict=True):
            assert tb.dtype == np.float16
            np.testing.assert_array_equal(ta, tb)
    assert pq.read_table(path)["length"].to_pylist() == [40 + 3 * k for k in range(6)]


def test_wrong_feature_dim_is_rejected_naming_the_item(tmp_path):
    item = _item(np.random.default_rng(1), 3, 1, 40)
    item.features = item.features[:, :-1]
    with pytest.raises(ValueError, match="000003"):
        write_split(tmp_path / "x.parquet", [item], D, E, H)
    assert not (tmp_path / "x.parquet").exists()


def test_unreadable_file_names_the_path(tmp_path):
    bad = tmp_path / "test.parquet"
    bad.write_bytes(b"PAR1 truncated")
    with pytest.raises(ValueError, match="test.parquet"):
        read_split(bad)


def test_a_parquet_file_without_a_stores_column_is_named_not_a_key_error(tmp_path):
    """A split missing ``text_tokens`` (another tool's Parquet file) raised pyarrow's KeyError, a traceback."""
    path = tmp_path / "val.parquet"
    write_split(path, [_item(np.random.default_rng(2), 1, 1, 40)], D, E, H)
    pq.write_table(pq.read_table(path).drop_columns(["text_tokens", "start"]), path)
    with pytest.raises(ValueError) as err:
        read_split(path)
    assert str(err.value) == f"{path}: not a feature-store split: no column(s) start, text_tokens"
