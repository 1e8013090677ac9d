"""The compiled allocation rules (mrta_rl/rules.py) on hand-computed cases and against the env."""

from __future__ import annotations

import numpy as np
import pytest

from mrta_rl import rules
from mrta_rl.envs import AuctionEnv, AuctionParams
from mrta_rl.envs.encodings import recency_level
from mrta_rl.learners import TeamReserveLearner
from tests.conftest import paper_system

# one copy, four robots, K = 3 slots; columns: wait, slot 1, slot 2, slot 3
MASK = np.array(
    [
        [True, False, False, False],  # busy or nothing to bid for: only wait
        [True, True, True, True],  # may bid for every slot
        [True, False, True, True],  # slots 2 and 3
        [True, False, False, True],  # slot 3 only
    ]
)
SLOT_HIGH = np.array([0, 1, 0])  # slot 1 L, slot 2 H, slot 3 L


def run(rule, *args) -> list[int]:
    """The actions ``rule`` writes for the four robots of :data:`MASK`."""
    out = np.full(MASK.shape[0], -1, np.int64)
    rule(*args, out)
    return out.tolist()


def test_greedy_bids_lowest_valid_slot():
    assert run(rules.greedy, MASK) == [0, 1, 2, 3]
    assert [rules.lowest_valid_bid(row) for row in MASK] == [0, 1, 2, 3]


def test_high_only_bids_lowest_high_slot_else_waits():
    assert run(rules.high_only, MASK, SLOT_HIGH) == [0, 2, 2, 0]


def test_valid_action_of_rank_counts_wait_first():
    row = MASK[2]  # wait, slot 2, slot 3
    assert rules.count_valid(row) == 3
    assert [rules.valid_action_of_rank(row, c) for c in range(3)] == [0, 2, 3]
    # u splits [0, 1) into count equal parts, one per valid action in order
    assert [rules.random_valid(row, u) for u in (0.0, 0.33, 0.34, 0.66, 0.67, 0.999)] == [
        0,
        0,
        2,
        2,
        3,
        3,
    ]


def test_spread_gives_distinct_slots_in_order():
    # index order: robot 1 takes slot 1, robot 2 slot 2, robot 3 slot 3
    assert run(rules.spread, MASK, np.arange(4)) == [0, 1, 2, 3]
    # reversed order: slot 1 only robot 1 may take; slot 2 robot 2 (asked before robot 1, who
    # has a bid already); slot 3 robot 3 (asked first)
    assert run(rules.spread, MASK, np.array([3, 2, 1, 0])) == [0, 1, 2, 3]
    # only the rows of order are written
    assert run(rules.spread, MASK, np.array([1, 2])) == [-1, 1, 2, -1]


def test_spread_leaves_robots_without_a_free_slot_waiting():
    mask = np.array([[True, True, False], [True, True, False], [True, True, True]])
    out = np.zeros(3, np.int64)
    rules.spread(mask, np.array([1, 0, 2]), out)
    assert out.tolist() == [0, 1, 2]  # robot 1 asked first for slot 1; robot 0 has no slot left


IDLE = np.ones(4, bool)
EVERY = np.ones(4, bool)


@pytest.mark.parametrize(
    ("idle", "may_take_low", "order", "kept", "expected"),
    [
        # H slot 2: robot 1, the first in order that may; L slot 1: nobody else may; L slot 3:
        # robot 2
        (IDLE, EVERY, [0, 1, 2, 3], 0, [0, 2, 3, 0]),
        # robot 2 asked first: it takes H slot 2; slot 1 to robot 1, slot 3 to robot 3
        (IDLE, EVERY, [2, 3, 0, 1], 0, [0, 1, 2, 3]),
        # keep 2 back: after the H bid 3 idle robots are left; slot 1 leaves 2, slot 3 would not
        (IDLE, EVERY, [2, 3, 0, 1], 2, [0, 1, 2, 0]),
        # keep 3 back: no L bid at all
        (IDLE, EVERY, [2, 3, 0, 1], 3, [0, 0, 2, 0]),
        # robot 1 may not take L now: slot 1 stays empty
        (IDLE, np.array([1, 0, 1, 1], bool), [2, 3, 0, 1], 0, [0, 0, 2, 3]),
        # the reserve counts idle robots with nothing to bid for (robot 0), and a busy robot
        # (robot 3) never bids: robot 0 is the one kept back
        (np.array([1, 1, 1, 0], bool), EVERY, [2, 3, 0, 1], 1, [0, 1, 2, 0]),
        # ... and with robot 0 busy too, robot 1 is the one kept back
        (np.array([0, 1, 1, 0], bool), EVERY, [2, 3, 0, 1], 1, [0, 0, 2, 0]),
    ],
)
def test_reserve_by_hand(idle, may_take_low, order, kept, expected):
    out = np.full(4, -1, np.int64)
    rules.reserve(MASK, SLOT_HIGH, idle, may_take_low, np.array(order), kept, out)
    assert out.tolist() == expected


def test_reserve_writes_only_its_group():
    out = np.full(4, -1, np.int64)
    rules.reserve(MASK, SLOT_HIGH, IDLE, EVERY, np.array([3, 2]), 0, out)
    assert out.tolist() == [-1, -1, 2, 3]


def test_slot_winner_is_the_most_willing_bidder():
    actions = np.array([1, 2, 1, 1])
    assert rules.slot_winner(actions, 1, np.array([0.5, 0.9, 0.8, 0.8])) == 2  # tie to robot 2
    assert rules.slot_winner(actions, 2, np.array([0.5, 0.1, 0.8, 0.8])) == 1  # the only bidder
    assert rules.slot_winner(actions, 3, np.ones(4)) == -1  # nobody bids


def test_deconflict_keeps_the_most_willing_bidder():
    weight = np.array([[0.5, 0.2], [0.9, 0.2], [0.9, 0.7], [0.1, 0.7]])
    actions = np.array([1, 1, 1, 2])
    rules.deconflict(actions, weight)
    assert actions.tolist() == [0, 1, 0, 2]  # slot 1: a tie of 0.9 goes to robot 1
    actions = np.array([2, 0, 2, 2])
    rules.deconflict(actions, weight)
    assert actions.tolist() == [0, 0, 2, 0]  # slot 2: a tie of 0.7 goes to robot 2


def random_masks(rng, count, m=5, k=3):
    """Masks as the env makes them: wait always valid, idle robots bid for some slots."""
    masks = rng.random((count, m, k + 1)) < 0.5
    masks[:, :, 0] = True
    masks[:, :, 1:] &= rng.random((count, m, 1)) < 0.7  # busy robots only wait
    return masks


def test_reserve_without_holding_back_is_spread_on_sorted_slots():
    rng = np.random.default_rng(3)
    masks = random_masks(rng, 300)
    for mask in masks:
        slot_high = np.sort(rng.integers(-1, 2, 3))[::-1].copy()  # H slots before L, then empty
        mask[:, 1:] &= slot_high >= 0  # an empty slot takes no bid
        order = rng.permutation(5)
        idle = mask[:, 1:].any(axis=1) | (rng.random(5) < 0.5)
        a, b = np.zeros(5, np.int64), np.zeros(5, np.int64)
        rules.spread(mask, order, a)
        rules.reserve(mask, slot_high, idle, np.ones(5, bool), order, 0, b)
        np.testing.assert_array_equal(a, b)


# ------------------------------------------------------------------ against the env's kernel
@pytest.mark.parametrize("policy", ["greedy", "high_only"])
def test_rules_are_the_kernels_fixed_policies(policy):
    env = AuctionEnv(paper_system("system2"), AuctionParams(horizon=60), batch_size=4, seed=1)
    out = np.zeros(env.n_robots, np.int64)
    while not env.done.all():
        expected = env.fixed_actions(policy)
        for b in range(env.batch_size):
            if policy == "greedy":
                rules.greedy(env.action_mask[b], out)
            else:
                rules.high_only(env.action_mask[b], env.slot_high[b], out)
            np.testing.assert_array_equal(out, expected[b])
        env.step(expected)


def test_deconflict_keeps_what_the_auction_assigns():
    """Spec step 5 settles the raw bids and the deconflicted ones the same way, tick by tick."""
    system = paper_system("system2")
    raw = AuctionEnv(system, AuctionParams(horizon=60), batch_size=3, seed=4)
    pruned = raw.clone()
    rng = np.random.default_rng(0)
    lost = 0
    while not raw.done.all():
        mask = raw.action_mask
        rank = rng.integers(0, mask.sum(axis=2))
        actions = rules.actions_of_rank(mask, rank)
        weight = np.zeros((3, raw.n_robots, raw.n_actions - 1))
        for b in range(3):
            filled = raw.slot_type[b] >= 0
            weight[b][:, filled] = system.willingness[:, raw.slot_type[b][filled]]
        kept = rules.deconflict_actions(actions, weight)
        lost += int((kept != actions).sum())
        np.testing.assert_array_equal(raw.step(actions).team_reward, pruned.step(kept).team_reward)
        np.testing.assert_array_equal(raw.busy_until, pruned.busy_until)
    np.testing.assert_array_equal(raw.stats.assigned, pruned.stats.assigned)
    assert lost > 0  # some bids were lost, and deconflict turned them into waits


def test_fewest_types_first():
    active = np.array([[1, 1, 1], [1, 0, 0], [0, 1, 1], [0, 0, 1]], bool)  # 3, 1, 2, 1 types
    assert rules.fewest_types_first(active).tolist() == [1, 3, 2, 0]  # ties to the lower index


@pytest.mark.parametrize(("reserve", "hold_level"), [(0, 1), (1, 0), (2, 2)])
def test_team_reserve_learner_plays_reserve(reserve, hold_level):
    env = AuctionEnv(paper_system("system2"), AuctionParams(horizon=80), batch_size=4, seed=2)
    learner = TeamReserveLearner(
        env=env,
        rng=np.random.default_rng(0),
        reserve=reserve,
        hold_level=hold_level,
        hold_scope="robot",
    )
    order = rules.fewest_types_first(env.active_tasks)
    out = np.zeros(env.n_robots, np.int64)
    while not env.done.all():
        expected = learner.act(learner.encode(env), env.action_mask, explore=False)
        may_take_low = recency_level(env, env.active_tasks) >= hold_level
        for b in range(env.batch_size):
            rules.reserve(
                env.action_mask[b],
                env.slot_high[b],
                env.idle[b],
                may_take_low[b],
                order,
                reserve,
                out,
            )
            np.testing.assert_array_equal(out, expected[b])
        env.step(expected)
