"""How editable the BVH export's angle curves are: every joint in Z X Y against each joint's own order.

    python benchmarks/bvh_curves.py [--clips 30] [--root artifacts/dataset]

For ``--clips`` clips spread over ``<root>/new_joints`` (HumanML3D layout), the rotations that
:func:`data.bvh.write_bvh` solves are turned into its Euler curves (:func:`data.bvh.euler_curves`)
twice: with ``Z X Y`` on every joint, and with the orders of :func:`data.bvh.rotation_orders`.
Between two frames a joint turns by an angle; its three curves move by a sum of absolute changes.
Near gimbal lock the curves move far more than the joint turns (two angles trade large opposite
changes), which an animator sees as spikes. Prints per clip and over all clips: the largest curve
move beyond 3 x the joint's turn (degrees), the largest single curve step, the largest turn, and how
many joints left Z X Y.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from data.bvh import bvh_nodes, euler_curves, rotation_orders, solve_rotations  # noqa: E402
from data.skeleton import HUMANML3D  # noqa: E402


def excess(angles: np.ndarray, turned: np.ndarray) -> float:
    """The largest sum of a joint's three curve changes between two frames beyond 3 x its turn (degrees)."""
    return float((np.abs(np.diff(angles, axis=0)).sum(-1) - 3.0 * turned).max())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--clips", type=int, default=30)
    parser.add_argument("--root", type=Path, default=Path("artifacts/dataset"))
    args = parser.parse_args()
    files = sorted((args.root / "new_joints").glob("*.npy"))
    files = files[:: max(1, len(files) // args.clips)][: args.clips]
    nodes = bvh_nodes(HUMANML3D)
    rows = []
    print("clip          excess ZXY  excess own  step ZXY  step own  largest turn  joints off ZXY")
    for path in files:
        local = solve_rotations(np.load(path).astype(np.float64), HUMANML3D, nodes)
        relative = np.swapaxes(local[:-1], -1, -2) @ local[1:]
        turned = np.degrees(Rotation.from_matrix(relative.reshape(-1, 3, 3)).magnitude()).reshape(len(relative), -1)
        orders = rotation_orders(local)
        zxy, own = euler_curves(local, ["ZXY"] * len(nodes)), euler_curves(local, orders)
        row = (excess(zxy, turned), excess(own, turned), np.abs(np.diff(zxy, axis=0)).max(),
               np.abs(np.diff(own, axis=0)).max(), turned.max(), sum(o != "ZXY" for o in orders))
        rows.append(row)
        print(f"{path.stem:12s} {row[0]:11.1f} {row[1]:11.1f} {row[2]:9.1f} {row[3]:9.1f} {row[4]:13.1f} {row[5]:10d}")
    worst = np.array(rows).max(axis=0)
    mean_off = np.mean([r[5] for r in rows])
    print(f"{len(rows)} clips, largest: excess {worst[0]:.1f} (Z X Y) / {worst[1]:.1f} (own orders), step "
          f"{worst[2]:.1f} / {worst[3]:.1f}, turn {worst[4]:.1f}; joints off Z X Y per clip {mean_off:.1f} "
          f"of {len(nodes)}")


if __name__ == "__main__":
    main()
