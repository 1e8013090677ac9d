"""The Q-learners' shared parts: masked epsilon-greedy, priors, replayed TD losses, target networks.

The Q-learners (``subg_dqn``, ``vdn``, ``qmix``, ``iql``) are off-policy torch learners
(:class:`~mrta_rl.learners.neural.torch_learner.TorchLearner`) built from TorchRL parts on the
keys of :class:`~mrta_rl.envs.torchrl_env.AuctionTorchRLEnv`: per group ``(group, "observation")``
``[*, n_g, F]`` (:func:`~mrta_rl.envs.encodings.local_features`) or the set inputs, ``(group,
"action_mask")`` ``[*, n_g, K + 1]`` and ``(group, "action")`` ``[*, n_g]``, root ``"state"``
(global features), and the rewards ``(group, "reward")`` (team reward, TorchRL's reward key),
``(group, "robot_reward")`` and ``(group, "group_reward")``, all ``[*, n_g, 1]``. The collector
runs :attr:`QLearner.collection_policy` (Q-network -> :class:`EpsilonGreedy`: masked argmax, random
valid actions), the loop replays the transitions of :meth:`QLearner.process_batch` and each
gradient step is the group losses' sum, followed by soft or hard target updates.

Auction prior (documented bias, ``auction_prior`` hyperparameter): the Q-value of the plain
auction's action -- the lowest-numbered valid bid (spec "Fixed policies", greedy) -- gets a fixed
bonus ``auction_prior`` added to the network output, and the network's last layer starts at zero.
An untrained network therefore *is* the greedy auction, and Q-learning only has to learn where
deviating from it pays (wait for an H task, spread bids over slots). The bonus is part of the
Q-function in the online and the target network alike, so it is an initialisation, not reward
shaping: the TD fixed point is unchanged, only the function the net must represent is
``Q* - prior``. ``auction_prior: 0`` turns it off.

Rule prior (``prior: hold``, the words of DQL's ``prior``): the bonus goes instead to the action of
the whole-team ``team_reserve`` rule (:class:`~mrta_rl.priors.HoldRule`, the
``prior_*`` settings), so the untrained network plays that rule exactly. The rule reads the whole
team (which robots are idle, which one the team asks first), more than a robot's local features.

Every prior (the plain auction's :class:`~mrta_rl.priors.GreedyPrior`, the rule,
subG-DQN's ``spread_wait``) is computed from the core env with the rules of ``mrta_rl/rules.py``
by the TorchRL view (its ``prior`` argument), in training and in evaluation alike, and reaches the
Q-network as the observation ``(group, "prior_action")``, the action index per robot, stored in
the replay buffer with the other observations so the target network sees the prior's action of
the next state; the networks expand it to a one-hot
(:func:`~mrta_rl.envs.torchrl_env.prior_one_hot`).
``prior_in_state`` (with ``hold``) also feeds that one-hot to the network as an input.

Network (``network``, QMIX, VDN and IQL): ``mlp`` is the per-robot MLP over the local features,
robot-id one-hot included; ``set`` is the shared robot-set network (``set_network.py``) over the
team-size independent set inputs (:func:`~mrta_rl.envs.encodings.set_inputs`): one set of weights
whatever the team, no robot id. QMIX's mixer keeps reading the global ``state``, so only VDN and
IQL with ``network=set`` fit any team (and train on a family of teams).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Annotated, Any, ClassVar, Literal

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase, TensorDictSequential
from torch import nn
from torchrl.envs.utils import ExplorationType, exploration_type
from torchrl.modules import QValueModule
from torchrl.objectives import HardUpdate, LossModule, SoftUpdate

from mrta_rl.config import Choices, ConfigError, Range
from mrta_rl.envs import AuctionEnv
from mrta_rl.envs.torchrl_env import GROUP_SET_KEYS, PRIOR_KEY, ROOT_SET_KEYS
from mrta_rl.learners.base import TrainingTeam
from mrta_rl.learners.memory import feature_sizes, mlp_weights
from mrta_rl.learners.neural.networks import PerRobotQ, joint_decode, joint_encode
from mrta_rl.learners.neural.set_network import SetNetworkOption
from mrta_rl.learners.neural.torch_learner import (
    ReplayLearner,
    check_decay,
    check_module_states,
    linear_decay,
)
from mrta_rl.partition import Partition
from mrta_rl.priors import (
    HOLD_PRIORS,
    HOLD_SCOPES,
    GreedyPrior,
    HoldLevel,
    HoldRule,
    Reserve,
    SpreadWaitPrior,
)
from mrta_rl.run_layout import RunDirError

JOINT = "joint"  # root sub-TensorDict of joint-action keys: (JOINT, group, leaf), batch [*]
Prior = GreedyPrior | HoldRule | SpreadWaitPrior  # env state -> [B, m] the prior's actions
# per-robot reward leaves of AuctionTorchRLEnv, [*, n_g, 1]: team (TorchRL's reward key),
# individual, and sub-group reward (spec step 8)
REWARD_KEYS = ("reward", "robot_reward", "group_reward")


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
        """Hold the exploration rate (a buffer, set by :meth:`QLearner.after_collect`).

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


class QLearner(ReplayLearner, abstract=True):
    """Base of the Q-learners (module docstring): off-policy replay, TD losses, target networks.

    Subclasses build, in ``_build``, ``self.networks``, the greedy policy (``self._policy``), the
    exploring one (``self._collection``, with :meth:`_egreedy`) and ``self.losses`` (TorchRL
    ``DQNLoss`` / ``QMixerLoss`` by group). They may override :meth:`process_batch` to add the
    keys their loss reads.
    """

    @classmethod
    def check_settings(cls, settings: Mapping[str, Any], team: TrainingTeam) -> None:
        """Refuse ``eps_end`` above ``eps_start``, and ``prior_in_state`` without the hold prior.

        Raises:
            ConfigError: naming the settings.
        """
        super().check_settings(settings, team)
        check_decay(settings, "eps_start", "eps_end", "epsilon")
        if settings["prior_in_state"] and settings["prior"] != "hold":
            raise ConfigError(
                "learner.prior_in_state: needs prior=hold (the plain auction is no input)"
            )

    def __init__(
        self,
        *,
        loss_function: Literal["l2", "smooth_l1"],
        prior: Annotated[str, Choices(*HOLD_PRIORS)],
        prior_reserve: Reserve,
        prior_hold_level: HoldLevel,
        prior_hold_scope: Annotated[str, Choices(*HOLD_SCOPES)],
        prior_in_state: bool,
        eps_start: Annotated[float, Range(0, 1)],
        eps_end: Annotated[float, Range(0, 1)],
        eps_decay_frames: Annotated[int, Range(1)],
        buffer_size: Annotated[int, Range(1)],
        batch_size: Annotated[int, Range(1)],
        collect_ticks: Annotated[int, Range(1)],
        updates_per_collect: Annotated[int, Range(0)],
        warmup_frames: Annotated[int, Range(0)],
        target_update: Literal["soft", "hard"],
        tau: Annotated[float, Range(0, 1, low_open=True)],
        hard_update_interval: Annotated[int, Range(1)],
        **settings: Any,
    ) -> None:
        """Build as every torch learner, then the TD targets and the target-network updates.

        Args:
            loss_function: TD loss, ``"l2"`` or ``"smooth_l1"`` (Huber).
            prior: The action the bonus goes to: ``greedy`` (the plain auction's bid) or ``hold``
                (the ``team_reserve`` rule's, :data:`~mrta_rl.priors.HOLD_PRIORS`;
                subG-DQN has its own ``prior``).
            prior_reserve: ``prior="hold"``: the rule's ``reserve``.
            prior_hold_level: ``prior="hold"``: the rule's ``hold_level``.
            prior_hold_scope: ``prior="hold"``: the rule's ``hold_scope``.
            prior_in_state: ``prior="hold"``: the rule's action (one-hot) is also a network input.
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
            **settings: Env, generator, partition and the settings of :class:`TorchLearner`.

        Raises:
            ConfigError: on settings that contradict each other (:meth:`check_settings`).
            ValueError: on an unavailable device.
        """
        # types and ranges: the annotations (mrta_rl.config); relations: check_settings
        self.egreedy: list[EpsilonGreedy] = []  # the exploration rates (anneal, checkpoints)
        super().__init__(**settings)
        self.rule: Prior = self._prior(self.env)
        for loss in self.losses.values():
            loss.make_value_estimator(gamma=self.hp["gamma"])
        self.target_updaters = [
            SoftUpdate(loss, tau=tau)
            if target_update == "soft"
            else HardUpdate(loss, value_network_update_interval=hard_update_interval)
            for loss in self.losses.values()
        ]

    # -------------------------------------------------------------- what subclasses build
    def _prior(self, env: AuctionEnv) -> Prior:
        """The prior of the settings, computed from ``env`` (module docstring)."""
        hp = self.hp
        if hp["prior"] == "hold":
            return HoldRule(
                env,
                reserve=hp["prior_reserve"],
                hold_level=hp["prior_hold_level"],
                hold_scope=hp["prior_hold_scope"],
            )
        return GreedyPrior()

    def _rebind(self) -> None:
        self.rule = self._prior(self.env)

    @property
    def prior(self) -> Prior:
        """The prior whose action the view writes (module docstring)."""
        return self.rule

    @property
    def inputs(self) -> dict[str, Any]:
        """The networks' inputs and the prior: its action is part of the Q-function."""
        prior = {key: value for key, value in self.hp.items() if key.startswith("prior")}
        if prior.get("prior") != "hold":  # the rule's settings matter only with the rule
            prior = {key: prior[key] for key in ("prior", "prior_in_state") if key in prior}
        return {**super().inputs, **prior}

    @property
    def policy(self) -> TensorDictModuleBase:
        """Q-networks and masked argmax (``QValueModule``): the greedy policy."""
        return self._policy

    @property
    def collection_policy(self) -> TensorDictModuleBase:
        """Q-networks and :class:`EpsilonGreedy`: what the collector runs."""
        return self._collection

    def _egreedy(self, joint: tuple[int, int] | None = None) -> EpsilonGreedy:
        """An :class:`EpsilonGreedy` at ``eps_start``, annealed by :meth:`after_collect`."""
        module = EpsilonGreedy(self.hp["eps_start"], self.device, joint)
        self.egreedy.append(module)
        return module

    def _td_loss(self, loss_class: type[LossModule], *modules: Any, **keys: Any) -> LossModule:
        """A TorchRL TD loss (``DQNLoss``, ``QMixerLoss``) of the settings, reading ``keys``.

        With a target network (``delay_value``), over categorical actions, the TD loss
        ``loss_function``; ``keys`` are its ``set_keys`` (which reward, which flags).
        """
        loss = loss_class(
            *modules,
            loss_function=self.hp["loss_function"],
            delay_value=True,
            action_space="categorical",
        )
        loss.set_keys(**keys)
        return loss

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
            prior_in_state=self.hp["prior_in_state"],
        )
        return qnet, [(group, "observation"), (group, PRIOR_KEY)]

    def _per_robot_policy(
        self, group: str, share_params: bool
    ) -> tuple[TensorDictSequential, TensorDictSequential]:
        """Greedy and exploring policies of one group over the same per-robot Q-network.

        Returns:
            ``(policy, collection policy)``: Q-network + ``QValueModule`` (masked argmax; the
            losses' value network, and the greedy policy), and Q-network +
            :class:`EpsilonGreedy` (writing ``(group, "action")``).
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

    # -------------------------------------------------------------- the loop's protocol
    @property
    def epsilon(self) -> float:
        """Current exploration rate (shown by the progress bar)."""
        return float(self.egreedy[0].eps) if self.egreedy else 0.0

    def after_collect(self, frames: int) -> None:
        """Advance the epsilon schedules by ``frames`` collected copy-ticks.

        The linear decay of ``EGreedyModule.step`` in closed form: ``EGreedyModule.step(n)``
        loops in Python over the ``n`` frames (one tensor op each), which cost as much as
        collecting them; ``eps = max(eps_end, eps_start - (eps_start - eps_end) f / F)``
        after ``f`` frames (``F = eps_decay_frames``) is the same schedule.
        """
        super().after_collect(frames)
        hp = self.hp
        eps = linear_decay(
            hp["eps_start"], hp["eps_end"], self.frames_collected, hp["eps_decay_frames"]
        )
        for module in self.egreedy:
            module.eps.fill_(eps)

    def process_batch(self, data: TensorDictBase) -> TensorDictBase:
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

    def loss(self, batch: TensorDictBase) -> tuple[torch.Tensor, dict[str, float]]:
        """The TD losses of the groups, summed (``train/loss``)."""
        total = sum(loss(batch)["loss"] for loss in self.losses.values())
        return total, {"train/loss": float(total.detach())}

    def after_step(self) -> None:
        """Move the target networks (soft or hard update)."""
        for updater in self.target_updaters:
            updater.step()

    # -------------------------------------------------------------- files
    def training_state(self) -> dict[str, Any]:
        """The optimiser's state, the losses' (target networks) and the exploration rates."""
        return {
            **super().training_state(),
            "losses": {name: loss.state_dict() for name, loss in self.losses.items()},
            "egreedy": [module.state_dict() for module in self.egreedy],
        }

    def restore_training_state(self, saved: dict[str, Any], path) -> None:
        """Check and restore :meth:`training_state`.

        Raises:
            RunDirError: naming the file and the key.
        """
        losses = {name: loss.state_dict() for name, loss in self.losses.items()}
        check_module_states(saved["losses"], losses, f"{path}: losses")
        saved_eps = saved["egreedy"]
        if not isinstance(saved_eps, list) or len(saved_eps) != len(self.egreedy):
            raise RunDirError(f"{path}: egreedy: expected {len(self.egreedy)} exploration states")
        for saved_module in saved_eps:
            eps = saved_module.get("eps") if isinstance(saved_module, dict) else None
            if not isinstance(eps, torch.Tensor) or eps.numel() != 1 or not 0 <= float(eps) <= 1:
                raise RunDirError(f"{path}: egreedy.eps: must be a number in [0, 1]")
        super().restore_training_state(saved, path)
        for name, loss in self.losses.items():
            loss.load_state_dict(saved["losses"][name])
        for module, saved_module in zip(self.egreedy, saved_eps, strict=True):
            module.eps.copy_(saved_module["eps"])

    def checkpoint_state(self, directory) -> dict[str, Any]:
        """Counters of the base (the epsilon clock among them) and the target updaters'."""
        return {
            **super().checkpoint_state(directory),
            "target_updaters": [u.state_dict() for u in self.target_updaters],
        }

    def restore_state(self, state: dict[str, Any], directory) -> None:
        """Restore :meth:`checkpoint_state`."""
        super().restore_state(state, directory)
        for updater, saved in zip(self.target_updaters, state["target_updaters"], strict=True):
            updater.load_state_dict(saved)


class PerRobotQLearner(SetNetworkOption, QLearner, abstract=True):
    """One Q-value per robot and action (VDN, QMIX, IQL); ``network`` chooses the network.

    ``network=mlp`` is :class:`~mrta_rl.learners.neural.networks.PerRobotQ` over the local
    features; ``network=set`` is the shared robot-set network
    (:class:`~mrta_rl.learners.neural.set_network.SetWithPrior`, one set of weights for every
    robot and any team, no robot id) with the same prior bonus. The ``embed_dim``, ``heads``,
    ``layers``, ``max_task_types`` and ``robot_attention`` settings are the set network's
    (``mlp`` ignores them; ``hidden`` and ``depth`` are the MLP's).
    """

    # network=mlp: one MLP shared by the robots (True), or one per robot
    shared_mlp: ClassVar[bool] = True

    @classmethod
    def network_weights(
        cls, env: AuctionEnv, partition: Partition | None, settings: dict[str, Any]
    ) -> int:
        """The shared set network (``set``), or the MLP(s) (``mlp``); a mixer adds its own."""
        if settings.get("network", "mlp") == "set":
            return cls.check_set_network(env.n_task_types, env.system.name, settings)
        n_in, _ = feature_sizes(env, settings)
        mlp = mlp_weights(n_in, env.n_actions, int(settings["depth"]), int(settings["hidden"]))
        return mlp if cls.shared_mlp else env.n_robots * mlp

    def _q_network(self, group: str, share_params: bool) -> tuple[nn.Module, list]:
        """With ``network=set``: :class:`SetWithPrior` over the set inputs, mask and prior."""
        if self.hp["network"] != "set":
            return super()._q_network(group, share_params)
        keys = [(group, key) for key in GROUP_SET_KEYS] + list(ROOT_SET_KEYS)
        return self._set_network(), [*keys, (group, "action_mask"), (group, PRIOR_KEY)]


class MixedQLearner(PerRobotQLearner, abstract=True):
    """Per-robot Q-network (shared parameters) mixed into a team Q (VDN, QMIX).

    One TorchRL group ``"agents"`` holds every robot; their chosen Q-values are mixed by
    :meth:`_mixer` and trained on the team reward (spec step 8) with TorchRL's ``QMixerLoss``.
    Subclasses differ only in the mixer (``vdn.py``: a sum, ``qmix.py``: ``QMixer``).
    """

    replay_loss_keys_only: ClassVar[bool] = True  # process_batch keeps the loss's in_keys

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
        self._policy, self._collection = self._per_robot_policy(group, share_params=True)
        mixer = self._mixer()
        self.networks["mixer"] = mixer.module
        self.losses[group] = self._td_loss(
            QMixerLoss,
            self._policy,
            mixer,
            action_value=(group, "action_value"),
            local_value=(group, "chosen_action_value"),
            global_value="chosen_action_value",
            action=(group, "action"),
            reward="reward",  # team reward (spec step 8), set at the root by process_batch()
            done="done",
            terminated="terminated",
        )

    def process_batch(self, data: TensorDictBase) -> TensorDictBase:
        """Scaled team reward, also at the root ``[N, 1]`` where ``QMixerLoss`` reads it.

        As in TorchRL's QMIX example. Only what the loss reads is kept (its ``in_keys``): the
        Q-values are recomputed by the loss, and the per-robot rewards, the root flags of the
        current step and (VDN: its mixer has no state input) the state are read by no one.
        """
        data = super().process_batch(data)
        data.set(("next", "reward"), data.get(("next", "agents", "reward"))[:, 0])
        return data.select(*self.losses["agents"].in_keys)
