"""Shared parts of the policy-gradient learners ``mappo`` and ``ippo``: actor, critic, PPO update.

Both learners are TorchRL's multi-agent PPO (Yu et al. 2022, de Witt et al. 2020) on the keys of
:class:`~mrta_rl.envs.torchrl_env.AuctionTorchRLEnv`, with one group ``"agents"`` of all robots
and parameter sharing:

* the actor is a ``ProbabilisticActor`` over a ``MaskedCategorical`` whose mask is the env's
  ``("agents", "action_mask")``: the logits ``[*, m, K + 1]`` come from one network shared by
  the robots, ``network=set`` the shared robot-set network
  (:class:`~mrta_rl.learners.neural.set_network.SetNetwork` on the set inputs: robots attend to
  the slots and to each other, no robot id) or ``network=mlp`` the per-robot MLP
  (:class:`~mrta_rl.learners.neural.networks.PerRobotQ` on ``("agents", "observation")``);
  invalid actions get probability zero, so none is ever sampled, and evaluation
  (``ExplorationType.DETERMINISTIC``) plays the masked mode;
* the critic gives a value per robot ``("agents", "state_value")`` ``[*, m, 1]``, an MLP shared
  by the robots. MAPPO's is centralised: it reads the robot's inputs (its set-token features,
  or its local features with ``mlp``) and the global ``state``. IPPO's reads only the robot's
  own inputs: no state, no attention, no pooling;
* the advantages and value targets are TorchRL's ``MultiAgentGAE`` on the team reward
  ``("agents", "reward")`` (spec step 8, the same for every robot) with the root ``done`` and
  ``terminated`` flags broadcast over the robots; the horizon is a truncation (``terminated`` is
  always False), so the last tick of an episode bootstraps from the value of its final state;
* the update is ``MAPPOLoss`` / ``IPPOLoss`` (clipped ratio, entropy bonus, critic loss; the
  advantages normalised, and with ``value_norm`` the critic loss on value targets scaled by
  their running statistics, ``PopArtValueNorm``), several
  epochs of minibatches per collected batch, sampled without replacement by the torch loop
  (``mrta_rl/runners/torch_loop.py``); on-policy, each batch is consumed, then dropped. IPPO
  with ``network=set`` holds nothing of one team (no state, no robot id) and trains on a family
  of teams; MAPPO's critic reads the team-sized state.

Auction prior (``auction_prior``, as for the Q-learners in ``q_learning.py``): the logit of the
plain auction's action (the lowest-numbered valid bid, the env's ``("agents", "prior_action")``)
gets a fixed bonus and the network's last layer starts at zero, so the untrained policy's mode is
the greedy auction and its samples mostly follow it. ``auction_prior: 0`` starts from the uniform
valid policy.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Annotated, Any, ClassVar

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from torch import nn
from torchrl.modules import MLP, MaskedCategorical, PopArtValueNorm, ProbabilisticActor
from torchrl.objectives import ValueEstimators
from torchrl.objectives.multiagent import MAPPOLoss

from mrta_rl.config import ConfigError, Range
from mrta_rl.envs import AuctionEnv, encodings
from mrta_rl.envs.torchrl_env import GROUP_SET_KEYS, PRIOR_KEY, ROOT_SET_KEYS
from mrta_rl.learners.base import MemoryQuery, TrainingTeam
from mrta_rl.learners.memory import BYTES_PER_WEIGHT, ResourceEstimate, feature_sizes, mlp_weights
from mrta_rl.learners.neural.networks import PerRobotQ
from mrta_rl.learners.neural.set_network import SetNetworkOption
from mrta_rl.learners.neural.tensor_files import check_state_dict
from mrta_rl.learners.neural.torch_learner import LoopSettings, TorchLearner
from mrta_rl.partition import Partition
from mrta_rl.priors import GreedyPrior

GROUP = "agents"  # the one TorchRL group of all robots
ACTION = (GROUP, "action")
LOG_PROB = (GROUP, "action_log_prob")
VALUE = (GROUP, "state_value")
SET_KEYS = [*((GROUP, key) for key in GROUP_SET_KEYS), *ROOT_SET_KEYS]  # SetNetwork's order
PPO_ADVICE = "lower learner.frames_per_batch or learner.hidden, or use a smaller system"
# the diagnostics of a PPO loss, logged as train/<key>
LOSS_TERMS = ("loss_objective", "loss_critic", "loss_entropy", "entropy")


class RobotValue(nn.Module):
    """Value per robot ``[*, m, 1]``: one MLP shared by the robots, on its inputs [and the state].

    The robot's inputs are its local features (``network=mlp``) or its set-token features
    (``network=set``: the critic reads the robot's own token, without attention or pooling; a
    critic with its own set network would double the cost of a PPO update, for a value that is
    only read in training). ``centralized=True`` (MAPPO) concatenates the global ``state`` to
    every robot's inputs, so the value sees the whole team; ``False`` (IPPO) reads the robot's
    own inputs only.
    """

    def __init__(
        self,
        n_features: int,
        state_size: int,
        *,
        centralized: bool,
        hidden: int,
        depth: int,
        device: Any = None,
    ) -> None:
        """Build the MLP.

        Args:
            n_features: ``F`` per robot.
            state_size: ``G``, the global state's size (read when centralised).
            centralized: Whether the global state is an input.
            hidden: Units per hidden layer.
            depth: Hidden layers.
            device: Parameter device.
        """
        super().__init__()
        self.centralized = centralized
        n_in = n_features + (state_size if centralized else 0)
        self.mlp = MLP(
            in_features=n_in,
            out_features=1,
            depth=depth,
            num_cells=hidden,
            activation_class=nn.Tanh,
            device=device,
        )

    def forward(self, inputs: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        """Values ``[*, m, 1]`` of the robots' ``inputs`` ``[*, m, F]`` (and ``state``)."""
        if self.centralized:
            team = state.unsqueeze(-2).expand(*inputs.shape[:-1], state.shape[-1])
            inputs = torch.cat([inputs, team], -1)
        return self.mlp(inputs)


class PPOLearner(SetNetworkOption, TorchLearner, abstract=True):
    """Base of ``mappo`` and ``ippo`` (module docstring); subclasses set :attr:`centralized_critic`.

    On-policy: each collected batch is consumed by ``epochs`` passes of minibatches (sampled
    without replacement) and then dropped.

    Attributes:
        actor: The ``ProbabilisticActor`` (masked categorical), writing ``("agents", "action")``
            and its log-probability; samples under ``ExplorationType.RANDOM``, plays the masked
            mode otherwise.
        critic: The value module, writing ``("agents", "state_value")``.
        losses: ``{"agents": MAPPOLoss or IPPOLoss}`` with its ``MultiAgentGAE``.
        networks: Everything that is saved (``actor``, ``critic``).
    """

    on_policy: ClassVar[bool] = True
    fused_optimizer: ClassVar[bool] = False
    centralized_critic: ClassVar[bool]
    loss_class: ClassVar[type[MAPPOLoss]]

    @classmethod
    def network_weights(
        cls, env: AuctionEnv, partition: Partition | None, settings: dict[str, Any]
    ) -> int:
        """Actor (-> K + 1 logits per robot) and critic (-> 1 value per robot)."""
        F, S = feature_sizes(env, settings)
        depth, hidden = int(settings["depth"]), int(settings["hidden"])
        if settings["network"] == "set":
            actor = cls.check_set_network(env.n_task_types, env.system.name, settings)
            critic_in = encodings.ROBOT_TOKEN_SIZE + (S if cls.centralized_critic else 0)
            return actor + mlp_weights(critic_in, 1, depth, hidden)
        critic_in = F + (S if cls.centralized_critic else 0)
        actor = mlp_weights(F, env.n_actions, depth, hidden)
        return actor + mlp_weights(critic_in, 1, depth, hidden)

    @classmethod
    def estimate_memory(cls, query: MemoryQuery) -> ResourceEstimate:
        """Networks (gradients and Adam moments) and one collected batch with its GAE outputs."""
        env, partition, settings = query.env, query.partition, query.settings
        m, A = env.n_robots, env.n_actions
        F, S = feature_sizes(env, settings)
        # one frame (copy-tick): observation, mask, the prior's action index, state (and their
        # next), per robot action, log-probability, value, advantage, target, reward; flags
        prior = encodings.prior_dtype(A).itemsize
        frame = 2 * (m * F * 4 + S * 4 + m * (A + prior)) + m * (8 + 5 * 4) + 32
        if settings["network"] == "set":  # the set inputs too: robot, slot and type tokens
            n, K = env.n_task_types, A - 1
            robots = m * (encodings.ROBOT_TOKEN_SIZE * 4 + n)  # float32 features, bool types
            slots = K * (encodings.SLOT_TOKEN_SIZE * 4 + 8)  # float32 features, int64 type
            frame += 2 * (robots + slots + n * encodings.TYPE_TOKEN_SIZE * 4)
        parts = {
            "networks": cls.network_weights(env, partition, settings) * BYTES_PER_WEIGHT,
            # the collected batch and its copy in the buffer
            "collector batch": 2 * int(settings["frames_per_batch"]) * frame,
        }
        total = sum(parts.values())
        return ResourceEstimate(cls.__name__, total, total, parts, advice=PPO_ADVICE)

    @classmethod
    def check_settings(cls, settings: Mapping[str, Any], team: TrainingTeam) -> None:
        """Refuse a batch that is not whole ticks of every copy, or a minibatch past it.

        Raises:
            ConfigError: naming ``learner.frames_per_batch`` or ``learner.minibatch_size``.
        """
        super().check_settings(settings, team)
        frames, minibatch, copies = (
            settings["frames_per_batch"],
            settings["minibatch_size"],
            team.copies,
        )
        if frames % copies:
            raise ConfigError(
                f"learner.frames_per_batch={frames} is not a multiple of the {copies} "
                "training copies (train.batch_size): a batch is whole ticks of every copy"
            )
        if minibatch > frames:
            raise ConfigError(
                f"learner.minibatch_size={minibatch} is larger than learner.frames_per_batch="
                f"{frames} (a minibatch is drawn from one collected batch)"
            )

    def __init__(
        self,
        *,
        lmbda: Annotated[float, Range(0, 1)],
        clip_epsilon: Annotated[float, Range(0, 1, low_open=True)],
        entropy_coeff: Annotated[float, Range(0)],
        critic_coeff: Annotated[float, Range(0, low_open=True)],
        frames_per_batch: Annotated[int, Range(1)],
        epochs: Annotated[int, Range(1)],
        minibatch_size: Annotated[int, Range(1)],
        value_norm: bool,
        **settings: Any,
    ) -> None:
        """Build actor, critic, loss (with ``MultiAgentGAE``) and optimiser.

        Args:
            lmbda: GAE's lambda.
            clip_epsilon: PPO's ratio clip.
            entropy_coeff: Weight of the entropy bonus.
            critic_coeff: Weight of the critic loss.
            frames_per_batch: Frames (copy-ticks) collected per PPO update; a multiple of the
                training copies (``train.batch_size``).
            epochs: Passes over each collected batch.
            minibatch_size: Frames per gradient step; at most ``frames_per_batch``.
            value_norm: Scale the critic's loss by running statistics of the value targets
                (``PopArtValueNorm``, MAPPO's value normalisation); its statistics are part of
                the training state, so a resumed run continues them.
            **settings: Env, generator, partition, the set network's and
                :class:`~mrta_rl.learners.neural.torch_learner.TorchLearner`'s settings
                (``hidden`` and ``depth`` are the MLPs': the ``mlp`` actor, the critic heads;
                ``auction_prior`` is the logit bonus of the plain auction's bid).

        Raises:
            ValueError: naming the setting, if the batch does not fit the copies or the
                minibatch, the set network does not fit the team, or the device is unavailable.
        """
        self.rule = GreedyPrior()  # the view writes its action as ("agents", "prior_action")
        self.value_norm: PopArtValueNorm | None = None
        super().__init__(**settings)

    def _build(self) -> None:
        hp = self.hp
        state_size = self.state_size
        if hp["network"] == "set":
            logits: nn.Module = self._set_network()
            value = RobotValue(
                encodings.ROBOT_TOKEN_SIZE,
                state_size,
                centralized=self.centralized_critic,
                hidden=hp["hidden"],
                depth=hp["depth"],
                device=self.device,
            )
            actor_keys = [*SET_KEYS, (GROUP, "action_mask"), (GROUP, PRIOR_KEY)]
            critic_keys = [(GROUP, "robots"), "state"]
        else:
            n_features = self.n_features
            logits = PerRobotQ(
                n_features,
                self.n_robots,
                self.n_actions,
                share_params=True,
                hidden=hp["hidden"],
                depth=hp["depth"],
                auction_prior=hp["auction_prior"],
                device=self.device,
            )
            value = RobotValue(
                n_features,
                state_size,
                centralized=self.centralized_critic,
                hidden=hp["hidden"],
                depth=hp["depth"],
                device=self.device,
            )
            actor_keys = [(GROUP, "observation"), (GROUP, PRIOR_KEY)]
            critic_keys = [(GROUP, "observation"), "state"]
        self.networks["actor"], self.networks["critic"] = logits, value
        self.actor = ProbabilisticActor(
            TensorDictModule(logits, in_keys=actor_keys, out_keys=[(GROUP, "logits")]),
            in_keys={"logits": (GROUP, "logits"), "mask": (GROUP, "action_mask")},
            out_keys=[ACTION],
            distribution_class=MaskedCategorical,
            return_log_prob=True,
            log_prob_key=LOG_PROB,
        )
        self.critic = TensorDictModule(value, in_keys=critic_keys, out_keys=[VALUE])
        if hp["value_norm"]:
            self.value_norm = PopArtValueNorm(shape=1, device=self.device)
        loss = self.loss_class(
            self.actor,
            self.critic,
            clip_epsilon=hp["clip_epsilon"],
            entropy_coeff=hp["entropy_coeff"],
            critic_coeff=hp["critic_coeff"],
            loss_critic_type="smooth_l1",
            value_norm=self.value_norm,
        )
        loss.set_keys(
            action=ACTION,
            sample_log_prob=LOG_PROB,
            value=VALUE,
            advantage=(GROUP, "advantage"),
            value_target=(GROUP, "value_target"),
            reward=(GROUP, "reward"),  # the team reward, repeated per robot (spec step 8)
            done="done",  # root [*, 1]: MultiAgentGAE broadcasts it over the robots
            terminated="terminated",
        )
        # the values of the states and of their next states in two plain calls: vmap over the
        # two has no batching rule for the set network's attention (a slow per-item fallback)
        loss.make_value_estimator(
            ValueEstimators.MAGAE, gamma=hp["gamma"], lmbda=hp["lmbda"], deactivate_vmap=True
        )
        self.losses[GROUP] = loss

    def training_state(self) -> dict[str, Any]:
        """The optimiser's state and, with ``value_norm``, the value targets' statistics."""
        state = super().training_state()
        if self.value_norm is not None:
            state["value_norm"] = self.value_norm.state_dict()
        return state

    def restore_training_state(self, saved: dict[str, Any], path) -> None:
        """Check and restore :meth:`training_state`.

        Raises:
            RunDirError: naming the file and the key.
        """
        if self.value_norm is not None:
            check_state_dict(
                saved["value_norm"], self.value_norm.state_dict(), f"{path}: value_norm"
            )
        super().restore_training_state(saved, path)
        if self.value_norm is not None:
            self.value_norm.load_state_dict(saved["value_norm"])

    # -------------------------------------------------------------- the loop's protocol
    @property
    def prior(self) -> GreedyPrior:
        """The plain auction, whose bid gets the logit bonus (module docstring)."""
        return self.rule

    @property
    def policy(self) -> TensorDictModuleBase:
        """The actor (its masked mode under deterministic exploration)."""
        return self.actor

    @property
    def collection_policy(self) -> TensorDictModuleBase:
        """The actor (it samples under the collector's random exploration)."""
        return self.actor

    @classmethod
    def batch_frames(cls, settings: Mapping[str, Any], copies: int, horizon: int) -> int:
        """``frames_per_batch`` (a multiple of the copies)."""
        return int(settings["frames_per_batch"])

    def loop_settings(self, copies: int, total_frames: int) -> LoopSettings:
        """One batch of ``frames_per_batch`` frames, ``epochs`` passes of whole minibatches.

        A run shorter than one batch (a benchmark's warm-up) trains once, on all of it.
        """
        frames = min(int(self.hp["frames_per_batch"]), total_frames)
        size = min(int(self.hp["minibatch_size"]), frames)
        return LoopSettings(
            frames_per_batch=frames,
            buffer_size=frames,
            minibatch_size=size,
            updates_per_batch=int(self.hp["epochs"]) * (frames // size),
            warmup_frames=0,
        )

    def process_batch(self, data: TensorDictBase) -> TensorDictBase:
        """Scale the team reward, write ``MultiAgentGAE``'s advantages and value targets, flatten.

        Args:
            data: ``[B, T]`` collected ticks (time last).

        Returns:
            ``[B * T]`` frames with ``("agents", "advantage")`` and ``("agents",
            "value_target")`` ``[*, m, 1]`` (and the critic's values).
        """
        loss = self.losses[GROUP]
        data = data.exclude("collector").to(self.device)
        key = ("next", *loss.tensor_keys.reward)
        data.set(key, data.get(key) * self.hp["reward_scale"])
        with torch.no_grad():
            loss.value_estimator(
                data,
                params=loss.critic_network_params,
                target_params=loss.target_critic_network_params,
            )
        return data.reshape(-1)

    def loss(self, batch: TensorDictBase) -> tuple[torch.Tensor, dict[str, float]]:
        """PPO's clipped objective, critic and entropy terms of a minibatch."""
        out = self.losses[GROUP](batch)
        total = out["loss_objective"] + out["loss_critic"] + out["loss_entropy"]
        return total, {f"train/{key}": float(out[key].detach()) for key in LOSS_TERMS}
