"""Tie-break priors of the tabular learners: the joint action an untrained state plays.

Q starts at 0 and, among the actions of greatest Q, the prior's choice wins (docs/learners.md,
"Exploration and ties"), so an untrained learner plays its prior exactly:

* ``greedy``: the plain auction (spec "Fixed policies"): every idle robot bids for its lowest
  valid slot; with conflict pruning, only each slot's auction winner keeps its bid
  (:func:`deconflict_row`, spec step 5).
* ``spread``: idle robots bid for distinct slots, in slot order, robots asked in a fixed order
  (:func:`spread_order`).
* ``spread_wait``: ``spread`` under a mask that holds L slots while an H task of the group's types
  arrived recently (the learner builds that mask).

The per-state rules are compiled (``*_row``) and called from the learners' kernels; the numpy
functions below apply them to batches (tests, inspection).

:class:`HoldRule` is the prior ``hold`` of DQL and of the neural learners (:data:`HOLD_PRIORS`):
the whole-team ``team_reserve`` rule (:class:`~mrta_rl.learners.fixed.TeamReserveLearner`),
computed from the env at each decision, so every learner that starts from it plays the same rule.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numba import njit

from mrta_rl.envs import AuctionEnv
from mrta_rl.learners.fixed import TeamReserveLearner

PRIORS = ("greedy", "spread", "spread_wait")  # tie-break joint action of an untrained state
PRIOR_ORDERS = ("index", "fewest_types")  # which idle robot the spread priors ask first
PRIOR_CODES = {name: k for k, name in enumerate(PRIORS)}  # the kernels' integer codes
HOLD_PRIORS = ("greedy", "hold")  # DQL's and the neural learners' prior: plain auction or rule


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
            env=env, rng=np.random.default_rng(0), reserve=reserve, hold_level=hold_level,
            hold_scope=hold_scope,
        )  # fmt: skip

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
    positions = np.arange(len(active_tasks))
    if rule == "index":
        return positions
    return np.lexsort((positions, active_tasks.sum(axis=1)))  # by type count, then index


# ---------------------------------------------------------------------------------- one state
@njit(cache=True)
def lowest_bid_row(mask: np.ndarray, out: np.ndarray) -> None:
    """Plain-auction choice per robot (spec "Fixed policies": greedy): lowest valid slot, else 0.

    Args:
        mask: ``[m_g, K + 1]`` bool valid actions.
        out: ``[m_g]`` int64 actions (written).
    """
    for r in range(mask.shape[0]):
        out[r] = 0
        for k in range(1, mask.shape[1]):
            if mask[r, k]:
                out[r] = k
                break


@njit(cache=True)
def deconflict_row(actions: np.ndarray, weight: np.ndarray) -> None:
    """Keep only each slot's auction winner as a bidder; losers wait (same outcome, spec step 5).

    Args:
        actions: ``[m_g]`` int64 actions of a group (modified in place).
        weight: ``[m_g, K]`` willingness ``d_i,type`` of each robot for each slot's type.
    """
    for k in range(1, weight.shape[1] + 1):
        winner, best, bidders = -1, -1.0, 0
        for r in range(actions.size):
            if actions[r] == k:
                bidders += 1
                # spec step 5: highest willingness wins; ties go to the lowest index
                if weight[r, k - 1] > best:
                    winner, best = r, weight[r, k - 1]
        if bidders > 1:
            for r in range(actions.size):
                if actions[r] == k and r != winner:
                    actions[r] = 0


@njit(cache=True)
def spread_row(mask: np.ndarray, order: np.ndarray, out: np.ndarray) -> None:
    """Spread prior: idle robots bid for distinct slots, in slot order, robots in ``order``.

    Slot 1 (the most urgent, spec step 3) gets the first robot in ``order`` that may bid for it,
    slot 2 the first among the others, and so on; robots left over wait. Unlike the plain auction
    no bid is lost, so no robot spends a busy tick on a lost bid (spec step 7).

    Args:
        mask: ``[m_g, K + 1]`` bool valid actions.
        order: ``[m_g]`` robot positions in the order they are asked.
        out: ``[m_g]`` int64 conflict-free actions (written).
    """
    out[:] = 0
    for k in range(1, mask.shape[1]):
        for r in order:
            if out[r] == 0 and mask[r, k]:
                out[r] = k
                break


@njit(cache=True)
def random_valid_row(mask: np.ndarray, u: float) -> int:
    """Uniform choice among the valid actions of ``mask`` (``[A]`` bool), from ``u`` in [0, 1)."""
    count = 0
    for a in range(mask.size):
        count += mask[a]
    pick = min(int(u * count), count - 1)  # rank of the chosen valid action
    for a in range(mask.size):
        if mask[a]:
            if pick == 0:
                return a
            pick -= 1
    return 0


# ---------------------------------------------------------------------------------- batches
@njit(cache=True)
def _greedy_batch(mask: np.ndarray) -> np.ndarray:
    out = np.zeros(mask.shape[:2], np.int64)
    for b in range(mask.shape[0]):
        lowest_bid_row(mask[b], out[b])
    return out


def greedy_actions(mask: np.ndarray) -> np.ndarray:
    """``[N, m, K + 1]`` bool valid actions -> ``[N, m]`` plain-auction actions (lowest slot)."""
    return _greedy_batch(np.asarray(mask, bool))


@njit(cache=True)
def _spread_batch(mask: np.ndarray, order: np.ndarray) -> np.ndarray:
    out = np.zeros(mask.shape[:2], np.int64)
    for b in range(mask.shape[0]):
        spread_row(mask[b], order, out[b])
    return out


def spread_actions(mask: np.ndarray, order: Sequence[int] | None = None) -> np.ndarray:
    """``[N, m_g, K + 1]`` valid actions -> ``[N, m_g]`` :func:`spread_row` actions.

    Args:
        mask: Valid actions of a group.
        order: Robot positions in the order they are asked; default: lowest index first.
    """
    mask = np.ascontiguousarray(mask, bool)  # one array type: _spread_batch compiles once
    order = np.arange(mask.shape[1]) if order is None else np.asarray(order, np.int64)
    return _spread_batch(mask, order)


@njit(cache=True)
def _deconflict_batch(actions: np.ndarray, slot_weight: np.ndarray) -> np.ndarray:
    out = actions.copy()
    for b in range(out.shape[0]):
        deconflict_row(out[b], slot_weight[b])
    return out


def deconflict(actions: np.ndarray, slot_weight: np.ndarray) -> np.ndarray:
    """``[N, m_g]`` actions -> conflict-free actions with the same winners (:func:`deconflict_row`).

    Args:
        actions: Actions of a group.
        slot_weight: ``[N, m_g, K]`` willingness of each robot for each slot's type.
    """
    return _deconflict_batch(np.asarray(actions, np.int64), np.asarray(slot_weight, np.float64))


@njit(cache=True)
def _random_batch(mask: np.ndarray, u: np.ndarray) -> np.ndarray:
    out = np.zeros(u.shape[0], np.int64)
    for j in range(u.shape[0]):
        out[j] = random_valid_row(mask[j], u[j])
    return out


def random_valid_actions(mask: np.ndarray, u: np.ndarray) -> np.ndarray:
    """``[N, A]`` bool valid actions and ``[N]`` uniforms -> ``[N]`` uniform valid actions."""
    return _random_batch(np.asarray(mask, bool), np.asarray(u, np.float64))
