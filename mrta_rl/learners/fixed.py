"""Fixed allocation policies: the spec's greedy, random and high_only, and the subG rule.

They are learners with ``kind = "fixed"`` and the base class's no-op ``update``, so the runner
evaluates them exactly like trained learners. ``greedy`` is the plain auction without learning,
the baseline every run reports next to its learner. ``team_reserve`` and ``subg_reserve`` are not
in the spec: a hand-written reserve rule over a grouping of the robots (the whole team, or the
subG sub-groups on the partition), yardsticks of what a rule on the learners' signals reaches.
All are vectorised over ``[B, m]``.
"""

from __future__ import annotations

from typing import Annotated, ClassVar

import numpy as np

from mrta_rl.config import Choices, Range
from mrta_rl.envs import AuctionEnv
from mrta_rl.envs.encodings import N_RECENCY_LEVELS, recency_level
from mrta_rl.learners.base import FixedLearner
from mrta_rl.partition import subg_partition


def lowest_valid_bid(bid_mask: np.ndarray) -> np.ndarray:
    """Lowest-numbered slot with a True bid, or 0 (wait) when there is none.

    A loop over the tiny slot axis (K = 3 by default) beats ``argmax`` on such a short last axis.

    Args:
        bid_mask: ``[B, m, K]`` bool, True where bidding for slot ``k + 1`` is allowed.

    Returns:
        ``[B, m]`` int64 actions in ``0..K``.
    """
    actions = np.zeros(bid_mask.shape[:2], dtype=np.int64)
    for k in reversed(range(bid_mask.shape[2])):
        actions = np.where(bid_mask[:, :, k], k + 1, actions)
    return actions


def fewest_types_first(active: np.ndarray, robots: list[int] | range) -> np.ndarray:
    """``robots`` in ``team_reserve``'s bidding order: fewest active types first, then index.

    Versatile robots are asked last, so they stay free for the tasks only they can do.

    Args:
        active: ``[m, n]`` bool ``Lambda_i``.
        robots: Robot indices.

    Returns:
        The indices, reordered, as int64.
    """
    return np.asarray(sorted(robots, key=lambda i: (active[i].sum(), i)), np.int64)


class GreedyLearner(FixedLearner):
    """Plain auction (spec "Fixed policies"): idle robots bid for their lowest-numbered valid slot.

    Slot 1 holds the most urgent task (spec step 3), so greedy bids for the most urgent task the
    robot may do. A busy robot has only action 0 in the mask, so it waits.
    """

    label: ClassVar[str] = "greedy"

    def act(self, view: None, mask: np.ndarray, *, explore: bool) -> np.ndarray:
        """Bid for the lowest-numbered valid slot, else wait.

        Args:
            view: Unused (None).
            mask: ``[B, m, K + 1]`` bool valid actions.
            explore: Unused: the policy is deterministic.

        Returns:
            ``[B, m]`` int64 actions.
        """
        return lowest_valid_bid(mask[:, :, 1:])


class SubGGreedyLearner(GreedyLearner):
    """Greedy on the subG partition: the plain auction, each robot bidding only for ``Lambda_i``.

    The switch-cost study (issue 11) compares it with greedy on the whole team: the partition's
    specialization can only pay when switching task types costs time (``env.switch_ticks``).
    """

    label: ClassVar[str] = "subG-greedy"
    requires_partition: ClassVar[bool] = True


class RandomLearner(FixedLearner):
    """Random bidding (spec "Fixed policies"): uniform over the ``v`` valid bids plus waiting.

    A robot with ``v`` valid bids picks each of its ``v + 1`` choices with probability
    ``1 / (v + 1)``; a busy robot (``v = 0``) waits.
    """

    label: ClassVar[str] = "random"

    def act(self, view: None, mask: np.ndarray, *, explore: bool) -> np.ndarray:
        """Draw one valid action per robot uniformly from ``self.rng``.

        Args:
            view: Unused (None).
            mask: ``[B, m, K + 1]`` bool valid actions; action 0 (wait) is always valid.
            explore: Unused: the policy is random in evaluation too, by definition.

        Returns:
            ``[B, m]`` int64 actions.
        """
        running = np.cumsum(mask, axis=2)  # [B, m, K + 1]; running[..., 0] = 1 (wait is valid)
        choice = self.rng.integers(0, running[:, :, -1])  # [B, m], uniform in 0..v
        # the valid action of rank `choice` is the number of places whose running count is <= it
        return (running <= choice[:, :, None]).sum(axis=2).astype(np.int64)


class HighOnlyLearner(FixedLearner):
    """Wait for high priority (spec "Fixed policies"): bid only for H tasks.

    Every idle robot bids for its lowest-numbered valid slot holding an H task, else waits.
    """

    label: ClassVar[str] = "high-only"

    def encode(self, env: AuctionEnv) -> np.ndarray:
        """The slot priorities, the only part of the state this policy reads.

        Args:
            env: The env at a decision point.

        Returns:
            ``[B, K]`` int copy of ``env.slot_high`` (1 = H, 0 = L, -1 = empty).
        """
        return env.slot_high.copy()

    def act(self, view: np.ndarray, mask: np.ndarray, *, explore: bool) -> np.ndarray:
        """Bid for the lowest-numbered valid H slot, else wait.

        Args:
            view: ``[B, K]`` slot priorities from :meth:`encode`.
            mask: ``[B, m, K + 1]`` bool valid actions.
            explore: Unused: the policy is deterministic.

        Returns:
            ``[B, m]`` int64 actions.
        """
        return lowest_valid_bid(mask[:, :, 1:] & (view[:, None, :] == 1))


# the rule's two numbers, declared once for team_reserve and subg_reserve (mrta_rl.config)
Reserve = Annotated[int, Range(0)]  # idle robots kept back for H work
HoldLevel = Annotated[int, Range(0, N_RECENCY_LEVELS)]  # recency level below which L waits
GROUPINGS = ("team", "subg")  # team_reserve: one group of all robots, or the subG sub-groups
HOLD_SCOPES = ("group", "robot")  # whose recency level holds an L bid back
ORDERS = ("fewest_types", "index")  # which idle robot of a group is asked first


class TeamReserveLearner(FixedLearner):
    """A hand-written reserve rule over any grouping of the robots: a yardstick for the learners.

    It reads no more than a centralized learner's group view (spec "Observations": slot contents,
    which robots are idle, the recency level of an H arrival) and bids for the robots' active
    types ``Lambda_i`` only. Per group ``G`` and copy:

    1. H slots, in slot order: the group's idle robot that may bid and comes first in ``order``
       (``fewest_types``: fewest active types first, ties to the lowest index, so versatile robots
       stay free; ``index``: lowest index) bids. No two robots bid for the same slot, so no bid is
       lost (spec step 7 counts a lost bid as busy time).
    2. L slots, in slot order, the same way, but only while at least ``reserve`` other robots of
       ``G`` stay idle after the bid, and only by a robot whose recency level is at least
       ``hold_level`` (``hold_scope="group"``: the level over the group's types ``T_g``;
       ``"robot"``: over the robot's own ``Lambda_i``). ``hold_level=1``: no such H task arrived
       within 3 ticks; ``0``: never hold; ``2``: within 10 ticks; ``3``: never bid for L.

    ``grouping="team"`` (default) is one group of all robots; ``"subg"`` the sub-groups of the
    subG partition (paper §4), computed from the env's system if the runner gave none. On the
    partitioned env, ``grouping="subg"`` is the ``subg_reserve`` rule (:class:`SubGReserveLearner`).
    ``experiment=team_reserve_grid`` sweeps the parameters per system.

    Args:
        reserve: Idle robots a group keeps back for H work when bidding for an L task.
        hold_level: L slots wait while the recency level is below this (0 = never).
        hold_scope: ``"group"`` or ``"robot"``: whose recency level ``hold_level`` reads.
        grouping: ``"team"`` or ``"subg"``.
        order: ``"fewest_types"`` or ``"index"``: the bidding preference inside a group.
        **kwargs: Env, generator and partition of :class:`~mrta_rl.learners.base.Learner`.

    Raises:
        ConfigError: on a negative ``reserve``, a ``hold_level`` outside 0..3 or an unknown
            ``hold_scope``, ``grouping`` or ``order`` (the declarations of the signature).
    """

    label: ClassVar[str] = "team_reserve"
    _rule_name: ClassVar[str] = "team_reserve"  # in error messages

    def __init__(
        self,
        *,
        reserve: Reserve = 0,
        hold_level: HoldLevel = 1,
        hold_scope: Annotated[str, Choices(*HOLD_SCOPES)] = "group",
        grouping: Annotated[str, Choices(*GROUPINGS)] = "team",
        order: Annotated[str, Choices(*ORDERS)] = "fewest_types",
        **kwargs,
    ) -> None:
        super().__init__(**kwargs)  # types, ranges and choices: the annotations (mrta_rl.config)
        self.reserve, self.hold_level, self.hold_scope = reserve, hold_level, hold_scope
        active = self.env.active_tasks  # Lambda_i, [m, n]
        if grouping == "team":
            groups = [list(range(self.n_robots))]
        else:
            partition = self.partition or subg_partition(self.env.system)
            groups = [
                [self.env.system.robots.index(r) for r in robots]
                for robots in partition.group_map().values()
            ]
        self._groups = []  # (robots in bidding preference order, T_g)
        for ids in groups:
            if order == "fewest_types":
                ids = fewest_types_first(active, ids)
            self._groups.append((np.asarray(ids, np.int64), active[ids].any(axis=0)))
        # the recency scope of each robot: its group's types T_g, or its own Lambda_i
        self._scope = active.copy()
        if hold_scope == "group":
            for robots, types in self._groups:
                self._scope[robots] = types

    def encode(self, env: AuctionEnv) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Slot priorities ``[B, K]``, idle flags ``[B, m]``, recency levels ``[B, m]``.

        The mask alone cannot tell an idle robot with nothing to bid for from a busy one, and the
        reserve counts every idle robot of the group. Robot ``i``'s recency level is over its
        ``hold_scope``: its group's types or its own.
        """
        return env.slot_high.copy(), env.idle.copy(), recency_level(env, self._scope)

    def act(
        self, view: tuple[np.ndarray, np.ndarray, np.ndarray], mask: np.ndarray, *, explore: bool
    ) -> np.ndarray:
        """Bid per the rule of the class docstring.

        Args:
            view: Slot priorities, idle flags and recency levels from :meth:`encode`.
            mask: ``[B, m, K + 1]`` bool valid actions.
            explore: Unused: the policy is deterministic.

        Returns:
            ``[B, m]`` int64 conflict-free actions.
        """
        slot_high, idle, recency = view
        batch, _, n_actions = mask.shape
        rows = np.arange(batch)
        actions = np.zeros(mask.shape[:2], np.int64)
        may_take_low = recency >= self.hold_level  # [B, m]
        for robots, _ in self._groups:
            free = idle[:, robots].copy()  # [B, m_g] idle robots without a bid yet
            idle_left = free.sum(axis=1)  # [B]
            for high in (1, 0):  # H slots first
                for k in range(n_actions - 1):
                    # mask: idle robots whose Lambda_i holds the slot's type (spec step 4)
                    candidates = mask[:, robots, k + 1] & free & (slot_high[:, k] == high)[:, None]
                    if not high:
                        candidates &= may_take_low[:, robots]
                        candidates &= (idle_left - 1 >= self.reserve)[:, None]
                    has = candidates.any(axis=1)
                    first = candidates.argmax(axis=1)  # first in preference order
                    actions[rows[has], robots[first[has]]] = k + 1
                    free[rows[has], first[has]] = False
                    idle_left -= has
        return actions


class SubGReserveLearner(TeamReserveLearner):
    """``team_reserve`` on the subG partition: the yardstick for subG-CQL and subG-DQN.

    The runner builds its env on the partition's ``Lambda_i``, and the groups are the
    sub-groups (``grouping="subg"``, ``hold_scope="group"``, ``order="fewest_types"``), so it
    sees no more than a sub-group learner may. With ``reserve=0, hold_level=1`` it is the
    untrained subG-CQL (the ``spread_wait`` prior with ``fewest_types``). A sweep over
    ``reserve`` and ``hold_level`` measures what the partition allows a sub-group policy built
    from these signals (``docs/results.md``, "What the partition costs").

    Args:
        reserve: Idle robots a group keeps back for H work when bidding for an L task.
        hold_level: L slots wait while the group's recency level is below this (0 = never).
        **kwargs: Env, generator and partition of :class:`~mrta_rl.learners.base.Learner`.
    """

    label: ClassVar[str] = "subG-reserve"
    requires_partition: ClassVar[bool] = True
    _rule_name: ClassVar[str] = "subg_reserve"

    def __init__(self, *, reserve: Reserve = 0, hold_level: HoldLevel = 1, **kwargs) -> None:
        super().__init__(reserve=reserve, hold_level=hold_level, grouping="subg", **kwargs)
