"""Queued tasks as packed int64 keys, ordered as the spec's queue (auction_env.md, step 2).

The high bits of a key are the queue order (H before L, then due tick, then id) and the low bits
carry type, duration and round, so sorting a copy's keys orders its queue and an empty place is
:data:`EMPTY`, which sorts last. Bits: 62 low-priority flag | 42-61 due | 20-41 id | 10-19 type |
1-9 duration | 0 round 2.

Every function is compiled with numba and generic: the compiled kernel (``envs/kernel.py``) calls
it on scalars, Python code on int64 arrays (broadcast), so the bit layout is written once.
"""

from __future__ import annotations

import numpy as np
from numba import njit

LOW_SHIFT, DUE_SHIFT, ID_SHIFT, TYPE_SHIFT, DURATION_SHIFT = 62, 42, 20, 10, 1
DUE_BITS, ID_BITS, TYPE_BITS, DURATION_BITS = 20, 22, 10, 9
EMPTY = np.int64(np.iinfo(np.int64).max)  # an empty place; its due field is all ones
DUE_FIELD = np.int64(((1 << DUE_BITS) - 1) << DUE_SHIFT)
_DUE_MASK, _ID_MASK = (1 << DUE_BITS) - 1, (1 << ID_BITS) - 1
_TYPE_MASK, _DURATION_MASK = (1 << TYPE_BITS) - 1, (1 << DURATION_BITS) - 1


@njit(cache=True)
def pack_tasks(high, due, task_id, task_type, duration, round2):
    """Pack task fields (int64 scalars or arrays, broadcast) into int64 keys."""
    return (
        ((1 - high) << LOW_SHIFT)
        | (due << DUE_SHIFT)
        | (task_id << ID_SHIFT)
        | (task_type << TYPE_SHIFT)
        | (duration << DURATION_SHIFT)
        | round2
    )


@njit(cache=True)
def task_high(keys):
    """1 for an H task, 0 for an L task (meaningless on ``EMPTY``)."""
    return 1 - (keys >> LOW_SHIFT)


@njit(cache=True)
def task_due(keys):
    """Due tick of packed tasks."""
    return (keys >> DUE_SHIFT) & _DUE_MASK


@njit(cache=True)
def task_id(keys):
    """Id of packed tasks (arrival order within the episode)."""
    return (keys >> ID_SHIFT) & _ID_MASK


@njit(cache=True)
def task_type(keys):
    """Task type index (0-based) of packed tasks."""
    return (keys >> TYPE_SHIFT) & _TYPE_MASK


@njit(cache=True)
def task_duration(keys):
    """Duration of packed tasks."""
    return (keys >> DURATION_SHIFT) & _DURATION_MASK


@njit(cache=True)
def task_round(keys):
    """Auction round (1 or 2) of packed tasks."""
    return (keys & 1) + 1


@njit(cache=True)
def to_second_round(keys, due):
    """Spec step 6: the same tasks in round 2, due at ``due`` (broadcast)."""
    return (keys & ~DUE_FIELD) | (due << DUE_SHIFT) | 1
