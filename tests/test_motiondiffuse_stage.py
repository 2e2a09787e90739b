"""MotionDiffuse's training stage, evaluation rows, evaluation bound and generate's composition flags.

Params checks; one Adam step lowers the loss; a Ray Train run resumed exactly; the stage's outputs and
the registry functions; the row's contract (shape, zero padding, determinism) on a tiny untrained model;
the DDPM row's ``eval_items`` bound in the evaluation protocol; ``--part`` / ``--segment`` parsing.
Model sizes and step counts are minimal: this checks wiring, not model quality.
"""

from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from state_checks import assert_same, final_state

from data.skeleton import HUMANML3D
from data.store import StoredItem
from models.diffusion import wiener_taps
from models.generator import Generator, TextBatch
from models.motiondiffuse import SKIP_EIG_FLOOR, MotionDiffuse, MotionDiffuseConfig
from pipelines import checkpoint as ckpt
from pipelines.evaluation import EvalConfig, evaluate, references
from pipelines.length_batches import batch_seed
from pipelines.motiondiffuse_family import (
    MotionDiffuseRow,
    load_motiondiffuse,
    motiondiffuse_generator,
    motiondiffuse_rows,
    sample_body_parts,
    sample_time_varied,
)
from pipelines.registry import FAMILIES, EvalContext, GenerateOptions, ModelFamily
from pipelines.runner import StepContext, run_training
from pipelines.stage import loop_config, train
from stages import generate
from stages import train_motiondiffuse as stage

pytestmark = pytest.mark.usefixtures("one_thread")  # tiny networks (tests/conftest.py)

FIXTURES = Path(__file__).parent / "fixtures" / "humanml3d"
D, E = 263, 8
TINY_MODEL = {"width": 16, "layers": 1, "heads": 2, "ff_dim": 32, "dropout": 0.0, "text_layers": 1, "text_heads": 2,
              "text_ff_dim": 32, "time_embed_mult": 2, "max_len": 64, "attention": "linear", "input_skip": False,
              "skip_kernel": 1, "temporal_kernel": 0, "patch_frames": 1, "overlap_out": False}
LOOP = {"seed": 0, "batch_size": 8, "max_steps": 6, "grad_clip": 0.5, "lr_schedule": "constant", "warmup_steps": 0,
        "min_lr_ratio": 0.0, "log_every": 3, "num_data_workers": 0, "length_buckets": 0}


def section(**overrides: Any) -> dict[str, Any]:
    """A tiny ``train_motiondiffuse`` section (EMA and caption dropout on, so a resume must restore both)."""
    return {"lr": 2e-4, "ema_decay": 0.9, "p_uncond": 0.25, "crop_frames": 64, "num_train_timesteps": 100,
            "beta_start": 1e-4, "beta_end": 0.02, "model": dict(TINY_MODEL), "loop": dict(LOOP)} | overrides


@pytest.fixture(scope="module")
def params(small_store) -> dict[str, Any]:
    params = copy.deepcopy(small_store)
    params["train_motiondiffuse"] = section(model=TINY_MODEL | {"input_skip": True, "skip_kernel": 3,
                                                                "patch_frames": 2, "overlap_out": True})
    params["sample"]["motiondiffuse_guidance"] = 2.0
    params["sample"]["motiondiffuse_ddpm_items"] = 32
    params["sample"]["motiondiffuse_ddpm_replications"] = 1
    params["ray"].update(num_workers=1, cpus_per_worker=1, checkpoint_every=3, max_failures=0)
    return params


# --------------------------------------------------------------------------------------------------
# Params (checked before the store is opened)
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("change", "key"), [
    ({"lr": 0.0}, "train_motiondiffuse.lr"),
    ({"ema_decay": 1.0}, "train_motiondiffuse.ema_decay"),
    ({"ema_decay": True}, "train_motiondiffuse.ema_decay"),
    ({"p_uncond": 1.0}, "train_motiondiffuse.p_uncond"),
    ({"p_uncond": -0.1}, "train_motiondiffuse.p_uncond"),
    ({"crop_frames": 65}, "train_motiondiffuse.crop_frames"),
    ({"num_train_timesteps": 10.5}, "train_motiondiffuse.num_train_timesteps"),
    ({"beta_end": 1e-5}, "train_motiondiffuse.beta_end"),
    ({"beta_end": 0.2, "num_train_timesteps": 100}, "train_motiondiffuse.beta_end"),
    ({"model": TINY_MODEL | {"attention": "full"}}, "train_motiondiffuse.model.attention"),
    ({"model": TINY_MODEL | {"heads": 3}}, "train_motiondiffuse.model.heads"),
    ({"model": TINY_MODEL | {"text_layers": -1}}, "train_motiondiffuse.model.text_layers"),
    ({"model": TINY_MODEL | {"dropout": 1.0}}, "train_motiondiffuse.model.dropout"),
    ({"model": TINY_MODEL | {"input_skip": True, "skip_kernel": 4}}, "train_motiondiffuse.model.skip_kernel"),
    ({"model": TINY_MODEL | {"skip_kernel": 3}}, "train_motiondiffuse.model.skip_kernel"),
    ({"model": TINY_MODEL | {"patch_frames": 0}}, "train_motiondiffuse.model.patch_frames"),
    ({"model": TINY_MODEL | {"patch_frames": 3, "overlap_out": True}}, "train_motiondiffuse.model.overlap_out"),
    ({"model": TINY_MODEL | {"overlap_out": "yes"}}, "train_motiondiffuse.model.overlap_out"),
    ({"model": TINY_MODEL | {"feature_dim": 10}}, "train_motiondiffuse.model: unknown key"),
    ({"model": {k: v for k, v in TINY_MODEL.items() if k != "width"}}, "train_motiondiffuse.model: .*missing key"),
    ({"lr_g": 1e-4}, "train_motiondiffuse: unknown key"),
])
def test_bad_params_name_the_key(change: dict[str, Any], key: str, tmp_path: Path) -> None:
    params = {"train_motiondiffuse": section(**change), "features": {"out": str(tmp_path / "no_store")},
              "paths": {"artifacts": str(tmp_path), "ray_storage": str(tmp_path)}, "ray": {}}
    with pytest.raises(ValueError, match=key.replace(".", r"\.").replace(r"\.*", ".*")):
        loop_config(stage.STAGE, params)


def test_a_good_section_reaches_the_store_and_the_stage_reads_its_params(tmp_path: Path) -> None:
    params = {"train_motiondiffuse": section(), "features": {"out": str(tmp_path / "no_store")}, "ray": {}}
    with pytest.raises(FileNotFoundError, match="no feature store"):
        stage.stage_config(params)
    assert stage.STAGE.params == ("train_motiondiffuse", "features.out", "paths", "ray")
    model = stage.model_config(section(), 263, 384)
    assert model["feature_dim"] == 263 and model["text_dim"] == 384 and model["num_train_timesteps"] == 100
    assert MotionDiffuseConfig(**model).width == 16  # every field, ready for the loader


# --------------------------------------------------------------------------------------------------
# One step (no runner)
# --------------------------------------------------------------------------------------------------


def _batch() -> dict[str, torch.Tensor]:
    feats = np.load(FIXTURES / "new_joint_vecs_012314.npy")
    mean, std = np.load(FIXTURES / "Mean.npy"), np.load(FIXTURES / "Std.npy")
    x = torch.tensor((np.stack([feats[0:16], feats[30:46], feats[60:76]]) - mean) / std, dtype=torch.float32)
    lengths = torch.tensor([16, 12, 9])
    x = torch.where(torch.arange(16)[None, :, None] < lengths[:, None, None], x, 0.0)
    tokens = torch.randn(3, 4, E, generator=torch.Generator().manual_seed(0))
    mask = torch.arange(4)[None] < torch.tensor([4, 2, 3])[:, None]
    return {"motion": x, "length": lengths, "tokens": tokens, "token_mask": mask}


def test_steps_lower_the_loss_with_clipping_and_no_ema_by_default() -> None:
    config = {"lr": 1e-3, "ema_decay": 0.0, "p_uncond": 0.0, "model": stage.model_config(section(), D, E)}
    comps = stage.build(config)
    assert set(comps.models) == set(comps.optimizers) == {"denoiser"} and comps.ema == {}
    assert isinstance(comps.optimizers["denoiser"], torch.optim.Adam) and comps.frozen["schedule"].num_steps == 100
    assert stage.build(config | {"ema_decay": 0.9}).ema == {"denoiser": 0.9}
    ctx = StepContext(config, comps.models, comps.optimizers, {}, comps.frozen, torch.device("cpu"), 0, 1, 0.5)
    batch, losses = _batch(), []
    for _ in range(6):
        torch.manual_seed(0)  # the same t and eps every step: the loss of one fixed problem
        out = stage.step(batch, ctx)
        assert set(out) == {"loss"} and not out["loss"].requires_grad
        losses.append(float(out["loss"]))
    assert "grad_norm/denoiser" in ctx.extra_metrics
    assert losses[0] == pytest.approx(1.0, abs=0.3)  # a fresh model predicts 0: the loss is E[eps^2]
    assert all(b < a for a, b in zip(losses, losses[1:], strict=False)), losses


# --------------------------------------------------------------------------------------------------
# Rows on a tiny untrained model
# --------------------------------------------------------------------------------------------------


def _tiny_model(steps: int = 50) -> MotionDiffuse:
    torch.manual_seed(0)
    model = MotionDiffuse(MotionDiffuseConfig(**stage.model_config(section(num_train_timesteps=steps), D, E)))
    with torch.no_grad():  # wake the zero-initialised layers
        for p in model.parameters():
            p.add_(0.1 * torch.randn(p.shape, generator=torch.Generator().manual_seed(p.numel())))
    return model.eval()


def _text(n: int = 3) -> TextBatch:
    rng = np.random.default_rng(0)
    pooled = rng.standard_normal((n, E)).astype(np.float32)
    tokens = [rng.standard_normal((k, E)).astype(np.float32) for k in (3, 5, 2, 4)[:n]]
    return TextBatch([f"t{k}" for k in range(n)], pooled, tokens)


@pytest.mark.parametrize(("method", "steps", "nfe"), [("ddpm", None, 50), ("ddim", 4, 4)])
def test_row_shape_padding_and_seed(method: str, steps: int | None, nfe: int) -> None:
    model = _tiny_model()
    row = MotionDiffuseRow("MD", model, model.config.make_schedule(), method, steps)  # type: ignore[arg-type]
    assert isinstance(row, Generator) and row.stochastic and row.nfe == nfe and row.eval_items is None
    text, lengths = _text(), np.array([12, 7, 9])
    x, y, z = row.sample(text, lengths, 1), row.sample(text, lengths, 1), row.sample(text, lengths, 2)
    assert x.shape == (3, 12, D) and x.dtype == np.float32 and np.isfinite(x).all()
    np.testing.assert_array_equal(x, y)
    assert not np.allclose(x, z)
    assert not x[1, 7:].any() and not x[2, 9:].any() and np.abs(x[1, :7]).sum() > 0
    with pytest.raises(ValueError, match="max_len=64"):
        row.sample(text, np.array([65, 7, 9]), 1)


def test_row_in_length_batches_is_each_batch_sampled_alone() -> None:
    """``batch``: the rows sorted by length, sampled ``batch`` at a time with the batch's seed; one batch that
    holds every row is the unbatched call bit for bit."""
    model = _tiny_model()
    schedule = model.config.make_schedule()
    text, lengths = _text(), np.array([12, 7, 9])
    plain = MotionDiffuseRow("MD", model, schedule, "ddim", 4)
    np.testing.assert_array_equal(MotionDiffuseRow("MD", model, schedule, "ddim", 4, batch=3).sample(text, lengths, 1),
                                  plain.sample(text, lengths, 1))
    out = MotionDiffuseRow("MD", model, schedule, "ddim", 4, batch=1).sample(text, lengths, 1)
    for rank, i in enumerate(np.argsort(lengths, kind="stable")):  # 7, 9, 12 frames
        alone = plain.sample(text.select([i]), lengths[[i]], batch_seed(1, rank))[0]
        np.testing.assert_array_equal(out[i, : lengths[i]], alone)
        assert not out[i, lengths[i]:].any()


def test_compositions_with_one_whole_part_or_segment_are_the_row_bit_for_bit() -> None:
    model = _tiny_model()
    text = _text(1)
    for row in (MotionDiffuseRow("DDPM", model, model.config.make_schedule()),
                MotionDiffuseRow("DDIM", model, model.config.make_schedule(), "ddim", 3)):
        plain = row.sample(text, np.array([10]), 5)
        np.testing.assert_array_equal(sample_body_parts(row, [("whole", text)], 10, 5), plain)
        np.testing.assert_array_equal(sample_time_varied(row, [(0, 10, text)], 10, 5), plain)
    two = sample_body_parts(row, [("upper", text), ("lower", _text(2).select([1]))], 10, 5)
    assert two.shape == (1, 10, D) and np.isfinite(two).all() and not np.array_equal(two, plain)


def test_row_rejects_wrong_steps() -> None:
    model = _tiny_model()
    schedule = model.config.make_schedule()
    with pytest.raises(ValueError, match="DDPM runs all 50 steps"):
        MotionDiffuseRow("x", model, schedule, "ddpm", 10)
    with pytest.raises(ValueError, match="DDIM needs 1..50 steps"):
        MotionDiffuseRow("x", model, schedule, "ddim", 51)


# --------------------------------------------------------------------------------------------------
# The evaluation bound (eval_items) with a stub evaluator
# --------------------------------------------------------------------------------------------------

CODE = slice(4, 12)


class _StubEmbedder:
    """Captions embed as their item's code, motions as their first frame's code (tests/test_evaluation.py)."""

    def __init__(self, codes: np.ndarray) -> None:
        self.codes = codes

    def texts(self, tokens: list[list[str]]) -> np.ndarray:
        return np.stack([self.codes[int(t[0].split("/")[0][1:])] for t in tokens])

    def motions(self, raw: np.ndarray, lengths: np.ndarray) -> np.ndarray:
        return raw[:, 0, CODE].astype(np.float64)


class _Noisy:
    """A stochastic generator answering with its caption's code plus noise; records the batch sizes it gets."""

    stochastic, nfe = True, 1

    def __init__(self, name: str, codes: np.ndarray, eval_items: int | None = None,
                 eval_replications: int | None = None) -> None:
        self.name, self.codes, self.calls = name, codes, []
        if eval_items is not None:
            self.eval_items = eval_items
        if eval_replications is not None:
            self.eval_replications = eval_replications

    def sample(self, text: TextBatch, lengths: np.ndarray, seed: int) -> np.ndarray:
        self.calls.append(len(text))
        out = np.zeros((len(text), int(lengths.max()), D), np.float32)
        noise = np.random.default_rng(seed).standard_normal((len(text), 8))
        out[:, :, CODE] = (np.stack([self.codes[int(t[1:])] for t in text.texts]) + noise)[:, None]
        return out


def _world() -> tuple[np.ndarray, list[StoredItem]]:
    rng = np.random.default_rng(0)
    codes = rng.standard_normal((96, 8)) * 3
    items = []
    for k, code in enumerate(codes):
        features = np.zeros((int(rng.integers(40, 120)), D), np.float32)
        features[:, 3], features[:, CODE] = 0.9, code
        items.append(StoredItem(f"t{k}", f"t{k}", None, 0, features, [f"t{k}"], [[f"c{k}/NOUN"]],
                                (code / np.linalg.norm(code)).astype(np.float32)[None], [np.zeros((3, 4), np.float16)]))
    return codes, items


def test_eval_items_bounds_one_row_and_leaves_the_others_alone() -> None:
    codes, items = _world()
    cfg = EvalConfig(replications=2, diversity_times=50, mm_texts=10, mm_repeats=12, mm_times=10, timing_sentences=2)
    embedder = _StubEmbedder(codes)
    refs = references(items, embedder, cfg)
    mean, std = np.zeros(D, np.float32), np.ones(D, np.float32)
    alone = evaluate(refs, items, mean, std, embedder, HUMANML3D, cfg, [_Noisy("full", codes)])
    full, bounded = _Noisy("full", codes), _Noisy("bounded", codes, eval_items=32)
    table = evaluate(refs, items, mean, std, embedder, HUMANML3D, cfg, [bounded, full])
    timed = ("AITS_s", "ms_per_frame")  # wall clock
    assert {k: v for k, v in table["full"].items() if k not in timed} == {  # a bounded row beside it changes nothing
        k: v for k, v in alone["full"].items() if k not in timed}
    assert "eval_items" not in table["full"] and "MultiModality" in table["full"]
    assert bounded.calls == [32, 32, 1, 1, 1]  # one 32-caption batch per replication, then warm-up and timing
    row = table["bounded"]
    assert row["eval_items"] == 32 and "MultiModality" not in row and row["NFE"] == 1
    assert row["R_precision_top3"] > 0.5 and np.isfinite([row["FID"], row["Diversity"], row["MM_Dist"]]).all()
    assert "eval_items" not in evaluate(refs, items, mean, std, embedder, HUMANML3D, cfg,
                                        [_Noisy("big", codes, eval_items=500)])["big"]  # no bound: full protocol
    with pytest.raises(ValueError, match="eval_items must be an integer >= group_size"):
        evaluate(refs, items, mean, std, embedder, HUMANML3D, cfg, [_Noisy("small", codes, eval_items=8)])


def test_eval_replications_evaluates_a_row_in_the_first_replications_only() -> None:
    codes, items = _world()
    cfg = EvalConfig(replications=3, diversity_times=50, mm_texts=10, mm_repeats=12, mm_times=10, timing_sentences=2)
    embedder = _StubEmbedder(codes)
    refs = references(items, embedder, cfg)
    mean, std = np.zeros(D, np.float32), np.ones(D, np.float32)
    three = evaluate(refs, items, mean, std, embedder, HUMANML3D, cfg, [_Noisy("row", codes, eval_items=32)])["row"]
    one_gen, full = _Noisy("row", codes, eval_items=32, eval_replications=1), _Noisy("full", codes)
    table = evaluate(refs, items, mean, std, embedder, HUMANML3D, cfg, [one_gen, full])
    assert one_gen.calls == [32, 1, 1, 1]  # replication 0 only, then warm-up and timing
    one = table["row"]
    assert one["eval_replications"] == 1 and one["eval_items"] == 32
    assert not any(key.endswith("_ci") and key[:-3] in one for key in one)  # one replication: no CI
    assert "FID_ci" in three and three["FID"] != one["FID"]  # the mean of three replications, not of one
    assert "eval_replications" not in table["full"] and "R_precision_top3_ci" in table["full"]
    two = evaluate(refs, items, mean, std, embedder, HUMANML3D, cfg,
                   [_Noisy("row", codes, eval_items=32, eval_replications=2)])["row"]
    assert two["eval_replications"] == 2 and "FID_ci" in two
    assert "eval_replications" not in evaluate(refs, items, mean, std, embedder, HUMANML3D, cfg, [
        _Noisy("row", codes, eval_items=32, eval_replications=5)])["row"]  # more than there are: all of them
    with pytest.raises(ValueError, match="eval_replications must be an integer >= 1"):
        evaluate(refs, items, mean, std, embedder, HUMANML3D, cfg, [_Noisy("row", codes, eval_replications=0)])


# --------------------------------------------------------------------------------------------------
# stages.generate --part / --segment
# --------------------------------------------------------------------------------------------------


def test_part_and_segment_specs_parse() -> None:
    assert generate.parse_parts(["upper=a person waves", " lower = walks "]) == [("upper", "a person waves"),
                                                                                  ("lower", "walks")]
    assert generate.parse_parts(["left_arm=waves", "rest=walks"]) == [("left_arm", "waves"), ("rest", "walks")]
    assert generate.parse_segments(["0:70=walks", "50:120=a:b=c"], 120) == [(0, 70, "walks"), (50, 120, "a:b=c")]


@pytest.mark.parametrize(("specs", "message"), [
    (["tail=wags"], "unknown body part 'tail'"),
    (["upper"], "expected NAME=TEXT"),
    (["upper="], "expected NAME=TEXT"),
    (["upper=waves", "arms=wave", "lower=walks"], "'upper' and 'arms' overlap"),
    (["upper=waves"], "leave left_leg, right_leg, root uncovered"),
    (["whole=walks", "rest=waves"], "'rest' is empty"),
    (["upper=waves", "rest=walks", "rest=runs"], "at most one part"),
])
def test_bad_parts_are_named(specs: list[str], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        generate.parse_parts(specs)


@pytest.mark.parametrize(("specs", "message"), [
    (["0-60=walks"], "expected A:B=TEXT"),
    (["0:x=walks"], "expected A:B=TEXT"),
    (["0:60"], "expected A:B=TEXT"),
    (["60:60=walks", "0:120=runs"], r"frames \[60, 60\) are outside"),
    (["0:130=walks"], r"frames \[0, 130\) are outside"),
    (["0:50=walks", "60:120=jumps"], r"frames 50\.\.59 \(10 in all\) are not covered"),
])
def test_bad_segments_are_named(specs: list[str], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        generate.parse_segments(specs, 120)


@pytest.mark.parametrize(("argv", "message"), [
    (["--model", "mld", "--part", "whole=walks"], "only --model motiondiffuse composes"),
    (["--model", "mld"], "no prompt: give --text"),
    (["--model", "mld", "--segment", "0:120=walks", "--part", "whole=walks"], "only --model motiondiffuse"),
    (["--model", "motiondiffuse", "--part", "hands=waves"], "unknown body part 'hands'"),
    (["--model", "motiondiffuse", "--segment", "-5:60=walks", "--segment", "60:120=runs"],
     r"--segment '-5:60=walks': frames [-5, 60) are outside"),
])
def test_generate_cli_errors_are_one_line_exit_1(argv: list[str], message: str,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """Composition errors as every other check before loading: ``generate: <reason>``, exit status 1."""
    with pytest.raises(SystemExit) as exit_info:
        generate.main([*argv, "--out", "x.gif"])
    code = exit_info.value.code  # sys.exit(message): printed to stderr, exit status 1
    assert isinstance(code, str) and code.startswith("generate: ") and message in code and "\n" not in code
    assert capsys.readouterr().err == ""  # no argparse usage block


def test_a_negative_segment_start_is_the_segment_s_value() -> None:
    """argparse would read ``-5:60=walks`` as an option; only a value after ``--segment`` that starts with a
    digit is attached, so a missing value stays argparse's error and other options are untouched."""
    assert generate.attach_dashed_values(["--segment", "-5:60=walks", "--seed", "-1"]) == [
        "--segment=-5:60=walks", "--seed", "-1"]
    assert generate.attach_dashed_values(["--segment", "--out", "x.gif"]) == ["--segment", "--out", "x.gif"]
    assert generate.attach_dashed_values(["--seg", "-5:60=walks", "--se", "-1"]) == ["--seg=-5:60=walks", "--se", "-1"]


def test_generate_cli_rejects_a_mistyped_option(capsys: pytest.CaptureFixture[str]) -> None:
    """An unknown ``--option`` is argparse's usage error, not a malformed ``key=value`` override."""
    with pytest.raises(SystemExit) as exit_info:
        generate.main(["--text", "walks", "--lenght", "60", "--out", "x.gif"])
    assert exit_info.value.code == 2 and "unrecognized arguments: --lenght" in capsys.readouterr().err


def test_generate_cli_checks_specs_for_motiondiffuse() -> None:
    """``check_composition``: the first problem of ``--part`` / ``--segment`` with the other options, else the specs."""
    base = {"model": "motiondiffuse", "text": [], "trajectory": None, "refine": False, "length": 120}
    cases = [({"part": ["upper=waves"], "segment": []}, "uncovered"),
             ({"part": ["whole=walks"], "segment": ["0:120=walks"]}, "use one kind"),
             ({"part": [], "segment": ["0:50=walks"]}, "not covered"),
             ({"part": ["whole=walks"], "segment": [], "text": ["walks"]}, "no --text")]
    for change, message in cases:
        with pytest.raises(ValueError, match=message):
            generate.check_composition(generate.argparse.Namespace(**(base | change)))
    ok = generate.argparse.Namespace(**(base | {"part": [], "segment": ["0:120=walks"]}))
    assert generate.check_composition(ok) == ([], [(0, 120, "walks")])


# --------------------------------------------------------------------------------------------------
# Through the runner (slow)
# --------------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_step_through_ray_resumes_exactly(params, ray_cluster, tmp_path: Path) -> None:
    """3 steps resumed to 6 equal 6 straight: the model, Adam, the scheduler, the EMA and the logged losses."""
    config = loop_config(stage.STAGE, params)
    assert config["model"]["text_dim"] == 384 and config["max_text_tokens"] == 32
    storage = str(tmp_path / "ray")
    straight = run_training("md", stage.STAGE.spec, config | {"max_steps": 6}, params["ray"], tmp_path / "straight",
                            storage)
    run_training("md", stage.STAGE.spec, config | {"max_steps": 3}, params["ray"], tmp_path / "part", storage,
                 run_name="md-resumed")
    resumed = run_training("md", stage.STAGE.spec, config | {"max_steps": 6}, params["ray"], tmp_path / "resumed",
                           storage, run_name="md-resumed")
    assert straight.attempts == [0] and resumed.attempts == [0, 3]
    a, b = final_state(straight.run_path), final_state(resumed.run_path)
    assert a["step"] == b["step"] == 6 and set(a["models"]) == set(a["ema"]) == {"denoiser"}
    for part in ("models", "optimizers", "schedulers", "ema"):
        assert_same(a[part], b[part], part)
    assert [row["step"] for row in straight.history] == [3, 6]
    for x, y in zip(straight.history, resumed.history, strict=True):
        assert x["loss"] == y["loss"] and np.isfinite(x["loss"])


@pytest.mark.slow
def test_stage_writes_outputs_and_the_rows_sample(params, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    local = copy.deepcopy(params)
    local["ray"]["num_workers"] = 0
    local["paths"]["artifacts"] = str(tmp_path / "artifacts")
    train(stage.STAGE, local)
    out = tmp_path / "artifacts" / "train_motiondiffuse"
    assert json.loads((out / "metrics.json").read_text())["step"] == 6
    model, schedule, config = load_motiondiffuse(out)
    assert schedule.num_steps == 100 and not model.training and config["model"]["text_dim"] == 384
    # the recipe set the skip filter from the training features' lag moments, and model.pt kept it
    expected = wiener_taps(torch.tensor(config["skip_moments"]), schedule.alphas_cumprod, 3, target="epsilon",
                           eig_floor=SKIP_EIG_FLOOR)
    assert torch.equal(model.skip_taps, expected) and bool(model.skip_taps[:, :, 0].any())
    payload = ckpt.load_final_model(out)
    for key, value in model.state_dict().items():  # the EMA weights
        assert torch.equal(value, payload["ema"]["denoiser"][key]), key

    ctx = EvalContext(local, tmp_path / "artifacts", Path(local["features"]["out"]))
    ddpm, ddim = motiondiffuse_rows(ctx)
    assert (ddpm.name, ddpm.nfe, ddpm.eval_items, ddpm.eval_replications) == ("MotionDiffuse-100", 200, 32, 1)
    assert "first 32 captions of the first 1 replication(s)" in ddpm.note
    assert (ddim.name, ddim.nfe, ddim.eval_items, ddim.guidance) == ("MotionDiffuse-DDIM10", 20, None, 2.0)
    text = ctx.store.encode_prompts(["a person walks", "a person jumps"])
    x = ddim.sample(text, np.array([20, 12]), 0)
    assert x.shape == (2, 20, 263) and not x[1, 12:].any() and np.isfinite(x).all()
    assert motiondiffuse_generator(ctx, GenerateOptions()).nfe == 200  # guidance doubles the passes
    assert motiondiffuse_generator(ctx, GenerateOptions(guidance=1.0)).nfe == 100
    assert motiondiffuse_generator(ctx, GenerateOptions(steps=100)).method == "ddpm"
    assert motiondiffuse_generator(ctx, GenerateOptions(steps=5)).name == "MotionDiffuse-DDIM5"
    with pytest.raises(ValueError, match="DDIM with 1..99 steps"):
        motiondiffuse_generator(ctx, GenerateOptions(steps=101))
    unguided = motiondiffuse_generator(ctx, GenerateOptions(steps=5, guidance=1.0)).sample(text, np.array([20, 12]), 0)
    guided = motiondiffuse_generator(ctx, GenerateOptions(steps=5)).sample(text, np.array([20, 12]), 0)
    assert np.isfinite(guided).all() and not np.allclose(guided, unguided)  # --guidance reaches the sampler

    # stages.generate --part / --segment end to end (the registry entry as it will read)
    monkeypatch.setitem(FAMILIES, "motiondiffuse", ModelFamily(
        "motiondiffuse", "pipelines.motiondiffuse_family", "motiondiffuse_rows",
        train_stages=("train_motiondiffuse",),
        params=("sample.motiondiffuse_guidance", "sample.motiondiffuse_ddpm_items",
                "sample.motiondiffuse_ddpm_replications"),
        generator="motiondiffuse_generator"))
    [parts] = generate.generate(local, "motiondiffuse", [], [24], tmp_path / "parts.npy", steps=3,
                                parts=[("upper", "a person waves"), ("lower", "a person walks")])
    [segments] = generate.generate(local, "motiondiffuse", [], [24], tmp_path / "segments.npy", steps=3,
                                   segments=[(0, 16, "a person walks"), (10, 24, "a person jumps")])
    for path in (parts, segments):
        joints = np.load(path)
        assert joints.shape == (24, 22, 3) and np.isfinite(joints).all()
    with pytest.raises(ValueError, match="'upper' and 'arms' overlap"):  # the model's own check, after parsing
        generate.generate(local, "motiondiffuse", [], [24], tmp_path / "x.npy", steps=3,
                          parts=[("upper", "waves"), ("arms", "waves"), ("lower", "walks")])

    local["sample"]["motiondiffuse_guidance"] = -1.0
    with pytest.raises(ValueError, match=r"sample\.motiondiffuse_guidance: expected a number >= 0"):
        motiondiffuse_rows(ctx)
    local["sample"]["motiondiffuse_guidance"] = 2.0
    local["sample"]["motiondiffuse_ddpm_items"] = 0
    with pytest.raises(ValueError, match="sample.motiondiffuse_ddpm_items"):
        motiondiffuse_rows(ctx)
