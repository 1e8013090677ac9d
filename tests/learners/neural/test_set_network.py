"""The shared robot-set network: equivariance, masking, any team with one set of weights."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mrta_rl.envs import AuctionEnv, AuctionParams
from mrta_rl.envs.torchrl_env import set_input_tensors
from mrta_rl.learners.neural.set_network import MASKED, SET_INPUT_KEYS, SetNetwork
from mrta_rl.systems import random_system
from tests.conftest import paper_system


@pytest.fixture(autouse=True)
def one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def played_env(system, batch: int = 3, ticks: int = 8, seed: int = 0) -> AuctionEnv:
    """An env some greedy ticks in: busy robots, queued tasks, some empty slots."""
    env = AuctionEnv(system, AuctionParams(horizon=50), batch_size=batch, seed=seed)
    for _ in range(ticks):
        env.step(env.fixed_actions("greedy"))
    return env


def inputs(env: AuctionEnv) -> tuple[list[torch.Tensor], torch.Tensor]:
    tensors = set_input_tensors(env)
    return [tensors[k] for k in SET_INPUT_KEYS], torch.from_numpy(env.action_mask.copy())


def trained_like(**settings) -> SetNetwork:
    """A network whose zero-initialised output layers hold random weights (outputs not all 0)."""
    torch.manual_seed(0)
    net = SetNetwork(**settings)
    with torch.no_grad():
        for p in net.parameters():
            if not p.any():
                p.normal_(0.0, 0.5)
    return net


@pytest.mark.parametrize("robot_attention", ["full", "pooled"])
def test_permuting_robots_or_slots_permutes_the_outputs(robot_attention):
    env = played_env(paper_system("system2"))
    (robots, robot_types, slots, slot_type, types), mask = inputs(env)
    net = trained_like(embed_dim=32, heads=4, layers=2, robot_attention=robot_attention)
    with torch.no_grad():
        out = net(robots, robot_types, slots, slot_type, types, mask)
        perm = torch.tensor([3, 0, 9, 1, 2, 8, 4, 7, 5, 6])
        by_robot = net(
            robots[:, perm], robot_types[:, perm], slots, slot_type, types, mask[:, perm]
        )
        torch.testing.assert_close(by_robot, out[:, perm], atol=1e-4, rtol=1e-4)
        order = torch.tensor([2, 0, 1])
        columns = torch.cat([torch.tensor([0]), 1 + order])
        by_slot = net(robots, robot_types, slots[:, order], slot_type[:, order], types, None)
        free = net(robots, robot_types, slots, slot_type, types, None)
        torch.testing.assert_close(by_slot, free[..., columns], atol=1e-4, rtol=1e-4)
    assert out.abs().max() > 0  # not the untrained zeros: the checks above compare values


def test_one_set_of_weights_runs_on_any_team():
    """System-I, System-II and a 200-robot random team: finite scores, invalid ones masked."""
    net = trained_like()
    count = sum(p.numel() for p in net.parameters())
    teams = {
        "system1": paper_system("system1"),
        "system2": paper_system("system2"),
        "random200": random_system(200, 20, density=0.15, seed=0),
    }
    for name, system in teams.items():
        env = played_env(system, batch=2)
        x, mask = inputs(env)
        with torch.no_grad():
            out = net(*x, mask)
            team = net.embed(*x)[1]
        m, K = env.n_robots, env.n_slots
        assert out.shape == (2, m, K + 1) and team.shape == (2, net.embed_dim), name
        assert torch.isfinite(out).all(), name
        assert (out[~mask] == MASKED).all(), name  # no invalid action scores high
        assert (out[mask] > MASKED / 2).all(), name
        assert mask[..., 1:].any() and not mask.all(), name  # both kinds of entries checked
    assert sum(p.numel() for p in net.parameters()) == count


def test_only_wait_valid_gives_a_proper_distribution():
    env = played_env(paper_system("system1"), batch=2)
    x, mask = inputs(env)
    mask[...] = False
    mask[..., 0] = True  # every robot busy: only "wait"
    with torch.no_grad():
        probs = torch.softmax(trained_like()(*x, mask), -1)
    torch.testing.assert_close(probs[..., 0], torch.ones(probs.shape[:-1]))


def test_untrained_scores_are_zero_and_leading_dims_are_kept():
    env = played_env(paper_system("system2"), batch=4)
    x, mask = inputs(env)
    net = SetNetwork(embed_dim=16, heads=2, layers=1)
    with torch.no_grad():
        out = net(*x, mask)
        assert (out[mask] == 0).all()
        folded = net(
            *(t.reshape(2, 2, *t.shape[1:]) for t in x), mask.reshape(2, 2, *mask.shape[1:])
        )
        h, team = net.embed(*x)
    torch.testing.assert_close(folded.reshape(out.shape), out)
    torch.testing.assert_close(team, h.mean(1))


def test_a_team_with_more_task_types_than_the_embedding_is_refused():
    env = played_env(random_system(12, 9, seed=0), batch=1, ticks=1)
    x, mask = inputs(env)
    with pytest.raises(ValueError, match=r"learner.max_task_types=8 .* 9 task types"):
        SetNetwork(max_task_types=8)(*x, mask)
    assert np.isfinite(SetNetwork(max_task_types=9)(*x, mask).detach().numpy()).all()
