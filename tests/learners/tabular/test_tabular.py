from __future__ import annotations

import numpy as np
import pytest

from mrta_rl.config import ConfigError
from mrta_rl.envs import AuctionEnv
from mrta_rl.envs import encodings as ob
from mrta_rl.learners.fixed import TeamReserveLearner
from mrta_rl.learners.tabular import group_kernels, robot_kernels
from mrta_rl.learners.tabular.base import Uniforms
from mrta_rl.learners.tabular.cql import CQLLearner
from mrta_rl.learners.tabular.dql import DQLLearner
from mrta_rl.learners.tabular.encoding import GroupEncoder, LocalEncoder
from mrta_rl.learners.tabular.joint_actions import JointActions, max_valid_joint_actions
from mrta_rl.learners.tabular.qtable import (
    ENTRY_CODE,
    ROW_PRIOR,
    JointQStorage,
    best_entry,
    max_q,
)
from mrta_rl.learners.tabular.schedules import LinearSchedule, visit_alpha
from mrta_rl.learners.tabular.semi_cql import SemiCQLLearner
from mrta_rl.learners.tabular.subg_cql import SubGCQLLearner
from mrta_rl.partition import subg_partition
from mrta_rl.priors import PRIOR_CODES, spread_order
from mrta_rl.rules import deconflict_actions as deconflict
from mrta_rl.rules import greedy_actions, random_valid_actions, spread_actions
from mrta_rl.systems import build_system
from tests.conftest import paper_system
from tests.learners.tabular.tabular_tables import (
    CASES,
    EXPLORE,
    FIXTURE,
    HORIZON,
    play,
    play_tables,
    saved_tables,
    train,
)

LEARNERS = [SubGCQLLearner, CQLLearner, SemiCQLLearner, DQLLearner]
# time_to_free digits need semi-CQL's paper-era whole-system state (its default is coarser)
SYSTEM_STATE = {SemiCQLLearner: {"state": "system"}}


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


def one_row(masks, prior="greedy", prior_masks=None, weight=None, state=7, prune=True):
    """Storage of one group of ``m_g`` robots 0..m_g-1 holding the row of one state."""
    masks = np.asarray(masks, bool)  # [1, m_g, K + 1]
    n, n_actions = masks.shape[1], masks.shape[2]
    storage = JointQStorage(1)
    storage.reserve(1, max_valid_joint_actions(n, n_actions, prune))
    weight_by_type = np.ones((2, n)) if weight is None else weight  # type 0, empty slot
    slot_type = np.zeros((1, n_actions - 1), np.int64)
    slot_high = np.zeros((1, n_actions - 1), np.int64)  # all L: spread_wait may hold them
    hold = np.array([prior_masks is not None])
    rows = np.empty(1, np.int64)
    robots = np.arange(n)[None]
    learner = group_kernels.learner_of(
        (
            tuple(getattr(storage, name) for name in group_kernels.QTable._fields),
            (robots, np.array([n]), robots, weight_by_type),
            kernel_settings(prior=PRIOR_CODES[prior], prune=prune),
        )
    )
    seen = group_kernels.Decision(np.array([[state]]), hold[None], masks, slot_type, slot_high)
    group_kernels.rows_of(learner, 0, seen, np.array([True]), rows)
    return storage, int(rows[0])


def kernel_settings(**settings):
    """``group_kernels.Settings`` as a tuple: these ``settings``, the others plain."""
    plain = dict(decisions_only=True, prior=0, prune=True, min_visits=0, lcb=0.0)
    plain |= dict(prior_target=False, gamma=0.9, alpha=0.1, alpha_power=0.0, alpha_min=0.0)
    return tuple(group_kernels.Settings(**(plain | settings)))


def best_actions(storage, row, n, min_visits=0):
    entry = best_entry(storage.rows, storage.entries, storage.q, row, min_visits)
    return JointActions(n, 4).decode(storage.entries[ENTRY_CODE, [entry]])[0].tolist()


def entry_of(storage, row, actions):
    code = JointActions(len(actions), 4).encode(np.array([actions]))[0]
    at = storage.row_entries(row)
    return at.start + int(np.flatnonzero(storage.entries[ENTRY_CODE, at] == code)[0])


def test_table_ties_go_to_the_plain_auction():
    storage, row = one_row([[[1, 1, 1, 0], [1, 1, 0, 0]]])
    assert best_actions(storage, row, 2) == [1, 0]  # both bid slot 1, R1 wins: R2's bid pruned
    q = storage.state_q(0, 7)
    assert len(q) == 5 and JointActions(2, 4).encode(np.array([[1, 1]]))[0] not in q
    storage.q[entry_of(storage, row, [2, 1])] = 0.5
    assert best_actions(storage, row, 2) == [2, 1]
    assert storage.row(0, 7) == row and storage.row(0, 8) == -1 and storage.row(1, 7) == -1


def test_greedy_prior_keeps_the_most_willing_bidder():
    weight = np.array([[1.0, 2.0], [0.0, 0.0]])  # T1: R2 more willing than R1
    storage, row = one_row([[[1, 1, 0, 0], [1, 1, 0, 0]]], weight=weight)
    assert best_actions(storage, row, 2) == [0, 1]  # spec step 5: R2 wins slot 1


def test_storage_grows_and_finds_every_row():
    storage = JointQStorage(2)
    rows = np.empty(300, np.int64)
    masks = np.ones((300, 2, 4), bool)
    zeros = np.zeros((300, 3), np.int64)
    robots = np.array([[0, 1], [0, 1]])
    groups = (robots, np.array([2, 2]), robots, np.ones((2, 2)))
    for g in (1, 0):  # 600 rows: the hash table (1024 slots, half full at most) grows
        storage.reserve(300, 300 * 13)
        states = np.zeros((2, 300), np.int64)
        states[g] = np.arange(300, dtype=np.int64)[::-1] * 1_000_003
        table = tuple(getattr(storage, name) for name in group_kernels.QTable._fields)
        learner = group_kernels.learner_of((table, groups, kernel_settings()))
        seen = group_kernels.Decision(states, np.zeros((2, 300), bool), masks, zeros, zeros)
        group_kernels.rows_of(learner, g, seen, np.ones(300, bool), rows)
        assert (np.diff(storage.rows[0, storage.group_rows(g)]) > 0).all()  # created in order
    assert storage.hash.shape[1] > 1024 and storage.n_rows == 600
    assert storage.n_entries == 600 * max_valid_joint_actions(2, 4, True) == 600 * 13
    assert all(storage.row(g, s * 1_000_003) >= 0 for g in (0, 1) for s in range(300))
    again = JointQStorage(2)
    again.from_arrays([storage.to_arrays(0), storage.to_arrays(1)])
    for g in (0, 1):
        for key, value in storage.to_arrays(g).items():
            np.testing.assert_array_equal(again.to_arrays(g)[key], value)


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
    orders = [learner.order[g, : len(robots)] for g, robots in enumerate(learner.groups)]
    asked = [
        [system.robots[robots[i]] for i in order]
        for robots, order in zip(learner.groups, orders, strict=True)
    ]
    # paper Table 4: R2 keeps 3 types (T1, T2, T8), R7 keeps 3 (T4, T6, T7), the others 2
    assert asked == [["R5", "R6", "R8", "R2"], ["R1", "R10"], ["R3", "R4", "R9", "R7"]]
    with pytest.raises(ValueError, match="prior_order"):
        SubGCQLLearner(
            env=env, rng=np.random.default_rng(0), partition=partition, prior_order="nope"
        )


@pytest.mark.parametrize("prior", ["spread", "spread_wait"])
def test_table_prior_is_the_tie_break(prior):
    masks = [[[1, 1, 1, 0], [1, 1, 1, 0]]]
    hold = [[[1, 1, 0, 0], [1, 1, 0, 0]]] if prior == "spread_wait" else None
    storage, row = one_row(masks, prior=prior, prior_masks=hold)
    # spread: R1 slot 1, R2 slot 2; spread_wait holds the L slots: nobody bids
    assert best_actions(storage, row, 2) == ([1, 2] if prior == "spread" else [0, 0])
    assert len(storage.state_q(0, 7)) == 7  # the stored actions still follow the full mask
    with pytest.raises(ValueError, match="prior: must be one of"):
        make(CQLLearner, build_system({"name": "x", "robots": {"R1": ["T1"]}}), prior="nope")


def test_min_visits_keeps_the_prior_until_an_entry_is_tried():
    storage, row = one_row([[[1, 1, 0, 0], [1, 0, 1, 0]]])
    prior = entry_of(storage, row, [1, 2])  # plain auction: R1 slot 1, R2 slot 2
    assert best_actions(storage, row, 2, min_visits=2) == [1, 2]
    other = entry_of(storage, row, [0, 0])
    storage.q[prior], storage.q[other] = -1.0, 5.0  # the untried entry looks better ...
    assert best_actions(storage, row, 2, min_visits=2) == [1, 2]  # ... but is not a candidate
    assert max_q(storage.rows, storage.entries, storage.q, row, 2) == -1.0  # eq. (3)'s max
    assert best_actions(storage, row, 2, min_visits=0) == [0, 0]
    storage.visits()[other] = 2
    assert best_actions(storage, row, 2, min_visits=2) == [0, 0]
    assert max_q(storage.rows, storage.entries, storage.q, row, 2) == 5.0


def test_lcb_makes_a_deviation_beat_the_prior_by_more_than_its_noise():
    """Hand-computed: prior Q 1, other entry Q 3 after 4 updates: bound 3 - lcb / 2."""
    storage, row = one_row([[[1, 1, 0, 0], [1, 0, 1, 0]]])
    prior, other = entry_of(storage, row, [1, 2]), entry_of(storage, row, [0, 0])
    storage.q[prior], storage.q[other] = 1.0, 3.0
    storage.visits()[[prior, other]] = 1, 4
    args = (storage.rows, storage.entries, storage.q, row, 0)
    assert best_actions(storage, row, 2) == [0, 0]  # lcb 0: the plain greater Q
    assert best_entry(*args, 3.0) == other and max_q(*args, 3.0) == 1.5  # 3 - 3/2 > 1
    assert best_entry(*args, 5.0) == prior and max_q(*args, 5.0) == 1.0  # 3 - 5/2 < 1


@pytest.mark.parametrize("cls", [SubGCQLLearner, CQLLearner])
def test_untrained_spread_prior_plays_spread(cls, trio, tiny_params):
    env, learner = make(cls, trio, tiny_params, batch=6, seed=3, prior="spread")
    while not env.done.any():
        mask = env.action_mask
        actions = learner.act(learner.encode(env), mask, explore=False)
        expected = np.zeros_like(actions)
        for g, robots in enumerate(learner.groups):
            expected[:, robots] = spread_actions(mask[:, robots], learner.order[g, : len(robots)])
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
def robot_settings(**settings):
    """``robot_kernels.Settings`` as a tuple: these ``settings``, the others plain."""
    plain = dict(decisions_only=True, gamma=0.9, min_visits=0, prior_target=False)
    plain |= dict(alpha=0.1, alpha_power=0.0, alpha_min=0.0)
    return tuple(robot_kernels.Settings(**(plain | settings)))


def test_updates_of_one_entry_are_sequential_eq3():
    """Two copies closing on one entry in a tick: two eq. (3) updates in copy order."""
    q, visits = np.array([0.0, 0.0, 7.0, 3.0]), np.zeros(4, np.int64)
    next_bases = np.array([[2], [2]])  # both copies' next state: Q = [7, 3] over 2 actions
    next_mask = np.array([[[True, False]], [[True, True]]])
    closing = np.ones((2, 1), bool)
    pending = (np.array([[1], [1]]), np.array([[1.0], [2.0]]), np.array([[0.5], [0.5]]))
    no_prior = np.zeros((2, 1), np.int64)  # min_visits 0: every valid action competes
    td = robot_kernels.close_transitions(
        (q, visits),
        (next_bases, next_mask, no_prior),
        robot_settings(alpha=0.5),
        closing,
        pending,
    )
    target = 1.0 + 0.5 * 7.0  # both targets from the table before the tick's updates
    first = 0.5 * target
    assert q[1] == pytest.approx(first + 0.5 * (2.0 + 0.5 * 7.0 - first))
    assert visits.tolist() == [0, 2, 0, 0] and pending[0].tolist() == [[-1], [-1]]
    assert td == pytest.approx(target + (2.0 + 3.5 - first))
    q, visits = np.zeros(2), np.zeros(2, np.int64)
    for target in (3.0, 6.0, 9.0):  # alpha = 1 / visits: the sample mean
        pending = (np.array([[0]]), np.array([[target]]), np.array([[0.0]]))
        robot_kernels.close_transitions(
            (q, visits),
            (np.array([[0]]), next_mask[:1], no_prior[:1]),
            robot_settings(alpha=1.0, alpha_power=1.0),
            closing[:1],
            pending,
        )
    assert q[0] == pytest.approx(6.0)


def test_dql_min_visits_keeps_the_prior_until_an_entry_has_enough_updates():
    """Hand-computed: Q = [0, -1, 5, 2] (wait, slots 1-3), prior = slot 1, visits [0, 1, 2, 3]."""
    q, visits = np.array([0.0, -1.0, 5.0, 2.0]), np.array([0, 1, 2, 3])
    mask, prior = np.ones((1, 1, 4), bool), np.array([[1]])
    bases = np.zeros((1, 1), np.int64)
    chosen = []
    for min_visits in (0, 3, 4):  # all compete: slot 2; visits >= 3: slot 3; only the prior
        actions = np.zeros((1, 1), np.int64)
        robot_kernels.act_robots(
            (q, visits), (bases, mask, prior), min_visits, (0.0, np.zeros(0)), actions
        )
        chosen.append(int(actions[0, 0]))
    assert chosen == [2, 3, 1]
    # eq. (3)'s max over the same competing actions: R = 0, gamma^tau = 1, alpha = 1
    targets = []
    for min_visits, prior_target in ((0, False), (3, False), (4, False), (0, True)):
        qq, vv = np.concatenate([[0.0], q]), np.concatenate([[0], visits])  # entry 0: (s, a)
        pending = (np.array([[0]]), np.array([[0.0]]), np.array([[1.0]]))
        robot_kernels.close_transitions(
            (qq, vv),
            (np.array([[1]]), mask, prior),
            robot_settings(min_visits=min_visits, prior_target=prior_target, alpha=1.0),
            np.ones((1, 1), bool),
            pending,
        )
        targets.append(qq[0])
    # target=prior: the prior's own Q (slot 1), whatever the others hold
    assert targets == [5.0, 2.0, -1.0, -1.0]


def test_schedules_and_pending_returns():
    eps = LinearSchedule(1.0, 0.0, 4)
    assert [eps(k) for k in range(6)] == [1.0, 0.75, 0.5, 0.25, 0.0, 0.0]
    assert visit_alpha(np.array([1, 4]), 0.5, 0.5, 0.2).tolist() == [0.5, 0.25]
    visits = np.arange(1, 50)
    np.testing.assert_array_equal(  # the floats of the vectorised rule, 1/n included
        visit_alpha(visits, 1.0, 1.0, 0.05), np.maximum(0.05, 1.0 * visits.astype(float) ** -1.0)
    )
    pending = (np.full((1, 2), -1), np.zeros((1, 2)), np.ones((1, 2)))
    masks = np.array([[[True, True], [True, False]], [[True, True], [True, True]]])  # tick 1, 2
    closing = np.zeros((1, 2), bool)
    args = (np.array([[5, 6]]), np.zeros((1, 2), np.int64))
    for tick, reward in enumerate(([1.0, 9.0], [2.0, 9.0])):  # robot 1 cannot bid at tick 0
        mask, after = masks[0 if tick == 0 else 1][None], masks[1][None]
        closed = robot_kernels.open_transitions(
            (*args, mask if tick == 0 else np.zeros_like(mask)),
            after if tick else mask,
            (np.array([reward]), np.array([False])),
            pending,
            robot_settings(decisions_only=True, gamma=0.9),
            closing,
        )
    assert closed == 1 and closing.tolist() == [[True, False]]
    assert pending[0].tolist() == [[5, -1]]
    assert pending[1][0, 0] == pytest.approx(1.0 + 0.9 * 2.0)
    assert pending[2][0, 0] == pytest.approx(0.81)


def test_random_valid_actions_are_uniform_over_the_valid_ones():
    mask = np.array([[True, False, True, True]] * 3)
    assert random_valid_actions(mask, np.array([0.0, 0.5, 0.99])).tolist() == [0, 2, 3]


def test_same_tables_as_the_vectorised_learners():
    """Same seeds, same tables as the numpy/dict learners (fixture: ``tabular_tables.py``)."""
    with np.load(FIXTURE, allow_pickle=False) as saved:
        expected = {k: saved[k] for k in saved.files}
    for case, (name, hyperparameters) in CASES.items():
        tables = play_tables(name, hyperparameters)
        keys = sorted(k.removeprefix(f"{case}/") for k in expected if k.startswith(f"{case}/"))
        assert sorted(tables) == keys, case
        for key, value in tables.items():
            np.testing.assert_array_equal(value, expected[f"{case}/{key}"], err_msg=f"{case}/{key}")
        assert any(np.abs(v).max() > 0 for k, v in tables.items() if k.endswith("q")), case


# the fixture's cases, and the priors and options with code of their own in the tick kernels
FUSED_CASES = {
    **CASES,
    "dql/hold": ("dql", {"prior": "hold", "prior_in_state": True, "min_visits": 2, **EXPLORE}),
    "dql/team": ("dql", {"reward": "team", "decisions_only": False, **EXPLORE}),
    "subg_cql/greedy": ("subg_cql", {"prior": "greedy", "prune_conflicts": False, **EXPLORE}),
    "cql/min_visits": ("cql", {"min_visits": 2, "decisions_only": False, **EXPLORE}),
    "cql/every_tick": ("cql", {"decisions_only": False, **EXPLORE}),
}
# the options target, lcb and semi-CQL's min_visits, each with the case it changes
OPTION_CASES = {
    "subg_cql/prior_target_lcb": (
        "subg_cql/explore",
        {"target": "prior", "lcb": 2.0, "min_visits": 1},
    ),
    "subg_cql/team": ("subg_cql/explore", {"reward": "team"}),
    "subg_cql/time_to_free": ("subg_cql/explore", {"features": "time_to_free"}),
    "subg_cql/n_step": ("subg_cql/explore", {"n_step": 3}),
    "subg_cql/n_step_prior_target": ("subg_cql/explore", {"n_step": 2, "target": "prior"}),
    "cql/lcb": ("cql/every_tick", {"lcb": 20.0}),
    "cql/prior_target": ("cql/every_tick", {"target": "prior"}),
    "cql/n_step": ("cql/every_tick", {"n_step": 2}),
    "semi_cql/prior_target": ("semi_cql/explore", {"target": "prior"}),
    "semi_cql/min_visits": ("semi_cql/explore", {"min_visits": 2}),
    "dql/prior_target": ("dql/explore", {"target": "prior"}),
    "dql/hold_prior_target": ("dql/hold", {"target": "prior"}),
    "cql/time_to_free": ("cql/every_tick", {"features": "time_to_free"}),
    "semi_cql/time_to_free": ("semi_cql/explore", {"features": "time_to_free"}),
    "semi_cql/idle_count": ("semi_cql/explore", {"state": "idle_count"}),
    "semi_cql/slots": ("semi_cql/explore", {"state": "slots"}),
    "dql/time_to_free": ("dql/explore", {"features": "time_to_free"}),
    "dql/hold_time_to_free": ("dql/hold", {"features": "time_to_free"}),
}
FUSED_CASES |= {
    case: (FUSED_CASES[base][0], {**FUSED_CASES[base][1], **options})
    for case, (base, options) in OPTION_CASES.items()
}


@pytest.mark.parametrize("case", FUSED_CASES)
def test_train_tick_is_encode_update_act(case):
    """One compiled call per tick builds the tables of encode / update / act, same draws."""
    name, hyperparameters = FUSED_CASES[case]
    ticks = 4 * HORIZON  # whole episodes: the last train_tick of an episode does not act
    plain, fused = (train(name, hyperparameters, ticks, fused=f) for f in (False, True))
    tables, fused_tables = saved_tables(plain), saved_tables(fused)
    assert sorted(tables) == sorted(fused_tables)
    for key, value in tables.items():
        np.testing.assert_array_equal(fused_tables[key], value, err_msg=f"{case}/{key}")
    assert plain.rng.bit_generator.state == fused.rng.bit_generator.state
    assert plain.rng.random() == fused.rng.random()
    if case in OPTION_CASES:  # the options change the tables (else this test could not fail)
        base_name, base_hyperparameters = FUSED_CASES[OPTION_CASES[case][0]]
        base_tables = saved_tables(train(base_name, base_hyperparameters, ticks))
        assert any(
            v.shape != tables[k].shape or not np.array_equal(v, tables[k])
            for k, v in base_tables.items()
        ), case


@pytest.mark.parametrize("cls", LEARNERS)
def test_train_tick_needs_the_start_of_the_episode(cls, trio, tiny_params):
    env, learner = make(cls, trio, tiny_params, batch=2)
    result = env.step(np.zeros((2, env.n_robots), np.int64))
    with pytest.raises(ValueError, match=r"train_tick\(env, None\)"):
        learner.train_tick(env, result)
    env.reset()
    actions = learner.train_tick(env, None)
    assert learner.train_tick(env, env.step(actions)).shape == (2, env.n_robots)


def test_uniforms_drawn_ahead_are_the_plain_stream():
    """Blocks drawn ahead, read in pieces and given back: the draws of ``rng.random()`` calls."""
    rng, plain = np.random.default_rng(3), np.random.default_rng(3)
    uniforms = Uniforms(rng)
    got = []
    for size, count in [(5, 3), (5, 0), (400, 250), (2, 2)]:
        block = uniforms.block(size)
        assert len(block) >= size
        got += block[:count].tolist()
        uniforms.used(count)
    uniforms.settle()
    assert got == plain.random(255).tolist()
    assert rng.random() == plain.random()


@pytest.mark.parametrize("system_name", ["system1", "system2"])
@pytest.mark.parametrize("features", ["paper", "time_to_free"])
def test_compiled_encodings_are_the_observation_codes(features, system_name):
    system = paper_system(system_name)
    env = AuctionEnv(system, batch_size=6, seed=3)
    m = env.n_robots
    groups = [np.array([0, 3, m - 1]), np.arange(m), np.array([m - 1])]
    group_encoder = GroupEncoder(env, groups, features)
    local_encoder = LocalEncoder(env, features)
    group_views = [ob.GroupView(env, robots, features) for robots in groups]  # decode the codes
    local_view = ob.LocalView(env, features)
    rng = np.random.default_rng(0)
    seen, local_seen = set(), set()
    for tick in range(120):
        if tick == 60:  # a full queue in copy 0: 3 H and 9 L tasks of T1 (queue levels 2)
            env.inject_tasks(0, [
                {"type": 0, "high": int(k < 3), "due": int(env.t[0]), "id": k, "duration": 4}
                for k in range(12)
            ])  # fmt: skip
        states, level = group_encoder.index(env)
        for g, robots in enumerate(groups):
            codes = ob.group_state_index(env, robots, features)
            np.testing.assert_array_equal(states[g], codes)
            seen.update(group_views[g].decode(int(c))["robots"].count(3) for c in codes)
            types = env.active_tasks[robots].any(axis=0)
            np.testing.assert_array_equal(level[g], ob.recency_level(env, types))
        local = local_encoder.index(env)
        np.testing.assert_array_equal(local, ob.local_state_index(env, features))
        for (_, robot), code in np.ndenumerate(local):
            fields = local_view.decode(robot, int(code))
            local_seen.add((fields.get("free", 0), fields.get("queue_high", 0),
                            fields.get("queue_low", 0)))  # fmt: skip
        logits = rng.random(env.action_mask.shape) * env.action_mask
        env.step(logits.argmax(axis=2))
        if env.done.any():
            env.reset()
    if features == "time_to_free":  # busy robots free soon were met (robot state 3)
        assert max(seen) > 0
        # every free level and queue level (H and L) was met by the local views
        for part in range(3):
            assert {levels[part] for levels in local_seen} == {0, 1, 2}, part


def robot_q(learner, view) -> list[np.ndarray]:
    """Each robot's Q-values ``[K + 1]`` in copy 0's state of ``view``, as views of ``learner.q``.

    The layout is the one ``save`` writes: DQL ``[robot, state, action]``; semi-CQL ``[row,
    robot, action]`` with row ``r`` the state ``learner.states[r]``.
    """
    m, k1 = learner.n_robots, learner.n_actions
    if isinstance(learner, DQLLearner):
        table = learner.q.reshape(m, -1, k1)
        return [table[i, view.states[0, i]] for i in range(m)]
    row = int(np.flatnonzero(learner.states == view.states[0])[0])
    table = learner.q[: len(learner.states) * m * k1].reshape(-1, m, k1)
    return [table[row, i] for i in range(m)]


# ---------------------------------------------------------------- hand-computed eq. (3), per learn
def _h_task_in_slot_1(env):
    """Copy 0 holds one H task of type T1 (index 0), due now: every idle T1 robot may bid slot 1."""
    env.inject_tasks(0, [{"type": 0, "high": 1, "due": 0, "id": 0, "duration": 5}])


@pytest.mark.parametrize("target", ["max", "prior"])
@pytest.mark.parametrize("cls", LEARNERS)
def test_hand_computed_q_update(cls, target, trio, tiny_params):
    """Eq. (3); with ``target=prior`` the next value is the prior's own Q, not the max."""
    alpha, gamma = 0.5, 0.9
    env, learner = make(
        cls, trio, tiny_params, batch=1, alpha=alpha, gamma=gamma, decisions_only=False,
        target=target,
    )  # fmt: skip
    _h_task_in_slot_1(env)
    view, mask = learner.encode(env), env.action_mask.copy()
    acted = learner.encode(env)  # a view of s of its own for act (update looks up view's rows)
    actions = np.zeros((1, 3), np.int64)
    actions[0, 1] = 1  # R2 bids for slot 1 and wins the H task
    result = env.step(actions)
    next_view = learner.encode(env)
    next_mask = env.action_mask
    # seed Q(s, a) = 1 and distinct values on s' so that the max over valid next actions matters
    if isinstance(learner, (SubGCQLLearner, CQLLearner)):
        g = next(k for k, rs in enumerate(learner.groups) if 1 in rs)
        robots, storage = learner.groups[g], learner.storage
        learner.act(acted, mask, explore=False)  # creates the rows of s (no learning) ...
        learner.act(next_view, next_mask, explore=False)  # ... and of s'
        entry = entry_of(storage, storage.row(g, view.states[g, 0]), actions[0, robots])
        next_row = storage.row(g, next_view.states[g, 0])
        at = storage.row_entries(next_row)
        if storage.row(g, view.states[g, 0]) != next_row:
            storage.q[at] = np.arange(at.stop - at.start) + 2.0
        storage.q[entry] = 1.0
        next_max = float(storage.q[at].max())
        if target == "prior":  # the prior's entry of s', put below the max
            prior_entry = storage.rows[ROW_PRIOR, next_row]
            if prior_entry != entry:
                storage.q[prior_entry] = 1.5
            next_max = float(storage.q[prior_entry])
            assert next_max < float(storage.q[at].max())
        reward = (
            result.robot_reward[0, robots].sum() if cls is SubGCQLLearner else result.team_reward[0]
        )
        assert reward == 10.0  # spec step 8: H assignment
        learner.update(view, actions, result, next_view, next_mask)
        assert storage.q[entry] == pytest.approx(1.0 + alpha * (10.0 + gamma * next_max - 1.0))
    else:
        learner.act(acted, mask, explore=False)  # creates the rows of s (semi-CQL) ...
        learner.act(next_view, next_mask, explore=False)  # ... and of s'
        q_s, q_next = robot_q(learner, view), robot_q(learner, next_view)
        for i in range(3):
            q_next[i][:] = [3.0, 7.0, 5.0, 9.0]
        q_s[0][:] = 0.0
        q_s[1][1] = 1.0  # Q_R2(s, bid slot 1)
        valid = next_mask[0, 1]
        next_max = max(v for v, ok in zip([3.0, 7.0, 5.0, 9.0], valid, strict=True) if ok)
        if target == "prior":  # the plain auction's action of R2 in s' (busy: wait; the
            # kernel test of min_visits checks a prior below the max)
            next_max = [3.0, 7.0, 5.0, 9.0][greedy_actions(next_mask)[0, 1]]
        assert result.robot_reward[0, 1] == 10.0
        learner.update(view, actions, result, next_view, next_mask)
        assert q_s[1][1] == pytest.approx(1.0 + alpha * (10.0 + gamma * next_max - 1.0))


# one robot, two actions (wait, bid slot 1); ticks 0-4 meet states 10-14 with rewards 1, 2, 4, 8,
# 16; state 12 is no decision (no slot), so decision 1's interval is ticks 1-2; tick 4 ends the
# episode. With gamma 1/2 and a state 1k's Q = [10k + 1 (wait), 10k (bid)], V_k is 10k + 1
# (max) or 10k (prior: the bid); the decisions bid (entries e0, e1, e3, e4; e4 is open at the end).
N_STEP_REWARDS = [1.0, 2.0, 4.0, 8.0, 16.0]


def _n_step_targets(n, v):
    """Hand-computed targets of e0, e1, e3 and the tick of each update (gamma = 1/2)."""
    r0, r1, r3 = 1.0, 2.0 + 0.5 * 4.0, 8.0  # R of the intervals after decisions 0, 1, 3
    d0, d1, d3 = 0.5, 0.25, 0.5  # their gamma^tau (decision 1's spans two ticks)
    one = [r0 + d0 * v[1], r1 + d1 * v[3], r3 + d3 * v[4]]
    if n == 1:  # decision 3's update at tick 3; e4's interval has no next state: dropped
        return one, [1, 0, 1, 1, 0]
    two = [r0 + d0 * (r1 + d1 * v[3]), r1 + d1 * (r3 + d3 * v[4])]
    if n == 2:  # at truncation e3 has one interval: bootstrapped from V_4
        return [*two, one[2]], [0, 0, 1, 1, 1]
    three = r0 + d0 * (r1 + d1 * (r3 + d3 * v[4]))
    return [three, two[1], one[2]], [0, 0, 0, 1, 2]  # truncation: e1 two intervals, e3 one


@pytest.mark.parametrize("target", ["max", "prior"])
@pytest.mark.parametrize("n_step", [1, 2, 3])
def test_hand_computed_n_step_targets(n_step, target):
    """``n_step``: the rewards of n decision intervals, then ``gamma^ticks`` times V(s_n)."""
    states = np.array([10, 11, 13, 14])  # the decision states
    mask = np.ones((4, 1, 2), bool)
    storage, rows = JointQStorage(1), np.empty(4, np.int64)
    storage.reserve(4, 8)
    tables = (storage.hash, storage.rows, storage.entries, storage.q, storage.sizes)
    group = (np.array([[0]]), np.array([1]), np.array([[0]]), np.ones((2, 1)))
    slots = np.zeros((1, 1), np.int64)  # one L slot of type 0
    spread = PRIOR_CODES["spread"]
    learner = (
        tables,
        group,
        kernel_settings(
            prior=spread, prior_target=target == "prior", gamma=0.5, alpha=1.0, alpha_power=0.0
        ),
    )
    seen = (states[None], np.zeros((1, 4), bool), mask, slots.repeat(4, 0), slots.repeat(4, 0))
    group_kernels.rows_of(
        group_kernels.learner_of(learner), 0, group_kernels.Decision(*seen), np.ones(4, bool), rows
    )
    bid = {}
    for k, row in zip(states.tolist(), rows.tolist(), strict=True):
        at = storage.row_entries(row)
        bid[k] = at.start + 1  # codes 0 (wait), 1 (bid)
        assert storage.entries[ENTRY_CODE, at].tolist() == [0, 1]
        assert storage.rows[ROW_PRIOR, row] == bid[k]  # the spread prior bids
        storage.q[at] = [10 * (k - 10) + 1.0, 10 * (k - 10)]
    v = {k - 10: float(storage.q[bid[k]] + (target == "max")) for k in states.tolist()}
    pending = (
        np.full((1, 1, n_step), -1),
        np.zeros((1, 1, n_step)),
        np.ones((1, 1, n_step)),
        np.zeros((1, 1), np.int64),
        np.zeros((1, 1), bool),
        np.zeros((1, 1)),
    )
    chosen = [bid[10], bid[11], -1, bid[13], bid[14]]
    counts = []
    for tick, reward in enumerate(N_STEP_REWARDS):
        after = 11 + tick
        next_mask = np.array([[[True, after != 12]]])  # state 12: no slot to bid for
        td_sum, td_count = np.zeros(1), np.zeros(1, np.int64)
        group_kernels.update_groups(
            learner,
            np.array([[chosen[tick]]]),
            (np.array([[after]]), np.zeros((1, 1), bool), next_mask, slots, slots),
            (np.array([[reward]]), np.zeros((1, 1), np.int64), np.array([tick == 4])),
            pending,
            (td_sum, td_count),
        )
        counts.append(int(td_count[0]))
    expected, ticks = _n_step_targets(n_step, v)
    assert counts == ticks
    # alpha 1: each entry holds its one target; e4 (open at truncation) is never updated
    assert storage.q[[bid[10], bid[11], bid[13]]].tolist() == pytest.approx(expected)
    assert storage.q[bid[14]] == 40.0 and storage.entries[1, bid[14]] == 0
    assert pending[3][0, 0] == 0 and not pending[4][0, 0]  # the episode's decisions all closed


@pytest.mark.parametrize(("reward", "learned"), [("group", [10.0, 2.0]), ("team", [12.0, 12.0])])
def test_subg_cql_reward_group_or_team(reward, learned, tiny_params):
    """``reward``: each sub-group learns from its robots' rewards (group) or the team's (team).

    Two sub-groups of one robot each; R1 wins an H task of T1 (10), R2 an L task of T2 (2), in
    the fused training tick. From Q = 0 and a new next state (Q = 0): ``Q(s, a) = alpha r``
    with ``r`` 10 and 2 (group), 12 for both (team).
    """
    duo = build_system({"name": "duo", "robots": {"R1": ["T1"], "R2": ["T2"]}})
    alpha = 0.5
    env, learner = make(
        SubGCQLLearner, duo, tiny_params, batch=1, alpha=alpha, decisions_only=False,
        epsilon_start=0.0, epsilon_end=0.0, prior="spread", reward=reward,
    )  # fmt: skip
    assert [list(rs) for rs in learner.groups] == [[0], [1]]
    env.inject_tasks(0, [
        {"type": 0, "high": 1, "due": 0, "id": 0, "duration": 5},
        {"type": 1, "high": 0, "due": 0, "id": 1, "duration": 5},
    ])  # fmt: skip
    states = learner.encode(env).states[:, 0]  # [G] the state of each group
    actions = learner.train_tick(env, None)
    slot = {int(t): k + 1 for k, t in enumerate(env.slot_type[0]) if t >= 0}
    assert actions.tolist() == [[slot[0], slot[1]]]  # each robot bids for its type's task
    storage = learner.storage
    entries = [  # the entry each group chose: its own robot's bid in its state's row
        entry_of(storage, storage.row(g, states[g]), actions[0, robots])
        for g, robots in enumerate(learner.groups)
    ]
    result = env.step(actions)
    assert result.robot_reward[0].tolist() == [10.0, 2.0]  # spec step 8
    learner.train_tick(env, result)
    assert learner.storage.q[entries].tolist() == pytest.approx([alpha * r for r in learned])


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


@pytest.mark.parametrize("system_name", ["trio", "system2"])
def test_untrained_dql_with_the_hold_prior_plays_team_reserve(system_name, trio, tiny_params):
    """prior=hold: every action of the untrained DQL is the team_reserve rule's, tick by tick."""
    system = trio if system_name == "trio" else paper_system("system2")
    env, learner = make(DQLLearner, system, tiny_params, batch=6, seed=3, prior="hold",
                        prior_reserve=1, prior_hold_level=1, prior_hold_scope="robot")  # fmt: skip
    rule = TeamReserveLearner(
        env=env, rng=np.random.default_rng(0), reserve=1, hold_level=1, hold_scope="robot"
    )
    waited = bid = 0
    while not env.done.any():
        mask = env.action_mask
        actions = learner.act(learner.encode(env), mask, explore=False)
        np.testing.assert_array_equal(actions, rule.act(rule.encode(env), mask, explore=False))
        plain = greedy_actions(mask)
        waited += int(((actions == 0) & (plain > 0)).sum())  # the rule differs from the auction
        bid += int((actions > 0).sum())
        env.step(actions)
    assert waited > 0 and bid > 0


def test_dql_prior_in_state_adds_the_rules_action_as_a_digit(trio, tiny_params):
    """Hand-computed: one L task of T1 in slot 1, all idle, no recent H arrival.

    team_reserve (reserve 0, fewest_types) asks R2 (one type) first: R2 bids for slot 1, R1 and
    R3 wait. With prior_in_state, robot i's state is its local index + action * |S_i|.
    """
    env, learner = make(DQLLearner, trio, tiny_params, batch=1, prior="hold", prior_in_state=True)
    env.inject_tasks(0, [{"type": 0, "high": 0, "due": 0, "id": 0, "duration": 4}])
    env.last_high_arrival[0, :] = env.t[0] - 50  # recency level 2: L slots are not held
    view = learner.encode(env)
    assert view.prior.tolist() == [[0, 1, 0]]
    local = LocalEncoder(env).index(env)
    counts = LocalEncoder(env).counts
    assert view.states.tolist() == [[local[0, 0], local[0, 1] + counts[1], local[0, 2]]]
    assert learner.state_counts == [4 * c for c in counts]
    plain = make(DQLLearner, trio, tiny_params, batch=1)[1]
    assert learner.learning_space()["analytic"] == 4 * plain.learning_space()["analytic"]
    env.last_high_arrival[0, 0] = env.t[0] - 2  # an H task of T1 2 ticks ago: everyone holds
    view = learner.encode(env)
    assert view.prior.tolist() == [[0, 0, 0]]
    assert view.states.tolist() == LocalEncoder(env).index(env).tolist()  # digit 0: unchanged


@pytest.mark.parametrize(
    ("reward", "learned"), [("individual", [0.0, 10.0, 0.0]), ("team", [10.0, 10.0, 10.0])]
)
def test_dql_learns_from_its_own_or_the_team_reward(reward, learned, trio, tiny_params):
    """reward=team: every robot's eq. (3) return is the team reward, not its own.

    R2 wins an H task (10), R1 and R3 wait (0). From Q = 0 with ``alpha = 1`` and
    ``gamma = 0``, each robot's one updated entry holds the reward it learns from.
    """
    env, learner = make(
        DQLLearner, trio, tiny_params, batch=1, alpha=1.0, gamma=0.0, decisions_only=False,
        reward=reward,
    )  # fmt: skip
    _h_task_in_slot_1(env)
    view = learner.encode(env)
    actions = np.array([[0, 1, 0]])
    result = env.step(actions)
    assert result.robot_reward[0].tolist() == [0.0, 10.0, 0.0] and result.team_reward[0] == 10.0
    learner.update(view, actions, result, learner.encode(env), env.action_mask)
    q, visits = learner.q.reshape(3, -1), learner.visits.reshape(3, -1)  # per robot
    assert visits.sum(axis=1).tolist() == [1, 1, 1]
    assert q[visits > 0].tolist() == learned


def test_dql_rejects_bad_priors(trio):
    with pytest.raises(ConfigError, match="prior: must be one of"):
        make(DQLLearner, trio, prior="spread")
    with pytest.raises(ConfigError, match="prior_reserve"):
        make(DQLLearner, trio, prior="hold", prior_reserve=-1)
    with pytest.raises(ConfigError, match="reward: must be one of"):
        make(DQLLearner, trio, reward="mine")
    with pytest.raises(ConfigError, match="min_visits"):
        make(DQLLearner, trio, min_visits=-1)


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
    saved, again = saved_tables(learner), saved_tables(restored)
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


def test_subg_cql_time_to_free_learning_space(tiny_params):
    """Two sub-groups of one robot and one type, K = 3: ``|S_g|`` is ``3^3 * 3 * 3`` (paper) and
    ``3^3 * 4 * 3 * 3 * 3`` (time_to_free), each times ``|A| = 4`` and summed (eq. 16)."""
    duo = build_system({"name": "duo", "robots": {"R1": ["T1"], "R2": ["T2"]}})
    for features, per_group in (("paper", 27 * 3 * 3), ("time_to_free", 27 * 4 * 27)):
        env, learner = make(
            SubGCQLLearner, duo, tiny_params, batch=4, features=features, state="group"
        )
        assert learner.learning_space()["analytic"] == 2 * per_group * 4
        play(env, learner, 60)
        states, _ = learner.encoder.index(env)
        assert (states < per_group).all() and learner.learning_space()["visited"] > 0


def test_dql_time_to_free_local_state_by_hand(trio, tiny_params):
    """Hand-computed local states with ``features=time_to_free`` (encodings, "Features").

    Copy 0 queues an H task of T1 and L tasks of T2, T2, T2, T1: the slots hold H T1, L T2, L T2.
    R1 is idle, R2 busy until t + 1 (idle again in 2 ticks: free level 1), R3 busy until t + 10
    (free level 2); no H arrival for 50 ticks (recency 2); batteries full (level 0). Queue over
    ``Lambda_i``: R1 and R3 (T1, T2) see 1 H (level 1) and 4 L (level 1); R2 (T1) 1 H, 1 L
    (levels 1, 0). Digits (least significant first): free level 3, slots ``1 + 2 |Lambda_i|``,
    battery 2, recency 3, H 3, L 3; slot code ``1 + 2 rank + high`` (0 outside ``Lambda_i``).
    """
    env, learner = make(DQLLearner, trio, tiny_params, batch=1, features="time_to_free")
    tasks = [(0, 1), (1, 0), (1, 0), (1, 0), (0, 0)]  # (type, high)
    env.inject_tasks(0, [
        {"type": ttype, "high": high, "due": int(env.t[0]), "id": k, "duration": 4}
        for k, (ttype, high) in enumerate(tasks)
    ])  # fmt: skip
    assert env.slot_type[0].tolist() == [0, 1, 1] and env.slot_high[0].tolist() == [1, 0, 0]
    env.busy_until[0] = [-1, env.t[0] + 1, env.t[0] + 10]
    env.idle[0] = [True, False, False]
    env.last_high_arrival[0, :] = env.t[0] - 50
    # R1, R3 places 1, 3, 15, 75, 375, 750, 2250, 6750; R2 places 1, 3, 9, 27, 81, 162, 486, 1458
    r1 = 0 + (2 * 3 + 3 * 15 + 3 * 75) + 0 * 375 + 2 * 750 + 1 * 2250 + 1 * 6750
    r2 = 1 + 2 * 3 + 0 * 81 + 2 * 162 + 1 * 486 + 0 * 1458
    r3 = r1 + 2
    assert learner.encode(env).states.tolist() == [[r1, r2, r3]] == [[10776, 817, 10778]]
    np.testing.assert_array_equal(
        learner.encoder.index(env), ob.local_state_index(env, "time_to_free")
    )


def test_time_to_free_learning_space_on_system1():
    """Hand-computed on System-I (6 robots, 5 types, K = 3, ``|A_i| = 4``; ``|Lambda_i|`` 3, 2,
    2, 2, 1, 3): DQL ``sum_i 3 (1 + 2 |Lambda_i|)^3 2 3 3 3 x 4``; the whole-system state
    ``11^3 4^6 3 3 3``, semi-CQL ``6 x 4`` times it, CQL ``4^6`` times it."""
    system = paper_system("system1")
    local = sum(3 * (1 + 2 * n) ** 3 * 2 * 3 * 3 * 3 for n in (3, 2, 2, 2, 1, 3))
    whole = 11**3 * 4**6 * 3 * 3 * 3
    expected = {DQLLearner: local * 4, SemiCQLLearner: whole * 6 * 4, CQLLearner: whole * 4**6}
    assert expected[DQLLearner] == 705_024 and whole == 147_197_952
    for cls, dimension in expected.items():
        hp = SYSTEM_STATE.get(cls, {})
        learner = make(cls, system, batch=1, features="time_to_free", **hp)[1]
        assert learner.learning_space()["analytic"] == dimension, cls.__name__
        paper = make(cls, system, batch=1, **hp)[1].learning_space()["analytic"]
        assert paper < dimension, cls.__name__


TIME_TO_FREE_CASES = [
    (CQLLearner, {}),
    (SemiCQLLearner, SYSTEM_STATE[SemiCQLLearner]),
    (DQLLearner, {}),
    (DQLLearner, {"prior": "hold", "prior_reserve": 1, "prior_in_state": True}),
]


@pytest.mark.parametrize(("cls", "hp"), TIME_TO_FREE_CASES)
def test_untrained_time_to_free_plays_as_paper(cls, hp, tiny_params):
    """Untrained, ``features=time_to_free`` plays the paper encoding's actions (the same prior),
    tick by tick over two episodes of System-II, and its states are observations' codes."""
    system = paper_system("system2")
    (env, paper), (env2, extra) = (
        make(cls, system, tiny_params, batch=5, seed=2, features=f, **hp)
        for f in ("paper", "time_to_free")
    )
    robots = list(range(env.n_robots))
    for _ in range(2):
        while not env.done.any():
            view, view2 = paper.encode(env), extra.encode(env2)
            states = view2.states[0] if cls is CQLLearner else view2.states
            if cls is DQLLearner:
                reference = ob.local_state_index(env2, "time_to_free")
                if extra.prior_in_state:
                    reference = reference + view2.prior * np.array(extra.encoder.counts)
            else:
                reference = ob.group_state_index(env2, robots, "time_to_free")
            np.testing.assert_array_equal(states, reference)
            actions = paper.act(view, env.action_mask, explore=False)
            np.testing.assert_array_equal(
                extra.act(view2, env2.action_mask, explore=False), actions
            )
            env.step(actions)
            env2.step(actions)
        env.reset()
        env2.reset()


def test_subg_requires_partition_env(trio):
    env = AuctionEnv(trio)
    with pytest.raises(ValueError):
        SubGCQLLearner(env=env, rng=np.random.default_rng(0))
    partition = subg_partition(trio)
    if not np.array_equal(partition.active_tasks(trio), env.active_tasks):
        with pytest.raises(ValueError):
            SubGCQLLearner(env=env, rng=np.random.default_rng(0), partition=partition)
