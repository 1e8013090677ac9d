"""Tests of the TorchRL view (mrta_rl/envs/torchrl_env.py): specs, and identity with AuctionEnv."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.envs import ActionMask, ParallelEnv, RewardSum, SerialEnv, TransformedEnv
from torchrl.envs.utils import check_env_specs

from mrta_rl.envs import AuctionEnv, AuctionParams
from mrta_rl.envs import encodings as ob
from mrta_rl.envs.torchrl_env import (
    AuctionTorchRLEnv,
    prior_index,
    prior_one_hot,
    resolve_group_map,
)
from mrta_rl.partition import subg_partition
from mrta_rl.rules import greedy_actions
from mrta_rl.systems import RobotSystem, build_system

ROOT = Path(__file__).resolve().parents[2]
GROUP_MAPS = ["all_in_one_group", "one_group_per_agent", "subg"]


def load_system(name: str) -> RobotSystem:
    return build_system(yaml.safe_load((ROOT / "conf" / "system" / f"{name}.yaml").read_text()))


def make(system: RobotSystem, kind: str, batch_size: int, horizon: int = 6, seed: int = 0, **view):
    """The TorchRL env for a group-map kind; subG also restricts Lambda_i as the runner does.

    ``view``: more arguments of the view (``features=``); none is how outside clients build it.
    """
    active, group_map = None, kind
    if kind == "subg":
        partition = subg_partition(system)
        active, group_map = partition.active_tasks(system), partition.group_map()
    core = AuctionEnv(
        system, AuctionParams(horizon=horizon), batch_size, active_tasks=active, seed=seed
    )
    return AuctionTorchRLEnv(core, group_map, **view)


def random_valid(mask: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    return (rng.random(mask.shape) * mask).argmax(axis=2)  # [B, m], a valid action per robot


def group_index(env: AuctionTorchRLEnv) -> dict[str, np.ndarray]:
    """Group -> the robot indices of its members, from the env's public group_map."""
    robots = env.auction.system.robots
    return {g: np.array([robots.index(r) for r in ids]) for g, ids in env.group_map.items()}


def to_td(env: AuctionTorchRLEnv, actions: np.ndarray) -> TensorDict:
    B = actions.shape[0]
    return TensorDict(
        {
            g: TensorDict(action=torch.as_tensor(actions[:, idx]), batch_size=(B, len(idx)))
            for g, idx in group_index(env).items()
        },
        batch_size=(B,),
    )


@pytest.mark.parametrize("kind", GROUP_MAPS)
@pytest.mark.parametrize("batch_size", [1, 64])
@pytest.mark.parametrize("system", ["system1", "system2"])
def test_check_env_specs(system, kind, batch_size):
    env = make(load_system(system), kind, batch_size, horizon=4)
    check_env_specs(env, break_when_any_done="both")


@pytest.mark.parametrize("kind", GROUP_MAPS)
def test_time_to_free_features_size_the_specs(kind):
    """features=time_to_free: observation and state specs are the wider encoding's sizes."""
    env = make(load_system("system2"), kind, 3, horizon=4, features="time_to_free")
    check_env_specs(env, break_when_any_done="both")
    core = env.auction
    F = ob.local_feature_size(core, "time_to_free")
    assert F == ob.local_feature_size(core) + 9
    for group, idx in group_index(env).items():
        assert env.observation_spec[group, "observation"].shape == (3, len(idx), F)
    G = ob.global_feature_size(core, "time_to_free")
    assert env.observation_spec["state"].shape == (3, G)
    with pytest.raises(ValueError, match="features must be one of"):
        AuctionTorchRLEnv(core, kind if kind != "subg" else None, features="queue")


@pytest.mark.parametrize("kind", GROUP_MAPS)
def test_prior_action_key_is_the_prior_action_per_group(kind):
    """prior=: that policy's action of every robot under every group, at reset and step."""
    env = make(load_system("system2"), kind, 5, horizon=4)
    assert "prior_action" not in env.reset().get(next(iter(env.group_map))).keys()
    with_prior = AuctionTorchRLEnv(env.auction, env.group_map, prior=greedy_of_core)
    check_env_specs(with_prior, break_when_any_done="both")
    td = with_prior.reset()
    rng = np.random.default_rng(0)
    for _ in range(3):
        for group in with_prior.group_map:
            mask, got = td.get((group, "action_mask")), td.get((group, "prior_action"))
            assert got.dtype == torch.int8 and got.shape == mask.shape[:2]  # K + 1 = 4
            expected = greedy_actions(mask.numpy())  # the plain auction, by the mask
            np.testing.assert_array_equal(got.numpy(), expected)
        actions = random_valid(with_prior.auction.action_mask, rng)
        td = with_prior.step(to_td(with_prior, actions))["next"]


def test_prior_action_is_the_smallest_integer_and_expands_to_a_one_hot():
    """int8 while every action 0..K fits (K + 1 <= 128), then int16; -1 is an all-False row."""
    assert [ob.prior_dtype(A) for A in (4, 128, 129, 32768, 32769)] == [
        np.int8,
        np.int8,
        np.int16,
        np.int16,
        np.int32,
    ]
    leaf = prior_index(np.array([[2, -1, 0]]), n_actions=4)
    assert leaf.dtype == torch.int8 and leaf.tolist() == [[2, -1, 0]]
    expected = [[[False, False, True, False], [False] * 4, [True, False, False, False]]]
    assert prior_one_hot(leaf, 4).tolist() == expected


def greedy_of_core(core: AuctionEnv) -> np.ndarray:
    """A prior read from the core env: the plain auction's actions."""
    return greedy_actions(core.action_mask)


def test_group_maps():
    robots = ("R1", "R2", "R3")
    assert resolve_group_map(robots, None) == {"agents": ["R1", "R2", "R3"]}
    assert resolve_group_map(robots, "one_group_per_agent") == {r: [r] for r in robots}
    assert resolve_group_map(robots, {"G1": [2, 0], "G2": ["R2"]}) == {
        "G1": ["R3", "R1"],
        "G2": ["R2"],
    }
    for bad in (
        {"G1": ["R1", "R2"]},
        {"G1": ["R1", "R2", "R3", "R1"]},
        {"G1": ["R9"]},
        "no_groups",
    ):
        with pytest.raises(ValueError):
            resolve_group_map(robots, bad)


@pytest.mark.parametrize("features", ob.FEATURES)
@pytest.mark.parametrize("kind", GROUP_MAPS)
def test_same_results_as_core(kind, features):
    """Driving the view and the core with the same seed and actions gives identical data."""
    system = load_system("system2")
    env = make(system, kind, batch_size=4, horizon=15, seed=11, features=features)
    core = AuctionEnv(system, env.auction.params, 4, active_tasks=env.auction.active_tasks, seed=11)
    rng = np.random.default_rng(0)
    env.set_seed(
        11
    )  # reseeding restarts the episode count: the next episode is a fresh core's first
    td = env.reset()
    team_return = np.zeros(4)
    for _ in range(15):
        mask = core.action_mask
        for g, idx in group_index(env).items():
            np.testing.assert_array_equal(td[g, "action_mask"].numpy(), mask[:, idx])
            np.testing.assert_array_equal(
                td[g, "observation"].numpy(), ob.local_features(core, features)[:, idx]
            )
        np.testing.assert_array_equal(td["state"].numpy(), ob.global_features(core, features))
        actions = random_valid(mask, rng)
        result = core.step(actions)
        out = env.step(to_td(env, actions))["next"]
        np.testing.assert_array_equal(out["done"].numpy()[:, 0], result.done)
        np.testing.assert_array_equal(out["truncated"].numpy()[:, 0], result.done)
        assert not out["terminated"].any()
        group_total = np.zeros(4)
        for g, idx in group_index(env).items():
            # TorchRL's reward key of every group: the team reward, repeated per robot
            team = np.repeat(result.team_reward[:, None], len(idx), axis=1)
            np.testing.assert_allclose(out[g, "reward"].numpy()[..., 0], team, rtol=1e-6)
            np.testing.assert_allclose(
                out[g, "robot_reward"].numpy()[..., 0], result.robot_reward[:, idx], atol=1e-5
            )
            # spec step 8: a sub-group's reward is the sum of its robots', repeated per robot
            expected = result.robot_reward[:, idx].sum(1)  # [B]
            np.testing.assert_allclose(
                out[g, "group_reward"].numpy()[..., 0],
                np.repeat(expected[:, None], len(idx), axis=1),
                atol=1e-4,
            )
            group_total += out[g, "group_reward"].numpy()[:, 0, 0]
        np.testing.assert_allclose(group_total, result.team_reward, atol=1e-3)  # groups add up
        team_return += result.team_reward
        td = out
    assert result.done.all()
    for field in ("assigned", "dropped", "busy_ticks", "team_return", "ticks"):
        np.testing.assert_array_equal(getattr(env.auction.stats, field), getattr(core.stats, field))
    np.testing.assert_allclose(core.stats.team_return, team_return)


def test_rollout_with_auto_reset_matches_core():
    """TorchRL's rollout resets finished copies itself; the next episode matches a core reset."""
    system = load_system("system1")
    env = make(system, "all_in_one_group", batch_size=2, horizon=5, seed=3)
    torch.manual_seed(0)
    env.set_seed(3)
    data = env.rollout(12, break_when_any_done=False)
    actions = data["agents", "action"].numpy()  # [B, T, m]
    core = AuctionEnv(system, env.auction.params, 2, seed=3)
    rewards = []
    for tick in range(12):
        if core.done.any():
            core.reset(core.done.copy())  # a copy: reset(mask) writes core.done, which would alias
        rewards.append(core.step(actions[:, tick]).team_reward)
    np.testing.assert_allclose(
        data["next", "agents", "reward"].numpy()[..., 0, 0], np.stack(rewards, 1), rtol=1e-6
    )


def test_returned_data_is_not_aliased_to_the_core():
    env = make(load_system("system2"), "all_in_one_group", batch_size=8, horizon=30)
    td = env.reset()
    kept = td.clone()
    for _ in range(5):
        env.step(env.rand_action(td.clone()))
    assert (td == kept).all()


def test_partial_reset_only_touches_masked_copies():
    env = make(load_system("system1"), "all_in_one_group", batch_size=4, horizon=50, seed=5)
    td = env.reset()
    rng = np.random.default_rng(1)
    for _ in range(7):
        td = env.step(td.update(to_td(env, random_valid(env.auction.action_mask, rng))))["next"]
    before = env.auction.stats.copy()
    # TorchRL's convention: the current data plus "_reset"; unreset copies keep their entries
    td.set("_reset", torch.tensor([[True], [False], [True], [False]]))
    td = env.reset(td)
    np.testing.assert_array_equal(env.auction.t, [0, 7, 0, 7])
    assert (env.auction.stats.ticks == [0, 7, 0, 7]).all()
    np.testing.assert_array_equal(env.auction.stats.busy_ticks[[1, 3]], before.busy_ticks[[1, 3]])
    assert (env.auction.stats.busy_ticks[[0, 2]] == 0).all()
    np.testing.assert_array_equal(td["agents", "action_mask"].numpy(), env.auction.action_mask)


def test_seeding_and_one_hot_and_invalid_actions():
    system = load_system("system1")
    env = make(system, "one_group_per_agent", batch_size=3, horizon=20)
    env.set_seed(42)
    env.reset()
    core = AuctionEnv(system, env.auction.params, 3, seed=42)
    np.testing.assert_array_equal(env.auction.slot_type, core.slot_type)
    # one-hot actions are accepted: all robots wait
    one_hot = TensorDict(
        {
            g: TensorDict(
                action=torch.nn.functional.one_hot(torch.zeros(3, 1, dtype=torch.long), 4),
                batch_size=(3, 1),
            )
            for g in env.group_map
        },
        batch_size=(3,),
    )
    out = env.step(one_hot)["next"]
    np.testing.assert_allclose(
        out["R1", "reward"].numpy()[:, 0, 0], core.step(np.zeros((3, 6), int)).team_reward
    )
    # rand_action samples the masked action spec: valid bids only
    for _ in range(20):
        action = env.rand_action()
        for g, idx in group_index(env).items():
            assert env.auction.action_mask[
                np.arange(3)[:, None], idx, action[g, "action"].numpy()
            ].all()
    bad = np.zeros((3, 6), int)
    empty = np.flatnonzero(env.auction.slot_type[0] < 0)
    bad[0, 0] = empty[0] + 1 if len(empty) else 9
    # invalid_action="raise": the core's error; "wait" (default): played as a wait, flagged
    strict = AuctionTorchRLEnv(env.auction, env.group_map, invalid_action="raise")
    with pytest.raises(ValueError, match="invalid action"):
        strict.step(to_td(strict, bad))
    out = env.step(to_td(env, bad))["next"]
    flags = np.concatenate([out[g, "invalid_action"].numpy()[:, :, 0] for g in env.group_map], 1)
    expected_flags = np.zeros((3, 6), bool)
    expected_flags[0, 0] = True
    np.testing.assert_array_equal(flags, expected_flags)
    waited = core.step(np.zeros((3, 6), int))  # the twin core, all waiting: the same tick
    np.testing.assert_allclose(out["R1", "reward"].numpy()[:, 0, 0], waited.team_reward)
    with pytest.raises(ValueError, match="invalid_action must be one of"):
        AuctionTorchRLEnv(env.auction, invalid_action="ignore")


# ---------------------------------------------------------------- outside clients
def paper_env(batch_size: int = 4, horizon: int = 8, seed: int = 0) -> AuctionTorchRLEnv:
    """System-II in the default configuration (one group, invalid_action="wait")."""
    core = AuctionEnv(load_system("system2"), AuctionParams(horizon=horizon), batch_size, seed=seed)
    return AuctionTorchRLEnv(core)


def test_reward_key_and_plain_reward_sum_give_the_team_return():
    env = paper_env()
    assert env.reward_key == ("agents", "reward")
    assert env.reward_keys == [("agents", "reward")]
    torch.manual_seed(0)
    data = TransformedEnv(env, RewardSum()).rollout(8)  # one episode: horizon 8
    summed = data["next", "agents", "episode_reward"][:, -1, :, 0]  # [B, m]
    expected = torch.as_tensor(env.auction.stats.team_return, dtype=torch.float32)  # [B]
    torch.testing.assert_close(summed, expected[:, None].expand_as(summed))


def test_spec_sampling_is_valid_and_follows_the_mask():
    """The action spec's mask is the current mask: spec samples are valid, every tick."""
    env = paper_env(batch_size=6, horizon=30)
    td = env.reset()
    spec = env.full_action_spec["agents", "action"]
    for _ in range(30):
        mask = td["agents", "action_mask"]
        assert torch.equal(spec.mask, mask)
        sample = spec.rand()
        assert mask.gather(-1, sample.unsqueeze(-1)).all()
        td = env.step(env.rand_action(td))
        assert not td["next", "agents", "invalid_action"].any()
        td = td["next"]


def test_collector_without_policy():
    """Collector(env, None): a RandomPolicy on a clone of the spec (its mask goes stale, so
    invalid samples are played as waits and flagged)."""
    torch.manual_seed(0)
    collector = Collector(paper_env(), None, frames_per_batch=40, total_frames=80)
    batches = list(collector)
    collector.shutdown()
    assert [b.shape for b in batches] == [torch.Size([4, 10])] * 2
    for data in batches:
        taken = data["agents", "action"]
        mask = data["agents", "action_mask"]
        valid = mask.gather(-1, taken.unsqueeze(-1))
        torch.testing.assert_close(data["next", "agents", "invalid_action"], ~valid)


def _masked(env):
    return TransformedEnv(env, ActionMask(("agents", "action"), ("agents", "action_mask")))


@pytest.mark.parametrize("batched", [SerialEnv, ParallelEnv])
def test_batched_envs_of_two_workers(batched):
    """Plain (stale parent spec: invalid samples wait) and with ActionMask (all valid)."""
    env = batched(2, paper_env)
    try:
        for outer, masked in ((env, False), (_masked(env), True)):
            check_env_specs(outer, seed=0)
            data = outer.rollout(10, break_when_any_done=False)
            assert data.shape == torch.Size([2, 4, 10])
            if masked:  # the ActionMask transform keeps the parent's spec current
                assert not data["next", "agents", "invalid_action"].any()
    finally:
        env.close()


def test_action_mask_transform():
    env = _masked(paper_env())
    check_env_specs(env)
    data = env.rollout(8)
    assert not data["next", "agents", "invalid_action"].any()


@pytest.mark.parametrize("kind", GROUP_MAPS)
def test_set_inputs_keys_have_specs_and_match_the_core(kind):
    """set_inputs=True: the set network's tokens under each group and at the root, specs checked,
    and the same TensorDict as another view of the core observes (evaluation's inputs)."""
    env = make(load_system("system2"), kind, 3, horizon=4, set_inputs=True)
    check_env_specs(env, break_when_any_done="both")
    core = env.auction
    n, K = core.n_task_types, core.n_slots
    assert env.observation_spec["slots"].shape == (3, K, ob.SLOT_TOKEN_SIZE)
    assert env.observation_spec["types"].shape == (3, n, ob.TYPE_TOKEN_SIZE)
    td = env.reset()
    rng = np.random.default_rng(0)
    for _ in range(3):
        expected = AuctionTorchRLEnv(core, env.group_map, set_inputs=True).observe()
        for key in ("slots", "slot_type", "types"):
            torch.testing.assert_close(td.get(key), expected.get(key))
        for group, idx in group_index(env).items():
            robots = td.get((group, "robots"))
            assert robots.shape == (3, len(idx), ob.ROBOT_TOKEN_SIZE)
            for key in ("robots", "robot_types", "action_mask"):
                torch.testing.assert_close(td.get((group, key)), expected.get((group, key)))
            types = td.get((group, "robot_types"))
            np.testing.assert_array_equal(types[0].numpy(), core.active_tasks[idx])
        td = env.step(to_td(env, random_valid(core.action_mask, rng)))["next"]
    assert "slots" not in make(load_system("system1"), kind, 2).reset().keys()
    only_set = make(load_system("system1"), kind, 2, set_inputs=True, local_features=False)
    check_env_specs(only_set, break_when_any_done="both")
    group = next(iter(only_set.group_map))
    assert "observation" not in only_set.reset().get(group).keys()
    assert "robots" in only_set.reset().get(group).keys()
