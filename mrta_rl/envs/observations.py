"""Finite observation encodings of an ``AuctionEnv`` (spec ``auction_env.md``, "Observations").

Every encoding below is a finite mixed-radix integer (for tabular learners) or a fixed-width
float32 one-hot vector (for neural nets), computed from the env's public arrays for all ``B``
copies at once. The counts are exact, so the learning space dimension (paper eqs 10-16) is
``|S| x |A|`` with ``|S|`` from here and ``|A| = K + 1`` per robot. Notation: ``m`` robots,
``n`` task types, ``K`` slots, ``Lambda_i`` the active task types of robot ``i``.

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

Neural features:
    * :func:`local_features` ``[B, m, F]`` with ``F = 1 + K (1 + 2n) + 1 + 3 + m``: idle bit; per
      slot a one-hot over ``1 + 2n`` codes (``1 + 2 type + high`` over *all* types, so robots share
      one layout, but 0 where the type is not in ``Lambda_i``, as in the local view); battery-low
      bit; recency one-hot (3); robot-id one-hot (m).
    * :func:`global_features` ``[B, G]`` with ``G = K (1 + 2n) + m + m + 3n``: per slot a one-hot
      over ``1 + 2n`` codes; idle bits; battery-low bits; per task type a recency one-hot (3).
"""

from __future__ import annotations

import weakref
from collections.abc import Sequence

import numpy as np

from mrta_rl.envs.auction import AuctionEnv

RECENCY_THRESHOLDS: tuple[int, int] = (3, 10)  # recency level 0: delta <= 3, 1: delta <= 10, else 2
N_RECENCY_LEVELS = 3
N_BATTERY_LEVELS = 2
N_ROBOT_STATES = 3  # group view: busy / idle ok battery / idle low battery
_NEVER = np.iinfo(np.int64).min // 4  # "no H arrival" sentinel, far below any tick

__all__ = [
    "GroupView",
    "LocalView",
    "N_RECENCY_LEVELS",
    "RECENCY_THRESHOLDS",
    "battery_level",
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


_LONGEST: weakref.WeakKeyDictionary[AuctionEnv, np.ndarray] = weakref.WeakKeyDictionary()


def battery_level(env: AuctionEnv) -> np.ndarray:
    """Coarse battery level per robot (module docstring).

    Args:
        env: The auction environment.

    Returns:
        ``[B, m]`` int64 in {0, 1}; 1 = low, the next task may send the robot to charge.
    """
    longest = _LONGEST.get(env)
    if longest is None:
        longest = _LONGEST[env] = _longest_durations(env)
    p = env.params
    return (env.battery - p.drain_per_tick * longest < p.battery_threshold).astype(np.int64)


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
    arrivals = env.last_high_arrival  # [B, n]
    if types_mask.ndim == 1:
        last = np.where(types_mask, arrivals, _NEVER).max(axis=-1)  # [B]
        delta = env.t - last
    else:
        last = np.where(types_mask[None], arrivals[:, None, :], _NEVER).max(axis=-1)  # [B, m']
        delta = env.t[:, None] - last
    return (delta > RECENCY_THRESHOLDS[0]).astype(np.int64) + (delta > RECENCY_THRESHOLDS[1])


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
    """

    def __init__(self, env: AuctionEnv) -> None:
        m, n, K = env.n_robots, env.n_task_types, env.n_slots
        active = env.active_tasks  # Lambda_i, [m, n]
        self.n_active = active.sum(axis=1)  # |Lambda_i|, [m]
        rank = np.cumsum(active, axis=1) - 1  # rank of each type within Lambda_i, [m, n]
        # slot code per (robot, type + empty row, high): 1 + 2 rank + high if the type is active
        codes = np.zeros((m, n + 1, 2), np.int64)  # row n answers slot_type -1 (empty)
        codes[:, :n, :] = np.where(active[:, :, None], 1 + 2 * rank[:, :, None] + np.arange(2), 0)
        self._codes = codes.transpose(1, 2, 0).copy()  # [n + 1, 2, m] for [B, K, m] lookups
        slot_radix = 1 + 2 * self.n_active  # [m]
        radices = np.column_stack(
            [np.full(m, 2), *([slot_radix] * K), np.full(m, N_BATTERY_LEVELS), np.full(m, 3)]
        )
        self.counts = [int(np.prod([int(r) for r in row], dtype=object)) for row in radices]
        if max(self.counts) >= 2**63:
            raise OverflowError(f"local state count {max(self.counts)} does not fit in int64")
        self.radices = radices  # [m, K + 3]
        self._places = _places(radices)  # [m, K + 3]
        self._slot_places = self._places[:, 1 : K + 1].T.copy()  # [K, m]
        self._active = active

    def index(self, env: AuctionEnv) -> np.ndarray:
        """``[B, m]`` int64 local state indices, each in ``[0, counts[i])``."""
        high = np.maximum(env.slot_high, 0)  # [B, K]; empty slots use row -1 whatever high is
        codes = self._codes[env.slot_type, high]  # [B, K, m]
        index = env.idle.astype(np.int64) + (codes * self._slot_places).sum(axis=1)  # [B, m]
        index += battery_level(env) * self._places[:, -2]
        index += recency_level(env, self._active) * self._places[:, -1]
        return index

    def decode(self, robot: int, index: int) -> dict[str, object]:
        """Fields of one robot's local index: ``idle``, ``slots``, ``battery``, ``recency``."""
        d = _decode(index, self.radices[robot])
        return {"idle": d[0], "slots": d[1:-2], "battery": d[-2], "recency": d[-1]}


class GroupView:
    """Group state index of some robots (module docstring), with tables precomputed for one env.

    Args:
        env: The auction environment.
        robots: Robot indices (or ids such as ``"R2"``) of the group, in the order of its digits.

    Raises:
        ValueError: on an empty group or an unknown robot.
    """

    def __init__(self, env: AuctionEnv, robots: Sequence[int | str]) -> None:
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
        self.radices = [1 + 2 * self.n_types] * K + [N_ROBOT_STATES] * len(ids) + [N_RECENCY_LEVELS]
        self.count = int(np.prod(self.radices, dtype=object))  # exact Python int
        self.fits_int64 = self.count < 2**63
        if self.fits_int64:
            places = _places(np.array(self.radices, np.int64))
            self._slot_places = places[:K]  # [K]
            self._robot_places = places[K:-1]  # [m_g]
            self._recency_place = int(places[-1])

    def index(self, env: AuctionEnv) -> np.ndarray:
        """``[B]`` int64 group state indices in ``[0, count)``.

        Raises:
            OverflowError: if :attr:`count` does not fit in int64 (use a smaller group).
        """
        if not self.fits_int64:
            raise OverflowError(
                f"group state count {self.count} >= 2**63: too many robots or types for one index"
            )
        high = np.maximum(env.slot_high, 0)
        index = self._codes[env.slot_type, high] @ self._slot_places  # [B]
        idle = env.idle[:, self.robots]  # [B, m_g]
        state = idle * (1 + battery_level(env)[:, self.robots])  # 0 busy, 1 idle ok, 2 idle low
        index += state @ self._robot_places
        index += recency_level(env, self.types_mask) * self._recency_place
        return index

    def decode(self, index: int) -> dict[str, list[int] | int]:
        """Fields of a group state index: ``slots`` (K), ``robots`` (m_g states), ``recency``."""
        digits = _decode(index, self.radices)
        K = len(self.radices) - len(self.robots) - 1
        return {"slots": digits[:K], "robots": digits[K:-1], "recency": digits[-1]}


# One precomputed view per env (and per group), so the per-tick functions only index tables.
_LOCAL: weakref.WeakKeyDictionary[AuctionEnv, LocalView] = weakref.WeakKeyDictionary()
_GroupViews = dict[tuple[int, ...], GroupView]
_GROUP: weakref.WeakKeyDictionary[AuctionEnv, _GroupViews] = weakref.WeakKeyDictionary()


def _local_view(env: AuctionEnv) -> LocalView:
    view = _LOCAL.get(env)
    if view is None:
        view = _LOCAL[env] = LocalView(env)
    return view


def _group_view(env: AuctionEnv, robots: Sequence[int | str]) -> GroupView:
    key = tuple(env.system.robots.index(r) if isinstance(r, str) else int(r) for r in robots)
    views = _GROUP.setdefault(env, {})
    if key not in views:
        views[key] = GroupView(env, key)
    return views[key]


def local_state_index(env: AuctionEnv) -> np.ndarray:
    """Local state index of every robot (module docstring).

    Args:
        env: The auction environment.

    Returns:
        ``[B, m]`` int64, robot ``i``'s index in ``[0, local_state_count(env)[i])``.
    """
    return _local_view(env).index(env)


def local_state_count(env: AuctionEnv) -> list[int]:
    """``[m]`` Python ints: ``|S_i| = 2 (1 + 2 |Lambda_i|)^K 2 * 3`` (paper eq. 10's ``|S_i|``)."""
    return list(_local_view(env).counts)


def group_state_index(env: AuctionEnv, robots: Sequence[int | str]) -> np.ndarray:
    """Group state index of the given robots (module docstring).

    Args:
        env: The auction environment.
        robots: Robot indices (or ids) of the group.

    Returns:
        ``[B]`` int64 in ``[0, group_state_count(env, robots))``.

    Raises:
        OverflowError: if the count does not fit in int64.
    """
    return _group_view(env, robots).index(env)


def group_state_count(env: AuctionEnv, robots: Sequence[int | str]) -> int:
    """Exact ``|S_g| = (1 + 2 |T_g|)^K 3^{m_g} 3`` as a Python int (paper eqs 13, 16)."""
    return _group_view(env, robots).count


def local_feature_size(env: AuctionEnv) -> int:
    """``F = 1 + K (1 + 2n) + 1 + 3 + m``, the last dimension of :func:`local_features`."""
    return 1 + env.n_slots * (1 + 2 * env.n_task_types) + 1 + N_RECENCY_LEVELS + env.n_robots


def global_feature_size(env: AuctionEnv) -> int:
    """``G = K (1 + 2n) + 2m + 3n``, the last dimension of :func:`global_features`."""
    n = env.n_task_types
    return env.n_slots * (1 + 2 * n) + 2 * env.n_robots + N_RECENCY_LEVELS * n


def _slot_codes(env: AuctionEnv) -> np.ndarray:
    """``[B, K]`` global slot codes: 0 empty, else ``1 + 2 type + high``."""
    return np.where(env.slot_type >= 0, 1 + 2 * env.slot_type + env.slot_high, 0)


def local_features(env: AuctionEnv) -> np.ndarray:
    """One-hot local view of every robot, for neural nets (layout in the module docstring).

    Args:
        env: The auction environment.

    Returns:
        ``[B, m, F]`` float32, ``F = local_feature_size(env)``.
    """
    B, m, K, n = env.batch_size, env.n_robots, env.n_slots, env.n_task_types
    n_codes = 1 + 2 * n
    codes = _slot_codes(env)  # [B, K]
    # as in the local view, a robot sees only the slots it may bid for (spec step 4: Lambda_i)
    # (an empty slot indexes row -1, a real type, but its code is 0 anyway)
    visible = env.active_tasks.T[env.slot_type] & (codes > 0)[:, :, None]  # [B, K, m]
    local_codes = np.where(visible, codes[:, :, None], 0).transpose(0, 2, 1)  # [B, m, K]
    at = local_feature_layout(K, n)
    out = np.zeros((B, m, local_feature_size(env)), np.float32)
    out[..., at["idle"].start] = env.idle
    slot_block = out[..., at["slots"]].reshape(B, m, K, n_codes)
    np.put_along_axis(slot_block, local_codes[..., None], 1.0, axis=-1)
    out[..., at["slots"]] = slot_block.reshape(B, m, K * n_codes)
    out[..., at["battery"].start] = battery_level(env)
    recency = recency_level(env, env.active_tasks)  # [B, m]
    np.put_along_axis(out, (at["recency"].start + recency)[..., None], 1.0, axis=-1)
    out[:, np.arange(m), at["robot"].start + np.arange(m)] = 1.0  # robot id one-hot
    return out


def local_feature_layout(n_slots: int, n_task_types: int) -> dict[str, slice]:
    """Where the parts of :func:`local_features` sit on the feature axis (module docstring).

    Args:
        n_slots: ``K``.
        n_task_types: ``n``.

    Returns:
        ``{"idle", "slots", "battery", "recency", "robot"}`` -> slice; ``"slots"`` holds ``K``
        one-hots of ``1 + 2n`` codes (code ``1 + 2 type + high``), ``"recency"`` the 3 levels.
    """
    slots_end = 1 + n_slots * (1 + 2 * n_task_types)
    recency_end = slots_end + 1 + N_RECENCY_LEVELS
    return {
        "idle": slice(0, 1),
        "slots": slice(1, slots_end),
        "battery": slice(slots_end, slots_end + 1),
        "recency": slice(slots_end + 1, recency_end),
        "robot": slice(recency_end, None),
    }


def global_features(env: AuctionEnv) -> np.ndarray:
    """One-hot global state, for centralized critics and mixers (layout in the module docstring).

    Args:
        env: The auction environment.

    Returns:
        ``[B, G]`` float32, ``G = global_feature_size(env)``.
    """
    B, m, K, n = env.batch_size, env.n_robots, env.n_slots, env.n_task_types
    n_codes = 1 + 2 * n
    out = np.zeros((B, global_feature_size(env)), np.float32)
    slots = np.zeros((B, K, n_codes), np.float32)
    np.put_along_axis(slots, _slot_codes(env)[..., None], 1.0, axis=-1)
    out[:, : K * n_codes] = slots.reshape(B, K * n_codes)
    base = K * n_codes
    out[:, base : base + m] = env.idle
    out[:, base + m : base + 2 * m] = battery_level(env)
    recency = recency_level(env, np.eye(n, dtype=bool))  # [B, n], one level per task type
    rec = np.zeros((B, n, N_RECENCY_LEVELS), np.float32)
    np.put_along_axis(rec, recency[..., None], 1.0, axis=-1)
    out[:, base + 2 * m :] = rec.reshape(B, n * N_RECENCY_LEVELS)
    return out
