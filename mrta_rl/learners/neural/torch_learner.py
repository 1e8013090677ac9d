"""The one base of the TorchRL learners: what the torch loop calls, and what every one of them owns.

Every torch learner (Q-learners ``subg_dqn``, ``vdn``, ``qmix``, ``iql``; policy-gradient ``mappo``,
``ippo``; and any plugin) is a :class:`TorchLearner`. The base owns, once, what they share: the
device, the settings (``hp``), building the networks from the learner's own generator, the
optimiser and the gradient step, acting on a core env through the same TorchRL view that training
collects from, and the learner's files (``weights.pt``, ``learner.json``, ``training.pt``).

The training loop (``mrta_rl/runners/torch_loop.py``) is the same for all of them, as BenchMARL's
``Experiment`` is for its algorithms. A subclass declares its regime and fills in the protocol the
loop calls (each abstract here):

* :attr:`TorchLearner.on_policy`: on-policy learners consume each collected batch (a buffer of
  one batch, sampled without replacement, ``epochs`` passes); off-policy learners replay from a
  buffer of ``buffer_size`` transitions sampled at random, after ``warmup_frames``;
* :meth:`TorchLearner.loop_settings`: frames per collected batch, buffer size, minibatch size,
  gradient steps per batch, warm-up;
* :attr:`TorchLearner.collection_policy`: the policy the collector runs (epsilon-greedy, or
  sampling the actor); :attr:`TorchLearner.policy` plays greedily (evaluation);
* :meth:`TorchLearner.process_batch`: a collected ``[B, T]`` batch -> the rows the buffer keeps
  (rewards scaled, the keys the loss reads; GAE's advantages for PPO);
* :meth:`TorchLearner.loss`: the loss of one sampled minibatch and its diagnostics;
* :meth:`TorchLearner.after_step` (target networks) and :meth:`TorchLearner.after_collect`
  (exploration schedules), optional.

A learner whose networks fit any team (the robot-set network and no part that reads the team's
size) says so from its settings (:meth:`~mrta_rl.learners.base.Learner.fits_any_team`) and
rebinds to each team of a family (:meth:`TorchLearner.bind_env`).
"""

from __future__ import annotations

import json
import weakref
from abc import abstractmethod
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any, ClassVar, NamedTuple

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torchrl.collectors import Collector
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.objectives import LossModule

from mrta_rl.checked_files import read_tensors, tensor_file_limit
from mrta_rl.config import Choices, ConfigError, Range, short_list
from mrta_rl.envs import AuctionEnv, encodings
from mrta_rl.envs.torchrl_env import AuctionTorchRLEnv
from mrta_rl.learners.base import FACTS, TORCH_LOOP, Learner, LearnerKind, MemoryQuery
from mrta_rl.learners.memory import NEURAL_ADVICE, ResourceEstimate, neural_estimate
from mrta_rl.learners.neural.tensor_files import (
    META_FILE,
    TRAINING_FILE,
    WEIGHTS_FILE,
    check_finite_weights,
    check_loss,
    check_optimizer_state,
    check_state_dict,
    read_meta,
    read_weights,
    write_tensors,
)
from mrta_rl.partition import Partition
from mrta_rl.run_layout import ANY, INT, STR, RunDirError
from mrta_rl.types import GroupMap

MIN_TORCHRL = (0, 14)  # Collector(auto_register_policy_transforms=...), torchrl 0.14 names
# learner.json as TorchLearner.save writes it (run_layout.check_schema)
META = {
    "class": STR,
    "group_map": {"*": [STR]},
    "gradient_steps": INT,
    "hyperparameters": {"*": ANY},
    "inputs": ANY,
}


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


class LoopSettings(NamedTuple):
    """How the torch loop collects and trains, from a learner's settings (its regime).

    Attributes:
        frames_per_batch: Frames (copy-ticks) per collected batch; whole ticks of every copy.
        buffer_size: Transitions the buffer holds (on-policy: one batch).
        minibatch_size: Transitions per gradient step.
        updates_per_batch: Gradient steps after each collected batch.
        warmup_frames: Frames collected before the first gradient step.
    """

    frames_per_batch: int
    buffer_size: int
    minibatch_size: int
    updates_per_batch: int
    warmup_frames: int


class TorchLearner(Learner, abstract=True):
    """Base of every TorchRL learner (module docstring).

    Subclasses build, in :meth:`_build`, ``self.networks`` (an ``nn.ModuleDict``: everything that
    is saved), :attr:`policy` and :attr:`collection_policy` (TensorDict modules writing ``(group,
    "action")``) and ``self.losses`` (TorchRL loss modules by name, whose parameters the optimiser
    trains); and they fill in the loop's protocol. Besides the facts of every learner a concrete
    class declares :attr:`on_policy` and counts its trainable weights (``network_weights``, a
    classmethod ``(env, partition, settings) -> int``) for the memory estimate.

    Attributes:
        device: Where the networks and the updates live (the env stays on cpu).
        group_map: The TorchRL groups of the view: ``{group: [robot ids]}``.
        networks: What :meth:`save` writes.
        losses: TorchRL loss modules by name.
        optimizer: Adam over the losses' parameters.
        gradient_steps: Gradient steps taken.
    """

    kind: ClassVar[LearnerKind] = "neural"
    training_loop: ClassVar[str] = TORCH_LOOP
    on_policy: ClassVar[bool]
    facts: ClassVar[tuple[str, ...]] = (*FACTS, "on_policy", "network_weights")
    # the optimiser's kernel: fused (one kernel over all parameters) or per tensor
    fused_optimizer: ClassVar[bool] = True
    # its collection policy reads only the view's observations: Ray workers may collect
    collection_on_workers: ClassVar[bool] = True

    def __init__(
        self,
        *,
        env: AuctionEnv,
        rng: np.random.Generator,
        partition: Partition | None = None,
        hidden: Annotated[int, Range(1)],
        depth: Annotated[int, Range(1)],
        lr: Annotated[float, Range(0, low_open=True)],
        gamma: Annotated[float, Range(0, 1, low_open=True, high_open=True)],
        reward_scale: Annotated[float, Range(0, low_open=True)],
        auction_prior: Annotated[float, Range(0)],
        features: Annotated[str, Choices(*encodings.FEATURES)],
        max_grad_norm: Annotated[float, Range(0, low_open=True)],
        device: Annotated[str, Choices("cpu", "cuda")] = "cpu",
    ) -> None:
        """Build the networks (from the learner's generator), the losses and the optimiser.

        Args:
            env: The training env (sizes; never stepped by the learner).
            rng: Seeds the network initialisation (in a forked torch state); exploration and
                sampling draw from torch, which the runner seeds.
            partition: The subG partition (learners that require one).
            hidden: Units per hidden layer of the MLPs.
            depth: Hidden layers of the MLPs.
            lr: Adam learning rate.
            gamma: Discount per tick.
            reward_scale: Rewards are multiplied by this before the loss (values stay O(10)).
            auction_prior: Bonus of the prior's action in the networks' output (Q-units or
                logits); the output layers start at zero, so the untrained policy is the prior.
            features: The inputs' encoding (``encodings.FEATURES``).
            max_grad_norm: Gradient clipping norm.
            device: ``"cpu"`` or ``"cuda"``.

        Raises:
            ValueError: if the device is unavailable.
        """
        require_torchrl()
        super().__init__(env=env, rng=rng, partition=partition)
        if torch.device(device).type == "cuda" and not torch.cuda.is_available():
            raise ValueError("device=cuda but CUDA is not available")
        self.device = torch.device(device)
        self.group_map: GroupMap = self._group_map()
        self.networks = nn.ModuleDict()
        self.losses: dict[str, LossModule] = {}
        # network initialisation draws from torch's generator: seeded from the learner's own
        # generator, in a forked state, so runs are reproducible and torch's global state is
        # left to the runner
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(int(rng.integers(2**31)))
            self._build()
        # what the optimiser trains: the losses' parameters (a learner without a TorchRL loss
        # module: its networks')
        trained = list(self.losses.values()) or [self.networks]
        params = list(dict.fromkeys(p for module in trained for p in module.parameters()))
        self.optimizer = torch.optim.Adam(params, lr=lr, fused=self.fused_optimizer or None)
        self.gradient_steps = 0
        self._views: weakref.WeakKeyDictionary[AuctionEnv, AuctionTorchRLEnv] = (
            weakref.WeakKeyDictionary()
        )

    # -------------------------------------------------------------- what subclasses build
    def _group_map(self) -> GroupMap:
        """TorchRL groups of the learner; default: all robots in one group ``"agents"``."""
        return {"agents": list(self.env.system.robots)}

    @abstractmethod
    def _build(self) -> None:
        """Build ``networks``, ``policy``, ``collection_policy`` and ``losses``."""

    @property
    @abstractmethod
    def policy(self) -> TensorDictModuleBase:
        """The greedy (deterministic) policy: evaluation plays it."""

    @property
    @abstractmethod
    def collection_policy(self) -> TensorDictModuleBase:
        """The policy the collector runs while training (it explores)."""

    @property
    def prior(self) -> Any:
        """The prior whose action the view writes (``(group, "prior_action")``), or None."""
        return None

    @property
    def n_features(self) -> int:
        """``F``: the local features per robot in the learner's encoding."""
        return encodings.local_feature_size(self.env, self.hp["features"])

    @property
    def state_size(self) -> int:
        """``G``: the global features (the ``state``) in the learner's encoding."""
        return encodings.global_feature_size(self.env, self.hp["features"])

    @property
    def view_options(self) -> dict[str, Any]:
        """What the TorchRL view writes for these networks (``AuctionTorchRLEnv``'s keywords).

        The prior's action, the features' encoding, and the set inputs instead of the local
        features when the networks read them (``network=set``).
        """
        set_inputs = self.hp.get("network") == "set"
        return {
            "prior": self.prior,
            "features": self.hp["features"],
            "set_inputs": set_inputs,
            "local_features": not set_inputs,
        }

    # -------------------------------------------------------------- the loop's protocol
    @classmethod
    @abstractmethod
    def batch_frames(cls, settings: Mapping[str, Any], copies: int, horizon: int) -> int:
        """Frames per collected batch of a learner of these settings (whole ticks of every copy).

        Args:
            settings: The learner's settings.
            copies: Training copies ``B``.
            horizon: Ticks of an episode.
        """

    @classmethod
    def check_family_settings(cls, settings: Mapping[str, Any], horizon: int, copies: int) -> None:
        """On a family, a batch must end with its team's episode: its frames divide an episode's.

        Raises:
            ConfigError: naming the learner's batch setting.
        """
        frames = cls.batch_frames(settings, copies, horizon)
        if (horizon * copies) % frames:
            raise ConfigError(
                f"learner: a collected batch of {frames} frames does not divide an episode of "
                f"{horizon} ticks x {copies} copies: on a family of teams each episode plays "
                "another team, so a batch must not straddle two"
            )

    @abstractmethod
    def loop_settings(self, copies: int, total_frames: int) -> LoopSettings:
        """How the loop collects and trains (:class:`LoopSettings`).

        Args:
            copies: Training copies ``B`` (a batch is whole ticks of every copy).
            total_frames: Frames of the whole run (a run shorter than a batch trains on all).
        """

    @abstractmethod
    def process_batch(self, data: TensorDictBase) -> TensorDictBase:
        """A collected ``[B, T]`` batch -> the ``[B * T]`` rows the buffer keeps."""

    @abstractmethod
    def loss(self, batch: TensorDictBase) -> tuple[torch.Tensor, dict[str, float]]:
        """The loss of a sampled minibatch (to minimise) and its diagnostics (``train/...``)."""

    def train_info(self) -> dict[str, float]:
        """Figures of the learner's own for the run's ``train`` info (rates); default: none."""
        return {}

    def after_step(self) -> None:  # noqa: B027 - optional hook, deliberately a no-op
        """After each gradient step (target-network updates); default: nothing."""

    def after_collect(self, frames: int) -> None:  # noqa: B027 - optional hook
        """After each collected batch of ``frames`` (exploration schedules); default: nothing."""

    def train_step(self, batch: TensorDictBase) -> dict[str, float]:
        """One gradient step on a sampled minibatch, checked to stay finite.

        Args:
            batch: Rows of :meth:`process_batch`, on :attr:`device`.

        Returns:
            The loss's diagnostics.

        Raises:
            NonFiniteState: if the loss is NaN or infinite (before the step uses it).
        """
        total, info = self.loss(batch)
        check_loss(float(total.detach()), self.label, self.gradient_steps + 1)
        self.optimizer.zero_grad(set_to_none=True)
        total.backward()
        params = [p for group in self.optimizer.param_groups for p in group["params"]]
        nn.utils.clip_grad_norm_(params, self.hp["max_grad_norm"])
        self.optimizer.step()
        self.after_step()
        self.gradient_steps += 1
        return info

    def bind_env(self, env: AuctionEnv) -> None:
        """Train on ``env`` from now on: the next team of a family (``system.family``).

        The networks are the same; the groups, the prior and the sizes are the new team's.

        Raises:
            NotImplementedError: if the learner's settings tie it to one team.
        """
        if not type(self).fits_any_team(self.hp):
            super().bind_env(env)
        self.env, self.n_robots, self.n_actions = env, env.n_robots, env.n_actions
        self.group_map = self._group_map()
        self._views.clear()
        self._rebind()

    def _rebind(self) -> None:  # noqa: B027 - optional hook, deliberately a no-op
        """Follow :meth:`bind_env` in the parts that depend on the team (priors); default: none."""

    # -------------------------------------------------------------- acting on a core env
    def view(self, env: AuctionEnv, **options: Any) -> AuctionTorchRLEnv:
        """The TorchRL view of ``env`` with this learner's inputs (one per env, kept).

        Args:
            env: A core env of the learner's team.
            **options: More ``AuctionTorchRLEnv`` keywords (the training loop's
                ``invalid_action``).
        """
        view = self._views.get(env)
        if view is None or options:
            view = AuctionTorchRLEnv(env, group_map=self.group_map, **self.view_options, **options)
            if not options:
                self._views[env] = view
        return view

    def training_view(self, env: AuctionEnv) -> AuctionTorchRLEnv:
        """The view the loop trains on: an invalid action is a bug of the learner, so it raises."""
        return self.view(env, invalid_action="raise")

    def collector(self, view: AuctionTorchRLEnv, frames_per_batch: int, frames: int) -> Collector:
        """The TorchRL collector of the loop: :attr:`collection_policy` on ``view``.

        Args:
            view: A :meth:`training_view`.
            frames_per_batch: Frames (copy-ticks) per batch: whole ticks of every copy.
            frames: Frames it collects in all.
        """
        return Collector(
            view,
            self.collection_policy,
            frames_per_batch=frames_per_batch,
            total_frames=frames,
            env_device="cpu",
            policy_device=self.device,
            storing_device=self.device,
            auto_register_policy_transforms=False,
        )

    def encode(self, env: AuctionEnv) -> TensorDictBase:
        """The observations of the decision point, as the view writes them while training."""
        return self.view(env).observe()

    def act(self, view: TensorDictBase, mask: np.ndarray, *, explore: bool) -> np.ndarray:
        """Greedy (or exploring) actions of the TorchRL policy, valid under ``mask``.

        Args:
            view: Output of :meth:`encode`.
            mask: ``[B, m, K + 1]`` bool valid actions (replaces the view's masks).
            explore: Play :attr:`collection_policy` instead of the greedy :attr:`policy`.

        Returns:
            ``[B, m]`` int64 actions.
        """
        td = view.clone()
        mask_t = torch.from_numpy(np.ascontiguousarray(mask, dtype=bool))
        index = self._robot_index()
        for group, idx in index.items():
            td.set((group, "action_mask"), mask_t[:, idx])
        td = td.to(self.device)
        exploration = ExplorationType.RANDOM if explore else ExplorationType.DETERMINISTIC
        with torch.no_grad(), set_exploration_type(exploration):
            td = (self.collection_policy if explore else self.policy)(td)
        actions = np.zeros(mask.shape[:2], np.int64)  # [B, m]
        for group, idx in index.items():
            actions[:, idx] = td.get((group, "action")).cpu().numpy()
        return actions

    def _robot_index(self) -> dict[str, list[int]]:
        robots = self.env.system.robots
        return {g: [robots.index(r) for r in ids] for g, ids in self.group_map.items()}

    def learning_space(self) -> dict[str, int]:
        """Network size: ``{"parameters": trainable parameter count}`` (no table dimension)."""
        return {"parameters": sum(p.numel() for p in self.networks.parameters())}

    @classmethod
    def learning_space_dimension(
        cls, env: AuctionEnv, partition: Partition | None, settings: dict[str, Any]
    ) -> int | None:
        """None: no table; :meth:`learning_space` counts the trained parameters instead."""
        return None

    # -------------------------------------------------------------- files
    @property
    def inputs(self) -> dict[str, Any]:
        """What the networks are a function of besides their weights (``learner.json``).

        A saved state is refused by a learner whose inputs differ: the encoding, the network,
        and the prior (its action is part of the networks' output).
        """
        return {"features": self.hp["features"], "network": self.hp.get("network")}

    def save(self, directory: Path) -> None:
        """Write ``weights.pt`` (a state_dict, ``weights_only`` loadable) and ``learner.json``.

        Raises:
            NonFiniteState: if a weight is NaN or infinite (nothing is written).
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
            "inputs": self.inputs,
        }
        (directory / META_FILE).write_text(json.dumps(meta, indent=2) + "\n")

    def load(self, directory: Path) -> None:
        """Restore the weights written by :meth:`save`, checked against this learner.

        A learner that fits any team takes the weights of a run on another team (its groups
        are then that team's).

        Raises:
            RunDirError: naming the file, if it is unreadable or its class, groups, inputs,
                tensor names, shapes or values do not fit this learner.
        """
        directory = Path(directory)
        meta_path = directory / META_FILE
        meta = read_meta(meta_path, META)
        if meta["group_map"] != self.group_map and not type(self).fits_any_team(self.hp):
            groups = short_list(meta["group_map"])
            raise RunDirError(f"{meta_path}: saved for the groups {groups}, not this run's")
        if meta["class"] != type(self).__name__:
            raise RunDirError(f"{directory} holds a {meta['class']}, not a {type(self).__name__}")
        saved, ours = meta["inputs"], self.inputs
        if saved != ours:
            saved = saved if isinstance(saved, dict) else {}
            key = next(k for k in sorted({*saved, *ours}) if saved.get(k) != ours.get(k))
            raise RunDirError(
                f"{meta_path}: trained with {key}={saved.get(key)}, this run's learner has "
                f"{key}={ours.get(key)} (the networks' inputs differ)"
            )
        self.networks.load_state_dict(read_weights(directory / WEIGHTS_FILE, self.networks))

    def training_state(self) -> dict[str, Any]:
        """Tensors training needs beyond the weights (``training.pt``): the optimiser's state.

        Subclasses add theirs (target networks, exploration) and check them in
        :meth:`restore_training_state`.
        """
        return {"optimizer": self.optimizer.state_dict()}

    def restore_training_state(self, saved: dict[str, Any], path: Path) -> None:
        """Check and restore :meth:`training_state` (the optimiser's; subclasses add theirs).

        Raises:
            RunDirError: naming the file and the key.
        """
        check_optimizer_state(saved["optimizer"], self.optimizer, path)
        self.optimizer.load_state_dict(saved["optimizer"])

    def checkpoint_state(self, directory: Path) -> dict[str, Any]:
        """Counters; :meth:`training_state` in ``training.pt`` (torch's generator: the runner's)."""
        write_tensors(self.training_state(), Path(directory) / TRAINING_FILE)
        return {**super().checkpoint_state(directory), "gradient_steps": self.gradient_steps}

    def restore_state(self, state: dict[str, Any], directory: Path) -> None:
        """Restore :meth:`checkpoint_state` (``weights_only`` loading of ``training.pt``)."""
        super().restore_state(state, directory)
        path = Path(directory) / TRAINING_FILE
        expected = self.training_state()
        params = [p for group in self.optimizer.param_groups for p in group["params"]]
        # besides the fresh state: Adam's two moments of every weight
        limit = tensor_file_limit(expected, params, params)
        saved = read_tensors(path, self.device, limit, f"a {TRAINING_FILE} of this learner")
        if not isinstance(saved, dict) or set(saved) != set(expected):
            raise RunDirError(f"{path}: expected the keys {short_list(sorted(expected))}")
        self.restore_training_state(saved, path)
        self.gradient_steps = int(state["gradient_steps"])


def check_module_states(saved: Any, expected: dict[str, Any], where: str) -> None:
    """Saved state dicts of named modules (losses, ...) against the learner's own.

    Raises:
        RunDirError: naming ``where`` and the first mismatch.
    """
    if not isinstance(saved, dict) or set(saved) != set(expected):
        raise RunDirError(f"{where}: expected {short_list(sorted(expected))}")
    for name, state in expected.items():
        check_state_dict(saved[name], state, f"{where}.{name}")


def linear_decay(start: float, end: float, frames: int, decay_frames: int) -> float:
    """A schedule's value after ``frames`` collected frames: ``start`` to ``end`` linearly.

    ``start - (start - end) * min(frames / decay_frames, 1)``: epsilon's (the Q-learners') and the
    teacher's share (``expert_iteration``'s ``beta``).
    """
    return start - (start - end) * min(frames / decay_frames, 1.0)


def check_decay(settings: Mapping[str, Any], start: str, end: str, what: str) -> None:
    """Refuse a schedule whose ``end`` setting is above its ``start`` (:func:`linear_decay`).

    Raises:
        ConfigError: naming both settings.
    """
    if settings[end] > settings[start]:
        raise ConfigError(
            f"learner.{end}: {settings[end]} is above learner.{start} {settings[start]} "
            f"({what} decays from {start} to {end})"
        )


class ReplayLearner(TorchLearner, abstract=True):
    """Base of the off-policy torch learners: a replay of the collected transitions.

    Its subclasses (the Q-learners, ``expert_iteration``) declare the replay's settings:
    ``buffer_size`` transitions kept, ``batch_size`` per gradient step, ``collect_ticks`` per
    collected batch, ``updates_per_collect`` gradient steps after each, ``warmup_frames`` before
    the first. The base turns them into the loop's :class:`LoopSettings`, estimates the replay's
    memory, and counts the collected frames (:attr:`frames_collected`), the clock of their
    schedules (:func:`linear_decay`), kept in checkpoints.
    """

    on_policy: ClassVar[bool] = False
    memory_advice: ClassVar[str] = NEURAL_ADVICE  # what to change when it does not fit
    # what a replayed transition keeps (memory.neural_estimate): only the loss's keys, and
    # the bytes per global feature of its states
    replay_loss_keys_only: ClassVar[bool] = False
    replay_state_bytes: ClassVar[int] = 4
    frames_collected: int = 0  # copy-ticks seen by after_collect: the schedules' clock

    @classmethod
    def estimate_memory(cls, query: MemoryQuery) -> ResourceEstimate:
        """Networks (gradients, Adam, target copies), replay buffer and collector batch.

        Raises:
            Unfit: if the networks cannot be built on the system (``network_weights``).
        """
        env, partition, settings, _, copies = query
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
    def batch_frames(cls, settings: Mapping[str, Any], copies: int, horizon: int) -> int:
        """``collect_ticks`` ticks (at most an episode's) of every copy."""
        return min(int(settings["collect_ticks"]), horizon) * copies

    def loop_settings(self, copies: int, total_frames: int) -> LoopSettings:
        """Replay of ``buffer_size`` transitions; ``updates_per_collect`` steps per batch.

        A short run (``debug=smoke``) still reaches the gradient steps: it warms up at most half
        of its frames.
        """
        hp = self.hp
        return LoopSettings(
            frames_per_batch=self.batch_frames(hp, copies, self.env.params.horizon),
            buffer_size=int(hp["buffer_size"]),
            minibatch_size=int(hp["batch_size"]),
            updates_per_batch=int(hp["updates_per_collect"]),
            warmup_frames=min(int(hp["warmup_frames"]), total_frames // 2),
        )

    def after_collect(self, frames: int) -> None:
        """Count ``frames`` collected copy-ticks (subclasses then advance their schedules)."""
        self.frames_collected += frames

    def checkpoint_state(self, directory: Path) -> dict[str, Any]:
        """Counters of the base and the schedules' clock."""
        return {**super().checkpoint_state(directory), "frames_collected": self.frames_collected}

    def restore_state(self, state: dict[str, Any], directory: Path) -> None:
        """Restore :meth:`checkpoint_state`; the subclasses' schedules follow the clock."""
        super().restore_state(state, directory)
        self.after_collect(int(state["frames_collected"]))
