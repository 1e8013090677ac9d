"""DQL (paper §3, §6): independent Q-learners, each robot over its local view and its own action.

:class:`RobotQLearner` is the per-robot machinery (eq. 3 for each robot, its own reward and
epsilon-greedy over its own valid actions), shared with semi-CQL, which only changes the state
each robot sees. :class:`DQLLearner` gives robot ``i`` its local view (``LocalView``: idle flag,
the slots it may bid for, battery level, recency of H arrivals of its types), stored densely.
The per-tick work runs in the compiled loops of :mod:`~mrta_rl.learners.tabular.robot_kernels`.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Annotated, Any, ClassVar

import numpy as np

from mrta_rl.config import Choices, Range
from mrta_rl.envs import AuctionEnv, StepResult
from mrta_rl.envs.encodings import FEATURES, local_state_count
from mrta_rl.learners.base import MemoryQuery
from mrta_rl.learners.memory import TABLE_ENTRY_BYTES, ResourceEstimate, Unfit
from mrta_rl.learners.tabular import robot_kernels as kernels
from mrta_rl.learners.tabular.base import NO_UNIFORMS, TabularLearner
from mrta_rl.learners.tabular.encoding import LocalEncoder, busy_arrays, env_arrays
from mrta_rl.metrics.learning_space import decentralized_dimension
from mrta_rl.partition import Partition
from mrta_rl.priors import HOLD_PRIORS, HOLD_SCOPES, HoldLevel, HoldRule, Reserve
from mrta_rl.rules import greedy_actions


@dataclass
class RobotObservation:
    """A decision point as the per-robot learners see it.

    Attributes:
        states: ``[B, m]`` (local views) or ``[B]`` (whole-system state) state indices.
        mask: ``[B, m, K + 1]`` valid actions (a copy).
        prior: ``[B, m]`` the prior's action of every robot, or None for the plain auction's.
    """

    states: np.ndarray
    mask: np.ndarray
    prior: np.ndarray | None = None


class RobotQLearner(TabularLearner, abstract=True):
    """Q-learning per robot (eq. 3) on its own action and individual reward (spec step 8).

    Subclasses map a view to ``[B, m]`` flat offsets ``base`` with ``Q_i(s, a) = q[base + a]``
    (:meth:`_bases`) and own the flat arrays :attr:`q` and :attr:`visits`.
    """

    q: np.ndarray
    visits: np.ndarray
    # learn from the team reward (spec step 8) instead of the robot's: DQL's reward=team
    team_reward: bool = False

    _pending: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    _last: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # train_tick's last decision
    _scratch: tuple[np.ndarray, ...] = ()  # arrays train_tick's kernel writes and nobody keeps

    def _bases(self, view: RobotObservation) -> np.ndarray:
        """``[B, m]`` flat offset of ``Q_i(s_i, 0)`` for every copy and robot."""
        raise NotImplementedError

    def _pending_of(self, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The open transitions ``[B, m]`` (entry, return, discount), new ones if ``B`` changed."""
        if self._pending is None or self._pending[0].shape != shape:
            self._pending = (np.full(shape, -1, np.int64), np.zeros(shape), np.ones(shape))
            # train_tick's scratch: int and float zeros (no last decision), prior, closing, states
            self._scratch = (
                np.zeros(shape, np.int64),
                np.zeros(shape),
                np.empty(shape, np.int64),
                np.empty(shape, bool),
                np.empty(shape, np.int64),
            )
        return self._pending

    def _next_prior(self, env: AuctionEnv, mask: np.ndarray) -> np.ndarray | None:
        """``[B, m]`` the prior's actions in the env's state; None: the plain auction's."""
        return None

    def _tick_kernel(
        self, env: AuctionEnv, prior: np.ndarray | None, shared: tuple, out: tuple
    ) -> int:
        """Call the learner's tick kernel (``robot_kernels.tick_*``): uniforms used, or -1.

        ``shared`` holds the arguments the kernels share (``learner``, ``last``, ``now``,
        ``learn``, ``outcome``, ``explore``), ``out`` the local states, next bases, closing
        flags and next actions; ``prior`` is :meth:`_next_prior`'s.
        """
        raise NotImplementedError

    @functools.cached_property
    def _kernel_settings(self) -> tuple:
        """The hyperparameters as a ``robot_kernels.Settings`` tuple (all set by ``__init__``)."""
        settings = kernels.Settings(
            decisions_only=self.hp["decisions_only"],
            gamma=self.hp["gamma"],
            min_visits=self.hp["min_visits"],
            prior_target=self.prior_target,
            alpha=self.hp["alpha"],
            alpha_power=self.hp["alpha_power"],
            alpha_min=self.hp["alpha_min"],
        )
        return tuple(settings)

    def train_tick(self, env: AuctionEnv, result: StepResult | None) -> np.ndarray | None:
        """:meth:`TabularLearner.train_tick` in one compiled call (``robot_kernels.tick_*``)."""
        shape = (env.batch_size, self.n_robots)
        pending = self._pending_of(shape)
        no_actions, no_rewards, greedy, closing, states = self._scratch
        mask = env.action_mask  # a new array every tick (AuctionEnv): kept as the last mask
        if result is not None:
            if self._last is None:
                raise self._no_last_decision()
            bases, actions, last_mask = self._last
            rewards, done = self._rewards(result, shape), result.done
        else:  # nothing to learn from at the start of an episode
            bases = actions = no_actions
            last_mask, rewards, done = mask, no_rewards, env.done
        prior = self._next_prior(env, mask)
        epsilon = self.epsilon
        block = self.uniforms.block(2 * bases.size) if epsilon > 0.0 else NO_UNIFORMS
        next_bases, next_actions = np.empty(shape, np.int64), np.zeros(shape, np.int64)
        shared = (
            ((self.q, self.visits), self._kernel_settings, pending),  # values, settings, pending
            (bases, actions, last_mask),  # robot_kernels.Step
            (mask, greedy if prior is None else prior),
            result is not None,
            (rewards, done),  # robot_kernels.Outcome
            (epsilon, block),
        )
        used = self._tick_kernel(env, prior, shared, (states, next_bases, closing, next_actions))
        if used < 0:  # the episode has ended
            self.uniforms.settle()
            self._last = None
            return None
        self.uniforms.used(used)
        self._last = (next_bases, next_actions, mask)
        return next_actions

    def act(self, view: RobotObservation, mask: np.ndarray, *, explore: bool) -> np.ndarray:
        """Per robot: epsilon-greedy over its valid actions; ties go to the prior's action.

        The prior is the plain auction's bid (lowest valid slot) unless the view carries one.

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
        block = self.uniforms.block(2 * actions.size) if epsilon > 0.0 else NO_UNIFORMS
        used = kernels.act_robots(
            (self.q, self.visits),
            (bases, mask, self._prior(view, mask)),
            self.hp["min_visits"],
            (epsilon, block),
            actions,
        )
        if epsilon > 0.0:
            self.uniforms.used(used)
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
        self._pending_of(shape)
        next_mask = np.ascontiguousarray(next_mask, bool)
        closing = np.empty(shape, bool)
        count = kernels.open_transitions(
            (self._bases(view), np.asarray(actions, np.int64), view.mask),
            next_mask,
            (self._rewards(result, shape), np.asarray(result.done, bool)),
            self._pending,
            self._kernel_settings,
            closing,
        )
        if count == 0:
            return {}
        # the prior only matters to the max when min_visits > 0 (else every action competes)
        # or when it is the target
        next_prior = (
            self._prior(next_view, next_mask)
            if self.hp["min_visits"] or self.prior_target
            else np.zeros(shape, np.int64)
        )
        td_sum = kernels.close_transitions(
            (self.q, self.visits),
            (self._bases(next_view), next_mask, next_prior),
            self._kernel_settings,
            closing,
            self._pending,
        )
        return {"learner/td_error": td_sum / count} if count else {}

    @staticmethod
    def _prior(view: RobotObservation, mask: np.ndarray) -> np.ndarray:
        """``[B, m]`` the prior's action of every robot: the view's, else the plain auction's."""
        return greedy_actions(mask) if view.prior is None else view.prior

    def _rewards(self, result: StepResult, shape: tuple[int, ...]) -> np.ndarray:
        """``[B, m]`` reward of each robot: its own, or the team's with ``team_reward``."""
        if self.team_reward:
            return np.ascontiguousarray(np.broadcast_to(result.team_reward[:, None], shape), float)
        return np.asarray(result.robot_reward, np.float64)

    def learning_space(self) -> dict[str, int]:
        """Analytic dimension (eq. 11) and the table entries updated at least once."""
        settings = {"features": self.hp["features"]}
        analytic = self.learning_space_dimension(self.env, self.partition, settings)
        return {"analytic": analytic, "visited": int(np.count_nonzero(self.visits))}


DQL_PRIORS = HOLD_PRIORS  # DQL's tie-break action of an untried state
DQL_REWARDS = ("individual", "team")  # what each robot's eq. (3) learns from


class DQLLearner(RobotQLearner):
    """Decentralized Q-learning (paper §6, independent learners after its ref. [32]).

    Robot ``i`` learns ``Q_i(s_i, a_i)`` over its local view ``s_i`` and its own action, from its
    individual reward, ignoring its teammates. Tables are dense: ``[m, max_i |S_i|, K + 1]``.

    Ties among the greatest Q go to the prior's action (docs/learners.md, "Exploration and
    ties"): ``greedy`` the plain auction's bid; ``hold`` the action of the whole-team rule
    ``team_reserve`` (:class:`~mrta_rl.learners.fixed.TeamReserveLearner`, whole team,
    ``fewest_types`` order, the ``prior_*`` settings), computed from the env at each decision:
    it reads what the local view lacks (the other robots' idleness, which robot the team asks
    first), so the untrained learner plays the rule exactly. ``prior_in_state`` adds that action
    as one more digit of the local state (``K + 1`` values: ``|S_i|`` times ``K + 1``), so a
    trained robot can still tell the situations in which the rule bids from those in which it
    waits.

    Args:
        prior: ``greedy`` or ``hold`` (:data:`DQL_PRIORS`).
        prior_reserve: ``prior="hold"``: the rule's ``reserve``.
        prior_hold_level: ``prior="hold"``: the rule's ``hold_level``.
        prior_hold_scope: ``prior="hold"``: the rule's ``hold_scope``.
        prior_in_state: Add the prior's action as a digit of the local state.
        reward: ``individual`` (the paper's: each robot its own reward, spec step 8) or ``team``
            (every robot learns from the team reward: a robot that holds back for H work is
            credited when a teammate does it).
        min_visits: Updates an entry needs before it competes with the prior's action, in the
            greedy choice and in eq. (3)'s max (0: every valid action competes).
        features: The local view's encoding (``encodings.FEATURES``): ``paper`` or
            ``time_to_free`` (the free level instead of the idle flag, queued H and L levels
            over ``Lambda_i``; coarse, docs/learners.md).
        **hyperparameters: Env, rng, partition (unused) and those of
            :class:`~mrta_rl.learners.tabular.base.TabularLearner`.

    Raises:
        ConfigError: on a setting outside its declaration (the annotations, ``mrta_rl.config``).
    """

    label: ClassVar[str] = "DQL"

    @classmethod
    def estimate_memory(cls, query: MemoryQuery) -> ResourceEstimate:
        """Dense tables ``[m, max_i |S_i|, K + 1]`` of Q and visits, allocated when built.

        Raises:
            Unfit: if a local state index passes int64.
        """
        env, partition, settings, decisions, copies = query
        try:
            stride = max(local_state_count(env, settings["features"]))
        except OverflowError as err:
            raise Unfit(str(err), "use fewer task types or slots") from None
        tables = env.n_robots * stride * env.n_actions * TABLE_ENTRY_BYTES  # dense, allocated
        return ResourceEstimate(cls.__name__, tables, tables, {"tables": tables})

    @classmethod
    def learning_space_dimension(
        cls, env: AuctionEnv, partition: Partition | None, settings: dict[str, Any]
    ) -> int:
        """Eqs. (10)-(11): ``sum_i |S_i| |A_i|`` over the local views of ``features``."""
        states = local_state_count(env, settings.get("features", "paper"))
        return decentralized_dimension(states, [env.n_actions] * env.n_robots)

    def __init__(
        self,
        *,
        prior: Annotated[str, Choices(*DQL_PRIORS)],
        prior_reserve: Reserve,
        prior_hold_level: HoldLevel,
        prior_hold_scope: Annotated[str, Choices(*HOLD_SCOPES)],
        prior_in_state: bool,
        reward: Annotated[str, Choices(*DQL_REWARDS)],
        min_visits: Annotated[int, Range(0)],
        features: Annotated[str, Choices(*FEATURES)],
        **hyperparameters,
    ) -> None:
        super().__init__(**hyperparameters)  # types, ranges and choices: the annotations
        self.prior_in_state = prior_in_state  # read by the kernels' call every tick
        self.team_reward = reward == "team"
        self.rule = None  # the hold rule (priors.HoldRule)
        if prior == "hold":
            self.rule = HoldRule(
                self.env,
                reserve=prior_reserve,
                hold_level=prior_hold_level,
                hold_scope=prior_hold_scope,
            )
        self.encoder = LocalEncoder(self.env, features)
        # |S_i|, times K + 1 with the prior's action as a digit (the most significant)
        self._local_counts = self.encoder.counts
        self.state_counts = [
            c * (self.n_actions if self.prior_in_state else 1) for c in self._local_counts
        ]
        self._stride = max(self.state_counts)
        size = self.n_robots * self._stride * self.n_actions
        self.q = np.zeros(size)  # Q_i(s, a) at (i * stride + s) * (K + 1) + a
        self.visits = np.zeros(size, np.int64)
        self._robot_base = np.arange(self.n_robots) * self._stride
        self._digit_place = np.asarray(self._local_counts, np.int64)  # the prior digit's place

    def encode(self, env: AuctionEnv) -> RobotObservation:
        """``[B, m]`` local state index of every robot, the mask and the prior's actions."""
        states, mask = self.encoder.index(env), env.action_mask.copy()
        if self.rule is None:
            return RobotObservation(states, mask)
        prior = self._rule_actions(env, mask)
        if self.prior_in_state:
            kernels.add_prior_digit(states, prior, self._digit_place)
        return RobotObservation(states, mask, prior)

    def _rule_actions(self, env: AuctionEnv, mask: np.ndarray) -> np.ndarray:
        """``[B, m]`` the hold rule's actions in the env's state."""
        return self.rule(env, mask)

    def _bases(self, view: RobotObservation) -> np.ndarray:
        bases = np.empty(view.states.shape, np.int64)
        kernels.local_bases(view.states, self._robot_base, self.n_actions, bases)
        return bases

    def _next_prior(self, env: AuctionEnv, mask: np.ndarray) -> np.ndarray | None:
        return None if self.rule is None else self._rule_actions(env, mask)

    def _tick_kernel(
        self, env: AuctionEnv, prior: np.ndarray | None, shared: tuple, out: tuple
    ) -> int:
        learner, last, now, learn, outcome, explore = shared
        encoding = (
            (env_arrays(env), busy_arrays(env), self.encoder.tables),
            self._robot_base,
            self._digit_place,
            prior is None,  # the plain auction's prior, computed by the kernel
            self.prior_in_state and prior is not None,
        )
        return kernels.tick_local(learner, encoding, last, now, learn, outcome, explore, out)

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

    def learning_space(self) -> dict[str, int]:
        """Eq. (11) over the local view, times ``K + 1`` with the prior's action in the state."""
        space = super().learning_space()
        if self.prior_in_state:
            space["analytic"] *= self.n_actions
        return space
