"""CTR, ITR (paper eq. 9) and team return on hand-built EpisodeStats (spec "Metrics")."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from mrta_rl.envs import AuctionEnv, AuctionParams, EpisodeStats
from mrta_rl.learners import GreedyLearner
from mrta_rl.metrics import (
    RunLogger,
    ctr,
    ctr_overall,
    format_percent,
    itr,
    return_by_type,
    summarize,
)

ROBOTS, TYPES = ["R1", "R2"], ["T1", "T2"]


def stats(assigned, dropped, busy, team_return, ticks) -> EpisodeStats:
    return EpisodeStats(
        np.array(assigned),
        np.array(dropped),
        np.array(busy),
        np.array(team_return, float),
        np.array(ticks),
    )


# two batches: the first of two episodes, the second of one; horizon 10
BATCH_A = stats(
    assigned=[[[3, 1], [0, 0]], [[1, 0], [0, 0]]],  # [B=2, n=2, (L, H)]
    dropped=[[[1, 1], [0, 0]], [[0, 0], [0, 0]]],
    busy=[[4, 10], [0, 5]],  # [B, m]
    team_return=[20.0, 8.0],
    ticks=[10, 10],
)
BATCH_B = stats(
    assigned=[[[0, 2], [0, 0]]],
    dropped=[[[0, 0], [2, 0]]],
    busy=[[6, 5]],
    team_return=[14.0],
    ticks=[10],
)


def test_ctr_by_type_and_priority():
    summary = summarize([BATCH_A, BATCH_B], ROBOTS, TYPES)
    # T1 L: assigned 3+1+0 = 4, dropped 1 -> 80 %; T1 H: assigned 1+2 = 3, dropped 1 -> 75 %
    assert summary.ctr["T1"]["L"] == pytest.approx(80.0)
    assert summary.ctr["T1"]["H"] == pytest.approx(75.0)
    # T2 L: nothing assigned, 2 dropped -> 0 %; T2 H: nothing decided -> no CTR
    assert summary.ctr["T2"]["L"] == 0.0
    assert math.isnan(summary.ctr["T2"]["H"])
    # overall L: 4 assigned, 3 dropped -> 400/7 %; overall H: 3 of 4
    assert summary.ctr_overall["L"] == pytest.approx(400 / 7)
    assert summary.ctr_overall["H"] == pytest.approx(75.0)


def test_itr_eq9_and_team_return():
    summary = summarize([BATCH_A, BATCH_B], ROBOTS, TYPES)
    # R1 busy 4 + 0 + 6 = 10 of 30 ticks -> 66.67 % idle; R2 busy 20 of 30 -> 33.33 %
    assert summary.itr["R1"] == pytest.approx(200 / 3)
    assert summary.itr["R2"] == pytest.approx(100 / 3)
    assert summary.episodes == 3
    assert summary.team_return_mean == pytest.approx(14.0)
    assert summary.team_return_std == pytest.approx(math.sqrt((36 + 36 + 0) / 3))
    # per episode, in episode order (batch A's two copies, then batch B's), for paired tests
    assert summary.team_returns == (20.0, 8.0, 14.0)
    assert summary.to_json()["team_return"]["per_episode"] == [20.0, 8.0, 14.0]


def test_functions_match_summary():
    pooled = stats(
        BATCH_A.assigned, BATCH_A.dropped, BATCH_A.busy_ticks, BATCH_A.team_return, BATCH_A.ticks
    )
    np.testing.assert_allclose(ctr(pooled), [[80.0, 50.0], [np.nan, np.nan]])
    np.testing.assert_allclose(ctr_overall(pooled), [80.0, 50.0])
    np.testing.assert_allclose(itr(pooled), [80.0, 25.0])  # idle (20-4)/20 and (20-15)/20


def test_return_by_task_type_by_hand():
    params = AuctionParams(
        reward_assign_high=10, reward_assign_low=2, penalty_drop_high=5, penalty_drop_low=1
    )
    summary = summarize([BATCH_A, BATCH_B], ROBOTS, TYPES, params)
    # T1: assigned 4 L and 3 H, dropped 1 L and 1 H: 4*2 + 3*10 - 1*1 - 1*5 = 32 over 3 episodes
    # T2: dropped 2 L: -2 over 3 episodes
    assert summary.return_by_type == {"T1": pytest.approx(32 / 3), "T2": pytest.approx(-2 / 3)}
    np.testing.assert_allclose(return_by_type(BATCH_B, params), [20.0, -2.0])
    assert summarize([BATCH_A], ROBOTS, TYPES).return_by_type == {}  # no rewards given


def test_json_and_table_show_missing_ctr():
    summary = summarize([BATCH_A, BATCH_B], ROBOTS, TYPES)
    payload = json.loads(json.dumps(summary.to_json(), allow_nan=False))  # no NaN in JSON
    assert payload["ctr"]["T2"]["H"] is None
    keys = {"episodes", "team_return", "ctr", "ctr_overall", "itr", "return_by_type"}
    assert set(payload) == keys
    assert format_percent(summary.ctr["T2"]["H"]) == "-"
    assert format_percent(None) == "-"
    assert format_percent(summary.ctr["T1"]["L"]) == "80.0"


def test_bad_input_is_a_clear_error():
    with pytest.raises(ValueError, match="no episode"):
        summarize([], ROBOTS, TYPES)
    with pytest.raises(ValueError, match="task types"):
        summarize([BATCH_A], ["R1", "R2", "R3"], TYPES)


def test_summary_of_real_episodes_is_consistent(tiny_system, tiny_params, rng):
    env = AuctionEnv(tiny_system, tiny_params, batch_size=3, seed=1)
    learner = GreedyLearner(env=env, rng=rng)
    while not env.done.all():
        env.step(learner.act(None, env.action_mask, explore=False))
    snapshot = env.stats.copy()
    summary = summarize([snapshot], tiny_system.robots, tiny_system.task_types, env.params)
    assert summary.episodes == 3
    assert summary.team_return_mean == pytest.approx(snapshot.team_return.mean())
    # every team reward is a task's assign reward or drop penalty (spec step 8)
    assert sum(summary.return_by_type.values()) == pytest.approx(summary.team_return_mean)
    for value in [*summary.itr.values(), *summary.ctr_overall.values()]:
        assert math.isnan(value) or 0.0 <= value <= 100.0


def test_csv_logger(tmp_path):
    with RunLogger(run_dir=tmp_path) as logger:
        logger.log({"env_ticks": 10, "episode": 1, "team_return_mean": 2.5})
        with pytest.raises(ValueError, match="columns"):
            logger.log({"episode": 2})
    assert (tmp_path / "curve.csv").read_text().splitlines() == [
        "env_ticks,episode,team_return_mean",
        "10,1,2.5",
    ]
