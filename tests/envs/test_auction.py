"""The batched auction dynamics against hand-built cases (one test group per spec step) and the
scalar reference reading of the spec (``reference_auction.py``)."""

from __future__ import annotations

import numpy as np
import pytest

from mrta_rl.config import ConfigError
from mrta_rl.envs import kernel
from mrta_rl.envs.auction import AuctionEnv
from mrta_rl.envs.params import AuctionParams
from mrta_rl.envs.reference import ReferenceAuction
from mrta_rl.envs.tasks import pack_tasks, task_high, task_type
from mrta_rl.systems import RobotSystem, build_system, random_system

SYSTEM1 = {
    "name": "system1",
    "robots": {
        "R1": ["T1", "T4", "T5"],
        "R2": ["T2", "T4"],
        "R3": ["T1", "T3"],
        "R4": ["T4", "T5"],
        "R5": ["T1"],
        "R6": ["T1", "T3", "T5"],
    },
}
# willingness differs, T2 has its own durations: exercises winner choice and duration overrides
MIXED = {
    "name": "mixed",
    "robots": {"R1": {"T1": 0.5, "T2": 1.0}, "R2": {"T1": 0.9}, "R3": {"T1": 0.9, "T2": 0.3}},
    "task_types": {"T2": {"duration_low": [1, 2], "duration_high": [20, 30]}},
}


def task(type=0, high=0, due=0, id=0, duration=4, round=1):
    return dict(type=type, high=high, due=due, id=id, duration=duration, round=round)


def quiet_env(system: dict, batch_size=1, **params) -> AuctionEnv:
    """No arrivals, so hand-built queues are all there is."""
    return AuctionEnv(
        build_system(system), AuctionParams(arrival_rate=0.0, **params), batch_size=batch_size
    )


def waits(env):
    return np.zeros((env.batch_size, env.n_robots), np.int64)


# ---------------------------------------------------------------- the oracle
def random_valid_actions(env, rng):
    """Uniform over each robot's valid actions (wait included)."""
    mask = env.action_mask
    scores = rng.random(mask.shape) * mask
    return scores.argmax(axis=2)


@pytest.mark.parametrize(
    "system, params",
    [
        (SYSTEM1, AuctionParams(horizon=150)),
        (
            MIXED,
            AuctionParams(horizon=150, arrival_rate=1.5, queue_capacity=4, penalty_drop_low=1.0),
        ),
        # a crowded queue: overflow (spec step 2) happens often
        (
            SYSTEM1,
            AuctionParams(horizon=120, arrival_rate=4.0, queue_capacity=5, battery_threshold=90),
        ),
        # task-switch setup cost (docs/spec/auction_env.md)
        (SYSTEM1, AuctionParams(horizon=150, arrival_rate=1.5, queue_capacity=6, switch_ticks=3)),
        (MIXED, AuctionParams(horizon=150, arrival_rate=1.5, switch_ticks=2, battery_threshold=60)),
        # auction zones (docs/spec/auction_env.md): 6 robots in 2 zones of 3 slots each
        (SYSTEM1, AuctionParams(horizon=150, arrival_rate=2.0, slots=6, zones=2)),
    ],
)
def test_batched_dynamics_equal_the_reference_tick_by_tick(system, params):
    rng = np.random.default_rng(0)
    env = AuctionEnv(build_system(system), params, batch_size=3, seed=11)
    refs = [ReferenceAuction(build_system(system), params, copy_seed=11 + b) for b in range(3)]
    for _episode in range(2):
        while not env.done.any():
            for b, ref in enumerate(refs):
                for i in range(env.n_robots):
                    assert list(np.flatnonzero(env.action_mask[b, i])) == ref.valid_actions(i)
            actions = random_valid_actions(env, rng)
            result = env.step(actions)
            for b, ref in enumerate(refs):
                team, robot = ref.step(list(actions[b]))
                assert result.team_reward[b] == pytest.approx(team)
                np.testing.assert_allclose(result.robot_reward[b], robot, atol=1e-9)
                assert list(env.busy_until[b]) == ref.busy_until
        assert env.done.all()
        for b, ref in enumerate(refs):
            np.testing.assert_array_equal(env.stats.assigned[b], ref.assigned)
            np.testing.assert_array_equal(env.stats.dropped[b], ref.dropped)
            np.testing.assert_array_equal(env.stats.busy_ticks[b], ref.busy_ticks)
        assert env.stats.dropped.sum() > 0 and env.stats.assigned.sum() > 0
        env.reset()
        for ref in refs:
            ref.reset()


# ---------------------------------------------------------------- spec step 1: arrivals
def test_arrivals_are_poisson_with_spec_priorities_types_and_durations():
    system = build_system(SYSTEM1)
    params = AuctionParams(queue_capacity=64)
    env = AuctionEnv(system, params, batch_size=20000, seed=5)
    rate = system.n_robots / 6  # spec default arrival_rate = m / 6
    counts = env.queue_length  # at tick 0 the queue holds exactly the tick's arrivals
    se = np.sqrt(rate / len(counts))
    assert abs(counts.mean() - rate) < 4 * se
    assert abs(counts.var() - rate) < 0.05 * rate  # Poisson: variance = mean
    queue = env.get_state()["queue"]
    keys = queue[queue != np.iinfo(np.int64).max]  # an empty place holds the largest key
    high = task_high(keys)
    assert abs(high.mean() - 0.33) < 4 * np.sqrt(0.33 * 0.67 / len(keys))
    type_counts = np.bincount(task_type(keys), minlength=5)
    expected = len(keys) / 5
    chi2 = ((type_counts - expected) ** 2 / expected).sum()
    assert chi2 < 20.5  # 4 dof, p ~ 0.0004
    tasks = [t for b in range(300) for t in env.queued_tasks(b)]
    low_durations = {t["duration"] for t in tasks if not t["high"]}
    high_durations = {t["duration"] for t in tasks if t["high"]}
    assert low_durations == {3, 4, 5, 6} and high_durations == set(range(6, 13))  # ends included


def test_duration_override_per_task_type():
    env = AuctionEnv(
        build_system(MIXED), AuctionParams(queue_capacity=64, arrival_rate=3.0), batch_size=3000
    )
    tasks = [t for b in range(3000) for t in env.queued_tasks(b) if t["type"] == 1]
    assert {t["duration"] for t in tasks if not t["high"]} == {1, 2}
    assert {t["duration"] for t in tasks if t["high"]} <= set(range(20, 31))


# ------------------------------------------------- spec step 2: queue order and overflow
def test_queue_order_is_high_first_then_due_then_id():
    env = quiet_env(SYSTEM1)
    env.inject_tasks(
        0,
        [
            task(id=5, due=0),
            task(id=2, due=0, high=1),
            task(id=1, due=0),
            task(id=0, due=2, high=1, round=2),
        ],
    )
    order = [(x["high"], x["due"], x["id"]) for x in env.queued_tasks(0)]
    assert order == [(1, 0, 2), (1, 2, 0), (0, 0, 1), (0, 0, 5)]


def test_overflow_drops_the_last_tasks_and_pays_their_penalty():
    env = quiet_env(SYSTEM1, queue_capacity=3, penalty_drop_low=1.0)
    keys = [
        pack_tasks(h, 0, i, ty, 4, 0) for i, (h, ty) in enumerate([(0, 0), (1, 1), (0, 2), (1, 3)])
    ]
    env._queue[0, :4] = keys
    env._queue_width = 4
    env._begin_tick(np.ones(1, bool))
    assert [(x["high"], x["id"]) for x in env.queued_tasks(0)] == [(1, 1), (1, 3), (0, 0)]
    assert (
        env.stats.dropped[0, 2, 0] == 1 and env.stats.dropped.sum() == 1
    )  # the L task with id 2 (T3)
    result = env.step(waits(env))
    # the penalty counts in this tick's reward, shared by T3's robots R3 and R6
    assert result.team_reward[0] == pytest.approx(-1.0)
    np.testing.assert_allclose(result.robot_reward[0], [0, 0, -0.5, 0, 0, -0.5])


# ---------------------------------------------------------------- spec step 3: slots
def test_slots_take_the_first_due_tasks_in_queue_order():
    env = quiet_env(SYSTEM1)
    env.t[:] = 1
    env.inject_tasks(
        0,
        [
            task(id=0, high=1, due=3, round=2, type=0),
            task(id=1, high=1, due=1, type=1),
            task(id=2, due=0, type=2),
            task(id=3, due=1, type=3),
            task(id=4, due=1, type=4),
        ],
    )
    assert list(env.slot_type[0]) == [1, 2, 3]  # H task due at 3 waits; the rest in queue order
    assert list(env.slot_high[0]) == [1, 0, 0]


def test_fewer_due_tasks_than_slots_leaves_slots_empty():
    env = quiet_env(SYSTEM1)
    env.inject_tasks(0, [task(type=0)])
    assert list(env.slot_type[0]) == [0, -1, -1]
    assert not env.action_mask[0, :, 2:].any()


# ---------------------------------------------------------------- spec step 4: decisions and masks
def test_masks_allow_only_idle_robots_bidding_for_their_active_types():
    system = build_system(SYSTEM1)
    active = system.rtm.astype(bool)
    active[0, 0] = False  # R1 dropped T1 (as subG-CQL does)
    env = AuctionEnv(system, AuctionParams(arrival_rate=0.0), active_tasks=active)
    env.busy_until[0, 2] = 4  # R3 is busy
    env.inject_tasks(0, [task(type=0), task(type=1, id=1)])
    mask = env.action_mask[0]
    assert mask[:, 0].all()  # waiting is always valid
    assert list(mask[:, 1]) == [
        False,
        False,
        False,
        False,
        True,
        True,
    ]  # T1: R5, R6 (R1 dropped it, R3 busy)
    assert list(mask[:, 2]) == [False, True, False, False, False, False]  # T2: R2 only
    assert not mask[:, 3].any()  # slot 3 is empty


def test_zones_split_the_slots_and_robots_into_separate_auctions():
    # zones = 2: R1-R3 (i * 2 // 6 = 0) bid for slots 1 and 3, R4-R6 for slots 2 and 4
    env = quiet_env(SYSTEM1, slots=4, zones=2)
    env.inject_tasks(0, [task(type=0, id=k) for k in range(4)])  # four T1 tasks
    mask = env.action_mask[0]
    capable = [True, False, True, False, True, True]  # T1: R1, R3, R5, R6
    zone_0 = [True, True, True, False, False, False]
    for slot in (1, 3):
        assert list(mask[:, slot]) == [c and z for c, z in zip(capable, zone_0, strict=True)]
    for slot in (2, 4):
        assert list(mask[:, slot]) == [c and not z for c, z in zip(capable, zone_0, strict=True)]
    with pytest.raises(ValueError, match="slot 2 is not in R1's auction zone 1"):
        env.step(np.array([[2, 0, 0, 0, 0, 0]]))
    # the two zones' greedy bidders win a T1 task each in the same tick
    result = env.step(env.fixed_actions("greedy"))
    assert result.team_reward[0] == 2 * AuctionParams().reward_assign_low
    assert env.stats.assigned[0, 0, 0] == 2


def test_zones_need_a_robot_and_a_slot_each():
    with pytest.raises(ValueError, match="zones .* = 7 exceeds the environment's limit 6"):
        quiet_env(SYSTEM1, slots=8, zones=7)
    with pytest.raises(ConfigError, match="AuctionParams.zones: must be <= slots"):
        AuctionParams(slots=2, zones=3)


def test_a_thousand_robots_bid_for_300_slots():
    # slot indices above 127 are actions like any other (no small-integer ceiling)
    system = random_system(1000, 12, 0.25, seed=0, scale_auction=True)
    env = AuctionEnv(system, AuctionParams.merged(system.env_overrides, {"horizon": 20}), seed=1)
    assert env.n_actions == 301 and env.action_mask.shape == (1, 1000, 301)
    assert env.action_mask[0, :, 128:].any()  # ~167 tasks arrive at tick 0
    stats = env.play("greedy", episodes=1)
    assert stats.assigned.sum() > 0 and stats.ticks[0] == 20


@pytest.mark.parametrize(
    "robot, action, message",
    [
        (1, 1, "R2 may not do T1"),
        (0, 3, "slot 3 is empty"),
        (2, 1, "R3 is busy"),
        (0, 7, "actions are 0..3"),
    ],
)
def test_invalid_action_raises_naming_robot_and_reason(robot, action, message):
    env = quiet_env(SYSTEM1)
    env.busy_until[0, 2] = 4
    env.inject_tasks(0, [task(type=0)])
    actions = waits(env)
    actions[0, robot] = action
    with pytest.raises(ValueError, match=message):
        env.step(actions)


def test_an_invalid_action_changes_nothing():
    """The kernel checks the actions before it writes anything: state and views stay."""
    env = AuctionEnv(build_system(SYSTEM1), AuctionParams(horizon=50), batch_size=3, seed=4)
    for _ in range(5):
        env.step(greedy_actions(env))
    before, views = env.get_state(), (env.slot_type, env.slot_high, env.idle, env.action_mask)
    copies = [v.copy() for v in views]
    actions = greedy_actions(env)
    actions[2, 4] = 7  # out of range in any case
    with pytest.raises(ValueError, match="invalid action 7 for robot R5 in copy 2"):
        env.step(actions)
    for name, value in before.items():
        np.testing.assert_array_equal(env.get_state()[name], value, err_msg=name)
    for now, view, copy in zip(
        (env.slot_type, env.slot_high, env.idle, env.action_mask), views, copies, strict=True
    ):
        assert now is view
        np.testing.assert_array_equal(now, copy)


def test_wrong_action_shape_raises():
    env = quiet_env(SYSTEM1)
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros((1, 3), np.int64))


# ---------------------------------------------------------------- spec step 5: winner determination
def test_highest_willingness_wins_and_ties_go_to_the_lowest_index():
    env = quiet_env(MIXED)
    env.inject_tasks(0, [task(type=0, duration=5)])
    env.step(np.array([[1, 1, 1]]))  # R1 d=0.5, R2 and R3 d=0.9: R2 wins the tie against R3
    assert list(env.busy_until[0]) == [-1, 5, -1]
    assert env.stats.assigned[0, 0, 0] == 1


def test_each_slot_is_settled_separately():
    env = quiet_env(SYSTEM1)
    env.inject_tasks(0, [task(type=0, high=1, duration=7), task(type=3, id=1, duration=3)])
    result = env.step(
        np.array([[1, 2, 0, 2, 1, 0]])
    )  # slot 1 (T1 H): R1, R5; slot 2 (T4 L): R2, R4
    assert list(env.busy_until[0]) == [7, 3, -1, -1, -1, -1]
    assert result.team_reward[0] == pytest.approx(12.0)  # 10 for H + 2 for L (spec defaults)
    np.testing.assert_allclose(result.robot_reward[0], [10, 2, 0, 0, 0, 0])


# ---------------------------------------------------------------- execution and charging
def test_winner_executes_for_the_duration_then_is_idle_again():
    env = quiet_env(SYSTEM1)
    env.inject_tasks(0, [task(type=4, duration=5)])
    env.step(np.array([[1, 0, 0, 0, 0, 0]]))
    assert env.battery[0, 0] == pytest.approx(95.0)  # drain 1.0 per tick of execution
    for tick in range(1, 6):  # executes during ticks 1..5
        assert not env.idle[0, 0], tick
        env.step(waits(env))
    assert env.idle[0, 0]  # idle at tick 6


def test_low_battery_after_a_task_charges_for_charge_ticks_then_is_full():
    env = quiet_env(SYSTEM1)
    env.battery[0, 0] = 24.0
    env.inject_tasks(0, [task(type=4, duration=5)])
    env.step(np.array([[1, 0, 0, 0, 0, 0]]))  # 24 - 5 = 19 < 20: charges right after
    assert env.busy_until[0, 0] == 5 + 10
    assert env.battery[0, 0] == pytest.approx(100.0)


def test_battery_exactly_at_threshold_does_not_charge():
    env = quiet_env(SYSTEM1)
    env.battery[0, 0] = 25.0
    env.inject_tasks(0, [task(type=4, duration=5)])
    env.step(np.array([[1, 0, 0, 0, 0, 0]]))  # 20 is not below 20
    assert env.busy_until[0, 0] == 5 and env.battery[0, 0] == pytest.approx(20.0)


# ------------------------------------------------- spec step 6: re-auction, then drop
def test_unassigned_task_is_auctioned_again_after_the_delay_then_dropped():
    env = quiet_env(SYSTEM1, penalty_drop_high=5.0)
    env.inject_tasks(0, [task(type=0, high=1)])
    env.step(waits(env))  # t=0: first auction fails -> round 2, due 3
    assert env.queued_tasks(0)[0] | {"round": 2, "due": 3} == env.queued_tasks(0)[0]
    for _ in (1, 2):
        assert (env.slot_type[0] == -1).all()  # not due yet
        assert env.step(waits(env)).team_reward[0] == 0
    assert env.slot_type[0, 0] == 0  # t=3: second auction
    result = env.step(waits(env))
    assert env.queue_length[0] == 0 and env.stats.dropped[0, 0, 1] == 1
    assert result.team_reward[0] == pytest.approx(-5.0)
    # shared by the robots whose Lambda holds T1: R1, R3, R5, R6
    np.testing.assert_allclose(result.robot_reward[0], [-1.25, 0, -1.25, 0, -1.25, -1.25])


def test_second_round_task_can_still_be_won():
    env = quiet_env(SYSTEM1)
    env.inject_tasks(0, [task(type=0, round=2, due=0)])
    env.step(np.array([[0, 0, 1, 0, 0, 0]]))
    assert env.stats.assigned[0, 0, 0] == 1 and env.stats.dropped.sum() == 0


# ---------------------------------------------------------------- spec step 7: busy time
def test_busy_time_counts_execution_and_bids_but_not_waiting():
    env = quiet_env(SYSTEM1)
    env.inject_tasks(0, [task(type=0, duration=3)])
    env.step(np.array([[1, 0, 1, 0, 1, 0]]))  # R1 wins; R3 and R5 lose but bid
    assert list(env.stats.busy_ticks[0]) == [1, 0, 1, 0, 1, 0]
    for _ in range(4):
        env.step(waits(env))
    assert list(env.stats.busy_ticks[0]) == [4, 0, 1, 0, 1, 0]  # R1 busy at ticks 0 (bid), 1, 2, 3


# ---------------------------------------------------------------- spec step 8 and episodes
def test_individual_rewards_sum_to_the_team_reward():
    system = build_system(SYSTEM1)
    env = AuctionEnv(system, AuctionParams(horizon=200, penalty_drop_low=0.5), batch_size=8, seed=3)
    rng = np.random.default_rng(1)
    total = 0.0
    while not env.done.any():
        result = env.step(random_valid_actions(env, rng))
        np.testing.assert_allclose(result.robot_reward.sum(axis=1), result.team_reward, atol=1e-9)
        total += result.team_reward.sum()
    assert env.stats.team_return.sum() == pytest.approx(total)
    assert env.stats.ticks.tolist() == [200] * 8


def test_a_copys_individual_rewards_do_not_depend_on_the_batch_size():
    """Spec step 8 shares penalties per copy: copy 0 alone or among 4 gets the same bits."""
    system = random_system(60, 12, 0.25, seed=0, name="random60")
    params = AuctionParams(horizon=100, penalty_drop_low=1.0)
    alone, batch = (AuctionEnv(system, params, batch_size=b, seed=7) for b in (1, 4))
    penalised = 0
    for _ in range(100):
        robot = batch.step(batch.fixed_actions("random")).robot_reward
        np.testing.assert_array_equal(
            alone.step(alone.fixed_actions("random")).robot_reward[0], robot[0]
        )
        penalised += (robot[0] < 0).sum()
    assert penalised > 0  # drops were shared


def test_episode_is_truncated_at_the_horizon_and_step_after_it_raises():
    env = quiet_env(SYSTEM1, horizon=3)
    for _ in range(3):
        assert not env.done.any()
        env.step(waits(env))
    assert env.done.all()
    with pytest.raises(ValueError, match="reset"):
        env.step(waits(env))


def test_same_seed_same_episode_and_copies_do_not_depend_on_the_batch():
    system = build_system(SYSTEM1)
    params = AuctionParams(horizon=80)

    def run(batch_size, seed):
        env = AuctionEnv(system, params, batch_size=batch_size, seed=seed)
        greedy_rewards = []
        while not env.done.any():
            mask = env.action_mask
            actions = np.where(mask[:, :, 1:].any(-1), mask[:, :, 1:].argmax(-1) + 1, 0)
            greedy_rewards.append(env.step(actions).team_reward)
        return np.array(greedy_rewards)

    np.testing.assert_array_equal(run(4, 9), run(4, 9))
    np.testing.assert_array_equal(run(1, 11)[:, 0], run(4, 9)[:, 2])  # copy 2 of seed 9 is seed 11
    assert not np.array_equal(run(1, 12)[:, 0], run(1, 11)[:, 0])


def test_partial_reset_restarts_only_the_masked_copies():
    system = build_system(SYSTEM1)
    params = AuctionParams(horizon=50)
    a = AuctionEnv(system, params, batch_size=3, seed=0)
    b = AuctionEnv(system, params, batch_size=3, seed=0)
    for _ in range(10):
        a.step(waits(a))
        b.step(waits(b))
    b.reset(mask=np.array([False, True, False]))
    assert b.t.tolist() == [10, 0, 10] and b.stats.ticks.tolist() == [10, 0, 10]
    for _ in range(5):
        ra, rb = a.step(waits(a)), b.step(waits(b))
        np.testing.assert_array_equal(ra.team_reward[[0, 2]], rb.team_reward[[0, 2]])
    np.testing.assert_array_equal(a.stats.dropped[[0, 2]], b.stats.dropped[[0, 2]])


def test_active_tasks_must_keep_every_type_and_stay_within_gamma():
    system = build_system(SYSTEM1)
    active = system.rtm.astype(bool)
    active[1, 1] = False  # R2 is T2's only robot
    with pytest.raises(ValueError, match="T2 has no robot left"):
        AuctionEnv(system, active_tasks=active)
    active = system.rtm.astype(bool)
    active[4, 1] = True
    with pytest.raises(ValueError, match="R5 cannot do T2"):
        AuctionEnv(system, active_tasks=active)


def test_system_env_block_sets_parameters_and_run_layer_wins():
    system = RobotSystem.from_table("s", {"R1": ["T1"]}, env={"horizon": 40, "slots": 2})
    params = AuctionParams.merged(system.env_overrides, {"horizon": 30, "p_high": None})
    assert (params.horizon, params.slots, params.p_high) == (30, 2, 0.33)
    with pytest.raises(ValueError, match="env.horizn: unknown setting of AuctionParams"):
        AuctionParams.merged({"horizn": 3})


def test_reset_with_the_done_array_itself_starts_fresh_episodes():
    system = build_system(SYSTEM1)
    params = AuctionParams(horizon=5)
    env = AuctionEnv(system, params, batch_size=4, seed=2)
    for _ in range(5):
        env.step(waits(env))
    env.reset(env.done)  # aliasing: reset clears env.done while it reads the mask
    fresh = AuctionEnv(system, params, batch_size=4, seed=2)
    fresh.reset()  # the second episode of every copy
    np.testing.assert_array_equal(env.queue_length, fresh.queue_length)
    assert env.queue_length.sum() > 0


# ---------------------------------------------------------------- many ticks in one call
def greedy_actions(env):
    mask = env.action_mask[:, :, 1:]
    return np.where(mask.any(-1), mask.argmax(-1) + 1, 0)


def high_only_actions(env):
    mask = env.action_mask[:, :, 1:] & (env.slot_high == 1)[:, None, :]
    return np.where(mask.any(-1), mask.argmax(-1) + 1, 0)


@pytest.mark.parametrize(
    "policy, act", [("greedy", greedy_actions), ("high_only", high_only_actions)]
)
@pytest.mark.parametrize("threads", [1, 2])
def test_play_equals_stepping_the_same_policy(policy, act, threads):
    system = build_system(SYSTEM1)
    params = AuctionParams(horizon=60, queue_capacity=6, penalty_drop_low=1.0)
    stepped = AuctionEnv(system, params, batch_size=3, seed=7)
    rounds = []
    for _ in range(2):
        while not stepped.done.any():
            stepped.step(act(stepped))
        rounds.append(stepped.stats.copy())
        stepped.reset()
    played = AuctionEnv(system, params, batch_size=3, seed=7)
    stats = played.play(policy, episodes=2, threads=threads)
    for field in ("assigned", "dropped", "busy_ticks", "team_return", "ticks"):
        expected = np.concatenate([getattr(r, field) for r in rounds])
        np.testing.assert_array_equal(getattr(stats, field), expected, err_msg=field)
    assert played.done.all() and stats.ticks.tolist() == [60] * 6
    # the finished episodes are not recorded again: the next call starts with episode 3
    while not stepped.done.any():  # the third episode of every copy (reset after the second)
        stepped.step(act(stepped))
    again = played.play(policy, episodes=1, threads=threads)
    np.testing.assert_array_equal(again.team_return, stepped.stats.team_return)


@pytest.mark.parametrize(
    "policy, act",
    [("greedy", greedy_actions), ("high_only", high_only_actions), ("random", None)],
)
def test_fixed_actions_are_the_policies_play_plays(policy, act):
    system = build_system(SYSTEM1)
    params = AuctionParams(horizon=30, queue_capacity=6)
    stepped = AuctionEnv(system, params, batch_size=3, seed=5)
    for _ in range(70):
        actions = stepped.fixed_actions(policy)
        assert stepped.action_mask[np.arange(3)[:, None], np.arange(6), actions].all()
        if act is not None:
            np.testing.assert_array_equal(actions, act(stepped))
        stepped.step(actions)
        if stepped.done.any():
            stepped.reset()
    played = AuctionEnv(system, params, batch_size=3, seed=5)
    assert played.play(policy, ticks=70) == 210
    for name, value in stepped.get_state().items():
        np.testing.assert_array_equal(played.get_state()[name], value, err_msg=name)
    with pytest.raises(ValueError, match="unknown fixed policy 'best'"):
        stepped.fixed_actions("best")


def test_the_named_arrays_are_the_kernels_storage():
    """Every state array the env names is the very memory the kernel reads and writes."""
    env = AuctionEnv(build_system(MIXED), AuctionParams(horizon=40), batch_size=3, seed=1)
    env.step(greedy_actions(env))
    tables, state = kernel.unpack(env._buffers)
    fields = tables._asdict() | state._asdict()
    for name, value in env.get_state().items():
        np.testing.assert_array_equal(fields[name], value, err_msg=name)
        assert np.shares_memory(fields[name], env._state[name]), name
        assert env._state[name].flags.c_contiguous, name
    np.testing.assert_array_equal(fields["willingness"], [[0.5, 0.9, 0.9], [1.0, 0.0, 0.3]])
    np.testing.assert_array_equal(fields["can_do"], [[True, True, True], [True, False, True]])


def test_play_ticks_leaves_the_state_of_stepping_with_resets():
    system = build_system(SYSTEM1)
    params = AuctionParams(horizon=25)
    stepped = AuctionEnv(system, params, batch_size=2, seed=3)
    for _ in range(70):
        stepped.step(greedy_actions(stepped))
        if stepped.done.any():
            stepped.reset()
    played = AuctionEnv(system, params, batch_size=2, seed=3)
    assert played.play("greedy", ticks=70) == 140
    for name, value in stepped.get_state().items():
        np.testing.assert_array_equal(played.get_state()[name], value, err_msg=name)
    np.testing.assert_array_equal(played.action_mask, stepped.action_mask)


def test_play_random_is_deterministic_valid_and_not_greedy():
    system = build_system(SYSTEM1)
    params = AuctionParams(horizon=100)
    a = AuctionEnv(system, params, batch_size=4, seed=1).play("random", episodes=1)
    b = AuctionEnv(system, params, batch_size=4, seed=1).play("random", episodes=1)
    greedy = AuctionEnv(system, params, batch_size=4, seed=1).play("greedy", episodes=1)
    np.testing.assert_array_equal(a.team_return, b.team_return)
    assert a.assigned.sum() > 0 and not np.array_equal(a.assigned, greedy.assigned)
    # random robots wait often, so they bid (and are busy) less than greedy ones
    assert a.busy_ticks.sum() < greedy.busy_ticks.sum()


def test_play_rejects_unknown_policies_and_bad_counts():
    env = AuctionEnv(build_system(SYSTEM1), AuctionParams(horizon=5))
    with pytest.raises(ValueError, match="unknown fixed policy 'greedyy'"):
        env.play("greedyy", episodes=1)
    with pytest.raises(ValueError, match="exactly one"):
        env.play("greedy")
    with pytest.raises(ValueError, match="positive int"):
        env.play("greedy", ticks=0)


# ---------------------------------------------------------------- snapshots
def test_restored_snapshot_replays_the_future_exactly_and_a_clone_steps_the_same():
    system = build_system(MIXED)
    params = AuctionParams(horizon=120, arrival_rate=1.5, queue_capacity=4, penalty_drop_low=1.0)
    env = AuctionEnv(system, params, batch_size=3, seed=5)
    rng = np.random.default_rng(2)
    for _ in range(30):
        env.step(random_valid_actions(env, rng))
    snapshot, twin = env.get_state(), env.clone()
    history = []
    for _ in range(40):
        actions = random_valid_actions(env, rng)
        mask = env.action_mask.copy()
        result = env.step(actions)
        history.append((actions, mask, result.team_reward, result.robot_reward))
        np.testing.assert_array_equal(twin.action_mask, mask)
        twin_result = twin.step(actions)
        np.testing.assert_array_equal(twin_result.team_reward, result.team_reward)
    end = env.get_state()
    env.set_state(snapshot)
    assert env.t.tolist() == [30, 30, 30]
    for actions, mask, team, robot in history:
        np.testing.assert_array_equal(env.action_mask, mask)
        result = env.step(actions)
        np.testing.assert_array_equal(result.team_reward, team)
        np.testing.assert_array_equal(result.robot_reward, robot)
    for name, value in end.items():
        np.testing.assert_array_equal(env.get_state()[name], value, err_msg=name)
        np.testing.assert_array_equal(twin.get_state()[name], value, err_msg=name)


def test_one_copy_broadcast_into_many_then_reseeded_apart():
    system = build_system(SYSTEM1)
    params = AuctionParams(horizon=200)
    source = AuctionEnv(system, params, batch_size=2, seed=8)
    for _ in range(15):
        source.step(greedy_actions(source))
    rollouts = AuctionEnv(system, params, batch_size=4, seed=100)
    rollouts.set_state(source.get_state(copies=[1]))  # [1, ...] arrays into every copy
    for b in range(4):
        np.testing.assert_array_equal(rollouts.action_mask[b], source.action_mask[1])
    same = rollouts.clone()
    for _ in range(10):  # unseeded apart, every copy follows copy 1 of the source
        result, expected = same.step(greedy_actions(same)), source.step(greedy_actions(source))
        assert (result.team_reward == expected.team_reward[1]).all()
    rollouts.reseed([1, 2, 3], [11, 12, 13])
    np.testing.assert_array_equal(
        rollouts.get_state()["episode_key"][1:],
        AuctionEnv(system, params, 3, seed=11).get_state()["episode_key"],
    )
    slots = rollouts.slot_type.copy()
    returns = []
    for _ in range(60):
        rollouts.step(greedy_actions(rollouts))
        returns.append(rollouts.stats.team_return.copy())
    assert (slots == slots[0]).all()  # the current tick is kept
    assert len({tuple(np.array(returns)[:, b]) for b in range(4)}) == 4  # then they diverge


def test_set_state_rejects_a_snapshot_of_another_shape():
    system = build_system(SYSTEM1)
    env = AuctionEnv(system, AuctionParams(horizon=20), batch_size=2)
    other = AuctionEnv(system, AuctionParams(horizon=20, queue_capacity=40), batch_size=2)
    t_before = env.t.copy()
    with pytest.raises(ValueError, match="set_state: queue has shape"):
        env.set_state(other.get_state())
    with pytest.raises(ValueError, match="missing \\['t'\\]"):
        env.set_state({k: v for k, v in env.get_state().items() if k != "t"})
    np.testing.assert_array_equal(env.t, t_before)


# ---------------------------------------------------------------- task-switch cost
def win(env, robot, ttype, duration, id=0):
    """Robot ``robot`` (0-based) alone bids for a fresh task at the current tick of copy 0."""
    env.inject_tasks(0, [task(type=ttype, due=int(env.t[0]), id=id, duration=duration)])
    actions = waits(env)
    actions[0, robot] = 1
    env.step(actions)


def test_switch_cost_only_when_the_type_changes_and_not_for_the_first_task():
    env = quiet_env(SYSTEM1, switch_ticks=2)
    win(env, 0, ttype=4, duration=5)  # t=0, R1's first task (T5): no setup
    assert env.busy_until[0, 0] == 5 and env.battery[0, 0] == pytest.approx(95.0)
    while env.t[0] < 6:
        env.step(waits(env))
    win(env, 0, ttype=0, duration=3, id=1)  # t=6, T1 after T5: 2 setup ticks, then 3 of work
    assert env.busy_until[0, 0] == 6 + 2 + 3
    assert env.battery[0, 0] == pytest.approx(95.0 - 5.0)  # setup drains as execution does
    for _ in range(5):  # setting up and executing: busy
        assert not env.idle[0, 0]
        env.step(waits(env))
    win(env, 0, ttype=0, duration=4, id=2)  # t=12, T1 again: no setup
    assert env.busy_until[0, 0] == 12 + 4 and env.battery[0, 0] == pytest.approx(86.0)
    while env.t[0] < 17:
        env.step(waits(env))
    # busy (spec step 7): bids at 0, 6, 12; work 1-5; setup 7-8 and work 9-11; work 13-16
    assert env.stats.busy_ticks[0, 0] == 3 + 5 + 5 + 4
    assert env.stats.assigned[0].sum() == 3


@pytest.mark.parametrize("switch_ticks, busy_until, battery", [(0, 5, 21.0), (2, 7 + 10, 100.0)])
def test_switch_setup_counts_before_the_battery_threshold(switch_ticks, busy_until, battery):
    env = quiet_env(SYSTEM1, switch_ticks=switch_ticks)
    state = env.get_state()
    state["last_type"][0, 0] = 4  # R1's previous task was a T5
    state["battery"][0, 0] = 26.0
    env.set_state(state)
    win(env, 0, ttype=0, duration=5)  # 26 - 5 = 21 stays; 26 - 7 = 19 < 20 charges
    assert env.busy_until[0, 0] == busy_until
    assert env.battery[0, 0] == pytest.approx(battery)


def test_switch_memory_survives_charging_and_a_reset_forgets_it():
    env = quiet_env(SYSTEM1, switch_ticks=3, battery_threshold=99)
    win(env, 0, ttype=4, duration=2)  # 100 - 2 < 99: charges after its T5
    assert env.busy_until[0, 0] == 2 + 10
    while env.t[0] < 13:
        env.step(waits(env))
    win(env, 0, ttype=4, duration=2, id=1)  # still a T5 after charging: no setup
    assert env.busy_until[0, 0] == 13 + 2 + 10
    env.reset()
    win(env, 0, ttype=0, duration=2)  # first task of the new episode: no setup
    assert env.busy_until[0, 0] == 2 + 10


def test_switch_cost_changes_greedy_on_the_same_task_streams():
    system = build_system(SYSTEM1)
    plain = AuctionEnv(system, AuctionParams(horizon=150)).play("greedy", episodes=1)
    costly = AuctionEnv(system, AuctionParams(horizon=150, switch_ticks=3)).play(
        "greedy", episodes=1
    )
    assert plain.assigned.sum() > costly.assigned.sum()
    assert plain.team_return[0] > costly.team_return[0]
