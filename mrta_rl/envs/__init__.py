"""Environments: the batched auction dynamics (auction.py) and its TorchRL/PettingZoo/Gym views."""

from __future__ import annotations

from mrta_rl.envs.auction import AuctionEnv, EpisodeStats, StepResult
from mrta_rl.envs.params import AuctionParams

__all__ = ["AuctionEnv", "AuctionParams", "EpisodeStats", "StepResult"]
