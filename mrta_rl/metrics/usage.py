"""Wall time, CPU time and peak memory of one run (the scaling study reports them per run).

Peak memory is the peak resident set size (RSS) of the process, in MiB. A sweep's worker process
runs several jobs (joblib reuses its workers), so the process-lifetime peak
(``getrusage().ru_maxrss``) would carry one run's peak into the next. On Linux the peak is reset
at the start of the run (writing ``5`` to ``/proc/self/clear_refs`` resets ``VmHWM``, Linux >= 4.0)
and read from ``/proc/self/status`` at the end, so the number is this run's own peak (it includes
the interpreter and the imported libraries). Where that is not possible the process-lifetime
peak is reported and ``peak_rss_scope`` says ``process``.

A run resumed from a checkpoint adds what the processes before it spent (the checkpoint's
``loop.spent``: wall and CPU seconds, peak memory), so its figures are those of its whole life.
"""

from __future__ import annotations

import resource
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

CLEAR_REFS = Path("/proc/self/clear_refs")
STATUS = Path("/proc/self/status")
MIB = 2**20


def process_peak_mib() -> float:
    """This process's peak resident memory since it started, in MiB (``getrusage``)."""
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss / MIB if sys.platform == "darwin" else rss * 1024 / MIB  # bytes on macOS, else KiB


def _vm_hwm_mib() -> float | None:
    """``VmHWM`` of /proc/self/status in MiB, None if unavailable."""
    try:
        for line in STATUS.read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024 / MIB  # the line is "VmHWM:   1234 kB"
    except OSError:
        return None
    return None


class RunResources:
    """Measure wall time, CPU time and peak RSS between :meth:`start` and :meth:`result`."""

    def __init__(self) -> None:
        self._start = self._cpu_start = 0.0
        self._scope = "process"
        # the share of the processes before a resume (add_before)
        self._before = {"run_wall_s": 0.0, "cpu_s": 0.0, "peak_rss_mb": 0.0}

    def start(self) -> RunResources:
        """Start the clocks and reset the peak RSS if the system allows it."""
        try:
            CLEAR_REFS.write_text("5")  # resets VmHWM to the current RSS
            self._scope = "run" if _vm_hwm_mib() is not None else "process"
        except OSError:
            self._scope = "process"
        self._start, self._cpu_start = time.perf_counter(), time.process_time()
        return self

    def add_before(self, spent: Mapping[str, float]) -> None:
        """Count what the processes before a resume spent (a checkpoint's ``loop.spent``).

        Args:
            spent: ``run_wall_s``, ``cpu_s`` and ``peak_rss_mb`` (absent keys: nothing).
        """
        for key in self._before:
            self._before[key] = float(spent.get(key, 0.0))

    def spent(self) -> dict[str, float]:
        """``{"run_wall_s", "cpu_s", "peak_rss_mb"}`` so far, the processes before included."""
        return {
            "run_wall_s": self._before["run_wall_s"] + time.perf_counter() - self._start,
            "cpu_s": self._before["cpu_s"] + time.process_time() - self._cpu_start,
            "peak_rss_mb": max(self._before["peak_rss_mb"], self._peak_mib()),
        }

    def _peak_mib(self) -> float:
        peak = _vm_hwm_mib() if self._scope == "run" else None
        if peak is None:
            peak = process_peak_mib()
        return peak

    def result(self) -> dict[str, Any]:
        """``{"wall_s", "cpu_s", "peak_rss_mb", "peak_rss_scope"}`` since :meth:`start`.

        Returns:
            Wall and CPU time (of all the process's threads) in seconds and peak RSS in MiB, the
            processes before a resume included; and ``run`` (peak of this run) or ``process``
            (peak of the whole process: the reset was not possible).
        """
        spent = self.spent()
        return {
            "wall_s": round(spent["run_wall_s"], 3),
            "cpu_s": round(spent["cpu_s"], 3),
            "peak_rss_mb": round(spent["peak_rss_mb"], 1),
            "peak_rss_scope": self._scope,
        }
