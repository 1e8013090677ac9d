"""Compiled state encodings of the tabular learners, code for code those of ``envs/encodings``.

:class:`GroupEncoder` computes ``encodings.group_state_index`` of several groups at once and
:class:`LocalEncoder` ``encodings.local_state_index``, in per-copy loops, from the same env
arrays (slots, idle flags, battery levels, H arrivals) and with the tables (slot codes, place
values) of ``encodings.GroupView`` / ``encodings.LocalView``, so the codes are the same
(tested). The battery rule (:func:`battery_low`) reads ``encodings.battery_margin``, the
recency rule (:func:`recency`) ``encodings.RECENCY_THRESHOLDS``.

A new digit of an encoding plugs in as one more place value: ``encodings`` adds it to the
view's radices (and its count), computes the digit for all copies, and the encoder adds
``digit * place`` in its loop (one more input array).

The group encoder takes the view's ``features`` (``encodings.FEATURES``): with
``time_to_free``, :meth:`GroupEncoder.offset` computes the extra digits (a busy robot free
within ``FREE_SOON`` ticks reads robot state 3; queued H and L levels over ``T_g``) in its
own compiled loop (:func:`group_offsets`) and adds them as ``[G, B]`` offsets to the paper-era
codes of :func:`encode_groups`, so the paper loop is unchanged (the fused ticks of subG-CQL,
CQL and semi-CQL add the same offset). The local encoder computes its ``time_to_free`` digits
in its compiled loop (:func:`encode_local`: the free level from ``busy_until``, the queued H and
L counts over ``Lambda_i`` from the queue), a flag of its tables, so DQL's fused tick needs no
offset.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numba import njit

from mrta_rl.config import ConfigError
from mrta_rl.envs import AuctionEnv
from mrta_rl.envs.encodings import (
    FREE_SOON,
    N_QUEUE_LEVELS,
    N_RECENCY_LEVELS,
    QUEUE_THRESHOLDS,
    RECENCY_THRESHOLDS,
    GroupView,
    LocalView,
    battery_margin,
)
from mrta_rl.envs.tasks import EMPTY, task_high, task_type

_THRESHOLDS = np.array(RECENCY_THRESHOLDS, np.int64)
_QUEUE_THRESHOLDS = np.array([QUEUE_THRESHOLDS["H"], QUEUE_THRESHOLDS["L"]], np.int64)  # [H, L]


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
def _slot_code(codes: np.ndarray, ttype: int, high: int) -> int:
    """Code of a slot; an empty slot (type -1) reads the table's last row."""
    return codes[ttype if ttype >= 0 else codes.shape[0] - 1, max(high, 0)]


@njit(cache=True)
def encode_groups(
    slot_type, slot_high, idle, battery, t, last_high, margin, threshold, codes, slot_places,
    robots, size, robot_places, recency_place, types, thresholds, states, level,
):  # fmt: skip
    """``GroupView`` state indices ``states`` and recency levels ``level`` ``[G, B]`` (written).

    The leading six arguments are :func:`env_arrays`, the next ten a ``GroupEncoder``'s
    :attr:`~GroupEncoder.tables`.
    """
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
def _level(count: int, thresholds: np.ndarray) -> int:
    """Queue level of a count (``encodings.queue_level``): 0, 1 or 2 over two thresholds."""
    return int(count > thresholds[0]) + int(count > thresholds[1])


@njit(cache=True)
def _queued(queue: np.ndarray, length: int, counts: np.ndarray) -> None:
    """Queued tasks of one copy per type and priority (``encodings.queue_counts``), written."""
    counts[:] = 0
    for w in range(length):  # places past the length are EMPTY (envs/kernel.py)
        if queue[w] != EMPTY:
            counts[task_type(queue[w]), task_high(queue[w])] += 1


@njit(cache=True)
def _free_level(busy_until: int, t: int, free_soon: int) -> int:
    """Free level (``encodings.free_level``): 0 idle, 1 free within ``free_soon``, 2 later."""
    ticks = busy_until - t + 1  # idle again at busy_until + 1; <= 0 when idle
    return int(ticks > 0) + int(ticks > free_soon)


@njit(cache=True)
def _queue_digits(counts, types, thresholds, high_place: int, low_place: int) -> int:
    """The queued H and L levels over the types ``types`` ``[n]``, times their places."""
    high = low = 0
    for j in range(types.shape[0]):
        if types[j]:
            high += counts[j, 1]
            low += counts[j, 0]
    return _level(high, thresholds[0]) * high_place + _level(low, thresholds[1]) * low_place


@njit(cache=True)
def group_offsets(
    busy_until, t, queue, queue_len, robots, size, soon_places, types, queue_places, free_soon,
    queue_thresholds, out,
):  # fmt: skip
    """``[G, B]`` what ``time_to_free`` adds to the paper codes of :func:`encode_groups` (written).

    A busy robot free within ``free_soon`` ticks reads robot state 3 (the busy state 0 plus
    ``3 x`` its place), and the queued H and L levels over ``T_g`` follow the recency digit
    (``encodings.GroupView``, "Features"). The first four arguments are
    :meth:`LocalEncoder.state_arrays`'s and ``env.t``.
    """
    counts = np.zeros((types.shape[1], 2), np.int64)  # [n, (L, H)]
    for b in range(out.shape[1]):
        _queued(queue[b], queue_len[b], counts)
        for g in range(out.shape[0]):
            value = _queue_digits(
                counts, types[g], queue_thresholds, queue_places[g, 0], queue_places[g, 1]
            )
            for r in range(size[g]):
                if _free_level(busy_until[b, robots[g, r]], t[b], free_soon) == 1:
                    value += soon_places[g, r]
            out[g, b] = value


@njit(cache=True)
def encode_local(
    slot_type, slot_high, idle, battery, t, last_high, busy_until, queue, queue_len, margin,
    threshold, codes, slot_places, places, active, thresholds, time_to_free, free_soon,
    queue_thresholds, out,
):  # fmt: skip
    """``LocalView`` state indices ``out`` ``[B, m]`` (written).

    The leading six arguments are :func:`env_arrays`, the next three
    :meth:`LocalEncoder.state_arrays`, the next ten a ``LocalEncoder``'s
    :attr:`~LocalEncoder.tables`. With ``time_to_free`` the first digit is the free level
    (instead of the idle flag) and the H and L queue levels over ``Lambda_i`` follow the recency
    digit (``encodings`` module docstring, "Features").
    """
    n_slots = slot_type.shape[1]
    counts = np.zeros((active.shape[1] if time_to_free else 0, 2), np.int64)  # [n, (L, H)]
    for b in range(out.shape[0]):
        if time_to_free:
            _queued(queue[b], queue_len[b], counts)
        for i in range(out.shape[1]):
            if time_to_free:
                index = np.int64(_free_level(busy_until[b, i], t[b], free_soon))
            else:
                index = np.int64(idle[b, i])
            for k in range(n_slots):
                ttype = slot_type[b, k] if slot_type[b, k] >= 0 else codes.shape[0] - 1
                index += codes[ttype, max(slot_high[b, k], 0), i] * slot_places[k, i]
            index += battery_low(battery[b, i], margin[i], threshold) * places[i, n_slots + 1]
            index += recency(last_high[b], t[b], active[i], thresholds) * places[i, n_slots + 2]
            if time_to_free:  # queued H and L tasks over Lambda_i
                index += _queue_digits(
                    counts, active[i], queue_thresholds, places[i, n_slots + 3],
                    places[i, n_slots + 4],
                )  # fmt: skip
            out[b, i] = index


def _battery_rule(env: AuctionEnv) -> tuple[np.ndarray, float]:
    """The arguments of :func:`battery_low` fixed by the env: margins per robot, threshold."""
    return battery_margin(env), float(env.params.battery_threshold)


def env_arrays(env: AuctionEnv) -> tuple[np.ndarray, ...]:
    """The env arrays the encodings read: slots, idle flags, batteries, ticks, H arrivals."""
    return env.slot_type, env.slot_high, env.idle, env.battery, env.t, env.last_high_arrival


class GroupEncoder:
    """Group state indices (``GroupView``) of several groups, all copies in one compiled loop.

    Args:
        env: The env (its slots, types and active tasks fix the tables).
        groups: Robot indices of each group, in the order of its digits.
        features: ``paper`` or ``time_to_free`` (``encodings.FEATURES``).

    Raises:
        OverflowError: if a group's state count does not fit in int64.
    """

    def __init__(
        self, env: AuctionEnv, groups: Sequence[np.ndarray], features: str = "paper"
    ) -> None:
        views = [GroupView(env, g, features) for g in groups]
        self.features = features
        for view in views:
            if not view.fits_int64:
                raise OverflowError(
                    f"group state count {view.count} >= 2**63: too many robots or types for one "
                    f"index (robots {view.robots.tolist()})"
                )
        widest = max(len(g) for g in groups)
        self.robots = np.zeros((len(groups), widest), np.int64)  # padded robot indices
        self.size = np.array([len(g) for g in groups], np.int64)
        self._robot_places = np.zeros((len(groups), widest), np.int64)
        for g, view in enumerate(views):
            self.robots[g, : len(view.robots)] = view.robots
            self._robot_places[g, : len(view.robots)] = view._robot_places
        self._codes = np.stack([v._codes for v in views])  # [G, n + 1, 2]
        self._slot_places = np.stack([v._slot_places for v in views])  # [G, K]
        self._recency_place = np.array([v._recency_place for v in views], np.int64)
        self.types = np.stack([v.types_mask for v in views])  # T_g, [G, n]
        if features == "time_to_free":
            # robot state 3 (busy, free soon) is the busy state 0 plus 3 places; queue places
            # (H, L) follow the recency digit (encodings.GroupView)
            self._offset_tables = (
                self.robots, self.size, 3 * self._robot_places,  # 0 on padding
                self.types, np.stack([v._queue_places for v in views]),  # [G, 2]
                FREE_SOON, _QUEUE_THRESHOLDS,
            )  # fmt: skip
        self._zeros = np.zeros((len(groups), 0), np.int64)  # paper: no offset (per batch size)
        # the arguments of encode_groups after the env's
        self.tables = (
            *_battery_rule(env), self._codes, self._slot_places, self.robots, self.size,
            self._robot_places, self._recency_place, self.types, _THRESHOLDS,
        )  # fmt: skip

    def offset(self, env: AuctionEnv) -> np.ndarray:
        """``[G, B]`` what the features add to the paper codes of :func:`encode_groups` (0s)."""
        if self.features == "paper":
            if self._zeros.shape[1] != env.batch_size:
                self._zeros = np.zeros((len(self.size), env.batch_size), np.int64)
            return self._zeros
        offset = np.empty((len(self.size), env.batch_size), np.int64)
        group_offsets(
            env.busy_until, env.t, env._queue, env._queue_len, *self._offset_tables, offset
        )
        return offset

    def index(self, env: AuctionEnv) -> tuple[np.ndarray, np.ndarray]:
        """``([G, B] state indices, [G, B] recency levels over T_g)``."""
        n_groups, batch = len(self.size), env.batch_size
        states = np.empty((n_groups, batch), np.int64)
        level = np.empty((n_groups, batch), np.int64)
        encode_groups(*env_arrays(env), *self.tables, states, level)
        if self.features != "paper":
            states += self.offset(env)
        return states, level


class LocalEncoder:
    """Local state indices (``LocalView``) of every robot, all copies in one compiled loop.

    Args:
        env: The env (its slots, types and active tasks fix the tables).
        features: ``paper`` or ``time_to_free`` (``encodings.FEATURES``).
    """

    def __init__(self, env: AuctionEnv, features: str = "paper") -> None:
        view = LocalView(env, features)
        self.features = features
        self.counts = view.counts  # |S_i|
        self._codes = view._codes  # [n + 1, 2, m]
        self._slot_places = view._slot_places  # [K, m]
        self._places = view._places  # [m, K + 3] (time_to_free: K + 5)
        self._active = view._active  # Lambda_i, [m, n]
        # the arguments of encode_local after the env's
        self.tables = (
            *_battery_rule(env), self._codes, self._slot_places, self._places, self._active,
            _THRESHOLDS, features == "time_to_free", FREE_SOON, _QUEUE_THRESHOLDS,
        )  # fmt: skip

    @staticmethod
    def state_arrays(env: AuctionEnv) -> tuple[np.ndarray, ...]:
        """The env arrays the ``time_to_free`` digits read: busy-until ticks, the queue."""
        return env.busy_until, env._queue, env._queue_len

    def index(self, env: AuctionEnv) -> np.ndarray:
        """``[B, m]`` int64 local state indices."""
        out = np.empty((env.batch_size, env.n_robots), np.int64)
        encode_local(*env_arrays(env), *self.state_arrays(env), *self.tables, out)
        return out


SYSTEM_STATES = ("system", "idle_count", "idle", "slots")  # semi-CQL's shared state (its `state`)


class SystemEncoder(GroupEncoder):
    """semi-CQL's shared whole-system state: the paper's group view, or a coarser one.

    ``state="system"`` is the ``GroupView`` of all robots (``features`` as given): slot codes,
    each robot's 3 states (busy, idle, idle with low battery), the recency level over all types.
    The coarser states keep the slot codes (``1 + 2n`` each, ``n`` the active types) and the
    recency level (3) and replace the robots' digits, with no battery and no ``time_to_free``
    digits (``features`` must be ``paper``):

    * ``idle_count``: the number of idle robots, one digit of radix ``m + 1``;
    * ``idle``: each robot's idle flag, ``m`` digits of radix 2 (robot 0 least significant);
    * ``slots``: nothing.

    Digits least significant first: slots, robots, recency, so ``|S| = (1 + 2n)^K x R x 3``
    with ``R`` = ``m + 1``, ``2^m`` or 1 (:func:`system_state_count`). The codes come from the
    paper loop (:func:`encode_groups`) with other tables: every idle robot adds the same place
    (``idle_count``) or its own (``idle``, ``slots``: 0), and a zero battery margin under a
    threshold of ``-inf`` makes no battery low, so the compiled ticks of semi-CQL need no code of
    their own. A coarser state also fits teams whose paper state does not fit in int64.

    Args:
        env: The env.
        state: One of :data:`SYSTEM_STATES`.
        features: ``encodings.FEATURES``; only ``paper`` with a coarser ``state``.

    Raises:
        ConfigError: on an unknown ``state``, or ``features`` other than ``paper`` with a
            coarser one (:func:`system_state_count`).
        OverflowError: if the state count does not fit in int64.
    """

    def __init__(self, env: AuctionEnv, state: str = "system", features: str = "paper") -> None:
        self.state = state
        self.count = system_state_count(env, state, features)  # checks state and features
        if state == "system":
            super().__init__(env, [np.arange(env.n_robots)], features)
            return
        if self.count >= 2**63:
            raise OverflowError(f"{state} state count {self.count} >= 2**63: too many robots")
        # the group view's slot codes and types T_g (its own count may pass int64: many robots)
        m, view = env.n_robots, GroupView(env, range(env.n_robots))
        radix = 1 + 2 * view.n_types
        place = radix**env.n_slots  # after the K slot digits
        robot_places = {
            "idle_count": np.full(m, place),
            "idle": place * 2 ** np.arange(m),
            "slots": np.zeros(m),
        }[state]
        robot_radix = _system_robot_radix(state, m)
        self.features, self.size = features, np.array([m], np.int64)
        self.robots, self.types = np.arange(m, dtype=np.int64)[None], view.types_mask[None]
        self._codes = view._codes[None]  # [1, n + 1, 2]
        self._slot_places = (radix ** np.arange(env.n_slots, dtype=np.int64))[None]  # [1, K]
        self._robot_places = robot_places.astype(np.int64)[None]  # [1, m]
        self._recency_place = np.array([place * robot_radix], np.int64)
        self._zeros = np.zeros((1, 0), np.int64)  # no offset (GroupEncoder.offset)
        self.tables = (
            np.zeros(m), -np.inf, self._codes, self._slot_places, self.robots, self.size,
            self._robot_places, self._recency_place, self.types, _THRESHOLDS,
        )  # fmt: skip


def system_state_count(env: AuctionEnv, state: str = "system", features: str = "paper") -> int:
    """Exact ``|S|`` of semi-CQL's shared state (:class:`SystemEncoder`), a Python int.

    Raises:
        ConfigError: on an unknown ``state``, or ``features`` other than ``paper`` with a
            coarser one (it has no ``time_to_free`` digits).
    """
    if state not in SYSTEM_STATES:
        raise ConfigError(f"learner.state: must be one of {SYSTEM_STATES}, got {state!r}")
    if state != "system" and features != "paper":
        raise ConfigError(
            f"learner.state={state}: the coarser states have no time_to_free digits; "
            f"learner.features must be paper, got {features!r}"
        )
    if state == "system":
        return GroupView(env, range(env.n_robots), features).count
    types = int(env.active_tasks.any(axis=0).sum())
    radix = _system_robot_radix(state, env.n_robots)
    return (1 + 2 * types) ** env.n_slots * radix * N_RECENCY_LEVELS


def _system_robot_radix(state: str, m: int) -> int:
    """Values of the robots' part of a coarser shared state (:class:`SystemEncoder`)."""
    return {"idle_count": m + 1, "idle": 2**m, "slots": 1}[state]


# subG-CQL's group state (its `state`): the paper's group view, or its robots' idle flags only
GROUP_STATES = ("group", "idle")


def _idle_radix(features: str) -> int:
    """Radix of a robot's digit in ``state=idle``: busy, idle (2); ``time_to_free``: + free soon."""
    return 3 if features == "time_to_free" else 2


def subgroup_state_count(
    env: AuctionEnv, robots: Sequence[int | str], state: str = "group", features: str = "paper"
) -> int:
    """Exact ``|S_g|`` of one group under subG-CQL's ``state`` (:class:`SubGroupEncoder`).

    Raises:
        ConfigError: on an unknown ``state``.
    """
    if state not in GROUP_STATES:
        raise ConfigError(f"learner.state: must be one of {GROUP_STATES}, got {state!r}")
    view = GroupView(env, robots, features)
    if state == "group":
        return view.count
    queue = N_QUEUE_LEVELS**2 if features == "time_to_free" else 1  # queued H and L levels
    robot_states = _idle_radix(features) ** len(view.robots)
    return (1 + 2 * view.n_types) ** env.n_slots * robot_states * N_RECENCY_LEVELS * queue


class SubGroupEncoder(GroupEncoder):
    """subG-CQL's group states: the paper's ``GroupView`` per group, or a coarser one.

    ``state="group"`` is :class:`GroupEncoder`. ``state="idle"`` keeps the slot codes over
    ``T_g``, the recency level and the ``features`` and drops the battery: each robot's digit
    reads busy (0) or idle (1), and with ``time_to_free`` busy but free within ``FREE_SOON``
    ticks (2) too, instead of the group view's busy / idle / idle with low battery (/ free
    soon): ``|S_g| = (1 + 2 n_g)^K x 2^{m_g} x 3`` (``paper``), ``(1 + 2 n_g)^K x 3^{m_g} x 3
    x 9`` (``time_to_free``, the queued H and L levels last; :func:`subgroup_state_count`). It
    is the coarsest state the joint-action tables allow: a row holds the valid joint actions
    and the prior's of its state's first visit, the mask is a function of the idle flags and
    the slots (spec step 4), the prior of the mask, the slots and the recency level; fewer
    robot digits (the idle count) would mix masks in one row. A battery changes neither. The
    codes come from the paper loop (:func:`encode_groups`) and :func:`group_offsets` with
    other tables, as :class:`SystemEncoder`'s: robot ``r`` of a group adds its place when
    idle, a zero battery margin under a threshold of ``-inf`` makes no battery low, so the
    compiled ticks need no code of their own.

    Args:
        env: The env.
        groups: Robot indices of each group, in the order of its digits.
        state: One of :data:`GROUP_STATES`.
        features: ``encodings.FEATURES``.

    Raises:
        ConfigError: on an unknown ``state``.
        OverflowError: if a group's state count does not fit in int64.
    """

    def __init__(
        self,
        env: AuctionEnv,
        groups: Sequence[np.ndarray],
        state: str = "group",
        features: str = "paper",
    ) -> None:
        self.state = state
        self.counts = [subgroup_state_count(env, g, state, features) for g in groups]  # checks
        super().__init__(env, groups, features)
        if state == "group":
            return
        radix = _idle_radix(features)
        queue_places = np.zeros((len(groups), 2), np.int64)  # (H, L) after the recency digit
        for g, robots in enumerate(groups):
            place = (1 + 2 * int(self.types[g].sum())) ** env.n_slots  # after the K slot digits
            self._robot_places[g, : len(robots)] = place * radix ** np.arange(len(robots))
            self._recency_place[g] = place * radix ** len(robots)
            queue_places[g] = self._recency_place[g] * N_RECENCY_LEVELS * np.array([1, 3])
        if features == "time_to_free":  # free soon: the busy digit 0 plus 2 places
            self._offset_tables = (
                self.robots, self.size, 2 * self._robot_places, self.types, queue_places,
                FREE_SOON, _QUEUE_THRESHOLDS,
            )  # fmt: skip
        self.tables = (np.zeros(env.n_robots), -np.inf, *self.tables[2:])
