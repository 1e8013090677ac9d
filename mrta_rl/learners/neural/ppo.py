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
* the update is ``MAPPOLoss`` / ``IPPOLoss`` (clipped ratio, entropy bonus, critic loss), several
  epochs of minibatches per collected batch (:meth:`PPOLearner.train_batch`), driven by the
  on-policy loop ``mrta_rl.runners.ppo``.

Auction prior (``auction_prior``, as for the Q-learners in ``common.py``): the logit of the plain
auction's action (the lowest-numbered valid bid, the env's ``("agents", "prior_action")``) gets
a fixed bonus and the network's last layer starts at zero, so the untrained policy's mode is the
greedy auction and its samples mostly follow it. ``auction_prior: 0`` starts from the uniform
valid policy.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any, ClassVar

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import MLP, MaskedCategorical, ProbabilisticActor
from torchrl.objectives import ValueEstimators
from torchrl.objectives.multiagent import MAPPOLoss

from mrta_rl.checked_files import read_tensors, tensor_file_limit
from mrta_rl.config import Choices, Range
from mrta_rl.envs import AuctionEnv, encodings
from mrta_rl.envs.torchrl_env import GROUP_SET_KEYS, PRIOR_KEY, ROOT_SET_KEYS, set_inputs_td
from mrta_rl.learners.base import PPO_LOOP, Learner, LearnerKind, MemoryQuery
from mrta_rl.learners.memory import BYTES_PER_WEIGHT, ResourceEstimate, feature_sizes, mlp_weights
from mrta_rl.learners.neural.common import (
    META_FILE,
    WEIGHTS_FILE,
    check_finite_weights,
    check_loss,
    check_optimizer_state,
    observation_td,
    read_meta,
    read_weights,
    require_torchrl,
    write_tensors,
)
from mrta_rl.learners.neural.networks import PerRobotQ
from mrta_rl.learners.neural.set_network import ROBOT_ATTENTION, SetWithPrior, check_fits
from mrta_rl.partition import Partition
from mrta_rl.priors import GreedyPrior
from mrta_rl.run_layout import ANY, INT, STR, RunDirError
from mrta_rl.types import GroupMap

TRAINING_FILE = "training.pt"  # optimizer state (training checkpoints)
LOSS_KEYS = ("loss_objective", "loss_critic", "loss_entropy", "entropy")  # train_batch's means
# learner.json as PPOLearner.save writes it (run_files.check_schema)
META = {
    "class": STR,
    "group_map": {"*": [STR]},
    "gradient_steps": INT,
    "hyperparameters": {"*": ANY},
}
GROUP = "agents"  # the one TorchRL group of all robots
ACTION = (GROUP, "action")
LOG_PROB = (GROUP, "action_log_prob")
VALUE = (GROUP, "state_value")
NETWORKS = ("set", "mlp")  # the actor's and critic's body: robot-set network or per-robot MLP
SET_KEYS = [*((GROUP, key) for key in GROUP_SET_KEYS), *ROOT_SET_KEYS]  # SetNetwork's order
SET_SETTINGS = ("embed_dim", "heads", "layers", "max_task_types", "robot_attention")
PPO_ADVICE = "lower learner.frames_per_batch or learner.hidden, or use a smaller system"


class PerRobotValue(nn.Module):
    """Value per robot ``[*, m, 1]``: one MLP shared by the robots, on its inputs [and the state].

    ``centralized=True`` (MAPPO) concatenates the global state to every robot's features, so the
    value sees the whole team; ``False`` (IPPO) reads the robot's own features only.
    """

    def __init__(
        self, n_features: int, state_size: int, *, centralized: bool, hidden: int, depth: int
    ) -> None:
        """Build the MLP.

        Args:
            n_features: ``F`` per robot.
            state_size: ``G``, the global state's size (read when centralised).
            centralized: Whether the global state is an input.
            hidden: Units per hidden layer.
            depth: Hidden layers.
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
        )

    def forward(self, observation: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        """Values ``[*, m, 1]`` of ``observation`` ``[*, m, F]`` (and ``state`` ``[*, G]``)."""
        if self.centralized:
            team = state.unsqueeze(-2).expand(*observation.shape[:-1], state.shape[-1])
            observation = torch.cat([observation, team], -1)
        return self.mlp(observation)


class SetValue(nn.Module):
    """Value per robot ``[*, m, 1]``: an MLP on the robot's own token features [and the state].

    ``centralized=True`` (MAPPO) concatenates the global ``state`` to the robot's token features
    (``SET_KEYS``' robots), so the value sees the whole team; ``False`` (IPPO) reads the robot's
    own token features only, without attention or pooling. A critic with its own set network
    (the pooled team embedding) doubles the cost of a PPO update, for a value that is only read
    in training.
    """

    def __init__(
        self, state_size: int, *, centralized: bool, hidden: int, depth: int, device: Any = None
    ) -> None:
        """Build the MLP (``state_size``: ``G``, read when centralised)."""
        super().__init__()
        self.centralized = centralized
        n_in = encodings.ROBOT_TOKEN_SIZE + (state_size if centralized else 0)
        self.mlp = MLP(
            in_features=n_in,
            out_features=1,
            depth=depth,
            num_cells=hidden,
            activation_class=nn.Tanh,
            device=device,
        )

    def forward(self, robots: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        """Values of the robots' token features ``[*, m, R]`` (and ``state`` ``[*, G]``)."""
        if self.centralized:
            team = state.unsqueeze(-2).expand(*robots.shape[:-1], state.shape[-1])
            robots = torch.cat([robots, team], -1)
        return self.mlp(robots)


class PPOLearner(Learner, abstract=True):
    """Base of ``mappo`` and ``ippo`` (module docstring); subclasses set :attr:`centralized_critic`.

    Attributes:
        actor: The ``ProbabilisticActor`` (masked categorical), writing ``("agents", "action")``
            and its log-probability; samples under ``ExplorationType.RANDOM``, plays the masked
            mode otherwise.
        critic: The value module, writing ``("agents", "state_value")``.
        loss: The TorchRL loss (``MAPPOLoss`` or ``IPPOLoss``) with its ``MultiAgentGAE``.
        networks: Everything that is saved (``actor``, ``critic``).
    """

    kind: ClassVar[LearnerKind] = "neural"
    training_loop: ClassVar[str] = PPO_LOOP
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
            cls.check_set_network(env, settings)
            learner = {key: settings[key] for key in SET_SETTINGS}
            actor = SetWithPrior(auction_prior=0.0, device="meta", **learner)
            actor_weights = sum(p.numel() for p in actor.parameters())
            critic_in = encodings.ROBOT_TOKEN_SIZE + (S if cls.centralized_critic else 0)
            return actor_weights + mlp_weights(critic_in, 1, depth, hidden)
        critic_in = F + (S if cls.centralized_critic else 0)
        actor = mlp_weights(F, env.n_actions, depth, hidden)
        return actor + mlp_weights(critic_in, 1, depth, hidden)

    @classmethod
    def check_set_network(cls, env: AuctionEnv, settings: dict[str, Any]) -> None:
        """Refuse set-network settings that cannot fit the team (``network=set``).

        Raises:
            ConfigError: naming ``learner.max_task_types`` (below the team's task types) or
                ``learner.embed_dim`` (not a multiple of ``learner.heads``).
        """
        check_fits(env.n_task_types, env.system.name, settings)

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
            "collector batch": int(settings["frames_per_batch"]) * frame,
        }
        total = sum(parts.values())
        return ResourceEstimate(cls.__name__, total, total, parts, advice=PPO_ADVICE)

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
        network: Annotated[str, Choices(*NETWORKS)] = "set",
        embed_dim: Annotated[int, Range(1)] = 32,
        heads: Annotated[int, Range(1)] = 4,
        layers: Annotated[int, Range(1)] = 1,
        max_task_types: Annotated[int, Range(1)] = 32,
        robot_attention: Annotated[str, Choices(*ROBOT_ATTENTION)] = "full",
        hidden: Annotated[int, Range(1)] = 128,
        depth: Annotated[int, Range(1)] = 2,
        features: Annotated[str, Choices(*encodings.FEATURES)] = "time_to_free",
        auction_prior: Annotated[float, Range(0)] = 2.0,
        lr: Annotated[float, Range(0, low_open=True)] = 1e-3,
        gamma: Annotated[float, Range(0, 1, low_open=True, high_open=True)] = 0.95,
        lmbda: Annotated[float, Range(0, 1)] = 0.95,
        clip_epsilon: Annotated[float, Range(0, 1, low_open=True)] = 0.2,
        entropy_coeff: Annotated[float, Range(0)] = 0.01,
        critic_coeff: Annotated[float, Range(0, low_open=True)] = 1.0,
        reward_scale: Annotated[float, Range(0, low_open=True)] = 0.1,
        frames_per_batch: Annotated[int, Range(1)] = 2_400,
        epochs: Annotated[int, Range(1)] = 4,
        minibatch_size: Annotated[int, Range(1)] = 1_200,
        max_grad_norm: Annotated[float, Range(0, low_open=True)] = 1.0,
        device: Annotated[str, Choices("cpu", "cuda")] = "cpu",
    ) -> None:
        """Build actor, critic, loss (with ``MultiAgentGAE``) and optimiser.

        Args:
            env: The training env (its copies set the collector's batch).
            rng: Generator; seeds the network initialisation.
            partition: Unused (one group of all robots).
            network: The actor's and critic's body: ``set`` (the robot-set network) or ``mlp``
                (per-robot MLP on the local features, with their robot-id one-hot).
            embed_dim: ``network=set``: token width (a multiple of ``heads``).
            heads: ``network=set``: attention heads.
            layers: ``network=set``: attention blocks.
            max_task_types: ``network=set``: rows of the type embedding (at least the team's
                task types).
            robot_attention: ``network=set``: ``full`` (robots attend to each other) or
                ``pooled`` (to the mean robot token: memory linear in the robots).
            hidden: Units per hidden layer of the MLPs (``mlp`` actor, critic heads).
            depth: Hidden layers of the MLPs.
            features: The inputs' encoding (``encodings.FEATURES``).
            auction_prior: Logit bonus of the plain auction's action (module docstring).
            lr: Adam learning rate (actor and critic).
            gamma: Discount per tick.
            lmbda: GAE's lambda.
            clip_epsilon: PPO's ratio clip.
            entropy_coeff: Weight of the entropy bonus.
            critic_coeff: Weight of the critic loss.
            reward_scale: Team reward x this before GAE (keeps values O(10)).
            frames_per_batch: Frames (copy-ticks) collected per PPO update; a multiple of the
                training copies (``train.batch_size``).
            epochs: Passes over each collected batch.
            minibatch_size: Frames per gradient step; at most ``frames_per_batch``.
            max_grad_norm: Gradient clipping norm.
            device: ``"cpu"`` or ``"cuda"``; networks and updates live there, the env on cpu.

        Raises:
            ValueError: naming the setting, if the batch does not fit the copies or the
                minibatch, the set network does not fit the team, or the device is unavailable.
        """
        require_torchrl()
        super().__init__(env=env, rng=rng, partition=partition)
        copies = env.batch_size
        if frames_per_batch % copies:
            raise ValueError(
                f"learner.frames_per_batch={frames_per_batch} is not a multiple of the {copies} "
                "training copies (train.batch_size): a batch is whole ticks of every copy"
            )
        if minibatch_size > frames_per_batch:
            raise ValueError(
                f"learner.minibatch_size={minibatch_size} is larger than learner.frames_per_batch="
                f"{frames_per_batch} (a minibatch is drawn from one collected batch)"
            )
        if network == "set":
            settings = {"max_task_types": max_task_types, "embed_dim": embed_dim, "heads": heads}
            self.check_set_network(env, settings)
        if torch.device(device).type == "cuda" and not torch.cuda.is_available():
            raise ValueError("device=cuda but CUDA is not available")
        self.device = torch.device(device)
        self.hp = {
            "network": network,
            "embed_dim": embed_dim,
            "heads": heads,
            "layers": layers,
            "max_task_types": max_task_types,
            "robot_attention": robot_attention,
            "hidden": hidden,
            "depth": depth,
            "features": features,  # saved with the weights: load() checks it
            "auction_prior": auction_prior,
            "lr": lr,
            "gamma": gamma,
            "lmbda": lmbda,
            "clip_epsilon": clip_epsilon,
            "entropy_coeff": entropy_coeff,
            "critic_coeff": critic_coeff,
            "reward_scale": reward_scale,
            "frames_per_batch": frames_per_batch,
            "epochs": epochs,
            "minibatch_size": minibatch_size,
            "max_grad_norm": max_grad_norm,
        }
        self.rule = GreedyPrior()  # the env view writes its action as ("agents", "prior_action")
        self.group_map: GroupMap = {GROUP: list(env.system.robots)}
        self.n_features = encodings.local_feature_size(env, features)
        self.state_size = encodings.global_feature_size(env, features)
        # network initialisation draws from torch's generator: seeded from the learner's own, in
        # a forked state, so runs are reproducible and torch's global state is the runner's
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(int(rng.integers(2**31)))
            self._build()
        self.optimizer = torch.optim.Adam(self.loss.parameters(), lr=lr)
        self.gradient_steps = 0

    def _build(self) -> None:
        hp = self.hp
        if hp["network"] == "set":
            settings: dict[str, Any] = {key: hp[key] for key in SET_SETTINGS}
            logits: nn.Module = SetWithPrior(
                auction_prior=hp["auction_prior"], device=self.device, **settings
            )
            value: nn.Module = SetValue(
                self.state_size,
                centralized=self.centralized_critic,
                hidden=hp["hidden"],
                depth=hp["depth"],
                device=self.device,
            )
            actor_keys = [*SET_KEYS, (GROUP, "action_mask"), (GROUP, PRIOR_KEY)]
            critic_keys = [(GROUP, "robots"), "state"]
        else:
            logits = PerRobotQ(
                self.n_features,
                self.n_robots,
                self.n_actions,
                share_params=True,
                hidden=hp["hidden"],
                depth=hp["depth"],
                auction_prior=hp["auction_prior"],
                device=self.device,
            )
            value = PerRobotValue(
                self.n_features,
                self.state_size,
                centralized=self.centralized_critic,
                hidden=hp["hidden"],
                depth=hp["depth"],
            ).to(self.device)
            actor_keys = [(GROUP, "observation"), (GROUP, PRIOR_KEY)]
            critic_keys = [(GROUP, "observation"), "state"]
        self.networks = nn.ModuleDict({"actor": logits, "critic": value})
        self.actor = ProbabilisticActor(
            TensorDictModule(logits, in_keys=actor_keys, out_keys=[(GROUP, "logits")]),
            in_keys={"logits": (GROUP, "logits"), "mask": (GROUP, "action_mask")},
            out_keys=[ACTION],
            distribution_class=MaskedCategorical,
            return_log_prob=True,
            log_prob_key=LOG_PROB,
        )
        self.critic = TensorDictModule(value, in_keys=critic_keys, out_keys=[VALUE])
        self.loss = self.loss_class(
            self.actor,
            self.critic,
            clip_epsilon=hp["clip_epsilon"],
            entropy_coeff=hp["entropy_coeff"],
            critic_coeff=hp["critic_coeff"],
            loss_critic_type="smooth_l1",
        )
        self.loss.set_keys(
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
        self.loss.make_value_estimator(
            ValueEstimators.MAGAE, gamma=hp["gamma"], lmbda=hp["lmbda"], deactivate_vmap=True
        )

    # -------------------------------------------------------------- training
    @property
    def features(self) -> str:
        """The inputs' encoding (``hp``): the env view builds the observations with it."""
        return self.hp["features"]

    @property
    def set_inputs(self) -> bool:
        """Whether the networks read the set inputs (``network=set``): the env view writes them."""
        return self.hp["network"] == "set"

    def advantages(self, data: TensorDictBase) -> TensorDictBase:
        """Scale the team reward, then write ``MultiAgentGAE``'s advantages and value targets.

        Args:
            data: ``[B, T]`` collected ticks (time last), on :attr:`device`.

        Returns:
            The same TensorDict with ``("agents", "advantage")`` and ``("agents",
            "value_target")`` ``[B, T, m, 1]`` (and the critic's values).
        """
        key = ("next", *self.loss.tensor_keys.reward)
        data.set(key, data.get(key) * self.hp["reward_scale"])
        with torch.no_grad():
            self.loss.value_estimator(
                data,
                params=self.loss.critic_network_params,
                target_params=self.loss.target_critic_network_params,
            )
        return data

    def train_batch(self, data: TensorDictBase) -> dict[str, float]:
        """One PPO update on a collected batch: GAE, then ``epochs`` passes of minibatches.

        Each epoch shuffles the batch's frames (torch's generator, which the runner seeds) and
        takes a gradient step on every whole minibatch of ``minibatch_size`` frames (the whole
        batch, if it is smaller: a run shorter than ``frames_per_batch``).

        Args:
            data: ``[B, T]`` collector output.

        Returns:
            Means over the gradient steps: ``train/loss_objective``, ``train/loss_critic``,
            ``train/loss_entropy``, ``train/entropy``.
        """
        data = self.advantages(data.exclude("collector").to(self.device)).reshape(-1)
        n = data.shape[0]
        size = min(int(self.hp["minibatch_size"]), n)  # a batch cut short by the run's end
        params = list(self.loss.parameters())
        sums: dict[str, float] = {}
        steps = 0
        for _ in range(int(self.hp["epochs"])):
            order = torch.randperm(n, device=self.device)
            for start in range(0, n - size + 1, size):
                out = self.loss(data[order[start : start + size]])
                total = out["loss_objective"] + out["loss_critic"] + out["loss_entropy"]
                values = {key: float(out[key].detach()) for key in LOSS_KEYS}
                # before the step changes the weights
                check_loss(float(total.detach()), self.label, self.gradient_steps + steps + 1)
                self.optimizer.zero_grad(set_to_none=True)
                total.backward()
                nn.utils.clip_grad_norm_(params, self.hp["max_grad_norm"])
                self.optimizer.step()
                steps += 1
                for key, value in values.items():
                    sums[f"train/{key}"] = sums.get(f"train/{key}", 0.0) + value
        self.gradient_steps += steps
        return {key: value / max(steps, 1) for key, value in sums.items()}

    # -------------------------------------------------------------- Learner interface
    def encode(self, env: AuctionEnv) -> TensorDict:
        """Observation TensorDict of the decision point, as the env view writes it."""
        td = observation_td(env, self.group_map, env.action_mask, self.rule, self.features)
        if self.set_inputs:
            td.update(set_inputs_td(env, self.group_map, env.action_mask))
        return td

    def act(self, view: TensorDict, mask: np.ndarray, *, explore: bool) -> np.ndarray:
        """Sampled (``explore``) or masked-mode actions of the actor, valid under ``mask``.

        Args:
            view: Output of :meth:`encode`.
            mask: ``[B, m, K + 1]`` bool valid actions (replaces the view's mask).
            explore: Sample from the policy (True) or play its masked mode (False).

        Returns:
            ``[B, m]`` int64 actions.
        """
        td = view.clone()
        td.set((GROUP, "action_mask"), torch.from_numpy(np.ascontiguousarray(mask, dtype=bool)))
        exploration = ExplorationType.RANDOM if explore else ExplorationType.DETERMINISTIC
        with torch.no_grad(), set_exploration_type(exploration):
            td = self.actor(td.to(self.device))
        return td.get(ACTION).cpu().numpy().astype(np.int64)

    def learning_space(self) -> dict[str, int]:
        """Network size: ``{"parameters": trainable parameter count}`` (no table dimension)."""
        return {"parameters": sum(p.numel() for p in self.networks.parameters())}

    def save(self, directory: Path) -> None:
        """Write ``weights.pt`` (a state_dict, ``weights_only`` loadable) and ``learner.json``."""
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
        }
        (directory / META_FILE).write_text(json.dumps(meta, indent=2) + "\n")

    def load(self, directory: Path) -> None:
        """Restore the weights written by :meth:`save`.

        Raises:
            ValueError: naming the file, if it is unreadable or its class, groups, inputs,
                tensor names or shapes differ from this learner's.
        """
        directory = Path(directory)
        meta_path = directory / META_FILE
        meta = read_meta(meta_path, META)
        saved_class, saved_groups = meta["class"], meta["group_map"]
        saved = meta["hyperparameters"]
        saved_inputs = (saved.get("network"), saved.get("features"))
        if saved_class != type(self).__name__:
            raise ValueError(f"{directory} holds a {saved_class}, not a {type(self).__name__}")
        if saved_groups != self.group_map:
            raise ValueError(
                f"{meta_path}: checkpoint groups {saved_groups} differ from {self.group_map}"
            )
        if saved_inputs != (self.hp["network"], self.features):
            raise ValueError(
                f"{meta_path}: trained with network={saved_inputs[0]}, features="
                f"{saved_inputs[1]}; this run's learner has network={self.hp['network']}, "
                f"features={self.features}"
            )
        self.networks.load_state_dict(read_weights(directory / WEIGHTS_FILE, self.networks))

    def checkpoint_state(self, directory: Path) -> dict[str, Any]:
        """Counters; the optimizer in ``training.pt`` (torch's generator is the runner's)."""
        write_tensors({"optimizer": self.optimizer.state_dict()}, Path(directory) / TRAINING_FILE)
        return {**super().checkpoint_state(directory), "gradient_steps": self.gradient_steps}

    def restore_state(self, state: dict[str, Any], directory: Path) -> None:
        """Restore :meth:`checkpoint_state` (``weights_only`` loading of ``training.pt``)."""
        super().restore_state(state, directory)
        path = Path(directory) / TRAINING_FILE
        params = list(self.loss.parameters())  # the optimizer's: Adam's two moments of each
        limit = tensor_file_limit(params, params)
        extra = read_tensors(path, self.device, limit, f"a {TRAINING_FILE} of this learner")
        if not isinstance(extra, dict) or set(extra) != {"optimizer"}:
            raise RunDirError(f"{path}: expected the key optimizer")
        check_optimizer_state(extra["optimizer"], self.optimizer, path)
        self.optimizer.load_state_dict(extra["optimizer"])
        self.gradient_steps = int(state["gradient_steps"])
