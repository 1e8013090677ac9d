"""Training progress shared by the runners: a tqdm bar on stderr, or lines in the log.

With ``train.progress_bar=true`` the loops draw a tqdm bar. Without it (every sweep sets it
false) :class:`ProgressLog` stands in for the bar, with the same ``update`` / ``set_postfix``
calls, and writes a line to the run's log at least every ``train.log_every_s`` seconds while the
loop advances::

    train reserve_es: episode 12/100, return 5230.1, 1630 tick/s, 0:14:02 left

Both count the rate (and the time left) from the end of the first update on: the first tick of
a process may compile the numba kernels (a minute on a cold cache), which says nothing about the
speed of training.
"""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Callable, Mapping
from types import TracebackType
from typing import Any

from tqdm.auto import tqdm

logger = logging.getLogger(__name__)

REDRAW_TERMINAL_S = 0.1  # tqdm's default on a terminal
REDRAW_LOG_S = 15.0  # in a log file or a pipe every redraw is a new line: a few per minute
CLOCK: Callable[[], float] = time.monotonic  # the lines' clock (tests put a fake one here)


def _hours(seconds: float) -> str:
    """``H:MM:SS``, the hours counted on past a day (``230:04:25``) as tqdm's bar shows them.

    Any number of seconds: ``datetime.timedelta`` overflows past a billion days (the time left
    of a run of 2**62 episodes).
    """
    minutes, secs = divmod(round(seconds), 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours}:{minutes:02d}:{secs:02d}"


class ProgressLog:
    """A progress bar's stand-in that writes log lines: episode, return, rate, time left.

    Attributes:
        n: Units done so far (ticks or frames), as tqdm's ``n``.
        lines: Progress lines written.
    """

    def __init__(
        self,
        *,
        total: int,
        unit: str,
        desc: str,
        every_s: float,
        episode_units: int,
        initial: int = 0,
        clock: Callable[[], float] | None = None,
    ) -> None:
        """Start the clock.

        Args:
            total: Units of the whole loop.
            unit: Unit name (``tick``, ``frame``).
            desc: Label at the start of each line (``train greedy``).
            every_s: Seconds between lines (``train.log_every_s``).
            episode_units: Units per training episode (the episode count is ``n`` over it).
            initial: Units done before (a resumed run); the rate counts only this process's.
            clock: Seconds, monotonic; default :data:`CLOCK`.
        """
        self.total, self.unit, self.desc = total, unit, desc
        self.every_s, self.episode_units = every_s, max(1, episode_units)
        self.n = self._start_n = initial
        self.lines = 0
        self._clock = clock or CLOCK
        self._start: float | None = None  # end of the first update: the rate counts from there
        self._last = self._clock()
        self._postfix: dict[str, Any] = {}

    def update(self, n: int = 1) -> None:
        """Count ``n`` more units; write a line if ``every_s`` has passed since the last one."""
        self.n += n
        now = self._clock()
        if self._start is None:  # the first update (compiling, maybe): not part of the rate
            self._start, self._start_n = now, self.n
        if now - self._last >= self.every_s:
            self._last = now
            self.lines += 1
            logger.info("%s", self.line(now))

    def set_postfix(self, postfix: Mapping[str, Any], refresh: bool = False) -> None:
        """Keep the values the next line shows (``return``; others as ``key value``)."""
        self._postfix = dict(postfix)

    def line(self, now: float) -> str:
        """The progress line at clock time ``now``."""
        elapsed = 0.0 if self._start is None else now - self._start
        rate = (self.n - self._start_n) / elapsed if elapsed > 0 else 0.0
        episodes = f"{self.n // self.episode_units}/{self.total // self.episode_units}"
        parts = [f"episode {episodes}", f"return {self._postfix.get('return', '-')}"]
        parts += [f"{k} {v}" for k, v in self._postfix.items() if k != "return"]
        left = _hours((self.total - self.n) / rate) if rate > 0 else "?"
        parts += [f"{rate:.0f} {self.unit}/s", f"{left} left"]
        return f"{self.desc}: {', '.join(parts)}"

    def __enter__(self) -> ProgressLog:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        return None


class ProgressBar(tqdm):
    """A tqdm bar whose rate, time left and elapsed time count from the end of the first update."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        """As tqdm's (every argument is passed on)."""
        super().__init__(*args, **kwargs)
        self._first = True

    def update(self, n: float = 1) -> bool | None:
        """Count ``n`` more units; after the first update, restart the clock of the rate."""
        if not self._first or self.disable:
            return super().update(n)
        self._first = False
        self.n += n
        # tqdm's rate: (n - initial) / (time since start_t), then a moving average of the
        # increments between redraws; both start here
        self.initial = self.last_print_n = self.n
        self.start_t = self.last_print_t = self._time()
        self.refresh()
        return True


def progress_bar(
    *,
    total: int,
    unit: str,
    desc: str,
    enabled: bool,
    log_every_s: float,
    episode_units: int = 1,
    **kwargs: Any,
) -> ProgressBar | ProgressLog:
    """A tqdm bar, or :class:`ProgressLog` lines when the bar is off.

    The bar redraws often on a terminal and rarely when stderr is a file or pipe.

    Args:
        total: Total count (ticks or frames).
        unit: Unit name shown by tqdm.
        desc: Label in front of the bar.
        enabled: ``cfg.train.progress_bar``.
        log_every_s: ``cfg.train.log_every_s``: seconds between log lines when the bar is off.
        episode_units: Units (ticks or frames) per training episode, for the lines' episode.
        **kwargs: More tqdm options (e.g. ``unit_scale``; ``initial`` for both).

    Returns:
        The bar or its stand-in (a context manager either way).
    """
    if not enabled:
        return ProgressLog(
            total=total,
            unit=unit,
            desc=desc,
            every_s=float(log_every_s),
            episode_units=episode_units,
            initial=int(kwargs.get("initial", 0)),
        )
    interactive = sys.stderr.isatty()
    return ProgressBar(
        total=total,
        unit=unit,
        desc=desc,
        dynamic_ncols=True,
        mininterval=REDRAW_TERMINAL_S if interactive else REDRAW_LOG_S,
        **kwargs,
    )
