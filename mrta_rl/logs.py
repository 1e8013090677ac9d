"""What the run's log says about the libraries underneath: numba compiling, TorchRL's own lines.

* numba compiles the kernels (``envs/kernel.py``, ``rules.py``, the tabular kernels) at their
  first call and caches them on disk: the first run on a machine is silent for a minute or two
  while it compiles, the next ones load the cache. :func:`announce_compiling` says so once per
  process, when numba actually compiles (a cache miss), never when it loads from its cache.
* TorchRL gives its logger a console handler of its own that wraps every line in ANSI colour
  codes and passes nothing on: redirected output gets escape codes, and the run's log file
  misses TorchRL's lines. :func:`log_torchrl_plainly` sends them through the application's
  logging instead (Hydra: the console and ``train.log``), plain.
"""

from __future__ import annotations

import logging
from typing import Any

logger = logging.getLogger(__name__)

COMPILING = (
    "compiling the numba kernels: the first run takes a minute or two longer "
    "(first run only; cached afterwards)"
)
_compile_listener: Any = None  # registered once per process


def announce_compiling() -> None:
    """Log :data:`COMPILING` once per process, at the first kernel numba compiles (not loads)."""
    global _compile_listener
    if _compile_listener is not None:
        return
    from numba.core import event

    class CompileNotice(event.Listener):
        """Says :data:`COMPILING` at the start of the first compilation, then nothing."""

        said = False

        def on_start(self, event: Any) -> None:
            if not self.said:
                self.said = True
                logger.info(COMPILING)

        def on_end(self, event: Any) -> None:
            return None

    _compile_listener = CompileNotice()
    event.register("numba:compile", _compile_listener)  # fired on a cache miss only


def log_torchrl_plainly() -> None:
    """Drop TorchRL's coloured console handler and let its lines reach the root logger."""
    torchrl_logger = logging.getLogger("torchrl")
    for handler in list(torchrl_logger.handlers):
        torchrl_logger.removeHandler(handler)
    torchrl_logger.propagate = True
