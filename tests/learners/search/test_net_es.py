"""net_es: its start is team_reserve, its rule part is reserve_es's, its ES step by hand."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from mrta_rl.envs import AuctionEnv, AuctionParams
from mrta_rl.learners import GreedyLearner, TeamReserveLearner
from mrta_rl.learners.search.net_es import N_HEADS, N_INPUTS, NetESLearner
from mrta_rl.learners.search.reserve_es import N_FEATURES, ReserveESLearner
from tests.conftest import paper_system


def make(system_name: str, batch: int = 8, pairs: int = 2, seed: int = 3, horizon: int = 200, **hp):
    env = AuctionEnv(
        paper_system(system_name), AuctionParams(horizon=horizon), batch_size=batch, seed=seed
    )
    return env, NetESLearner(env=env, rng=np.random.default_rng(seed), pairs=pairs, **hp)


@pytest.mark.parametrize(
    ("system_name", "reserve", "hold_level"), [("system1", 0, 1), ("system2", 1, 1)]
)
def test_untrained_policy_is_team_reserve(system_name, reserve, hold_level):
    """Untrained (output layer zero), every action is team_reserve's, tick by tick."""
    env, learner = make(system_name, reserve=reserve, hold_level=hold_level)
    rule = TeamReserveLearner(
        env=env,
        rng=np.random.default_rng(0),
        reserve=reserve,
        hold_level=hold_level,
        hold_scope="robot",
    )
    greedy = GreedyLearner(env=env, rng=np.random.default_rng(0))
    differs = 0
    while not env.done.any():
        mask = env.action_mask
        actions = learner.act(learner.encode(env), mask, explore=False)
        np.testing.assert_array_equal(actions, rule.act(rule.encode(env), mask, explore=False))
        differs += int((actions != greedy.act(None, mask, explore=False)).sum())
        env.step(actions)
    assert differs > 0  # the rule is not the plain auction: the comparison can fail


@pytest.mark.parametrize("system_name", ["system1", "system2"])
def test_rule_part_plays_reserve_es(system_name):
    """With the network's output at zero, any rule weights bid as reserve_es with those weights."""
    env, learner = make(system_name, batch=8, horizon=150)
    reference = ReserveESLearner(env=env, rng=np.random.default_rng(0), pairs=1)
    start = NetESLearner(env=env, rng=np.random.default_rng(0), pairs=1)
    weights = np.random.default_rng(7).normal(size=N_FEATURES)
    learner.theta[:N_FEATURES] = weights
    reference.theta = weights
    differs = 0
    while not env.done.any():
        mask = env.action_mask
        actions = learner.act(learner.encode(env), mask, explore=False)
        np.testing.assert_array_equal(
            actions, reference.act(reference.encode(env), mask, explore=False)
        )
        differs += int((actions != start.act(start.encode(env), mask, explore=False)).sum())
        env.step(actions)
    assert differs > 0  # these weights are not the start's: the comparison can fail


def test_network_output_changes_the_bids():
    """A large negative L head (its output bias) makes every robot hold back from L slots."""
    env, learner = make("system2", batch=4, horizon=100, reserve=0)
    learner.theta[-N_HEADS] = -100.0  # f_L's bias: every L score below zero
    bids_low = 0
    while not env.done.any():
        mask = env.action_mask
        actions = learner.act(learner.encode(env), mask, explore=False)
        slot = np.take_along_axis(env.slot_high, np.maximum(actions - 1, 0), axis=1)
        bids_low += int(((actions > 0) & (slot == 0)).sum())
        env.step(actions)
    assert bids_low == 0
    assert env.stats.team_return.min() > 0  # H tasks were still taken


def test_es_step_by_hand():
    """The first member pays 10, the others nothing: the gradient is ``eps_0`` and Adam's first
    step moves every weight, the network's too, by ``lr`` in the direction of ``eps_0``."""
    env, learner = make("system1", batch=4, pairs=2, lr=0.25)  # 4 members x 1 copy
    start, eps = learner.theta.copy(), learner.perturbations.copy()
    assert start.size == N_FEATURES + N_INPUTS * 16 + 16 + 16 * N_HEADS + N_HEADS
    returns = np.array([10.0, 0.0, 0.0, 0.0])  # members +eps_0, +eps_1, -eps_0, -eps_1
    learner.update(None, None, SimpleNamespace(team_reward=returns), None, None)
    learner.end_episode()
    np.testing.assert_allclose(learner.theta, start + 0.25 * np.sign(eps[0]), atol=1e-6)
    assert learner.steps == 1


def test_members_play_their_own_weights():
    """Exploring, copy b plays member b // copies: a member whose L head is very negative never
    bids for an L slot while the others do."""
    env, learner = make("system2", batch=8, pairs=2, horizon=100)  # 4 members x 2 copies
    learner.copy_theta = np.repeat(learner.theta[None], 8, axis=0)
    learner.copy_theta[2:4, -N_HEADS] = -100.0  # member 1
    low_bids = np.zeros(8, int)
    while not env.done.any():
        view = learner.encode(env)
        actions = learner.act(view, env.action_mask, explore=True)
        slot = np.take_along_axis(env.slot_high, np.maximum(actions - 1, 0), axis=1)
        low_bids += ((actions > 0) & (slot == 0)).sum(axis=1)
        env.step(actions)
    assert low_bids[2] == low_bids[3] == 0
    assert (np.delete(low_bids, [2, 3]) > 0).all()


def test_a_base_plays_another_team_and_leaves_its_copies_as_they_are():
    """As a planner's base (play_on), the policy acts on another team's env of any batch, with
    that env's copies untouched; training on it (bind_env) would clone them per member."""
    _, learner = make("system1", batch=8, pairs=2)
    other = AuctionEnv(paper_system("system2"), AuctionParams(horizon=50), batch_size=5, seed=11)
    before = other.get_state()
    learner.play_on(other)
    after = other.get_state()
    for name, value in before.items():
        np.testing.assert_array_equal(np.asarray(after[name]), np.asarray(value), err_msg=name)
    rule = TeamReserveLearner(
        env=other, rng=np.random.default_rng(0), reserve=0, hold_level=1, hold_scope="robot"
    )
    mask = other.action_mask
    actions = learner.act(learner.encode(other), mask, explore=False)  # untrained: the rule
    np.testing.assert_array_equal(actions, rule.act(rule.encode(other), mask, explore=False))
    with pytest.raises(Exception, match="multiple of 2 \\* pairs"):
        learner.bind_env(other)  # 5 copies: not a training batch of 2 pairs


def test_save_and_load_round_trip(tmp_path):
    _, learner = make("system1")
    learner.theta = np.arange(learner.theta.size, dtype=float)
    learner.steps = 7
    learner.save(tmp_path)
    _, other = make("system1")
    other.load(tmp_path)
    np.testing.assert_array_equal(other.theta, learner.theta)
    assert other.steps == 7
    _, smaller = make("system1", hidden=4)
    with pytest.raises(ValueError, match="weights"):
        smaller.load(tmp_path)


def test_size_does_not_depend_on_the_team():
    """20 rule weights + 18 x 16 + 16 + 16 x 2 + 2 network weights, for either system."""
    for system_name in ("system1", "system2"):
        _, learner = make(system_name)
        assert learner.theta.size == 358
        assert NetESLearner.learning_space_dimension(learner.env, None, {}) == 358
    assert NetESLearner.learning_space_dimension(learner.env, None, {"hidden": 4}) == 106


def random_heads(learner: NetESLearner) -> None:
    """Output layer drawn (not zero), so every pair input reaches the bids."""
    size = learner.hidden * N_HEADS + N_HEADS
    learner.theta[-size:] = np.random.default_rng(9).normal(size=size)


@pytest.mark.parametrize(("system_name", "team_return"), [("system1", 1516.0), ("system2", 2740.0)])
def test_one_zone_counts_the_whole_team(system_name, team_return):
    """With one auction zone the inputs count the whole team: the team return of fixed weights on
    fixed streams is the one of the team-wide policy (measured with it, 4 copies x 120 ticks)."""
    env = AuctionEnv(paper_system(system_name), AuctionParams(horizon=120), batch_size=4, seed=5)
    learner = NetESLearner(env=env, rng=np.random.default_rng(5), pairs=1, reserve=1)
    random_heads(learner)
    total = 0.0
    while not env.done.any():
        step = env.step(learner.act(learner.encode(env), env.action_mask, explore=False))
        total += float(step.team_reward.sum())
    assert total == team_return


def test_a_robot_counts_only_its_own_zone():
    """Two zones (robots 0-4 and 5-9): making zone 1's robots busy for long changes no bid of
    zone 0's robots, tick after tick, though zone 1's idle robots and covers are inputs of both."""
    env = AuctionEnv(
        paper_system("system2"), AuctionParams(horizon=120, zones=2), batch_size=4, seed=5
    )
    learner = NetESLearner(env=env, rng=np.random.default_rng(5), pairs=1, reserve=1)
    random_heads(learner)
    other = np.arange(10) >= 5  # zone 1: robot i is in zone i * 2 // 10
    compared = 0
    while not env.done.any():
        view, mask = learner.encode(env), env.action_mask
        actions = learner.act(view, mask, explore=False)
        busy = {**view, "idle": view["idle"] & ~other, "busy_until": view["busy_until"].copy()}
        busy["busy_until"][:, other] = view["t"][:, None] + 30
        busy_mask = mask.copy()
        busy_mask[:, other, 1:] = False
        changed = learner.act(busy, busy_mask, explore=False)
        np.testing.assert_array_equal(changed[:, ~other], actions[:, ~other])
        compared += int((actions[:, ~other] > 0).sum())
        env.step(actions)
    assert compared > 0  # zone 0's robots bid: there are bids to change
