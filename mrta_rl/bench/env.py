"""Env throughput benchmark: env-ticks per second of the auction dynamics, three ways.

Throughput is ``copies x ticks / wall seconds`` under the greedy policy, the policy's own cost
included, in one process:

- ``step``: :meth:`AuctionEnv.step` under actions from :meth:`AuctionEnv.fixed_actions`
  (``greedy``, compiled; the same actions as
  :class:`~mrta_rl.learners.fixed.GreedyLearner`'s numpy policy), one call per tick as a learner
  drives it (one thread, or the copies split over threads by
  :class:`~mrta_rl.bench.threaded.ThreadedAuctionEnv`);
- ``play``: :meth:`AuctionEnv.play`, many ticks in one compiled call with the policy compiled in
  (one thread, or the copies split over threads);
- ``plain``: the plain per-copy Python loop of the spec, ``mrta_rl/envs/reference.py``
  under greedy, the yardstick the ratios are taken against.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from statistics import median

import numpy as np

from mrta_rl.bench.threaded import ThreadedAuctionEnv
from mrta_rl.envs.auction import AuctionEnv
from mrta_rl.envs.params import AuctionParams
from mrta_rl.envs.reference import ReferenceAuction
from mrta_rl.systems import RobotSystem


@dataclass(frozen=True)
class BenchResult:
    """One benchmark cell."""

    system: str
    n_robots: int
    path: str  # step, play or plain
    batch_size: int
    threads: int
    ticks: int
    wall_s: float
    cpu_s: float  # CPU time of this process (all its threads)
    ticks_per_s: float  # copies x ticks per second of the chosen clock

    def as_dict(self) -> dict:
        """JSON-ready dict."""
        return asdict(self)


def _timed(run_chunk, min_seconds: float, min_ticks: int) -> tuple[int, float, float]:
    """Call ``run_chunk()`` (returns ticks per copy) until both minimums are met.

    Returns the ticks per copy, the wall seconds and the CPU seconds of the process.
    """
    ticks, start, cpu = 0, time.perf_counter(), time.process_time()
    while ticks < min_ticks or time.perf_counter() - start < min_seconds:
        ticks += run_chunk()
    return ticks, time.perf_counter() - start, time.process_time() - cpu


def _result(system, path, batch_size, threads, ticks, wall, cpu, clock) -> BenchResult:
    if clock not in ("wall", "cpu"):
        raise ValueError(f"unknown clock {clock!r}; known: wall, cpu")
    seconds = wall if clock == "wall" else cpu
    return BenchResult(
        system.name,
        system.n_robots,
        path,
        batch_size,
        threads,
        ticks,
        wall,
        cpu,
        batch_size * ticks / seconds,
    )


def bench_env(
    system: RobotSystem,
    batch_size: int,
    threads: int = 1,
    min_seconds: float = 1.0,
    min_ticks: int = 50,
    path: str = "step",
    clock: str = "wall",
) -> BenchResult:
    """Run ``batch_size`` copies under greedy until ``min_seconds`` and ``min_ticks`` have passed.

    Episodes restart as they end (the horizon is the system's), so long runs include resets.

    Args:
        system: The robot team.
        batch_size: Number of copies ``B``.
        threads: 1, or more: :class:`ThreadedAuctionEnv` shards (``step``) or copy ranges
            (``play``).
        min_seconds: Least wall time to measure.
        min_ticks: Least number of ticks per copy to measure.
        path: ``step`` or ``play`` (module docstring).
        clock: ``wall``, or ``cpu`` (the process's CPU time: steadier on a shared machine, but
            it adds up the threads' times).

    Returns:
        The measured cell.

    Raises:
        ValueError: on an unknown path.
    """
    params = AuctionParams.merged(system.env_overrides)
    if path == "play":
        env = AuctionEnv(system, params, batch_size=batch_size, seed=0)
        chunk = max(min_ticks, 1)
        env.play("greedy", ticks=1, threads=threads)  # warm-up: compiled code, caches

        def run_chunk() -> int:
            env.play("greedy", ticks=chunk, threads=threads)
            return chunk

    elif path == "step":
        if threads == 1:
            env = AuctionEnv(system, params, batch_size=batch_size, seed=0)
        else:
            env = ThreadedAuctionEnv(system, params, batch_size=batch_size, seed=0, threads=threads)
        for _ in range(5):  # warm-up: first allocations, caches
            env.step(env.fixed_actions("greedy"))

        def run_chunk() -> int:
            env.step(env.fixed_actions("greedy"))
            if env.done.any():
                env.reset()
            return 1

    else:
        raise ValueError(f"unknown benchmark path {path!r}; known: step, play")
    ticks, wall, cpu = _timed(run_chunk, min_seconds, min_ticks)
    if isinstance(env, ThreadedAuctionEnv):
        env.close()
    return _result(system, path, batch_size, threads, ticks, wall, cpu, clock)


def bench_plain_loop(
    system: RobotSystem, min_seconds: float = 1.0, clock: str = "wall"
) -> BenchResult:
    """Ticks per second of the plain one-copy loop (:mod:`mrta_rl.envs.reference`) under greedy."""
    params = AuctionParams.merged(system.env_overrides).resolve(system.n_robots)
    copy = ReferenceAuction(system, params, copy_seed=0)

    def run_chunk() -> int:
        # greedy: every idle robot bids for its lowest-numbered valid slot
        valid = [copy.valid_actions(i) for i in range(system.n_robots)]
        copy.step([v[1] if len(v) > 1 else 0 for v in valid])
        if copy.t >= params.horizon:
            copy.reset()
        return 1

    for _ in range(50):  # warm-up: the hashes' compiled scalar variants
        run_chunk()
    ticks, wall, cpu = _timed(run_chunk, min_seconds, 50)
    return _result(system, "plain", 1, 1, ticks, wall, cpu, clock)


def format_table(results: list[BenchResult]) -> str:
    """Markdown table: a row per system, path and thread count, a column per batch size.

    With several repeats of a cell, the cell shows the median; ``best`` is the best median, and
    ``x plain`` the min and median over repeats of (best of the repeat) / (plain of the repeat).
    """
    sizes = sorted({r.batch_size for r in results if r.path != "plain"})
    rows = list(dict.fromkeys((r.system, r.n_robots, r.path, r.threads) for r in results))
    systems = list(dict.fromkeys(r.system for r in results))
    rows.sort(key=lambda row: (systems.index(row[0]), row[2] != "plain"))  # its yardstick first
    cells: dict[tuple, list[float]] = {}
    for r in results:
        cells.setdefault((r.system, r.path, r.threads, r.batch_size), []).append(r.ticks_per_s)
    lines = [
        "| system (robots) | path | threads | "
        + " | ".join(f"B={b}" for b in sizes)
        + " | best | x plain (min / median) |",
        "| --- | --- | ---: | " + " | ".join("---:" for _ in sizes) + " | ---: | ---: |",
    ]
    for name, m, path, threads in rows:
        if path == "plain":
            plain = cells[(name, path, threads, 1)]
            lines.append(
                f"| {name} ({m}) | plain loop | 1 | "
                + " | ".join("-" for _ in sizes)
                + f" | {median(plain):,.0f} | 1 |"
            )
            continue
        row = [median(cells.get((name, path, threads, b), [np.nan])) for b in sizes]
        ratio = ""
        plain = cells.get((name, "plain", 1, 1))
        if plain:  # repeat j of every cell is one side-by-side measurement
            best = np.nanmax(
                [cells.get((name, path, threads, b), [np.nan] * len(plain)) for b in sizes], axis=0
            )
            ratios = best[: len(plain)] / np.array(plain)
            ratio = f"{ratios.min():,.0f} / {median(ratios):,.0f}"
        lines.append(
            f"| {name} ({m}) | {path} | {threads} | "
            + " | ".join("-" if np.isnan(x) else f"{x:,.0f}" for x in row)
            + f" | {np.nanmax(row):,.0f} | {ratio} |"
        )
    return "\n".join(lines)
