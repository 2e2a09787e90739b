"""The MLD family end to end on a tiny store: evaluator, VAE and MLD through Ray, then evaluate.

Model sizes and step counts are minimal: this checks the stages' wiring, artefacts and the
generator interface (values, determinism, padding), not model quality.
"""

import copy
import json
from pathlib import Path

import numpy as np
import pytest

from models.generator import Generator, TextBatch
from pipelines.generators import MLDGenerator
from stages import evaluate, generate, train_evaluator, train_mld, train_vae

TINY_NET = {"layers": 1, "heads": 2, "ff_dim": 32}


@pytest.fixture(scope="module")
def trained(small_store, ray_cluster):
    params = copy.deepcopy(small_store)
    params["ray"].update(num_workers=1, checkpoint_every=3, max_failures=0)
    params["train_evaluator"].update(profile="smoke", movement_steps=4, matching_steps=6, batch_size=16)
    params["train_vae"].update(max_steps=6, batch_size=8, max_frames=64, log_every=3, warmup_steps=0)
    params["train_vae"]["model"].update(latent_dim=16, **TINY_NET)
    params["train_mld"].update(max_steps=6, batch_size=8, max_frames=64, log_every=3, warmup_steps=0)
    params["train_mld"]["model"].update(time_freq_dim=16, **TINY_NET)
    params["evaluate"].update(replications=1, diversity_times=10, mm_texts=4, mm_repeats=11, timing_sentences=2)
    params["evaluate"]["samples"].update(prompts=["a person walks forward"], length=40)
    in_process = copy.deepcopy(params)
    in_process["ray"]["num_workers"] = 0
    train_evaluator.run(in_process)
    train_vae.run(params)
    train_mld.run(params)
    return params


def test_vae_and_mld_write_resumable_models(trained):
    artifacts = trained["paths"]["artifacts"]
    for stage in ("train_vae", "train_mld"):
        metrics = json.loads(open(f"{artifacts}/{stage}/metrics.json").read())
        assert metrics["step"] == 6 and np.isfinite(metrics["loss"])
        run = json.loads(open(f"{artifacts}/{stage}/run.json").read())
        assert run["run_path"] is not None  # ran under Ray Train, with checkpoints in storage
    denoiser, schedule, config = train_mld.load_mld(Path(artifacts) / "train_mld")
    assert config["model"]["latent_dim"] == 16 and config["model"]["latent_scale"] > 0
    assert schedule.num_steps == 1000


def test_vae_dataset_lengths_are_the_served_lengths(trained):
    """``lengths`` (what the VAE's length-bucketed batch order sorts by) match what items serve."""
    data = train_vae.dataset(train_vae.loop_config(trained))
    assert trained["train_vae"]["length_buckets"] > 0
    served = [int(data[k]["length"]) for k in range(len(data))]
    assert data.lengths.tolist() == served
    assert data.lengths.tolist() == [min(item.length, 64) for item in data.items]
    assert any(item.length > 64 for item in data.items)  # long items are served cropped to max_frames


def test_latent_cache_is_each_items_own_posterior(trained):
    """The cached (mu, logvar) of an item equal encoding it alone, unpadded; captions are the item's own."""
    import torch

    config = train_mld.loop_config(trained)
    assert config["model"]["latent_scale"] > 0
    data = train_mld.dataset(config)
    vae = train_vae.load_vae(Path(config["vae_dir"]))
    for k in (0, len(data) // 2, len(data) - 1):
        x, n = data.motions.window(k)
        dist = vae.encode_distribution(torch.from_numpy(x[None, :n]), [n])
        torch.testing.assert_close(data.mu[k], dist.mu[0], rtol=1e-4, atol=1e-5)
        torch.testing.assert_close(data.logvar[k], dist.logvar[0], rtol=1e-4, atol=1e-5)
        text = data[k]["text"].numpy()
        assert np.isclose(data.motions.items[k].text_pooled, text).all(axis=1).any()


def test_latent_items_carry_their_captions_word_tokens(trained):
    """With word tokens the item's word tokens are its drawn caption's, zero-padded; a batch is cut
    to its longest caption."""
    import torch

    config = train_mld.loop_config(trained)
    assert config["model"]["word_tokens"] != "none" and config["model"]["token_dim"] == 384
    data = train_mld.dataset(config)
    torch.manual_seed(3)
    items = [data[k] for k in range(8)]
    for k, item in enumerate(items):
        caption = next(c for c, pooled in enumerate(data.motions.items[k].text_pooled)
                       if np.array_equal(pooled.astype(np.float32), item["text"].numpy()))
        words = data.motions.items[k].text_tokens[caption]
        n = int(item["token_mask"].sum())
        assert n == len(words) and item["token_mask"][:n].all() and item["tokens"].shape == (32, 384)
        np.testing.assert_array_equal(item["tokens"][:n].numpy(), words.astype(np.float32))
        assert not item["tokens"][n:].any()
    batch = train_mld.collate_words(items)
    longest = max(int(item["token_mask"].sum()) for item in items)
    assert batch["tokens"].shape == (8, longest, 384) and batch["token_mask"].shape == (8, longest)
    for k, item in enumerate(items):  # trimming removed padding only
        torch.testing.assert_close(batch["tokens"][k], item["tokens"][:longest], atol=0, rtol=0)
        assert torch.equal(batch["token_mask"][k], item["token_mask"][:longest])


def test_mld_generator_is_seeded_and_zero_padded(trained):
    artifacts = Path(trained["paths"]["artifacts"])
    denoiser, schedule, _ = train_mld.load_mld(artifacts / "train_mld")
    gen = MLDGenerator("MLD-DDIM4", denoiser, train_vae.load_vae(artifacts / "train_vae"), schedule, 4, 7.5)
    assert isinstance(gen, Generator) and gen.nfe == 8
    rng = np.random.default_rng(0)
    pooled = rng.standard_normal((3, 384)).astype(np.float32)
    words = [rng.standard_normal((n, 384)).astype(np.float16) for n in (5, 3, 7)]
    text = TextBatch(["a", "b", "c"], pooled / np.linalg.norm(pooled, axis=1, keepdims=True), words)
    lengths = np.array([40, 24, 32])
    a, b, c = gen.sample(text, lengths, 1), gen.sample(text, lengths, 1), gen.sample(text, lengths, 2)
    assert a.shape == (3, 40, 263) and np.isfinite(a).all()
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)
    reordered = TextBatch(text.texts, text.pooled, [words[0][::-1], words[1], words[2]])
    d = gen.sample(reordered, lengths, 1)  # the denoiser sees word order (word_tokens)
    assert not np.allclose(a[0], d[0]) and np.allclose(a[1:], d[1:], atol=1e-5)
    assert not a[1, 24:].any() and not a[2, 32:].any() and np.abs(a[1, :24]).sum() > 0


def test_evaluate_reports_every_row(trained):
    table = evaluate.run(trained)
    assert {"Real", "Random", "Retrieval", "VAE", "MLD-DDIM50", "MLD-DDIM1", "MLD-DDIM2", "MLD-DDIM4"} <= set(table)
    assert table["VAE"]["MPJPE_mm"] > 0 and "MPJPE_mm" not in table["Real"]
    assert table["MLD-DDIM50"]["NFE"] == 100 and table["MLD-DDIM50"]["AITS_s"] > table["MLD-DDIM1"]["AITS_s"]
    assert "MultiModality" in table["MLD-DDIM4"]
    out = trained["paths"]["artifacts"] + "/eval"
    assert json.loads(open(f"{out}/metrics.json").read()) == table
    assert "| MLD-DDIM50 |" in open(f"{out}/report.md").read()
    assert (Path(out) / "samples" / "MLD-DDIM50_0.gif").stat().st_size > 1000


def test_generate_command_writes_joints_and_animation(trained, tmp_path):
    [npy] = generate.generate(trained, "mld", ["a person kicks"], [44], tmp_path / "kick.npy", seed=3)
    joints = np.load(npy)
    assert joints.shape == (44, 22, 3) and np.isfinite(joints).all()
    gifs = generate.generate(trained, "mld", ["a person runs", "a person waves"], [40, 40], tmp_path / "m.gif",
                             steps=2)
    assert [p.name for p in gifs] == ["m_0.gif", "m_1.gif"] and all(p.stat().st_size > 1000 for p in gifs)
    with pytest.raises(ValueError, match="unknown model"):
        generate.generate(trained, "nope", ["x"], [40], tmp_path / "x.npy")
