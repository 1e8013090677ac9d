"""The training progress bar shared by the runners (tqdm on stderr)."""

from __future__ import annotations

import sys

from tqdm.auto import tqdm

REDRAW_TERMINAL_S = 0.1  # tqdm's default on a terminal
REDRAW_LOG_S = 15.0  # in a log file or a pipe every redraw is a new line: a few per minute


def progress_bar(*, total: int, unit: str, desc: str, enabled: bool, **kwargs) -> tqdm:
    """A tqdm bar that redraws often on a terminal and rarely when stderr is a file or pipe.

    Args:
        total: Total count (ticks or frames).
        unit: Unit name shown by tqdm.
        desc: Label in front of the bar.
        enabled: ``cfg.train.progress_bar``.
        **kwargs: More tqdm options (e.g. ``unit_scale``).

    Returns:
        The bar (a context manager).
    """
    interactive = sys.stderr.isatty()
    return tqdm(
        total=total,
        unit=unit,
        desc=desc,
        disable=not enabled,
        dynamic_ncols=True,
        mininterval=REDRAW_TERMINAL_S if interactive else REDRAW_LOG_S,
        **kwargs,
    )
