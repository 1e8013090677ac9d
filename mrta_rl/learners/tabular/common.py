"""Shared machinery of the tabular learners: Q storage, joint actions, eq. (3) updates, schedules.

Paper §2 eq. (3) is the update of every tabular learner; §5.2 eqs. (10)-(16) count the tables.
Design (see ``docs/learners.md``):

* **Joint actions** of a group of ``m_g`` robots are mixed-radix integers
  ``code = sum_r a_r (K + 1)^r`` (robot ``r`` of the group, in group order; robot 0 is the least
  significant digit). :class:`JointQTable` stores, per visited state, only the joint actions that
  are valid in it (the product of each robot's valid actions under the mask, spec step 4), so the
  table of CQL on System-II stays small although its analytic size overflows 64 bits.
* **Conflict-free joint actions** (``prune_conflicts``): a joint action in which several robots bid
  for one slot has the same winner, next state and rewards (team and individual) as the one where
  only the winner bids (spec step 5: losing a bid changes nothing but the loser's busy-tick
  count, spec step 7). Such duplicates are left out of the table; an outside action is mapped to
  its conflict-free equivalent before it is looked up.
* **Ties go to the plain auction.** Q starts at 0 and, among joint actions of equal greatest Q, the
  greedy policy's choice (every idle robot bids for its lowest valid slot, conflicts resolved as
  the auction would) wins. An untrained state therefore behaves like the plain auction.
* **Decision points** (``decisions_only``): a state where an agent has one valid action carries no
  choice. By default such ticks are folded into the transition (semi-Markov Q-learning): the
  update of the last decision ``(s, a)`` waits for the next decision state ``s'`` and uses
  ``R = sum_k gamma^k r_k`` and ``gamma^tau``, which is eq. (3) for the tick-by-tick chain when
  ``tau = 1``. With ``decisions_only=False`` every tick is updated, no-choice states included.
* **Many copies per tick.** The transitions closing at a tick in the ``B`` copies are applied one
  after another in copy order, each by eq. (3), with targets computed from the table before the
  tick's updates (a synchronous target, as in batched Q-learning).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from mrta_rl.envs import AuctionEnv
from mrta_rl.learners.base import Learner
from mrta_rl.partition import Partition

logger = logging.getLogger(__name__)

Q_FILE = "q_tables.npz"  # arrays of every table, np.savez without object arrays
META_FILE = "learner.json"  # hyperparameters and schedule position


# ---------------------------------------------------------------------------------- schedules
@dataclass(frozen=True)
class LinearSchedule:
    """Value moving linearly from ``start`` to ``end`` over ``steps`` steps, then constant.

    Attributes:
        start: Value at step 0.
        end: Value from step ``steps`` on.
        steps: Length of the ramp (0: always ``end``).
    """

    start: float
    end: float
    steps: int

    def __call__(self, step: int) -> float:
        """The value at ``step``."""
        if self.steps <= 0 or step >= self.steps:
            return float(self.end)
        return float(self.start + (self.end - self.start) * step / self.steps)


def visit_alpha(visits: np.ndarray, alpha: float, power: float, alpha_min: float) -> np.ndarray:
    """Learning rate of eq. (3) from the visit count: ``max(alpha_min, alpha / n^power)``.

    ``power = 0`` is a constant ``alpha``; ``power = 1`` with ``alpha = 1`` averages the targets.

    Args:
        visits: Visit counts ``n >= 1`` of the entries, this update included.
        alpha: Base learning rate.
        power: Decay exponent ``w``.
        alpha_min: Floor of the learning rate.

    Returns:
        Learning rates, same shape as ``visits``.
    """
    if power == 0:
        return np.full(visits.shape, float(alpha))
    return np.maximum(alpha_min, alpha * visits.astype(np.float64) ** (-power))


# ---------------------------------------------------------------------------------- actions
def greedy_actions(mask: np.ndarray) -> np.ndarray:
    """Plain-auction choice (spec "Fixed policies": greedy): the lowest valid slot, else wait.

    Args:
        mask: ``[..., K + 1]`` bool valid actions.

    Returns:
        ``[...]`` int64 actions.
    """
    bids = mask[..., 1:]
    return np.where(bids.any(axis=-1), bids.argmax(axis=-1) + 1, 0).astype(np.int64)


def spread_actions(mask: np.ndarray, order: Sequence[int] | None = None) -> np.ndarray:
    """Spread prior: idle robots bid for distinct slots, in slot order, robots in a fixed order.

    Slot 1 (the most urgent, spec step 3) gets the first robot in ``order`` that may bid for it,
    slot 2 the first among the others, and so on; robots left over wait. Unlike the plain auction
    no bid is lost, so no robot spends a busy tick on a lost bid (spec step 7) and more slots are
    filled at the same tick.

    Args:
        mask: ``[N, m_g, K + 1]`` bool valid actions of a group.
        order: The group's robot positions in the order they are asked (see
            :data:`PRIOR_ORDERS`); default: lowest index first.

    Returns:
        ``[N, m_g]`` int64 conflict-free actions.
    """
    n, m_g, n_actions = mask.shape
    order = np.arange(m_g) if order is None else np.asarray(order, np.int64)
    ranked = mask[:, order]  # robots in the order they are asked
    actions = np.zeros((n, m_g), np.int64)
    taken = np.zeros((n, m_g), bool)
    rows = np.arange(n)
    for k in range(1, n_actions):
        candidates = ranked[:, :, k] & ~taken  # [N, m_g]
        has = candidates.any(axis=1)
        first = candidates.argmax(axis=1)  # first in order among the candidates
        actions[rows[has], order[first[has]]] = k
        taken[rows[has], first[has]] = True
    return actions


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


PRIORS = ("greedy", "spread", "spread_wait")  # tie-break joint action of an untrained state
PRIOR_ORDERS = ("index", "fewest_types")  # which idle robot the spread priors ask first


def random_valid_actions(mask: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Uniform choice among the valid actions, driven by uniforms ``u`` in [0, 1).

    Args:
        mask: ``[..., A]`` bool valid actions (at least one per row).
        u: ``[...]`` uniforms.

    Returns:
        ``[...]`` int64 valid actions.
    """
    counts = mask.sum(axis=-1)
    pick = np.minimum((u * counts).astype(np.int64), counts - 1)  # rank of the chosen valid action
    return (np.cumsum(mask, axis=-1) > pick[..., None]).argmax(axis=-1).astype(np.int64)


def deconflict(actions: np.ndarray, slot_weight: np.ndarray) -> np.ndarray:
    """Keep only each slot's auction winner as a bidder; losers wait (same outcome, spec step 5).

    Args:
        actions: ``[N, m_g]`` actions of a group.
        slot_weight: ``[N, m_g, K]`` willingness ``d_i,type`` of each robot for each slot's type.

    Returns:
        ``[N, m_g]`` conflict-free actions with the same winners.
    """
    out = actions.copy()
    for k in range(slot_weight.shape[-1]):
        bids = actions == k + 1  # [N, m_g]
        several = bids.sum(axis=1) > 1
        if not several.any():
            continue
        # spec step 5: highest willingness wins; argmax takes the first, i.e. the lowest index
        winner = np.where(bids, slot_weight[:, :, k], -1.0).argmax(axis=1)
        lose = bids & several[:, None]
        lose[np.arange(len(actions)), winner] = False
        out[lose] = 0
    return out


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
        """All valid joint actions of ``N`` states: the product of each robot's valid actions.

        Args:
            masks: ``[N, m_g, A]`` bool valid actions per robot.
            prune_conflicts: Leave out joint actions with two bids for one slot (module docstring).

        Returns:
            ``(state, code)``: ``[E]`` state number (non-decreasing) and ``[E]`` joint code, in
            lexicographic order of ``(a_0, a_1, ...)`` within each state.
        """
        n = len(masks)
        state = np.arange(n)
        code = np.zeros(n, np.int64)
        used = np.zeros(n, np.int64)  # bit k-1 set: slot k already has a bidder
        slot_bits = np.arange(self.n_actions - 1)
        for r in range(self.n_robots):  # expand robot by robot (a vectorised product)
            valid = masks[state, r].copy()  # [E, A]
            if prune_conflicts:
                valid[:, 1:] &= ((used[:, None] >> slot_bits) & 1) == 0
            entry, action = np.nonzero(valid)
            state, code = state[entry], code[entry] + action * self.places[r]
            used = used[entry] | np.where(action > 0, 1 << np.maximum(action - 1, 0), 0)
        return state, code


# ---------------------------------------------------------------------------------- storage
class _Growable:
    """A 1-D numpy array with amortised appends."""

    def __init__(self, dtype: Any, capacity: int = 1024) -> None:
        self._data = np.zeros(capacity, dtype)
        self.size = 0

    @property
    def data(self) -> np.ndarray:
        return self._data[: self.size]

    def append(self, values: np.ndarray) -> None:
        need = self.size + len(values)
        if need > len(self._data):
            grown = np.zeros(max(need, 2 * len(self._data)), self._data.dtype)
            grown[: self.size] = self._data[: self.size]
            self._data = grown
        self._data[self.size : need] = values
        self.size = need

    def set(self, values: np.ndarray) -> None:
        self.size = 0
        self.append(values)


def apply_updates(
    q: np.ndarray,
    visits: np.ndarray,
    entries: np.ndarray,
    targets: np.ndarray,
    alpha: float,
    alpha_power: float,
    alpha_min: float,
) -> float:
    """Eq. (3) ``Q <- Q + alpha_n (target - Q)`` for each transition, in order, in place.

    Transitions hitting the same entry are applied one after another (their order in the
    arrays), so a batch equals the sequential updates; each bumps the entry's visit count.

    Args:
        q: Flat Q values (modified).
        visits: Flat visit counts (modified).
        entries: ``[N]`` flat indices.
        targets: ``[N]`` targets ``r + gamma max Q(s', .)``.
        alpha: Base learning rate; ``alpha_power``, ``alpha_min``: see :func:`visit_alpha`.
        alpha_power: Decay exponent of the learning rate with visits.
        alpha_min: Floor of the learning rate.

    Returns:
        Mean absolute TD error (0.0 for no transition).
    """
    if len(entries) == 0:
        return 0.0
    order = np.argsort(entries, kind="stable")
    sorted_entries = entries[order]
    first = np.r_[True, sorted_entries[1:] != sorted_entries[:-1]]  # first of a run of one entry
    run_start = np.maximum.accumulate(np.where(first, np.arange(len(order)), 0))
    rank = np.empty(len(order), np.int64)
    rank[order] = np.arange(len(order)) - run_start  # 0 for the first transition of an entry
    td_sum = 0.0
    for p in range(int(rank.max()) + 1):
        sel = rank == p  # entries are unique within a pass
        e = entries[sel]
        visits[e] += 1
        td = targets[sel] - q[e]
        q[e] += visit_alpha(visits[e], alpha, alpha_power, alpha_min) * td
        td_sum += float(np.abs(td).sum())
    return td_sum / len(entries)


class JointQTable:
    """Q over (state, valid joint action) of one group, storing only visited states.

    Per state (a row): its valid joint actions (their codes), their Q values and visit counts,
    contiguous in flat arrays, and the entry of the plain auction's joint action (tie-break).
    The valid set is a function of the group state (the state holds each robot's idle flag and
    the slot types within the group's types), so it is enumerated once, on the first visit.

    Args:
        n_robots: Robots in the group ``m_g``.
        n_actions: Actions per robot ``K + 1``.
        prune_conflicts: Store only conflict-free joint actions (module docstring).
        prior: Tie-break joint action: ``"greedy"`` (the plain auction) or ``"spread"``
            (:func:`spread_actions`) or ``"spread_wait"`` (spread under the prior masks passed
            to :meth:`rows`); each is valid in every state.
        min_visits: Entries other than the prior compete for the greedy choice and the max of
            eq. (3) once updated this many times (0: all entries, untried ones at Q = 0).
        order: The order in which the spread priors ask the group's robots
            (:func:`spread_order`); default: lowest index first.

    Raises:
        ValueError: on an unknown prior.
    """

    _ARRAYS = ("states", "offset", "length", "greedy", "codes", "q", "visits")  # saved arrays

    def __init__(
        self,
        n_robots: int,
        n_actions: int,
        prune_conflicts: bool = True,
        prior: str = "greedy",
        min_visits: int = 0,
        order: Sequence[int] | None = None,
    ) -> None:
        if prior not in PRIORS:
            raise ValueError(f"prior must be one of {PRIORS}, got {prior!r}")
        if min_visits < 0:
            raise ValueError(f"min_visits must be >= 0, got {min_visits}")
        self.joint = JointActions(n_robots, n_actions)
        self.prune_conflicts = prune_conflicts
        self.prior = prior
        self.min_visits = min_visits
        self.order = np.arange(n_robots) if order is None else np.asarray(order, np.int64)
        self.index: dict[int, int] = {}  # state index -> row
        self._states = _Growable(np.int64)  # row -> state index
        self._offset = _Growable(np.int64)  # row -> first entry
        self._length = _Growable(np.int64)  # row -> number of valid joint actions
        self._greedy = _Growable(np.int64)  # row -> entry of the plain auction's joint action
        self._codes = _Growable(np.int64)  # entry -> joint action code
        self._q = _Growable(np.float64)  # entry -> Q(s, a)
        self._visits = _Growable(np.int64)  # entry -> updates so far

    # -- rows
    def rows(
        self,
        states: np.ndarray,
        masks: np.ndarray,
        slot_weight: np.ndarray,
        prior_masks: np.ndarray | None = None,
    ) -> np.ndarray:
        """Rows of ``N`` states, created on the first visit.

        Args:
            states: ``[N]`` group state indices.
            masks: ``[N, m_g, K + 1]`` valid actions of the group's robots in those states.
            slot_weight: ``[N, m_g, K]`` willingness of the robots for the slots' types.
            prior_masks: ``[N, m_g, K + 1]`` the bids the prior may use (a subset of ``masks``,
                a function of the state); None = ``masks``.

        Returns:
            ``[N]`` int64 rows.
        """
        get = self.index.get
        rows = np.fromiter((get(s, -1) for s in states.tolist()), np.int64, len(states))
        new = rows < 0
        if new.any():
            fresh, first = np.unique(states[new], return_index=True)
            at = np.flatnonzero(new)[first]
            prior = masks[at] if prior_masks is None else prior_masks[at]
            self._add_rows(fresh, masks[at], slot_weight[at], prior)
            rows[new] = np.fromiter((get(s) for s in states[new].tolist()), np.int64, new.sum())
        return rows

    def _add_rows(
        self,
        states: np.ndarray,
        masks: np.ndarray,
        slot_weight: np.ndarray,
        prior_masks: np.ndarray,
    ) -> None:
        state_of, codes = self.joint.enumerate_valid(masks, self.prune_conflicts)
        lengths = np.bincount(state_of, minlength=len(states))
        offsets = self._codes.size + np.cumsum(lengths) - lengths
        if self.prior in ("spread", "spread_wait"):
            greedy = spread_actions(prior_masks, self.order)  # [N, m_g], conflict-free
        else:
            greedy = greedy_actions(prior_masks)  # [N, m_g]
            if self.prune_conflicts:
                greedy = deconflict(greedy, slot_weight)
        greedy_code = self.joint.encode(greedy)
        greedy_entry = self._codes.size + np.flatnonzero(codes == greedy_code[state_of])
        first_row = self._states.size
        self._states.append(states)
        self._offset.append(offsets)
        self._length.append(lengths)
        self._greedy.append(greedy_entry)
        self._codes.append(codes)
        self._q.append(np.zeros(len(codes)))
        self._visits.append(np.zeros(len(codes), np.int64))
        self.index.update(
            zip(states.tolist(), range(first_row, first_row + len(states)), strict=True)
        )

    # -- queries
    def _segments(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        lengths = self._length.data[rows]
        starts = np.cumsum(lengths) - lengths
        idx = np.repeat(self._offset.data[rows] - starts, lengths) + np.arange(lengths.sum())
        return idx, starts, lengths

    def _candidate_values(
        self, rows: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Q of each row's candidates (the prior, entries tried ``min_visits`` times), else -inf."""
        idx, starts, lengths = self._segments(rows)
        values = self._q.data[idx]
        if self.min_visits > 0:
            prior = np.repeat(self._greedy.data[rows], lengths)
            tried = (self._visits.data[idx] >= self.min_visits) | (idx == prior)
            values = np.where(tried, values, -np.inf)
        return idx, starts, lengths, values

    def max_q(self, rows: np.ndarray) -> np.ndarray:
        """``[N]`` max over the valid joint actions of each row (eq. 3's ``max_a'``).

        With ``min_visits > 0`` the max ranges over the candidates of :meth:`best_entries`, so
        the target is the value of the greedy policy (untried entries hold no estimate yet).
        """
        if len(rows) == 0:
            return np.zeros(0)
        _, starts, _, values = self._candidate_values(rows)
        return np.maximum.reduceat(values, starts)

    def best_entries(self, rows: np.ndarray) -> np.ndarray:
        """``[N]`` entry of the greatest Q per row; ties go to the prior's joint action.

        With ``min_visits > 0`` only the prior and the entries updated at least ``min_visits``
        times compete: an entry tried once by exploration holds a single noisy target (or, with a
        constant alpha, a fraction of it) and must not replace the prior on that evidence.
        """
        if len(rows) == 0:
            return np.zeros(0, np.int64)
        q = self._q.data
        idx, starts, lengths, values = self._candidate_values(rows)
        best = np.maximum.reduceat(values, starts)
        positions = np.where(values == np.repeat(best, lengths), np.arange(len(idx)), len(idx))
        first = idx[np.minimum.reduceat(positions, starts)]
        greedy = self._greedy.data[rows]
        return np.where(q[greedy] >= best, greedy, first)

    def random_entries(self, rows: np.ndarray, u: np.ndarray) -> np.ndarray:
        """``[N]`` uniform valid joint action per row (exploration), from uniforms ``u``."""
        lengths = self._length.data[rows]
        return self._offset.data[rows] + np.minimum((u * lengths).astype(np.int64), lengths - 1)

    def entries_of(self, rows: np.ndarray, codes: np.ndarray) -> np.ndarray:
        """``[N]`` entry of joint action ``codes[k]`` in row ``rows[k]``.

        Raises:
            ValueError: if a joint action is not stored in its row (invalid under the mask, or
                with conflicts while ``prune_conflicts``).
        """
        if len(rows) == 0:
            return np.zeros(0, np.int64)
        idx, _, lengths = self._segments(rows)
        hit = self._codes.data[idx] == np.repeat(codes, lengths)
        if (
            hit.sum() != len(rows)
            or not np.logical_or.reduceat(hit, np.cumsum(lengths) - lengths).all()
        ):
            raise ValueError("joint action not valid in its state (masked, or conflicting bids)")
        return idx[hit]

    def actions_of(self, entries: np.ndarray) -> np.ndarray:
        """``[N, m_g]`` per-robot actions of table entries."""
        return self.joint.decode(self._codes.data[entries])

    # -- learning
    @property
    def q(self) -> np.ndarray:
        """Flat Q values (a view; entries index it)."""
        return self._q.data

    @property
    def visits(self) -> np.ndarray:
        """Flat visit counts (a view)."""
        return self._visits.data

    def n_states(self) -> int:
        """Rows stored (states seen at a decision)."""
        return self._states.size

    def n_visited(self) -> int:
        """Entries updated at least once."""
        return int(np.count_nonzero(self._visits.data))

    def state_q(self, state: int) -> dict[int, float]:
        """``{joint code: Q}`` of a stored state (for tests and inspection)."""
        row = self.index[int(state)]
        o, n = int(self._offset.data[row]), int(self._length.data[row])
        return dict(
            zip(self._codes.data[o : o + n].tolist(), self._q.data[o : o + n].tolist(), strict=True)
        )

    def to_arrays(self, prefix: str) -> dict[str, np.ndarray]:
        """Plain arrays for ``np.savez`` (no objects)."""
        return {f"{prefix}{k}": getattr(self, f"_{k}").data.copy() for k in self._ARRAYS}

    def from_arrays(self, arrays: dict[str, np.ndarray], prefix: str) -> None:
        """Restore from :meth:`to_arrays` output, checked to form one consistent table.

        Raises:
            ValueError: if the arrays do not fit together or this group (lengths, offsets,
                joint-action codes out of range, the prior's entry outside its row).
        """
        a = {k: np.asarray(arrays[f"{prefix}{k}"]) for k in self._ARRAYS}
        n_rows, n_entries = len(a["states"]), len(a["codes"])
        problems = [
            f"{k}: {len(a[k])} values for {n_rows} states"
            for k in ("offset", "length", "greedy")
            if len(a[k]) != n_rows
        ]
        problems += [
            f"{k}: {len(a[k])} values for {n_entries} joint actions"
            for k in ("q", "visits")
            if len(a[k]) != n_entries
        ]
        if not problems:
            ends = np.cumsum(a["length"])
            tiled = int(a["length"].sum()) == n_entries and np.array_equal(
                a["offset"], ends - a["length"]
            )
            if (a["length"] < 1).any() or not tiled:
                problems.append("row offsets and lengths do not tile the joint actions")
            elif ((a["codes"] < 0) | (a["codes"] >= self.joint.count)).any():
                problems.append(f"joint-action codes outside [0, {self.joint.count})")
            elif ((a["greedy"] < a["offset"]) | (a["greedy"] >= ends)).any():
                problems.append("a prior entry lies outside its state's row")
            elif len(np.unique(a["states"])) != n_rows or (a["visits"] < 0).any():
                problems.append("repeated states or negative visit counts")
        if problems:
            raise ValueError(f"table {prefix.rstrip('.') or 'Q'}: " + "; ".join(problems))
        for k in self._ARRAYS:
            getattr(self, f"_{k}").set(a[k])
        states = self._states.data.tolist()
        self.index = dict(zip(states, range(len(states)), strict=True))


class PendingTransitions:
    """Open transitions ``(entry, R, gamma^tau)`` per (copy, agent), for decision-point updates.

    Args:
        shape: ``(B, agents)``.
    """

    def __init__(self, shape: tuple[int, ...]) -> None:
        self.entry = np.full(shape, -1, np.int64)  # -1: nothing open
        self.ret = np.zeros(shape)  # R = sum_k gamma^k r_k since the decision
        self.discount = np.ones(shape)  # gamma^tau

    def start(self, where: np.ndarray, entries: np.ndarray) -> None:
        """Open a transition at a decision (replacing nothing: the last one was closed)."""
        self.entry[where] = entries[where]
        self.ret[where] = 0.0
        self.discount[where] = 1.0

    def accumulate(self, rewards: np.ndarray, gamma: float) -> None:
        """Add one tick's reward to the open transitions."""
        self.ret += self.discount * rewards
        self.discount *= gamma

    def drop(self, where: np.ndarray) -> None:
        """Forget open transitions without updating (episode truncation: no next state)."""
        self.entry[where] = -1

    def close(
        self, where: np.ndarray
    ) -> tuple[tuple[np.ndarray, ...], np.ndarray, np.ndarray, np.ndarray]:
        """Close the open transitions selected by ``where``.

        Args:
            where: Bool array of the pending shape.

        Returns:
            ``(positions, entries, ret, discount)``: ``np.nonzero`` positions of the closed
            transitions, their entries, ``R`` and ``gamma^tau``.
        """
        sel = where & (self.entry >= 0)
        pos = np.nonzero(sel)
        out = pos, self.entry[pos], self.ret[pos], self.discount[pos]
        self.entry[sel] = -1
        return out


# ---------------------------------------------------------------------------------- learner base
class TabularLearner(Learner):
    """Q-learning (paper eq. 3) with epsilon-greedy over valid actions; shared plumbing.

    Subclasses implement :meth:`encode`, :meth:`act`, :meth:`update`, the table arrays for
    save / load and :meth:`learning_space`.

    Args:
        env: The env (sizes, active tasks).
        rng: Exploration randomness.
        partition: The subG partition (subG-CQL only).
        alpha: Learning rate of eq. (3) (base value, see ``alpha_power``).
        alpha_power: ``alpha_n = max(alpha_min, alpha / n^alpha_power)`` with ``n`` the entry's
            visits; 0 keeps ``alpha`` constant.
        alpha_min: Floor of the decaying learning rate.
        gamma: Discount per tick.
        epsilon_start: Exploration rate in the first episode.
        epsilon_end: Exploration rate after the decay.
        epsilon_decay_episodes: Episodes of the linear decay (0: always ``epsilon_end``).
        decisions_only: Update only at decision points (semi-Markov, module docstring).
    """

    kind: ClassVar = "tabular"

    def __init__(
        self,
        *,
        env: AuctionEnv,
        rng: np.random.Generator,
        partition: Partition | None = None,
        alpha: float = 0.1,
        alpha_power: float = 0.0,
        alpha_min: float = 0.0,
        gamma: float = 0.9,
        epsilon_start: float = 0.2,
        epsilon_end: float = 0.0,
        epsilon_decay_episodes: int = 20,
        decisions_only: bool = True,
    ) -> None:
        super().__init__(env=env, rng=rng, partition=partition)
        if not 0.0 < alpha <= 1.0 or not 0.0 <= gamma <= 1.0:
            raise ValueError(f"need 0 < alpha <= 1 and 0 <= gamma <= 1, got {alpha}, {gamma}")
        if not (0.0 <= epsilon_start <= 1.0 and 0.0 <= epsilon_end <= 1.0):
            raise ValueError("epsilon_start and epsilon_end must be in [0, 1]")
        self.alpha, self.alpha_power, self.alpha_min = alpha, alpha_power, alpha_min
        self.gamma = gamma
        self.epsilon_schedule = LinearSchedule(epsilon_start, epsilon_end, epsilon_decay_episodes)
        self.decisions_only = decisions_only
        self.episodes_done = 0
        self.n_slots = env.n_slots
        # willingness d_i,type by slot type; the extra last row answers an empty slot (type -1)
        self._weight_by_type = np.vstack([env.system.willingness.T, np.zeros(env.n_robots)])

    @property
    def epsilon(self) -> float:
        """Current exploration rate (linear schedule over episodes)."""
        return self.epsilon_schedule(self.episodes_done)

    def end_episode(self) -> None:
        """Advance the epsilon schedule by one episode."""
        self.episodes_done += 1

    def _slot_weight(self, env: AuctionEnv) -> np.ndarray:
        """``[B, m, K]`` willingness of each robot for each slot's task type (0 if empty)."""
        return self._weight_by_type[env.slot_type].transpose(0, 2, 1)

    def _update(
        self, q: np.ndarray, visits: np.ndarray, entries: np.ndarray, targets: np.ndarray
    ) -> float:
        return apply_updates(
            q, visits, entries, targets, self.alpha, self.alpha_power, self.alpha_min
        )

    # -- persistence
    def _table_arrays(self) -> dict[str, np.ndarray]:
        raise NotImplementedError

    def _load_table_arrays(self, arrays: dict[str, np.ndarray]) -> None:
        raise NotImplementedError

    def save(self, directory: Path) -> None:
        """Write the tables (``q_tables.npz``) and the schedule position (``learner.json``).

        Args:
            directory: Target folder, created if missing.
        """
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(directory / Q_FILE, **self._table_arrays())
        meta = {"class": type(self).__name__, "episodes_done": self.episodes_done}
        (directory / META_FILE).write_text(json.dumps(meta, indent=2) + "\n")

    def load(self, directory: Path) -> None:
        """Restore what :meth:`save` wrote (``allow_pickle=False``), checked against this learner.

        Args:
            directory: Folder written by :meth:`save`.

        Raises:
            ValueError: naming the file, if it is unreadable, written by another learner class,
                or its arrays do not fit this learner (other system or partition, wrong
                dtype or shape, inconsistent tables).
        """
        directory = Path(directory)
        meta_path = directory / META_FILE
        try:
            meta = json.loads(meta_path.read_text())
            saved_class, episodes_done = meta["class"], int(meta["episodes_done"])
        except (OSError, ValueError, KeyError, TypeError) as err:
            raise ValueError(
                f"{meta_path}: not a learner description written by save ({err})"
            ) from err
        if saved_class != type(self).__name__:
            raise ValueError(f"{directory} holds a {saved_class}, not a {type(self).__name__}")
        arrays = read_npz(directory / Q_FILE)
        check_arrays(arrays, self._table_arrays(), directory / Q_FILE)
        try:
            self._load_table_arrays(arrays)
        except (ValueError, KeyError, IndexError) as err:
            raise ValueError(f"{directory / Q_FILE}: {err}") from err
        self.episodes_done = episodes_done


ZIP_MAGIC = b"PK\x03\x04"  # every npz file is a zip archive


def read_npz(path: Path) -> dict[str, np.ndarray]:
    """All arrays of an npz file written by ``np.savez``, never unpickling anything.

    Args:
        path: The file.

    Returns:
        ``{name: array}``.

    Raises:
        ValueError: naming the file, if it is missing, not an npz archive, or truncated.
    """
    try:
        with path.open("rb") as handle:
            head = handle.read(len(ZIP_MAGIC))
    except OSError as err:
        raise ValueError(f"{path}: cannot read the table file ({err})") from err
    if head != ZIP_MAGIC:
        raise ValueError(f"{path}: not a table file written by save (not an npz archive)")
    try:
        with np.load(path, allow_pickle=False) as data:
            return {k: data[k] for k in data.files}
    except Exception as err:  # zipfile, zlib and numpy raise several types on damaged files
        raise ValueError(
            f"{path}: truncated or damaged table file ({type(err).__name__}: {err})"
        ) from err


def check_arrays(
    arrays: dict[str, np.ndarray], expected: dict[str, np.ndarray], path: Path
) -> None:
    """Saved arrays against the arrays of the learner built for the run: names, dtypes, shapes.

    An expected array with no rows yet (a table that grows with visited states) fixes only its
    trailing dimensions; any other fixes its whole shape.

    Args:
        arrays: The loaded arrays.
        expected: The learner's own arrays (``_table_arrays()`` of the fresh learner).
        path: The file, for messages.

    Raises:
        ValueError: naming the file and the first mismatch.
    """
    if set(arrays) != set(expected):
        raise ValueError(
            f"{path}: holds arrays {sorted(arrays)}, this run's learner has {sorted(expected)} "
            "(saved for another system, partition or learner?)"
        )
    for name, want in expected.items():
        got = arrays[name]
        if got.dtype != want.dtype:
            raise ValueError(f"{path}: array {name} has dtype {got.dtype}, expected {want.dtype}")
        grows = want.ndim > 0 and want.shape[0] == 0
        fits = (
            got.shape[1:] == want.shape[1:] and got.ndim == want.ndim
            if grows
            else got.shape == want.shape
        )
        if not fits:
            shape = ("rows", *want.shape[1:]) if grows else want.shape
            raise ValueError(f"{path}: array {name} has shape {got.shape}, expected {shape}")
