"""Wall time and peak memory of one run (the scaling study reports both per run).

Peak memory is the peak resident set size (RSS) of the process, in MiB. A sweep's worker process
runs several jobs (joblib reuses its workers), so the process-lifetime peak
(``getrusage().ru_maxrss``) would carry one run's peak into the next. On Linux the peak is reset
at the start of the run (writing ``5`` to ``/proc/self/clear_refs`` resets ``VmHWM``, Linux >= 4.0)
and read from ``/proc/self/status`` at the end, so the number is this run's own peak (it includes
the interpreter and the imported libraries). Where that is not possible the process-lifetime
peak is reported and ``peak_rss_scope`` says ``process``.
"""

from __future__ import annotations

import resource
import sys
import time
from pathlib import Path
from typing import Any

CLEAR_REFS = Path("/proc/self/clear_refs")
STATUS = Path("/proc/self/status")
MIB = 2**20


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
    """Measure the wall time and the peak RSS between :meth:`start` and :meth:`result`."""

    def __init__(self) -> None:
        self._start = 0.0
        self._scope = "process"

    def start(self) -> RunResources:
        """Start the clock and reset the peak RSS if the system allows it."""
        try:
            CLEAR_REFS.write_text("5")  # resets VmHWM to the current RSS
            self._scope = "run" if _vm_hwm_mib() is not None else "process"
        except OSError:
            self._scope = "process"
        self._start = time.perf_counter()
        return self

    def result(self) -> dict[str, Any]:
        """``{"wall_s", "peak_rss_mb", "peak_rss_scope"}`` since :meth:`start`.

        Returns:
            Wall time in seconds, peak RSS in MiB, and ``run`` (peak of this run) or ``process``
            (peak of the whole process, the reset was not possible).
        """
        wall = time.perf_counter() - self._start
        peak = _vm_hwm_mib() if self._scope == "run" else None
        if peak is None:
            rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
            peak = rss / MIB if sys.platform == "darwin" else rss * 1024 / MIB  # bytes on macOS
        return {
            "wall_s": round(wall, 3),
            "peak_rss_mb": round(peak, 1),
            "peak_rss_scope": self._scope,
        }
