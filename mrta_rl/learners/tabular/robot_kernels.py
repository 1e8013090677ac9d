"""Compiled per-copy loops of the per-robot learners (DQL, semi-CQL): act, eq. (3), one tick.

Robot ``i`` of copy ``b`` reads ``Q_i(s, a) = q[base[b, i] + a]``; the learner computes the
offsets ``base`` from its state encoding. Loops run over copies then robots (C order), so a
batch gives exactly the tables of the earlier vectorised code. Exploration uses uniforms drawn by
the caller, consumed in order: one per (copy, robot) (explore?), then one per exploring robot
(which valid action).

The arrays travel in named records, declared once below: the :class:`Values` ``Q_i`` and their
visit counts, the hyperparameters :class:`Settings`, a state's :class:`Decision` (offsets, mask,
the prior's actions), the last :class:`Step`, the open :class:`Pending` transitions, a tick's
:class:`Outcome` and :class:`Exploration`. Python passes each as a plain tuple in its fields'
order (as cheap to pass as the arrays themselves; a namedtuple built in Python costs more), and
every function that Python calls names them first (``Values(*values)``: the same record again
when compiled code passes one).
"""

from __future__ import annotations

from collections import namedtuple

import numpy as np
from numba import njit

from mrta_rl.envs.state_codes import encode_groups, encode_local
from mrta_rl.learners.tabular.qtable import ROW_STATE, find_row, insert_row
from mrta_rl.learners.tabular.schedules import alpha_of_visits
from mrta_rl.rules import greedy as lowest_bid_row
from mrta_rl.rules import random_valid as random_valid_row

Values = namedtuple("Values", ("q", "visits"))  # flat: Q_i(s, a) = q[base + a]
Settings = namedtuple(
    "Settings",
    (
        "decisions_only",  # a robot learns only where it may bid
        "gamma",
        "min_visits",  # actions updated fewer times do not compete (the prior's always does)
        "prior_target",  # bootstrap from the prior's action instead of the max
        "alpha",  # alpha_of_visits(visits, alpha, alpha_power, alpha_min)
        "alpha_power",
        "alpha_min",
    ),
)
# bases [B, m] (each robot's offset in q), mask [B, m, K + 1], prior [B, m] (its action)
Decision = namedtuple("Decision", ("bases", "mask", "prior"))
Step = namedtuple("Step", ("bases", "actions", "mask"))  # the last decision and what was done
Pending = namedtuple("Pending", ("entry", "returns", "discount"))  # [B, m] open transitions
Outcome = namedtuple("Outcome", ("rewards", "done"))  # [B, m] individual rewards, [B]
Exploration = namedtuple("Exploration", ("epsilon", "uniforms"))  # uniforms consumed in order


@njit(cache=True)
def _can_bid(mask: np.ndarray) -> bool:
    for k in range(1, mask.size):
        if mask[k]:
            return True
    return False


@njit(cache=True)
def _max_valid(q, visits, base, mask, tie, min_visits):
    """Max of Q over the valid actions that compete: the prior's and those visited enough."""
    best = -np.inf
    for a in range(mask.size):
        if mask[a] and (a == tie or visits[base + a] >= min_visits):
            best = max(best, q[base + a])
    return best


@njit(cache=True)
def act_robots(values, seen, min_visits, explore, actions):
    """Per robot: epsilon-greedy over its valid actions; ties go to the prior's (valid) action.

    ``seen`` is the state's :class:`Decision`: ``prior`` ``[B, m]`` is the prior's action of
    every robot (the plain auction's bid, or the ``hold`` rule's). Only the prior's action and
    the actions updated at least ``min_visits`` times compete (0: all). Writes ``actions``
    ``[B, m]``; returns the number of uniforms used (``explore``, :class:`Exploration`).
    """
    q, visits = Values(*values)
    seen, (epsilon, uniforms) = Decision(*seen), Exploration(*explore)
    bases, mask, prior = seen
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
        explored = np.zeros((batch, n_robots), np.bool_)
        for b in range(batch):
            for i in range(n_robots):
                explored[b, i] = uniforms[used] < epsilon and _can_bid(mask[b, i])
                used += 1
        for b in range(batch):
            for i in range(n_robots):
                if explored[b, i]:
                    actions[b, i] = random_valid_row(mask[b, i], uniforms[used])
                    used += 1
    return used


@njit(cache=True)
def open_transitions(last, next_mask, outcome, pending, settings, closing):
    """First half of eq. (3) per robot (semi-Markov): open, accumulate, drop, find the closing.

    After the :class:`Step` ``last``, a robot opens a transition where it decided (may bid, or
    always), adds its individual reward (``R += gamma^k r``, :class:`Outcome`), drops it at
    truncation (``done``: no next state) and closes it where it decides at the next state
    (``next_mask``; ``closing`` ``[B, m]``, written). ``pending`` and ``settings`` are
    :class:`Pending` and :class:`Settings`. Returns the number closing.
    """
    bases, actions, mask = Step(*last)
    rewards, done = Outcome(*outcome)
    pending_entry, pending_return, pending_discount = Pending(*pending)
    settings = Settings(*settings)
    decisions_only, gamma = settings.decisions_only, settings.gamma
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
def close_transitions(values, next_seen, settings, closing, pending):
    """Second half: ``Q_i(s,a) += alpha_n [R + gamma^tau max_a' Q_i(s',a') - Q_i(s,a)]``.

    The max runs over the next actions that compete (``act_robots``: the prior's, in the
    :class:`Decision` ``next_seen``, and those updated at least ``min_visits`` times); with
    ``prior_target`` the prior's own ``Q_i(s', prior_i(s'))`` replaces it (the table evaluates
    the prior). Every target is taken from the table before the tick's updates, then the
    updates are applied in (copy, robot) order. Returns the summed absolute TD error.
    """
    q, visits = Values(*values)
    next_bases, next_mask, next_prior = Decision(*next_seen)
    settings = Settings(*settings)
    pending_entry, pending_return, pending_discount = Pending(*pending)
    batch, n_robots = closing.shape
    targets = np.zeros((batch, n_robots))
    for b in range(batch):
        for i in range(n_robots):
            if closing[b, i]:
                # eq. (3): r + gamma max_a' Q_i(s', a') over the valid next actions
                if settings.prior_target:  # the prior's value: its own Q, no max over noise
                    best = q[next_bases[b, i] + next_prior[b, i]]
                else:
                    best = _max_valid(
                        q,
                        visits,
                        next_bases[b, i],
                        next_mask[b, i],
                        next_prior[b, i],
                        settings.min_visits,
                    )
                targets[b, i] = pending_return[b, i] + pending_discount[b, i] * best
    td_sum = 0.0
    alpha, alpha_power, alpha_min = settings.alpha, settings.alpha_power, settings.alpha_min
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
def rows_of_states(index, states, out):
    """Rows of whole-system states (semi-CQL), new ones appended in increasing state order.

    ``index`` is ``(hash, rows, sizes)`` of a one-group ``JointQStorage`` (its entries unused:
    a row's ``m x (K + 1)`` values live in the learner's own arrays).
    """
    table, rows, sizes = index
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
def local_bases(states, robot_base, n_actions, out):
    """DQL's offsets: ``out[b, i] = (robot_base[i] + states[b, i]) * (K + 1)`` (dense tables)."""
    for b in range(states.shape[0]):
        for i in range(states.shape[1]):
            out[b, i] = (robot_base[i] + states[b, i]) * n_actions


@njit(cache=True)
def row_bases(rows, row_size, n_actions, out):
    """semi-CQL's offsets: ``out[b, i] = rows[b] * m (K + 1) + i (K + 1)``."""
    for b in range(out.shape[0]):
        for i in range(out.shape[1]):
            out[b, i] = rows[b] * row_size + i * n_actions


@njit(cache=True)
def add_prior_digit(states, prior, counts):
    """The prior's action as the most significant digit of each local state (in place)."""
    for b in range(states.shape[0]):
        for i in range(states.shape[1]):
            states[b, i] += prior[b, i] * counts[i]


# ---------------------------------------------------------------------------------- one tick
@njit(cache=True)
def _greedy_prior(mask, out):
    """The plain auction's bid of every robot (``rules.greedy``), into ``out``."""
    for b in range(mask.shape[0]):
        lowest_bid_row(mask[b], out[b])


@njit(cache=True)
def _close_and_act(learner, next_seen, count, closing, act, explore, next_actions):
    """The end of ``update`` (``count`` transitions closing) and ``act`` (-1 if not ``act``).

    ``learner`` is ``(values, settings, pending)``.
    """
    values, settings, pending = learner
    if count:
        close_transitions(values, next_seen, settings, closing, pending)
    if not act:
        return -1
    return act_robots(values, next_seen, settings.min_visits, explore, next_actions)


@njit(cache=True)
def tick_local(learner, encoding, last, now, learn, outcome, explore, out):
    """One DQL training tick: ``encode``, ``update`` (if ``learn``), ``act``.

    ``learner`` is ``(values, settings, pending)`` (:class:`Values`, :class:`Settings`,
    :class:`Pending`); ``encoding`` is ``(arguments, robot_base, digit_place, greedy_prior,
    prior_digit)``: the arguments of :func:`~mrta_rl.envs.state_codes.encode_local` but its
    output (the env's arrays, its busy-until ticks and queue, the encoder's ``tables``), each
    robot's first state in ``q`` and the places of the prior's digit. ``last`` is the previous
    decision's :class:`Step`, ``now`` the new state's ``(mask, prior)``: the prior's action in
    the new state (computed here, the plain auction's bid, if ``greedy_prior``; else given,
    the hold rule's), a digit of the state if ``prior_digit``. ``out`` is ``(states,
    next_bases, closing, next_actions)``, written. Returns the number of uniforms used, or -1
    without acting where a copy is done (the episode has ended).
    """
    values, settings, pending = learner
    learner = (Values(*values), Settings(*settings), Pending(*pending))
    arguments, robot_base, digit_place, greedy_prior, prior_digit = encoding
    next_mask, next_prior = now
    states, next_bases, closing, next_actions = out
    outcome = Outcome(*outcome)
    act = not outcome.done.any()
    if greedy_prior:
        _greedy_prior(next_mask, next_prior)
    encode_local(*arguments, states)
    if prior_digit:
        add_prior_digit(states, next_prior, digit_place)
    local_bases(states, robot_base, next_mask.shape[2], next_bases)
    count = 0
    if learn:
        count = open_transitions(last, next_mask, outcome, learner[2], learner[1], closing)
    next_seen = Decision(next_bases, next_mask, next_prior)
    return _close_and_act(learner, next_seen, count, closing, act, explore, next_actions)


@njit(cache=True)
def tick_system(learner, encoding, last, now, learn, outcome, explore, out):
    """One semi-CQL training tick, as :func:`tick_local` with the plain auction's prior.

    ``encoding`` is ``(arguments, offset, index, row_size)``: the arguments of
    :func:`~mrta_rl.envs.state_codes.encode_groups` but its outputs (one group), ``offset``
    ``[1, B]`` (``GroupEncoder.offset``: the ``time_to_free`` digits, 0 for the paper's), the
    row index ``(hash, rows, sizes)`` (:func:`rows_of_states`) and a row's size ``m (K + 1)``.
    ``out`` is ``(states, level, next_rows, next_bases, closing, next_actions)`` with the
    whole-system state ``[1, B]``. Its row is looked up, and created on a first visit, only
    when ``update`` or ``act`` reads it (as the learner's calls do), so the rows are numbered
    as theirs.
    """
    values, settings, pending = learner
    learner = (Values(*values), Settings(*settings), Pending(*pending))
    arguments, offset, index, row_size = encoding
    next_mask, next_prior = now
    states, level, next_rows, next_bases, closing, next_actions = out
    outcome = Outcome(*outcome)
    _greedy_prior(next_mask, next_prior)
    encode_groups(*arguments, states, level)
    for b in range(states.shape[1]):
        states[0, b] += offset[0, b]
    count = 0
    if learn:
        count = open_transitions(last, next_mask, outcome, learner[2], learner[1], closing)
    act = not outcome.done.any()
    if act or count:
        rows_of_states(index, states[0], next_rows)
        row_bases(next_rows, row_size, next_mask.shape[2], next_bases)
    next_seen = Decision(next_bases, next_mask, next_prior)
    return _close_and_act(learner, next_seen, count, closing, act, explore, next_actions)
