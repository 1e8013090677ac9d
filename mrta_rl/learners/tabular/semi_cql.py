"""semi-CQL (paper §6): each robot learns Q over the whole system's state and its own action.

Robots share the observation of the whole system (the whole-team ``GroupView``, as CQL) but each
learns its own ``Q_i(s, a_i)`` from its individual reward, as in the paper's ref. [38]. The state
space is large (``|S|`` of CQL), so rows are stored only for the states met: a hash table
(``qtable``) from state index to a row of ``m x (K + 1)`` values. ``state`` selects a coarser
shared state (``encoding.SystemEncoder``): at the default budget the paper's one meets 314,000
states on System-II, each too rarely for any robot's action to leave the prior.
"""

from __future__ import annotations

from typing import Annotated, Any, ClassVar

import numpy as np

from mrta_rl.config import Choices, Range
from mrta_rl.envs import AuctionEnv, StepResult
from mrta_rl.envs.encodings import FEATURES
from mrta_rl.learners.base import MemoryQuery
from mrta_rl.learners.memory import (
    GROWTH,
    INT64_CODES,
    JOINT_ROW_BYTES,
    TABLE_ENTRY_BYTES,
    ResourceEstimate,
    Unfit,
)
from mrta_rl.learners.tabular import robot_kernels as kernels
from mrta_rl.learners.tabular.dql import RobotObservation, RobotQLearner
from mrta_rl.learners.tabular.encoding import (
    SYSTEM_STATES,
    SystemEncoder,
    env_arrays,
    system_state_count,
)
from mrta_rl.learners.tabular.qtable import ROW_STATE, JointQStorage
from mrta_rl.metrics.learning_space import decentralized_dimension
from mrta_rl.partition import Partition


class SemiCQLLearner(RobotQLearner):
    """Semi-centralized Q-learning: shared whole-system state, individual actions and rewards.

    Args:
        env: The env (full task sets).
        rng: Exploration randomness.
        partition: Unused.
        min_visits: Updates an entry needs before it competes with the prior's action (the plain
            auction's bid), in the greedy choice and in eq. (3)'s max (0: every valid action).
        features: The whole-system state's encoding (``encodings.FEATURES``): ``paper`` or
            ``time_to_free`` (robot state 3 = busy, free soon; queued H and L levels; coarse,
            docs/learners.md).
        state: The shared state (``encoding.SYSTEM_STATES``): ``system``, the paper's group view
            of all robots; or, coarser, the slot codes and the recency level with the number of
            idle robots (``idle_count``), each robot's idle flag (``idle``) or nothing more
            (``slots``, the default: docs/notebook.md, "semi-CQL: a coarser shared state"); the
            coarser ones need ``features=paper``.
        **hyperparameters: See :class:`~mrta_rl.learners.tabular.base.TabularLearner`.
    """

    label: ClassVar[str] = "semi-CQL"

    @classmethod
    def estimate_memory(cls, query: MemoryQuery) -> ResourceEstimate:
        """Rows of the shared states met, ``m (K + 1)`` Q and visits each, in a growable table.

        Raises:
            Unfit: if the shared state's index passes int64.
        """
        env, partition, settings, decisions, copies = query
        states = system_state_count(env, settings["state"], settings["features"])
        if states >= INT64_CODES:
            reason = f"{states:.3g} whole-system states do not fit in int64"
            raise Unfit(reason, "use a smaller system")
        row = env.n_robots * env.n_actions * TABLE_ENTRY_BYTES + JOINT_ROW_BYTES
        table = GROWTH * min(states, decisions) * row
        return ResourceEstimate(cls.__name__, 0, table, {"table": table})

    @classmethod
    def learning_space_dimension(
        cls, env: AuctionEnv, partition: Partition | None, settings: dict[str, Any]
    ) -> int:
        """Eq. (11) with each robot's state the shared one: ``sum_i |S| |A_i|``.

        ``settings["state"]`` is the shared state (default ``system``, the paper's).
        """
        whole = system_state_count(
            env, settings.get("state", "system"), settings.get("features", "paper")
        )
        return decentralized_dimension([whole] * env.n_robots, [env.n_actions] * env.n_robots)

    def __init__(
        self,
        *,
        min_visits: Annotated[int, Range(0)],
        features: Annotated[str, Choices(*FEATURES)],
        state: Annotated[str, Choices(*SYSTEM_STATES)],
        **hyperparameters,
    ) -> None:
        super().__init__(**hyperparameters)
        self.encoder = SystemEncoder(self.env, state, features)
        self._row_size = self.n_robots * self.n_actions
        self._index = JointQStorage(1)  # state index -> row (hash), row -> state index
        self.q = np.zeros(1024 * self._row_size)  # Q_i(s, a) at (row * m + i) * (K + 1) + a
        self.visits = np.zeros(1024 * self._row_size, np.int64)
        self._room = 0  # rows that fit in every array (_reserve); train_tick grows past it
        self._system_scratch: tuple[np.ndarray, ...] = ()  # tick_system's states, level, rows

    @property
    def _n_rows(self) -> int:
        return self._index.n_rows

    @property
    def states(self) -> np.ndarray:
        """Row -> whole-system state index."""
        return self._index.rows[ROW_STATE, : self._n_rows]

    def encode(self, env: AuctionEnv) -> RobotObservation:
        """``[B]`` whole-system state index, and the mask."""
        return RobotObservation(self.encoder.index(env)[0][0], env.action_mask.copy())

    def _rows(self, states: np.ndarray) -> np.ndarray:
        self._reserve(len(states))
        rows = np.empty(len(states), np.int64)
        index = self._index
        kernels.rows_of_states((index.hash, index.rows, index.sizes), states, rows)
        return rows

    def _reserve(self, extra: int) -> None:
        self._index.reserve(extra, 0)  # rows and hash table
        need = (int(self._index.sizes[0]) + extra) * self._row_size
        if need > len(self.q):
            capacity = max(need, 2 * len(self.q))
            try:  # in place (realloc moves the pages: no copy, no fresh pages to zero)
                self.q.resize(capacity, refcheck=True)
                self.visits.resize(capacity, refcheck=True)
            except ValueError:  # a view of the arrays is alive somewhere: copy them instead
                used = self._n_rows * self._row_size
                q, visits = np.zeros(capacity), np.zeros(capacity, np.int64)
                q[:used], visits[:used] = self.q[:used], self.visits[:used]
                self.q, self.visits = q, visits
        # rows that fit now: the row arrays, the hash table at most half full, the values
        rows, slots = self._index.rows.shape[1], self._index.hash.shape[1]
        self._room = min(rows, slots // 2, len(self.q) // self._row_size)

    def _bases(self, view: RobotObservation) -> np.ndarray:
        bases = np.empty((len(view.states), self.n_robots), np.int64)
        kernels.row_bases(self._rows(view.states), self._row_size, self.n_actions, bases)
        return bases

    def train_tick(self, env: AuctionEnv, result: StepResult | None) -> np.ndarray | None:
        """:meth:`RobotQLearner.train_tick`, with room first for the rows of the new states."""
        if self._index.sizes[0] + env.batch_size > self._room:  # amortised: rarely grows
            self._reserve(env.batch_size)
        return super().train_tick(env, result)

    def _tick_kernel(
        self, env: AuctionEnv, prior: np.ndarray | None, shared: tuple, out: tuple
    ) -> int:
        index, batch = self._index, env.batch_size
        if not self._system_scratch or self._system_scratch[0].shape[1] != batch:
            # the whole-system state and level (one group, [1, B]) and their rows [B], not the
            # local states [B, m] of out[0]; written by the kernel, kept by nobody
            self._system_scratch = (
                np.empty((1, batch), np.int64),
                np.empty((1, batch), np.int64),
                np.empty(batch, np.int64),
            )
        learner, last, now, learn, outcome, explore = shared
        encoding = (
            (env_arrays(env), self.encoder.tables),
            self.encoder.offset(env),
            (index.hash, index.rows, index.sizes),
            self._row_size,
        )
        out = (*self._system_scratch, *out[1:])
        return kernels.tick_system(learner, encoding, last, now, learn, outcome, explore, out)

    def learning_space(self) -> dict[str, int]:
        """Analytic dimension (eq. 11 over the shared ``state``) and the entries updated."""
        analytic = self.learning_space_dimension(self.env, None, self.hp)
        return {**super().learning_space(), "analytic": analytic}

    def _table_arrays(self) -> dict[str, np.ndarray]:
        used = self._n_rows * self._row_size
        shape = (self._n_rows, self.n_robots, self.n_actions)
        # a coarser shared state marks its file (as subG-CQL's group states do), so that a table
        # of one state never loads into a learner of another, in either direction (its indices
        # would read as other states; TabularLearner.load compares the arrays' names); `system`
        # adds nothing, so the files of before load as they are
        state = self.hp["state"]
        marker = {} if state == "system" else {f"state.{state}": np.zeros(1, np.int64)}
        return {
            **marker,
            "states": self.states.copy(),
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
        self._index = JointQStorage(1)
        self._index.from_rows(states)
        self._reserve(0)
        self.q[: arrays["q"].size] = arrays["q"].ravel()
        self.visits[: arrays["visits"].size] = arrays["visits"].ravel()
