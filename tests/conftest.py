"""Shared pytest fixtures: test environment variables, ONE Ray cluster per session, one torch thread.

The Ray cluster is a ``ray.cluster_utils.Cluster`` simulating two nodes on this machine
(head + one worker node), started lazily by the first test that asks for
``ray_cluster`` and shut down at the end of the session. Tests that only need
"some Ray" use it too; 1-worker Train runs land on either node. Every test that uses it
(directly or through another fixture) is marked ``slow``: starting the cluster alone takes
~10 s here, and such tests run Ray Train or Tune.

``pytest -m "not slow"`` (``make test-fast``) leaves out the ``slow`` tests: Ray runs, training
runs and end-to-end stage runs (each over ~1 s on the 2-core machine); ``pytest`` runs them all.
"""

from __future__ import annotations

import os
import signal
from collections.abc import Iterator
from pathlib import Path

import pytest

#: Set before anything imports ray or wandb (subprocesses inherit them).
TEST_ENV = {
    "WANDB_MODE": "disabled",
    "WANDB_SILENT": "true",
    "DVC_NO_ANALYTICS": "1",
    "RAY_USAGE_STATS_ENABLED": "0",
    "RAY_TRAIN_HEALTH_CHECK_INTERVAL_S": "0.2",
    "RAY_TRAIN_ENABLE_PREEMPTION_WATCHER": "0",  # one process less per Train run (no cloud node is preempted here)
    # Token auth (default for local clusters in 2.60) breaks joining nodes and
    # ray.init(address=...) from subprocesses unless every process agrees on a mode.
    "RAY_AUTH_MODE": "disabled",
}
os.environ.update(TEST_ENV)

def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Mark every test that needs the session Ray cluster as ``slow``."""
    for item in items:
        if "ray_cluster" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.slow)


@pytest.fixture(scope="module")
def one_thread() -> Iterator[None]:
    """torch on one intra-op thread for a module of tiny networks, restored afterwards.

    Thread start-up dominates tiny ops, and on 2 shared cores 2 threads run ~5x slower.
    Use it with ``pytestmark = pytest.mark.usefixtures("one_thread")``.
    """
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


#: Logical CPUs per simulated node (the machine has 2 cores; Ray only counts).
CPUS_PER_NODE = 2


@pytest.fixture(scope="session")
def ray_cluster() -> Iterator[object]:
    """A connected two-node simulated Ray cluster; ``.address`` is its GCS address."""
    import ray
    from ray.cluster_utils import Cluster

    if ray.is_initialized():
        ray.shutdown()
    cluster = Cluster(initialize_head=True, connect=True, head_node_args={"num_cpus": CPUS_PER_NODE})
    raylets: set[int] = set()
    try:
        cluster.add_node(num_cpus=CPUS_PER_NODE)
        cluster.wait_for_nodes()
        raylets = {info.process.pid for node in cluster.list_all_nodes()
                   for info in node.all_processes.get("raylet", [])}
        yield cluster
    finally:
        ray.shutdown()
        cluster.shutdown()
        reap_ray_workers(raylets)


def reap_ray_workers(raylets: set[int]) -> list[int]:
    """Kill the processes that a raylet of ``raylets`` started and that outlived the cluster's shutdown; their PIDs.

    Ray's workers exit when their raylet dies, but once (CI, 2026-12-04) a ``ray::TrainController`` worker
    stayed asleep, reparented to init, after the session's cluster had shut down. A worker carries its
    raylet's PID in ``RAY_RAYLET_PID``; only this session's workers match, never another Ray on the machine.
    Linux only (``/proc``); elsewhere a no-op.
    """
    killed = []
    for entry in Path("/proc").glob("[0-9]*"):
        if entry.name == str(os.getpid()):
            continue
        try:
            env = (entry / "environ").read_bytes().split(b"\0")
        except OSError:
            continue
        if any(item.startswith(b"RAY_RAYLET_PID=") and item[15:].isdigit() and int(item[15:]) in raylets
               for item in env):
            try:
                os.kill(int(entry.name), signal.SIGKILL)
                killed.append(int(entry.name))
            except OSError:
                continue
    return killed


FIXTURE_JOINTS = os.path.join(os.path.dirname(__file__), "fixtures", "humanml3d", "new_joints_012314.npy")
SMALL_VERBS = ("walk", "run", "jump", "kick", "wave", "turn")


def make_fixture_dataset(root, clips: int = 120, test_from: int = 75):
    """A HumanML3D-layout dataset of ``clips`` motions made from the real fixture clip.

    Clip k is the fixture from frame k % 60, turned by 0.5 k rad about y; its three captions name
    one of six verbs. Clips [0, 70) are train, [70, 75) val, [test_from, clips) test.
    """
    import numpy as np

    from data.humanml3d import Caption
    from data.humanml3d_writer import Clip, write_dataset

    base = np.load(FIXTURE_JOINTS)
    out = []
    for k in range(clips):
        c, s = np.cos(0.5 * k), np.sin(0.5 * k)
        joints = base[k % 60 :] @ np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]).T
        verb = SMALL_VERBS[k % len(SMALL_VERBS)]
        captions = [
            Caption(f"a person {verb}s {how}", (("a", "DET"), ("person", "NOUN"), (verb, "VERB"), (how, "ADV")))
            for how in ("forward", "slowly", "quickly")
        ]
        out.append(Clip(f"{k:04d}", captions, joints=joints.astype(np.float32), action=verb))
    ids = [clip.clip_id for clip in out]
    write_dataset(root, out, {"train": ids[:70], "val": ids[70:75], "test": ids[test_from:]})
    return root


@pytest.fixture(scope="session")
def small_store(tmp_path_factory):
    """params for a feature store extracted from :func:`make_fixture_dataset` (built once per session)."""
    from pipelines.config import compose_params
    from stages.extract_features import run

    base = tmp_path_factory.mktemp("small_store")
    root = make_fixture_dataset(base / "dataset")
    params = compose_params(["scale=smoke"])
    params["data"]["root"] = str(root)
    params["features"].update(out=str(base / "features"), workers=1)
    params["paths"].update(artifacts=str(base / "artifacts"), ray_storage=str(base / "ray_storage"))
    run(params)
    return params
