from __future__ import annotations

import pytest

from mrta_rl.envs import AuctionEnv
from mrta_rl.learners.registry import learning_space_dimension, learning_space_table
from mrta_rl.metrics.learning_space import (
    centralized_dimension,
    decentralized_dimension,
    factorize,
    subgroup_dimension,
)
from mrta_rl.partition import subg_partition
from tests.conftest import paper_system


def test_formulas_by_hand():
    assert decentralized_dimension([10, 20], [4, 2]) == 10 * 4 + 20 * 2  # eq. 11
    assert centralized_dimension(7, [4, 4, 2]) == 7 * 32  # eq. 16
    assert subgroup_dimension([(7, [4, 4]), (5, [4])]) == 7 * 16 + 5 * 4
    with pytest.raises(ValueError):
        decentralized_dimension([1, 2], [4])


def test_tiny_system_by_hand(tiny_system):
    env = AuctionEnv(tiny_system)  # R1: T1, T2; R2: T2; K = 3 slots, 4 actions
    # |S_i| = idle 2 x (1 + 2 |Lambda_i|)^3 x battery 2 x recency 3
    s1, s2 = 2 * 5**3 * 2 * 3, 2 * 3**3 * 2 * 3
    assert learning_space_dimension("dql", env) == (s1 + s2) * 4
    whole = 5**3 * 3**2 * 3  # slots (1 + 2n)^K x robot states 3^m x recency 3
    assert learning_space_dimension("cql", env) == whole * 4**2
    assert learning_space_dimension("semi_cql", env) == 2 * whole * 4
    partition = subg_partition(tiny_system)  # G1 {R2: T2}, G2 {R1: T1}
    sub_env = AuctionEnv(tiny_system, active_tasks=partition.active_tasks(tiny_system))
    g = 3**3 * 3 * 3  # one type, one robot per group
    assert learning_space_dimension("subg_cql", sub_env, partition) == 2 * g * 4
    with pytest.raises(ValueError):
        learning_space_dimension("subg_cql", sub_env)


@pytest.mark.parametrize("name", ["system1", "system2"])
def test_table9_ordering(name):
    system = paper_system(name)
    table = learning_space_table(system)
    assert table["cql"] > 10 * table["subg_cql"] > 10 * table["dql"]  # CQL far above subG > DQL
    assert all(isinstance(v, int) for v in table.values())


def test_factorize():
    assert factorize(2**12 * 3**4 * 17) == "2^12 * 3^4 * 17"
    assert factorize(1) == "1"


def test_time_to_free_dimensions_by_hand(tiny_system):
    env = AuctionEnv(tiny_system)  # R1: T1, T2; R2: T2; K = 3 slots, 4 actions
    # |S_i| = free level 3 x (1 + 2 |Lambda_i|)^3 x battery 2 x recency 3 x queue levels 3 x 3
    s1, s2 = 3 * 5**3 * 2 * 3 * 9, 3 * 3**3 * 2 * 3 * 9
    assert learning_space_dimension("dql", env, features="time_to_free") == (s1 + s2) * 4
    whole = 5**3 * 4**2 * 3 * 9  # robot states 4: busy, idle ok, idle low, free soon
    assert learning_space_dimension("cql", env, features="time_to_free") == whole * 4**2
    partition = subg_partition(tiny_system)
    sub_env = AuctionEnv(tiny_system, active_tasks=partition.active_tasks(tiny_system))
    g = 3**3 * 4 * 3 * 9
    dim = learning_space_dimension("subg_cql", sub_env, partition, "time_to_free")
    assert dim == 2 * g * 4
