"""Tests of the PettingZoo and Gymnasium views (pettingzoo_env.py, gymnasium_env.py)."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml
from gymnasium.utils.env_checker import check_env
from pettingzoo.test import parallel_api_test, parallel_seed_test

from mrta_rl.envs import AuctionEnv, AuctionParams
from mrta_rl.envs import observations as ob
from mrta_rl.envs.gymnasium_env import AuctionGymEnv
from mrta_rl.envs.pettingzoo_env import AuctionParallelEnv, sanitize_actions
from mrta_rl.partition import subg_partition
from mrta_rl.systems import RobotSystem, build_system

ROOT = Path(__file__).resolve().parents[2]
SHORT = AuctionParams(horizon=40)


def load_system(name: str) -> RobotSystem:
    return build_system(yaml.safe_load((ROOT / "conf" / "system" / f"{name}.yaml").read_text()))


def random_valid(mask: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    return (rng.random(mask.shape) * mask).argmax(axis=-1)


def test_sanitize_actions():
    mask = np.array([[[True, True, False], [True, False, False]]])  # [1, 2, 3]
    actions = np.array([[2, 1]])
    assert sanitize_actions(actions, mask, "raise") is actions
    assert sanitize_actions(actions, mask, "wait").tolist() == [[0, 0]]
    assert sanitize_actions(np.array([[1, 7]]), mask, "wait").tolist() == [[1, 0]]
    assert sanitize_actions(np.array([[-1, 0]]), mask, "wait").tolist() == [[0, 0]]


# ---------------------------------------------------------------- PettingZoo
@pytest.mark.parametrize("name", ["system1", "system2"])
def test_parallel_api(name):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # any API warning is a failure
        parallel_api_test(AuctionParallelEnv(load_system(name), SHORT), num_cycles=100)
    partition = subg_partition(load_system(name))
    system = load_system(name)
    parallel_api_test(
        AuctionParallelEnv(system, SHORT, active_tasks=partition.active_tasks(system)), 60
    )


def test_parallel_seed():
    # the seed test samples unmasked actions, hence the lenient mode
    system = load_system("system1")
    parallel_seed_test(lambda: AuctionParallelEnv(system, SHORT, invalid_action="wait"), 50)
    first, second = AuctionParallelEnv(system, SHORT), AuctionParallelEnv(system, SHORT)
    obs1, _ = first.reset(seed=3)
    obs2, _ = second.reset(seed=3)
    for agent in first.agents:
        np.testing.assert_array_equal(obs1[agent]["observation"], obs2[agent]["observation"])


def test_parallel_matches_core():
    system = load_system("system2")
    env = AuctionParallelEnv(system, SHORT)
    core = AuctionEnv(system, SHORT, seed=7)
    obs, infos = env.reset(seed=7)
    assert env.agents == list(system.robots) and set(infos) == set(env.agents)
    rng = np.random.default_rng(0)
    for tick in range(SHORT.horizon):
        features = ob.local_features(core)[0]
        for i, agent in enumerate(env.agents):
            np.testing.assert_array_equal(obs[agent]["observation"], features[i])
            np.testing.assert_array_equal(obs[agent]["action_mask"], core.action_mask[0, i])
            assert env.observation_space(agent).contains(obs[agent])
        np.testing.assert_array_equal(env.state(), ob.global_features(core)[0])
        actions = random_valid(core.action_mask, rng)  # [1, m]
        result = core.step(actions)
        obs, rewards, terms, truncs, infos = env.step(
            dict(zip(env.agents, actions[0].tolist(), strict=True))
        )
        np.testing.assert_allclose([rewards[a] for a in system.robots], result.robot_reward[0])
        team = infos["R1"]["team_reward"]
        assert team == pytest.approx(result.team_reward[0])
        assert sum(rewards.values()) == pytest.approx(team)  # spec step 8
        assert not any(terms.values())
        assert all(v == (tick == SHORT.horizon - 1) for v in truncs.values())
    assert env.agents == []
    with pytest.raises(ValueError, match="reset"):
        env.step({})


def test_parallel_invalid_actions():
    system = load_system("system1")
    for mode in ("raise", "wait"):
        env = AuctionParallelEnv(system, SHORT, invalid_action=mode)
        obs, _ = env.reset(seed=1)
        bad = {
            a: int(np.flatnonzero(obs[a]["action_mask"] == 0)[0])
            for a in env.agents
            if not obs[a]["action_mask"].all()
        }
        assert bad, "every robot could bid for every slot: pick another seed"
        if mode == "raise":
            with pytest.raises(ValueError, match="invalid action"):
                env.step(bad)
        else:
            core = AuctionEnv(system, SHORT, seed=1)
            _, rewards, *_ = env.step(
                bad
            )  # the invalid bids become waits (and missing agents wait)
            np.testing.assert_allclose(
                list(rewards.values()), core.step(np.zeros((1, 6), int)).robot_reward[0]
            )
    with pytest.raises(ValueError):
        AuctionParallelEnv(system, invalid_action="ignore")


# ---------------------------------------------------------------- Gymnasium
@pytest.mark.parametrize("name", ["system1", "system2"])
def test_gym_check_env(name):
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*render modes.*")
        check_env(AuctionGymEnv(load_system(name), SHORT, invalid_action="wait"))


def test_gym_matches_core():
    system = load_system("system1")
    env = AuctionGymEnv(system, SHORT)
    core = AuctionEnv(system, SHORT, seed=4)
    obs, info = env.reset(seed=4)
    env.action_space.seed(2)
    for tick in range(SHORT.horizon):
        assert env.observation_space.contains(obs)
        np.testing.assert_array_equal(obs, ob.global_features(core)[0])
        np.testing.assert_array_equal(info["action_mask"], core.action_mask[0])
        action = env.action_space.sample(mask=tuple(info["action_mask"]))  # valid under the mask
        result = core.step(action[None])
        obs, reward, terminated, truncated, info = env.step(action)
        assert reward == pytest.approx(result.team_reward[0])
        np.testing.assert_allclose(info["robot_reward"], result.robot_reward[0])
        assert not terminated and truncated == (tick == SHORT.horizon - 1)
    with pytest.raises(ValueError, match="reset"):
        env.step(np.zeros(6, int))
    # reset(seed) is deterministic; a reset without seed starts the next episode
    first, _ = env.reset(seed=9)
    again, _ = env.reset(seed=9)
    np.testing.assert_array_equal(first, again)


def test_gym_invalid_actions():
    system = load_system("system1")
    env = AuctionGymEnv(system, SHORT)
    _, info = env.reset(seed=1)
    robot, action = np.argwhere(info["action_mask"] == 0)[0]
    joint = np.zeros(6, int)
    joint[robot] = action
    with pytest.raises(ValueError, match="invalid action"):
        env.step(joint)
    lenient = AuctionGymEnv(system, SHORT, invalid_action="wait")
    lenient.reset(seed=1)
    core = AuctionEnv(system, SHORT, seed=1)
    _, reward, *_ = lenient.step(joint)
    assert reward == pytest.approx(core.step(np.zeros((1, 6), int)).team_reward[0])
