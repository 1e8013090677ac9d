"""``expert_iteration``: the rollout planner teaches the shared robot-set network (ExIt, DAgger).

The student is a masked per-robot policy: the robot-set network (``network=set``, one set of
weights for any team) or the per-robot MLP (``network=mlp``), scoring ``[*, m, K + 1]`` actions
with a logit bonus (``auction_prior``) on the action of a prior: the plain auction's bid (as
MAPPO's actor) or, with ``prior=base``, the teacher's base policy's action, so that the untrained
student plays its base and learns where the planner departs from it (a residual policy on the
base, as the Q-learners' ``hold`` prior is on the rule). It acts
without search: each robot plays its highest-scoring valid action (``decode=argmax``), or the
bids are matched to slots so that no two robots bid for one (``decode=match``).

The teacher is the ``rollout`` planner (``learners/planning/rollout.py``) with this learner's
planner settings (``samples``, ``horizon``, ``candidates``, ``neighbours``, ``margin``,
``gamma``) on a base policy: a rule of the planner's candidates, or a trained run
(``base=<run dir>``, handed over by the runner as ``base_policy``, as to ``rollout``).

Training runs on the torch loop (``runners/torch_loop.py``) like every torch learner:

* **collect** (:class:`TeacherMix`, the collection policy): at every tick of every copy the
  teacher labels the state the copy is in; the copy plays the teacher's joint action with
  probability ``beta`` (DAgger's mix, decaying linearly from ``beta_start`` to ``beta_end`` over
  ``beta_decay_frames`` collected frames) and the student's otherwise, so the labels come from
  the states the student itself visits (Ross et al., DAgger);
* **label**: per robot a distribution over its actions: the teacher's chosen joint action
  (one-hot), mixed with weight ``soft_targets`` with the candidates' distribution: the softmax of
  the candidates' mean rollout returns (times ``reward_scale``) over the candidate joint actions,
  marginalised per robot (soft targets, as ExIt's visit counts);
* **imitate the base first**: for the first ``imitate_base_frames`` collected frames the label
  is the teacher's base policy's action, unplanned (a rule or a trained run: microseconds a
  tick), so the planner's expensive labels go to a student that already plays like its base;
* **aggregate**: the labelled states go into the loop's replay buffer (``buffer_size``
  transitions, sampled at random: the aggregated data set of DAgger);
* **fit**: ``updates_per_collect`` steps of cross-entropy per robot, over the robots that have a
  choice (a valid bid), on minibatches of ``batch_size`` transitions.

The teacher's base stays the one configured. A run dir of an earlier ``expert_iteration`` run is a
base too, so rounds of expert iteration are runs that each name the last as their base, at a
cost: the planner then runs the student's network in every rollout tick of every rollout copy,
tens of times a compiled base's time (docs/results.md). The
planner reads the full env state (its snapshot), which only the training env has: the labels are
made while collecting, never from stored observations. Outside collection (evaluation, the replay
layout probe) the collection policy plays the student and labels with the student's own action.

With ``network=set`` the learner holds nothing of one team and trains on a family of teams
(``system.family``): the teacher is rebuilt on each team, its trained base rebound to it.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Annotated, Any, ClassVar

import numpy as np
import torch
from numba import njit
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from torch import nn
from torch.nn import functional as F
from torchrl.envs.utils import ExplorationType, exploration_type

from mrta_rl.config import Choices, ConfigError, Range
from mrta_rl.envs import AuctionEnv
from mrta_rl.envs.torchrl_env import GROUP_SET_KEYS, PRIOR_KEY, ROOT_SET_KEYS
from mrta_rl.learners.base import Learner, TrainingTeam
from mrta_rl.learners.memory import feature_sizes, mlp_weights
from mrta_rl.learners.neural.networks import PerRobotQ
from mrta_rl.learners.neural.set_network import SetNetworkOption
from mrta_rl.learners.neural.torch_learner import ReplayLearner, check_decay, linear_decay
from mrta_rl.learners.planning.rollout import CANDIDATES, NEIGHBOURS, RolloutPlanner
from mrta_rl.partition import Partition
from mrta_rl.priors import GreedyPrior

GROUP = "agents"  # the one TorchRL group of all robots
ACTION = (GROUP, "action")
MASK = (GROUP, "action_mask")
LOGITS = (GROUP, "logits")
TARGET = (GROUP, "target")  # the teacher's label: per robot a distribution over its actions
SET_KEYS = [*((GROUP, key) for key in GROUP_SET_KEYS), *ROOT_SET_KEYS]  # SetNetwork's order
CLOCK: Callable[[], float] = time.perf_counter  # the teacher's labelling time (labels/s)
ADVICE = "lower learner.buffer_size or learner.collect_ticks, or use a smaller system"


def match_bids(logits: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """A joint action without two bids for one slot, from per-robot scores.

    Bids are taken in decreasing order of their margin over the robot's wait score: the best
    (robot, slot) pair of a copy is kept, its robot and slot are struck out, and so on while a
    margin is positive (equal margins: the lower robot, then the lower slot, first). A robot
    whose bids were all struck out, or whose bids all score below its wait, waits. Without
    competing bids this is each robot's argmax; with them, the robot that loses a slot bids for
    its next best instead of bidding in vain (spec step 5: one winner per slot, and a losing bid
    costs the robot its tick, step 7).

    Args:
        logits: ``[*, m, K + 1]`` scores (column 0: wait).
        mask: ``[*, m, K + 1]`` bool valid actions.

    Returns:
        ``[*, m]`` int64 actions.
    """
    *lead, m, width = logits.shape
    K = width - 1
    margin = (logits[..., 1:] - logits[..., :1]).masked_fill(~mask[..., 1:], -torch.inf)
    flat = margin.detach().reshape(-1, m * K).to("cpu", torch.float64).numpy()
    actions = np.zeros((flat.shape[0], m), np.int64)
    _match_in_order(flat, K, actions)
    return torch.from_numpy(actions).to(logits.device).reshape(*lead, m)


@njit(cache=True)
def _match_in_order(margin: np.ndarray, n_slots: int, actions: np.ndarray) -> None:
    """:func:`match_bids` per copy: ``margin`` ``[N, m * K]`` robot-major, into ``actions``.

    One stable sort of a copy's positive margins replaces a round per bid: the scan meets the
    pairs in the order the rounds would take them, and skips those whose robot or slot is gone.
    """
    n_robots = actions.shape[1]
    for copy in range(margin.shape[0]):
        row = margin[copy]
        positive = np.flatnonzero(row > 0)
        order = positive[np.argsort(-row[positive], kind="mergesort")]  # ties: lower index
        robot_taken = np.zeros(n_robots, np.bool_)
        slot_taken = np.zeros(n_slots, np.bool_)
        left = min(n_robots, n_slots)
        for pair in order:
            robot, slot = pair // n_slots, pair % n_slots
            if robot_taken[robot] or slot_taken[slot]:
                continue
            actions[copy, robot] = slot + 1
            robot_taken[robot] = slot_taken[slot] = True
            left -= 1
            if left == 0:
                break


PRIORS = ("greedy", "base")  # the action of the logit bonus: the plain auction's, or the base's
DECODERS = ("argmax", "match")  # each robot's best action; or bids matched to slots


class StudentPolicy(TensorDictModuleBase):
    """The student acting without search: its scores decoded into a joint action."""

    def __init__(self, scores: TensorDictModule, decode: str) -> None:
        """Decode ``scores``' masked logits (``(agents, "logits")``) by ``decode``."""
        super().__init__()
        self.scores, self.decode = scores, decode
        self.in_keys = list(dict.fromkeys([*scores.in_keys, MASK]))
        self.out_keys = [LOGITS, ACTION]

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        """Write the logits and the joint action (:data:`DECODERS`)."""
        td = self.scores(td)
        logits = td.get(LOGITS)
        if self.decode == "match":
            td.set(ACTION, match_bids(logits, td.get(MASK)))
        else:
            td.set(ACTION, logits.argmax(-1))
        return td


class TeacherMix(TensorDictModuleBase):
    """The collection policy: the teacher labels each state; a copy plays it with prob. ``beta``.

    Labelling reads the core env the collector is stepping (the learner's ``env``, at the state
    of the TensorDict the collector passes): it happens under the collector's random exploration
    only. Under deterministic exploration (evaluation, the replay layout probe) the student plays
    and its own action is the label.
    """

    def __init__(self, learner: ExpertIterationLearner) -> None:
        """The student and the teacher of ``learner``."""
        super().__init__()
        self.learner = learner
        self.student = learner.student  # a submodule: the collector finds the policy's device
        self.in_keys = list(learner.student.in_keys)
        self.out_keys = [LOGITS, ACTION, TARGET]

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        """Write the played action and the label ``(agents, "target")`` per robot."""
        td = self.student(td)
        student = td.get(ACTION)
        n_actions = td.get(LOGITS).shape[-1]
        if exploration_type() != ExplorationType.RANDOM:
            td.set(TARGET, F.one_hot(student, n_actions).to(torch.float32))
            return td
        teacher, target = self.learner.teach()
        teacher = torch.as_tensor(teacher, device=student.device)
        target = torch.as_tensor(target, dtype=torch.float32, device=student.device)
        mixed = torch.rand(student.shape[0], device=student.device) < self.learner.beta
        td.set(ACTION, torch.where(mixed[:, None], teacher, student))
        td.set(TARGET, target)
        return td


def planner_labels(
    chosen: np.ndarray,
    candidates: np.ndarray,
    returns: np.ndarray,
    scale: float,
    weight: float,
    n_actions: int,
) -> np.ndarray:
    """Per robot a distribution over its actions from the planner's decision (module docstring).

    Args:
        chosen: ``[B, m]`` the planner's joint action.
        candidates: ``[C, B, m]`` the candidate joint actions it compared.
        returns: ``[C, B]`` their mean rollout returns (``-inf``: not rolled out: a duplicate,
            or a copy whose candidates all agree).
        scale: Multiplies the returns in the softmax (an inverse temperature).
        weight: Weight of the candidates' distribution; ``1 - weight`` goes to ``chosen``.
        n_actions: ``A``, actions per robot.

    Returns:
        ``[B, m, A]`` float32 rows that sum to 1.
    """
    hard = np.eye(n_actions, dtype=np.float32)[chosen]  # [B, m, A]
    if weight == 0 or not np.isfinite(returns).any():
        return hard
    rolled = np.isfinite(returns)  # [C, B]
    planned = rolled.any(axis=0)  # [B]: copies whose candidates were compared
    best = np.where(planned, np.where(rolled, returns, -np.inf).max(axis=0), 0.0)
    w = np.where(rolled, np.exp(scale * (np.where(rolled, returns, 0.0) - best)), 0.0)
    w = w / np.maximum(w.sum(axis=0), 1e-30)  # [C, B]
    one_hot = np.eye(n_actions, dtype=np.float32)[candidates]  # [C, B, m, A]
    soft = np.einsum("cb,cbma->bma", w.astype(np.float32), one_hot)
    mixed = (1 - weight) * hard + weight * soft
    return np.where(planned[:, None, None], mixed, hard).astype(np.float32)


class ExpertIterationLearner(SetNetworkOption, ReplayLearner):
    """Expert iteration: a planner's labels on the student's own states (module docstring).

    Attributes:
        teacher: The ``rollout`` planner that labels.
        student: The student's greedy policy (logits and action).
        beta: The current probability that a copy plays the teacher's action.
        labelled: Copy-ticks the planner has labelled (the base's own labels aside).
        label_s: Seconds the planner spent labelling them.
    """

    label: ClassVar[str] = "ExIt"
    # the teacher reads the core env the collector steps: collection stays in the process
    collection_on_workers: ClassVar[bool] = False
    memory_advice: ClassVar[str] = ADVICE
    replay_loss_keys_only: ClassVar[bool] = True  # process_batch keeps the inputs and the label
    replay_state_bytes: ClassVar[int] = 0  # no global state stored

    @classmethod
    def fits_any_team(cls, settings: Mapping[str, Any]) -> bool:
        """With the set network: the student reads robot, slot and type tokens only."""
        return settings.get("network") == "set"

    @classmethod
    def base_run(cls, settings: Mapping[str, Any]) -> Path | None:
        """The run dir the teacher's base names, or None for a rule (the planner's reading)."""
        return RolloutPlanner.base_run(settings)

    @classmethod
    def network_weights(
        cls, env: AuctionEnv, partition: Partition | None, settings: dict[str, Any]
    ) -> int:
        """The student's weights (set network, or the per-robot MLP with its robot id)."""
        if settings["network"] == "set":
            return cls.check_set_network(env.n_task_types, env.system.name, settings)
        n_in, _ = feature_sizes(env, settings)
        return mlp_weights(n_in, env.n_actions, int(settings["depth"]), int(settings["hidden"]))

    @classmethod
    def check_settings(cls, settings: Mapping[str, Any], team: TrainingTeam) -> None:
        """Refuse a DAgger schedule that rises, or labels with no teacher choice.

        Raises:
            ConfigError: naming the settings.
        """
        super().check_settings(settings, team)
        check_decay(settings, "beta_start", "beta_end", "the teacher's share")
        if settings["horizon"] == 0:
            raise ConfigError(
                "learner.horizon: 0 makes the teacher its base policy; give the planner at least "
                "1 tick to roll out"
            )

    def __init__(
        self,
        *,
        samples: Annotated[int, Range(1)],
        horizon: Annotated[int, Range(0)],
        candidates: Annotated[tuple[str, ...], Choices(*CANDIDATES)],
        base: str,
        margin: Annotated[float, Range(0)],
        gamma: Annotated[float, Range(0, 1, low_open=True)],
        neighbours: Annotated[tuple[str, ...], Choices(*NEIGHBOURS)],
        beta_start: Annotated[float, Range(0, 1)],
        beta_end: Annotated[float, Range(0, 1)],
        beta_decay_frames: Annotated[int, Range(1)],
        soft_targets: Annotated[float, Range(0, 1)],
        decode: Annotated[str, Choices(*DECODERS)],
        prior: Annotated[str, Choices(*PRIORS)],
        imitate_base_frames: Annotated[int, Range(0)],
        buffer_size: Annotated[int, Range(1)],
        batch_size: Annotated[int, Range(1)],
        collect_ticks: Annotated[int, Range(1)],
        updates_per_collect: Annotated[int, Range(1)],
        warmup_frames: Annotated[int, Range(0)],
        base_policy: Learner | None = None,
        **settings: Any,
    ) -> None:
        """Build the student, its loss and optimiser, and the teacher.

        Args:
            samples: The teacher's sampled futures per candidate.
            horizon: The teacher's rollout ticks (at least 1).
            candidates: The teacher's candidate rules (``rollout.CANDIDATES``).
            base: The teacher's base: a rule of ``candidates``' names or a run dir.
            margin: The teacher's switching margin (``rollout``'s ``margin``).
            gamma: The teacher's discount per rollout tick (1: the plain sum of rewards).
            neighbours: The teacher's local candidates around its base's action.
            beta_start: Probability that a copy plays the teacher's action, at the start.
            beta_end: That probability after ``beta_decay_frames`` collected frames.
            beta_decay_frames: Frames of the linear decay of ``beta``.
            soft_targets: Weight of the candidates' distribution in the labels (0: the chosen
                joint action only).
            decode: How the student's scores become a joint action: ``argmax`` (each robot's
                best) or ``match`` (no two bids for one slot, :func:`match_bids`).
            prior: The action whose logit gets the ``auction_prior`` bonus: ``greedy`` (the plain
                auction's bid) or ``base`` (the teacher's base policy's action: the untrained
                student plays its base, and learns where the planner departs from it).
            imitate_base_frames: Collected frames labelled by the teacher's base alone, before
                the planner labels (cheap labels: the student first learns the base).
            buffer_size: Labelled transitions kept (the aggregated data set).
            batch_size: Transitions per gradient step.
            collect_ticks: Ticks per collected batch (frames = ticks x copies).
            updates_per_collect: Gradient steps after each collected batch.
            warmup_frames: Frames labelled before the first gradient step.
            base_policy: The trained learner of the run dir ``base`` names (the runner's).
            **settings: Env, generator, partition, the set network's and
                :class:`~mrta_rl.learners.neural.torch_learner.TorchLearner`'s settings
                (``reward_scale`` is the inverse temperature of the soft labels' softmax over
                mean rollout returns).
        """
        self.rule = GreedyPrior()  # the view writes its action as ("agents", "prior_action")
        self.base_policy = base_policy
        self.labelled, self.label_s = 0, 0.0
        self._decisions: dict[int, list] = {}  # copies -> [ticks, seconds] of the student's
        self._last_copies = 0
        super().__init__(gamma=gamma, **settings)
        self.teacher = self._teacher()
        self.mix = TeacherMix(self)

    def _teacher(self) -> RolloutPlanner:
        """The planner on the current team, drawing from the learner's generator."""
        hp = self.hp
        return RolloutPlanner(
            env=self.env,
            rng=self.rng,
            partition=self.partition,
            samples=hp["samples"],
            horizon=hp["horizon"],
            candidates=hp["candidates"],
            base=hp["base"],
            gamma=hp["gamma"],
            margin=hp["margin"],
            neighbours=hp["neighbours"],
            base_policy=self.base_policy,
        )

    def _build(self) -> None:
        hp = self.hp
        if hp["network"] == "set":
            logits: nn.Module = self._set_network()
            keys = [*SET_KEYS, MASK, (GROUP, PRIOR_KEY)]
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
            keys = [(GROUP, "observation"), (GROUP, PRIOR_KEY)]
        self.networks["student"] = logits
        self.scores = TensorDictModule(logits, in_keys=keys, out_keys=[LOGITS])
        self.student = StudentPolicy(self.scores, hp["decode"])

    def _rebind(self) -> None:
        """A new team: the teacher plans on it, its trained base playing it (not trained on it)."""
        if self.base_policy is not None:
            self.base_policy.play_on(self.env)
        self.teacher = self._teacher()

    # -------------------------------------------------------------- the loop's protocol
    @property
    def prior(self) -> Callable[..., np.ndarray]:
        """The policy whose action gets the logit bonus: the plain auction, or the base."""
        return self.rule if self.hp["prior"] == "greedy" else self._base_prior

    @property
    def inputs(self) -> dict[str, Any]:
        """The encoding, the network and the prior (its action is part of the scores)."""
        return {**super().inputs, "prior": self.hp["prior"]}

    def _base_prior(self, env: AuctionEnv, mask: np.ndarray | None = None) -> np.ndarray:
        """The teacher's base policy's action on ``env`` (a prior for the TorchRL view)."""
        return self.teacher.base_action(env)

    @property
    def policy(self) -> TensorDictModuleBase:
        """The student, without search."""
        return self.student

    @property
    def collection_policy(self) -> TensorDictModuleBase:
        """The teacher's labels and DAgger's mix (:class:`TeacherMix`)."""
        return self.mix

    def encode(self, env: AuctionEnv) -> TensorDictBase:
        """The student's inputs (its prior's action among them), timed as its decision."""
        start = CLOCK()
        view = super().encode(env)
        self._decided(env.batch_size, CLOCK() - start, ticks=0)
        return view

    def act(self, view: TensorDictBase, mask: np.ndarray, *, explore: bool) -> np.ndarray:
        """The student's joint action, without search; timed as its decision (module docstring)."""
        start = CLOCK()
        actions = super().act(view, mask, explore=explore)
        self._decided(mask.shape[0], CLOCK() - start, ticks=1)
        return actions

    def _decided(self, copies: int, seconds: float, ticks: int) -> None:
        spent = self._decisions.setdefault(copies, [0, 0.0])
        spent[0] += ticks
        spent[1] += seconds
        self._last_copies = copies

    def decision_time(self) -> dict[str, float]:
        """The student's time per tick (inputs and action) at the batch size it played last.

        Evaluation plays last, so ``metrics.json`` gets the time per tick of ``eval.batch_size``
        copies; the planner's (``rollout``'s ``decision_time``) is measured the same way.
        """
        ticks, seconds = self._decisions.get(self._last_copies, (0, 0.0))
        if not ticks:
            return {}
        return {
            "ms_per_tick": round(1000 * seconds / ticks, 4),
            "total_s": round(seconds, 4),
            "ticks": ticks,
            "copies": self._last_copies,
        }

    def teach(self) -> tuple[np.ndarray, np.ndarray]:
        """The teacher's joint action and the labels at the training env's current state.

        Returns:
            ``([B, m]`` int64 joint action, ``[B, m, A]`` float32 labels).
        """
        env = self.env
        start = CLOCK()
        if self.frames_collected < self.hp["imitate_base_frames"]:  # the base alone: no plan
            chosen = self.teacher.base_action(env)
            return chosen, np.eye(self.n_actions, dtype=np.float32)[chosen]
        view = self.teacher.encode(env)
        chosen = self.teacher.act(view, env.action_mask, explore=False)
        labels = planner_labels(
            chosen,
            view[1],
            self.teacher.candidate_returns,
            self.hp["reward_scale"],
            self.hp["soft_targets"],
            self.n_actions,
        )
        self.label_s += CLOCK() - start
        self.labelled += env.batch_size
        return chosen, labels

    @property
    def beta(self) -> float:
        """The probability that a copy plays the teacher's action now (DAgger's schedule)."""
        hp = self.hp
        return linear_decay(
            hp["beta_start"], hp["beta_end"], self.frames_collected, hp["beta_decay_frames"]
        )

    def process_batch(self, data: TensorDictBase) -> TensorDictBase:
        """Collector batch -> labelled states (the student's inputs, mask and label), flattened."""
        keys = [*self.scores.in_keys, MASK, TARGET]
        return data.select(*dict.fromkeys(keys)).to(self.device).reshape(-1)

    def loss(self, batch: TensorDictBase) -> tuple[torch.Tensor, dict[str, float]]:
        """Cross-entropy per robot against the labels, over the robots with a choice."""
        logits = self.scores(batch).get(LOGITS)  # [N, m, A]
        target = batch.get(TARGET)
        deciding = batch.get(MASK)[..., 1:].any(-1)  # a valid bid: the robot has a choice
        nll = -(target * F.log_softmax(logits, -1)).sum(-1)  # [N, m]
        n = deciding.sum().clamp(min=1)
        loss = (nll * deciding).sum() / n
        agree = (logits.argmax(-1) == target.argmax(-1)) & deciding
        info = {
            "train/loss_imitation": float(loss.detach()),
            "train/agreement": float(agree.sum() / n),
            "train/beta": self.beta,
        }
        if self.label_s > 0:
            info["train/labels_per_s"] = self.labelled / self.label_s
        return loss, info

    def train_info(self) -> dict[str, float]:
        """The planner's labels and its labelling rate (copy-ticks labelled per second)."""
        rate = self.labelled / self.label_s if self.label_s > 0 else 0.0
        return {"labels": self.labelled, "labels_per_s": round(rate, 1)}

    def checkpoint_state(self, directory: Path) -> dict[str, Any]:
        """Counters of the base and the planner's labels (its rate over the whole run)."""
        return {**super().checkpoint_state(directory), "labels": [self.labelled, self.label_s]}

    def restore_state(self, state: dict[str, Any], directory: Path) -> None:
        """Restore :meth:`checkpoint_state`.

        Raises:
            ValueError: if the labels are not a count and its seconds.
        """
        super().restore_state(state, directory)
        labelled, seconds = state["labels"]
        if not isinstance(labelled, int) or labelled < 0 or not 0 <= seconds < math.inf:
            raise ValueError(f"labels: a count and its seconds, got {state['labels']!r}")
        self.labelled, self.label_s = labelled, float(seconds)
