"""MAPPO and IPPO: masked sampling and mode, MultiAgentGAE on the team reward, bad settings."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from mrta_rl.config import ConfigError
from mrta_rl.envs import AuctionEnv, AuctionParams
from mrta_rl.learners.neural import IPPOLearner, MAPPOLearner
from mrta_rl.runners import train
from tests.conftest import ROOT, paper_system

SMALL = {"hidden": 16, "depth": 1, "frames_per_batch": 40, "minibatch_size": 20, "embed_dim": 8}
CASES = [
    (cls, network)
    for cls in (MAPPOLearner, IPPOLearner)
    for network in ("set", "mlp")  # the robot-set network and the per-robot MLP
]


def make(cls, batch=4, seed=0, **hp):
    env = AuctionEnv(
        paper_system("system1"), AuctionParams(horizon=20), batch_size=batch, seed=seed
    )
    return cls(env=env, rng=np.random.default_rng(seed), **(SMALL | hp)), env


# ---------------------------------------------------------------------------------- masking
@pytest.mark.parametrize(("cls", "network"), CASES)
def test_no_invalid_action_is_ever_sampled_even_where_the_logits_favour_one(cls, network):
    """Most actions masked, and the prior's logit bonus put on a masked one: never sampled."""
    learner, env = make(cls, batch=8, auction_prior=20.0, network=network)
    view = learner.encode(env)
    B, m, A = env.action_mask.shape
    gen = np.random.default_rng(1)
    mask = gen.random((B, m, A)) < 0.3  # about 70 % of the bids masked
    mask[..., 0] = True  # wait is always valid (spec step 4)
    mask[0] = False
    mask[0, :, 0] = True  # copy 0: a wait-only state
    invalid = np.where(~mask[..., 1:].all(-1), (~mask[..., 1:]).argmax(-1) + 1, 0)  # [B, m]
    favoured = torch.from_numpy(invalid).to(view.get(("agents", "prior_action")).dtype)
    view.set(("agents", "prior_action"), favoured)  # e^20 times likelier, if it were valid
    assert (~mask[np.arange(B)[:, None], np.arange(m), invalid]).sum() > B  # really masked
    torch.manual_seed(0)
    draws = np.stack([learner.act(view, mask, explore=True) for _ in range(300)])  # [300, B, m]
    valid = np.take_along_axis(mask[None], draws[..., None], -1)[..., 0]
    assert valid.all()
    assert (draws[:, 0] == 0).all()  # wait-only: wait
    assert len(np.unique(draws[:, 1:])) > 1  # it does sample: more than one action was drawn
    mode = learner.act(view, mask, explore=False)
    assert np.take_along_axis(mask, mode[..., None], -1).all()
    assert (mode[0] == 0).all()


@pytest.mark.parametrize(("cls", "network"), CASES)
def test_evaluation_plays_the_masked_mode_the_untrained_policy_is_greedy(cls, network):
    """Untrained (last layer zero), the logits are the prior's bonus: the mode is greedy's bid."""
    learner, env = make(cls, batch=4, auction_prior=1.0, network=network)
    for _ in range(20):
        mask = env.action_mask.copy()
        greedy = env.fixed_actions("greedy")
        np.testing.assert_array_equal(learner.act(learner.encode(env), mask, explore=False), greedy)
        env.step(greedy)


# ---------------------------------------------------------------------------------- GAE
def test_multiagent_gae_on_the_team_reward_against_a_hand_computed_case():
    """Four ticks of one copy, an episode end after tick 2, values set through the critic.

    gamma 0.9, lambda 0.8, value v_t of robot i set to ``tanh(x)`` of its first feature (a
    depth-1 critic reading only that input), rewards 1, 2, 3, 4 (reward_scale 1):

    * delta_t = r_t + gamma v_{t+1} - v_t (the horizon is a truncation: the episode's last tick
      bootstraps from the value of its final state, ``next`` of tick 2);
    * A_t = delta_t + gamma lambda A_{t+1}, cut after a done tick and at the batch's end;
    * value target = A_t + v_t.
    """
    learner, _ = make(
        IPPOLearner, network="mlp", gamma=0.9, lmbda=0.8, reward_scale=1.0, depth=1, hidden=4
    )
    critic = learner.networks["critic"].mlp
    with torch.no_grad():
        for p in critic.parameters():
            p.zero_()
        critic[0].weight[0, 0] = 1.0  # hidden unit 0 = tanh(feature 0)
        critic[2].weight[0, 0] = 1.0  # value = hidden unit 0
    m, F, G, A = learner.n_robots, learner.n_features, learner.state_size, learner.n_actions
    # values of the states s_0..s_3 and of the next states (after tick 1, the episode's final
    # state f; after tick 2 the new episode's s_2 ... and after tick 3 the batch's last next s_4)
    v = [0.5, -0.2, 0.3, 0.1]
    v_next = [-0.2, 0.6, 0.1, 0.4]  # tick 1 ends the episode: its next is the final state (0.6)
    rewards = [1.0, 2.0, 3.0, 4.0]
    done = [False, True, False, False]

    def obs(values):
        x = torch.zeros(1, 4, m, F)
        x[..., 0] = torch.atanh(torch.tensor(values))[None, :, None]
        return x

    flags = torch.tensor(done)[None, :, None]  # [1, 4, 1]
    agents = {"action_mask": torch.ones(1, 4, m, A, dtype=torch.bool)}
    data = TensorDict(
        {
            "agents": {"observation": obs(v), **agents},
            "state": torch.zeros(1, 4, G),
            "next": {
                "agents": {
                    "observation": obs(v_next),
                    "reward": torch.tensor(rewards)[None, :, None, None].expand(1, 4, m, 1),
                    **agents,
                },
                "state": torch.zeros(1, 4, G),
                "done": flags,
                "terminated": torch.zeros_like(flags),
            },
        },
        batch_size=(1, 4),
    )
    out = learner.process_batch(data).reshape(1, 4)  # the loop's rows are flattened
    gamma, lam = 0.9, 0.8
    delta = [rewards[t] + gamma * v_next[t] - v[t] for t in range(4)]
    # by hand: delta = [1 - 0.18 - 0.5, 2 + 0.54 + 0.2, 3 + 0.09 - 0.3, 4 + 0.36 - 0.1]
    assert delta == pytest.approx([0.32, 2.74, 2.79, 4.26])
    a3 = 4.26  # the batch ends: nothing after it
    a2 = 2.79 + gamma * lam * a3  # 2.79 + 0.72 * 4.26 = 5.8572
    a1 = 2.74  # done: the recursion stops at the episode's end
    a0 = 0.32 + gamma * lam * a1  # 0.32 + 0.72 * 2.74 = 2.2928
    expected = torch.tensor([a0, a1, a2, a3])
    advantage = out.get(("agents", "advantage"))  # [1, 4, m, 1]
    target = out.get(("agents", "value_target"))
    assert advantage.shape == (1, 4, m, 1)
    for robot in range(m):
        torch.testing.assert_close(advantage[0, :, robot, 0], expected, atol=1e-5, rtol=0)
        torch.testing.assert_close(
            target[0, :, robot, 0], expected + torch.tensor(v), atol=1e-5, rtol=0
        )
    assert math.isclose(float(expected[2]), 5.8572, abs_tol=1e-5)


# ---------------------------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    ("override", "key"),
    [
        ("learner.minibatch_size=101", "minibatch_size"),  # smoke: 100 frames per batch
        ("learner.frames_per_batch=102", "frames_per_batch"),  # smoke: 4 copies
        ("learner.epochs=0", "epochs"),
        ("learner.network=sets", "network"),
        ("learner.max_task_types=2", "max_task_types"),  # System-I has 5 task types
        ("learner.embed_dim=10", "embed_dim"),  # 4 heads
    ],
)
def test_bad_settings_are_named_before_any_run_dir(compose_cfg, tmp_path, override, key):
    cfg = compose_cfg(["learner=mappo", "system=system1", "debug=smoke", override])
    with pytest.raises(ConfigError, match=f"learner.*{key}"):
        train(cfg, run_dir=tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_the_script_prints_one_error_line_naming_the_key(tmp_path):
    run = subprocess.run(
        [
            sys.executable,
            str(ROOT / "scripts" / "train.py"),
            "learner=ippo",
            "debug=smoke",
            "learner.minibatch_size=1000",
            f"hydra.run.dir={tmp_path / 'run'}",
        ],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"},
        timeout=120,
    )
    assert run.returncode != 0
    assert "Traceback" not in run.stderr + run.stdout
    lines = [line for line in run.stderr.splitlines() if line.startswith("error:")]
    assert len(lines) == 1 and "learner.minibatch_size=1000" in lines[0], run.stderr
    assert not (tmp_path / "run").exists()


# ---------------------------------------------------------------------- value normalisation
def test_value_normalisation_statistics_are_training_state_checked_on_resume(tmp_path):
    """``value_norm``: the running statistics of the value targets go into the training state,
    come back into a fresh learner, and a saved NaN is refused naming them."""
    learner, _ = make(MAPPOLearner, value_norm=True)
    learner.value_norm.update(torch.tensor([[2.0], [4.0]]))  # mean 3, mean of squares 10
    state = learner.training_state()
    assert set(state) == {"optimizer", "value_norm"}
    fresh, _ = make(MAPPOLearner, value_norm=True)
    fresh.restore_training_state(state, tmp_path / "training.pt")
    assert fresh.value_norm.normalize(torch.tensor([3.0])).item() == pytest.approx(0.0, abs=1e-4)
    assert fresh.value_norm.scale().item() == pytest.approx(1.0, rel=1e-3)  # var = 10 - 9
    state["value_norm"]["running_mean"] = torch.tensor([math.nan])
    with pytest.raises(ValueError, match="value_norm.*NaN"):
        fresh.restore_training_state(state, tmp_path / "training.pt")
    assert set(make(MAPPOLearner, value_norm=False)[0].training_state()) == {"optimizer"}
