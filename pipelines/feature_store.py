"""The feature store as one object: ``extract_features``'s folder, read by every later stage.

Layout (written by ``stages/extract_features.py``): ``<split>.parquet`` per split
(:mod:`data.store`), ``mean.npy`` / ``std.npy`` (D,) float32 feature statistics and ``meta.json``
(``text_encoder``: name, path, max_length, dim, token_dim; and the extraction settings).

:class:`FeatureStore` owns them: it checks the statistics once, encodes prompts with the same
frozen text encoder the captions were encoded with, and turns normalised generator output back
into joints.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from data.features import check_stats, recover_from_ric
from data.store import StoredItem, read_split
from data.text_encoders import TextEncoder, build_text_encoder
from models.generator import TextBatch


class FeatureStore:
    """A feature-store folder: statistics, metadata, splits and its text encoder.

    The statistics are checked once, on opening: ``mean.npy`` and ``std.npy`` must be finite
    ``(D,)`` arrays with ``std > 0``, where D is the features' dimension (``meta.json``'s
    ``feature_dim`` and every split's Parquet width, which must agree). Any other store would
    fail far downstream (a broadcast error, or a model training on NaN); this names the file.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path).resolve()
        if not self.path.is_dir():
            raise FileNotFoundError(f"{self.path}: no feature store (run `dvc repro extract_features`)")
        meta_path = self.path / "meta.json"
        try:
            self.meta: dict[str, Any] = json.loads(meta_path.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as err:
            raise ValueError(f"{meta_path}: cannot read the store's metadata ({err})") from err
        if "text_encoder" not in self.meta:
            raise ValueError(f"{meta_path}: no 'text_encoder' entry")
        self.mean = self._load_stat("mean.npy")
        self.std = self._load_stat("std.npy")
        check_stats(self.mean, self.std, self.path, self._declared_feature_dim())
        self._check_split_widths()

    def _load_stat(self, name: str) -> np.ndarray:
        path = self.path / name
        try:
            values = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as err:
            raise ValueError(f"{path}: cannot read ({err})") from err
        if not (np.issubdtype(values.dtype, np.floating) or np.issubdtype(values.dtype, np.integer)):
            raise ValueError(f"{path}: dtype {values.dtype} is not a real number type")
        return values.astype(np.float32)

    def _declared_feature_dim(self) -> int | None:
        """``meta.json``'s feature_dim (stores written by hand may leave it out)."""
        dim = self.meta.get("feature_dim")
        if dim is not None and (isinstance(dim, bool) or not isinstance(dim, int)):
            raise ValueError(f"{self.path / 'meta.json'}: feature_dim {dim!r} is not an integer")
        return dim

    def _check_split_widths(self) -> None:
        """Every split's Parquet features have the statistics' dimension (read from the footer)."""
        for path in sorted(self.path.glob("*.parquet")):
            try:
                width = pq.read_schema(path).field("features").type.value_type.list_size
            except (OSError, KeyError, AttributeError, pa.ArrowException) as err:
                raise ValueError(f"{path}: not a feature-store split ({err})") from err
            if width != self.feature_dim:
                raise ValueError(f"{path}: features are ({width},) per frame but {self.path / 'mean.npy'} "
                                 f"and std.npy are {self.mean.shape}")

    @property
    def feature_dim(self) -> int:
        return int(self.mean.shape[0])

    @property
    def joints_num(self) -> int:
        """Joints of the skeleton the features describe (D = 12 J - 1)."""
        return (self.feature_dim + 1) // 12

    @property
    def text_encoder_meta(self) -> dict[str, Any]:
        """``name``, ``path``, ``max_length``, ``dim`` (pooled) and ``token_dim`` of the caption encoder."""
        return self.meta["text_encoder"]

    def split(self, name: str) -> list[StoredItem]:
        """The items of split ``name`` (``train``, ``val`` or ``test``)."""
        path = self.path / f"{name}.parquet"
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such split in the feature store")
        return read_split(path)

    def normalised_motions(self, name: str) -> list[np.ndarray]:
        """Each item's features (T_i, D) of split ``name``, normalised by the store's Mean/Std (float32)."""
        return [((item.features - self.mean) / self.std).astype(np.float32) for item in self.split(name)]

    @cached_property
    def text_encoder(self) -> TextEncoder:
        """The frozen encoder the captions were encoded with, loaded once (None path: the packaged one)."""
        meta = self.text_encoder_meta
        return build_text_encoder(meta["name"], path=meta["path"], max_length=meta["max_length"])

    def encode_prompts(self, texts: Sequence[str]) -> TextBatch:
        """Prompts as a :class:`TextBatch` (pooled and real-token embeddings)."""
        enc = self.text_encoder.encode(list(texts))
        return TextBatch(list(texts), enc.pooled, [enc.tokens[k][enc.mask[k]] for k in range(len(texts))])

    def to_joints(self, features: np.ndarray, lengths: Sequence[int]) -> list[np.ndarray]:
        """Normalised (B, T, D) generator output -> B global joint arrays (L_b, J, 3) in metres."""
        return [recover_from_ric(features[b, :n] * self.std + self.mean, self.joints_num)
                for b, n in enumerate(lengths)]
