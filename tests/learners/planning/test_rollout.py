"""The rollout planner (mrta_rl/learners/planning/rollout.py): valid, deterministic, reduces to
its base rule, and restoring env snapshots into other copies replays them exactly."""

from __future__ import annotations

import numpy as np
import pytest

from mrta_rl.envs import AuctionEnv, AuctionParams
from mrta_rl.learners import GreedyLearner, TeamReserveLearner
from mrta_rl.learners.fixed import SubGReserveLearner
from mrta_rl.learners.planning.rollout import (
    RolloutPlanner,
    SubGRolloutPlanner,
    neighbours,
    restore,
)
from mrta_rl.partition import subg_partition
from tests.conftest import paper_system


def make(seed=0, batch=3, ticks=60, **hp):
    env = AuctionEnv(paper_system("system1"), AuctionParams(horizon=ticks), batch, seed=seed)
    planner = RolloutPlanner(env=env, rng=np.random.default_rng(seed), **hp)
    return planner, env


def play(planner, env, other=None):
    """One episode of ``planner``; per tick its actions (and ``other``'s on the same state)."""
    ours, theirs = [], []
    while not env.done.all():
        mask = env.action_mask.copy()
        actions = planner.act(planner.encode(env), mask, explore=False)
        if other is not None:
            theirs.append(other.act(other.encode(env), mask, explore=False))
        ours.append(actions)
        env.step(actions)  # raises on an invalid action
    return np.stack(ours), (np.stack(theirs) if theirs else None)


def test_planner_plays_valid_deterministic_episodes():
    planner, env = make(samples=2, horizon=5)
    first, _ = play(planner, env)
    assert planner.decisions > 0  # it did compare candidates
    again, _ = play(*make(samples=2, horizon=5))
    np.testing.assert_array_equal(first, again)
    other, _ = play(*make(seed=0, samples=2, horizon=5, candidates=["greedy", "spread"]))
    assert (other != first).any()  # the candidates matter


@pytest.mark.parametrize("hp", [{"horizon": 0}, {"candidates": ["hold_group"]}])
def test_no_planning_plays_the_base_rule(hp):
    planner, env = make(**hp)
    # the default base "hold_group": L waits on the whole team's recency (not the best rule)
    base = TeamReserveLearner(env=env, rng=np.random.default_rng(1), hold_scope="group")
    ours, theirs = play(planner, env, base)
    np.testing.assert_array_equal(ours, theirs)
    assert planner.decisions == 0


def test_a_margin_keeps_the_base_more_often():
    """A candidate must beat the base by ``margin`` standard errors: fewer switches as it grows.

    Even an unreachable margin lets through a candidate that every sampled future prefers by
    the same amount (a paired difference without spread).
    """
    switches = []
    for margin in (0.0, 2.0, 1e9):
        planner, env = make(samples=3, horizon=5, margin=margin)
        base = TeamReserveLearner(env=env, rng=np.random.default_rng(1), hold_scope="group")
        ours, theirs = play(planner, env, base)
        assert planner.decisions > 0  # candidates were rolled out at every margin
        switches.append(int((ours != theirs).any(axis=-1).sum()))
    assert switches[0] > switches[1] >= switches[2]


@pytest.mark.parametrize("system", ["system1", "system2"])
def test_subg_rollout_without_planning_is_subg_reserve(system):
    partition = subg_partition(paper_system(system))
    env = AuctionEnv(
        paper_system(system),
        AuctionParams(horizon=60),
        3,
        seed=4,
        active_tasks=partition.active_tasks(paper_system(system)),
    )
    planner = SubGRolloutPlanner(
        env=env, rng=np.random.default_rng(0), partition=partition, horizon=0
    )
    rule = SubGReserveLearner(env=env, rng=np.random.default_rng(1), partition=partition)
    ours, theirs = play(planner, env, rule)
    np.testing.assert_array_equal(ours, theirs)
    assert planner.requires_partition and not RolloutPlanner.requires_partition  # runner: Lambda_i


def test_greedy_base_with_no_planning_is_greedy():
    planner, env = make(horizon=0, base="greedy")
    ours, theirs = play(planner, env, GreedyLearner(env=env, rng=np.random.default_rng(1)))
    np.testing.assert_array_equal(ours, theirs)


def test_neighbours_of_a_joint_action_move_one_bid():
    """Two copies of 3 robots and 2 slots, worked by hand.

    Copy 0: robot 0 bids for slot 1, robot 1 waits (it may bid for 1 or 2), robot 2 is busy.
    Copy 1: everyone waits; robot 0 may bid for 2, robot 1 for nothing, robot 2 for 1 or 2.
    """
    action = np.array([[1, 0, 0], [0, 0, 0]])
    mask = np.zeros((2, 3, 3), bool)
    mask[:, :, 0] = True  # waiting is always valid
    mask[0, 0, [1, 2]] = mask[0, 1, [1, 2]] = True
    mask[1, 0, 2] = mask[1, 2, [1, 2]] = True
    drop = neighbours(action, mask, ("drop",))
    # one row per robot: only copy 0's robot 0 has a bid to drop
    np.testing.assert_array_equal(drop[:, 0], [[0, 0, 0], [1, 0, 0], [1, 0, 0]])
    np.testing.assert_array_equal(drop[:, 1], [[0, 0, 0]] * 3)
    add = neighbours(action, mask, ("add",))
    assert add.shape == (6, 2, 3)  # robot-major rows (robot, slot): (0,1) (0,2) (1,1) ... (2,2)
    # copy 0: slot 1 is taken by robot 0, robot 2 is busy: only robot 1 -> slot 2
    expect0 = [[1, 0, 0], [1, 0, 0], [1, 0, 0], [1, 2, 0], [1, 0, 0], [1, 0, 0]]
    np.testing.assert_array_equal(add[:, 0], expect0)
    # copy 1: robot 0 -> slot 2, robot 2 -> slot 1 or 2
    expect1 = [[0, 0, 0], [2, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 1], [0, 0, 2]]
    np.testing.assert_array_equal(add[:, 1], expect1)
    both = neighbours(action, mask, ("drop", "add"))
    np.testing.assert_array_equal(both, np.concatenate([drop, add]))
    assert neighbours(action, mask, ()).shape == (0, 2, 3)


def test_with_neighbours_only_it_plays_the_base_or_one_bid_away():
    """Base ``hold_group`` and no other rule: each tick plays the rule's action or a neighbour."""
    planner, env = make(samples=3, horizon=5, candidates=["hold_group"], neighbours=["drop", "add"])
    rule = TeamReserveLearner(env=env, rng=np.random.default_rng(1), hold_scope="group")
    moved = 0
    while not env.done.all():
        mask = env.action_mask.copy()
        base = rule.act(rule.encode(env), mask, explore=False)
        actions = planner.act(planner.encode(env), mask, explore=False)
        near = neighbours(base, mask, ("drop", "add"))
        assert ((near == actions).all(axis=-1).any(axis=0) | (base == actions).all(axis=-1)).all()
        moved += int((actions != base).any(axis=-1).sum())
        env.step(actions)  # raises on an invalid action (or a conflict-free move gone wrong)
    assert planner.decisions > 0 and moved > 0  # the neighbours were rolled out and some played


def test_rejects_bad_settings():
    for bad, match in (
        ({"samples": 0}, "samples: must be an integer >= 1"),
        ({"horizon": -1}, "horizon: must be an integer >= 0"),
        ({"gamma": 0.0}, r"gamma: must be a number in \(0, 1\]"),
        ({"base": "nope"}, "base: must be one of 'greedy'"),
        ({"candidates": ["greedy", "nope"]}, "candidates: must be a list, each item one of"),
        ({"neighbours": ["drop", "swap"]}, "neighbours: must be a list, each item one of"),
    ):
        with pytest.raises(ValueError, match=match):
            make(**bad)


def test_restored_copies_replay_the_source_and_reseeding_changes_arrivals():
    system = paper_system("system2")
    params = AuctionParams(horizon=80)
    src = AuctionEnv(system, params, batch_size=3, seed=9)
    greedy = GreedyLearner(env=src, rng=np.random.default_rng(0))
    for _ in range(25):
        src.step(greedy.act(None, src.action_mask, explore=False))
    state = src.get_state()
    rows = np.array([2, 0, 2, 2])
    dst = AuctionEnv(system, params, batch_size=4, seed=123)
    restore(dst, state, rows)  # the arrival keys come with the state
    for _ in range(30):
        r_src = src.step(greedy.act(None, src.action_mask, explore=False))
        r_dst = dst.step(greedy.act(None, dst.action_mask, explore=False))
        np.testing.assert_array_equal(r_dst.team_reward, r_src.team_reward[rows])
        np.testing.assert_array_equal(dst.slot_type, src.slot_type[rows])
        np.testing.assert_array_equal(dst.busy_until, src.busy_until[rows])
    np.testing.assert_array_equal(dst.stats.team_return, src.stats.team_return[rows])
    # reseeded copies of one state: the same future for the same seed, another for another
    restore(dst, state, np.array([1, 1, 1, 1]))
    dst.reseed(None, np.array([3, 3, 4, 5]))
    for _ in range(10):
        dst.step(greedy.act(None, dst.action_mask, explore=False))
    assert dst.queued_tasks(0) == dst.queued_tasks(1)
    assert dst.queued_tasks(0) != dst.queued_tasks(2) != dst.queued_tasks(3)


def test_the_planner_plays_the_base_policy_the_runner_hands_it(tmp_path):
    """A run dir ``base`` is the runner's to load: the planner takes the policy, reads no file."""
    env = AuctionEnv(paper_system("system1"), AuctionParams(horizon=60), 3, seed=2)
    policy = TeamReserveLearner(env=env, rng=np.random.default_rng(1), hold_scope="robot")
    nowhere = tmp_path / "not" / "a_run"  # never read: no such dir
    planner = RolloutPlanner(
        env=env, rng=np.random.default_rng(0), horizon=0, base=str(nowhere), base_policy=policy
    )
    ours, theirs = play(planner, env, policy)
    np.testing.assert_array_equal(ours, theirs)
    assert planner.names[0] == "base"  # the handed policy's action is the first candidate
    with pytest.raises(ValueError, match="base_policy"):  # a run dir without its policy
        RolloutPlanner(env=env, rng=np.random.default_rng(0), base=str(nowhere))
