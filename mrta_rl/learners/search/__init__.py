"""Policy-search learners: the weights of a parametric policy learned from team returns by ES."""

from __future__ import annotations

from mrta_rl.learners.search.net_es import NetESLearner
from mrta_rl.learners.search.reserve_es import ReserveESLearner

__all__ = ["NetESLearner", "ReserveESLearner"]
