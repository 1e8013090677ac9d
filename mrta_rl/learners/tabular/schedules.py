"""Schedules of the tabular learners: epsilon over episodes, eq. (3)'s learning rate over visits."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit


@dataclass(frozen=True)
class LinearSchedule:
    """Value moving linearly from ``start`` to ``end`` over ``steps`` steps, then constant.

    Attributes:
        start: Value at step 0.
        end: Value from step ``steps`` on.
        steps: Length of the ramp (0: always ``end``).
    """

    start: float
    end: float
    steps: int

    def __call__(self, step: int) -> float:
        """The value at ``step``."""
        if self.steps <= 0 or step >= self.steps:
            return float(self.end)
        return float(self.start + (self.end - self.start) * step / self.steps)


@njit(cache=True)
def alpha_of_visits(visits: int, alpha: float, power: float, alpha_min: float) -> float:
    """Learning rate of eq. (3) after ``visits`` updates: ``max(alpha_min, alpha / n^power)``.

    ``power = 0`` is a constant ``alpha``; ``power = 1`` with ``alpha = 1`` averages the targets.
    ``n^-1`` is taken as ``1 / n``, as numpy's power does for that exponent (same floats).
    """
    if power == 0.0:
        return alpha
    scale = 1.0 / visits if power == 1.0 else float(visits) ** (-power)
    return max(alpha_min, alpha * scale)


@njit(cache=True)
def _visit_alpha(visits: np.ndarray, alpha: float, power: float, alpha_min: float) -> np.ndarray:
    out = np.empty(visits.size)
    for k in range(visits.size):
        out[k] = alpha_of_visits(visits.flat[k], alpha, power, alpha_min)
    return out


def visit_alpha(visits: np.ndarray, alpha: float, power: float, alpha_min: float) -> np.ndarray:
    """:func:`alpha_of_visits` of each visit count ``n >= 1``, same shape as ``visits``."""
    visits = np.asarray(visits, np.int64)
    return _visit_alpha(visits, float(alpha), float(power), float(alpha_min)).reshape(visits.shape)
