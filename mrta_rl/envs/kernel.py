"""The tick of ``auction_env.md`` as compiled per-copy loops (numba): THE dynamics of the project.

:class:`~mrta_rl.envs.auction.AuctionEnv` owns the arrays and calls these functions; nothing else
implements a rule of the spec. Each function loops over copies and, per copy, over the spec's
steps in order, reading and writing the env's arrays in place. All are compiled once per process
(``cache=True``: the machine code is stored in ``__pycache__`` next to this file, so later
processes only load it) and release the GIL, so threads over shards of copies run concurrently.

A tick is split at the decision: :func:`begin_copy` runs spec steps 1-3 (arrivals, queue order
and overflow, slots) so that the caller sees the slots it decides on, :func:`step_copies` steps 4-8
and then steps 1-3 of the next tick. Overflow drops of step 2 are paid in the reward of that same
tick, returned by the following step.

Arguments keep one order everywhere (the env builds them once, see ``AuctionEnv``):

- ``fields`` (:data:`FIELDS`): the tables, then the state. The entry points (:func:`step`,
  :func:`refresh`, :func:`fixed_actions`, :func:`play`) take them as one flat buffer per dtype
  (:data:`BUFFER_DTYPES`) and a ``layout`` (:func:`unpack`): numba unboxes every array argument
  of a call from Python, the larger part of a call's cost at small batch sizes, so 4 buffers
  cost less than 27 arrays. The per-copy functions take the fields as separate arrays.
- ``tables``: ``iparams`` (int64, indices ``I_*``), ``fparams`` (float64, indices ``F_*``),
  ``cdf`` (Poisson CDF of the arrival count), ``dur_lo`` / ``dur_span`` (``[2n]`` by
  ``2 * type + high``), ``willingness`` (``[n, m]`` ``d_iz`` by type), ``can_do`` (``[n, m]``
  bool, ``Lambda_i`` by type).
- ``state``: :data:`STATE_FIELDS`, per-copy arrays ``[B, ...]``.
- ``views``: ``slot_type``, ``slot_high`` ``[B, K]`` (-1: empty), ``idle`` ``[B, m]``, ``mask``
  ``[B, m, K + 1]``: what a decision sees, written fresh by the env each tick.
"""

from __future__ import annotations

import numpy as np
from numba import njit

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

# integer parameters (iparams)
I_HORIZON, I_SLOTS, I_QUEUE_CAPACITY, I_REAUCTION_DELAY, I_CHARGE_TICKS, I_SWITCH_TICKS = range(6)
# float parameters (fparams); assign / drop amounts are indexed by F_* + high
F_P_HIGH, F_BATTERY_CAPACITY, F_DRAIN, F_THRESHOLD, F_ASSIGN, F_DROP = 0, 1, 2, 3, 4, 6
NEVER = -(1 << 30)  # last_high_arrival before any H arrival: far in the past

STATE_FIELDS = (
    "seed_key",  # [B] uint64, key of the copy's seed
    "episode",  # [B] uint64, episodes started so far (the next episode's number)
    "episode_key",  # [B] uint64, key of the current episode's draws
    "t",  # [B] current tick
    "queue",  # [B, W] packed tasks (envs/tasks.py), EMPTY after queue_len
    "queue_len",  # [B] places in use (may hold EMPTY holes until the next compaction)
    "next_id",  # [B] id of the next arriving task
    "busy_until",  # [B, m] robot i is idle at t when t > busy_until
    "battery",  # [B, m]
    "last_type",  # [B, m] type of the robot's previous task, -1: none yet (switch cost)
    "last_high_arrival",  # [B, n] tick of the last H arrival per type
    "done",  # [B] the episode has reached the horizon
    "pending_penalty",  # [B, n] drop penalties of this tick's overflow, paid by the next step
    "assigned",  # [B, n, 2] stats: tasks assigned per type and priority (0 = L, 1 = H)
    "dropped",  # [B, n, 2] stats: tasks dropped per type and priority
    "busy_ticks",  # [B, m] stats: busy ticks per robot (spec step 7)
    "team_return",  # [B] stats: sum of team rewards
    "ticks",  # [B] stats: ticks played
    "slot_pos",  # [B, K] queue place of each slot's task, -1: empty slot
    "slot_keys",  # [B, K] packed task of each slot, EMPTY: empty slot
)
TABLE_FIELDS = ("iparams", "fparams", "cdf", "dur_lo", "dur_span", "willingness", "can_do")
FIELDS = TABLE_FIELDS + STATE_FIELDS  # the order of unpack() and of every per-copy function
BUFFER_DTYPES = (np.uint64, np.int64, np.float64, np.bool_)  # a field lives in its dtype's buffer
_EPISODE_KEY, _T, _DONE = (FIELDS.index(f) for f in ("episode_key", "t", "done"))
POLICIES = {"greedy": 0, "random": 1, "high_only": 2}  # the spec's fixed policies
_POLICY_SALT = np.uint64(0x5851F42D4C957F2D)  # keys the random policy's draws apart from arrivals


# ---------------------------------------------------------------------------- spec steps 1-3
@njit(cache=True, nogil=True)
def begin_copy(
    b, iparams, fparams, cdf, dur_lo, dur_span, state_episode_key, t, queue, queue_len, next_id,
    last_high_arrival, pending_penalty, dropped,
):  # fmt: skip
    """Spec steps 1-2 of tick ``t[b]`` in copy ``b``: arrivals, queue order, overflow drops."""
    n = last_high_arrival.shape[1]
    now = t[b]
    pending_penalty[b, :] = 0.0
    # drop the holes left by the last step's slot tasks (assigned or dropped)
    length = 0
    for j in range(queue_len[b]):
        if queue[b, j] != EMPTY:
            queue[b, length] = queue[b, j]
            length += 1
    for j in range(length, queue_len[b]):
        queue[b, j] = EMPTY
    # spec step 1: N ~ Poisson(arrival_rate) new tasks, all counter-based hashes (counter_rng)
    key = tick_key(state_episode_key[b], np.uint64(now))
    count = np.searchsorted(cdf, unit_float(key), side="right")
    for k in range(count):
        h_priority, h_kind = task_hash_pair(key, np.uint64(k + 1))
        # H with probability p_high; type uniform over the n types (high 32 bits of h_kind),
        # duration uniform over its type and priority's range, ends included (low 32 bits)
        high = np.int64(unit_float(h_priority) < fparams[F_P_HIGH])
        ttype = np.int64(bounded_uint(high_bits(h_kind), np.uint64(n)))
        kind = 2 * ttype + high
        duration = dur_lo[kind] + np.int64(bounded_uint(h_kind, np.uint64(dur_span[kind])))
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
    capacity = iparams[I_QUEUE_CAPACITY]
    for j in range(capacity, length):
        x = queue[b, j]
        ttype, high = task_type(x), task_high(x)
        dropped[b, ttype, high] += 1
        pending_penalty[b, ttype] += fparams[F_DROP + high]
        queue[b, j] = EMPTY
    queue_len[b] = min(length, capacity)


@njit(cache=True, nogil=True)
def select_copy(
    b, t, queue, queue_len, busy_until, done, slot_pos, slot_keys, can_do, slot_type, slot_high,
    idle, mask,
):  # fmt: skip
    """Spec step 3 and the decision's inputs (step 4) of copy ``b``; idempotent."""
    K, m = slot_pos.shape[1], busy_until.shape[1]
    now = t[b]
    k = 0
    if not done[b]:  # a finished copy auctions nothing
        # the first K queued tasks due by now, in queue order (EMPTY is never due)
        for j in range(queue_len[b]):
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
    # the slot holds a task of one of its active types (Lambda_i); waiting is always valid
    for i in range(m):
        free = now > busy_until[b, i]
        idle[b, i] = free
        mask[b, i, 0] = True
        for kk in range(K):
            ttype = slot_type[b, kk]
            mask[b, i, kk + 1] = free and ttype >= 0 and can_do[ttype, i]


# ---------------------------------------------------------------------------- spec steps 4-8
@njit(cache=True, nogil=True)
def step_copies(
    lo, hi, actions, iparams, fparams, cdf, dur_lo, dur_span, willingness, can_do,
    seed_key, episode, state_episode_key, t, queue, queue_len, next_id, busy_until, battery,
    last_type, last_high_arrival, done, pending_penalty, assigned, dropped, busy_ticks,
    team_return, ticks, slot_pos, slot_keys,
    idle_before, slot_type, slot_high, idle, mask,
    team_reward, assign_reward, type_penalty,
):  # fmt: skip
    """Spec steps 4-8 of copies ``lo .. hi - 1`` under ``actions`` (valid), each then steps 1-3.

    Copy by copy, each one's next tick begins before the following copy is stepped.

    One call for many copies: numba increfs and decrefs every array argument at each call (atomic
    operations, a fifth of a small batch's tick when this was called once per copy).

    ``idle_before`` holds the idle flags the actions were decided on (spec step 7 reads them);
    the next tick's views are written into ``slot_type``, ``slot_high``, ``idle`` and ``mask``
    (the same arrays or fresh ones).

    Writes the tick's team reward ``team_reward[b]``, the assign reward each robot won
    ``assign_reward[b]`` and the drop penalties by type ``type_penalty[b]`` (spec step 8).
    """
    K, m, n = slot_pos.shape[1], busy_until.shape[1], last_high_arrival.shape[1]
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
        # lowest robot index
        for k in range(K):
            x = slot_keys[b, k]
            if x == EMPTY:
                continue
            ttype, high = task_type(x), task_high(x)
            winner, best = -1, -1.0
            for i in range(m):
                if actions[b, i] == k + 1 and willingness[ttype, i] > best:
                    winner, best = i, willingness[ttype, i]
            if winner < 0:
                continue
            # a task of another type than the robot's previous one first needs switch_ticks of
            # setup, busy and draining as execution does (docs/spec/auction_env.md, task-switch
            # cost)
            duration = task_duration(x)
            if last_type[b, winner] >= 0 and last_type[b, winner] != ttype:
                duration += iparams[I_SWITCH_TICKS]
            # spec step 5: executes during ticks t+1 .. t+duration, draining the battery; below the
            # threshold afterwards, it charges right after and is full again
            ready = now + duration
            level = battery[b, winner] - fparams[F_DRAIN] * duration
            if level < fparams[F_THRESHOLD]:
                ready += iparams[I_CHARGE_TICKS]
                level = fparams[F_BATTERY_CAPACITY]
            busy_until[b, winner], battery[b, winner] = ready, level
            last_type[b, winner] = ttype
            reward = fparams[F_ASSIGN + high]
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
                queue[b, slot_pos[b, k]] = to_second_round(x, now + iparams[I_REAUCTION_DELAY])
            else:
                ttype, high = task_type(x), task_high(x)
                dropped[b, ttype, high] += 1
                penalty = fparams[F_DROP + high]
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
        done[b] = t[b] >= iparams[I_HORIZON]
        begin = 0 if done[b] else 1  # spec steps 1-3 of the next tick, unless at the horizon
        refresh_copy(
            b, begin, iparams, fparams, cdf, dur_lo, dur_span, willingness, can_do,
            seed_key, episode, state_episode_key, t, queue, queue_len, next_id, busy_until, battery,
            last_type, last_high_arrival, done, pending_penalty, assigned, dropped, busy_ticks,
            team_return, ticks, slot_pos, slot_keys, slot_type, slot_high, idle, mask,
        )  # fmt: skip


@njit(cache=True, nogil=True)
def reset_copy(
    b, iparams, fparams, cdf, dur_lo, dur_span, seed_key, episode, state_episode_key, t, queue,
    queue_len, next_id, busy_until, battery, last_type, last_high_arrival, done, pending_penalty,
    assigned, dropped, busy_ticks, team_return, ticks,
):  # fmt: skip
    """Start copy ``b``'s next episode (full batteries, idle robots, empty queue) and its tick 0.

    The slots are left to :func:`select_copy`.
    """
    state_episode_key[b] = episode_key(seed_key[b], episode[b])
    episode[b] += np.uint64(1)
    t[b], next_id[b], done[b] = 0, 0, False
    queue[b, :] = EMPTY
    queue_len[b] = 0
    busy_until[b, :] = -1
    battery[b, :] = fparams[F_BATTERY_CAPACITY]
    last_type[b, :] = -1
    last_high_arrival[b, :] = NEVER
    assigned[b], dropped[b], busy_ticks[b] = 0, 0, 0
    team_return[b], ticks[b] = 0.0, 0
    begin_copy(
        b, iparams, fparams, cdf, dur_lo, dur_span, state_episode_key, t, queue, queue_len, next_id,
        last_high_arrival, pending_penalty, dropped,
    )  # fmt: skip


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
def unpack(layout, ubuf, ibuf, fbuf, bbuf):
    """The :data:`FIELDS` as views of the uint64, int64, float64 and bool buffers.

    Row ``f`` of ``layout`` (int64 ``[len(FIELDS), 4]``) holds field ``f``'s offset in its
    buffer and its shape (unused trailing dimensions 1); ``AuctionEnv`` writes it.
    """
    o, d = layout[:, 0], layout[:, 1:]
    return (
        ibuf[o[0] : o[0] + d[0].prod()],  # iparams
        fbuf[o[1] : o[1] + d[1].prod()],  # fparams
        fbuf[o[2] : o[2] + d[2].prod()],  # cdf
        ibuf[o[3] : o[3] + d[3].prod()],  # dur_lo
        ibuf[o[4] : o[4] + d[4].prod()],  # dur_span
        fbuf[o[5] : o[5] + d[5].prod()].reshape((d[5, 0], d[5, 1])),  # willingness
        bbuf[o[6] : o[6] + d[6].prod()].reshape((d[6, 0], d[6, 1])),  # can_do
        ubuf[o[7] : o[7] + d[7].prod()],  # seed_key
        ubuf[o[8] : o[8] + d[8].prod()],  # episode
        ubuf[o[9] : o[9] + d[9].prod()],  # episode_key
        ibuf[o[10] : o[10] + d[10].prod()],  # t
        ibuf[o[11] : o[11] + d[11].prod()].reshape((d[11, 0], d[11, 1])),  # queue
        ibuf[o[12] : o[12] + d[12].prod()],  # queue_len
        ibuf[o[13] : o[13] + d[13].prod()],  # next_id
        ibuf[o[14] : o[14] + d[14].prod()].reshape((d[14, 0], d[14, 1])),  # busy_until
        fbuf[o[15] : o[15] + d[15].prod()].reshape((d[15, 0], d[15, 1])),  # battery
        ibuf[o[16] : o[16] + d[16].prod()].reshape((d[16, 0], d[16, 1])),  # last_type
        ibuf[o[17] : o[17] + d[17].prod()].reshape((d[17, 0], d[17, 1])),  # last_high_arrival
        bbuf[o[18] : o[18] + d[18].prod()],  # done
        fbuf[o[19] : o[19] + d[19].prod()].reshape((d[19, 0], d[19, 1])),  # pending_penalty
        ibuf[o[20] : o[20] + d[20].prod()].reshape((d[20, 0], d[20, 1], d[20, 2])),  # assigned
        ibuf[o[21] : o[21] + d[21].prod()].reshape((d[21, 0], d[21, 1], d[21, 2])),  # dropped
        ibuf[o[22] : o[22] + d[22].prod()].reshape((d[22, 0], d[22, 1])),  # busy_ticks
        fbuf[o[23] : o[23] + d[23].prod()],  # team_return
        ibuf[o[24] : o[24] + d[24].prod()],  # ticks
        ibuf[o[25] : o[25] + d[25].prod()].reshape((d[25, 0], d[25, 1])),  # slot_pos
        ibuf[o[26] : o[26] + d[26].prod()].reshape((d[26, 0], d[26, 1])),  # slot_keys
    )  # fmt: skip


@njit(cache=True, nogil=True)
def step(
    check, actions, layout, ubuf, ibuf, fbuf, bbuf,
    idle_before, mask_before, slot_type, slot_high, idle, mask,
    team_reward, assign_reward, type_penalty,
):  # fmt: skip
    """One tick of every copy (:func:`step_copies`), unless ``actions`` are invalid.

    With ``check``, the actions are first checked (:func:`first_invalid`, one call instead of
    two) and a problem is returned before anything is written; without, the caller vouches
    for them. Returns :func:`first_invalid`'s ``(problem, where)``, ``(0, 0)`` once stepped.
    """
    fields = unpack(layout, ubuf, ibuf, fbuf, bbuf)
    if check:
        problem, where = first_invalid(actions, fields[_DONE], mask_before)
        if problem:
            return problem, where
    step_copies(
        0, actions.shape[0], actions, *fields, idle_before, slot_type, slot_high, idle, mask,
        team_reward, assign_reward, type_penalty,
    )  # fmt: skip
    return 0, 0


@njit(cache=True, nogil=True)
def refresh_copy(
    b, begin, iparams, fparams, cdf, dur_lo, dur_span, willingness, can_do,
    seed_key, episode, state_episode_key, t, queue, queue_len, next_id, busy_until, battery,
    last_type, last_high_arrival, done, pending_penalty, assigned, dropped, busy_ticks,
    team_return, ticks, slot_pos, slot_keys,
    slot_type, slot_high, idle, mask,
):  # fmt: skip
    """Reset (``begin=2``), begin the tick (``begin=1``) or not (0) copy ``b``, then select."""
    if begin == 2:
        reset_copy(
            b, iparams, fparams, cdf, dur_lo, dur_span, seed_key, episode, state_episode_key,
            t, queue, queue_len, next_id, busy_until, battery, last_type, last_high_arrival,
            done, pending_penalty, assigned, dropped, busy_ticks, team_return, ticks,
        )  # fmt: skip
    elif begin == 1:
        begin_copy(
            b, iparams, fparams, cdf, dur_lo, dur_span, state_episode_key, t, queue,
            queue_len, next_id, last_high_arrival, pending_penalty, dropped,
        )  # fmt: skip
    select_copy(
        b, t, queue, queue_len, busy_until, done, slot_pos, slot_keys, can_do, slot_type,
        slot_high, idle, mask,
    )  # fmt: skip


@njit(cache=True, nogil=True)
def refresh(
    rows, begin, layout, ubuf, ibuf, fbuf, bbuf, slot_type, slot_high, idle, mask
):  # fmt: skip
    """Reset (``begin=2``), begin the tick (``begin=1``) or only re-select (0) the ``rows``.

    Every copy's slots and mask are (re)written, as the views are fresh arrays.
    """
    fields = unpack(layout, ubuf, ibuf, fbuf, bbuf)
    for b in range(rows.shape[0]):
        refresh_copy(
            b, begin if rows[b] else 0, *fields, slot_type, slot_high, idle, mask
        )  # fmt: skip


@njit(cache=True, nogil=True)
def fixed_policy_copy(b, policy, actions, slot_high, mask, state_episode_key, t):
    """The spec's fixed policies for copy ``b``, into ``actions[b]``.

    ``greedy`` bids for the lowest-numbered valid slot, ``high_only`` for the lowest-numbered
    valid slot holding an H task; ``random`` picks uniformly among the valid bids and waiting,
    from counter-based hashes of the copy's episode key, tick and robot.
    """
    m, n_actions = mask.shape[1], mask.shape[2]
    key = np.uint64(0)
    if policy == 1:  # only random draws (a hash per copy is a third of greedy's cost)
        key = mix64(tick_key(state_episode_key[b], np.uint64(t[b])) ^ _POLICY_SALT)
    for i in range(m):
        choice = 0
        if policy == 1:  # random
            valid = 0
            for a in range(1, n_actions):
                valid += mask[b, i, a]
            pick = np.int64(bounded_uint(mix64(key + np.uint64(i + 1)), np.uint64(valid + 1)))
            for a in range(1, n_actions):
                if pick > 0 and mask[b, i, a]:
                    pick -= 1
                    if pick == 0:
                        choice = a
        else:
            for a in range(1, n_actions):
                if mask[b, i, a] and (policy == 0 or slot_high[b, a - 1] == 1):
                    choice = a
                    break
        actions[b, i] = choice


@njit(cache=True, nogil=True)
def fixed_actions(policy, layout, ubuf, ibuf, fbuf, bbuf, slot_high, mask, actions):
    """:func:`fixed_policy_copy` of every copy, into ``actions`` ``[B, m]``."""
    fields = unpack(layout, ubuf, ibuf, fbuf, bbuf)
    state_episode_key, t = fields[_EPISODE_KEY], fields[_T]
    for b in range(t.shape[0]):
        fixed_policy_copy(b, policy, actions, slot_high, mask, state_episode_key, t)


@njit(cache=True, nogil=True)
def play_copy(
    b, policy, max_ticks, rounds, iparams, fparams, cdf, dur_lo, dur_span, willingness, can_do,
    seed_key, episode, state_episode_key, t, queue, queue_len, next_id, busy_until, battery,
    last_type, last_high_arrival, done, pending_penalty, assigned, dropped, busy_ticks,
    team_return, ticks, slot_pos, slot_keys,
    slot_type, slot_high, idle, mask,
    actions, team_reward, assign_reward, type_penalty,
    out_assigned, out_dropped, out_busy_ticks, out_team_return, out_ticks,
):  # fmt: skip
    """Copy ``b`` under fixed policy ``policy`` (:data:`POLICIES`), many ticks in one call.

    A copy whose episode has ended is first reset. With ``rounds > 0`` the copy plays until
    ``rounds`` episodes have ended, recording episode ``r``'s statistics in row ``r * B + b`` of
    the ``out_*`` arrays and resetting between episodes (the last one is left done). With
    ``rounds = 0`` it plays ``max_ticks`` ticks, resetting finished episodes, and records
    nothing. Returns the number of ticks played.
    """
    B = t.shape[0]
    played, recorded = 0, 0
    while True:
        if done[b]:
            if played > 0 and recorded < rounds:  # (an episode ended before this call: not)
                row = recorded * B + b
                # element by element: a slice copy (out[row] = a[b]) makes numba compile its
                # shape-mismatch message (string formatting), about 7 s per empty-cache process
                for j in range(assigned.shape[1]):
                    for h in range(2):
                        out_assigned[row, j, h] = assigned[b, j, h]
                        out_dropped[row, j, h] = dropped[b, j, h]
                for i in range(busy_ticks.shape[1]):
                    out_busy_ticks[row, i] = busy_ticks[b, i]
                out_team_return[row], out_ticks[row] = team_return[b], ticks[b]
                recorded += 1
            if rounds > 0 and recorded == rounds:
                break
            refresh_copy(  # begin typed int64 (a literal 2 would compile refresh_copy again)
                b, np.int64(2), iparams, fparams, cdf, dur_lo, dur_span, willingness, can_do,
                seed_key, episode, state_episode_key, t, queue, queue_len, next_id, busy_until,
                battery, last_type, last_high_arrival, done, pending_penalty, assigned, dropped,
                busy_ticks, team_return, ticks, slot_pos, slot_keys, slot_type, slot_high, idle,
                mask,
            )  # fmt: skip
        if played == max_ticks:
            break
        fixed_policy_copy(b, policy, actions, slot_high, mask, state_episode_key, t)
        step_copies(
            b, b + 1, actions, iparams, fparams, cdf, dur_lo, dur_span, willingness, can_do,
            seed_key, episode, state_episode_key, t, queue, queue_len, next_id, busy_until,
            battery, last_type, last_high_arrival, done, pending_penalty, assigned, dropped,
            busy_ticks, team_return, ticks, slot_pos, slot_keys,
            idle, slot_type, slot_high, idle, mask,
            team_reward, assign_reward, type_penalty,
        )  # fmt: skip
        played += 1
    return played


@njit(cache=True, nogil=True)
def play(
    lo, hi, policy, max_ticks, rounds, layout, ubuf, ibuf, fbuf, bbuf,
    slot_type, slot_high, idle, mask,
    out_assigned, out_dropped, out_busy_ticks, out_team_return, out_ticks,
):  # fmt: skip
    """:func:`play_copy` of copies ``lo .. hi - 1`` in turn; returns the ticks they played.

    Calls on disjoint copy ranges may run in concurrent threads (the GIL is released).
    """
    B, m = idle.shape
    n = out_assigned.shape[1]
    actions = np.zeros((B, m), np.int64)  # scratch rows of play_copy
    team_reward, assign_reward, type_penalty = np.zeros(B), np.zeros((B, m)), np.zeros((B, n))
    fields = unpack(layout, ubuf, ibuf, fbuf, bbuf)
    played = 0
    for b in range(lo, hi):
        played += play_copy(
            b, policy, max_ticks, rounds, *fields, slot_type, slot_high, idle, mask,
            actions, team_reward, assign_reward, type_penalty,
            out_assigned, out_dropped, out_busy_ticks, out_team_return, out_ticks,
        )  # fmt: skip
    return played
