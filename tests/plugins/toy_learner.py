"""A learner of one's own: one module plus one yaml, outside the package (no other file).

:class:`ToyLearner` bids, for each robot, for its lowest valid slot with a probability it
learns per robot from the robot's rewards. It declares the facts every learner answers for
(``mrta_rl.learners.base.Learner``): label, kind, training loop, memory estimate and learning
space.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, ClassVar

import numpy as np

from mrta_rl.config import Range
from mrta_rl.envs import AuctionEnv, StepResult
from mrta_rl.learners.base import NUMPY_LOOP, Learner, MemoryQuery
from mrta_rl.learners.memory import ResourceEstimate
from mrta_rl.partition import Partition

RATE_BYTES = 8  # one float64 bid rate per robot
RATES_FILE = "rates.npy"


class ToyLearner(Learner):
    """Per-robot bid rate, moved towards bidding after a positive reward, away after a negative.

    Args:
        env: The env.
        rng: The learner's randomness.
        partition: Unused.
        bid_rate: Starting probability of bidding for the lowest valid slot.
        lr: Step of the bid rate per rewarded tick.
    """

    label: ClassVar[str] = "Toy bidder"
    kind: ClassVar[str] = "tabular"
    training_loop: ClassVar[str] = NUMPY_LOOP

    def __init__(
        self,
        *,
        env: AuctionEnv,
        rng: np.random.Generator,
        partition: Partition | None = None,
        bid_rate: Annotated[float, Range(0, 1)] = 0.5,
        lr: Annotated[float, Range(0, 1)] = 0.01,
    ) -> None:
        super().__init__(env=env, rng=rng, partition=partition)
        self.rates = np.full(env.n_robots, bid_rate)
        self.lr = lr
        self.updates = 0

    @classmethod
    def estimate_memory(cls, query: MemoryQuery) -> ResourceEstimate:
        """One bid rate per robot."""
        env, partition, settings, decisions, copies = query
        rates = RATE_BYTES * env.n_robots
        return ResourceEstimate(cls.__name__, rates, rates, {"bid rates": rates})

    @classmethod
    def learning_space_dimension(
        cls, env: AuctionEnv, partition: Partition | None, settings: dict[str, Any]
    ) -> int:
        """One number per robot."""
        return env.n_robots

    def act(self, view: Any, mask: np.ndarray, *, explore: bool) -> np.ndarray:
        """Lowest valid slot with the robot's bid rate, else wait."""
        slots = mask[..., 1:]  # [B, m, K]
        lowest = np.where(slots.any(-1), slots.argmax(-1) + 1, 0)  # [B, m]
        bid = self.rng.random(lowest.shape) < self.rates  # [B, m]
        return np.where(bid, lowest, 0)

    def update(
        self,
        view: Any,
        actions: np.ndarray,
        result: StepResult,
        next_view: Any,
        next_mask: np.ndarray,
    ) -> dict[str, float]:
        """Move each robot's rate by the sign of its mean reward over the copies where it bid."""
        bid = actions > 0  # [B, m]
        reward = np.asarray(result.robot_reward, float) * bid  # [B, m]
        self.rates = np.clip(self.rates + self.lr * np.sign(reward.sum(0)), 0.0, 1.0)
        self.updates += 1
        return {}

    def learning_space(self) -> dict[str, int]:
        """One rate per robot (the class's dimension)."""
        return {"analytic": self.learning_space_dimension(self.env, self.partition, {})}

    def save(self, directory: Path) -> None:
        """``rates.npy``: the bid rates."""
        directory.mkdir(parents=True, exist_ok=True)
        np.save(directory / RATES_FILE, self.rates, allow_pickle=False)

    def load(self, directory: Path) -> None:
        """Restore the bid rates written by :meth:`save`.

        Raises:
            ValueError: if the file holds another number of rates.
        """
        path = directory / RATES_FILE
        rates = np.load(path, allow_pickle=False)
        if rates.shape != self.rates.shape:
            raise ValueError(f"{path}: shape {rates.shape}, not {self.rates.shape}")
        self.rates = rates.astype(float)
