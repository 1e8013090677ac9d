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

The arrays travel in named records, declared once below: :class:`Learner` (the Q-table
:class:`QTable`, the :class:`Groups` and the hyperparameters :class:`Settings`), a
:class:`Decision` (what the groups see at one state), the n-step :class:`Pending` decisions, one
tick's :class:`Outcome`, :class:`Exploration`, the :class:`Chosen` rows and entries and the
:class:`TD` errors. Python passes each as a plain tuple in its fields' order (as cheap to pass
as the arrays themselves; a namedtuple built in Python costs more), and the entry points
(:func:`act_groups`, :func:`entries_for_actions`, :func:`update_groups`, :func:`tick_groups`)
name them.
"""

from __future__ import annotations

from collections import namedtuple

import numpy as np
from numba import njit

from mrta_rl.envs.state_codes import EnvArrays, encode_groups
from mrta_rl.learners.tabular.joint_actions import enumerate_row
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
from mrta_rl.priors import PRIOR_CODES
from mrta_rl.rules import deconflict as deconflict_row
from mrta_rl.rules import greedy as lowest_bid_row
from mrta_rl.rules import spread as spread_row

GREEDY, SPREAD_WAIT = PRIOR_CODES["greedy"], PRIOR_CODES["spread_wait"]  # compile-time constants


QTable = namedtuple("QTable", ("hash", "rows", "entries", "q", "sizes"))  # JointQStorage's
# robots [G, n] and size [G] (padded), order [G, n] (the spread prior's), weight_by_type [n + 1, m]
Groups = namedtuple("Groups", ("robots", "size", "order", "weight_by_type"))
Settings = namedtuple(
    "Settings",
    (
        "decisions_only",  # a group learns only where one of its robots may bid
        "prior",  # PRIOR_CODES
        "prune",  # conflicting bids pruned (one joint action per outcome)
        "min_visits",  # entries updated fewer times do not compete (the prior's always does)
        "lcb",  # the greedy value's lower-confidence margin
        "prior_target",  # bootstrap from the prior's entry instead of the max
        "gamma",
        "alpha",  # alpha_of_visits(visits, alpha, alpha_power, alpha_min)
        "alpha_power",
        "alpha_min",
    ),
)
Learner = namedtuple("Learner", ("table", "groups", "settings"))  # QTable, Groups, Settings
# states, hold [G, B] (hold: recency level 0), mask [B, m, K + 1], slot_type, slot_high [B, K]
Decision = namedtuple("Decision", ("states", "hold", "mask", "slot_type", "slot_high"))
# per group and copy the last n decisions, oldest first (update_groups)
Pending = namedtuple("Pending", ("entry", "returns", "discounts", "count", "open", "value"))
Outcome = namedtuple("Outcome", ("rewards", "columns", "done"))  # one tick's, update_groups
Exploration = namedtuple("Exploration", ("epsilon", "uniforms"))  # uniforms consumed in order
Chosen = namedtuple("Chosen", ("rows", "entries"))  # [G, B], -1 where the group does not decide
TD = namedtuple("TD", ("sum", "count"))  # [G] summed absolute TD errors and updates


@njit(cache=True)
def learner_of(parts):
    """The :class:`Learner` record of a ``(table, groups, settings)`` tuple of plain tuples."""
    table, groups, settings = parts
    return Learner(QTable(*table), Groups(*groups), Settings(*settings))


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
def _add_row(learner, g, seen, b):
    """Create the row of group ``g``'s state in copy ``b`` of ``seen`` (a :class:`Decision`).

    The row holds the valid joint actions and the entry of the prior's one.
    """
    table, groups, settings = learner
    mask, slot_type, slot_high = seen.mask[b], seen.slot_type[b], seen.slot_high[b]
    robots, n, weight_by_type = groups.robots[g], groups.size[g], groups.weight_by_type
    prior, hold = settings.prior, seen.hold[g, b]
    entries, sizes = table.entries, table.sizes
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
    count = enumerate_row(group_mask, settings.prune, entries[ENTRY_CODE], start)
    chosen = np.zeros(n, np.int64)
    if prior == GREEDY:
        lowest_bid_row(prior_mask, chosen)
        if settings.prune:
            deconflict_row(chosen, weight)
    else:
        spread_row(prior_mask, groups.order[g, :n], chosen)
    code, place = 0, 1
    for r in range(n):
        code += chosen[r] * place
        place *= n_actions
    prior_entry = start
    for e in range(start, start + count):
        if entries[ENTRY_CODE, e] == code:
            prior_entry = e
            break
    state, rows, row = seen.states[g, b], table.rows, sizes[0]
    rows[ROW_STATE, row], rows[ROW_GROUP, row], rows[ROW_OFFSET, row] = state, g, start
    rows[ROW_LENGTH, row], rows[ROW_PRIOR, row] = count, prior_entry
    entries[ENTRY_VISITS, start : start + count] = 0
    table.q[start : start + count] = 0.0
    insert_row(table.hash, state, g, row)
    sizes[0] += 1
    sizes[1] += count


@njit(cache=True)
def rows_of(learner, g, seen, use, out):
    """Rows of group ``g`` in the copies ``use`` (bool ``[B]``) of ``seen``, made on a first visit.

    New states are created in increasing state order, each from the first copy showing it.
    ``out[b]`` is the row (-1 where not ``use``).
    """
    hash_table, states = learner.table.hash, seen.states[g]
    batch = states.size
    new_states = np.empty(batch, np.int64)
    new_copy = np.empty(batch, np.int64)
    n_new = 0
    for b in range(batch):
        out[b] = -1
        if not use[b]:
            continue
        out[b] = find_row(hash_table, states[b], g)
        if out[b] < 0:
            seen_before = False
            for j in range(n_new):
                seen_before = seen_before or new_states[j] == states[b]
            if not seen_before:
                new_states[n_new], new_copy[n_new] = states[b], b
                n_new += 1
    if n_new == 0:
        return
    for j in np.argsort(new_states[:n_new]):
        _add_row(learner, g, seen, new_copy[j])
    for b in range(batch):
        if use[b] and out[b] < 0:
            out[b] = find_row(hash_table, states[b], g)


@njit(cache=True)
def _decode_into(code: int, n_actions: int, robots: np.ndarray, n: int, out: np.ndarray) -> None:
    for r in range(n):
        out[robots[r]] = code % n_actions
        code //= n_actions


@njit(cache=True)
def _rows_of_deciding(learner, g, seen, use, out):
    """Group ``g``'s rows in ``seen`` where it decides (``out`` ``[B]``, -1 elsewhere).

    ``use`` ``[B]`` is scratch (written: where the group decides).
    """
    robots, n = learner.groups.robots[g], learner.groups.size[g]
    decisions_only = learner.settings.decisions_only
    for b in range(out.shape[0]):
        use[b] = decides(seen.mask[b], robots, n, decisions_only)
    rows_of(learner, g, seen, use, out)


# ---------------------------------------------------------------------------------- act
@njit(cache=True)
def _act(learner, seen, explore, chosen, actions):
    """Epsilon-greedy joint action of every group and copy (ties to the prior).

    Writes ``chosen`` (-1 where the group does not decide) and ``actions`` ``[B, m]``; returns
    the number of uniforms used.
    """
    table, groups, settings = learner
    rows, entries, q = table.rows, table.entries, table.q
    row_out, entry_out = chosen
    epsilon, uniforms = explore
    n_groups, batch = seen.states.shape
    n_actions = seen.mask.shape[2]
    use = np.empty(batch, np.bool_)
    for g in range(n_groups):  # rows first: creating them draws nothing
        _rows_of_deciding(learner, g, seen, use, row_out[g])
    actions[:] = 0
    used = 0
    explored = np.zeros(batch, np.bool_)
    for g in range(n_groups):
        for b in range(batch):
            row = row_out[g, b]
            entry_out[g, b] = (
                -1
                if row < 0
                else best_entry(rows, entries, q, row, settings.min_visits, settings.lcb)
            )
        if epsilon > 0.0:
            for b in range(batch):
                explored[b] = False
                if row_out[g, b] >= 0:
                    explored[b] = uniforms[used] < epsilon
                    used += 1
            for b in range(batch):
                if explored[b]:
                    entry_out[g, b] = random_entry(rows, row_out[g, b], uniforms[used])
                    used += 1
        for b in range(batch):
            if entry_out[g, b] >= 0:
                code = entries[ENTRY_CODE, entry_out[g, b]]
                _decode_into(code, n_actions, groups.robots[g], groups.size[g], actions[b])
    return used


@njit(cache=True)
def act_groups(learner, seen, explore, chosen, actions):
    """:func:`_act` on plain tuples.

    ``learner`` as :func:`learner_of` takes it, ``seen`` a :class:`Decision`, ``explore`` an
    :class:`Exploration`, ``chosen`` the :class:`Chosen` arrays to write.
    """
    return _act(
        learner_of(learner), Decision(*seen), Exploration(*explore), Chosen(*chosen), actions
    )


@njit(cache=True)
def entries_for_actions(learner, seen, actions, chosen):
    """Rows and entries of actions chosen elsewhere; returns the first copy not stored, or -1.

    With pruning, the actions are first mapped to their conflict-free equivalent (same winners).
    The arguments are plain tuples, as :func:`act_groups`'.
    """
    learner, seen, chosen = learner_of(learner), Decision(*seen), Chosen(*chosen)
    table, groups, settings = learner
    rows, entries = table.rows, table.entries
    row_out, entry_out = chosen
    slot_type, weight_by_type = seen.slot_type, groups.weight_by_type
    n_groups, batch = seen.states.shape
    n_actions = seen.mask.shape[2]
    use = np.empty(batch, np.bool_)
    for g in range(n_groups):
        _rows_of_deciding(learner, g, seen, use, row_out[g])
        n, robots = groups.size[g], groups.robots[g]
        taken = np.empty(n, np.int64)
        weight = np.empty((n, n_actions - 1))
        for b in range(batch):
            entry_out[g, b] = -1
            row = row_out[g, b]
            if row < 0:
                continue
            for r in range(n):
                taken[r] = actions[b, robots[r]]
                for k in range(n_actions - 1):
                    ttype = slot_type[b, k] if slot_type[b, k] >= 0 else weight_by_type.shape[0] - 1
                    weight[r, k] = weight_by_type[ttype, robots[r]]
            if settings.prune:
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
def _learn(entries, q, e, target, settings) -> float:
    """Eq. (3) on entry ``e`` towards ``target``; returns ``|TD error|``."""
    entries[ENTRY_VISITS, e] += 1
    td = target - q[e]
    visits = entries[ENTRY_VISITS, e]
    q[e] += alpha_of_visits(visits, settings.alpha, settings.alpha_power, settings.alpha_min) * td
    return abs(td)


@njit(cache=True)
def _update(learner, chosen, next_seen, outcome, pending, td):
    """Eq. (3) per group on decision points (semi-Markov, n-step), all copies, in copy order.

    ``chosen`` ``[G, B]`` holds the entries chosen at the last decision (-1: none), ``next_seen``
    the :class:`Decision` after the tick, ``outcome`` its :class:`Outcome`.

    Per group and copy, ``pending`` holds the last ``n`` decisions (``n`` = the last axis of its
    arrays), oldest first: ``entry [G, B, n]`` the chosen entries, ``returns`` / ``discounts``
    the interval after each (``R = sum_k gamma^k r_k`` over its ticks and ``gamma^tau``),
    ``count [G, B]`` how many are held, ``open`` whether the newest interval still runs,
    ``value`` the bootstrap of the last decision state met.

    A decision (``chosen[g, b] >= 0``) opens an interval; the tick's group reward is added to
    the open one (the group reward is the sum of the columns ``outcome.columns[g]`` of
    ``outcome.rewards`` ``[B, R]``, -1 padded, added left to right as numpy sums fewer than 9
    terms along a row of a batch). When the group decides at the next state, the open interval
    ends and, once ``n`` decisions are held, the oldest is updated and dropped:
    ``Q(s,a) += alpha_n [R_0 + gamma^tau_0 (R_1 + ... gamma^tau_n-1 V(s')) - Q(s,a)]`` with
    ``V(s') = max_a' Q(s', a')`` (with ``prior_target`` the prior's entry ``Q(s', prior(s'))``:
    the table then evaluates the prior, docs/learners.md "target"), every target taken from
    the table before the tick's updates. ``n = 1`` is the one-step semi-Markov eq. (3).
    At truncation (``outcome.done``: no next state) the open interval is dropped and the
    decisions before it are updated with the intervals they have, bootstrapped from the last
    decision state's value. ``td`` (:class:`TD`, ``[G]``) gets the summed absolute TD errors
    and the number of updates.
    """
    table, groups, settings = learner
    rows, entries, q = table.rows, table.entries, table.q
    robots, size = groups.robots, groups.size
    decisions_only, gamma = settings.decisions_only, settings.gamma
    rewards, reward_columns, done = outcome
    next_states, next_mask = next_seen.states, next_seen.mask
    pending_entry, pending_count, pending_open = pending.entry, pending.count, pending.open
    pending_value, td_sum, td_count = pending.value, td.sum, td.count
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
        rows_of(learner, g, next_seen, closing, next_rows)
    for g in range(n_groups):
        td_sum[g], td_count[g] = 0.0, 0
        returns, discounts = pending.returns[g], pending.discounts[g]
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
                next_rows[b] = find_row(table.hash, next_states[g, b], g)
                # eq. (3): r + gamma max_a' Q(s', a'), from the table before this tick's updates
                if settings.prior_target:  # the prior's value: its own Q, no max over noise
                    best = q[rows[ROW_PRIOR, next_rows[b]]]
                else:
                    best = max_q(rows, entries, q, next_rows[b], settings.min_visits, settings.lcb)
                pending_open[g, b] = False
                pending_value[g, b] = best
                if c + 1 == n_step:  # the oldest decision has its n intervals
                    closing[b] = True
                    targets[b] = n_step_target(returns[b], discounts[b], 0, c, best)
        for b in range(batch):
            if closing[b]:
                td_sum[g] += _learn(entries, q, pending_entry[g, b, 0], targets[b], settings)
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
                    td_sum[g] += _learn(entries, q, pending_entry[g, b, j], target, settings)
                    td_count[g] += 1
                pending_count[g, b] = 0
                pending_open[g, b] = False


@njit(cache=True)
def update_groups(learner, chosen, next_seen, outcome, pending, td):
    """:func:`_update` on plain tuples.

    ``learner`` as :func:`learner_of` takes it, ``next_seen`` a :class:`Decision`, ``outcome``
    an :class:`Outcome`, ``pending`` and ``td`` the :class:`Pending` and :class:`TD` arrays.
    """
    _update(
        learner_of(learner),
        chosen,
        Decision(*next_seen),
        Outcome(*outcome),
        Pending(*pending),
        TD(*td),
    )


# ---------------------------------------------------------------------------------- one tick
@njit(cache=True)
def tick_groups(learner, now, learn, outcome, pending, explore, tick, out):
    """One training tick in one call: encode the new state, eq. (3), act in it.

    ``now`` is ``(env_arrays, mask, tables, offset)``: the env's arrays and the encoder's
    ``tables`` that :func:`~mrta_rl.envs.state_codes.encode_groups` reads (``env_arrays(env)``
    and ``GroupEncoder.tables``), the action mask ``[B, m, K + 1]`` and ``offset`` ``[G, B]``
    (``GroupEncoder.offset``: the digits of the ``time_to_free`` features; 0 for the paper's).
    ``tick`` is ``(states, level, hold, rows, entries)`` ``[G, B]``: this tick's state codes
    (written) and the rows and entries chosen (in: the previous tick's, out: this tick's);
    ``out`` is ``(actions, td_sum, td_count)``.

    Exactly ``encode_groups`` (``states``, ``level``, and ``hold = level == 0``) plus ``offset``,
    then, if ``learn``, :func:`update_groups` with the entries chosen at the previous tick and
    this tick's :class:`Outcome`, then, unless a copy is done (the episode has ended),
    :func:`act_groups`: the calls of ``encode`` / ``update`` / ``act`` of the training loop, in
    the same order, with the same draws. Returns the number of uniforms used, or -1 without
    acting.
    """
    learner, outcome = learner_of(learner), Outcome(*outcome)
    env_arrays, mask, tables, offset = now
    states, level, hold, row_out, entry_out = tick
    actions, td_sum, td_count = out
    encode_groups(env_arrays, tables, states, level)
    for g in range(states.shape[0]):
        for b in range(states.shape[1]):
            states[g, b] += offset[g, b]
            hold[g, b] = level[g, b] == 0
    arrays = EnvArrays(*env_arrays)
    seen = Decision(states, hold, mask, arrays.slot_type, arrays.slot_high)
    if learn:
        _update(learner, entry_out, seen, outcome, Pending(*pending), TD(td_sum, td_count))
    if outcome.done.any():
        return -1
    return _act(learner, seen, Exploration(*explore), Chosen(row_out, entry_out), actions)
