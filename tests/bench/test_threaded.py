"""ThreadedAuctionEnv gives exactly the results of one AuctionEnv with the same seed."""

from __future__ import annotations

import numpy as np
import pytest

from mrta_rl.bench.threaded import ThreadedAuctionEnv
from mrta_rl.envs import AuctionEnv, AuctionParams
from mrta_rl.systems import build_system
from tests.envs.test_auction import SYSTEM1, random_valid_actions


@pytest.mark.parametrize("threads", [2, 3])
def test_threaded_env_equals_one_env_copy_by_copy(threads):
    system = build_system(SYSTEM1)
    params = AuctionParams(horizon=60, queue_capacity=6, penalty_drop_low=1.0)
    one = AuctionEnv(system, params, batch_size=7, seed=4)
    many = ThreadedAuctionEnv(system, params, batch_size=7, seed=4, threads=threads)
    rng = np.random.default_rng(0)
    for _episode in range(2):
        while not one.done.any():
            np.testing.assert_array_equal(one.action_mask, many.action_mask)
            np.testing.assert_array_equal(one.slot_type, many.slot_type)
            actions = random_valid_actions(one, rng)
            a, b = one.step(actions), many.step(actions)
            np.testing.assert_array_equal(a.team_reward, b.team_reward)
            np.testing.assert_allclose(a.robot_reward, b.robot_reward)
        assert many.done.all()
        for field in ("assigned", "dropped", "busy_ticks", "team_return"):
            np.testing.assert_array_equal(getattr(one.stats, field), getattr(many.stats, field))
        mask = np.array([True, False, True, True, False, True, True])
        one.reset(mask)
        many.reset(mask)
        one.reset(~mask)
        many.reset(~mask)
    many.close()


def test_invalid_action_names_the_copy_of_the_whole_batch_and_moves_no_shard():
    system = build_system(SYSTEM1)
    env = ThreadedAuctionEnv(system, AuctionParams(arrival_rate=0.0), batch_size=4, threads=2)
    actions = np.zeros((4, 6), np.int64)
    actions[3, 1] = 2  # slot 2 is empty everywhere
    with pytest.raises(ValueError, match="robot R2 in copy 3 at tick 0: slot 2 is empty"):
        env.step(actions)
    assert env.t.tolist() == [0, 0, 0, 0]
    env.close()
