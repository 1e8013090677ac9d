"""ThreadedAuctionEnv: the batched auction env split over threads, one shard of copies each.

The compiled kernel of :class:`AuctionEnv` (``envs/kernel.py``) releases the GIL, so shards of
an :class:`AuctionEnv` stepped by concurrent threads use several cores. Copies are independent and
their random draws depend only on their own seeds (``counter_rng``), so a threaded env gives
exactly the results of one ``AuctionEnv`` with the same seed: copy ``b`` is copy ``b`` of the
same shard-less env. It exposes the same interface; per-copy arrays are the shards' arrays
joined along the copy axis.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np

from mrta_rl.envs.auction import AuctionEnv, EpisodeStats, StepResult
from mrta_rl.envs.params import AuctionParams
from mrta_rl.systems import RobotSystem


class ThreadedAuctionEnv:
    """``threads`` shards of :class:`AuctionEnv` over contiguous copy ranges (same interface).

    Arguments:
        system: The robot team.
        params: Dynamics parameters (as :class:`AuctionEnv`).
        batch_size: Number of copies ``B`` (at least ``threads``).
        active_tasks: ``[m, n]`` bool ``Lambda_i`` (as :class:`AuctionEnv`).
        seed: Copy ``b`` is seeded with ``seed + b``, as in :class:`AuctionEnv`.
        threads: Number of shards and threads.
    """

    def __init__(
        self,
        system: RobotSystem,
        params: AuctionParams | None = None,
        batch_size: int = 1,
        active_tasks: np.ndarray | None = None,
        seed: int = 0,
        threads: int = 2,
    ) -> None:
        if not 1 <= threads <= batch_size:
            raise ValueError(f"threads must be in 1..batch_size={batch_size}, got {threads}")
        bounds = np.linspace(0, batch_size, threads + 1).astype(int)
        self._ranges = [
            slice(int(lo), int(hi)) for lo, hi in zip(bounds[:-1], bounds[1:], strict=True)
        ]
        self._shards = [
            AuctionEnv(system, params, r.stop - r.start, active_tasks, seed=seed + r.start)
            for r in self._ranges
        ]
        for shard, r in zip(self._shards, self._ranges, strict=True):
            shard.copy_offset = r.start  # error messages name copies of the whole batch
        self._pool = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="auction")
        first = self._shards[0]
        self.system, self.params, self.active_tasks = system, first.params, first.active_tasks
        self.batch_size, self.n_robots, self.n_task_types = (
            batch_size,
            first.n_robots,
            first.n_task_types,
        )
        self.n_slots, self.n_actions = first.n_slots, first.n_actions

    def _map(self, fn, *per_shard):
        """Run ``fn(shard, *args)`` on every shard concurrently; results in shard order."""
        jobs = zip(self._shards, *per_shard, strict=True)
        futures = [self._pool.submit(fn, shard, *args) for shard, *args in jobs]
        return [f.result() for f in futures]

    def _split(self, array) -> list:
        return [None if array is None else array[r] for r in self._ranges]

    def _join(self, name: str) -> np.ndarray:
        return np.concatenate([getattr(shard, name) for shard in self._shards])

    def seed(self, seed: int | np.ndarray) -> None:
        """As :meth:`AuctionEnv.seed`: an int gives copy ``b`` the seed ``seed + b``."""
        seeds = np.asarray(seed, dtype=np.int64)
        if seeds.ndim == 0:
            seeds = seeds + np.arange(self.batch_size)
        for shard, part in zip(self._shards, self._split(seeds), strict=True):
            shard.seed(part)

    def reset(self, mask: np.ndarray | None = None, seed: int | np.ndarray | None = None) -> None:
        """As :meth:`AuctionEnv.reset` (all copies, or those where ``mask`` is True)."""
        if seed is not None:
            self.seed(seed)
        masks = self._split(None if mask is None else np.array(mask, bool))
        self._map(lambda shard, part: shard.reset(part), masks)

    def step(self, actions: np.ndarray) -> StepResult:
        """As :meth:`AuctionEnv.step`: every shard's actions are checked before any shard steps."""
        actions = np.asarray(actions)
        if actions.shape != (self.batch_size, self.n_robots):
            raise ValueError(
                f"actions must have shape (B, m) = {(self.batch_size, self.n_robots)}, "
                f"got {actions.shape}"
            )
        parts = self._split(actions)
        for shard, part in zip(
            self._shards, parts, strict=True
        ):  # all valid before any shard moves
            shard.validate(part)
        results = self._map(lambda shard, part: shard.step(part, validated=True), parts)
        return StepResult(
            np.concatenate([r.team_reward for r in results]),
            np.concatenate([r.done for r in results]),
            np.concatenate([r._assign for r in results]),
            np.concatenate([r._type_penalty for r in results]),
            results[0]._share,
        )

    def fixed_actions(self, policy: str = "greedy") -> np.ndarray:
        """As :meth:`AuctionEnv.fixed_actions`, joined over shards."""
        return np.concatenate([shard.fixed_actions(policy) for shard in self._shards])

    # per-copy state, joined over shards (the same names and shapes as AuctionEnv)
    action_mask = property(lambda self: self._join("action_mask"), doc="``[B, m, K + 1]`` bool.")
    slot_type = property(lambda self: self._join("slot_type"), doc="``[B, K]`` (-1 empty).")
    slot_high = property(lambda self: self._join("slot_high"), doc="``[B, K]`` (-1 empty).")
    idle = property(lambda self: self._join("idle"), doc="``[B, m]`` bool.")
    battery = property(lambda self: self._join("battery"), doc="``[B, m]``.")
    busy_until = property(lambda self: self._join("busy_until"), doc="``[B, m]``.")
    last_high_arrival = property(lambda self: self._join("last_high_arrival"), doc="``[B, n]``.")
    t = property(lambda self: self._join("t"), doc="``[B]`` current tick.")
    done = property(lambda self: self._join("done"), doc="``[B]`` bool.")
    queue_length = property(lambda self: self._join("queue_length"), doc="``[B]``.")

    @property
    def stats(self) -> EpisodeStats:
        """Counters of the current episodes, joined over shards (a snapshot)."""
        parts = [shard.stats for shard in self._shards]
        fields = EpisodeStats.__dataclass_fields__
        return EpisodeStats(*(np.concatenate([getattr(p, f) for p in parts]) for f in fields))

    def close(self) -> None:
        """Stop the worker threads."""
        self._pool.shutdown(wait=False)
