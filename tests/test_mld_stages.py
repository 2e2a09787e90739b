"""The MLD family end to end on a tiny store: evaluator, VAE and MLD through Ray, then the
per-family evaluation stages and the report.

Model sizes and step counts are minimal: this checks the stages' wiring, artefacts and the
generator interface (values, determinism, padding), not model quality.
"""

import copy
import json
from functools import partial
from pathlib import Path

import numpy as np
import pytest
import torch
from standin_device import STANDIN, StandIn, syncs_of

from data.trajectories import make_trajectory
from models.generator import Generator, TextBatch
from pipelines import registry
from pipelines.action_evaluation import load_recogniser
from pipelines.checkpoint import load_final_model
from pipelines.evaluation import load_evaluator
from pipelines.latent_cache import collate_words, latent_dataset
from pipelines.mld_family import MLDGenerator, load_mld, load_vae
from pipelines.registry import FAMILIES, EvalContext
from pipelines.runner import run_training
from pipelines.stage import loop_config, train
from stages import (
    distill_lcm,
    evaluate,
    generate,
    report,
    speed,
    train_controlnet,
    train_emdm,
    train_emdm_action,
    train_evaluator,
    train_mld,
    train_motiondiffuse,
    train_vae,
)

pytestmark = pytest.mark.slow

TINY_NET = {"layers": 1, "heads": 2, "ff_dim": 32}


@pytest.fixture(scope="module")
def trained(small_store, ray_cluster):
    params = copy.deepcopy(small_store)
    params["ray"].update(num_workers=1, checkpoint_every=3, max_failures=0)
    params["train_evaluator"]["profile"] = "smoke"
    params["train_evaluator"]["movement_loop"].update(max_steps=4, batch_size=16)
    params["train_evaluator"]["loop"].update(max_steps=6, batch_size=16)
    for stage in ("train_vae", "train_mld"):
        params[stage]["loop"].update(max_steps=6, batch_size=8, log_every=3, warmup_steps=0)
        params[stage]["crop_frames"] = 64
    params["train_vae"]["model"].update(latent_dim=16, **TINY_NET)
    params["train_mld"]["model"].update(time_freq_dim=16, **TINY_NET)
    params["distill_lcm"]["loop"].update(max_steps=6, batch_size=8, log_every=3, warmup_steps=0)
    params["train_controlnet"]["loop"].update(max_steps=6, batch_size=8, log_every=3, warmup_steps=0)
    params["train_controlnet"]["encoder"].update(dim=16, **TINY_NET)
    params["sample"]["control_refine_steps"] = 2
    for stage in ("train_emdm", "train_emdm_action", "train_motiondiffuse"):
        params[stage]["loop"].update(max_steps=4, batch_size=8, log_every=2)
        params[stage]["crop_frames"] = 64
    for stage in ("train_emdm", "train_emdm_action"):
        params[stage]["model"].update(width=16, heads=2, ff_dim=32, d_width=16, d_heads=2, d_ff_dim=32, layers=1)
    params["train_motiondiffuse"]["model"].update(width=16, heads=2, ff_dim=32, text_heads=2, text_ff_dim=32,
                                                  layers=1)
    params["train_motiondiffuse"]["num_train_timesteps"] = 50
    params["evaluate"].update(replications=1, diversity_times=10, mm_texts=4, mm_repeats=11, timing_sentences=2)
    params["evaluate"]["samples"].update(prompts=["a person walks forward"], length=40)
    in_process = copy.deepcopy(params)
    in_process["ray"]["num_workers"] = 0
    train_evaluator.run(in_process)
    train(train_vae.STAGE, params)
    train(train_mld.STAGE, params)
    return params


def test_vae_and_mld_write_resumable_models(trained):
    """Both ran under Ray Train with checkpoints in storage; run again unchanged they resume at the
    last checkpoint (train no step) and write the same weights."""
    artifacts = Path(trained["paths"]["artifacts"])
    for stage in (train_vae.STAGE, train_mld.STAGE):
        metrics = json.loads((artifacts / stage.name / "metrics.json").read_text())
        assert metrics["step"] == 6 and np.isfinite(metrics["loss"])
        run = json.loads((artifacts / stage.name / "run.json").read_text())
        assert Path(run["run_path"]).parent == Path(trained["paths"]["ray_storage"]).resolve()
        assert any(Path(run["run_path"]).glob("checkpoint_*"))
        before = load_final_model(artifacts / stage.name)["models"]
        again = train(stage, trained)
        assert again.run_name == run["run_name"] and again.attempts == [0, 6]
        after = load_final_model(artifacts / stage.name)["models"]
        assert all(np.array_equal(before[m][k].numpy(), after[m][k].numpy()) for m in before for k in before[m])
    denoiser, schedule, config = load_mld(artifacts / "train_mld")
    assert config["model"]["latent_dim"] == 16 and config["model"]["latent_scale"] > 0
    assert schedule.num_steps == 1000


def test_vae_dataset_lengths_are_the_served_lengths(trained):
    """``lengths`` (what the VAE's length-bucketed batch order sorts by) match what items serve."""
    data = train_vae.dataset(loop_config(train_vae.STAGE, trained))
    assert trained["train_vae"]["loop"]["length_buckets"] > 0
    served = [int(data[k]["length"]) for k in range(len(data))]
    assert data.lengths.tolist() == served
    assert data.lengths.tolist() == [min(item.length, 64) for item in data.items]
    assert any(item.length > 64 for item in data.items)  # long items are served cropped to crop_frames


def test_latent_cache_is_each_items_own_posterior(trained):
    """The cached (mu, logvar) of an item equal encoding it alone, unpadded; captions are the item's own."""
    import torch

    config = loop_config(train_mld.STAGE, trained)
    assert config["model"]["latent_scale"] > 0
    data = latent_dataset(config)
    vae = load_vae(Path(config["vae_dir"]))
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

    config = loop_config(train_mld.STAGE, trained)
    assert config["model"]["word_tokens"] != "none" and config["model"]["token_dim"] == 384
    data = latent_dataset(config)
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
    batch = collate_words(items)
    longest = max(int(item["token_mask"].sum()) for item in items)
    assert batch["tokens"].shape == (8, longest, 384) and batch["token_mask"].shape == (8, longest)
    for k, item in enumerate(items):  # trimming removed padding only
        torch.testing.assert_close(batch["tokens"][k], item["tokens"][:longest], atol=0, rtol=0)
        assert torch.equal(batch["token_mask"][k], item["token_mask"][:longest])


def test_mld_generator_is_seeded_and_zero_padded(trained):
    artifacts = Path(trained["paths"]["artifacts"])
    denoiser, schedule, _ = load_mld(artifacts / "train_mld")
    gen = MLDGenerator("MLD-DDIM4", denoiser, load_vae(artifacts / "train_vae"), schedule, 4, 7.5)
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


def train_every_family(trained: dict) -> None:
    """The stages after the fixture's MLD (each resumes at its last step when it has trained already)."""
    train(distill_lcm.STAGE, trained)
    train(train_controlnet.STAGE, trained)
    in_process = copy.deepcopy(trained) | {"ray": trained["ray"] | {"num_workers": 0}}
    for stage in (train_emdm.STAGE, train_emdm_action.STAGE, train_motiondiffuse.STAGE):
        train(stage, in_process)


def test_evaluation_stages_and_report(trained):
    """Each family's stage writes its rows; the report merges them in registry order after Real."""
    train_every_family(trained)
    rows = {name: evaluate.run(name, trained) for name in ("real", *FAMILIES)}
    assert list(rows["real"]) == ["Real"] and list(rows["baselines"]) == ["Random", "Retrieval"]
    # the names preflight checks evaluate.paraphrase_rows, samples.rows and speed.rows against, from params alone
    assert {name: FAMILIES[name].text_row_names(trained) for name in FAMILIES} == {
        name: [] if name in ("vae", "emdm-action") else list(rows[name]) for name in FAMILIES}
    assert list(rows["vae"]) == ["VAE"] and list(rows["mld"]) == ["MLD-DDIM50", "MLD-DDIM1", "MLD-DDIM2", "MLD-DDIM4"]
    assert list(rows["motionlcm"]) == ["MotionLCM-1", "MotionLCM-2", "MotionLCM-4"]
    assert list(rows["motionlcm-control"]) == ["MotionLCM-Control", "MotionLCM-Control-5f", "MotionLCM-Control+refine",
                                               "MotionLCM-1-uncontrolled"]
    for row in rows["motionlcm-control"].values():
        assert 0 <= row["loc_err_20cm"] <= row["traj_err_20cm"] <= 1 and row["avg_err_m"] > 0
        assert row["loc_err_50cm"] <= row["loc_err_20cm"]
    control = rows["motionlcm-control"]  # the projection leaves only the pelvis height's error
    assert control["MotionLCM-Control+refine"]["avg_err_m"] < 0.5 * control["MotionLCM-Control"]["avg_err_m"]
    # the uncontrolled reference answers the same captions with the same seeds as MotionLCM-1
    assert rows["motionlcm-control"]["MotionLCM-1-uncontrolled"]["FID"] == rows["motionlcm"]["MotionLCM-1"]["FID"]
    assert list(rows["emdm"]) == ["EMDM-10"] and list(rows["emdm-action"]) == ["Real-action", "EMDM-action"]
    assert list(rows["motiondiffuse"]) == ["MotionDiffuse-50", "MotionDiffuse-DDIM10"]
    assert rows["emdm-action"]["Real-action"]["Accuracy"] > 0 and "Accuracy" not in rows["emdm"]["EMDM-10"]
    timed = speed.run(trained | {"speed": {"rows": ["EMDM-10", "MotionDiffuse-50"], "rounds": 1}})
    # both guide (sample.emdm_guidance, sample.motiondiffuse_guidance): two passes per step
    assert list(timed) == ["EMDM-10", "MotionDiffuse-50"] and [t["NFE"] for t in timed.values()] == [20, 100]
    assert sorted(t["speedup"] for t in timed.values())[0] == 1.0 and all(t["params_M"] > 0 for t in timed.values())
    with pytest.raises(ValueError, match="speed.rows: no generator row"):
        speed.run(trained | {"speed": {"rows": ["EMDM-10", "MotionDiffuse-1000"], "rounds": 1}})
    table = report.run(trained)
    assert list(table) == [row for name in ("real", *FAMILIES) for row in rows[name]]
    assert table["VAE"]["MPJPE_mm"] > 0 and "MPJPE_mm" not in table["Real"]
    assert table["VAE"]["path_err_m"] > 0 and "turn_refs" in table["VAE"] and "path_err_m" not in table["MLD-DDIM50"]
    assert 0 <= table["VAE"]["action_accuracy"] <= 1 and "action_accuracy" in table["Real"]  # the same labelled items
    assert [table[f"MLD-DDIM{n}"]["NFE"] for n in (50, 1, 2, 4)] == [100, 2, 4, 8]
    assert "MultiModality" in table["MLD-DDIM4"] and "MultiModality" not in table["Retrieval"]
    out = Path(trained["paths"]["artifacts"]) / "eval"
    assert json.loads((out / "metrics.json").read_text()) == table
    assert "| MLD-DDIM50 |" in (out / "report.md").read_text()
    assert "## Trajectory control" in (out / "report.md").read_text()
    assert "## Reconstruction detail" in (out / "report.md").read_text()
    assert "## Action-to-motion" in (out / "report.md").read_text()
    assert "| MotionDiffuse-50 |" in (out / "report.md").read_text().split("## Inference speed side by side")[1]
    assert (out / "samples" / "MLD-DDIM50_0.gif").stat().st_size > 1000
    # a family evaluated again alone gives the same values: its rows do not depend on the others
    again = evaluate.run("baselines", trained)
    assert again["Retrieval"]["R_precision_top3"] == rows["baselines"]["Retrieval"]["R_precision_top3"]
    assert again["Random"]["Diversity"] == rows["baselines"]["Random"]["Diversity"]


def row_networks(row: object) -> list[torch.nn.Module]:
    """The networks an evaluation row holds, also through the rows it wraps."""
    found = []
    for value in vars(row).values():
        if isinstance(value, torch.nn.Module):
            found.append(value)
        elif hasattr(value, "__dict__") and not isinstance(value, type):
            found += row_networks(value)
    return found


def untimed(table: dict[str, dict[str, float]]) -> dict[str, dict[str, float]]:
    """A table without its timing columns (AITS and ms/frame, with their intervals)."""
    return {row: {k: v for k, v in m.items() if not k.startswith(("AITS_s", "ms_per_frame"))}
            for row, m in table.items()}


def test_every_family_evaluates_on_a_gpu_as_on_the_cpu(trained, monkeypatch, tmp_path):
    """``sample.device``: every evaluation stage, run with its networks (the rows', the evaluator's and the
    recogniser's) on a stand-in GPU (tests/standin_device.py: CUDA's rules on mixing devices, the CPU's
    arithmetic), writes the CPU's table, timing aside; and so do ``eval_speed`` and ``generate``. The
    stand-in may take another CPU kernel for a tensor subclass, so values are compared to 1e-5."""
    train_every_family(trained)
    artifacts = Path(trained["paths"]["artifacts"])
    local = copy.deepcopy(trained)  # the trained models, in a folder of its own: the module's eval/ stays the CPU's
    local["paths"]["artifacts"] = str(tmp_path / "artifacts")
    (tmp_path / "artifacts").mkdir()
    for folder in artifacts.iterdir():
        if folder.name.startswith("train_") or folder.name == "distill_lcm":
            (tmp_path / "artifacts" / folder.name).symlink_to(folder)
    names = ("real", *FAMILIES)
    on_cpu = {name: evaluate.run(name, local) for name in names}
    speed_params = local | {"speed": {"rows": ["EMDM-10", "MotionDiffuse-50"], "rounds": 1}}
    timed_on_cpu = speed.run(speed_params)
    out = tmp_path / "generated"
    parts = [("upper", "a person waves"), ("lower", "a person walks forward")]
    [walk_on_cpu] = generate.generate(local, "motionlcm-control", ["a person walks"], [40], out / "walk_cpu.npy",
                                      trajectory="line", refine=True)
    [parts_on_cpu] = generate.generate(local, "motiondiffuse", [], [40], out / "parts_cpu.npy", parts=parts)
    monkeypatch.setattr(registry, "sampling_device", lambda spec: STANDIN)  # sample.device, as every stage reads it
    with StandIn():
        on_gpu = {name: evaluate.run(name, local) for name in names}
        timed_on_gpu = speed.run(speed_params)
        [walk_on_gpu] = generate.generate(local, "motionlcm-control", ["a person walks"], [40],
                                          out / "walk_gpu.npy", trajectory="line", refine=True)
        [parts_on_gpu] = generate.generate(local, "motiondiffuse", [], [40], out / "parts_gpu.npy", parts=parts)
    for name, table in on_cpu.items():
        assert list(on_gpu[name]) == list(table)
        for row, metrics in untimed(table).items():
            assert untimed(on_gpu[name])[row] == pytest.approx(metrics, rel=1e-5, abs=1e-6), (name, row)
    # protocol.json names the device (the stand-in is torch's meta device): the report does not mix the two
    assert json.loads((tmp_path / "artifacts" / "eval" / "mld" / "protocol.json").read_text())["device"] == "meta"
    with StandIn():  # ... because every network was on the device (CPU networks would give the same numbers)
        ctx = EvalContext(trained, artifacts, Path(trained["features"]["out"]), STANDIN)
        networks = [module for name in FAMILIES for row in FAMILIES[name].build_rows(ctx)
                    for module in row_networks(row)]
        networks += [load_evaluator(artifacts / "train_evaluator", STANDIN).evaluator,
                     load_recogniser(artifacts / evaluate.RECOGNISER, STANDIN)]
        assert len(networks) >= 10 and {p.device for m in networks for p in [*m.parameters(), *m.buffers()]} == {
            STANDIN}
    assert [t["NFE"] for t in timed_on_gpu.values()] == [t["NFE"] for t in timed_on_cpu.values()]
    np.testing.assert_allclose(np.load(walk_on_gpu), np.load(walk_on_cpu), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.load(parts_on_gpu), np.load(parts_on_cpu), rtol=1e-5, atol=1e-6)
    def sample(family: str, steps: int) -> None:
        generate.generate(local, family, ["a person walks"], [40], out / f"{family}{steps}.npy", steps=steps)

    for family in ("mld", "motiondiffuse"):  # no row makes the host wait for the device at every step
        assert syncs_of(partial(sample, family, 2)) == syncs_of(partial(sample, family, 4)), family
    with StandIn():  # the stand-in refuses what CUDA refuses: a latent left on the CPU
        vae = load_vae(artifacts / "train_vae", STANDIN)
        with pytest.raises(RuntimeError, match="stand-in device met a CPU tensor"):
            vae.decode(torch.zeros(1, vae.config.latent_tokens, vae.config.latent_dim), [8])


def test_generate_command_writes_joints_and_animation(trained, tmp_path):
    [npy] = generate.generate(trained, "mld", ["a person kicks"], [44], tmp_path / "kick.npy", seed=3)
    joints = np.load(npy)
    assert joints.shape == (44, 22, 3) and np.isfinite(joints).all()
    gifs = generate.generate(trained, "mld", ["a person runs", "a person waves"], [40, 40], tmp_path / "m", steps=2)
    assert [p.name for p in gifs] == ["00_a_person_runs.gif", "01_a_person_waves.gif"]
    assert all(p.stat().st_size > 1000 for p in gifs)
    # prompt k samples on its own with seed + k: the kick of the pair is the kick alone with seed 4
    _, kick = generate.generate(trained, "mld", ["a person runs", "a person kicks"], [40, 44], tmp_path / "pair",
                                seed=3, fmt="npy")
    [alone] = generate.generate(trained, "mld", ["a person kicks"], [44], tmp_path / "alone.npy", seed=4)
    np.testing.assert_array_equal(np.load(kick), np.load(alone))
    assert not np.array_equal(np.load(alone), joints)  # seed 3 and seed 4 differ
    with pytest.raises(ValueError, match="unknown model family 'nope'"):
        generate.generate(trained, "nope", ["x"], [40], tmp_path / "x.npy")


def test_distill_lcm_trains_resumes_exactly_and_samples(trained, tmp_path):
    """MotionLCM through the runner: a 3-step run resumed to 6 steps equals 6 steps straight
    (constant LR, so the schedule does not depend on max_steps); then its rows and the CLI."""
    params = copy.deepcopy(trained)
    params["distill_lcm"]["loop"].update(batch_size=8, log_every=3, warmup_steps=0, lr_schedule="constant",
                                         min_lr_ratio=0.0)
    config = loop_config(distill_lcm.STAGE, params)
    assert config["model"]["time_cond_dim"] == 256 and config["teacher_dir"].endswith("train_mld")
    storage = str(tmp_path / "ray")
    straight = run_training("lcm", distill_lcm.STAGE.spec, config | {"max_steps": 6}, params["ray"],
                            tmp_path / "straight", storage)
    run_training("lcm", distill_lcm.STAGE.spec, config | {"max_steps": 3}, params["ray"], tmp_path / "part", storage,
                 run_name="lcm-resumed")
    resumed = run_training("lcm", distill_lcm.STAGE.spec, config | {"max_steps": 6}, params["ray"],
                           tmp_path / "resumed", storage, run_name="lcm-resumed")
    assert straight.attempts == [0] and resumed.attempts == [0, 3]
    a, b = load_final_model(tmp_path / "straight"), load_final_model(tmp_path / "resumed")
    for part in ("models", "ema"):
        for key, value in a[part]["student"].items():
            assert np.array_equal(value.numpy(), b[part]["student"][key].numpy()), (part, key)
    train(distill_lcm.STAGE, params)
    if not (Path(params["paths"]["artifacts"]) / "eval" / "real").exists():  # when run alone
        evaluate.run("real", params)
    rows = evaluate.run("motionlcm", params)
    assert list(rows) == ["MotionLCM-1", "MotionLCM-2", "MotionLCM-4"]
    assert [rows[f"MotionLCM-{n}"]["NFE"] for n in (1, 2, 4)] == [1, 2, 4]
    [npy] = generate.generate(params, "motionlcm", ["a person kicks"], [44], tmp_path / "kick.npy", seed=3)
    assert np.load(npy).shape == (44, 22, 3)
    with pytest.raises(ValueError, match="MotionLCM samples with"):
        generate.generate(params, "motionlcm", ["x"], [40], tmp_path / "x.npy", steps=3)


def test_distill_lcm_sweep_ranks_trials_by_a_validation_metric(trained):
    """Two trials of distill_lcm (fixed w vs a w range), each scored after training on the val split."""
    from pipelines.sweep import run_sweep

    params = copy.deepcopy(trained)
    params["evaluate"]["group_size"] = 4  # the fixture's val split is small
    params["distill_lcm"]["loop"].update(max_steps=2, batch_size=8, log_every=1, warmup_steps=0)
    params["sweep"]["settings"].update(num_samples=1, metric="val_FID", mode="min", scheduler="fifo",
                                       report_every=2, max_concurrent_trials=1)
    params["sweep"]["distill_lcm"] = {"w_range": "grid([[1.0, 3.0], [2.0, 2.0]])"}
    result = run_sweep(distill_lcm.sweep_target(params), params, Path(params["paths"]["artifacts"]).parent)
    assert [row["status"] for row in result.table] == ["completed", "completed"]
    scores = [row["val_FID"] for row in result.table]
    assert all(np.isfinite(scores)) and result.best["val_FID"] == min(scores)
    assert result.best["w_range"] in ([1.0, 3.0], [2.0, 2.0])


def test_train_controlnet_resumes_exactly_and_follows_the_cli_trajectory(trained, tmp_path):
    """The ControlNet through the runner: 3 steps resumed to 6 equal 6 straight; then the trajectory CLI."""
    params = copy.deepcopy(trained)
    if not (Path(params["paths"]["artifacts"]) / "distill_lcm" / "model.pt").exists():  # when run alone
        train(distill_lcm.STAGE, params)
    params["train_controlnet"]["loop"].update(lr_schedule="constant", min_lr_ratio=0.0)
    config = loop_config(train_controlnet.STAGE, params)
    assert config["student_dir"].endswith("distill_lcm") and len(config["control"]["hint_mean"]) == 66
    storage = str(tmp_path / "ray")
    straight = run_training("cn", train_controlnet.STAGE.spec, config | {"max_steps": 6}, params["ray"],
                            tmp_path / "straight", storage)
    run_training("cn", train_controlnet.STAGE.spec, config | {"max_steps": 3}, params["ray"], tmp_path / "part",
                 storage, run_name="cn-resumed")
    resumed = run_training("cn", train_controlnet.STAGE.spec, config | {"max_steps": 6}, params["ray"],
                           tmp_path / "resumed", storage, run_name="cn-resumed")
    assert straight.attempts == [0] and resumed.attempts == [0, 3]
    a, b = load_final_model(tmp_path / "straight"), load_final_model(tmp_path / "resumed")
    assert a["models"]["controlnet"].keys() == b["models"]["controlnet"].keys()
    for key, value in a["models"]["controlnet"].items():
        assert np.array_equal(value.numpy(), b["models"]["controlnet"][key].numpy()), key
    train(train_controlnet.STAGE, params)
    [npy] = generate.generate(params, "motionlcm-control", ["a person walks"], [40], tmp_path / "c.npy",
                              trajectory="line", size=1.0)
    assert np.load(npy).shape == (40, 22, 3)
    [gif] = generate.generate(params, "motionlcm-control", ["a person walks"], [40], tmp_path / "c.gif",
                              trajectory="circle", refine=True)
    assert gif.stat().st_size > 1000
    # --refine ends in the root projection: the pelvis follows the circle horizontally on every frame
    [npy] = generate.generate(params, "motionlcm-control", ["a person walks"], [40], tmp_path / "r.npy",
                              trajectory="circle", refine=True)
    circle = make_trajectory("circle", 40)
    np.testing.assert_allclose(np.load(npy)[:, 0, [0, 2]], circle[:, [0, 2]], atol=1e-3)
    # a shape spans each prompt's own length: the 40-frame line and the 48-frame line both end 1 m ahead
    paths = generate.generate(params, "motionlcm-control", ["a person walks", "a person walks"], [40, 48],
                              tmp_path / "lines", trajectory="line", size=1.0, refine=True, fmt="npy")
    for path, frames in zip(paths, (40, 48), strict=True):
        line = make_trajectory("line", frames, size=1.0)
        np.testing.assert_allclose(np.load(path)[:, 0, [0, 2]], line[:, [0, 2]], atol=1e-3)
    path = tmp_path / "path.npy"
    np.save(path, np.zeros((30, 3), np.float32))
    with pytest.raises(ValueError, match="length mismatch"):
        generate.generate(params, "motionlcm-control", ["x"], [40], tmp_path / "x.npy", trajectory=str(path))
    with pytest.raises(ValueError, match="pass --trajectory"):
        generate.generate(params, "motionlcm-control", ["x"], [40], tmp_path / "x.npy")
    with pytest.raises(ValueError, match="need a controlled model"):
        generate.generate(params, "motionlcm", ["x"], [40], tmp_path / "x.npy", trajectory="line")
