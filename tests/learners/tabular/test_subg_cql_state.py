"""subG-CQL's group states (``learner.state``, ``encoding.SubGroupEncoder``), by hand."""

from __future__ import annotations

import numpy as np
import pytest

from mrta_rl.config import ConfigError
from mrta_rl.envs import AuctionEnv, AuctionParams
from mrta_rl.envs import encodings as ob
from mrta_rl.learners.memory import (
    GROWTH,
    JOINT_ENTRY_BYTES,
    JOINT_ROW_BYTES,
    conflict_free_joint_actions,
    estimate_resources,
)
from mrta_rl.learners.tabular.qtable import ROW_STATE
from mrta_rl.learners.tabular.subg_cql import SubGCQLLearner
from mrta_rl.partition import subg_partition
from mrta_rl.runners.evaluate import evaluate_policy
from mrta_rl.systems import build_system
from tests.conftest import paper_system
from tests.learners.tabular.tabular_tables import saved_tables

# the trio and its hand-made situation of semi-CQL's states: subg_partition keeps every type,
# one sub-group G1 of all three robots, T_g = {T1, T2}; slot codes 2, 3, 3 (places 1, 5, 25)
from tests.learners.tabular.test_semi_cql_state import SLOTS, TRIO, hand_made

# R1 and R3 idle (R3 with a low battery), R2 busy; recency level 1
HAND = {
    "group": SLOTS + 1 * 125 + 0 * 375 + 2 * 1125 + 1 * 3375,  # robot states 1, 0, 2; radix 3
    "idle": SLOTS + (1 + 4) * 125 + 1 * 125 * 8,  # idle flags of R1 (1) and R3 (4), radix 2^3
}
COUNTS = {"group": 125 * 27 * 3, "idle": 125 * 8 * 3}


def _learner(
    state: str,
    system: dict | None = None,
    batch: int = 1,
    seed: int = 0,
    features: str = "paper",  # the hand-computed states below are of the paper's encoding
    **hp,
) -> tuple[AuctionEnv, SubGCQLLearner]:
    team = build_system(system or TRIO)
    partition = subg_partition(team)
    env = AuctionEnv(
        team, AuctionParams(horizon=20), batch_size=batch, seed=seed,
        active_tasks=partition.active_tasks(team),
    )  # fmt: skip
    rng = np.random.default_rng(seed)
    return env, SubGCQLLearner(
        env=env, rng=rng, partition=partition, state=state, features=features, **hp
    )


def _play(env: AuctionEnv, learner: SubGCQLLearner, episodes: int = 1) -> None:
    for _ in range(episodes):
        env.reset()
        actions = learner.train_tick(env, None)
        while actions is not None:
            actions = learner.train_tick(env, env.step(actions))


@pytest.mark.parametrize("state", HAND)
def test_group_state_by_hand(state):
    """Digits least significant first: slots (``1 + 2n`` = 5 codes each, code ``1 + 2 type +
    high``), the robots' digits, recency (3). ``group`` is the paper's group view (0 busy, 1
    idle, 2 idle with low battery); ``idle`` reads the idle flags and ignores the battery."""
    env, learner = _learner(state)
    hand_made(env)
    assert learner.encode(env).states.tolist() == [[HAND[state]]]
    if state == "group":
        assert ob.group_state_index(env, [0, 1, 2]).tolist() == [HAND[state]]
    # the fused training tick encodes the same state: its row is made
    learner.train_tick(env, None)
    assert learner.storage.rows[ROW_STATE, : learner.storage.n_rows].tolist() == [HAND[state]]


def test_idle_state_with_time_to_free_by_hand():
    """``idle`` with ``time_to_free``: robot digits busy 0 / idle 1 / free soon 2 (radix 3, no
    battery), then recency (3), queued H and L levels over ``T_g`` (3 each). The hand-made
    situation with R2 idle again in 3 ticks (free soon); the queue holds 1 H task (level 1:
    0 < 1 <= 1) and 3 L tasks (level 1: 2 < 3 <= 8)."""
    env, learner = _learner("idle", features="time_to_free")
    hand_made(env)
    env.busy_until[0, 1] = env.t[0] + 2  # idle again at t + 3: within FREE_SOON = 3 ticks
    robots = 1 * 125 + 2 * 375 + 1 * 1125  # R1 idle, R2 free soon, R3 idle (battery ignored)
    expected = SLOTS + robots + 1 * 3375 + 1 * 3375 * 3 + 1 * 3375 * 9
    assert learner.encode(env).states.tolist() == [[expected]]
    assert learner.encoder.counts == [125 * 27 * 3 * 9]
    learner.train_tick(env, None)  # the fused tick adds the same offset
    assert learner.storage.rows[ROW_STATE, : learner.storage.n_rows].tolist() == [expected]


def test_idle_state_of_two_groups_by_hand():
    """G1 = R1, R2 over T1, T2 (radix 5); G2 = R3, R4 over T3 alone (radix 3: empty, L, H).
    Slots H T1, L T3, L T2; R1 busy, R2 idle, R3 idle with a low battery, R4 busy; H arrival 5
    ticks ago in every type (recency level 1)."""
    duo = {"name": "duo", "robots": {"R1": ["T1", "T2"], "R2": ["T1"], "R3": ["T2", "T3"],
                                     "R4": ["T3"]}}  # fmt: skip
    env, learner = _learner("idle", duo)
    assert [g.tolist() for g in learner.groups] == [[0, 1], [2, 3]]
    tasks = [(0, 1), (2, 0), (1, 0), (1, 0)]
    env.inject_tasks(0, [
        {"type": ttype, "high": high, "due": int(env.t[0]), "id": k, "duration": 4}
        for k, (ttype, high) in enumerate(tasks)
    ])  # fmt: skip
    assert env.slot_type[0].tolist() == [0, 2, 1]
    env.busy_until[0] = [env.t[0] + 4, -1, -1, env.t[0] + 4]
    env.idle[0] = [False, True, True, False]
    env.battery[0, 2] = 0.0
    env.last_high_arrival[0, :] = env.t[0] - 5
    # G1: codes H T1 = 2, T3 (not in T_g) = 0 (empty), L T2 = 3; R2 idle (2^1); recency 1
    g1 = 2 + 0 * 5 + 3 * 25 + 2 * 125 + 1 * 125 * 4
    # G2: codes T1, T2 not in T_g = 0, L T3 = 1; R3 idle (2^0), low battery ignored; recency 1
    g2 = 0 + 1 * 3 + 0 * 9 + 1 * 27 + 1 * 27 * 4
    assert learner.encode(env).states[:, 0].tolist() == [g1, g2]
    assert learner.encoder.counts == [125 * 4 * 3, 27 * 4 * 3]


@pytest.mark.parametrize("state", HAND)
def test_learning_space_of_each_state(state):
    """``sum_g |S_g| (K + 1)^{m_g}``: the trio ``|S| x 4^3``; System-II by hand (G1, G3: 4
    robots over 3 types, radix 7; G2: 2 robots over 2 types, radix 5)."""
    _, learner = _learner(state)
    assert learner.learning_space()["analytic"] == COUNTS[state] * 4**3
    system = paper_system("system2")
    partition = subg_partition(system)
    env = AuctionEnv(system, batch_size=1, active_tasks=partition.active_tasks(system))
    learner = SubGCQLLearner(
        env=env, rng=np.random.default_rng(0), partition=partition, state=state, features="paper"
    )
    robots = {"group": lambda m: 3**m, "idle": lambda m: 2**m}[state]
    big, small = 7**3 * robots(4) * 3, 5**3 * robots(2) * 3
    assert learner.encoder.counts == [big, small, big]
    assert learner.learning_space()["analytic"] == 2 * big * 4**4 + small * 4**2


def test_states_stay_below_the_count():
    env, learner = _learner("idle", batch=4, epsilon_start=0.5, epsilon_end=0.5)
    _play(env, learner, 3)
    states = learner.storage.rows[ROW_STATE, : learner.storage.n_rows]
    assert 0 < len(states) and states.max() < COUNTS["idle"]
    assert learner.learning_space()["visited"] > 0


def test_unknown_state_is_refused():
    with pytest.raises(ConfigError, match="state: must be one of"):
        _learner("slots")


def test_untrained_learner_plays_its_prior_with_either_state():
    """A row's entries and prior come from its state's first visit; the idle flags and the slots
    fix the mask (spec step 4), so the untrained ``idle`` learner plays ``spread_wait`` exactly
    as ``group`` does (System-I, 8 episodes)."""
    system = paper_system("system1")
    partition = subg_partition(system)
    returns = {}
    for state in HAND:
        env = AuctionEnv(system, batch_size=8, active_tasks=partition.active_tasks(system))
        learner = SubGCQLLearner(
            env=env, rng=np.random.default_rng(0), partition=partition, state=state
        )
        summary = evaluate_policy(learner, env, 8, seed=5)
        returns[state] = summary.team_return_mean
    assert returns["idle"] == returns["group"]


def test_memory_estimate_bounds_rows_by_the_state_count():
    """Rows at most ``min(|S_g|, decisions)``: 64 copies x 100 episodes x 1,000 ticks of
    System-II pass every count, so G2's table is ``GROWTH x |S_G2| x`` its row."""
    system, params = paper_system("system2"), AuctionParams()
    # 2 robots, K = 3: 4 x 4 joint actions less the 3 with both on one slot
    assert conflict_free_joint_actions(2, 3) == 13
    row = 13 * JOINT_ENTRY_BYTES + JOINT_ROW_BYTES
    for state, count in (("group", 5**3 * 9 * 3), ("idle", 5**3 * 4 * 3)):
        estimate = estimate_resources(
            SubGCQLLearner, system, params, subg_partition(system),
            {"state": state, "features": "paper"},
            batch_size=64, episodes=100,
        )  # fmt: skip
        assert estimate.parts["G2 table"] == GROWTH * count * row, state


def test_save_load_keeps_the_table_and_refuses_another_state(tmp_path):
    env, learner = _learner("idle", batch=4, epsilon_start=0.5, epsilon_end=0.5)
    _play(env, learner)
    learner.save(tmp_path / "idle")
    _, restored = _learner("idle", seed=9)
    restored.load(tmp_path / "idle")
    saved, again = saved_tables(learner), saved_tables(restored)
    assert saved.keys() == again.keys()
    for key, value in saved.items():
        np.testing.assert_array_equal(again[key], value, err_msg=key)
    with pytest.raises(ValueError, match="state.idle"):
        _learner("group")[1].load(tmp_path / "idle")
    env, paper = _learner("group", batch=4, epsilon_start=0.5, epsilon_end=0.5)
    _play(env, paper)
    paper.save(tmp_path / "group")
    with pytest.raises(ValueError, match="state.idle"):
        _learner("idle")[1].load(tmp_path / "group")
