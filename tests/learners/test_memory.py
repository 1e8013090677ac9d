"""What a learner needs, estimated before any work."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from mrta_rl.envs import AuctionEnv, AuctionParams
from mrta_rl.learners.memory import (
    BYTES_PER_WEIGHT,
    conflict_free_joint_actions,
    estimate_resources,
)
from mrta_rl.learners.neural.vdn import VDNLearner
from mrta_rl.learners.resources import format_bytes
from mrta_rl.learners.tabular.dql import DQLLearner
from mrta_rl.learners.tabular.joint_actions import JointActions
from mrta_rl.learners.tabular.qtable import JointQStorage, TableGrowthError
from mrta_rl.learners.tabular.subg_cql import SubGCQLLearner
from mrta_rl.partition import subg_partition
from mrta_rl.runners import build_run
from mrta_rl.systems import random_system
from tests.conftest import paper_system

BIG = ["system=random", "system.n_robots=300", "debug=smoke"]


@pytest.mark.parametrize(
    ("learner", "message"),
    [
        (
            "subg_cql",
            r"subg_cql on system random \(300 robots\): sub-group G\d+ has \d\d robots: "
            r"4\^\d\d joint actions do not fit in int64; use fewer robots per group",
        ),
        ("cql", r"the team has 300 robots: 4\^300 joint actions do not fit in int64"),
        (
            "qmix",
            r"qmix on system random \(300 robots\): needs about [\d.]+ GB up front "
            r"\(replay buffer .*more than the limit .*lower learner.buffer_size.*limits.memory_gb",
        ),
    ],
)
def test_large_teams_are_refused_before_any_work(learner, message, compose_cfg):
    """Refused by name before building anything, not an OverflowError or a huge allocation."""
    cfg = compose_cfg([f"learner={learner}", *BIG])
    with pytest.raises(ValueError, match=message):
        build_run(cfg)


def test_a_run_that_only_plays_needs_no_replay_buffer(compose_cfg):
    """Zero-shot play (``train.episodes=0``) collects nothing: the team that training refuses
    for its replay buffer plays."""
    assert build_run(compose_cfg(["learner=qmix", *BIG, "train.episodes=0"]))
    system, params = paper_system("system1"), AuctionParams()
    hp = {"buffer_size": 1000}
    plays = estimate_resources(VDNLearner, system, params, None, hp, batch_size=4, episodes=0)
    trains = estimate_resources(VDNLearner, system, params, None, hp, batch_size=4, episodes=1)
    assert plays.parts["replay buffer"] == plays.parts["collector batch"] == 0
    assert trains.parts["replay buffer"] > trains.parts["collector batch"] > 0


def test_memory_limit_is_a_setting(compose_cfg):
    cfg = compose_cfg(["learner=greedy", "system=system1", "debug=smoke", "limits.memory_gb=1e-6"])
    with pytest.raises(ValueError, match=r"env copies .*limit of 1 kB.*limits.memory_gb"):
        build_run(cfg)


def test_estimate_needs_no_learner_and_gives_a_reason():
    """The scaling study calls it directly: a structured answer, nothing built."""
    system = random_system(300, 20, 0.15, seed=0)
    partition = subg_partition(system)
    estimate = estimate_resources(SubGCQLLearner, system, AuctionParams(), partition)
    assert estimate.reason is not None and "do not fit in int64" in estimate.reason
    assert estimate.refusal(10**12) == estimate.reason
    fine = estimate_resources(SubGCQLLearner, paper_system("system2"), AuctionParams(), None)
    assert fine.reason is None and fine.refusal(10**12) is None
    assert fine.up_front < 10**6 <= fine.worst  # tables grow with the states met


def test_conflict_free_joint_actions_match_the_table_enumeration():
    # 2 robots, 3 slots, all valid: both wait (1), one bids (2 x 3), both on distinct slots (6)
    assert conflict_free_joint_actions(2, 3) == 13
    for m, K in [(1, 3), (3, 3), (4, 2), (5, 3)]:
        masks = np.ones((1, m, K + 1), bool)
        _, codes = JointActions(m, K + 1).enumerate_valid(masks, prune_conflicts=True)
        assert conflict_free_joint_actions(m, K) == len(codes)


@pytest.mark.parametrize("features", ["paper", "time_to_free"])
def test_dense_dql_tables_are_counted_exactly(features, rng):
    """With time_to_free the tables are 13.5x larger (the estimate counted the paper's)."""
    system = paper_system("system2")
    estimate = estimate_resources(DQLLearner, system, AuctionParams(), None, {"features": features})
    learner = DQLLearner(env=AuctionEnv(system), rng=rng, features=features)
    assert estimate.parts["tables"] == learner.q.nbytes + learner.visits.nbytes


@pytest.mark.parametrize(
    ("learner", "network", "team"),
    [
        ("iql", "mlp", "system1"),
        ("vdn", "mlp", "system1"),
        ("qmix", "mlp", "system1"),
        ("subg_dqn", None, "system1"),
        ("qmix", "set", "system1"),
        # a large team: the per-robot leaves (inputs and masks) dominate a transition; QMIX
        # keeps its state as bool, VDN none
        ("qmix", "set", "random60"),
        ("vdn", "set", "random60"),
    ],
)
def test_network_and_transition_sizes_match_built_learners(learner, network, team, compose_cfg):
    from torchrl.collectors import Collector

    from mrta_rl.envs.torchrl_env import AuctionTorchRLEnv

    choice = [] if network is None else [f"learner.network={network}"]
    system = ["system=system1"]
    if team == "random60":
        system = ["system=random", "system.n_robots=60", "system.scale_auction=true"]
    cfg = compose_cfg([f"learner={learner}", *system, "debug=smoke", *choice])
    run = build_run(cfg)
    hp = run.learner.hp
    estimate = estimate_resources(
        type(run.learner), run.system, run.params, run.partition, dict(hp), batch_size=4
    )
    weights = sum(p.numel() for p in run.learner.networks.parameters())
    assert estimate.parts["networks"] == weights * BYTES_PER_WEIGHT
    env = AuctionTorchRLEnv(  # as the runner builds it
        run.env, group_map=run.learner.group_map, invalid_action="raise", **run.learner.view_options
    )
    collector = Collector(
        env,
        run.learner.collection_policy,
        frames_per_batch=run.env.batch_size,
        total_frames=run.env.batch_size,
        auto_register_policy_transforms=False,
    )
    data = run.learner.process_batch(next(iter(collector)))
    collector.shutdown()
    measured = (
        sum(
            v.element_size() * v.numel() for v in data.values(include_nested=True, leaves_only=True)
        )
        / data.numel()
    )
    assert estimate.parts["replay buffer"] / hp["buffer_size"] == pytest.approx(measured, rel=0.03)


def test_format_bytes():
    assert format_bytes(25.7e9) == "25.7 GB" and format_bytes(512) == "512 B"


def test_a_joint_row_that_cannot_fit_is_refused_up_front():
    """A 50-robot team with the auction scaled (15 slots) has an 11-robot sub-group: one row of
    its table (all robots idle) holds sum_j C(11, j) 15!/(15-j)! = 3.3e11 joint actions (7.9 TB):
    refused before the run starts, not when numpy is asked for the memory."""
    system = random_system(50, 12, 0.25, seed=0, scale_auction=True)
    params = AuctionParams(**system.env_overrides)
    estimate = estimate_resources(SubGCQLLearner, system, params, subg_partition(system))
    largest = max(len(robots) for robots in subg_partition(system).groups.values())
    assert largest == 11
    assert estimate.up_front >= conflict_free_joint_actions(11, 15) * 24  # 24 bytes an entry
    assert re.match(r"needs about \d+ TB up front", estimate.refusal(8 * 2**30))
    assert estimate.advice.startswith("use fewer robots per group")
    bounded = estimate_resources(SubGCQLLearner, system, params, subg_partition(system, 4))
    assert bounded.reason is None and bounded.refusal(8 * 2**30) is None  # 4 robots: 1.1 MB rows


def test_a_table_growing_past_the_limit_is_refused_and_left_unchanged():
    """The growth check counts the arrays a growth would make (int64 / float64 columns)."""
    storage = JointQStorage(1)
    before = {name: getattr(storage, name).copy() for name in ("hash", "rows", "entries", "q")}
    storage.max_bytes = storage.nbytes  # no room to grow at all
    storage.reserve(10, 100)  # fits in the first arrays: no growth, no error
    with pytest.raises(TableGrowthError, match=r"would grow from 133 kB to 231 kB .*limit of 133"):
        storage.reserve(10, 5000)  # entries 4096 -> 8192: 3 columns x 4096 x 8 B more
    for name, array in before.items():
        assert np.array_equal(getattr(storage, name), array)  # nothing changed
    storage.max_bytes = None
    storage.reserve(10, 5000)
    assert storage.q.size == 8192 and storage.nbytes == 8 * (3 * 1024 + 5 * 256 + 3 * 8192)


@pytest.mark.parametrize(
    ("settings", "copies", "room"),
    [
        ([], 102, "15.5 GB"),  # training: 5120 // 50 copies (conf/budget/subg_cql.yaml)
        (["train.batch_size=2", "eval.batch_size=20"], 20, "3.03 GB"),  # evaluation's copies
    ],
)
def test_a_first_tick_that_cannot_fit_is_refused_up_front(settings, copies, room, compose_cfg):
    """subG-CQL at 50 robots with max_group_size=6 (scaled auction: 15 slots) makes room, before
    each tick, for a new row per group and copy: a 6-robot group's row holds
    sum_j C(6, j) 15!/(15-j)! = 1 + 90 + 3,150 + 54,600 + 491,400 + 2,162,160 + 3,603,600 =
    6,315,001 joint actions (24 B each, plus 152 B a row: 151.6 MB), for the most copies that
    play a tick, training's or evaluation's: refused by group, rows and limit before any work,
    where it used to grow past 30 GiB in training."""
    cfg = compose_cfg(
        [
            "experiment=scaling",
            "learner=subg_cql",
            "partition.max_group_size=6",
            "system.n_robots=50",
            "system.seed=0",
            "limits.memory_gb=3",
            *settings,
        ]  # fmt: skip
    )
    message = (
        rf"subg_cql on system random \(50 robots\): needs about [\d.]+ GB up front \({copies} "
        rf"copies x G\d+ row \(6,315,001 joint actions\) {room}, .*more than the limit of 3 GB; "
        r"use fewer robots per group"
    )
    with pytest.raises(ValueError, match=message):
        build_run(cfg)


def test_tables_that_outgrow_the_memory_limit_stop_the_run_with_the_reason(compose_cfg, tmp_path):
    """A table that passes the up-front check may still grow past limits.memory_gb with the
    states it meets in training: the run stops with a user error naming the group that asks the
    most (System-I's 3-robot G2: rows of up to 1 + 3 x 3 + 3 x 6 + 6 = 34 joint actions with 3
    slots, a new one per copy), its rows and the limit, and leaves the reason as data, instead
    of asking numpy for more memory than the machine has."""
    from mrta_rl.runners import train

    cfg = compose_cfg(
        [
            "learner=subg_cql",
            "system=system1",
            "debug=smoke",
            "limits.memory_gb=1e-4",
            "train.episodes=10",
            "train.batch_size=16",
        ]  # fmt: skip
    )
    with pytest.raises(TableGrowthError, match=r"subg_cql on system system1 \(6 robots\): stopped "
                       r"in training: group G2 \(3 robots\) asks the most: \d+ rows met "
                       r"\(\d+ joint actions\) and room for 16 new rows of up to 34 joint actions: "
                       r"the Q-table would grow .* more than the limit of 100 kB; "
                       r"use smaller sub-groups .*or raise limits.memory_gb"):  # fmt: skip
        train(cfg, run_dir=tmp_path)
    assert not (tmp_path / "metrics.json").exists()
    refused = json.loads((tmp_path / "refused.json").read_text())
    assert refused["learner"] == "subg_cql" and "stopped in training" in refused["reason"]
