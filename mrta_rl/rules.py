"""The allocation rules, each compiled once: what a fixed policy or a prior bids in one copy.

Every rule reads one copy's arrays (``docs/spec/auction_env.md``): the action mask ``[m, K + 1]``
(column 0 is wait, column ``k`` a bid for slot ``k``), the slot priorities ``[K]`` (1 = H, 0 = L,
-1 = empty) and per-robot flags ``[m]``, and writes the robots' actions into ``out`` ``[m]``
(int64, ``0`` = wait). The env's kernel, the fixed learners, the tabular learners' priors and the
env-computed priors of the neural learners all call these functions, so a rule has one home.

The functions are compiled with numba (``cache=True``, ``nogil=True``) and may be called from
other compiled code, or from Python with numpy arrays of the stated dtypes.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numba import njit


# ------------------------------------------------------------------------------ one robot
@njit(cache=True, nogil=True)
def lowest_valid_bid(mask_row):
    """Spec "Fixed policies", ``greedy``: the lowest-numbered slot the robot may bid for, else 0.

    Args:
        mask_row: ``[K + 1]`` bool valid actions of one robot.

    Returns:
        The action, ``0..K``.
    """
    for k in range(1, mask_row.shape[0]):
        if mask_row[k]:
            return k
    return 0


@njit(cache=True, nogil=True)
def lowest_valid_high_bid(mask_row, slot_high):
    """Spec "Fixed policies", ``high_only``: the lowest-numbered valid slot holding an H task.

    Args:
        mask_row: ``[K + 1]`` bool valid actions of one robot.
        slot_high: ``[K]`` slot priorities (1 = H).

    Returns:
        The action, ``0..K`` (0: no valid H slot, wait).
    """
    for k in range(1, mask_row.shape[0]):
        if mask_row[k] and slot_high[k - 1] == 1:
            return k
    return 0


@njit(cache=True, nogil=True)
def count_valid(mask_row):
    """The number of valid actions of one robot (``v + 1`` with waiting, spec "Fixed policies").

    Args:
        mask_row: ``[A]`` bool valid actions.

    Returns:
        The count of True entries.
    """
    count = 0
    for a in range(mask_row.shape[0]):
        count += mask_row[a]
    return count


@njit(cache=True, nogil=True)
def valid_action_of_rank(mask_row, rank):
    """The valid action of rank ``rank`` (0: the first valid one), the draw of spec ``random``.

    With waiting valid (column 0), rank 0 is waiting and rank ``c >= 1`` the ``c``-th valid bid,
    as spec "Fixed policies" words the random policy.

    Args:
        mask_row: ``[A]`` bool valid actions.
        rank: ``0 .. count_valid(mask_row) - 1``.

    Returns:
        The action; 0 when ``rank`` is past the last valid action.
    """
    for a in range(mask_row.shape[0]):
        if mask_row[a]:
            if rank == 0:
                return a
            rank -= 1
    return 0


@njit(cache=True, nogil=True)
def random_valid(mask_row, u):
    """Spec "Fixed policies", ``random``: a uniform valid action, chosen by ``u`` in [0, 1).

    Args:
        mask_row: ``[A]`` bool valid actions (at least one True).
        u: A uniform draw in [0, 1).

    Returns:
        The valid action of rank ``floor(u * count)``.
    """
    count = count_valid(mask_row)
    return valid_action_of_rank(mask_row, min(int(u * count), count - 1))


# ------------------------------------------------------------------------------ one copy
@njit(cache=True, nogil=True)
def greedy(mask, out):
    """Spec "Fixed policies", ``greedy`` (the plain auction), for every robot of a copy.

    Args:
        mask: ``[m, K + 1]`` bool valid actions.
        out: ``[m]`` int64 actions (written).
    """
    for r in range(mask.shape[0]):
        out[r] = lowest_valid_bid(mask[r])


@njit(cache=True, nogil=True)
def high_only(mask, slot_high, out):
    """Spec "Fixed policies", ``high_only`` (wait for high priority), for every robot of a copy.

    Args:
        mask: ``[m, K + 1]`` bool valid actions.
        slot_high: ``[K]`` slot priorities (1 = H, 0 = L, -1 = empty).
        out: ``[m]`` int64 actions (written).
    """
    for r in range(mask.shape[0]):
        out[r] = lowest_valid_high_bid(mask[r], slot_high)


@njit(cache=True, nogil=True)
def slot_winner(actions, slot, willingness):
    """Spec step 5: among the robots bidding for ``slot``, the most willing; ties to the lowest.

    Args:
        actions: ``[m]`` int64 actions of the robots.
        slot: The slot ``k`` (1-based, the bid's action).
        willingness: ``[m]`` willingness ``d_iz`` of each robot for the slot's type.

    Returns:
        The winner's row, or -1 when nobody bids for the slot.
    """
    winner, best = -1, -1.0
    for r in range(actions.shape[0]):
        if actions[r] == slot and willingness[r] > best:
            winner, best = r, willingness[r]
    return winner


@njit(cache=True, nogil=True)
def deconflict(actions, weight):
    """Spec step 5 as a rule on a joint action: each slot's winner keeps its bid, losers wait.

    The winner is :func:`slot_winner`'s, so the env assigns the same tasks to the same robots;
    the losers' bids, which would only cost them a busy tick (spec step 7), become waits.

    Args:
        actions: ``[m]`` int64 actions of a group (modified in place).
        weight: ``[m, K]`` willingness ``d_iz`` of each robot for each slot's type.
    """
    for k in range(1, weight.shape[1] + 1):
        winner = slot_winner(actions, k, weight[:, k - 1])
        for r in range(actions.shape[0]):
            if actions[r] == k and r != winner:
                actions[r] = 0


@njit(cache=True, nogil=True)
def spread(mask, order, out):
    """Spread: idle robots bid for distinct slots, in slot order, robots asked in ``order``.

    Slot 1 (the most urgent, spec step 3) gets the first robot in ``order`` that may bid for it,
    slot 2 the first among the others, and so on; the robots left over wait. Unlike the plain
    auction no bid is lost, so no robot spends a busy tick on a lost bid (spec step 7).

    Args:
        mask: ``[m, K + 1]`` bool valid actions.
        order: int64 robot rows in the order they are asked; only these rows are written.
        out: ``[m]`` int64 actions (written at the rows of ``order``).
    """
    for r in order:
        out[r] = 0
    for k in range(1, mask.shape[1]):
        for r in order:
            if out[r] == 0 and mask[r, k]:
                out[r] = k
                break


@njit(cache=True, nogil=True)
def reserve(mask, slot_high, idle, may_take_low, order, kept, out):
    """Reserve (``team_reserve``, ``subg_reserve``): spread over H slots, L slots held back.

    One group's robots (the rows of ``order``, in bidding preference) bid for distinct slots:

    1. H slots, in slot order: the first idle robot in ``order`` without a bid that may bid.
    2. L slots, in slot order, the same way, but only while at least ``kept`` other idle robots
       of the group stay without a bid after this one, and only by a robot ``may_take_low``
       (its recency level reached the rule's ``hold_level``).

    No two robots bid for one slot, so no bid is lost (spec step 7). Slots hold H tasks before L
    ones (spec steps 2-3), so with ``kept = 0`` and every robot ``may_take_low`` this is
    :func:`spread`.

    Args:
        mask: ``[m, K + 1]`` bool valid actions.
        slot_high: ``[K]`` slot priorities (1 = H, 0 = L, -1 = empty).
        idle: ``[m]`` bool idle robots (spec step 4); the reserve counts every idle robot.
        may_take_low: ``[m]`` bool robots that may bid for an L slot now.
        order: int64 the group's robot rows in bidding preference; only these rows are written.
        kept: Idle robots the group keeps back for H work (the rule's ``reserve``).
        out: ``[m]`` int64 actions (written at the rows of ``order``).
    """
    idle_left = 0
    for r in order:
        out[r] = 0
        idle_left += idle[r]
    for high in (1, 0):  # H slots first
        for k in range(1, mask.shape[1]):
            if slot_high[k - 1] != high or (not high and idle_left - 1 < kept):
                continue
            for r in order:
                if out[r] == 0 and idle[r] and mask[r, k] and (high or may_take_low[r]):
                    out[r] = k
                    idle_left -= 1
                    break


# ------------------------------------------------------------------------------ batches
@njit(cache=True, nogil=True)
def greedy_actions(mask):
    """:func:`greedy` of every copy: ``[B, m, K + 1]`` bool valid actions -> ``[B, m]`` int64."""
    out = np.zeros(mask.shape[:2], np.int64)
    for b in range(mask.shape[0]):
        greedy(mask[b], out[b])
    return out


@njit(cache=True, nogil=True)
def high_only_actions(mask, slot_high):
    """:func:`high_only` of every copy: ``[B, m, K + 1]`` mask and ``[B, K]`` priorities."""
    out = np.zeros(mask.shape[:2], np.int64)
    for b in range(mask.shape[0]):
        high_only(mask[b], slot_high[b], out[b])
    return out


@njit(cache=True, nogil=True)
def actions_of_rank(mask, rank):
    """:func:`valid_action_of_rank` of every robot: ``[B, m, A]`` mask, ``[B, m]`` ranks."""
    out = np.zeros(rank.shape, np.int64)
    for b in range(mask.shape[0]):
        for r in range(mask.shape[1]):
            out[b, r] = valid_action_of_rank(mask[b, r], rank[b, r])
    return out


@njit(cache=True, nogil=True)
def random_valid_actions(mask, u):
    """:func:`random_valid` of every row: ``[N, A]`` bool valid actions, ``[N]`` uniforms."""
    out = np.zeros(u.shape[0], np.int64)
    for j in range(u.shape[0]):
        out[j] = random_valid(mask[j], u[j])
    return out


@njit(cache=True, nogil=True)
def _spread_batch(mask, order):
    out = np.zeros(mask.shape[:2], np.int64)
    for b in range(mask.shape[0]):
        spread(mask[b], order, out[b])
    return out


def spread_actions(mask: np.ndarray, order: Sequence[int] | None = None) -> np.ndarray:
    """:func:`spread` of every copy: ``[B, m_g, K + 1]`` valid actions -> ``[B, m_g]``.

    Args:
        mask: Valid actions of a group.
        order: Robot positions in the order they are asked; default: lowest index first.
    """
    mask = np.ascontiguousarray(mask, bool)  # one array type: _spread_batch compiles once
    order = np.arange(mask.shape[1]) if order is None else np.asarray(order, np.int64)
    return _spread_batch(mask, order)


@njit(cache=True, nogil=True)
def reserve_actions(mask, slot_high, idle, may_take_low, order, kept, out):
    """:func:`reserve` of every copy for one group (``[B, ...]`` arrays; ``out`` ``[B, m]``)."""
    for b in range(mask.shape[0]):
        reserve(mask[b], slot_high[b], idle[b], may_take_low[b], order, kept, out[b])


@njit(cache=True, nogil=True)
def _deconflict_batch(actions, weight):
    out = actions.copy()
    for b in range(out.shape[0]):
        deconflict(out[b], weight[b])
    return out


def deconflict_actions(actions: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """:func:`deconflict` of every copy: ``[B, m_g]`` actions -> conflict-free actions.

    Args:
        actions: Actions of a group.
        weight: ``[B, m_g, K]`` willingness of each robot for each slot's type.
    """
    return _deconflict_batch(np.asarray(actions, np.int64), np.asarray(weight, np.float64))


def fewest_types_first(active_tasks: np.ndarray) -> np.ndarray:
    """The reserve and spread rules' preferred order: fewest active types first, then index.

    Versatile robots are asked last, so they stay free for the types only they can do.

    Args:
        active_tasks: ``[m_g, n]`` bool ``Lambda_i`` of a group's robots.

    Returns:
        ``[m_g]`` int64 permutation of the rows.
    """
    active_tasks = np.asarray(active_tasks, bool)
    positions = np.arange(len(active_tasks))
    return np.lexsort((positions, active_tasks.sum(axis=1)))
