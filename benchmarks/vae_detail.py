"""What a trained VAE keeps of the test motions: MPJPE and the reconstruction-detail fractions.

    python benchmarks/vae_detail.py [VAE_DIR ...] [--features artifacts/features] [--split test]
        [--recogniser artifacts/train_evaluator_recogniser]

Encodes every motion of the split whole (posterior mean), decodes it, and prints one JSON line per
VAE folder (default ``artifacts/train_vae``): ``MPJPE_mm`` (root-aligned, as the VAE row) and
:func:`data.joint_measures.reconstruction_detail` (pelvis path error, and the fractions of turns,
kicks, wave swings and jump counts kept, with how many references each has), and ``action_accuracy``:
the action recogniser's top-1 accuracy on the reconstructions of the split's labelled whole clips
(when the recogniser's folder exists). The evaluation's VAE row
reports the same measures on each replication's draw; this script compares VAEs trained elsewhere
(``python -m stages.train_vae paths.artifacts=/tmp/x ...``) without running the evaluation stages.
"""
import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from data.skeleton import get_skeleton  # noqa: E402
from pipelines.action_evaluation import action_accuracy, load_recogniser  # noqa: E402
from pipelines.evaluation import detail, mpjpe_mm  # noqa: E402
from pipelines.feature_store import FeatureStore  # noqa: E402
from pipelines.mld_family import VAEReconstruction, load_vae  # noqa: E402
from pipelines.recogniser import labelled_items  # noqa: E402


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("vaes", nargs="*", default=["artifacts/train_vae"], help="train_vae output folders")
    parser.add_argument("--features", default="artifacts/features", help="the feature store")
    parser.add_argument("--split", default="test")
    parser.add_argument("--recogniser", default="artifacts/train_evaluator_recogniser",
                        help="train_evaluator's recogniser folder (skipped when missing)")
    args = parser.parse_args(argv)
    torch.set_num_threads(2)
    store = FeatureStore(Path(args.features))
    skeleton = get_skeleton(store.meta["skeleton"])
    items = store.split(args.split)
    lengths = np.array([item.length for item in items])
    real = np.zeros((len(items), lengths.max(), store.feature_dim), np.float32)
    for k, item in enumerate(items):
        real[k, : item.length] = item.features
    normalised = ((real - store.mean) / store.std).astype(np.float32)  # padding is ignored by length
    labelled = {id(item) for item in labelled_items(items)}
    which = np.array([id(item) in labelled for item in items])
    actions = [item.action for item, keep in zip(items, which, strict=True) if keep]
    recogniser = load_recogniser(args.recogniser) if Path(args.recogniser, "model.pt").exists() else None
    for vae in args.vaes:
        recon_normalised = VAEReconstruction(load_vae(Path(vae))).reconstruct(normalised, lengths)
        recon = recon_normalised * store.std + store.mean
        row = {"MPJPE_mm": mpjpe_mm(real, recon, lengths, skeleton), **detail(real, recon, lengths, skeleton)}
        if recogniser is not None and actions:
            row["action_accuracy"] = action_accuracy(
                recogniser, recon_normalised[which].astype(np.float32), lengths[which], actions)
        print(json.dumps({"vae": vae, **{key: round(value, 3) for key, value in row.items()}}))


if __name__ == "__main__":
    main()
