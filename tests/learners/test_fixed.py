"""Fixed policies (spec "Fixed policies") on hand-built masks, and on the real env."""

from __future__ import annotations

import numpy as np
import pytest

from mrta_rl.envs import AuctionEnv, AuctionParams
from mrta_rl.envs.encodings import recency_level
from mrta_rl.learners import (
    GreedyLearner,
    HighOnlyLearner,
    RandomLearner,
    SubGReserveLearner,
    TeamReserveLearner,
)
from mrta_rl.learners.tabular.subg_cql import SubGCQLLearner
from mrta_rl.partition import subg_partition
from mrta_rl.runners import build_run, evaluate_policy
from mrta_rl.splits import split_seed
from tests.conftest import paper_system

# one copy, four robots, K = 3 slots; columns: wait, slot 1, slot 2, slot 3
MASK = np.array(
    [
        [
            [True, False, False, False],  # busy or nothing to bid for: only wait
            [True, True, True, True],  # may bid for every slot
            [True, False, True, True],  # slots 2 and 3
            [True, False, False, True],  # slot 3 only
        ]
    ]
)
SLOT_HIGH = np.array([[0, 1, 0]])  # slot 1 L, slot 2 H, slot 3 L


def make(cls, tiny_system, rng):
    return cls(env=AuctionEnv(tiny_system), rng=rng)


def test_greedy_bids_lowest_valid_slot(tiny_system, rng):
    learner = make(GreedyLearner, tiny_system, rng)
    np.testing.assert_array_equal(learner.act(None, MASK, explore=True), [[0, 1, 2, 3]])


def test_high_only_bids_lowest_high_slot_else_waits(tiny_system, rng):
    learner = make(HighOnlyLearner, tiny_system, rng)
    np.testing.assert_array_equal(learner.act(SLOT_HIGH, MASK, explore=False), [[0, 2, 2, 0]])


def test_random_is_uniform_over_valid_choices(tiny_system, rng):
    learner = make(RandomLearner, tiny_system, rng)
    draws = 20_000
    mask = np.repeat(MASK, draws, axis=0)  # [draws, 4, 4]
    actions = learner.act(None, mask, explore=True)
    assert mask[np.arange(draws)[:, None], np.arange(4)[None, :], actions].all()  # never invalid
    for robot in range(4):
        valid = np.flatnonzero(MASK[0, robot])
        counts = np.bincount(actions[:, robot], minlength=4)[valid]
        assert counts.sum() == draws
        expected = draws / len(valid)
        chi2 = ((counts - expected) ** 2 / expected).sum()
        # 99.9 % quantile of chi-square with up to 3 degrees of freedom is 16.3
        assert chi2 < 16.3, (robot, counts)


def test_random_is_reproducible(tiny_system):
    mask = np.repeat(MASK, 50, axis=0)
    a = make(RandomLearner, tiny_system, np.random.default_rng(7)).act(None, mask, explore=True)
    b = make(RandomLearner, tiny_system, np.random.default_rng(7)).act(None, mask, explore=True)
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("cls", [GreedyLearner, RandomLearner, HighOnlyLearner])
def test_fixed_policies_play_valid_episodes(cls, tiny_system, tiny_params, rng):
    env = AuctionEnv(tiny_system, tiny_params, batch_size=5, seed=3)
    learner = cls(env=env, rng=rng)
    assert learner.kind == "fixed" and learner.learning_space() == {}
    while not env.done.all():
        view = learner.encode(env)
        actions = learner.act(view, env.action_mask, explore=False)
        result = env.step(actions)  # raises on an invalid action
        assert learner.update(view, actions, result, learner.encode(env), env.action_mask) == {}
    assert (env.stats.ticks == tiny_params.horizon).all()


def test_greedy_matches_spec_on_env(tiny_system, tiny_params, rng):
    env = AuctionEnv(tiny_system, tiny_params, batch_size=4, seed=0)
    learner = GreedyLearner(env=env, rng=rng)
    for _ in range(tiny_params.horizon):
        actions = learner.act(None, env.action_mask, explore=False)
        bids = env.action_mask[:, :, 1:]
        expected = np.where(bids.any(axis=2), bids.argmax(axis=2) + 1, 0)
        np.testing.assert_array_equal(actions, expected)
        env.step(actions)


# subg_reserve on System-I, whose sub-group G1 is {R3: T1, T3; R5: T1; R6: T1, T3} (paper
# Table 3); R5 (one kept type) is asked first, then R3 and R6. Slots: 1 = H T1, 2 = L T3,
# 3 = L T1. Robots R1, R2, R4 (sub-group G2) have nothing to bid for.
NO_BID = [True, False, False, False]
RESERVE_MASK = np.array(
    [
        [
            NO_BID,
            NO_BID,
            [True, True, True, True],  # R3: T1 and T3
            NO_BID,
            [True, True, False, True],  # R5: T1 only
            [True, True, True, True],  # R6: T1 and T3
        ]
    ]
)
RESERVE_SLOTS = np.array([[1, 0, 0]])
ALL_IDLE = np.ones((1, 6), bool)


def on_partition(system, horizon=1000, batch=1, seed=0):
    """System, partition and an env on the partition's task sets Lambda_i."""
    partition = subg_partition(system)
    params = AuctionParams(horizon=horizon)
    env = AuctionEnv(system, params, batch, active_tasks=partition.active_tasks(system), seed=seed)
    return partition, env


def make_reserve(rng, system=None, **rule):
    system = system or paper_system("system1")
    partition = subg_partition(system)
    env = AuctionEnv(system, active_tasks=partition.active_tasks(system))
    return SubGReserveLearner(env=env, rng=rng, partition=partition, **rule)


@pytest.mark.parametrize(
    ("rule", "recency", "expected"),
    [
        # the H slot goes to R5 (fewest kept types), then R3 and R6 take the L slots
        ({"reserve": 0, "hold_level": 1}, 2, [[0, 0, 2, 0, 1, 3]]),
        # reserve 1: R6 would be the last idle robot of G1, it stays back for H work
        ({"reserve": 1, "hold_level": 1}, 2, [[0, 0, 2, 0, 1, 0]]),
        ({"reserve": 2, "hold_level": 1}, 2, [[0, 0, 0, 0, 1, 0]]),
        # an H task of T_g arrived within 3 ticks (recency level 0): L slots wait
        ({"reserve": 0, "hold_level": 1}, 0, [[0, 0, 0, 0, 1, 0]]),
        # hold_level 0 never holds
        ({"reserve": 0, "hold_level": 0}, 0, [[0, 0, 2, 0, 1, 3]]),
        # recency level 1 (4..10 ticks ago) holds only under hold_level 2
        ({"reserve": 0, "hold_level": 1}, 1, [[0, 0, 2, 0, 1, 3]]),
        ({"reserve": 0, "hold_level": 2}, 1, [[0, 0, 0, 0, 1, 0]]),
    ],
)
def test_subg_reserve_rule_by_hand(rng, rule, recency, expected):
    learner = make_reserve(rng, **rule)
    # per-robot recency levels: G1 = R3, R5, R6 see `recency`, G2 = R1, R2, R4 see 2
    view = (RESERVE_SLOTS, ALL_IDLE, np.array([[2, 2, recency, 2, recency, recency]]))
    np.testing.assert_array_equal(learner.act(view, RESERVE_MASK, explore=False), expected)


def test_subg_reserve_counts_idle_robots_without_a_bid(rng):
    # slot 1 holds an L T3 task: R3 may bid, R5 (T1 only) is idle with nothing to bid for and R6
    # is busy. With reserve 1, R5 is the robot kept back, so R3 bids; with R5 busy too it waits.
    learner = make_reserve(rng, reserve=1, hold_level=0)
    mask = np.array([[NO_BID, NO_BID, [True, True, False, False], NO_BID, NO_BID, NO_BID]])
    slots, recency = np.array([[0, -1, -1]]), np.full((1, 6), 2)
    r6_busy = np.array([[True, True, True, True, True, False]])
    expected = [[0, 0, 1, 0, 0, 0]]
    np.testing.assert_array_equal(
        learner.act((slots, r6_busy, recency), mask, explore=False), expected
    )
    r5_r6_busy = np.array([[True, True, True, True, False, False]])
    waits = [[0, 0, 0, 0, 0, 0]]
    np.testing.assert_array_equal(
        learner.act((slots, r5_r6_busy, recency), mask, explore=False), waits
    )


def test_subg_reserve_needs_a_partition_and_valid_rule(tiny_system, rng):
    with pytest.raises(ValueError, match="requires a subG partition"):
        SubGReserveLearner(env=AuctionEnv(tiny_system), rng=rng)
    with pytest.raises(ValueError, match="reserve: must be an integer >= 0, got -1"):
        make_reserve(rng, tiny_system, reserve=-1)
    with pytest.raises(ValueError, match=r"hold_level: must be an integer in \[0, 3\], got 4"):
        make_reserve(rng, tiny_system, hold_level=4)


def test_subg_reserve_plays_valid_conflict_free_episodes(rng):
    partition, env = on_partition(paper_system("system2"), horizon=200, batch=8, seed=5)
    learner = SubGReserveLearner(env=env, rng=rng, partition=partition)
    while not env.done.all():
        actions = learner.act(learner.encode(env), env.action_mask, explore=False)
        for k in range(1, env.n_actions):  # no two robots bid for the same slot
            assert ((actions == k).sum(axis=1) <= 1).all()
        env.step(actions)  # raises on an invalid action (a type outside Lambda_i included)
    assert env.stats.assigned.sum() > 0


def test_subg_reserve_with_no_reserve_is_the_untrained_subg_cql(rng):
    """docs/learners.md: untrained subG-CQL (spread_wait, fewest_types) plays subg_reserve."""
    partition, env = on_partition(paper_system("system2"), horizon=150, batch=6, seed=11)
    rule = SubGReserveLearner(env=env, rng=rng, partition=partition, reserve=0, hold_level=1)
    table = SubGCQLLearner(env=env, rng=rng, partition=partition)
    while not env.done.all():
        mask = env.action_mask
        expected = rule.act(rule.encode(env), mask, explore=False)
        np.testing.assert_array_equal(table.act(table.encode(env), mask, explore=False), expected)
        env.step(expected)


def make_team(rng, **rule):
    """team_reserve on the same partitioned System-I env as :func:`make_reserve`."""
    system = paper_system("system1")
    partition = subg_partition(system)
    env = AuctionEnv(system, active_tasks=partition.active_tasks(system))
    return TeamReserveLearner(env=env, rng=rng, **rule)


@pytest.mark.parametrize(
    ("rule", "expected"),
    [
        # one group of six idle robots: reserve 2 still lets R3 and R6 take the L slots ...
        ({"reserve": 2, "hold_level": 0}, [[0, 0, 2, 0, 1, 3]]),
        # ... reserve 4 keeps four back: after R5 (H) and R3 (L), only 4 idle remain
        ({"reserve": 4, "hold_level": 0}, [[0, 0, 2, 0, 1, 0]]),
        # per-robot recency: R3 saw an H task within 3 ticks, R6 did not, so R6 takes slot 2
        ({"reserve": 0, "hold_level": 1}, [[0, 0, 0, 0, 1, 2]]),
        # index order: R3 (lowest index) takes the H slot, R5 slot 3, R6 (recency 2) slot 2
        ({"reserve": 0, "hold_level": 0, "order": "index"}, [[0, 0, 1, 0, 3, 2]]),
    ],
)
def test_team_reserve_rule_by_hand(rng, rule, expected):
    learner = make_team(rng, hold_scope="robot", **rule)
    view = (RESERVE_SLOTS, ALL_IDLE, np.array([[2, 2, 0, 2, 2, 2]]))  # R3's recency level 0
    np.testing.assert_array_equal(learner.act(view, RESERVE_MASK, explore=False), expected)


def test_team_reserve_recency_scope(rng):
    _, env = on_partition(paper_system("system2"), horizon=50, batch=4, seed=2)
    for _ in range(7):
        env.step(np.zeros((4, env.n_robots), np.int64))
    robot = TeamReserveLearner(env=env, rng=rng, hold_scope="robot")
    np.testing.assert_array_equal(robot.encode(env)[2], recency_level(env, env.active_tasks))
    team = TeamReserveLearner(env=env, rng=rng, hold_scope="group")
    every_type = recency_level(env, np.ones(env.n_task_types, bool))  # [B], T_g = all types
    np.testing.assert_array_equal(team.encode(env)[2], np.repeat(every_type[:, None], 10, axis=1))


@pytest.mark.parametrize(("reserve", "hold_level"), [(0, 1), (1, 1), (2, 0), (1, 2)])
def test_team_reserve_on_subg_grouping_plays_subg_reserve(reserve, hold_level):
    """team_reserve with grouping=subg (partition derived from the system) is subg_reserve."""
    partition, env = on_partition(paper_system("system2"), horizon=120, batch=6, seed=4)
    rng = np.random.default_rng(0)
    rule = {"reserve": reserve, "hold_level": hold_level}
    subg = SubGReserveLearner(env=env, rng=rng, partition=partition, **rule)
    team = TeamReserveLearner(env=env, rng=rng, grouping="subg", hold_scope="group", **rule)
    whole = TeamReserveLearner(env=env, rng=rng, **rule)
    differs = 0
    while not env.done.all():
        mask = env.action_mask
        expected = subg.act(subg.encode(env), mask, explore=False)
        np.testing.assert_array_equal(team.act(team.encode(env), mask, explore=False), expected)
        differs += int((whole.act(whole.encode(env), mask, explore=False) != expected).any())
        env.step(expected)
    assert differs > 0  # the whole-team grouping is a different rule


def test_team_reserve_rejects_bad_settings(rng):
    for bad, match in (
        ({"hold_scope": "nope"}, "hold_scope: must be one of 'group', 'robot', got 'nope'"),
        ({"grouping": "nope"}, "grouping: must be one of 'team', 'subg', got 'nope'"),
        ({"order": "nope"}, "order: must be one of 'fewest_types', 'index', got 'nope'"),
        ({"reserve": -1}, "reserve: must be an integer >= 0, got -1"),
    ):
        with pytest.raises(ValueError, match=match):
            make_team(rng, **bad)


RANDOM50 = ["system=random", "system.n_robots=50", "system.scale_auction=true"]


@pytest.mark.parametrize(
    ("learner", "system", "episodes", "team_return"),
    [  # docs/notebook.md, "team_reserve, the subg_reserve rule over the whole team" (100 episodes)
        ("subg_reserve", ["system=system1"], 100, 2671.9),
        ("subg_reserve", ["system=system2"], 100, 4956.0),
        ("team_reserve", ["system=system1"], 100, 2811.0),
        ("team_reserve", ["system=system2"], 100, 5524.4),
        # a random 50-robot team (scaled auction: 15 slots in 5 zones): train.py's eval.episodes=20
        ("subg_reserve", RANDOM50, 20, 8971.3),
        ("team_reserve", RANDOM50, 20, 17177.1),
    ],
)
def test_rules_score_what_the_reports_recorded(learner, system, episodes, team_return, compose_cfg):
    """The rules at their yaml defaults on the test split score the team returns recorded from
    ``scripts/train.py learner=<rule> ... eval.episodes=<episodes>``: the same actions on every
    task stream, whatever the rules' code becomes."""
    run = build_run(compose_cfg([f"learner={learner}", *system]))
    seed = split_seed("test")
    env = AuctionEnv(
        run.system, run.params, batch_size=episodes, active_tasks=run.active_tasks, seed=seed
    )
    summary = evaluate_policy(run.learner, env, episodes, seed)
    assert round(summary.team_return_mean, 1) == team_return
