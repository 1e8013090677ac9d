"""Copy-ticks per second of an ES run on Ray workers, for several worker counts side by side.

Each repeat trains the learner once per worker count, one after another, each run starting its
own local Ray instance of that many CPUs. A run's rate counts its ES steps after the first (the
first loads the compiled code in every worker): copy-ticks played over the steps' wall time, as
the training process sees it (transfers included). Ratios are taken within a repeat, so a busy
machine slows both sides of each ratio alike.
"""

from __future__ import annotations

import statistics
from typing import Any

from mrta_rl.bench.learners import train_once


def measure(
    learner: str, system: str, workers: list[int], repeats: int, overrides: list[str]
) -> dict[str, Any]:
    """Train ``learner`` on ``system`` with each worker count, ``repeats`` times.

    Args:
        learner: A learner with ``population_on_workers`` (net_es, reserve_es).
        system: A shipped system name.
        workers: Worker counts; the first is the ratios' reference.
        repeats: Side-by-side repeats.
        overrides: More run settings (``train.episodes=5`` ...).

    Returns:
        ``{"rates": {workers: [copy-ticks/s per repeat]}, "ratios": {workers: [...]},
        "bytes": {workers: the run's bytes per step}}``.
    """
    rates: dict[int, list[float]] = {count: [] for count in workers}
    traffic: dict[int, dict[str, int]] = {}
    for _ in range(repeats):
        for count in workers:
            _, _, _, batch, info = train_once(
                learner, system, [f"train.workers={count}", *overrides]
            )
            record = info["workers"]
            steps = record["step_seconds"][1:]
            horizon = info["env_ticks"] // (batch * len(record["step_seconds"]))
            rates[count].append(batch * horizon * len(steps) / sum(steps))
            traffic[count] = record["bytes"]
    reference = rates[workers[0]]
    ratios = {
        count: [rate / base for rate, base in zip(rates[count], reference, strict=True)]
        for count in workers
    }
    return {"rates": rates, "ratios": ratios, "bytes": traffic}


def format_table(result: dict[str, Any]) -> str:
    """Rates (k copy-ticks/s) and ratios to the first worker count: min and median."""
    lines = [
        "workers | k copy-ticks/s min / median | ratio min / median | bytes sent / received"
    ]
    for count, rates in result["rates"].items():
        ratios = result["ratios"][count]
        sent = result["bytes"][count]
        lines.append(
            f"{count:7d} | {min(rates) / 1e3:8.1f} / {statistics.median(rates) / 1e3:8.1f} | "
            f"{min(ratios):5.2f} / {statistics.median(ratios):5.2f} | "
            f"{sent['sent_per_step']:,} / {sent['received_per_step']:,}"
        )
    return "\n".join(lines)
