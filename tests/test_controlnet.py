"""MotionLCM's ControlNet (models/controlnet.py) and its hints (data/control.py) on tiny networks."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch
from tolerance import float32_atol
from torch import nn

from data.control import evaluation_mask, joint_ids, keyframe_count, training_mask
from data.features import recover_from_ric
from data.skeleton import HUMANML3D, KIT
from models.controlnet import (
    ControlConfig,
    ControlledStudent,
    MotionControlNet,
    control_loss,
    controlnet_loss,
    decode_joints,
    refine_noise,
    training_timesteps,
)
from models.diffusion import NoiseSchedule
from models.generator import Hint
from models.mld import MLDConfig, MLDDenoiser
from models.motionlcm import guidance_embedding, motionlcm_latents
from models.vae import MotionVAE
from pipelines.config import ConfigError, load_params, restrict_params
from stages import train_controlnet

pytestmark = pytest.mark.usefixtures("one_thread")

J, D = 22, 263
STUDENT = MLDConfig(latent_tokens=2, latent_dim=8, hidden_dim=16, text_dim=6, layers=3, heads=2, ff_dim=16,
                    dropout=0.0, time_freq_dim=16, word_tokens="cross_attention", token_dim=5, time_cond_dim=256)
SCHEDULE = NoiseSchedule.from_name("scaled_linear", 1000, beta_start=0.00085, beta_end=0.012)


def control_config(**overrides) -> ControlConfig:
    return ControlConfig(joints_num=J, hint_mean=[0.0] * 3 * J, hint_std=[1.0] * 3 * J, dim=16, layers=1, heads=2,
                         ff_dim=16, **overrides)


def student() -> MLDDenoiser:
    torch.manual_seed(0)
    net = MLDDenoiser(STUDENT)
    with torch.no_grad():  # outputs that are not ~0 everywhere
        for p in net.parameters():
            p.add_(0.2 * torch.randn_like(p))
    return net.eval()


def batch(b: int = 3, frames: int = 10) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(1)
    mask = torch.zeros(b, frames, J, dtype=torch.bool)
    mask[:, ::2, 0] = True
    return {"z_t": torch.randn(b, 2, 8, generator=g), "t": torch.tensor([799, 99, 499][:b]),
            "text_emb": torch.randn(b, 6, generator=g), "hint": torch.randn(b, frames, J, 3, generator=g),
            "mask": mask, "time_cond": guidance_embedding(torch.full((b,), 1.5)),
            "text_tokens": torch.randn(b, 4, 5, generator=g), "text_mask": torch.ones(b, 4, dtype=torch.bool)}


def randomise(module: torch.nn.Module, seed: int = 2) -> None:
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.parameters():
            p.add_(0.3 * torch.randn(p.shape, generator=g))


def words(x: dict) -> dict:
    return {k: x[k] for k in ("time_cond", "text_tokens", "text_mask")}


def test_fresh_controlnet_leaves_the_student_unchanged():
    """Zero-initialised projections: at initialisation the controlled output is the student's, for any hint."""
    base = student()
    controlnet = MotionControlNet(base, control_config())
    x = batch()
    plain = base(x["z_t"], x["t"], x["text_emb"], **words(x))
    controlled = ControlledStudent(base, controlnet, x["hint"], x["mask"])(x["z_t"], x["t"], x["text_emb"], **words(x))
    assert torch.equal(plain, controlled)
    randomise(controlnet)  # trained weights: the hint now changes the output
    controlled = ControlledStudent(base, controlnet, x["hint"], x["mask"])(x["z_t"], x["t"], x["text_emb"], **words(x))
    assert (controlled - plain).abs().max() > 1e-3


def test_controlnet_copies_the_student_and_only_it_trains():
    base = student()
    controlnet = MotionControlNet(base, control_config())
    copied = controlnet.copy.state_dict()
    for key, value in base.state_dict().items():
        if key in copied:
            assert torch.equal(copied[key], value), key
    assert all(p.requires_grad for p in controlnet.parameters())
    assert "transformer.norm.weight" not in copied and "latent_out.weight" not in copied  # unused by a ControlNet


@pytest.mark.parametrize("patch_frames", [1, 4])  # 4: the 10 frames padded to 3 tokens of 4
def test_encoder_ignores_uncontrolled_entries(patch_frames: int):
    """Hint values outside the mask never reach the ControlNet; the mask itself does."""
    base = student()
    controlnet = MotionControlNet(base, control_config(patch_frames=patch_frames))
    randomise(controlnet)
    x = batch()
    out = controlnet.encoder(x["hint"], x["mask"])
    other = torch.where(x["mask"][..., None], x["hint"], torch.randn_like(x["hint"]) * 5)
    assert torch.allclose(controlnet.encoder(other, x["mask"]), out, atol=float32_atol(out))  # tests/tolerance.py
    missing = torch.where(x["mask"][..., None], x["hint"], float("nan"))  # a hint known on its keyframes only
    assert torch.allclose(controlnet.encoder(missing, x["mask"]), out, atol=float32_atol(out))
    fewer = x["mask"].clone()
    fewer[:, 4:] = False
    assert not torch.allclose(controlnet.encoder(x["hint"], fewer), out, atol=1e-4)
    first = controlnet.encoder(x["hint"][:, :4], fewer[:, :4])  # tokens with no controlled frame are not attended
    assert torch.allclose(controlnet.encoder(x["hint"], fewer), first, atol=float32_atol(first))
    nothing = controlnet.encoder(x["hint"], torch.zeros_like(x["mask"]))  # only the global tokens: finite
    assert torch.isfinite(nothing).all()
    # uncontrolled frames appended (12 frames: 3 whole tokens of 4) change nothing, whatever they hold
    longer = torch.cat([x["hint"], torch.full_like(x["hint"][:, :2], float("nan"))], dim=1)
    longer_mask = torch.cat([x["mask"], torch.zeros_like(x["mask"][:, :2])], dim=1)
    assert torch.allclose(controlnet.encoder(longer, longer_mask), out, atol=float32_atol(out))
    assert controlnet.encoder.input.in_features == (3 * J if patch_frames == 1 else patch_frames * 4 * J)


def test_patched_encoder_tells_a_controlled_frame_at_the_mean_from_an_uncontrolled_one():
    """With several frames per token a masked position reads 0, as a controlled one at the mean does:
    the mask bits beside the positions keep the two apart (models/controlnet.py)."""
    base = student()
    controlnet = MotionControlNet(base, control_config(patch_frames=4))
    randomise(controlnet)
    x = batch()
    at_mean = torch.where(x["mask"][..., None], x["hint"], 0.0)  # hint_mean is 0: uncontrolled entries at the mean
    mask = x["mask"].clone()
    out = controlnet.encoder(at_mean, mask)
    mask[:, 1, 0] = True  # frame 1 shares a token with controlled frames 0 and 2, its hint exactly at the mean
    assert not torch.allclose(controlnet.encoder(at_mean, mask), out, atol=1e-4)


def test_control_loss_known_values():
    joints = torch.zeros(2, 4, J, 3)
    hint = joints.clone()
    mask = torch.zeros(2, 4, J, dtype=torch.bool)
    mask[0, 1, 0] = mask[1, 3, 0] = True
    assert control_loss(joints, hint, mask) == 0
    hint[0, 1, 0] = torch.tensor([0.3, 0.0, 0.4])  # squared error 0.25 over 2 entries x 3 axes
    hint[:, :, 5] = float("nan")  # uncontrolled entries: ignored, even NaN
    assert control_loss(joints, hint, mask).item() == pytest.approx(0.25 / 6)
    assert control_loss(joints, hint, torch.zeros_like(mask)) == 0


def test_keyframe_counts_and_evaluation_masks():
    assert [keyframe_count(120, d) for d in ("100%", "25%", "5", "2", "1")] == [120, 30, 5, 2, 1]
    assert keyframe_count(3, "5") == 3 and keyframe_count(2, "25%") == 1
    assert keyframe_count(199, "25%") == 49  # rounded down, as MotionLCM's int(199 * 25 / 100)
    for bad in ("0%", "150%", "many", "0"):
        with pytest.raises(ValueError, match="control density"):
            keyframe_count(10, bad)
    lengths = np.array([40, 17, 80])
    for density, counts in (("100%", [40, 17, 80]), ("25%", [10, 4, 20]), ("5", [5, 5, 5])):  # 17 / 4 -> 4
        mask = evaluation_mask(lengths, 80, J, [0, 21], density, np.random.default_rng(0))
        assert mask.shape == (3, 80, J)
        assert mask[:, :, 0].sum(1).tolist() == counts and np.array_equal(mask[:, :, 0], mask[:, :, 21])
        assert mask.sum() == 2 * sum(counts)
        assert not any(mask[b, n:].any() for b, n in enumerate(lengths))  # padded frames never count
    assert joint_ids(["pelvis", "right_wrist"]) == (0, 21)
    # KIT-ML's ids name the same body points (HumanML3D's ids there were a hip, a toe and out of range)
    kit = joint_ids(["pelvis", "left_foot", "right_foot", "head", "left_wrist", "right_wrist"], KIT.joints_num)
    assert [KIT.joint_names[j] for j in kit] == ["root", "l_toe", "r_toe", "bun", "l_wrist", "r_wrist"]
    assert [HUMANML3D.joint_names[j] for j in joint_ids(["left_foot", "head", "left_wrist"])] == [
        "left_foot", "head", "left_wrist"]
    with pytest.raises(ValueError, match="no control joints for a skeleton of 17 joints"):
        joint_ids(["pelvis"], 17)
    with pytest.raises(ValueError, match="control joints"):
        joint_ids(["tail"])


def test_training_masks_one_joint_and_a_random_density():
    lengths = torch.tensor([30, 2, 60, 1] * 50)
    mask = training_mask(lengths, 60, J, (0, 10, 15), torch.Generator().manual_seed(0))
    joints_used = mask.any(1)  # (B, J)
    assert (joints_used.sum(1) == 1).all() and set(joints_used.nonzero()[:, 1].tolist()) == {0, 10, 15}
    counts = mask.sum((1, 2))
    assert ((counts >= 1) & (counts <= (lengths - 1).clamp(min=1))).all()
    assert counts[lengths == 1].eq(1).all() and counts[lengths == 2].eq(1).all()
    assert counts[lengths == 60].min() < 10 and counts[lengths == 60].max() > 45  # spread over [1, 59]
    valid = torch.arange(60)[None] < lengths[:, None]
    assert not mask[~valid].any()


def tiny_vae() -> MotionVAE:
    torch.manual_seed(3)
    return MotionVAE({"latent_tokens": 2, "latent_dim": 8, "layers": 1, "heads": 2, "ff_dim": 16}).eval()


class ForwardOnly(torch.nn.Module):
    """Exposes only ``forward``, as DistributedDataParallel does (the runner wraps models with it)."""

    def __init__(self, module: torch.nn.Module) -> None:
        super().__init__()
        self.module = module

    def forward(self, *args, **kwargs):
        return self.module(*args, **kwargs)


def test_controlnet_loss_trains_only_the_controlnet_and_weights_the_control_term():
    base, vae = student().requires_grad_(False), tiny_vae().requires_grad_(False)
    controlnet = MotionControlNet(base, control_config())
    randomise(controlnet)
    x = batch(b=2, frames=12)
    lengths = torch.tensor([12, 9])
    mean, std = torch.zeros(D), torch.full((D,), 0.1)
    kwargs = {"mean": mean, "std": std, "w_range": (1.0, 2.0), "text_tokens": x["text_tokens"],
              "text_mask": x["text_mask"]}
    args = (controlnet, base, vae, SCHEDULE, torch.randn(2, 2, 8), x["text_emb"], x["hint"], x["mask"], lengths)
    a = controlnet_loss(*args, control_weight=0.0, generator=torch.Generator().manual_seed(4), **kwargs)
    wrapped = (ForwardOnly(controlnet), *args[1:])
    b = controlnet_loss(*wrapped, control_weight=2.0, generator=torch.Generator().manual_seed(4), **kwargs)
    assert torch.equal(a["latent"], b["latent"]) and torch.equal(a["control"], b["control"])
    assert b["total"].item() == pytest.approx((b["latent"] + 2.0 * b["control"]).item(), rel=1e-6)
    b["total"].backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in controlnet.parameters())
    assert all(p.grad is None for p in (*base.parameters(), *vae.parameters()))


def test_controlnet_loss_never_reads_a_hint_on_padded_frames(monkeypatch: pytest.MonkeyPatch) -> None:
    """A mask entry past a motion's length reaches neither the ControlNet nor the control term: the loss equals
    the loss of the mask cut to the lengths, and the control term sees only valid controlled entries."""
    import models.controlnet as module

    base, vae = student().requires_grad_(False), tiny_vae().requires_grad_(False)
    controlnet = MotionControlNet(base, control_config())
    randomise(controlnet)
    x, lengths = batch(b=2, frames=12), torch.tensor([12, 9])
    assert x["mask"][1, 9:].any()
    seen, real = [], module.control_loss
    monkeypatch.setattr(module, "control_loss", lambda j, h, m: seen.append(m) or real(j, h, m))
    kwargs = {"mean": torch.zeros(D), "std": torch.full((D,), 0.1), "w_range": (1.0, 2.0),
              "text_tokens": x["text_tokens"], "text_mask": x["text_mask"]}
    cut = x["mask"] & (torch.arange(12)[None] < lengths[:, None])[..., None]
    z0 = torch.randn(2, 2, 8, generator=torch.Generator().manual_seed(5))
    with torch.no_grad():
        a = controlnet_loss(controlnet, base, vae, SCHEDULE, z0, x["text_emb"], x["hint"], x["mask"], lengths,
                            generator=torch.Generator().manual_seed(4), **kwargs)
        b = controlnet_loss(controlnet, base, vae, SCHEDULE, z0, x["text_emb"], x["hint"], cut, lengths,
                            generator=torch.Generator().manual_seed(4), **kwargs)
    assert torch.equal(seen[0], cut) and torch.equal(seen[1], cut)
    assert torch.equal(a["total"], b["total"])


def test_training_timesteps_draw_only_and_every_listed_value():
    t = training_timesteps([799, 99], 400, 1000, torch.Generator().manual_seed(0))
    assert t.dtype == torch.long and set(t.tolist()) == {99, 799}
    assert 150 < int((t == 799).sum()) < 250  # uniform over the list
    for bad in ([], [1000], [-1]):
        message = f"timesteps: expected a non-empty list in [0, 1000), got {bad}"
        with pytest.raises(ValueError, match=re.escape(message)):
            training_timesteps(bad, 4, 1000)


def test_controlnet_loss_at_listed_timesteps_equals_the_grid_of_that_point():
    """A one-point solver grid is [999]: ``timesteps=[999]`` must give the same loss, draw for draw; another
    t gives another loss (the list reaches the model)."""
    base, vae = student().requires_grad_(False), tiny_vae().requires_grad_(False)
    controlnet = MotionControlNet(base, control_config())
    randomise(controlnet)
    x = batch(b=2, frames=12)
    kwargs = {"mean": torch.zeros(D), "std": torch.full((D,), 0.1), "w_range": (1.0, 2.0), "control_weight": 1.0,
              "text_tokens": x["text_tokens"], "text_mask": x["text_mask"]}
    args = (controlnet, base, vae, SCHEDULE, torch.randn(2, 2, 8), x["text_emb"], x["hint"], x["mask"],
            torch.tensor([12, 9]))

    def loss(**extra) -> torch.Tensor:
        with torch.no_grad():
            return controlnet_loss(*args, generator=torch.Generator().manual_seed(4), **kwargs, **extra)["total"]

    assert torch.equal(loss(num_ddim_steps=1), loss(timesteps=[999]))
    assert not torch.allclose(loss(timesteps=[999]), loss(timesteps=[99]))


def test_text_dropout_replaces_the_caption_by_the_unconditional_one():
    """At dropout 1 every sample gets the student's null embedding and no word tokens, draw for draw; at 0
    nothing changes and no random number is drawn (the default keeps the paper's training)."""
    base, vae = student().requires_grad_(False), tiny_vae().requires_grad_(False)
    controlnet = MotionControlNet(base, control_config())
    randomise(controlnet)
    x = batch(b=2, frames=12)
    args = (controlnet, base, vae, SCHEDULE, torch.randn(2, 2, 8))
    tail = (x["hint"], x["mask"], torch.tensor([12, 9]))
    kwargs = {"mean": torch.zeros(D), "std": torch.full((D,), 0.1), "w_range": (1.0, 2.0), "control_weight": 1.0,
              "text_tokens": x["text_tokens"]}

    def loss(text_emb: torch.Tensor, text_mask: torch.Tensor, **extra) -> torch.Tensor:
        with torch.no_grad():
            return controlnet_loss(*args, text_emb, *tail, generator=torch.Generator().manual_seed(4),
                                   text_mask=text_mask, **kwargs, **extra)["total"]

    null, no_words = base.null_text_like(x["text_emb"]), torch.zeros_like(x["text_mask"])
    assert torch.equal(loss(x["text_emb"], x["text_mask"], text_dropout=1.0), loss(null, no_words))
    assert torch.equal(loss(x["text_emb"], x["text_mask"], text_dropout=0.0), loss(x["text_emb"], x["text_mask"]))
    assert not torch.allclose(loss(null, no_words), loss(x["text_emb"], x["text_mask"]))


def test_decode_joints_matches_the_numpy_recovery():
    vae = tiny_vae()
    z = torch.randn(2, 2, 8)
    lengths = torch.tensor([10, 7])
    mean, std = torch.randn(D) * 0.1, torch.rand(D) + 0.5
    joints = decode_joints(vae, z, lengths, 10, mean, std, latent_scale=2.0)
    features = (vae.decode(2.0 * z, lengths, 10) * std + mean).detach().numpy()
    assert np.allclose(joints.detach().numpy(), recover_from_ric(features.astype(np.float64), J), atol=1e-4)


def test_noise_refinement_pulls_the_decoded_joints_to_the_hint_and_keeps_the_noise_norm():
    vae = tiny_vae()  # trainable weights: the refinement must still leave them without gradients
    lengths = torch.tensor([12, 12])
    mean, std = torch.zeros(D), torch.full((D,), 0.1)
    target = decode_joints(vae, torch.randn(2, 2, 8), lengths, 12, mean, std, 1.0).detach()
    mask = torch.zeros(2, 12, J, dtype=torch.bool)
    mask[:, :, 0] = True
    mixer = nn.Linear(8, 8)  # a trainable stand-in for the one-step sampler
    x_T = torch.randn(2, 2, 8, generator=torch.Generator().manual_seed(1))

    def refine(denoise, hint_mask=mask, lens=lengths, steps=30):
        return refine_noise(denoise, vae, x_T, target, hint_mask, lens, mean=mean, std=std, latent_scale=1.0,
                            steps=steps, lr=0.1)

    before = control_loss(decode_joints(vae, mixer(x_T), lengths, 12, mean, std, 1.0), target, mask)
    z = refine(mixer)
    after = control_loss(decode_joints(vae, z, lengths, 12, mean, std, 1.0), target, mask)
    assert after < 0.5 * before
    assert all(p.grad is None for p in [*vae.parameters(), *mixer.parameters()])
    assert torch.equal(refine(mixer, steps=0), mixer(x_T).detach())
    # with the identity as sampler the result is the optimised noise itself: on the sphere of x_T's norm
    moved = refine(lambda x: x)
    assert not torch.allclose(moved, x_T)
    assert torch.allclose(moved.flatten(1).norm(dim=1), x_T.flatten(1).norm(dim=1), atol=1e-5)
    padded = mask.clone()
    padded[:, 10:] = True  # controlled entries past the lengths below are ignored
    short = torch.tensor([10, 10])
    assert torch.equal(refine(mixer, padded, short, 3), refine(mixer, mask & (torch.arange(12) < 10)[None, :, None],
                                                            short, 3))


def test_controlled_sampling_reduces_to_motionlcm_at_initialisation():
    base = student()
    x = batch()
    controlled = ControlledStudent(base, MotionControlNet(base, control_config()), x["hint"], x["mask"])
    kwargs = {"text_tokens": x["text_tokens"], "text_mask": x["text_mask"]}
    plain = motionlcm_latents(base, SCHEDULE, x["text_emb"], 1, 1.5, torch.Generator().manual_seed(5), **kwargs)
    same = motionlcm_latents(controlled, SCHEDULE, x["text_emb"], 1, 1.5, torch.Generator().manual_seed(5), **kwargs)
    assert torch.equal(plain, same)
    x_T = torch.randn(plain.shape, generator=torch.Generator().manual_seed(5))  # the draw the generator makes
    assert torch.equal(motionlcm_latents(controlled, SCHEDULE, x["text_emb"], 1, 1.5, x_T=x_T, **kwargs), plain)


def test_hint_validation():
    joints = np.zeros((2, 5, J, 3), np.float32)
    mask = np.zeros((2, 5, J), bool)
    Hint(joints, mask)
    with pytest.raises(ValueError, match="mask must be boolean"):
        Hint(joints, mask.astype(int))
    with pytest.raises(ValueError, match=r"\(B, T, J, 3\)"):
        Hint(joints[..., :2], mask)
    joints[0, 1, 0, 0] = np.nan
    Hint(joints, mask)  # NaN outside the mask is ignored
    mask[0, 1, 0] = True
    with pytest.raises(ValueError, match="NaN"):
        Hint(joints, mask)


def test_control_config_validates_statistics_and_patch():
    with pytest.raises(ValueError, match="66 values"):
        ControlConfig(joints_num=J, hint_mean=[0.0] * 3, hint_std=[1.0] * 3)
    with pytest.raises(ValueError, match="positive"):
        ControlConfig(joints_num=J, hint_mean=[0.0] * 66, hint_std=[0.0] * 66)
    with pytest.raises(ValueError, match="patch_frames must be >= 1, got 0"):
        control_config(patch_frames=0)


@pytest.mark.parametrize("value", ["[]", "[-1]", "[7.5]", "799"])
def test_stage_check_names_bad_timesteps(value):
    params = restrict_params(load_params([f"train_controlnet.timesteps={value}"]), train_controlnet.STAGE.params)
    message = "train_controlnet.timesteps: expected null or a non-empty list of integers >= 0"
    with pytest.raises(ConfigError, match=re.escape(message)):
        train_controlnet.check_section(params)
    train_controlnet.check_section(restrict_params(load_params(["train_controlnet.timesteps=[0,799]"]),
                                                   train_controlnet.STAGE.params))


@pytest.mark.parametrize("value", ["-0.1", "1.5", "yes"])
def test_stage_check_names_a_bad_text_dropout(value):
    with pytest.raises(ConfigError, match=re.escape("train_controlnet.text_dropout: expected a number")):
        train_controlnet.check_section(load_params([f"train_controlnet.text_dropout={value}"]))


@pytest.mark.parametrize(("value", "message"), [
    (0, "train_controlnet.encoder.patch_frames: expected an integer >= 1, got 0"),
    (2.5, "train_controlnet.encoder.patch_frames: expected an integer, got 2.5"),
])
def test_stage_check_names_a_bad_patch_size_before_any_work(value, message):
    params = load_params([f"train_controlnet.encoder.patch_frames={value}"])
    with pytest.raises(ConfigError, match=re.escape(message)):
        train_controlnet.check_section(params)
    train_controlnet.check_section(load_params([]))  # the shipped params pass


@pytest.mark.parametrize("refine_steps", [None, 0, 3])
def test_controlnet_rows_count_every_forward_pass_as_nfe(refine_steps):
    """NFE of MotionLCM-Control (2: the copy and the student) and of +refine (2 more per refinement step),
    counted against the forward passes one sample makes."""
    from models.generator import TextBatch
    from pipelines.controlnet_family import ControlNetGenerator, ControlSpec

    base = student()
    controlnet = MotionControlNet(base, control_config()).eval()
    calls = []
    for net in (base, controlnet):  # the student, and the ControlNet (its copy runs through `run`)
        net.register_forward_hook(lambda *_: calls.append(1))
    refine = None if refine_steps is None else {"steps": refine_steps, "lr": 0.1, "project": False, "batch": None}
    gen = ControlNetGenerator("c", base, controlnet, tiny_vae().eval(), SCHEDULE, 2.5, ControlSpec("100%"),
                              np.zeros(D, np.float32), np.ones(D, np.float32), refine)
    x = batch(1, 8)
    text = TextBatch(texts=["a"], pooled=x["text_emb"].numpy(), tokens=[x["text_tokens"][0].numpy()])
    gen.sample(text, np.array([8]), 0, Hint(joints=x["hint"].numpy(), mask=x["mask"].numpy()))
    assert len(calls) == gen.nfe == 2 * (1 + (refine_steps or 0))


def test_refinement_in_batches_holds_that_many_motions_and_gives_the_same_motions(monkeypatch):
    """``sample.control_refine_batch``: the refinement backpropagates through the decoder for that many motions at
    a time (what bounds its memory), from the same noise. Each batch's control loss is its own mean, and Adam's
    steps do not depend on the loss's scale, so the motions come out as from one batch, up to float noise (which
    Adam's normalised first step amplifies where a gradient is near zero: about 1e-4 here)."""
    import models.controlnet
    from models.generator import TextBatch
    from pipelines.controlnet_family import ControlNetGenerator, ControlSpec

    base = student()
    randomise(base)
    controlnet = MotionControlNet(base, control_config()).eval()
    randomise(controlnet, seed=3)
    vae = tiny_vae().eval()
    decoded = []

    def decode_joints(vae: MotionVAE, z: torch.Tensor, *args, **kwargs) -> torch.Tensor:
        decoded.append(z.shape[0])
        return models.controlnet.__dict__["_decode_joints"](vae, z, *args, **kwargs)

    monkeypatch.setitem(models.controlnet.__dict__, "_decode_joints", models.controlnet.decode_joints)
    monkeypatch.setattr(models.controlnet, "decode_joints", decode_joints)
    x, lengths = batch(5, 8), np.array([8, 6, 8, 5, 7])
    text = TextBatch(texts=list("abcde"), pooled=x["text_emb"].numpy(), tokens=list(x["text_tokens"].numpy()))
    hint = Hint(joints=x["hint"].numpy(), mask=x["mask"].numpy())
    motions = {}
    for size in (None, 2):
        gen = ControlNetGenerator("c", base, controlnet, vae, SCHEDULE, 2.5, ControlSpec("100%"),
                                  np.zeros(D, np.float32), np.ones(D, np.float32),
                                  {"steps": 3, "lr": 0.1, "project": False, "batch": size})
        decoded.clear()
        motions[size] = gen.sample(text, lengths, 7, hint)
        assert decoded == ([5] * 3 if size is None else [2] * 3 + [2] * 3 + [1] * 3)
    np.testing.assert_allclose(motions[2], motions[None], rtol=0, atol=1e-3)


def test_refinement_waits_for_the_gpu_a_fixed_number_of_times_whatever_its_steps():
    """On a GPU (the stand-in counts the host's waits: tests/standin_device.py) a refinement step reads nothing
    back and copies nothing over: the schedule sits on the device, the lengths were checked once. Three
    refinement steps wait as often as one."""
    from standin_device import STANDIN, syncs_of

    from models.generator import TextBatch
    from pipelines.controlnet_family import ControlNetGenerator, ControlSpec

    x = batch(2, 8)
    text = TextBatch(texts=["a", "b"], pooled=x["text_emb"].numpy(), tokens=list(x["text_tokens"].numpy()))
    hint = Hint(joints=x["hint"].numpy(), mask=x["mask"].numpy())

    def refine(steps: int) -> None:
        base = student().to(STANDIN)
        controlnet, vae = MotionControlNet(base, control_config()).eval().to(STANDIN), tiny_vae().eval().to(STANDIN)
        gen = ControlNetGenerator("c", base, controlnet, vae, SCHEDULE.to(STANDIN), 2.5, ControlSpec("100%"),
                                  np.zeros(D, np.float32), np.ones(D, np.float32),
                                  {"steps": steps, "lr": 0.1, "project": False, "batch": None})
        gen.sample(text, np.array([8, 6]), 0, hint)

    assert syncs_of(lambda: refine(1)) == syncs_of(lambda: refine(3)) != {}
