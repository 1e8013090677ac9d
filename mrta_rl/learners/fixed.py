"""Fixed allocation policies of the spec ("Fixed policies"): greedy, random and high_only.

They are learners with ``kind = "fixed"`` and the base class's no-op ``update``, so the runner
evaluates them exactly like trained learners. ``greedy`` is the plain auction without learning,
the baseline every run reports next to its learner. All three are vectorised over ``[B, m]``.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from mrta_rl.envs import AuctionEnv
from mrta_rl.learners.base import Learner, LearnerKind


def lowest_valid_bid(bid_mask: np.ndarray) -> np.ndarray:
    """Lowest-numbered slot with a True bid, or 0 (wait) when there is none.

    A loop over the tiny slot axis (K = 3 by default) beats ``argmax`` on such a short last axis.

    Args:
        bid_mask: ``[B, m, K]`` bool, True where bidding for slot ``k + 1`` is allowed.

    Returns:
        ``[B, m]`` int64 actions in ``0..K``.
    """
    actions = np.zeros(bid_mask.shape[:2], dtype=np.int64)
    for k in reversed(range(bid_mask.shape[2])):
        actions = np.where(bid_mask[:, :, k], k + 1, actions)
    return actions


class GreedyLearner(Learner):
    """Plain auction (spec "Fixed policies"): idle robots bid for their lowest-numbered valid slot.

    Slot 1 holds the most urgent task (spec step 3), so greedy bids for the most urgent task the
    robot may do. A busy robot has only action 0 in the mask, so it waits.
    """

    kind: ClassVar[LearnerKind] = "fixed"

    def act(self, view: None, mask: np.ndarray, *, explore: bool) -> np.ndarray:
        """Bid for the lowest-numbered valid slot, else wait.

        Args:
            view: Unused (None).
            mask: ``[B, m, K + 1]`` bool valid actions.
            explore: Unused: the policy is deterministic.

        Returns:
            ``[B, m]`` int64 actions.
        """
        return lowest_valid_bid(mask[:, :, 1:])


class RandomLearner(Learner):
    """Random bidding (spec "Fixed policies"): uniform over the ``v`` valid bids plus waiting.

    A robot with ``v`` valid bids picks each of its ``v + 1`` choices with probability
    ``1 / (v + 1)``; a busy robot (``v = 0``) waits.
    """

    kind: ClassVar[LearnerKind] = "fixed"

    def act(self, view: None, mask: np.ndarray, *, explore: bool) -> np.ndarray:
        """Draw one valid action per robot uniformly from ``self.rng``.

        Args:
            view: Unused (None).
            mask: ``[B, m, K + 1]`` bool valid actions; action 0 (wait) is always valid.
            explore: Unused: the policy is random in evaluation too, by definition.

        Returns:
            ``[B, m]`` int64 actions.
        """
        running = np.cumsum(mask, axis=2)  # [B, m, K + 1]; running[..., 0] = 1 (wait is valid)
        choice = self.rng.integers(0, running[:, :, -1])  # [B, m], uniform in 0..v
        # the valid action of rank `choice` is the number of places whose running count is <= it
        return (running <= choice[:, :, None]).sum(axis=2).astype(np.int64)


class HighOnlyLearner(Learner):
    """Wait for high priority (spec "Fixed policies"): bid only for H tasks.

    Every idle robot bids for its lowest-numbered valid slot holding an H task, else waits.
    """

    kind: ClassVar[LearnerKind] = "fixed"

    def encode(self, env: AuctionEnv) -> np.ndarray:
        """The slot priorities, the only part of the state this policy reads.

        Args:
            env: The env at a decision point.

        Returns:
            ``[B, K]`` int copy of ``env.slot_high`` (1 = H, 0 = L, -1 = empty).
        """
        return env.slot_high.copy()

    def act(self, view: np.ndarray, mask: np.ndarray, *, explore: bool) -> np.ndarray:
        """Bid for the lowest-numbered valid H slot, else wait.

        Args:
            view: ``[B, K]`` slot priorities from :meth:`encode`.
            mask: ``[B, m, K + 1]`` bool valid actions.
            explore: Unused: the policy is deterministic.

        Returns:
            ``[B, m]`` int64 actions.
        """
        return lowest_valid_bid(mask[:, :, 1:] & (view[:, None, :] == 1))
