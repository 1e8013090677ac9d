"""Compiled per-copy loops of the per-robot learners (DQL, semi-CQL): act, eq. (3), one tick.

Robot ``i`` of copy ``b`` reads ``Q_i(s, a) = q[base[b, i] + a]``; the learner computes the
offsets ``base`` from its state encoding. Loops run over copies then robots (C order), so a
batch gives exactly the tables of the earlier vectorised code. Exploration uses uniforms drawn by
the caller, consumed in order: one per (copy, robot) (explore?), then one per exploring robot
(which valid action).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from mrta_rl.envs.state_codes import encode_groups, encode_local
from mrta_rl.learners.tabular.qtable import ROW_STATE, find_row, insert_row
from mrta_rl.learners.tabular.schedules import alpha_of_visits
from mrta_rl.rules import greedy as lowest_bid_row
from mrta_rl.rules import random_valid as random_valid_row


@njit(cache=True)
def _can_bid(mask: np.ndarray) -> bool:
    for k in range(1, mask.size):
        if mask[k]:
            return True
    return False


@njit(cache=True)
def _max_valid(q, visits, base, mask, tie, min_visits):  # fmt: skip
    """Max of Q over the valid actions that compete: the prior's and those visited enough."""
    best = -np.inf
    for a in range(mask.size):
        if mask[a] and (a == tie or visits[base + a] >= min_visits):
            best = max(best, q[base + a])
    return best


@njit(cache=True)
def act_robots(q, visits, bases, mask, prior, min_visits, epsilon, uniforms, actions):  # fmt: skip
    """Per robot: epsilon-greedy over its valid actions; ties go to the prior's (valid) action.

    ``prior`` ``[B, m]`` is the prior's action of every robot (the plain auction's bid, or the
    ``hold`` rule's). Only the prior's action and the actions updated at least ``min_visits``
    times compete (0: all). Writes ``actions`` ``[B, m]``; returns the number of uniforms used.
    """
    batch, n_robots, n_actions = mask.shape
    for b in range(batch):
        for i in range(n_robots):
            base = bases[b, i]
            tie = prior[b, i]
            best_action, best = 0, -np.inf
            for a in range(n_actions):
                if mask[b, i, a] and (a == tie or visits[base + a] >= min_visits):
                    if q[base + a] > best:
                        best, best_action = q[base + a], a
            # Q starts at 0: ties keep the prior's choice
            actions[b, i] = tie if q[base + tie] >= best else best_action
    used = 0
    if epsilon > 0.0:
        explore = np.zeros((batch, n_robots), np.bool_)
        for b in range(batch):
            for i in range(n_robots):
                explore[b, i] = uniforms[used] < epsilon and _can_bid(mask[b, i])
                used += 1
        for b in range(batch):
            for i in range(n_robots):
                if explore[b, i]:
                    actions[b, i] = random_valid_row(mask[b, i], uniforms[used])
                    used += 1
    return used


@njit(cache=True)
def open_transitions(
    bases, actions, mask, next_mask, rewards, done, pending_entry, pending_return,
    pending_discount, decisions_only, gamma, closing,
):  # fmt: skip
    """First half of eq. (3) per robot (semi-Markov): open, accumulate, drop, find the closing.

    A robot opens a transition where it decides (may bid, or always), adds its individual reward
    (``R += gamma^k r``), drops it at truncation (``done``: no next state) and closes it where it
    decides at the next state (``closing`` ``[B, m]``, written). Returns the number closing.
    """
    batch, n_robots = actions.shape
    count = 0
    for b in range(batch):
        for i in range(n_robots):
            if not decisions_only or _can_bid(mask[b, i]):
                pending_entry[b, i] = bases[b, i] + actions[b, i]
                pending_return[b, i] = 0.0
                pending_discount[b, i] = 1.0
            pending_return[b, i] += pending_discount[b, i] * rewards[b, i]
            pending_discount[b, i] *= gamma
            if done[b]:  # truncation: no next state to bootstrap from (spec: horizon)
                pending_entry[b, i] = -1
            decides = not decisions_only or _can_bid(next_mask[b, i])
            closing[b, i] = decides and pending_entry[b, i] >= 0
            count += closing[b, i]
    return count


@njit(cache=True)
def close_transitions(
    q, visits, next_bases, next_mask, next_prior, min_visits, prior_target, closing,
    pending_entry, pending_return, pending_discount, alpha, alpha_power, alpha_min,
):  # fmt: skip
    """Second half: ``Q_i(s,a) += alpha_n [R + gamma^tau max_a' Q_i(s',a') - Q_i(s,a)]``.

    The max runs over the next actions that compete (``act_robots``: the prior's, ``next_prior``
    ``[B, m]``, and those updated at least ``min_visits`` times); with ``prior_target`` the
    prior's own ``Q_i(s', prior_i(s'))`` replaces it (the table evaluates the prior). Every
    target is taken from the table before the tick's updates, then the updates are applied in
    (copy, robot) order. Returns the summed absolute TD error.
    """
    batch, n_robots = closing.shape
    targets = np.zeros((batch, n_robots))
    for b in range(batch):
        for i in range(n_robots):
            if closing[b, i]:
                # eq. (3): r + gamma max_a' Q_i(s', a') over the valid next actions
                if prior_target:  # the prior's value: its own Q, no max over noisy entries
                    best = q[next_bases[b, i] + next_prior[b, i]]
                else:
                    best = _max_valid(
                        q, visits, next_bases[b, i], next_mask[b, i], next_prior[b, i], min_visits
                    )
                targets[b, i] = pending_return[b, i] + pending_discount[b, i] * best
    td_sum = 0.0
    for b in range(batch):
        for i in range(n_robots):
            if closing[b, i]:
                e = pending_entry[b, i]
                visits[e] += 1
                td = targets[b, i] - q[e]
                q[e] += alpha_of_visits(visits[e], alpha, alpha_power, alpha_min) * td
                td_sum += abs(td)
                pending_entry[b, i] = -1
    return td_sum


@njit(cache=True)
def rows_of_states(table, rows, sizes, states, out):  # fmt: skip
    """Rows of whole-system states (semi-CQL), new ones appended in increasing state order.

    ``table``, ``rows`` and ``sizes`` are those of a one-group ``JointQStorage`` (its entries
    unused: a row's ``m x (K + 1)`` values live in the learner's own arrays).
    """
    batch = states.size
    new_states = np.empty(batch, np.int64)
    n_new = 0
    for b in range(batch):
        out[b] = find_row(table, states[b], 0)
        if out[b] < 0:
            seen = False
            for j in range(n_new):
                seen = seen or new_states[j] == states[b]
            if not seen:
                new_states[n_new] = states[b]
                n_new += 1
    if n_new == 0:
        return
    for state in np.sort(new_states[:n_new]):
        row = sizes[0]
        rows[ROW_STATE, row] = state
        insert_row(table, state, 0, row)
        sizes[0] += 1
    for b in range(batch):
        if out[b] < 0:
            out[b] = find_row(table, states[b], 0)


# ---------------------------------------------------------------------------------- offsets
@njit(cache=True)
def local_bases(states, robot_base, n_actions, out):  # fmt: skip
    """DQL's offsets: ``out[b, i] = (robot_base[i] + states[b, i]) * (K + 1)`` (dense tables)."""
    for b in range(states.shape[0]):
        for i in range(states.shape[1]):
            out[b, i] = (robot_base[i] + states[b, i]) * n_actions


@njit(cache=True)
def row_bases(rows, row_size, n_actions, out):  # fmt: skip
    """semi-CQL's offsets: ``out[b, i] = rows[b] * m (K + 1) + i (K + 1)``."""
    for b in range(out.shape[0]):
        for i in range(out.shape[1]):
            out[b, i] = rows[b] * row_size + i * n_actions


@njit(cache=True)
def add_prior_digit(states, prior, counts):  # fmt: skip
    """The prior's action as the most significant digit of each local state (in place)."""
    for b in range(states.shape[0]):
        for i in range(states.shape[1]):
            states[b, i] += prior[b, i] * counts[i]


# ---------------------------------------------------------------------------------- one tick
@njit(cache=True)
def _greedy_prior(mask, out):  # fmt: skip
    """The plain auction's bid of every robot (``priors.greedy_actions``), into ``out``."""
    for b in range(mask.shape[0]):
        lowest_bid_row(mask[b], out[b])


@njit(cache=True)
def _open_if(
    learn, bases, actions, mask, next_mask, rewards, done, pending_entry, pending_return,
    pending_discount, decisions_only, gamma, closing,
):  # fmt: skip
    """:func:`open_transitions` if ``learn`` (its count of closing transitions), else 0."""
    if not learn:
        return 0
    return open_transitions(
        bases, actions, mask, next_mask, rewards, done, pending_entry, pending_return,
        pending_discount, decisions_only, gamma, closing,
    )  # fmt: skip


@njit(cache=True)
def _close_and_act(
    q, visits, next_bases, next_mask, next_prior, count, closing, pending_entry, pending_return,
    pending_discount, alpha, alpha_power, alpha_min, act, min_visits, prior_target, epsilon,
    uniforms, next_actions,
):  # fmt: skip
    """The end of ``update`` (``count`` transitions closing) and ``act`` (-1 if not ``act``)."""
    if count:
        close_transitions(
            q, visits, next_bases, next_mask, next_prior, min_visits, prior_target, closing,
            pending_entry, pending_return, pending_discount, alpha, alpha_power, alpha_min,
        )  # fmt: skip
    if not act:
        return -1
    return act_robots(
        q, visits, next_bases, next_mask, next_prior, min_visits, epsilon, uniforms, next_actions
    )


@njit(cache=True)
def tick_local(
    slot_type, slot_high, idle, battery, t, last_high, busy_until, queue, queue_len, margin,
    threshold, codes, slot_places, places, active, thresholds, time_to_free, free_soon,
    queue_thresholds, greedy_prior, prior_digit, counts, robot_base, q, visits,
    bases, actions, mask, next_mask, next_prior, rewards, done, pending_entry, pending_return,
    pending_discount, learn, decisions_only, gamma, min_visits, prior_target, alpha, alpha_power,
    alpha_min, epsilon, uniforms, states, next_bases, closing, next_actions,
):  # fmt: skip
    """One DQL training tick: ``encode``, ``update`` (if ``learn``), ``act``.

    ``bases``, ``actions`` and ``mask`` are the previous decision's; ``next_prior`` is the
    prior's action in the new state (computed here, the plain auction's bid, if
    ``greedy_prior``; else given, the hold rule's), a digit of the state if ``prior_digit``.
    Writes ``states``, ``next_bases``, ``next_actions``; returns the number of uniforms used,
    or -1 without acting where a copy is ``done`` (the episode has ended).
    """
    act = not done.any()
    if greedy_prior:
        _greedy_prior(next_mask, next_prior)
    encode_local(
        slot_type, slot_high, idle, battery, t, last_high, busy_until, queue, queue_len, margin,
        threshold, codes, slot_places, places, active, thresholds, time_to_free, free_soon,
        queue_thresholds, states,
    )  # fmt: skip
    if prior_digit:
        add_prior_digit(states, next_prior, counts)
    local_bases(states, robot_base, next_mask.shape[2], next_bases)
    count = _open_if(
        learn, bases, actions, mask, next_mask, rewards, done, pending_entry, pending_return,
        pending_discount, decisions_only, gamma, closing,
    )  # fmt: skip
    return _close_and_act(
        q, visits, next_bases, next_mask, next_prior, count, closing, pending_entry,
        pending_return, pending_discount, alpha, alpha_power, alpha_min, act, min_visits,
        prior_target, epsilon, uniforms, next_actions,
    )  # fmt: skip


@njit(cache=True)
def tick_system(
    slot_type, slot_high, idle, battery, t, last_high, margin, threshold, codes, slot_places,
    robots, size, robot_places, recency_place, types, thresholds, offset, table, rows, sizes,
    row_size,
    q, visits, bases, actions, mask, next_mask, next_prior, rewards, done, pending_entry,
    pending_return, pending_discount, learn, decisions_only, gamma, min_visits, prior_target,
    alpha, alpha_power, alpha_min, epsilon, uniforms, states, level, next_rows, next_bases,
    closing, next_actions,
):  # fmt: skip
    """One semi-CQL training tick, as :func:`tick_local` with the plain auction's prior.

    The state is the whole system's (``encode_groups``, one group, plus ``offset`` ``[1, B]``,
    ``GroupEncoder.offset``: the ``time_to_free`` digits, 0 for the paper's); its row is looked
    up, and created on a first visit, only when ``update`` or ``act`` reads it (as the learner's
    calls do), so the rows are numbered as theirs.
    """
    _greedy_prior(next_mask, next_prior)
    encode_groups(
        slot_type, slot_high, idle, battery, t, last_high, margin, threshold, codes, slot_places,
        robots, size, robot_places, recency_place, types, thresholds, states, level,
    )  # fmt: skip
    for b in range(states.shape[1]):
        states[0, b] += offset[0, b]
    count = _open_if(
        learn, bases, actions, mask, next_mask, rewards, done, pending_entry, pending_return,
        pending_discount, decisions_only, gamma, closing,
    )  # fmt: skip
    act = not done.any()
    if act or count:
        rows_of_states(table, rows, sizes, states[0], next_rows)
        row_bases(next_rows, row_size, next_mask.shape[2], next_bases)
    return _close_and_act(
        q, visits, next_bases, next_mask, next_prior, count, closing, pending_entry,
        pending_return, pending_discount, alpha, alpha_power, alpha_min, act, min_visits,
        prior_target, epsilon, uniforms, next_actions,
    )  # fmt: skip
