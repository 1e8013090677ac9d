"""CQL (paper §3, §6): one Q-table over the whole system's state and all robots' joint action.

The analytic table is astronomically large for System-II (paper Table 9; here ``|S| 4^10``,
beyond 64 bits), so the table stores only the states met at decisions and, per state, only its
valid conflict-free joint actions (``qtable.JointQStorage``).
"""

from __future__ import annotations

from typing import Annotated, Any, ClassVar

import numpy as np

from mrta_rl.config import Choices
from mrta_rl.envs import AuctionEnv, StepResult
from mrta_rl.envs.encodings import FEATURES, group_state_count
from mrta_rl.learners.base import MemoryQuery
from mrta_rl.learners.memory import ResourceEstimate, group_table_estimate
from mrta_rl.learners.tabular.subg_cql import GroupQLearner
from mrta_rl.metrics.learning_space import centralized_dimension
from mrta_rl.partition import Partition


class CQLLearner(GroupQLearner):
    """Centralized Q-learning (paper §6, after its ref. [28]) over the whole team.

    One group of all robots: Q over the whole-system group state and the joint action of all
    robots, learned from the team reward (spec step 8).

    Args:
        env: The env (full task sets).
        rng: Exploration randomness.
        partition: Unused.
        prune_conflicts: Keep only conflict-free joint actions (``joint_actions``).
        prior: Tie-break joint action of untried states (``priors.PRIORS``, docs/learners.md).
        min_visits: Updates an entry needs before it competes with the prior.
        prior_order: Which idle robot the spread priors ask first (default ``index``).
        features: The whole-system state's encoding (``encodings.FEATURES``): ``paper`` or
            ``time_to_free`` (robot state 3 = busy, free soon; queued H and L levels; coarse,
            docs/learners.md).
        **hyperparameters: See :class:`~mrta_rl.learners.tabular.base.TabularLearner`.
    """

    label: ClassVar[str] = "CQL"

    @classmethod
    def estimate_memory(cls, query: MemoryQuery) -> ResourceEstimate:
        """One joint Q-table of the whole-system states met (:mod:`~.memory`).

        Raises:
            Unfit: if the team's joint actions or states pass the int64 codes.
        """
        env, partition, settings, decisions, copies = query
        features = settings["features"]

        def states(robots: list[int]) -> int:
            return group_state_count(env, robots, features)

        groups = {"team": list(range(env.n_robots))}
        return group_table_estimate(cls.__name__, env, groups, states, settings, decisions)

    @classmethod
    def learning_space_dimension(
        cls, env: AuctionEnv, partition: Partition | None, settings: dict[str, Any]
    ) -> int:
        """Eqs. (13), (15), (16): ``|S| prod_i |A_i|`` over the whole-system group view."""
        robots = list(range(env.n_robots))
        states = group_state_count(env, robots, settings.get("features", "paper"))
        return centralized_dimension(states, [env.n_actions] * env.n_robots)

    def __init__(self, *, features: Annotated[str, Choices(*FEATURES)], **hyperparameters) -> None:
        super().__init__(**hyperparameters)
        self._set_groups(["team"], [list(range(self.env.n_robots))], features)

    def _group_rewards(self, result: StepResult) -> tuple[np.ndarray, np.ndarray]:
        # spec step 8: the team reward
        return np.asarray(result.team_reward, np.float64)[:, None], np.zeros((1, 1), np.int64)
