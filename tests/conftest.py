"""Shared pytest fixtures: test environment variables and ONE Ray cluster per session.

The Ray cluster is a ``ray.cluster_utils.Cluster`` simulating two nodes on this machine
(head + one worker node), started lazily by the first test that asks for
``ray_cluster`` and shut down at the end of the session. Tests that only need
"some Ray" use it too; 1-worker Train runs land on either node.
"""

from __future__ import annotations

import os
from collections.abc import Iterator

import pytest

#: Set before anything imports ray or wandb (subprocesses inherit them).
TEST_ENV = {
    "WANDB_MODE": "disabled",
    "WANDB_SILENT": "true",
    "DVC_NO_ANALYTICS": "1",
    "RAY_USAGE_STATS_ENABLED": "0",
    "RAY_TRAIN_HEALTH_CHECK_INTERVAL_S": "0.2",
    # Token auth (default for local clusters in 2.60) breaks joining nodes and
    # ray.init(address=...) from subprocesses unless every process agrees on a mode.
    "RAY_AUTH_MODE": "disabled",
}
os.environ.update(TEST_ENV)

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
    try:
        cluster.add_node(num_cpus=CPUS_PER_NODE)
        cluster.wait_for_nodes()
        yield cluster
    finally:
        ray.shutdown()
        cluster.shutdown()
