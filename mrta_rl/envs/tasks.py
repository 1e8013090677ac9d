"""Queued tasks as packed int64 keys, ordered as the spec's queue (auction_env.md, step 2).

The high bits of a key are the queue order (H before L, then due tick, then id) and the low bits
carry type, duration and round, so one ``np.sort`` per tick orders every copy's queue and an empty
place is :data:`EMPTY`, which sorts last. Bits: 62 low-priority flag | 42-61 due | 20-41 id |
10-19 type | 1-9 duration | 0 round 2.
"""

from __future__ import annotations

import numpy as np

LOW_SHIFT, DUE_SHIFT, ID_SHIFT, TYPE_SHIFT, DURATION_SHIFT = 62, 42, 20, 10, 1
DUE_BITS, ID_BITS, TYPE_BITS, DURATION_BITS = 20, 22, 10, 9
EMPTY = np.int64(np.iinfo(np.int64).max)  # an empty place; its due field is all ones
DUE_FIELD = np.int64(((1 << DUE_BITS) - 1) << DUE_SHIFT)


def pack_tasks(high, due, task_id, task_type, duration, round2) -> np.ndarray:
    """Pack task fields (arrays or ints, broadcast) into int64 keys."""
    return (
        ((1 - np.asarray(high, np.int64)) << LOW_SHIFT)
        | (np.asarray(due, np.int64) << DUE_SHIFT)
        | (np.asarray(task_id, np.int64) << ID_SHIFT)
        | (np.asarray(task_type, np.int64) << TYPE_SHIFT)
        | (np.asarray(duration, np.int64) << DURATION_SHIFT)
        | np.asarray(round2, np.int64)
    )


def _field(keys: np.ndarray, shift: int, bits: int) -> np.ndarray:
    return (keys >> shift) & ((1 << bits) - 1)


def task_high(keys: np.ndarray) -> np.ndarray:
    """1 for an H task, 0 for an L task (meaningless on ``EMPTY``)."""
    return 1 - (keys >> LOW_SHIFT)


def task_due(keys: np.ndarray) -> np.ndarray:
    """Due tick of packed tasks."""
    return _field(keys, DUE_SHIFT, DUE_BITS)


def task_id(keys: np.ndarray) -> np.ndarray:
    """Id of packed tasks (arrival order within the episode)."""
    return _field(keys, ID_SHIFT, ID_BITS)


def task_type(keys: np.ndarray) -> np.ndarray:
    """Task type index (0-based) of packed tasks."""
    return _field(keys, TYPE_SHIFT, TYPE_BITS)


def task_duration(keys: np.ndarray) -> np.ndarray:
    """Duration of packed tasks."""
    return _field(keys, DURATION_SHIFT, DURATION_BITS)


def task_round(keys: np.ndarray) -> np.ndarray:
    """Auction round (1 or 2) of packed tasks."""
    return (keys & 1) + 1


def to_second_round(keys: np.ndarray, due: np.ndarray) -> np.ndarray:
    """Spec step 6: the same tasks in round 2, due at ``due`` (broadcast)."""
    return (keys & ~DUE_FIELD) | (np.asarray(due, np.int64) << DUE_SHIFT) | 1
