"""mrta_rl: multi-robot task allocation with reinforcement learning (subG-CQL and baselines)."""

from __future__ import annotations

__version__ = "0.1.0"
