"""Environments: the batched auction dynamics (auction.py) and its TorchRL/PettingZoo/Gym views.

Importing this package registers the Gymnasium ids (``gym.make("mrta_rl/Auction-System1-v0")``,
see :mod:`mrta_rl.envs.gymnasium_env`), and makes the log say when numba compiles the kernels
(:func:`mrta_rl.logs.announce_compiling`).
"""

from __future__ import annotations

from mrta_rl.envs import gymnasium_env as _gymnasium_env  # noqa: F401  (registers the gym ids)
from mrta_rl.envs.auction import AuctionEnv, EpisodeStats, StepResult
from mrta_rl.envs.params import AuctionParams
from mrta_rl.logs import announce_compiling

announce_compiling()  # before the first call of a kernel: the log says when numba compiles

__all__ = ["AuctionEnv", "AuctionParams", "EpisodeStats", "StepResult"]
