"""Stage ``train_emdm_action``: EMDM conditioned on action labels (the action-to-motion protocol).

``python -m stages.train_emdm_action [key=value ...]``: :mod:`stages.train_emdm`'s recipe with the
``train_emdm_action`` params section (``condition: action``), trained on the store's labelled
single-action motions. ``tiny`` keeps the text model's loss (R = 100, lambda = 0) because it fine-tunes
that model (docs/emdm.md); EMDM's action setting, R = 1 and lambda = 1 from scratch, is the ``paper``
profile's. ``init_from: train_emdm`` (ours;
the paper and the ``paper`` profile: null, from scratch) starts G and D from the text stage's, each
label's token from the captions of its training motions (:func:`models.emdm.action_from_text`). Writes
``artifacts/train_emdm_action/``, evaluated by ``eval_emdm-action`` (recogniser accuracy, FID,
Diversity, MultiModality).
"""

from __future__ import annotations

from pipelines.emdm_training import training_stage
from pipelines.stage import main

STAGE = training_stage("train_emdm_action", __name__)

if __name__ == "__main__":
    main(STAGE)
