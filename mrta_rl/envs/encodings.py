"""Finite observation encodings of an ``AuctionEnv`` (spec ``auction_env.md``, "Observations").

Every encoding below is a finite mixed-radix integer (for tabular learners) or a fixed-width
float32 one-hot vector (for neural nets), computed from the env's public arrays for all ``B``
copies at once. This module holds the tables (slot codes, place values) and the formulas; the
digits and the state indices themselves are computed by the compiled loops of
``envs/state_codes.py``, the one implementation the tabular learners' kernels call too. The
counts are exact, so the learning space dimension (paper eqs 10-16) is ``|S| x |A|`` with ``|S|``
from here and ``|A| = K + 1`` per robot. Notation: ``m`` robots, ``n`` task types, ``K`` slots,
``Lambda_i`` the active task types of robot ``i``.

Coarse signals:
    * **battery level** (2 values), :func:`battery_level`: ``1`` (low) when
      ``battery_i - drain_per_tick * longest_i < battery_threshold``, where ``longest_i`` is the
      longest possible duration of a task of ``Lambda_i`` (both priorities): the next task may send
      the robot to charge (spec step 5). Else ``0``.
    * **recency level** (3 values), :func:`recency_level`: with ``delta = t - (last H arrival
      among the given types)``, ``0`` if ``delta <= 3``, ``1`` if ``delta <= 10``, ``2`` if longer
      or never (thresholds :data:`RECENCY_THRESHOLDS`). An arrival at the current tick has
      ``delta = 0``.

Local view of robot ``i`` (decentralized learners), :class:`LocalView`, digits (least
significant first) and radices:
    * idle flag: 2 (spec step 4);
    * slot ``k = 1..K``: ``1 + 2 |Lambda_i|``; code 0 = the slot is empty or holds a type not in
      ``Lambda_i``, else ``1 + 2 * (rank of the slot's type within Lambda_i) + high``. The code
      does not depend on the idle flag (a busy robot sees the slots but may not bid);
    * battery level: 2;
    * recency level over ``Lambda_i``: 3.

    ``|S_i| = 2 * (1 + 2 |Lambda_i|)^K * 2 * 3`` (:func:`local_state_count`).

Group view of robots ``g`` with types ``T_g = union of their Lambda_i`` (centralized learners:
the whole system for CQL / semi-CQL, one sub-group for subG-CQL), :class:`GroupView`, digits
(least significant first):
    * slot ``k = 1..K``: ``1 + 2 |T_g|``; 0 = empty or a type outside ``T_g``, else
      ``1 + 2 * (rank of the type within T_g) + high``;
    * robot ``r`` of the group, in the given order: 3 (0 = busy, 1 = idle with ok battery,
      2 = idle with low battery);
    * recency level over ``T_g``: 3.

    ``|S_g| = (1 + 2 |T_g|)^K * 3^{m_g} * 3`` (:func:`group_state_count`, an exact Python int;
    :func:`group_state_index` raises ``OverflowError`` if it does not fit in int64).

Features (``features`` argument of every encoding, :data:`FEATURES`): ``"paper"`` (default) is
the encoding above, the paper-era one; ``"time_to_free"`` adds what the paper's state leaves out
and rules that know it use: when busy robots become free and how full the queue is.
    * **free level** (3 values), :func:`free_level`: ``0`` idle, ``1`` busy but free within
      :data:`FREE_SOON` ticks, ``2`` busy for longer. A robot busy until tick ``u`` (execution and
      charging included) is idle again at ``u + 1``: ``u - t + 1`` ticks from now.
    * **queue levels** (3 values per priority), :func:`queue_level`: the number of queued tasks
      (slot tasks and round-2 tasks included) of the given types, per priority, cut at
      :data:`QUEUE_THRESHOLDS`: H ``0 | 1 | 2+``, L ``0-2 | 3-8 | 9+``.
    With ``"time_to_free"``:
    * local view: the idle flag becomes the free level (3), and the queue levels over
      ``Lambda_i`` (H then L, 3 each) follow the recency digit:
      ``|S_i| = 3 (1 + 2 |Lambda_i|)^K * 2 * 3 * 3 * 3``;
    * group view: robot states gain ``3`` = busy but free within :data:`FREE_SOON` ticks (so 4
      states), and the queue levels over ``T_g`` (H then L) follow the recency digit:
      ``|S_g| = (1 + 2 |T_g|)^K * 4^{m_g} * 3 * 3 * 3``;
    * local features: a free-level one-hot (3) and queue-level one-hots over ``Lambda_i`` (H 3,
      L 3) between the recency and the robot id (``F + 9``); global features: per robot a
      free-level one-hot (``3m``) and per task type its queue-level one-hots (``6n``) at the end.

Neural features:
    * :func:`local_features` ``[B, m, F]`` with ``F = 1 + K (1 + 2n) + 1 + 3 + m``: idle bit; per
      slot a one-hot over ``1 + 2n`` codes (``1 + 2 type + high`` over *all* types, so robots share
      one layout, but 0 where the type is not in ``Lambda_i``, as in the local view, or where the
      slot is in another auction zone, spec "Auction zones"); battery-low bit; recency one-hot
      (3); robot-id one-hot (m).
    * :func:`global_features` ``[B, G]`` with ``G = K (1 + 2n) + m + m + 3n``: per slot a one-hot
      over ``1 + 2n`` codes; idle bits; battery-low bits; per task type a recency one-hot (3).

Set inputs (:func:`set_inputs`, team-size independent, for the shared robot-set network of
``learners/neural/set_network.py``): tokens whose widths depend on no ``m``, ``K`` or ``n``, so one
network runs on any team. Every float lies in ``[0, 1]``; counts are divided by a scale and cut at
1 (:data:`COUNT_SCALES`), times by :data:`TIME_SCALE` ticks.
    * ``robots`` ``[B, m, R]`` (:data:`ROBOT_FEATURES`): idle, free soon (free level 1), time to
      free, battery fraction, battery low, recency one-hot over ``Lambda_i`` (3), queued H and L
      over ``Lambda_i`` (scaled counts and levels / 2), for its least-covered type whether no
      other robot is idle, the other idle robots and the other idle or soon-free robots (scaled),
      and ``|Lambda_i| / n``. No robot id.
    * ``robot_types`` ``[B, m, n]`` bool: ``Lambda_i`` as a multi-hot.
    * ``slots`` ``[B, K, S]`` (:data:`SLOT_FEATURES`): present, high, ticks since due (scaled),
      round 2 (the task is dropped if nobody wins it now, spec step 6), duration (scaled), the
      robots that may bid for it (idle, its type in their ``Lambda_i``, in its auction zone;
      scaled). An empty slot is all zeros.
    * ``slot_type`` ``[B, K]`` int64: the slot task's type, 0 for an empty slot.
    * ``types`` ``[B, n, T]`` (:data:`TYPE_FEATURES`): queued H and L (scaled counts and levels /
      2), recency one-hot (3), ticks since the last H arrival (scaled), idle robots and idle or
      soon-free robots covering it (scaled), robots whose ``Lambda`` holds it (scaled).
"""

from __future__ import annotations

import weakref
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from mrta_rl.envs import state_codes
from mrta_rl.envs.auction import AuctionEnv
from mrta_rl.envs.tasks import task_due, task_duration, task_round

RECENCY_THRESHOLDS: tuple[int, int] = (3, 10)  # recency level 0: delta <= 3, 1: delta <= 10, else 2
N_RECENCY_LEVELS = 3
N_BATTERY_LEVELS = 2
N_ROBOT_STATES = 3  # group view: busy / idle ok battery / idle low battery
FEATURES = ("paper", "time_to_free")  # selectable encodings; "paper" is the paper-era default
FREE_SOON = 3  # free level 1: a busy robot idle again within this many ticks
N_FREE_LEVELS = 3  # idle / free soon / free later
QUEUE_THRESHOLDS = {"H": (0, 1), "L": (2, 8)}  # queue level: count <= t0 -> 0, <= t1 -> 1, else 2
N_QUEUE_LEVELS = 3
# the thresholds as the compiled loops (envs/state_codes.py) take them
RECENCY_THRESHOLDS_ARRAY = np.array(RECENCY_THRESHOLDS, np.int64)
QUEUE_THRESHOLDS_ARRAY = np.array(
    [QUEUE_THRESHOLDS["H"], QUEUE_THRESHOLDS["L"]], np.int64
)  # [H, L]

__all__ = [
    "FEATURES",
    "FREE_SOON",
    "QUEUE_THRESHOLDS",
    "GroupView",
    "LocalView",
    "N_RECENCY_LEVELS",
    "RECENCY_THRESHOLDS",
    "battery_level",
    "battery_margin",
    "check_features",
    "free_level",
    "queue_counts",
    "queue_level",
    "global_feature_size",
    "global_features",
    "group_state_count",
    "group_state_index",
    "local_feature_layout",
    "local_feature_size",
    "local_features",
    "local_state_count",
    "local_state_index",
    "recency_level",
    "ROBOT_FEATURES",
    "ROBOT_TOKEN_SIZE",
    "SLOT_FEATURES",
    "SLOT_TOKEN_SIZE",
    "SetInputs",
    "TYPE_FEATURES",
    "TYPE_TOKEN_SIZE",
    "set_inputs",
]


def _longest_durations(env: AuctionEnv) -> np.ndarray:
    """``[m]`` longest duration of a task of ``Lambda_i`` (system overrides, else params)."""
    p, system = env.params, env.system
    longest = np.zeros(env.n_task_types, np.int64)
    for j, name in enumerate(system.task_types):
        over = system.durations.get(name, {})
        keys = ("duration_low", "duration_high")
        highs = [over[k].hi if k in over else getattr(p, k)[1] for k in keys]
        longest[j] = max(highs)
    return np.where(env.active_tasks, longest[None, :], 0).max(axis=1)


_MARGIN: weakref.WeakKeyDictionary[AuctionEnv, np.ndarray] = weakref.WeakKeyDictionary()


def battery_margin(env: AuctionEnv) -> np.ndarray:
    """``[m]`` ``drain_per_tick * longest_i``: robot ``i``'s battery is low below threshold + this.

    Args:
        env: The auction environment.

    Returns:
        ``[m]`` float64; :func:`battery_level` is ``battery - margin < battery_threshold``.
    """
    margin = _MARGIN.get(env)
    if margin is None:
        margin = _MARGIN[env] = env.params.drain_per_tick * _longest_durations(env)
    return margin


def battery_level(env: AuctionEnv) -> np.ndarray:
    """Coarse battery level per robot (module docstring).

    Args:
        env: The auction environment.

    Returns:
        ``[B, m]`` int64 in {0, 1}; 1 = low, the next task may send the robot to charge.
    """
    out = np.empty((env.batch_size, env.n_robots), np.int64)
    state_codes.battery_levels(
        env.battery, battery_margin(env), float(env.params.battery_threshold), out
    )
    return out


def recency_level(env: AuctionEnv, types_mask: np.ndarray) -> np.ndarray:
    """Coarse time since the last H arrival of one of the given task types (module docstring).

    Args:
        env: The auction environment.
        types_mask: ``[n]`` bool (one set of types) or ``[m', n]`` bool (one set per row).

    Returns:
        ``[B]`` (for ``[n]``) or ``[B, m']`` (for ``[m', n]``) int64 levels in {0, 1, 2}.

    Raises:
        ValueError: if ``types_mask`` does not end in ``n``.
    """
    types_mask = np.asarray(types_mask, dtype=bool)
    if types_mask.shape[-1] != env.n_task_types or types_mask.ndim not in (1, 2):
        raise ValueError(
            f"types_mask must be [n] or [m, n] with n={env.n_task_types}, got {types_mask.shape}"
        )
    rows = np.atleast_2d(types_mask)  # [m', n]
    out = np.empty((env.batch_size, len(rows)), np.int64)
    state_codes.recency_levels(env.last_high_arrival, env.t, rows, RECENCY_THRESHOLDS_ARRAY, out)
    return out[:, 0] if types_mask.ndim == 1 else out


def check_features(features: str) -> str:
    """The encoding name, checked against :data:`FEATURES`.

    Raises:
        ValueError: naming the unknown value and the known ones.
    """
    if features not in FEATURES:
        raise ValueError(f"features must be one of {FEATURES}, got {features!r}")
    return features


def free_level(env: AuctionEnv) -> np.ndarray:
    """Coarse time until each robot is idle again (module docstring, "Features").

    Args:
        env: The auction environment.

    Returns:
        ``[B, m]`` int64 in {0, 1, 2}: idle, free within :data:`FREE_SOON` ticks, later.
    """
    out = np.empty((env.batch_size, env.n_robots), np.int64)
    state_codes.free_levels(env.busy_until, env.t, FREE_SOON, out)
    return out


def queue_counts(env: AuctionEnv) -> np.ndarray:
    """Queued tasks per type and priority, slot tasks and round-2 tasks included.

    Args:
        env: The auction environment.

    Returns:
        ``[B, n, 2]`` int64 counts (priority index 0 = L, 1 = H).
    """
    counts = np.empty((env.batch_size, env.n_task_types, 2), np.int64)
    state_codes.queue_counts_of(env._queue, env._queue_len, counts)
    return counts


def queue_level(env: AuctionEnv, types_mask: np.ndarray, counts: np.ndarray | None = None):
    """Coarse queued H and L counts over the given task types (module docstring, "Features").

    Args:
        env: The auction environment.
        types_mask: ``[n]`` bool (one set of types) or ``[m', n]`` bool (one set per row).
        counts: :func:`queue_counts` of ``env`` if already computed.

    Returns:
        ``[B, 2]`` (for ``[n]``) or ``[B, m', 2]`` int64 levels in {0, 1, 2}: index 0 = H,
        index 1 = L.
    """
    counts = queue_counts(env) if counts is None else counts  # [B, n, 2]
    types_mask = np.asarray(types_mask, dtype=bool)
    rows = np.atleast_2d(types_mask)  # [m', n]
    out = np.empty((env.batch_size, len(rows), 2), np.int64)
    state_codes.queue_levels(counts, rows, QUEUE_THRESHOLDS_ARRAY, out)
    return out[:, 0] if types_mask.ndim == 1 else out


def env_arrays(env: AuctionEnv) -> tuple[np.ndarray, ...]:
    """The env arrays the state codes read (``state_codes.EnvArrays``), a plain tuple."""
    return env.slot_type, env.slot_high, env.idle, env.battery, env.t, env.last_high_arrival


def busy_arrays(env: AuctionEnv) -> tuple[np.ndarray, ...]:
    """The env arrays the ``time_to_free`` digits read (``state_codes.BusyArrays``), a tuple."""
    return env.busy_until, env._queue, env._queue_len


def _places(radices: np.ndarray) -> np.ndarray:
    """Little-endian mixed-radix place values along the last axis (``place_0 = 1``)."""
    places = np.ones_like(radices)
    places[..., 1:] = np.cumprod(radices[..., :-1], axis=-1)
    return places


def _decode(index: int, radices: Sequence[int]) -> list[int]:
    digits = []
    for radix in radices:
        index, digit = divmod(int(index), int(radix))
        digits.append(digit)
    if index:
        raise ValueError("index out of range")
    return digits


class LocalView:
    """Per-robot local state index (module docstring), with tables precomputed for one env.

    Args:
        env: The auction environment (its ``active_tasks`` and ``n_slots`` fix the tables).
        features: ``"paper"`` or ``"time_to_free"`` (module docstring, "Features").
    """

    def __init__(self, env: AuctionEnv, features: str = "paper") -> None:
        self.features = check_features(features)
        extra = features == "time_to_free"
        m, n, K = env.n_robots, env.n_task_types, env.n_slots
        active = env.active_tasks  # Lambda_i, [m, n]
        self.n_active = active.sum(axis=1)  # |Lambda_i|, [m]
        rank = np.cumsum(active, axis=1) - 1  # rank of each type within Lambda_i, [m, n]
        # slot code per (robot, type + empty row, high): 1 + 2 rank + high if the type is active
        codes = np.zeros((m, n + 1, 2), np.int64)  # row n answers slot_type -1 (empty)
        codes[:, :n, :] = np.where(active[:, :, None], 1 + 2 * rank[:, :, None] + np.arange(2), 0)
        self._codes = codes.transpose(1, 2, 0).copy()  # [n + 1, 2, m] for [B, K, m] lookups
        slot_radix = 1 + 2 * self.n_active  # [m]
        first = N_FREE_LEVELS if extra else 2  # free level, or the idle flag
        queue = [np.full(m, N_QUEUE_LEVELS)] * 2 if extra else []  # H, L queue levels
        radices = np.column_stack(
            [
                np.full(m, first),
                *([slot_radix] * K),
                np.full(m, N_BATTERY_LEVELS),
                np.full(m, N_RECENCY_LEVELS),
                *queue,
            ]
        )
        self.counts = [int(np.prod([int(r) for r in row], dtype=object)) for row in radices]
        if max(self.counts) >= 2**63:
            raise OverflowError(f"local state count {max(self.counts)} does not fit in int64")
        self.radices = radices  # [m, K + 3] (+ 2 queue digits)
        self._places = _places(radices)
        self._slot_places = self._places[:, 1 : K + 1].T.copy()  # [K, m]
        self._active = active
        # what state_codes.encode_local reads besides the env (the tabular kernels' too)
        self.tables = tuple(
            state_codes.LocalTables(
                margin=battery_margin(env),
                threshold=float(env.params.battery_threshold),
                codes=self._codes,
                slot_places=self._slot_places,
                places=self._places,
                active=self._active,
                thresholds=RECENCY_THRESHOLDS_ARRAY,
                time_to_free=extra,
                free_soon=FREE_SOON,
                queue_thresholds=QUEUE_THRESHOLDS_ARRAY,
            )
        )

    def index(self, env: AuctionEnv) -> np.ndarray:
        """``[B, m]`` int64 local state indices, each in ``[0, counts[i])``."""
        out = np.empty((env.batch_size, env.n_robots), np.int64)
        state_codes.encode_local(env_arrays(env), busy_arrays(env), self.tables, out)
        return out

    def decode(self, robot: int, index: int) -> dict[str, object]:
        """Fields of one robot's local index (``free``, ``queue_*`` with ``time_to_free``).

        Returns:
            ``idle`` (or ``free``), ``slots``, ``battery``, ``recency`` (, ``queue_high``,
            ``queue_low``).
        """
        d = _decode(index, self.radices[robot])
        K = len(self._slot_places)
        fields = {"slots": d[1 : K + 1], "battery": d[K + 1], "recency": d[K + 2]}
        if self.features == "paper":
            return {"idle": d[0], **fields}
        return {"free": d[0], **fields, "queue_high": d[K + 3], "queue_low": d[K + 4]}


class GroupView:
    """Group state index of some robots (module docstring), with tables precomputed for one env.

    Args:
        env: The auction environment.
        robots: Robot indices (or ids such as ``"R2"``) of the group, in the order of its digits.
        features: ``"paper"`` or ``"time_to_free"`` (module docstring, "Features").

    Raises:
        ValueError: on an empty group, an unknown robot or unknown features.
    """

    def __init__(
        self, env: AuctionEnv, robots: Sequence[int | str], features: str = "paper"
    ) -> None:
        self.features = check_features(features)
        extra = features == "time_to_free"
        if len(robots) == 0:
            raise ValueError("a group needs at least one robot")
        ids = [env.system.robots.index(r) if isinstance(r, str) else int(r) for r in robots]
        if any(not 0 <= i < env.n_robots for i in ids):
            raise ValueError(f"robot index out of range in {robots}")
        n, K = env.n_task_types, env.n_slots
        self.robots = np.array(ids, np.int64)  # [m_g]
        self.types_mask = env.active_tasks[self.robots].any(axis=0)  # T_g, [n]
        self.n_types = int(self.types_mask.sum())
        rank = np.cumsum(self.types_mask) - 1
        codes = np.zeros((n + 1, 2), np.int64)  # row n answers slot_type -1 (empty)
        codes[:n] = np.where(self.types_mask[:, None], 1 + 2 * rank[:, None] + np.arange(2), 0)
        self._codes = codes
        self.n_slots = K
        robot_states = N_ROBOT_STATES + 1 if extra else N_ROBOT_STATES  # + busy, free soon
        queue = [N_QUEUE_LEVELS] * 2 if extra else []  # H, L queue levels over T_g
        self.radices = (
            [1 + 2 * self.n_types] * K + [robot_states] * len(ids) + [N_RECENCY_LEVELS] + queue
        )
        self.count = int(np.prod(self.radices, dtype=object))  # exact Python int
        self.fits_int64 = self.count < 2**63
        if self.fits_int64:
            places = _places(np.array(self.radices, np.int64))
            self._slot_places = places[:K]  # [K]
            self._robot_places = places[K : K + len(ids)]  # [m_g]
            self._recency_place = int(places[K + len(ids)])
            self._queue_places = places[K + len(ids) + 1 :]  # [2] (H, L) or empty
            # the tables of state_codes.encode_groups and group_offsets for this one group;
            # robot state 3 (busy, free soon) is the busy state 0 plus 3 places
            robots, size = self.robots[None], np.array([len(ids)], np.int64)
            self._tables = tuple(
                state_codes.GroupTables(
                    margin=battery_margin(env),
                    threshold=float(env.params.battery_threshold),
                    codes=self._codes[None],
                    slot_places=self._slot_places[None],
                    robots=robots,
                    size=size,
                    robot_places=self._robot_places[None],
                    recency_place=np.array([self._recency_place], np.int64),
                    types=self.types_mask[None],
                    thresholds=RECENCY_THRESHOLDS_ARRAY,
                )
            )
            self._offset_tables = tuple(
                state_codes.OffsetTables(
                    robots=robots,
                    size=size,
                    soon_places=3 * self._robot_places[None],
                    types=self.types_mask[None],
                    queue_places=self._queue_places[None],
                    free_soon=FREE_SOON,
                    queue_thresholds=QUEUE_THRESHOLDS_ARRAY,
                )
            )

    def index(self, env: AuctionEnv) -> np.ndarray:
        """``[B]`` int64 group state indices in ``[0, count)``.

        Raises:
            OverflowError: if :attr:`count` does not fit in int64 (use a smaller group).
        """
        if not self.fits_int64:
            raise OverflowError(
                f"group state count {self.count} >= 2**63: too many robots or types for one index"
            )
        index = np.empty((1, env.batch_size), np.int64)
        level = np.empty((1, env.batch_size), np.int64)
        state_codes.encode_groups(env_arrays(env), self._tables, index, level)
        if self.features == "time_to_free":  # the free-soon robot states and queue levels
            offset = np.empty((1, env.batch_size), np.int64)
            state_codes.group_offsets(env.t, busy_arrays(env), self._offset_tables, offset)
            index += offset
        return index[0]

    def decode(self, index: int) -> dict[str, list[int] | int]:
        """Fields of a group state index (``queue_*`` with ``time_to_free``).

        Returns:
            ``slots`` (K), ``robots`` (m_g states), ``recency`` (, ``queue_high``, ``queue_low``).
        """
        digits = _decode(index, self.radices)
        K, m_g = self.n_slots, len(self.robots)
        fields = {
            "slots": digits[:K],
            "robots": digits[K : K + m_g],
            "recency": digits[K + m_g],
        }
        if self.features == "time_to_free":
            fields |= {"queue_high": digits[K + m_g + 1], "queue_low": digits[K + m_g + 2]}
        return fields


# One precomputed view per env (and per group and encoding), so per-tick calls only index tables.
_LocalViews = dict[str, LocalView]
_LOCAL: weakref.WeakKeyDictionary[AuctionEnv, _LocalViews] = weakref.WeakKeyDictionary()
_GroupViews = dict[tuple[str, tuple[int, ...]], GroupView]
_GROUP: weakref.WeakKeyDictionary[AuctionEnv, _GroupViews] = weakref.WeakKeyDictionary()


def _local_view(env: AuctionEnv, features: str) -> LocalView:
    views = _LOCAL.setdefault(env, {})
    if features not in views:
        views[features] = LocalView(env, features)
    return views[features]


def _group_view(env: AuctionEnv, robots: Sequence[int | str], features: str) -> GroupView:
    ids = tuple(env.system.robots.index(r) if isinstance(r, str) else int(r) for r in robots)
    views = _GROUP.setdefault(env, {})
    if (features, ids) not in views:
        views[(features, ids)] = GroupView(env, ids, features)
    return views[(features, ids)]


def local_state_index(env: AuctionEnv, features: str = "paper") -> np.ndarray:
    """Local state index of every robot (module docstring).

    Args:
        env: The auction environment.
        features: ``"paper"`` or ``"time_to_free"``.

    Returns:
        ``[B, m]`` int64, robot ``i``'s index in ``[0, local_state_count(env, features)[i])``.
    """
    return _local_view(env, features).index(env)


def local_state_count(env: AuctionEnv, features: str = "paper") -> list[int]:
    """``[m]`` Python ints ``|S_i|`` (paper eq. 10's; formulas in the module docstring)."""
    return list(_local_view(env, features).counts)


def group_state_index(
    env: AuctionEnv, robots: Sequence[int | str], features: str = "paper"
) -> np.ndarray:
    """Group state index of the given robots (module docstring).

    Args:
        env: The auction environment.
        robots: Robot indices (or ids) of the group.
        features: ``"paper"`` or ``"time_to_free"``.

    Returns:
        ``[B]`` int64 in ``[0, group_state_count(env, robots, features))``.

    Raises:
        OverflowError: if the count does not fit in int64.
    """
    return _group_view(env, robots, features).index(env)


def group_state_count(env: AuctionEnv, robots: Sequence[int | str], features: str = "paper") -> int:
    """Exact ``|S_g|`` as a Python int (paper eqs 13, 16; formulas in the module docstring)."""
    return _group_view(env, robots, features).count


def _extra_local(env: AuctionEnv, features: str) -> int:
    """Width of the "time_to_free" blocks of the local features: free level and queue levels."""
    return N_FREE_LEVELS + 2 * N_QUEUE_LEVELS if check_features(features) == "time_to_free" else 0


def local_feature_size(env: AuctionEnv, features: str = "paper") -> int:
    """``F = 1 + K (1 + 2n) + 1 + 3 + m`` (+ 9 with ``"time_to_free"``), see the layout."""
    paper = 1 + env.n_slots * (1 + 2 * env.n_task_types) + 1 + N_RECENCY_LEVELS + env.n_robots
    return paper + _extra_local(env, features)


def global_feature_size(env: AuctionEnv, features: str = "paper") -> int:
    """``G = K (1 + 2n) + 2m + 3n`` (+ ``3m + 6n`` with ``"time_to_free"``)."""
    n, m = env.n_task_types, env.n_robots
    paper = env.n_slots * (1 + 2 * n) + 2 * m + N_RECENCY_LEVELS * n
    if check_features(features) == "time_to_free":
        return paper + N_FREE_LEVELS * m + 2 * N_QUEUE_LEVELS * n
    return paper


def _slot_codes(env: AuctionEnv) -> np.ndarray:
    """``[B, K]`` global slot codes: 0 empty, else ``1 + 2 type + high``."""
    return np.where(env.slot_type >= 0, 1 + 2 * env.slot_type + env.slot_high, 0)


def local_features(env: AuctionEnv, features: str = "paper") -> np.ndarray:
    """One-hot local view of every robot, for neural nets (layout in the module docstring).

    Args:
        env: The auction environment.
        features: ``"paper"`` or ``"time_to_free"`` (free and queue levels, "Features").

    Returns:
        ``[B, m, F]`` float32, ``F = local_feature_size(env, features)``.
    """
    B, m, K, n = env.batch_size, env.n_robots, env.n_slots, env.n_task_types
    n_codes = 1 + 2 * n
    codes = _slot_codes(env)  # [B, K]
    # as in the local view, a robot sees only the slots it may bid for (spec step 4: Lambda_i,
    # and its auction zone's slots) (an empty slot indexes row -1, a real type, but its code is
    # 0 anyway)
    visible = env.active_tasks.T[env.slot_type] & (codes > 0)[:, :, None]  # [B, K, m]
    visible &= env.zone_slots.T[None]
    local_codes = np.where(visible, codes[:, :, None], 0).transpose(0, 2, 1)  # [B, m, K]
    at = local_feature_layout(K, n, features)
    out = np.zeros((B, m, local_feature_size(env, features)), np.float32)
    out[..., at["idle"].start] = env.idle
    slot_block = out[..., at["slots"]].reshape(B, m, K, n_codes)
    np.put_along_axis(slot_block, local_codes[..., None], 1.0, axis=-1)
    out[..., at["slots"]] = slot_block.reshape(B, m, K * n_codes)
    out[..., at["battery"].start] = battery_level(env)
    recency = recency_level(env, env.active_tasks)  # [B, m]
    np.put_along_axis(out, (at["recency"].start + recency)[..., None], 1.0, axis=-1)
    out[:, np.arange(m), at["robot"].start + np.arange(m)] = 1.0  # robot id one-hot
    if features == "time_to_free":
        np.put_along_axis(out, (at["free"].start + free_level(env))[..., None], 1.0, axis=-1)
        queue = queue_level(env, env.active_tasks)  # [B, m, 2]: H, L levels over Lambda_i
        offsets = at["queue"].start + np.array([0, N_QUEUE_LEVELS])
        np.put_along_axis(out, queue + offsets, 1.0, axis=-1)
    return out


def local_feature_layout(
    n_slots: int, n_task_types: int, features: str = "paper"
) -> dict[str, slice]:
    """Where the parts of :func:`local_features` sit on the feature axis (module docstring).

    Args:
        n_slots: ``K``.
        n_task_types: ``n``.
        features: ``"paper"`` or ``"time_to_free"``.

    Returns:
        ``{"idle", "slots", "battery", "recency", "robot"}`` -> slice (and ``"free"``, the free
        level one-hot, and ``"queue"``, the H then L queue-level one-hots, between ``"recency"``
        and ``"robot"`` with ``"time_to_free"``); ``"slots"`` holds ``K`` one-hots of ``1 + 2n``
        codes (code ``1 + 2 type + high``), ``"recency"`` the 3 levels.
    """
    slots_end = 1 + n_slots * (1 + 2 * n_task_types)
    recency_end = slots_end + 1 + N_RECENCY_LEVELS
    layout = {
        "idle": slice(0, 1),
        "slots": slice(1, slots_end),
        "battery": slice(slots_end, slots_end + 1),
        "recency": slice(slots_end + 1, recency_end),
    }
    if check_features(features) == "time_to_free":
        free_end = recency_end + N_FREE_LEVELS
        layout["free"] = slice(recency_end, free_end)
        layout["queue"] = slice(free_end, free_end + 2 * N_QUEUE_LEVELS)
        recency_end = free_end + 2 * N_QUEUE_LEVELS
    layout["robot"] = slice(recency_end, None)
    return layout


def global_features(env: AuctionEnv, features: str = "paper") -> np.ndarray:
    """One-hot global state, for centralized critics and mixers (layout in the module docstring).

    Args:
        env: The auction environment.
        features: ``"paper"`` or ``"time_to_free"`` (free and queue levels at the end).

    Returns:
        ``[B, G]`` float32, ``G = global_feature_size(env, features)``.
    """
    B, m, K, n = env.batch_size, env.n_robots, env.n_slots, env.n_task_types
    n_codes = 1 + 2 * n
    out = np.zeros((B, global_feature_size(env, features)), np.float32)
    slots = np.zeros((B, K, n_codes), np.float32)
    np.put_along_axis(slots, _slot_codes(env)[..., None], 1.0, axis=-1)
    out[:, : K * n_codes] = slots.reshape(B, K * n_codes)
    base = K * n_codes
    out[:, base : base + m] = env.idle
    out[:, base + m : base + 2 * m] = battery_level(env)
    recency = recency_level(env, np.eye(n, dtype=bool))  # [B, n], one level per task type
    rec = np.zeros((B, n, N_RECENCY_LEVELS), np.float32)
    np.put_along_axis(rec, recency[..., None], 1.0, axis=-1)
    end = base + 2 * m + n * N_RECENCY_LEVELS
    out[:, base + 2 * m : end] = rec.reshape(B, n * N_RECENCY_LEVELS)
    if features == "time_to_free":
        free = np.zeros((B, m, N_FREE_LEVELS), np.float32)
        np.put_along_axis(free, free_level(env)[..., None], 1.0, axis=-1)
        out[:, end : end + N_FREE_LEVELS * m] = free.reshape(B, -1)
        queue = queue_level(env, np.eye(n, dtype=bool))  # [B, n, 2]: H, L level per type
        one_hot = np.zeros((B, n, 2, N_QUEUE_LEVELS), np.float32)
        np.put_along_axis(one_hot, queue[..., None], 1.0, axis=-1)
        out[:, end + N_FREE_LEVELS * m :] = one_hot.reshape(B, -1)
    return out


# ---------------------------------------------------------------------------------- set inputs
ROBOT_FEATURES = (
    "idle",
    "free_soon",  # busy, idle again within FREE_SOON ticks
    "time_to_free",  # ticks until idle / TIME_SCALE, 0 when idle
    "battery",  # battery / battery_capacity
    "battery_low",  # battery_level
    "recency_0",  # recency level over Lambda_i, one-hot
    "recency_1",
    "recency_2",
    "queued_high",  # queued H tasks of Lambda_i's types / COUNT_SCALES["high"]
    "queued_low",  # queued L tasks of Lambda_i's types / COUNT_SCALES["low"]
    "queue_level_high",  # queue_level H over Lambda_i / 2
    "queue_level_low",  # queue_level L over Lambda_i / 2
    "sole_idle",  # no other robot is idle for one of its types
    "others_idle",  # other idle robots for its least-covered type / COUNT_SCALES["robots"]
    "others_soon",  # other idle or soon-free robots for its least-covered type, scaled
    "versatility",  # |Lambda_i| / n
)
SLOT_FEATURES = (
    "present",
    "high",
    "waiting",  # ticks since the task's due tick / TIME_SCALE
    "round_2",  # dropped if nobody wins it this tick (spec step 6)
    "duration",  # duration / TIME_SCALE
    "bidders",  # robots that may bid for it (idle, Lambda, zone) / COUNT_SCALES["robots"]
)
TYPE_FEATURES = (
    "queued_high",  # / COUNT_SCALES["high"]
    "queued_low",  # / COUNT_SCALES["low"]
    "queue_level_high",  # / 2
    "queue_level_low",  # / 2
    "recency_0",  # recency level of the type, one-hot
    "recency_1",
    "recency_2",
    "since_high",  # ticks since the last H arrival / TIME_SCALE (never: 1)
    "idle_robots",  # idle robots whose Lambda holds it / COUNT_SCALES["robots"]
    "soon_robots",  # idle or soon-free robots whose Lambda holds it, scaled
    "robots",  # robots whose Lambda holds it / COUNT_SCALES["team"]
)
ROBOT_TOKEN_SIZE = len(ROBOT_FEATURES)  # R
SLOT_TOKEN_SIZE = len(SLOT_FEATURES)  # S
TYPE_TOKEN_SIZE = len(TYPE_FEATURES)  # T
TIME_SCALE = 24.0  # ticks: longer than the longest default task (12) plus a recharge (10)
COUNT_SCALES = {"high": 4.0, "low": 16.0, "robots": 4.0, "team": 8.0}  # a count / scale, cut at 1


class SetInputs(NamedTuple):
    """The set network's inputs of every copy (module docstring, "Set inputs").

    Attributes:
        robots: ``[B, m, R]`` float32 robot features (:data:`ROBOT_FEATURES`).
        robot_types: ``[B, m, n]`` bool ``Lambda_i`` multi-hot (a read-only broadcast view).
        slots: ``[B, K, S]`` float32 slot features (:data:`SLOT_FEATURES`).
        slot_type: ``[B, K]`` int64 slot task types, 0 for an empty slot.
        types: ``[B, n, T]`` float32 task-type features (:data:`TYPE_FEATURES`).
    """

    robots: np.ndarray
    robot_types: np.ndarray
    slots: np.ndarray
    slot_type: np.ndarray
    types: np.ndarray


def prior_dtype(n_actions: int) -> np.dtype:
    """The smallest signed integer dtype holding every action ``0..K`` and -1 (no action).

    The dtype of a prior's action per robot as the TorchRL view writes it (``prior_action``).
    """
    for dtype in (np.int8, np.int16, np.int32):
        if n_actions - 1 <= np.iinfo(dtype).max:
            return np.dtype(dtype)
    return np.dtype(np.int64)


def _scaled(count: np.ndarray, scale: float) -> np.ndarray:
    return np.minimum(count / scale, 1.0)


def set_inputs(env: AuctionEnv) -> SetInputs:
    """The set network's inputs of the env's decision point (module docstring, "Set inputs").

    Args:
        env: The auction environment.

    Returns:
        :class:`SetInputs` of batch ``B``; widths :data:`ROBOT_TOKEN_SIZE`,
        :data:`SLOT_TOKEN_SIZE` and :data:`TYPE_TOKEN_SIZE` whatever the team.
    """
    B, m, n = env.batch_size, env.n_robots, env.n_task_types
    active = env.active_tasks  # Lambda_i, [m, n]
    active_f = active.astype(np.float32)
    t = env.t[:, None]  # [B, 1]
    idle = env.idle  # [B, m]
    free = free_level(env)  # [B, m]
    soon = free <= 1  # idle or free within FREE_SOON ticks
    counts = queue_counts(env).astype(np.float32)  # [B, n, 2]: L, H
    # robots covering each type: idle, idle or soon free, all
    idle_cover = idle.astype(np.float32) @ active_f  # [B, n]
    soon_cover = soon.astype(np.float32) @ active_f  # [B, n]

    robots = np.zeros((B, m, ROBOT_TOKEN_SIZE), np.float32)
    r = {name: k for k, name in enumerate(ROBOT_FEATURES)}
    robots[..., r["idle"]] = idle
    robots[..., r["free_soon"]] = free == 1
    robots[..., r["time_to_free"]] = _scaled(np.maximum(env.busy_until - t + 1, 0), TIME_SCALE)
    robots[..., r["battery"]] = env.battery / env.params.battery_capacity
    robots[..., r["battery_low"]] = battery_level(env)
    # a set's recency level is its types' least (the latest H arrival among them)
    type_recency = recency_level(env, _eye(n))  # [B, n]
    recency = np.where(active, type_recency[:, None], N_RECENCY_LEVELS - 1).min(-1)  # [B, m]
    np.put_along_axis(robots, (r["recency_0"] + recency)[..., None], 1.0, axis=-1)
    own = active_f @ counts  # [B, m, 2] queued per robot over Lambda_i: L, H
    robots[..., r["queued_high"]] = _scaled(own[..., 1], COUNT_SCALES["high"])
    robots[..., r["queued_low"]] = _scaled(own[..., 0], COUNT_SCALES["low"])
    robots[..., r["queue_level_high"]] = _level(own[..., 1], "H") / 2
    robots[..., r["queue_level_low"]] = _level(own[..., 0], "L") / 2
    # others covering each of robot i's types: the type's count minus robot i itself
    others_idle = np.where(active, idle_cover[:, None] - (idle[..., None] & active), np.inf)
    others_soon = np.where(active, soon_cover[:, None] - (soon[..., None] & active), np.inf)
    least_idle, least_soon = others_idle.min(-1), others_soon.min(-1)  # [B, m]
    robots[..., r["sole_idle"]] = idle & (least_idle == 0)
    robots[..., r["others_idle"]] = _scaled(least_idle, COUNT_SCALES["robots"])
    robots[..., r["others_soon"]] = _scaled(least_soon, COUNT_SCALES["robots"])
    robots[..., r["versatility"]] = active.sum(1) / n

    K = env.n_slots
    slots = np.zeros((B, K, SLOT_TOKEN_SIZE), np.float32)
    present = env.slot_type >= 0  # [B, K]
    keys = env._state["slot_keys"]  # [B, K] packed slot tasks (envs/tasks.py)
    slot_type = np.where(present, env.slot_type, 0)
    s = {name: k for k, name in enumerate(SLOT_FEATURES)}
    slots[..., s["present"]] = present
    slots[..., s["high"]] = env.slot_high == 1
    slots[..., s["waiting"]] = np.where(present, _scaled(t - task_due(keys), TIME_SCALE), 0)
    slots[..., s["round_2"]] = present & (task_round(keys) == 2)
    slots[..., s["duration"]] = np.where(present, _scaled(task_duration(keys), TIME_SCALE), 0)
    # the robots that may bid for each slot (spec step 4: idle, its type in Lambda_i, its zone)
    bidders = env.action_mask[:, :, 1:].sum(axis=1)  # [B, K], 0 for an empty slot
    slots[..., s["bidders"]] = _scaled(bidders, COUNT_SCALES["robots"])

    types = np.zeros((B, n, TYPE_TOKEN_SIZE), np.float32)
    y = {name: k for k, name in enumerate(TYPE_FEATURES)}
    types[..., y["queued_high"]] = _scaled(counts[..., 1], COUNT_SCALES["high"])
    types[..., y["queued_low"]] = _scaled(counts[..., 0], COUNT_SCALES["low"])
    types[..., y["queue_level_high"]] = _level(counts[..., 1], "H") / 2
    types[..., y["queue_level_low"]] = _level(counts[..., 0], "L") / 2
    np.put_along_axis(types, (y["recency_0"] + type_recency)[..., None], 1.0, axis=-1)
    types[..., y["since_high"]] = _scaled(t - env.last_high_arrival, TIME_SCALE)
    types[..., y["idle_robots"]] = _scaled(idle_cover, COUNT_SCALES["robots"])
    types[..., y["soon_robots"]] = _scaled(soon_cover, COUNT_SCALES["robots"])
    types[..., y["robots"]] = _scaled(active_f.sum(0), COUNT_SCALES["team"])
    robot_types = np.broadcast_to(active, (B, m, n))
    return SetInputs(robots, robot_types, slots, slot_type, types)


def _level(count: np.ndarray, priority: str) -> np.ndarray:
    """:func:`queue_level`'s levels of counts already summed over the types (0, 1 or 2)."""
    low, high = QUEUE_THRESHOLDS[priority]
    return (count > low).astype(np.float32) + (count > high)


_EYE: dict[int, np.ndarray] = {}


def _eye(n: int) -> np.ndarray:
    """``[n, n]`` bool identity: one set of types per type (cached, read every tick)."""
    if n not in _EYE:
        _EYE[n] = np.eye(n, dtype=bool)
    return _EYE[n]
