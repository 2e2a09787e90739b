"""Word vocabulary and part-of-speech classes for the T2M evaluator's text input.

Reference: ``reference/humanml3d_eval.md`` section B.1 (text-to-motion ``utils/word_vectorizer.py``).

A caption reaches the evaluator as its HumanML3D tokens, ``"word/POS"`` strings (the feature store's
``tokens`` column; the POS follows the *last* ``/``). Each token becomes

- a word id in a :class:`WordVocab` built from the training captions (words seen at least
  ``min_count`` times, plus ``sos``, ``eos`` and ``unk``), and
- a one-hot over the 15 POS classes of :data:`POS_CLASSES`. A word from one of the VIP lists
  (:data:`VIP_WORDS`) takes its VIP class instead of its spaCy POS; a POS outside the
  enumeration becomes ``OTHER``.

As in the reference, a word that is not in the vocabulary becomes ``unk`` **with POS OTHER** (its
tagged POS and any VIP class are dropped): the network sees exactly what it sees for padding.

:meth:`WordVocab.encode_tokens` builds the fixed-size input (reference B.1): the first
``max_words`` (20) tokens, ``sos/OTHER`` before them, ``eos/OTHER`` after them, ``unk/OTHER``
padding up to ``max_words + 2`` (22) positions, and ``sent_len = n + 2``.

:func:`load_glove` optionally initialises the word embeddings from GloVe-format text vectors. This
module is numpy-only and never imports ``models``; its only file access is :func:`load_glove`.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np

#: The 15 POS classes in index order (reference B.1).
POS_CLASSES: tuple[str, ...] = (
    "VERB",
    "NOUN",
    "DET",
    "ADP",
    "NUM",
    "AUX",
    "PRON",
    "ADJ",
    "ADV",
    "Loc_VIP",
    "Body_VIP",
    "Obj_VIP",
    "Act_VIP",
    "Desc_VIP",
    "OTHER",
)
POS_INDEX: dict[str, int] = {name: i for i, name in enumerate(POS_CLASSES)}
NUM_POS = len(POS_CLASSES)
OTHER = POS_INDEX["OTHER"]

#: Words that override their tagged POS with a VIP class (reference B.1), lower case.
VIP_WORDS: dict[str, frozenset[str]] = {
    "Loc_VIP": frozenset(
        "left right clockwise counterclockwise anticlockwise forward back backward up down straight curve".split()
    ),
    "Body_VIP": frozenset("arm chin foot feet face hand mouth leg waist eye knee shoulder thigh".split()),
    "Obj_VIP": frozenset("stair dumbbell chair window floor car ball handrail baseball basketball".split()),
    "Act_VIP": frozenset(
        (
            "walk run swing pick bring kick put squat throw hop dance jump turn stumble stop sit lift lower raise "
            "wash stand kneel stroll rub bend balance flap jog shuffle lean rotate spin spread climb"
        ).split()
    ),
    "Desc_VIP": frozenset("slowly carefully fast careful slow quickly happy angry sad happily angrily sadly".split()),
}
#: word -> VIP class index. The lists are disjoint, so the order of lookup does not matter.
_VIP_CLASS: dict[str, int] = {word: POS_INDEX[name] for name, words in VIP_WORDS.items() for word in words}

SOS, EOS, UNK = "sos", "eos", "unk"
SPECIAL_WORDS: tuple[str, ...] = (SOS, EOS, UNK)
MAX_WORDS = 20

_FORMAT = "motionforge-word-vocab"
_VERSION = 1


def split_token(token: str) -> tuple[str, str]:
    """``"word/POS"`` -> ``("word", "POS")``; the POS is after the last ``/``. Raises ValueError."""
    if not isinstance(token, str):
        raise TypeError(f"token must be a 'word/POS' string, got {type(token).__name__}")
    word, sep, pos = token.rpartition("/")
    if not sep or not word or not pos:
        raise ValueError(f"token {token!r} is not 'word/POS'")
    return word, pos


def pos_class(word: str, pos: str) -> int:
    """POS class index of a known word: its VIP class if it has one, else its POS, else OTHER.

    ``word`` is compared to the (lower-case) VIP lists as given; :class:`WordVocab` lower-cases
    words before calling this when it is built with ``lowercase=True``.
    """
    vip = _VIP_CLASS.get(word)
    if vip is not None:
        return vip
    return POS_INDEX.get(pos, OTHER)


class WordVocab:
    """Word <-> id map with the special words ``sos`` (id 0), ``eos`` (1) and ``unk`` (2).

    Build it from training captions with :meth:`build`; persist it with :meth:`to_dict` /
    :meth:`from_dict` (JSON-serialisable). Ids ``3..`` are the words, most frequent first (ties
    alphabetical), so a vocabulary is fully determined by its training tokens and ``min_count``.

    Args:
        words: every word in id order, starting with ``sos, eos, unk``.
        lowercase: whether words are lower-cased before lookup (and were when building).
    """

    def __init__(self, words: Sequence[str], lowercase: bool = True) -> None:
        words = list(words)
        if tuple(words[: len(SPECIAL_WORDS)]) != SPECIAL_WORDS:
            raise ValueError(f"a vocabulary must start with {SPECIAL_WORDS}, got {tuple(words[:3])}")
        index: dict[str, int] = {}
        for i, word in enumerate(words):
            if not isinstance(word, str) or not word or any(ch.isspace() for ch in word):
                raise ValueError(f"invalid vocabulary word {word!r} at id {i}")
            if word in index:
                raise ValueError(f"duplicate vocabulary word {word!r} (ids {index[word]} and {i})")
            index[word] = i
        self._words = words
        self._index = index
        self.lowercase = bool(lowercase)

    # -- construction -----------------------------------------------------------------------

    @classmethod
    def build(cls, captions: Iterable[Sequence[str]], min_count: int = 1, lowercase: bool = True) -> WordVocab:
        """Vocabulary of the words occurring at least ``min_count`` times in ``captions``.

        Args:
            captions: token lists, each a sequence of ``"word/POS"`` strings (all training captions;
                truncation to 20 words is *not* applied when counting).
            min_count: minimum number of occurrences (>= 1).
            lowercase: lower-case words before counting and lookup.
        """
        if int(min_count) != min_count or min_count < 1:
            raise ValueError(f"min_count must be an integer >= 1, got {min_count!r}")
        counts: Counter[str] = Counter()
        for tokens in captions:
            if isinstance(tokens, str):
                raise TypeError("captions must be token lists, not strings")
            for token in tokens:
                word, _ = split_token(token)
                counts[word.lower() if lowercase else word] += 1
        kept = sorted((w for w, c in counts.items() if c >= min_count and w not in SPECIAL_WORDS),
                      key=lambda w: (-counts[w], w))
        return cls([*SPECIAL_WORDS, *kept], lowercase=lowercase)

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable description; :meth:`from_dict` inverts it."""
        return {"format": _FORMAT, "version": _VERSION, "lowercase": self.lowercase, "words": list(self._words)}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> WordVocab:
        """Inverse of :meth:`to_dict`. Raises ValueError on a foreign or malformed dict."""
        if data.get("format") != _FORMAT or data.get("version") != _VERSION:
            raise ValueError(
                f"not a {_FORMAT} v{_VERSION} dict (format={data.get('format')!r}, version={data.get('version')!r})"
            )
        words = data.get("words")
        if not isinstance(words, list):
            raise ValueError("vocabulary dict has no 'words' list")
        return cls(words, lowercase=bool(data.get("lowercase", True)))

    # -- lookup -----------------------------------------------------------------------------

    @property
    def words(self) -> list[str]:
        """All words in id order (a copy)."""
        return list(self._words)

    @property
    def sos_id(self) -> int:
        return 0

    @property
    def eos_id(self) -> int:
        return 1

    @property
    def unk_id(self) -> int:
        return 2

    def __len__(self) -> int:
        return len(self._words)

    def __contains__(self, word: object) -> bool:
        return isinstance(word, str) and self._key(word) in self._index

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, WordVocab):
            return NotImplemented
        return self._words == other._words and self.lowercase == other.lowercase

    def __repr__(self) -> str:
        return f"WordVocab({len(self)} words, lowercase={self.lowercase})"

    def _key(self, word: str) -> str:
        return word.lower() if self.lowercase else word

    def id_of(self, word: str) -> int:
        """Id of ``word``, or the ``unk`` id when it is not in the vocabulary."""
        return self._index.get(self._key(word), self.unk_id)

    def word_of(self, word_id: int) -> str:
        return self._words[word_id]

    def encode_token(self, token: str) -> tuple[int, int]:
        """``"word/POS"`` -> ``(word id, POS class)``.

        A known word gets its VIP class or its POS (unknown POS -> OTHER); an unknown word gets
        ``(unk id, OTHER)`` as in the reference.
        """
        word, pos = split_token(token)
        key = self._key(word)
        word_id = self._index.get(key)
        if word_id is None:
            return self.unk_id, OTHER
        return word_id, pos_class(key, pos)

    def encode_tokens(self, tokens: Sequence[str], max_words: int = MAX_WORDS) -> tuple[np.ndarray, np.ndarray, int]:
        """Fixed-size evaluator input of one caption (reference B.1).

        Args:
            tokens: ``"word/POS"`` strings, n of them.
            max_words: words kept (20); the output has ``L = max_words + 2`` positions.

        Returns:
            ``word_ids`` (L,) int64: ``sos, w_1..w_m, eos, unk...`` with ``m = min(n, max_words)``;
            ``pos_onehot`` (L, 15) float32: OTHER at sos/eos/padding, the token classes between;
            ``sent_len`` = m + 2.
        """
        if isinstance(tokens, str):
            raise TypeError("tokens must be a list of 'word/POS' strings, not one string")
        if int(max_words) != max_words or max_words < 0:
            raise ValueError(f"max_words must be an integer >= 0, got {max_words!r}")
        encoded = [self.encode_token(t) for t in list(tokens)[:max_words]]
        length = max_words + 2
        sent_len = len(encoded) + 2
        word_ids = np.full(length, self.unk_id, dtype=np.int64)
        classes = np.full(length, OTHER, dtype=np.int64)
        word_ids[0] = self.sos_id
        for i, (word_id, cls) in enumerate(encoded, start=1):
            word_ids[i] = word_id
            classes[i] = cls
        word_ids[sent_len - 1] = self.eos_id
        pos_onehot = np.zeros((length, NUM_POS), dtype=np.float32)
        pos_onehot[np.arange(length), classes] = 1.0
        return word_ids, pos_onehot, sent_len

    def encode_batch(
        self, captions: Sequence[Sequence[str]], max_words: int = MAX_WORDS
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`encode_tokens` of B captions: ``(B, L)`` int64, ``(B, L, 15)`` float32, ``(B,)`` int64."""
        rows = [self.encode_tokens(tokens, max_words) for tokens in captions]
        length = max_words + 2
        if not rows:
            return (np.zeros((0, length), np.int64), np.zeros((0, length, NUM_POS), np.float32), np.zeros(0, np.int64))
        return (
            np.stack([r[0] for r in rows]),
            np.stack([r[1] for r in rows]),
            np.array([r[2] for r in rows], dtype=np.int64),
        )


def load_glove(
    path: str | PathLike[str],
    vocab: WordVocab,
    dim: int | None = None,
    seed: int = 0,
    missing_std: float = 0.1,
) -> np.ndarray:
    """Word vectors for ``vocab`` from a GloVe-format text file.

    Each non-empty line is ``word v_1 ... v_dim`` (whitespace separated; no header line). A vocabulary
    word is matched by its vocabulary spelling (lower case for a lower-casing vocabulary); the first
    line of a word wins. Lines of words outside the vocabulary are checked for their width but
    otherwise skipped, so only ``len(vocab)`` vectors are held.

    Words absent from the file (always ``sos``, ``eos`` and ``unk`` for a plain GloVe file) get
    small random vectors ``N(0, missing_std^2)`` drawn from ``numpy.random.default_rng(seed)``: the
    whole (V, dim) matrix is drawn first and the found rows are overwritten, so a row's random
    vector depends only on the seed, the vocabulary size and ``dim``.

    Args:
        path: the vectors file (UTF-8).
        vocab: the vocabulary whose rows to fill.
        dim: expected vector width; ``None`` takes it from the first line.
        seed, missing_std: the random vectors of missing words.

    Returns:
        (len(vocab), dim) float32; row i is the vector of ``vocab.word_of(i)``.

    Raises:
        ValueError naming the file (and line) on a malformed line, a width mismatch, an empty file
        or a non-UTF-8 file; FileNotFoundError when it does not exist.
    """
    path = Path(path)
    found: dict[int, np.ndarray] = {}
    width = dim
    try:
        with path.open("r", encoding="utf-8") as handle:
            for line_no, line in enumerate(handle, start=1):
                parts = line.split()
                if not parts:
                    continue
                word, values = parts[0], parts[1:]
                if width is None:
                    width = len(values)
                    if width == 0:
                        raise ValueError(f"{path}:{line_no}: malformed line, word {word!r} has no vector values")
                if len(values) != width:
                    raise ValueError(
                        f"{path}:{line_no}: vector of {word!r} has {len(values)} values, expected {width} "
                        "(dimension mismatch or malformed line)"
                    )
                word_id = vocab._index.get(vocab._key(word))
                if word_id is None or word_id in found:
                    continue
                try:
                    vector = np.array([float(v) for v in values], dtype=np.float32)
                except ValueError:
                    raise ValueError(f"{path}:{line_no}: malformed line, non-numeric value in vector of {word!r}") \
                        from None
                if not np.all(np.isfinite(vector)):
                    raise ValueError(f"{path}:{line_no}: non-finite value in vector of {word!r}")
                found[word_id] = vector
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not a UTF-8 text file ({exc})") from None
    if width is None:
        raise ValueError(f"{path}: no word vectors found (empty file)")
    rng = np.random.default_rng(seed)
    table = (rng.standard_normal((len(vocab), width)) * missing_std).astype(np.float32)
    for word_id, vector in found.items():
        table[word_id] = vector
    return table
