"""The feature store: one Parquet file per split, one row per motion item.

A row is one HumanML3D *item* (a whole clip, or a captioned time span of it) with all of its
captions. Columns:

=================  =============================================  ==============================
column             Arrow type                                     numpy on read
=================  =============================================  ==============================
item_id, clip_id   string                                         str
action             string (null when the dataset has no labels)   str | None
start, length      int32 (feature frames within the clip)         int
features           list<fixed_size_list<float32, D>>              (length, D) float32
captions           list<string>                                   list[str] (C captions)
tokens             list<list<string>> ("word/POS")                list[list[str]]
text_pooled        list<fixed_size_list<float32, E>>              (C, E) float32
text_tokens        list<list<fixed_size_list<float16, H>>>        list of (n_c, H) float16
=================  =============================================  ==============================

Token embeddings are stored in float16 and only for real tokens (the mask is their count): they
are the bulk of the store. Readers return plain Python/numpy objects (:class:`StoredItem`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq


@dataclass
class StoredItem:
    """One row of the store (shapes in the module docstring)."""

    item_id: str
    clip_id: str
    action: str | None
    start: int
    features: np.ndarray
    captions: list[str]
    tokens: list[list[str]]
    text_pooled: np.ndarray
    text_tokens: list[np.ndarray]

    @property
    def length(self) -> int:
        return int(self.features.shape[0])


#: The columns :func:`read_split` reads (:func:`write_split` writes them and ``length``).
COLUMNS = ("item_id", "clip_id", "action", "start", "features", "captions", "tokens", "text_pooled", "text_tokens")

def _fixed_rows(rows: Sequence[np.ndarray], width: int, dtype: pa.DataType) -> pa.Array:
    """list<fixed_size_list<dtype, width>> from a sequence of (n_i, width) arrays."""
    np_dtype = np.float16 if dtype == pa.float16() else np.float32
    flat = np.concatenate([np.asarray(r, dtype=np_dtype).reshape(-1) for r in rows]) if rows else np.zeros(0)
    values = pa.FixedSizeListArray.from_arrays(pa.array(flat.astype(np_dtype), type=dtype), width)
    offsets = np.concatenate([[0], np.cumsum([len(r) for r in rows])]).astype(np.int32)
    return pa.ListArray.from_arrays(pa.array(offsets), values)


def _nested_token_rows(items: Sequence[StoredItem], width: int) -> pa.Array:
    """list<list<fixed_size_list<float16, H>>> of every item's per-caption token embeddings."""
    per_caption = [t for item in items for t in item.text_tokens]
    inner = _fixed_rows(per_caption, width, pa.float16())
    offsets = np.concatenate([[0], np.cumsum([len(item.text_tokens) for item in items])]).astype(np.int32)
    return pa.ListArray.from_arrays(pa.array(offsets), inner)


def items_to_table(items: Sequence[StoredItem], feature_dim: int, text_dim: int, token_dim: int) -> pa.Table:
    """Build the Arrow table of a split; checks every array's trailing dimension."""
    for item in items:
        if item.features.ndim != 2 or item.features.shape[1] != feature_dim:
            raise ValueError(f"item {item.item_id}: features {item.features.shape}, expected (T, {feature_dim})")
        if item.text_pooled.shape != (len(item.captions), text_dim):
            raise ValueError(f"item {item.item_id}: text_pooled {item.text_pooled.shape} for "
                             f"{len(item.captions)} captions of dim {text_dim}")
        if len(item.text_tokens) != len(item.captions) or len(item.tokens) != len(item.captions):
            raise ValueError(f"item {item.item_id}: one tokens entry per caption is required")
    columns = {
        "item_id": pa.array([i.item_id for i in items], pa.string()),
        "clip_id": pa.array([i.clip_id for i in items], pa.string()),
        "action": pa.array([i.action for i in items], pa.string()),
        "start": pa.array([i.start for i in items], pa.int32()),
        "length": pa.array([i.length for i in items], pa.int32()),
        "features": _fixed_rows([i.features for i in items], feature_dim, pa.float32()),
        "captions": pa.array([i.captions for i in items], pa.list_(pa.string())),
        "tokens": pa.array([i.tokens for i in items], pa.list_(pa.list_(pa.string()))),
        "text_pooled": _fixed_rows([i.text_pooled for i in items], text_dim, pa.float32()),
        "text_tokens": _nested_token_rows(items, token_dim),
    }
    return pa.table(columns)


def write_split(path: Path, items: Sequence[StoredItem], feature_dim: int, text_dim: int, token_dim: int) -> None:
    """Write one split's Parquet file (the caller makes the whole store atomic)."""
    pq.write_table(items_to_table(items, feature_dim, text_dim, token_dim), path, compression="zstd")


def _split_rows(list_array: pa.Array, dtype: type) -> list[np.ndarray]:
    """Per-row numpy arrays (n_i, width) of a list<fixed_size_list> column."""
    list_array = list_array.combine_chunks() if isinstance(list_array, pa.ChunkedArray) else list_array
    inner = list_array.values
    width = inner.type.list_size
    flat = inner.values.to_numpy(zero_copy_only=False).astype(dtype).reshape(-1, width)
    offsets = list_array.offsets.to_numpy()
    return [flat[offsets[k] : offsets[k + 1]] for k in range(len(list_array))]


def read_split(path: Path) -> list[StoredItem]:
    """Read a split written by :func:`write_split`; raises ValueError naming a malformed file."""
    try:
        table = pq.read_table(path)
    except (OSError, pa.ArrowException) as err:
        raise ValueError(f"{path}: not a readable Parquet file ({err})") from err
    missing = [name for name in COLUMNS if name not in table.column_names]
    if missing:
        raise ValueError(f"{path}: not a feature-store split: no column(s) {', '.join(missing)}")
    features = _split_rows(table["features"], np.float32)
    pooled = _split_rows(table["text_pooled"], np.float32)
    nested = table["text_tokens"].combine_chunks()
    per_caption = _split_rows(nested.values, np.float16)
    cap_offsets = nested.offsets.to_numpy()
    cols = {name: table[name].to_pylist() for name in ("item_id", "clip_id", "action", "start", "captions", "tokens")}
    return [
        StoredItem(
            item_id=cols["item_id"][k],
            clip_id=cols["clip_id"][k],
            action=cols["action"][k],
            start=cols["start"][k],
            features=features[k],
            captions=cols["captions"][k],
            tokens=cols["tokens"][k],
            text_pooled=pooled[k],
            text_tokens=per_caption[cap_offsets[k] : cap_offsets[k + 1]],
        )
        for k in range(table.num_rows)
    ]
