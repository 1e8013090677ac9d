"""subG-CQL (paper §4, §6): one centralized Q-table per sub-group, over its joint action.

:class:`GroupQLearner` is centralized Q-learning (eq. 3) for any list of robot groups: each
group has a :class:`~mrta_rl.learners.tabular.common.JointQTable` over its group state
(``GroupView``: slots restricted to the group's task types, each robot's busy / idle / low-battery
state, recency of H arrivals over the group's types) and the joint action of its robots, and
learns from the group's reward. :class:`SubGCQLLearner` takes the groups of the subG partition;
``mrta_rl.learners.tabular.cql.CQLLearner`` takes one group of all robots.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from mrta_rl.envs import AuctionEnv, StepResult
from mrta_rl.envs.observations import group_state_index, recency_level
from mrta_rl.learners.tabular.common import (
    JointQTable,
    PendingTransitions,
    TabularLearner,
    deconflict,
    spread_order,
)
from mrta_rl.metrics.learning_space import learning_space_dimension


@dataclass
class GroupObservation:
    """A decision point as the group learners see it (built by :meth:`GroupQLearner.encode`).

    Attributes:
        states: Per group, ``[B]`` group state indices.
        mask: ``[B, m, K + 1]`` valid actions (copied from the env).
        slot_weight: ``[B, m, K]`` willingness of each robot for each slot's type (conflicts).
        prior_masks: Per group, ``[B, m, K + 1]`` the bids the tie-break prior may use.
        rows: Per group, ``[B]`` table rows (-1: no decision), filled by ``act``.
        entries: Per group, ``[B]`` chosen table entries (-1: none), filled by ``act``.
        actions: The ``[B, m]`` actions ``act`` returned, to check the cache in ``update``.
    """

    states: list[np.ndarray]
    mask: np.ndarray
    slot_weight: np.ndarray
    prior_masks: list[np.ndarray]
    rows: list[np.ndarray | None] = field(default_factory=list)
    entries: list[np.ndarray | None] = field(default_factory=list)
    actions: np.ndarray | None = None


class GroupQLearner(TabularLearner):
    """Centralized Q-learning per robot group (paper eq. 3 over joint actions).

    Subclasses set the groups in ``__init__`` via :meth:`_set_groups` and define
    :meth:`_group_rewards` and :attr:`space_name`.

    Args:
        prune_conflicts: Keep only conflict-free joint actions (see ``common``).
        prior: Tie-break joint action of untried states (``common.PRIORS``).
        prior_order: Which idle robot the spread priors ask first (``common.PRIOR_ORDERS``).
        min_visits: Updates an entry needs before it competes with the prior.
        **kwargs: Env, generator, partition and the hyperparameters of
            :class:`~mrta_rl.learners.tabular.common.TabularLearner`.
    """

    space_name: ClassVar[str]
    default_prior: ClassVar[str] = "spread"
    default_prior_order: ClassVar[str] = "index"

    def __init__(
        self,
        *,
        prune_conflicts: bool = True,
        prior: str | None = None,
        prior_order: str | None = None,
        min_visits: int = 0,
        **hyperparameters,
    ) -> None:
        super().__init__(**hyperparameters)
        self.prune_conflicts, self.min_visits = prune_conflicts, min_visits
        self.prior = self.default_prior if prior is None else prior
        self.prior_order = self.default_prior_order if prior_order is None else prior_order

    def _set_groups(self, names: list[str], groups: list[list[int]]) -> None:
        self.group_names = names
        self.groups = [np.asarray(g, np.int64) for g in groups]
        active = self.env.active_tasks
        self.tables = [
            JointQTable(
                len(g),
                self.n_actions,
                self.prune_conflicts,
                self.prior,
                self.min_visits,
                order=spread_order(active[np.asarray(g, np.int64)], self.prior_order),
            )
            for g in groups
        ]
        self._group_types = [active[np.asarray(g, np.int64)].any(axis=0) for g in groups]  # T_g
        self._pending: list[PendingTransitions] = []

    def _group_rewards(self, result: StepResult) -> np.ndarray:
        """``[B, G]`` reward of each group."""
        raise NotImplementedError

    def _decides(self, mask: np.ndarray, robots: np.ndarray) -> np.ndarray:
        """``[B]`` True where the group learns at this state: it has a choice, or always."""
        choice = mask[:, robots, 1:].any(axis=(1, 2))  # some robot of the group may bid
        return choice if self.decisions_only else np.ones(len(mask), bool)

    def encode(self, env: AuctionEnv) -> GroupObservation:
        """Group state of every group, the mask and the slot willingness (copies)."""
        states = [group_state_index(env, g) for g in self.groups]
        mask = env.action_mask.copy()
        if self.prior == "spread_wait":
            # the prior holds L slots while the group's recency level is 0 (an H task of T_g
            # arrived within 3 ticks; it is in the group state), as the rule spread_wait3
            low = (env.slot_high == 0)[:, None, :]  # [B, 1, K]
            prior_masks = []
            for types in self._group_types:
                hold = (recency_level(env, types) == 0)[:, None, None]  # [B, 1, 1]
                prior = mask.copy()
                prior[:, :, 1:] &= ~(low & hold)
                prior_masks.append(prior)
        else:
            prior_masks = [mask] * len(self.groups)
        return GroupObservation(states, mask, self._slot_weight(env), prior_masks)

    def act(self, view: GroupObservation, mask: np.ndarray, *, explore: bool) -> np.ndarray:
        """Epsilon-greedy joint action per group over its valid joint actions.

        Args:
            view: Output of :meth:`encode`.
            mask: ``[B, m, K + 1]`` valid actions.
            explore: Use epsilon (else greedy in Q, ties to the plain auction).

        Returns:
            ``[B, m]`` valid actions.
        """
        batch = len(mask)
        actions = np.zeros((batch, self.n_robots), np.int64)
        epsilon = self.epsilon if explore else 0.0
        view.rows, view.entries = [], []
        for g, (robots, table) in enumerate(zip(self.groups, self.tables, strict=True)):
            rows = np.full(batch, -1, np.int64)
            entries = np.full(batch, -1, np.int64)
            decide = np.flatnonzero(self._decides(mask, robots))
            if len(decide):
                rows[decide] = table.rows(
                    view.states[g][decide],
                    mask[decide][:, robots],
                    view.slot_weight[decide][:, robots],
                    view.prior_masks[g][decide][:, robots],
                )
                chosen = table.best_entries(rows[decide])
                if epsilon > 0.0:
                    explore_now = self.rng.random(len(decide)) < epsilon
                    if explore_now.any():
                        chosen[explore_now] = table.random_entries(
                            rows[decide[explore_now]], self.rng.random(int(explore_now.sum()))
                        )
                entries[decide] = chosen
                actions[np.ix_(decide, robots)] = table.actions_of(chosen)
            view.rows.append(rows)
            view.entries.append(entries)
        view.actions = actions.copy()
        return actions

    def _chosen_entries(
        self, view: GroupObservation, actions: np.ndarray, g: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """``[B]`` rows and entries of the actions taken in ``view`` (-1 where no decision)."""
        if view.actions is not None and view.rows and np.array_equal(view.actions, actions):
            return view.rows[g], view.entries[g]
        robots, table = self.groups[g], self.tables[g]
        rows = np.full(len(actions), -1, np.int64)
        entries = np.full(len(actions), -1, np.int64)
        decide = np.flatnonzero(self._decides(view.mask, robots))
        if len(decide):
            weight = view.slot_weight[decide][:, robots]
            prior = view.prior_masks[g][decide][:, robots]
            rows[decide] = table.rows(
                view.states[g][decide], view.mask[decide][:, robots], weight, prior
            )
            taken = actions[decide][:, robots]
            if table.prune_conflicts:
                taken = deconflict(taken, weight)  # same outcome as the bids taken (spec step 5)
            entries[decide] = table.entries_of(rows[decide], table.joint.encode(taken))
        return rows, entries

    def update(
        self,
        view: GroupObservation,
        actions: np.ndarray,
        result: StepResult,
        next_view: GroupObservation,
        next_mask: np.ndarray,
    ) -> dict[str, float]:
        """Eq. (3) per group, on decision points (see ``common``), for all copies.

        Args:
            view: View before acting.
            actions: ``[B, m]`` actions taken.
            result: Rewards and done flags.
            next_view: View after the step.
            next_mask: ``[B, m, K + 1]`` valid actions after the step.

        Returns:
            ``learner/<group>/td_error``: mean absolute TD error of the updates of this tick.
        """
        batch = len(actions)
        if not self._pending or self._pending[0].entry.shape[0] != batch:
            self._pending = [PendingTransitions((batch,)) for _ in self.groups]
        rewards = self._group_rewards(result)  # [B, G]
        done = np.asarray(result.done, bool)
        logs: dict[str, float] = {}
        for g, (robots, table, pending) in enumerate(
            zip(self.groups, self.tables, self._pending, strict=True)
        ):
            _, entries = self._chosen_entries(view, actions, g)
            pending.start(entries >= 0, entries)
            pending.accumulate(rewards[:, g], self.gamma)
            pending.drop(done)  # truncation: no next state to bootstrap from (spec: horizon)
            closing = self._decides(next_mask, robots) & ~done
            (pos,), closed, ret, discount = pending.close(closing)
            if len(pos) == 0:
                continue
            next_rows = table.rows(
                next_view.states[g][pos],
                next_mask[pos][:, robots],
                next_view.slot_weight[pos][:, robots],
                next_view.prior_masks[g][pos][:, robots],
            )
            targets = ret + discount * table.max_q(next_rows)  # eq. (3): r + gamma max_a' Q(s', a')
            logs[f"learner/{self.group_names[g]}/td_error"] = self._update(
                table.q, table.visits, closed, targets
            )
        return logs

    def learning_space(self) -> dict[str, int]:
        """Analytic dimension (eqs. 13-16) and the table entries updated at least once."""
        analytic = learning_space_dimension(self.space_name, self.env, self.partition)
        return {"analytic": analytic, "visited": sum(t.n_visited() for t in self.tables)}

    def _table_arrays(self) -> dict[str, np.ndarray]:
        arrays: dict[str, np.ndarray] = {}
        for name, table in zip(self.group_names, self.tables, strict=True):
            arrays.update(table.to_arrays(f"{name}."))
        return arrays

    def _load_table_arrays(self, arrays: dict[str, np.ndarray]) -> None:
        for name, table in zip(self.group_names, self.tables, strict=True):
            table.from_arrays(arrays, f"{name}.")


class SubGCQLLearner(GroupQLearner):
    """subG-CQL (paper §4 and §6): centralized Q-learning inside each subG sub-group.

    The runner builds the env with the partition's ``Lambda_i``, so robots bid only for their
    kept task types. Each sub-group ``G_g`` learns Q over its group state and the joint action of
    its robots from the sub-group reward, the sum of its robots' individual rewards (spec step 8).

    Args:
        env: The env built with the partition's active tasks.
        rng: Exploration randomness.
        partition: The subG partition (required).
        prune_conflicts: Keep only conflict-free joint actions (see ``common``).
        prior: Tie-break joint action of untried states (``common.PRIORS``, docs/learners.md).
        min_visits: Updates an entry needs before it competes with the prior (``JointQTable``).
        prior_order: Which idle robot the spread priors ask first (default ``fewest_types``).
        **hyperparameters: See :class:`~mrta_rl.learners.tabular.common.TabularLearner`.
    """

    requires_partition: ClassVar[bool] = True
    space_name: ClassVar[str] = "subg_cql"
    default_prior: ClassVar[str] = "spread_wait"
    # a sub-group keeps its versatile robots free for the types only they can do (docs/learners.md)
    default_prior_order: ClassVar[str] = "fewest_types"

    def __init__(self, **hyperparameters) -> None:
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
        )

    def _group_rewards(self, result: StepResult) -> np.ndarray:
        # spec step 8: a sub-group's reward is the sum of its robots' individual rewards
        return np.stack([result.robot_reward[:, g].sum(axis=1) for g in self.groups], axis=1)
