"""The tick of ``auction_env.md`` as compiled per-copy loops (numba): THE dynamics of the project.

:class:`~mrta_rl.envs.auction.AuctionEnv` owns the arrays and calls these functions; nothing else
implements a rule of the spec. Each function loops over copies and, per copy, over the spec's
steps in order, reading and writing the env's arrays in place. All are compiled once per process
(``cache=True``: the machine code is stored in ``__pycache__`` next to this file, so later
processes only load it) and release the GIL, so threads over shards of copies run concurrently.

A tick is split at the decision: :func:`begin_copy` runs spec steps 1-3 (arrivals, queue order
and overflow, slots) so that the caller sees the slots it decides on, :func:`step_copies` steps 4-8
and then steps 1-3 of the next tick. Overflow drops of step 2 are paid in the reward of that same
tick, returned by the following step; :func:`robot_rewards` shares the drop penalties (step 8).

The arrays travel in named records (numba namedtuples), each declared once below:

- :class:`Tables` (:data:`TABLE_FIELDS`, the parameters named by :class:`Params`:
  :data:`INT_PARAMS`, :data:`FLOAT_PARAMS`), written once by the env, and :class:`State`
  (:data:`STATE_FIELDS`), per-copy arrays ``[B, ...]``. The env keeps them in one flat buffer
  per dtype (:data:`BUFFER_DTYPES`), the int64 one starting with their layout; the entry points
  (:func:`step`, :func:`refresh`, :func:`fixed_actions`, :func:`play`) take the buffers and
  :func:`unpack` builds the two records inside compiled code. numba unboxes every array
  argument of a call from Python, the larger part of a call's cost at small batch sizes, so 4
  buffers cost less than 27 arrays (and a namedtuple built in Python costs more than its
  arrays).
- :class:`Views` (:data:`VIEW_FIELDS`): what a decision sees, fresh arrays written each tick.
- :class:`Rewards`: one tick's rewards; :class:`Stats` (:data:`STATS`): finished episodes'
  statistics, written by :func:`play`.

Python passes the views, rewards and statistics as plain tuples in their fields' order (as cheap
as separate arrays), and the entry points name them.
"""

from __future__ import annotations

from collections import namedtuple

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic

from mrta_rl.envs.counter_rng import (
    bounded_uint,
    episode_key,
    high_bits,
    mix64,
    task_hash_pair,
    tick_key,
    unit_float,
)
from mrta_rl.envs.tasks import (
    EMPTY,
    pack_tasks,
    task_due,
    task_duration,
    task_high,
    task_round,
    task_type,
    to_second_round,
)
from mrta_rl.rules import count_valid, greedy, high_only, slot_winner, valid_action_of_rank

# The env's parameters the dynamics read, named as AuctionParams' fields. The env stores them
# in two arrays of the tables (iparams, fparams, in this order) and unpack names them (Params).
INT_PARAMS = (
    "horizon",
    "slots",
    "queue_capacity",
    "reauction_delay",
    "charge_ticks",
    "switch_ticks",
    "zones",
)
FLOAT_PARAMS = (
    "p_high",
    "battery_capacity",
    "drain_per_tick",
    "battery_threshold",
    "reward_assign_low",
    "reward_assign_high",
    "penalty_drop_low",
    "penalty_drop_high",
)
NEVER = -(1 << 30)  # last_high_arrival before any H arrival: far in the past

# The env's arrays: name, dimensions, dtype. A dimension is a number or one of the env's sizes:
# B copies, m robots, n task types, K slots, W queue places, C arrival counts (``len(cdf)``).
TABLE_FIELDS = (
    ("iparams", str(len(INT_PARAMS)), np.int64),  # INT_PARAMS' values
    ("fparams", str(len(FLOAT_PARAMS)), np.float64),  # FLOAT_PARAMS' values
    ("cdf", "C", np.float64),  # Poisson CDF of the arrival count
    ("dur_lo", "n 2", np.int64),  # shortest duration by type and priority (0 = L, 1 = H)
    ("dur_span", "n 2", np.int64),  # number of possible durations by type and priority
    ("willingness", "n m", np.float64),  # d_iz by type
    ("can_do", "n m", np.bool_),  # Lambda_i by type
)
STATE_FIELDS = (
    ("seed_key", "B", np.uint64),  # key of the copy's seed
    ("episode", "B", np.uint64),  # episodes started so far (the next episode's number)
    ("episode_key", "B", np.uint64),  # key of the current episode's draws
    ("t", "B", np.int64),  # current tick
    ("queue", "B W", np.int64),  # packed tasks (envs/tasks.py), EMPTY after queue_len
    ("queue_len", "B", np.int64),  # places in use (may hold EMPTY holes until compaction)
    ("next_id", "B", np.int64),  # id of the next arriving task
    ("busy_until", "B m", np.int64),  # robot i is idle at t when t > busy_until
    ("battery", "B m", np.float64),
    ("last_type", "B m", np.int64),  # type of the robot's previous task, -1: none (switch cost)
    ("last_high_arrival", "B n", np.int64),  # tick of the last H arrival per type
    ("done", "B", np.bool_),  # the episode has reached the horizon
    ("pending_penalty", "B n", np.float64),  # this tick's overflow penalties, paid next step
    ("assigned", "B n 2", np.int64),  # stats: tasks assigned per type and priority (0 = L)
    ("dropped", "B n 2", np.int64),  # stats: tasks dropped per type and priority
    ("busy_ticks", "B m", np.int64),  # stats: busy ticks per robot (spec step 7)
    ("team_return", "B", np.float64),  # stats: sum of team rewards
    ("ticks", "B", np.int64),  # stats: ticks played
    ("slot_pos", "B K", np.int64),  # queue place of each slot's task, -1: empty slot
    ("slot_keys", "B K", np.int64),  # packed task of each slot, EMPTY: empty slot
)
FIELDS = TABLE_FIELDS + STATE_FIELDS  # the rows of the layout
# slot_type, slot_high [B, K] (-1: empty), idle [B, m], mask [B, m, K + 1]
VIEW_FIELDS = ("slot_type", "slot_high", "idle", "mask")
STATS = ("assigned", "dropped", "busy_ticks", "team_return", "ticks")  # a State's statistics
BUFFER_DTYPES = (np.uint64, np.int64, np.float64, np.bool_)  # a field lives in its dtype's buffer
LAYOUT_SIZE = 4 * len(FIELDS)  # the int64 buffer's first places: the layout (see unpack)

PARAM_FIELDS = {"iparams": INT_PARAMS, "fparams": FLOAT_PARAMS}  # the tables' named values
Params = namedtuple("Params", INT_PARAMS + FLOAT_PARAMS)
# the tables without the parameter arrays, and their values as one record first
Tables = namedtuple(
    "Tables", ["params"] + [name for name, _, _ in TABLE_FIELDS if name not in PARAM_FIELDS]
)
State = namedtuple("State", [name for name, _, _ in STATE_FIELDS])
Views = namedtuple("Views", VIEW_FIELDS)
# team [B], assign [B, m] (assign reward each robot won), type_penalty [B, n] (drops by type)
Rewards = namedtuple("Rewards", ("team", "assign", "type_penalty"))
Stats = namedtuple("Stats", STATS)  # row r * B + b: episode r of copy b
Plan = namedtuple("Plan", ("policy", "max_ticks", "rounds"))  # what play() plays, see play_copy
Scratch = namedtuple("Scratch", ("actions", "rewards"))  # play_copy's working rows

POLICIES = {"greedy": 0, "random": 1, "high_only": 2}  # the spec's fixed policies
_POLICY_SALT = np.uint64(0x5851F42D4C957F2D)  # keys the random policy's draws apart from arrivals


def _compile_unpack():
    """``unpack(buffers) -> (Tables, State)``, generated from :data:`FIELDS`.

    The int64 buffer starts with the layout ``[len(FIELDS), 4]`` (written by ``AuctionEnv``):
    row ``f`` holds field ``f``'s offset in its dtype's buffer and its shape (unused trailing
    dimensions 1). The values of the parameter arrays (:data:`PARAM_FIELDS`) become the
    :class:`Params` record, ``Tables.params``. The source is generated because numba needs each
    field's buffer and number of dimensions at compile time; it is compiled under this file's
    name, so numba caches it with the rest.
    """
    views, arrays, values = [], [], []
    for f, (name, dims, dtype) in enumerate(FIELDS):
        view = f"buffers[{BUFFER_DTYPES.index(dtype)}][o[{f}] : o[{f}] + d[{f}].prod()]"
        ndim = len(dims.split())
        if ndim > 1:
            view += f".reshape(({', '.join(f'd[{f}, {k}]' for k in range(ndim))}))"
        if name in PARAM_FIELDS:  # one view, then its values
            arrays.append(f"    {name} = {view}\n")
            values += [f"{name}[{k}]" for k in range(len(PARAM_FIELDS[name]))]
        else:
            views.append(view)
    split = len(TABLE_FIELDS) - len(PARAM_FIELDS)
    tables, state = ", ".join(["params", *views[:split]]), ", ".join(views[split:])
    source = (
        "def unpack(buffers):\n"
        f"    layout = buffers[{BUFFER_DTYPES.index(np.int64)}][:{LAYOUT_SIZE}]"
        f".reshape(({len(FIELDS)}, 4))\n"
        "    o, d = layout[:, 0], layout[:, 1:]\n"
        f"{''.join(arrays)}"
        f"    params = Params({', '.join(values)})\n"
        f"    return Tables({tables}), State({state})\n"
    )
    namespace = {"__name__": __name__, "Tables": Tables, "State": State, "Params": Params}
    exec(compile(source, __file__, "exec"), namespace)
    return njit(cache=True, nogil=True)(namespace["unpack"])


unpack = _compile_unpack()


@intrinsic
def _fma(typingctx, x, y, z):
    """``x * y + z`` rounded once (LLVM's ``fma``)."""
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context, builder, signature, args):
        double = ir.DoubleType()
        fma = builder.module.declare_intrinsic(
            "llvm.fma", [double], ir.FunctionType(double, [double] * 3)
        )
        return builder.call(fma, args)

    return sig, codegen


@njit(cache=True, nogil=True)
def drop_penalty(params, high):
    """Spec step 8: the penalty of dropping a task of priority ``high`` (1 = H)."""
    return params.penalty_drop_high if high else params.penalty_drop_low


# ---------------------------------------------------------------------------- spec steps 1-3
@njit(cache=True, nogil=True)
def begin_copy(b, tables, state):
    """Spec steps 1-2 of tick ``t[b]`` in copy ``b``: arrivals, queue order, overflow drops."""
    # the fields as locals: numba counts a reference at each read of a record's field
    queue, queue_len, next_id = state.queue, state.queue_len, state.next_id
    pending_penalty, dropped, last_high_arrival = (
        state.pending_penalty,
        state.dropped,
        state.last_high_arrival,
    )
    params, dur_lo, dur_span = tables.params, tables.dur_lo, tables.dur_span
    length, now, n = 0, state.t[b], last_high_arrival.shape[1]
    pending_penalty[b, :] = 0.0
    # drop the holes left by the last step's slot tasks (assigned or dropped)
    for j in range(queue_len[b]):
        if queue[b, j] != EMPTY:
            queue[b, length] = queue[b, j]
            length += 1
    for j in range(length, queue_len[b]):
        queue[b, j] = EMPTY
    # spec step 1: N ~ Poisson(arrival_rate) new tasks, all counter-based hashes (counter_rng)
    key = tick_key(state.episode_key[b], np.uint64(now))
    count = np.searchsorted(tables.cdf, unit_float(key), side="right")
    for k in range(count):
        h_priority, h_kind = task_hash_pair(key, np.uint64(k + 1))
        # H with probability p_high; type uniform over the n types (high 32 bits of h_kind),
        # duration uniform over its type and priority's range, ends included (low 32 bits)
        high = np.int64(unit_float(h_priority) < params.p_high)
        ttype = np.int64(bounded_uint(high_bits(h_kind), np.uint64(n)))
        span = np.uint64(dur_span[ttype, high])
        duration = dur_lo[ttype, high] + np.int64(bounded_uint(h_kind, span))
        queue[b, length] = pack_tasks(high, now, next_id[b] + k, ttype, duration, np.int64(0))
        length += 1
        if high:
            last_high_arrival[b, ttype] = now
    next_id[b] += count
    # spec step 2: queue order (H before L, due tick, id) is the keys' order; insertion sort, as
    # the queue is sorted already but for the new tasks and the re-auctioned ones
    for j in range(1, length):
        x = queue[b, j]
        i = j - 1
        while i >= 0 and queue[b, i] > x:
            queue[b, i + 1] = queue[b, i]
            i -= 1
        queue[b, i + 1] = x
    # spec step 2: while the queue holds more than queue_capacity tasks, the last one is dropped
    capacity = params.queue_capacity
    for j in range(capacity, length):
        x = queue[b, j]
        ttype, high = task_type(x), task_high(x)
        dropped[b, ttype, high] += 1
        pending_penalty[b, ttype] += drop_penalty(params, high)
        queue[b, j] = EMPTY
    queue_len[b] = min(length, capacity)


@njit(cache=True, nogil=True)
def select_copy(b, tables, state, views):
    """Spec step 3 and the decision's inputs (step 4) of copy ``b``; idempotent."""
    queue, slot_pos, slot_keys, busy_until = (
        state.queue,
        state.slot_pos,
        state.slot_keys,
        state.busy_until,
    )
    slot_type, slot_high, idle, mask = views
    can_do = tables.can_do
    K, m = slot_pos.shape[1], busy_until.shape[1]
    now = state.t[b]
    k = 0
    if not state.done[b]:  # a finished copy auctions nothing
        # the first K queued tasks due by now, in queue order (EMPTY is never due)
        for j in range(state.queue_len[b]):
            x = queue[b, j]
            if x != EMPTY and task_due(x) <= now:
                slot_pos[b, k], slot_keys[b, k] = j, x
                slot_type[b, k], slot_high[b, k] = task_type(x), task_high(x)
                k += 1
                if k == K:
                    break
    for kk in range(k, K):
        slot_pos[b, kk], slot_keys[b, kk], slot_type[b, kk], slot_high[b, kk] = -1, EMPTY, -1, -1
    # spec step 4: idle when t > busy_until; a bid for slot k is valid if the robot is idle and
    # the slot holds a task of one of its active types (Lambda_i) in the robot's zone (robot i's
    # zone is i * zones // m, slot k's is (k - 1) % zones); waiting is always valid
    zones = tables.params.zones
    for i in range(m):
        free = now > busy_until[b, i]
        idle[b, i] = free
        mask[b, i, 0] = True
        if zones == 1:  # one auction (a plain loop: a stepped range costs System-II 12 %)
            for kk in range(K):
                ttype = slot_type[b, kk]
                mask[b, i, kk + 1] = free and ttype >= 0 and can_do[ttype, i]
            continue
        for kk in range(K):  # other zones' slots
            mask[b, i, kk + 1] = False
        for kk in range(i * zones // m, K, zones):
            ttype = slot_type[b, kk]
            mask[b, i, kk + 1] = free and ttype >= 0 and can_do[ttype, i]


# ---------------------------------------------------------------------------- spec steps 4-8
@njit(cache=True, nogil=True)
def step_copies(lo, hi, actions, tables, state, idle_before, views, rewards):
    """Spec steps 4-8 of copies ``lo .. hi - 1`` under ``actions`` (valid), each then steps 1-3.

    Copy by copy, each one's next tick begins before the following copy is stepped.

    One call for many copies: numba increfs and decrefs every array argument at each call (atomic
    operations, a fifth of a small batch's tick when this was called once per copy).

    ``idle_before`` holds the idle flags the actions were decided on (spec step 7 reads them);
    the next tick's ``views`` are written (the same arrays or fresh ones).

    Writes the tick's :class:`Rewards` of each copy: the team reward, the assign reward each
    robot won and the drop penalties by type (spec step 8; :func:`robot_rewards` shares them).
    """
    params, willingness = tables.params, tables.willingness
    queue, slot_keys, slot_pos = state.queue, state.slot_keys, state.slot_pos
    t, done, pending_penalty = state.t, state.done, state.pending_penalty
    busy_until, battery, last_type = state.busy_until, state.battery, state.last_type
    assigned, dropped, busy_ticks = state.assigned, state.dropped, state.busy_ticks
    team_return, ticks = state.team_return, state.ticks
    team_reward, assign_reward, type_penalty = rewards
    K, m, n = slot_pos.shape[1], busy_until.shape[1], pending_penalty.shape[1]
    for b in range(lo, hi):
        now = t[b]
        # spec step 8 counts this tick's overflow drops (spec step 2)
        team = 0.0
        for j in range(n):
            team += pending_penalty[b, j]
            type_penalty[b, j] = pending_penalty[b, j]
        team = -team
        for i in range(m):
            assign_reward[b, i] = 0.0
        # spec step 5, slot by slot: among the bidders, the highest willingness wins, ties to the
        # lowest robot index (rules.slot_winner)
        for k in range(K):
            x = slot_keys[b, k]
            if x == EMPTY:
                continue
            ttype, high = task_type(x), task_high(x)
            winner = slot_winner(actions[b], k + 1, willingness[ttype])
            if winner < 0:
                continue
            # a task of another type than the robot's previous one first needs switch_ticks of
            # setup, busy and draining as execution does (docs/spec/auction_env.md, task-switch
            # cost)
            duration = task_duration(x)
            if last_type[b, winner] >= 0 and last_type[b, winner] != ttype:
                duration += params.switch_ticks
            # spec step 5: executes during ticks t+1 .. t+duration, draining the battery; below the
            # threshold afterwards, it charges right after and is full again
            ready = now + duration
            level = battery[b, winner] - params.drain_per_tick * duration
            if level < params.battery_threshold:
                ready += params.charge_ticks
                level = params.battery_capacity
            busy_until[b, winner], battery[b, winner] = ready, level
            last_type[b, winner] = ttype
            # spec step 8: the task's assign reward, to the team and to its winner
            reward = params.reward_assign_high if high else params.reward_assign_low
            assign_reward[b, winner] += reward
            team += reward
            assigned[b, ttype, high] += 1
            queue[b, slot_pos[b, k]] = EMPTY
            slot_keys[b, k] = -1  # marks the slot as assigned for the loop below
        # spec step 6: an unassigned slot task goes to round 2, due t + delay; in round 2, dropped
        for k in range(K):
            x = slot_keys[b, k]
            if x == EMPTY or x == -1:
                continue
            if task_round(x) == 1:
                queue[b, slot_pos[b, k]] = to_second_round(x, now + params.reauction_delay)
            else:
                ttype, high = task_type(x), task_high(x)
                dropped[b, ttype, high] += 1
                penalty = drop_penalty(params, high)  # spec step 8
                type_penalty[b, ttype] += penalty
                team -= penalty
                queue[b, slot_pos[b, k]] = EMPTY
        # spec step 7: busy if not idle at step 4, or if it bid (the auction takes its time)
        for i in range(m):
            if not idle_before[b, i] or actions[b, i] > 0:
                busy_ticks[b, i] += 1
        team_reward[b] = team
        team_return[b] += team
        ticks[b] += 1
        t[b] = now + 1
        done[b] = t[b] >= params.horizon
        begin = 0 if done[b] else 1  # spec steps 1-3 of the next tick, unless at the horizon
        refresh_copy(b, begin, tables, state, views)


# ---------------------------------------------------------------------------- spec step 8
@njit(cache=True, nogil=True)
def penalty_shares(can_do):
    """``[n, m]``: robot ``i``'s share of a dropped type-``z`` task's penalty.

    Spec step 8: the penalty is shared equally by the robots whose ``Lambda_i`` holds ``z``
    (``can_do`` ``[n, m]``).
    """
    n, m = can_do.shape
    share = np.zeros((n, m))
    for z in range(n):
        count = 0
        for i in range(m):
            count += can_do[z, i]
        for i in range(m):
            if can_do[z, i]:
                share[z, i] = 1.0 / count
    return share


@njit(cache=True, nogil=True)
def robot_rewards(assign, type_penalty, share):
    """Spec step 8, ``[B, m]``: the assign reward a robot won minus its shares of drop penalties.

    ``assign`` and ``type_penalty`` are a tick's :class:`Rewards` fields, ``share`` is
    :func:`penalty_shares`'. A robot's share sums over the types in type order with fused
    multiply-adds (one rounding per type), the rounding of the BLAS matrix product the env used
    on FMA hardware, so the rewards keep their values, and the same on every machine.
    """
    B, m = assign.shape
    out = np.empty((B, m))
    for b in range(B):
        for i in range(m):
            penalty = 0.0
            for z in range(share.shape[0]):
                penalty = _fma(type_penalty[b, z], share[z, i], penalty)
            out[b, i] = assign[b, i] - penalty
    return out


@njit(cache=True, nogil=True)
def reset_copy(b, tables, state):
    """Start copy ``b``'s next episode (full batteries, idle robots, empty queue) and its tick 0.

    The slots are left to :func:`select_copy`.
    """
    state.episode_key[b] = episode_key(state.seed_key[b], state.episode[b])
    state.episode[b] += np.uint64(1)
    state.t[b], state.next_id[b], state.done[b] = 0, 0, False
    state.queue[b, :] = EMPTY
    state.queue_len[b] = 0
    state.busy_until[b, :] = -1
    state.battery[b, :] = tables.params.battery_capacity
    state.last_type[b, :] = -1
    state.last_high_arrival[b, :] = NEVER
    state.assigned[b], state.dropped[b], state.busy_ticks[b] = 0, 0, 0
    state.team_return[b], state.ticks[b] = 0.0, 0
    begin_copy(b, tables, state)


@njit(cache=True, nogil=True)
def refresh_copy(b, begin, tables, state, views):
    """Reset (``begin=2``), begin the tick (``begin=1``) or not (0) copy ``b``, then select."""
    if begin == 2:
        reset_copy(b, tables, state)
    elif begin == 1:
        begin_copy(b, tables, state)
    select_copy(b, tables, state, views)


# ---------------------------------------------------------------------------- batch entry points
@njit(cache=True, nogil=True)
def first_invalid(actions, done, mask):
    """``(0, 0)`` if every copy may step under ``actions``, else the first problem found.

    ``(1, b)``: copy ``b`` has finished its episode; ``(2, b * m + i)``: robot ``i``'s action in
    copy ``b`` is out of range or masked (spec step 4).
    """
    B, m = actions.shape
    n_actions = mask.shape[2]
    for b in range(B):
        if done[b]:
            return 1, b
    for b in range(B):
        for i in range(m):
            a = actions[b, i]
            if a < 0 or a >= n_actions or not mask[b, i, a]:
                return 2, b * m + i
    return 0, 0


@njit(cache=True, nogil=True)
def step(check, actions, buffers, before, views, rewards):
    """One tick of every copy (:func:`step_copies`), unless ``actions`` are invalid.

    ``before`` is ``(idle, mask)`` of the views the actions were decided on, ``views`` and
    ``rewards`` the tuples of :data:`VIEW_FIELDS` and :class:`Rewards` arrays to write. With
    ``check``, the actions are first checked (:func:`first_invalid`, one call instead of two)
    and a problem is returned before anything is written; without, the caller vouches for them.
    Returns :func:`first_invalid`'s ``(problem, where)``, ``(0, 0)`` once stepped.
    """
    tables, state = unpack(buffers)
    idle_before, mask_before = before
    if check:
        problem, where = first_invalid(actions, state.done, mask_before)
        if problem:
            return problem, where
    step_copies(
        0, actions.shape[0], actions, tables, state, idle_before, Views(*views), Rewards(*rewards)
    )
    return 0, 0


@njit(cache=True, nogil=True)
def refresh(rows, begin, buffers, views):
    """Reset (``begin=2``), begin the tick (``begin=1``) or only re-select (0) the ``rows``.

    Every copy's slots and mask are (re)written into ``views`` (fresh arrays, :data:`VIEW_FIELDS`).
    """
    tables, state = unpack(buffers)
    views = Views(*views)
    for b in range(rows.shape[0]):
        refresh_copy(b, begin if rows[b] else 0, tables, state, views)


@njit(cache=True, nogil=True)
def fixed_policy_copy(b, policy, episode_key, t, mask, slot_high, actions):
    """The spec's fixed policies for copy ``b`` at its tick ``t``, into ``actions[b]``.

    The rules are ``mrta_rl.rules``' (spec "Fixed policies") on the views ``mask`` and
    ``slot_high``; ``random`` draws the rank of its valid action (waiting or a bid) from
    counter-based hashes of the copy's ``episode_key``, tick and robot. (The fields come one by
    one: a record argument costs a reference count per array.)
    """
    mask = mask[b]
    if policy == 0:
        greedy(mask, actions[b])
    elif policy == 2:
        high_only(mask, slot_high[b], actions[b])
    else:  # random; only it draws (a hash per copy is a third of greedy's cost)
        key = mix64(tick_key(episode_key, np.uint64(t)) ^ _POLICY_SALT)
        for i in range(mask.shape[0]):
            count = np.uint64(count_valid(mask[i]))  # waiting is always valid (spec step 4)
            rank = bounded_uint(mix64(key + np.uint64(i + 1)), count)
            actions[b, i] = valid_action_of_rank(mask[i], np.int64(rank))


@njit(cache=True, nogil=True)
def fixed_actions(policy, buffers, views, actions):
    """:func:`fixed_policy_copy` of every copy, into ``actions`` ``[B, m]``.

    ``views`` is ``(mask, slot_high)``, the only views a fixed policy reads.
    """
    state = unpack(buffers)[1]
    episode_key, t = state.episode_key, state.t
    mask, slot_high = views
    for b in range(actions.shape[0]):
        fixed_policy_copy(b, policy, episode_key[b], t[b], mask, slot_high, actions)


@njit(cache=True, nogil=True)
def play_copy(b, plan, tables, state, views, scratch, out):
    """Copy ``b`` under fixed policy ``plan.policy`` (:data:`POLICIES`), many ticks in one call.

    A copy whose episode has ended is first reset. With ``plan.rounds > 0`` the copy plays until
    ``rounds`` episodes have ended, recording episode ``r``'s statistics in row ``r * B + b`` of
    ``out`` (:class:`Stats`) and resetting between episodes (the last one is left done). With
    ``rounds = 0`` it plays ``plan.max_ticks`` ticks, resetting finished episodes, and records
    nothing. ``scratch`` holds the actions and rewards of copy ``b``'s row. Returns the number of
    ticks played.
    """
    policy, max_ticks, rounds = plan
    actions, rewards = scratch
    done, B = state.done, state.t.shape[0]
    played, recorded = 0, 0
    while True:
        if done[b]:
            if played > 0 and recorded < rounds:  # (an episode ended before this call: not)
                row = recorded * B + b
                # element by element: a slice copy (out[row] = a[b]) makes numba compile its
                # shape-mismatch message (string formatting), about 7 s per empty-cache process
                for j in range(state.assigned.shape[1]):
                    for h in range(2):
                        out.assigned[row, j, h] = state.assigned[b, j, h]
                        out.dropped[row, j, h] = state.dropped[b, j, h]
                for i in range(state.busy_ticks.shape[1]):
                    out.busy_ticks[row, i] = state.busy_ticks[b, i]
                out.team_return[row], out.ticks[row] = state.team_return[b], state.ticks[b]
                recorded += 1
            if rounds > 0 and recorded == rounds:
                break
            # begin typed int64 (a literal 2 would compile refresh_copy again)
            refresh_copy(b, np.int64(2), tables, state, views)
        if played == max_ticks:
            break
        key, now = state.episode_key[b], state.t[b]
        fixed_policy_copy(b, policy, key, now, views.mask, views.slot_high, actions)
        step_copies(b, b + 1, actions, tables, state, views.idle, views, rewards)
        played += 1
    return played


@njit(cache=True, nogil=True)
def play(lo, hi, plan, buffers, views, out):
    """:func:`play_copy` of copies ``lo .. hi - 1`` in turn; returns the ticks they played.

    ``plan`` is a :class:`Plan` tuple, ``views`` and ``out`` the tuples of :data:`VIEW_FIELDS`
    and :data:`STATS` arrays. Calls on disjoint copy ranges may run in concurrent threads (the
    GIL is released).
    """
    plan, views, out = Plan(*plan), Views(*views), Stats(*out)
    B, m = views.idle.shape
    n = out.assigned.shape[1]
    rewards = Rewards(np.zeros(B), np.zeros((B, m)), np.zeros((B, n)))
    scratch = Scratch(np.zeros((B, m), np.int64), rewards)
    tables, state = unpack(buffers)
    played = 0
    for b in range(lo, hi):
        played += play_copy(b, plan, tables, state, views, scratch, out)
    return played
