"""Tests of the PettingZoo and Gymnasium views (pettingzoo_env.py, gymnasium_env.py).

The outside clients run on the views in their DEFAULT configuration: Gymnasium's and SB3's
``check_env``, ``gym.make`` ids, PettingZoo's ``parallel_api_test``, ``parallel_seed_test`` and
AEC ``api_test`` (through ``parallel_to_aec``), sb3-contrib's mask convention.
"""

from __future__ import annotations

import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env
from pettingzoo.test import api_test, parallel_api_test, parallel_seed_test
from pettingzoo.utils.conversions import parallel_to_aec
from sb3_contrib.common.maskable.utils import get_action_masks, is_masking_supported
from stable_baselines3.common.env_checker import check_env as sb3_check_env

from mrta_rl.envs import AuctionEnv, AuctionParams
from mrta_rl.envs import encodings as ob
from mrta_rl.envs.gymnasium_env import GYM_IDS, AuctionGymEnv
from mrta_rl.envs.pettingzoo_env import AuctionParallelEnv
from mrta_rl.envs.view_inputs import resolve_params, resolve_system, sanitize_actions
from mrta_rl.partition import subg_partition
from tests.conftest import paper_system

SHORT = AuctionParams(horizon=40)


def random_valid(mask: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    return (rng.random(mask.shape) * mask).argmax(axis=-1)


def first_stream(env, n_ticks: int = 30) -> list[np.ndarray]:
    """Observations of the first ``n_ticks`` ticks under waits (the task stream alone)."""
    obs, _ = env.reset()
    wait = np.zeros(env.action_space.shape, np.int64)
    return [obs] + [env.step(wait)[0] for _ in range(n_ticks)]


def test_sanitize_actions():
    mask = np.array([[[True, True, False], [True, False, False]]])  # [1, 2, 3]
    actions = np.array([[2, 1]])
    same, flags = sanitize_actions(actions, mask, "raise")
    assert same is actions and not flags.any()
    played, flags = sanitize_actions(actions, mask, "wait")
    assert played.tolist() == [[0, 0]] and flags.tolist() == [[True, True]]
    played, flags = sanitize_actions(np.array([[1, 7]]), mask, "wait")
    assert played.tolist() == [[1, 0]] and flags.tolist() == [[False, True]]
    played, flags = sanitize_actions(np.array([[-1, 0]]), mask, "wait")
    assert played.tolist() == [[0, 0]] and flags.tolist() == [[True, False]]


def test_resolve_inputs():
    system = resolve_system("system2")
    assert system.robots == paper_system("system2").robots
    assert resolve_system(system) is system
    assert resolve_params(system, None) is None
    assert resolve_params(system, {"horizon": 7}) == AuctionParams(horizon=7)
    assert AuctionParallelEnv("system2").possible_agents == list(system.robots)
    with pytest.raises(ValueError, match="unknown system 'system9'.*system1"):
        resolve_system("system9")
    with pytest.raises(ValueError, match="invalid_action must be one of"):
        AuctionGymEnv("system9", invalid_action="skip")  # checked first, before the system
    with pytest.raises(ValueError, match="env.horizn: unknown setting of AuctionParams"):
        resolve_params(system, {"horizn": 7})


# ---------------------------------------------------------------- PettingZoo
@pytest.mark.parametrize("name", ["system1", "system2"])
def test_parallel_api(name):
    system = paper_system(name)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # any API warning is a failure
        parallel_api_test(AuctionParallelEnv(system, SHORT), num_cycles=100)
        partition = subg_partition(system)
        parallel_api_test(
            AuctionParallelEnv(system, SHORT, active_tasks=partition.active_tasks(system)), 60
        )


def test_aec_conversion_does_not_warn():
    # observations are float32 arrays of the observation space (PettingZoo warned at every step
    # when they were dicts); the AEC test samples with infos[agent]["action_mask"]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        api_test(parallel_to_aec(AuctionParallelEnv(paper_system("system1"), SHORT)), 200)
    # robots keep the paper's names R1..Rm, not PettingZoo's suggested "robot_0"
    messages = [str(w.message) for w in caught if "named in the format" not in str(w.message)]
    assert messages == []


def test_parallel_seed():
    # the default configuration: parallel_seed_test samples unmasked actions
    system = paper_system("system1")
    parallel_seed_test(lambda: AuctionParallelEnv(system, SHORT), 50)
    first, second = AuctionParallelEnv(system, SHORT), AuctionParallelEnv(system, SHORT)
    obs1, _ = first.reset(seed=3)
    obs2, _ = second.reset(seed=3)
    for agent in first.agents:
        np.testing.assert_array_equal(obs1[agent], obs2[agent])


def test_parallel_unseeded_envs_differ():
    system = paper_system("system1")

    def stream(env):
        obs, _ = env.reset()
        states = [env.state()]
        for _ in range(30):
            env.step({})
            states.append(env.state())
        return np.array(states)

    assert not np.array_equal(
        stream(AuctionParallelEnv(system, SHORT)), stream(AuctionParallelEnv(system, SHORT))
    )
    np.testing.assert_array_equal(  # a constructor seed makes the unseeded reset reproducible
        stream(AuctionParallelEnv(system, SHORT, seed=5)),
        stream(AuctionParallelEnv(system, SHORT, seed=5)),
    )


def test_parallel_matches_core():
    system = paper_system("system2")
    env = AuctionParallelEnv(system, SHORT)
    core = AuctionEnv(system, SHORT, seed=7)
    obs, infos = env.reset(seed=7)
    assert env.agents == list(system.robots) and set(infos) == set(env.agents)
    rng = np.random.default_rng(0)
    for tick in range(SHORT.horizon):
        features = ob.local_features(core)[0]
        for i, agent in enumerate(env.agents):
            np.testing.assert_array_equal(obs[agent], features[i])
            np.testing.assert_array_equal(infos[agent]["action_mask"], core.action_mask[0, i])
            np.testing.assert_array_equal(env.action_mask(agent), core.action_mask[0, i])
            assert env.observation_space(agent).contains(obs[agent])
        np.testing.assert_array_equal(env.state(), ob.global_features(core)[0])
        assert env.state_space.contains(env.state())
        actions = random_valid(core.action_mask, rng)  # [1, m]
        result = core.step(actions)
        obs, rewards, terms, truncs, infos = env.step(
            dict(zip(env.agents, actions[0].tolist(), strict=True))
        )
        np.testing.assert_allclose([rewards[a] for a in system.robots], result.robot_reward[0])
        team = infos["R1"]["team_reward"]
        assert team == pytest.approx(result.team_reward[0])
        assert sum(rewards.values()) == pytest.approx(team)  # spec step 8
        assert not any(info["invalid_action"] for info in infos.values())
        assert not any(terms.values())
        assert all(v == (tick == SHORT.horizon - 1) for v in truncs.values())
    assert env.agents == []
    with pytest.raises(ValueError, match="reset"):
        env.step({})


def test_parallel_invalid_actions():
    system = paper_system("system1")
    for mode in ("raise", "wait"):
        env = AuctionParallelEnv(system, SHORT, invalid_action=mode)
        _, infos = env.reset(seed=1)
        bad = {
            a: int(np.flatnonzero(infos[a]["action_mask"] == 0)[0])
            for a in env.agents
            if not infos[a]["action_mask"].all()
        }
        assert bad, "every robot could bid for every slot: pick another seed"
        if mode == "raise":
            with pytest.raises(ValueError, match="invalid action"):
                env.step(bad)
        else:
            core = AuctionEnv(system, SHORT, seed=1)
            # the invalid bids become waits (and missing agents wait), flagged in the infos
            _, rewards, _, _, infos = env.step(bad)
            np.testing.assert_allclose(
                list(rewards.values()), core.step(np.zeros((1, 6), int)).robot_reward[0]
            )
            assert {a for a, info in infos.items() if info["invalid_action"]} == set(bad)
    assert AuctionParallelEnv(system).invalid_action == "wait"  # the default
    with pytest.raises(ValueError, match="invalid_action must be one of"):
        AuctionParallelEnv(system, invalid_action="ignore")


# ---------------------------------------------------------------- Gymnasium and SB3
@pytest.mark.parametrize("env_id", ["mrta_rl/Auction-System1-v0", "mrta_rl/Auction-System2-v0"])
def test_gym_check_env(env_id):
    env = gym.make(env_id, params={"horizon": 40}).unwrapped  # made: it has a spec to check
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the default configuration passes without a warning
        gym_check_env(env)


@pytest.mark.parametrize("name", ["system1", "system2"])
def test_sb3_check_env(name):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sb3_check_env(AuctionGymEnv(paper_system(name), SHORT), warn=True)


def test_gym_make_ids():
    assert set(GYM_IDS) <= set(gym.registry)  # registered by importing mrta_rl.envs
    for env_id, name in [
        ("mrta_rl/Auction-System1-v0", "system1"),
        ("mrta_rl/Auction-System2-v0", "system2"),
    ]:
        env = gym.make(env_id, params={"horizon": 40})
        core = AuctionEnv(paper_system(name), SHORT, seed=11)
        obs, _ = env.reset(seed=11)
        np.testing.assert_array_equal(obs, ob.global_features(core)[0])
        assert env.unwrapped.core.params.horizon == 40
    env = gym.make("mrta_rl/Auction-v0", system="system2", invalid_action="raise")
    assert env.unwrapped.core.n_robots == 10 and env.unwrapped.invalid_action == "raise"
    with pytest.raises(ValueError, match="unknown system"):
        gym.make("mrta_rl/Auction-v0", system="system7")


def test_gym_action_masks():
    env = AuctionGymEnv(paper_system("system2"), SHORT)
    _, info = env.reset(seed=2)
    rng = np.random.default_rng(1)
    for _ in range(SHORT.horizon):
        flat = env.action_masks()
        assert flat.dtype == bool and flat.shape == (int(env.action_space.nvec.sum()),)
        np.testing.assert_array_equal(flat, info["action_mask"].reshape(-1).astype(bool))
        np.testing.assert_array_equal(flat.reshape(10, -1), env.core.action_mask[0])
        _, _, _, _, info = env.step(random_valid(info["action_mask"][None], rng)[0])
        assert not info["invalid_action"].any()
    assert is_masking_supported(env)  # sb3-contrib finds the method
    np.testing.assert_array_equal(get_action_masks(env), env.action_masks())


def test_gym_unseeded_envs_differ():
    system = paper_system("system1")
    one, two = (
        first_stream(AuctionGymEnv(system, SHORT)),
        first_stream(AuctionGymEnv(system, SHORT)),
    )
    assert not np.array_equal(np.array(one), np.array(two))
    touched = [AuctionGymEnv(system, SHORT), AuctionGymEnv(system, SHORT)]
    for env in touched:
        env.np_random  # noqa: B018  (Gymnasium creates it, unseeded, on first access)
    assert not np.array_equal(*(np.array(first_stream(env)) for env in touched))
    # a vector env reset without seeds: each copy draws its own entropy
    vec = gym.vector.SyncVectorEnv([lambda: AuctionGymEnv(system, SHORT)] * 2)
    obs, _ = vec.reset()
    wait = np.zeros(vec.action_space.shape, np.int64)
    frames = [obs] + [vec.step(wait)[0] for _ in range(30)]
    assert not np.array_equal(np.array(frames)[:, 0], np.array(frames)[:, 1])
    # seeded resets stay deterministic; unseeded resets after them continue the seeded copy
    env_a, env_b = AuctionGymEnv(system, SHORT), AuctionGymEnv(system, SHORT)
    for env in (env_a, env_b):
        env.reset(seed=4)
    np.testing.assert_array_equal(np.array(first_stream(env_a)), np.array(first_stream(env_b)))


def test_gym_matches_core():
    system = paper_system("system1")
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
    first, _ = env.reset(seed=9)
    again, _ = env.reset(seed=9)
    np.testing.assert_array_equal(first, again)


def test_gym_invalid_actions():
    system = paper_system("system1")
    strict = AuctionGymEnv(system, SHORT, invalid_action="raise")
    _, info = strict.reset(seed=1)
    robot, action = np.argwhere(info["action_mask"] == 0)[0]
    joint = np.zeros(6, int)
    joint[robot] = action
    with pytest.raises(ValueError, match="invalid action"):
        strict.step(joint)
    lenient = AuctionGymEnv(system, SHORT)  # the default: played as a wait, flagged
    assert lenient.invalid_action == "wait"
    lenient.reset(seed=1)
    core = AuctionEnv(system, SHORT, seed=1)
    _, reward, *_, info = lenient.step(joint)
    assert reward == pytest.approx(core.step(np.zeros((1, 6), int)).team_reward[0])
    assert np.flatnonzero(info["invalid_action"]).tolist() == [robot]
