"""``rollout``: an online planner that scores a few candidate joint actions by simulation.

At each decision point it takes, per copy, the joint actions of a few candidate rules (greedy,
spread, reserve or hold variants, see :data:`CANDIDATES`) and scores each by rolling copies of the
env forward ``horizon`` ticks: the candidate's action at the current tick, then the ``base``
policy, under ``samples`` sampled futures of the arrivals. The candidate with the highest mean
rollout return is played (ties to the base policy). Every candidate is scored on the same sampled
futures (common random numbers), so their differences are not drowned by arrival noise.

The base policy is a rule of :data:`CANDIDATES` (``base=hold_group``) or a trained run
(``base=<run dir>``: a path, a run dir of ``scripts/train.py`` on the same team, or of a policy
that fits any team, such as a family's, which plays this team as ``init=`` plays it). The planner
loads no run: :meth:`RolloutPlanner.base_run` tells the runner which value is a run dir, and the
runner rebuilds that run from its own config, read as data, with its saved learner state, as
re-evaluation does, and hands its trained learner to the planner (``base_policy``, a runner
argument like ``env``). It plays on the rollout copies through its own ``encode`` / ``act``
without exploration. Its own action at the current tick is then one more candidate, ``base``,
scored first (ties go to it), so planning can only improve on the learned policy in expectation.
A value that names a rule is the rule: write ``./hold`` for a run dir named ``hold``.

``neighbours`` adds local candidates around the base policy's joint action (:func:`neighbours`):
the base action with one of its bids dropped (``drop``: that robot waits) or with one waiting
robot bidding for a slot that no bid of the base action takes (``add``). The rules' joint
actions are whole-team changes, far from a good learned action; a neighbour changes one robot's
bid, so the planner can improve such a base one bid at a time. Neighbours are valid under the
mask and add no conflict (an added bid's slot has no other bidder).

This is a reference, not a learner: it reads the full env state (queue, busy times, batteries),
which no learner's observation holds, and it knows the arrival process of the spec. It has no
training (``kind = "fixed"``). ``horizon=0``, or a single candidate without neighbours, plays
the base policy. Its decision time per tick (candidates and rollouts) goes into
``metrics.json`` (:meth:`RolloutPlanner.decision_time`).

Copies are snapshot, restored and re-seeded with the env's own exact ``AuctionEnv.get_state`` /
``set_state`` / ``reseed`` (docs/spec/auction_env.md); ``reseed`` draws the future arrivals of a
copy from a new key, so its queue and robots stay those of the snapshot.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Annotated, Any, ClassVar

import numpy as np

from mrta_rl.config import Choices, ConfigError, Range
from mrta_rl.envs import AuctionEnv
from mrta_rl.learners.base import FixedLearner, Learner
from mrta_rl.learners.fixed import GreedyLearner, TeamReserveLearner

logger = logging.getLogger(__name__)
LOG_EVERY = 250  # planned ticks between two decision-time log lines
CLOCK: Callable[[], float] = time.perf_counter  # the decision time's clock (tests: a fake one)

# candidate rule name -> its team_reserve settings (mrta_rl/learners/fixed.py; None: the plain
# auction). "hold" and "hold_reserve1" are the best whole-team rules of experiment=team_reserve_grid
# (System-I and System-II: L waits while an H task of the robot's OWN types arrived within 3
# ticks); "hold_group" waits on the group's types instead (with grouping=subg: the subg_reserve
# rule, subG-CQL's starting policy). All are conflict-free except greedy.
CANDIDATES: dict[str, dict[str, Any] | None] = {
    "greedy": None,
    "spread": {"reserve": 0, "hold_level": 0, "hold_scope": "group"},
    "hold": {"reserve": 0, "hold_level": 1, "hold_scope": "robot"},
    "hold_reserve1": {"reserve": 1, "hold_level": 1, "hold_scope": "robot"},
    "hold_group": {"reserve": 0, "hold_level": 1, "hold_scope": "group"},
    "hold2": {"reserve": 0, "hold_level": 2, "hold_scope": "robot"},
    "reserve1": {"reserve": 1, "hold_level": 0, "hold_scope": "group"},
    "reserve2": {"reserve": 2, "hold_level": 0, "hold_scope": "group"},
    "high_only": {"reserve": 0, "hold_level": 3, "hold_scope": "group"},  # never bids for L
}


BASE_RUN = "base"  # the candidate name of a trained base policy's own action
# local moves around the base policy's joint action (neighbours())
NEIGHBOURS = ("drop", "add")


def neighbours(action: np.ndarray, mask: np.ndarray, kinds: tuple[str, ...]) -> np.ndarray:
    """The joint actions one bid away from ``action``, per copy (module docstring).

    ``drop``: one row per robot ``i``, ``action`` with robot ``i`` waiting. ``add``: one row per
    robot ``i`` and slot ``k`` (robot-major), ``action`` with robot ``i`` bidding for ``k``,
    where robot ``i`` waits in ``action``, the bid is valid under ``mask`` and no robot bids for
    ``k`` in ``action``. A move that does not apply to a copy leaves its row equal to ``action``
    (the planner rolls out each distinct joint action once). Rows come in the order of ``kinds``.

    Args:
        action: ``[B, m]`` int joint actions (0 = wait, ``k`` = bid for slot ``k``).
        mask: ``[B, m, K + 1]`` bool valid actions.
        kinds: Moves of :data:`NEIGHBOURS`.

    Returns:
        ``[N, B, m]`` joint actions; ``N`` = ``m`` per ``drop`` and ``m * K`` per ``add``.
    """
    n_copies, m = action.shape
    n_slots = mask.shape[2] - 1
    rows = []
    for kind in kinds:
        if kind == "drop":
            moved = np.repeat(action[None], m, axis=0)  # [m, B, m]
            moved[np.arange(m), :, np.arange(m)] = 0
            rows.append(moved)
        elif kind == "add":
            slots = np.arange(1, n_slots + 1)
            taken = (action[:, :, None] == slots).any(axis=1)  # [B, K]: some robot bids for k
            ok = (action == 0)[:, :, None] & mask[:, :, 1:] & ~taken[:, None, :]  # [B, m, K]
            moved = np.repeat(action[None], m * n_slots, axis=0)  # [m * K, B, m]
            for i in range(m):
                for k in range(n_slots):
                    moved[i * n_slots + k, :, i] = np.where(ok[:, i, k], k + 1, action[:, i])
            rows.append(moved)
    if not rows:
        return np.empty((0, n_copies, m), action.dtype)
    return np.concatenate(rows)


def is_rule(base: str) -> bool:
    """True if ``learner.base`` names a rule of :data:`CANDIDATES`, not a run dir."""
    return base in CANDIDATES


def restore(env: AuctionEnv, state: dict[str, np.ndarray], rows: np.ndarray) -> None:
    """Load copy ``rows[i]`` of ``state`` (``AuctionEnv.get_state``) into copy ``i`` of ``env``.

    ``env.batch_size`` must equal ``len(rows)``; rows may repeat (one state, many copies).
    """
    env.set_state({name: array[rows] for name, array in state.items()})


class RolloutPlanner(FixedLearner):
    """Online rollout planner over candidate rules (module docstring).

    Args:
        samples: Sampled futures of the arrivals per candidate (common to all candidates).
        horizon: Ticks rolled forward per rollout (the candidate's tick included); 0 = no planning.
        candidates: Names of candidate rules (:data:`CANDIDATES`); the base policy is always one.
        base: The policy that plays after the first tick of a rollout, and on ties: the name of
            a rule of :data:`CANDIDATES`, or a run dir of ``scripts/train.py`` on the same team or
            of a policy that fits any team (module docstring).
        base_policy: The trained learner of the run dir ``base`` names, supplied by the runner
            (:meth:`base_run`); None for a rule.
        gamma: Discount per tick of the rollout return (1 = plain sum).
        neighbours: Local candidates around the base policy's joint action (:func:`neighbours`):
            ``drop`` (one bid dropped), ``add`` (one waiting robot bids for a free slot).
        margin: A candidate replaces the base policy's action only where its mean rollout
            return beats the base's by more than ``margin`` standard errors of their paired
            difference over the samples (the futures are common to both); among those, the
            highest lower bound ``mean - margin * se`` wins. 0: the highest mean return wins.
            A learned base is already good: its rollouts' noise, not their mean, then decides
            most switches, and a margin keeps them out.
        **kwargs: Env, generator and partition of :class:`~mrta_rl.learners.base.Learner`.

    Raises:
        ConfigError: on a setting outside its declaration, or a ``base`` that is neither a rule
            nor a run dir, naming ``learner.base``.
        ValueError: if ``base`` names a run dir and no ``base_policy`` is given, or a rule and
            one is.
    """

    label: ClassVar[str] = "rollout"
    # the candidates' grouping (team_reserve's): one group of all robots, or the subG sub-groups
    grouping: ClassVar[str] = "team"

    def __init__(
        self,
        *,
        samples: Annotated[int, Range(1)],
        horizon: Annotated[int, Range(0)],
        candidates: Annotated[tuple[str, ...], Choices(*CANDIDATES)],
        base: str,
        gamma: Annotated[float, Range(0, 1, low_open=True)],
        margin: Annotated[float, Range(0)],
        neighbours: Annotated[tuple[str, ...], Choices(*NEIGHBOURS)],
        base_policy: Learner | None = None,
        **kwargs,
    ) -> None:
        super().__init__(**kwargs)  # types and ranges: the annotations (mrta_rl.config)
        self.samples, self.horizon, self.gamma, self.margin = samples, horizon, gamma, margin
        self.neighbours = neighbours
        run_dir = self.base_run({"base": base})
        if (run_dir is None) != (base_policy is None):
            raise ValueError(
                f"learner.base={base!r}: the runner passes base_policy exactly when base names a "
                f"run dir ({'none' if base_policy is None else 'one'} given)"
            )
        if base_policy is None:
            names = [base, *(c for c in candidates if c != base)]  # the base first: ties to it
            self._rules = [self._rule(CANDIDATES[name]) for name in names]
        else:
            names = [BASE_RUN, *candidates]  # the learned action first: ties go to it
            self._rules = [base_policy, *(self._rule(CANDIDATES[name]) for name in candidates)]
        self.names = names
        self._base = self._rules[0]
        self._rollout_envs: dict[int, AuctionEnv] = {}  # batch size -> env
        self.candidate_returns = np.empty((0, 0))  # [C, B] of the last decision (_plan)
        self.decisions = 0  # ticks at which some copy had candidates to compare
        self.planning_s = 0.0  # wall time spent in those decisions
        self.ticks = 0  # decisions made (calls of act)
        self.decision_s = 0.0  # wall time of encode and act: candidates and rollouts

    @classmethod
    def base_run(cls, settings: Mapping[str, Any]) -> Path | None:
        """The run dir ``base`` names, or None for a rule (:meth:`Learner.base_run`).

        Raises:
            ConfigError: naming ``learner.base`` for a bare word that is no rule and no path (a
                misspelt rule).
        """
        base = settings.get("base")
        if not isinstance(base, str) or is_rule(base):
            return None
        run_dir = Path(base)
        if not run_dir.exists() and len(run_dir.parts) == 1:  # a bare word: a misspelt rule
            rules = ", ".join(repr(name) for name in CANDIDATES)
            raise ConfigError(
                f"learner.base: must be one of {rules} or a run dir of scripts/train.py, got "
                f"{base!r}"
            )
        return run_dir

    def _rule(self, settings: dict[str, Any] | None) -> Learner:
        """The fixed policy of a candidate's settings, on the planner's env and partition."""
        if settings is None:
            return GreedyLearner(env=self.env, rng=self.rng)
        return TeamReserveLearner(
            env=self.env,
            rng=self.rng,
            partition=self.partition,
            grouping=self.grouping,
            order="fewest_types",
            **settings,
        )

    def encode(self, env: AuctionEnv) -> tuple[Any, np.ndarray]:
        """A snapshot of every copy and the candidates' joint actions ``[C, B, m]``.

        The rules' actions (the base's first), then the base action's :func:`neighbours`.
        """
        start = CLOCK()
        mask = env.action_mask
        actions = np.stack(
            [rule.act(rule.encode(env), mask, explore=False) for rule in self._rules]
        )
        if self.neighbours:
            actions = np.concatenate([actions, neighbours(actions[0], mask, self.neighbours)])
        state = env.get_state()
        self.decision_s += CLOCK() - start
        return state, actions

    def base_action(self, env: AuctionEnv) -> np.ndarray:
        """The base policy's joint action ``[B, m]`` at ``env``'s decision point, unplanned."""
        return self._base.act(self._base.encode(env), env.action_mask, explore=False)

    def act(self, view: tuple[Any, np.ndarray], mask: np.ndarray, *, explore: bool) -> np.ndarray:
        """The candidate with the best mean rollout return, per copy.

        Args:
            view: Snapshot and candidate actions from :meth:`encode`.
            mask: ``[B, m, K + 1]`` bool valid actions (every candidate is valid under it).
            explore: Unused: the planner has no exploration.

        Returns:
            ``[B, m]`` int64 actions.
        """
        start = CLOCK()
        chosen = self._plan(view)
        self.ticks += 1
        self.decision_s += CLOCK() - start
        return chosen

    def _plan(self, view: tuple[Any, np.ndarray]) -> np.ndarray:
        """:meth:`act` itself (timed there)."""
        state, actions = view
        chosen = actions[0].copy()  # the base policy
        # each candidate's mean rollout return per copy (-inf: not rolled out), for a student
        # that learns from the candidates' scores (learners/neural/expert_iteration.py)
        self.candidate_returns = np.full((len(actions), chosen.shape[0]), -np.inf)
        # copies where some candidate differs from the base rule: only they need planning
        plan = np.flatnonzero((actions != actions[0]).any(axis=(0, 2)))
        if self.horizon == 0 or len(actions) == 1 or len(plan) == 0:
            return chosen
        start = CLOCK()
        n_cand, n_plan, S = len(actions), len(plan), self.samples
        # a candidate equal to an earlier one for a copy is not rolled out again
        same = (actions[:, None, plan] == actions[None, :, plan]).all(axis=-1)  # [C, C, P]
        earlier = np.tril(np.ones((n_cand, n_cand), bool), -1)[:, :, None]
        pairs = np.argwhere(~(same & earlier).any(axis=1).T)  # [(p, c)], by copy then candidate
        # rollout rows: each (copy, candidate) pair once per sample
        row_pair = np.repeat(np.arange(len(pairs)), S)
        copy, cand = pairs[row_pair, 0], pairs[row_pair, 1]
        seeds = self.rng.integers(0, 2**62, size=(n_plan, S))  # one future per (copy, sample)
        env = self._rollout_env(len(row_pair))
        restore(env, state, plan[copy])
        env.reseed(None, seeds[copy, np.tile(np.arange(S), len(pairs))])
        returns = self._roll(env, actions[cand, plan[copy]]).reshape(len(pairs), S)
        self.candidate_returns[pairs[:, 1], plan[pairs[:, 0]]] = returns.mean(axis=1)
        best = self._choose(returns, pairs, n_plan, n_cand)
        chosen[plan] = actions[best, plan]
        self.decisions += 1
        self.planning_s += CLOCK() - start
        if self.decisions % LOG_EVERY == 0:
            logger.info(
                "rollout: %d planned ticks, %.2f ms per planned tick (%d copies planned now)",
                self.decisions,
                1000 * self.planning_s / self.decisions,
                n_plan,
            )
        return chosen

    def _choose(
        self, returns: np.ndarray, pairs: np.ndarray, n_plan: int, n_cand: int
    ) -> np.ndarray:
        """The chosen candidate per planned copy (``margin`` in the class docstring).

        Args:
            returns: ``[len(pairs), S]`` rollout returns of each rolled (copy, candidate) pair.
            pairs: ``[(p, c)]`` the rolled pairs; every copy's base (``c = 0``) is among them.
            n_plan: Planned copies.
            n_cand: Candidates.

        Returns:
            ``[n_plan]`` candidate indices; ties go to the base policy (index 0).
        """
        score = np.full((n_plan, n_cand), -np.inf)
        if self.margin == 0:
            score[pairs[:, 0], pairs[:, 1]] = returns.mean(axis=1)
            return score.argmax(axis=1)  # first maximum: ties go to the base policy (index 0)
        base = np.empty((n_plan, returns.shape[1]))
        is_base = pairs[:, 1] == 0
        base[pairs[is_base, 0]] = returns[is_base]
        diff = returns - base[pairs[:, 0]]  # paired over the common futures
        se = diff.std(axis=1, ddof=1) / np.sqrt(diff.shape[1]) if diff.shape[1] > 1 else 0.0
        lower = diff.mean(axis=1) - self.margin * se
        score[pairs[:, 0], pairs[:, 1]] = np.where(is_base | (lower > 0), lower, -np.inf)
        score[:, 0] = 0.0  # the base: a candidate must beat it by the margin
        return score.argmax(axis=1)

    def _roll(self, env: AuctionEnv, first: np.ndarray) -> np.ndarray:
        """Play ``first``, then the base policy, up to ``horizon`` ticks; returns ``[N]``."""
        returns = np.zeros(env.batch_size)
        discount = 1.0
        actions = first
        for tick in range(self.horizon):
            if env.done.any():  # the episode ends inside the horizon: no reward after it
                break
            if tick:
                actions = self._base.act(self._base.encode(env), env.action_mask, explore=False)
            returns += discount * env.step(actions, validated=tick > 0).team_reward
            discount *= self.gamma
        return returns

    def _rollout_env(self, batch_size: int) -> AuctionEnv:
        """A scratch env of ``batch_size`` copies: the learner env's system, params, ``Lambda``."""
        env = self._rollout_envs.get(batch_size)
        if env is None:
            env = AuctionEnv(
                self.env.system,
                self.env.params,
                batch_size=batch_size,
                active_tasks=self.env.active_tasks,
            )
            self._rollout_envs[batch_size] = env
        return env

    def learning_space(self) -> dict[str, int]:
        """No table: ``{}`` (a fixed policy)."""
        return {}

    def decision_time(self) -> dict[str, float]:
        """Mean wall time per decision (``encode`` and ``act``: candidates, rollouts) and total.

        A decision is one tick of all the env's copies at once (evaluation: ``eval.batch_size``).

        Returns:
            ``{"ms_per_tick", "total_s", "ticks", "planned_ticks"}``; ``planned_ticks``: the
            ticks at which some copy had differing candidates to roll out. ``{}`` before any.
        """
        if not self.ticks:
            return {}
        return {
            "ms_per_tick": round(1000 * self.decision_s / self.ticks, 4),
            "total_s": round(self.decision_s, 4),
            "ticks": self.ticks,
            "planned_ticks": self.decisions,
        }


class SubGRolloutPlanner(RolloutPlanner):
    """``rollout`` bound to the subG partition: how far a planner gets inside it.

    The runner builds its env on the partition's ``Lambda_i`` (robots bid only for their kept
    types) and every candidate rule bids per sub-group (``grouping="subg"``); the base
    ``hold_group`` is then the ``subg_reserve`` rule, subG-CQL's starting policy. Its margin over
    ``subg_reserve`` measures what a partition-bound policy can still gain, with the planner's
    full view of the state. Its settings are :class:`RolloutPlanner`'s; its yaml compares six
    of the nine candidates (all nine do worse on System-I, docs/notebook.md).
    """

    label: ClassVar[str] = "subg_rollout"
    requires_partition: ClassVar[bool] = True
    grouping: ClassVar[str] = "subg"
