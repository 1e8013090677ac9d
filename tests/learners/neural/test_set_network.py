"""The shared robot-set network: equivariance, masking, any team with one set of weights."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mrta_rl.config import ConfigError
from mrta_rl.envs import AuctionEnv, AuctionParams
from mrta_rl.envs.torchrl_env import set_input_tensors
from mrta_rl.learners.memory import BYTES_PER_WEIGHT, estimate_resources
from mrta_rl.learners.neural import IQLLearner, QMIXLearner, VDNLearner
from mrta_rl.learners.neural.set_network import MASKED, SET_INPUT_KEYS, SetNetwork
from mrta_rl.runners.evaluate import evaluate_policy
from mrta_rl.runners.validation import validate_config
from mrta_rl.systems import random_system
from tests.commands.test_cli import assert_user_error
from tests.commands.test_cli import train as train_script
from tests.conftest import paper_system
from tests.learners.neural.test_neural import collect, make


def played_env(system, batch: int = 3, ticks: int = 8, seed: int = 0) -> AuctionEnv:
    """An env some greedy ticks in: busy robots, queued tasks, some empty slots."""
    env = AuctionEnv(system, AuctionParams(horizon=50), batch_size=batch, seed=seed)
    for _ in range(ticks):
        env.step(env.fixed_actions("greedy"))
    return env


def inputs(env: AuctionEnv) -> tuple[list[torch.Tensor], torch.Tensor]:
    tensors = set_input_tensors(env)
    return [tensors[k] for k in SET_INPUT_KEYS], torch.from_numpy(env.action_mask.copy())


# the network the tests build, unless they say otherwise
NET = {"embed_dim": 64, "heads": 4, "layers": 2, "max_task_types": 32, "robot_attention": "full"}


def trained_like(**settings) -> SetNetwork:
    """A network whose zero-initialised output layers hold random weights (outputs not all 0)."""
    torch.manual_seed(0)
    net = SetNetwork(**{**NET, **settings})
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
        m, K = env.n_robots, env.n_slots
        assert out.shape == (2, m, K + 1), name
        assert torch.isfinite(out).all(), name
        assert (out[~mask] == MASKED).all(), name  # no invalid action scores high
        assert (out[mask] > MASKED / 2).all(), name
        assert mask[..., 1:].any() and not mask.all(), name  # both kinds of entries checked
    assert sum(p.numel() for p in net.parameters()) == count


def test_masked_scores_and_gradients_are_those_of_every_pair():
    """Scoring only the valid pairs changes no valid score and no gradient (scaled auction zones:
    a robot's valid slots are a few of the team's)."""
    system = random_system(40, 6, density=0.25, seed=0, scale_auction=True)
    env = AuctionEnv(
        system, AuctionParams.merged({**system.env_overrides, "horizon": 50}), batch_size=2
    )
    for _ in range(6):
        env.step(env.fixed_actions("greedy"))
    x, mask = inputs(env)
    assert 0 < mask[..., 1:].float().mean() < 0.2  # most pairs are invalid
    grads = []
    for masked in (False, True):
        net = trained_like()
        out = net(*x, mask if masked else None)
        if masked:
            assert (out[~mask] == MASKED).all()
        (out[mask] ** 2).sum().backward()
        grads.append((out[mask].detach(), [p.grad for p in net.parameters()]))
    (dense, dense_grads), (sparse, sparse_grads) = grads
    torch.testing.assert_close(sparse, dense)
    for dense_grad, sparse_grad in zip(dense_grads, sparse_grads, strict=True):
        torch.testing.assert_close(sparse_grad, dense_grad, rtol=1e-4, atol=1e-5)


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
    net = SetNetwork(**{**NET, "embed_dim": 16, "heads": 2, "layers": 1})
    with torch.no_grad():
        out = net(*x, mask)
        assert (out[mask] == 0).all()
        folded = net(
            *(t.reshape(2, 2, *t.shape[1:]) for t in x), mask.reshape(2, 2, *mask.shape[1:])
        )
    torch.testing.assert_close(folded.reshape(out.shape), out)


def test_a_team_with_more_task_types_than_the_embedding_is_refused():
    env = played_env(random_system(12, 9, seed=0), batch=1, ticks=1)
    x, mask = inputs(env)
    with pytest.raises(ValueError, match=r"max_task_types: 8 is smaller than the 9 task types"):
        SetNetwork(**{**NET, "max_task_types": 8})(*x, mask)
    assert np.isfinite(SetNetwork(**{**NET, "max_task_types": 9})(*x, mask).detach().numpy()).all()


# ---------------------------------------------------------------------------------- learners
SET = {"network": "set", "embed_dim": 16, "heads": 2}
TEAMS = {
    "system1": paper_system("system1"),
    "system2": paper_system("system2"),
    "random200": random_system(200, 20, density=0.15, seed=0),
}


@pytest.mark.parametrize(
    ("cls", "attention"),
    [(VDNLearner, "full"), (QMIXLearner, "full"), (IQLLearner, "full"), (QMIXLearner, "pooled")],
)
def test_untrained_set_network_is_the_plain_auction(cls, attention):
    """Zero output layers + the auction prior: an untrained network=set bids like greedy."""
    system = paper_system("system2")
    learner, env = make(cls, system, batch=4, robot_attention=attention, **SET)
    assert learner.view_options["set_inputs"] and "robots" in learner.encode(env)["agents"].keys()
    for _ in range(30):
        mask = env.action_mask.copy()
        actions = learner.act(learner.encode(env), mask, explore=False)
        bids = mask[..., 1:]
        np.testing.assert_array_equal(actions, np.where(bids.any(-1), bids.argmax(-1) + 1, 0))
        env.step(actions)


@pytest.mark.parametrize("cls", [QMIXLearner, IQLLearner])
def test_set_network_trains_and_reloads_to_identical_evaluation(cls, tmp_path):
    torch.manual_seed(0)
    system = paper_system("system1")
    learner, env = make(cls, system, lr=1e-2, target_update="hard", **SET)
    batch = collect(learner, env, view=learner.view_options)
    assert ("agents", "observation") not in batch.keys(True)  # the set inputs only
    before = learner.train_step(batch)["train/loss"]
    for _ in range(15):
        after = learner.train_step(batch)["train/loss"]
    assert after < before
    learner.save(tmp_path)
    fresh, _ = make(cls, system, seed=7, **SET)  # another init: must not matter after load
    fresh.load(tmp_path)
    eval_env = AuctionEnv(system, env.params, batch_size=3, seed=5)
    a = evaluate_policy(learner, eval_env, 3, seed=5).to_json()
    b = evaluate_policy(fresh, eval_env, 3, seed=5).to_json()
    assert a == b
    other, _ = make(cls, system)  # network=mlp
    with pytest.raises(ValueError, match="trained with network=set, this run's learner has net"):
        other.load(tmp_path)


def test_set_network_weights_do_not_depend_on_the_team():
    """Counted by the memory estimate: the same for every team with set, growing with mlp."""

    def networks(system, network):
        hp = {"network": network}
        estimate = estimate_resources(VDNLearner, system, AuctionParams(), None, hp)
        return estimate.parts["networks"] // BYTES_PER_WEIGHT

    assert len({networks(system, "set") for system in TEAMS.values()}) == 1
    assert len({networks(system, "mlp") for system in TEAMS.values()}) == 3
    learner, _ = make(VDNLearner, TEAMS["system1"], network="set")
    assert learner.learning_space()["parameters"] == networks(TEAMS["system2"], "set")


def test_200_robot_qmix_with_the_set_network_passes_validation(compose_cfg):
    """The robot-id one-hot made QMIX's replay buffer grow with m^2; the set inputs do not."""
    args = ["learner=qmix", "system=random", "system.n_robots=200", "debug=smoke"]
    checked = validate_config(compose_cfg([*args, "learner.network=set"]))
    assert checked.system.n_robots == 200
    with pytest.raises(ValueError, match=r"qmix on system random \(200 robots\): needs about"):
        validate_config(compose_cfg([*args, "learner.network=mlp"]))


def test_set_settings_that_cannot_work_are_refused_by_name(compose_cfg):
    args = ["learner=vdn", "system=system1", "debug=smoke", "learner.network=set"]
    with pytest.raises(ConfigError, match=r"learner.embed_dim: 30 must be a multiple of learner.h"):
        validate_config(compose_cfg([*args, "learner.embed_dim=30", "learner.heads=4"]))
    with pytest.raises(ConfigError, match="learner.prior_in_state: needs network=mlp"):
        validate_config(compose_cfg([*args, "learner.prior=hold", "learner.prior_in_state=true"]))
    validate_config(compose_cfg([*args, "learner.embed_dim=32", "learner.heads=4"]))


def test_a_team_with_more_task_types_than_max_task_types_is_refused_before_any_work(tmp_path):
    run_dir = tmp_path / "run"
    code, _, err = train_script(
        run_dir, "learner=qmix", "system=system2", "learner.network=set", "learner.max_task_types=4"
    )
    assert_user_error(code, err, "learner.max_task_types: 4", "8 task types", "system2")
    assert err.count("\n") == 1  # one line
    assert not run_dir.exists()


@pytest.mark.slow  # about 10 s: two processes starting torch, as the other neural resume cases
def test_a_killed_set_network_run_resumes_to_the_same_end(compose_cfg, tmp_path):
    from tests.runners import test_checkpoint as ckpt

    args = [
        "learner=qmix",
        "learner.network=set",
        "learner.embed_dim=16",
        "system=system1",
        "debug=smoke",
        *ckpt.BUDGETS["neural"],
    ]
    full_dir, cut_dir = tmp_path / "full", tmp_path / "cut"
    killed_after = ckpt.killed_at_checkpoint(args, cut_dir, 2)
    assert not (cut_dir / "metrics.json").exists()
    resumed = ckpt.script("scripts/train.py", f"resume={cut_dir}")
    ckpt.train(compose_cfg(args), run_dir=full_dir)
    assert killed_after <= ckpt.resumed_run(resumed, cut_dir) < 6
    ckpt.assert_same_run(full_dir, cut_dir)
