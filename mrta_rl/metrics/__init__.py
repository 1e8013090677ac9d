"""Metrics of the spec and paper §5.2 (CTR, ITR eq. 9, team return) and the curve logger."""

from __future__ import annotations

from mrta_rl.metrics.episode import (
    EpisodeSummary,
    concat_stats,
    ctr,
    ctr_overall,
    format_percent,
    itr,
    return_by_type,
    summarize,
)
from mrta_rl.metrics.run_logger import CURVE_COLUMNS, RunLogger

__all__ = [
    "CURVE_COLUMNS",
    "EpisodeSummary",
    "RunLogger",
    "concat_stats",
    "ctr",
    "ctr_overall",
    "format_percent",
    "itr",
    "return_by_type",
    "summarize",
]
