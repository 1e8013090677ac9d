"""Environments: the batched auction dynamics (auction.py) and its TorchRL/PettingZoo/Gym views.

Importing this package registers the Gymnasium ids (``gym.make("mrta_rl/Auction-System1-v0")``,
see :mod:`mrta_rl.envs.gymnasium_env`).
"""

from __future__ import annotations

from mrta_rl.envs import gymnasium_env as _gymnasium_env  # noqa: F401  (registers the gym ids)
from mrta_rl.envs.auction import AuctionEnv, EpisodeStats, StepResult
from mrta_rl.envs.params import AuctionParams

__all__ = ["AuctionEnv", "AuctionParams", "EpisodeStats", "StepResult"]
