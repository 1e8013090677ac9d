"""Joint actions of a robot group: mixed-radix codes and the valid (conflict-free) ones of a state.

A joint action of ``m_g`` robots is ``code = sum_r a_r A^r`` with ``A = K + 1`` (robot ``r`` of the
group, in group order; robot 0 is the least significant digit). The valid joint actions of a
state are the product of each robot's valid actions under the mask (spec step 4). With
``prune_conflicts`` a joint action in which several robots bid for one slot is left out: it has
the same winner, next state and rewards as the one where only the winner bids (spec step 5;
only the losers' busy ticks, spec step 7, differ), so it is a duplicate.
"""

from __future__ import annotations

from math import comb, perm

import numpy as np
from numba import njit


@njit(cache=True)
def enumerate_row(mask: np.ndarray, prune: bool, out: np.ndarray, start: int) -> int:
    """Valid joint codes of one state, in lexicographic order of ``(a_0, a_1, ...)``.

    Args:
        mask: ``[m_g, A]`` bool valid actions per robot.
        prune: Leave out joint actions with two bids for one slot.
        out: Codes are written from ``out[start]`` on (None-like: pass a 0-size array to count).
        start: First position written.

    Returns:
        Number of valid joint actions.
    """
    m_g, n_actions = mask.shape
    chosen = np.full(m_g, -1, np.int64)
    place = np.ones(m_g, np.int64)
    for r in range(1, m_g):
        place[r] = place[r - 1] * n_actions
    used = np.zeros(n_actions, np.bool_)  # slot k already has a bidder (pruning)
    count, code, r = 0, 0, 0
    while r >= 0:
        a = chosen[r]
        if a >= 0:  # undo robot r's current action before moving to its next one
            code -= a * place[r]
            used[a] = False
        a += 1
        while a < n_actions and not (mask[r, a] and (a == 0 or not prune or not used[a])):
            a += 1
        if a == n_actions:
            chosen[r] = -1
            r -= 1
            continue
        chosen[r] = a
        code += a * place[r]
        if a > 0:
            used[a] = True
        if r == m_g - 1:
            if out.size > 0:
                out[start + count] = code
            count += 1
        else:
            r += 1
    return count


def max_valid_joint_actions(n_robots: int, n_actions: int, prune: bool) -> int:
    """Most valid joint actions a state can have (every robot idle, every slot valid for all).

    Without pruning ``A^m_g``; with pruning the joint actions where ``j`` distinct slots of
    ``K = A - 1`` get one bidder each: ``sum_j C(K, j) m_g! / (m_g - j)!``.
    """
    if not prune:
        return n_actions**n_robots
    slots = n_actions - 1
    return sum(comb(slots, j) * perm(n_robots, j) for j in range(min(slots, n_robots) + 1))


class JointActions:
    """Mixed-radix codes of a group's joint action: ``code = sum_r a_r A^r`` (``A = K + 1``).

    Args:
        n_robots: Robots in the group ``m_g``.
        n_actions: Actions per robot ``A = K + 1``.

    Raises:
        OverflowError: if ``A^m_g`` does not fit in int64.
    """

    def __init__(self, n_robots: int, n_actions: int) -> None:
        self.n_robots, self.n_actions = n_robots, n_actions
        self.count = n_actions**n_robots  # eq. (15): |A| = prod |A_i|, exact int
        if self.count >= 2**63:
            raise OverflowError(f"{n_actions}^{n_robots} joint actions do not fit in int64")
        self.places = n_actions ** np.arange(n_robots, dtype=np.int64)  # [m_g]

    def encode(self, actions: np.ndarray) -> np.ndarray:
        """``[N, m_g]`` actions -> ``[N]`` int64 codes."""
        return np.asarray(actions, np.int64) @ self.places

    def decode(self, codes: np.ndarray) -> np.ndarray:
        """``[N]`` codes -> ``[N, m_g]`` int64 actions."""
        return (np.asarray(codes, np.int64)[:, None] // self.places) % self.n_actions

    def enumerate_valid(
        self, masks: np.ndarray, prune_conflicts: bool
    ) -> tuple[np.ndarray, np.ndarray]:
        """All valid joint actions of ``N`` states (:func:`enumerate_row` of each).

        Args:
            masks: ``[N, m_g, A]`` bool valid actions per robot.
            prune_conflicts: Leave out joint actions with two bids for one slot.

        Returns:
            ``(state, code)``: ``[E]`` state number (non-decreasing) and ``[E]`` joint code, in
            lexicographic order of ``(a_0, a_1, ...)`` within each state.
        """
        masks = np.asarray(masks, bool)
        empty = np.zeros(0, np.int64)
        counts = [enumerate_row(m, prune_conflicts, empty, 0) for m in masks]
        codes = np.zeros(sum(counts), np.int64)
        start = 0
        for m, n in zip(masks, counts, strict=True):
            enumerate_row(m, prune_conflicts, codes, start)
            start += n
        return np.repeat(np.arange(len(masks)), counts), codes
