"""subG-CQL (paper §4, §6): one centralized Q-table per sub-group, over its joint action.

:class:`GroupQLearner` is centralized Q-learning (eq. 3) for any list of robot groups: each
group has a Q table (:class:`~mrta_rl.learners.tabular.qtable.JointQStorage`) over its group state
(``GroupView``: slots restricted to the group's task types, each robot's busy / idle / low-battery
state, recency of H arrivals over the group's types) and the joint action of its robots, and
learns from the group's reward. :class:`SubGCQLLearner` takes the groups of the subG partition;
``mrta_rl.learners.tabular.cql.CQLLearner`` takes one group of all robots. The per-tick work runs
in the compiled loops of :mod:`~mrta_rl.learners.tabular.group_kernels`.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Annotated, Any, ClassVar

import numpy as np

from mrta_rl.config import Choices, Range
from mrta_rl.envs import AuctionEnv, StepResult
from mrta_rl.envs.encodings import FEATURES
from mrta_rl.learners.base import MemoryQuery
from mrta_rl.learners.memory import ResourceEstimate, group_table_estimate, robot_groups
from mrta_rl.learners.tabular import group_kernels as kernels
from mrta_rl.learners.tabular.base import NO_UNIFORMS, TabularLearner
from mrta_rl.learners.tabular.encoding import (
    GROUP_STATES,
    SubGroupEncoder,
    env_arrays,
    subgroup_state_count,
)
from mrta_rl.learners.tabular.joint_actions import JointActions, max_valid_joint_actions
from mrta_rl.learners.tabular.qtable import (
    ROW_GROUP,
    ROW_LENGTH,
    TABLE_KEYS,
    JointQStorage,
    TableGrowthError,
)
from mrta_rl.metrics.learning_space import subgroup_dimension
from mrta_rl.partition import Partition
from mrta_rl.priors import PRIOR_CODES, PRIOR_ORDERS, PRIORS, spread_order

# what each sub-group's eq. (3) learns from (docs/learners.md, "Credit"): ``group``, the sum of
# its robots' rewards (spec step 8, the paper's); ``team``, the team reward of the tick
SUBG_REWARDS = ("group", "team")


@dataclass
class GroupObservation:
    """A decision point as the group learners see it (built by :meth:`GroupQLearner.encode`).

    Attributes:
        states: ``[G, B]`` group state index of each group and copy.
        level: ``[G, B]`` recency level of each group (0: an H task of ``T_g`` arrived within 3
            ticks; the ``spread_wait`` prior holds L slots then).
        mask: ``[B, m, K + 1]`` valid actions (a copy).
        slot_type: ``[B, K]`` slot types, -1 empty (a copy).
        slot_high: ``[B, K]`` slot priorities (a copy).
        rows: ``[G, B]`` table rows (-1: no decision), filled by ``act``.
        entries: ``[G, B]`` chosen table entries (-1: none), filled by ``act``.
        actions: The ``[B, m]`` actions ``act`` returned, to check the cache in ``update``.
    """

    states: np.ndarray
    level: np.ndarray
    mask: np.ndarray
    slot_type: np.ndarray
    slot_high: np.ndarray
    rows: np.ndarray | None = None
    entries: np.ndarray | None = None
    actions: np.ndarray | None = None


class GroupQLearner(TabularLearner, abstract=True):
    """Centralized Q-learning per robot group (paper eq. 3 over joint actions).

    Subclasses set the groups in ``__init__`` via :meth:`_set_groups` and define
    :meth:`_group_rewards`, and declare their ``label``, ``estimate_memory`` and
    ``learning_space_dimension`` (``learners/base.py``).

    Args:
        prune_conflicts: Keep only conflict-free joint actions (``joint_actions``).
        prior: Tie-break joint action of untried states (``priors.PRIORS``).
        prior_order: Which idle robot the spread priors ask first (``priors.PRIOR_ORDERS``).
        min_visits: Updates an entry needs before it competes with the prior.
        lcb: An entry other than the prior's competes with ``Q - lcb / sqrt(visits)`` (reward
            units; 0: with its Q), in the greedy choice and in eq. (3)'s max.
        n_step: Decision intervals in eq. (3)'s target: the discounted group rewards of the next
            ``n_step`` intervals plus ``gamma^ticks`` times the bootstrap (``target``) of the
            decision state after them (1: the one-step semi-Markov eq. 3; docs/learners.md).
        **kwargs: Env, generator, partition and the hyperparameters of
            :class:`~mrta_rl.learners.tabular.base.TabularLearner`.
    """

    def __init__(
        self,
        *,
        prune_conflicts: bool,
        prior: Annotated[str, Choices(*PRIORS)],
        prior_order: Annotated[str, Choices(*PRIOR_ORDERS)],
        min_visits: Annotated[int, Range(0)],
        lcb: Annotated[float, Range(0)],
        n_step: Annotated[int, Range(1)],
        **hyperparameters,
    ) -> None:
        # types, ranges and choices: the annotations; the values: self.hp
        super().__init__(**hyperparameters)

    def _set_groups(
        self,
        names: list[str],
        groups: list[list[int]],
        features: str,
        state: str = "group",
    ) -> None:
        env = self.env
        self.features, self.state = features, state  # the group state (CQL's: the paper's)
        self.group_names = names
        self.groups = [np.asarray(g, np.int64) for g in groups]
        self.joint = [JointActions(len(g), self.n_actions) for g in groups]  # checks int64 codes
        # checks state, features and that the counts fit int64
        self.encoder = SubGroupEncoder(env, self.groups, state, features)
        self.robots, self.size = self.encoder.robots, self.encoder.size
        self.order = np.zeros_like(self.robots)
        for g, robots in enumerate(self.groups):
            self.order[g, : len(robots)] = spread_order(
                env.active_tasks[robots], self.hp["prior_order"]
            )
        self._prior_code = PRIOR_CODES[self.hp["prior"]]
        self._row_entries = np.array(  # the most entries a row of each group holds
            [
                max_valid_joint_actions(len(g), self.n_actions, self.hp["prune_conflicts"])
                for g in groups
            ],
            np.int64,
        )
        self.storage = JointQStorage(len(groups))
        self._pending: tuple[np.ndarray, ...] | None = None
        self._tick: tuple[np.ndarray, ...] | None = None  # train_tick's arrays, [G, B] each
        self._td_sum, self._td_count = np.zeros(len(groups)), np.zeros(len(groups), np.int64)

    def _group_rewards(self, result: StepResult) -> tuple[np.ndarray, np.ndarray]:
        """``([B, R] rewards, [G, M] columns)``: a group's reward is the sum of its columns."""
        raise NotImplementedError

    def _reserve(self, mask: np.ndarray) -> None:
        """Room for the rows one kernel call may create (at most one per group and copy).

        Args:
            mask: ``[B, m, K + 1]`` valid actions of the state the call meets.
        """
        copies = len(mask)
        if self.hp["prune_conflicts"] or self._row_entries.max() <= 4096:
            entries = copies * self._row_entries  # [G]: each group's largest row per copy
        else:  # without pruning, bound each copy by the product of its valid action counts
            counts = mask.sum(axis=2)  # [B, m]
            entries = np.array([int(counts[:, g].prod(axis=1).sum()) for g in self.groups])
        try:
            self.storage.reserve(len(self.groups) * copies, int(entries.sum()))
        except TableGrowthError as err:
            raise TableGrowthError(f"{self._largest_group(copies, entries)}: {err}") from None

    def _largest_group(self, copies: int, new_entries: np.ndarray) -> str:
        """The group that asks the most of a growth: its name, its rows and the room it asks.

        Args:
            copies: The new rows each group may create this tick (one per copy).
            new_entries: ``[G]`` the entries the new rows of each group may take.
        """
        n_rows = self.storage.n_rows
        group = self.storage.rows[ROW_GROUP, :n_rows]
        held = np.bincount(group, self.storage.rows[ROW_LENGTH, :n_rows], len(self.groups))
        g = int(np.argmax(held + new_entries))
        return (
            f"group {self.group_names[g]} ({len(self.groups[g])} robots) asks the most: "
            f"{int(np.count_nonzero(group == g)):,} rows met ({int(held[g]):,} joint actions) "
            f"and room for {copies:,} new rows of up to {int(self._row_entries[g]):,} joint actions"
        )

    @functools.cached_property
    def _kernel_settings(self) -> tuple:
        """The hyperparameters as a ``group_kernels.Settings`` tuple (all set by ``__init__``)."""
        settings = kernels.Settings(
            decisions_only=self.hp["decisions_only"],
            prior=self._prior_code,
            prune=self.hp["prune_conflicts"],
            min_visits=self.hp["min_visits"],
            lcb=self.hp["lcb"],
            prior_target=self.prior_target,
            gamma=self.hp["gamma"],
            alpha=self.hp["alpha"],
            alpha_power=self.hp["alpha_power"],
            alpha_min=self.hp["alpha_min"],
        )
        return tuple(settings)

    def _kernel_learner(self) -> tuple:
        """The ``group_kernels.Learner`` parts, as the plain tuples the kernels take."""
        s = self.storage  # its arrays are replaced as it grows: read at each call
        return (
            (s.hash, s.rows, s.entries, s.q, s.sizes),  # group_kernels.QTable
            (self.robots, self.size, self.order, self._weight_by_type),  # group_kernels.Groups
            self._kernel_settings,
        )

    @staticmethod
    def _decision(view: GroupObservation, mask: np.ndarray) -> tuple:
        """``view`` with ``mask`` as a ``group_kernels.Decision`` tuple."""
        return view.states, view.level == 0, mask, view.slot_type, view.slot_high

    def encode(self, env: AuctionEnv) -> GroupObservation:
        """Group state and recency level of every group, and copies of the mask and the slots."""
        states, level = self.encoder.index(env)
        return GroupObservation(
            states, level, env.action_mask.copy(), env.slot_type.copy(), env.slot_high.copy()
        )

    def act(self, view: GroupObservation, mask: np.ndarray, *, explore: bool) -> np.ndarray:
        """Epsilon-greedy joint action per group over its valid joint actions.

        Args:
            view: Output of :meth:`encode`.
            mask: ``[B, m, K + 1]`` valid actions.
            explore: Use epsilon (else greedy in Q, ties to the prior).

        Returns:
            ``[B, m]`` valid actions.
        """
        batch = len(mask)
        epsilon = self.epsilon if explore else 0.0
        self._reserve(view.mask)
        view.rows = np.empty((len(self.groups), batch), np.int64)
        view.entries = np.empty((len(self.groups), batch), np.int64)
        actions = np.zeros((batch, self.n_robots), np.int64)
        block = self.uniforms.block(2 * view.states.size) if epsilon > 0.0 else NO_UNIFORMS
        mask = np.ascontiguousarray(mask, bool)
        used = kernels.act_groups(
            self._kernel_learner(),
            self._decision(view, mask),
            (epsilon, block),
            (view.rows, view.entries),
            actions,
        )
        if epsilon > 0.0:
            self.uniforms.used(used)
        view.actions = actions.copy()
        return actions

    def _pending_of(self, batch: int) -> tuple[np.ndarray, ...]:
        """The last ``n_step`` decisions of ``batch`` copies per group (new ones if ``B`` changed).

        The ``pending_*`` arrays of ``group_kernels.update_groups``.
        """
        n_groups = len(self.groups)
        if self._pending is None or self._pending[0].shape[1] != batch:
            ring = (n_groups, batch, self.hp["n_step"])
            self._pending = (
                np.full(ring, -1, np.int64),  # the decisions' entries, oldest first
                np.zeros(ring),  # R = sum_k gamma^k r_k over the interval after each
                np.ones(ring),  # gamma^tau of that interval
                np.zeros((n_groups, batch), np.int64),  # decisions held
                np.zeros((n_groups, batch), bool),  # the newest interval still runs
                np.zeros((n_groups, batch)),  # bootstrap value of the last decision state met
            )
        return self._pending

    def train_tick(self, env: AuctionEnv, result: StepResult | None) -> np.ndarray | None:
        """:meth:`TabularLearner.train_tick` in one call of ``group_kernels.tick_groups``."""
        n_groups, batch = len(self.groups), env.batch_size
        if result is not None and (self._tick is None or self._tick[0].shape[1] != batch):
            raise self._no_last_decision()
        pending = self._pending_of(batch)
        if self._tick is None or self._tick[0].shape[1] != batch:
            # states, level, hold, rows, entries (in: the last decision's, out: this tick's)
            shape = (n_groups, batch)
            self._tick = (
                np.empty(shape, np.int64),
                np.empty(shape, np.int64),
                np.empty(shape, bool),
                np.empty(shape, np.int64),
                np.full(shape, -1, np.int64),
            )
        mask = env.action_mask
        self._reserve(mask)
        if result is not None:
            rewards, columns = self._group_rewards(result)
            done = result.done
        else:  # nothing to learn from at the start of an episode
            rewards, columns = np.zeros((batch, 1)), np.zeros((n_groups, 1), np.int64)
            done = env.done
        epsilon = self.epsilon
        actions = np.zeros((batch, self.n_robots), np.int64)
        block = self.uniforms.block(2 * n_groups * batch) if epsilon > 0.0 else NO_UNIFORMS
        used = kernels.tick_groups(
            self._kernel_learner(),
            (env_arrays(env), mask, self.encoder.tables, self.encoder.offset(env)),
            result is not None,
            (rewards, columns, done),  # group_kernels.Outcome
            pending,
            (epsilon, block),
            self._tick,
            (actions, self._td_sum, self._td_count),
        )
        if used < 0:  # the episode has ended
            self.uniforms.settle()
            return None
        self.uniforms.used(used)
        return actions

    def _chosen_entries(self, view: GroupObservation, actions: np.ndarray) -> np.ndarray:
        """``[G, B]`` entries of the actions taken in ``view`` (-1 where no decision).

        Raises:
            ValueError: if a joint action is not valid in its state.
        """
        if view.actions is not None and np.array_equal(view.actions, actions):
            return view.entries
        self._reserve(view.mask)
        rows = np.empty_like(view.states)
        entries = np.empty_like(view.states)
        missing = kernels.entries_for_actions(
            self._kernel_learner(),
            self._decision(view, view.mask),
            np.asarray(actions, np.int64),
            (rows, entries),
        )
        if missing >= 0:
            raise ValueError(
                f"joint action not valid in its state in copy {missing} (masked, or "
                "conflicting bids)"
            )
        return entries

    def update(
        self,
        view: GroupObservation,
        actions: np.ndarray,
        result: StepResult,
        next_view: GroupObservation,
        next_mask: np.ndarray,
    ) -> dict[str, float]:
        """Eq. (3) per group, on decision points (docs/learners.md), for all copies.

        Args:
            view: View before acting.
            actions: ``[B, m]`` actions taken.
            result: Rewards and done flags.
            next_view: View after the step.
            next_mask: ``[B, m, K + 1]`` valid actions after the step.

        Returns:
            ``learner/<group>/td_error``: mean absolute TD error of the updates of this tick.
        """
        n_groups = len(self.groups)
        self._pending_of(len(actions))
        chosen = self._chosen_entries(view, actions)
        self._reserve(next_view.mask)
        td_sum, td_count = np.zeros(n_groups), np.zeros(n_groups, np.int64)
        kernels.update_groups(
            self._kernel_learner(),
            chosen,
            self._decision(next_view, np.ascontiguousarray(next_mask, bool)),
            (*self._group_rewards(result), np.asarray(result.done, bool)),
            self._pending,
            (td_sum, td_count),
        )
        return {
            f"learner/{name}/td_error": float(td_sum[g] / td_count[g])
            for g, name in enumerate(self.group_names)
            if td_count[g]
        }

    def learning_space(self) -> dict[str, int]:
        """Analytic dimension (eqs. 13-16) and the table entries updated at least once."""
        settings = {"features": self.features, "state": self.state}
        analytic = self.learning_space_dimension(self.env, self.partition, settings)
        return {"analytic": analytic, "visited": self.storage.n_visited()}

    def _table_arrays(self) -> dict[str, np.ndarray]:
        # a coarser group state marks its file, so that a table of one state never loads into a
        # learner of another (its state indices would read as other states); ``group`` adds
        # nothing, so the files of before load as they are
        arrays: dict[str, np.ndarray] = (
            {} if self.state == "group" else {f"state.{self.state}": np.zeros(1, np.int64)}
        )
        for g, name in enumerate(self.group_names):
            arrays.update({f"{name}.{k}": v for k, v in self.storage.to_arrays(g).items()})
        return arrays

    def _load_table_arrays(self, arrays: dict[str, np.ndarray]) -> None:
        for name, count in zip(self.group_names, self.encoder.counts, strict=True):
            states = arrays[f"{name}.states"]
            if len(states) and int(states.max()) >= count:
                raise ValueError(
                    f"saved table of {name} has state {int(states.max())}, past the {count} "
                    f"states of state={self.state!r}: saved with another learner.state?"
                )
        self.storage.from_arrays(
            [{k: arrays[f"{name}.{k}"] for k in TABLE_KEYS} for name in self.group_names],
            [joint.count for joint in self.joint],
        )


class SubGCQLLearner(GroupQLearner):
    """subG-CQL (paper §4 and §6): centralized Q-learning inside each subG sub-group.

    The runner builds the env with the partition's ``Lambda_i``, so robots bid only for their
    kept task types. Each sub-group ``G_g`` learns Q over its group state and the joint action of
    its robots from the sub-group reward, the sum of its robots' individual rewards (spec step 8).

    Args:
        env: The env built with the partition's active tasks.
        rng: Exploration randomness.
        partition: The subG partition (required).
        prune_conflicts: Keep only conflict-free joint actions (``joint_actions``).
        prior: Tie-break joint action of untried states (``priors.PRIORS``, docs/learners.md).
        min_visits: Updates an entry needs before it competes with the prior.
        prior_order: Which idle robot the spread priors ask first (default ``fewest_types``).
        reward: What each sub-group learns from (:data:`SUBG_REWARDS`): ``group``, the sum of
            its robots' individual rewards (the paper's); ``team``, the team reward of the tick
            (a sub-group is credited with what its choice does to the others' rewards too).
        features: The group state's encoding (``encodings.FEATURES``): ``paper`` (the
            paper's) or ``time_to_free`` (the default: adds when busy robots become free and the
            queued H and L counts over ``T_g``, coarsely; docs/learners.md).
        state: The group state (``encoding.GROUP_STATES``): ``group``, the paper's
            ``GroupView``; or ``idle`` (the default), each robot's idle flag instead of its three
            states (no battery digit; with ``features=time_to_free`` busy / idle / free soon and
            the queue levels; ``encoding.SubGroupEncoder``). The paper's subG-CQL is
            ``state="group", features="paper"`` (``experiment=paper`` pins it; docs/notebook.md,
            "subG-CQL: larger budgets on the coarse state").
        **hyperparameters: See :class:`~mrta_rl.learners.tabular.base.TabularLearner`.
    """

    requires_partition: ClassVar[bool] = True
    label: ClassVar[str] = "subG-CQL"

    @classmethod
    def estimate_memory(cls, query: MemoryQuery) -> ResourceEstimate:
        """A joint Q-table of the group states met per sub-group (:mod:`~.memory`).

        Raises:
            Unfit: if a sub-group's joint actions or states pass the int64 codes.
        """
        env, partition, settings, decisions, copies = query
        features, state = settings["features"], settings["state"]

        def states(robots: list[int]) -> int:
            return subgroup_state_count(env, robots, state, features)

        groups = robot_groups(env, partition)
        return group_table_estimate(cls.__name__, env, groups, states, settings, decisions)

    @classmethod
    def learning_space_dimension(
        cls, env: AuctionEnv, partition: Partition | None, settings: dict[str, Any]
    ) -> int:
        """``sum_g |S_g| prod_(i in g) |A_i|`` over the sub-groups (§5.2, last paragraph).

        ``settings["state"]`` is the group state (default ``group``, the paper's).

        Raises:
            ValueError: without the partition.
        """
        if partition is None:
            raise ValueError("subg_cql needs the partition")
        features, state = settings.get("features", "paper"), settings.get("state", "group")
        groups = []
        for robots in partition.group_map().values():
            count = subgroup_state_count(env, robots, state, features)
            groups.append((count, [env.n_actions] * len(robots)))
        return subgroup_dimension(groups)

    def __init__(
        self,
        *,
        reward: Annotated[str, Choices(*SUBG_REWARDS)],
        features: Annotated[str, Choices(*FEATURES)],
        state: Annotated[str, Choices(*GROUP_STATES)],
        **hyperparameters,
    ) -> None:
        super().__init__(**hyperparameters)
        env, partition = self.env, self.partition
        assert partition is not None  # checked by Learner.__init__
        expected = partition.active_tasks(env.system)
        if not np.array_equal(env.active_tasks, expected):
            raise ValueError(
                "subG-CQL needs the env built with the partition's active tasks (Lambda_i)"
            )
        group_map = partition.group_map()
        robots = env.system.robots
        self._set_groups(
            list(group_map),
            [[robots.index(r) for r in rs] for rs in group_map.values()],
            features,
            state,
        )
        if reward == "team":  # every group reads the one column of the team reward
            self._reward_columns = np.zeros((len(self.groups), 1), np.int64)
        else:  # the group's robots, -1 padded
            self._reward_columns = np.where(
                np.arange(self.robots.shape[1]) < self.size[:, None], self.robots, -1
            )

    def _group_rewards(self, result: StepResult) -> tuple[np.ndarray, np.ndarray]:
        if self.hp["reward"] == "team":  # spec step 8's team reward, for every sub-group
            return np.asarray(result.team_reward, np.float64)[:, None], self._reward_columns
        # spec step 8: a sub-group's reward is the sum of its robots' individual rewards
        return np.asarray(result.robot_reward, np.float64), self._reward_columns
