"""Q storage of the joint-action learners: per (group, state) a row of valid joint actions.

:class:`JointQStorage` keeps the Q tables of all the groups of a learner (subG-CQL's sub-groups,
CQL's one group) in flat numpy arrays, so that compiled loops can read and grow them:

* an open-addressing hash table (linear probing, power-of-two capacity, at most half full) maps
  ``(group, state index)`` to a row;
* per row (``rows[:, row]``): the state, its group, the first entry, the number of entries (its
  valid joint actions, :func:`~mrta_rl.learners.tabular.joint_actions.enumerate_row`) and the
  entry of the prior's joint action (the tie-break);
* per entry: the joint action code, the visit count and ``Q(s, a)``.

Rows are created on a state's first visit at a decision, in increasing state order within a
batch, entries of a row are contiguous. :meth:`JointQStorage.to_arrays` gives each group's table
as it is saved (``q_tables.npz``, the format of the earlier per-group tables).

The tables grow with the states met, which no up-front estimate bounds tightly
(``learners/resources.py``). :attr:`JointQStorage.max_bytes` (set by the runner from
``limits.memory_gb``, :func:`limit_growth`) makes a growth past the limit a
:class:`TableGrowthError`, a user error with the sizes, instead of numpy's allocation failure (or
the machine swapping) deep inside training.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import njit

from mrta_rl.config import UserError
from mrta_rl.learners.resources import format_bytes

ROW_STATE, ROW_GROUP, ROW_OFFSET, ROW_LENGTH, ROW_PRIOR = range(5)  # rows of ``rows``
ENTRY_CODE, ENTRY_VISITS = range(2)  # rows of ``entries``
TABLE_KEYS = ("states", "offset", "length", "greedy", "codes", "q", "visits")  # saved per group
_EMPTY = -1  # free hash slot


@njit(cache=True)
def _slot(state: int, group: int, capacity: int) -> int:
    """Start of the probe sequence of ``(group, state)`` (splitmix64 finaliser of the pair)."""
    x = np.uint64(state) * np.uint64(0x9E3779B97F4A7C15) + np.uint64(group)
    x ^= x >> np.uint64(30)
    x *= np.uint64(0xBF58476D1CE4E5B9)
    x ^= x >> np.uint64(27)
    x *= np.uint64(0x94D049BB133111EB)
    x ^= x >> np.uint64(31)
    return np.int64(x & np.uint64(capacity - 1))


@njit(cache=True)
def find_row(table: np.ndarray, state: int, group: int) -> int:
    """Row of ``(group, state)`` in the hash ``table`` (``[3, capacity]``), or -1 if absent."""
    capacity = table.shape[1]
    h = _slot(state, group, capacity)
    while table[0, h] != _EMPTY:
        if table[0, h] == state and table[1, h] == group:
            return table[2, h]
        h = (h + 1) & (capacity - 1)
    return -1


@njit(cache=True)
def insert_row(table: np.ndarray, state: int, group: int, row: int) -> None:
    """Map ``(group, state)`` to ``row`` (the key must be new; the table must have room)."""
    capacity = table.shape[1]
    h = _slot(state, group, capacity)
    while table[0, h] != _EMPTY:
        h = (h + 1) & (capacity - 1)
    table[0, h], table[1, h], table[2, h] = state, group, row


@njit(cache=True)
def _rebuild_hash(rows: np.ndarray, n_rows: int, capacity: int) -> np.ndarray:
    table = np.full((3, capacity), _EMPTY, np.int64)
    for row in range(n_rows):
        insert_row(table, rows[ROW_STATE, row], rows[ROW_GROUP, row], row)
    return table


@njit(cache=True)
def candidate_value(rows, entries, q, row: int, entry: int, min_visits: int, lcb=0.0) -> float:
    """Q of an entry if it competes (the prior, or tried ``min_visits`` times), else -inf.

    With ``lcb > 0`` an entry other than the prior's competes with its lower confidence bound
    ``Q - lcb / sqrt(visits)``: the greatest of many noisy means is biased upwards (the winner's
    curse), so a deviation from the prior must beat it by more than its own noise.
    """
    visits = entries[ENTRY_VISITS, entry]
    if entry == rows[ROW_PRIOR, row]:
        return q[entry]
    if min_visits > 0 and visits < min_visits:
        return -np.inf
    if lcb > 0.0:
        return q[entry] - lcb / np.sqrt(max(visits, 1))
    return q[entry]


@njit(cache=True)
def max_q(rows, entries, q, row: int, min_visits: int, lcb=0.0) -> float:
    """Eq. (3)'s ``max_a'`` over the competing entries of a row (the greedy policy's value)."""
    start = rows[ROW_OFFSET, row]
    best = -np.inf
    for e in range(start, start + rows[ROW_LENGTH, row]):
        best = max(best, candidate_value(rows, entries, q, row, e, min_visits, lcb))
    return best


@njit(cache=True)
def best_entry(rows, entries, q, row: int, min_visits: int, lcb=0.0) -> int:
    """Entry of the greatest Q of a row; ties go to the prior's joint action.

    With ``min_visits > 0`` only the prior and the entries updated at least ``min_visits`` times
    compete: an entry tried once by exploration holds a single noisy target and must not replace
    the prior on that evidence.
    """
    start = rows[ROW_OFFSET, row]
    best, first = -np.inf, start
    for e in range(start, start + rows[ROW_LENGTH, row]):
        value = candidate_value(rows, entries, q, row, e, min_visits, lcb)
        if value > best:
            best, first = value, e
    prior = rows[ROW_PRIOR, row]
    return prior if q[prior] >= best else first


@njit(cache=True)
def random_entry(rows, row: int, u: float) -> int:
    """Uniform valid joint action of a row (exploration), from ``u`` in [0, 1)."""
    length = rows[ROW_LENGTH, row]
    return rows[ROW_OFFSET, row] + min(int(u * length), length - 1)


class TableGrowthError(UserError):
    """A Q-table would grow past the memory it may take (:attr:`JointQStorage.max_bytes`)."""


def limit_growth(learner: Any, max_bytes: int | None) -> None:
    """Bound the growth of every :class:`JointQStorage` a learner holds (None: unbounded).

    Args:
        learner: Any learner; those without a joint table are left as they are.
        max_bytes: The bytes each table may take.
    """
    for value in vars(learner).values():
        if isinstance(value, JointQStorage):
            value.max_bytes = max_bytes


class JointQStorage:
    """The Q tables of ``n_groups`` groups over (state, valid joint action), in flat arrays.

    Args:
        n_groups: Number of groups ``G``.

    Attributes:
        hash: ``[3, capacity]`` int64 open-addressing table: state, group, row (-1: free).
        rows: ``[5, row capacity]`` int64 per row: state, group, offset, length, prior entry.
        entries: ``[2, entry capacity]`` int64 per entry: joint code, visits.
        q: ``[entry capacity]`` float64 ``Q(s, a)``.
        sizes: ``[2]`` int64 rows and entries in use (the compiled loops bump them).
        max_bytes: Bytes the arrays may take after a growth (None: unbounded; module docstring).
    """

    max_bytes: int | None = None

    def __init__(self, n_groups: int) -> None:
        self.n_groups = n_groups
        self.hash = np.full((3, 1024), _EMPTY, np.int64)
        self.rows = np.zeros((5, 256), np.int64)
        self.entries = np.zeros((2, 4096), np.int64)
        self.q = np.zeros(4096)
        self.sizes = np.zeros(2, np.int64)

    @property
    def n_rows(self) -> int:
        """Rows in use (states met at a decision, all groups)."""
        return int(self.sizes[0])

    @property
    def n_entries(self) -> int:
        """Entries in use."""
        return int(self.sizes[1])

    def reserve(self, rows: int, entries: int) -> None:
        """Make room for ``rows`` more rows and ``entries`` more entries (amortised doubling).

        Raises:
            TableGrowthError: if the grown arrays would take more than :attr:`max_bytes`;
                nothing is changed then.
        """
        n_rows, n_entries = self.sizes.tolist()
        need_rows, need_entries = n_rows + rows, n_entries + entries
        if (  # the usual case, checked first: room everywhere
            need_rows <= self.rows.shape[1]
            and need_entries <= self.q.size
            and 2 * need_rows <= self.hash.shape[1]
        ):
            return
        row_capacity = self.rows.shape[1]
        if need_rows > row_capacity:
            row_capacity = max(need_rows, 2 * row_capacity)
        entry_capacity = self.q.size
        if need_entries > entry_capacity:
            entry_capacity = max(need_entries, 2 * entry_capacity)
        hash_capacity = self.hash.shape[1]
        while 2 * need_rows > hash_capacity:  # at most half full: short probe sequences
            hash_capacity *= 2
        self._check_growth(row_capacity, entry_capacity, hash_capacity, need_rows)
        if row_capacity > self.rows.shape[1]:
            grown = np.zeros((5, row_capacity), np.int64)
            grown[:, : self.n_rows] = self.rows[:, : self.n_rows]
            self.rows = grown
        if entry_capacity > self.q.size:
            grown = np.zeros((2, entry_capacity), np.int64)
            grown[:, : self.n_entries] = self.entries[:, : self.n_entries]
            q = np.zeros(entry_capacity)
            q[: self.n_entries] = self.q[: self.n_entries]
            self.entries, self.q = grown, q
        if hash_capacity > self.hash.shape[1]:
            self.hash = _rebuild_hash(self.rows, self.n_rows, hash_capacity)

    @property
    def nbytes(self) -> int:
        """Bytes of the arrays (capacity, not only what is in use)."""
        return self.hash.nbytes + self.rows.nbytes + self.entries.nbytes + self.q.nbytes

    def _check_growth(self, rows: int, entries: int, hash_slots: int, states: int) -> None:
        """Raise :class:`TableGrowthError` if arrays of these capacities pass :attr:`max_bytes`."""
        if self.max_bytes is None:
            return
        grown = 8 * (3 * hash_slots + 5 * rows + 3 * entries)  # int64 / float64 columns
        if grown > self.max_bytes:
            raise TableGrowthError(
                f"the Q-table would grow from {format_bytes(self.nbytes)} to "
                f"{format_bytes(grown)} (room for {states:,} rows, states met, and their valid "
                f"joint actions), more than the limit of {format_bytes(self.max_bytes)}"
            )

    def row(self, group: int, state: int) -> int:
        """Row of a state of a group, or -1 if it was never met."""
        return int(find_row(self.hash, int(state), int(group)))

    def visits(self) -> np.ndarray:
        """Visit counts of the entries in use (a view)."""
        return self.entries[ENTRY_VISITS, : self.n_entries]

    def n_visited(self) -> int:
        """Entries updated at least once."""
        return int(np.count_nonzero(self.visits()))

    def group_rows(self, group: int) -> np.ndarray:
        """Rows of a group, in creation order."""
        return np.flatnonzero(self.rows[ROW_GROUP, : self.n_rows] == group)

    def row_entries(self, row: int) -> slice:
        """The entries of a row."""
        start = int(self.rows[ROW_OFFSET, row])
        return slice(start, start + int(self.rows[ROW_LENGTH, row]))

    def state_q(self, group: int, state: int) -> dict[int, float]:
        """``{joint code: Q}`` of a stored state (for tests and inspection).

        Raises:
            KeyError: if the state was never met.
        """
        row = self.row(group, state)
        if row < 0:
            raise KeyError(f"state {state} of group {group} is not stored")
        at = self.row_entries(row)
        return dict(zip(self.entries[ENTRY_CODE, at].tolist(), self.q[at].tolist(), strict=True))

    def to_arrays(self, group: int) -> dict[str, np.ndarray]:
        """One group's table as saved: :data:`TABLE_KEYS` arrays, entries numbered per group."""
        rows = self.group_rows(group)
        lengths = self.rows[ROW_LENGTH, rows]
        offsets = np.cumsum(lengths) - lengths
        starts = self.rows[ROW_OFFSET, rows]
        idx = np.repeat(starts - offsets, lengths) + np.arange(lengths.sum(), dtype=np.int64)
        return {
            "states": self.rows[ROW_STATE, rows].copy(),
            "offset": offsets,
            "length": lengths.copy(),
            "greedy": self.rows[ROW_PRIOR, rows] - starts + offsets,
            "codes": self.entries[ENTRY_CODE, idx].copy(),
            "q": self.q[idx].copy(),
            "visits": self.entries[ENTRY_VISITS, idx].copy(),
        }

    def from_rows(self, states: np.ndarray) -> None:
        """Restore rows without entries (one group): row ``k`` holds ``states[k]``."""
        self.__init__(self.n_groups)
        self.reserve(len(states), 0)
        self.rows[ROW_STATE, : len(states)] = states
        self.sizes[0] = len(states)
        self.hash = _rebuild_hash(self.rows, len(states), self.hash.shape[1])

    def from_arrays(
        self, tables: list[dict[str, np.ndarray]], joint_counts: list[int] | None = None
    ) -> None:
        """Restore every group from :meth:`to_arrays` outputs (one dict per group, in order).

        Args:
            tables: One dict of :data:`TABLE_KEYS` arrays per group.
            joint_counts: Number of joint-action codes of each group, to check the codes.

        Raises:
            ValueError: if a group's arrays do not form one consistent table (see
                :func:`check_table`).
        """
        for group, t in enumerate(tables):
            check_table(t, None if joint_counts is None else joint_counts[group], f"G{group + 1}")
        self.__init__(self.n_groups)
        n_rows = sum(len(t["states"]) for t in tables)
        n_entries = sum(len(t["codes"]) for t in tables)
        self.reserve(n_rows, n_entries)
        row, entry = 0, 0
        for group, t in enumerate(tables):
            n, e = len(t["states"]), len(t["codes"])
            self.rows[ROW_STATE, row : row + n] = t["states"]
            self.rows[ROW_GROUP, row : row + n] = group
            self.rows[ROW_OFFSET, row : row + n] = t["offset"] + entry
            self.rows[ROW_LENGTH, row : row + n] = t["length"]
            self.rows[ROW_PRIOR, row : row + n] = t["greedy"] + entry
            self.entries[ENTRY_CODE, entry : entry + e] = t["codes"]
            self.entries[ENTRY_VISITS, entry : entry + e] = t["visits"]
            self.q[entry : entry + e] = t["q"]
            row, entry = row + n, entry + e
        self.sizes[:] = row, entry
        self.hash = _rebuild_hash(self.rows, row, self.hash.shape[1])


def check_table(t: dict[str, np.ndarray], joint_count: int | None, name: str) -> None:
    """Check that one group's saved arrays form one consistent table.

    Args:
        t: The group's :data:`TABLE_KEYS` arrays.
        joint_count: Number of joint-action codes of the group (None: codes not checked).
        name: The group, for messages.

    Raises:
        ValueError: if lengths, offsets, joint-action codes, prior entries or visit counts do
            not fit together.
    """
    a = {k: np.asarray(t[k]) for k in TABLE_KEYS}
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
        elif joint_count is not None and ((a["codes"] < 0) | (a["codes"] >= joint_count)).any():
            problems.append(f"joint-action codes outside [0, {joint_count})")
        elif ((a["greedy"] < a["offset"]) | (a["greedy"] >= ends)).any():
            problems.append("a prior entry lies outside its state's row")
        elif len(np.unique(a["states"])) != n_rows or (a["visits"] < 0).any():
            problems.append("repeated states or negative visit counts")
    if problems:
        raise ValueError(f"table {name}: " + "; ".join(problems))
