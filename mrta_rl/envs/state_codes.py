"""The digits of the state encodings, compiled: the one implementation of every code.

``envs/encodings.py`` describes the encodings (module docstring) and builds their tables
(slot codes, place values); the loops here compute the codes from the env's arrays, per copy,
for the numpy-facing functions of ``encodings`` and, called from compiled code, for the
tabular learners' fused ticks (``learners/tabular``). A digit rule lives in one function:

* recency level (:func:`recency`), battery level (:func:`battery_low`), free level
  (:func:`free_level_of`), queued counts and their levels (:func:`count_queued`,
  :func:`queue_levels_of`);
* the local state index of every robot (:func:`encode_local`), the group state indices of
  several groups (:func:`encode_groups`) and the ``time_to_free`` digits of a group
  (:func:`group_offsets`).
"""

from __future__ import annotations

from collections import namedtuple

import numpy as np
from numba import njit

from mrta_rl.envs.tasks import EMPTY, task_high, task_type

# The arrays of the state indices travel in named records, declared once here. Python passes
# each as a plain tuple in its fields' order (``encodings.env_arrays``, ``LocalView.tables``,
# ...); the compiled loops name them (``EnvArrays(*env)``).
EnvArrays = namedtuple(
    "EnvArrays",
    (
        "slot_type",  # [B, K] type of each slot's task, -1 empty
        "slot_high",  # [B, K] its priority (1 = H)
        "idle",  # [B, m]
        "battery",  # [B, m]
        "t",  # [B] ticks
        "last_high",  # [B, n] tick of the last H arrival per type
    ),
)
BusyArrays = namedtuple(
    "BusyArrays",
    (
        "busy_until",  # [B, m] robot i is idle at t when t > busy_until
        "queue",  # [B, W] packed tasks (envs/tasks.py), EMPTY after queue_len
        "queue_len",  # [B]
    ),
)
LocalTables = namedtuple(
    "LocalTables",
    (
        "margin",  # [m] battery_low's margin of each robot (encodings.battery_margin)
        "threshold",  # battery_low's threshold
        "codes",  # [n + 1, 2, m] slot code per (type, high, robot); row n: empty slot
        "slot_places",  # [K, m]
        "places",  # [m, digits] every digit's place
        "active",  # [m, n] bool Lambda_i
        "thresholds",  # [2] recency thresholds
        "time_to_free",  # bool: the free level and the queue levels (encodings.FEATURES)
        "free_soon",  # free level 1 within this many ticks
        "queue_thresholds",  # [2, 2] the H and the L thresholds
    ),
)
GroupTables = namedtuple(
    "GroupTables",
    (
        "margin",  # [m] battery_low's margin of each robot
        "threshold",  # battery_low's threshold
        "codes",  # [G, n + 1, 2] slot code per (group, type, high); row n: empty slot
        "slot_places",  # [G, K]
        "robots",  # [G, widest] robot indices of each group (padded)
        "size",  # [G] robots per group
        "robot_places",  # [G, widest]
        "recency_place",  # [G]
        "types",  # [G, n] bool T_g
        "thresholds",  # [2] recency thresholds
    ),
)
OffsetTables = namedtuple(
    "OffsetTables",
    (
        "robots",  # [G, widest] robot indices of each group (padded)
        "size",  # [G] robots per group
        "soon_places",  # [G, widest] what a robot free soon adds (0 on padding)
        "types",  # [G, n] bool T_g
        "queue_places",  # [G, 2] the places of the H and the L queue levels
        "free_soon",  # free level 1 within this many ticks
        "queue_thresholds",  # [2, 2] the H and the L thresholds
    ),
)


# ------------------------------------------------------------------------------ digits
@njit(cache=True)
def recency(last_high: np.ndarray, t: int, types: np.ndarray, thresholds: np.ndarray) -> int:
    """Recency level (``encodings.recency_level``) of one copy over the types ``types``."""
    last, found = 0, False
    for j in range(types.size):
        if types[j] and (not found or last_high[j] > last):
            last, found = last_high[j], True
    if not found:
        return 2  # never: the longest level
    delta = t - last
    return int(delta > thresholds[0]) + int(delta > thresholds[1])


@njit(cache=True)
def battery_low(battery: float, margin: float, threshold: float) -> int:
    """Battery level (``encodings.battery_level``) of one robot: 1 low, 0 ok."""
    return int(battery - margin < threshold)


@njit(cache=True)
def free_level_of(busy_until: int, t: int, free_soon: int) -> int:
    """Free level (``encodings.free_level``): 0 idle, 1 free within ``free_soon``, 2 later."""
    ticks = busy_until - t + 1  # idle again at busy_until + 1; <= 0 when idle
    return int(ticks > 0) + int(ticks > free_soon)


@njit(cache=True)
def _level(count: int, thresholds: np.ndarray) -> int:
    """Queue level of a count (``encodings.queue_level``): 0, 1 or 2 over two thresholds."""
    return int(count > thresholds[0]) + int(count > thresholds[1])


@njit(cache=True)
def count_queued(queue: np.ndarray, length: int, counts: np.ndarray) -> None:
    """Queued tasks of one copy per type and priority (``encodings.queue_counts``), written."""
    counts[:] = 0
    for w in range(length):  # places past the length are EMPTY (envs/kernel.py)
        if queue[w] != EMPTY:
            counts[task_type(queue[w]), task_high(queue[w])] += 1


@njit(cache=True)
def queue_levels_of(counts: np.ndarray, types: np.ndarray, thresholds: np.ndarray):
    """The queued H and L levels over the types ``types`` ``[n]`` (``encodings.queue_level``).

    Args:
        counts: ``[n, 2]`` queued tasks by type and priority (0 = L, 1 = H).
        types: ``[n]`` bool.
        thresholds: ``[2, 2]`` the H and the L thresholds.

    Returns:
        ``(H level, L level)``.
    """
    high = low = 0
    for j in range(types.shape[0]):
        if types[j]:
            high += counts[j, 1]
            low += counts[j, 0]
    return _level(high, thresholds[0]), _level(low, thresholds[1])


@njit(cache=True)
def _queue_digits(counts, types, thresholds, high_place: int, low_place: int) -> int:
    """The queued H and L levels over the types ``types`` ``[n]``, times their places."""
    high, low = queue_levels_of(counts, types, thresholds)
    return high * high_place + low * low_place


@njit(cache=True)
def _slot_code(codes: np.ndarray, ttype: int, high: int) -> int:
    """Code of a slot; an empty slot (type -1) reads the table's last row."""
    return codes[ttype if ttype >= 0 else codes.shape[0] - 1, max(high, 0)]


# ------------------------------------------------------------------------------ all copies
@njit(cache=True)
def recency_levels(last_high, t, types, thresholds, out):
    """``out[b, r]``: :func:`recency` of copy ``b`` over the types ``types[r]`` (``[R, n]``)."""
    for b in range(out.shape[0]):
        for r in range(out.shape[1]):
            out[b, r] = recency(last_high[b], t[b], types[r], thresholds)


@njit(cache=True)
def battery_levels(battery, margin, threshold, out):
    """``out[b, i]``: :func:`battery_low` of robot ``i`` in copy ``b``."""
    for b in range(out.shape[0]):
        for i in range(out.shape[1]):
            out[b, i] = battery_low(battery[b, i], margin[i], threshold)


@njit(cache=True)
def free_levels(busy_until, t, free_soon, out):
    """``out[b, i]``: :func:`free_level_of` of robot ``i`` in copy ``b``."""
    for b in range(out.shape[0]):
        for i in range(out.shape[1]):
            out[b, i] = free_level_of(busy_until[b, i], t[b], free_soon)


@njit(cache=True)
def queue_counts_of(queue, queue_len, out):
    """``out[b]``: :func:`count_queued` of copy ``b`` (``[B, n, 2]``)."""
    for b in range(out.shape[0]):
        count_queued(queue[b], queue_len[b], out[b])


@njit(cache=True)
def queue_levels(counts, types, thresholds, out):
    """``out[b, r]``: :func:`queue_levels_of` of copy ``b`` over ``types[r]`` (``[B, R, 2]``)."""
    for b in range(out.shape[0]):
        for r in range(out.shape[1]):
            out[b, r, 0], out[b, r, 1] = queue_levels_of(counts[b], types[r], thresholds)


# ------------------------------------------------------------------------------ state indices
@njit(cache=True)
def encode_groups(env, tables, states, level):
    """``GroupView`` state indices ``states`` and recency levels ``level`` ``[G, B]`` (written).

    ``env`` holds the env's arrays (:class:`EnvArrays`), ``tables`` the groups' tables
    (:class:`GroupTables`, ``learners.tabular.encoding.GroupEncoder``).
    """
    # the fields as locals: numba counts a reference at each read of a record's field
    env, tables = EnvArrays(*env), GroupTables(*tables)
    slot_type, slot_high, idle, battery = env.slot_type, env.slot_high, env.idle, env.battery
    codes, slot_places, margin = tables.codes, tables.slot_places, tables.margin
    robots, size, robot_places = tables.robots, tables.size, tables.robot_places
    types, recency_place, thresholds = tables.types, tables.recency_place, tables.thresholds
    t, last_high, threshold = env.t, env.last_high, tables.threshold
    for g in range(states.shape[0]):
        for b in range(states.shape[1]):
            index = 0
            for k in range(slot_type.shape[1]):
                index += _slot_code(codes[g], slot_type[b, k], slot_high[b, k]) * slot_places[g, k]
            for r in range(size[g]):
                i = robots[g, r]
                # robot digit: 0 busy, 1 idle with ok battery, 2 idle with low battery
                low = battery_low(battery[b, i], margin[i], threshold)
                index += idle[b, i] * (1 + low) * robot_places[g, r]
            level[g, b] = recency(last_high[b], t[b], types[g], thresholds)
            states[g, b] = index + level[g, b] * recency_place[g]


@njit(cache=True)
def group_offsets(t, busy, tables, out):
    """``[G, B]`` what ``time_to_free`` adds to the paper codes of :func:`encode_groups` (written).

    A busy robot free within ``free_soon`` ticks reads robot state 3 (the busy state 0 plus
    ``3 x`` its place), and the queued H and L levels over ``T_g`` follow the recency digit
    (``encodings.GroupView``, "Features"). ``t`` ``[B]`` holds the env's ticks, ``busy`` its
    busy-until ticks and queue (:class:`BusyArrays`), ``tables`` the groups' :class:`OffsetTables`.
    """
    # the fields as locals: numba counts a reference at each read of a record's field
    busy, tables = BusyArrays(*busy), OffsetTables(*tables)
    busy_until, queue, queue_len = busy.busy_until, busy.queue, busy.queue_len
    robots, size = tables.robots, tables.size
    types, queue_places, soon_places = tables.types, tables.queue_places, tables.soon_places
    thresholds, free_soon = tables.queue_thresholds, tables.free_soon
    counts = np.zeros((types.shape[1], 2), np.int64)  # [n, (L, H)]
    for b in range(out.shape[1]):
        count_queued(queue[b], queue_len[b], counts)
        for g in range(out.shape[0]):
            high, low = queue_places[g, 0], queue_places[g, 1]
            value = _queue_digits(counts, types[g], thresholds, high, low)
            for r in range(size[g]):
                if free_level_of(busy_until[b, robots[g, r]], t[b], free_soon) == 1:
                    value += soon_places[g, r]
            out[g, b] = value


@njit(cache=True)
def encode_local(env, busy, tables, out):
    """``LocalView`` state indices ``out`` ``[B, m]`` (written).

    ``env`` holds the env's arrays (:class:`EnvArrays`), ``busy`` its busy-until ticks and
    queue (:class:`BusyArrays`, ``encodings.busy_arrays``), ``tables`` a ``LocalView``'s
    :class:`LocalTables`. With ``time_to_free`` the first digit is the free level (instead of
    the idle flag) and the H and L queue levels over ``Lambda_i`` follow the recency digit
    (``encodings`` module docstring, "Features").
    """
    # the fields as locals: numba counts a reference at each read of a record's field
    env, busy, tables = EnvArrays(*env), BusyArrays(*busy), LocalTables(*tables)
    slot_type, slot_high, idle, battery = env.slot_type, env.slot_high, env.idle, env.battery
    t, last_high = env.t, env.last_high
    busy_until, queue, queue_len = busy.busy_until, busy.queue, busy.queue_len
    codes, slot_places, places = tables.codes, tables.slot_places, tables.places
    margin, threshold, active = tables.margin, tables.threshold, tables.active
    thresholds, time_to_free, free_soon = tables.thresholds, tables.time_to_free, tables.free_soon
    queue_thresholds = tables.queue_thresholds
    n_slots = slot_type.shape[1]
    counts = np.zeros((active.shape[1] if time_to_free else 0, 2), np.int64)  # [n, (L, H)]
    for b in range(out.shape[0]):
        if time_to_free:
            count_queued(queue[b], queue_len[b], counts)
        for i in range(out.shape[1]):
            if time_to_free:
                index = np.int64(free_level_of(busy_until[b, i], t[b], free_soon))
            else:
                index = np.int64(idle[b, i])
            for k in range(n_slots):
                ttype = slot_type[b, k] if slot_type[b, k] >= 0 else codes.shape[0] - 1
                index += codes[ttype, max(slot_high[b, k], 0), i] * slot_places[k, i]
            index += battery_low(battery[b, i], margin[i], threshold) * places[i, n_slots + 1]
            index += recency(last_high[b], t[b], active[i], thresholds) * places[i, n_slots + 2]
            if time_to_free:  # queued H and L tasks over Lambda_i
                high_place, low_place = places[i, n_slots + 3], places[i, n_slots + 4]
                index += _queue_digits(counts, active[i], queue_thresholds, high_place, low_place)
            out[b, i] = index
