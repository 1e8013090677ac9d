"""Neural learners: joint-action masking, VDN/QMIX mixing, training steps, checkpoints, devices."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from tensordict import TensorDict, unravel_key
from torchrl.collectors import Collector
from torchrl.data import Categorical
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import EGreedyModule, MultiAgentMLP, QValueModule

from mrta_rl.envs import AuctionEnv, AuctionParams
from mrta_rl.envs import encodings as ob
from mrta_rl.envs.torchrl_env import AuctionTorchRLEnv, prior_index, prior_one_hot
from mrta_rl.learners import SubGReserveLearner, TeamReserveLearner
from mrta_rl.learners.neural import IQLLearner, QMIXLearner, SubGDQNLearner, VDNLearner
from mrta_rl.learners.neural.networks import (
    PerRobotQ,
    joint_combine,
    joint_decode,
    stacked_forward,
)
from mrta_rl.learners.neural.q_learning import EpsilonGreedy
from mrta_rl.learners.neural.tensor_files import WEIGHTS_FILE
from mrta_rl.partition import subg_partition
from mrta_rl.priors import GreedyPrior
from mrta_rl.runners import build_run, evaluate_checkpoint, train
from mrta_rl.runners.evaluate import evaluate_policy
from mrta_rl.systems import build_system
from tests.conftest import paper_system
from tests.runners.test_checkpoint import save_hydra_files

SMALL = {"hidden": 16, "depth": 1, "batch_size": 32, "buffer_size": 1000}


@pytest.fixture
def system():
    """Four robots in two sub-groups (subG partition), three task types."""
    return build_system(
        {
            "name": "four",
            "robots": {"R1": ["T1", "T2"], "R2": ["T1"], "R3": ["T3"], "R4": ["T2", "T3"]},
        }
    )


def make(cls, system, batch=4, seed=0, horizon=60, **hp):
    partition = subg_partition(system)
    env = AuctionEnv(
        system,
        AuctionParams(horizon=horizon),
        batch_size=batch,
        active_tasks=partition.active_tasks(system) if cls.requires_partition else None,
        seed=seed,
    )
    learner = cls(env=env, rng=np.random.default_rng(seed), partition=partition, **(SMALL | hp))
    return learner, env


def randomize(learner, scale=3.0, seed=0):
    """Random weights everywhere (the last layers start at zero), so the prior does not decide."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in learner.networks.parameters():
            p.copy_(torch.randn(p.shape, generator=gen) * scale)


def collect(learner, env, frames=100, view=None):
    """One collector batch of the learner's exploring policy, as replay transitions.

    ``view``: the view's keywords (default: the prior and features, as the runner builds it).
    """
    view = view or {"prior": learner.rule, "features": learner.hp["features"]}
    view = AuctionTorchRLEnv(env, group_map=learner.group_map, **view)
    collector = Collector(
        view,
        learner.collection_policy,
        frames_per_batch=frames,
        total_frames=frames,
        auto_register_policy_transforms=False,
    )
    data = next(iter(collector))
    collector.shutdown()
    return learner.process_batch(data)


def assert_plays_the_rule(learner, env, rule):
    """The learner's greedy actions are the rule's for a whole episode, in which it holds back."""
    held = 0
    while not env.done.all():
        mask = env.action_mask.copy()
        expected = rule.act(rule.encode(env), mask, explore=False)
        np.testing.assert_array_equal(
            learner.act(learner.encode(env), mask, explore=False), expected
        )
        held += int(((expected == 0) & mask[:, :, 1:].any(-1)).sum())  # a robot kept back
        env.step(expected)
    assert held > 0  # the rule did hold robots back, so this is not the plain auction again


def test_joint_combine_and_decode_round_trip():
    A, n = 4, 3
    masks = torch.rand(5, n, A) < 0.6
    masks[..., 0] = True
    joint = joint_combine(masks, "and")  # [5, A^n]
    values = torch.randn(5, n, A)
    summed = joint_combine(values, "add")
    for j in range(A**n):
        actions = joint_decode(torch.tensor(j), n, A)  # [n]
        assert int(sum(int(a) * A**r for r, a in enumerate(actions))) == j
        expected_mask = torch.stack([masks[:, r, actions[r]] for r in range(n)]).all(0)
        assert torch.equal(joint[:, j], expected_mask)
        expected_sum = sum(values[:, r, actions[r]] for r in range(n))
        torch.testing.assert_close(summed[:, j], expected_sum)


def test_greedy_bid_is_the_lowest_valid_bid(system):
    mask = np.array([[[1, 0, 1, 1], [1, 0, 0, 0], [1, 1, 1, 0]]], dtype=bool)
    expected = torch.tensor([[0, 0, 1, 0], [0, 0, 0, 0], [0, 1, 0, 0]], dtype=torch.float32)
    greedy_bid = prior_one_hot(prior_index(GreedyPrior()(AuctionEnv(system), mask), 4), 4)[0]
    assert torch.equal(greedy_bid.float(), expected)


@pytest.mark.parametrize("features", ob.FEATURES)
@pytest.mark.parametrize("cls", [SubGDQNLearner, VDNLearner, QMIXLearner, IQLLearner])
def test_untrained_network_is_the_plain_auction(cls, system, features):
    """auction_prior + zero last layer: the greedy policy of an untrained net bids like greedy."""
    hp = {"prior": "greedy"} if cls is SubGDQNLearner else {}  # subG-DQN's default: spread_wait
    learner, env = make(cls, system, batch=6, features=features, **hp)
    for _ in range(40):
        mask = env.action_mask.copy()
        actions = learner.act(learner.encode(env), mask, explore=False)
        bids = mask[..., 1:]
        greedy = np.where(bids.any(-1), bids.argmax(-1) + 1, 0)
        np.testing.assert_array_equal(actions, greedy)
        env.step(actions)


@pytest.mark.parametrize("features", ob.FEATURES)
def test_untrained_subg_dqn_plays_the_subg_cql_prior(features):
    """prior spread_wait: the untrained nets play subG-CQL's prior, i.e. subg_reserve (0, 1),
    reading the slots and the recency from either encoding's layout."""
    system2 = paper_system("system2")
    learner, env = make(SubGDQNLearner, system2, batch=6, horizon=150, seed=11, features=features)
    rule = SubGReserveLearner(
        env=env, rng=np.random.default_rng(0), partition=learner.partition, reserve=0
    )
    assert_plays_the_rule(learner, env, rule)
    with pytest.raises(ValueError, match="prior: must be one of"):
        make(SubGDQNLearner, system2, prior="nope")
    with pytest.raises(ValueError, match="prior_order: must be one of"):
        make(SubGDQNLearner, system2, prior_order="nope")


HOLD = {"prior": "hold", "prior_hold_level": 1, "prior_hold_scope": "robot"}


@pytest.mark.parametrize(
    ("cls", "system_name", "reserve", "in_state", "features"),
    [
        (QMIXLearner, "system2", 1, False, "paper"),
        (QMIXLearner, "system1", 0, False, "paper"),
        (QMIXLearner, "system2", 1, True, "paper"),
        (VDNLearner, "system1", 0, True, "paper"),
        (IQLLearner, "system2", 1, False, "paper"),
        (QMIXLearner, "system2", 1, False, "time_to_free"),
        (VDNLearner, "system1", 0, True, "time_to_free"),
        (IQLLearner, "system2", 1, True, "time_to_free"),
    ],
)
def test_untrained_network_with_the_hold_prior_plays_team_reserve(
    cls, system_name, reserve, in_state, features
):
    """prior=hold: the untrained greedy policy is the team_reserve rule, tick by tick.

    Random weights below the zero last layer (so ``prior_in_state``'s input does reach it), and
    a whole episode, in which the rule holds robots back where the plain auction would bid.
    """
    system = paper_system(system_name)
    learner, env = make(
        cls, system, batch=6, horizon=150, seed=11, prior_reserve=reserve,
        prior_in_state=in_state, features=features, **HOLD,
    )  # fmt: skip
    zero_last = {name: p.clone() for name, p in learner.networks.named_parameters()}
    randomize(learner)
    with torch.no_grad():  # back to the zero output layer of an untrained net
        for name, p in learner.networks.named_parameters():
            if not zero_last[name].any():
                p.zero_()
    rule = TeamReserveLearner(
        env=env, rng=np.random.default_rng(0), reserve=reserve, hold_scope="robot"
    )
    assert_plays_the_rule(learner, env, rule)


def test_hold_prior_reaches_the_network_through_the_torchrl_env(system):
    """Training path: the env's prior_action is the rule's action, the collector plays it (eps
    0), the replayed transitions carry it for the next state too, and a gradient step runs."""
    learner, env = make(
        QMIXLearner, system, batch=5, prior_reserve=1, eps_start=0.0, eps_end=0.0, **HOLD
    )
    rule = TeamReserveLearner(env=env, rng=np.random.default_rng(0), reserve=1, hold_scope="robot")
    torchrl_env = AuctionTorchRLEnv(env, group_map=learner.group_map, prior=learner.rule)
    td = torchrl_env.reset()
    prior = td.get(("agents", "prior_action"))
    expected = rule.act(rule.encode(env), env.action_mask, explore=False)
    assert prior.dtype == torch.int8  # System-II: K + 1 = 4 actions
    assert torch.equal(prior.long(), torch.from_numpy(expected))
    data = collect(learner, env, frames=200)
    played = data.get(("agents", "action"))
    assert torch.equal(played, data.get(("agents", "prior_action")).long())
    assert ("next", "agents", "prior_action") in data.keys(include_nested=True)
    assert np.isfinite(learner.train_step(data[:64])["train/loss"])


@pytest.mark.parametrize("cls", [VDNLearner, QMIXLearner])
def test_mixed_learners_replay_only_what_their_loss_reads(cls, system):
    """No per-robot rewards, flags or Q-values in the replay; QMIX's state as exact bool, VDN's
    (its mixer has no state input) not at all; the loss still runs on the stored batch."""
    learner, env = make(cls, system, batch=4)
    data = collect(learner, env, frames=40)
    stored = set(data.keys(include_nested=True, leaves_only=True))
    assert stored == {unravel_key(k) for k in learner.losses["agents"].in_keys}
    assert ("next", "agents", "robot_reward") not in stored and ("agents", "reward") not in stored
    if cls is VDNLearner:
        assert "state" not in stored and ("next", "state") not in stored
    else:
        state = data.get("state")
        assert state.dtype == torch.bool and state.shape == (40, learner.state_size)
        assert data.get(("next", "state")).dtype == torch.bool
    assert np.isfinite(learner.train_step(data[:32])["train/loss"])


def test_qmix_mixes_a_bool_state_as_its_float_values(system):
    """The mixer reads the bool state it is stored as exactly as the float 0/1 state."""
    learner, _ = make(QMIXLearner, system)
    mixer = learner.networks["mixer"]
    torch.manual_seed(0)
    chosen = torch.randn(6, learner.n_robots, 1)
    state = torch.rand(6, learner.state_size) < 0.3
    assert torch.equal(mixer(chosen, state), mixer(chosen, state.float()))


def test_qmix_refuses_to_store_a_state_that_is_not_binary(system):
    learner, env = make(QMIXLearner, system, batch=2, features="paper")
    view = AuctionTorchRLEnv(env, group_map=learner.group_map, prior=learner.rule)
    data = view.rollout(3, learner.collection_policy)  # [B, T]
    data.set("state", data.get("state") * 0.5)
    with pytest.raises(RuntimeError, match="state: the global features are not 0/1"):
        learner.process_batch(data)


def test_checkpoint_of_another_prior_is_refused(system, tmp_path):
    learner, _ = make(QMIXLearner, system, prior_reserve=1, **HOLD)
    learner.save(tmp_path)
    make(QMIXLearner, system, seed=3, prior_reserve=1, **HOLD)[0].load(tmp_path)  # same prior
    for other in ({}, {**HOLD, "prior_reserve": 0}):
        with pytest.raises(ValueError, match="trained with prior"):
            make(QMIXLearner, system, **other)[0].load(tmp_path)


TTF = "time_to_free"


@pytest.mark.parametrize("cls", [SubGDQNLearner, VDNLearner, QMIXLearner, IQLLearner])
def test_time_to_free_features_are_what_the_networks_read(cls, system):
    """features=time_to_free: the networks' input sizes are the encoding's, and the observation
    and state of encode() (evaluation) and of the TorchRL view (training) are that encoding."""
    learner, env = make(cls, system, batch=3, features=TTF)
    F, G = ob.local_feature_size(env, TTF), ob.global_feature_size(env, TTF)
    assert (learner.n_features, learner.state_size) == (F, G)
    assert (F, G) != (ob.local_feature_size(env), ob.global_feature_size(env))
    for name, net in learner.networks.items():  # first layer: F per robot (or state G)
        first = next((p for p in net.parameters() if p.dim() >= 2), None)
        if name == "mixer":  # QMIX's hypernetworks read the state; VDN's sum has no weights
            assert first is None if cls is VDNLearner else first.shape[-1] == G
        elif cls is SubGDQNLearner:
            assert first.shape[-1] == len(learner.group_map[name]) * F
        else:
            assert first.shape[-1] == F
    view = AuctionTorchRLEnv(env, group_map=learner.group_map, features=learner.hp["features"])
    td = view.reset()
    encoded = learner.encode(env)
    local = torch.from_numpy(ob.local_features(env, TTF))
    robots = env.system.robots
    for group, ids in learner.group_map.items():
        idx = [robots.index(r) for r in ids]
        assert torch.equal(encoded.get((group, "observation")), local[:, idx])
        assert torch.equal(td.get((group, "observation")), local[:, idx])
    state = torch.from_numpy(ob.global_features(env, TTF))
    assert torch.equal(encoded.get("state"), state) and torch.equal(td.get("state"), state)
    randomize(learner)
    assert np.isfinite(learner.train_step(collect(learner, env, frames=60))["train/loss"])
    with pytest.raises(ValueError, match="features: must be one of"):
        make(cls, system, features="queue")


def test_checkpoint_of_other_features_is_refused(system, tmp_path):
    learner, _ = make(QMIXLearner, system, features=TTF)
    learner.save(tmp_path)
    make(QMIXLearner, system, seed=3, features=TTF)[0].load(tmp_path)
    with pytest.raises(ValueError, match="trained with features=time_to_free"):
        make(QMIXLearner, system, features="paper")[0].load(tmp_path)


@pytest.mark.parametrize("key", ["class", "group_map", "inputs", "hyperparameters"])
def test_weights_without_their_description_are_refused_naming_the_file(system, tmp_path, key):
    learner, _ = make(QMIXLearner, system)
    learner.save(tmp_path)
    meta = tmp_path / "learner.json"
    make(QMIXLearner, system, seed=3)[0].load(tmp_path)  # as saved: loads
    meta.write_text(json.dumps({k: v for k, v in json.loads(meta.read_text()).items() if k != key}))
    with pytest.raises(ValueError, match=f"learner.json: not a learner description.*{key}"):
        make(QMIXLearner, system)[0].load(tmp_path)
    meta.unlink()
    with pytest.raises(ValueError, match="learner.json: not a learner description"):
        make(QMIXLearner, system)[0].load(tmp_path)


@pytest.mark.parametrize("learner", ["subg_dqn", "qmix"])
def test_time_to_free_run_evaluates_again_from_its_checkpoint(compose_cfg, tmp_path, learner):
    """One tiny training episode with time_to_free, then scripts/evaluate.py's path rebuilds the
    same inputs from the run dir: the same evaluation, episode by episode."""
    overrides = [f"learner={learner}", "system=system1", "debug=smoke", "train.episodes=1"]
    cfg = compose_cfg([*overrides, f"learner.features={TTF}", "learner.warmup_frames=50"])
    save_hydra_files(cfg, tmp_path, learner, "system1")
    metrics = train(cfg, run_dir=tmp_path)
    assert metrics["train"]["gradient_steps"] > 0
    saved = (tmp_path / "learner" / "learner.json").read_text()
    assert f'"features": "{TTF}"' in saved
    again = evaluate_checkpoint(tmp_path)
    assert again["eval"]["team_return"] == metrics["eval"]["team_return"]
    assert build_run(cfg).learner.hp["features"] == TTF


def test_hold_prior_settings_are_checked(system):
    with pytest.raises(ValueError, match="prior: must be one of"):
        make(QMIXLearner, system, prior="spread_wait")
    with pytest.raises(ValueError, match="prior_in_state: needs prior=hold"):
        make(VDNLearner, system, prior_in_state=True)
    with pytest.raises(ValueError, match="prior_reserve"):
        make(QMIXLearner, system, prior="hold", prior_reserve=-1)


def test_joint_action_network_never_selects_a_masked_action(system):
    learner, env = make(SubGDQNLearner, system, batch=8)
    randomize(learner)
    for module in learner.egreedy:  # exploring half the time: random joint actions too
        module.eps.fill_(0.5)
    for _ in range(60):
        mask = env.action_mask.copy()
        view = learner.encode(env)
        for explore in (False, True):
            actions = learner.act(view, mask, explore=explore)
            chosen = np.take_along_axis(mask, actions[..., None], axis=-1)[..., 0]
            assert chosen.all(), "a masked action was selected"
        # the joint argmax of a group equals the masked argmax over the joint Q-values
        td = learner.policy(view.clone())
        for group in learner.group_map:
            values = td.get(("joint", group, "action_value"))
            joint_mask = td.get(("joint", group, "action_mask"))
            joint = td.get(("joint", group, "action"))
            assert joint_mask.gather(-1, joint.unsqueeze(-1)).all()
            best = torch.where(joint_mask, values, -torch.inf).argmax(-1)
            assert torch.equal(values.gather(-1, joint[:, None]), values.gather(-1, best[:, None]))
        env.step(learner.act(view, mask, explore=True))


def test_vdn_mix_equals_the_sum_of_chosen_values(system):
    learner, env = make(VDNLearner, system)
    randomize(learner)
    td = learner.policy(learner.encode(env))
    mixer = learner.losses["agents"].mixer_network
    local = td.get(("agents", "chosen_action_value"))  # [B, m, 1]
    mixed = mixer(td.clone()).get("chosen_action_value")  # [B, 1]
    torch.testing.assert_close(mixed, local.sum(dim=-2))


def test_qmix_mix_is_monotone_in_each_robot_value(system):
    learner, env = make(QMIXLearner, system)
    randomize(learner, scale=0.5)
    mixer = learner.networks["mixer"]
    gen = torch.Generator().manual_seed(1)
    state = torch.rand(64, learner.state_size, generator=gen).round()
    local = torch.randn(64, learner.n_robots, 1, generator=gen, requires_grad=True)
    mixer(local, state).sum().backward()
    assert (local.grad >= 0).all()  # non-negative mixing weights (hypernetwork abs)
    for i in range(learner.n_robots):  # and a finite step: raising Q_i never lowers Q_team
        higher = local.detach().clone()
        higher[:, i] += 1.0
        assert (mixer(higher, state) >= mixer(local.detach(), state) - 1e-6).all()


@pytest.mark.parametrize("cls", [SubGDQNLearner, VDNLearner, QMIXLearner, IQLLearner])
def test_train_step_lowers_the_loss_on_a_fixed_batch(cls, system):
    torch.manual_seed(0)
    learner, env = make(cls, system, lr=1e-2, target_update="hard", hard_update_interval=10**6)
    batch = collect(learner, env)
    before = learner.train_step(batch)["train/loss"]
    for _ in range(15):
        after = learner.train_step(batch)["train/loss"]
    assert after < before


@pytest.mark.parametrize("cls", [SubGDQNLearner, QMIXLearner])
def test_checkpoint_reloads_to_identical_evaluation(cls, system, tmp_path):
    torch.manual_seed(0)
    learner, env = make(cls, system, lr=1e-2)
    batch = collect(learner, env)
    for _ in range(10):
        learner.train_step(batch)
    learner.save(tmp_path)
    state = torch.load(tmp_path / WEIGHTS_FILE, weights_only=True)
    assert set(state) == set(learner.networks.state_dict())

    fresh, fresh_env = make(cls, system, seed=7)  # other init: must not matter after load
    fresh.load(tmp_path)
    eval_env = AuctionEnv(system, env.params, batch_size=3, active_tasks=env.active_tasks, seed=5)
    a = evaluate_policy(learner, eval_env, 3, seed=5).to_json()
    b = evaluate_policy(fresh, eval_env, 3, seed=5).to_json()
    assert a == b
    assert fresh.learning_space() == learner.learning_space()
    assert list(fresh.learning_space()) == ["parameters"]


def test_checkpoint_of_other_groups_is_refused(system, tmp_path):
    learner, _ = make(SubGDQNLearner, system)
    learner.save(tmp_path)
    other, _ = make(QMIXLearner, system)
    with pytest.raises(ValueError, match="groups"):
        other.load(tmp_path)


def test_encode_copies_the_mask(system):
    learner, env = make(VDNLearner, system)
    view = learner.encode(env)
    before = view.get(("agents", "action_mask")).clone()
    env.step(np.zeros((env.batch_size, env.n_robots), np.int64))
    assert torch.equal(view.get(("agents", "action_mask")), before)
    assert isinstance(view, TensorDict)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("cls", [SubGDQNLearner, QMIXLearner])
def test_cuda_runs_the_same_code(cls, system):
    learner, env = make(cls, system, device="cuda")
    batch = collect(learner, env).to("cuda")
    assert np.isfinite(learner.train_step(batch)["train/loss"])
    actions = learner.act(learner.encode(env), env.action_mask, explore=False)
    assert actions.shape == (env.batch_size, env.n_robots)


def test_epsilon_in_closed_form_follows_the_egreedy_schedule(system):
    """anneal(): EGreedyModule.step's linear decay, computed from the frame count."""
    learner, _ = make(QMIXLearner, system, eps_start=0.3, eps_end=0.02, eps_decay_frames=1000)
    reference = EGreedyModule(Categorical(5), eps_init=0.3, eps_end=0.02, annealing_num_steps=1000)
    assert learner.epsilon == pytest.approx(0.3)
    for frames in (100, 250, 400, 600):  # 100, 350, 750, 1350 frames: past the decay at the end
        learner.after_collect(frames)
        reference.step(frames)
        assert learner.epsilon == pytest.approx(float(reference.eps), abs=1e-5)
    assert learner.epsilon == pytest.approx(0.02)
    learner, _ = make(QMIXLearner, system, eps_start=0.3, eps_end=0.02, eps_decay_frames=1000)
    learner.after_collect(500)  # half way: 0.3 - 0.28 / 2, by hand
    assert learner.epsilon == pytest.approx(0.16)


def small_multiagent_mlp(share_params: bool) -> MultiAgentMLP:
    """TorchRL's multi-agent MLP: 7 features -> 4 actions, 5 robots, two hidden layers of 16."""
    return MultiAgentMLP(
        7,
        4,
        5,
        centralized=False,
        share_params=share_params,
        depth=2,
        num_cells=16,
        activation_class=torch.nn.ReLU,
    )


def test_shared_q_network_loads_multiagent_mlp_checkpoints():
    """The shared per-robot net is TorchRL's MLP; weights saved from the former shared
    MultiAgentMLP (keys mlp.params.*) load into it and give the same Q-values."""
    torch.manual_seed(3)
    old = small_multiagent_mlp(share_params=True)
    with torch.no_grad():
        for p in old.parameters():
            p.normal_()
    net = PerRobotQ(
        7,
        5,
        4,
        share_params=True,
        hidden=16,
        depth=2,
        auction_prior=0.0,
        device=torch.device("cpu"),
    )
    net.load_state_dict({f"mlp.{k}": v for k, v in old.state_dict().items()})
    x, prior = torch.rand(3, 5, 7), torch.zeros(3, 5, dtype=torch.int8)
    torch.testing.assert_close(net(x, prior), old(x))


@pytest.mark.parametrize("name", ["qmix", "vdn", "iql", "subg_dqn"])
def test_neural_budget_is_more_copies_for_the_same_frames_and_batches(name):
    """conf/budget/neural.yaml: 80 copies x 6 episodes = the tabular 30 x 16 copy-episodes.

    Every neural learner gets its copies by default; the frames, and the 800 frames per Collector
    batch (10 ticks x 80 copies, as 50 x 16 before), are those of the 16-copy budget; subG-DQN
    trains three times the episodes (conf/budget/subg_dqn.yaml, which pulls in the neural budget);
    the tabular learners keep 16 copies (subG-CQL its own 512); the command line and debug=smoke
    still win.
    """
    from pathlib import Path

    from hydra import compose, initialize_config_dir

    conf = str(Path(__file__).resolve().parents[3] / "conf")

    def budget(*overrides: str) -> tuple[int, int, int | None]:
        with initialize_config_dir(config_dir=conf, version_base=None):
            cfg = compose(config_name="config", overrides=list(overrides))
        train = cfg.train
        return int(train.batch_size), int(train.episodes), cfg.learner.get("collect_ticks")

    episodes = 18 if name == "subg_dqn" else 6  # subG-DQN: 3x (docs/results.md)
    assert budget(f"learner={name}") == (80, episodes, 10)
    assert budget(f"learner={name}", "system=system1") == (80, episodes, 10)
    assert budget("learner=subg_cql") == (512, 30, None)  # its own: conf/budget/subg_cql.yaml
    assert budget("learner=dql") == (16, 30, None)
    assert budget(f"learner={name}", "train.batch_size=16", "train.episodes=30")[:2] == (16, 30)
    assert budget(f"learner={name}", "debug=smoke")[:2] == (4, 2)


def _masks(shape, seed=0):
    gen = torch.Generator().manual_seed(seed)
    mask = torch.rand(shape, generator=gen) < 0.5
    mask[..., 0] = True  # wait is always valid (spec step 4)
    return mask


def test_epsilon_greedy_plays_torchrl_masked_argmax_when_not_exploring():
    """EpsilonGreedy's greedy action is QValueModule's masked argmax (the outside reference)."""
    values, mask = torch.randn(64, 5, 4), _masks((64, 5, 4))
    reference = QValueModule(
        action_space="categorical",
        action_value_key="action_value",
        action_mask_key="action_mask",
        out_keys=["action", "action_value", "chosen_action_value"],
    )
    expected = reference(TensorDict(action_value=values, action_mask=mask, batch_size=[64]))
    module = EpsilonGreedy(1.0, torch.device("cpu"))  # would always explore under RANDOM
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        torch.testing.assert_close(module(values, mask), expected["action"])
    module.eps.fill_(0.0)
    with set_exploration_type(ExplorationType.RANDOM):
        torch.testing.assert_close(module(values, mask), expected["action"])


def test_epsilon_greedy_draws_uniform_valid_actions():
    """eps = 1: each robot's action is uniform over its valid actions, never a masked one."""
    n = 20_000
    mask = torch.tensor([[1, 0, 1, 1], [1, 1, 0, 0]], dtype=torch.bool).expand(n, 2, 4)
    module = EpsilonGreedy(1.0, torch.device("cpu"))
    torch.manual_seed(0)
    with set_exploration_type(ExplorationType.RANDOM):
        actions = module(torch.randn(n, 2, 4), mask)
    for robot, valid in enumerate(([0, 2, 3], [0, 1])):
        counts = torch.bincount(actions[:, robot], minlength=4) / n
        for a in range(4):
            expected = 1 / len(valid) if a in valid else 0.0
            assert counts[a] == pytest.approx(expected, abs=0.015)


def test_joint_epsilon_greedy_explores_per_group_and_copy():
    """Joint actions: one coin per copy (as EGreedyModule on the group's [B] keys), a uniform
    valid joint action drawn per robot, and the joint action is the robots' actions encoded."""
    n, n_g, A = 20_000, 3, 3
    robot_mask = torch.tensor([1, 1, 0], dtype=torch.bool).expand(n, n_g, A)  # wait or slot 1
    joint_mask = joint_combine(robot_mask, "and")  # [n, 27]
    values = torch.zeros(n, A**n_g)
    values[:, 0] = 1.0  # greedy: everyone waits
    module = EpsilonGreedy(0.5, torch.device("cpu"), joint=(n_g, A))
    torch.manual_seed(1)
    with set_exploration_type(ExplorationType.RANDOM):
        joint, robots = module(values, joint_mask, robot_mask)
    torch.testing.assert_close(robots, joint_decode(joint, n_g, A))
    assert joint_mask.gather(-1, joint.unsqueeze(-1)).all()
    # all wait: greedy (1/2) or a random joint action that is all-wait (1/2 x 1/8); one coin
    # per robot would give (1/2 + 1/4)^3 = 0.42
    all_wait = (robots == 0).all(-1).float().mean()
    assert all_wait == pytest.approx(0.5 + 0.5 / 8, abs=0.015)
    # among explored copies, every valid joint action is equally likely
    explored = joint[joint != 0]
    counts = torch.bincount(explored, minlength=A**n_g) / (0.5 * n)
    valid = joint_mask[0].nonzero().flatten()
    assert counts[valid[1:]].sub(1 / 8).abs().max() < 0.015
    assert counts.sum() == pytest.approx(7 / 8, abs=0.02)


def test_stacked_forward_is_multiagent_mlp():
    """IQL's per-robot nets as batched matmuls: MultiAgentMLP's outputs and gradients."""
    torch.manual_seed(0)
    mlp = small_multiagent_mlp(share_params=False)
    x = torch.rand(3, 2, 5, 7)
    expected = mlp(x)
    expected.square().sum().backward()
    grads = [p.grad.clone() for p in mlp.parameters()]
    mlp.zero_grad()
    got = stacked_forward(mlp, x)
    got.square().sum().backward()
    torch.testing.assert_close(got, expected)
    for p, grad in zip(mlp.parameters(), grads, strict=True):
        torch.testing.assert_close(p.grad, grad)
