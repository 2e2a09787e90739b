"""Evaluation protocol and baselines, with a stub evaluator whose embeddings are known exactly.

Each item's motion is constant over time and carries a random code in its RIC dims; its caption
is the token ``c<k>``; the stub embeds a caption as its code and a motion as its first frame's
code. So Real and a perfect Retrieval must reach R-precision 1, Random must sit at chance.
The code also sets the heights of joints 1-3 (the other joints stand on the floor, y = 0), so
the physical measures have known values. Timings use a fake clock, never the wall clock.
"""

import numpy as np
import pytest

from data.motion_dataset import pad_motions
from data.skeleton import HUMANML3D, KIT
from data.store import StoredItem
from models.generator import ControlledGenerator, ControlSpec, Generator, Hint, TextBatch
from pipelines import evaluation
from pipelines.baselines import RandomMotion, Retrieval
from pipelines.evaluation import (
    EvalConfig,
    aggregate,
    crop_lengths,
    draw,
    evaluate,
    load_references,
    physical,
    references,
    save_references,
    time_generator,
)

D, E, CODE = HUMANML3D.feature_dim, 8, slice(4, 12)
CODE_HEIGHTS = [1, 4, 7]  # code entries that are RIC y of joints 1, 2, 3 (dims 5, 8, 11)


def _items(codes: np.ndarray, rng: np.random.Generator, prefix: str) -> list[StoredItem]:
    items = []
    for k, code in enumerate(codes):
        length = int(rng.integers(40, 120))
        features = np.zeros((length, D), np.float32)
        features[:, 3] = 0.9  # root height: a standing body
        features[:, CODE] = code
        pooled = (code / np.linalg.norm(code)).astype(np.float32)[None]
        items.append(StoredItem(f"{prefix}{k}", f"{prefix}{k}", None, 0, features, [f"c{k}"], [[f"c{k}/NOUN"]],
                                pooled, [np.zeros((3, 4), np.float16)]))
    return items


class StubEmbedder:
    def __init__(self, codes: np.ndarray) -> None:
        self.codes = codes

    def texts(self, tokens):
        return np.stack([self.codes[int(t[0].split("/")[0][1:])] for t in tokens])

    def motions(self, raw, lengths):
        return raw[:, 0, CODE].astype(np.float64)


@pytest.fixture(scope="module")
def world():
    rng = np.random.default_rng(0)
    codes = rng.standard_normal((96, E)) * 3
    test = _items(codes, np.random.default_rng(1), "t")
    train = _items(codes, np.random.default_rng(1), "r")  # every test item has an identical training twin
    return codes, test, train


CFG = EvalConfig(replications=3, diversity_times=50, mm_texts=10, mm_repeats=12, mm_times=10, timing_sentences=3)


class FakeClock:
    """Stands in for the ``time`` module in pipelines.evaluation: ``perf_counter`` reads ``now``,
    which moves only by ``tick`` per read and by what a :class:`TimedGenerator` spends."""

    def __init__(self, tick: float = 0.0) -> None:
        self.now, self.tick = 0.0, tick

    def perf_counter(self) -> float:
        self.now += self.tick
        return self.now


def expected_penetration_mm(codes: np.ndarray) -> float:
    """Mean depth (mm) of each item's lowest joint below the floor, beyond the 5 mm tolerance."""
    depth = np.maximum(0.0, -codes[:, CODE_HEIGHTS].min(axis=1))
    return 1000.0 * float(np.where(depth > 0.005, depth, 0.0).mean())


def test_real_and_perfect_retrieval_reach_one_random_sits_at_chance(world, monkeypatch):
    codes, test, train = world
    monkeypatch.setattr(evaluation, "time", FakeClock(tick=0.25))  # every timed sample() "takes" 0.25 s
    mean, std = np.zeros(D, np.float32), np.ones(D, np.float32)
    gens = [RandomMotion(train, mean, std), Retrieval(train, mean, std)]
    assert all(isinstance(g, Generator) for g in gens)
    embedder = StubEmbedder(codes)
    table = evaluate(references(test, embedder, CFG), test, mean, std, embedder, HUMANML3D, CFG, gens, real=True)
    assert table["Real"]["R_precision_top1"] == 1.0 and table["Real"]["MM_Dist"] == pytest.approx(0.0, abs=1e-5)
    assert table["Retrieval"]["R_precision_top3"] == 1.0
    assert table["Retrieval"]["FID"] == pytest.approx(table["Real"]["FID"], abs=1e-6)
    assert abs(table["Random"]["R_precision_top3"] - 3 / 32) < 0.1
    assert table["Random"]["FID"] > 1.0
    assert table["Random"]["MultiModality"] > 1.0  # random motions differ
    # metrics that do not apply are absent, never faked
    assert "MultiModality" not in table["Real"] and "MultiModality" not in table["Retrieval"]
    assert "AITS_s" not in table["Real"]
    assert table["Retrieval"]["AITS_s"] == table["Random"]["AITS_s"] == 0.25
    assert table["Retrieval"]["NFE"] == table["Random"]["NFE"] == 0
    assert table["Real"]["R_precision_top1_ci"] == 0.0
    # every replication draws all 96 items, so the physical measures are the items' mean, with CI 0
    assert expected_penetration_mm(codes) > 100.0  # the codes do put most bodies below the floor
    for row in ("Real", "Retrieval"):  # Retrieval answers with each item's identical training twin
        assert table[row]["penetration_mm"] == pytest.approx(expected_penetration_mm(codes), rel=1e-5)
        assert table[row]["penetration_mm_ci"] == pytest.approx(0.0, abs=1e-6)
        assert table[row]["floating_mm"] == 0.0  # the lowest joint is never above the floor
        assert table[row]["skating_ratio"] == 0.0  # nothing moves


def test_physical_measures_the_joints_recovered_from_valid_frames():
    """Known depths and heights through recover_from_ric; frames past each length are ignored."""
    raw = np.zeros((2, 12, D), np.float32)
    raw[:, :, 3] = 0.9  # root height
    raw[0, :5, 5] = -0.02  # motion A, frames 0-4 of 10: joint 1 is 2 cm below the floor (RIC y)
    raw[1, :, 3] = 0.1  # motion B, 8 frames: the whole body 10 cm above the floor...
    raw[1, :, 5:66:3] = 0.1  # ...every RIC y too
    raw[0, 10:, 3:66] = -1.0  # padding: 1 m below the floor, must not count
    raw[1, 8:, 3:66] = -1.0
    out = physical(raw, np.array([10, 8]), HUMANML3D)
    assert out["penetration_mm"] == pytest.approx((20.0 * 5 / 10 + 0.0) / 2, rel=1e-5)  # mean over motions
    assert out["floating_mm"] == pytest.approx((0.0 + 100.0) / 2, rel=1e-5)
    assert out["skating_ratio"] == 0.0


class TimedGenerator:
    """Each ``sample`` call is recorded and takes a known time on ``clock``: 100 s for the first
    (the warm-up, which must not be timed), then 0.5 s + 10 ms per frame."""

    name, nfe, stochastic = "Timed", 0, False

    def __init__(self, clock: FakeClock) -> None:
        self.clock, self.calls = clock, []

    def sample(self, text: TextBatch, lengths: np.ndarray, seed: int) -> np.ndarray:
        self.clock.now += 0.5 + 0.01 * int(lengths.sum()) if self.calls else 100.0
        self.calls.append((list(text.texts), lengths.tolist(), seed))
        return np.zeros((len(lengths), int(lengths.max()), D), np.float32)


def test_aits_times_each_caption_alone_after_an_untimed_warm_up(world, monkeypatch):
    _, test, _ = world
    clock = FakeClock()
    monkeypatch.setattr(evaluation, "time", clock)
    d = draw(test, np.random.default_rng(4), 4)
    gen = TimedGenerator(clock)
    out = time_generator(gen, d, 5)
    warm_up, *timed = gen.calls
    assert warm_up == ([d.text.texts[0]], [int(d.lengths[0])], 0)
    assert timed == [([d.text.texts[k]], [int(d.lengths[k])], k) for k in range(5)]  # batch 1, seed k
    frames = d.lengths[:5].astype(np.float64)
    assert out["AITS_s"] == pytest.approx(float(np.mean(0.5 + 0.01 * frames)))
    assert out["ms_per_frame"] == pytest.approx(1000.0 * float(np.sum(0.5 + 0.01 * frames) / np.sum(frames)))
    capped = TimedGenerator(clock)
    time_generator(capped, d, 1000)
    assert len(capped.calls) == 1 + len(d.lengths)  # at most one timed call per caption of the draw


def test_aits_time_budget_stops_after_three_captions_at_the_earliest(world, monkeypatch):
    _, test, _ = world
    clock = FakeClock()
    monkeypatch.setattr(evaluation, "time", clock)
    d = draw(test, np.random.default_rng(4), 4)
    per_call = 0.5 + 0.01 * d.lengths[:10].astype(np.float64)
    tiny = TimedGenerator(clock)  # any budget below one caption's time still times three captions
    out = time_generator(tiny, d, 10, budget_s=1e-6)
    assert len(tiny.calls) == 1 + evaluation.MIN_TIMED_SENTENCES
    assert out["AITS_s"] == pytest.approx(float(np.mean(per_call[:3])))
    budget = float(per_call[:5].sum()) - 1e-9  # reached after the fifth caption
    assert len(_timed_calls(clock, d, budget)) == 1 + 5
    assert len(_timed_calls(clock, d, None)) == 1 + 10  # no budget: all n captions


def _timed_calls(clock, d, budget):
    gen = TimedGenerator(clock)
    time_generator(gen, d, 10, budget_s=budget)
    return gen.calls


def test_crop_lengths_follow_the_reference_rounding():
    rng = np.random.default_rng(1)
    lengths = np.full(30000, 103)
    crops = crop_lengths(lengths, rng)
    assert set(np.unique(crops)) == {96, 100}
    assert np.mean(crops == 100) == pytest.approx(2 / 3, abs=0.01)


def test_draw_crops_real_windows_of_the_chosen_items(world):
    _, test, _ = world
    d = draw(test, np.random.default_rng(2), 4)
    for b, length in enumerate(d.lengths):
        k = int(d.text.texts[b][1:])
        assert length % 4 == 0 and length <= test[k].length
        np.testing.assert_array_equal(d.real[b, :length], test[k].features[:length])  # constant frames
        assert not d.real[b, length:].any()


def test_retrieval_answers_with_the_nearest_caption_motion(world):
    codes, _, train = world
    gen = Retrieval(train, np.zeros(D, np.float32), np.ones(D, np.float32))
    query = TextBatch(["x", "y"], np.stack([train[5].text_pooled[0], train[9].text_pooled[0]]), [None, None])
    out = gen.sample(query, np.array([40, 32]), seed=0)
    np.testing.assert_allclose(out[0, :40, CODE], np.broadcast_to(codes[5], (40, E)), rtol=1e-6)
    np.testing.assert_allclose(out[1, :32, CODE], np.broadcast_to(codes[9], (32, E)), rtol=1e-6)
    assert not out[1, 32:].any()


def test_random_motion_is_seeded_and_respects_lengths(world):
    _, _, train = world
    gen = RandomMotion(train, np.zeros(D, np.float32), np.ones(D, np.float32))
    text = TextBatch(["a"] * 4, np.zeros((4, E), np.float32), [None] * 4)
    a, b = gen.sample(text, np.array([40, 44, 48, 52]), 7), gen.sample(text, np.array([40, 44, 48, 52]), 7)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, gen.sample(text, np.array([40, 44, 48, 52]), 8))
    with pytest.raises(ValueError, match="no training motion"):
        gen.sample(text.select([0]), np.array([500]), 0)


def test_aggregate_gives_mean_and_ci():
    reps = [{"Real": {"FID": 1.0}}, {"Real": {"FID": 3.0}}]
    table = aggregate(reps)
    assert table["Real"]["FID"] == 2.0
    assert table["Real"]["FID_ci"] == pytest.approx(1.96 * 1.0 / np.sqrt(2))


def test_aggregate_averages_a_metric_over_the_replications_that_have_it():
    reps = [{"VAE": {"MPJPE_mm": 40.0, "turn_kept": 0.5}}, {"VAE": {"MPJPE_mm": 42.0}},
            {"VAE": {"MPJPE_mm": 44.0, "turn_kept": 1.0}}]
    table = aggregate(reps)
    assert table["VAE"]["MPJPE_mm"] == 42.0 and table["VAE"]["turn_kept"] == 0.75
    assert table["VAE"]["turn_kept_ci"] == pytest.approx(1.96 * np.std([0.5, 1.0]) / np.sqrt(2))
    assert "turn_kept" not in aggregate([{"VAE": {"MPJPE_mm": 40.0}}])["VAE"]


def test_pad_motions_zero_fills():
    out = pad_motions([np.ones((3, 2)), np.ones((5, 2))], np.array([3, 5]))
    assert out.shape == (2, 5, 2) and out[0, 3:].sum() == 0 and out.sum() == 16


def test_a_group_larger_than_the_split_is_a_clear_error(world, tmp_path):
    codes, test, _ = world
    expected = (f"evaluate.group_size={CFG.group_size} is larger than the {{split}} split (10 items): "
                "R-precision needs one full group; set a smaller evaluate.group_size")
    with pytest.raises(ValueError) as err:
        references(test[:10], StubEmbedder(codes), CFG)
    assert str(err.value) == expected.format(split="test")
    with pytest.raises(ValueError) as err:
        references(test[:10], StubEmbedder(codes), CFG, split="val")
    assert str(err.value) == expected.format(split="val")
    path = tmp_path / "references.npz"
    save_references(path, references(test, StubEmbedder(codes), CFG))
    with pytest.raises(ValueError) as err:  # saved references read back for fewer items than a group
        load_references(path, test[:10], CFG)
    assert str(err.value) == expected.format(split="test")


def test_mpjpe_is_root_aligned_and_in_millimetres():
    from pipelines.evaluation import mpjpe_mm

    rng = np.random.default_rng(3)
    real = rng.standard_normal((2, 50, D)).astype(np.float32) * 0.05
    moved = real.copy()
    moved[..., 1:3] += 0.3  # different root velocity: the whole body drifts, poses are unchanged
    lengths = np.array([50, 30])
    assert mpjpe_mm(real, moved, lengths, HUMANML3D) == pytest.approx(0.0, abs=1e-3)
    bent = real.copy()
    bent[..., 4:7] += 0.01  # joint 1 shifted by 1 cm in every valid frame (RIC positions)
    assert mpjpe_mm(real, bent, lengths, HUMANML3D) == pytest.approx(10 * np.sqrt(3) / 22, rel=1e-3)  # 1 of 22
    # KIT-ML is stored in millimetres: a 10-unit shift of one of its 21 joints is 10 mm, not 10 m
    kit_dim = 12 * KIT.joints_num - 1
    real, bent = real[..., :kit_dim], bent[..., :kit_dim] * 1000.0
    real = real * 1000.0
    assert mpjpe_mm(real, bent, lengths, KIT) == pytest.approx(10 * np.sqrt(3) / 21, rel=1e-3)


def test_reconstruction_detail_is_humanml3d_only():
    """The detail measures read HumanML3D's joint indices in metres: KIT-ML rows get none (they crashed on
    joint 21), HumanML3D rows get every column."""
    from pipelines.evaluation import detail

    rng = np.random.default_rng(4)
    lengths = np.array([60, 40])
    kit = rng.standard_normal((2, 60, 12 * KIT.joints_num - 1)).astype(np.float32)
    assert detail(kit, kit, lengths, KIT) == {}
    hml = rng.standard_normal((2, 60, D)).astype(np.float32) * 0.05
    assert {"path_err_m", "turn_kept"} <= set(detail(hml, hml, lengths, HUMANML3D))
    assert detail(hml, hml, lengths, HUMANML3D)["path_err_m"] == 0.0


class DriftingController:
    """A controlled generator whose pelvis drifts ``speed`` m/frame along x from the origin: against the
    world's motions (pelvis still at the origin) its error on frame t is exactly ``speed * t``."""

    nfe, stochastic = 1, False

    def __init__(self, name: str, speed: float, density: str) -> None:
        self.name, self.speed, self.control, self.hints = name, speed, ControlSpec(density), []

    def sample(self, text: TextBatch, lengths: np.ndarray, seed: int, hint: Hint) -> np.ndarray:
        self.hints.append(hint)
        out = np.zeros((len(lengths), int(lengths.max()), D), np.float32)
        for b, n in enumerate(lengths):
            out[b, :n, 3] = 0.9
            out[b, :n, 1] = self.speed  # root x velocity in the (unturned) facing frame
        return out


def test_controlled_rows_are_scored_on_their_hints_keyframes(world):
    codes, test, _ = world
    mean, std = np.zeros(D, np.float32), np.ones(D, np.float32)
    embedder = StubEmbedder(codes)
    refs = references(test, embedder, CFG)
    still, drifting = DriftingController("Still", 0.0, "100%"), DriftingController("Drift", 0.01, "100%")
    sparse = DriftingController("Drift-5f", 0.01, "5")
    assert isinstance(still, ControlledGenerator)
    table = evaluate(refs, test, mean, std, embedder, HUMANML3D, CFG, [still, drifting, sparse])
    assert table["Still"]["avg_err_m"] == pytest.approx(0.0, abs=1e-6) and table["Still"]["traj_err_20cm"] == 0.0
    expected = np.mean([np.mean(0.01 * (ref.draw.lengths - 1) / 2) for ref in refs])  # mean of 0.01 t over t < L
    assert table["Drift"]["avg_err_m"] == pytest.approx(expected, rel=1e-4)
    assert 0 < table["Drift"]["loc_err_50cm"] < table["Drift"]["traj_err_50cm"] <= 1  # only late frames miss
    for first, second in zip(still.hints[:3], drifting.hints[:3], strict=True):  # one density, the same hints
        assert np.array_equal(first.mask, second.mask) and np.array_equal(first.joints, second.joints)
    for hint, ref in zip(sparse.hints[:3], refs, strict=True):
        assert hint.mask[:, :, 0].sum(1).tolist() == [min(5, n) for n in ref.draw.lengths]
        assert not hint.mask[:, :, 1:].any()  # the pelvis only
        assert np.allclose(hint.joints[:, :, 0, 1][hint.mask[:, :, 0]], 0.9)  # the real crops' pelvis height
    assert "avg_err_m" in table["Drift-5f"] and "AITS_s" in table["Drift-5f"]


def test_a_bad_references_file_is_one_line_naming_it(world, tmp_path):
    """Truncated, missing an array, holding objects, or arrays that do not fit: a ValueError naming the file
    and how to write it again (they came as tracebacks or without the file); never unpickled."""
    codes, test, _ = world
    good = tmp_path / "references.npz"
    save_references(good, references(test, StubEmbedder(codes), CFG))
    assert len(load_references(good, test, CFG)) == CFG.replications
    saved = dict(np.load(good))
    cases = {"truncated": None, "no mu": {k: v for k, v in saved.items() if k != "ref_mu_0"},
             "objects": {**saved, "ref_mu_0": np.array([{"x": 1}], dtype=object)},
             "shapes": {**saved, "ref_mu_0": saved["ref_mu_0"][:3]}}
    for name, arrays in cases.items():
        path = tmp_path / f"{name}.npz"
        if arrays is None:
            path.write_bytes(good.read_bytes()[:100])
        else:
            np.savez(path, **arrays)
        with pytest.raises(ValueError) as err:
            load_references(path, test, CFG)
        message = str(err.value)
        assert message.startswith(f"{path}: ") and message.endswith("; run `dvc repro eval_real` to write it again"), \
            (name, message)


def test_a_row_whose_motions_are_not_finite_is_named():
    """NaN motions (an extreme guidance scale) failed far away, in the FID's matrix square root."""
    from pipelines.evaluation import sample_rows

    class NaNGenerator:
        name, nfe, stochastic = "Overdriven", 1, True

        def sample(self, text: TextBatch, lengths: np.ndarray, seed: int) -> np.ndarray:
            return np.full((len(lengths), int(lengths.max()), D), np.nan, np.float32)

    text = TextBatch(["a person walks"], np.zeros((1, 4), np.float32), [np.zeros((2, 4), np.float32)])
    with pytest.raises(ValueError, match=r"^row Overdriven: its sampled motions are not finite"):
        sample_rows(NaNGenerator(), text, np.array([8]), 0, None, [0])


def test_a_missing_model_names_the_dvc_stage_that_writes_it(tmp_path):
    """The recogniser and movement encoder are written by ``train_evaluator``: no stage bears their names."""
    from pipelines.registry import EvalContext

    ctx = EvalContext({}, tmp_path, tmp_path / "features")
    for run, stage in (("train_evaluator_recogniser", "train_evaluator"), ("train_mld", "train_mld")):
        with pytest.raises(FileNotFoundError, match=rf"{run}/model.pt is missing: run `dvc repro {stage}` first"):
            ctx.trained(run)
