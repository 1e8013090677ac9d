"""Planners: reference policies that read the full env state (not learners; docs/learners.md)."""

from __future__ import annotations

from mrta_rl.learners.planning.rollout import RolloutPlanner, SubGRolloutPlanner

__all__ = ["RolloutPlanner", "SubGRolloutPlanner"]
