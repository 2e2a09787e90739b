"""Configuration: committed params.yaml == composed conf/ defaults; overrides and their errors."""

import pytest

from pipelines.config import (
    PARAMS_PATH,
    ConfigError,
    apply_overrides,
    compose_params,
    load_params,
    main,
    read_params,
)


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
    lcm = paper["distill_lcm"]  # MotionLCM V2's distillation settings
    assert (tuple(lcm["w_range"]), lcm["ema_decay"], lcm["num_ddim_steps"], lcm["distance"], lcm["huber_c"]) == (
        (5.0, 15.0), 0.95, 10, "huber", 0.5)
    assert (lcm["lr"], lcm["loop"]["batch_size"], paper["sample"]["motionlcm_guidance"]) == (2e-4, 128, 8.0)


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
