"""Learners: the Learner interface (base.py), fixed baselines (fixed.py), tabular, neural."""

from __future__ import annotations

from mrta_rl.learners.base import FixedLearner, Learner, LearnerKind
from mrta_rl.learners.fixed import (
    GreedyLearner,
    HighOnlyLearner,
    RandomLearner,
    SubGReserveLearner,
    TeamReserveLearner,
)

__all__ = [
    "FixedLearner",
    "GreedyLearner",
    "HighOnlyLearner",
    "Learner",
    "LearnerKind",
    "RandomLearner",
    "SubGReserveLearner",
    "TeamReserveLearner",
]
