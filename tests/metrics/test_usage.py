"""A run's wall time, CPU time and peak memory (metrics/usage.py), on fake clocks."""

from __future__ import annotations

import time

from mrta_rl.metrics.usage import RunResources


class FakeClock:
    def __init__(self, now: float) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


def test_a_resumed_run_adds_the_share_of_the_processes_before_it(monkeypatch):
    wall, cpu = FakeClock(100.0), FakeClock(7.0)
    monkeypatch.setattr(time, "perf_counter", wall)
    monkeypatch.setattr(time, "process_time", cpu)
    resources = RunResources().start()
    wall.now += 2.5
    cpu.now += 1.25
    alone = resources.result()
    assert (alone["wall_s"], alone["cpu_s"]) == (2.5, 1.25)
    resources.add_before({"run_wall_s": 10.0, "cpu_s": 4.0, "peak_rss_mb": 1e9})
    spent = resources.spent()
    assert (spent["run_wall_s"], spent["cpu_s"], spent["peak_rss_mb"]) == (12.5, 5.25, 1e9)
    whole = resources.result()
    assert (whole["wall_s"], whole["cpu_s"], whole["peak_rss_mb"]) == (12.5, 5.25, 1e9)
