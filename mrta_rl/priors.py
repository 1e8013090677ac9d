"""Tie-break priors of the tabular learners: the joint action an untrained state plays.

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

:class:`HoldRule` is the prior ``hold`` of DQL and of the neural learners (:data:`HOLD_PRIORS`):
the whole-team ``team_reserve`` rule (:class:`~mrta_rl.learners.fixed.TeamReserveLearner`),
computed from the env at each decision, so every learner that starts from it plays the same rule.
The neural learners' other priors are computed from the env the same way (:class:`GreedyPrior`,
and :class:`SpreadWaitPrior` for subG-DQN) and reach the networks as an input, so no network
computes a rule again.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mrta_rl import rules
from mrta_rl.envs import AuctionEnv
from mrta_rl.envs.encodings import recency_level
from mrta_rl.learners.fixed import TeamReserveLearner

PRIORS = ("greedy", "spread", "spread_wait")  # tie-break joint action of an untrained state
PRIOR_ORDERS = ("index", "fewest_types")  # which idle robot the spread priors ask first
PRIOR_CODES = {name: k for k, name in enumerate(PRIORS)}  # the kernels' integer codes
HOLD_PRIORS = ("greedy", "hold")  # DQL's and the neural learners' prior: plain auction or rule
JOINT_PRIORS = ("greedy", "spread_wait")  # what an untrained subG-DQN plays


class HoldRule:
    """The prior ``hold``: the whole-team ``team_reserve`` rule's action of every robot.

    The rule (:class:`~mrta_rl.learners.fixed.TeamReserveLearner`, whole team, ``fewest_types``
    order) reads what a robot's local view lacks (the other robots' idleness, which robot the
    team asks first), so it is computed from the env, not from a learner's observation.

    Args:
        env: The env (sizes and ``Lambda_i``; the rule is evaluated on the env it is called with).
        reserve: The rule's ``reserve``.
        hold_level: The rule's ``hold_level``.
        hold_scope: The rule's ``hold_scope``.
    """

    def __init__(self, env: AuctionEnv, *, reserve: int, hold_level: int, hold_scope: str):
        # a fixed, deterministic rule: its generator is never drawn
        self.rule = TeamReserveLearner(
            env=env,
            rng=np.random.default_rng(0),
            reserve=reserve,
            hold_level=hold_level,
            hold_scope=hold_scope,
        )

    def __call__(self, env: AuctionEnv, mask: np.ndarray | None = None) -> np.ndarray:
        """``[B, m]`` int64 the rule's actions in the env's state (mask: default the env's)."""
        mask = env.action_mask if mask is None else mask
        return self.rule.act(self.rule.encode(env), mask, explore=False)


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
