"""Policy-search learners: the weights of a parametric rule learned from team returns."""

from __future__ import annotations

from mrta_rl.learners.search.reserve_es import ReserveESLearner

__all__ = ["ReserveESLearner"]
