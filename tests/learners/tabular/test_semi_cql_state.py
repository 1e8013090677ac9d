"""semi-CQL's coarser shared states (``learner.state``, ``encoding.SystemEncoder``), by hand."""

from __future__ import annotations

import numpy as np
import pytest

from mrta_rl.config import ConfigError
from mrta_rl.envs import AuctionEnv, AuctionParams
from mrta_rl.envs import encodings as ob
from mrta_rl.learners.memory import (
    GROWTH,
    JOINT_ROW_BYTES,
    TABLE_ENTRY_BYTES,
    estimate_resources,
)
from mrta_rl.learners.tabular.semi_cql import SemiCQLLearner
from mrta_rl.systems import build_system
from tests.conftest import paper_system
from tests.learners.tabular.tabular_tables import saved_tables

TRIO = {"name": "trio", "robots": {"R1": ["T1", "T2"], "R2": ["T1"], "R3": ["T1", "T2"]}}
# the hand-made situation below: slot codes 2, 3, 3 (places 1, 5, 25); 5^3 = 125 slot states
SLOTS = 2 + 3 * 5 + 3 * 25
# R1 and R3 idle (R3 with a low battery), R2 busy; recency level 1
HAND = {
    "system": SLOTS + 1 * 125 + 0 * 375 + 2 * 1125 + 1 * 3375,  # robot states 1, 0, 2; radix 3
    "idle_count": SLOTS + 2 * 125 + 1 * 125 * 4,  # two idle robots, radix m + 1 = 4
    "idle": SLOTS + (1 + 4) * 125 + 1 * 125 * 8,  # idle flags of R1 (1) and R3 (4), radix 2^3
    "slots": SLOTS + 1 * 125,
}
COUNTS = {"system": 125 * 27 * 3, "idle_count": 125 * 4 * 3, "idle": 125 * 8 * 3, "slots": 375}


def _learner(state: str, batch: int = 1, seed: int = 0, **hp) -> tuple[AuctionEnv, SemiCQLLearner]:
    env = AuctionEnv(build_system(TRIO), AuctionParams(horizon=20), batch_size=batch, seed=seed)
    return env, SemiCQLLearner(env=env, rng=np.random.default_rng(seed), state=state, **hp)


def hand_made(env: AuctionEnv) -> None:
    """Copy 0: slots H T1, L T2, L T2; R1 idle, R2 busy, R3 idle with a low battery; the last H
    arrival 5 ticks ago (recency level 1: 3 < 5 <= 10)."""
    tasks = [(0, 1), (1, 0), (1, 0), (1, 0)]  # (type, high)
    env.inject_tasks(0, [
        {"type": ttype, "high": high, "due": int(env.t[0]), "id": k, "duration": 4}
        for k, (ttype, high) in enumerate(tasks)
    ])  # fmt: skip
    assert env.slot_type[0].tolist() == [0, 1, 1] and env.slot_high[0].tolist() == [1, 0, 0]
    env.busy_until[0] = [-1, env.t[0] + 4, -1]
    env.idle[0] = [True, False, True]
    env.battery[0, 2] = 0.0  # below the threshold: low
    env.last_high_arrival[0, :] = env.t[0] - 5


@pytest.mark.parametrize("state", HAND)
def test_shared_state_by_hand(state):
    """Digits least significant first: slots (``1 + 2n`` = 5 codes each, code ``1 + 2 type +
    high``), the robots' digits of the state, recency (3). ``system`` is the paper's group view
    (0 busy, 1 idle, 2 idle with low battery); the coarser states ignore the battery."""
    env, learner = _learner(state)
    hand_made(env)
    assert learner.encode(env).states.tolist() == [HAND[state]]
    if state == "system":
        assert ob.group_state_index(env, [0, 1, 2]).tolist() == [HAND[state]]
    # the fused training tick encodes the same state: the row it makes is that state's
    learner.train_tick(env, None)
    assert learner.states.tolist() == [HAND[state]]


@pytest.mark.parametrize("state", HAND)
def test_learning_space_of_each_state(state):
    """Eq. (11) over the shared state: ``m |S| (K + 1)`` = ``3 x |S| x 4``; System-II by hand."""
    _, learner = _learner(state)
    assert learner.learning_space()["analytic"] == 3 * COUNTS[state] * 4
    system2 = AuctionEnv(paper_system("system2"), batch_size=1)
    count = {"system": 17**3 * 3**10 * 3, "idle_count": 17**3 * 11 * 3, "idle": 17**3 * 2**10 * 3}
    count["slots"] = 17**3 * 3
    learner = SemiCQLLearner(env=system2, rng=np.random.default_rng(0), state=state)
    assert learner.learning_space()["analytic"] == 10 * count[state] * 4


@pytest.mark.parametrize("state", HAND)
def test_states_stay_below_the_count_and_the_table_grows(state):
    env, learner = _learner(state, batch=4, epsilon_start=0.5, epsilon_end=0.5)
    actions = learner.train_tick(env, None)
    for _ in range(3):
        while actions is not None:
            actions = learner.train_tick(env, env.step(actions))
        env.reset()
        actions = learner.train_tick(env, None)
    states = learner.states
    assert 0 < len(states) and states.max() < COUNTS[state]
    assert learner.learning_space()["visited"] > 0


def test_coarser_states_take_only_the_paper_features():
    with pytest.raises(ConfigError, match="learner.features must be paper"):
        _learner("idle_count", features="time_to_free")
    with pytest.raises(ConfigError, match="state: must be one of"):
        _learner("robots")


def test_memory_estimate_bounds_rows_by_the_coarser_count():
    """Rows at most ``min(|S|, decisions)``, each ``m (K + 1)`` Q and visits: System-II, 64
    copies x 100 episodes x 1,000 ticks = 6.4 M decisions; ``slots`` has 17^3 x 3 states."""
    system, params = paper_system("system2"), AuctionParams()
    row = 10 * 4 * TABLE_ENTRY_BYTES + JOINT_ROW_BYTES
    for state, rows in (("system", 6_400_000), ("slots", 17**3 * 3)):
        estimate = estimate_resources(
            SemiCQLLearner, system, params, None, {"state": state}, batch_size=64, episodes=100
        )
        assert estimate.parts["table"] == GROWTH * rows * row, state


def test_save_load_keeps_the_coarse_table_and_refuses_another_state(tmp_path):
    env, learner = _learner("idle_count", batch=4, epsilon_start=0.5, epsilon_end=0.5)
    actions = learner.train_tick(env, None)
    while actions is not None:
        actions = learner.train_tick(env, env.step(actions))
    learner.save(tmp_path)
    _, restored = _learner("idle_count", seed=9)
    restored.load(tmp_path)
    saved, again = saved_tables(learner), saved_tables(restored)
    assert saved.keys() == again.keys()
    for key, value in saved.items():
        np.testing.assert_array_equal(again[key], value, err_msg=key)
    # the paper's states of the same play lie past the 1,500 of idle_count
    env, paper = _learner("system", batch=4, epsilon_start=0.5, epsilon_end=0.5)
    actions = paper.train_tick(env, None)
    while actions is not None:
        actions = paper.train_tick(env, env.step(actions))
    paper.save(tmp_path / "system")
    with pytest.raises(ValueError, match="state.idle_count"):
        _learner("idle_count")[1].load(tmp_path / "system")
    # and the other way: the coarse table's small indices would fit the paper's state space
    with pytest.raises(ValueError, match="state.idle_count"):
        _learner("system")[1].load(tmp_path)


def test_a_coarser_state_fits_a_team_whose_paper_state_does_not():
    """45 robots of one type: ``3^3 x 3^45 x 3`` paper states pass int64; ``slots`` has 81,
    ``idle_count`` ``27 x 46 x 3``."""
    team = build_system({"name": "many", "robots": {f"R{i}": ["T1"] for i in range(1, 46)}})
    env = AuctionEnv(team, AuctionParams(horizon=20), batch_size=4, seed=0)
    with pytest.raises(OverflowError):
        SemiCQLLearner(env=env, rng=np.random.default_rng(0), state="system")
    for state, count in (("slots", 81), ("idle_count", 27 * 46 * 3)):
        learner = SemiCQLLearner(env=env, rng=np.random.default_rng(0), state=state)
        assert learner.learning_space()["analytic"] == 45 * count * 4
        env.reset()
        actions = learner.train_tick(env, None)
        while actions is not None:
            actions = learner.train_tick(env, env.step(actions))
        assert 0 < len(learner.states) and learner.states.max() < count
