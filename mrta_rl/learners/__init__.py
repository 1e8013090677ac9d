"""Learners: the Learner interface (base.py), fixed baselines (fixed.py), tabular, neural."""

from __future__ import annotations

from mrta_rl.learners.base import Learner, LearnerKind

__all__ = ["Learner", "LearnerKind"]
