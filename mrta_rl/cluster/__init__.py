"""One run's work spread over Ray workers, on this machine or a cluster (``train.workers``).

Ray is the ``cluster`` extra; nothing here imports it until workers are asked for.
"""

from __future__ import annotations

import importlib.util

EXTRA = "cluster"  # the extra that installs Ray: pip install 'mrta_rl[cluster]'


def ray_installed() -> bool:
    """Whether Ray is installed (the ``cluster`` extra), without importing it."""
    return importlib.util.find_spec("ray") is not None
