"""Shared parts of the TorchRL learners: features, masked epsilon-greedy, training, checkpoints.

The neural learners (``subg_dqn``, ``vdn``, ``qmix``, ``iql``) are built from TorchRL parts on the
keys of :class:`~mrta_rl.envs.torchrl_env.AuctionTorchRLEnv`: per group ``(group,
"observation")`` ``[*, n_g, F]`` (:func:`~mrta_rl.envs.encodings.local_features`), ``(group,
"action_mask")`` ``[*, n_g, K + 1]`` and ``(group, "action")`` ``[*, n_g]``, root ``"state"``
(global features), and the rewards ``(group, "reward")`` (team reward, TorchRL's reward key),
``(group, "robot_reward")`` and ``(group, "group_reward")``, all ``[*, n_g, 1]``. The same
modules serve

* the TorchRL training loop (``mrta_rl.runners.torchrl``): :attr:`NeuralLearner.explore_policy`
  (Q-network -> :class:`EpsilonGreedy`: masked argmax, random valid actions) runs inside a
  ``Collector``, and :meth:`NeuralLearner.train_step` optimises the TorchRL loss on replayed
  batches;
* the shared evaluation of every learner kind (``runners/evaluate.py``): :meth:`encode` builds the
  same TensorDict from a core :class:`~mrta_rl.envs.AuctionEnv` and :meth:`act` runs the greedy
  policy, so a neural run is scored exactly like a tabular one.

Auction prior (documented bias, ``auction_prior`` hyperparameter): the Q-value of the plain
auction's action -- the lowest-numbered valid bid (spec "Fixed policies", greedy) -- gets a fixed
bonus ``auction_prior`` added to the network output, and the network's last layer starts at zero.
An untrained network therefore *is* the greedy auction, and Q-learning only has to learn where
deviating from it pays (wait for an H task, spread bids over slots). The bonus is part of the
Q-function in the online and the target network alike, so it is an initialisation, not reward
shaping: the TD fixed point is unchanged, only the function the net must represent is
``Q* - prior``. ``auction_prior: 0`` turns it off.

Rule prior (``prior: hold``, the words of DQL's ``prior``): the bonus goes instead to the action of
the whole-team ``team_reserve`` rule (:class:`~mrta_rl.learners.tabular.priors.HoldRule`, the
``prior_*`` settings), so the untrained network plays that rule exactly. The rule reads the whole
team (which robots are idle, which one the team asks first), more than a robot's local features.

Every prior (the plain auction's :class:`~mrta_rl.learners.tabular.priors.GreedyPrior`, the rule,
subG-DQN's ``spread_wait``) is computed from the core env with the rules of ``mrta_rl/rules.py``
-- by :class:`~mrta_rl.envs.torchrl_env.AuctionTorchRLEnv` (its ``prior`` argument) while
training and by :meth:`NeuralLearner.encode` in evaluation -- and reaches the Q-network as the
observation ``(group, "prior_action")``, the action index per robot, stored in the replay buffer
with the other observations so the target network sees the prior's action of the next state;
the networks expand it to a one-hot (:func:`~mrta_rl.envs.torchrl_env.prior_one_hot`).
``prior_in_state`` (with ``hold``) also feeds that one-hot to the network as an input.

Inputs (``features``, :data:`~mrta_rl.envs.encodings.FEATURES`): ``paper`` (default) or
``time_to_free`` (free levels and queue levels added, ``encodings`` module docstring,
"Features"). The networks are built for that encoding's sizes; the training runner builds the
TorchRL view with it and :meth:`NeuralLearner.encode` uses it in evaluation, and checkpoints
record it (``learner.json``), so a re-evaluation rebuilds the same inputs.

Network (``network``, :data:`NETWORKS`, QMIX, VDN and IQL): ``mlp`` (default) is the per-robot
MLP over the local features above, robot-id one-hot included; ``set`` is the shared robot-set
network (``set_network.py``) over the team-size independent set inputs
(:func:`~mrta_rl.envs.encodings.set_inputs`): one set of weights whatever the team, no robot id,
the local features left out of the env view and the replay buffer. QMIX's mixer keeps reading
the global ``state``.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Annotated, Any, ClassVar, Literal

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.envs.utils import ExplorationType, exploration_type, set_exploration_type
from torchrl.modules import QValueModule
from torchrl.objectives import HardUpdate, LossModule, SoftUpdate

from mrta_rl.checked_files import read_tensors, tensor_file_limit
from mrta_rl.config import Choices, ConfigError, Range, UserError, short_list
from mrta_rl.envs import AuctionEnv, encodings
from mrta_rl.envs.torchrl_env import (
    GROUP_SET_KEYS,
    PRIOR_KEY,
    ROOT_SET_KEYS,
    prior_index,
    set_inputs_td,
)
from mrta_rl.learners.base import (
    FACTS,
    TORCHRL_LOOP,
    Learner,
    LearnerKind,
    MemoryQuery,
    NonFiniteState,
    read_description,
)
from mrta_rl.learners.fixed import HOLD_SCOPES, HoldLevel, Reserve
from mrta_rl.learners.memory import (
    NEURAL_ADVICE,
    ResourceEstimate,
    feature_sizes,
    mlp_weights,
    neural_estimate,
)
from mrta_rl.learners.neural.networks import PerRobotQ, joint_decode, joint_encode
from mrta_rl.learners.neural.set_network import (
    ROBOT_ATTENTION,
    SetNetwork,
    SetWithPrior,
    check_fits,
)
from mrta_rl.partition import Partition
from mrta_rl.priors import HOLD_PRIORS, GreedyPrior, HoldRule, SpreadWaitPrior
from mrta_rl.run_layout import ANY, INT, STR, RunDirError
from mrta_rl.types import GroupMap

logger = logging.getLogger(__name__)

WEIGHTS_FILE = "weights.pt"  # state_dict of the Q-networks (and mixer), torch.load(weights_only)
META_FILE = "learner.json"  # group map and sizes, to check a checkpoint fits the run
TRAINING_FILE = "training.pt"  # optimizer, target networks, epsilon (training checkpoints)
# learner.json as NeuralLearner.save writes it (run_files.check_schema)
META = {
    "class": STR,
    "group_map": {"*": [STR]},
    "gradient_steps": INT,
    "hyperparameters": {"*": ANY},
    "prior": ANY,
}
JOINT = "joint"  # root sub-TensorDict of joint-action keys: (JOINT, group, leaf), batch [*]
Prior = GreedyPrior | HoldRule | SpreadWaitPrior  # env state -> [B, m] the prior's actions
# per-robot reward leaves of AuctionTorchRLEnv, [*, n_g, 1]: team (TorchRL's reward key),
# individual, and sub-group reward (spec step 8)
REWARD_KEYS = ("reward", "robot_reward", "group_reward")


MIN_TORCHRL = (0, 14)  # Collector(auto_register_policy_transforms=...), torchrl 0.14 names


def require_torchrl() -> None:
    """Fail clearly under an older torchrl (e.g. BenchMARL's venv, which pins ``torchrl<0.12``).

    The env and its TorchRL view run under BenchMARL's torchrl; the project's own learners and
    runner use torchrl 0.14 parts.

    Raises:
        RuntimeError: naming the installed and the needed version.
    """
    import torchrl

    installed = tuple(int(part) for part in torchrl.__version__.split(".")[:2])
    if installed < MIN_TORCHRL:
        raise RuntimeError(
            f"the neural learners need torchrl>=0.14 (installed: {torchrl.__version__}); "
            "BenchMARL's venv pins torchrl<0.12: train them from the project's own venv"
        )


# ---------------------------------------------------------------------------------- features
def observation_td(
    env: AuctionEnv,
    group_map: GroupMap,
    mask: np.ndarray,
    prior: Prior | None = None,
    features: str = "paper",
    set_inputs: bool = False,
) -> TensorDict:
    """The TorchRL observation of the env's decision point, as ``AuctionTorchRLEnv`` writes it.

    Args:
        env: The core env at a decision point (any batch size ``B``).
        group_map: ``{group: [robot ids]}``.
        mask: ``[B, m, K + 1]`` bool valid actions (copied, the core reuses its buffer).
        prior: The prior (module docstring), or None (no ``prior_action`` key).
        features: ``encodings.FEATURES``: the encoding of ``observation`` and ``state``.
        set_inputs: The set network's inputs instead of the local features (``AuctionTorchRLEnv``
            with ``set_inputs=True, local_features=False``).

    Returns:
        TensorDict of batch ``[B]``: ``state`` ``[B, G]`` and per group ``observation``
        ``[B, n_g, F]``, ``action_mask`` ``[B, n_g, K + 1]`` [and ``prior_action`` ``[B, n_g]``];
        with ``set_inputs``, ``slots``, ``slot_type``, ``types`` and per group ``robots``,
        ``robot_types`` instead of ``observation``.
    """
    robots = env.system.robots
    index = {g: torch.tensor([robots.index(r) for r in ids]) for g, ids in group_map.items()}
    if set_inputs:
        td = set_inputs_td(env, group_map, mask)
    else:
        local = torch.from_numpy(encodings.local_features(env, features))  # [B, m, F]
        mask_t = torch.from_numpy(np.ascontiguousarray(mask, dtype=bool))  # [B, m, K + 1]
        B = mask_t.shape[0]
        leaves = {
            group: TensorDict(
                {"observation": local[:, idx], "action_mask": mask_t[:, idx].clone()},
                batch_size=(B, len(idx)),
            )
            for group, idx in index.items()
        }
        td = TensorDict(leaves, batch_size=(B,))
    td.set("state", torch.from_numpy(encodings.global_features(env, features)))
    if prior is not None:
        prior_t = prior_index(prior(env, mask), env.n_actions)
        for group, idx in index.items():
            td.set((group, PRIOR_KEY), prior_t[:, idx])
    return td


# ---------------------------------------------------------------------------------- exploration
class EpsilonGreedy(nn.Module):
    """Masked argmax of Q-values, then epsilon-greedy among valid actions: the collection policy.

    Computes what TorchRL's ``QValueModule`` (masked argmax) followed by ``EGreedyModule`` with
    ``action_mask_key`` [and ``JointDecode``] compute, in a few tensor ops per tick (the module
    chain, its spec updates and ``multinomial`` draws over the masks were half of a collection
    tick): with probability ``eps`` (one draw per robot, or per sub-group and copy for joint
    actions, as ``EGreedyModule`` draws per element of its action's TensorDict) the greedy action
    is replaced by a uniform valid one. A uniform valid *joint* action is a uniform valid action
    per robot, since the joint mask is the product of the robots' masks (``joint_combine``), so
    it is drawn on ``[*, n_g, K + 1]`` rather than over the ``(K + 1)^{n_g}`` joint actions. As
    ``EGreedyModule``, it explores only under ``ExplorationType.RANDOM`` (the Collector's) or no
    exploration type, and plays the greedy action otherwise. Draws come from torch's generator,
    which the runner seeds.
    """

    def __init__(self, eps: float, device: torch.device, joint: tuple[int, int] | None = None):
        """Hold the exploration rate (a buffer, set by :meth:`NeuralLearner.anneal`).

        Args:
            eps: Initial exploration rate.
            device: Buffer device.
            joint: ``(n_g, K + 1)`` for joint actions (subG-DQN), None for per-robot actions.
        """
        super().__init__()
        self.register_buffer("eps", torch.tensor(float(eps), device=device))
        self.joint = joint

    def forward(
        self, values: torch.Tensor, mask: torch.Tensor, robot_mask: torch.Tensor | None = None
    ) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        """Actions of the Q-values.

        Args:
            values: ``[*, n, A]`` per-robot Q-values, or ``[*, A^n_g]`` joint Q-values.
            mask: Valid actions of ``values`` (bool, same shape).
            robot_mask: Joint actions only: ``[*, n_g, K + 1]`` the robots' masks.

        Returns:
            ``[*, n]`` actions, or ``([*] joint actions, [*, n_g] the robots' actions)``.
        """
        action = torch.where(mask, values, torch.finfo(values.dtype).min).argmax(-1)
        if self.joint is not None:
            action = joint_decode(action, *self.joint)  # [*, n_g]
            mask = robot_mask
        if exploration_type() in (ExplorationType.RANDOM, None):
            coin_shape = mask.shape[:-2] + (1 if self.joint else mask.shape[-2],)
            explore = torch.rand(coin_shape, device=mask.device) < self.eps
            # the largest of i.i.d. uniforms over the valid actions is a uniform valid action
            random = (torch.rand(mask.shape, device=mask.device) * mask).argmax(-1)
            action = torch.where(explore, random, action)
        if self.joint is None:
            return action
        return joint_encode(action, self.joint[1]), action


# ---------------------------------------------------------------------------------- learner
class NeuralLearner(Learner, abstract=True):
    """Base of the TorchRL learners: policies, masked epsilon-greedy, optimiser, target updates.

    Subclasses set :attr:`group_map` and build, in :meth:`_build`, ``self.networks`` (an
    ``nn.ModuleDict``, everything that is saved), ``self.policy`` (greedy, writes ``(group,
    "action")``), ``self.explore_policy`` (with :class:`EpsilonGreedy`) and ``self.losses`` (TorchRL
    loss modules). They may override :meth:`transitions` to add the keys their loss reads.
    Training runs in ``mrta_rl.runners.torchrl``; :meth:`update` stays the base no-op. Besides
    the facts of every learner, a subclass counts its trainable weights (``network_weights``,
    a classmethod ``(env, partition, settings) -> int``) for the memory estimate.
    """

    kind: ClassVar[LearnerKind] = "neural"
    training_loop: ClassVar[str] = TORCHRL_LOOP
    facts: ClassVar[tuple[str, ...]] = (*FACTS, "network_weights")
    memory_advice: ClassVar[str] = NEURAL_ADVICE  # what to change when it does not fit
    # what a replayed transition keeps (memory.neural_estimate): only the loss's keys, and
    # the bytes per global feature of its states
    replay_loss_keys_only: ClassVar[bool] = False
    replay_state_bytes: ClassVar[int] = 4

    @classmethod
    def estimate_memory(cls, query: MemoryQuery) -> ResourceEstimate:
        """Networks (with target copies, gradients, Adam), replay buffer and collector batch.

        Raises:
            Unfit: if the networks cannot be built on the system (``network_weights``).
        """
        env, partition, settings, decisions, copies = query
        weights = cls.network_weights(env, partition, settings)
        return neural_estimate(
            cls.__name__,
            env,
            settings,
            weights,
            copies,
            cls.memory_advice,
            loss_keys_only=cls.replay_loss_keys_only,
            state_bytes=cls.replay_state_bytes,
        )

    @classmethod
    def learning_space_dimension(
        cls, env: AuctionEnv, partition: Partition | None, settings: dict[str, Any]
    ) -> int | None:
        """None: no table; :meth:`learning_space` counts the trained parameters instead."""
        return None

    def __init__(
        self,
        *,
        env: AuctionEnv,
        rng: np.random.Generator,
        partition: Partition | None = None,
        hidden: Annotated[int, Range(1)] = 128,
        depth: Annotated[int, Range(1)] = 2,
        lr: Annotated[float, Range(0, low_open=True)] = 5e-4,
        gamma: Annotated[float, Range(0, 1, low_open=True, high_open=True)] = 0.95,
        loss_function: Literal["l2", "smooth_l1"] = "smooth_l1",
        reward_scale: Annotated[float, Range(0, low_open=True)] = 0.1,
        auction_prior: Annotated[float, Range(0)] = 1.0,
        prior: Annotated[str, Choices(*HOLD_PRIORS)] = "greedy",
        prior_reserve: Reserve = 0,
        prior_hold_level: HoldLevel = 1,
        prior_hold_scope: Annotated[str, Choices(*HOLD_SCOPES)] = "robot",
        prior_in_state: bool = False,
        features: Annotated[str, Choices(*encodings.FEATURES)] = "paper",
        eps_start: Annotated[float, Range(0, 1)] = 0.3,
        eps_end: Annotated[float, Range(0, 1)] = 0.02,
        eps_decay_frames: Annotated[int, Range(1)] = 200_000,
        buffer_size: Annotated[int, Range(1)] = 100_000,
        batch_size: Annotated[int, Range(1)] = 256,
        collect_ticks: Annotated[int, Range(1)] = 50,
        updates_per_collect: Annotated[int, Range(0)] = 25,
        warmup_frames: Annotated[int, Range(0)] = 2_000,
        target_update: Literal["soft", "hard"] = "soft",
        tau: Annotated[float, Range(0, 1, low_open=True)] = 0.01,
        hard_update_interval: Annotated[int, Range(1)] = 500,
        max_grad_norm: Annotated[float, Range(0, low_open=True)] = 10.0,
        device: Annotated[str, Choices("cpu", "cuda")] = "cpu",
    ) -> None:
        """Store the hyperparameters and build the networks (see ``conf/learner/*.yaml``).

        Args:
            env: The training env (sizes only; never stepped by the learner).
            rng: Seeds the network initialisation (in a forked torch state); exploration and
                replay draw from torch, which the runner seeds.
            partition: The subG partition (subG-DQN only).
            hidden: Units per hidden layer of the Q-networks.
            depth: Hidden layers of the Q-networks.
            lr: Adam learning rate.
            gamma: Discount per tick.
            loss_function: TD loss, ``"l2"`` or ``"smooth_l1"`` (Huber).
            reward_scale: Rewards are multiplied by this before the TD target (Q-value scale).
            auction_prior: Bonus of the prior's action in Q-units (module docstring); 0 = off.
            prior: The action the bonus goes to: ``greedy`` (the plain auction's bid) or ``hold``
                (the ``team_reserve`` rule's, :data:`~mrta_rl.learners.tabular.priors.HOLD_PRIORS`;
                subG-DQN has its own ``prior``).
            prior_reserve: ``prior="hold"``: the rule's ``reserve``.
            prior_hold_level: ``prior="hold"``: the rule's ``hold_level``.
            prior_hold_scope: ``prior="hold"``: the rule's ``hold_scope``.
            prior_in_state: ``prior="hold"``: the rule's action (one-hot) is also a network input.
            features: The inputs' encoding (``encodings.FEATURES``): ``paper`` (the paper-era
                local and global features) or ``time_to_free`` (+ free levels and queue levels).
            eps_start: Initial exploration rate (random valid actions).
            eps_end: Final exploration rate.
            eps_decay_frames: Collected frames (copy-ticks) over which epsilon decays linearly.
            buffer_size: Replay buffer capacity in transitions (copy-ticks).
            batch_size: Transitions per gradient step.
            collect_ticks: Ticks per collector batch (frames per batch = ticks x copies).
            updates_per_collect: Gradient steps after each collector batch.
            warmup_frames: Frames collected before the first gradient step.
            target_update: ``"soft"`` (``SoftUpdate``, Polyak ``tau``) or ``"hard"``
                (``HardUpdate`` every ``hard_update_interval`` gradient steps).
            tau: Soft update rate.
            hard_update_interval: Gradient steps between hard target copies.
            max_grad_norm: Gradient clipping norm.
            device: ``"cpu"`` or ``"cuda"``; networks and training live there, the env on cpu.

        Raises:
            ValueError: on an out-of-range hyperparameter or an unavailable device.
        """
        require_torchrl()
        super().__init__(env=env, rng=rng, partition=partition)
        if torch.device(device).type == "cuda" and not torch.cuda.is_available():
            raise ValueError("device=cuda but CUDA is not available")
        # types and ranges: the annotations (mrta_rl.config); here only a relation
        if eps_end > eps_start:
            raise ValueError(f"need eps_end <= eps_start, got {eps_end}, {eps_start}")
        if prior_in_state and prior != "hold":
            raise ValueError("prior_in_state needs prior=hold (the plain auction is no input)")
        # the prior, computed from the env (module docstring)
        self.rule: Prior = GreedyPrior()
        if prior == "hold":
            self.rule = HoldRule(
                env,
                reserve=prior_reserve,
                hold_level=prior_hold_level,
                hold_scope=prior_hold_scope,
            )
        self.prior_in_state = prior_in_state
        # what the Q bonus is added to: part of the Q-function, so a checkpoint must match it
        self.prior_settings: dict[str, Any] = {"prior": prior, "prior_in_state": prior_in_state}
        if prior == "hold":
            self.prior_settings |= {
                "prior_reserve": prior_reserve,
                "prior_hold_level": prior_hold_level,
                "prior_hold_scope": prior_hold_scope,
            }
        self.device = torch.device(device)
        self.hp = {
            "hidden": hidden,
            "depth": depth,
            "lr": lr,
            "gamma": gamma,
            "loss_function": loss_function,
            "reward_scale": reward_scale,
            "auction_prior": auction_prior,
            "eps_start": eps_start,
            "eps_end": eps_end,
            "eps_decay_frames": eps_decay_frames,
            "buffer_size": buffer_size,
            "batch_size": batch_size,
            "collect_ticks": collect_ticks,
            "updates_per_collect": updates_per_collect,
            "warmup_frames": warmup_frames,
            "target_update": target_update,
            "tau": tau,
            "hard_update_interval": hard_update_interval,
            "max_grad_norm": max_grad_norm,
            "features": features,  # saved with the weights: load() checks it
        }
        self.n_features = encodings.local_feature_size(env, features)
        self.state_size = encodings.global_feature_size(env, features)
        self.group_map: GroupMap = self._group_map()
        self.networks = nn.ModuleDict()
        self.losses: dict[str, LossModule] = {}
        self.egreedy: list[EpsilonGreedy] = []  # the exploration rates (anneal, checkpoints)
        # network initialisation draws from torch's generator: seed it from the learner's own
        # generator, in a forked state, so runs are reproducible and torch's global state is
        # left to the runner
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(int(rng.integers(2**31)))
            self._build()
        for loss in self.losses.values():
            loss.make_value_estimator(gamma=gamma)
        params = [p for loss in self.losses.values() for p in loss.parameters()]
        # fused: one kernel over all parameters (the per-tensor loop was ~3 % of a gradient step)
        self.optimizer = torch.optim.Adam(params, lr=lr, fused=True)
        self.target_updaters = [
            SoftUpdate(loss, tau=tau)
            if target_update == "soft"
            else HardUpdate(loss, value_network_update_interval=hard_update_interval)
            for loss in self.losses.values()
        ]
        self.gradient_steps = 0
        self.frames_collected = 0  # copy-ticks seen by anneal(): the epsilon schedule's clock

    # -------------------------------------------------------------- for subclasses
    def _group_map(self) -> GroupMap:
        """TorchRL groups of the learner; default: all robots in one group ``"agents"``."""
        return {"agents": list(self.env.system.robots)}

    def _build(self) -> None:  # pragma: no cover - abstract in spirit
        raise NotImplementedError

    def _egreedy(self, joint: tuple[int, int] | None = None) -> EpsilonGreedy:
        """An :class:`EpsilonGreedy` at ``eps_start``, annealed by :meth:`anneal`."""
        module = EpsilonGreedy(self.hp["eps_start"], self.device, joint)
        self.egreedy.append(module)
        return module

    def _q_network(self, group: str, share_params: bool) -> tuple[nn.Module, list]:
        """The per-robot Q-network of a group and the keys it reads, in its arguments' order.

        Returns:
            A :class:`PerRobotQ` over ``(group, "observation")`` and ``(group, "prior_action")``.
        """
        qnet = PerRobotQ(
            self.n_features,
            len(self.group_map[group]),
            self.n_actions,
            share_params=share_params,
            hidden=self.hp["hidden"],
            depth=self.hp["depth"],
            auction_prior=self.hp["auction_prior"],
            device=self.device,
            prior_in_state=self.prior_in_state,
        )
        return qnet, [(group, "observation"), (group, PRIOR_KEY)]

    def _per_robot_policy(
        self, group: str, share_params: bool
    ) -> tuple[TensorDictSequential, TensorDictSequential]:
        """Greedy and exploring policies of one group over the same per-robot Q-network.

        Returns:
            ``(policy, explore_policy)``: Q-network + ``QValueModule`` (masked argmax; the
            losses' value network, and the greedy policy), and Q-network +
            :class:`EpsilonGreedy` (the collection policy, writing ``(group, "action")``).
        """
        qnet, in_keys = self._q_network(group, share_params)
        self.networks[group] = qnet
        value = TensorDictModule(qnet, in_keys=in_keys, out_keys=[(group, "action_value")])
        policy = TensorDictSequential(
            value,
            QValueModule(
                action_space="categorical",
                action_value_key=(group, "action_value"),
                action_mask_key=(group, "action_mask"),
                out_keys=[
                    (group, "action"),
                    (group, "action_value"),
                    (group, "chosen_action_value"),
                ],
            ),
        )
        explore = TensorDictSequential(
            value,
            TensorDictModule(
                self._egreedy(),
                in_keys=[(group, "action_value"), (group, "action_mask")],
                out_keys=[(group, "action")],
            ),
        )
        return policy, explore

    # -------------------------------------------------------------- runner hooks
    @property
    def epsilon(self) -> float:
        """Current exploration rate (shown by the progress bar)."""
        return float(self.egreedy[0].eps) if self.egreedy else 0.0

    def anneal(self, frames: int) -> None:
        """Advance the epsilon schedules by ``frames`` collected copy-ticks.

        The linear decay of ``EGreedyModule.step`` in closed form: ``EGreedyModule.step(n)``
        loops in Python over the ``n`` frames (one tensor op each), which cost as much as
        collecting them; ``eps = max(eps_end, eps_start - (eps_start - eps_end) f / F)``
        after ``f`` frames (``F = eps_decay_frames``) is the same schedule.
        """
        self.frames_collected += frames
        start, end = self.hp["eps_start"], self.hp["eps_end"]
        progress = min(self.frames_collected / self.hp["eps_decay_frames"], 1.0)
        eps = start - (start - end) * progress
        for module in self.egreedy:
            module.eps.fill_(eps)

    def transitions(self, data: TensorDictBase) -> TensorDictBase:
        """Collector batch -> replay transitions (flattened; rewards scaled).

        Args:
            data: ``[B, T]`` collector output.

        Returns:
            ``[B * T]`` transitions with the keys the loss reads.
        """
        # the collector's trajectory ids are read by no loss, and restart on resume
        data = data.reshape(-1).exclude("collector")
        scale = self.hp["reward_scale"]
        for group in self.group_map:
            for key in REWARD_KEYS:
                data.set(("next", group, key), data.get(("next", group, key)) * scale)
        return data

    def train_step(self, batch: TensorDictBase) -> dict[str, float]:
        """One gradient step on a replayed batch, then the target-network update.

        Args:
            batch: Transitions from :meth:`transitions`, on :attr:`device`.

        Returns:
            ``{"train/loss": ...}`` (summed over the groups' losses).
        """
        total = sum(loss(batch)["loss"] for loss in self.losses.values())
        value = float(total.detach())
        check_loss(value, self.label, self.gradient_steps + 1)  # before the step changes weights
        self.optimizer.zero_grad(set_to_none=True)
        total.backward()
        params = [p for group in self.optimizer.param_groups for p in group["params"]]
        nn.utils.clip_grad_norm_(params, self.hp["max_grad_norm"])
        self.optimizer.step()
        for updater in self.target_updaters:
            updater.step()
        self.gradient_steps += 1
        return {"train/loss": value}

    # -------------------------------------------------------------- Learner interface
    @property
    def features(self) -> str:
        """The inputs' encoding (``hp``): the env view builds the observations with it."""
        return self.hp["features"]

    @property
    def set_inputs(self) -> bool:
        """The networks read the set inputs instead of the local features (``network=set``)."""
        return self.hp.get("network") == "set"

    @property
    def view_options(self) -> dict[str, Any]:
        """What the TorchRL view must write for these networks (``AuctionTorchRLEnv``'s keywords).

        The prior's action, the features' encoding, and the set inputs instead of the local
        features with ``network=set``.
        """
        return {
            "prior": self.rule,
            "features": self.features,
            "set_inputs": self.set_inputs,
            "local_features": not self.set_inputs,
        }

    def encode(self, env: AuctionEnv) -> TensorDict:
        """Observation TensorDict of the decision point (:func:`observation_td`, copied arrays).

        With ``prior=hold`` it carries the rule's action, computed under the env's mask (the
        runner's evaluation passes that same mask to :meth:`act`).
        """
        return observation_td(
            env, self.group_map, env.action_mask, self.rule, self.features, self.set_inputs
        )

    def act(self, view: TensorDict, mask: np.ndarray, *, explore: bool) -> np.ndarray:
        """Greedy (or epsilon-greedy) actions of the TorchRL policy, valid under ``mask``.

        Args:
            view: Output of :meth:`encode`.
            mask: ``[B, m, K + 1]`` bool valid actions (replaces the view's masks).
            explore: Use ``explore_policy`` (epsilon-greedy) instead of the greedy ``policy``.

        Returns:
            ``[B, m]`` int64 actions.
        """
        td = view.clone()
        mask_t = torch.from_numpy(np.ascontiguousarray(mask, dtype=bool))
        robots = self.env.system.robots
        index = {g: [robots.index(r) for r in ids] for g, ids in self.group_map.items()}
        for group, idx in index.items():
            td.set((group, "action_mask"), mask_t[:, idx])
        td = td.to(self.device)
        exploration = ExplorationType.RANDOM if explore else ExplorationType.DETERMINISTIC
        with torch.no_grad(), set_exploration_type(exploration):
            td = (self.explore_policy if explore else self.policy)(td)
        actions = np.zeros(mask.shape[:2], np.int64)  # [B, m]
        for group, idx in index.items():
            actions[:, idx] = td.get((group, "action")).cpu().numpy()
        return actions

    def learning_space(self) -> dict[str, int]:
        """Network size: ``{"parameters": trainable parameter count}`` (no table dimension)."""
        return {"parameters": sum(p.numel() for p in self.networks.parameters())}

    def save(self, directory: Path) -> None:
        """Write ``weights.pt`` (a state_dict, loadable with ``weights_only=True``) and meta json.

        Args:
            directory: Target folder (created if missing).
        """
        directory = Path(directory)
        state = self.networks.state_dict()
        check_finite_weights(state, f"{self.label} after gradient step {self.gradient_steps}")
        directory.mkdir(parents=True, exist_ok=True)
        write_tensors(state, directory / WEIGHTS_FILE)
        meta = {
            "class": type(self).__name__,
            "group_map": self.group_map,
            "gradient_steps": self.gradient_steps,
            "hyperparameters": self.hp,
            "prior": self.prior_settings,
        }
        (directory / META_FILE).write_text(json.dumps(meta, indent=2) + "\n")

    def load(self, directory: Path) -> None:
        """Restore the weights written by :meth:`save` (``torch.load(..., weights_only=True)``).

        Args:
            directory: Folder written by :meth:`save`.

        Raises:
            ValueError: naming the file, if it or its description (``learner.json``) is
                unreadable, or its class, groups, prior, features, tensor names or shapes
                differ from this learner's.
        """
        directory = Path(directory)
        meta_path = directory / META_FILE
        meta = read_meta(meta_path, META)
        saved_class, saved_groups = meta["class"], meta["group_map"]
        saved_prior, saved_features = meta["prior"], meta["hyperparameters"].get("features")
        if saved_groups != self.group_map:
            raise ValueError(
                f"{meta_path}: checkpoint groups {saved_groups} differ from {self.group_map}"
            )
        if saved_class != type(self).__name__:
            raise ValueError(f"{directory} holds a {saved_class}, not a {type(self).__name__}")
        if saved_prior != self.prior_settings:
            raise ValueError(
                f"{meta_path}: trained with prior {saved_prior}, this run's learner has "
                f"{self.prior_settings} (the prior is part of the Q-function)"
            )
        saved_network = meta["hyperparameters"].get("network", "mlp")
        if saved_network != self.hp.get("network", "mlp"):
            raise ValueError(
                f"{meta_path}: trained with network={saved_network}, this run's learner has "
                f"network={self.hp.get('network', 'mlp')} (the networks differ)"
            )
        if saved_features != self.features:
            raise ValueError(
                f"{meta_path}: trained with features={saved_features}, this run's learner has "
                f"features={self.features} (the networks' inputs differ)"
            )
        self.networks.load_state_dict(read_weights(directory / WEIGHTS_FILE, self.networks))

    def checkpoint_state(self, directory: Path) -> dict[str, Any]:
        """Counters; optimizer, target networks and epsilon in ``training.pt``.

        Torch's global generator (exploration, replay sampling) belongs to the runner, which
        seeds it and saves it with the replay buffer.
        """
        extra = {
            "optimizer": self.optimizer.state_dict(),
            "losses": {name: loss.state_dict() for name, loss in self.losses.items()},
            "egreedy": [module.state_dict() for module in self.egreedy],
        }
        write_tensors(extra, Path(directory) / TRAINING_FILE)
        return {
            **super().checkpoint_state(directory),
            "gradient_steps": self.gradient_steps,
            "frames_collected": self.frames_collected,
            "target_updaters": [u.state_dict() for u in self.target_updaters],
        }

    def restore_state(self, state: dict[str, Any], directory: Path) -> None:
        """Restore :meth:`checkpoint_state` (``weights_only`` loading of ``training.pt``)."""
        super().restore_state(state, directory)
        path = Path(directory) / TRAINING_FILE
        losses = {name: loss.state_dict() for name, loss in self.losses.items()}
        egreedy = [module.state_dict() for module in self.egreedy]
        params = [p for group in self.optimizer.param_groups for p in group["params"]]
        # the optimizer's state: Adam's two moments of every weight
        limit = tensor_file_limit(losses, egreedy, params, params)
        extra = read_tensors(path, self.device, limit, f"a {TRAINING_FILE} of this learner")
        if not isinstance(extra, dict) or set(extra) != {"optimizer", "losses", "egreedy"}:
            raise RunDirError(f"{path}: expected the keys egreedy, losses, optimizer")
        if not isinstance(extra["losses"], dict) or set(extra["losses"]) != set(losses):
            raise RunDirError(f"{path}: losses: expected {short_list(losses)}")
        for name, loss in self.losses.items():
            check_state_dict(extra["losses"][name], losses[name], f"{path}: losses.{name}")
            loss.load_state_dict(extra["losses"][name])
        check_optimizer_state(extra["optimizer"], self.optimizer, path)
        self.optimizer.load_state_dict(extra["optimizer"])
        saved_eps = extra["egreedy"]
        if not isinstance(saved_eps, list) or len(saved_eps) != len(self.egreedy):
            raise RunDirError(f"{path}: egreedy: expected {len(self.egreedy)} exploration states")
        for module, saved in zip(self.egreedy, saved_eps, strict=True):
            eps = saved.get("eps") if isinstance(saved, dict) else None
            if not isinstance(eps, torch.Tensor) or eps.numel() != 1 or not 0 <= float(eps) <= 1:
                raise RunDirError(f"{path}: egreedy.eps: must be a number in [0, 1]")
            module.eps.copy_(eps)  # also EGreedyModule's state of older checkpoints
        self.gradient_steps = int(state["gradient_steps"])
        self.frames_collected = int(state["frames_collected"])
        for updater, saved in zip(self.target_updaters, state["target_updaters"], strict=True):
            updater.load_state_dict(saved)


def read_meta(path: Path, schema: dict[str, Any]) -> dict[str, Any]:
    """A neural learner's ``learner.json``, checked against its schema (``run_files``).

    Raises:
        RunDirError: naming the file and the key.
    """
    meta = read_description(path, schema)
    if meta["gradient_steps"] < 0:
        raise RunDirError(f"{path}: gradient_steps: must be >= 0, got {meta['gradient_steps']}")
    return meta


def write_tensors(payload: Any, path: Path) -> None:
    """``torch.save`` through a Python file object, so that a refused write is an ``OSError``.

    Given a path, torch's own writer turns a full disk or a file size limit into a
    ``RuntimeError`` that names neither the fault nor the file; through a file object the
    ``OSError`` is that error's context, which the commands report in one line naming the file
    (``mrta_rl/errors.py``). The bytes written are the same.
    """
    with open(path, "wb") as file:
        torch.save(payload, file)


def read_weights(path: Path, networks: nn.Module) -> dict[str, torch.Tensor]:
    """``weights.pt`` of a learner's networks, checked against them (:func:`check_state_dict`).

    Raises:
        RunDirError: naming the file, if it is not a regular file, too big for these networks,
            not a weights file, or its tensors are not the networks' (names, shapes, dtypes,
            finite values).
    """
    expected = networks.state_dict()
    device = next(iter(expected.values())).device if expected else torch.device("cpu")
    state = read_tensors(
        path, device, tensor_file_limit(expected), "a weights file written by this package"
    )
    check_state_dict(state, expected, path)
    return state


def check_state_dict(
    state: Any,
    expected: dict[str, torch.Tensor],
    path: Path | str,
    error: type[UserError] = RunDirError,
) -> None:
    """Saved tensors against the learner's own: names, shapes, dtypes and finite values.

    Args:
        state: The loaded state dict.
        expected: The learner's own (``state_dict()``).
        path: The file (and key), or what made the tensors, for messages.
        error: The error to raise.

    Raises:
        RunDirError: (or ``error``) naming the file and the first mismatch.
    """
    if not isinstance(state, dict) or set(state) != set(expected):
        names = short_list(sorted(state)) if isinstance(state, dict) else type(state).__name__
        raise error(
            f"{path}: holds tensors {names}, this run's learner has {short_list(sorted(expected))} "
            "(saved for another system, partition or learner?)"
        )
    for name, want in expected.items():
        got = state[name]
        if not isinstance(got, torch.Tensor) or got.shape != want.shape or got.dtype != want.dtype:
            shape = tuple(got.shape) if isinstance(got, torch.Tensor) else type(got).__name__
            raise error(
                f"{path}: tensor {name} is {shape}, expected {tuple(want.shape)} {want.dtype}"
            )
        if got.is_floating_point() and not torch.isfinite(got).all():
            raise error(f"{path}: tensor {name} holds NaN or infinite values")


def check_finite_weights(state: dict[str, torch.Tensor], source: str) -> None:
    """Refuse to keep weights that hold NaN or infinity (before they are saved).

    Raises:
        NonFiniteState: naming the learner, the step and the tensor.
    """
    check_state_dict(state, state, source, NonFiniteState)


def check_loss(value: float, label: str, step: int) -> None:
    """Stop training at a NaN or infinite loss, before the gradient step would use it.

    Raises:
        NonFiniteState: naming the learner and the gradient step.
    """
    if not math.isfinite(value):
        raise NonFiniteState(f"{label}: gradient step {step}: the loss is {value}")


def check_optimizer_state(saved: Any, optimizer: torch.optim.Optimizer, path: Path) -> None:
    """An optimizer's saved state (Adam's) against the optimizer the run built.

    The parameter groups must hold the same parameters and settings (learning rate, betas...);
    each parameter's state tensors are finite and of its shape, its ``step`` and its second
    moments (``*_sq``) >= 0.

    Raises:
        RunDirError: naming the file and the key.
    """
    fresh = optimizer.state_dict()
    where = f"{path}: optimizer"
    if not isinstance(saved, dict) or set(saved) != set(fresh):
        raise RunDirError(f"{where}: expected the keys {short_list(sorted(fresh))}")
    groups = saved["param_groups"]
    if not isinstance(groups, list) or len(groups) != len(fresh["param_groups"]):
        raise RunDirError(f"{where}.param_groups: expected {len(fresh['param_groups'])} groups")
    shapes = {}
    for g, (group, want, live) in enumerate(
        zip(groups, fresh["param_groups"], optimizer.param_groups, strict=True)
    ):
        if not isinstance(group, dict) or group.get("params") != want["params"]:
            raise RunDirError(f"{where}.param_groups[{g}]: not this run's parameters")
        for key, value in want.items():
            if key != "params" and key in group and group[key] != value:
                raise RunDirError(
                    f"{where}.param_groups[{g}].{key}: {str(group[key])[:40]}, the run's is {value}"
                )
        shapes.update(zip(want["params"], (p.shape for p in live["params"]), strict=True))
    state = saved["state"]
    if not isinstance(state, dict) or not set(state) <= set(shapes):
        raise RunDirError(f"{where}.state: not the state of this run's parameters")
    for index, entries in state.items():
        if not isinstance(entries, dict):
            raise RunDirError(f"{where}.state.{index}: must be a mapping of tensors")
        for key, value in entries.items():
            name = f"{where}.state.{index}.{key}"
            if not isinstance(value, torch.Tensor) or not value.is_floating_point():
                raise RunDirError(f"{name}: must be a float tensor")
            if value.numel() != 1 and value.shape != shapes[index]:
                raise RunDirError(
                    f"{name}: shape {tuple(value.shape)}, the parameter's is {tuple(shapes[index])}"
                )
            if not torch.isfinite(value).all():
                raise RunDirError(f"{name}: holds NaN or infinite values")
            if (key == "step" or key.endswith("_sq")) and bool((value < 0).any()):
                raise RunDirError(f"{name}: holds {float(value.min())}, must be >= 0")


NETWORKS = ("mlp", "set")  # the per-robot Q-network: local-feature MLP or the robot-set network


class PerRobotQLearner(NeuralLearner, abstract=True):
    """One Q-value per robot and action (VDN, QMIX, IQL); ``network`` chooses the network.

    ``network=mlp`` is :class:`~mrta_rl.learners.neural.networks.PerRobotQ` over the local
    features; ``network=set`` is the shared robot-set network
    (:class:`~mrta_rl.learners.neural.set_network.SetWithPrior`, one set of weights for every
    robot and any team, no robot id) with the same prior bonus. The ``embed_dim``, ``heads``,
    ``layers``, ``max_task_types`` and ``robot_attention`` settings are the set network's
    (``mlp`` ignores them; ``hidden`` and ``depth`` are the MLP's).
    """

    @classmethod
    def set_settings(cls, settings: dict[str, Any]) -> dict[str, Any]:
        """The :class:`SetNetwork` keywords among a learner's settings."""
        keys = ("embed_dim", "heads", "layers", "max_task_types", "robot_attention")
        return {key: settings[key] for key in keys}

    @classmethod
    def check_set_network(cls, env: AuctionEnv, settings: dict[str, Any]) -> int:
        """Check the set network's settings against the team; its trainable weights.

        Raises:
            ConfigError: naming the key: ``learner.max_task_types`` below the team's task
                types, ``learner.embed_dim`` not a multiple of ``learner.heads``, or
                ``learner.prior_in_state`` (the set network has no such input).
        """
        check_fits(env.n_task_types, env.system.name, settings)
        if settings.get("prior_in_state"):
            raise ConfigError("learner.prior_in_state: needs network=mlp (no such set input)")
        net = SetNetwork(**cls.set_settings(settings), device="meta")
        return sum(p.numel() for p in net.parameters())

    def __init__(
        self,
        *,
        network: Annotated[str, Choices(*NETWORKS)] = "mlp",
        embed_dim: Annotated[int, Range(1)] = 32,
        heads: Annotated[int, Range(1)] = 4,
        layers: Annotated[int, Range(1)] = 1,
        max_task_types: Annotated[int, Range(1)] = 32,
        robot_attention: Annotated[str, Choices(*ROBOT_ATTENTION)] = "full",
        **hyperparameters: Any,
    ) -> None:
        """Keep the network's settings, then build as every neural learner.

        Args:
            network: ``mlp`` (local features, robot-id one-hot) or ``set`` (module docstring).
            embed_dim: ``network=set``: token width (a multiple of ``heads``).
            heads: ``network=set``: attention heads.
            layers: ``network=set``: attention blocks.
            max_task_types: ``network=set``: rows of the task-type embedding, the most task
                types a team may have.
            robot_attention: ``network=set``: ``full`` (robots attend to each other) or
                ``pooled`` (to the mean robot token: memory linear in the robots).
            **hyperparameters: Those of :class:`NeuralLearner`.

        Raises:
            ConfigError: on set settings that cannot fit the team (:meth:`check_set_network`).
        """
        settings = {
            "network": network,
            "embed_dim": embed_dim,
            "heads": heads,
            "layers": layers,
            "max_task_types": max_task_types,
            "robot_attention": robot_attention,
        }
        if network == "set":
            env = hyperparameters["env"]
            prior_in_state = hyperparameters.get("prior_in_state", False)
            self.check_set_network(env, {**settings, "prior_in_state": prior_in_state})
        self._network_settings = settings  # _build reads them, before NeuralLearner sets hp
        super().__init__(**hyperparameters)
        self.hp |= settings  # saved with the weights: load() checks the network

    @classmethod
    def robot_network_weights(cls, env: AuctionEnv, settings: dict[str, Any]) -> int | None:
        """Weights of the shared set network with ``network=set``, else None (the MLP's)."""
        if settings.get("network", "mlp") != "set":
            return None
        return cls.check_set_network(env, settings)

    def _q_network(self, group: str, share_params: bool) -> tuple[nn.Module, list]:
        """With ``network=set``: :class:`SetWithPrior` over the set inputs, mask and prior."""
        settings = self._network_settings
        if settings["network"] != "set":
            return super()._q_network(group, share_params)
        qnet = SetWithPrior(
            auction_prior=self.hp["auction_prior"],
            device=self.device,
            **self.set_settings(settings),
        )
        keys = [(group, key) for key in GROUP_SET_KEYS] + list(ROOT_SET_KEYS)
        return qnet, [*keys, (group, "action_mask"), (group, PRIOR_KEY)]


class MixedQLearner(PerRobotQLearner, abstract=True):
    """Per-robot Q-network (shared parameters) mixed into a team Q (VDN, QMIX).

    One TorchRL group ``"agents"`` holds every robot; their chosen Q-values are mixed by
    :meth:`_mixer` and trained on the team reward (spec step 8) with TorchRL's ``QMixerLoss``.
    Subclasses differ only in the mixer (``vdn.py``: ``VDNMixer``, ``qmix.py``: ``QMixer``).
    """

    replay_loss_keys_only: ClassVar[bool] = True  # transitions() keeps the loss's in_keys

    @classmethod
    def network_weights(
        cls, env: AuctionEnv, partition: Partition | None, settings: dict[str, Any]
    ) -> int:
        """One network shared by the robots (a mixer with weights adds its own)."""
        shared = cls.robot_network_weights(env, settings)
        if shared is not None:
            return shared
        n_in, _ = feature_sizes(env, settings)
        return mlp_weights(n_in, env.n_actions, int(settings["depth"]), int(settings["hidden"]))

    def _mixer(self) -> TensorDictModule:
        """The mixer module.

        Returns:
            A module reading ``("agents", "chosen_action_value")`` (and ``"state"``) and writing
            the root ``"chosen_action_value"`` ``[*, 1]``.
        """
        raise NotImplementedError

    def _build(self) -> None:
        from torchrl.objectives.multiagent import QMixerLoss

        group = "agents"
        self.policy, self.explore_policy = self._per_robot_policy(group, share_params=True)
        mixer = self._mixer()
        self.networks["mixer"] = mixer.module
        loss = QMixerLoss(
            self.policy,
            mixer,
            loss_function=self.hp["loss_function"],
            delay_value=True,
            action_space="categorical",
        )
        loss.set_keys(
            action_value=(group, "action_value"),
            local_value=(group, "chosen_action_value"),
            global_value="chosen_action_value",
            action=(group, "action"),
            reward="reward",  # team reward (spec step 8), set at the root by transitions()
            done="done",
            terminated="terminated",
        )
        self.losses[group] = loss

    def transitions(self, data: TensorDictBase) -> TensorDictBase:
        """Scaled team reward, also at the root ``[N, 1]`` where ``QMixerLoss`` reads it.

        As in TorchRL's QMIX example. Only what the loss reads is kept (its ``in_keys``): the
        Q-values are recomputed by the loss, and the per-robot rewards, the root flags of the
        current step and (VDN: its mixer has no state input) the state are read by no one.
        """
        data = super().transitions(data)
        data.set(("next", "reward"), data.get(("next", "agents", "reward"))[:, 0])
        return data.select(*self.losses["agents"].in_keys)
