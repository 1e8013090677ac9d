"""Compiled per-copy loops of the joint-action learners (subG-CQL, CQL): encode, act, eq. (3).

Every function loops over groups ``g`` and copies ``b`` in order, so a batch of ``B`` copies gives
exactly the tables of the earlier vectorised code (tested against it). Group data are padded
arrays: ``robots[g, :size[g]]`` are the group's robot indices in group order, ``order[g]`` the
order in which the spread priors ask them (positions within the group).

Learner conventions (docs/learners.md): a group decides at a copy when one of its robots may bid
(``decisions_only``), else always. Rows are created on a state's first visit, in increasing state
order within one call, with the masks of the first copy showing the state. Exploration uses
uniforms drawn by the caller, consumed in order: per group, one per deciding copy (explore?),
then one per exploring copy (which joint action).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from mrta_rl.envs.state_codes import encode_groups
from mrta_rl.learners.tabular.joint_actions import enumerate_row
from mrta_rl.learners.tabular.priors import PRIOR_CODES
from mrta_rl.learners.tabular.qtable import (
    ENTRY_CODE,
    ENTRY_VISITS,
    ROW_GROUP,
    ROW_LENGTH,
    ROW_OFFSET,
    ROW_PRIOR,
    ROW_STATE,
    best_entry,
    find_row,
    insert_row,
    max_q,
    random_entry,
)
from mrta_rl.learners.tabular.schedules import alpha_of_visits
from mrta_rl.rules import deconflict as deconflict_row
from mrta_rl.rules import greedy as lowest_bid_row
from mrta_rl.rules import spread as spread_row

GREEDY, SPREAD_WAIT = PRIOR_CODES["greedy"], PRIOR_CODES["spread_wait"]  # compile-time constants


# ---------------------------------------------------------------------------------- rows
@njit(cache=True)
def decides(mask: np.ndarray, robots: np.ndarray, n: int, decisions_only: bool) -> bool:
    """True where the group learns: one of its robots may bid (``mask`` ``[m, K + 1]``), or all."""
    if not decisions_only:
        return True
    for r in range(n):
        for k in range(1, mask.shape[1]):
            if mask[robots[r], k]:
                return True
    return False


@njit(cache=True)
def _add_row(
    table, rows, entries, q, sizes, g, state, mask, slot_type, slot_high, hold, robots, n,
    order, weight_by_type, prior, prune,
):  # fmt: skip
    """Create the row of a new state: its valid joint actions and its prior's entry."""
    n_actions = mask.shape[1]
    group_mask = np.empty((n, n_actions), np.bool_)
    prior_mask = np.empty((n, n_actions), np.bool_)
    weight = np.empty((n, n_actions - 1))
    for r in range(n):
        for a in range(n_actions):
            group_mask[r, a] = mask[robots[r], a]
            # spread_wait holds L slots while an H task of T_g arrived recently (level 0)
            held = prior == SPREAD_WAIT and hold and a > 0 and slot_high[a - 1] == 0
            prior_mask[r, a] = group_mask[r, a] and not held
        for k in range(n_actions - 1):
            ttype = slot_type[k] if slot_type[k] >= 0 else weight_by_type.shape[0] - 1
            weight[r, k] = weight_by_type[ttype, robots[r]]
    start = sizes[1]
    count = enumerate_row(group_mask, prune, entries[ENTRY_CODE], start)
    chosen = np.zeros(n, np.int64)
    if prior == GREEDY:
        lowest_bid_row(prior_mask, chosen)
        if prune:
            deconflict_row(chosen, weight)
    else:
        spread_row(prior_mask, order[:n], chosen)
    code, place = 0, 1
    for r in range(n):
        code += chosen[r] * place
        place *= n_actions
    prior_entry = start
    for e in range(start, start + count):
        if entries[ENTRY_CODE, e] == code:
            prior_entry = e
            break
    row = sizes[0]
    rows[ROW_STATE, row], rows[ROW_GROUP, row], rows[ROW_OFFSET, row] = state, g, start
    rows[ROW_LENGTH, row], rows[ROW_PRIOR, row] = count, prior_entry
    entries[ENTRY_VISITS, start : start + count] = 0
    q[start : start + count] = 0.0
    insert_row(table, state, g, row)
    sizes[0] += 1
    sizes[1] += count


@njit(cache=True)
def rows_of(
    table, rows, entries, q, sizes, g, states, use, mask, slot_type, slot_high, hold, robots, n,
    order, weight_by_type, prior, prune, out,
):  # fmt: skip
    """Rows of the copies ``use`` (bool ``[B]``) of group ``g``, created on a first visit.

    New states are created in increasing state order, each from the first copy showing it.
    ``out[b]`` is the row (-1 where not ``use``).
    """
    batch = states.size
    new_states = np.empty(batch, np.int64)
    new_copy = np.empty(batch, np.int64)
    n_new = 0
    for b in range(batch):
        out[b] = -1
        if not use[b]:
            continue
        out[b] = find_row(table, states[b], g)
        if out[b] < 0:
            seen = False
            for j in range(n_new):
                seen = seen or new_states[j] == states[b]
            if not seen:
                new_states[n_new], new_copy[n_new] = states[b], b
                n_new += 1
    if n_new == 0:
        return
    for j in np.argsort(new_states[:n_new]):
        b = new_copy[j]
        _add_row(
            table, rows, entries, q, sizes, g, states[b], mask[b], slot_type[b], slot_high[b],
            hold[b], robots, n, order, weight_by_type, prior, prune,
        )  # fmt: skip
    for b in range(batch):
        if use[b] and out[b] < 0:
            out[b] = find_row(table, states[b], g)


@njit(cache=True)
def _decode_into(code: int, n_actions: int, robots: np.ndarray, n: int, out: np.ndarray) -> None:
    for r in range(n):
        out[robots[r]] = code % n_actions
        code //= n_actions


# ---------------------------------------------------------------------------------- act
@njit(cache=True)
def act_groups(
    table, rows, entries, q, sizes, robots, size, order, weight_by_type, states, hold, mask,
    slot_type, slot_high, decisions_only, prior, prune, min_visits, lcb, epsilon, uniforms,
    row_out, entry_out, actions,
):  # fmt: skip
    """Epsilon-greedy joint action of every group and copy (ties to the prior).

    Writes ``row_out`` / ``entry_out`` ``[G, B]`` (-1 where the group does not decide) and
    ``actions`` ``[B, m]``; returns the number of uniforms used.
    """
    n_groups, batch = states.shape
    use = np.empty(batch, np.bool_)
    for g in range(n_groups):  # rows first: creating them draws nothing
        for b in range(batch):
            use[b] = decides(mask[b], robots[g], size[g], decisions_only)
        rows_of(
            table, rows, entries, q, sizes, g, states[g], use, mask, slot_type, slot_high,
            hold[g], robots[g], size[g], order[g], weight_by_type, prior, prune, row_out[g],
        )  # fmt: skip
    actions[:] = 0
    used = 0
    explore = np.zeros(batch, np.bool_)
    for g in range(n_groups):
        for b in range(batch):
            row = row_out[g, b]
            entry_out[g, b] = -1 if row < 0 else best_entry(rows, entries, q, row, min_visits, lcb)
        if epsilon > 0.0:
            for b in range(batch):
                explore[b] = False
                if row_out[g, b] >= 0:
                    explore[b] = uniforms[used] < epsilon
                    used += 1
            for b in range(batch):
                if explore[b]:
                    entry_out[g, b] = random_entry(rows, row_out[g, b], uniforms[used])
                    used += 1
        for b in range(batch):
            if entry_out[g, b] >= 0:
                code = entries[ENTRY_CODE, entry_out[g, b]]
                _decode_into(code, mask.shape[2], robots[g], size[g], actions[b])
    return used


@njit(cache=True)
def entries_for_actions(
    table, rows, entries, q, sizes, robots, size, order, weight_by_type, states, hold, mask,
    slot_type, slot_high, decisions_only, prior, prune, actions, row_out, entry_out,
):  # fmt: skip
    """Rows and entries of actions chosen elsewhere; returns the first copy not stored, or -1.

    With pruning, the actions are first mapped to their conflict-free equivalent (same winners).
    """
    n_groups, batch = states.shape
    n_actions = mask.shape[2]
    use = np.empty(batch, np.bool_)
    for g in range(n_groups):
        n = size[g]
        for b in range(batch):
            use[b] = decides(mask[b], robots[g], n, decisions_only)
        rows_of(
            table, rows, entries, q, sizes, g, states[g], use, mask, slot_type, slot_high,
            hold[g], robots[g], n, order[g], weight_by_type, prior, prune, row_out[g],
        )  # fmt: skip
        taken = np.empty(n, np.int64)
        weight = np.empty((n, n_actions - 1))
        for b in range(batch):
            entry_out[g, b] = -1
            row = row_out[g, b]
            if row < 0:
                continue
            for r in range(n):
                taken[r] = actions[b, robots[g, r]]
                for k in range(n_actions - 1):
                    ttype = slot_type[b, k] if slot_type[b, k] >= 0 else weight_by_type.shape[0] - 1
                    weight[r, k] = weight_by_type[ttype, robots[g, r]]
            if prune:
                deconflict_row(taken, weight)  # same outcome as the bids taken (spec step 5)
            code, place = 0, 1
            for r in range(n):
                code += taken[r] * place
                place *= n_actions
            start = rows[ROW_OFFSET, row]
            for e in range(start, start + rows[ROW_LENGTH, row]):
                if entries[ENTRY_CODE, e] == code:
                    entry_out[g, b] = e
                    break
            if entry_out[g, b] < 0:
                return b
    return -1


# ---------------------------------------------------------------------------------- eq. (3)
@njit(cache=True)
def n_step_target(returns: np.ndarray, discounts: np.ndarray, first: int, last: int, value: float):
    """``R_first + D_first (R_first+1 + ... + D_last-1 (R_last + D_last value))``.

    The n-step semi-Markov target of the decision ``first`` (docs/learners.md, ``n_step``):
    ``R_j`` the discounted reward sum of the interval after decision ``j``, ``D_j`` its
    ``gamma^tau``, ``value`` the bootstrap of the decision state after interval ``last``. Folded
    from the newest interval, so that one interval is exactly ``R + gamma^tau value``.
    """
    for j in range(last, first - 1, -1):
        value = returns[j] + discounts[j] * value
    return value


@njit(cache=True)
def _learn(entries, q, e, target, alpha, alpha_power, alpha_min) -> float:
    """Eq. (3) on entry ``e`` towards ``target``; returns ``|TD error|``."""
    entries[ENTRY_VISITS, e] += 1
    td = target - q[e]
    q[e] += alpha_of_visits(entries[ENTRY_VISITS, e], alpha, alpha_power, alpha_min) * td
    return abs(td)


@njit(cache=True)
def update_groups(
    table, rows, entries, q, sizes, robots, size, order, weight_by_type, chosen, next_states,
    next_hold, next_mask, next_slot_type, next_slot_high, rewards, reward_columns, done,
    pending_entry, pending_return, pending_discount, pending_count, pending_open, pending_value,
    decisions_only, prior, prune, min_visits, lcb, prior_target, gamma, alpha, alpha_power,
    alpha_min, td_sum, td_count,
):  # fmt: skip
    """Eq. (3) per group on decision points (semi-Markov, n-step), all copies, in copy order.

    Per group and copy, ``pending_*`` hold the last ``n`` decisions (``n`` = their last axis),
    oldest first: ``pending_entry [G, B, n]`` the chosen entries, ``pending_return`` /
    ``pending_discount`` the interval after each (``R = sum_k gamma^k r_k`` over its ticks and
    ``gamma^tau``), ``pending_count [G, B]`` how many are held, ``pending_open`` whether the
    newest interval still runs, ``pending_value`` the bootstrap of the last decision state met.

    A decision (``chosen[g, b] >= 0``) opens an interval; the tick's group reward is added to
    the open one (the group reward is the sum of the columns ``reward_columns[g]`` of
    ``rewards`` ``[B, R]``, -1 padded, added left to right as numpy sums fewer than 9 terms
    along a row of a batch). When the group decides at the next state, the open interval ends
    and, once ``n`` decisions are held, the oldest is updated and dropped:
    ``Q(s,a) += alpha_n [R_0 + gamma^tau_0 (R_1 + ... gamma^tau_n-1 V(s')) - Q(s,a)]`` with
    ``V(s') = max_a' Q(s', a')`` (with ``prior_target`` the prior's entry ``Q(s', prior(s'))``:
    the table then evaluates the prior, docs/learners.md "target"), every target taken from
    the table before the tick's updates. ``n = 1`` is the one-step semi-Markov eq. (3).
    At truncation (``done``: no next state) the open interval is dropped and the decisions
    before it are updated with the intervals they have, bootstrapped from the last decision
    state's value. ``td_sum`` / ``td_count`` ``[G]`` get the summed absolute TD errors and the
    number of updates.
    """
    n_groups, batch = chosen.shape
    n_step = pending_entry.shape[2]
    closing = np.empty(batch, np.bool_)
    next_rows = np.empty(batch, np.int64)
    targets = np.empty(batch)
    for g in range(n_groups):  # next rows first (creating them draws and updates nothing)
        for b in range(batch):
            opened = chosen[g, b] >= 0 or pending_open[g, b]
            closing[b] = (
                opened and not done[b] and decides(next_mask[b], robots[g], size[g], decisions_only)
            )
        rows_of(
            table, rows, entries, q, sizes, g, next_states[g], closing, next_mask,
            next_slot_type, next_slot_high, next_hold[g], robots[g], size[g], order[g],
            weight_by_type, prior, prune, next_rows,
        )  # fmt: skip
    for g in range(n_groups):
        td_sum[g], td_count[g] = 0.0, 0
        returns, discounts = pending_return[g], pending_discount[g]
        for b in range(batch):
            if chosen[g, b] >= 0:  # a decision opens an interval
                if pending_open[g, b]:  # the last one never met its next state: chain broken
                    pending_count[g, b] = 0
                c = pending_count[g, b]
                pending_entry[g, b, c] = chosen[g, b]
                returns[b, c] = 0.0
                discounts[b, c] = 1.0
                pending_count[g, b] = c + 1
                pending_open[g, b] = True
            closing[b] = False
            if not pending_open[g, b]:
                continue
            c = pending_count[g, b] - 1
            reward = rewards[b, reward_columns[g, 0]]
            for k in range(1, reward_columns.shape[1]):
                if reward_columns[g, k] >= 0:
                    reward += rewards[b, reward_columns[g, k]]
            returns[b, c] += discounts[b, c] * reward
            discounts[b, c] *= gamma
            if done[b]:  # truncation: no next state; the decisions before are flushed below
                continue
            if decides(next_mask[b], robots[g], size[g], decisions_only):
                next_rows[b] = find_row(table, next_states[g, b], g)
                # eq. (3): r + gamma max_a' Q(s', a'), from the table before this tick's updates
                if prior_target:  # the prior's value: its own Q, no max over noisy entries
                    best = q[rows[ROW_PRIOR, next_rows[b]]]
                else:
                    best = max_q(rows, entries, q, next_rows[b], min_visits, lcb)
                pending_open[g, b] = False
                pending_value[g, b] = best
                if c + 1 == n_step:  # the oldest decision has its n intervals
                    closing[b] = True
                    targets[b] = n_step_target(returns[b], discounts[b], 0, c, best)
        for b in range(batch):
            if closing[b]:
                td_sum[g] += _learn(
                    entries, q, pending_entry[g, b, 0], targets[b], alpha, alpha_power, alpha_min
                )
                td_count[g] += 1
                for j in range(n_step - 1):  # drop the oldest
                    pending_entry[g, b, j] = pending_entry[g, b, j + 1]
                    returns[b, j] = returns[b, j + 1]
                    discounts[b, j] = discounts[b, j + 1]
                pending_count[g, b] -= 1
            elif done[b]:
                # truncation: the open interval has no next state and is dropped; each decision
                # before it bootstraps from the last decision state met (fewer than n intervals)
                last = pending_count[g, b] - (2 if pending_open[g, b] else 1)
                for j in range(last + 1):
                    target = n_step_target(returns[b], discounts[b], j, last, pending_value[g, b])
                    td_sum[g] += _learn(
                        entries, q, pending_entry[g, b, j], target, alpha, alpha_power, alpha_min
                    )
                    td_count[g] += 1
                pending_count[g, b] = 0
                pending_open[g, b] = False


# ---------------------------------------------------------------------------------- one tick
@njit(cache=True)
def tick_groups(
    table, rows, entries, q, sizes, order, weight_by_type, slot_type, slot_high, idle, battery,
    t, last_high, margin, threshold, codes, slot_places, robots, size, robot_places,
    recency_place, types, thresholds, offset, mask, learn, rewards, reward_columns, done,
    pending_entry, pending_return, pending_discount, pending_count, pending_open, pending_value,
    epsilon, uniforms, decisions_only, prior, prune, min_visits, lcb, prior_target, gamma, alpha,
    alpha_power, alpha_min, states, level, hold, row_out, entry_out, actions, td_sum, td_count,
):  # fmt: skip
    """One training tick in one call: encode the new state, eq. (3), act in it.

    Exactly :func:`~mrta_rl.envs.state_codes.encode_groups` (``states``, ``level``,
    and ``hold = level == 0``) plus ``offset`` ``[G, B]`` (``GroupEncoder.offset``: the digits
    of the ``time_to_free`` features; 0 for the paper's), then, if ``learn``,
    :func:`update_groups` with the entries ``entry_out`` chosen at the previous tick and this
    tick's rewards, then, unless a copy is ``done`` (the episode has ended), :func:`act_groups`
    (``row_out``, ``entry_out``, ``actions``): the calls of ``encode`` / ``update`` / ``act``
    of the training loop, in the same order, with the same draws. Returns the number of
    uniforms used, or -1 without acting.
    """
    encode_groups(
        slot_type, slot_high, idle, battery, t, last_high, margin, threshold, codes, slot_places,
        robots, size, robot_places, recency_place, types, thresholds, states, level,
    )  # fmt: skip
    for g in range(states.shape[0]):
        for b in range(states.shape[1]):
            states[g, b] += offset[g, b]
            hold[g, b] = level[g, b] == 0
    if learn:
        update_groups(
            table, rows, entries, q, sizes, robots, size, order, weight_by_type, entry_out,
            states, hold, mask, slot_type, slot_high, rewards, reward_columns, done,
            pending_entry, pending_return, pending_discount, pending_count, pending_open,
            pending_value, decisions_only, prior, prune, min_visits, lcb, prior_target, gamma,
            alpha, alpha_power, alpha_min, td_sum, td_count,
        )  # fmt: skip
    if done.any():
        return -1
    return act_groups(
        table, rows, entries, q, sizes, robots, size, order, weight_by_type, states, hold, mask,
        slot_type, slot_high, decisions_only, prior, prune, min_visits, lcb, epsilon, uniforms,
        row_out, entry_out, actions,
    )  # fmt: skip
