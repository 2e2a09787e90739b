"""Configuration: committed params.yaml == composed conf/ defaults; overrides, their types and errors; every
stage's up-front checks, ``--help`` and ``--cfg`` through the real command line."""

import functools
import importlib
import json
import subprocess
import sys
import time
from collections.abc import Callable

import pytest
import yaml

from pipelines import config
from pipelines.cli import _flatten, check_params, check_shared
from pipelines.config import (
    PARAMS_PATH,
    REPO_ROOT,
    ConfigError,
    apply_overrides,
    check_choice,
    check_number,
    compose_params,
    every_problem,
    load_params,
    main,
    parse_value,
    read_params,
    restrict_params,
)
from pipelines.registry import FAMILIES
from pipelines.stage import checks
from pipelines.stage import main as stage_main
from stages import evaluate, extract_features, train_vae


def test_committed_params_equal_composed_defaults():
    assert read_params(PARAMS_PATH) == compose_params()


def test_group_choice_recomposes_conf():
    kit = load_params(["dataset=kit", "scale=smoke"])
    assert kit["data"]["skeleton"] == "kit"
    assert kit["data"]["root"] == "datasets/KIT-ML"
    assert kit["scale"] == "smoke"
    # the scale group changes sizes; sections it does not touch come from conf/config.yaml unchanged
    assert kit["synthetic"]["num_motions"] < compose_params()["synthetic"]["num_motions"]
    assert kit["paths"] == compose_params()["paths"]


def test_plus_group_choice_is_the_group_choice():
    """``+scale=smoke`` chooses the smoke profile (it was a plain ``scale`` key a stage then dropped)."""
    smoke = load_params(["scale=smoke"])
    assert load_params(["+scale=smoke"]) == smoke and compose_params(["+scale=smoke"]) == smoke
    vae = restrict_params(load_params(["+scale=smoke", "train_vae.lr=0.002"]), train_vae.STAGE.params)["train_vae"]
    assert (vae["loop"]["max_steps"], vae["lr"]) == (50, 0.002)
    assert vae["loop"]["max_steps"] != read_params(PARAMS_PATH)["train_vae"]["loop"]["max_steps"]
    kit = load_params(["+dataset=kit", "+scale=smoke"])
    assert (kit["data"]["skeleton"], kit["scale"]) == ("kit", "smoke")
    with pytest.raises(ConfigError) as info:
        load_params(["+scale=nope"])
    assert str(info.value) == "scale='nope': no such choice; scale is one of ['paper', 'smoke', 'tiny']"


def test_paper_profile_is_mlds_published_architecture():
    """`scale=paper` must not inherit the tiny profile's sizes (e.g. the tiny denoiser's width 128)."""
    paper = compose_params(["scale=paper"])
    vae, mld = paper["train_vae"], paper["train_mld"]
    keys = ("latent_tokens", "latent_dim", "hidden_dim", "layers", "ff_dim", "logvar_offset")
    assert {k: vae["model"][k] for k in keys} == {
        "latent_tokens": 1, "latent_dim": 256, "hidden_dim": None, "layers": 9, "ff_dim": 1024, "logvar_offset": 0.0}
    # denoiser width = the VAE's latent_dim (no latent projections), MLD's 9 layers, ff 1024, 768-d time sinusoid
    assert {k: mld["model"][k] for k in ("hidden_dim", "layers", "ff_dim", "time_freq_dim", "word_tokens")} == {
        "hidden_dim": None, "layers": 9, "ff_dim": 1024, "time_freq_dim": 768, "word_tokens": "none"}
    assert (paper["sample"]["mld_guidance"], mld["beta_schedule"], mld["num_train_timesteps"], mld["lr"]) == (
        7.5, "scaled_linear", 1000, 1e-4)
    assert vae["kl_weight"] == 1e-4 and vae["loop"]["length_buckets"] == 0
    assert (vae["joint_space"], vae["joint_weight"]) == ("global", 1.0)  # MLD's joint loss
    # MLD's optimisation for both: AdamW with torch's default decay, no schedule, no clipping; batch 128 / 64
    schedule = ("lr_schedule", "warmup_steps", "grad_clip")
    for section, batch in ((vae, 128), (mld, 64)):
        assert (section["weight_decay"], section["loop"]["batch_size"], *(section["loop"][k] for k in schedule)) == (
            0.01, batch, "constant", 0, 0.0)
    lcm = paper["distill_lcm"]  # MotionLCM V2's distillation settings
    assert (tuple(lcm["w_range"]), lcm["ema_decay"], lcm["num_ddim_steps"], lcm["distance"], lcm["huber_c"]) == (
        (5.0, 15.0), 0.95, 10, "huber", 0.5)
    assert (lcm["lr"], lcm["loop"]["batch_size"], paper["sample"]["motionlcm_guidance"]) == (2e-4, 128, 8.0)


def test_paper_profile_keeps_motiondiffuses_optimiser_and_sampler():
    """`scale=paper` is the code's Adam 2e-4, constant, clip 0.5, no null caption and no guidance, whatever
    `tiny` trains and samples with."""
    params = compose_params(["scale=paper"])
    paper = params["train_motiondiffuse"]
    schedule = ("lr_schedule", "warmup_steps", "min_lr_ratio", "grad_clip")
    assert (paper["lr"], *(paper["loop"][k] for k in schedule)) == (2e-4, "constant", 0, 0.0, 0.5)
    assert (paper["p_uncond"], params["sample"]["motiondiffuse_guidance"]) == (0.0, 1.0)


def test_paper_profile_keeps_emdms_constant_rates_and_lambdas():
    """`scale=paper` is EMDM's Adam rates, constant (its cosine never decays within training), its
    λ of Eq. 12 per condition, its action model trained from scratch, and its released code's
    guidance: 2.5 for text, none for action labels (trained without a null label), whatever `tiny`
    does."""
    params = compose_params(["scale=paper"])
    text, action = params["train_emdm"], params["train_emdm_action"]
    schedule = ("lr_schedule", "warmup_steps", "min_lr_ratio")
    assert (text["lr_g"], text["lr_d"], *(text["loop"][k] for k in schedule)) == (2e-5, 1.25e-4, "constant", 0, 0.0)
    assert (action["lr_g"], action["lr_d"], *(action["loop"][k] for k in schedule)) == (
        3e-5, 1.25e-4, "constant", 0, 0.0)
    assert (text["geometric_lambda"], action["geometric_lambda"]) == (0.0, 1.0)
    assert (text["ema_decay"], action["ema_decay"]) == (0.9999, 0.9999)
    assert action["init_from"] is None and action["geometric_weight"] is None  # R = 1 for action
    assert (params["sample"]["emdm_guidance"], params["sample"]["emdm_action_guidance"]) == (2.5, 1.0)
    assert (text["p_uncond"], action["p_uncond"]) == (0.1, 0.0)
    assert compose_params([])["train_emdm_action"]["init_from"] == "train_emdm"


def test_dotted_override_parses_yaml_values_and_keeps_the_rest():
    params = {"data": {"on_error": "fail", "max_frames": 200}, "seed": 0}
    out = apply_overrides(params, ["data.on_error=skip", "data.max_frames=150", "seed=3"])
    assert out == {"data": {"on_error": "skip", "max_frames": 150}, "seed": 3}
    assert params["data"]["on_error"] == "fail"  # input not mutated


def test_unknown_key_is_an_error_naming_it():
    with pytest.raises(ConfigError, match="data.on_eror"):
        apply_overrides({"data": {"on_error": "fail"}}, ["data.on_eror=skip"])
    with pytest.raises(ConfigError, match="nope"):
        apply_overrides({"data": {}}, ["nope.x=1"])
    with pytest.raises(ConfigError, match="key=value"):
        apply_overrides({}, ["seed"])


def test_plus_adds_a_new_key():
    assert apply_overrides({"a": {}}, ["+a.b.c=1"]) == {"a": {"b": {"c": 1}}}


def test_check_mode_detects_a_stale_params_file(tmp_path):
    stale = tmp_path / "params.yaml"
    stale.write_text("seed: 1\n")
    with pytest.raises(SystemExit, match="differs"):
        main(["--check", "--out", str(stale)])
    main(["--out", str(stale)])
    main(["--check", "--out", str(stale)])
    assert read_params(stale) == compose_params()


def test_malformed_params_file_names_the_file(tmp_path):
    bad = tmp_path / "params.yaml"
    bad.write_text("- a list\n")
    with pytest.raises(ConfigError, match="params.yaml"):
        read_params(bad)


# --------------------------------------------------------------------------- typed values


@pytest.mark.parametrize(("raw", "value"), [
    ("1e-3", 0.001), ("1E5", 100000.0), (".5", 0.5), ("-2.5e+1", -25.0), ("7", 7), ("017", 17), ("0x1f", 31),
    ("true", True), ("False", False), ("null", None), ("", None),
    # YAML 1.1 would make these booleans, octal, sexagesimal or dates: YAML 1.2 and OmegaConf keep them strings
    ("yes", "yes"), ("off", "off"), ("1:30", "1:30"), ("2024-01-01", "2024-01-01"), ("abc", "abc"),
    ("loguniform(1e-4, 3e-3)", "loguniform(1e-4, 3e-3)"), ("[1, 2.5e-1]", [1, 0.25]),
])
def test_override_values_are_typed_as_yaml_1_2(raw, value):
    parsed = parse_value(raw)
    assert parsed == value and type(parsed) is type(value)


def test_scientific_learning_rate_is_a_float():
    params = apply_overrides(read_params(PARAMS_PATH), ["train_vae.lr=1e-3"])
    assert params["train_vae"]["lr"] == 0.001 and isinstance(params["train_vae"]["lr"], float)


def test_malformed_value_is_a_config_error_naming_it():
    with pytest.raises(ConfigError, match=r"'\[1,2' is not valid YAML"):
        apply_overrides({"a": 0}, ["a=[1,2"])


def test_tilde_removes_a_key_and_names_an_unknown_one():
    assert apply_overrides({"a": {"b": 1, "c": 2}}, ["~a.b"]) == {"a": {"c": 2}}
    with pytest.raises(ConfigError, match="'a.x'"):
        apply_overrides({"a": {"b": 1}}, ["~a.x"])


def test_group_choice_must_be_a_file_of_its_conf_group():
    for choice in ("../../elsewhere/file", "nope", "smoke/../tiny"):
        with pytest.raises(ConfigError, match=r"scale=.*one of \['paper', 'smoke', 'tiny'\]"):
            load_params([f"scale={choice}"])
    with pytest.raises(SystemExit, match="dataset="):
        main(["dataset=../../x"])


# --------------------------------------------------------------------------- checks in process


def test_every_stage_accepts_every_composition_of_conf(capsys, monkeypatch):
    """The up-front checks pass on each profile and dataset of conf/ (`--cfg` checks without running)."""
    compose = functools.cache(lambda groups: compose_params(list(groups)))  # one Hydra composition per choice
    monkeypatch.setattr(config, "compose_params", lambda groups: compose(tuple(groups)))
    for groups in ([], ["scale=smoke"], ["scale=paper"], ["dataset=kit"], ["dataset=humanml3d", "scale=paper"]):
        for _, entry in stage_entries():
            entry(["--cfg", *groups])
        for name in [evaluate.REAL, *FAMILIES]:
            evaluate.main([name, "--cfg", *groups])
    capsys.readouterr()


def test_help_lists_each_key_with_its_value_and_meaning(capsys):
    for name, entry in stage_entries():
        entry(["--help"])
        text = capsys.readouterr().out
        assert text.startswith(f"usage: {name} [key=value ...]"), name
        for key, value, is_mapping in _flatten(stage_params(name), ""):
            if not is_mapping:
                shown = value if isinstance(value, str) else json.dumps(value)
                assert f"\n  {key} = {shown}" in text, (name, key)
    stage_main(train_vae.STAGE, ["--help", "train_vae.lr=1e-3"])
    text = capsys.readouterr().out
    assert "\n  train_vae.lr = 0.001\n" in text  # overrides shown as they will run
    assert "\n  train_vae.joint_space = root  # global (MLD) | root: joints relative to the root joint\n" in text
    extract_features.main(["--help"])
    assert "\n  features.workers = 2  # processes for feature extraction\n" in capsys.readouterr().out


def test_errors_of_several_keys_are_one_line_each():
    params = restrict_params(load_params(["train_vae.lr=abc", "ray.num_workers=-1", "train_vae.loop.seed=x"]),
                             train_vae.STAGE.params)
    assert check_params(params, train_vae.STAGE.params, checks(train_vae.STAGE)) == [
        "ray.num_workers: expected an integer >= 0, got -1",
        "train_vae.loop.seed: expected int, got 'x'",
        "train_vae.lr: expected a number > 0.0, got 'abc'",
    ]


def test_every_bad_value_of_a_stages_own_section_is_listed():
    """A stage's own section is checked to its end: each bad value one line, in the order it is checked;
    a value the later checks cannot use (heads "x") ends the list there, without a second, derived error."""
    params = restrict_params(load_params(["train_vae.kl_weight=-1", "train_vae.heading_weight=-1",
                                          "train_vae.joint_beta=0", "train_vae.joint_space=local"]),
                             train_vae.STAGE.params)
    assert check_params(params, train_vae.STAGE.params, checks(train_vae.STAGE)) == [
        "train_vae.kl_weight: expected a number >= 0.0, got -1",
        "train_vae.heading_weight: expected a number >= 0.0, got -1",
        "train_vae.joint_beta: expected a number > 0.0, got 0",
        "train_vae.joint_space: expected one of ['global', 'root'], got 'local'",
    ]
    params = restrict_params(load_params(["train_vae.lr=0", "train_vae.model.heads=x"]), train_vae.STAGE.params)
    assert check_params(params, train_vae.STAGE.params, checks(train_vae.STAGE)) == [
        "train_vae.lr: expected a number > 0.0, got 0",
        "train_vae.model.heads: expected an integer, got 'x'",  # once, by the first check that refused it
    ]


def test_outside_every_problem_a_check_raises_at_the_first_bad_value():
    """The sweeps and the stages' own code call the checks directly: the first bad value raises."""
    with pytest.raises(ConfigError, match=r"^s\.a: expected a number >= 0, got -1$"):
        check_number({"a": -1, "b": -1}, "a", "s", low=0)
    listed = r"^s\.a: expected a number >= 0, got -1\ns\.b: expected one of \[1\], got 2$"
    with pytest.raises(ConfigError, match=listed):
        with every_problem():
            check_number({"a": -1}, "a", "s", low=0)
            check_choice({"b": 2}, "b", "s", choices=[1])
            raise ZeroDivisionError  # code that used the bad value: the list stands for it
    with pytest.raises(ZeroDivisionError), every_problem():  # nothing noted: the error is the code's own
        raise ZeroDivisionError


@pytest.mark.parametrize("override", ["train_vae.lr=.nan", "train_vae.lr=.inf", "train_vae.kl_weight=.inf"])
def test_nan_and_infinity_are_not_numbers_in_bounds(override):
    """A YAML ``.nan`` compares False with every bound and ``.inf`` passes a lower one: both are refused."""
    params = restrict_params(load_params([override]), train_vae.STAGE.params)
    key, value = override.split("=")
    [error] = check_params(params, train_vae.STAGE.params, checks(train_vae.STAGE))
    assert error.startswith(f"{key}: expected a number ") and error.endswith(f"got {float(value.replace('.', '', 1))}")


def test_unknown_key_of_a_shared_section_added_with_plus_is_an_error():
    params = restrict_params(load_params(["+features.wrokers=2"]), extract_features.PARAMS)
    assert check_shared(params, extract_features.PARAMS) == [
        "features.wrokers: unknown key; features holds ['out', 'workers', 'text_encoder', 'text_encoder_path', "
        "'max_text_tokens', 'text_batch_size']"]


@pytest.mark.parametrize(("value", "errors"), [
    (None, []), (16, []),
    (0, ["sample.motion_batch: expected an integer >= 1, got 0"]),
    (1.5, ["sample.motion_batch: expected an integer >= 1, got 1.5"]),
    (True, ["sample.motion_batch: expected an integer >= 1, got True"]),
])
def test_null_or_count_keys_take_null_or_a_positive_integer(value, errors):
    params = load_params([])
    params["sample"]["motion_batch"] = value
    assert check_shared(params, ["sample"]) == errors


@pytest.mark.parametrize(("value", "errors"), [
    (-1, []), (0, []), (3, []),
    (-2, ["ray.max_failures: expected an integer >= -1, got -2"]),
    (1.5, ["ray.max_failures: expected an integer >= -1, got 1.5"]),
])
def test_max_failures_takes_minus_one_for_no_limit(value, errors):
    """-1 is documented (RayOptions, fit_retrying) as retrying worker crashes without a limit."""
    params = load_params([])
    params["ray"]["max_failures"] = value
    assert check_shared(params, ["ray"]) == errors


def test_a_seed_whose_epoch_seeds_overflow_int64_is_refused_before_the_run(capsys):
    """``train_vae.loop.seed=100000000000`` passed ``--cfg`` and then failed in the run (torch: Overflow when
    unpacking long long)."""
    from pipelines.runner import max_seed

    steps = read_params(PARAMS_PATH)["train_vae"]["loop"]["max_steps"]
    with pytest.raises(SystemExit) as exc:
        stage_main(train_vae.STAGE, ["train_vae.loop.seed=100000000000", "--cfg"])
    assert str(exc.value.code).splitlines() == [
        f"train_vae: train_vae.loop.seed: expected an integer >= 0 and <= {max_seed(steps)} (with max_steps "
        f"{steps}, so that every epoch seed (seed*1000003 + epoch)*1024 + rank stays within int64), got 100000000000"]
    stage_main(train_vae.STAGE, [f"train_vae.loop.seed={max_seed(steps)}", "--cfg"])  # the largest one passes
    capsys.readouterr()


@pytest.mark.parametrize("address", [None, "auto", "local", "10.0.0.1:6379", "headnode:6379", "[::1]:6379",
                                     "ray://10.0.0.1:10001", "numpy://a-provider-module"])
def test_ray_address_takes_the_forms_ray_connects_to(address):
    """``scheme://`` passes when the scheme is an installed module (``ray.init`` imports it for a provider's
    client builder); numpy stands in for such a package."""
    params = load_params([])
    params["ray"]["address"] = address
    assert check_shared(params, ["ray"]) == []


@pytest.mark.parametrize("address", ["headnode", "headnode:", ":6379", "h:0", "h:65536", "ray://h", "http://h:8265",
                                     "HTTP://h:8265", "RAY://h:10001", "nosuchprovider://c", "10.0.0.1 :6379", 6379])
def test_a_malformed_ray_address_is_named_before_ray_starts(address):
    """Without a port (or with one out of range, or the dashboard's http:// address) Ray would fail later, with
    a message that does not name the key."""
    params = load_params([])
    params["ray"]["address"] = address
    assert check_shared(params, ["ray"]) == [
        "ray.address: expected null, 'auto', 'local' or HOST:PORT (e.g. 10.0.0.1:6379, ray://10.0.0.1:10001), "
        f"got {address!r}"]


# --------------------------------------------------------------------------- the real command line


def run_stage(*args: str) -> tuple[subprocess.CompletedProcess, float]:
    """``python -m <args>`` from the repository root; (the process, wall seconds)."""
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", *args], cwd=REPO_ROOT, capture_output=True, text=True, timeout=120)
    return proc, time.perf_counter() - start


#: An override per stage that makes its run fail at once on a missing input: a config error reported
#: instead proves the checks ran before any work.
NO_INPUT = {"stages.train_vae": "features.out=/nonexistent/features",
            "stages.extract_features": "data.root=/nonexistent/dataset",
            "stages.evaluate": "paths.artifacts=/nonexistent/artifacts"}


@pytest.mark.slow
@pytest.mark.parametrize(("args", "message"), [
    (("stages.train_vae", "train_vae.lr=abc"), "train_vae.lr: expected a number > 0.0, got 'abc'"),
    (("stages.extract_features", "features.workers=abc"), "features.workers: expected an integer >= 1, got 'abc'"),
    (("stages.extract_features", "features.workers=-3"), "features.workers: expected an integer >= 1, got -3"),
    (("stages.extract_features", "data.feature_frames_below=lots"),
     "data.feature_frames_below: expected an integer >= 2, got 'lots'"),
    (("stages.extract_features", "data.max_frames=lots"), "unknown config key 'data.max_frames'"),
    (("stages.train_vae", "train_vae.lrr=0.1"), "unknown config key 'train_vae.lrr'"),
    (("stages.train_vae", "~train_vae"), "params have no 'train_vae'"),
    (("stages.train_vae", "~train_vae.lr"), "train_vae.lr: missing; train_vae holds ['lr', "),
    (("stages.train_vae", "train_vae.joint_space=sideways"),
     "train_vae.joint_space: expected one of ['global', 'root'], got 'sideways'"),
    (("stages.train_vae", "train_vae.model.activation=tanh"), "train_vae.model.activation: expected one of ['gelu'"),
    (("stages.train_vae", "scale=../../elsewhere/file"),
     "scale='../../elsewhere/file': no such choice; scale is one of ['paper', 'smoke', 'tiny']"),
    (("stages.evaluate", "mld", "sample.mld_guidance=lots"), "sample.mld_guidance: expected a number >= 0.0"),
])
def test_config_error_is_one_line_naming_the_key_before_any_work(args, message):
    proc, seconds = run_stage(*args, NO_INPUT[args[0]])
    stage = "eval_mld" if args[0] == "stages.evaluate" else args[0].split(".")[1]
    assert proc.returncode == 1, proc.stderr
    assert "Traceback" not in proc.stderr
    [line] = proc.stderr.splitlines()
    assert line.startswith(f"{stage}: ") and message in line, line
    # the failure came a minute later, after Ray started and retried; the import alone (torch) takes
    # 3-5 s on an idle 2-core machine, more on a loaded one: the bound leaves room for load, not for work
    assert seconds < 30


@pytest.mark.slow
def test_help_and_cfg_exit_0_without_running(tmp_path):
    out = tmp_path / "artifacts"
    proc, _ = run_stage("stages.train_vae", "--help", f"paths.artifacts={out}")
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr
    steps = load_params([f"paths.artifacts={out}"])["train_vae"]["loop"]["max_steps"]
    assert proc.stdout.startswith("usage: train_vae ") and f"\n  train_vae.loop.max_steps = {steps}\n" in proc.stdout
    proc, _ = run_stage("stages.train_vae", "train_vae.lr=1e-3", "scale=smoke", "--cfg", f"paths.artifacts={out}")
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr
    printed = yaml.safe_load(proc.stdout)
    assert printed == restrict_params(load_params(["train_vae.lr=1e-3", "scale=smoke", f"paths.artifacts={out}"]),
                                      train_vae.STAGE.params)
    assert printed["train_vae"]["lr"] == 0.001 and printed["train_vae"]["loop"]["max_steps"] == 50
    assert not out.exists()  # nothing written, no run started
    proc, _ = run_stage("stages.evaluate", "--help")
    assert proc.returncode == 0 and "usage: python -m stages.evaluate <real | baselines" in proc.stdout


@pytest.mark.slow
def test_cfg_of_a_bad_config_prints_it_and_fails():
    proc, _ = run_stage("stages.train_vae", "train_vae.lr=abc", "--cfg")
    assert proc.returncode == 1 and "  lr: abc\n" in proc.stdout
    assert proc.stderr.splitlines() == ["train_vae: train_vae.lr: expected a number > 0.0, got 'abc'"]


@pytest.mark.slow
def test_unknown_option_is_one_line():
    proc, _ = run_stage("stages.report", "--cfgg")
    assert proc.returncode == 1
    assert proc.stderr.splitlines() == [
        "report: unknown option(s) ['--cfgg']; options are --help and --cfg, the rest is key=value"]


# --------------------------------------------------------------------------- helpers


STAGES = ("make_dataset", "extract_features", "train_evaluator", "train_vae", "train_mld", "distill_lcm",
          "train_controlnet", "train_emdm", "train_emdm_action", "train_motiondiffuse", "report")


def stage_entries() -> list[tuple[str, Callable[[list[str]], None]]]:
    """(name, main(argv)) of every stage module with a params command line (evaluate takes a family first)."""
    entries = []
    for name in STAGES:
        module = importlib.import_module(f"stages.{name}")
        entries.append((name, functools.partial(stage_main, module.STAGE) if hasattr(module, "STAGE") else module.main))
    return entries


def stage_params(name: str) -> dict:
    """params.yaml restricted to the keys stage ``name`` reads."""
    module = importlib.import_module(f"stages.{name}")
    keys = module.STAGE.params if hasattr(module, "STAGE") else module.PARAMS
    return restrict_params(read_params(PARAMS_PATH), keys)


def test_the_evaluation_protocol_refuses_counts_it_would_divide_by_or_draw_from():
    """Each of these passed the checks and failed after the whole evaluation (a division by zero, an empty
    batch), or dropped MultiModality without a word (mm_repeats <= mm_times)."""
    from pipelines.evaluation import check_protocol

    cfg = dict(load_params([])["evaluate"], timing_sentences=0, mm_texts=0, diversity_times=0, mm_repeats=5)
    with pytest.raises(ConfigError) as err, every_problem():
        check_protocol(cfg)
    assert str(err.value).splitlines() == [
        "evaluate.diversity_times: expected an integer >= 1, got 0",
        "evaluate.mm_texts: expected an integer >= 1, got 0",
        "evaluate.timing_sentences: expected an integer >= 1, got 0",
        "evaluate.mm_repeats: expected 0 (no MultiModality) or more than evaluate.mm_times (10), got 5",
    ]
    check_protocol(dict(load_params([])["evaluate"], mm_repeats=0))  # 0: no MultiModality, as documented
    for scale in ("smoke", "paper"):
        check_protocol(load_params([f"scale={scale}"])["evaluate"])
