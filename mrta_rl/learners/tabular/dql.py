"""DQL (paper §3, §6): independent Q-learners, each robot over its local view and its own action.

:class:`RobotQLearner` is the per-robot machinery (eq. 3 for each robot, its own reward and
epsilon-greedy over its own valid actions), shared with semi-CQL, which only changes the state
each robot sees. :class:`DQLLearner` gives robot ``i`` its local view (``LocalView``: idle flag,
the slots it may bid for, battery level, recency of H arrivals of its types), stored densely.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from mrta_rl.envs import AuctionEnv, StepResult
from mrta_rl.envs.observations import local_state_count, local_state_index
from mrta_rl.learners.tabular.common import (
    PendingTransitions,
    TabularLearner,
    greedy_actions,
    random_valid_actions,
)
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

    _pending: PendingTransitions | None = None

    def _bases(self, view: RobotObservation) -> np.ndarray:
        """``[B, m]`` flat offset of ``Q_i(s_i, 0)`` for every copy and robot."""
        raise NotImplementedError

    def _values(self, bases: np.ndarray) -> np.ndarray:
        return self.q[bases[..., None] + np.arange(self.n_actions)]  # [B, m, K + 1]

    def _decides(self, mask: np.ndarray) -> np.ndarray:
        """``[B, m]`` True where a robot learns: it has a valid bid, or always."""
        return mask[:, :, 1:].any(axis=2) if self.decisions_only else np.ones(mask.shape[:2], bool)

    def act(self, view: RobotObservation, mask: np.ndarray, *, explore: bool) -> np.ndarray:
        """Per robot: epsilon-greedy over its valid actions; ties go to the plain auction's bid.

        Args:
            view: Output of :meth:`encode`.
            mask: ``[B, m, K + 1]`` valid actions.
            explore: Use epsilon (else greedy in Q).

        Returns:
            ``[B, m]`` valid actions.
        """
        values = np.where(mask, self._values(self._bases(view)), -np.inf)  # [B, m, K + 1]
        best = values.max(axis=2)
        plain = greedy_actions(mask)  # Q starts at 0: ties keep the auction's choice
        plain_value = np.take_along_axis(values, plain[..., None], axis=2)[..., 0]
        actions = np.where(plain_value >= best, plain, values.argmax(axis=2))
        epsilon = self.epsilon if explore else 0.0
        if epsilon > 0.0:
            explore_now = (self.rng.random(actions.shape) < epsilon) & mask[:, :, 1:].any(axis=2)
            if explore_now.any():
                u = self.rng.random(int(explore_now.sum()))
                actions[explore_now] = random_valid_actions(mask[explore_now], u)
        return actions

    def update(
        self,
        view: RobotObservation,
        actions: np.ndarray,
        result: StepResult,
        next_view: RobotObservation,
        next_mask: np.ndarray,
    ) -> dict[str, float]:
        """Eq. (3) for every robot on its own decision points (see ``common``), all copies.

        Args:
            view: View before acting.
            actions: ``[B, m]`` actions taken.
            result: Rewards (individual) and done flags.
            next_view: View after the step.
            next_mask: ``[B, m, K + 1]`` valid actions after the step.

        Returns:
            ``learner/td_error``: mean absolute TD error of the updates of this tick.
        """
        batch = len(actions)
        if self._pending is None or self._pending.entry.shape[0] != batch:
            self._pending = PendingTransitions((batch, self.n_robots))
        pending = self._pending
        entries = self._bases(view) + actions  # [B, m]
        pending.start(self._decides(view.mask), entries)
        pending.accumulate(np.asarray(result.robot_reward, np.float64), self.gamma)
        done = np.asarray(result.done, bool)
        pending.drop(np.broadcast_to(done[:, None], pending.entry.shape))
        closing = self._decides(next_mask) & ~done[:, None]
        pos, closed, ret, discount = pending.close(closing)
        if len(closed) == 0:
            return {}
        next_bases = self._bases(next_view)[pos]
        next_values = np.where(next_mask[pos], self._values(next_bases), -np.inf)
        targets = ret + discount * next_values.max(axis=-1)  # eq. (3): r + gamma max_a' Q_i(s', a')
        return {"learner/td_error": self._update(self.q, self.visits, closed, targets)}

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
        **hyperparameters: See :class:`~mrta_rl.learners.tabular.common.TabularLearner`.
    """

    space_name: ClassVar[str] = "dql"

    def __init__(self, **hyperparameters) -> None:
        super().__init__(**hyperparameters)
        env = self.env
        self.state_counts = local_state_count(env)  # |S_i|
        self._stride = max(self.state_counts)
        size = self.n_robots * self._stride * self.n_actions
        self.q = np.zeros(size)  # Q_i(s, a) at (i * stride + s) * (K + 1) + a
        self.visits = np.zeros(size, np.int64)
        self._robot_base = np.arange(self.n_robots) * self._stride

    def encode(self, env: AuctionEnv) -> RobotObservation:
        """``[B, m]`` local state index of every robot, and the mask."""
        return RobotObservation(local_state_index(env), env.action_mask.copy())

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
