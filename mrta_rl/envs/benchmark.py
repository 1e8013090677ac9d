"""Env throughput benchmark (foundation issue): env-ticks per second under the greedy policy.

Throughput is ``copies x ticks / wall seconds`` of :class:`AuctionEnv` stepping with the plain
auction (greedy) policy, the policy's own cost included, in one process: one thread, or the copies
split over threads by :class:`~mrta_rl.envs.threaded.ThreadedAuctionEnv`.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np

from mrta_rl.envs.auction import AuctionEnv
from mrta_rl.envs.params import AuctionParams
from mrta_rl.envs.threaded import ThreadedAuctionEnv
from mrta_rl.learners.fixed import lowest_valid_bid
from mrta_rl.systems import RobotSystem


@dataclass(frozen=True)
class BenchResult:
    """One benchmark cell."""

    system: str
    n_robots: int
    batch_size: int
    threads: int
    ticks: int
    wall_s: float
    ticks_per_s: float

    def as_dict(self) -> dict:
        """JSON-ready dict."""
        return asdict(self)


def bench_env(
    system: RobotSystem,
    batch_size: int,
    threads: int = 1,
    min_seconds: float = 1.0,
    min_ticks: int = 50,
) -> BenchResult:
    """Step ``batch_size`` copies under greedy until ``min_seconds`` and ``min_ticks`` have passed.

    Episodes restart as they end (the horizon is the spec default), so long runs include resets.
    The greedy policy runs on the whole batch in the calling thread, as a learner would.

    Args:
        system: The robot team.
        batch_size: Number of copies ``B``.
        threads: 1 for :class:`AuctionEnv`, more for a :class:`ThreadedAuctionEnv`.
        min_seconds: Least wall time to measure.
        min_ticks: Least number of ticks to measure.

    Returns:
        The measured cell.
    """
    params = AuctionParams.merged(system.env_overrides)
    if threads == 1:
        env = AuctionEnv(system, params, batch_size=batch_size, seed=0)
    else:
        env = ThreadedAuctionEnv(system, params, batch_size=batch_size, seed=0, threads=threads)
    for _ in range(5):  # warm-up: first allocations, caches
        env.step(lowest_valid_bid(env.action_mask[:, :, 1:]))
    ticks, start = 0, time.perf_counter()
    while ticks < min_ticks or time.perf_counter() - start < min_seconds:
        env.step(lowest_valid_bid(env.action_mask[:, :, 1:]))
        ticks += 1
        if env.done.any():
            env.reset()
    wall = time.perf_counter() - start
    if threads > 1:
        env.close()
    return BenchResult(
        system.name, system.n_robots, batch_size, threads, ticks, wall, batch_size * ticks / wall
    )


def format_table(results: list[BenchResult]) -> str:
    """Markdown table: a row per system and thread count, a column per batch size (env-ticks/s)."""
    sizes = sorted({r.batch_size for r in results})
    rows = list(dict.fromkeys((r.system, r.n_robots, r.threads) for r in results))
    cells = {(r.system, r.threads, r.batch_size): r.ticks_per_s for r in results}
    lines = [
        "| system (robots) | threads | " + " | ".join(f"B={b}" for b in sizes) + " | best |",
        "| --- | ---: | " + " | ".join("---:" for _ in sizes) + " | ---: |",
    ]
    for name, m, threads in rows:
        row = [cells.get((name, threads, b), np.nan) for b in sizes]
        lines.append(
            f"| {name} ({m}) | {threads} | "
            + " | ".join("-" if np.isnan(x) else f"{x:,.0f}" for x in row)
            + f" | {np.nanmax(row):,.0f} |"
        )
    return "\n".join(lines)
