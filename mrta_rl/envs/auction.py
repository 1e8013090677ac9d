"""The auction dynamics of ``docs/spec/auction_env.md``, batched over ``B`` copies (numpy).

This module is THE dynamics: every learner, view (TorchRL, PettingZoo, Gymnasium) and metric runs
on :class:`AuctionEnv`. It is plain vectorised numpy over ``[B, ...]`` arrays with no Python loop
over copies: at batch size 1 a numpy op costs about 0.7 us against 1.7 us for a torch op, and at
large batches numpy's row sort is several times faster than torch's on CPU. The TorchRL adapter
wraps these arrays zero-copy with ``torch.from_numpy``.

Design notes:
- **Tasks are packed int64 keys.** A queued task is one non-negative int64 whose high bits are the
  spec's queue order (H before L, due tick, id) and whose low bits carry type, duration and round,
  so one ``np.sort`` per tick orders the queue (spec step 2) and an empty place is ``EMPTY``.
- **Counter-based randomness.** Every random number is a hash of (copy seed, episode number, tick,
  draw index), never a shared generator's stream. A copy's episode therefore depends only on its
  own seed and actions, not on the batch size or on when other copies reset, and a plain scalar
  implementation drawing the same hashes reproduces it exactly (see ``tests/unit``).
- **A tick is split at the decision.** ``reset`` and the end of ``step`` run spec steps 1-3 of the
  next tick (arrivals, queue order, slots) so that the caller sees the slots it decides on;
  ``step(actions)`` runs steps 4-8. Drops from step 2 (overflow) are paid in the reward of that
  same tick, returned by the following ``step``.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

import numpy as np

from mrta_rl.envs import counter_rng as rng
from mrta_rl.envs.params import AuctionParams
from mrta_rl.envs.tasks import (
    DUE_BITS,
    DUE_FIELD,
    DUE_SHIFT,
    DURATION_BITS,
    EMPTY,
    ID_BITS,
    TYPE_BITS,
    pack_tasks,
    task_due,
    task_duration,
    task_high,
    task_id,
    task_round,
    task_type,
    to_second_round,
)
from mrta_rl.systems import RobotSystem

_ONE = np.uint64(1)
_BITMASK_ROWS = sys.byteorder == "little"  # 8 packed bytes read as one uint64


def _first_true_positions(flags: np.ndarray, k: int, buffer: np.ndarray) -> np.ndarray:
    """Positions of the first ``k`` True places of each row of ``flags`` ``[B, w<=64]``; 64: none.

    Each row becomes one uint64 bitmask, and the lowest set bit is peeled off ``k`` times: a few
    ``[B]`` operations instead of a reduction over a short last axis, which numpy does slowly.
    """
    packed = np.packbits(flags, axis=1, bitorder="little")  # [B, ceil(w / 8)]
    buffer[:, : packed.shape[1]] = packed
    buffer[:, packed.shape[1] :] = 0
    bits = buffer.view(np.uint64)[:, 0].copy()  # [B]
    positions = np.empty((flags.shape[0], k), np.int64)
    for j in range(k):
        lowest = bits & (~bits + _ONE)  # isolates the lowest set bit (0 if none)
        positions[:, j] = np.bitwise_count(lowest - _ONE)  # its index; 64 when bits == 0
        bits &= bits - _ONE
    return positions


def _occupied_width(queue: np.ndarray) -> int:
    """Number of leading columns holding a task in some row of a row-sorted queue (empties last).

    A binary search over columns: each probe reads one column, instead of counting every place.
    """
    lo, hi = 0, queue.shape[1]  # the width lies in [lo, hi]
    while lo < hi:
        mid = (lo + hi) // 2
        if (queue[:, mid] != EMPTY).any():
            lo = mid + 1
        else:
            hi = mid
    return lo


@dataclass
class EpisodeStats:
    """Per-copy counters of the current episode, the input of ``mrta_rl.metrics``.

    Attributes:
        assigned: ``[B, n, 2]`` tasks assigned per type and priority (index 0 = L, 1 = H).
        dropped: ``[B, n, 2]`` tasks dropped per type and priority (spec steps 2 and 6).
        busy_ticks: ``[B, m]`` ticks each robot was busy (spec step 7).
        team_return: ``[B]`` sum of team rewards.
        ticks: ``[B]`` ticks played so far.
    """

    assigned: np.ndarray
    dropped: np.ndarray
    busy_ticks: np.ndarray
    team_return: np.ndarray
    ticks: np.ndarray

    def copy(self) -> EpisodeStats:
        """An independent snapshot."""
        return EpisodeStats(*(np.array(getattr(self, f)) for f in self.__dataclass_fields__))


class StepResult:
    """One tick's outcome: ``team_reward`` ``[B]``, ``robot_reward`` ``[B, m]``, ``done`` ``[B]``.

    Individual rewards (spec step 8) are computed on first access: learners that use only the
    team reward never pay for sharing drop penalties among robots.
    """

    __slots__ = ("team_reward", "done", "_assign", "_type_penalty", "_share", "_robot_reward")

    def __init__(self, team_reward, done, assign, type_penalty, share) -> None:
        self.team_reward, self.done = team_reward, done
        self._assign, self._type_penalty, self._share = assign, type_penalty, share
        self._robot_reward = None

    @property
    def robot_reward(self) -> np.ndarray:
        """``[B, m]``: the assign reward a robot won minus its shares of drop penalties."""
        if self._robot_reward is None:
            self._robot_reward = self._assign - self._type_penalty @ self._share
        return self._robot_reward


class AuctionEnv:
    """Batched auction environment (spec ``auction_env.md``), ``B`` independent copies.

    Description:
        Tasks of ``n`` types and two priorities arrive at random, wait in a queue and are auctioned
        in up to ``K`` slots per tick; idle robots wait or bid, the most willing bidder wins and is
        busy while it executes (and charges). See the spec for every rule; comments below cite it.

    Action Space:
        ``[B, m]`` ints: 0 = wait, ``k`` in 1..K = bid for slot ``k``. :attr:`action_mask`
        (``[B, m, K + 1]`` bool) marks the valid ones (spec step 4); others raise ``ValueError``.

    Observation Space:
        Raw state arrays (:attr:`slot_type`, :attr:`slot_high`, :attr:`idle`, :attr:`battery`,
        :attr:`last_high_arrival`, :attr:`t`); ``mrta_rl.envs.observations`` encodes them.

    Reward:
        Team reward ``[B]`` and individual rewards ``[B, m]`` (spec step 8); they sum to the team's.

    Episode End:
        Truncation after ``horizon`` ticks; call :meth:`reset` (all or some copies) to restart.

    Arguments:
        system: The robot team.
        params: Dynamics parameters (default: spec defaults plus the system file's ``env:`` block).
        batch_size: Number of copies ``B``.
        active_tasks: ``[m, n]`` bool ``Lambda_i`` (default ``Gamma_i``); subG-CQL removes types.
        seed: Copy ``b`` is seeded with ``seed + b``.
    """

    def __init__(
        self,
        system: RobotSystem,
        params: AuctionParams | None = None,
        batch_size: int = 1,
        active_tasks: np.ndarray | None = None,
        seed: int = 0,
    ) -> None:
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        self.system = system
        self.params = (params or AuctionParams.merged(system.env_overrides)).resolve(
            system.n_robots
        )
        p = self.params
        self.batch_size = batch_size
        self.n_robots, self.n_task_types = system.n_robots, system.n_task_types
        self.n_slots = p.slots  # K
        self.n_actions = p.slots + 1  # wait + one bid per slot
        capable = system.willingness > 0
        active = capable if active_tasks is None else np.asarray(active_tasks, dtype=bool)
        if active.shape != capable.shape:
            raise ValueError(f"active_tasks has shape {active.shape}, expected {capable.shape}")
        for i, j in zip(*np.nonzero(active & ~capable), strict=True):
            raise ValueError(
                f"active_tasks: robot {system.robots[i]} cannot do {system.task_types[j]}"
            )
        for j in np.flatnonzero(~active.any(axis=0)):
            raise ValueError(f"active_tasks: task type {system.task_types[j]} has no robot left")
        self.active_tasks = active  # Lambda_i, [m, n]
        self.copy_offset = 0  # index of copy 0 in a larger batch (ThreadedAuctionEnv), for errors
        self._check_limits()

        # per (type, priority) duration ranges: system file overrides, else the params' defaults
        self._dur_lo = np.zeros((self.n_task_types, 2), np.int64)
        self._dur_span = np.zeros((self.n_task_types, 2), np.int64)
        for j, name in enumerate(system.task_types):
            for prio, key in enumerate(("duration_low", "duration_high")):
                override = system.durations.get(name, {}).get(key)
                lo, hi = (override.lo, override.hi) if override is not None else getattr(p, key)
                self._dur_lo[j, prio], self._dur_span[j, prio] = lo, hi - lo + 1
        # flat tables, indexed by 2 * type + high
        self._dur_lo, self._dur_span = self._dur_lo.reshape(-1), self._dur_span.reshape(-1)
        self._assign_reward = np.array([p.reward_assign_low, p.reward_assign_high])
        self._drop_penalty = np.array([p.penalty_drop_low, p.penalty_drop_high])
        # Lookup tables [n + 1, m] by slot type; the extra last row answers type -1, an empty slot.
        # spec step 8: a dropped task's penalty is shared by the robots whose Lambda holds its type
        no_robot = np.zeros(self.n_robots)
        self._penalty_share = np.vstack([(active / active.sum(axis=0)).T, no_robot])
        self._willingness_by_type = np.vstack([system.willingness.T, no_robot])
        self._uniform_willingness = np.ptp(system.willingness[capable]) == 0
        self._can_do_by_type = np.vstack([active.T, np.zeros(self.n_robots, bool)])  # [n+1, m]
        self._poisson_cdf = rng.poisson_cdf(p.arrival_rate)

        B, m, n, K, Q = batch_size, self.n_robots, self.n_task_types, self.n_slots, p.queue_capacity
        self._seeds = np.zeros(B, np.uint64)
        self._episode = np.zeros(B, np.uint64)
        self._episode_key = np.zeros(B, np.uint64)
        self.t = np.zeros(B, np.int64)  # current tick per copy
        self._queue = np.full((B, Q + 1), EMPTY)  # column Q is scratch, always empty
        self._queue_width = 0  # no copy holds more than this many tasks
        # flat index of each row's first place
        self._queue_row_offsets = np.arange(B)[:, None] * (Q + 1)
        self._next_id = np.zeros(B, np.int64)
        self.busy_until = np.full((B, m), -1, np.int64)
        self.battery = np.full((B, m), float(p.battery_capacity))
        # tick of the last H arrival per type; far in the past until one arrives
        self.last_high_arrival = np.full((B, n), -(1 << 30), np.int64)
        self.done = np.zeros(B, bool)
        self._pending_type_penalty = np.zeros((B, n))  # [B, n], shared among robots lazily
        self.stats = EpisodeStats(
            np.zeros((B, n, 2), np.int64),
            np.zeros((B, n, 2), np.int64),
            np.zeros((B, m), np.int64),
            np.zeros(B),
            np.zeros(B, np.int64),
        )
        self._slot_pos = np.full((B, K), Q, np.int64)
        self._slot_numbers = np.arange(1, K + 1)[None, :, None]  # [1, K, 1]
        self._bit_buffer = np.zeros((B, 8), np.uint8)  # one uint64 bitmask per copy
        self._action_row_offsets = np.arange(B)[:, None] * (K + 1)  # flat (copy, action) index
        # valid actions are stored action-major, [B, K + 1, m], so per-action slices are contiguous
        self._mask_by_action = np.ones((B, K + 1, m), bool)
        # flat index of (b, 0, i) in that layout
        self._mask_offsets = np.arange(B)[:, None] * ((K + 1) * m) + np.arange(m)
        self.seed(seed)
        self.reset()

    def _check_limits(self) -> None:
        p = self.params
        limits = {
            "horizon + reauction_delay": (p.horizon + p.reauction_delay, 1 << DUE_BITS),
            "number of task types": (self.n_task_types, 1 << TYPE_BITS),
            "longest duration": (
                max(
                    p.duration_low[1],
                    p.duration_high[1],
                    *(r.hi for d in self.system.durations.values() for r in d.values()),
                ),
                1 << DURATION_BITS,
            ),
            "expected tasks per episode x 4": (4 * p.arrival_rate * p.horizon, 1 << ID_BITS),
            "slots + 1 (actions fit in int8)": (p.slots + 1, 128),
        }
        for what, (value, limit) in limits.items():
            if value >= limit:
                raise ValueError(f"{what} = {value} exceeds the environment's limit {limit - 1}")

    # ------------------------------------------------------------------ seeding and reset
    def seed(self, seed: int | np.ndarray) -> None:
        """Seed the copies: an int gives copy ``b`` the seed ``seed + b``; or one per copy."""
        seeds = np.asarray(seed, dtype=np.int64)
        if seeds.ndim == 0:
            seeds = seeds + np.arange(self.batch_size)
        if seeds.shape != (self.batch_size,):
            raise ValueError(
                f"expected one seed or {self.batch_size} seeds, got shape {seeds.shape}"
            )
        self._seeds = rng.seed_keys(seeds)
        self._episode[:] = 0

    def reset(self, mask: np.ndarray | None = None, seed: int | np.ndarray | None = None) -> None:
        """Start a new episode in all copies, or in those where ``mask`` is True (partial reset).

        Args:
            mask: ``[B]`` bool, copies to reset (default: all).
            seed: Optional reseeding (see :meth:`seed`), applied before the reset.
        """
        if seed is not None:
            self.seed(seed)
        # a copy: the caller may pass self.done itself, which this method overwrites
        rows = np.ones(self.batch_size, bool) if mask is None else np.array(mask, bool)
        self._episode_key[rows] = rng.episode_keys(self._seeds[rows], self._episode[rows])
        self._episode[rows] += np.uint64(1)
        self.t[rows] = 0
        self._queue[rows] = EMPTY
        self._next_id[rows] = 0
        self.busy_until[rows] = -1
        self.battery[rows] = self.params.battery_capacity
        self.last_high_arrival[rows] = -(1 << 30)
        self.done[rows] = False
        for counter in (
            self.stats.assigned,
            self.stats.dropped,
            self.stats.busy_ticks,
            self.stats.team_return,
            self.stats.ticks,
        ):
            counter[rows] = 0
        self._pending_type_penalty[rows] = 0.0
        self._begin_tick(rows)

    # ------------------------------------------------------------------ spec steps 1-3
    def _begin_tick(self, rows: np.ndarray) -> None:
        """Spec steps 1-3 of tick ``t`` for ``rows``; other copies keep their slots (idempotent)."""
        p, t, Q = self.params, self.t, self.params.queue_capacity
        # spec step 1: N ~ Poisson(arrival_rate) new tasks, one hash per copy and tick
        tick_key = rng.tick_keys(self._episode_key, t)  # [B]
        n_new = np.searchsorted(self._poisson_cdf, rng.unit_float(tick_key), side="right")
        n_new[~rows] = 0
        width = int(n_new.max())
        self._pending_type_penalty[rows] = 0.0
        end = self._queue_width + width
        if end > self._queue.shape[1] - 1:  # grow the spare columns (the last one stays empty)
            grow = np.full((self.batch_size, end + 1 - self._queue.shape[1] + 8), EMPTY)
            self._queue = np.concatenate([self._queue, grow], axis=1)
            self._queue_row_offsets = np.arange(self.batch_size)[:, None] * self._queue.shape[1]
        if width:
            h_prio, h_kind = rng.task_hashes(tick_key, width)  # [B, W] each
            # priority H with probability p_high; type uniform over all n types (high 32 bits of
            # h_kind); duration uniform over the type's range, ends included (low 32 bits)
            high = (rng.unit_float(h_prio) < p.p_high).astype(np.int64)
            ttype = rng.bounded_int(rng.high_bits(h_kind), self.n_task_types)
            kind = 2 * ttype + high
            duration = self._dur_lo[kind] + rng.bounded_int(h_kind, self._dur_span[kind])
            arrived = np.arange(width) < n_new[:, None]  # [B, W]
            ids = self._next_id[:, None] + np.arange(width)
            new = np.where(arrived, pack_tasks(high, t[:, None], ids, ttype, duration, 0), EMPTY)
            self._next_id += n_new
            b_h, k_h = np.nonzero(arrived & (high == 1))
            self.last_high_arrival[b_h, ttype[b_h, k_h]] = t[b_h]
            self._queue[:, self._queue_width : end] = new  # places past the width are empty
        queue = self._queue[:, :end]
        queue.sort(axis=1)  # spec step 2: (H before L, due tick, id); empties last
        if end > Q:  # spec step 2: overflow drops the last tasks
            overflow = queue[:, Q:end]
            if (overflow != EMPTY).any():
                self._pending_type_penalty += self._drop(overflow)
                overflow[:] = EMPTY
        self._queue_width = _occupied_width(queue[:, : min(end, Q)])
        self._select_slots()

    def _select_slots(self) -> None:
        """Spec step 3: the first K queued tasks due by now, in queue order, fill slots 1..K."""
        Q = self.params.queue_capacity
        # Only round-2 tasks can be due later than now, and at most K of them enter per tick for
        # reauction_delay ticks, so the first K eligible tasks lie within K * (delay + 1) places.
        width = min(self._queue_width, self.n_slots * (self.params.reauction_delay + 1))
        queue = self._queue[:, :width]
        # EMPTY's due field is all ones, later than any tick (see _check_limits): no separate test
        due_now = (queue & DUE_FIELD) <= (self.t << DUE_SHIFT)[:, None]  # [B, width]
        if self.done.any():
            due_now &= ~self.done[:, None]
        if width <= 64 and _BITMASK_ROWS:
            pos = _first_true_positions(due_now, self.n_slots, self._bit_buffer)
        else:  # the k-th due task sits where the running count first reaches k
            count = np.cumsum(due_now, axis=1)
            pos = (count[:, None, :] < self._slot_numbers[:, :, 0, None]).sum(axis=2)
        self._slot_pos = np.where(pos < width, pos, Q)  # [B, K]; Q = the always-empty place
        keys = self._queue.reshape(-1)[self._slot_pos + self._queue_row_offsets]  # [B, K]
        self._slot_keys = keys
        filled = keys != EMPTY
        self.slot_type = np.where(filled, task_type(keys), -1)  # [B, K], -1 = empty slot
        self.slot_high = np.where(filled, task_high(keys), -1)  # [B, K], 1 = H, 0 = L, -1 = empty
        self.idle = self.t[:, None] > self.busy_until  # spec step 4, [B, m]
        # spec step 4: a bid for slot k is valid if the robot is idle and may do the slot's type
        can_do = self._can_do_by_type[self.slot_type]  # [B, K, m]; row -1 (empty slot) is all False
        # a fresh array every tick: callers may keep the last one
        mask = np.empty((self.batch_size, self.n_actions, self.n_robots), bool)
        mask[:, 0] = True  # waiting is always valid
        np.logical_and(can_do, self.idle[:, None, :], out=mask[:, 1:, :])
        self._mask_by_action = mask

    # ------------------------------------------------------------------ spec steps 4-8
    def step(self, actions: np.ndarray, *, validated: bool = False) -> StepResult:
        """Play spec steps 4-8 of the current tick in every copy, then steps 1-3 of the next.

        Args:
            actions: ``[B, m]`` ints, 0 = wait, k = bid for slot k.
            validated: The caller has already run :meth:`validate` on these actions.

        Returns:
            Team and individual rewards of the tick and the done flags.

        Raises:
            ValueError: on a wrong shape, an invalid action (naming copy, robot and reason), or a
                copy whose episode has ended and was not reset.
        """
        actions = np.asarray(actions)
        if not validated:
            self.validate(actions)
        p, t = self.params, self.t
        # spec step 8 counts this tick's overflow drops (spec step 2)
        team = -self._pending_type_penalty.sum(axis=1)
        type_penalty = self._pending_type_penalty.copy()  # [B, n]
        robot = np.zeros((self.batch_size, self.n_robots))  # assign rewards won
        keys, slot_type, slot_high = self._slot_keys, self.slot_type, self.slot_high
        # spec step 5: each robot bids for at most one slot, so all slots are settled at once.
        # Per slot, the highest willingness wins; argmax takes the first maximum, so ties go to the
        # lowest robot index.
        bid_counts = np.bincount(
            (actions + self._action_row_offsets).ravel(), minlength=self.batch_size * self.n_actions
        )
        assigned = bid_counts.reshape(self.batch_size, self.n_actions)[:, 1:] > 0  # [B, K]
        b, k = np.nonzero(assigned)
        if len(b):
            bids = (
                actions.astype(np.int8)[b] == (k + 1)[:, None]
            )  # [P, m] bidders of each auctioned slot
            if self._uniform_willingness:  # all d equal: the lowest-index bidder wins
                w = bids.argmax(axis=1)
            else:
                w = np.where(bids, self._willingness_by_type[slot_type[b, k]], -1.0).argmax(axis=1)
            duration = task_duration(keys[b, k])
            busy_until = t[b] + duration  # executes during ticks t+1 .. t+duration
            battery = self.battery[b, w] - p.drain_per_tick * duration
            charge = battery < p.battery_threshold  # charges right after the task, then is full
            self.busy_until[b, w] = busy_until + np.where(charge, p.charge_ticks, 0)
            self.battery[b, w] = np.where(charge, p.battery_capacity, battery)
            high = slot_high[b, k]
            reward = self._assign_reward[high]
            robot[b, w] += reward
            np.add.at(team, b, reward)
            np.add.at(self.stats.assigned, (b, slot_type[b, k], high), 1)
        # spec step 6: unassigned slot tasks go to round 2 (due t + delay); in round 2, are dropped
        unassigned = (keys != EMPTY) & ~assigned
        round2 = task_round(keys) == 2
        reauction = unassigned & ~round2
        rekeyed = to_second_round(keys, t[:, None] + p.reauction_delay)
        self._queue.reshape(-1)[self._slot_pos + self._queue_row_offsets] = np.where(
            reauction, rekeyed, EMPTY
        )
        dropped = unassigned & round2
        if dropped.any():
            b, k = np.nonzero(dropped)
            ttype, high = slot_type[b, k], slot_high[b, k]
            penalty = self._drop_penalty[high]
            np.add.at(self.stats.dropped, (b, ttype, high), 1)
            np.add.at(type_penalty, (b, ttype), penalty)
            np.subtract.at(team, b, penalty)
        # spec step 7: busy if not idle at step 4, or if it bid (the auction takes its time)
        self.stats.busy_ticks += ~self.idle | (actions > 0)
        self.stats.team_return += team
        self.stats.ticks += 1
        self.t += 1
        self.done = self.t >= p.horizon
        self._begin_tick(~self.done)
        return StepResult(team, self.done.copy(), robot, type_penalty, self._penalty_share[:-1])

    def validate(self, actions: np.ndarray) -> None:
        """Check a joint action against shape, episode end and the action mask (spec step 4).

        Raises:
            ValueError: naming the copy, the robot and the reason.
        """
        if actions.shape != (self.batch_size, self.n_robots):
            raise ValueError(
                f"actions must have shape (B, m) = {(self.batch_size, self.n_robots)}, "
                f"got {actions.shape}"
            )
        if self.done.any():
            raise ValueError(
                f"copy {int(np.flatnonzero(self.done)[0]) + self.copy_offset} has finished its "
                "episode; reset it first"
            )
        in_range = (actions >= 0) & (actions < self.n_actions)
        flat = self._mask_offsets + np.where(in_range, actions, 0) * self.n_robots
        valid = in_range & self._mask_by_action.reshape(-1)[flat]
        if not valid.all():
            b, i = (int(x[0]) for x in np.nonzero(~valid))
            a, robot = int(actions[b, i]), self.system.robots[i]
            if not in_range[b, i]:
                why = f"actions are 0..{self.n_slots}"
            elif not self.idle[b, i]:
                why = f"{robot} is busy until tick {self.busy_until[b, i]}"
            elif self.slot_type[b, a - 1] < 0:
                why = f"slot {a} is empty"
            else:
                why = f"{robot} may not do {self.system.task_types[self.slot_type[b, a - 1]]}"
            raise ValueError(
                f"invalid action {a} for robot {robot} in copy {b + self.copy_offset} "
                f"at tick {self.t[b]}: {why}"
            )

    def _drop(self, keys: np.ndarray) -> np.ndarray:
        """Count dropped tasks (``keys`` ``[B, W]``, ``EMPTY``: none); penalties ``[B, n]``."""
        b, k = np.nonzero(keys != EMPTY)
        dropped_keys = keys[b, k]
        ttype, high = task_type(dropped_keys), task_high(dropped_keys)
        np.add.at(self.stats.dropped, (b, ttype, high), 1)
        penalty = np.zeros((self.batch_size, self.n_task_types))  # [B, n]
        np.add.at(penalty, (b, ttype), self._drop_penalty[high])
        return penalty

    # ------------------------------------------------------------------ introspection
    @property
    def action_mask(self) -> np.ndarray:
        """``[B, m, K + 1]`` bool valid actions (spec step 4), a view of this tick's own array."""
        return self._mask_by_action.transpose(0, 2, 1)

    @property
    def queue_length(self) -> np.ndarray:
        """``[B]`` tasks waiting in the queue (slot tasks included)."""
        return (self._queue[:, : self._queue_width] != EMPTY).sum(axis=1)

    def queued_tasks(self, copy: int) -> list[dict[str, int]]:
        """The queue of one copy, decoded, in queue order (for tests and debugging)."""
        keys = np.sort(self._queue[copy][self._queue[copy] != EMPTY])
        return [
            {
                "type": int(task_type(x)),
                "high": int(task_high(x)),
                "due": int(task_due(x)),
                "id": int(task_id(x)),
                "duration": int(task_duration(x)),
                "round": int(task_round(x)),
            }
            for x in keys
        ]

    def inject_tasks(self, copy: int, tasks: list[dict[str, int]]) -> None:
        """Replace one copy's queue by hand-built tasks and re-select its slots (for tests).

        Args:
            copy: Copy index.
            tasks: Dicts with ``type`` (0-based), ``high`` (0/1), ``due``, ``id``, ``duration``,
                ``round`` (1/2).
        """
        if len(tasks) > self.params.queue_capacity:
            raise ValueError("more tasks than queue_capacity")
        keys = np.sort(
            [
                pack_tasks(
                    x["high"], x["due"], x["id"], x["type"], x["duration"], x.get("round", 1) - 1
                )
                for x in tasks
            ]
        ).astype(np.int64)
        self._queue[copy] = EMPTY
        self._queue[copy, : len(keys)] = keys
        self._queue_width = max(self._queue_width, len(keys))
        self._select_slots()
