"""Compiled per-copy loops of the per-robot learners (DQL, semi-CQL): act and eq. (3).

Robot ``i`` of copy ``b`` reads ``Q_i(s, a) = q[base[b, i] + a]``; the learner computes the
offsets ``base`` from its state encoding. Loops run over copies then robots (C order), so a
batch gives exactly the tables of the earlier vectorised code. Exploration uses uniforms drawn by
the caller, consumed in order: one per (copy, robot) (explore?), then one per exploring robot
(which valid action).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from mrta_rl.learners.tabular.priors import random_valid_row
from mrta_rl.learners.tabular.qtable import ROW_STATE, find_row, insert_row
from mrta_rl.learners.tabular.schedules import alpha_of_visits


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
    q, visits, next_bases, next_mask, next_prior, min_visits, closing, pending_entry,
    pending_return, pending_discount, alpha, alpha_power, alpha_min,
):  # fmt: skip
    """Second half: ``Q_i(s,a) += alpha_n [R + gamma^tau max_a' Q_i(s',a') - Q_i(s,a)]``.

    The max runs over the next actions that compete (``act_robots``: the prior's, ``next_prior``
    ``[B, m]``, and those updated at least ``min_visits`` times). Every target is taken from the
    table before the tick's updates, then the updates are applied in (copy, robot) order. Returns
    the summed absolute TD error.
    """
    batch, n_robots = closing.shape
    targets = np.zeros((batch, n_robots))
    for b in range(batch):
        for i in range(n_robots):
            if closing[b, i]:
                # eq. (3): r + gamma max_a' Q_i(s', a') over the valid next actions
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
