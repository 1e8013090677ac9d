"""Fixed allocation policies: the spec's greedy, random and high_only, and the subG rule.

They are learners with ``kind = "fixed"`` and the base class's no-op ``update``, so the runner
evaluates them exactly like trained learners. ``greedy`` is the plain auction without learning,
the baseline every run reports next to its learner. ``team_reserve`` and ``subg_reserve`` are not
in the spec: a hand-written reserve rule over a grouping of the robots (the whole team, or the
subG sub-groups on the partition), yardsticks of what a rule on the learners' signals reaches.
The rules themselves are :mod:`mrta_rl.rules`' compiled ones, applied to every copy; the
reserve rule over a grouping is :class:`mrta_rl.priors.TeamReserveRule`, which the priors share.
"""

from __future__ import annotations

from typing import Annotated, ClassVar

import numpy as np

from mrta_rl import rules
from mrta_rl.config import Choices
from mrta_rl.envs import AuctionEnv
from mrta_rl.learners.base import FixedLearner
from mrta_rl.partition import Partition
from mrta_rl.priors import GROUPINGS, HOLD_SCOPES, ORDERS, HoldLevel, Reserve, TeamReserveRule


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
        return rules.greedy_actions(mask)


class SubGGreedyLearner(GreedyLearner):
    """Greedy on the subG partition: the plain auction, each robot bidding only for ``Lambda_i``.

    The switch-cost study compares it with greedy on the whole team: the partition's
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
        rank = self.rng.integers(0, mask.sum(axis=2))  # [B, m], uniform in 0..v (wait is valid)
        return rules.actions_of_rank(mask, rank)


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
        return rules.high_only_actions(mask, view)


class TeamReserveLearner(FixedLearner):
    """A hand-written reserve rule over any grouping of the robots: a yardstick for the learners.

    It reads no more than a centralized learner's group view (spec "Observations": slot contents,
    which robots are idle, the recency level of an H arrival) and bids for the robots' active
    types ``Lambda_i`` only, by the rule :class:`~mrta_rl.priors.TeamReserveRule` (its docstring
    says how ``reserve``, ``hold_level``, ``hold_scope`` and ``order`` shape the bids).

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
        reserve: Reserve,
        hold_level: HoldLevel,
        hold_scope: Annotated[str, Choices(*HOLD_SCOPES)],
        grouping: Annotated[str, Choices(*GROUPINGS)],
        order: Annotated[str, Choices(*ORDERS)],
        **kwargs,
    ) -> None:
        super().__init__(**kwargs)  # types, ranges and choices: the annotations (mrta_rl.config)
        self.rule = TeamReserveRule(
            self.env,
            reserve=reserve,
            hold_level=hold_level,
            hold_scope=hold_scope,
            grouping=grouping,
            order=order,
            partition=self.partition,
        )

    def encode(self, env: AuctionEnv) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Slot priorities ``[B, K]``, idle flags ``[B, m]``, recency levels ``[B, m]``.

        The rule's view (:meth:`~mrta_rl.priors.TeamReserveRule.encode`).
        """
        return self.rule.encode(env)

    def act(
        self, view: tuple[np.ndarray, np.ndarray, np.ndarray], mask: np.ndarray, *, explore: bool
    ) -> np.ndarray:
        """Bid per the rule of the class docstring (:meth:`~mrta_rl.priors.TeamReserveRule.act`).

        Args:
            view: Slot priorities, idle flags and recency levels from :meth:`encode`.
            mask: ``[B, m, K + 1]`` bool valid actions.
            explore: Unused: the policy is deterministic.

        Returns:
            ``[B, m]`` int64 conflict-free actions.
        """
        return self.rule.act(view, mask)


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
        env: The env built on the partition's ``Lambda_i``.
        rng: Unused (the rule is deterministic).
        partition: The subG partition (required).
    """

    label: ClassVar[str] = "subG-reserve"
    requires_partition: ClassVar[bool] = True
    _rule_name: ClassVar[str] = "subg_reserve"

    def __init__(
        self,
        *,
        env: AuctionEnv,
        rng: np.random.Generator,
        partition: Partition | None = None,
        reserve: Reserve,
        hold_level: HoldLevel,
    ) -> None:
        super().__init__(
            env=env,
            rng=rng,
            partition=partition,
            reserve=reserve,
            hold_level=hold_level,
            hold_scope="group",
            grouping="subg",
            order="fewest_types",
        )
