"""Fixed allocation policies: the spec's greedy, random and high_only, and the subG rule.

They are learners with ``kind = "fixed"`` and the base class's no-op ``update``, so the runner
evaluates them exactly like trained learners. ``greedy`` is the plain auction without learning,
the baseline every run reports next to its learner. ``team_reserve`` and ``subg_reserve`` are not
in the spec: a hand-written reserve rule over a grouping of the robots (the whole team, or the
subG sub-groups on the partition), yardsticks of what a rule on the learners' signals reaches.
The rules themselves are :mod:`mrta_rl.rules`' compiled ones, applied to every copy.
"""

from __future__ import annotations

from typing import Annotated, ClassVar

import numpy as np

from mrta_rl import rules
from mrta_rl.config import Choices, Range
from mrta_rl.envs import AuctionEnv
from mrta_rl.envs.encodings import N_RECENCY_LEVELS, recency_level
from mrta_rl.learners.base import Learner, LearnerKind
from mrta_rl.partition import subg_partition


class GreedyLearner(Learner):
    """Plain auction (spec "Fixed policies"): idle robots bid for their lowest-numbered valid slot.

    Slot 1 holds the most urgent task (spec step 3), so greedy bids for the most urgent task the
    robot may do. A busy robot has only action 0 in the mask, so it waits.
    """

    kind: ClassVar[LearnerKind] = "fixed"

    def act(self, view: None, mask: np.ndarray, *, explore: bool) -> np.ndarray:
        """Bid for the lowest-numbered valid slot, else wait.

        Args:
            view: Unused (None).
            mask: ``[B, m, K + 1]`` bool valid actions.
            explore: Unused: the policy is deterministic.

        Returns:
            ``[B, m]`` int64 actions.
        """
        return rules.greedy_actions(mask)


class SubGGreedyLearner(GreedyLearner):
    """Greedy on the subG partition: the plain auction, each robot bidding only for ``Lambda_i``.

    The switch-cost study (issue 11) compares it with greedy on the whole team: the partition's
    specialization can only pay when switching task types costs time (``env.switch_ticks``).
    """

    requires_partition: ClassVar[bool] = True


class RandomLearner(Learner):
    """Random bidding (spec "Fixed policies"): uniform over the ``v`` valid bids plus waiting.

    A robot with ``v`` valid bids picks each of its ``v + 1`` choices with probability
    ``1 / (v + 1)``; a busy robot (``v = 0``) waits.
    """

    kind: ClassVar[LearnerKind] = "fixed"

    def act(self, view: None, mask: np.ndarray, *, explore: bool) -> np.ndarray:
        """Draw one valid action per robot uniformly from ``self.rng``.

        Args:
            view: Unused (None).
            mask: ``[B, m, K + 1]`` bool valid actions; action 0 (wait) is always valid.
            explore: Unused: the policy is random in evaluation too, by definition.

        Returns:
            ``[B, m]`` int64 actions.
        """
        rank = self.rng.integers(0, mask.sum(axis=2))  # [B, m], uniform in 0..v (wait is valid)
        return rules.actions_of_rank(mask, rank)


class HighOnlyLearner(Learner):
    """Wait for high priority (spec "Fixed policies"): bid only for H tasks.

    Every idle robot bids for its lowest-numbered valid slot holding an H task, else waits.
    """

    kind: ClassVar[LearnerKind] = "fixed"

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
        return rules.high_only_actions(mask, view)


# the rule's two numbers, declared once for team_reserve and subg_reserve (mrta_rl.config)
Reserve = Annotated[int, Range(0)]  # idle robots kept back for H work
HoldLevel = Annotated[int, Range(0, N_RECENCY_LEVELS)]  # recency level below which L waits
GROUPINGS = ("team", "subg")  # team_reserve: one group of all robots, or the subG sub-groups
HOLD_SCOPES = ("group", "robot")  # whose recency level holds an L bid back
ORDERS = ("fewest_types", "index")  # which idle robot of a group is asked first


class TeamReserveLearner(Learner):
    """A hand-written reserve rule over any grouping of the robots: a yardstick for the learners.

    It reads no more than a centralized learner's group view (spec "Observations": slot contents,
    which robots are idle, the recency level of an H arrival) and bids for the robots' active
    types ``Lambda_i`` only. Per group ``G`` and copy it bids the reserve rule
    (:func:`mrta_rl.rules.reserve`): H slots first, then L slots, one robot per slot, so no bid is
    lost (spec step 7). Robots are asked in ``order`` (``fewest_types``: fewest active types
    first, ties to the lowest index, so versatile robots stay free; ``index``: lowest index). An
    L bid needs at least ``reserve`` other idle robots of ``G`` left without a bid, and a robot
    whose recency level is at least ``hold_level`` (``hold_scope="group"``: the level over the
    group's types ``T_g``; ``"robot"``: over the robot's own ``Lambda_i``). ``hold_level=1``: no
    such H task arrived within 3 ticks; ``0``: never hold; ``2``: within 10 ticks; ``3``: never
    bid for L.

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

    kind: ClassVar[LearnerKind] = "fixed"
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
            ids = np.asarray(ids, np.int64)
            if order == "fewest_types":
                ids = np.sort(ids)  # ties go to the lowest index
                ids = ids[rules.fewest_types_first(active[ids])]
            self._groups.append((ids, active[ids].any(axis=0)))
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
        actions = np.zeros(mask.shape[:2], np.int64)
        may_take_low = recency >= self.hold_level  # [B, m]
        for robots, _ in self._groups:
            rules.reserve_actions(
                mask, slot_high, idle, may_take_low, robots, self.reserve, actions
            )
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

    requires_partition: ClassVar[bool] = True
    _rule_name: ClassVar[str] = "subg_reserve"

    def __init__(self, *, reserve: Reserve = 0, hold_level: HoldLevel = 1, **kwargs) -> None:
        super().__init__(reserve=reserve, hold_level=hold_level, grouping="subg", **kwargs)
