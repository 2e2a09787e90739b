"""EMDM's training stage and evaluation rows on a tiny store: params checks, one GAN step, a Ray Train
run resumed exactly (both models, both optimisers, the EMA), the stage's outputs and the row generator.

Model sizes and step counts are minimal: this checks wiring, exact resume and the generator
interface (values, determinism, padding), not model quality.
"""

from __future__ import annotations

import copy
import json
import re
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import torch
from state_checks import assert_same, final_state

from models.emdm import EMDMConfig, EMDMGenerator
from models.generator import Generator, TextBatch
from pipelines import checkpoint as ckpt
from pipelines import emdm_training
from pipelines.action_evaluation import ActionGenerator
from pipelines.emdm_family import (
    EMDMActionPrompts,
    EMDMActionRow,
    EMDMGeneratorRow,
    emdm_action_generator,
    emdm_action_rows,
    emdm_generator,
    emdm_rows,
    load_emdm,
)
from pipelines.feature_store import FeatureStore
from pipelines.length_batches import batch_seed
from pipelines.recogniser import action_classes, labelled_items
from pipelines.registry import EvalContext, GenerateOptions
from pipelines.runner import StepContext, run_training
from pipelines.stage import loop_config, train
from stages import train_emdm

pytestmark = pytest.mark.usefixtures("one_thread")  # tiny networks (tests/conftest.py)

FIXTURES = Path(__file__).parent / "fixtures" / "humanml3d"
TINY_MODEL = {"width": 16, "layers": 1, "heads": 2, "ff_dim": 32, "dropout": 0.0, "activation": "selu",
              "norm_first": False, "z_dim": 4, "mapping_layers": 2, "d_width": 16, "d_layers": 1, "d_heads": 2,
              "d_ff_dim": 16, "d_time_dim": 8, "patch_frames": 1, "overlap_out": False,
              "d_condition": True, "input_skip": False, "skip_kernel": 1, "word_tokens": False,
              "text_norm": False}
LOOP = {"seed": 0, "batch_size": 8, "max_steps": 6, "grad_clip": 1.0, "lr_schedule": "constant", "warmup_steps": 0,
        "min_lr_ratio": 0.0, "log_every": 3, "num_data_workers": 0, "length_buckets": 0}


def test_class_captions_are_all_pooled_embeddings_and_the_words_of_the_one_nearest_their_mean() -> None:
    first = SimpleNamespace(text_pooled=np.array([[1.0, 0.0], [0.8, 0.6]], np.float16),
                            text_tokens=[np.full((2, 3), 1.0), np.full((4, 3), 2.0)])
    second = SimpleNamespace(text_pooled=np.array([[0.0, 1.0]], np.float16), text_tokens=[np.full((1, 3), 3.0)])
    pooled, words = emdm_training.class_captions([first, second])  # mean (0.6, 0.53): dots 0.6, 0.8, 0.53
    assert pooled.dtype == words.dtype == torch.float32
    torch.testing.assert_close(pooled, torch.tensor([[1.0, 0.0], [0.8, 0.6], [0.0, 1.0]]), rtol=1e-3, atol=1e-3)
    assert torch.equal(words, torch.full((4, 3), 2.0))
    _, words = emdm_training.class_captions([second, first])  # order does not change the choice
    assert torch.equal(words, torch.full((4, 3), 2.0))


def emdm_section(**overrides: Any) -> dict[str, Any]:
    """A tiny ``train_emdm`` params section (R1 every 2 steps, so short runs regularise)."""
    section = {"condition": "text", "num_steps": 10, "lr_g": 2e-4, "lr_d": 1e-3, "ema_decay": 0.9,
               "geometric_weight": None, "geometric_lambda": 1.0, "foot_lambda": None, "r1_gamma": 0.02,
               "r1_interval": 2, "p_uncond": 0.1, "crop_frames": 64, "model": dict(TINY_MODEL), "loop": dict(LOOP)}
    if overrides.get("condition") == "action":
        section["init_from"] = None
    return section | overrides


@pytest.fixture(scope="module")
def params(small_store) -> dict[str, Any]:
    params = copy.deepcopy(small_store)
    # the runner serves word tokens; G writes overlapping patches of 2 frames, as the pipeline's of 4
    params["train_emdm"] = emdm_section(model=TINY_MODEL | {"word_tokens": True, "patch_frames": 2,
                                                           "overlap_out": True})
    params["sample"]["emdm_guidance"] = 2.5
    params["ray"].update(num_workers=1, cpus_per_worker=1, checkpoint_every=3, max_failures=0)
    return params


# --------------------------------------------------------------------------------------------------
# Params (no store needed: the section is checked before the store is opened)
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("change", "key"), [
    ({"condition": "audio"}, "train_emdm.condition"),
    ({"lr_d": 0.0}, "train_emdm.lr_d"),
    ({"r1_interval": 1.5}, "train_emdm.r1_interval"),
    ({"p_uncond": 1.5}, "train_emdm.p_uncond"),
    ({"geometric_weight": "big"}, "train_emdm.geometric_weight"),
    ({"foot_lambda": -1.0}, "train_emdm.foot_lambda"),
    ({"ema_decay": True}, "train_emdm.ema_decay"),
    ({"model": TINY_MODEL | {"depth": 3}}, "train_emdm.model"),
    ({"model": {k: v for k, v in TINY_MODEL.items() if k != "z_dim"}}, "train_emdm.model"),
    ({"lr": 1e-4}, "train_emdm: unknown key"),
    ({"init_from": "train_emdm"}, "train_emdm: unknown key(s) ['init_from']"),  # text starts from scratch
    ({"condition": "action", "init_from": 3}, "train_emdm.init_from: expected the name of a text EMDM stage"),
])
def test_bad_params_name_the_key(change: dict[str, Any], key: str, tmp_path: Path) -> None:
    params = {"train_emdm": emdm_section(**change), "features": {"out": str(tmp_path / "no_store")},
              "paths": {"artifacts": str(tmp_path), "ray_storage": str(tmp_path)}, "ray": {}}
    with pytest.raises(ValueError, match=re.escape(key)):
        loop_config(train_emdm.STAGE, params)


def test_a_good_section_reaches_the_store(tmp_path: Path) -> None:
    params = {"train_emdm": emdm_section(), "features": {"out": str(tmp_path / "no_store")}, "ray": {}}
    with pytest.raises(FileNotFoundError, match="no feature store"):
        emdm_training.stage_config(params)


# --------------------------------------------------------------------------------------------------
# One GAN step (no runner)
# --------------------------------------------------------------------------------------------------


def _batch() -> dict[str, torch.Tensor]:
    feats = np.load(FIXTURES / "new_joint_vecs_012314.npy")
    mean, std = np.load(FIXTURES / "Mean.npy"), np.load(FIXTURES / "Std.npy")
    x = torch.tensor((np.stack([feats[0:16], feats[30:46], feats[60:76]]) - mean) / std, dtype=torch.float32)
    lengths = torch.tensor([16, 12, 9])
    x = torch.where(torch.arange(16)[None, :, None] < lengths[:, None, None], x, 0.0)
    text = torch.nn.functional.normalize(torch.randn(3, 8, generator=torch.Generator().manual_seed(0)), dim=1)
    return {"motion": x, "length": lengths, "text": text}


def test_one_gan_step_updates_both_networks_and_r1_only_when_due() -> None:
    torch.manual_seed(0)
    mean, std = np.load(FIXTURES / "Mean.npy"), np.load(FIXTURES / "Std.npy")
    section = emdm_section(r1_interval=3)
    config = {"mean": mean.tolist(), "std": std.tolist(), "lr_g": 1e-3, "lr_d": 1e-3, "ema_decay": 0.9,
              "model": emdm_training.model_config(section, 263, 8)}
    assert config["model"]["geo_weight"] is None and "guidance" not in config["model"]
    assert config["model"]["geo_foot_lambda"] is None  # null: the foot term takes geometric_lambda
    assert emdm_training.model_config(emdm_section(foot_lambda=3.0), 263, 8)["geo_foot_lambda"] == 3.0
    comps = emdm_training.build(config)
    assert set(comps.models) == {"generator", "discriminator"} and set(comps.optimizers) == {"g", "d"}
    assert all(opt.defaults["betas"] == (0.5, 0.9) for opt in comps.optimizers.values())
    assert comps.ema == {"generator": 0.9} and comps.frozen["schedule"].num_steps == 10
    ctx = StepContext(config, comps.models, comps.optimizers, {}, comps.frozen, torch.device("cpu"), 0, 1, 1.0)
    before = {name: {k: p.detach().clone() for k, p in m.named_parameters()} for name, m in comps.models.items()}
    batch = _batch()
    first = emdm_training.step(batch, ctx)  # step 0: R1 due
    assert {"loss", "g_adv", "geo", "recon", "pos", "vel", "foot", "d_loss", "d_real", "d_fake", "r1"} == set(first)
    assert all(torch.isfinite(v) and v.ndim == 0 and not v.requires_grad for v in first.values())
    assert first["r1"] > 0  # R = 100 for text: the total is the adversarial term plus 100 x the geometric one
    assert first["loss"] == pytest.approx(float(first["g_adv"] + 100 * first["geo"]), rel=1e-5)
    assert {"grad_norm/g", "grad_norm/d"} == set(ctx.extra_metrics)
    for name, model in comps.models.items():  # both optimisers stepped every tensor
        changed = [k for k, p in model.named_parameters() if not torch.equal(before[name][k], p.detach())]
        assert set(before[name]) - set(changed) <= {"null_cond"}, name  # null_cond: only if a caption was dropped
        assert all(p.requires_grad for p in model.parameters())  # D unfrozen again after the G update
    ctx.step = 1
    assert "r1" not in emdm_training.step(batch, ctx)
    ctx.step = 3
    assert emdm_training.step(batch, ctx)["r1"] > 0


def test_action_condition_trains_on_labels_with_r_one() -> None:
    torch.manual_seed(0)
    mean, std = np.load(FIXTURES / "Mean.npy"), np.load(FIXTURES / "Std.npy")
    section = emdm_section(condition="action")
    config = {"mean": mean.tolist(), "std": std.tolist(), "lr_g": 1e-3, "lr_d": 1e-3, "ema_decay": 0.0,
              "model": emdm_training.model_config(section, 263, 8, num_actions=3, section="train_emdm_action")}
    comps = emdm_training.build(config)
    assert comps.models["generator"].config.geometric_weight == 1.0
    ctx = StepContext(config, comps.models, comps.optimizers, {}, comps.frozen, torch.device("cpu"), 1, 1, 1.0)
    batch = {key: value for key, value in _batch().items() if key != "text"} | {"label": torch.tensor([0, 2, 1])}
    out = emdm_training.step(batch, ctx)
    torch.testing.assert_close(out["loss"], out["g_adv"] + out["geo"])  # R = 1
    with pytest.raises(ValueError, match=r"train_emdm_action\.model: condition='action' needs num_actions"):
        emdm_training.model_config(section, 263, 8, num_actions=0, section="train_emdm_action")
    odd = emdm_section(model=TINY_MODEL | {"patch_frames": 3, "overlap_out": True})
    with pytest.raises(ValueError, match=r"train_emdm\.model: overlap_out needs an even patch_frames, got 3"):
        emdm_training.model_config(odd, 263, 8)


def test_action_stage_reads_the_labelled_classes_of_the_store(params) -> None:
    section = emdm_section(condition="action", model=TINY_MODEL | {"word_tokens": True, "text_norm": True})
    action = copy.deepcopy(params) | {"train_emdm_action": section}
    config = emdm_training.stage_config(action, "train_emdm_action")
    assert config["model"]["word_tokens"] and config["model"]["text_norm"] is False  # G cross-attends to the label
    assert config["init_dir"] is None
    store = FeatureStore(config["features_dir"])
    assert config["classes"] == list(action_classes(store.split("train"))) and len(config["classes"]) >= 2
    assert config["model"]["num_actions"] == len(config["classes"])
    data = emdm_training.dataset(config)
    labelled = labelled_items(store.split("train"))
    assert len(data) == len(labelled) and set(data.labels.tolist()) <= set(range(len(config["classes"])))
    assert "classes" not in emdm_training.stage_config(params)  # text: no classes


def test_only_the_action_stage_is_skipped_without_two_action_labels(params, monkeypatch) -> None:
    action = copy.deepcopy(params) | {"train_emdm_action": emdm_section(condition="action")}
    action_stage = emdm_training.training_stage("train_emdm_action", __name__)
    assert action_stage.skip(action) is None  # the small store has labels
    monkeypatch.setattr(emdm_training, "missing_actions", lambda p: "no actions.txt")
    assert action_stage.skip(action) == "no actions.txt"
    assert emdm_training.training_stage("train_emdm", __name__).skip(params) is None  # text needs no labels


def test_action_row_samples_labels_deterministically() -> None:
    torch.manual_seed(0)
    model = EMDMConfig(**emdm_training.model_config(emdm_section(condition="action"), 263, 8, num_actions=3))
    row = EMDMActionRow("EMDM-action", EMDMGenerator(model), model.make_schedule(), 2.5, ["clap", "jump", "walk"])
    out = row.sample_actions(np.array([0, 2]), np.array([12, 7]), seed=4)
    assert out.shape == (2, 12, 263) and np.all(out[1, 7:] == 0) and np.abs(out[1, :7]).sum() > 0
    np.testing.assert_array_equal(out, row.sample_actions(np.array([0, 2]), np.array([12, 7]), seed=4))
    assert row.nfe == 20 and isinstance(row, ActionGenerator)
    with pytest.raises(ValueError, match="not on the 2 action classes"):
        EMDMActionRow("EMDM-action", EMDMGenerator(model), model.make_schedule(), 2.5, ["clap", "jump"])


def test_generate_s_action_prompts_are_labels_and_sample_as_the_row_does(tmp_path: Path) -> None:
    """``--model emdm-action``: each prompt's text names a class (trimmed, any case) and samples exactly what
    the action row samples for that class id; an unknown label's error lists the labels; a dataset without
    labels gives the stage's reason instead of a missing model."""
    torch.manual_seed(0)
    model = EMDMConfig(**emdm_training.model_config(emdm_section(condition="action"), 263, 8, num_actions=3))
    row = EMDMActionRow("EMDM-action", EMDMGenerator(model), model.make_schedule(), 2.5, ["clap", "jump", "walk"])
    prompts = EMDMActionPrompts(row)
    assert isinstance(prompts, Generator) and (prompts.name, prompts.nfe) == ("EMDM-action", 20)
    text = TextBatch([" Walk", "clap"], np.zeros((2, 8), np.float32), [np.zeros((1, 8), np.float32)] * 2)
    lengths = np.array([9, 12])
    np.testing.assert_array_equal(prompts.sample(text, lengths, 3), row.sample_actions(np.array([2, 0]), lengths, 3))
    unknown = TextBatch(["walk", "a person walks"], text.pooled, text.tokens)
    with pytest.raises(ValueError, match=r"'a person walks' is not an action label; the model knows clap, jump, walk"):
        prompts.sample(unknown, lengths, 3)

    (tmp_path / "train_emdm_action").mkdir()
    (tmp_path / "train_emdm_action" / ckpt.SKIPPED).write_text(json.dumps({"reason": "no actions.txt in the data"}))
    ctx = EvalContext({"sample": {"emdm_action_guidance": 2.5, "motion_batch": None}}, tmp_path, tmp_path)
    with pytest.raises(ValueError, match="train_emdm_action trained nothing: no actions.txt in the data"):
        emdm_action_generator(ctx, GenerateOptions())


def test_rows_in_length_batches_are_each_batch_sampled_alone() -> None:
    """``batch`` (both rows): sorted by length, ``batch`` rows at a time with the batch's seed; one batch that
    holds every row is the unbatched call bit for bit."""
    torch.manual_seed(0)
    text_model = EMDMConfig(**emdm_training.model_config(emdm_section(num_steps=3), 263, 8))
    action_model = EMDMConfig(**emdm_training.model_config(emdm_section(num_steps=3, condition="action"), 263, 8,
                                                             num_actions=3))
    text_gen, action_gen = EMDMGenerator(text_model), EMDMGenerator(action_model)
    pooled = np.random.default_rng(0).standard_normal((3, 8)).astype(np.float32)
    text = TextBatch(["a", "b", "c"], pooled, [np.zeros((2, 8), np.float32)] * 3)
    actions, lengths = np.array([2, 0, 1]), np.array([12, 7, 9])

    def text_row(batch: int | None):
        return EMDMGeneratorRow("EMDM", text_gen, text_model.make_schedule(), 2.5, batch).sample

    def action_row(batch: int | None):
        row = EMDMActionRow("EMDM-action", action_gen, action_model.make_schedule(), 2.5, ["a", "b", "c"], batch)
        return lambda labels, n, seed: row.sample_actions(labels, n, seed)

    for make, cond in ((text_row, text), (action_row, actions)):
        np.testing.assert_array_equal(make(3)(cond, lengths, 1), make(None)(cond, lengths, 1))
        out = make(1)(cond, lengths, 1)
        for rank, i in enumerate(np.argsort(lengths, kind="stable")):
            alone = make(None)(cond.select([i]) if isinstance(cond, TextBatch) else cond[[i]], lengths[[i]],
                               batch_seed(1, rank))[0]
            np.testing.assert_array_equal(out[i, : lengths[i]], alone)
            assert not out[i, lengths[i]:].any()


def test_the_sweep_hook_scores_the_trial_s_ema_generator(monkeypatch: pytest.MonkeyPatch) -> None:
    """``emdm_scores`` builds the trial's generator from its final state (EMA weights when kept), samples in
    the trained T steps with ``sample.emdm_guidance`` in batches of ``sample.motion_batch``, and returns what
    the validation protocol measures."""
    from pipelines import validation

    model = emdm_training.model_config(emdm_section(num_steps=5), 263, 8)
    torch.manual_seed(0)
    raw, ema = EMDMGenerator(EMDMConfig(**model)), EMDMGenerator(EMDMConfig(**model))
    seen = {}

    def fake_scores(params: dict[str, Any], row: Generator) -> dict[str, float]:
        seen["row"] = row
        return {"val_FID": 1.0, "val_R_precision_top3": 0.5}

    monkeypatch.setattr(validation, "generator_scores", fake_scores)
    sample = {"sample": {"emdm_guidance": 1.5, "motion_batch": 16}}
    state = {"models": {"generator": raw.state_dict()}, "ema": {"generator": {"module": ema.state_dict()}}}
    out = validation.emdm_scores(sample, {"model": model}, state)
    row = seen["row"]
    assert out == {"val_FID": 1.0, "val_R_precision_top3": 0.5}
    assert row.name == "EMDM-5" and row.guidance == 1.5 and row.nfe == 10 and row.batch == 16
    for name, value in row.generator.state_dict().items():
        assert torch.equal(value, ema.state_dict()[name]), name
    validation.emdm_scores(sample, {"model": model}, state | {"ema": {}})
    assert all(torch.equal(v, raw.state_dict()[k]) for k, v in seen["row"].generator.state_dict().items())


# --------------------------------------------------------------------------------------------------
# Through the runner
# --------------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_gan_step_through_ray_resumes_exactly(params, ray_cluster, tmp_path: Path) -> None:
    """3 steps resumed to 6 equal 6 straight: G, D, both Adam states, both schedulers, the EMA and the
    logged losses (R1 on steps 0, 2, 4 included)."""
    config = loop_config(train_emdm.STAGE, params)
    assert config["model"]["text_dim"] == 384 and config["model"]["r1_interval"] == 2
    assert config["model"]["word_tokens"] and config["max_text_tokens"] == 32
    storage = str(tmp_path / "ray")
    straight = run_training("emdm", train_emdm.STAGE.spec, config | {"max_steps": 6}, params["ray"],
                            tmp_path / "straight", storage)
    run_training("emdm", train_emdm.STAGE.spec, config | {"max_steps": 3}, params["ray"], tmp_path / "part", storage,
                 run_name="emdm-resumed")
    resumed = run_training("emdm", train_emdm.STAGE.spec, config | {"max_steps": 6}, params["ray"],
                           tmp_path / "resumed", storage, run_name="emdm-resumed")
    assert straight.attempts == [0] and resumed.attempts == [0, 3]
    a, b = final_state(straight.run_path), final_state(resumed.run_path)
    assert a["step"] == b["step"] == 6
    assert set(a["models"]) == {"generator", "discriminator"} and set(a["optimizers"]) == {"g", "d"}
    assert set(a["ema"]) == {"generator"} and set(a["schedulers"]) == {"g", "d"}
    for part in ("models", "optimizers", "schedulers", "ema"):
        assert_same(a[part], b[part], part)
    assert all(a["optimizers"][name]["state"] for name in ("g", "d"))
    assert not torch.equal(a["ema"]["generator"]["module"]["frame_out.weight"],
                           a["models"]["generator"]["frame_out.weight"])
    assert [row["step"] for row in straight.history] == [3, 6]
    for x, y in zip(straight.history, resumed.history, strict=True):
        for key in ("loss", "d_loss", "r1", "geo", "g_adv"):
            assert x[key] == y[key] and np.isfinite(x[key]), key
        assert x["r1"] > 0


@pytest.mark.slow
def test_stage_writes_outputs_and_the_row_samples(params, tmp_path: Path) -> None:
    local = copy.deepcopy(params)
    local["ray"]["num_workers"] = 0
    result = train(train_emdm.STAGE, local)
    out = Path(local["paths"]["artifacts"]) / "train_emdm"
    assert result.out_dir.resolve() == out.resolve() and (out / "model.pt").is_file()
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["step"] == 6
    assert all(np.isfinite(metrics[k]) for k in ("loss", "d_loss", "d_real", "d_fake", "geo", "g_adv", "r1"))
    payload = ckpt.load_final_model(out)
    generator, schedule, config = load_emdm(out)
    assert schedule.num_steps == 10 and config["model"]["condition"] == "text" and not generator.training
    for key, value in generator.state_dict().items():  # the EMA weights
        assert torch.equal(value, payload["ema"]["generator"][key]), key

    ctx = EvalContext(local, Path(local["paths"]["artifacts"]), Path(local["features"]["out"]))
    [row] = emdm_rows(ctx)
    assert isinstance(row, Generator) and isinstance(row, EMDMGeneratorRow)
    assert row.name == "EMDM-10" and row.nfe == 20 and row.stochastic and row.guidance == 2.5
    rng = np.random.default_rng(0)
    pooled = rng.standard_normal((3, 384)).astype(np.float32)
    text = TextBatch(["a", "b", "c"], pooled / np.linalg.norm(pooled, axis=1, keepdims=True),
                     [np.zeros((2, 384), np.float32)] * 3)
    lengths = np.array([40, 24, 32])
    x, y, z = row.sample(text, lengths, 1), row.sample(text, lengths, 1), row.sample(text, lengths, 2)
    assert x.shape == (3, 40, 263) and x.dtype == np.float32 and np.isfinite(x).all()
    np.testing.assert_array_equal(x, y)
    assert not np.allclose(x, z)
    assert not x[1, 24:].any() and not x[2, 32:].any() and np.abs(x[1, :24]).sum() > 0
    assert row.sample(text.select([1]), lengths[1:2], 1).shape == (1, 24, 263)

    plain = emdm_generator(ctx, GenerateOptions(guidance=1.0))
    assert plain.nfe == 10 and plain.name == "EMDM-10"
    assert emdm_generator(ctx, GenerateOptions(steps=10)).guidance == 2.5
    with pytest.raises(ValueError, match="EMDM samples with the 10 steps"):
        emdm_generator(ctx, GenerateOptions(steps=4))

    # the action stage starts from it: every weight but the label table is the text stage's
    action = local | {"train_emdm_action": emdm_section(condition="action", init_from="train_emdm",
                                                        model=local["train_emdm"]["model"])}
    config = emdm_training.stage_config(action, "train_emdm_action")
    assert config["init_dir"] == str(out)
    comps = emdm_training.build(config)
    sources = {"generator": payload["ema"]["generator"], "discriminator": payload["models"]["discriminator"]}
    for name, model in comps.models.items():
        for key, value in model.state_dict().items():
            if key != "cond_embed.embed.weight" and not key.startswith("label_word_"):
                assert torch.equal(value, sources[name][key]), (name, key)
        assert model.cond_embed.embed.weight.shape[0] == len(config["classes"])
    # ... and G's word slots hold the words of each class's central caption
    gen, items = comps.models["generator"], labelled_items(FeatureStore(config["features_dir"]).split("train"))
    assert config["model"]["label_words"] == config["max_text_tokens"]
    for c, label in enumerate(config["classes"]):
        _, words = emdm_training.class_captions([item for item in items if item.action == label])
        assert torch.equal(gen.label_word_states[c, : len(words)], words)
        assert gen.label_word_mask[c].sum() == len(words) and not gen.label_word_states[c, len(words):].any()
    # each condition samples with its own guidance scale (sample.emdm_guidance / emdm_action_guidance)
    (tmp_path / "train_emdm").symlink_to(out.resolve())
    (tmp_path / "train_emdm_action").mkdir()
    ckpt.save_final_model(tmp_path / "train_emdm_action", ckpt.final_model_payload(
        {"models": ckpt.state_dicts(comps.models), "step": 0}, config))
    scales = local | {"sample": local["sample"] | {"emdm_guidance": 1.25, "emdm_action_guidance": 4.0}}
    scaled = EvalContext(scales, tmp_path, Path(local["features"]["out"]))
    (action_row,) = emdm_action_rows(scaled)
    assert (action_row.guidance, emdm_rows(scaled)[0].guidance) == (4.0, 1.25)
    assert action_row.classes == tuple(config["classes"])
    # stages.generate --model emdm-action: the same model, labels as prompts, its own steps and guidance
    prompts = emdm_action_generator(scaled, GenerateOptions())
    assert prompts.row.guidance == 4.0 and prompts.row.classes == action_row.classes
    assert emdm_action_generator(scaled, GenerateOptions(guidance=1.0)).nfe == 10
    with pytest.raises(ValueError, match="EMDM-action samples with the 10 steps"):
        emdm_action_generator(scaled, GenerateOptions(steps=4))
    for change, message in (({"init_from": "nowhere"}, "nowhere holds no trained EMDM"),
                            ({"model": local["train_emdm"]["model"] | {"ff_dim": 48}}, "ff_dim 32 != 48")):
        bad = local | {"train_emdm_action": action["train_emdm_action"] | change}
        with pytest.raises(ValueError, match=r"train_emdm_action\.init_from: .*" + message):
            emdm_training.stage_config(bad, "train_emdm_action")
