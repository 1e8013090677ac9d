"""A rule of one's own: one compiled function, and the fixed learner that plays it.

The rule reads one copy's action mask, as the rules of ``mrta_rl/rules.py`` do; the learner
applies it to every copy. Fixed learners are not trained: the runner evaluates them.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from numba import njit

from mrta_rl.learners.base import FixedLearner


@njit(cache=True, nogil=True)
def last_slot(mask, out):
    """Every robot bids for its highest-numbered (least urgent) valid slot, else waits.

    Args:
        mask: ``[m, K + 1]`` bool valid actions of one copy (column 0: wait).
        out: ``[m]`` int64 actions, written.
    """
    for i in range(mask.shape[0]):
        out[i] = 0
        for k in range(mask.shape[1] - 1, 0, -1):
            if mask[i, k]:
                out[i] = k
                break


class LastSlotLearner(FixedLearner):
    """The rule :func:`last_slot` in every copy: the most urgent tasks are left to the others."""

    label: ClassVar[str] = "last slot"

    def act(self, view: None, mask: np.ndarray, *, explore: bool) -> np.ndarray:
        """``[B, m]`` actions of the rule, copy by copy."""
        actions = np.zeros(mask.shape[:2], np.int64)  # [B, m]
        for b in range(mask.shape[0]):
            last_slot(mask[b], actions[b])
        return actions
