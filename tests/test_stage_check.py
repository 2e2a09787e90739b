"""benchmarks/stage_check.py: its scratch folders and what it reports from a stage's log."""

from pathlib import Path

from tests.bench_module import load_benchmark

stage_check = load_benchmark("stage_check")


def test_scratch_folder_links_all_but_the_fresh_outputs(tmp_path: Path) -> None:
    artifacts = tmp_path / "artifacts"
    for name in ("features", "train_vae", "train_mld"):
        (artifacts / name).mkdir(parents=True)
        (artifacts / name / "model.pt").write_text(name)
    folder = tmp_path / "scratch" / "train_mld"
    folder.mkdir(parents=True)
    (folder / "stale.log").write_text("from an earlier check")
    assert stage_check.scratch_folder(folder, artifacts, {"train_mld"}) == folder
    assert sorted(p.name for p in folder.iterdir()) == ["features", "train_vae"]
    assert (folder / "train_vae").is_symlink() and (folder / "train_vae" / "model.pt").read_text() == "train_vae"
    assert (artifacts / "train_mld" / "model.pt").read_text() == "train_mld"  # the source is untouched


def test_first_error_is_the_first_line_naming_an_exception() -> None:
    log = ("[train_mld] step 1/4\n"
           "(RayTrainWorker pid=7) AttributeError: 'DistributedDataParallel' object has no attribute 'null_text'\n"
           "ray.exceptions.RayTaskError: the worker failed\n")
    assert stage_check.first_error(log) == (
        "(RayTrainWorker pid=7) AttributeError: 'DistributedDataParallel' object has no attribute 'null_text'")
    assert stage_check.first_error("[train_vae] step 4/4 loss=0.1\ntrain_vae: final loss 0.1\n") == ""
