"""The auction dynamics of ``docs/spec/auction_env.md``, batched over ``B`` copies.

:class:`AuctionEnv` is the interface every learner, view (TorchRL, PettingZoo, Gymnasium) and
metric uses. It owns the per-copy arrays; the rules themselves are the compiled per-copy loops of
``envs/kernel.py`` (numba), the one implementation of the spec. The TorchRL adapter wraps the
arrays zero-copy with ``torch.from_numpy``.

Design notes:
- **Tasks are packed int64 keys** (``envs/tasks.py``): the high bits are the spec's queue order (H
  before L, due tick, id), the low bits type, duration and round; an empty place is ``EMPTY``.
- **Counter-based randomness.** Every random number is a hash of (copy seed, episode number, tick,
  draw index), never a shared generator's stream. A copy's episode therefore depends only on its
  own seed and actions, not on the batch size or on when other copies reset, and a plain scalar
  implementation drawing the same hashes reproduces it exactly (see ``tests/envs/test_auction.py``).
- **A tick is split at the decision.** ``reset`` and the end of ``step`` run spec steps 1-3 of the
  next tick (arrivals, queue order, slots) so that the caller sees the slots it decides on;
  ``step(actions)`` runs steps 4-8. Drops from step 2 (overflow) are paid in the reward of that
  same tick, returned by the following ``step``.
- **Two entry points:** :meth:`AuctionEnv.step` (one tick under the caller's actions, for
  learners and views) and :meth:`AuctionEnv.play` (many ticks under a compiled fixed policy, for
  evaluation, baselines and benchmarks).
- **Fresh views.** ``slot_type``, ``slot_high``, ``idle`` and ``action_mask`` are new arrays
  every tick (callers may keep the last ones); the state arrays (``t``, ``busy_until``,
  ``battery``, ``last_high_arrival``, ``done``, ``stats``) are updated in place.
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from itertools import pairwise

import numpy as np

from mrta_rl.envs import counter_rng as rng
from mrta_rl.envs import kernel
from mrta_rl.envs.params import AuctionParams
from mrta_rl.envs.tasks import (
    DUE_BITS,
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
)
from mrta_rl.systems import RobotSystem


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


def _packed(
    tables: dict[str, np.ndarray], sizes: dict[str, int]
) -> tuple[tuple[np.ndarray, ...], dict[str, np.ndarray]]:
    """The kernel's storage of :data:`kernel.FIELDS` (see :func:`kernel.unpack`).

    Every field becomes a C-contiguous piece of one flat buffer per dtype, so that a compiled
    call takes 4 buffers instead of 27 arrays; the int64 buffer starts with the layout.

    Args:
        tables: The value of every table field, by name.
        sizes: The env's sizes by the letters of the fields' dimensions; the state fields
            start at zero (a reset writes them).

    Returns:
        The buffers (``kernel.BUFFER_DTYPES`` order) and the fields by name, as views of them.
    """
    layout = np.ones((len(kernel.FIELDS), 4), np.int64)  # offset and shape of each field
    used = [0] * len(kernel.BUFFER_DTYPES)  # places taken in each buffer
    used[kernel.BUFFER_DTYPES.index(np.int64)] = kernel.LAYOUT_SIZE
    places = []
    for f, (name, dims, dtype) in enumerate(kernel.FIELDS):
        shape = tuple(int(d) if d.isdigit() else sizes[d] for d in dims.split())
        kind = kernel.BUFFER_DTYPES.index(dtype)
        layout[f, 0], layout[f, 1 : 1 + len(shape)] = used[kind], shape
        places.append((name, kind, used[kind], shape))
        used[kind] += math.prod(shape)
    buffers = tuple(
        np.zeros(size, dtype) for size, dtype in zip(used, kernel.BUFFER_DTYPES, strict=True)
    )
    fields = {
        name: buffers[kind][start : start + math.prod(shape)].reshape(shape)
        for name, kind, start, shape in places
    }
    for name, value in tables.items():
        if value.shape != fields[name].shape:
            raise ValueError(f"table {name} has shape {value.shape}, not {fields[name].shape}")
        fields[name][...] = value
    buffers[kernel.BUFFER_DTYPES.index(np.int64)][: kernel.LAYOUT_SIZE] = layout.reshape(-1)
    return buffers, fields


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
            self._robot_reward = kernel.robot_rewards(self._assign, self._type_penalty, self._share)
        return self._robot_reward


def check_limits(system: RobotSystem, params: AuctionParams) -> None:
    """Refuse a team and parameters whose state the env's packed fields cannot hold.

    Checked from the sizes alone, before anything is built: validation
    (``runners/validation.py``) refuses such a run before any work.

    Args:
        system: The robot team.
        params: Its parameters (``arrival_rate`` resolved for the team, or None: ``m / 6``).

    Raises:
        ValueError: naming the quantity, its value and the limit.
    """
    p = params.resolve(system.n_robots)
    limits = {
        "horizon + reauction_delay": (p.horizon + p.reauction_delay, 1 << DUE_BITS),
        "number of task types": (system.n_task_types, 1 << TYPE_BITS),
        "longest duration": (
            max(
                p.duration_low[1],
                p.duration_high[1],
                *(r.hi for d in system.durations.values() for r in d.values()),
            ),
            1 << DURATION_BITS,
        ),
        "expected tasks per episode x 4": (4 * p.arrival_rate * p.horizon, 1 << ID_BITS),
        "zones (one robot at least in each)": (p.zones, system.n_robots + 1),
    }
    for what, (value, limit) in limits.items():
        if value >= limit:
            raise ValueError(f"{what} = {value} exceeds the environment's limit {limit - 1}")


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
        :attr:`last_high_arrival`, :attr:`t`); ``mrta_rl.envs.encodings`` encodes them.

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
        self._action_shape = (batch_size, system.n_robots)  # [B, m]
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
        # [m]: robot i bids in auction zone i * zones // m, which holds the slots k with
        # k % zones == zone (spec, "Auction zones"; every robot in zone 0 for one)
        zones = self.params.zones
        self.robot_zone = np.arange(system.n_robots) * zones // system.n_robots
        self.zone_slots = np.arange(p.slots)[None, :] % zones == self.robot_zone[:, None]
        self.copy_offset = 0  # index of copy 0 in a larger batch (ThreadedAuctionEnv), for errors
        check_limits(system, self.params)

        # per (type, priority) duration ranges: system file overrides, else the params' defaults
        dur_lo = np.zeros((self.n_task_types, 2), np.int64)
        dur_span = np.zeros((self.n_task_types, 2), np.int64)
        for j, name in enumerate(system.task_types):
            for prio, key in enumerate(("duration_low", "duration_high")):
                override = system.durations.get(name, {}).get(key)
                lo, hi = (override.lo, override.hi) if override is not None else getattr(p, key)
                dur_lo[j, prio], dur_span[j, prio] = lo, hi - lo + 1
        iparams = np.array([getattr(p, name) for name in kernel.INT_PARAMS], np.int64)
        fparams = np.array([getattr(p, name) for name in kernel.FLOAT_PARAMS], np.float64)
        cdf = rng.poisson_cdf(p.arrival_rate)
        tables = {
            "iparams": iparams,
            "fparams": fparams,
            "cdf": cdf,
            "dur_lo": dur_lo,
            "dur_span": dur_span,
            "willingness": system.willingness.T.astype(np.float64),  # d_iz by type, [n, m]
            "can_do": active.T.copy(),  # Lambda_i by type, [n, m]
        }
        self._penalty_share = kernel.penalty_shares(tables["can_do"])  # spec step 8, [n, m]

        # a queue holds at most queue_capacity tasks between ticks, plus one tick's arrivals
        sizes = {"B": batch_size, "m": self.n_robots, "n": self.n_task_types, "K": self.n_slots}
        sizes |= {"W": p.queue_capacity + len(cdf), "C": len(cdf)}
        self._buffers, fields = _packed(tables, sizes)
        self._state = {name: fields[name] for name in kernel.State._fields}
        state = self._state
        self.t = state["t"]  # current tick per copy
        self.busy_until, self.battery = state["busy_until"], state["battery"]  # [B, m]
        # tick of the last H arrival per type; far in the past until one arrives
        self.last_high_arrival = state["last_high_arrival"]  # [B, n]
        self.done = state["done"]  # [B]
        self._queue, self._queue_len = state["queue"], state["queue_len"]
        self.stats = EpisodeStats(**{name: state[name] for name in kernel.STATS})
        self._new_views()
        self.seed(seed)
        self.reset()

    # ------------------------------------------------------------------ seeding and reset
    def seed(self, seed: int | np.ndarray) -> None:
        """Seed the copies: an int gives copy ``b`` the seed ``seed + b``; or one per copy."""
        seeds = self._seed_array(seed, self.batch_size)
        self._state["seed_key"][:] = rng.seed_keys(seeds)
        self._state["episode"][:] = 0

    @staticmethod
    def _seed_array(seed: int | np.ndarray, count: int) -> np.ndarray:
        seeds = np.asarray(seed, dtype=np.int64)
        if seeds.ndim == 0:
            seeds = seeds + np.arange(count)
        if seeds.shape != (count,):
            raise ValueError(f"expected one seed or {count} seeds, got shape {seeds.shape}")
        return seeds

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
        self._refresh(rows, begin=2)

    def reseed(self, copies: np.ndarray | list[int] | None, seeds: int | np.ndarray) -> None:
        """Re-seed the FUTURE arrivals of some copies without resetting them.

        From the next tick on, the arrivals of copy ``copies[j]`` are those of episode 0 of seed
        ``seeds[j]`` at the same ticks (the current tick's arrivals and slots are kept), and its
        next :meth:`reset` starts episode 1 of that seed. With :meth:`set_state` this lets a
        planner roll many copies of one state forward under different sampled arrivals.

        Args:
            copies: Copy indices (default: all copies).
            seeds: One seed per copy, or an int ``s`` giving the ``j``-th listed copy ``s + j``.
        """
        rows = np.arange(self.batch_size) if copies is None else self._rows(copies)
        keys = rng.seed_keys(self._seed_array(seeds, len(rows)))
        self._state["seed_key"][rows] = keys
        self._state["episode_key"][rows] = rng.episode_keys(keys, np.zeros(len(rows), np.uint64))
        self._state["episode"][rows] = 1

    def _rows(self, copies: np.ndarray | list[int]) -> np.ndarray:
        """Copy indices from indices or a ``[B]`` bool mask; a ValueError names a bad one."""
        rows = np.asarray(copies)
        if rows.dtype == np.bool_:
            if rows.shape != (self.batch_size,):
                raise ValueError(f"a copy mask must have shape ({self.batch_size},)")
            return np.flatnonzero(rows)
        rows = rows.astype(np.int64).reshape(-1)
        bad = rows[(rows < 0) | (rows >= self.batch_size)]
        if len(bad):
            raise ValueError(f"copy {bad[0]} is not in 0..{self.batch_size - 1}")
        return rows

    # ------------------------------------------------------------------ the kernel's arguments
    def _fresh_views(self) -> tuple[np.ndarray, ...]:
        """New arrays for the next decision's views (callers may keep the previous ones)."""
        B, m, K = self.batch_size, self.n_robots, self.n_slots
        return (
            np.empty((B, K), np.int64),  # slot_type [B, K], -1 = empty slot
            np.empty((B, K), np.int64),  # slot_high [B, K], 1 = H, 0 = L, -1 = empty
            np.empty((B, m), np.bool_),  # idle [B, m], spec step 4
            np.empty((B, m, K + 1), np.bool_),  # action mask
        )

    def _new_views(self) -> tuple[np.ndarray, ...]:
        """Fresh view arrays, installed as this tick's (the kernel writes them next)."""
        views = self._fresh_views()
        self.slot_type, self.slot_high, self.idle, self._mask = views
        return views

    def _refresh(self, rows: np.ndarray | None, begin: int) -> None:
        """Reset (``begin=2``) or begin the tick of (1) the ``rows``, then re-select all slots."""
        rows = np.zeros(self.batch_size, bool) if rows is None else rows
        kernel.refresh(rows, begin, self._buffers, self._new_views())

    def _begin_tick(self, rows: np.ndarray) -> None:
        """Spec steps 1-3 of tick ``t`` for ``rows``; other copies keep their slots."""
        self._refresh(np.asarray(rows, bool), begin=1)

    def _select_slots(self) -> None:
        """Spec step 3 and the masks again, after a test or tool edited the state by hand."""
        self._refresh(None, begin=0)

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
        if (
            type(actions) is not np.ndarray
            or actions.dtype != np.int64
            or actions.shape != self._action_shape
            or not actions.flags.c_contiguous
        ):
            actions = self._as_actions(actions)
        B = self.batch_size
        views = self._fresh_views()  # installed only once the tick has been played
        team = np.empty(B)
        assign = np.empty((B, self.n_robots))  # assign rewards won
        type_penalty = np.empty((B, self.n_task_types))  # drop penalties by type
        # the kernel checks the actions first (unless validated) and changes nothing if invalid
        problem, where = kernel.step(
            not validated,
            actions,
            self._buffers,
            (self.idle, self._mask),
            views,
            (team, assign, type_penalty),
        )
        if problem:
            self._raise_invalid(problem, where, actions)
        self.slot_type, self.slot_high, self.idle, self._mask = views
        return StepResult(team, self.done.copy(), assign, type_penalty, self._penalty_share)

    def _as_actions(self, actions: np.ndarray) -> np.ndarray:
        """``actions`` as a C-ordered int64 ``[B, m]`` array, or a ValueError naming the problem."""
        actions = np.asarray(actions)
        if actions.shape != (self.batch_size, self.n_robots):
            raise ValueError(
                f"actions must have shape (B, m) = {(self.batch_size, self.n_robots)}, "
                f"got {actions.shape}"
            )
        if actions.dtype != np.int64:
            if not np.issubdtype(actions.dtype, np.integer):
                raise ValueError(f"actions must be integers, got dtype {actions.dtype}")
            actions = actions.astype(np.int64)
        return np.ascontiguousarray(actions)

    def validate(self, actions: np.ndarray) -> None:
        """Check a joint action against shape, episode end and the action mask (spec step 4).

        Raises:
            ValueError: naming the copy, the robot and the reason.
        """
        actions = self._as_actions(actions)
        problem, where = kernel.first_invalid(actions, self.done, self._mask)
        if problem:
            self._raise_invalid(problem, where, actions)

    def _raise_invalid(self, problem: int, where: int, actions: np.ndarray) -> None:
        """The ValueError of :func:`kernel.first_invalid`'s ``(problem, where)``."""
        if problem == 1:
            raise ValueError(
                f"copy {where + self.copy_offset} has finished its episode; reset it first"
            )
        if problem == 2:
            b, i = divmod(int(where), self.n_robots)
            a, robot = int(actions[b, i]), self.system.robots[i]
            if not 0 <= a < self.n_actions:
                why = f"actions are 0..{self.n_slots}"
            elif not self.idle[b, i]:
                why = f"{robot} is busy until tick {self.busy_until[b, i]}"
            elif self.slot_type[b, a - 1] < 0:
                why = f"slot {a} is empty"
            elif not self.zone_slots[i, a - 1]:
                why = f"slot {a} is not in {robot}'s auction zone {self.robot_zone[i] + 1}"
            else:
                why = f"{robot} may not do {self.system.task_types[self.slot_type[b, a - 1]]}"
            raise ValueError(
                f"invalid action {a} for robot {robot} in copy {b + self.copy_offset} "
                f"at tick {self.t[b]}: {why}"
            )

    # ------------------------------------------------------------------ fixed policies, compiled
    @staticmethod
    def _policy_code(policy: str) -> int:
        """The kernel's code of a spec fixed policy, or a ValueError naming the known ones."""
        if policy not in kernel.POLICIES:
            raise ValueError(f"unknown fixed policy {policy!r}; known: {sorted(kernel.POLICIES)}")
        return kernel.POLICIES[policy]

    def fixed_actions(self, policy: str = "greedy") -> np.ndarray:
        """This tick's ``[B, m]`` actions of a spec fixed policy, from the compiled kernel.

        The same rules as :meth:`play` plays: ``greedy`` equals
        :func:`~mrta_rl.learners.fixed.lowest_valid_bid` of the mask, in one compiled call
        instead of a few numpy ones (what counts at small batch sizes).

        Args:
            policy: ``greedy``, ``random`` or ``high_only``.

        Returns:
            ``[B, m]`` int64 actions, valid for :meth:`step` (waits in finished copies).

        Raises:
            ValueError: on an unknown policy.
        """
        actions = np.empty((self.batch_size, self.n_robots), np.int64)
        views = (self._mask, self.slot_high)
        kernel.fixed_actions(self._policy_code(policy), self._buffers, views, actions)
        return actions

    # ------------------------------------------------------------------ many ticks, compiled
    def play(
        self,
        policy: str,
        *,
        episodes: int | None = None,
        ticks: int | None = None,
        threads: int = 1,
    ) -> EpisodeStats | int:
        """Play many ticks of every copy under a fixed policy, in one compiled call.

        The spec's fixed policies (``greedy``, ``random``, ``high_only``) run inside the kernel.
        ``greedy`` and ``high_only`` give exactly what stepping with
        :class:`~mrta_rl.learners.fixed.GreedyLearner` / ``HighOnlyLearner`` gives; ``random``
        draws from counter-based hashes of the copy's episode key, tick and robot (not from a
        learner's generator), so it too is deterministic under the env's seed. A copy whose
        episode has ended is reset first.

        Args:
            policy: ``greedy``, ``random`` or ``high_only``.
            episodes: Play until every copy has finished this many episodes (resetting between
                them; the last one is left done) and return their statistics.
            ticks: Instead, play this many ticks per copy (finished episodes are reset) and
                return the number of copy-ticks played.
            threads: Split the copies into this many contiguous ranges played by concurrent
                threads.

        Returns:
            With ``episodes``: :class:`EpisodeStats` ``[episodes * B, ...]``, episode ``r`` of
            copy ``b`` in row ``r * B + b`` (as :func:`mrta_rl.runners.evaluate.evaluate_policy`
            orders its rounds). With ``ticks``: copies x ticks.

        Raises:
            ValueError: on an unknown policy, or unless exactly one of ``episodes`` and
                ``ticks`` is a positive int.
        """
        if not 1 <= threads <= self.batch_size:
            raise ValueError(f"play: threads must be in 1..{self.batch_size}, got {threads}")
        code = self._policy_code(policy)
        if (episodes is None) == (ticks is None):
            raise ValueError("play: give exactly one of episodes= and ticks=")
        count = episodes if ticks is None else ticks
        if isinstance(count, bool) or not isinstance(count, int | np.integer) or count < 1:
            raise ValueError(f"play: episodes/ticks must be a positive int, got {count!r}")
        B, m, n = self.batch_size, self.n_robots, self.n_task_types
        rounds = 0 if episodes is None else int(episodes)
        out = EpisodeStats(
            np.zeros((rounds * B, n, 2), np.int64),
            np.zeros((rounds * B, n, 2), np.int64),
            np.zeros((rounds * B, m), np.int64),
            np.zeros(rounds * B),
            np.zeros(rounds * B, np.int64),
        )
        current = (self.slot_type, self.slot_high, self.idle, self._mask)
        views = self._new_views()
        for fresh, now in zip(views, current, strict=True):
            fresh[...] = now  # play_copy decides on them first
        args = (
            (code, -1 if ticks is None else int(ticks), rounds),  # kernel.Plan
            self._buffers,
            views,
            tuple(getattr(out, f) for f in kernel.STATS),
        )
        if threads == 1:
            played = kernel.play(0, B, *args)
        else:  # disjoint copy ranges in concurrent threads (the kernel releases the GIL)
            bounds = np.linspace(0, B, threads + 1).astype(int)
            with ThreadPoolExecutor(max_workers=threads) as pool:
                jobs = [pool.submit(kernel.play, lo, hi, *args) for lo, hi in pairwise(bounds)]
                played = sum(job.result() for job in jobs)
        return out if episodes is not None else int(played)

    # ------------------------------------------------------------------ snapshots
    def get_state(self, copies: np.ndarray | list[int] | None = None) -> dict[str, np.ndarray]:
        """An exact snapshot of the copies' state: a dict of numpy arrays (copies, not views).

        Args:
            copies: Copy indices to take (default: all); the arrays are ``[len(copies), ...]``.

        Returns:
            ``{name: array}`` for every field of ``kernel.State``; :meth:`set_state` takes
            it back, here or in another env of the same system and parameters.
        """
        if copies is None:
            return {name: array.copy() for name, array in self._state.items()}
        rows = self._rows(copies)
        return {name: array[rows] for name, array in self._state.items()}

    def set_state(
        self, state: dict[str, np.ndarray], copies: np.ndarray | list[int] | None = None
    ) -> None:
        """Restore a :meth:`get_state` snapshot into all copies, or into ``copies``.

        A snapshot of one copy (arrays ``[1, ...]``) is broadcast into every listed copy, so one
        state can be rolled forward in many copies (then :meth:`reseed` them apart). The copies
        continue exactly as the snapshot's copies would have, tick by tick.

        Args:
            state: A snapshot of an env of the same system and parameters.
            copies: Copy indices to overwrite (default: all).

        Raises:
            ValueError: naming a missing, unknown or wrongly shaped array, before any change.
        """
        if set(state) != set(self._state):
            missing, unknown = set(self._state) - set(state), set(state) - set(self._state)
            raise ValueError(f"set_state: missing {sorted(missing)}, unknown {sorted(unknown)}")
        rows = slice(None) if copies is None else self._rows(copies)
        count = self.batch_size if copies is None else len(rows)
        values = {}
        for name, target in self._state.items():
            value = np.asarray(state[name], dtype=target.dtype)
            if value.shape[1:] != target.shape[1:] or value.shape[0] not in (1, count):
                raise ValueError(
                    f"set_state: {name} has shape {value.shape}, expected "
                    f"({count} or 1, {', '.join(map(str, target.shape[1:]))})"
                )
            values[name] = value
        for name, value in values.items():
            self._state[name][rows] = value
        self._select_slots()

    def clone(self) -> AuctionEnv:
        """An independent env in exactly this state: it steps as this one would."""
        twin = AuctionEnv(self.system, self.params, self.batch_size, self.active_tasks)
        twin.copy_offset = self.copy_offset
        twin.set_state(self.get_state())
        return twin

    # ------------------------------------------------------------------ introspection
    @property
    def action_mask(self) -> np.ndarray:
        """``[B, m, K + 1]`` bool valid actions (spec step 4), this tick's own array."""
        return self._mask

    @property
    def queue_length(self) -> np.ndarray:
        """``[B]`` tasks waiting in the queue (slot tasks included)."""
        return (self._queue != EMPTY).sum(axis=1)

    @property
    def _queue_width(self) -> int:
        """No copy holds more than this many places (tests write queues by hand)."""
        return int(self._queue_len.max())

    @_queue_width.setter
    def _queue_width(self, width: int) -> None:
        np.maximum(self._queue_len, width, out=self._queue_len)

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
        self._queue_len[copy] = len(keys)
        self._select_slots()
