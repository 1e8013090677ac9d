"""DQL (paper §3, §6): independent Q-learners, each robot over its local view and its own action.

:class:`RobotQLearner` is the per-robot machinery (eq. 3 for each robot, its own reward and
epsilon-greedy over its own valid actions), shared with semi-CQL, which only changes the state
each robot sees. :class:`DQLLearner` gives robot ``i`` its local view (``LocalView``: idle flag,
the slots it may bid for, battery level, recency of H arrivals of its types), stored densely.
The per-tick work runs in the compiled loops of :mod:`~mrta_rl.learners.tabular.robot_kernels`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from mrta_rl.envs import AuctionEnv, StepResult
from mrta_rl.learners.tabular import robot_kernels as kernels
from mrta_rl.learners.tabular.base import TabularLearner
from mrta_rl.learners.tabular.encoding import LocalEncoder
from mrta_rl.metrics.learning_space import learning_space_dimension


@dataclass
class RobotObservation:
    """A decision point as the per-robot learners see it.

    Attributes:
        states: ``[B, m]`` (local views) or ``[B]`` (whole-system state) state indices.
        mask: ``[B, m, K + 1]`` valid actions (a copy).
    """

    states: np.ndarray
    mask: np.ndarray


class RobotQLearner(TabularLearner):
    """Q-learning per robot (eq. 3) on its own action and individual reward (spec step 8).

    Subclasses map a view to ``[B, m]`` flat offsets ``base`` with ``Q_i(s, a) = q[base + a]``
    (:meth:`_bases`) and own the flat arrays :attr:`q` and :attr:`visits`.
    """

    space_name: ClassVar[str]
    q: np.ndarray
    visits: np.ndarray

    _pending: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def _bases(self, view: RobotObservation) -> np.ndarray:
        """``[B, m]`` flat offset of ``Q_i(s_i, 0)`` for every copy and robot."""
        raise NotImplementedError

    def act(self, view: RobotObservation, mask: np.ndarray, *, explore: bool) -> np.ndarray:
        """Per robot: epsilon-greedy over its valid actions; ties go to the plain auction's bid.

        Args:
            view: Output of :meth:`encode`.
            mask: ``[B, m, K + 1]`` valid actions.
            explore: Use epsilon (else greedy in Q).

        Returns:
            ``[B, m]`` valid actions.
        """
        mask = np.ascontiguousarray(mask, bool)
        epsilon = self.epsilon if explore else 0.0
        bases = self._bases(view)
        actions = np.zeros(mask.shape[:2], np.int64)
        block = self.uniforms.block(2 * actions.size) if epsilon > 0.0 else np.zeros(0)
        used = kernels.act_robots(self.q, bases, mask, epsilon, block, actions)
        if epsilon > 0.0:
            self.uniforms.used(block, used)
        return actions

    def update(
        self,
        view: RobotObservation,
        actions: np.ndarray,
        result: StepResult,
        next_view: RobotObservation,
        next_mask: np.ndarray,
    ) -> dict[str, float]:
        """Eq. (3) for every robot on its own decision points (docs/learners.md), all copies.

        Args:
            view: View before acting.
            actions: ``[B, m]`` actions taken.
            result: Rewards (individual) and done flags.
            next_view: View after the step.
            next_mask: ``[B, m, K + 1]`` valid actions after the step.

        Returns:
            ``learner/td_error``: mean absolute TD error of the updates of this tick.
        """
        shape = actions.shape
        if self._pending is None or self._pending[0].shape != shape:
            self._pending = (np.full(shape, -1, np.int64), np.zeros(shape), np.ones(shape))
        next_mask = np.ascontiguousarray(next_mask, bool)
        closing = np.empty(shape, bool)
        count = kernels.open_transitions(
            self._bases(view), np.asarray(actions, np.int64), view.mask, next_mask,
            np.asarray(result.robot_reward, np.float64), np.asarray(result.done, bool),
            *self._pending, self.decisions_only, self.gamma, closing,
        )  # fmt: skip
        if count == 0:
            return {}
        td_sum = kernels.close_transitions(
            self.q, self.visits, self._bases(next_view), next_mask, closing, *self._pending,
            self.alpha, self.alpha_power, self.alpha_min,
        )  # fmt: skip
        return {"learner/td_error": td_sum / count} if count else {}

    def learning_space(self) -> dict[str, int]:
        """Analytic dimension (eq. 11) and the table entries updated at least once."""
        analytic = learning_space_dimension(self.space_name, self.env, self.partition)
        return {"analytic": analytic, "visited": int(np.count_nonzero(self.visits))}


class DQLLearner(RobotQLearner):
    """Decentralized Q-learning (paper §6, independent learners after its ref. [32]).

    Robot ``i`` learns ``Q_i(s_i, a_i)`` over its local view ``s_i`` and its own action, from its
    individual reward, ignoring its teammates. Tables are dense: ``[m, max_i |S_i|, K + 1]``.

    Args:
        env: The env (full task sets).
        rng: Exploration randomness.
        partition: Unused.
        **hyperparameters: See :class:`~mrta_rl.learners.tabular.base.TabularLearner`.
    """

    space_name: ClassVar[str] = "dql"

    def __init__(self, **hyperparameters) -> None:
        super().__init__(**hyperparameters)
        self.encoder = LocalEncoder(self.env)
        self.state_counts = self.encoder.counts  # |S_i|
        self._stride = max(self.state_counts)
        size = self.n_robots * self._stride * self.n_actions
        self.q = np.zeros(size)  # Q_i(s, a) at (i * stride + s) * (K + 1) + a
        self.visits = np.zeros(size, np.int64)
        self._robot_base = np.arange(self.n_robots) * self._stride

    def encode(self, env: AuctionEnv) -> RobotObservation:
        """``[B, m]`` local state index of every robot, and the mask."""
        return RobotObservation(self.encoder.index(env), env.action_mask.copy())

    def _bases(self, view: RobotObservation) -> np.ndarray:
        return (self._robot_base + view.states) * self.n_actions

    def _table_arrays(self) -> dict[str, np.ndarray]:
        shape = (self.n_robots, self._stride, self.n_actions)
        return {"q": self.q.reshape(shape), "visits": self.visits.reshape(shape)}

    def _load_table_arrays(self, arrays: dict[str, np.ndarray]) -> None:
        if arrays["q"].size != self.q.size:
            raise ValueError(
                f"saved table has shape {arrays['q'].shape}, this env needs {self.q.size} values"
            )
        self.q[:] = arrays["q"].ravel()
        self.visits[:] = arrays["visits"].ravel()
