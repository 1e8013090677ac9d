"""The tabular learners' state encoders: the encodings of ``envs/encodings`` for their kernels.

The codes are computed once, by the compiled loops of ``envs/state_codes.py``, which the views
of ``envs/encodings`` call too. :class:`GroupEncoder` stacks the tables (slot codes, place
values) of several ``encodings.GroupView`` so that :func:`~mrta_rl.envs.state_codes.encode_groups`
encodes all groups in one call, and :class:`LocalEncoder` is ``encodings.LocalView``. The
compiled ticks of the tabular learners call the same loops with these tables.

A new digit of an encoding plugs in as one more place value: ``encodings`` adds it to the
view's radices (and its count), and ``state_codes`` adds ``digit * place`` in its loop.

The group encoder takes the view's ``features`` (``encodings.FEATURES``): with
``time_to_free``, :meth:`GroupEncoder.offset` computes the extra digits (a busy robot free
within ``FREE_SOON`` ticks reads robot state 3; queued H and L levels over ``T_g``) with
:func:`~mrta_rl.envs.state_codes.group_offsets` and adds them as ``[G, B]`` offsets to the
paper-era codes, so the paper loop is unchanged (the fused ticks of subG-CQL, CQL and semi-CQL
add the same offset). The local view computes its ``time_to_free`` digits in its own loop (a
flag of its tables), so DQL's fused tick needs no offset.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mrta_rl.config import ConfigError
from mrta_rl.envs import AuctionEnv
from mrta_rl.envs.encodings import (
    FREE_SOON,
    N_QUEUE_LEVELS,
    N_RECENCY_LEVELS,
    QUEUE_THRESHOLDS_ARRAY,
    RECENCY_THRESHOLDS_ARRAY,
    GroupView,
    LocalView,
    battery_margin,
    busy_arrays,
    env_arrays,
)
from mrta_rl.envs.state_codes import GroupTables, OffsetTables, encode_groups, group_offsets


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
            self._offset_tables = tuple(
                OffsetTables(
                    robots=self.robots,
                    size=self.size,
                    soon_places=3 * self._robot_places,  # 0 on padding
                    types=self.types,
                    queue_places=np.stack([v._queue_places for v in views]),  # [G, 2]
                    free_soon=FREE_SOON,
                    queue_thresholds=QUEUE_THRESHOLDS_ARRAY,
                )
            )
        self._zeros = np.zeros((len(groups), 0), np.int64)  # paper: no offset (per batch size)
        # what encode_groups reads besides the env (the tabular kernels' too)
        self.tables = tuple(
            GroupTables(
                margin=battery_margin(env),
                threshold=float(env.params.battery_threshold),
                codes=self._codes,
                slot_places=self._slot_places,
                robots=self.robots,
                size=self.size,
                robot_places=self._robot_places,
                recency_place=self._recency_place,
                types=self.types,
                thresholds=RECENCY_THRESHOLDS_ARRAY,
            )
        )

    def offset(self, env: AuctionEnv) -> np.ndarray:
        """``[G, B]`` what the features add to the paper codes of :func:`encode_groups` (0s)."""
        if self.features == "paper":
            if self._zeros.shape[1] != env.batch_size:
                self._zeros = np.zeros((len(self.size), env.batch_size), np.int64)
            return self._zeros
        offset = np.empty((len(self.size), env.batch_size), np.int64)
        group_offsets(env.t, busy_arrays(env), self._offset_tables, offset)
        return offset

    def index(self, env: AuctionEnv) -> tuple[np.ndarray, np.ndarray]:
        """``([G, B] state indices, [G, B] recency levels over T_g)``."""
        n_groups, batch = len(self.size), env.batch_size
        states = np.empty((n_groups, batch), np.int64)
        level = np.empty((n_groups, batch), np.int64)
        encode_groups(env_arrays(env), self.tables, states, level)
        if self.features != "paper":
            states += self.offset(env)
        return states, level


# DQL's local states: the local view itself computes them with the compiled loop (its
# ``tables``, with ``env_arrays`` and ``busy_arrays``, are what ``state_codes.encode_local`` reads)
LocalEncoder = LocalView


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
        self.tables = tuple(
            GroupTables(
                margin=np.zeros(m),
                threshold=-np.inf,
                codes=self._codes,
                slot_places=self._slot_places,
                robots=self.robots,
                size=self.size,
                robot_places=self._robot_places,
                recency_place=self._recency_place,
                types=self.types,
                thresholds=RECENCY_THRESHOLDS_ARRAY,
            )
        )


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
            soon = {"soon_places": 2 * self._robot_places, "queue_places": queue_places}
            self._offset_tables = tuple(OffsetTables(*self._offset_tables)._replace(**soon))
        no_battery = {"margin": np.zeros(env.n_robots), "threshold": -np.inf}
        self.tables = tuple(GroupTables(*self.tables)._replace(**no_battery))
