"""A local multi-node Ray cluster for the tests of train.workers."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def cluster():
    """A Ray cluster of a head without CPUs and two nodes of one CPU: two worker processes."""
    cluster_utils = pytest.importorskip("ray.cluster_utils")
    cluster = cluster_utils.Cluster(
        initialize_head=True, head_node_args={"num_cpus": 0, "include_dashboard": False}
    )
    for _ in range(2):
        cluster.add_node(num_cpus=1)
    cluster.wait_for_nodes()
    yield cluster
    cluster.shutdown()
