"""reserve_es: its start is team_reserve, its members share task streams, its ES step by hand."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from mrta_rl.envs import AuctionEnv, AuctionParams
from mrta_rl.learners import GreedyLearner, TeamReserveLearner
from mrta_rl.learners.search.reserve_es import (
    HIGH_FEATURES,
    N_FEATURES,
    N_LOW,
    ReserveESLearner,
)
from tests.conftest import paper_system


def make(system_name: str, batch: int = 8, pairs: int = 2, seed: int = 3, horizon: int = 200, **hp):
    env = AuctionEnv(
        paper_system(system_name), AuctionParams(horizon=horizon), batch_size=batch, seed=seed
    )
    return env, ReserveESLearner(env=env, rng=np.random.default_rng(seed), pairs=pairs, **hp)


@pytest.mark.parametrize(
    ("system_name", "reserve", "hold_level"),
    [("system1", 0, 1), ("system2", 1, 1), ("system2", 2, 2), ("system1", 0, 0), ("system1", 1, 3)],
)
def test_untrained_policy_is_team_reserve(system_name, reserve, hold_level):
    """Untrained, every action is team_reserve's (hold_scope=robot), tick by tick."""
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


def test_members_play_the_same_task_streams():
    """Copy b starts as copy b mod copies: every member meets the same arrivals, episode after
    episode, while the copies of one member differ."""
    env, learner = make("system1", batch=8, pairs=2)  # 4 members x 2 copies
    assert learner.copies == 2
    for _ in range(2):  # this episode and the next
        env.reset()
        state = env.get_state()
        arrivals = []
        while not env.done.any():
            view = learner.encode(env)
            env.step(learner.act(view, env.action_mask, explore=True))
            arrivals.append(env.last_high_arrival.copy())
        seen = np.stack(arrivals)  # [T, B, n]: the H arrivals do not depend on the policy
        for b in range(2, 8):
            np.testing.assert_array_equal(seen[:, b], seen[:, b % 2])
            np.testing.assert_array_equal(state["seed_key"][b], state["seed_key"][b % 2])
        assert not np.array_equal(seen[:, 0], seen[:, 1])
        learner.end_episode()


def test_es_step_by_hand():
    """The first member pays 10, the others nothing: pair 0's difference is 10, pair 1's is 0;
    scaled by their spread (5) the gradient is ``eps_0``, and Adam's first step
    (``m_hat / sqrt(v_hat)`` = the sign of the gradient) moves every weight by ``lr`` in the
    direction of ``eps_0``."""
    env, learner = make("system1", batch=4, pairs=2, lr=0.25)  # 4 members x 1 copy
    start, eps = learner.theta.copy(), learner.perturbations.copy()
    returns = np.array([10.0, 0.0, 0.0, 0.0])  # members +eps_0, +eps_1, -eps_0, -eps_1
    learner.update(None, None, SimpleNamespace(team_reward=returns), None, None)  # a tick's reward
    learner.end_episode()
    np.testing.assert_allclose(learner.theta, start + 0.25 * np.sign(eps[0]), rtol=1e-6)
    assert learner.steps == 1
    assert not np.array_equal(learner.perturbations, eps)  # the next episode's are new


def test_member_weights_follow_the_perturbations():
    env, learner = make("system1", batch=8, pairs=2, sigma=0.5)
    members = learner.copy_theta.reshape(4, 2, N_FEATURES)  # member-major, 2 copies each
    eps = learner.perturbations
    np.testing.assert_allclose(members[0, 0], learner.theta + 0.5 * eps[0])
    np.testing.assert_allclose(members[3, 1], learner.theta - 0.5 * eps[1])
    with pytest.raises(ValueError, match="training batch 8"):
        view = learner.encode(AuctionEnv(paper_system("system1"), batch_size=3))
        learner.act(view, np.ones((3, 6, 4), bool), explore=True)


def test_batch_must_fit_the_population():
    with pytest.raises(ValueError, match="multiple of 2 \\* pairs = 24"):
        make("system1", batch=30, pairs=12)


def test_save_and_load_round_trip(tmp_path):
    _, learner = make("system1")
    learner.theta = np.arange(N_FEATURES, dtype=float)
    learner.steps = 7
    learner.save(tmp_path)
    _, other = make("system1")
    other.load(tmp_path)
    np.testing.assert_array_equal(other.theta, learner.theta)
    assert other.steps == 7
    with np.load(tmp_path / "reserve_es.npz") as saved:
        files = {k: saved[k] for k in saved.files}
    files["features"] = np.asarray(["bias"] * N_FEATURES)
    np.savez(tmp_path / "reserve_es.npz", **files)
    with pytest.raises(ValueError, match="weights"):
        other.load(tmp_path)


def test_h_preference_picks_who_takes_an_h_slot():
    """theta_H = +1 on versatility: the H slot goes to the capable idle robot with the most
    active types, where the start (all preferences equal) gives it to the one with the fewest."""
    env, learner = make("system1", batch=16, horizon=100)
    versatile = learner.theta.copy()
    versatile[N_LOW + HIGH_FEATURES.index("versatility")] = 1.0
    types = env.active_tasks.sum(axis=1)
    checked = 0
    while not env.done.any():
        mask, view = env.action_mask, learner.encode(env)
        start = learner.act(view, mask, explore=False)
        learner.theta, kept = versatile, learner.theta
        moved = learner.act(view, mask, explore=False)
        learner.theta = kept
        for b in range(env.batch_size):
            if env.slot_high[b, 0] == 1:  # slot 1 holds an H task: the first slot settled
                capable = np.flatnonzero(mask[b, :, 1])
                if len(capable) >= 2 and len(set(types[capable])) > 1:
                    order = sorted(capable, key=lambda i: (types[i], i))
                    assert np.flatnonzero(start[b] == 1).tolist() == [order[0]]
                    most = sorted(capable, key=lambda i: (-types[i], types[i], i))[0]
                    assert types[np.flatnonzero(moved[b] == 1)[0]] == types[most]
                    checked += 1
        env.step(start)
    assert checked > 10
