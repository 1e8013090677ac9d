"""The priors: the joint action an untrained learner plays, and the reserve rule they start from.

Q starts at 0 and, among the actions of greatest Q, the prior's choice wins (docs/learners.md,
"Exploration and ties"), so an untrained learner plays its prior exactly:

* ``greedy``: the plain auction (:func:`mrta_rl.rules.greedy`): every idle robot bids for its
  lowest valid slot; with conflict pruning, only each slot's auction winner keeps its bid
  (:func:`mrta_rl.rules.deconflict`, spec step 5).
* ``spread``: idle robots bid for distinct slots, in slot order, robots asked in a fixed order
  (:func:`mrta_rl.rules.spread` in the order of :func:`spread_order`).
* ``spread_wait``: ``spread`` under a mask that holds L slots while an H task of the group's types
  arrived recently (the learner builds that mask).

The rules are :mod:`mrta_rl.rules`' compiled ones, called from the learners' kernels; this module
names the priors and the robot orders.

:class:`TeamReserveRule` is the reserve rule over a grouping of the robots, which the fixed
learners ``team_reserve`` and ``subg_reserve`` play
(:class:`~mrta_rl.learners.fixed.TeamReserveLearner`).
:class:`HoldRule` is the prior ``hold`` of DQL and of the neural learners (:data:`HOLD_PRIORS`):
that rule on the whole team, computed from the env at each decision, so every learner that
starts from it plays the same rule. This module imports no learner.
The neural learners' other priors are computed from the env the same way (:class:`GreedyPrior`,
and :class:`SpreadWaitPrior` for subG-DQN) and reach the networks as an input, so no network
computes a rule again.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Annotated

import numpy as np

from mrta_rl import rules
from mrta_rl.config import Range
from mrta_rl.envs import AuctionEnv
from mrta_rl.envs.encodings import N_RECENCY_LEVELS, recency_level
from mrta_rl.partition import Partition, subg_partition

PRIORS = ("greedy", "spread", "spread_wait")  # tie-break joint action of an untrained state
PRIOR_ORDERS = ("index", "fewest_types")  # which idle robot the spread priors ask first
PRIOR_CODES = {name: k for k, name in enumerate(PRIORS)}  # the kernels' integer codes
HOLD_PRIORS = ("greedy", "hold")  # DQL's and the neural learners' prior: plain auction or rule
JOINT_PRIORS = ("greedy", "spread_wait")  # what an untrained subG-DQN plays


# the rule's settings, declared once for team_reserve, subg_reserve and the hold priors
# (mrta_rl.config checks them against these declarations before anything is built)
Reserve = Annotated[int, Range(0)]  # idle robots kept back for H work
HoldLevel = Annotated[int, Range(0, N_RECENCY_LEVELS)]  # recency level below which L waits
GROUPINGS = ("team", "subg")  # one group of all robots, or the subG sub-groups
HOLD_SCOPES = ("group", "robot")  # whose recency level holds an L bid back
ORDERS = ("fewest_types", "index")  # which idle robot of a group is asked first


class TeamReserveRule:
    """The reserve rule over a grouping of the robots: ``team_reserve``'s bids in any state.

    Per group ``G`` and copy it bids :func:`mrta_rl.rules.reserve`: H slots first, then L slots,
    one robot per slot, so no bid is lost (spec step 7), robots asked in ``order``. An L bid
    needs at least ``reserve`` other idle robots of ``G`` left without a bid, and a robot whose
    recency level is at least ``hold_level`` (``hold_scope="group"``: the level over the group's
    types ``T_g``; ``"robot"``: over the robot's own ``Lambda_i``). ``hold_level=1``: no such H
    task arrived within 3 ticks; ``0``: never hold; ``2``: within 10 ticks; ``3``: never bid for
    L. The fixed learners ``team_reserve`` and
    ``subg_reserve`` (:class:`~mrta_rl.learners.fixed.TeamReserveLearner`) play it, and the
    ``hold`` prior (:class:`HoldRule`) is it on the whole team.

    Args:
        env: The env: ``Lambda_i`` of the robots and, for ``grouping="subg"``, its system.
        reserve: Idle robots a group keeps back for H work when bidding for an L task.
        hold_level: L slots wait while the recency level is below this (0 = never).
        hold_scope: ``"group"`` or ``"robot"``: whose recency level ``hold_level`` reads.
        grouping: ``"team"`` (one group of all robots) or ``"subg"`` (the sub-groups of
            ``partition``, else of the subG partition of the env's system).
        order: ``"fewest_types"`` (fewest active types first, ties to the lowest index, so
            versatile robots stay free) or ``"index"`` (lowest index first).
        partition: The subG partition of ``grouping="subg"`` (None: computed from the env).
    """

    def __init__(
        self,
        env: AuctionEnv,
        *,
        reserve: int,
        hold_level: int,
        hold_scope: str = "group",
        grouping: str = "team",
        order: str = "fewest_types",
        partition: Partition | None = None,
    ) -> None:
        self.reserve, self.hold_level, self.hold_scope = reserve, hold_level, hold_scope
        active = env.active_tasks  # Lambda_i, [m, n]
        if grouping == "team":
            groups = [list(range(env.n_robots))]
        else:
            partition = partition or subg_partition(env.system)
            groups = [
                [env.system.robots.index(r) for r in robots]
                for robots in partition.group_map().values()
            ]
        self.groups = []  # (robots in bidding preference order, T_g)
        for ids in groups:
            ids = np.asarray(ids, np.int64)
            if order == "fewest_types":
                ids = np.sort(ids)  # ties go to the lowest index
                ids = ids[rules.fewest_types_first(active[ids])]
            self.groups.append((ids, active[ids].any(axis=0)))
        # the recency scope of each robot: its group's types T_g, or its own Lambda_i
        self.scope = active.copy()
        if hold_scope == "group":
            for robots, types in self.groups:
                self.scope[robots] = types

    def encode(self, env: AuctionEnv) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Slot priorities ``[B, K]``, idle flags ``[B, m]``, recency levels ``[B, m]``.

        The mask alone cannot tell an idle robot with nothing to bid for from a busy one, and the
        reserve counts every idle robot of the group. Robot ``i``'s recency level is over its
        ``hold_scope``: its group's types or its own.
        """
        return env.slot_high.copy(), env.idle.copy(), recency_level(env, self.scope)

    def act(self, view: tuple[np.ndarray, np.ndarray, np.ndarray], mask: np.ndarray) -> np.ndarray:
        """The rule's bids.

        Args:
            view: Slot priorities, idle flags and recency levels from :meth:`encode`.
            mask: ``[B, m, K + 1]`` bool valid actions.

        Returns:
            ``[B, m]`` int64 conflict-free actions.
        """
        slot_high, idle, recency = view
        actions = np.zeros(mask.shape[:2], np.int64)
        may_take_low = recency >= self.hold_level  # [B, m]
        for robots, _ in self.groups:
            rules.reserve_actions(
                mask, slot_high, idle, may_take_low, robots, self.reserve, actions
            )
        return actions

    def __call__(self, env: AuctionEnv, mask: np.ndarray | None = None) -> np.ndarray:
        """``[B, m]`` int64 the rule's actions in the env's state (mask: default the env's)."""
        return self.act(self.encode(env), env.action_mask if mask is None else mask)


class HoldRule(TeamReserveRule):
    """The prior ``hold``: the whole-team ``team_reserve`` rule's action of every robot.

    The rule (whole team, ``fewest_types`` order) reads what a robot's local view lacks (the
    other robots' idleness, which robot the team asks first), so it is computed from the env,
    not from a learner's observation.

    Args:
        env: The env (sizes and ``Lambda_i``; the rule is evaluated on the env it is called with).
        reserve: The rule's ``reserve``.
        hold_level: The rule's ``hold_level``.
        hold_scope: The rule's ``hold_scope``.
    """

    def __init__(self, env: AuctionEnv, *, reserve: int, hold_level: int, hold_scope: str):
        super().__init__(env, reserve=reserve, hold_level=hold_level, hold_scope=hold_scope)


def spread_order(active_tasks: np.ndarray, rule: str) -> np.ndarray:
    """The order in which the spread priors ask a group's robots (:data:`PRIOR_ORDERS`).

    Args:
        active_tasks: ``[m_g, n]`` bool ``Lambda_i`` of the group's robots, in group order.
        rule: ``"index"`` (lowest index first) or ``"fewest_types"`` (robots with the fewest
            active types first, ties to the lowest index: versatile robots stay free for the
            types only they can do).

    Returns:
        ``[m_g]`` int64 permutation of the group's robot positions.

    Raises:
        ValueError: on an unknown rule.
    """
    if rule not in PRIOR_ORDERS:
        raise ValueError(f"prior_order must be one of {PRIOR_ORDERS}, got {rule!r}")
    if rule == "index":
        return np.arange(len(active_tasks))
    return rules.fewest_types_first(active_tasks)


class GreedyPrior:
    """The neural learners' prior ``greedy``: the plain auction's bid (:func:`rules.greedy`).

    A robot without a valid bid has no prior action (-1), not waiting: the bonus of the neural
    learners goes to the auction's bid only.
    """

    def __call__(self, env: AuctionEnv, mask: np.ndarray | None = None) -> np.ndarray:
        """``[B, m]`` int64 the lowest valid bid of every robot, else -1 (mask: the env's)."""
        bids = rules.greedy_actions(env.action_mask if mask is None else mask)
        return np.where(bids > 0, bids, -1)


class SpreadWaitPrior:
    """The prior ``spread_wait`` of subG-CQL, per group: what an untrained subG-DQN plays.

    In each group, L slots wait while an H task of the group's types ``T_g`` arrived within 3
    ticks (recency level 0), and the idle robots, asked in the ``prior_order``, bid for distinct
    slots in slot order: :func:`rules.reserve` with nothing kept back.

    Args:
        env: The env (``Lambda_i`` of the robots; the prior is evaluated on the env it is called
            with).
        groups: Robot indices of each group.
        prior_order: :data:`PRIOR_ORDERS`, the order of :func:`spread_order` within a group.
    """

    def __init__(self, env: AuctionEnv, groups: Sequence[Sequence[int]], prior_order: str):
        self.orders = []  # per group, its robots in the order they are asked
        for robots in groups:
            robots = np.asarray(robots, np.int64)
            self.orders.append(robots[spread_order(env.active_tasks[robots], prior_order)])
        self.types = np.stack([env.active_tasks[robots].any(axis=0) for robots in self.orders])

    def __call__(self, env: AuctionEnv, mask: np.ndarray | None = None) -> np.ndarray:
        """``[B, m]`` int64 the prior's actions in the env's state (mask: default the env's)."""
        mask = env.action_mask if mask is None else mask
        may_take_low = recency_level(env, self.types) >= 1  # [B, G]: no H of T_g within 3 ticks
        actions = np.zeros(mask.shape[:2], np.int64)
        for g, order in enumerate(self.orders):
            group_may = np.repeat(may_take_low[:, g : g + 1], mask.shape[1], axis=1)  # [B, m]
            rules.reserve_actions(mask, env.slot_high, env.idle, group_may, order, 0, actions)
        return actions
