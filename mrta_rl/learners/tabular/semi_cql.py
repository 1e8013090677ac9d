"""semi-CQL (paper §6): each robot learns Q over the whole system's state and its own action.

Robots share the observation of the whole system (the whole-team ``GroupView``, as CQL) but each
learns its own ``Q_i(s, a_i)`` from its individual reward, as in the paper's ref. [38]. The state
space is large (``|S|`` of CQL), so rows are stored only for the states met: a dict from state
index to a row of ``m x (K + 1)`` values.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from mrta_rl.envs import AuctionEnv
from mrta_rl.envs.observations import group_state_index
from mrta_rl.learners.tabular.dql import RobotObservation, RobotQLearner


class SemiCQLLearner(RobotQLearner):
    """Semi-centralized Q-learning: shared whole-system state, individual actions and rewards.

    Args:
        env: The env (full task sets).
        rng: Exploration randomness.
        partition: Unused.
        **hyperparameters: See :class:`~mrta_rl.learners.tabular.common.TabularLearner`.
    """

    space_name: ClassVar[str] = "semi_cql"

    def __init__(self, **hyperparameters) -> None:
        super().__init__(**hyperparameters)
        env = self.env
        self._robots = list(range(env.n_robots))
        self._row_size = self.n_robots * self.n_actions
        self.index: dict[int, int] = {}  # whole-system state index -> row
        self.states = np.zeros(0, np.int64)  # row -> state index
        self.q = np.zeros(0)  # Q_i(s, a) at (row * m + i) * (K + 1) + a
        self.visits = np.zeros(0, np.int64)
        self._n_rows = 0

    def encode(self, env: AuctionEnv) -> RobotObservation:
        """``[B]`` whole-system state index, and the mask."""
        return RobotObservation(group_state_index(env, self._robots), env.action_mask.copy())

    def _rows(self, states: np.ndarray) -> np.ndarray:
        get = self.index.get
        rows = np.fromiter((get(s, -1) for s in states.tolist()), np.int64, len(states))
        new = rows < 0
        if new.any():
            fresh = np.unique(states[new])
            self._grow(len(fresh))
            first = self._n_rows
            self.states[first : first + len(fresh)] = fresh
            self.index.update(zip(fresh.tolist(), range(first, first + len(fresh)), strict=True))
            self._n_rows += len(fresh)
            rows[new] = np.fromiter(
                (get(s) for s in states[new].tolist()), np.int64, int(new.sum())
            )
        return rows

    def _grow(self, extra: int) -> None:
        need = self._n_rows + extra
        if need <= len(self.states):
            return
        capacity = max(need, 2 * len(self.states), 1024)
        states = np.zeros(capacity, np.int64)
        states[: self._n_rows] = self.states[: self._n_rows]
        q = np.zeros(capacity * self._row_size)
        visits = np.zeros(capacity * self._row_size, np.int64)
        used = self._n_rows * self._row_size
        q[:used], visits[:used] = self.q[:used], self.visits[:used]
        self.states, self.q, self.visits = states, q, visits

    def _bases(self, view: RobotObservation) -> np.ndarray:
        rows = self._rows(view.states)  # [B]
        return rows[:, None] * self._row_size + np.arange(self.n_robots) * self.n_actions  # [B, m]

    def _table_arrays(self) -> dict[str, np.ndarray]:
        used = self._n_rows * self._row_size
        shape = (self._n_rows, self.n_robots, self.n_actions)
        return {
            "states": self.states[: self._n_rows].copy(),
            "q": self.q[:used].reshape(shape),
            "visits": self.visits[:used].reshape(shape),
        }

    def _load_table_arrays(self, arrays: dict[str, np.ndarray]) -> None:
        states = arrays["states"]
        if arrays["q"].shape[1:] != (self.n_robots, self.n_actions):
            raise ValueError(
                f"saved table has shape {arrays['q'].shape}, "
                f"expected [rows, {self.n_robots}, {self.n_actions}]"
            )
        self._n_rows = 0
        self.states, self.q, self.visits = np.zeros(0, np.int64), np.zeros(0), np.zeros(0, np.int64)
        self._grow(len(states))
        self._n_rows = len(states)
        self.states[: len(states)] = states
        self.q[: arrays["q"].size] = arrays["q"].ravel()
        self.visits[: arrays["visits"].size] = arrays["visits"].ravel()
        self.index = dict(zip(states.tolist(), range(len(states)), strict=True))
