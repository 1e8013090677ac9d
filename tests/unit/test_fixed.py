"""Fixed policies (spec "Fixed policies") on hand-built masks, and on the real env."""

from __future__ import annotations

import numpy as np
import pytest

from mrta_rl.envs import AuctionEnv
from mrta_rl.learners import GreedyLearner, HighOnlyLearner, RandomLearner

# one copy, four robots, K = 3 slots; columns: wait, slot 1, slot 2, slot 3
MASK = np.array([[
    [True, False, False, False],  # busy or nothing to bid for: only wait
    [True, True, True, True],  # may bid for every slot
    [True, False, True, True],  # slots 2 and 3
    [True, False, False, True],  # slot 3 only
]])
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
