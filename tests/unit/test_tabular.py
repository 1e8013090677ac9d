from __future__ import annotations

import numpy as np
import pytest

from mrta_rl.envs import AuctionEnv
from mrta_rl.learners.tabular.common import (
    JointActions,
    JointQTable,
    LinearSchedule,
    PendingTransitions,
    apply_updates,
    deconflict,
    greedy_actions,
    spread_actions,
    spread_order,
    visit_alpha,
)
from mrta_rl.learners.tabular.cql import CQLLearner
from mrta_rl.learners.tabular.dql import DQLLearner
from mrta_rl.learners.tabular.semi_cql import SemiCQLLearner
from mrta_rl.learners.tabular.subg_cql import SubGCQLLearner
from mrta_rl.partition import subg_partition
from mrta_rl.systems import build_system
from tests.conftest import paper_system

LEARNERS = [SubGCQLLearner, CQLLearner, SemiCQLLearner, DQLLearner]


@pytest.fixture
def trio():
    """Three robots sharing T1, so joint actions conflict."""
    return build_system(
        {"name": "trio", "robots": {"R1": ["T1", "T2"], "R2": ["T1"], "R3": ["T1", "T2"]}}
    )


def make(cls, system, params=None, batch=4, seed=0, **hp):
    partition = subg_partition(system) if cls.requires_partition else None
    active = partition.active_tasks(system) if partition else None
    env = AuctionEnv(system, params, batch_size=batch, active_tasks=active, seed=seed)
    return env, cls(env=env, rng=np.random.default_rng(seed), partition=partition, **hp)


def play(env, learner, ticks, explore=True, learn=True):
    view = learner.encode(env)
    for _ in range(ticks):
        mask = env.action_mask
        actions = learner.act(view, mask, explore=explore)
        assert mask[np.arange(len(mask))[:, None], np.arange(mask.shape[1]), actions].all()
        result = env.step(actions)
        next_view = learner.encode(env)
        if learn:
            learner.update(view, actions, result, next_view, env.action_mask)
        view = next_view
        if env.done.any():
            env.reset()
            learner.end_episode()
            view = learner.encode(env)


# ------------------------------------------------------------------ joint actions
def test_joint_encode_decode_round_trip():
    joint = JointActions(3, 4)
    actions = np.array([[0, 0, 0], [1, 2, 3], [3, 0, 1], [3, 3, 3]])
    codes = joint.encode(actions)
    assert codes.tolist() == [0, 1 + 2 * 4 + 3 * 16, 3 + 16, 63]  # robot 0 least significant
    assert (joint.decode(codes) == actions).all()
    all_codes = np.arange(joint.count)
    assert (joint.encode(joint.decode(all_codes)) == all_codes).all()


def test_enumerate_valid_is_product_of_valid_actions():
    joint = JointActions(2, 4)
    masks = np.array(
        [
            [[1, 1, 0, 1], [1, 1, 1, 0]],  # robot 0: wait/1/3, robot 1: wait/1/2
            [[1, 0, 0, 0], [1, 0, 0, 0]],  # nobody may bid
        ],
        bool,
    )
    state, codes = joint.enumerate_valid(masks, prune_conflicts=False)
    assert np.bincount(state).tolist() == [9, 1]
    got = {tuple(a) for a in joint.decode(codes[state == 0])}
    assert got == {(a0, a1) for a0 in (0, 1, 3) for a1 in (0, 1, 2)}
    state, codes = joint.enumerate_valid(masks, prune_conflicts=True)
    got = {tuple(a) for a in joint.decode(codes[state == 0])}
    assert got == {(a0, a1) for a0 in (0, 1, 3) for a1 in (0, 1, 2)} - {
        (1, 1)
    }  # two bids for slot 1


def test_deconflict_keeps_the_auction_winner():
    actions = np.array([[1, 1, 2], [1, 1, 1]])
    weight = np.ones((2, 3, 3))
    weight[1, 2, 0] = 2.0  # copy 1: robot 2 is the most willing for slot 1
    assert deconflict(actions, weight).tolist() == [[1, 0, 2], [0, 0, 1]]


def test_table_ties_go_to_the_plain_auction():
    table = JointQTable(2, 4)
    masks = np.array([[[1, 1, 1, 0], [1, 1, 0, 0]]], bool)
    weight = np.ones((1, 2, 3))
    rows = table.rows(np.array([7]), masks, weight)
    greedy = table.actions_of(table.best_entries(rows))
    assert greedy.tolist() == [[1, 0]]  # both bid slot 1, R1 wins: R2's losing bid is pruned
    q = table.state_q(7)
    assert len(q) == 5 and table.joint.encode(np.array([[1, 1]]))[0] not in q
    entry = table.entries_of(rows, table.joint.encode(np.array([[2, 1]])))
    table.q[entry] = 0.5
    assert table.actions_of(table.best_entries(rows)).tolist() == [[2, 1]]
    with pytest.raises(ValueError):
        table.entries_of(rows, table.joint.encode(np.array([[3, 0]])))  # slot 3 masked


def test_spread_actions_give_distinct_slots_in_order():
    masks = np.array(
        [
            [[1, 1, 1, 0], [1, 1, 0, 0], [1, 1, 1, 1]],  # R1: slots 1-2, R2: slot 1, R3: all
            [[1, 0, 0, 0], [1, 0, 1, 0], [1, 0, 1, 0]],  # slot 2 only: R2 bids, R3 waits
        ],
        bool,
    )
    # copy 0: slot 1 -> R1 (lowest index), slot 2 -> R3 (R1 taken, R2 cannot), slot 3 -> nobody
    assert spread_actions(masks).tolist() == [[1, 0, 2], [0, 2, 0]]


def test_spread_actions_ask_robots_in_the_given_order():
    masks = np.array([[[1, 1, 1, 0], [1, 1, 0, 0], [1, 1, 1, 1]]], bool)  # copy 0 above
    # R3 first: slot 1 -> R3, slot 2 -> R1 (R2 cannot), slot 3 -> nobody left who may
    assert spread_actions(masks, [2, 0, 1]).tolist() == [[2, 0, 1]]
    # R2 first: slot 1 -> R2, slot 2 -> R1 (asked before R3), slot 3 -> R3
    assert spread_actions(masks, [1, 0, 2]).tolist() == [[2, 1, 3]]


def test_spread_order_rules():
    active = np.array([[1, 1, 1], [1, 0, 0], [0, 1, 1], [0, 0, 1]], bool)  # 3, 1, 2, 1 types
    assert spread_order(active, "index").tolist() == [0, 1, 2, 3]
    assert spread_order(active, "fewest_types").tolist() == [1, 3, 2, 0]  # ties to lower index
    with pytest.raises(ValueError, match="prior_order must be one of"):
        spread_order(active, "most_types")


def test_subg_cql_asks_robots_with_fewest_kept_types_first():
    system = paper_system("system2")
    partition = subg_partition(system)
    env = AuctionEnv(system, active_tasks=partition.active_tasks(system))
    learner = SubGCQLLearner(env=env, rng=np.random.default_rng(0), partition=partition)
    pairs = zip(learner.groups, learner.tables, strict=True)
    asked = [[system.robots[robots[i]] for i in table.order] for robots, table in pairs]
    # paper Table 4: R2 keeps 3 types (T1, T2, T8), R7 keeps 3 (T4, T6, T7), the others 2
    assert asked == [["R5", "R6", "R8", "R2"], ["R1", "R10"], ["R3", "R4", "R9", "R7"]]
    with pytest.raises(ValueError, match="prior_order"):
        SubGCQLLearner(
            env=env, rng=np.random.default_rng(0), partition=partition, prior_order="nope"
        )


@pytest.mark.parametrize("prior", ["spread", "spread_wait"])
def test_table_prior_is_the_tie_break(prior):
    table = JointQTable(2, 4, prior=prior)
    masks = np.array([[[1, 1, 1, 0], [1, 1, 1, 0]]], bool)
    prior_masks = masks.copy()
    prior_masks[:, :, 2] = False  # e.g. spread_wait holding an L task in slot 2
    rows = table.rows(np.array([3]), masks, np.ones((1, 2, 3)), prior_masks)
    assert table.actions_of(table.best_entries(rows)).tolist() == [[1, 0]]
    assert len(table.state_q(3)) == 7  # the stored actions still follow the full mask
    with pytest.raises(ValueError):
        JointQTable(2, 4, prior="nope")


def test_min_visits_keeps_the_prior_until_an_entry_is_tried():
    table = JointQTable(2, 4, min_visits=2)
    masks = np.array([[[1, 1, 0, 0], [1, 0, 1, 0]]], bool)
    rows = table.rows(np.array([0]), masks, np.ones((1, 2, 3)))
    prior = table.best_entries(rows)
    assert table.actions_of(prior).tolist() == [[1, 2]]  # plain auction: R1 slot 1, R2 slot 2
    other = table.entries_of(rows, table.joint.encode(np.array([[0, 0]])))
    table.q[prior], table.q[other] = -1.0, 5.0  # the untried entry looks better ...
    assert table.best_entries(rows).tolist() == prior.tolist()  # ... but is not a candidate
    assert table.max_q(rows).tolist() == [-1.0]  # eq. (3)'s max over the candidates
    table.visits[other] = 2
    assert table.best_entries(rows).tolist() == other.tolist()
    assert table.max_q(rows).tolist() == [5.0]


@pytest.mark.parametrize("cls", [SubGCQLLearner, CQLLearner])
def test_untrained_spread_prior_plays_spread(cls, trio, tiny_params):
    env, learner = make(cls, trio, tiny_params, batch=6, seed=3, prior="spread")
    while not env.done.any():
        mask = env.action_mask
        actions = learner.act(learner.encode(env), mask, explore=False)
        expected = np.zeros_like(actions)
        for robots, table in zip(learner.groups, learner.tables, strict=True):
            expected[:, robots] = spread_actions(mask[:, robots], table.order)
        np.testing.assert_array_equal(actions, expected)
        env.step(actions)


def test_spread_wait_prior_holds_low_slots_after_a_recent_high(trio, tiny_params):
    env, learner = make(CQLLearner, trio, tiny_params, batch=1, prior="spread_wait")
    env.inject_tasks(0, [{"type": 0, "high": 0, "due": 0, "id": 0, "duration": 4}])
    assert env.action_mask[0, :, 1].all()  # everyone may bid for the L task in slot 1
    env.last_high_arrival[0, 0] = env.t[0] - 2  # an H task of T1 arrived 2 ticks ago: level 0
    assert learner.act(learner.encode(env), env.action_mask, explore=False).tolist() == [[0, 0, 0]]
    env.last_high_arrival[0, :] = env.t[0] - 50  # long ago: spread bids for the L task
    assert learner.act(learner.encode(env), env.action_mask, explore=False).tolist() == [[1, 0, 0]]


# ------------------------------------------------------------------ updates and schedules
def test_apply_updates_is_sequential_eq3():
    q, visits = np.zeros(3), np.zeros(3, np.int64)
    td = apply_updates(q, visits, np.array([1, 1, 2]), np.array([1.0, 2.0, 4.0]), 0.5, 0.0, 0.0)
    assert q.tolist() == [0.0, 0.5 + 0.5 * (2.0 - 0.5), 2.0]  # entry 1: two updates in order
    assert visits.tolist() == [0, 2, 1]
    assert td == pytest.approx((1.0 + 1.5 + 4.0) / 3)
    q, visits = np.zeros(1), np.zeros(1, np.int64)
    apply_updates(q, visits, np.array([0, 0, 0]), np.array([3.0, 6.0, 9.0]), 1.0, 1.0, 0.0)
    assert q[0] == pytest.approx(6.0)  # alpha = 1 / visits: the sample mean


def test_schedules_and_pending_returns():
    eps = LinearSchedule(1.0, 0.0, 4)
    assert [eps(k) for k in range(6)] == [1.0, 0.75, 0.5, 0.25, 0.0, 0.0]
    assert visit_alpha(np.array([1, 4]), 0.5, 0.5, 0.2).tolist() == [0.5, 0.25]
    pending = PendingTransitions((2,))
    pending.start(np.array([True, False]), np.array([5, 6]))
    pending.accumulate(np.array([1.0, 9.0]), 0.9)
    pending.accumulate(np.array([2.0, 9.0]), 0.9)
    (pos,), entries, ret, discount = pending.close(np.array([True, True]))
    assert pos.tolist() == [0] and entries.tolist() == [5]
    assert ret[0] == pytest.approx(1.0 + 0.9 * 2.0) and discount[0] == pytest.approx(0.81)


# ---------------------------------------------------------------- hand-computed eq. (3), per learn
def _h_task_in_slot_1(env):
    """Copy 0 holds one H task of type T1 (index 0), due now: every idle T1 robot may bid slot 1."""
    env.inject_tasks(0, [{"type": 0, "high": 1, "due": 0, "id": 0, "duration": 5}])


@pytest.mark.parametrize("cls", LEARNERS)
def test_hand_computed_q_update(cls, trio, tiny_params):
    alpha, gamma = 0.5, 0.9
    env, learner = make(
        cls, trio, tiny_params, batch=1, alpha=alpha, gamma=gamma, decisions_only=False
    )
    _h_task_in_slot_1(env)
    view = learner.encode(env)
    actions = np.zeros((1, 3), np.int64)
    actions[0, 1] = 1  # R2 bids for slot 1 and wins the H task
    result = env.step(actions)
    next_view = learner.encode(env)
    next_mask = env.action_mask
    # seed Q(s, a) = 1 and distinct values on s' so that the max over valid next actions matters
    if isinstance(learner, (SubGCQLLearner, CQLLearner)):
        g = next(k for k, rs in enumerate(learner.groups) if 1 in rs)
        table, robots = learner.tables[g], learner.groups[g]
        rows, entries = learner._chosen_entries(view, actions, g)
        next_row = table.rows(
            next_view.states[g], next_mask[:, robots], next_view.slot_weight[:, robots]
        )
        offset, length = int(table._offset.data[next_row[0]]), int(table._length.data[next_row[0]])
        if rows[0] != next_row[0]:
            table.q[offset : offset + length] = np.arange(length) + 2.0
            next_max = length + 1.0
        else:
            next_max = None  # same state: computed below
        table.q[entries[0]] = 1.0
        if next_max is None:
            next_max = float(table.q[offset : offset + length].max())
        reward = (
            result.robot_reward[0, robots].sum() if cls is SubGCQLLearner else result.team_reward[0]
        )
        assert reward == 10.0  # spec step 8: H assignment
        learner.update(view, actions, result, next_view, next_mask)
        assert table.q[entries[0]] == pytest.approx(1.0 + alpha * (10.0 + gamma * next_max - 1.0))
    else:
        bases = learner._bases(view)
        next_bases = learner._bases(next_view)
        entry = bases[0, 1] + 1  # Q_R2(s, bid slot 1)
        for i in range(3):
            learner.q[next_bases[0, i] : next_bases[0, i] + 4] = [3.0, 7.0, 5.0, 9.0]
        learner.q[bases[0, 0] : bases[0, 0] + 4] = 0.0
        learner.q[entry] = 1.0
        valid = next_mask[0, 1]
        next_max = max(v for v, ok in zip([3.0, 7.0, 5.0, 9.0], valid, strict=True) if ok)
        assert result.robot_reward[0, 1] == 10.0
        learner.update(view, actions, result, next_view, next_mask)
        assert learner.q[entry] == pytest.approx(1.0 + alpha * (10.0 + gamma * next_max - 1.0))


# ------------------------------------------------------------------ masking, ties, persistence
@pytest.mark.parametrize("cls", LEARNERS)
def test_epsilon_one_never_picks_an_invalid_action(cls, trio, tiny_params):
    env, learner = make(cls, trio, tiny_params, batch=8, epsilon_start=1.0, epsilon_end=1.0)
    play(env, learner, 60)  # play() asserts validity under the mask; env.step also rejects
    assert learner.learning_space()["visited"] > 0


@pytest.mark.parametrize("cls", LEARNERS)
def test_untrained_learner_plays_the_plain_auction(cls, trio, tiny_params):
    hp = {"prior": "greedy"} if cls in (SubGCQLLearner, CQLLearner) else {}
    env, learner = make(cls, trio, tiny_params, batch=6, seed=3, **hp)
    plain = AuctionEnv(trio, tiny_params, batch_size=6, active_tasks=env.active_tasks, seed=3)
    while not env.done.any():
        env_result = env.step(learner.act(learner.encode(env), env.action_mask, explore=False))
        plain_result = plain.step(greedy_actions(plain.action_mask))
        np.testing.assert_allclose(env_result.team_reward, plain_result.team_reward)


@pytest.mark.parametrize("cls", LEARNERS)
def test_save_load_round_trip(cls, trio, tiny_params, tmp_path):
    env, learner = make(cls, trio, tiny_params, batch=4, seed=1, epsilon_start=0.5)
    play(env, learner, 45)
    learner.save(tmp_path)
    with np.load(tmp_path / "q_tables.npz", allow_pickle=False) as data:
        assert all(data[k].dtype != object for k in data.files)
    env2, restored = make(cls, trio, tiny_params, batch=4, seed=99)
    restored.load(tmp_path)
    assert restored.episodes_done == learner.episodes_done
    assert restored.learning_space() == learner.learning_space()
    saved, again = learner._table_arrays(), restored._table_arrays()
    assert saved.keys() == again.keys()
    for key in saved:
        np.testing.assert_array_equal(saved[key], again[key])
    view = learner.encode(env)
    np.testing.assert_array_equal(
        learner.act(view, env.action_mask, explore=False),
        restored.act(restored.encode(env), env.action_mask, explore=False),
    )
    other = DQLLearner if cls is not DQLLearner else CQLLearner
    with pytest.raises(ValueError):
        make(other, trio, tiny_params)[1].load(tmp_path)


def test_subg_requires_partition_env(trio):
    env = AuctionEnv(trio)
    with pytest.raises(ValueError):
        SubGCQLLearner(env=env, rng=np.random.default_rng(0))
    partition = subg_partition(trio)
    if not np.array_equal(partition.active_tasks(trio), env.active_tasks):
        with pytest.raises(ValueError):
            SubGCQLLearner(env=env, rng=np.random.default_rng(0), partition=partition)
