"""Stage ``train_emdm``: EMDM, a conditional denoising-diffusion GAN for few-step text-to-motion.

``python -m stages.train_emdm [key=value ...]`` trains :class:`models.emdm.EMDMGenerator` and
:class:`models.emdm.EMDMDiscriminator` through the one runner, as two models with two Adam
optimisers (betas (0.5, 0.9), no weight decay; EMDM's code) and an EMA of the generator. The data
are the training motions of the feature store (normalised with its Mean/Std, random windows of
``crop_frames``), each with the pooled frozen embedding of one of its captions (and, with
``model.word_tokens``, that caption's word-token states, which G cross-attends to). One runner step is
DDGAN's iteration (EMDM App. C.3, :mod:`models.emdm` docstring items 5-7):

1. one D update: non-saturating softplus loss on a real pair ``(x_t, x_{t+1})`` and a fake ``x_t``
   posterior-sampled around ``G(x_{t+1}, t, z, c)``; R1 (gamma ``r1_gamma``) on the real ``x_t``
   every ``r1_interval`` steps (lazy regularisation, weighted by the interval; the runner's step
   count decides when, so a resumed run regularises on the same steps);
2. one G update with D frozen: non-saturating adversarial loss plus ``R * geo`` (Eqs. 7-12), R =
   ``geometric_weight`` (null: 100 for text, 1 for action), lambda = ``geometric_lambda`` (on the foot term:
   ``foot_lambda``, null: the same).

All randomness (t, pairs, z, condition dropout) comes from the process-global torch RNG, which the
runner seeds per rank and checkpoints, so a resumed run is bit-identical to an uninterrupted one.
The runner's ``grad_clip`` applies to each optimiser separately, and its LR schedule to both (each
relative to its own learning rate). Writes ``artifacts/train_emdm/`` (model.pt with the generator,
the discriminator and the generator's EMA).

Conditions (``condition``): ``text``, the pooled caption embedding of the store's frozen encoder;
``action``, the label of the store's labelled single-action motions (whole, up to ``crop_frames``),
as an index into ``classes`` (the sorted training labels, saved in the model's config). The
pipeline trains both: this module for ``train_emdm`` (text) and :mod:`stages.train_emdm_action` for
the ``train_emdm_action`` section (action), with one recipe. With several Ray Train workers the
networks are not wrapped in DDP (``TrainSpec.ddp=False``): the D step runs D twice and
double-backpropagates for R1, which DDP's reducer does not allow. The runner averages each
optimiser's gradients over the workers instead, which is what DDP computes.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from pipelines.emdm_training import training_stage
from pipelines.stage import checks, loop_config, main

if TYPE_CHECKING:
    from pipelines.sweep import SweepTarget

STAGE = training_stage("train_emdm", __name__)


def sweep_loop_config(params: dict[str, Any]) -> dict[str, Any]:
    """A sweep trial's loop config (its values applied to ``params``)."""
    return loop_config(STAGE, params)


def sweep_target(params: dict[str, Any]) -> SweepTarget:
    """``python -m stages.sweep train_emdm``: the ablations (steps T, weight R, naive DDGAN), each trial
    scored by its validation FID and R@3."""
    from pipelines.sweep import SweepTarget  # imports Ray Tune: only when sweeping
    from pipelines.validation import emdm_scores  # evaluation code: only when sweeping

    return SweepTarget(stage="train_emdm", spec=STAGE.spec, loop_config=sweep_loop_config,
                       validate=emdm_scores, metric="val_FID", mode="min", checks=checks(STAGE),
                       module=STAGE.module, inputs=STAGE.inputs)


if __name__ == "__main__":
    main(STAGE)
