"""``reserve_es``: evolution strategies over the weights of a parametric whole-team reserve rule.

The policy is the ``team_reserve`` rule (``mrta_rl/learners/fixed.py``) over the whole team with
its two fixed choices made by learned linear scores over coarse features (:data:`FEATURES`):

* **who takes an H slot**: among the idle robots without a bid that may bid for it, the one with
  the highest preference ``theta_H . phi_H(i)`` (:data:`HIGH_FEATURES`); ties go to the rule's
  order (fewest active types first, then the lowest index);
* **whether and who takes an L slot**: an idle robot ``i`` may bid for L slot ``k`` only if its
  score ``theta_L . phi(i, k)`` is positive, and the one with the highest score bids (ties to the
  same order).

H slots go first, then L slots, each in slot order, one robot per slot, so a joint action never
has two bids for one slot (no lost bids, spec step 7).

The weights (``len(FEATURES) + len(HIGH_FEATURES)`` = 20 numbers) are learned from the team
return by antithetic evolution strategies (Salimans et al. 2017, "Evolution Strategies as a
Scalable Alternative to Reinforcement Learning"): each training episode plays ``2 * pairs``
perturbed policies ``theta +- sigma eps_j``, each on ``train.batch_size / (2 * pairs)`` copies, and
all of them on the *same* task streams (common random numbers): copy ``b`` starts as a clone of
copy ``b mod copies``, so the members differ only by their policy. The gradient estimate is
``sum_j (F+_j - F-_j) eps_j / pairs`` with the differences divided by their standard deviation
(fitness shaping), and Adam takes the step. Evaluation plays ``theta`` itself.

The start ``theta_0`` (``theta_H = 0``: every H preference ties) reproduces ``team_reserve`` with
``hold_scope=robot`` and the given ``reserve`` (0-2) and ``hold_level`` exactly (a test checks it
tick by tick), so the untrained policy is the best whole-team rule of
``experiment=team_reserve_grid`` (System-I: the defaults; System-II: ``reserve=1``), and every
gain over it is learned from returns.

Every feature is a coarse function of what the robots' ``time_to_free`` views show together
(``docs/neural.md``, "Inputs"): slot contents, idle flags, free levels, per-robot recency levels
and queue levels over ``Lambda_i``, and the team's ``Lambda`` (fixed). The two team queue levels
bucket the count over all types, where the views bucket it per robot. It reads neither the
queue's order, nor durations, nor batteries.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, ClassVar

import numpy as np

from mrta_rl import rules
from mrta_rl.checked_files import ArraySpec, check_arrays, read_arrays
from mrta_rl.config import ConfigError, Range
from mrta_rl.envs import AuctionEnv, StepResult
from mrta_rl.envs.encodings import N_RECENCY_LEVELS, free_level, queue_level, recency_level
from mrta_rl.learners.base import (
    NUMPY_LOOP,
    Learner,
    LearnerKind,
    MemoryQuery,
    NonFiniteState,
    TrainingTeam,
)
from mrta_rl.learners.memory import ResourceEstimate
from mrta_rl.partition import Partition

# phi(i, k) for idle robot i and L slot k; levels in {0, 1, 2} enter divided by 2.
FEATURES = (
    "bias",  # 1
    "h_within_3",  # an H task of one of Lambda_i's types arrived within 3 ticks (recency level 0)
    "h_within_10",  # ... within 4-10 ticks (recency level 1)
    "queued_h",  # queued H tasks of Lambda_i's types, level 0-2 (encodings.QUEUE_THRESHOLDS)
    "queued_l",  # queued L tasks of Lambda_i's types, level 0-2
    "sole_idle",  # i is the only idle robot for one of its types
    "sole_soon",  # no other robot is idle or free within 3 ticks for one of its types
    "no_other_idle",  # no other idle robot is left without a bid (so far this tick)
    "one_other_idle",  # exactly one is
    "slot_contested",  # another idle robot without a bid may also take slot k
    "versatility",  # |Lambda_i| / n
    "team_queued_l",  # queued L tasks of all types, level 0-2
    "team_queued_h",  # queued H tasks of all types, level 0-2
)
# phi_H(i) for the H-slot preference: the robot's own features (the others are equal for every
# robot of a copy, so they cannot change who is preferred)
HIGH_FEATURES = (
    "h_within_3",
    "h_within_10",
    "queued_h",
    "queued_l",
    "sole_idle",
    "sole_soon",
    "versatility",
)
N_LOW = len(FEATURES)
HIGH_COLUMNS = np.array([FEATURES.index(name) for name in HIGH_FEATURES])
WEIGHT_NAMES = FEATURES + tuple(f"H:{name}" for name in HIGH_FEATURES)  # theta = [theta_L, theta_H]
N_FEATURES = len(WEIGHT_NAMES)
DYNAMIC = ("no_other_idle", "one_other_idle", "slot_contested")  # depend on the bids placed so far
START_WEIGHT = 2.0  # |theta_0| of a hold: any weight > 1 outweighs the bias of 1
ADAM_BETAS = (0.9, 0.999)  # Adam's moment decays (Kingma and Ba 2015's defaults)
ADAM_EPS = 1e-8
STATE_FILE = "reserve_es.npz"
# the largest weight (and Adam first moment) a state may hold: every feature is in [0, 1] and
# the bias is 1, so a weight of 1e9 already outweighs any other; larger ones only overflow.
# Adam moves a weight by at most about 3.2 lr a step, so training never comes near it.
MAX_WEIGHT = 1e9
# the most ES steps a state may count: the count is saved as an int64 and grows by one a step
MAX_STEPS = 2**62


def start_theta(reserve: int, hold_level: int) -> np.ndarray:
    """``theta_0``: the weights that bid exactly where ``team_reserve`` (``hold_scope=robot``) bids.

    L score ``1 - 2 [level < hold_level] - 2 [fewer than reserve other idle robots]``, with the
    recency level read as its two indicators and the reserve as ``no_other_idle`` /
    ``one_other_idle``; ``hold_level=3`` (never bid for L) is a bias of -1. Every positive score
    is 1, so the highest is the first in the rule's order; ``theta_H = 0`` likewise.
    """
    theta = np.zeros(N_FEATURES)  # theta_H (the last entries) stays 0
    theta[FEATURES.index("bias")] = 1.0
    if hold_level >= 1:
        theta[FEATURES.index("h_within_3")] = -START_WEIGHT
    if hold_level >= 2:
        theta[FEATURES.index("h_within_10")] = -START_WEIGHT
    if hold_level >= N_RECENCY_LEVELS:
        theta[FEATURES.index("bias")] = -1.0
    if reserve >= 1:
        theta[FEATURES.index("no_other_idle")] = -START_WEIGHT
    if reserve >= 2:
        theta[FEATURES.index("one_other_idle")] = -START_WEIGHT
    return theta


def draw_perturbations(rng: np.random.Generator, pairs: int, size: int) -> np.ndarray:
    """``[pairs, size]`` the ``eps_j`` of one ES step, drawn from ``rng``."""
    return rng.standard_normal((pairs, size))


def member_weights(theta: np.ndarray, sigma: float, eps: np.ndarray) -> np.ndarray:
    """``[2 pairs, P]`` the members ``theta + sigma eps_j``, then ``theta - sigma eps_j``."""
    return np.concatenate([theta + sigma * eps, theta - sigma * eps])


@dataclass(frozen=True)
class Population:
    """One ES step's members, as a worker rebuilds them: the weights and the draw's seed.

    Attributes:
        theta: The weights the members perturb.
        sigma: The perturbations' standard deviation.
        pairs: Antithetic pairs.
        rng_state: The generator's state before the step's perturbations were drawn.
        copies: Copies each member plays.
    """

    theta: np.ndarray
    sigma: float
    pairs: int
    rng_state: dict[str, Any]
    copies: int

    def members(self) -> np.ndarray:
        """``[2 pairs, P]`` the members, exactly as the learner drew them."""
        rng = np.random.Generator(getattr(np.random, self.rng_state["bit_generator"])())
        rng.bit_generator.state = self.rng_state
        eps = draw_perturbations(rng, self.pairs, self.theta.size)
        return member_weights(self.theta, self.sigma, eps)


class ReserveESLearner(Learner):
    """Evolution strategies over the weights of a whole-team reserve rule (module docstring).

    Args:
        pairs: Antithetic pairs per training episode; ``train.batch_size`` must be a multiple of
            ``2 * pairs`` (each member plays ``train.batch_size / (2 * pairs)`` copies).
        sigma: Standard deviation of the perturbations ``eps_j`` (in weight units; the start's
            weights are 1 and 2).
        lr: Adam's step size.
        reserve: Start rule: idle robots kept back for H work (``team_reserve``'s ``reserve``).
        hold_level: Start rule: L waits while the robot's recency level is below this.
        **kwargs: Env, generator and partition of :class:`~mrta_rl.learners.base.Learner`.

    Attributes:
        theta: The weights ``theta`` the rule plays (evaluation plays these).
        perturbations: ``[pairs, P]`` the ``eps_j`` of the current training episode.
        copy_theta: ``[B, P]`` the weights each training copy plays this episode:
            ``theta + sigma eps_j`` then ``theta - sigma eps_j``, member-major.
        steps: ES updates made.

    Raises:
        ValueError: if the training batch is not a multiple of ``2 * pairs``.
    """

    label: ClassVar[str] = "reserve-ES"
    kind: ClassVar[LearnerKind] = "search"
    training_loop: ClassVar[str] = NUMPY_LOOP  # policy search on the numpy loop
    # every weight multiplies a feature that reads the team through counts and fractions only
    any_team: ClassVar[bool] = True
    # an ES step's members play their episodes anywhere (play_members): on Ray workers too
    population_on_workers: ClassVar[bool] = True

    @classmethod
    def estimate_memory(cls, query: MemoryQuery) -> ResourceEstimate:
        """Nothing beyond the env copies: a few weights and their Adam moments."""
        env, partition, settings, decisions, copies = query
        return ResourceEstimate(cls.__name__)

    @classmethod
    def learning_space_dimension(
        cls, env: AuctionEnv, partition: Partition | None, settings: dict[str, Any]
    ) -> int:
        """The weights of the rule (no table)."""
        return N_FEATURES

    @classmethod
    def check_settings(cls, settings: Mapping[str, Any], team: TrainingTeam) -> None:
        """Refuse training copies that are not a multiple of ``2 * pairs``.

        Raises:
            ConfigError: naming ``train.batch_size`` and ``learner.pairs``.
        """
        super().check_settings(settings, team)
        pairs, copies = settings["pairs"], team.copies
        if copies % (2 * pairs):
            raise ConfigError(
                f"train.batch_size {copies} must be a multiple of 2 * pairs = {2 * pairs} "
                "(every perturbed policy plays the same number of copies): change learner.pairs "
                "or train.batch_size"
            )

    def __init__(
        self,
        *,
        pairs: Annotated[int, Range(1)],
        sigma: Annotated[float, Range(0, low_open=True)],
        lr: Annotated[float, Range(0, low_open=True)],
        reserve: Annotated[int, Range(0, 2)],
        hold_level: Annotated[int, Range(0, N_RECENCY_LEVELS)],
        **kwargs: Any,
    ) -> None:
        super().__init__(**kwargs)
        self.pairs, self.sigma, self.lr = pairs, sigma, lr
        self.theta = start_theta(reserve, hold_level)
        self._adam_m = np.zeros(N_FEATURES)
        self._adam_v = np.zeros(N_FEATURES)
        self.steps = 0  # ES updates made
        self._team_env: AuctionEnv | None = None  # the env whose team facts _team holds
        self.bind_env(self.env)
        self._draw()

    def bind_env(self, env: AuctionEnv) -> None:
        """Train on ``env`` from now on (the first env, or the next team of a family).

        Raises:
            ValueError: if its batch is not a multiple of ``2 * pairs``.
        """
        batch = env.batch_size
        type(self).check_settings(self.hp, TrainingTeam(env, self.partition, batch))
        self.env, self.n_robots, self.n_actions = env, env.n_robots, env.n_actions
        self.copies = batch // (2 * self.pairs)  # copies per perturbed policy
        # common random numbers: copy b starts as a clone of copy b mod copies (seed and episode
        # count included), so every member plays the same task streams, episode after episode
        env.set_state(env.get_state(np.arange(batch) % self.copies))

    def play_on(self, env: AuctionEnv) -> None:
        """Act on ``env``'s team (a planner's base): nothing to bind.

        :meth:`encode` reads the team of the env it is given, and a play without exploration reads
        no member's copies, so ``env`` keeps its own copies (training would clone them,
        :meth:`bind_env`).
        """

    def _team(self, env: AuctionEnv) -> dict[str, np.ndarray]:
        """What the policy reads of the team of ``env`` (computed once per env).

        Returns:
            ``order`` ``[m]``: the rule's order (fewest active types first); ``versatility``
            ``[m]``: ``|Lambda_i| / n``.
        """
        if self._team_env is not env:
            active = env.active_tasks  # Lambda_i, [m, n]
            self._team_facts = {
                "order": rules.fewest_types_first(active),
                "versatility": active.sum(axis=1) / env.n_task_types,
            }
            self._team_env = env
        return self._team_facts

    # ------------------------------------------------------------------ policy
    def _draw(self) -> None:
        """New perturbations and the per-copy weights of the next training episode."""
        self._rng_before_draw = self.rng.bit_generator.state  # a fresh dict: resuming redraws
        self.perturbations = eps = draw_perturbations(self.rng, self.pairs, self.theta.size)
        members = member_weights(self.theta, self.sigma, eps)
        self.copy_theta = np.repeat(members, self.copies, axis=0)  # [B, P], member-major
        self._returns = np.zeros(len(self.copy_theta))

    def population(self) -> Population:
        """What rebuilds this ES step's members elsewhere: the weights and the draw's seed."""
        return Population(
            self.theta.copy(), self.sigma, self.pairs, self._rng_before_draw, self.copies
        )

    def record_returns(self, returns: np.ndarray) -> None:
        """Add the members' copies' team returns, played elsewhere (:meth:`play_members`)."""
        self._returns += returns

    def play_members(
        self, env: AuctionEnv, members: np.ndarray, copies: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """One training episode of some members on ``env``, from its current state.

        The ticks are those of the training loop (encode, act exploring, step), so each copy
        plays exactly what the same copy of the whole population plays there.

        Args:
            env: ``len(members) * copies`` copies at the start of an episode.
            members: ``[M, P]`` weights; copy ``b`` plays ``members[b // copies]``.
            copies: Copies per member.

        Returns:
            ``(returns, team_returns)``, both ``[len(members) * copies]``: the team rewards summed
            tick by tick (the members' fitness) and the env's team return per copy.
        """
        returns = np.zeros(env.batch_size)
        while not env.done.any():  # copies share the horizon: all finish at the same tick
            actions = self._bids(self.encode(env), env.action_mask, members, copies)
            returns += env.step(actions).team_reward
        return returns, env.stats.team_return.copy()

    def encode(self, env: AuctionEnv) -> dict[str, np.ndarray]:
        """The features that do not change while a tick's bids are placed, and the slots.

        Returns:
            ``static`` ``[B, m, len(FEATURES)]`` (the robot features of :data:`FEATURES`, zero
            where a feature depends on the bids), ``slot_high`` ``[B, K]``, ``idle`` ``[B, m]``,
            ``order`` ``[m]`` (the rule's robot order of this env's team).
        """
        active = env.active_tasks
        batch = env.batch_size
        idle = env.idle.astype(bool)
        level = recency_level(env, active)  # [B, m]
        queued = queue_level(env, active)  # [B, m, 2]: H, L
        team = queue_level(env, np.ones(env.n_task_types, bool))  # [B, 2]
        covers = active.astype(np.int64)
        idle_per_type = idle.astype(np.int64) @ covers  # [B, n]
        soon_per_type = (free_level(env) <= 1).astype(np.int64) @ covers
        facts = self._team(env)
        shape = (batch, env.n_robots)
        columns = {
            "bias": np.ones(shape),
            "h_within_3": level == 0,
            "h_within_10": level == 1,
            "queued_h": queued[..., 0] / 2,
            "queued_l": queued[..., 1] / 2,
            "sole_idle": ((idle_per_type[:, None, :] == 1) & active[None]).any(-1) & idle,
            # a robot counts itself among the idle-or-soon robots of its types
            "sole_soon": ((soon_per_type[:, None, :] <= 1) & active[None]).any(-1),
            "versatility": np.broadcast_to(facts["versatility"], shape),
            "team_queued_l": np.broadcast_to(team[:, None, 1] / 2, shape),
            "team_queued_h": np.broadcast_to(team[:, None, 0] / 2, shape),
        }
        static = np.zeros((*shape, N_LOW))  # the DYNAMIC columns stay 0: act adds them
        for name, column in columns.items():
            static[..., FEATURES.index(name)] = column
        return {
            "static": static,
            "slot_high": env.slot_high.copy(),
            "idle": idle,
            "order": facts["order"],
        }

    def act(self, view: dict[str, np.ndarray], mask: np.ndarray, *, explore: bool) -> np.ndarray:
        """Bid per the rule of the module docstring, with the member's weights when exploring."""
        batch = mask.shape[0]
        if explore:
            if batch != len(self.copy_theta):
                raise ValueError(f"explore=True needs the training batch {len(self.copy_theta)}")
            return self._bids(view, mask, self.copy_theta[:: self.copies], self.copies)
        return self._bids(view, mask, self.theta[None], batch)

    def _bids(
        self, view: dict[str, np.ndarray], mask: np.ndarray, theta: np.ndarray, group: int
    ) -> np.ndarray:
        """The rule's bids when copy ``b`` plays the weights ``theta[b // group]``."""
        batch, _, n_actions = mask.shape
        if len(theta) == 1:
            theta = np.broadcast_to(theta[0], (batch, theta.shape[1]))
        elif group > 1:
            theta = np.repeat(theta, group, axis=0)
        robots = view["order"]
        features = view["static"][:, robots]  # [B, m, P] in the rule's order
        low = np.einsum("bmp,bp->bm", features, theta[:, :N_LOW])
        preference = np.einsum("bmp,bp->bm", features[..., HIGH_COLUMNS], theta[:, N_LOW:])
        w_none, w_one, w_contested = (theta[:, FEATURES.index(name)] for name in DYNAMIC)
        rows = np.arange(batch)
        actions = np.zeros(mask.shape[:2], np.int64)
        free = view["idle"][:, robots].copy()  # idle robots without a bid yet, in order
        idle_left = free.sum(axis=1)
        slot_high = view["slot_high"]
        for high in (1, 0):  # H slots first, as team_reserve
            for k in range(n_actions - 1):
                candidates = mask[:, robots, k + 1] & free & (slot_high[:, k] == high)[:, None]
                if not high:
                    others = idle_left - 1
                    dynamic = (
                        w_none * (others == 0)
                        + w_one * (others == 1)
                        + w_contested * (candidates.sum(axis=1) > 1)
                    )
                    score = low + dynamic[:, None]
                    candidates &= score > 0
                else:
                    score = preference
                # the highest score among the candidates; argmax takes the first of equals
                has = candidates.any(axis=1)
                first = np.where(candidates, score, -np.inf).argmax(axis=1)
                actions[rows[has], robots[first[has]]] = k + 1
                free[rows[has], first[has]] = False
                idle_left -= has
        return actions

    # ------------------------------------------------------------------ learning
    def update(
        self,
        view: Any,
        actions: np.ndarray,
        result: StepResult,
        next_view: Any,
        next_mask: np.ndarray,
    ) -> dict[str, float]:
        """Add the tick's team reward to each copy's return (the fitness of its member)."""
        self._returns += result.team_reward
        return {}

    def end_episode(self) -> None:
        """One ES step from the members' mean returns, then new perturbations."""
        fitness = self._returns.reshape(2 * self.pairs, self.copies).mean(axis=1)
        diff = fitness[: self.pairs] - fitness[self.pairs :]  # F+_j - F-_j, same streams
        scale = diff.std()
        eps = self.perturbations
        grad = (diff / scale) @ eps / self.pairs if scale > 0 else np.zeros_like(self.theta)
        beta1, beta2 = ADAM_BETAS
        self.steps += 1
        self._adam_m = beta1 * self._adam_m + (1 - beta1) * grad
        self._adam_v = beta2 * self._adam_v + (1 - beta2) * grad**2
        m_hat = self._adam_m / (1 - beta1**self.steps)
        v_hat = self._adam_v / (1 - beta2**self.steps)
        self.theta = self.theta + self.lr * m_hat / (np.sqrt(v_hat) + ADAM_EPS)
        # a step that made NaN or infinite weights stops the run before they are saved
        check_arrays(
            self._state_arrays(),
            self.state_schema(),
            f"{self.label} after ES step {self.steps}",
            NonFiniteState,
        )
        self._draw()

    def learning_space(self) -> dict[str, int]:
        """The weights learned (no table: the policy has ``len(FEATURES)`` parameters)."""
        return {"analytic": N_FEATURES, "visited": N_FEATURES}

    # ------------------------------------------------------------------ persistence
    # the file of :meth:`save` and the names of the weights it holds (a subclass with more
    # weights names its own)
    state_file: ClassVar[str] = STATE_FILE
    weight_names: ClassVar[tuple[str, ...]] = WEIGHT_NAMES

    def state_schema(self) -> dict[str, ArraySpec]:
        """The arrays of :attr:`state_file`, as this learner's settings shape them.

        ``theta`` and Adam's moments ``adam_m``, ``adam_v`` are real floats of the weights' shape
        (the rule's weights, then a subclass's), finite, within :data:`MAX_WEIGHT` (``adam_v``,
        a mean of squared gradients: >= 0, within its square); ``steps`` an integer in
        [0, :data:`MAX_STEPS`]; ``features`` the names of the weights (:attr:`weight_names`).
        """
        weights = self.theta.shape
        moment = "Adam's {} moment of the weights"
        return {
            "theta": ArraySpec(weights, magnitude=MAX_WEIGHT, meaning="the weights"),
            "adam_m": ArraySpec(weights, magnitude=MAX_WEIGHT, meaning=moment.format("first")),
            "adam_v": ArraySpec(
                weights, low=0.0, magnitude=MAX_WEIGHT**2, meaning=moment.format("second")
            ),
            "steps": ArraySpec((), kinds="iu", low=0, magnitude=MAX_STEPS, meaning="ES steps made"),
            "features": ArraySpec(
                (len(self.weight_names),),
                kinds="U",
                names=self.weight_names,
                meaning="the weights' names",
            ),
        }

    def _state_arrays(self) -> dict[str, np.ndarray]:
        """What :meth:`save` writes (:meth:`state_schema`)."""
        return {
            "theta": self.theta,
            "adam_m": self._adam_m,
            "adam_v": self._adam_v,
            "steps": np.int64(self.steps),
            "features": np.asarray(self.weight_names),
        }

    def save(self, directory: Path) -> None:
        """:attr:`state_file`: the weights, Adam's moments, the step count and their names.

        Raises:
            NonFiniteState: if the state breaks :meth:`state_schema` (nothing is written).
        """
        arrays = self._state_arrays()
        where = f"{self.label} after ES step {self.steps}, saving"
        check_arrays(arrays, self.state_schema(), where, NonFiniteState)
        directory.mkdir(parents=True, exist_ok=True)
        np.savez(directory / self.state_file, **arrays)

    def load(self, directory: Path) -> None:
        """Restore :meth:`save`'s file, checked against :meth:`state_schema` before it is used.

        Raises:
            RunDirError: naming the file and the array: another learner's or size's weights,
                NaN, infinite or out-of-range values, a negative step count or Adam second
                moment, or not such a file at all.
        """
        path = directory / self.state_file
        saved = read_arrays(path, self.state_schema(), what=f"a {self.state_file} of {self.label}")
        self.theta = saved["theta"].astype(float)
        self._adam_m = saved["adam_m"].astype(float)
        self._adam_v = saved["adam_v"].astype(float)
        self.steps = int(saved["steps"])

    def checkpoint_state(self, directory: Path) -> dict[str, Any]:
        """The generator before the current perturbations were drawn, so resuming redraws them.

        The weights, Adam's moments and the step count are in :meth:`save`'s file.
        """
        return {"rng": self._rng_before_draw}

    def restore_state(self, state: dict[str, Any], directory: Path) -> None:
        """Restore the generator and redraw the perturbations of the next episode."""
        super().restore_state(state, directory)
        self._draw()
